"""The mixed adjustment (Gauss-Helmert) solver: batch, weighted parameters, sequential update.

Notation follows METHOD.md and the paper (Sec. III): observations ``l_b`` with weight
``P = S^-1``, residuals ``v``, unknowns ``x``, constraints ``f(l, x) = 0`` linearised as
``A d + B v + w = 0`` with ``w = f(l0, x0) + B (l_b - l0)``. Per connection
``M = B S B'`` (block diagonal), ``N = A' M^-1 A``, ``u = A' M^-1 w``, ``d = -N^-1 u`` (eq. 15),
``k = -M^-1 (A d + w)``, ``v = S B' k`` (eq. 16), ``sigma0^2 = v' P v / (r - u)``,
``Q_x = N^-1`` (eq. 17).

Weighted parameters (Sec. III-E) and the sequential update (Sec. III-D) are both a
:class:`GaussianPrior`: a second observation group ``x - l_p = 0`` with covariance ``S_p`` (or
information ``N_1``), which adds ``A_p' S_p^-1 A_p`` to ``N``. The sequential update
(:func:`sequential_update`) uses only the previous estimate and its normal matrix, never the old
observations.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import columns, kernels, models
from ga_ros.core.network import ConnectionArrays, ConnectionNetwork
from ga_ros.core.sparse import BlockPattern, SparseCholesky, kept_block_pattern, spd_inverse
from ga_ros.errors import DegenerateGeometryError, InputError, NetworkError, SolverError
from ga_ros.geometry import se2, se3
from ga_ros.runtime import blas_threads, lazy_import

sp = lazy_import('scipy.sparse')  # only some functions need it (start-up)

ROBUST_LOSSES = ('none', 'huber', 'cauchy')
#: Above this many requested nodes, covariances come from selected inversion of the whole
#: normal matrix instead of one sparse solve per column.
_MANY_NODES = 24
DAMPINGS = ('none', 'lm', 'dogleg')
FACTORS = ('supernodal', 'auto')
#: From this many unknowns on, those covariances come from selected inversion on the sparse
#: Cholesky factor (:class:`ga_ros.core.selinv.SelectedInverse`: time ~ the factorisation's,
#: memory ~ ``nnz(L)``) instead of the banded matrix (memory ~ unknowns x band): at 12,000
#: unknowns (an aerial survey of 2,000 poses) 0.7 s against 4.5 s, at 60,000 6 s against 34 s.
#: Below it (windows) the banded path needs no compiled kernel (loading numba costs ~0.5 s and
#: ~90 MiB per process).
_SPARSE_SELINV_UNKNOWNS = 12_000
#: Problems with more connections (motion models) are linearised and assembled in parts
#: (:func:`_motion_system_in_parts`) ...
_PARTS_ABOVE = 65_536
#: ... of this many connections (the temporaries of a part: ~60 MB).
_CONNECTIONS_PER_PART = 16_384


@dataclass(frozen=True)
class SolverConfig:
    """Settings of :func:`solve`.

    Attributes
    ----------
    model : constraint model, ``'se3'`` (full poses, default), ``'se2'`` (planar poses: 3 unknowns
        per node, for 2-D graphs), ``'paper'`` (eq. 1, positions) or ``'linear'`` (positions,
        ``R = I``); see :mod:`ga_ros.core.models`.
    max_iterations : cap on relinearisations.
    tolerance : stop when the largest correction ``max |d|`` is below this (m and rad).
    damping : ``'none'``: the paper's Gauss-Helmert iteration; ``'dogleg'``: Powell's dogleg
        trust region (Gauss-Newton steps while they decrease the cost, one factorisation per
        iteration even when a step is refused), for poor initial guesses; ``'lm'``:
        Levenberg-Marquardt (each refused step costs one more factorisation).
    robust_loss : ``'none'``, ``'huber'`` or ``'cauchy'`` on each connection's Mahalanobis
        misclosure ``sqrt(w' M^-1 w)`` (iteratively reweighted).
    robust_scale : Mahalanobis distance at which the robust loss departs from least squares.
    reuse_factor_below : once a correction is smaller than this (m, rad), later iterations reuse
        the last factorisation of ``N`` (chord steps: the same fixed point ``u(x) = 0``, reached
        linearly instead of quadratically, at the cost of one solve instead of a factorisation).
        0 refactors every iteration.
    cost_tolerance : also stop (converged) when a full Gauss-Newton step lowers the cost by less
        than this fraction of it (GTSAM's ``relativeErrorTol``), or when the next chord step
        (``reuse_factor_below``) predicts a decrease ``-u' h`` below this fraction: the estimate
        is kept as it is, without that step (chord steps converge linearly, and along weakly
        observed modes a factor from a few metres away overshoots, so a small decrease of the
        step just taken says little about the distance left); 0 (default) stops on the
        correction size only.
    factor : ``'supernodal'`` (default) or ``'auto'``: below ~6,000 unknowns CHOLMOD may choose
        a simplicial factor of ``N`` when it has few flops per entry (a pose graph of ~1,700
        planar poses: ~2 ms less per solve). Selected inversion reads a simplicial factor
        through a copy, so the window, which inverts its factor in place, keeps the default.
    chord_decrease : dogleg only: after a Gauss-Newton step that lowered the cost by less than
        this fraction of it, the next iteration first tries the chord step ``-N_old^-1 u`` with
        the last factorisation (one solve instead of a factorisation) and keeps it when the new
        linearisation confirms it (see :func:`_chord_step`); when the decrease that step
        predicts, ``-u' h = h' N_old h``, shows that less than ``cost_tolerance`` of the cost
        is left to gain (:func:`_left_to_gain`), the iteration takes that step if it lowers the
        cost as predicted, and stops (converged) without assembling ``N``. Near the optimum
        this saves the iteration that only confirms convergence (all but its gradient and one
        cost evaluation), and on slowly converging graphs most factorisations (torus3D: 17
        instead of 72 for 72 iterations).
        Only with a ``cost_tolerance`` stop (chord steps converge linearly, so a stop on the
        correction size alone would need more iterations). 0 disables.
    """

    model: str = 'se3'
    max_iterations: int = 20
    tolerance: float = 1e-8
    damping: str = 'none'
    robust_loss: str = 'none'
    robust_scale: float = 3.0
    reuse_factor_below: float = 0.1
    cost_tolerance: float = 0.0
    chord_decrease: float = 0.05
    factor: str = 'supernodal'

    def __post_init__(self) -> None:
        models.check_model(self.model)
        if self.factor not in FACTORS:
            raise InputError(f'factor must be one of {FACTORS}, got {self.factor!r}')
        if self.damping not in DAMPINGS:
            raise InputError(f'damping must be one of {DAMPINGS}, got {self.damping!r}')
        if self.robust_loss not in ROBUST_LOSSES:
            raise InputError(f'robust_loss must be one of {ROBUST_LOSSES}, '
                             f'got {self.robust_loss!r}')
        if not (self.max_iterations >= 1 and self.tolerance > 0 and self.robust_scale > 0
                and 0.0 <= self.cost_tolerance < 1.0 and 0.0 <= self.chord_decrease < 1.0):
            raise InputError('max_iterations >= 1, tolerance > 0, robust_scale > 0, '
                             '0 <= cost_tolerance < 1 and 0 <= chord_decrease < 1 required')


@dataclass(frozen=True)
class GaussianPrior:
    """Known values of some node parameters (weighted parameters, paper Sec. III-E).

    Attributes
    ----------
    node_ids : (k,) node ids.
    T_world_node : (k, 4, 4) prior mean poses (for the position models only the translation
        counts).
    information : (d k, d k) inverse covariance (dense array or scipy.sparse), node-major, each
        node's block in the order ``[x y z rx ry rz]`` (se3, d = 6), ``[x y rz]`` (se2, d = 3)
        or ``[x y z]`` (positions, d = 3), of the residual of
        :func:`~ga_ros.core.models.prior_residual` (se3: ``[R_mean' (p - p_mean),
        log(R_mean' R)]``, the right perturbation ``T_mean exp(e)`` to first order).
    rank : the rank of ``information`` (the number of equations the prior adds to the
        redundancy), when the caller knows it (e.g. positive definite by construction: ``d k``);
        ``None`` (default): the solver determines it (a Cholesky, or an eigen-decomposition of a
        singular information), and only when it needs it (the variance factor).
    """

    node_ids: IntArray
    T_world_node: FloatArray
    information: FloatArray | sp.spmatrix
    rank: int | None = None

    @staticmethod
    def from_covariances(node_ids, T_world_node, cov: FloatArray) -> GaussianPrior:
        """Block-diagonal prior from per-node covariances ``(k, d, d)``."""
        cov = np.asarray(cov, dtype=float)
        info = np.linalg.inv(cov)
        info = 0.5 * (info + np.swapaxes(info, 1, 2))
        return GaussianPrior(np.asarray(node_ids, dtype=np.int64),
                             np.asarray(T_world_node, dtype=float),
                             sp.block_diag(list(info), format='csr'))


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
                 factored: bool = False) -> None:
        self.node_ids = node_ids
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
            self._index = {int(i): k for k, i in enumerate(self.node_ids)}
        try:
            return np.array([self._index[int(i)] for i in ids], dtype=np.int64)
        except KeyError as exc:
            raise NetworkError(f'node {exc.args[0]} is not part of this solution') from None

    @property
    def chol(self) -> SparseCholesky:
        """Factor of ``N`` at the solution, computed on first use (reusing the ordering)."""
        if not self._factored:
            if self._chol is None:
                self._chol = SparseCholesky(self.pattern, self.data)
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
        out = np.zeros((ids.size, d, d))
        for start in range(0, ids.size, 256):  # bounded memory: n x (256 d) at a time
            chunk = ids[start:start + 256]
            X, cols = self._columns(chunk)
            k = 0
            for s, c in enumerate(cols):
                if c >= 0:
                    blk = X[c * d:(c + 1) * d, k * d:(k + 1) * d]
                    out[start + s] = 0.5 * (blk + blk.T)
                    k += 1
        return out

    def _selected_blocks(self, cols: IntArray) -> FloatArray | None:
        """Diagonal blocks of ``N^-1`` for the block columns ``cols`` by selected inversion:
        on the sparse factor for large systems (:class:`~ga_ros.core.selinv.SelectedInverse`,
        memory ~ ``nnz(L)``; it takes over this system's factor, which is computed again if a
        solve needs it), else on the banded matrix (:func:`banded_marginal_blocks`, no
        compiled code to load; ``None`` when the band is too wide)."""
        from ga_ros.core import selinv  # lazy: scipy.linalg, numba

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


# ----------------------------------------------------------------------------------- solve
def solve(network: ConnectionNetwork, T_init: FloatArray, config: SolverConfig | None = None,
          fixed: Sequence[int] | None = None,
          priors: Sequence[GaussianPrior] = (), jit: bool = False,
          weights: FloatArray | None = None,
          factor: SparseCholesky | None = None,
          factor_at_solution: bool = True,
          measured: tuple[FloatArray, FloatArray] | None = None) -> SolveResult:
    """Batch mixed-adjustment solution with relinearisation (paper Sec. III-C, steps 1-6).

    Parameters
    ----------
    network : the connections (validated on insertion).
    T_init : (n, 4, 4) initial poses ``T_world_node`` in network index order (e.g.
        :func:`initial_guess_f2f`).
    config : solver settings.
    fixed : node ids held fixed (the datum). Default: the first node when there are no priors,
        none otherwise (then the priors must define the datum).
    priors : weighted parameters / sequential priors (see :class:`GaussianPrior`).
    jit : use the compiled se3 kernels (:mod:`ga_ros.core.kernels`) from the first
        linearisation on, for a caller that solves many problems in one process (the window
        aligner): the one-off cost of loading them is paid once. Default: only once a solve
        has run :data:`~ga_ros.core.kernels.AFTER_ITERATIONS` linearisations.
    weights : (m, 6, 6) the inverses of the connections' covariances, if the caller has them
        (se3; e.g. kept from the previous window update), or (m, 3, 3) those of their
        ``[x y rz]`` blocks (se2; a 2-D g2o file's information): not inverted again.
    factor : a factor handed over by :meth:`SolveResult.release_factor` of an earlier solve;
        if its pattern is this problem's, its symbolic analysis is reused (a window update
        solves the same pattern every track).
    factor_at_solution : ``True`` (default): the result's covariances ``Q_x = N^-1`` (eq. 17)
        come from ``N`` factored at the solution (on first use). ``False`` (undamped
        iterations only): from the iteration's last numeric factorisation, at the start of its
        last full Gauss-Newton step (the chord steps after it reuse that factor), so a solve
        that converges with one factorisation needs no second one for its covariances.
        ``N = J' P J`` depends on the estimate only through the connections' relative poses
        ``T_i^-1 T_j`` (the Jacobians ``[-Ad(T_ij^-1), I]``) and the priors' residuals, so the
        two differ by the change of those over the last correction (first order in it; a
        rigid motion of the whole network changes nothing). ``Q_x`` is itself the first-order
        covariance of an estimate that lies about one standard deviation from the truth, so a
        linearisation point a fraction of a correction away is within its own approximation.
        Measured: a small survey at 10 % noise, variances within 1.1 % of the dense inverse
        at the solution (``test_window_fast.py`` bounds them at 5 %); the aerial survey's
        window (6,732 unknowns, 10 % noise) 0.4-2.3 % for the track that leaves it next and up
        to 10 % for the newest two tracks, whose weak modes the last correction moved by metres.
        :attr:`SolveResult.factor_offset` bounds the distance. The normal matrix of the result
        (:attr:`SolveResult.normal_matrix`, a sequential prior) is then the factored one too.
    measured : se3 only: ``(T_meas, T_meas^-1)``, the (m, 4, 4) measured motions of the
        connections (``T_src_dst`` of each ``z``,
        :func:`ga_ros.geometry.se3.from_translation_rotvec`) and their inverses, if the caller
        has them (e.g. kept from the previous window update, as ``weights``): not computed
        again.

    Returns
    -------
    SolveResult with the estimate, residuals, adjusted observations, variance factor,
    redundancy and access to marginal covariances.

    Raises
    ------
    InputError, NetworkError
        Bad shapes, unknown nodes, nodes not connected to the datum (named).
    DegenerateGeometryError
        Singular normal matrix.
    """
    t0 = time.perf_counter()
    cfg = config or SolverConfig()
    model = cfg.model
    d = models.dof(model)
    n = network.n_nodes
    if n == 0:
        raise InputError('the network has no nodes')
    T0 = np.asarray(T_init, dtype=float)
    if T0.shape != (n, 4, 4):
        raise InputError(f'T_init must have shape ({n}, 4, 4), got {T0.shape}')
    if not np.isfinite(T0).all():
        raise InputError('T_init has NaN or inf entries')
    conn = network.arrays()
    node_ids = network.node_ids

    if fixed is None:
        fixed = [int(node_ids[0])] if not priors else []
    fixed_idx = network.indices_of(list(fixed)) if len(fixed) else np.zeros(0, dtype=np.int64)
    prior_data = [_PriorData.build(network, p, d) for p in priors]
    anchors = list(fixed) + [int(i) for p in priors for i in p.node_ids]
    if not anchors:
        raise DegenerateGeometryError('no datum: fix a node or give priors (weighted parameters)')
    network.check_connected(anchors)
    free = np.ones(n, dtype=bool)
    free[fixed_idx] = False
    if not free.any():
        raise InputError('every node is fixed: nothing to estimate')
    want = {'se3': (len(conn), 6, 6), 'se2': (len(conn), 3, 3)}.get(model)
    if weights is not None and np.shape(weights) != want:
        raise InputError(f'weights must be {want} for the {model} model, got '
                         f'{np.shape(weights)}' if want else 'weights only for se3 and se2')
    if measured is not None and (model != 'se3' or any(
            np.shape(a) != (len(conn), 4, 4) for a in measured)):
        raise InputError(f'measured must be two ({len(conn)}, 4, 4) arrays, for the se3 model')
    prob = _Problem.build(model, conn, prior_data, cfg, free, weights, measured)
    prob.jit = bool(jit)
    if factor is not None and factor.pattern.key == prob.pattern.key:
        prob.factor = factor
    with blas_threads():
        out = _iterate(prob, T0.copy(), keep_values=not factor_at_solution)
    return _finish(prob, node_ids, out, t0)


@dataclass
class _Iterations:
    """Outcome of the iteration loop of :func:`solve` (before the final linearisation)."""

    T: FloatArray
    v: FloatArray
    converged: bool
    iterations: int
    reason: str
    history: list[float]
    chol: SparseCholesky | None
    factorisations: int
    since_factor: float = np.inf  # sum of max |dx| since the last factorisation of N (undamped)
    factored: FloatArray | None = None  # the values of N last factored (keep_values)


@dataclass
class _Step:
    """One accepted (or refused) correction of :func:`_iterate`."""

    T: FloatArray
    v: FloatArray
    step: float  # max |dx| (m, rad); 0 when refused
    accepted: bool
    cost: float = np.nan  # cost at T (damped strategies only)
    gauss_newton: bool = True  # the full Gauss-Newton step was taken
    predicted: float = np.nan  # the decrease its quadratic model predicted (dogleg)


@dataclass
class _Trust:
    """State carried between iterations by the damped strategies."""

    chol: SparseCholesky | None = None
    factorisations: int = 0
    lam: float = 1e-4  # Levenberg-Marquardt damping
    radius: float = 0.0  # dogleg trust radius (0: not set yet, the first step tries full GN)
    auto: bool = False  # a new factor may be simplicial (SolverConfig.factor 'auto')
    cost: float = np.inf  # cost at the current estimate
    chord: bool = False  # dogleg: try the last factorisation first (see _chord_step)
    predicted: float = np.nan  # dogleg: the decrease the last step's model predicted

    def factor(self, pattern: BlockPattern, data: FloatArray) -> SparseCholesky:
        if self.chol is None:
            self.chol = SparseCholesky(pattern, data, auto=self.auto)
        else:
            self.chol.refactor(data)
        self.factorisations += 1
        return self.chol


def _iterate(prob: _Problem, T: FloatArray, keep_values: bool = False) -> _Iterations:
    """Relinearise and correct until the largest correction is below the tolerance (or a
    Gauss-Newton step lowers the cost by less than ``cost_tolerance``).

    Undamped chord steps (the last factorisation reused once a correction is below
    ``reuse_factor_below``) need the gradient only (:meth:`_Problem.gradient`). With a
    ``cost_tolerance`` the iteration stops before a chord step whose predicted decrease
    ``-u' h = h' N_old h`` is below that fraction of the cost (the Newton decrement in the
    metric of the last factor: the cost left to gain, up to the factor's error). A chord step
    that is taken is kept only if it lowers the cost as predicted (:func:`_chord_kept`), and
    only while chord steps converge fast: one whose decrease is more than a quarter of the
    previous step's (a contraction slower than 1/2 per step, e.g. a factor from far away on a
    weak mode of the network) makes the next iteration factor ``N`` anew. Measured on the
    aerial window (10 % noise, after the pre-alignment): the chord step after the first
    Gauss-Newton step predicted 0.005-0.02 (cost ~30,000), so the update stops at the
    Gauss-Newton step's estimate, 0.01-0.17 m RMS from the window's optimum; the chord step
    the earlier rule took (stopping after it on its realised decrease) moved the estimate
    0.1-0.35 m away from the optimum along the weak modes for a decrease of 0.01.
    The dogleg's chord step (:attr:`SolverConfig.chord_decrease`) is solved before ``N`` is
    assembled: when it shows less than ``cost_tolerance`` left to gain (:func:`_left_to_gain`)
    it is the last step, taken if it lowers the cost as predicted (:func:`_chord_kept`).
    ``keep_values``: the values of ``N`` last factored are kept in the result (for
    :func:`solve`'s ``factor_at_solution=False``).
    """
    cfg = prob.cfg
    # the fused kernel's first system gives the motion model's residuals (the misclosure at T)
    v = None if prob.fused_gradient else prob.consistent(T, prob.zero_residuals())
    state = _Trust(chol=prob.factor, auto=cfg.factor == 'auto')
    last_step = since_factor = np.inf
    slow = False  # the last chord step contracted too slowly: factor anew
    factored = None  # the values of N last factored (keep_values)
    history: list[float] = []
    converged = False
    reason = 'max_iterations'
    it = 0
    # without a robust loss a damped step's cost (the motion models': at T) is this sum
    plain = cfg.damping == 'none' or (prob.Pf is not None and cfg.robust_loss == 'none')

    def objective(cost: float, v: FloatArray, T: FloatArray, sysd: _System) -> float:
        """The cost history's entry at ``T`` after a step whose cost was ``cost``."""
        return cost if plain else (_adjustment_cost(v, prob.P, sysd.weights)
                                   + _prior_cost(prob.model, T, prob.prior_data))

    for it in range(1, cfg.max_iterations + 1):
        # the last values of N go before the next are assembled (~190 MB at 100,000 poses)
        data = None
        if state.chol is not None:
            state.chol.release_values()
        chord = (cfg.damping == 'none' and state.chol is not None
                 and last_step < cfg.reuse_factor_below and not slow)
        # a chord step needs the gradient only (it reuses the last factor of N)
        sysd = prob.gradient(T, v) if chord else prob.linear_system(T, v)
        if v is None:
            v = sysd.w
        if it == 1:  # the se3 shortcut's cost0 is the exact cost
            state.cost = sysd.cost0 if prob.Pf is not None else prob.cost_at(T)
            history.append(state.cost)
        chord_h = None  # dogleg: the chord step from the last factor, tried first
        if cfg.damping == 'dogleg' and state.chord and state.chol is not None:
            chord_h = -state.chol.solve(sysd.u)
            predicted = -float(sysd.u @ chord_h)
            if (_left_to_gain(predicted, state.predicted, history)
                    < cfg.cost_tolerance * history[-1]):
                # the last step, N never assembled: kept if it lowers the cost as predicted
                T_new = prob.retract(T, chord_h)
                cost = prob.cost_at(T_new)
                if state.cost - cost >= 0 and _chord_kept(predicted, state.cost, cost):
                    T, v = T_new, prob.next_residuals(T_new, sysd, chord_h)
                    history.append(objective(cost, v, T, sysd))
                converged, reason = True, 'cost_converged'
                break
        # a chord step reuses the last factor: N's values are not needed
        # the (4 m, d, d) blocks are freed before factoring
        data = None if chord else sysd.normal_values(prob.pattern, prob.compiled)
        sysd.drop_blocks()
        if cfg.damping == 'none':
            if not chord:
                state.factor(prob.pattern, data)
                since_factor = 0.0
                factored = data if keep_values else None
            dx = -state.chol.solve(sysd.u)
            if not np.isfinite(dx).all():
                raise SolverError('the correction is not finite')
            if (chord and cfg.cost_tolerance > 0
                    and -float(sysd.u @ dx) < cfg.cost_tolerance * history[-1]):
                converged, reason = True, 'cost_converged'
                break
            T_new = prob.retract(T, dx)
            ahead = prob.gradient_ahead(T_new, float(np.abs(dx).max()) if dx.size else 0.0)
            if ahead is not None:  # the next chord step's gradient, residuals and cost at once
                v_new, cost = ahead.w, ahead.cost0
            else:
                v_new = prob.next_residuals(T_new, sysd, dx)
                cost = (_adjustment_cost(v_new, prob.P, sysd.weights)
                        + _prior_cost(prob.model, T_new, prob.prior_data))
            if chord and not _chord_kept(-float(sysd.u @ dx), history[-1], cost):
                last_step = np.inf  # undone: this point again, with a factorisation
                continue
            T, v = T_new, v_new
            step = _Step(T, v, float(np.abs(dx).max()) if dx.size else 0.0, True, cost,
                         not chord)
            since_factor += step.step
        else:
            step = (_dogleg_step(prob, T, sysd, data, state, chord_h)
                    if cfg.damping == 'dogleg' else _lm_step(prob, T, sysd, data, state))
            if not step.accepted:
                reason = 'no_decrease'
                converged = step.step < cfg.tolerance * 10
                break
            T, v = step.T, step.v
        last_step = step.step
        history.append(objective(step.cost, v, T, sysd))
        state.chord = (step.gauss_newton and cfg.chord_decrease > 0 and cfg.cost_tolerance > 0
                       and state.cost > 0
                       and state.cost - step.cost < cfg.chord_decrease * state.cost)
        state.cost, state.predicted = step.cost, step.predicted
        if not np.isfinite(T).all():
            raise SolverError(f'the estimate became non-finite at iteration {it}; the previous '
                              'estimate stands')
        if step.step < cfg.tolerance:
            converged = True
            reason = 'converged'
            break
        if step.gauss_newton and 0 <= history[-2] - history[-1] < cfg.cost_tolerance * \
                history[-1]:
            converged = True
            reason = 'cost_converged'
            break
        slow = (chord and len(history) > 2
                and history[-2] - history[-1] > 0.25 * (history[-3] - history[-2]))
    return _Iterations(T, v, converged, it, reason, history, state.chol, state.factorisations,
                       since_factor if cfg.damping == 'none' else np.inf, factored)


def _left_to_gain(predicted: float, previous: float, history: list[float]) -> float:
    """The cost still to gain before a dogleg chord step, estimated from the decrease it
    predicts (``predicted = -u' h = h' N_old h``): with the contraction ``r`` of the decreases,
    the geometric series ``predicted / (1 - r)`` (``inf`` when ``r >= 1``). ``r`` is the larger
    of ``predicted`` over the decrease the last step predicted (``previous``) and over the one it
    achieved (``history[-2] - history[-1]``).

    A chord step right after a converging Gauss-Newton step predicts a decrease thousands of
    times below the last one (parking-garage 2e-9 after 1.5e-3, sphere2500 1.5e-5 after 0.06):
    what is left is that prediction. On a graph that converges linearly (torus3D from the
    file's guess: each chord step predicts ~0.93 of the one before, and achieves twice what it
    predicted) the steps left add up to many predictions, and the prediction alone would stop
    too early (+0.013 % cost on torus3D).
    """
    last = history[-2] - history[-1] if len(history) > 1 else 0.0
    r = max(predicted / previous if previous > 0 else np.inf,
            predicted / last if last > 0 else np.inf)
    return predicted / (1.0 - r) if r < 1.0 else np.inf


def _chord_kept(predicted: float, cost_before: float, cost: float) -> bool:
    """Whether an undamped chord step ``dx = -N_old^-1 u`` (the last factorisation reused,
    :attr:`SolverConfig.reuse_factor_below`) is kept: the cost must fall from ``cost_before``
    to ``cost`` by at least a quarter of the decrease its quadratic model predicts,
    ``predicted = -u' dx = dx' N_old dx`` (the dogleg's acceptance ratio), up to rounding
    (``1e-9`` of the cost). A stale factor (e.g. after a correction that turned the network's
    rotations) fails it: the step is undone and the iteration factors ``N`` at the same point.
    """
    return cost_before - cost >= 0.25 * predicted - 1e-9 * abs(cost_before)


def _finish(prob: _Problem, node_ids: IntArray, out: _Iterations, t0: float) -> SolveResult:
    """Final linearisation at the solution: residuals, variance factor, ``N`` (eq. 17); the
    covariances from the iteration's last factor when it kept that factor's values
    (:func:`solve`'s ``factor_at_solution=False``)."""
    T = out.T
    d, conn = prob.d, prob.conn
    n_free = int(prob.free.sum())
    if prob.Pf is not None:
        # motion models: out.v is the misclosure at T, so the residuals (v = weights * w) need
        # no linearisation; N is assembled only if a covariance or prior asks for it
        if prob.cfg.robust_loss == 'none':
            weights, v = np.ones(len(conn)), out.v.copy()
        else:
            weights = _robust_weights(np.sqrt(np.maximum(_maha2(out.v, prob.P), 0.0)), prob.cfg)
            v = out.v * weights[:, None]

        def data() -> FloatArray:
            return prob.linear_system(T, out.v).normal_values(prob.pattern)
    else:
        final = prob.linear_system(T, out.v)
        v = prob.residual_update(final, np.zeros(n_free * d))
        weights = final.weights
        data = final.normal_values(prob.pattern)
    if (prob.Pf is not None and prob.cfg.robust_loss == 'none' and prob.cfg.damping == 'none'
            and len(out.history) > 1):
        cost = out.history[-1]  # this very sum, evaluated at T after the last step (_iterate)
    else:
        cost = (_adjustment_cost(v, prob.P, weights)
                + _prior_cost(prob.model, T, prob.prior_data))
    r_eq = len(conn) * models.equations_per_connection(prob.model) + sum(
        p.rank for p in prob.prior_data)
    redundancy = r_eq - n_free * d
    sigma0_sq = cost / redundancy if redundancy > 0 else float('nan')
    o = models.observations_per_connection(prob.model)
    if o != conn.z.shape[1]:  # se2: the planar components of the 6-vector
        v6 = np.zeros_like(conn.z)
        v6[:, se2.AXES] = v
        v = v6
    # kept only by undamped iterations asked to (keep_values), at their last factorisation
    last = out.factored is not None
    if last:  # N as factored: covariances, normal matrix and priors of one matrix
        data = out.factored
    system = _NormalSystem(node_ids, prob.free, prob.col, d, prob.pattern, data, out.chol,
                           factored=last)
    system.coords = T[prob.free, :3, 3]
    return SolveResult(
        node_ids=node_ids, T_world_node=T, converged=out.converged, iterations=out.iterations,
        reason=out.reason, cost=float(cost), cost_history=out.history,
        sigma0_sq=float(sigma0_sq), redundancy=int(redundancy), n_equations=int(r_eq),
        n_observations=int(o * len(conn) + sum(p.idx.size * d for p in prob.prior_data)),
        n_unknowns=int(n_free * d), residuals=v, adjusted=conn.z + v,
        seconds=time.perf_counter() - t0, model=prob.model, weights=weights,
        factorisations=out.factorisations, factor_offset=out.since_factor if last else 0.0,
        _system=system)


# ------------------------------------------------------------------------------ internals
@dataclass
class _PriorData:
    idx: IntArray  # (k,) node indices
    T_mean: FloatArray
    H_blocks: FloatArray  # (b, d, d) non-zero d x d blocks of the information
    blk_r: IntArray  # (b,) block row (position in idx)
    blk_c: IntArray
    information: FloatArray | sp.spmatrix  # as given (for the rank, when it is asked for)
    known_rank: int | None = None  # the prior's own rank, or computed on first use
    blocked: sp.bsr_matrix | None = None  # the information as (d, d) blocks, for products

    def weighted(self, e: FloatArray) -> FloatArray:
        """``H e`` ``(k, d)`` of residuals ``e`` ``(k, d)`` (one sparse product)."""
        return (self.blocked @ e.reshape(-1)).reshape(e.shape)

    @property
    def rank(self) -> int:
        """Rank of the information: the number of equations the prior adds. Given with the
        prior (:attr:`GaussianPrior.rank`) or computed once, when the variance factor needs it
        (not for a linearisation alone, e.g. :func:`normal_matrix_at`)."""
        if self.known_rank is None:
            self.known_rank = _information_rank(self.H_blocks, self.blk_r, self.blk_c,
                                                self.information)
        return self.known_rank

    @staticmethod
    def build(network: ConnectionNetwork, prior: GaussianPrior, d: int) -> _PriorData:
        ids = np.asarray(prior.node_ids, dtype=np.int64).ravel()
        k = ids.size
        if np.unique(ids).size != k:
            raise InputError('a prior names a node more than once; give each node once')
        Tm = np.asarray(prior.T_world_node, dtype=float)
        if Tm.shape != (k, 4, 4) or not np.isfinite(Tm).all():
            raise InputError(f'prior mean must be finite with shape ({k}, 4, 4), got {Tm.shape}')
        H = prior.information
        if H.shape != (d * k, d * k):
            raise InputError(f'prior information must be ({d * k}, {d * k}) for {k} nodes with '
                             f'{d} parameters each, got {H.shape}')
        if sp.issparse(H) and H.format == 'bsr' and H.blocksize == (d, d):
            Hb = H.copy()  # already in blocks (the window's joint priors): no conversion
        else:
            Hb = sp.bsr_matrix(sp.csr_matrix(H), blocksize=(d, d))
        Hb.sort_indices()
        if not np.isfinite(Hb.data).all():
            raise InputError('prior information has NaN or inf entries')
        rows = np.repeat(np.arange(k), np.diff(Hb.indptr))
        cols = Hb.indices.astype(np.int64)
        rank = prior.rank
        if rank is not None and not 0 <= int(rank) <= d * k:
            raise InputError(f'prior rank must be in [0, {d * k}] for {k} nodes, got {rank}')
        return _PriorData(network.indices_of(ids), Tm, Hb.data, rows, cols, H,
                          None if rank is None else int(rank), Hb)


def information_rank(information: FloatArray | sp.spmatrix, d: int = 6) -> int:
    """Rank of a prior's information ``(d k, d k)`` (dense or sparse, ``d x d`` blocks): the
    number of equations it adds to the redundancy (see :attr:`GaussianPrior.rank`)."""
    Hb = sp.bsr_matrix(sp.csr_matrix(information), blocksize=(d, d))
    Hb.sort_indices()
    rows = np.repeat(np.arange(Hb.shape[0] // d), np.diff(Hb.indptr))
    return _information_rank(Hb.data, rows, Hb.indices.astype(np.int64), information)


def _information_rank(blocks: FloatArray, rows: IntArray, cols: IntArray, H) -> int:
    """Rank of a prior's information matrix: the number of independent equations it adds to
    the redundancy (a zero-weight prior adds none).

    Block-diagonal information (per-node priors): the ranks of its blocks. Otherwise a
    Cholesky decides full rank (sparse for a sparse, e.g. block-banded, information), and only
    a singular matrix pays for an eigen-decomposition.
    """
    if blocks.size == 0 or not np.any(blocks):
        return 0
    if np.array_equal(rows, cols):
        return int(np.linalg.matrix_rank(0.5 * (blocks + np.swapaxes(blocks, 1, 2)),
                                         hermitian=True).sum())
    if sp.issparse(H):  # a sparse Cholesky on the block pattern
        try:
            pattern = BlockPattern(rows, cols, blocks.shape[1], H.shape[0] // blocks.shape[1])
            SparseCholesky(pattern, pattern.assemble(blocks))
            return int(H.shape[0])
        except DegenerateGeometryError:  # singular: the eigen-decomposition below
            pass
    Hd = H.toarray() if sp.issparse(H) else np.asarray(H, dtype=float)
    Hd = 0.5 * (Hd + Hd.T)
    try:
        np.linalg.cholesky(Hd)
        return int(Hd.shape[0])
    except np.linalg.LinAlgError:
        return int(np.linalg.matrix_rank(Hd, hermitian=True))


@dataclass
class _Problem:
    """One adjustment's fixed parts (connections, priors, datum, pattern of ``N``), built once.

    Its methods are the pieces of an iteration: the linear system at ``(T, v)``, the cost at
    ``T``, the residual update (eq. 16) and the retraction of a correction.
    """

    model: str
    conn: ConnectionArrays
    P: FloatArray | _PartWeights  # (m, o, o) weights S^-1 of the connections
    prior_data: list[_PriorData]
    cfg: SolverConfig
    free: np.ndarray  # (n,) bool
    col: IntArray  # (n,) block column of each node in N, -1 if fixed
    d: int
    pattern: BlockPattern
    S: FloatArray  # (m, o, o) covariance of the connections' observations
    T_meas: FloatArray | None  # (m, 4, 4) measured motions (motion models, not in parts)
    Tm_inv: FloatArray | None  # (m, 4, 4) their inverses (se3, not in parts)
    _last: tuple = (None, None)  # (T, e): the last misclosure computed, reused once
    linearisations: int = 0  # calls of linear_system so far
    jit: bool = False  # compiled kernels from the first linearisation (solve's ``jit``)
    factor: SparseCholesky | None = None  # a factor of this pattern to refactor (solve's)
    in_columns: bool = False  # se3 not in parts: linearised in columns unless compiled
    _meas: columns.MeasuredInverse | None = None  # meas, once computed
    _sqrt_w: columns.SqrtWeights | None = None  # sqrt_w, once computed
    _mis: tuple = (None, None)  # (T, columns.Misclosure) of the last cost_at, reused once
    _ahead: tuple = (None, None)  # (T, _System) of gradient_ahead, for the next gradient

    @staticmethod
    def build(model: str, conn: ConnectionArrays, prior_data: list[_PriorData],
              cfg: SolverConfig, free: np.ndarray, P: FloatArray | None = None,
              measured: tuple[FloatArray, FloatArray] | None = None) -> _Problem:
        d = models.dof(model)
        col = np.full(free.size, -1, dtype=np.int64)
        col[free] = np.arange(int(free.sum()))
        # block pattern: connection blocks (ii, ij, ji, jj) then prior blocks
        br = [col[conn.src], col[conn.src], col[conn.dst], col[conn.dst]]
        bc = [col[conn.src], col[conn.dst], col[conn.src], col[conn.dst]]
        for pd in prior_data:
            br.append(col[pd.idx[pd.blk_r]])
            bc.append(col[pd.idx[pd.blk_c]])
        pattern = kept_block_pattern(np.concatenate(br), np.concatenate(bc), d, int(free.sum()))
        S = models.observation_covariance(model, conn.cov)
        # the measured motions and their inverses are kept, except by problems linearised in
        # parts, which compute them a part at a time (the same values: ~150 MB less at 100,000
        # poses for a few tenths of a second per linearisation)
        in_parts = _linearised_in_parts(model, len(conn))
        if measured is not None and not in_parts:  # solve's measured (se3): the caller's
            T_meas, Tm_inv = measured[0], np.ascontiguousarray(measured[1])
        else:
            T_meas = (se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
                      if model in models.MOTION_MODELS and not in_parts else None)
            # their inverses: se3 only (se2 composes the planar motions themselves)
            Tm_inv = (np.ascontiguousarray(se3.inverse(T_meas))
                      if T_meas is not None and model == 'se3' else None)
        if P is None:  # the weights; a part at a time for problems linearised in parts
            P = _PartWeights(S) if in_parts else _inv_spd(S)
        return _Problem(model, conn, P, prior_data, cfg, free, col, d, pattern, S, T_meas,
                        Tm_inv, in_columns=model == 'se3' and not in_parts)

    @property
    def meas(self) -> columns.MeasuredInverse | None:
        """``Tm_inv`` as columns (se3 in columns; computed on first use: a problem
        linearised by the compiled kernel never needs it)."""
        if self._meas is None and self.in_columns:
            self._meas = columns.MeasuredInverse.of(self.Tm_inv)
        return self._meas

    @property
    def sqrt_w(self) -> columns.SqrtWeights | None:
        """``P = U'U`` as columns (se3 in columns; computed on first use)."""
        if self._sqrt_w is None and self.in_columns:
            self._sqrt_w = columns.SqrtWeights.of(self.P)
        return self._sqrt_w

    @property
    def Pf(self) -> FloatArray | None:
        """The weights when the shortcut of :func:`_linear_system` applies (se3, se2)."""
        return self.P if self.model in models.MOTION_MODELS else None

    def zero_residuals(self) -> FloatArray:
        """``v = 0``: (m, o) with ``o`` the observations per connection."""
        return np.zeros((len(self.conn), models.observations_per_connection(self.model)))

    def linear_system(self, T: FloatArray, v: FloatArray) -> _System:
        self.linearisations += 1
        if _linearised_in_parts(self.model, len(self.conn)):
            return _motion_system_in_parts(self, T)
        last_T, mis = self._mis
        self._mis = (None, None)
        compiled = self.compiled
        return _linear_system(self.model, T, self.conn, self.S, v, self.prior_data, self.cfg,
                              self.col, self.d, self.Pf, self.T_meas, self.Tm_inv, compiled,
                              None if compiled else self.meas,
                              None if compiled else self.sqrt_w, mis if last_T is T else None)

    def gradient(self, T: FloatArray, v: FloatArray) -> _System:
        """:meth:`linear_system` without ``N``: ``u``, the misclosure, the robust weights and
        the cost at ``T`` (``blocks`` ``None``), what a chord step needs (it reuses the last
        factorisation of ``N``). The compiled se3 kernel skips the blocks' products (~3x
        faster); the NumPy paths leave them pending (:meth:`_System.all_blocks`) and drop
        them."""
        ahead_T, ahead = self._ahead
        self._ahead = (None, None)
        if ahead_T is T:  # computed by gradient_ahead after the step that led to T
            return ahead
        if not self.fused_gradient:
            sysd = self.linear_system(T, v)  # the NumPy paths leave the blocks pending
            sysd.drop_blocks()
            return sysd
        self.linearisations += 1
        self._mis = (None, None)
        return _motion_system(self.model, T, self.conn, self.P, self.prior_data, self.cfg,
                              self.col, self.d, self.T_meas, self.Tm_inv, True,
                              gradient_only=True)

    @property
    def fused_gradient(self) -> bool:
        """The gradient comes from the compiled se3 kernel without the blocks of ``N``
        (:meth:`gradient`), whose misclosure is :meth:`misclosure`'s (the same compiled
        function) and, without a robust loss, whose ``cost0`` is the cost at ``T``."""
        return self.compiled and self.T_meas is not None

    def gradient_ahead(self, T: FloatArray, step: float) -> _System | None:
        """After an undamped step of size ``step`` (max ``|dx|``) to ``T``: the gradient system
        at ``T``, when the next iteration will be a chord step (``step`` below
        ``reuse_factor_below``) and the fused kernel gives the residuals and the cost at ``T``
        with it (:attr:`fused_gradient`, no robust loss). Its misclosure ``w`` and ``cost0``
        then stand for :meth:`next_residuals` and the cost of the step, and the next
        :meth:`gradient` at this very ``T`` returns it: one kernel pass instead of a misclosure,
        a cost and, in the next iteration, the gradient's own pass. ``None`` otherwise."""
        cfg = self.cfg
        if not (cfg.damping == 'none' and cfg.robust_loss == 'none' and self.fused_gradient
                and step < cfg.reuse_factor_below):
            return None
        sysd = self.gradient(T, None)
        self._ahead = (T, sysd)
        return sysd

    @property
    def compiled(self) -> bool:
        """Use the compiled se3 kernels: from the first linearisation with ``jit`` (the caller
        has loaded them: whatever the size, e.g. the window aligner's pre-alignment of ~1,200
        connections), else only once a solve has run more than
        :data:`ga_ros.core.kernels.AFTER_ITERATIONS` linearisations, on a large enough problem
        (loading numba costs ~1 s and ~100 MiB, which a short solve never earns back)."""
        if self.model != 'se3':
            return False
        if self.jit:
            return kernels.AVAILABLE
        return (self.linearisations > kernels.AFTER_ITERATIONS
                and kernels.use_for(len(self.conn)))

    def cost_at(self, T: FloatArray) -> float:
        if self.model not in models.MOTION_MODELS:
            return _cost_at(self.model, T, self.conn, self.S, self.prior_data, self.cfg,
                            self.col, self.d)
        if not self.compiled and self.meas is not None:  # in columns, kept for linear_system
            mis = columns.misclosure(T, self.conn.src, self.conn.dst, self.meas)
            self._last, self._mis = (T, mis.e), (T, mis)
            return (float(np.sum(_robust_rho(columns.maha2(mis, self.sqrt_w), self.cfg)))
                    + _prior_cost(self.model, T, self.prior_data))
        e = self.misclosure(T)
        self._last = (T, e)
        return _cost_of_misclosure(self.model, T, e, self.P, self.prior_data, self.cfg)

    def residual_update(self, sysd: _System, dx: FloatArray) -> FloatArray:
        """Residuals after the correction ``dx`` (eq. 16). For the motion models only
        ``dx = 0`` is asked (their residuals after a step come from :meth:`next_residuals`):
        ``v = S B' k = weights * w``."""
        if self.model in models.MOTION_MODELS:
            return sysd.w * sysd.weights[:, None]
        return _residual_update(sysd, dx, self.conn, self.col, self.d, self.S)

    def consistent(self, T: FloatArray, v_linear: FloatArray) -> FloatArray:
        if self.model in models.MOTION_MODELS:
            last_T, e = self._last
            self._last = (None, None)
            return e if last_T is T else self.misclosure(T)
        return _consistent_residuals(self.model, T, self.conn, v_linear)

    def misclosure(self, T: FloatArray) -> FloatArray:
        """``e = log(T_meas^-1 T_i^-1 T_j)`` of the motion models at ``T`` (in parts if the
        problem does not keep the measured motions)."""
        if self.T_meas is not None:
            compiled = self.compiled
            return _misclosure(self.model, T, self.conn, self.T_meas, self.Tm_inv, compiled,
                               None if compiled else self.meas)
        return np.concatenate([_misclosure(self.model, T, part, None, None, self.compiled)
                               for _, part in self.parts()])

    def parts(self):
        """``(a, connections a..b-1)`` for consecutive parts of :data:`_CONNECTIONS_PER_PART`
        connections."""
        conn = self.conn
        for s in _part_slices(len(conn)):
            yield s.start, ConnectionArrays(conn.src[s], conn.dst[s], conn.z[s], conn.cov[s])

    def next_residuals(self, T: FloatArray, sysd: _System, dx: FloatArray) -> FloatArray:
        """Residuals to relinearise at after the step ``dx`` took the estimate to ``T``."""
        if self.model in models.MOTION_MODELS:
            return self.consistent(T, sysd.w)
        return self.consistent(T, self.residual_update(sysd, dx))

    def retract(self, T: FloatArray, dx: FloatArray) -> FloatArray:
        return models.retract(self.model, T, np.nonzero(self.free)[0], dx.reshape(-1, self.d))


@dataclass
class _System:
    blocks: FloatArray  # (4 m + b, d, d) in pattern order
    u: FloatArray  # (n_free d,)
    w: FloatArray  # (m, r)
    A_src: FloatArray | None  # None: the compiled se3 kernel (motion models need no A, B, M)
    A_dst: FloatArray | None
    B: FloatArray | None
    Minv: FloatArray | None  # weighted M^-1
    weights: FloatArray  # (m,) robust weights
    cost0: float  # sum w' M^-1 w (robust-weighted) + prior cost at the linearisation point
    data: FloatArray | None = None  # N's lower-triangle values, when assembled in parts
    pending: Callable[[], FloatArray] | None = None  # computes the blocks (NumPy se3, se2)

    def all_blocks(self) -> FloatArray | None:
        """The ``(4 m + b, d, d)`` blocks, computed now if they were left pending (the NumPy
        motion systems compute them only when ``N`` is needed: a chord step, or a stop on the
        decrease it predicts, needs the gradient alone)."""
        if self.blocks is None and self.pending is not None:
            self.blocks, self.pending = self.pending(), None
        return self.blocks

    def drop_blocks(self) -> None:
        """Let go of the blocks (and of what would compute them)."""
        self.blocks = self.pending = None

    def normal_values(self, pattern: BlockPattern, compiled: bool = False) -> FloatArray:
        """``N``'s lower-triangle values on ``pattern``, handed over once: the system keeps
        neither them nor its blocks (the next iteration's are assembled without them).
        ``compiled``: assembled by the compiled loop (:meth:`BlockPattern.assemble`)."""
        data = (self.data if self.data is not None
                else pattern.assemble(self.all_blocks(), compiled))
        self.data = None
        self.drop_blocks()
        return data


def _linear_system(model, T, conn: ConnectionArrays, S, v, prior_data, cfg, col, d,
                   P: FloatArray | None = None, T_meas: FloatArray | None = None,
                   Tm_inv: FloatArray | None = None, compiled: bool = False,
                   meas: columns.MeasuredInverse | None = None,
                   sqrt_w: columns.SqrtWeights | None = None,
                   mis: columns.Misclosure | None = None) -> _System:
    """``N`` blocks and ``u`` of the linearised adjustment at ``(l0 = l_b + v, x0 = T)``.

    se3 with the weights ``P = S^-1`` given takes a shortcut: with ``v`` consistent with ``x0``
    (see :func:`_consistent_residuals`) the misclosure ``f(l0, x0)`` is zero, ``B = -J_r(v)``,
    ``w = v`` and ``A = [-Ad(T_ij^-1), I]``, so ``A' M^-1 A = J' P J`` and ``A' M^-1 w = J' P e``
    with ``J = J_r(e)^-1 A`` and ``e = v = log(T_meas^-1 T_i^-1 T_j)``: the Gauss-Newton system
    of ``sum e' P e``, which needs neither ``B`` nor a 6x6 inverse per connection (a test checks
    it against the general form). se2 takes the same shortcut in its 3 planar components; se3
    runs it in the compiled kernel :func:`ga_ros.core.kernels.se3_system` when ``compiled``.
    """
    shortcut = model in models.MOTION_MODELS and P is not None
    if shortcut:
        return _motion_system(model, T, conn, P, prior_data, cfg, col, d, T_meas, Tm_inv,
                              compiled, meas, sqrt_w, mis)
    lin = models.linearise(model, T, conn.src, conn.dst, conn.z, v)
    B = lin.B
    w = lin.f - (B @ v[:, :, None])[:, :, 0]  # w = f(l0, x0) + B (l_b - l0)
    M = B @ S @ np.swapaxes(B, 1, 2)
    Minv = _inv_spd(M)
    maha2 = np.einsum('mi,mij,mj->m', w, Minv, w)
    weights = _robust_weights(np.sqrt(np.maximum(maha2, 0.0)), cfg)
    Wm = Minv * weights[:, None, None]
    AiT = np.swapaxes(lin.A_src, 1, 2) @ Wm
    AjT = np.swapaxes(lin.A_dst, 1, 2) @ Wm
    blocks = [AiT @ lin.A_src, AiT @ lin.A_dst, AjT @ lin.A_src, AjT @ lin.A_dst]
    gi = (AiT @ w[:, :, None])[:, :, 0]
    gj = (AjT @ w[:, :, None])[:, :, 0]
    n_free = int((col >= 0).sum())
    u = np.zeros((n_free, d))
    _scatter_gradient(u, col[conn.src], gi)
    _scatter_gradient(u, col[conn.dst], gj)
    cost0 = float(np.sum(_robust_rho(maha2, cfg)))
    cost0 += _add_priors(model, T, prior_data, col, u, blocks)
    return _System(np.concatenate(blocks), u.reshape(-1), w, lin.A_src, lin.A_dst, B, Wm,
                   weights, cost0)


def _motion_system(model, T, conn: ConnectionArrays, P, prior_data, cfg, col, d, T_meas,
                   Tm_inv, compiled: bool, meas: columns.MeasuredInverse | None = None,
                   sqrt_w: columns.SqrtWeights | None = None,
                   mis: columns.Misclosure | None = None,
                   gradient_only: bool = False) -> _System:
    """The shortcut of :func:`_linear_system` (se3, se2): ``H = J' W J``, ``g = J' W e`` with
    ``J = J_r(e)^-1`` shared by both ends (``A_dst = J``, ``A_src = -J Ad(T_ij^-1)``).

    The blocks are written into one preallocated ``(4 m + b, d, d)`` array (connection blocks
    ``ii, ij, ji, jj``, then the ``b`` prior blocks), without a concatenated copy; the NumPy
    paths compute them only when asked (:meth:`_System.all_blocks`).
    ``gradient_only`` (compiled se3 only: :meth:`_Problem.gradient`): no blocks are computed
    (``blocks`` ``None``), the rest is the same.
    """
    m = len(conn)
    u = np.zeros((int((col >= 0).sum()), d))
    prior_blocks: list[FloatArray] = []
    prior_cost = _add_priors(model, T, prior_data, col, u,
                             None if gradient_only else prior_blocks)
    extra = sum(len(b) for b in prior_blocks)
    if T_meas is None and (model != 'se3' or (Tm_inv is None and meas is None)):
        T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    if model == 'se3' and Tm_inv is None and (compiled or meas is None):
        Tm_inv = np.ascontiguousarray(se3.inverse(T_meas))
    if model == 'se3' and compiled:
        w, blocks, gi, gj, maha2 = kernels.se3_system(T, conn.src, conn.dst, Tm_inv, P, extra,
                                                       blocks=not gradient_only)
        weights = _robust_weights(np.sqrt(np.maximum(maha2, 0.0)), cfg)
        if cfg.robust_loss != 'none':
            if not gradient_only:
                blocks[:4 * m] *= np.tile(weights, 4)[:, None, None]
            gi *= weights[:, None]
            gj *= weights[:, None]
    else:  # structure of arrays (NumPy), the blocks' products left pending
        robust = None if cfg.robust_loss == 'none' else (
            lambda r2: _robust_weights(np.sqrt(np.maximum(r2, 0.0)), cfg))
        if model == 'se3':  # columns.linearise
            lin = columns.linearise(
                T, conn.src, conn.dst,
                meas if meas is not None else columns.MeasuredInverse.of(Tm_inv),
                sqrt_w if sqrt_w is not None else columns.SqrtWeights.of(P), robust, mis)
        else:  # se2: columns.planar_linearise
            lin = columns.planar_linearise(T, conn.src, conn.dst, T_meas, P, robust)
        w, gi, gj, maha2 = lin.e, lin.g_src, lin.g_dst, lin.maha2
        weights = _robust_weights(np.sqrt(np.maximum(maha2, 0.0)), cfg)
        blocks = None
    _scatter_gradient(u, col[conn.src], gi)
    _scatter_gradient(u, col[conn.dst], gj)

    def with_priors(blocks: FloatArray) -> FloatArray:
        k = 4 * m
        for b in prior_blocks:
            blocks[k:k + len(b)] = b
            k += len(b)
        return blocks

    pending = None
    if blocks is not None:
        blocks = with_priors(blocks)
    elif not gradient_only:
        pending = lambda: with_priors(lin.normal_blocks(extra).blocks)  # noqa: E731
    cost0 = float(np.sum(_robust_rho(maha2, cfg))) + prior_cost
    # the motion models' residual update needs only w and the weights (no A, B, M)
    return _System(None if gradient_only else blocks, u.reshape(-1), w, None, None, None, None,
                   weights, cost0, pending=pending)


def _motion_system_in_parts(prob: _Problem, T: FloatArray) -> _System:
    """:func:`_motion_system` over :data:`_CONNECTIONS_PER_PART` connections at a time, each
    part's blocks added into ``N`` at once (:meth:`BlockPattern.assemble_at`): the ``4 m``
    blocks of a large problem never exist together (~700 MB for 100,000 poses). The system has
    ``data`` set and no blocks."""
    m, d = len(prob.conn), prob.d
    data = np.zeros(prob.pattern.nnz)
    u = np.zeros((int(prob.free.sum()), d))
    w, weights, cost0 = [], [], 0.0
    for a, part in prob.parts():
        b = a + len(part)
        sysp = _motion_system(prob.model, T, part, prob.P[a:b], [], prob.cfg, prob.col, d,
                              None, None, prob.compiled)  # T_meas, its inverse: of the part
        k = np.arange(a, b)
        prob.pattern.assemble_at(sysp.all_blocks(),
                                 np.concatenate([k, k + m, k + 2 * m, k + 3 * m]), data)
        u += sysp.u.reshape(-1, d)
        w.append(sysp.w)
        weights.append(sysp.weights)
        cost0 += sysp.cost0
    prior_blocks: list[FloatArray] = []
    cost0 += _add_priors(prob.model, T, prob.prior_data, prob.col, u, prior_blocks)
    if prior_blocks:
        extra = np.concatenate(prior_blocks)
        prob.pattern.assemble_at(extra, 4 * m + np.arange(len(extra)), data)
    return _System(None, u.reshape(-1), np.concatenate(w), None, None, None, None,
                   np.concatenate(weights), cost0, data)


def _scatter_gradient(u: FloatArray, c: IntArray, g: FloatArray) -> None:
    """``u[c] += g`` over the free nodes (``c >= 0``), repeated indices summed."""
    keep = c >= 0
    for k in range(u.shape[1]):
        u[:, k] += np.bincount(c[keep], weights=g[keep, k], minlength=u.shape[0])


def _add_priors(model, T, prior_data, col, u, blocks: list | None) -> float:
    """Add the prior terms to ``u`` and ``blocks`` (in place; ``None``: the gradient only);
    return their cost."""
    cost = 0.0
    for pd in prior_data:
        e, J = models.prior_residual(model, T[pd.idx], pd.T_mean)
        JT = np.swapaxes(J, 1, 2)
        if blocks is not None:  # block (a, b) of J' H J = J_a' H_ab J_b
            blocks.append(JT[pd.blk_r] @ pd.H_blocks @ J[pd.blk_c])
        He = pd.weighted(e)
        g = (JT @ He[:, :, None])[:, :, 0]
        c = col[pd.idx]
        u[c[c >= 0]] += g[c >= 0]  # a prior's nodes are distinct
        cost += float(np.sum(e * He))
    return cost


def _misclosure(model: str, T: FloatArray, conn: ConnectionArrays, T_meas: FloatArray | None,
                Tm_inv: FloatArray | None = None, compiled: bool = False,
                meas: columns.MeasuredInverse | None = None) -> FloatArray:
    """``e = log(T_meas^-1 T_i^-1 T_j)`` of the motion models (se3: compiled if asked, else
    in columns, :func:`ga_ros.core.columns.misclosure`)."""
    if model == 'se3' and meas is not None and not compiled:
        return columns.misclosure(T, conn.src, conn.dst, meas).e
    if T_meas is None:
        T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    if model != 'se3':
        return models.motion_misclosure(model, T, conn.src, conn.dst, T_meas)
    if Tm_inv is None:
        Tm_inv = np.ascontiguousarray(se3.inverse(T_meas))
    if compiled:
        return kernels.se3_misclosure(T, conn.src, conn.dst, Tm_inv)
    return columns.misclosure(T, conn.src, conn.dst, columns.MeasuredInverse.of(Tm_inv)).e


class _PartWeights:
    """The weights ``P = S^-1`` of a problem linearised in parts, computed a part at a time
    from the covariances ``S`` (the same values as one inversion of all: ~160 MB not kept at
    100,000 poses, for ~20 ms per 16,384 connections each time they are read). Slicing
    ``P[a:b]`` gives an array; :func:`_maha2` and :func:`_adjustment_cost` take it whole."""

    def __init__(self, S: FloatArray) -> None:
        self.S = S
        self.shape = S.shape

    def __getitem__(self, part: slice) -> FloatArray:
        return _inv_spd(self.S[part])

    def parts(self) -> list[slice]:
        """The parts' slices (:func:`_part_slices`)."""
        return _part_slices(self.shape[0])


def _linearised_in_parts(model: str, m: int) -> bool:
    """Whether a problem of ``m`` connections is linearised and assembled in parts (motion
    models above :data:`_PARTS_ABOVE` connections; :func:`_motion_system_in_parts`)."""
    return model in models.MOTION_MODELS and m > _PARTS_ABOVE


def _part_slices(m: int) -> list[slice]:
    """Consecutive slices of :data:`_CONNECTIONS_PER_PART` of ``m`` connections."""
    return [slice(a, min(a + _CONNECTIONS_PER_PART, m))
            for a in range(0, m, _CONNECTIONS_PER_PART)]


def _maha2(e: FloatArray, P: FloatArray | _PartWeights) -> FloatArray:
    """Squared Mahalanobis norms ``e_k' P_k e_k`` ``(m,)``."""
    if isinstance(P, _PartWeights):
        return np.concatenate([_maha2(e[s], P[s]) for s in P.parts()])
    return np.einsum('mi,mij,mj->m', e, P, e)


def _cost_of_misclosure(model, T, e, P, prior_data, cfg) -> float:
    maha2 = _maha2(e, P)
    return float(np.sum(_robust_rho(maha2, cfg))) + _prior_cost(model, T, prior_data)


def _residual_update(sysd: _System, dx: FloatArray, conn, col, d, S) -> FloatArray:
    """``k = -M^-1 (A d + w)``, ``v = S B' k`` (eq. 16), with the robust weights in ``M^-1``."""
    D = np.zeros((col.size, d))
    free = col >= 0
    D[free] = dx.reshape(-1, d)[col[free]]
    Ad = (sysd.A_src @ D[conn.src][:, :, None] + sysd.A_dst @ D[conn.dst][:, :, None])[:, :, 0]
    k = -(sysd.Minv @ (Ad + sysd.w)[:, :, None])
    return (S @ np.swapaxes(sysd.B, 1, 2) @ k)[:, :, 0]


def _lm_step(prob: _Problem, T: FloatArray, sysd: _System, data: FloatArray,
             state: _Trust) -> _Step:
    """One Levenberg-Marquardt step of the Gauss-Helmert system.

    The system is linearised at the adjusted observations ``l0 = l_b + v`` exactly as in the
    undamped iteration (so its fixed point is the adjustment's optimum); the damping
    ``lam * diag(N)`` only shortens steps, and a step is accepted when the cost (the value of
    ``sum w' M^-1 w`` at ``v = 0``, which for se3 is exactly ``sum e' P e``) does not increase.
    Each refused step costs one more factorisation (see :func:`_dogleg_step` for a strategy
    that needs one per iteration).
    """
    diag_pos = prob.pattern.indptr[:-1]  # first entry of each CSC column is its diagonal
    diag = data[diag_pos]
    for _ in range(12):
        damped = data.copy()
        damped[diag_pos] += state.lam * np.maximum(diag, 1e-9)
        try:
            dx = -state.factor(prob.pattern, damped).solve(sysd.u)
        except DegenerateGeometryError:
            state.lam *= 10.0
            continue
        T_new = prob.retract(T, dx)
        cost = prob.cost_at(T_new)
        if cost <= state.cost:
            state.lam = max(state.lam / 10.0, 1e-9)
            return _Step(T_new, prob.next_residuals(T_new, sysd, dx),
                         float(np.abs(dx).max()), True, cost, False)
        state.lam *= 10.0
    return _Step(T, prob.residual_update(sysd, np.zeros_like(sysd.u)), 0.0, False, state.cost)


def _dogleg_step(prob: _Problem, T: FloatArray, sysd: _System, data: FloatArray,
                 state: _Trust, chord_h: FloatArray | None = None) -> _Step:
    """One step of Powell's dogleg (Nocedal & Wright, Sec. 4.1): one factorisation at most.

    The cost ``F = sum e' P e`` (+ priors) has the quadratic model
    ``F + 2 u' h + h' N h`` around ``T``. The Gauss-Newton step ``h_gn = -N^-1 u`` (the only
    factorisation) and the Cauchy point ``h_sd = -(u'u / u'N u) u`` span the dogleg path; a step
    of length at most the trust radius on it is tried, and a refused step only shrinks the
    radius and moves along the same path (no new factorisation). The first iteration tries the
    full Gauss-Newton step, so on a good initial guess this is Gauss-Newton. ``chord_h``: the
    chord step ``-N_old^-1 u`` (:func:`_chord_step`), tried first when given.
    """
    u = sysd.u
    if chord_h is not None:
        chord = _chord_step(prob, T, sysd, data, chord_h, state)
        if chord is not None:
            return chord
    h_gn = -state.factor(prob.pattern, data).solve(u)
    n_gn = float(np.linalg.norm(h_gn))
    radius = state.radius if state.radius > 0 else n_gn
    Nu = h_sd = None  # the Cauchy point, computed only when the radius cuts the GN step
    alpha = n_sd = 0.0
    for _ in range(30):
        if n_gn > radius and h_sd is None:
            Nu = prob.pattern.matvec(data, u)
            uNu = float(u @ Nu)
            alpha = float(u @ u) / uNu if uNu > 0 else 0.0
            h_sd = -alpha * u
            n_sd = float(np.linalg.norm(h_sd))
        if n_gn <= radius:
            a, b = 0.0, 1.0
        elif n_sd >= radius:
            a, b = radius / n_sd, 0.0
        else:  # |h_sd + t (h_gn - h_sd)| = radius, t in (0, 1)
            p = h_gn - h_sd
            pp, sp_, ss = float(p @ p), float(h_sd @ p), n_sd * n_sd
            t = (-sp_ + np.sqrt(sp_ * sp_ + pp * (radius * radius - ss))) / pp
            a, b = 1.0 - t, t
        h = b * h_gn if a == 0.0 else a * h_sd + b * h_gn
        Nh = -b * u if a == 0.0 else -a * alpha * Nu - b * u  # N h_gn = -u, N h_sd = -alpha Nu
        predicted = -(2.0 * float(u @ h) + float(h @ Nh))
        T_new = prob.retract(T, h)
        cost = prob.cost_at(T_new)
        actual = state.cost - cost
        norm_h = float(np.linalg.norm(h))
        rho = actual / predicted if predicted > 0 else -1.0
        if rho > 1e-4 or (actual >= 0 and predicted <= 1e-300):
            if rho > 0.75:
                radius = max(radius, 3.0 * norm_h)
            elif rho < 0.25:
                radius = 0.5 * norm_h
            state.radius = radius
            return _Step(T_new, prob.next_residuals(T_new, sysd, h),
                         float(np.abs(h).max()) if h.size else 0.0, True, cost, b == 1.0,
                         predicted)
        radius = 0.25 * norm_h
        if radius < 1e-12:
            break
    state.radius = max(radius, 1e-12)
    return _Step(T, prob.residual_update(sysd, np.zeros_like(u)), 0.0, False, state.cost)


def _chord_step(prob: _Problem, T: FloatArray, sysd: _System, data: FloatArray,
                h: FloatArray, state: _Trust) -> _Step | None:
    """The chord step ``h = -N_old^-1 u`` from the last factorisation (``N_old``, one
    iteration old), kept instead of factoring ``N`` anew when the new linearisation confirms it.

    With the quadratic model ``q(h) = 2 u' h + h' N h`` of the current linearisation, the step
    is kept when (a) the new and the old matrix agree along it, ``h' N h / h' N_old h`` within
    ``[0.8, 1.25]`` (``h' N_old h = -u' h``; a stale factor, e.g. of ``10 N``, fails), so that
    ``h`` is close to the Gauss-Newton step, and (b) the cost falls by at least a quarter of the
    predicted ``-q(h)`` (the dogleg's acceptance). It then counts as a Gauss-Newton step for the
    convergence test on the relative cost decrease. Otherwise ``None``: the caller factors ``N``
    as usual (the chord cost one solve, one product with ``N`` and perhaps one cost evaluation).
    """
    u = sysd.u
    old = -float(u @ h)  # h' N_old h
    hNh = float(h @ prob.pattern.matvec(data, h))
    if not (old > 0 and 0.8 * old <= hNh <= 1.25 * old):
        return None
    predicted = 2.0 * old - hNh
    T_new = prob.retract(T, h)
    cost = prob.cost_at(T_new)
    actual = state.cost - cost
    if not (actual >= 0 and actual >= 0.25 * predicted):
        return None
    return _Step(T_new, prob.next_residuals(T_new, sysd, h),
                 float(np.abs(h).max()) if h.size else 0.0, True, cost, True, predicted)


def _consistent_residuals(model: str, T: FloatArray, conn: ConnectionArrays,
                          v_linear: FloatArray, T_meas: FloatArray | None = None) -> FloatArray:
    """Residuals to relinearise at next (paper Sec. III-C step 5: ``l0 = l_b + v``).

    For se3 the constraint ``f = 0`` has the closed-form solution
    ``v = log(T_meas^-1 T_i^-1 T_j)`` at the new ``x``; using it (instead of the linear
    prediction ``v = S B' k``) keeps ``v`` on the principal branch of the rotation log, and the
    Gauss-Helmert step becomes exactly Gauss-Newton on ``sum e' P e``. The position models keep
    the linear prediction (their constraints are not solvable for ``v`` in closed form). se2 as
    se3, in its planar components.
    """
    if model not in models.MOTION_MODELS:
        return v_linear
    return _misclosure(model, T, conn, T_meas)


def _cost_at(model, T, conn, S, prior_data, cfg, col, d, P=None, T_meas=None) -> float:
    """Cost of the adjustment at ``x = T``: ``sum rho(e' P e)`` for se3/se2 (``e`` the
    misclosure ``log(T_meas^-1 T_i^-1 T_j)``), else the value of ``sum w' M^-1 w`` linearised at
    ``v = 0``; plus the prior terms."""
    if model not in models.MOTION_MODELS:
        return _linear_system(model, T, conn, S, np.zeros_like(conn.z), prior_data, cfg, col,
                              d).cost0
    e = _misclosure(model, T, conn, T_meas)
    return _cost_of_misclosure(model, T, e, _inv_spd(S) if P is None else P, prior_data, cfg)


def _robust_weights(r: FloatArray, cfg: SolverConfig) -> FloatArray:
    c = cfg.robust_scale
    if cfg.robust_loss == 'huber':
        return np.where(r <= c, 1.0, c / np.maximum(r, 1e-300))
    if cfg.robust_loss == 'cauchy':
        return 1.0 / (1.0 + (r / c) ** 2)
    return np.ones_like(r)


def _robust_rho(r2: FloatArray, cfg: SolverConfig) -> FloatArray:
    """Robust cost of squared Mahalanobis distances (equals ``r2`` for least squares)."""
    c = cfg.robust_scale
    if cfg.robust_loss == 'huber':
        r = np.sqrt(np.maximum(r2, 0.0))
        return np.where(r <= c, r2, 2.0 * c * r - c * c)
    if cfg.robust_loss == 'cauchy':
        return c * c * np.log1p(r2 / (c * c))
    return r2


def _adjustment_cost(v: FloatArray, P: FloatArray | _PartWeights, weights: FloatArray) -> float:
    if isinstance(P, _PartWeights):
        return float(sum(_adjustment_cost(v[s], P[s], weights[s]) for s in P.parts()))
    return float(_maha2(v, P) @ weights)  # ~2x faster than one four-operand einsum


def _prior_cost(model: str, T: FloatArray, prior_data) -> float:
    total = 0.0
    for pd in prior_data:
        e, _ = models.prior_residual(model, T[pd.idx], pd.T_mean)
        total += float(np.sum(e * pd.weighted(e)))
    return total


def _inv_spd(M: FloatArray) -> FloatArray:
    """Inverse of a stack of SPD matrices, via Cholesky (raises on a non-PD block)."""
    return spd_inverse(M, "a connection has a singular B S B' block")


# ------------------------------------------------------------------------ helpers for users
def initial_guess_f2f(network: ConnectionNetwork,
                      T_world_first: FloatArray | None = None) -> FloatArray:
    """Frame-to-frame (F2F) initial poses: chain the measured motions along a spanning tree.

    The tree prefers connections between nodes adjacent in insertion order (consecutive
    frames), so on a survey it is exactly the F2F integration of the consecutive motions.

    Returns
    -------
    (n, 4, 4) poses ``T_world_node``; the first node is at ``T_world_first`` (identity default).
    """
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree  # lazy: start-up

    n = network.n_nodes
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    if T_world_first is not None:
        T[0] = T_world_first
    conn = network.arrays()
    if n <= 1 or len(conn) == 0:
        return T
    network.check_connected([int(network.node_ids[0])])
    gap = np.abs(conn.dst - conn.src).astype(float)
    G = sp.coo_matrix((gap + 1e-9 * np.arange(len(conn)) / len(conn), (conn.src, conn.dst)),
                      shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(G)
    tree = tree + tree.T
    order, pred = breadth_first_order(tree, 0, directed=False, return_predecessors=True)
    # measured motion for each (parent -> child) tree edge
    lookup: dict[tuple[int, int], int] = {}
    for k in range(len(conn)):
        lookup.setdefault((int(conn.src[k]), int(conn.dst[k])), k)
    T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    for child in order[1:]:
        parent = int(pred[child])
        k = lookup.get((parent, int(child)))
        if k is not None:
            T[child] = T[parent] @ T_meas[k]
        else:
            T[child] = T[parent] @ se3.inverse(T_meas[lookup[(int(child), parent)]])
    return T


def connection_cost(network: ConnectionNetwork, T_world_node: FloatArray) -> float:
    """``sum e' Omega e`` over connections, ``e = log(T_meas^-1 T_i^-1 T_j)`` in
    ``[rho, phi]`` order and ``Omega = cov^-1`` (the g2o/GTSAM between-factor cost)."""
    conn = network.arrays()
    T = np.asarray(T_world_node, dtype=float)
    T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    e = se3.log(se3.inverse(T_meas) @ se3.inverse(T[conn.src]) @ T[conn.dst])
    return float(np.einsum('mi,mij,mj->', e, _inv_spd(conn.cov), e))


# ------------------------------------------------------------------- sequential (Sec. III-D)
def sequential_update(previous: SolveResult, group2: ConnectionNetwork, T_init: FloatArray,
                      config: SolverConfig | None = None) -> SolveResult:
    """Sequential solution (paper Sec. III-D, information form of METHOD.md Sec. 4).

    Group 1 is represented only by ``previous`` (its estimate ``x1`` and normal matrix ``N1``);
    its observations are not used again. ``group2`` holds the new observations; it must contain
    every node of ``previous`` (same ids) and may add new nodes (new unknowns ``y``).

    Parameters
    ----------
    previous : result of the group-1 solution (carries ``x1`` and ``N1``).
    group2 : network of all nodes (old and new) with only the new connections.
    T_init : (n, 4, 4) initial poses in ``group2`` index order: the previous estimate for old nodes
        and e.g. an F2F extrapolation for new ones.
    config : solver settings (the model must match ``previous``).
    """
    cfg = config or SolverConfig(model=previous.model)
    if cfg.model != previous.model:
        raise InputError(f"model {cfg.model!r} differs from the previous solution's "
                         f'{previous.model!r}')
    missing = np.setdiff1d(previous.node_ids, group2.node_ids)
    if missing.size:
        raise NetworkError(f'group 2 must contain every node of the previous solution; missing '
                           f'{missing[:10].tolist()}')
    sysm = previous._system
    fixed = [int(i) for i in sysm.node_ids[~sysm.free]]
    return solve(group2, T_init, cfg, fixed=fixed, priors=[previous.prior()])


def covariance_form_update(previous: SolveResult, group2: ConnectionNetwork,
                           config: SolverConfig | None = None) -> tuple[FloatArray, FloatArray]:
    """One sequential step in covariance form (METHOD.md Sec. 4), no new unknowns.

    ``K = Q1 A2' (M2 + A2 Q1 A2')^-1``, ``x2 = x1 - K w2(x1)``, ``Q2 = Q1 - K A2 Q1``.

    Dense in the number of unknowns: meant for small problems and for checking the information
    form (:func:`sequential_update`), which is what the package uses.

    Returns
    -------
    T_world_node : (n, 4, 4) updated poses (group-2 index order, equal to ``previous`` order).
    Q2 : (u, u) updated cofactor matrix of the free unknowns.
    """
    cfg = config or SolverConfig(model=previous.model)
    if not np.array_equal(np.sort(previous.node_ids), np.sort(group2.node_ids)) or \
            group2.n_nodes != previous.node_ids.size:
        raise InputError('the covariance form handles no new unknowns: group 2 must have '
                         'exactly the nodes of the previous solution')
    sysm = previous._system
    d = sysm.d
    order = group2.indices_of(previous.node_ids)
    T1 = np.empty_like(previous.T_world_node)
    T1[order] = previous.T_world_node
    free = np.zeros(group2.n_nodes, dtype=bool)
    free[order[sysm.free]] = True
    col = np.full(group2.n_nodes, -1, dtype=np.int64)
    col[order[sysm.free]] = np.arange(int(sysm.free.sum()))
    N1 = previous.normal_matrix.toarray()
    Q1 = np.linalg.inv(N1)
    conn = group2.arrays()
    o = models.observations_per_connection(cfg.model)
    v0 = _consistent_residuals(cfg.model, T1, conn, np.zeros((len(conn), o)))
    lin = models.linearise(cfg.model, T1, conn.src, conn.dst, conn.z, v0)
    m, r = lin.f.shape
    A2 = np.zeros((m * r, Q1.shape[0]))
    rows = np.arange(m * r).reshape(m, r)
    for k in range(m):
        for node, Ablk in ((conn.src[k], lin.A_src[k]), (conn.dst[k], lin.A_dst[k])):
            if col[node] >= 0:
                A2[rows[k][:, None], col[node] * d + np.arange(d)] += Ablk
    M2 = np.zeros((m * r, m * r))
    Mb = lin.B @ models.observation_covariance(cfg.model, conn.cov) @ np.swapaxes(lin.B, 1, 2)
    for k in range(m):
        M2[rows[k][:, None], rows[k]] = Mb[k]
    w2 = (lin.f - (lin.B @ v0[:, :, None])[:, :, 0]).reshape(-1)  # w = f + B (l_b - l0)
    K = Q1 @ A2.T @ np.linalg.inv(M2 + A2 @ Q1 @ A2.T)
    dx = -K @ w2
    Q2 = Q1 - K @ A2 @ Q1
    T2 = models.retract(cfg.model, T1, np.nonzero(free)[0], dx.reshape(-1, d)[col[free]])
    return T2, 0.5 * (Q2 + Q2.T)


def normal_matrix_at(network: ConnectionNetwork, T: FloatArray, model: str = 'se3',
                     fixed: Sequence[int] = (),
                     priors: Sequence[GaussianPrior] = ()
                     ) -> tuple[sp.csc_matrix, IntArray, FloatArray]:
    """Normal matrix ``N = A' M^-1 A`` and ``u = A' M^-1 w`` (+ prior terms) linearised at ``T``.

    Unlike :func:`solve`, no datum is required and nothing is factored, so ``N`` may be
    singular; it is what marginalisation (Schur complements) works on.

    Returns
    -------
    N : (d u, d u) symmetric CSC over the free nodes.
    free_ids : (u,) ids of the free nodes, in the order of ``N``'s blocks.
    u : (d u,) half the gradient of the cost at ``T`` (the Gauss-Newton step is ``-N^-1 u``).
    """
    d = models.dof(model)
    conn = network.arrays()
    free = np.ones(network.n_nodes, dtype=bool)
    if len(fixed):
        free[network.indices_of(list(fixed))] = False
    prior_data = [_PriorData.build(network, p, d) for p in priors]
    prob = _Problem.build(model, conn, prior_data, SolverConfig(model=model), free)
    T = np.asarray(T, dtype=float)
    sysd = prob.linear_system(T, prob.consistent(T, prob.zero_residuals()))
    pattern = prob.pattern
    return pattern.full_csc(sysd.normal_values(pattern)), network.node_ids[free], sysd.u
