"""``M = B B^T`` of fixed targets' survey errors, target by target, in one compiled pass.

:func:`fieldcal.field.variance_components.survey_consider_matrix` needs
``M = B S B^T`` over the reduced unknowns ``[interior | exterior by image]``, where column
block ``t`` of ``B S^(1/2)`` is the sum of the (p + 6, 3) products ``P_k`` of target
``t``'s image points (docs/uncertainty.md, the fixed targets' survey errors; the module
docstring of :mod:`fieldcal.field.variance_components`). The NumPy reference there builds
``B`` as a sparse matrix and multiplies (SciPy's ``csr_matmat``: three passes, index
sorting, ~60 ms on the 72-image paper field). This kernel adds each target's contribution
in place, forming each ``P_k`` from the derivative blocks as it goes (no (m, p + 6, 3)
array): with ``S_t = sum_k P_k[:p]`` (the interior rows, shared by all its points) and
``E_k = P_k[p:]`` (the 6 rows of the image of point k)::

    M[int, int]          += S_t S_t^T
    M[int, ext(i_k)]     += S_t E_k^T          (and its transpose)
    M[ext(i_k), ext(i_l)] += E_k E_l^T          for every pair k, l of target t

Each pair (k, l), k < l, is formed once and added to both ``M[ext(i_k), ext(i_l)]`` and its
mirror (the two products are bit for bit the same); the order of the additions into an entry
is that of the loop over all ordered pairs unless a target has two points in one image.

The contract test (``tests/field/test_honest_uncertainty.py``) runs both implementations.
Compilation, caching and the fallback: :mod:`fieldcal.contract.compiled`.
"""

from __future__ import annotations

import numpy as np

from fieldcal.contract import compiled

__all__ = ["kernel", "status"]

_NAME = "survey consider matrix"


def _consider(d_int, d_ext, sigma_m, image, order, ptr, M):
    """Add ``B S B^T`` into ``M`` (n_r, n_r). ``d_int`` (m, 2, p), ``d_ext`` (m, 2, 6): the image
    residuals' derivatives; ``sigma_m`` (m,) the survey sigma of each point's target;
    ``order[ptr[t]:ptr[t+1]]`` the points of target t; ``image`` (m,) their images (exterior
    rows ``p + 6 i``). ``P_k = [d_int_k | d_ext_k]^T J_X,k`` with ``J_X,k = -sigma_k
    d_ext_k[:, 3:]`` (the derivative by the target is minus that by the centre) is formed
    point by point."""
    p = d_int.shape[2]
    n_max = 0
    for t in range(ptr.shape[0] - 1):
        n_max = max(n_max, ptr[t + 1] - ptr[t])
    P = np.empty((n_max, p + 6, 3))
    S = np.empty((p, 3))
    for t in range(ptr.shape[0] - 1):
        a0, a1 = ptr[t], ptr[t + 1]
        for a in range(a0, a1):
            k = order[a]
            for c in range(3):
                x0, x1 = -sigma_m[k] * d_ext[k, 0, 3 + c], -sigma_m[k] * d_ext[k, 1, 3 + c]
                for r in range(p):
                    P[a - a0, r, c] = d_int[k, 0, r] * x0 + d_int[k, 1, r] * x1
                for r in range(6):
                    P[a - a0, p + r, c] = d_ext[k, 0, r] * x0 + d_ext[k, 1, r] * x1
        S[:, :] = 0.0
        for a in range(a1 - a0):
            for r in range(p):
                for c in range(3):
                    S[r, c] += P[a, r, c]
        for r in range(p):
            for s in range(p):
                M[r, s] += S[r, 0] * S[s, 0] + S[r, 1] * S[s, 1] + S[r, 2] * S[s, 2]
        for a in range(a1 - a0):
            ok = p + 6 * image[order[a0 + a]]
            for r in range(p):
                for e in range(6):
                    v = S[r, 0] * P[a, p + e, 0] + S[r, 1] * P[a, p + e, 1] + S[r, 2] * P[a, p + e, 2]
                    M[r, ok + e] += v
                    M[ok + e, r] += v
            # the pairs (a, b) and (b, a) give each other's transposed blocks with the same bits
            # (products commute, the sums run over c in one order): each pair once, written twice
            for e in range(6):
                for f in range(e, 6):
                    v = (P[a, p + e, 0] * P[a, p + f, 0] + P[a, p + e, 1] * P[a, p + f, 1]
                         + P[a, p + e, 2] * P[a, p + f, 2])
                    M[ok + e, ok + f] += v
                    if f != e:
                        M[ok + f, ok + e] += v
            for b in range(a + 1, a1 - a0):
                ol = p + 6 * image[order[a0 + b]]
                for e in range(6):
                    for f in range(6):
                        v = (P[a, p + e, 0] * P[b, p + f, 0] + P[a, p + e, 1] * P[b, p + f, 1]
                             + P[a, p + e, 2] * P[b, p + f, 2])
                        M[ok + e, ol + f] += v
                        M[ol + f, ok + e] += v


if compiled.numba is not None:
    _compiled = compiled.numba.njit(cache=True, nogil=True)(_consider)
else:  # pragma: no cover
    _compiled = None


def _smoke(k):
    rng = np.random.default_rng(0)
    d_int, d_ext, sigma = rng.standard_normal((2, 2, 1)), rng.standard_normal((2, 2, 6)), np.array([0.5, 2.0])
    M = np.zeros((13, 13))
    k(d_int, d_ext, sigma, np.array([0, 1], np.int64), np.array([0, 1], np.int64), np.array([0, 2], np.int64), M)
    P = np.einsum("kai,kaj->kij", np.concatenate([d_int, d_ext], axis=2), -d_ext[:, :, 3:] * sigma[:, None, None])
    B = np.zeros((13, 3))
    B[0] = P[0, 0] + P[1, 0]
    B[1:7], B[7:13] = P[0, 1:], P[1, 1:]
    if not np.allclose(M, B @ B.T):
        raise RuntimeError("the compiled survey consider matrix gives wrong numbers on a trivial problem")


def kernel():
    """The compiled kernel, or ``None`` (then the NumPy reference runs; see :func:`status`)."""
    return compiled.kernel(_NAME, _compiled, _smoke)


def status() -> str:
    """One line: whether the compiled kernel is in use, and why not."""
    kernel()
    return compiled.status(_NAME)
