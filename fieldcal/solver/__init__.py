"""Generic least squares over block-sparse Jacobians (knows no camera).

- :mod:`.blocksparse`: the block-sparse Jacobian and normal equations, Schur complement.
- :mod:`.lsq`: the Levenberg-Marquardt and hybrid LM / quasi-Newton (LMQN) engines.
"""
