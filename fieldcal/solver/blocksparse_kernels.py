"""Compiled loops of :mod:`fieldcal.solver.blocksparse`: ``J^T J`` in block form, ``J^T r``, ``J h``.

Each kernel does, group by group and with no temporaries, what the NumPy code of
:class:`fieldcal.solver.blocksparse.NormalEquations` and
:class:`fieldcal.solver.blocksparse.BlockSparseJacobian` does with batched products and
``np.bincount`` (that code is the reference; ``tests/solver/test_blocksparse.py`` runs the
same contract over both). For one residual block with values ``v`` (k, r, c), whose column
positions ``red_pos`` are reduced and ``elim_pos`` eliminated:

- ``U[key_cols[key_id[g], i], key_cols[key_id[g], j]] += v[g, :, red_pos[i]] . v[g, :, red_pos[j]]``
- ``V[e[g], local[g, i], local[g, j]] += v[g, :, elim_pos[i]] . v[g, :, elim_pos[j]]``
- ``W_slots[slot_idx[g, i], local[g, j]] += v[g, :, red_pos[i]] . v[g, :, elim_pos[j]]``

Compilation, caching and the NumPy fallback: :mod:`fieldcal.solver.compiled`.
"""

from __future__ import annotations

import numpy as np

from fieldcal.solver import compiled

__all__ = ["assemble", "gradient", "matvec"]

_NAME = "block-sparse normal equations"


def _assemble(v, red_pos, elim_pos, key_cols, key_id, e, local, slot_idx, U, V, Ws):
    k, r = v.shape[0], v.shape[1]
    c_r, c_e = red_pos.shape[0], elim_pos.shape[0]
    for g in range(k):
        if c_r:
            kc = key_cols[key_id[g]]
            for ii in range(c_r):
                a = red_pos[ii]
                for jj in range(ii, c_r):
                    b = red_pos[jj]
                    s = 0.0
                    for q in range(r):
                        s += v[g, q, a] * v[g, q, b]
                    U[kc[ii], kc[jj]] += s
                    if jj != ii:
                        U[kc[jj], kc[ii]] += s
        if c_e:
            eg = e[g]
            for ii in range(c_e):
                a = elim_pos[ii]
                for jj in range(ii, c_e):
                    b = elim_pos[jj]
                    s = 0.0
                    for q in range(r):
                        s += v[g, q, a] * v[g, q, b]
                    V[eg, local[g, ii], local[g, jj]] += s
                    if jj != ii:
                        V[eg, local[g, jj], local[g, ii]] += s
            for ii in range(c_r):
                a = red_pos[ii]
                sl = slot_idx[g, ii]
                for jj in range(c_e):
                    b = elim_pos[jj]
                    s = 0.0
                    for q in range(r):
                        s += v[g, q, a] * v[g, q, b]
                    Ws[sl, local[g, jj]] += s


def _gradient(v, rows, cols, res, out):
    k, r, c = v.shape
    for g in range(k):
        for j in range(c):
            s = 0.0
            for q in range(r):
                s += v[g, q, j] * res[rows[g, q]]
            out[cols[g, j]] += s


def _matvec(v, rows, cols, h, out):
    k, r, c = v.shape
    for g in range(k):
        for q in range(r):
            s = 0.0
            for j in range(c):
                s += v[g, q, j] * h[cols[g, j]]
            out[rows[g, q]] = s


if compiled.numba is not None:
    _jit = compiled.numba.njit(cache=True, nogil=True)
    _kernels = (_jit(_assemble), _jit(_gradient), _jit(_matvec))
else:  # pragma: no cover
    _kernels = None


def _smoke(ks):
    a, gr, mv = ks
    v = np.array([[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]])
    U, V, Ws = np.zeros((2, 2)), np.zeros((1, 1, 1)), np.zeros((2, 1))
    a(v, np.array([0, 1]), np.array([2]), np.array([[0, 1]]), np.zeros(1, np.intp), np.zeros(1, np.intp),
      np.zeros((1, 1), np.intp), np.array([[0, 1]]), U, V, Ws)
    if not (np.allclose(U, [[17.0, 22.0], [22.0, 29.0]]) and V[0, 0, 0] == 45.0 and np.allclose(Ws, [[27.0], [36.0]])):
        raise RuntimeError("the compiled assembly gives wrong numbers on a trivial problem")
    g = np.zeros(3)
    gr(v, np.array([[0, 1]]), np.array([[0, 1, 2]]), np.array([1.0, 1.0]), g)
    out = np.zeros(2)
    mv(v, np.array([[0, 1]]), np.array([[0, 1, 2]]), np.ones(3), out)
    if not (np.allclose(g, [5.0, 7.0, 9.0]) and np.allclose(out, [6.0, 15.0])):
        raise RuntimeError("the compiled J^T r or J h gives wrong numbers on a trivial problem")


def _get():
    ks = compiled.kernel(_NAME, _kernels, _smoke)
    return ks


def assemble():
    """The compiled assembly of U, V, W_slots (in place), or None (use the NumPy reference)."""
    ks = _get()
    return None if ks is None else ks[0]


def gradient():
    """The compiled ``J^T r`` of one residual block (adds into ``out``), or None."""
    ks = _get()
    return None if ks is None else ks[1]


def matvec():
    """The compiled ``J h`` of one residual block (writes ``out[rows]``), or None."""
    ks = _get()
    return None if ks is None else ks[2]
