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

Compilation, caching and the NumPy fallback: :mod:`fieldcal.contract.compiled`.
"""

from __future__ import annotations

import numpy as np

from fieldcal.contract import compiled

__all__ = ["assemble", "gradient", "matvec", "schur", "elim_covariances", "group_covariance"]

_NAME = "block-sparse normal equations"


def _assemble(v, red_pos, elim_pos, key_cols, key_id, e, local, slot_idx, U, V, Ws, with_U):
    k, r = v.shape[0], v.shape[1]
    c_r, c_e = red_pos.shape[0], elim_pos.shape[0]
    if r == 2 and c_e and not with_U:
        _assemble_rows2(v, red_pos, elim_pos, e, local, slot_idx, V, Ws)
        return
    for g in range(k):
        if c_r and with_U:
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


def _assemble_rows2(v, red_pos, elim_pos, e, local, slot_idx, V, Ws):
    """V and W_slots of :func:`_assemble` for groups of two rows (image points), each group's
    values gathered once (the same arithmetic in the same order)."""
    k = v.shape[0]
    c_r, c_e = red_pos.shape[0], elim_pos.shape[0]
    ar, ae = np.empty((2, max(c_r, 1))), np.empty((2, c_e))
    for g in range(k):
        for jj in range(c_r):
            ar[0, jj], ar[1, jj] = v[g, 0, red_pos[jj]], v[g, 1, red_pos[jj]]
        for jj in range(c_e):
            ae[0, jj], ae[1, jj] = v[g, 0, elim_pos[jj]], v[g, 1, elim_pos[jj]]
        eg = e[g]
        for ii in range(c_e):
            a0, a1, li = ae[0, ii], ae[1, ii], local[g, ii]
            for jj in range(ii, c_e):
                s = a0 * ae[0, jj] + a1 * ae[1, jj]
                lj = local[g, jj]
                V[eg, li, lj] += s
                if jj != ii:
                    V[eg, lj, li] += s
        for ii in range(c_r):
            a0, a1, sl = ar[0, ii], ar[1, ii], slot_idx[g, ii]
            for jj in range(c_e):
                Ws[sl, local[g, jj]] += a0 * ae[0, jj] + a1 * ae[1, jj]


def _gradient(v, rows, cols, res, out):
    k, r, c = v.shape
    if r == 2:    # image points: the group's two residuals loaded once (the same sums, in order)
        for g in range(k):
            r0, r1 = res[rows[g, 0]], res[rows[g, 1]]
            for j in range(c):
                s = 0.0
                s += v[g, 0, j] * r0
                s += v[g, 1, j] * r1
                out[cols[g, j]] += s
        return
    for g in range(k):
        for j in range(c):
            s = 0.0
            for q in range(r):
                s += v[g, q, j] * res[rows[g, q]]
            out[cols[g, j]] += s


def _matvec(v, rows, cols, h, out):
    k, r, c = v.shape
    if r == 2:    # image points: both rows in one pass over the columns (the same sums, in order)
        for g in range(k):
            s0, s1 = 0.0, 0.0
            for j in range(c):
                hj = h[cols[g, j]]
                s0 += v[g, 0, j] * hj
                s1 += v[g, 1, j] * hj
            out[rows[g, 0]] = s0
            out[rows[g, 1]] = s1
        return
    for g in range(k):
        for q in range(r):
            s = 0.0
            for j in range(c):
                s += v[g, q, j] * h[cols[g, j]]
            out[rows[g, q]] = s


def _schur(W, slot_col, slot_ptr, Vinv, T, Y):
    """``T[slot_col[s], slot_col[t]] += W_s V*_e^-1 W_t^T`` for the slots ``s <= t`` of each
    block (one triangle: each pair once, written along a row of ``T``), and ``Y[s] = W[s] V*_e^-1``.
    ``W V*^-1 W^T = T + T^T - diag(T)`` (the caller symmetrises)."""
    nb, b = Vinv.shape[0], Vinv.shape[1]
    for e in range(nb):
        s0, s1 = slot_ptr[e], slot_ptr[e + 1]
        if b == 3:
            _schur_block3(W, slot_col, s0, s1, Vinv[e], T, Y)
            continue
        for s in range(s0, s1):
            for j in range(b):
                acc = 0.0
                for q in range(b):
                    acc += W[s, q] * Vinv[e, q, j]
                Y[s, j] = acc
        for s in range(s0, s1):
            cs = slot_col[s]
            for t in range(s, s1):
                acc = 0.0
                for j in range(b):
                    acc += Y[s, j] * W[t, j]
                T[cs, slot_col[t]] += acc


def _schur_block3(W, slot_col, s0, s1, Vi, T, Y):
    """One block of 3 (a target) of :func:`_schur`, ``V*_e^-1`` and the row's ``Y`` in
    registers (the same arithmetic in the same order)."""
    v00, v01, v02 = Vi[0, 0], Vi[0, 1], Vi[0, 2]
    v10, v11, v12 = Vi[1, 0], Vi[1, 1], Vi[1, 2]
    v20, v21, v22 = Vi[2, 0], Vi[2, 1], Vi[2, 2]
    for s in range(s0, s1):
        w0, w1, w2 = W[s, 0], W[s, 1], W[s, 2]
        Y[s, 0] = w0 * v00 + w1 * v10 + w2 * v20
        Y[s, 1] = w0 * v01 + w1 * v11 + w2 * v21
        Y[s, 2] = w0 * v02 + w1 * v12 + w2 * v22
    for s in range(s0, s1):
        cs = slot_col[s]
        y0, y1, y2 = Y[s, 0], Y[s, 1], Y[s, 2]
        for t in range(s, s1):
            T[cs, slot_col[t]] += y0 * W[t, 0] + y1 * W[t, 1] + y2 * W[t, 2]


def _elim_covariances(Y, slot_col, slot_ptr, Cr, Cee, cross):
    """``Cee[e] += Y_e^T Cr_ee Y_e`` (in place on ``V*^-1``) and ``cross[s] = -(Cr Y_e)[s]``.

    ``X_e = Cr_ee Y_e`` over the slots of block e, each pair of slots once (``Cr`` is
    symmetric): an entry of ``Cr`` is read once, along its row, and used twice."""
    nb, b = Cee.shape[0], Cee.shape[1]
    n_max = 0
    for e in range(nb):
        n_max = max(n_max, slot_ptr[e + 1] - slot_ptr[e])
    X = np.empty((n_max, b))
    for e in range(nb):
        s0, s1 = slot_ptr[e], slot_ptr[e + 1]
        X[: s1 - s0, :] = 0.0
        if b == 3:
            _cr_times_y3(Y, slot_col, s0, s1, Cr, X)
        else:
            for s in range(s0, s1):
                cs = slot_col[s]
                c = Cr[cs, cs]
                for j in range(b):
                    X[s - s0, j] += c * Y[s, j]
                for t in range(s + 1, s1):
                    c = Cr[cs, slot_col[t]]
                    for j in range(b):
                        X[s - s0, j] += c * Y[t, j]
                        X[t - s0, j] += c * Y[s, j]
        for s in range(s0, s1):
            for j in range(b):
                cross[s, j] = -X[s - s0, j]
            for i in range(b):
                for j in range(b):
                    Cee[e, i, j] += Y[s, i] * X[s - s0, j]


def _cr_times_y3(Y, slot_col, s0, s1, Cr, X):
    """``X += Cr_ee Y_e`` for blocks of 3 (targets), as in :func:`_elim_covariances` with the
    row being summed held in registers (the same arithmetic in the same order)."""
    for s in range(s0, s1):
        cs = slot_col[s]
        y0, y1, y2 = Y[s, 0], Y[s, 1], Y[s, 2]
        c = Cr[cs, cs]
        x0, x1, x2 = X[s - s0, 0] + c * y0, X[s - s0, 1] + c * y1, X[s - s0, 2] + c * y2
        for t in range(s + 1, s1):
            c = Cr[cs, slot_col[t]]
            x0 += c * Y[t, 0]
            x1 += c * Y[t, 1]
            x2 += c * Y[t, 2]
            X[t - s0, 0] += c * y0
            X[t - s0, 1] += c * y1
            X[t - s0, 2] += c * y2
        X[s - s0, 0], X[s - s0, 1], X[s - s0, 2] = x0, x1, x2


def _group_covariance(v, red_pos, elim_pos, key_cols, key_id, e, local, slot_idx, Cr, Cee, cross, Q):
    """``Q[g] = J_g N^-1 J_g^T`` from the reduced block ``Cr``, the eliminated diagonal blocks
    ``Cee`` and the cross blocks per slot ``cross`` (see ``NormalEquations.group_covariance``).
    The reduced part as ``A (Cr_g A^T)``: ``u = Cr_g A^T`` first, each entry of ``Cr`` read once.
    The group's eliminated values and its blocks of ``Cee`` and ``cross`` are gathered once (not
    once per entry of Q); the sums are the same, in the same order."""
    k, r = v.shape[0], v.shape[1]
    c_r, c_e = red_pos.shape[0], elim_pos.shape[0]
    u, vr = np.empty((r, max(c_r, 1))), np.empty((r, max(c_r, 1)))
    ve = np.empty((r, max(c_e, 1)))
    Cg, Xg = np.empty((max(c_e, 1), max(c_e, 1))), np.empty((max(c_r, 1), max(c_e, 1)))
    for g in range(k):
        if c_r:
            kc = key_cols[key_id[g]]
            for q in range(r):
                for jj in range(c_r):
                    vr[q, jj] = v[g, q, red_pos[jj]]
            for ii in range(c_r):
                row = kc[ii]
                if r == 2:            # image points: both rows at once, in registers
                    u0, u1 = 0.0, 0.0
                    for jj in range(c_r):
                        c = Cr[row, kc[jj]]
                        u0 += c * vr[0, jj]
                        u1 += c * vr[1, jj]
                    u[0, ii], u[1, ii] = u0, u1
                else:
                    for q in range(r):
                        acc = 0.0
                        for jj in range(c_r):
                            acc += Cr[row, kc[jj]] * vr[q, jj]
                        u[q, ii] = acc
        if c_e:
            eg = e[g]
            for q in range(r):
                for jj in range(c_e):
                    ve[q, jj] = v[g, q, elim_pos[jj]]
            for ii in range(c_e):
                li = local[g, ii]
                for jj in range(c_e):
                    Cg[ii, jj] = Cee[eg, li, local[g, jj]]
            for ii in range(c_r):
                sl = slot_idx[g, ii]
                for jj in range(c_e):
                    Xg[ii, jj] = cross[sl, local[g, jj]]
        for p in range(r):
            for q in range(p, r):
                acc = 0.0
                for ii in range(c_r):
                    acc += vr[p, ii] * u[q, ii]
                if c_e:
                    for ii in range(c_e):
                        a = ve[p, ii]
                        row = 0.0
                        for jj in range(c_e):
                            row += Cg[ii, jj] * ve[q, jj]
                        acc += a * row
                    for ii in range(c_r):
                        for jj in range(c_e):
                            acc += Xg[ii, jj] * (vr[p, ii] * ve[q, jj] + vr[q, ii] * ve[p, jj])
                Q[g, p, q] = acc
                Q[g, q, p] = acc


if compiled.numba is not None:
    _jit = compiled.numba.njit(cache=True, nogil=True)
    _cr_times_y3, _schur_block3, _assemble_rows2 = _jit(_cr_times_y3), _jit(_schur_block3), _jit(_assemble_rows2)
    _kernels = (_jit(_assemble), _jit(_gradient), _jit(_matvec), _jit(_schur), _jit(_elim_covariances),
                _jit(_group_covariance))
else:  # pragma: no cover
    _kernels = None


def _smoke(ks):
    a, gr, mv = ks[:3]
    v = np.array([[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]])
    U, V, Ws = np.zeros((2, 2)), np.zeros((1, 1, 1)), np.zeros((2, 1))
    a(v, np.array([0, 1]), np.array([2]), np.array([[0, 1]]), np.zeros(1, np.intp), np.zeros(1, np.intp),
      np.zeros((1, 1), np.intp), np.array([[0, 1]]), U, V, Ws, True)
    if not (np.allclose(U, [[17.0, 22.0], [22.0, 29.0]]) and V[0, 0, 0] == 45.0 and np.allclose(Ws, [[27.0], [36.0]])):
        raise RuntimeError("the compiled assembly gives wrong numbers on a trivial problem")
    g = np.zeros(3)
    gr(v, np.array([[0, 1]]), np.array([[0, 1, 2]]), np.array([1.0, 1.0]), g)
    out = np.zeros(2)
    mv(v, np.array([[0, 1]]), np.array([[0, 1, 2]]), np.ones(3), out)
    if not (np.allclose(g, [5.0, 7.0, 9.0]) and np.allclose(out, [6.0, 15.0])):
        raise RuntimeError("the compiled J^T r or J h gives wrong numbers on a trivial problem")


def _smoke_schur(ks):
    sc, ec = ks[3], ks[4]
    W = np.array([[1.0, 2.0], [3.0, 4.0]])
    Vinv = np.array([[[2.0, 0.0], [0.0, 0.5]]])
    T, Y = np.zeros((2, 2)), np.empty((2, 2))
    sc(W, np.array([0, 1]), np.array([0, 2]), Vinv, T, Y)
    ref = W @ Vinv[0] @ W.T
    S = -(T + T.T - np.diag(np.diag(T)))
    Cee, cross = Vinv.copy(), np.zeros((2, 2))
    ec(Y, np.array([0, 1]), np.array([0, 2]), np.eye(2), Cee, cross)
    if not (np.allclose(S, -ref) and np.allclose(Cee[0], Vinv[0] + Y.T @ Y) and np.allclose(cross, -Y)):
        raise RuntimeError("the compiled Schur complement gives wrong numbers on a trivial problem")


def _get():
    return compiled.kernel(_NAME, _kernels, lambda ks: (_smoke(ks), _smoke_schur(ks)))


def assemble():
    """The compiled assembly of U (``with_U``), V, W_slots (in place), or None (use the NumPy
    reference). fieldcal forms U with BLAS (groups sharing reduced columns make one dense
    product, faster than this loop's scattered updates) and V, W_slots here."""
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


def schur():
    """The compiled ``W V*^-1 W^T`` as one triangle ``T`` (and ``Y = W V*^-1`` per slot), or None."""
    ks = _get()
    return None if ks is None else ks[3]


def elim_covariances():
    """The compiled ``(N^-1)_ee`` diagonal blocks and cross blocks per slot, or None."""
    ks = _get()
    return None if ks is None else ks[4]


def group_covariance():
    """The compiled ``J_g N^-1 J_g^T`` of every group of one residual block (into ``Q``), or None."""
    ks = _get()
    return None if ks is None else ks[5]
