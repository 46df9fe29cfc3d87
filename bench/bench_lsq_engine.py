"""Micro-benchmark of the block-sparse normal equations at the field bundle's sizes.

Random Jacobians with the structure of the field bundle (no camera model): 10 shared
"interior" columns, 72 "images" x 6 columns, 2000 "targets" x 3 eliminated columns,
12 000 two-row observation groups (each target in about 6 images, 24 000 rows) and, with
adjusted targets, 2000 three-row survey groups (+6000 rows, +6000 eliminated columns).
Times what one LM iteration costs besides the model: building the normal equations
and one damped solve; also the one-off index analysis, J^T r, and the covariances.
(Each timing builds a fresh ``NormalEquations``: ``J.normal_equations()`` is made once per
Jacobian and shared. The loops run compiled by default; ``FIELDCAL_NUMBA=0`` times the
NumPy reference.)

Run (single-threaded BLAS, as the numbers below)::

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 .venv/bin/python bench/bench_lsq_engine.py

Results on the 2-core shared development machine, under load from other jobs (best of
30, of 5 for the one-offs; ranges over the sorted/shuffled observation orders and runs, ms)::

    case                                 build N + solve  build N  analysis  J^T r  covariances
    fixed targets (m 24 000, n 442)              2.7-3.5  0.7-1.0      6-15    0.6        14-31
    adjusted targets (m 30 000, n 6442)            27-30  5.5-7.0     36-62    0.7        69-73

(``covariances`` = build N + reduced block + eliminated blocks + J_g N^-1 J_g^T of every
observation group; done once per adjustment, not per iteration.)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from fieldcal.solver.blocksparse import BlockSparseJacobian, NormalEquations, ResidualBlock  # noqa: E402

N_INT, N_IMG, N_TGT, N_OBS = 10, 72, 2000, 12000


def bundle_like(adjusted: bool, seed: int = 0, sort_by_image: bool = True):
    """A random Jacobian with the bundle's sparsity pattern; returns ``(J, r)``."""
    rng = np.random.default_rng(seed)
    pairs = rng.choice(N_IMG * N_TGT, N_OBS, replace=False)       # distinct (image, target)
    pairs = np.sort(pairs) if sort_by_image else pairs
    img, tgt = pairs // N_TGT, pairs % N_TGT
    n_red = N_INT + 6 * N_IMG
    k = N_OBS
    rows = np.arange(2 * k).reshape(k, 2)
    parts = [(np.arange(N_INT), rng.standard_normal((k, 2, N_INT))),
             (N_INT + 6 * img[:, None] + np.arange(6), rng.standard_normal((k, 2, 6)))]
    blocks = []
    n_rows, n_params = 2 * k, n_red
    if adjusted:
        parts.append((n_red + 3 * tgt[:, None] + np.arange(3), rng.standard_normal((k, 2, 3))))
        srows = 2 * k + np.arange(3 * N_TGT).reshape(N_TGT, 3)
        scols = n_red + 3 * np.arange(N_TGT)[:, None] + np.arange(3)
        survey = np.broadcast_to(np.eye(3) / 0.005, (N_TGT, 3, 3))
        blocks.append(ResidualBlock(srows, scols, survey))
        n_rows += 3 * N_TGT
        n_params += 3 * N_TGT
    blocks.insert(0, ResidualBlock.from_parts(rows, parts))
    J = BlockSparseJacobian(n_rows, n_params, n_red, 3, blocks)
    return J, rng.standard_normal(n_rows)


def best_ms(fn, repeat=30):
    """Best wall time of ``repeat`` calls after one warm-up call [ms]."""
    fn()
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def covariances(J):
    ne = NormalEquations(J)           # a fresh one: J.normal_equations() is made once per Jacobian
    ne.covariance_reduced()
    ne.covariance_elim_blocks()
    ne.group_covariance(0)


def main():
    bundle_like(True)[0].normal_equations()            # warm up the allocator
    print(f"{'case':40s} {'build+solve':>11s} {'build N':>8s} {'analysis':>9s} {'J^T r':>6s} "
          f"{'cov':>6s}  [ms]")
    for adjusted in (False, True):
        for sort in (True, False):
            J, r = bundle_like(adjusted, sort_by_image=sort)
            g = J.gradient(r)
            damping = 1e-3 * J.column_norms() ** 2
            t_solve = best_ms(lambda J=J, g=g, damping=damping:
                              NormalEquations(J).solve(g, damping))
            t_build = best_ms(lambda J=J: NormalEquations(J))
            t_analysis = best_ms(lambda J=J: BlockSparseJacobian(*J.shape, J.n_reduced, 3,
                                                                 J.blocks), repeat=5)
            t_grad = best_ms(lambda J=J, r=r: J.gradient(r))
            t_cov = best_ms(lambda J=J: covariances(J), repeat=3)
            name = (f"{'adjusted' if adjusted else 'fixed'} targets (m {J.n_rows}, "
                    f"n {J.n_params}), {'sorted' if sort else 'shuffled'}")
            print(f"{name:40s} {t_solve:11.2f} {t_build:8.2f} {t_analysis:9.1f} {t_grad:6.2f} "
                  f"{t_cov:6.1f}")


if __name__ == "__main__":
    main()
