"""Block sparsity patterns of normal matrices and their assembly.

The normal matrix ``N = A' M^-1 A`` has one ``d x d`` block per node and one off-diagonal block
pair per connected node pair, so it has the sparsity of the connection graph. It is assembled from
per-connection blocks with a pattern computed once (:class:`BlockPattern`), kept per pattern
(:func:`kept_block_pattern`) so a sliding window whose pattern repeats every track builds it once.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import lazy_import

try:  # CPython's BLAKE2 module: what hashlib.blake2b is, without loading OpenSSL (~5 ms)
    from _blake2 import blake2b as _blake2b
except ImportError:  # pragma: no cover - another interpreter
    from hashlib import blake2b as _blake2b

sla = lazy_import('scipy.linalg')  # only some functions need them (start-up)
sp = lazy_import('scipy.sparse')

#: Blocks assembled per pass by :meth:`BlockPattern.assemble` (bounds its temporaries).
_ASSEMBLY_CHUNK = 1 << 18


#: Patterns with fewer stored entries keep the position of every block entry (a gather per
#: assembly); larger ones compute them from each block's column and rank when assembling
#: (~180 MB less at 100,000 poses).
_POSITIONS_KEPT_BELOW = 1 << 22


class BlockPattern:
    """Where each entry of many dense ``d x d`` blocks lands in a sparse lower triangle (CSC).

    Only block *pairs* are sorted (not their ``d^2`` scalars): the scalar layout of a lower
    block column follows from its sorted block rows, the diagonal block first.

    Parameters
    ----------
    block_rows, block_cols : (k,) block coordinates (column index of the unknown block; -1 for a
        fixed node, whose entries are dropped). Every block column must hold its diagonal block.
    d : block size.
    n : number of unknown blocks.
    """

    def __init__(self, block_rows: IntArray, block_cols: IntArray, d: int, n: int) -> None:
        self.d = d
        self.size = d * n
        br = np.asarray(block_rows, dtype=np.int64)
        bc = np.asarray(block_cols, dtype=np.int64)
        keep_blk = (br >= 0) & (bc >= 0) & (br >= bc)
        self._keep_blk = keep_blk
        kbr, kbc = br[keep_blk], bc[keep_blk]
        key = kbc * max(n, 1) + kbr  # column-major: sorted by column, then row
        ukey, inv = np.unique(key, return_inverse=True)
        ucol, urow = ukey // max(n, 1), ukey % max(n, 1)
        self.n_blocks = n
        self.block_lower = (urow, ucol)  # unique lower block pairs (row >= col), column-major
        self.key = _blake2b(np.ascontiguousarray(ukey).tobytes()
                                   + np.int64(n).tobytes() + np.int64(d).tobytes(),
                                   digest_size=16).digest()
        nblk_col = np.bincount(ucol, minlength=n)
        if n and not np.array_equal(np.sort(ucol[urow == ucol]), np.arange(n)):
            raise DegenerateGeometryError('a block column has no diagonal block')
        first = np.concatenate([[0], np.cumsum(nblk_col)[:-1]])
        rank = np.arange(ukey.size) - first[ucol]  # 0 for the diagonal block
        a = np.arange(d)
        # entries per scalar column J*d + a: d * blocks - a
        counts = (d * nblk_col[:, None] - a[None, :]).reshape(-1)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.nnz = int(self.indptr[-1])
        self._ucol, self._urank = ucol, rank
        self._tril = (a[:, None] >= a[None, :]).reshape(-1)  # (d^2,) row-major: row >= col
        # the row of every stored entry: kept for small patterns, computed when asked for large
        # ones (~180 MB at 100,000 poses; only the analysis and CSC views read it)
        small = self.nnz < _POSITIONS_KEPT_BELOW
        # positions of the unique blocks' entries: computed once for both uses below
        upos = self._block_positions(np.arange(ukey.size)) if small else None
        self._indices = self._row_indices(upos) if small else None
        # which entries of each kept block land in the lower triangle: all of an off-diagonal
        # block, the lower triangle of a diagonal one (one flag per block, not per entry)
        self._kept_diag = (rank == 0)[inv]
        # each kept block's unique block, that block's column and rank in it: positions of
        # the entries of any kept blocks (:meth:`_positions`)
        self._kept_u = inv.astype(np.int32 if ukey.size < 2**31 else np.int64)
        self._pos: IntArray | None = None
        if small:  # kept: a gather instead of the arithmetic (int32: it fits)
            self._pos = upos[self._kept_u][self._valid(slice(None))]
        self._gather: IntArray | None = None  # built by assemble on first use
        self._kept_idx: IntArray | None = None  # the kept blocks (compiled assemble)
        self._full: tuple | None = None  # built by full_csc on first use
        self._valid_before: IntArray | None = None  # built by assemble_at on first use
        self._kept_rank: IntArray | None = None

    @staticmethod
    def from_matrix(N: sp.spmatrix, d: int) -> tuple[BlockPattern, FloatArray]:
        """The block pattern of a symmetric sparse matrix of ``d x d`` blocks and its lower
        triangle's values on it (every diagonal block is kept, even if zero).

        With the compiled kernels, one pass over ``N``'s lower triangle finds its blocks
        (:func:`_lower_blocks_py`) and one puts its values where they land
        (:func:`_lower_values_py`): the same pattern and the same values, bit for bit, as
        the NumPy path (a block-sparse copy of ``N``, a pattern built from its block list of
        both triangles and the blocks summed into it), in about a third of the time."""
        kernels = _from_matrix_kernels()
        if kernels is None:
            return BlockPattern._from_matrix_numpy(N, d)
        find_blocks, put_values = kernels
        C = sp.csc_matrix(N)
        if not C.has_canonical_format:
            C = C.copy()
            C.sum_duplicates()
        n = C.shape[0] // d
        indptr, indices = C.indptr, C.indices
        count = np.zeros(n, dtype=np.int64)
        rows = np.empty(indices.size + n, dtype=np.int64)  # at most one block per entry
        mark = np.full(n, -1, dtype=np.int64)
        k = find_blocks(indptr, indices, d, n, count, rows, mark)
        pattern = BlockPattern._of_lower(rows[:k], count, d, n)
        out = np.zeros(pattern.nnz)
        put_values(indptr, indices, np.ascontiguousarray(C.data, dtype=float), d, n,
                   pattern.indptr, count, rows, mark, out)
        return pattern, out

    @staticmethod
    def _of_lower(urow: IntArray, count: IntArray, d: int, n: int) -> BlockPattern:
        """The pattern of the lower block pairs ``urow`` (per block column ``count[J]`` of
        them, the diagonal block first, then ascending: :func:`_lower_blocks_py`), built from
        that list itself: the same pattern as ``BlockPattern(urow, ucol, d, n)`` (its block
        list the unique pairs), without sorting them again; the row of every entry comes from
        one compiled pass (:func:`_lower_rows_py`), the positions of a block list's entries
        (:meth:`assemble`) are computed if it is ever asked to assemble one."""
        self = BlockPattern.__new__(BlockPattern)
        self.d = d
        self.size = d * n
        self.n_blocks = n
        ucol = np.repeat(np.arange(n, dtype=np.int64), count)
        first = np.zeros(n, dtype=np.int64)
        np.cumsum(count[:-1], out=first[1:])
        rank = np.arange(urow.size, dtype=np.int64) - first[ucol]
        self._keep_blk = np.ones(urow.size, dtype=bool)
        self.block_lower = (urow, ucol)
        ukey = ucol * max(n, 1) + urow
        self.key = _blake2b(np.ascontiguousarray(ukey).tobytes() + np.int64(n).tobytes()
                            + np.int64(d).tobytes(), digest_size=16).digest()
        a = np.arange(d)
        counts = (d * count[:, None] - a[None, :]).reshape(-1)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.nnz = int(self.indptr[-1])
        self._ucol, self._urank = ucol, rank
        self._tril = (a[:, None] >= a[None, :]).reshape(-1)
        self._indices = np.empty(self.nnz, dtype=np.int64)
        _lower_rows_kernel()(d, n, count, urow, self._indices)
        self._kept_diag = rank == 0
        self._kept_u = np.arange(urow.size, dtype=np.int32 if urow.size < 2**31 else np.int64)
        self._pos = None
        self._gather = None
        self._kept_idx = None
        self._full = None
        self._valid_before = None
        self._kept_rank = None
        return self

    @staticmethod
    def _from_matrix_numpy(N: sp.spmatrix, d: int) -> tuple[BlockPattern, FloatArray]:
        """:meth:`from_matrix` with NumPy and SciPy only (without numba; the reference of the
        compiled path's tests)."""
        n = N.shape[0] // d
        Nb = sp.bsr_matrix(sp.csr_matrix(N), blocksize=(d, d))
        Nb.sort_indices()
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(Nb.indptr))
        cols = Nb.indices.astype(np.int64)
        diag = np.arange(n, dtype=np.int64)
        blocks = np.concatenate([Nb.data, np.zeros((n, d, d))])
        pattern = BlockPattern(np.concatenate([rows, diag]), np.concatenate([cols, diag]), d, n)
        return pattern, pattern.assemble(blocks)

    def assemble(self, blocks: FloatArray, compiled: bool = False) -> FloatArray:
        """Sum blocks ``(k, d, d)`` (block row, col) into the lower-triangle CSC values.

        More than :data:`_ASSEMBLY_CHUNK` blocks go in chunks, added in place: the temporaries
        (two copies of the blocks in one pass, ~1.4 GB for a survey of 100,000 poses) stay
        ~150 MB. ``compiled`` (a caller that runs the compiled kernels anyway, e.g. a window
        update): the blocks of a small pattern are added by one compiled loop instead of a
        gather and a ``bincount`` (the same sums in the same order; ~2x faster)."""
        small = blocks.shape[0] <= _ASSEMBLY_CHUNK
        if small and self._pos is not None and blocks.shape[0] == self._keep_blk.size:
            scatter = _scatter_kernel() if compiled else None
            if scatter is not None:  # no gather index (~1 M entries for a window) either
                if self._kept_idx is None:
                    self._kept_idx = np.flatnonzero(self._keep_blk)
                out = np.zeros(self.nnz)
                scatter(np.ascontiguousarray(blocks, dtype=float).reshape(-1), self._kept_idx,
                        self._kept_diag, self._tril, self._pos, out)
                return out
            # one gather of the kept entries (instead of two masked copies): ~2x faster
            if self._gather is None:
                self._gather = self._kept_entries()
            vals = blocks.reshape(-1)[self._gather]
            return np.bincount(self._pos, weights=vals, minlength=self.nnz)
        if small:
            vals = blocks[self._keep_blk].reshape(-1)[self._valid(slice(None)).reshape(-1)]
            pos = self._pos if self._pos is not None else self._positions(slice(None))
            return np.bincount(pos, weights=vals, minlength=self.nnz)
        keep, done = np.nonzero(self._keep_blk)[0], 0
        out = np.zeros(self.nnz)
        for a in range(0, keep.size, _ASSEMBLY_CHUNK):
            part = slice(a, a + _ASSEMBLY_CHUNK)
            vals = blocks[keep[part]].reshape(-1)[self._valid(part).reshape(-1)]
            pos = (self._pos[done:done + vals.size] if self._pos is not None
                   else self._positions(part))
            np.add.at(out, pos, vals)  # no nnz-long temporary
            done += vals.size
        return out

    def _kept_entries(self) -> IntArray:
        """``(len(_pos),)`` flat index, into the ``(k, d, d)`` block list this pattern was
        built from, of each entry that lands in the lower triangle, in the order of ``_pos``."""
        d2 = self.d * self.d
        it = np.int32 if self._keep_blk.size * d2 < 2**31 else np.int64  # half the traffic
        kept = np.flatnonzero(self._keep_blk).astype(it)
        return (kept[:, None] * it(d2) + np.arange(d2, dtype=it)[None, :])[
            self._valid(slice(None))]

    def assemble_at(self, blocks: FloatArray, index: IntArray, out: FloatArray) -> None:
        """Add blocks ``(k, d, d)`` that stand at the positions ``index`` of the block list
        this pattern was built from into ``out`` (lower-triangle CSC values, in place): the
        assembly of a large system a part at a time (``assemble`` of the whole list equals the
        sum over disjoint parts)."""
        d = self.d
        d2 = d * d
        if self._kept_rank is None:  # position among the kept blocks
            self._kept_rank = (np.cumsum(self._keep_blk) - 1).astype(np.int32)
        if self._valid_before is None and self._pos is not None:
            per = np.where(self._kept_diag, d * (d + 1) // 2, d2)
            self._valid_before = np.concatenate([[0], np.cumsum(per)])
        index = np.asarray(index, dtype=np.int64)
        keep = self._keep_blk[index]
        rank = self._kept_rank[index[keep]]
        valid = self._valid(rank)
        if self._pos is None:
            where = self._positions(rank)
        else:
            count = valid.sum(axis=1)
            first = np.repeat(self._valid_before[rank] - np.cumsum(count) + count, count)
            where = self._pos[first + np.arange(first.size)]
        # in place: a bincount would allocate an nnz-long array per part (~190 MB at 100,000
        # poses) and np.add.at is faster for a part's few million entries
        np.add.at(out, where, blocks[keep].reshape(-1, d2)[valid])

    @property
    def indices(self) -> IntArray:
        """(nnz,) int64 row of each stored entry of the lower-triangle CSC values."""
        return self._indices if self._indices is not None else self._row_indices()

    def _row_indices(self, upos: IntArray | None = None) -> IntArray:
        """(nnz,) row of each stored entry; ``upos``: the unique blocks' positions
        (:meth:`_block_positions` of all of them) if the caller has them."""
        d = self.d
        if upos is None:
            upos = self._block_positions(np.arange(self._ucol.size))
        valid = np.where((self._urank == 0)[:, None], self._tril[None, :], True)
        it = np.int32 if self.size < 2**31 else np.int64  # the temporaries: half the traffic
        rows = (self.block_lower[0].astype(it)[:, None] * it(d)
                + np.repeat(np.arange(d, dtype=it), d)[None, :])
        out = np.empty(self.nnz, dtype=np.int64)
        out[upos[valid]] = rows[valid]
        return out

    def _block_positions(self, u: IntArray) -> IntArray:
        """``(k, d^2)`` positions in the lower-triangle CSC values of the entries (row-major)
        of the unique blocks ``u`` (meaningless for the upper entries of a diagonal block);
        int32 when the values fit.

        Row ``b``, column ``a`` of a block of rank ``r`` in its block column lies
        ``r d + b - a`` entries after the start of scalar column ``a`` of that block column:
        after the ``d - a`` entries of the diagonal block's column ``a`` and ``r - 1`` earlier
        blocks of ``d`` rows (the diagonal block itself, ``r = 0``: ``b - a``)."""
        d = self.d
        a = np.arange(d)
        it = np.int32 if self.nnz < 2**31 else np.int64
        colstart = self.indptr[:-1].reshape(-1, d).astype(it)  # (block columns, a)
        start = colstart[self._ucol[u]] - a.astype(it)  # (k, a)
        start += (self._urank[u] * d).astype(it)[:, None]
        out = start[:, None, :] + a.astype(it)[None, :, None]  # (k, b, a)
        return out.reshape(-1, d * d)

    def _positions(self, kept) -> IntArray:
        """Positions in the lower-triangle CSC values of the entries of the kept blocks
        ``kept`` (an index or a slice of the kept blocks) that land there, block by block, each
        block's entries row-major (the order of ``_pos``)."""
        return self._block_positions(self._kept_u[kept])[self._valid(kept)]

    def _valid(self, kept) -> np.ndarray:
        """``(k, d^2)`` flags of the entries of the kept blocks ``kept`` (an index or a slice
        of the kept blocks) that land in the lower triangle."""
        return np.where(self._kept_diag[kept][:, None], self._tril[None, :], True)

    def matvec(self, data: FloatArray, x: FloatArray) -> FloatArray:
        """``N x`` for the symmetric matrix whose lower triangle is ``data`` (NumPy only: the
        dogleg's products need no ``scipy.sparse``)."""
        cols = np.repeat(np.arange(self.size), np.diff(self.indptr))
        x = np.asarray(x, dtype=float)
        y = np.bincount(self.indices, weights=data * x[cols], minlength=self.size)  # L x
        y += np.bincount(cols, weights=data * x[self.indices], minlength=self.size)  # L' x
        return y - data[self.indptr[:-1]] * x  # the diagonal entry heads each column

    def lower_csc(self, data: FloatArray) -> sp.csc_matrix:
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))

    def full_csc(self, data: FloatArray) -> sp.csc_matrix:
        """The symmetric matrix (both triangles), canonical, without explicit zeros (those of the
        sum ``L + L'`` of SciPy). A small pattern keeps where each entry comes from in
        ``data`` (a window's freeze builds one matrix of a repeating pattern per track)."""
        if self._full is None and self.nnz < _POSITIONS_KEPT_BELOW:
            L = self.lower_csc(np.arange(1.0, self.nnz + 1.0))  # positions, never zero
            F = (L + sp.tril(L, -1).T).tocsc()
            self._full = (F.indptr, F.indices, np.rint(F.data).astype(np.int64) - 1)
        if self._full is not None:
            indptr, indices, source = self._full
            vals = data[source]
            if vals.all():  # else: explicit zeros, dropped below as the sum drops them
                return sp.csc_matrix((vals, indices.copy(), indptr.copy()),
                                     shape=(self.size, self.size))
        L = self.lower_csc(data)
        return (L + sp.tril(L, -1).T).tocsc()


#: Guards the caches of :func:`_kept` (the freeze ahead reads them from a background thread).
_KEPT_LOCK = threading.Lock()


def _kept(cache: OrderedDict, limit: int, key: bytes, build):
    """``cache[key]``, built by ``build()`` on a miss; the ``limit`` most recent are kept.
    Thread-safe; ``build`` runs outside the lock (two threads missing at once may each build
    it, one value is kept)."""
    with _KEPT_LOCK:
        value = cache.get(key)
        if value is not None:
            cache.move_to_end(key)
            return value
    value = build()
    with _KEPT_LOCK:
        cache[key] = value
        cache.move_to_end(key)
        while len(cache) > limit:
            cache.popitem(last=False)
    return value


#: Block patterns kept by the block coordinates they were built from (the few latest).
_PATTERNS: OrderedDict[bytes, BlockPattern] = OrderedDict()


_MAX_PATTERNS = 4


def kept_block_pattern(block_rows: IntArray, block_cols: IntArray, d: int, n: int
                       ) -> BlockPattern:
    """:class:`BlockPattern` of these block coordinates, kept for the few latest (a window
    update solves problems of one repeating pattern: building it sorts every block again)."""
    key = _blake2b(block_rows.tobytes() + block_cols.tobytes()
                          + np.array([d, n], dtype=np.int64).tobytes(), digest_size=16).digest()
    return _kept(_PATTERNS, _MAX_PATTERNS, key,
                 lambda: BlockPattern(block_rows, block_cols, d, n))


def _scatter_add_py(flat, kept, diag, tril, pos, out):  # pragma: no cover - compiled
    """Add the entries of the kept blocks ``kept`` of ``flat`` (the ``(k, d, d)`` blocks,
    flattened) into ``out`` at ``pos``: block by block, each block's entries row-major, of a
    diagonal block (``diag``) only those on or below the diagonal (``tril``). The entries and
    their order are those of :meth:`BlockPattern._kept_entries`, so the sums are
    ``np.bincount(pos, weights=flat[_kept_entries()])``'s, without the gathered copy."""
    d2 = tril.size
    p = 0
    for b in range(kept.size):
        base = kept[b] * d2
        lower = diag[b]
        for e in range(d2):
            if lower and not tril[e]:
                continue
            out[pos[p]] += flat[base + e]
            p += 1


_SCATTER: list = []  # [the compiled _scatter_add_py or None], compiled on first use


def _lower_blocks_py(indptr, indices, d, n, count, rows, mark):  # pragma: no cover - compiled
    """The lower block pattern of a symmetric CSC matrix (sorted row indices) of ``d x d``
    blocks, ``n`` block columns: for block column ``J``, ``count[J]`` block rows in ``rows``
    (appended column after column): ``J`` itself first, then every block row ``R > J`` with a
    stored entry in block ``(R, J)``, ascending. ``mark``: (n,) -1, the last column that saw
    each block row (scratch). Returns the number of block rows written."""
    k = 0
    for J in range(n):
        start = k
        rows[k] = J
        mark[J] = J
        k += 1
        for j in range(J * d, J * d + d):
            for p in range(indptr[j], indptr[j + 1]):
                R = indices[p] // d
                if R > J and mark[R] != J:
                    mark[R] = J
                    rows[k] = R
                    k += 1
        # insertion sort of the off-diagonal block rows (a few per column)
        for a in range(start + 2, k):
            v = rows[a]
            b = a - 1
            while b > start and rows[b] > v:
                rows[b + 1] = rows[b]
                b -= 1
            rows[b + 1] = v
        count[J] = k - start
    return k


def _lower_values_py(indptr, indices, data, d, n, out_indptr, count, rows, rank,
                     out):  # pragma: no cover - compiled
    """Add the lower-triangle entries (row >= column) of a symmetric CSC matrix into ``out``,
    the values of its :class:`BlockPattern` (block rows per block column ``count`` and
    ``rows`` of :func:`_lower_blocks_py`, scalar column pointers ``out_indptr``): row ``b`` of
    the block of rank ``r`` in block column ``J``, scalar column ``a``, lies at
    ``out_indptr[J d + a] - a + r d + b`` (:meth:`BlockPattern._block_positions`). ``rank``:
    (n,) scratch."""
    first = 0
    for J in range(n):
        for r in range(count[J]):
            rank[rows[first + r]] = r
        first += count[J]
        for a in range(d):
            j = J * d + a
            base = out_indptr[j] - a
            for p in range(indptr[j], indptr[j + 1]):
                i = indices[p]
                if i >= j:
                    out[base + rank[i // d] * d + i % d] += data[p]


def _lower_rows_py(d, n, count, rows, out):  # pragma: no cover - compiled
    """The row of every stored entry (:attr:`BlockPattern.indices`) of the pattern of the
    lower block rows ``rows`` (``count[J]`` per block column ``J``, the diagonal first):
    scalar column ``J d + a`` holds rows ``J d + a .. J d + d - 1``, then the ``d`` rows of
    each off-diagonal block in order."""
    p = 0
    first = 0
    for J in range(n):
        for a in range(d):
            for b in range(a, d):
                out[p] = J * d + b
                p += 1
            for r in range(1, count[J]):
                R = rows[first + r]
                for b in range(d):
                    out[p] = R * d + b
                    p += 1
        first += count[J]


_ROWS: list = []  # [the compiled _lower_rows_py or None], compiled on first use


def _lower_rows_kernel():
    """:func:`_lower_rows_py` compiled (its caller runs only with the compiled kernels)."""
    return _compiled(_ROWS, _lower_rows_py)


_FROM_MATRIX: list = []  # [(the two compiled kernels) or None], compiled on first use


def _from_matrix_kernels():
    """:func:`_lower_blocks_py` and :func:`_lower_values_py` compiled, or ``None`` without
    numba (:meth:`BlockPattern.from_matrix` converts with SciPy then)."""
    if not _FROM_MATRIX:
        blocks_k = _compiled([], _lower_blocks_py)
        values_k = _compiled([], _lower_values_py)
        _FROM_MATRIX.append(None if blocks_k is None or values_k is None
                            else (blocks_k, values_k))
    return _FROM_MATRIX[0]


def _compiled(slot: list, fn):
    """``fn`` compiled with numba (cached on disk) on first use and kept in ``slot`` (a
    one-element list), or ``None`` without numba."""
    if not slot:
        from ga_ros.core.kernels import AVAILABLE, jit

        compiled = jit(fn) if AVAILABLE else None
        slot.append(compiled)
    return slot[0]


def _scatter_kernel():
    """:func:`_scatter_add_py` compiled, or ``None`` without numba
    (:meth:`BlockPattern.assemble` gathers and counts with NumPy then)."""
    return _compiled(_SCATTER, _scatter_add_py)


def _expand_cols(indptr: IntArray) -> IntArray:
    return np.repeat(np.arange(indptr.size - 1, dtype=np.int64), np.diff(indptr))


def _permute_py(x, where, inverse, seen):  # pragma: no cover - compiled
    """In place, cycle by cycle: ``x[k] <- x[where[k]]`` for every ``k`` (a gather without a
    copy), or with ``inverse`` its inverse, ``x[where[k]] <- x[k]``. ``seen``: (x.size,) False."""
    for s in range(x.size):
        if seen[s]:
            continue
        tmp = x[s]
        j = s
        while True:
            seen[j] = True
            k = where[j]
            if inverse:
                nxt = x[k]
                x[k] = tmp
                tmp = nxt
                if k == s:
                    break
            elif k == s:
                x[j] = tmp
                break
            else:
                x[j] = x[k]
            j = k


_PERMUTE: list = []  # [the compiled _permute_py or None], compiled on first use


def _permutation_kernel():
    """:func:`_permute_py` compiled, or ``None`` without numba (the values are gathered into
    a copy then)."""
    return _compiled(_PERMUTE, _permute_py)


@dataclass(frozen=True)
class _Permuted:
    """The lower triangle of ``P N P'`` in CSC: ``where`` (its entries' positions in ``N``'s
    values), ``indptr``, ``indices`` (int64, as CHOLMOD's long interface reads them)."""

    where: IntArray
    indptr: IntArray
    indices: IntArray
