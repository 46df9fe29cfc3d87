"""Block-sparse Jacobians and their normal equations, solved by the Schur complement.

Structure
---------
The parameter vector ``x`` (n,) is laid out as ``[reduced | eliminated]``: the first
``n_reduced`` parameters are solved densely; the rest form ``n_elim_blocks`` consecutive
blocks of ``b = elim_block_size`` parameters each, eliminated block by block.

The residual vector ``r`` (m,) is covered by *residual blocks*. A residual block holds
``k`` groups of ``r_rows`` rows; group ``g`` depends on a few parameter columns only, and
its eliminated columns (if any) lie in one eliminated block ``e(g)``. Every residual row
belongs to at most one group. A residual block is given either as one array of columns
``cols`` (k, c) with values ``values`` (k, r_rows, c) (``values[g, i, j] = d r[rows[g, i]] /
d x[cols[g, j]]``), or as several *parts*: column sets that are either shared by every
group (``cols`` (c,)) or given per group (``cols`` (k, c)). Shared columns (and columns
that repeat across many groups) cost one dense product, not one product per group.

Normal equations
----------------
With ``J = [J_r | J_e]`` and ``N = J^T J``::

    N = [[U,   W],        U = J_r^T J_r   (n_r, n_r), dense
         [W^T, V]]        V = J_e^T J_e   block diagonal, (n_blocks, b, b)
                          W = J_r^T J_e   (n_r, n_blocks * b), sparse

A damped system ``(N + diag(D)) h = -g`` (``D = [D_r | D_e]`` >= 0) is solved by
eliminating the eliminated blocks::

    V* = V + D_e                             batched b x b inverses
    S  = U + D_r - W V*^-1 W^T               dense Schur complement (n_r, n_r)
    S h_r = -g_r + W V*^-1 g_e               Cholesky (scipy.linalg.cho_factor)
    h_e = V*^-1 (-g_e - W^T h_r)             back-substitution, block by block

``W`` is stored by *slots*: one ``b``-vector ``W[col, e-block]`` for every pair (eliminated
block ``e``, reduced column ``col``) that some group couples. The Schur term
``W_e V*_e^-1 W_e^T`` of block ``e`` is a small dense product over its slots; blocks with
the same number of slots are processed together (batched matrix products), and the
products are added into ``S`` with one ``np.bincount`` per batch.

The inverse of N (covariance for unit-weight residuals) in block form::

    (N^-1)_rr = S^-1
    (N^-1)_re = -S^-1 W V^-1
    (N^-1)_ee = V^-1 + V^-1 W^T S^-1 W V^-1

of which :class:`NormalEquations` evaluates the reduced block, the diagonal b x b blocks
of the eliminated part, and, per group, ``J_g N^-1 J_g^T`` (r_rows, r_rows): the
quantity that redundancy numbers and data snooping need (``Q_vv = I - J_g N^-1 J_g^T``).

Both ``S`` and the ``V*`` blocks are equilibrated (scaled to a unit diagonal) before they
are factored, so parameters of wildly different magnitudes do not spoil the factorisation;
a pivot below ``n * eps`` of its diagonal (after equilibration) means the system is
singular and raises :class:`SingularSystemError`.

Nothing here forms a dense (m, n) matrix, nor a dense (n, n) one when there are
eliminated blocks. The index analysis (which groups share columns, which slots exist, the
batches) is done once per sparsity pattern and kept in a :class:`JacobianStructure`, which
a later Jacobian with the same index arrays reuses (``structure=previous.structure``, or
automatically when blocks are made with :meth:`ResidualBlock.with_values`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg
import scipy.sparse

from fieldcal.errors import GeometryError, InputError
from fieldcal.solver import blocksparse_kernels

__all__ = [
    "SingularSystemError",
    "ResidualBlock",
    "BlockSparseJacobian",
    "JacobianStructure",
    "NormalEquations",
    "equilibrated_cholesky",
]

_EPS = np.finfo(float).eps


class SingularSystemError(GeometryError):
    """The normal equations are singular: the data do not determine every parameter.

    Attributes
    ----------
    where : str
        ``"reduced"`` or ``"eliminated"``: the part of the system that failed.
    index : int or None
        The parameter (column of ``x``) with the smallest pivot, when known.
    """

    def __init__(self, message: str, where: str, index: int | None = None):
        self.where = where
        self.index = index
        super().__init__(message)


# ----------------------------------------------------------------------------------------
# residual blocks
# ----------------------------------------------------------------------------------------


def _as_index_array(a, name: str) -> np.ndarray:
    arr = np.array(a, dtype=np.intp, copy=True)
    arr.flags.writeable = False
    return arr


class ResidualBlock:
    """``k`` groups of ``r_rows`` residual rows, group ``g`` depending on a few columns.

    Parameters
    ----------
    rows : (k, r_rows) int array_like
        Indices into the residual vector; a row belongs to at most one group.
    cols : (k, c) int array_like
        Parameter columns group ``g`` depends on (distinct within a group). Column
        position ``j`` must be a reduced column in every group or an eliminated column in
        every group; a group's eliminated columns lie in one eliminated block.
    values : (k, r_rows, c) float array_like
        ``values[g, i, j] = d r[rows[g, i]] / d x[cols[g, j]]``.

    Notes
    -----
    :meth:`from_parts` builds a block from several column parts, some of them shared by
    all groups; :meth:`with_values` makes a block with the same rows and columns and new
    values, which lets :class:`BlockSparseJacobian` reuse its index analysis.
    """

    def __init__(self, rows, cols, values):
        self._init(rows, [(cols, values)], where="ResidualBlock")

    @classmethod
    def from_parts(cls, rows, parts: Sequence[tuple[np.ndarray, np.ndarray]]) -> ResidualBlock:
        """A block from column parts.

        Parameters
        ----------
        rows : (k, r_rows) int array_like
        parts : sequence of ``(cols, values)``
            ``cols`` is (c_i,) (the same columns for every group) or (k, c_i) (per group);
            ``values`` is (k, r_rows, c_i). The block's columns are the parts' columns in
            order, e.g. ``[(shared_cols, d_shared), (per_group_cols, d_per_group),
            (eliminated_cols, d_eliminated)]``.
        """
        block = cls.__new__(cls)
        block._init(rows, list(parts), where="ResidualBlock.from_parts")
        return block

    def _init(self, rows, parts, where):
        rows = _as_index_array(rows, "rows")
        if rows.ndim != 2 or rows.shape[1] < 1:
            raise InputError(f"rows must have shape (k, r_rows), got {rows.shape}", where)
        k, r_rows = rows.shape
        if not parts:
            raise InputError("a residual block needs at least one column part", where)
        cols_list, values_list = [], []
        for i, (cols, values) in enumerate(parts):
            cols = _as_index_array(cols, "cols")
            if cols.ndim not in (1, 2) or (cols.ndim == 2 and cols.shape[0] != k):
                raise InputError(f"part {i}: cols must have shape (c,) or ({k}, c), "
                                 f"got {cols.shape}", where)
            c = cols.shape[-1]
            values = np.asarray(values, dtype=float)
            if values.shape != (k, r_rows, c):
                raise InputError(f"part {i}: values must have shape ({k}, {r_rows}, {c}), "
                                 f"got {values.shape}", where)
            cols_list.append(cols)
            values_list.append(values)
        self.rows = rows
        self.part_cols: tuple[np.ndarray, ...] = tuple(cols_list)
        self.part_values: tuple[np.ndarray, ...] = tuple(values_list)
        self._values = None

    @property
    def n_groups(self) -> int:
        """``k``, the number of groups."""
        return self.rows.shape[0]

    @property
    def r_rows(self) -> int:
        """Rows per group."""
        return self.rows.shape[1]

    @property
    def values(self) -> np.ndarray:
        """(k, r_rows, c) the values of all parts side by side."""
        if self._values is None:
            pv = self.part_values
            self._values = pv[0] if len(pv) == 1 else np.concatenate(pv, axis=2)
        return self._values

    @property
    def cols(self) -> np.ndarray:
        """(k, c) the columns of all parts side by side (shared parts broadcast)."""
        k = self.n_groups
        return np.concatenate([np.broadcast_to(c, (k, c.shape[-1])) for c in self.part_cols],
                              axis=1)

    def with_values(self, *values, combined=None) -> ResidualBlock:
        """The same rows and columns with new values, one (k, r_rows, c_i) array per part.

        ``combined`` (k, r_rows, c), optional: the parts side by side in one array, when the
        caller made them so (the parts being views of it); spares :attr:`values` a copy.
        """
        if len(values) != len(self.part_cols):
            raise InputError(f"with_values: expected {len(self.part_cols)} value arrays (one per "
                             f"part), got {len(values)}", "ResidualBlock")
        block = ResidualBlock.__new__(ResidualBlock)
        block.rows = self.rows
        block.part_cols = self.part_cols
        vals = []
        for i, (c, v) in enumerate(zip(self.part_cols, values, strict=True)):
            v = np.asarray(v, dtype=float)
            if v.shape != (self.n_groups, self.r_rows, c.shape[-1]):
                raise InputError(f"with_values: part {i} values must have shape "
                                 f"{(self.n_groups, self.r_rows, c.shape[-1])}, got {v.shape}",
                                 "ResidualBlock")
            vals.append(v)
        block.part_values = tuple(vals)
        block._values = None
        if combined is not None:
            width = sum(c.shape[-1] for c in self.part_cols)
            if combined.shape != (self.n_groups, self.r_rows, width):
                raise InputError(f"with_values: combined values must have shape "
                                 f"{(self.n_groups, self.r_rows, width)}, got {combined.shape}", "ResidualBlock")
            block._values = combined
        return block


# ----------------------------------------------------------------------------------------
# index analysis
# ----------------------------------------------------------------------------------------

_BUCKET_WASTE = 1.15  # batches of eliminated blocks pad their products by at most ~15%


def _positions(mask: np.ndarray):
    """Indices of True in a 1-D mask, as a slice when they are contiguous."""
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return slice(0, 0), idx
    if idx[-1] - idx[0] + 1 == len(idx):
        return slice(int(idx[0]), int(idx[-1]) + 1), idx
    return idx, idx


def _unique_inverse(keys, n_max: int):
    """``np.unique(keys, return_inverse=True)`` for integer keys in ``[0, n_max)``: by a marker
    array (no sort) when ``n_max`` is modest, else by ``np.unique``."""
    if n_max > 20_000_000:
        uniq, inv = np.unique(keys, return_inverse=True)
        return uniq, inv.reshape(-1)
    mark = np.zeros(n_max, bool)
    mark[keys] = True
    uniq = np.flatnonzero(mark)
    rank = np.empty(n_max, np.intp)            # set where marked only (no cumsum over n_max)
    rank[uniq] = np.arange(len(uniq))
    return uniq, rank[keys]


def _unique_rows(rows, n_cols: int):
    """``(first index of each distinct row, id of every row's distinct row)``, ids ordered as
    ``np.unique(rows, axis=0)`` orders them. Fast path: when the first column alone tells the
    rows apart (as an image's columns do), a 1-D unique of it."""
    first_col = rows[:, 0]
    uniq, first, inv = np.unique(first_col, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    if rows.shape[1] == 1 or np.array_equal(rows[first][inv], rows):
        return first, inv
    _, first, inv = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    return first, inv.reshape(-1)


def _may_repeat_a_column(part_cols, n_params: int) -> bool:
    """False when no group of a block repeats a column (then the full check is skipped),
    True when one may: the shared parts' columns (one list for all groups) repeat, a group's
    own columns (its per-group parts side by side) repeat, or one of them is a shared column.
    Exact in the False case; the caller's sort of every group's columns decides the rest and
    names the group."""
    shared = [c for c in part_cols if c.ndim == 1]
    own = [c for c in part_cols if c.ndim == 2]
    s = np.concatenate(shared) if shared else np.zeros(0, np.intp)
    if len(np.unique(s)) != len(s):
        return True
    if not own:
        return False
    g = own[0] if len(own) == 1 else np.concatenate(own, axis=1)
    if g.size and (g.min() < 0 or g.max() >= n_params):
        return True                       # out of range: the caller's check says so
    if g.shape[1] > 1:
        sg = np.sort(g, axis=1)
        if (sg[:, 1:] == sg[:, :-1]).any():
            return True
    if len(s):
        marked = np.zeros(n_params, bool)
        marked[s[(s >= 0) & (s < n_params)]] = True
        if marked[g].any():
            return True
    return False


class _BlockLayout:
    """Index analysis of one residual block (see :class:`JacobianStructure`)."""

    def __init__(self, i, block: ResidualBlock, n_params, n_reduced, b):
        where = f"residual block {i}"
        self.rows = block.rows
        self.part_cols = block.part_cols
        k, r = block.rows.shape
        self.k, self.r = k, r
        cols = block.cols
        self.cols = cols
        c = cols.shape[1]
        if k and (cols.min() < 0 or cols.max() >= n_params):
            raise InputError(f"columns must lie in [0, {n_params}), got {cols.min()}..{cols.max()}",
                             where)
        if k and c > 1 and _may_repeat_a_column(block.part_cols, n_params):
            sc = np.sort(cols, axis=1)
            dup = np.flatnonzero((sc[:, 1:] == sc[:, :-1]).any(axis=1))
            if len(dup):
                raise InputError(f"group {dup[0]} repeats a column ({sc[dup[0]].tolist()})", where)
        is_red = cols < n_reduced
        red_mask = is_red.all(axis=0) if k else np.ones(c, bool)
        elim_mask = (~is_red).all(axis=0) if k else np.zeros(c, bool)
        mixed = np.flatnonzero(~(red_mask | elim_mask))
        if len(mixed):
            raise InputError(f"column position {mixed[0]} is a reduced column in some groups and "
                             "an eliminated one in others; order the columns so that each "
                             "position is one or the other in every group", where)
        self.red_sel, red_pos = _positions(red_mask)
        self.elim_sel, elim_pos = _positions(elim_mask)
        self.red_pos, self.elim_pos = red_pos.astype(np.intp), elim_pos.astype(np.intp)
        self.c_r, self.c_e = len(red_pos), len(elim_pos)
        red_cols = cols[:, red_pos]
        self.red_cols = red_cols

        # -- reduced part: groups with identical reduced columns share one dense product
        if self.c_r and k:
            varying = ~(red_cols == red_cols[:1]).all(axis=0)
            if varying.any():
                first, key_id = _unique_rows(red_cols[:, varying], n_params)
            else:
                first, key_id = np.zeros(1, np.intp), np.zeros(k, np.intp)
            self.n_keys = len(first)
            self.key_id = key_id.astype(np.intp)
            self.key_cols = red_cols[first]
            order = np.argsort(key_id, kind="stable")
            self.order = None if np.all(order == np.arange(k)) else order
            counts = np.bincount(key_id, minlength=self.n_keys)
            self.starts = np.concatenate([[0], np.cumsum(counts)])
            kc = self.key_cols
            self.U_dest = (kc[:, :, None] * n_reduced + kc[:, None, :]).ravel()
            self.loop_keys = self.n_keys <= max(1, k // 16)
        else:
            self.n_keys = 0

        # -- eliminated part: one block per group, expanded to all b columns of the block
        if self.c_e and k:
            ec = cols[:, elim_pos] - n_reduced
            e = ec // b
            bad = np.flatnonzero((e != e[:, :1]).any(axis=1))
            if len(bad):
                raise InputError(f"group {bad[0]} has eliminated columns in more than one block "
                                 f"({(cols[bad[0]][elim_pos]).tolist()})", where)
            self.e = e[:, 0].copy()
            self.local = ec - b * e
            self.full = self.c_e == b and bool(np.all(self.local == np.arange(b)))
            self._b, self._V_dest = b, None
        else:
            self.c_e = 0

    @property
    def V_dest(self):
        """Where each group's (b, b) product lands in the flattened V (the NumPy assembly's
        ``bincount``; made on first use, the compiled assembly does not need it)."""
        if self._V_dest is None:
            b = self._b
            self._V_dest = (self.e[:, None] * (b * b) + np.arange(b * b)).ravel()
        return self._V_dest

    def reduced_values(self, values):
        return values[:, :, self.red_sel]

    def elim_values_full(self, values, b):
        """(k, r, b) the eliminated part of each group spread over its block's b columns."""
        B = values[:, :, self.elim_sel]
        if self.full:
            return B
        out = np.zeros((self.k, b, self.r))
        out[np.arange(self.k)[:, None], self.local] = B.transpose(0, 2, 1)
        return out.transpose(0, 2, 1)


class JacobianStructure:
    """The index analysis of a block-sparse Jacobian, reusable while the pattern is unchanged.

    Built by :class:`BlockSparseJacobian`; treat it as opaque. It records which groups share
    reduced columns, the coupling slots (eliminated block, reduced column) and the batches
    in which the Schur complement is formed, and owns a scratch buffer for those batches:
    Jacobians sharing one structure must not be factored concurrently from several threads
    (give each thread its own structure).
    """

    def __init__(self, n_rows, n_params, n_reduced, b, blocks: Sequence[ResidualBlock]):
        self.n_rows, self.n_params, self.n_reduced, self.b = n_rows, n_params, n_reduced, b
        self.n_blocks = (n_params - n_reduced) // b if b else 0
        self.layouts = [_BlockLayout(i, blk, n_params, n_reduced, b)
                        for i, blk in enumerate(blocks)]
        all_rows = np.concatenate([lay.rows.ravel() for lay in self.layouts]) if self.layouts else \
            np.zeros(0, np.intp)
        if len(all_rows):
            if all_rows.min() < 0 or all_rows.max() >= n_rows:
                raise InputError(f"rows must lie in [0, {n_rows}), got "
                                 f"{all_rows.min()}..{all_rows.max()}", "BlockSparseJacobian")
            if np.bincount(all_rows, minlength=n_rows).max() > 1:
                raise InputError("a residual row belongs to more than one group",
                                 "BlockSparseJacobian")

        # coupling slots: unique (eliminated block, reduced column) pairs, sorted by block
        nr = n_reduced
        keys = [lay.e[:, None] * nr + lay.red_cols for lay in self.layouts if lay.c_e and lay.c_r]
        if keys:
            uniq, inv = _unique_inverse(np.concatenate([kk.ravel() for kk in keys]),
                                        self.n_blocks * max(nr, 1))
        else:
            uniq, inv = np.zeros(0, np.intp), np.zeros(0, np.intp)
        self.n_slots = len(uniq)
        self.slot_e = (uniq // nr).astype(np.intp) if nr else uniq
        self.slot_col = (uniq % nr).astype(np.intp) if nr else uniq
        pos = 0
        for lay in self.layouts:
            if lay.c_e and lay.c_r:
                n = lay.k * lay.c_r
                lay.slot_idx = inv[pos:pos + n].reshape(lay.k, lay.c_r)
                pos += n
            else:
                lay.slot_idx = None
        counts = np.bincount(self.slot_e, minlength=self.n_blocks)
        self.slot_ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
        self._counts = counts
        self._buckets = None
        self._workspace = None

    @property
    def buckets(self):
        """The batches of the NumPy Schur complement (made on first use: the compiled loop
        of :mod:`fieldcal.solver.blocksparse_kernels` does not need them)."""
        if self._buckets is None:
            self._buckets = self._make_buckets(self._counts)
            self.dest_all = (np.concatenate([bk.dest for bk in self._buckets]) if self._buckets
                             else np.zeros(0, np.intp))
            for bk in self._buckets:
                bk.dest = None
        return self._buckets

    def workspace(self):
        """A reusable buffer for the Schur products of all batches, and its per-batch views.

        Reusing it spares the page faults of a fresh multi-megabyte array per solve.
        """
        if self._workspace is None:
            T_all = np.empty(len(self.dest_all))
            views, pos = [], 0
            for bk in self.buckets:
                n_t, s = bk.gather.shape
                views.append(T_all[pos:pos + n_t * s * s].reshape(n_t, s, s))
                pos += n_t * s * s
            self._workspace = (T_all, views)
        return self._workspace

    def _make_buckets(self, counts):
        """Batches of eliminated blocks with similar slot counts (padded to the largest)."""
        sizes = np.unique(counts[counts > 0])
        groups, cur = [], []
        for s in sizes:
            if cur and s * s > _BUCKET_WASTE * cur[0] * cur[0]:
                groups.append(cur)
                cur = []
            cur.append(int(s))
        if cur:
            groups.append(cur)
        nr, pad_slot, trash = self.n_reduced, self.n_slots, self.n_reduced * self.n_reduced
        buckets = []
        for sizes_in in groups:
            s = sizes_in[-1]
            es = np.flatnonzero(np.isin(counts, sizes_in))
            j = np.arange(s)
            valid = j[None, :] < counts[es][:, None]
            gather = np.where(valid, self.slot_ptr[es][:, None] + j, pad_slot)
            cols_e = np.where(valid, self.slot_col[np.minimum(gather, max(self.n_slots - 1, 0))], 0)
            both = valid[:, :, None] & valid[:, None, :]
            dest = np.where(both, cols_e[:, :, None] * nr + cols_e[:, None, :], trash).ravel()
            buckets.append(_Bucket(es, gather, cols_e, dest))
        return buckets

    def matches(self, blocks: Sequence[ResidualBlock]) -> bool:
        """Whether ``blocks`` have the index arrays this structure was made from."""
        if len(blocks) != len(self.layouts):
            return False
        for lay, blk in zip(self.layouts, blocks, strict=True):
            if len(blk.part_cols) != len(lay.part_cols):
                return False
            same = blk.rows is lay.rows and all(a is c for a, c in zip(blk.part_cols, lay.part_cols,
                                                                        strict=True))
            if not same:
                if blk.rows.shape != lay.rows.shape or not np.array_equal(blk.rows, lay.rows):
                    return False
                for a, c in zip(blk.part_cols, lay.part_cols, strict=True):
                    if a.shape != c.shape or not np.array_equal(a, c):
                        return False
        return True


class _Bucket:
    __slots__ = ("es", "gather", "cols_e", "dest")

    def __init__(self, es, gather, cols_e, dest):
        self.es, self.gather, self.cols_e, self.dest = es, gather, cols_e, dest


# ----------------------------------------------------------------------------------------
# the Jacobian
# ----------------------------------------------------------------------------------------


class BlockSparseJacobian:
    """A Jacobian made of residual blocks over ``[reduced | eliminated]`` parameters.

    Parameters
    ----------
    n_rows : int
        ``m``, the length of the residual vector.
    n_params : int
        ``n``, the length of the parameter vector.
    n_reduced : int
        The first ``n_reduced`` parameters are solved densely.
    elim_block_size : int
        ``b``: the remaining ``n - n_reduced`` parameters form blocks of ``b`` (must
        divide). Ignored (may be 0) when ``n_reduced == n_params``.
    blocks : sequence of ResidualBlock
    structure : JacobianStructure, optional
        The index analysis of a previous Jacobian; reused when the blocks have the same
        rows and columns (checked by identity, then by value), recomputed otherwise.
    """

    def __init__(self, n_rows: int, n_params: int, n_reduced: int, elim_block_size: int,
                 blocks: Sequence[ResidualBlock], *, structure: JacobianStructure | None = None):
        where = "BlockSparseJacobian"
        n_rows, n_params, n_reduced = int(n_rows), int(n_params), int(n_reduced)
        if n_rows < 0 or n_params < 1 or not 0 <= n_reduced <= n_params:
            raise InputError(f"need n_rows >= 0, n_params >= 1 and 0 <= n_reduced <= n_params, "
                             f"got {n_rows}, {n_params}, {n_reduced}", where)
        b = int(elim_block_size)
        n_elim = n_params - n_reduced
        if n_elim:
            if b < 1 or n_elim % b:
                raise InputError(f"the {n_elim} eliminated parameters do not form blocks of "
                                 f"elim_block_size={elim_block_size}", where)
        else:
            b = max(b, 1)
        self.blocks = list(blocks)
        if not all(isinstance(blk, ResidualBlock) for blk in self.blocks):
            raise InputError("blocks must be ResidualBlock objects", where)
        self.n_rows, self.n_params, self.n_reduced = n_rows, n_params, n_reduced
        self.elim_block_size = b
        self.n_elim_blocks = n_elim // b
        dims = (n_rows, n_params, n_reduced, b)
        same_dims = structure is not None and (structure.n_rows, structure.n_params,
                                               structure.n_reduced, structure.b) == dims
        if same_dims and structure.matches(self.blocks):
            self.structure = structure
        else:
            self.structure = JacobianStructure(n_rows, n_params, n_reduced, b, self.blocks)

    @property
    def shape(self) -> tuple[int, int]:
        """``(m, n)``."""
        return self.n_rows, self.n_params

    def _pairs(self):
        return zip(self.structure.layouts, self.blocks, strict=True)

    def gradient(self, r) -> np.ndarray:
        """``J^T r`` (n,) for residuals ``r`` (m,).

        Part by part: a column set shared by every group is one dense product, a per-group
        set one ``bincount``; the parts are never concatenated.
        """
        r = np.asarray(r, dtype=float)
        g = np.zeros(self.n_params)
        kern = blocksparse_kernels.gradient()
        if kern is not None:
            r = np.ascontiguousarray(r)
            for lay, blk in self._pairs():
                if lay.k:
                    kern(np.ascontiguousarray(blk.values), lay.rows, lay.cols, r, g)
            return g
        for lay, blk in self._pairs():
            if not lay.k:
                continue
            rr = r[lay.rows]
            for cols, v in zip(blk.part_cols, blk.part_values, strict=True):
                if cols.ndim == 1:
                    g[cols] += np.einsum("krc,kr->c", v, rr)
                else:
                    g += np.bincount(cols.ravel(), np.einsum("krc,kr->kc", v, rr).ravel(),
                                     minlength=self.n_params)
        return g

    def matvec(self, h) -> np.ndarray:
        """``J h`` (m,) for a parameter step ``h`` (n,)."""
        h = np.asarray(h, dtype=float)
        out = np.zeros(self.n_rows)
        kern = blocksparse_kernels.matvec()
        if kern is not None:
            h = np.ascontiguousarray(h)
            for lay, blk in self._pairs():
                if lay.k:
                    kern(np.ascontiguousarray(blk.values), lay.rows, lay.cols, h, out)
            return out
        for lay, blk in self._pairs():
            if not lay.k:
                continue
            acc = np.zeros((lay.k, lay.r))
            for cols, v in zip(blk.part_cols, blk.part_values, strict=True):
                spec = "krc,c->kr" if cols.ndim == 1 else "krc,kc->kr"
                acc += np.einsum(spec, v, h[cols])
            out[lay.rows] = acc
        return out

    def column_norms(self) -> np.ndarray:
        """(n,) the Euclidean norm of every column of J."""
        sq = np.zeros(self.n_params)
        for lay, blk in self._pairs():
            if lay.k:
                sq2 = np.einsum("krc,krc->kc", blk.values, blk.values)
                sq += np.bincount(lay.cols.ravel(), sq2.ravel(), minlength=self.n_params)
        return np.sqrt(sq)

    def all_finite(self) -> bool:
        """Whether every stored derivative is finite (a block's parts side by side in one
        contiguous array, when it has them so, else part by part)."""
        for blk in self.blocks:
            v = blk._values
            if v is not None:
                if not np.isfinite(v).all():
                    return False
            elif not all(np.isfinite(p).all() for p in blk.part_values):
                return False
        return True

    def to_csr(self) -> scipy.sparse.csr_matrix:
        """J as a ``scipy.sparse.csr_matrix`` (m, n)."""
        rows, cols, data = [], [], []
        for lay, blk in self._pairs():
            k, r, c = blk.values.shape
            rows.append(np.broadcast_to(lay.rows[:, :, None], (k, r, c)).ravel())
            cols.append(np.broadcast_to(lay.cols[:, None, :], (k, r, c)).ravel())
            data.append(blk.values.ravel())
        if rows:
            rows, cols, data = np.concatenate(rows), np.concatenate(cols), np.concatenate(data)
        return scipy.sparse.csr_matrix((data, (rows, cols)), shape=self.shape)

    def normal_equations(self) -> NormalEquations:
        """``N = J^T J`` in block form (see :class:`NormalEquations`), made once per Jacobian
        (its values never change) and shared by every caller, with its factorisations."""
        if getattr(self, "_ne", None) is None:
            self._ne = NormalEquations(self)
        return self._ne


# ----------------------------------------------------------------------------------------
# normal equations
# ----------------------------------------------------------------------------------------


class _Factor:
    """A factorisation of the damped system: V*^-1 blocks, Y = W V*^-1 per batch, chol(S)."""

    __slots__ = ("Vinv", "Ys", "Y_slots", "cho", "s_scale")


class NormalEquations:
    """``N = J^T J`` of a :class:`BlockSparseJacobian` in block form.

    Attributes
    ----------
    U : (n_r, n_r) ndarray
        The reduced-reduced block.
    V : (n_blocks, b, b) ndarray
        The diagonal blocks of the eliminated part.
    W_slots : (n_slots, b) ndarray
        The coupling ``W = J_r^T J_e`` by slots: ``W[slot_col[s], b*slot_e[s] + j] =
        W_slots[s, j]`` (see :meth:`coupling` for the sparse matrix).
    """

    def __init__(self, jac: BlockSparseJacobian):
        self.jac = jac
        st = jac.structure
        self.structure = st
        nr, b, nb = jac.n_reduced, jac.elim_block_size, jac.n_elim_blocks
        self.n_reduced, self.b, self.n_blocks = nr, b, nb
        U = np.zeros(nr * nr)
        V = np.zeros(nb * b * b)
        Ws = np.zeros(st.n_slots * b)
        kern = blocksparse_kernels.assemble()
        for lay, blk in jac._pairs():
            if not lay.k:
                continue
            values = blk.values
            if lay.c_r:
                A = lay.reduced_values(values)
                if lay.n_keys == 1:
                    As = A.reshape(-1, lay.c_r)
                    U += np.bincount(lay.U_dest, (As.T @ As).ravel(), minlength=nr * nr)
                else:
                    if lay.order is not None:
                        A = A[lay.order]
                    if lay.loop_keys:
                        As = A.reshape(-1, lay.c_r)
                        M = np.empty((lay.n_keys, lay.c_r, lay.c_r))
                        rs = lay.starts * lay.r
                        for p in range(lay.n_keys):
                            seg = As[rs[p]:rs[p + 1]]
                            M[p] = seg.T @ seg
                    else:
                        M = np.add.reduceat(A.transpose(0, 2, 1) @ A, lay.starts[:-1], axis=0)
                    U += np.bincount(lay.U_dest, M.ravel(), minlength=nr * nr)
            if lay.c_e and kern is not None:         # V and W by the compiled loop
                self._assemble_compiled(kern, lay, values, V.reshape(nb, b, b), Ws.reshape(st.n_slots, b))
            elif lay.c_e:
                B = lay.elim_values_full(values, b)
                V += np.bincount(lay.V_dest, (B.transpose(0, 2, 1) @ B).ravel(),
                                 minlength=nb * b * b)
                if lay.c_r:
                    A = lay.reduced_values(values)
                    W_dest = (lay.slot_idx[:, :, None] * b + np.arange(b)).ravel()
                    Ws += np.bincount(W_dest, (A.transpose(0, 2, 1) @ B).ravel(),
                                      minlength=st.n_slots * b)
        self.U = U.reshape(nr, nr)
        self.V = V.reshape(nb, b, b)
        self.W_slots = Ws.reshape(st.n_slots, b)
        self._zero = self._WT = self._Cr = self._Cee = self._cross = self._dense_cov = None

    def _assemble_compiled(self, kern, lay, values, V, Ws):
        """V and W_slots of one residual block by the compiled loop (U is formed by BLAS)."""
        slot_idx = np.ascontiguousarray(lay.slot_idx, np.intp) if lay.c_r else np.zeros((0, 0), np.intp)
        kern(np.ascontiguousarray(values), lay.red_pos, lay.elim_pos, np.zeros((1, 0), np.intp),
             np.zeros(lay.k, np.intp), lay.e.astype(np.intp), np.ascontiguousarray(lay.local, np.intp), slot_idx,
             np.zeros((0, 0)), V, Ws, False)

    # -- assembled views (for checks and small problems) ---------------------------------

    def coupling(self) -> scipy.sparse.csr_matrix:
        """``W`` (n_r, n_blocks * b) as a sparse matrix."""
        st, b = self.structure, self.b
        rows = np.repeat(st.slot_col, b)
        cols = (st.slot_e[:, None] * b + np.arange(b)).ravel()
        return scipy.sparse.csr_matrix((self.W_slots.ravel(), (rows, cols)),
                                       shape=(self.n_reduced, self.n_blocks * b))

    # -- factorisation ------------------------------------------------------------------

    def _damping(self, damping):
        n = self.jac.n_params
        if damping is None:
            return np.zeros(n)
        d = np.asarray(damping, dtype=float)
        d = np.broadcast_to(d, (n,)) if d.ndim == 0 else d
        if d.shape != (n,) or not np.all(np.isfinite(d)) or np.any(d < 0):
            raise InputError(f"damping must be a finite, non-negative scalar or ({n},) array",
                             "NormalEquations.solve")
        return d

    def _factor(self, damping) -> _Factor:
        if damping is None and self._zero is not None:
            return self._zero
        d = self._damping(damping)
        nr, b, nb = self.n_reduced, self.b, self.n_blocks
        f = _Factor()
        # V* = V + D_e, inverted block by block (equilibrated, Cholesky-checked)
        if nb:
            Vd = self.V + d[nr:].reshape(nb, b)[:, :, None] * np.eye(b)
            f.Vinv = _batched_spd_inverse(Vd, offset=nr, b=b)
        else:
            f.Vinv = np.zeros((0, b, b))
        # S = U + D_r - sum_e W_e V*_e^-1 W_e^T
        S, f.Ys, f.Y_slots = self._schur(d[:nr], f.Vinv)
        f.cho, f.s_scale = equilibrated_cholesky(S)
        if damping is None:
            self._zero = f
        return f

    def _schur(self, d_r, Vinv):
        """``S = U + diag(d_r) - W V*^-1 W^T`` and the per-batch ``Y = W_e V*_e^-1``."""
        nr, b, st = self.n_reduced, self.b, self.structure
        S = self.U.copy()
        S[np.diag_indices(nr)] += d_r
        kern = blocksparse_kernels.schur()
        if kern is not None:                       # W_s V*_e^-1 per slot, S -= W V*^-1 W^T
            Y = np.empty_like(self.W_slots)
            if st.n_slots:
                T = np.zeros((nr, nr))             # one triangle of W V*^-1 W^T (each pair once)
                kern(np.ascontiguousarray(self.W_slots), st.slot_col.astype(np.intp), st.slot_ptr,
                     np.ascontiguousarray(Vinv), T, Y)
                S -= T + T.T
                S[np.diag_indices(nr)] += np.diag(T)
            return 0.5 * (S + S.T), None, Y
        Ys = []
        if st.buckets:
            Wx = np.vstack([self.W_slots, np.zeros((1, b))])
            T_all, T_views = st.workspace()
            for bk, T in zip(st.buckets, T_views, strict=True):
                Wg = Wx[bk.gather]                                  # (n_t, s, b)
                Y = Wg @ Vinv[bk.es]                                # W_e V*_e^-1
                np.matmul(Y, Wg.transpose(0, 2, 1), out=T)          # W_e V*_e^-1 W_e^T
                Ys.append(Y)
            S -= np.bincount(st.dest_all, T_all, minlength=nr * nr + 1)[:-1].reshape(nr, nr)
        return 0.5 * (S + S.T), Ys, None

    def schur_complement(self, damping=None) -> np.ndarray:
        """``S = U + D_r - W (V + D_e)^-1 W^T`` (n_r, n_r) for damping ``D`` (n,) or scalar."""
        d = self._damping(damping)
        nr, b, nb = self.n_reduced, self.b, self.n_blocks
        Vinv = (_batched_spd_inverse(self.V + d[nr:].reshape(nb, b)[:, :, None] * np.eye(b), nr, b)
                if nb else np.zeros((0, b, b)))
        return self._schur(d[:nr], Vinv)[0]

    def solve(self, g, damping=None) -> np.ndarray:
        """Solve ``(N + diag(damping)) h = -g``.

        Parameters
        ----------
        g : (n,) array_like
            The gradient ``J^T r``.
        damping : float or (n,) array_like, optional
            Non-negative values added to the diagonal of N (default 0).

        Returns
        -------
        h : (n,) ndarray

        Raises
        ------
        SingularSystemError
            When the damped system is not (numerically) positive definite.
        """
        g = np.asarray(g, dtype=float)
        n, nr, b, nb, st = self.jac.n_params, self.n_reduced, self.b, self.n_blocks, self.structure
        if g.shape != (n,):
            raise InputError(f"g must have shape ({n},), got {g.shape}", "NormalEquations.solve")
        f = self._factor(damping)
        g_r, g_e = g[:nr], g[nr:].reshape(nb, b)
        Vg = np.einsum("eij,ej->ei", f.Vinv, g_e)                       # V*^-1 g_e
        WT = self._coupling_transposed() if st.n_slots else None
        rhs = -g_r
        if WT is not None:                # -g_r + W V*^-1 g_e, slot by slot (no transposed copy of W^T)
            rhs = rhs + np.bincount(st.slot_col, np.einsum("sj,sj->s", self.W_slots, Vg[st.slot_e]),
                                    minlength=nr)
        h_r = _cho_solve(f, rhs)
        h = np.empty(n)
        h[:nr] = h_r
        if nb:
            t = -g_e if WT is None else -g_e - (WT @ h_r).reshape(nb, b)   # -g_e - W^T h_r
            h[nr:] = np.einsum("eij,ej->ei", f.Vinv, t).ravel()
        return h

    def _coupling_transposed(self):
        """``W^T`` (n_blocks * b, n_r) as a block-sparse (b x 1 blocks) matrix, in slot order."""
        if self._WT is None:
            st = self.structure
            self._WT = scipy.sparse.bsr_matrix((self.W_slots[:, :, None], st.slot_col, st.slot_ptr),
                                               shape=(self.n_blocks * self.b, self.n_reduced))
        return self._WT

    # -- covariance (N^-1, undamped) ------------------------------------------------------

    def covariance_reduced(self) -> np.ndarray:
        """``(N^-1)_rr = S^-1`` (n_r, n_r): the reduced block of the inverse normal matrix."""
        if self._Cr is None:
            f = self._factor(None)
            nr = self.n_reduced
            if nr:
                C = _inverse_from_cholesky(f.cho)
                C = f.s_scale[:, None] * C * f.s_scale[None, :]
                self._Cr = 0.5 * (C + C.T)
            else:
                self._Cr = np.zeros((0, 0))
        return self._Cr

    def _elim_covariances(self):
        """(N^-1)_ee diagonal blocks and the cross blocks (N^-1)[slot_col, e-block] per slot."""
        if self._Cee is not None:
            return self._Cee, self._cross
        f = self._factor(None)
        Cr = self.covariance_reduced()
        st, b = self.structure, self.b
        Cee = f.Vinv.copy()
        if f.Y_slots is not None:                  # the compiled path keeps Y per slot
            cross = np.zeros((st.n_slots, b))
            if st.n_slots and self.n_reduced:
                blocksparse_kernels.elim_covariances()(f.Y_slots, st.slot_col.astype(np.intp), st.slot_ptr,
                                                       np.ascontiguousarray(Cr), Cee, cross)
            self._Cee, self._cross = 0.5 * (Cee + Cee.transpose(0, 2, 1)), cross
            return self._Cee, self._cross
        cross = np.zeros((st.n_slots + 1, b))
        if st.n_slots and self.n_reduced:
            for bk, Y in zip(st.buckets, f.Ys, strict=True):
                Crs = Cr[bk.cols_e[:, :, None], bk.cols_e[:, None, :]]      # (n_t, s, s)
                X = Crs @ Y                                                  # S^-1 W_e V_e^-1 rows
                Cee[bk.es] += Y.transpose(0, 2, 1) @ X
                cross[bk.gather] = -X
        self._Cee = 0.5 * (Cee + Cee.transpose(0, 2, 1))
        self._cross = cross[:-1]
        return self._Cee, self._cross

    def dense_matrix(self) -> np.ndarray:
        """``N`` (n, n) assembled densely from ``U``, ``W`` and ``V`` (for modest n only)."""
        nr, b, nb = self.n_reduced, self.b, self.n_blocks
        n = nr + nb * b
        N = np.zeros((n, n))
        N[:nr, :nr] = self.U
        if nb:
            W = self.coupling().toarray()
            N[:nr, nr:] = W
            N[nr:, :nr] = W.T
            idx = nr + np.arange(nb)[:, None] * b + np.arange(b)
            N[idx[:, :, None], idx[:, None, :]] = self.V
        return N

    def covariance_dense(self) -> np.ndarray:
        """``N^-1`` (n, n) from the blocks (for modest n only; see the module docstring).

        ``(N^-1)_rr = S^-1``, ``(N^-1)_re = -S^-1 Y``, ``(N^-1)_ee = V^-1 + Y^T S^-1 Y``
        with ``Y = W V^-1``; raises :class:`SingularSystemError` as :meth:`solve` does.
        """
        if self._dense_cov is not None:          # made once per normal equations; a copy each call
            return self._dense_cov.copy()
        Cr = self.covariance_reduced()
        nr, b, nb = self.n_reduced, self.b, self.n_blocks
        if not nb:
            return Cr.copy()
        Vinv = self._factor(None).Vinv
        W = self.coupling().toarray().reshape(nr, nb, b)
        Y = np.einsum("rej,ejk->rek", W, Vinv).reshape(nr, nb * b)
        n = nr + nb * b
        C = np.zeros((n, n))
        C[:nr, :nr] = Cr
        C[:nr, nr:] = -Cr @ Y
        C[nr:, :nr] = C[:nr, nr:].T
        Cee = Y.T @ Cr @ Y
        idx = np.arange(nb)[:, None] * b + np.arange(b)
        Cee[idx[:, :, None], idx[:, None, :]] += Vinv
        C[nr:, nr:] = 0.5 * (Cee + Cee.T)
        self._dense_cov = C
        return C.copy()

    def covariance_elim_blocks(self) -> np.ndarray:
        """(n_blocks, b, b) the diagonal blocks of ``N^-1`` for the eliminated parameters."""
        return self._elim_covariances()[0]

    def group_covariance(self, block_index: int) -> np.ndarray:
        """``J_g N^-1 J_g^T`` (k, r_rows, r_rows) for every group of one residual block.

        For unit-weight residuals the cofactor matrix of group ``g``'s residuals is
        ``Q_vv = I - J_g N^-1 J_g^T`` and its redundancy numbers are the diagonal of Q_vv.
        """
        st = self.structure
        if not 0 <= block_index < len(st.layouts):
            raise InputError(f"block_index must lie in [0, {len(st.layouts)}), got {block_index}",
                             "NormalEquations.group_covariance")
        lay = st.layouts[block_index]
        values = self.jac.blocks[block_index].values
        Q = np.zeros((lay.k, lay.r, lay.r))
        if not lay.k:
            return Q
        kern = blocksparse_kernels.group_covariance()
        if kern is not None:
            empty2, empty3 = np.zeros((0, 0), np.intp), np.zeros((0, 0, 0))
            Cr = self.covariance_reduced() if lay.c_r else np.zeros((0, 0))
            key_cols, key_id = ((lay.key_cols.astype(np.intp), lay.key_id) if lay.c_r
                                else (np.zeros((1, 0), np.intp), np.zeros(lay.k, np.intp)))
            if lay.c_e:
                Cee, cross = self._elim_covariances()
                e, local = lay.e.astype(np.intp), np.ascontiguousarray(lay.local, np.intp)
                slot_idx = np.ascontiguousarray(lay.slot_idx, np.intp) if lay.c_r else empty2
                cross = np.ascontiguousarray(cross) if lay.c_r else np.zeros((0, 0))
            else:
                Cee, cross, e, local, slot_idx = empty3, np.zeros((0, 0)), np.zeros(0, np.intp), empty2, empty2
            kern(np.ascontiguousarray(values), lay.red_pos, lay.elim_pos, key_cols, key_id, e, local, slot_idx,
                 np.ascontiguousarray(Cr), np.ascontiguousarray(Cee), cross, Q)
            return Q
        if lay.c_r:
            Cr = self.covariance_reduced()
            kc = lay.key_cols
            Ck = Cr[kc[:, :, None], kc[:, None, :]]                         # (n_keys, c_r, c_r)
            A = lay.reduced_values(values)
            AC = A @ (Ck if lay.n_keys == 1 else Ck[lay.key_id])
            Q += AC @ A.transpose(0, 2, 1)
        if lay.c_e:
            Cee, cross = self._elim_covariances()
            B = lay.elim_values_full(values, self.b)
            Q += B @ Cee[lay.e] @ B.transpose(0, 2, 1)
            if lay.c_r:
                T = A @ cross[lay.slot_idx] @ B.transpose(0, 2, 1)
                Q += T + T.transpose(0, 2, 1)
        return Q


def _pivot_tol(n: int) -> float:
    return max(n, 1) * _EPS


def equilibrated_cholesky(S):
    """Cholesky of ``D S D`` with ``D = diag(S)^-1/2``; raises SingularSystemError."""
    nr = S.shape[0]
    if nr == 0:
        return None, np.zeros(0)
    dg = np.diag(S).copy()
    if not np.all(np.isfinite(S)):
        raise SingularSystemError("the reduced normal equations contain non-finite numbers",
                                  "reduced")
    if np.any(dg <= 0):
        j = int(np.argmin(dg))
        raise SingularSystemError(f"reduced parameter {j} has no information (diagonal {dg[j]:.3g} "
                                  "of the Schur complement)", "reduced", j)
    s = 1.0 / np.sqrt(dg)
    try:
        c, low = scipy.linalg.cho_factor(S * s[:, None] * s[None, :], lower=False,
                                         check_finite=False)
    except np.linalg.LinAlgError as err:
        raise SingularSystemError(f"the reduced Schur complement is not positive definite ({err})",
                                  "reduced") from None
    piv = np.diag(c) ** 2
    j = int(np.argmin(piv))
    if piv[j] < _pivot_tol(nr):
        raise SingularSystemError(f"the reduced Schur complement is singular: pivot {piv[j]:.2e} "
                                  f"of reduced parameter {j} (relative to its diagonal)", "reduced",
                                  j)
    return (c, low), s


def _inverse_from_cholesky(cho) -> np.ndarray:
    """``A^-1`` from the Cholesky factor ``(c, lower)`` of :func:`scipy.linalg.cho_factor`
    by LAPACK ``potri`` (a third of the work of solving for the identity), both triangles."""
    c, lower = cho
    inv, info = scipy.linalg.lapack.dpotri(c, lower=lower)
    if info != 0:
        raise SingularSystemError(f"the reduced Schur complement cannot be inverted (LAPACK potri info {info})",
                                  "reduced")
    if lower:
        full = np.tril(inv)
        full += np.tril(inv, -1).T
    else:
        full = np.triu(inv)
        full += np.triu(inv, 1).T
    return full


def _cho_solve(f: _Factor, rhs):
    if f.cho is None:
        return np.zeros(0)
    return f.s_scale * scipy.linalg.cho_solve(f.cho, f.s_scale * rhs, check_finite=False)


def _batched_spd_inverse(Vd, offset: int, b: int):
    """Inverses of symmetric positive definite blocks (nb, b, b), equilibrated and checked."""
    dg = np.diagonal(Vd, axis1=1, axis2=2)
    bad = ~np.isfinite(dg) | (dg <= 0)
    if bad.any():
        e, j = np.argwhere(bad)[0]
        raise SingularSystemError(f"eliminated block {e} (parameter {offset + b * e + j}) has no "
                                  "information", "eliminated", int(offset + b * e + j))
    s = 1.0 / np.sqrt(dg)
    Vs = Vd * s[:, :, None] * s[:, None, :]
    try:
        L = np.linalg.cholesky(Vs)
        piv = np.diagonal(L, axis1=1, axis2=2) ** 2
    except np.linalg.LinAlgError:
        piv = np.linalg.eigvalsh(Vs)
    e, j = np.unravel_index(np.argmin(piv), piv.shape) if piv.size else (0, 0)
    if piv.size and not piv[e, j] >= _pivot_tol(b):
        raise SingularSystemError(f"eliminated block {e} is singular (pivot {piv[e, j]:.2e} "
                                  "relative to its diagonal)", "eliminated", int(offset + b * e))
    Vinv = np.linalg.inv(Vs)
    Vinv = Vinv * s[:, :, None] * s[:, None, :]
    return 0.5 * (Vinv + Vinv.transpose(0, 2, 1))
