"""The outcome of a solve (:class:`SolveResult`) and the factored normal matrix behind its
covariances and sequential priors."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.solver.priors import GaussianPrior
from ga_ros.errors import InputError, NetworkError, SolverError
from ga_ros.runtime import blas_threads, lazy_import

sp = lazy_import('scipy.sparse')  # only some functions need it (start-up)

#: Above this many requested nodes, covariances come from selected inversion of the whole
#: normal matrix instead of one sparse solve per column.
_MANY_NODES = 24


#: From this many unknowns on, those covariances come from selected inversion on the sparse
#: Cholesky factor (:class:`ga_ros.core.linalg.selinv.SelectedInverse`: time ~ the factorisation's,
#: memory ~ ``nnz(L)``) instead of the banded matrix (memory ~ unknowns x band): at 12,000
#: unknowns (an aerial survey of 2,000 poses) 0.7 s against 4.5 s, at 60,000 6 s against 34 s.
#: Below it (windows) the banded path needs no compiled kernel (loading numba costs ~0.5 s and
#: ~90 MiB per process).
_SPARSE_SELINV_UNKNOWNS = 12_000

#: From this many unknowns on, the covariances of up to :data:`_MANY_NODES` nodes come from a
#: forward solve along each node's elimination-tree path only
#: (:func:`ga_ros.core.linalg.selinv.path_marginal_blocks`) instead of full solves: a window's
#: newest node (the pose a node publishes after each update) lies in the factor's last
#: supernode, 1-2 ms instead of 10-20 ms at 6,700 unknowns; nodes deep in the elimination tree
#: (a window's older fix nodes) have long paths and are solved for when that is cheaper.
_PATH_FROM_UNKNOWNS = 3_000


@dataclass
class SolveResult:
    """Outcome of :func:`solve`.

    ``T_world_node``, ``node_ids`` are in network index order; ``residuals`` (``v``, (m, 6); for
    se2 the ``[x y rz]`` components, the others zero) and ``adjusted`` (``l = l_b + v``, as
    ``[t, w]``) in connection order. ``cost`` is ``v' P v`` over
    connections (with the robust weights) plus the prior terms. ``factorisations`` counts the
    numeric Cholesky factorisations of ``N`` during the iterations. ``factor_offset`` is 0 when
    the covariances come from ``N`` factored at the solution (the default), else (``solve(...,
    factor_at_solution=False)``) the sum of the largest corrections (m, rad) taken since the
    factorisation they come from: a bound on how far from the solution it was computed.
    ``quality`` is ``None``
    unless quality control was requested (:func:`ga_ros.core.quality.checked_solve` fills in its
    :class:`~ga_ros.core.quality.QualityReport`: global test, redundancy numbers, w-tests, MDBs).
    """

    node_ids: IntArray
    T_world_node: FloatArray
    converged: bool
    iterations: int
    reason: str
    cost: float
    cost_history: list[float]
    sigma0_sq: float
    redundancy: int
    n_equations: int
    n_observations: int
    n_unknowns: int
    residuals: FloatArray
    adjusted: FloatArray
    seconds: float
    model: str = 'se3'
    weights: FloatArray | None = None
    factorisations: int = 0
    quality: object | None = None
    factor_offset: float = 0.0
    _system: _NormalSystem | None = field(default=None, repr=False)

    def covariance(self, node_ids) -> FloatArray:
        """Marginal covariance blocks ``(k, d, d)`` of ``Q_x = N^-1`` (eq. 17) for some nodes.

        Columns of ``N^-1`` are obtained by sparse solves with the Cholesky factor; no dense
        inverse of ``N`` is formed. A fixed node has a zero block.
        """
        if self._system is None:
            raise SolverError('this result carries no normal matrix')
        with blas_threads():
            return self._system.marginal_blocks(
                np.atleast_1d(np.asarray(node_ids, dtype=np.int64)))

    def solve_normal(self, rhs: FloatArray) -> FloatArray:
        """``N^-1 rhs`` with the factor of the normal matrix at the solution: ``rhs`` (u d,)
        or (u d, k), rows in the order of :attr:`free_node_ids` (``d`` unknowns per node,
        ``[x y z rx ry rz]`` for se3). Used to reduce additional unknowns that border ``N``
        (:mod:`ga_ros.core.calibration`)."""
        if self._system is None:
            raise SolverError('this result carries no normal matrix')
        rhs = np.asarray(rhs, dtype=float)
        with blas_threads():
            return self._system.chol.solve(rhs) if rhs.size else rhs.copy()

    def release_factor(self) -> SparseCholesky | None:
        """Hand this result's sparse factor over to a next :func:`solve` (its ``factor``), which
        then skips the symbolic analysis if its pattern is the same. This result keeps working:
        it factors its normal matrix anew if its covariances are asked for later."""
        return None if self._system is None else self._system.take_factor()

    @property
    def normal_matrix(self) -> sp.csc_matrix:
        """The normal matrix ``N`` over the free nodes (full symmetric CSC): at the solution,
        or where the covariances were factored (``solve(..., factor_at_solution=False)``)."""
        if self._system is None:
            raise SolverError('this result carries no normal matrix')
        return self._system.full()

    @property
    def free_node_ids(self) -> IntArray:
        """Ids of the unknown nodes, in the row/column order of :attr:`normal_matrix`."""
        if self._system is None:
            raise SolverError('this result carries no normal matrix')
        return self._system.node_ids[self._system.free]

    def prior(self, node_ids=None) -> GaussianPrior:
        """The result as a Gaussian prior ``(x, N)`` for a sequential update (Sec. III-D).

        Over all free nodes (default) this is the information form of the previous solution.
        For a subset, the marginal (Schur complement) information of those nodes is returned.
        """
        sysm = self._system
        if sysm is None:
            raise SolverError('this result carries no normal matrix')
        free_ids = sysm.node_ids[sysm.free]
        if node_ids is None:
            return GaussianPrior(free_ids, self.T_world_node[sysm.free], sysm.full())
        ids = np.asarray(node_ids, dtype=np.int64)
        with blas_threads():
            cov = sysm.joint_covariance(ids)
        info = np.linalg.inv(cov)
        return GaussianPrior(ids, self.T_world_node[sysm.index_of(ids)], 0.5 * (info + info.T))


class _NormalSystem:
    """The factored normal matrix at the solution, for covariances and sequential priors."""

    def __init__(self, node_ids: IntArray, free: np.ndarray, col: IntArray, d: int,
                 pattern: BlockPattern, data: FloatArray, chol: SparseCholesky | None,
                 factored: bool = False, auto: bool = False) -> None:
        self.node_ids = node_ids
        self.auto = auto  # a factor made here is of the solve's kind (SolverConfig.factor)
        self.free = free
        self.col = col
        self.d = d
        self.pattern = pattern
        self._data = data  # the lower triangle of N, or a function assembling it on first use
        if chol is not None:  # factored anew from this system's values when first needed
            chol.release_values()
        self._chol = chol
        self._factored = factored and chol is not None  # chol's numeric factor is N's
        self.coords: FloatArray | None = None  # (u, 3) positions of the free nodes, for ordering
        self._index: dict[int, int] | None = None  # node id -> index, built on first use

    @property
    def data(self) -> FloatArray:
        """Lower-triangle CSC values of ``N`` at the solution (assembled on first use)."""
        if callable(self._data):
            self._data = self._data()
        return self._data

    def index_of(self, ids: IntArray) -> IntArray:
        if self._index is None:  # not for a solve whose covariances nobody asks for (~1 ms)
            self._index = dict(zip(np.asarray(self.node_ids).tolist(), range(len(self.node_ids))))
        try:
            return np.array([self._index[int(i)] for i in ids], dtype=np.int64)
        except KeyError as exc:
            raise NetworkError(f'node {exc.args[0]} is not part of this solution') from None

    @property
    def chol(self) -> SparseCholesky:
        """Factor of ``N`` at the solution, computed on first use (reusing the ordering)."""
        if not self._factored:
            if self._chol is None:
                self._chol = SparseCholesky(self.pattern, self.data, auto=self.auto)
            else:
                self._chol.refactor(self.data)
            self._factored = True
        return self._chol

    def full(self) -> sp.csc_matrix:
        return self.pattern.full_csc(self.data)

    def _columns(self, ids: IntArray) -> tuple[FloatArray, IntArray]:
        idx = self.index_of(ids)
        cols = self.col[idx]
        d = self.d
        free_sel = np.nonzero(cols >= 0)[0]
        E = np.zeros((self.pattern.size, free_sel.size * d))
        for k, s in enumerate(free_sel):
            E[cols[s] * d:(cols[s] + 1) * d, k * d:(k + 1) * d] = np.eye(d)
        X = self.chol.solve(E) if E.shape[1] else E
        return X, cols

    def marginal_blocks(self, ids: IntArray) -> FloatArray:
        d = self.d
        if ids.size > _MANY_NODES:
            cols = self.col[self.index_of(ids)]
            blocks = self._selected_blocks(cols[cols >= 0])
            if blocks is not None:
                out = np.zeros((ids.size, d, d))
                out[cols >= 0] = blocks
                return out
        if self.pattern.size >= _PATH_FROM_UNKNOWNS:
            blocks = self._path_blocks(ids)
            if blocks is not None:
                return blocks
        out = np.zeros((ids.size, d, d))
        for start in range(0, ids.size, 256):  # bounded memory: n x (256 d) at a time
            chunk = ids[start:start + 256]
            blocks = self._forward_blocks(chunk)
            if blocks is not None:
                out[start:start + chunk.size] = blocks
                continue
            X, cols = self._columns(chunk)
            k = 0
            for s, c in enumerate(cols):
                if c >= 0:
                    blk = X[c * d:(c + 1) * d, k * d:(k + 1) * d]
                    out[start + s] = 0.5 * (blk + blk.T)
                    k += 1
        return out

    def _forward_blocks(self, ids: IntArray) -> FloatArray | None:
        """Diagonal blocks of ``N^-1`` for the nodes ``ids`` (zero blocks for fixed nodes) as
        ``Y_k' Y_k`` with ``Y_k = L^-1 P E_k`` (``E_k`` the node's unit columns): a forward
        solve, half the work of the full solves of :meth:`_columns` (equal to ~1e-13
        relative); ``None`` without CHOLMOD's factor."""
        idx = self.index_of(ids)
        cols = self.col[idx]
        d = self.d
        free_sel = np.nonzero(cols >= 0)[0]
        out = np.zeros((ids.size, d, d))
        if free_sel.size == 0:
            return out
        E = np.zeros((self.pattern.size, free_sel.size * d))
        for k, s in enumerate(free_sel):
            E[cols[s] * d:(cols[s] + 1) * d, k * d:(k + 1) * d] = np.eye(d)
        Y = self.chol.forward(E)
        if Y is None:
            return None
        Y = np.ascontiguousarray(Y.reshape(self.pattern.size, free_sel.size, d).swapaxes(0, 1))
        blocks = np.swapaxes(Y, 1, 2) @ Y
        out[free_sel] = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
        return out

    def _path_blocks(self, ids: IntArray) -> FloatArray | None:
        """Diagonal blocks of ``N^-1`` for a few nodes by forward solves along their
        elimination-tree paths (zero blocks for fixed nodes); ``None`` if the factor cannot be
        read in place or full solves are cheaper."""
        from ga_ros.core.linalg import selinv  # lazy: scipy.linalg

        cols = self.col[self.index_of(ids)]
        blocks = selinv.path_marginal_blocks(self.chol, cols[cols >= 0],
                                             cheaper_than_solve=True)
        if blocks is None:
            return None
        out = np.zeros((ids.size, self.d, self.d))
        out[cols >= 0] = blocks
        return out

    def _selected_blocks(self, cols: IntArray) -> FloatArray | None:
        """Diagonal blocks of ``N^-1`` for the block columns ``cols`` by selected inversion:
        on the sparse factor for large systems
        (:class:`~ga_ros.core.linalg.selinv.SelectedInverse`,
        memory ~ ``nnz(L)``; it takes over this system's factor, which is computed again if a
        solve needs it), else on the banded matrix (:func:`banded_marginal_blocks`, no
        compiled code to load; ``None`` when the band is too wide)."""
        from ga_ros.core.linalg import selinv  # lazy: scipy.linalg, numba

        if self.pattern.size >= _SPARSE_SELINV_UNKNOWNS and selinv.COMPILED:
            chol = self.chol  # factored at the solution
            self.take_factor()  # read out and overwritten: factored anew if needed later
            return selinv.SelectedInverse(chol, columns=cols).diagonal_blocks(cols)
        blocks = selinv.banded_marginal_blocks(self.full(), self.d, wanted=cols,
                                               coords=self.coords)
        return None if blocks is None else blocks[cols]

    def take_factor(self) -> SparseCholesky | None:
        """Hand this system's sparse factor over (its symbolic analysis, and its numeric factor
        if computed); the system factors ``N`` anew if it needs it later."""
        chol, self._chol, self._factored = self._chol, None, False
        return chol

    def give_factor(self, chol: SparseCholesky) -> None:
        """Hand a factor of this system's pattern back (e.g. its symbolic analysis after a
        selected inversion, :meth:`take_factor`'s counterpart): ``N`` is factored anew on it
        when needed."""
        self._chol, self._factored = chol, False

    def joint_covariance(self, ids: IntArray) -> FloatArray:
        """Joint covariance ``(d k, d k)`` of the given (free) nodes."""
        X, cols = self._columns(ids)
        if (cols < 0).any():
            raise InputError('a fixed node has no covariance; leave it out')
        d = self.d
        rows = np.concatenate([np.arange(c * d, (c + 1) * d) for c in cols])
        C = X[rows]
        return 0.5 * (C + C.T)


#: The scalar fields of a :class:`SolveResult` that :func:`result_arrays` stores as JSON, with
#: their types ...
_SCALARS = {'converged': bool, 'iterations': int, 'reason': str, 'redundancy': int,
            'n_equations': int, 'n_observations': int, 'n_unknowns': int, 'model': str,
            'factorisations': int}
#: ... and those it stores in the array ``figures`` (floats, NaN possible).
_FIGURES = ('cost', 'sigma0_sq', 'factor_offset')


def result_arrays(res: SolveResult) -> tuple[dict, dict[str, np.ndarray]] | None:
    """A solve's outcome as JSON fields and named arrays, its normal matrix ``N`` included as
    its values (the lower triangle on its block pattern: the values its covariances come from,
    where they were factored), so that :func:`result_of_arrays` gives back a result whose
    covariances and sequential priors are the same bit for bit (``N`` factored anew on first
    use: the same values, the same ordering of the same pattern). ``None`` for a result without
    a normal matrix. Its time (``seconds``) and quality report are not kept."""
    sysm = res._system
    if sysm is None:
        return None
    meta = {name: _SCALARS[name](getattr(res, name)) for name in _SCALARS}
    meta.update(d=int(sysm.d), n_blocks=int(sysm.pattern.n_blocks),
                weights=res.weights is not None, factor_auto=bool(sysm.auto))
    brow, bcol = sysm.pattern.block_lower
    arrays = {'ids': np.asarray(res.node_ids, np.int64), 'T': np.asarray(res.T_world_node),
              'residuals': np.asarray(res.residuals), 'adjusted': np.asarray(res.adjusted),
              'weights': (np.zeros(0) if res.weights is None else np.asarray(res.weights)),
              'free': np.asarray(sysm.free, bool), 'col': np.asarray(sysm.col, np.int64),
              'brow': np.asarray(brow, np.int64), 'bcol': np.asarray(bcol, np.int64),
              'figures': np.array([getattr(res, name) for name in _FIGURES], dtype=float),
              'cost_history': np.asarray(res.cost_history, dtype=float),
              'N': np.asarray(sysm.data, float)}
    return meta, arrays


def result_of_arrays(meta: dict, arrays: dict[str, np.ndarray]) -> SolveResult:
    """Inverse of :func:`result_arrays` (its arrays by the same names); ``N`` is factored on
    first use. Raises ``ValueError`` / ``KeyError`` for inconsistent input."""
    ids = np.array(arrays['ids'], dtype=np.int64)
    T = np.array(arrays['T'], dtype=float).reshape(ids.size, 4, 4)
    free = np.array(arrays['free'], dtype=bool)
    col = np.array(arrays['col'], dtype=np.int64)
    d, n_blocks = int(meta['d']), int(meta['n_blocks'])
    if free.shape != ids.shape or col.shape != ids.shape or int(free.sum()) != n_blocks:
        raise ValueError("the last adjustment's unknowns do not match its nodes")
    pattern = BlockPattern(np.array(arrays['brow'], dtype=np.int64),
                           np.array(arrays['bcol'], dtype=np.int64), d, n_blocks)
    data = np.array(arrays['N'], dtype=float)
    if data.shape != (pattern.nnz,):
        raise ValueError(f"the last adjustment's normal matrix has {data.size} values, its "
                         f'pattern {pattern.nnz}')
    system = _NormalSystem(ids, free, col, d, pattern, data, None,
                           auto=bool(meta.get('factor_auto', False)))
    system.coords = T[free, :3, 3]
    scalars = {name: meta[name] for name in _SCALARS}
    scalars.update(zip(_FIGURES, np.asarray(arrays['figures'], dtype=float).tolist()))
    return SolveResult(node_ids=ids, T_world_node=T,
                       cost_history=np.asarray(arrays['cost_history'], dtype=float).tolist(),
                       residuals=np.array(arrays['residuals'], dtype=float),
                       adjusted=np.array(arrays['adjusted'], dtype=float),
                       weights=(np.array(arrays['weights'], dtype=float) if meta['weights']
                                else None),
                       seconds=0.0, _system=system, **scalars)
