"""Track-by-track sliding-window alignment (paper Sec. IV and Appendix).

A lawnmower survey is flown as tracks. Measurements arrive one by one; when a track ends
(explicitly, or because a measurement introduces a node of a newer track), the mixed adjustment
runs over the nodes of the latest ``K`` tracks only. The adjustment is warm-started from the
previous estimate (the new track's nodes start from their frame-to-frame integration), so each
update solves only for the increment the new track brings. Nodes of the track that leaves the
window stop being unknowns and are *frozen*:

* ``freeze_policy='weighted'`` (the paper, Sec. III-E): every frozen node that is still connected
  to the window stays an unknown of the next adjustments, as a weighted parameter with one joint
  Gaussian prior over all such nodes (their full covariance, correlations kept). The prior holds
  the information of the connections among frozen nodes only (absorbed by a Schur complement
  when a track freezes, the other frozen nodes eliminated); connections to the window stay in
  the window problem and are relinearised there. No connection is counted twice, so the
  published covariances are not overconfident (earlier versions used independent per-node
  priors with the marginal covariances of the last adjustment, which counted shared information
  again at every update: position NEES ~100 instead of 3).
* ``freeze_policy='marginal'``: the leaving track is marginalised out exactly (Schur complement
  of its terms, as fixed-lag smoothers do), which leaves a joint Gaussian prior on the window
  nodes it was connected to; its connections are absorbed into that prior.

The exact joint prior is dense over the boundary nodes (a whole swath); it is stored sparse
(``prior_band``, ``prior_hubs``; :func:`~ga_ros.core.refinement.band_prior`): the exact mean and
the exact covariance on a skeleton (a band along the trajectory plus hub nodes), maximum entropy
beyond it, so a freeze and every window factorisation cost linear in the swath length.

The cost of an update depends on the window only, not on the number of tracks flown.

A background refinement (``refine_every_tracks``, :mod:`ga_ros.core.refinement`) re-solves the
survey (its last ``refine_horizon_tracks`` tracks, the older ones as one prior) off the update
path and hands the result back at a fixed later track: frozen poses and covariances refined,
priors rebuilt at the refined estimate, and the window's corrections carried back to the frozen
nodes of that horizon, so the online path follows the batch solution.

Measurement policy (what :meth:`TrackWindowAligner.add_measurement` rejects with
:class:`~ga_ros.errors.InputError`, leaving the state unchanged): non-finite values or a
covariance that is not symmetric positive definite or outside the configured eigenvalue range
and condition number (``bad_covariance``); a self-loop; ids outside ``[0, 2**63)``; a new node or
track id far above the largest seen (``id_jump``, ``track_jump``); an unknown ``kind``;
an unknown source node (every measurement after the first must start at a known node); a new node
of an older track than the current one (out of order); a re-delivered identical measurement; an
endpoint on a frozen track. Gross outliers among overlap (cross) connections are detected after
each update by a chi-square test on the Mahalanobis misclosure and excluded; excluded connections
of the window are re-tested at each new estimate and re-admitted when consistent.
"""

from __future__ import annotations

import threading
import time
import zlib
from dataclasses import asdict, dataclass, fields, replace

import numpy as np
import scipy.linalg as sla
from scipy.stats import chi2

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.linalg import selinv
from ga_ros.core.linalg.banded import spd_inverse
from ga_ros.core.linalg.cholesky import trailing_factor
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.core.network import ConnectionNetwork, check_covariances
from ga_ros.core.prealign import prealign
from ga_ros.core.quality import (
    QualityConfig,
    QualityReport,
    QualitySummary,
    quality_control,
    summarise,
)
from ga_ros.core.refinement import (
    REFINE_EXECUTORS,
    AbsorbedPrior,
    RefinementResult,
    RefinementSnapshot,
    RefinementWorker,
    absorbed_priors,
    marginal_prior,
    prior_nodes,
)
from ga_ros.core.solver import (
    GaussianPrior,
    SolverConfig,
    SolveResult,
    information_rank,
    normal_matrix_at,
    solve,
)
from ga_ros.core.storage import IdIndex, SymArray, SymRows, TrackLists, TrackRanges, grow_rows
from ga_ros.core.storage import Rows as _Rows
from ga_ros.errors import DegenerateGeometryError, GaError, InputError
from ga_ros.geometry import se3
from ga_ros.runtime import blas_threads, limit_blas_threads

FREEZE_POLICIES = ('weighted', 'marginal')
#: The process-wide BLAS thread limit (:func:`~ga_ros.runtime.limit_blas_threads`) set by the
#: first freeze computed ahead (``freeze_ahead``) and kept: the background thread runs under it,
#: since the ``blas_threads()`` contexts of two threads would restore each other's limits.
_BLAS_LIMIT = None
_EYE6 = np.eye(6)
_potrf = sla.get_lapack_funcs('potrf', (_EYE6,))
GATES = ('chi2', 'w-test')


def measurement_fingerprints(z: FloatArray, cov: FloatArray) -> list[int]:
    """CRC-32 of each measurement's values (rows of ``z`` (m, 6) and ``cov`` (m, 6, 6)), the
    third part of the duplicate-test key ``(low id, high id, fingerprint)``; two different
    measurements between the same two nodes share it with probability 2**-32."""
    rows = np.ascontiguousarray(np.concatenate(
        [np.reshape(z, (-1, 6)), np.reshape(cov, (-1, 36))], axis=1, dtype=np.float64))
    flat = memoryview(rows.reshape(-1).view(np.uint8))
    return [zlib.crc32(flat[k:k + 336]) for k in range(0, flat.nbytes, 336)]


#: The aligner's solver defaults where they differ from :class:`SolverConfig`'s (the rest are
#: SolverConfig's): a window update is warm-started, so 10 iterations, a 1 um / 1 urad
#: correction and a relative cost decrease of 1e-6 suffice (a step that gains less, or a chord
#: step that predicts less, ends the update; the estimate then lies within ~1e-3 standard
#: deviations of the window's optimum, ``test_window_fast.py``). The new track
#: is first pre-aligned alone (:mod:`ga_ros.core.prealign`), so the window's first correction,
#: though metres long on its weak modes, leaves the factorisation usable: later iterations
#: reuse it as chord steps once a correction is below 20 m / rad (a chord step that does not
#: lower the cost as predicted, or chord steps contracting slower than 1/2, make the next
#: iteration factor anew). A full window then takes one numeric factorisation and two
#: linearisations per update (aerial survey, 10 % noise; it took two and three, plus one
#: factorisation at the solution for the covariances: with ``cost_tolerance > 0`` they now come
#: from the update's one factorisation, ``solve(factor_at_solution=False)``).
ALIGNER_SOLVER = SolverConfig(max_iterations=10, tolerance=1e-6, cost_tolerance=1e-6,
                              reuse_factor_below=20.0)


@dataclass(frozen=True)
class AlignerConfig:
    """Settings of :class:`TrackWindowAligner` (mirrors the alignment node's parameters).

    Attributes
    ----------
    window_tracks : ``K``, the number of latest tracks adjusted after each track (paper: 5).
    freeze_policy : ``'weighted'`` (paper) or ``'marginal'`` (Schur complement), see module doc.
    freeze_ahead : compute the freeze of the track that will leave the window at the next
        update right after an update, in a background thread (it needs only the state after
        that update), so the next track end only installs it; identical results (it is
        recomputed at the track end if a new measurement touched that track, or after
        anything else that changes what it depends on). ``False``: at the track end.
    solver : settings of each window update (parameters ``solver.<field>``), documented in
        :class:`~ga_ros.core.solver.SolverConfig`; default :data:`ALIGNER_SOLVER`. The live
        aligner supports model ``'se3'`` only (relative motions in the sensor frame; the
        position-only models need world-frame observations, see :mod:`ga_ros.core.models`).
        With ``cost_tolerance > 0`` (default) an update stops once a step lowers the cost by
        less than that fraction and its covariances come from its last factorisation
        (``solve(factor_at_solution=False)``: a fraction of a correction from the solution);
        ``cost_tolerance = 0`` solves to ``tolerance`` and factors ``N`` at the solution.
    outlier_chi2_prob : chi-square quantile of the misclosure test that excludes cross
        connections after an update (6 degrees of freedom); 0 disables the test.
    cov_min_eigenvalue : smallest eigenvalue a measurement covariance may have (m^2 / rad^2);
        default 1e-12, i.e. a standard deviation of 1 um / 1 urad. Smaller ones (e.g. 1e-20 I)
        make the normal matrix numerically singular; they are rejected as ``bad_covariance``.
    cov_max_eigenvalue : largest eigenvalue (m^2 / rad^2); default 1e6 (1 km / 1000 rad): larger
        ones are placeholders for "unknown" (e.g. 1e308 I), rejected as ``bad_covariance``.
    cov_max_condition : largest ratio of the largest to the smallest eigenvalue; default 1e12.
    max_track_jump : largest step of a new track id above the largest track id seen (default
        100); a far-ahead id (track 1,000,000 after track 3) would end the survey. 0 = no limit.
    max_node_id_jump : largest step of a new node id above the largest node id seen (default
        10**7); e.g. a node id 2**53 after 500 is rejected (``id_jump``). 0 = no limit.
    gate : how gross errors among cross connections are found after each update: ``'chi2'``
        (the Mahalanobis misclosure against ``chi2_6(outlier_chi2_prob)``, every failing one
        excluded at once) or ``'w-test'`` (Baarda's data snooping over the window's cross
        connections: every cross connection whose w-test of :mod:`ga_ros.core.quality` rejects
        at level ``quality_alpha0`` is excluded, the window re-adjusted, and so on until none
        rejects; as with ``'chi2'``, a good connection excluded next to a gross error comes back
        by re-admission. Baarda's one-at-a-time removal needs too many re-adjustments per
        update at 20 % wrong connections: see the README).
        ``outlier_chi2_prob = 0`` disables either gate (it is also the re-admission level).
    quality : compute the quality control of every window update (``UpdateResult.quality``:
        global test, ``sigma0^2``, largest ``|w|``, w-test rejections, smallest redundancy
        number, median MDB, over the window's connections; :mod:`ga_ros.core.quality`).
    quality_every : compute it at every N-th update only (1: every update). It costs about as
        much as the update itself (the blocks of ``Q_x`` on every connected pair); the
        ``'w-test'`` gate needs it at every update anyway and then it is always reported.
    quality_alpha : significance level of the global test of the variance factor.
    quality_alpha0 : level of the 1-D w-test (critical value ``z_{1-alpha0/2}``: 3.89 at 1e-4,
        3.29 at 1e-3), for the quality figures and the ``'w-test'`` gate.
    refine_every_tracks : background refinement (:mod:`ga_ros.core.refinement`): after every
        this many tracks (counted when at least one track is frozen) the survey (its last
        ``refine_horizon_tracks`` tracks) is solved in batch off the update path and handed back
        as the new frozen estimate (poses, published covariances, relinearised priors). 0
        disables it.
    refine_lag_tracks : a refinement started after track ``k`` is installed at the start of the
        update of track ``k + refine_lag_tracks`` (waiting for it there if it is not ready), so
        the result does not depend on timing: a replay and a live node give the same path.
    refine_executor : where the refinement runs: ``'process'`` (a separate process, 'spawn'
        start method; truly parallel), ``'thread'`` or ``'inline'`` (solved at the hand-off;
        same result, for tests and single-core machines).
    refine_horizon_tracks : ``H``, tracks a refinement re-solves (:mod:`ga_ros.core.refinement`,
        bounded refinement): the newest ``H`` finished tracks (and older ones not retired yet);
        the terms of older tracks enter as one joint prior over the horizon's oldest nodes, and
        those tracks stay where the last refinement that covered them left them. Per-track cost
        and memory of the refinement are then flat in the survey length. 0: the whole survey
        every time (its cost grows with the survey). While the survey has at most ``H``
        tracks both are the same. The default 20 is full from the 21st track on, so the
        per-track cost is flat from there (30 was not, at 25 tracks); on the paper's aerial
        survey (25 double tracks, 10 % noise, 3 noise draws) its rigid-ATE gap to batch is
        within 0.5 % of the whole-survey refinement's (-0.0 / +0.5 / -0.1 % against -0.0 /
        +0.0 / -0.0 %); 15 lost 0.8 % on the first draw, 10 lost 8.7 %.
    prior_band : half-bandwidth ``w`` (nodes, along the trajectory) of the joint priors'
        information (:func:`~ga_ros.core.refinement.band_prior`): the exact marginal
        covariance of the prior nodes on that band (every node's covariance and its
        correlations with ``w`` nodes on either side) and with the hubs, maximum entropy
        beyond it, so the
        information is block-banded and a freeze and each window factorisation cost linear in
        the swath length. -1: the exact dense Schur complement (a dense block of up to a whole
        swath in every factorisation).
    prior_hubs : hub nodes of the sparse joint priors (spread evenly along the prior nodes):
        their covariances with every prior node are kept exactly too, which keeps the
        long-range correlations (the common drift of a frozen swath) that a band alone loses.
        Each adds one dense block row to the window's normal matrix.
    """

    window_tracks: int = 5
    freeze_policy: str = 'weighted'
    freeze_ahead: bool = True
    solver: SolverConfig = ALIGNER_SOLVER
    outlier_chi2_prob: float = 0.99999
    cov_min_eigenvalue: float = 1e-12
    cov_max_eigenvalue: float = 1e6
    cov_max_condition: float = 1e12
    max_track_jump: int = 100
    max_node_id_jump: int = 10_000_000
    gate: str = 'chi2'
    quality: bool = False
    quality_every: int = 1
    quality_alpha: float = 0.05
    quality_alpha0: float = 1e-4
    refine_every_tracks: int = 1
    refine_lag_tracks: int = 1
    refine_executor: str = 'process'
    refine_horizon_tracks: int = 20
    prior_band: int = 16
    prior_hubs: int = 16

    def __post_init__(self) -> None:
        if int(self.window_tracks) < 1:
            raise InputError(f'window_tracks must be >= 1, got {self.window_tracks}')
        if self.freeze_policy not in FREEZE_POLICIES:
            raise InputError(f'freeze_policy must be one of {FREEZE_POLICIES}, '
                             f'got {self.freeze_policy!r}')
        if not isinstance(self.solver, SolverConfig):
            raise InputError(f'solver must be a SolverConfig, got {type(self.solver).__name__} '
                             '(use AlignerConfig.from_dict for a saved mapping)')
        if self.solver.model != 'se3':
            raise InputError(f"the track-window aligner supports model 'se3' only, got "
                             f'{self.solver.model!r}: live measurements are motions in the '
                             'sensor frame; use ga-ros solve/reproduce for the paper model')
        if not 0.0 <= self.outlier_chi2_prob < 1.0:
            raise InputError('outlier_chi2_prob must be in [0, 1)')
        if not 0.0 < self.cov_min_eigenvalue < self.cov_max_eigenvalue < np.inf:
            raise InputError('need 0 < cov_min_eigenvalue < cov_max_eigenvalue < inf, got '
                             f'{self.cov_min_eigenvalue}, {self.cov_max_eigenvalue}')
        if not 1.0 <= self.cov_max_condition < np.inf:
            raise InputError(f'cov_max_condition must be >= 1, got {self.cov_max_condition}')
        if int(self.max_track_jump) < 0 or int(self.max_node_id_jump) < 0:
            raise InputError('max_track_jump and max_node_id_jump must be >= 0 (0 = no limit)')
        if self.gate not in GATES:
            raise InputError(f'gate must be one of {GATES}, got {self.gate!r}')
        if int(self.quality_every) < 1:
            raise InputError(f'quality_every must be >= 1, got {self.quality_every}')
        self.quality_config()  # range checks of the levels

        if int(self.refine_every_tracks) < 0 or int(self.refine_lag_tracks) < 1:
            raise InputError('refine_every_tracks must be >= 0 (0 = off) and refine_lag_tracks '
                             f'>= 1, got {self.refine_every_tracks}, {self.refine_lag_tracks}')
        if self.refine_executor not in REFINE_EXECUTORS:
            raise InputError(f'refine_executor must be one of {REFINE_EXECUTORS}, '
                             f'got {self.refine_executor!r}')
        if int(self.refine_horizon_tracks) < 0:
            raise InputError('refine_horizon_tracks must be >= 0 (0 = the whole survey), got '
                             f'{self.refine_horizon_tracks}')
        if int(self.prior_band) < -1 or int(self.prior_hubs) < 0:
            raise InputError(f'prior_band must be >= 0 (nodes) or -1 (dense) and prior_hubs '
                             f'>= 0, got {self.prior_band}, {self.prior_hubs}')

    def quality_config(self) -> QualityConfig:
        """The test settings of the quality control and of the ``'w-test'`` gate."""
        return QualityConfig(alpha=self.quality_alpha, alpha0=self.quality_alpha0,
                             snoop_test='w')

    def solver_config(self) -> SolverConfig:
        """The settings of each window update (:attr:`solver`)."""
        return self.solver

    @classmethod
    def from_dict(cls, values: dict) -> AlignerConfig:
        """The config of a mapping written by ``dataclasses.asdict`` (a snapshot header).

        Reads the nested layout (``{'solver': {...}, ...}``) and the flat one of files written
        before the solver settings were nested (``max_iterations``, ``tolerance``, ... beside
        ``window_tracks``); solver fields missing from either take :data:`ALIGNER_SOLVER`'s.

        Raises
        ------
        InputError
            An unknown field or a value the config rejects.
        """
        own = {f.name for f in fields(cls)} - {'solver'}
        solver_names = {f.name for f in fields(SolverConfig)}
        nested = values.get('solver') or {}
        flat = {k: v for k, v in values.items() if k in solver_names}
        unknown = set(values) - own - solver_names - {'solver'}
        if unknown or not isinstance(nested, dict):
            raise InputError(f'unknown aligner config fields {sorted(unknown)}; expected '
                             f'{sorted(own | {"solver"})}')
        try:
            solver = replace(ALIGNER_SOLVER, **{**flat, **nested})
            return cls(solver=solver, **{k: v for k, v in values.items() if k in own})
        except TypeError as exc:
            raise InputError(f'bad aligner config: {exc}') from exc


@dataclass
class UpdateResult:
    """Summary of one window adjustment.

    ``quality``: its quality control, :class:`~ga_ros.core.quality.QualitySummary`, when
    ``AlignerConfig.quality`` is on. ``refined_after_tracks`` is the track count of the
    background refinement installed in this update (-1: none), ``refine_reason`` its
    outcome (the batch solve's reason, or why it was not installed), ``refine_wait_ms`` the
    time spent waiting for it and installing it (part of ``update_ms``).
    """

    track_id: int
    iterations: int
    converged: bool
    sigma0_sq: float
    update_ms: float
    n_window_nodes: int
    n_window_connections: int
    n_tracks_in_window: int
    n_outliers: int
    reason: str
    n_priors: int = 0
    n_unknowns: int = 0
    n_readmitted: int = 0
    quality: QualitySummary | None = None
    refined_after_tracks: int = -1
    refine_reason: str = ''
    refine_wait_ms: float = 0.0


@dataclass
class CorrectedPath:
    """Every node seen so far, in arrival order, with its corrected pose.

    ``T_world_node`` is the latest estimate: adjusted for nodes of finished tracks, the
    frame-to-frame continuation from the last adjusted node for the open track.
    """

    node_ids: IntArray
    track_ids: IntArray
    stamps_ns: IntArray
    T_world_node: FloatArray
    frozen: BoolArray


@dataclass
class AlignerStats:
    n_nodes: int
    n_connections: int
    n_rejected: dict[str, int]
    tracks_in_window: list[int]
    n_updates: int
    n_outliers: int
    last_update: UpdateResult | None = None


@dataclass
class BatchResult:
    """Outcome of :meth:`TrackWindowAligner.add_measurements`.

    Attributes
    ----------
    updates : window updates the batch triggered (one per track end), in order.
    n_accepted, n_rejected : measurements added / rejected (state unchanged for those).
    rejected : rejections by reason.
    """

    updates: list[UpdateResult]
    n_accepted: int
    n_rejected: int
    rejected: dict[str, int]


#: Freezing: above this many leaving nodes, their marginal covariances come from one partial
#: factorisation of the window with them ordered last, below it from sparse solves.
_TRAILING_MIN_NODES = 24
#: Freezing with block-banded priors: from this many leaving nodes on, their covariances come
#: from the banded selected inversion of the window (linear in the swath length) instead of the
#: trailing dense block (cubic in it). Aerial survey, window 5, CPU of one freeze: 204 nodes
#: 272 ms trailing vs 319 ms banded; 1,000 nodes 10.9-12.8 s vs 1.2-1.6 s.
_BANDED_MIN_NODES = 300


def _marginal_covariances(res: SolveResult, node_ids: IntArray, banded: bool = False
                          ) -> FloatArray:
    """``(k, 6, 6)`` marginal covariances of free nodes of an adjustment (eq. 17).

    Many nodes (a track leaving the window), with the compiled kernels: selected inversion
    (:class:`~ga_ros.core.linalg.selinv.SelectedInverse`, Takahashi's equations in place) on the
    adjustment's own sparse factor, refactored at the solution with its symbolic analysis (the
    analysis is handed back, so the next window solve does not repeat it): every node block of
    ``N^-1`` in about the time of one factorisation. Without the kernels: ``banded`` (the
    window's priors are block-banded, ``prior_band >= 0``) the block-tridiagonal selected
    inversion of :meth:`SolveResult.covariance`, otherwise the window's normal matrix factored
    once more with those nodes ordered last (the trailing dense block of the factor is the
    Cholesky factor of their joint marginal information ``S = L L'``; the diagonal blocks of
    ``S^-1 = L^-T L^-1`` are read from ``L^-1``). All exact. Few nodes: sparse solves.
    """
    ids = np.asarray(node_ids, dtype=np.int64)
    sysm = res._system
    if ids.size > _TRAILING_MIN_NODES and sysm is not None:
        cols = sysm.col[sysm.index_of(ids)]
        if (cols >= 0).all():
            if selinv.COMPILED:
                try:
                    return _selected_marginals(sysm, cols)
                except DegenerateGeometryError:  # not positive definite: the general path
                    pass
            elif not banded:
                try:
                    return trailing_factor(sysm.pattern, sysm.data, cols).marginal_blocks()
                except DegenerateGeometryError:  # not positive definite there: the general path
                    pass
    return res.covariance(ids)


def _selected_marginals(sysm, cols: IntArray) -> FloatArray:
    """Diagonal blocks of ``N^-1`` for the block columns ``cols`` of a solve's normal system by
    selected inversion on its factor (numeric factorisation at the solution, symbolic analysis
    reused and kept: after the in-place inversion the factor object is a valid symbolic one
    again, factored anew by the next solve that is handed it)."""
    chol = sysm.chol  # factored at the solution (the solve's analysis reused)
    sysm.take_factor()
    analysis = chol.analysis
    inv = selinv.SelectedInverse(chol, columns=cols)  # their supernodes and ancestors
    blocks = inv.diagonal_blocks(cols)
    if inv.in_place:  # CHOLMOD refactors a supernodal factor of the same pattern in place
        chol.keep_analysis(analysis)
        sysm.give_factor(chol)
    return blocks


@dataclass(frozen=True)
class _FreezePlan:
    """Everything freezing one leaving track changes, computed without changing the aligner
    (:meth:`TrackWindowAligner._plan_freeze`) and installed by
    :meth:`TrackWindowAligner._install_freeze`.

    Attributes
    ----------
    track : the leaving track.
    nodes : (k,) its node rows.
    cov_rows : (c,) rows whose marginal covariance is stored, ``cov`` (c, 6, 6) those blocks.
    absorbed : connection rows absorbed into the new prior (status 1 from now on).
    dropped : indices (into the aligner's list of priors) of the priors merged into it.
    prior : the new joint prior (``None``: no node kept, the absorbed terms vanish).
    """

    track: int
    nodes: IntArray
    cov_rows: IntArray
    cov: FloatArray
    absorbed: IntArray
    dropped: tuple[int, ...]
    prior: JointPrior | None


class _AheadFreeze:
    """The freeze of the next leaving track, computed in a background thread right after an
    update from the state that update left (:meth:`TrackWindowAligner._freeze_ahead`), with
    what it was computed from, so that the next update can check it still applies."""

    def __init__(self, track: int, res: SolveResult, window: IntArray, priors: list,
                 n_nodes: int, n_conns: int) -> None:
        self.track, self.res, self.window, self.priors = track, res, window, priors
        self.n_nodes, self.n_conns = n_nodes, n_conns
        self.plan: _FreezePlan | None = None
        self.cpu_ms = 0.0  # CPU time of the worker thread
        self.thread: threading.Thread | None = None

    def run(self, compute) -> None:
        """Compute the plan (BLAS limited by the process-wide limit :data:`_BLAS_LIMIT`: a
        ``blas_threads()`` context here would undo one of the caller's thread midway)."""
        c0 = time.thread_time()
        try:
            self.plan = compute(self.track, self.res, self.window, self.priors, self.n_nodes,
                                self.n_conns)
        except BaseException:  # noqa: BLE001
            # no plan: the update computes the freeze itself (and reports an error that recurs)
            pass
        self.cpu_ms = 1e3 * (time.thread_time() - c0)

    def wait(self) -> None:
        if self.thread is not None:
            self.thread.join()


@dataclass(frozen=True)
class _ConnectionTerms:
    """Per-connection terms of a window's connections that depend on the measurement only,
    kept from one update to the next (:meth:`TrackWindowAligner._connection_terms`)."""

    rows: IntArray  # (m,) sorted connection rows
    cov: FloatArray  # (m, 6, 6) S, unpacked from the connection table
    weights: FloatArray  # (m, 6, 6) S^-1
    T_meas: FloatArray  # (m, 4, 4) the measured motions T_src_dst
    T_meas_inv: FloatArray  # (m, 4, 4) their inverses


class JointPrior(tuple):
    """One joint prior as the aligner keeps it: ``(node rows (k,), T_mean (k, 4, 4),
    information (6k, 6k))``, unpacked as that 3-tuple (state files, the refinement's snapshot),
    with the rank of the information in ``rank`` when known (a prior positive definite by
    construction: ``6k``), so that no window solve factors the information again only to count
    its equations (``None``: determined once, on first use, :meth:`TrackWindowAligner._ranked`).
    """

    def __new__(cls, idx: IntArray, mean: FloatArray, info, rank: int | None = None
                ) -> JointPrior:
        out = super().__new__(cls, (idx, mean, info))
        out.rank = rank
        return out

    def __reduce__(self):
        return (JointPrior, (*self, self.rank))

    @classmethod
    def absorbed(cls, p: AbsorbedPrior, first_node: int = 0) -> JointPrior:
        """The aligner's prior of a refinement's :class:`~ga_ros.core.refinement.AbsorbedPrior`
        (node rows relative to the snapshot's ``first_node``), with its rank."""
        return cls(p.nodes + first_node, p.T_world_node, p.information, p.rank)


def _no_weighted() -> tuple[IntArray, FloatArray]:
    """No frozen node adjusted as a weighted parameter: ``(node rows (0,), poses (0, 4, 4))``
    (``TrackWindowAligner._T_weighted`` before any update and after a refinement)."""
    return np.zeros(0, np.int64), np.zeros((0, 4, 4))


def _carry_over(T_init: FloatArray, nodes: IntArray, prev_nodes: IntArray,
                T_prev: FloatArray) -> FloatArray:
    """``T_init`` (poses of ``nodes``) with the poses of the nodes that were also in the previous
    problem (``prev_nodes``, estimate ``T_prev``) taken from that estimate."""
    out = T_init.copy()
    if prev_nodes.size == 0 or nodes.size == 0:
        return out
    pos = np.full(int(max(nodes.max(), prev_nodes.max())) + 1, -1, dtype=np.int64)
    pos[prev_nodes] = np.arange(prev_nodes.size)
    k = pos[nodes]
    out[k >= 0] = T_prev[k[k >= 0]]
    return out


@dataclass
class _Rollback:
    """What :meth:`TrackWindowAligner.finish_track` puts back if an update fails: the rows an
    update can change (:meth:`TrackWindowAligner._mutable_rows`: of the window and the
    refinement horizon, not of the whole survey, so that the copy costs the same at every
    track) and the small bookkeeping around them."""

    node_row: int
    conn_row: int
    T: FloatArray
    cov21: FloatArray
    frozen: BoolArray
    status: IntArray
    bookkeeping: dict

    #: Attributes saved and restored as they are (replaced, never changed in place, by an update).
    KEPT = ('_priors', '_last_window', '_n_outliers', '_n_updates', '_T_weighted', '_retired',
            '_past')

    @classmethod
    def of(cls, al: TrackWindowAligner) -> _Rollback:
        """The aligner's mutable rows and bookkeeping, copied."""
        lo, r0 = al._mutable_rows()
        n = al._idarr.n
        book = {k: getattr(al, k) for k in cls.KEPT}
        book['_priors'] = list(al._priors)
        return cls(lo, r0, al._T[lo:n].copy(), al._cov.packed[lo:n].copy(),
                   al._frozen[lo:n].copy(), al._status.a[r0:].copy(), book)

    def restore(self, al: TrackWindowAligner) -> None:
        """Put the copied rows and bookkeeping back (rows added since are not touched)."""
        lo, r0 = self.node_row, self.conn_row
        hi = lo + self.frozen.size
        al._T[lo:hi] = self.T
        al._cov.packed[lo:hi] = self.cov21
        al._frozen[lo:hi] = self.frozen
        al._status.a[r0:r0 + self.status.size] = self.status
        for k, v in self.bookkeeping.items():
            setattr(al, k, v)

    @property
    def nbytes(self) -> int:
        """Bytes of the copied rows."""
        return self.T.nbytes + self.cov21.nbytes + self.frozen.nbytes + self.status.nbytes


class TrackWindowAligner:
    """Online sliding-window global alignment, fed one :class:`Measurement` at a time.

    Parameters
    ----------
    config : settings (window size, freezing policy, solver tolerances).
    T_world_first : pose of the first node (the datum), identity by default.
    """

    #: Size of the duplicate-key set below which it is never pruned (see :meth:`_prune_pairs`).
    _PAIRS_MIN = 4096

    def __init__(self, config: AlignerConfig | None = None,
                 T_world_first: FloatArray | None = None) -> None:
        self.config = config or AlignerConfig()
        self._T_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first, float)
        if self._T_first.shape != (4, 4) or not np.isfinite(self._T_first).all():
            raise InputError('T_world_first must be a finite 4x4 pose')
        # storage (ga_ros.core.storage: numpy tables, no Python object per node or connection)
        # nodes, by row index in arrival order; T, cov and frozen have spare capacity
        self._index = IdIndex()  # node id -> row
        self._idarr = _Rows((), np.int64)
        self._trackarr = _Rows((), np.int64)
        self._stamparr = _Rows((), np.int64)
        self._T = np.zeros((0, 4, 4))
        self._cov = SymArray()  # frozen nodes' marginal covariances, 21 values each
        self._frozen = np.zeros(0, dtype=bool)
        # connections (by node index); status 0 active, 1 absorbed into a prior, 2 outlier
        self._src = _Rows((), np.int64)
        self._dst = _Rows((), np.int64)
        self._z = _Rows((6,))
        self._ccov = SymRows()  # 21 values each; self._ccov.a[k] unpacks to 6x6
        self._cross = _Rows((), bool)
        self._status = _Rows((), np.int8)
        self._fp = _Rows((), np.uint32)  # third part of each connection's duplicate key
        # duplicate keys (low id, high id, fingerprint) of the connections between two nodes
        # that are not frozen (a measurement touching a frozen node is refused as such
        # first); rebuilt without the others as it grows (see _prune_pairs)
        self._pairs: set[tuple[int, int, int]] = set()
        self._pairs_kept = 0
        # tracks
        self._tracks: list[int] = []  # in order of appearance
        self._track_nodes = TrackRanges()  # track -> its rows (contiguous)
        self._track_conns = TrackLists()  # track -> rows of the connections touching it
        self._open_track: int | None = None
        self._finished: set[int] = set()
        # marginal-policy priors: list of (node indices, mean (k,4,4), information (6k, 6k))
        self._priors: list[JointPrior | tuple[IntArray, FloatArray, FloatArray]] = []
        self._last: SolveResult | None = None
        self._last_window: IntArray = np.zeros(0, dtype=np.int64)
        # the last adjustment's estimate of the frozen nodes it adjusted as weighted parameters
        # (node rows, (k, 4, 4)): where the next update starts them (their published pose,
        # self._T, stays the frozen one)
        self._T_weighted: tuple[IntArray, FloatArray] = _no_weighted()
        # weights S^-1 and measured motions of the last window's connections: an update
        # computes them only for the connections that entered the window since
        self._conn_terms = _ConnectionTerms(np.zeros(0, np.int64), np.zeros((0, 6, 6)),
                                            np.zeros((0, 6, 6)), np.zeros((0, 4, 4)),
                                            np.zeros((0, 4, 4)))
        self._rejected: dict[str, int] = {}
        self._n_updates = 0
        self._n_outliers = 0
        self._last_update: UpdateResult | None = None
        # background refinement (core.refinement): the worker, the snapshot it is solving
        self._refiner = RefinementWorker(self.config.refine_executor)
        self._refine_snap: RefinementSnapshot | None = None
        self._n_refinements = 0
        # bounded refinement: the first _retired finished tracks have left its horizon; _past
        # is the joint prior of their terms (node rows, mean, information) it starts from
        self._retired = 0
        self._past: list[tuple[IntArray, FloatArray, FloatArray]] = []
        # the next leaving track's freeze, computed in a background thread after an update
        # (freeze_ahead); the lock guards the last adjustment's factor, which its marginal
        # covariances share with covariances()
        self._ahead: _AheadFreeze | None = None
        self._factor_lock = threading.Lock()
        self._n_ahead = [0, 0]  # freezes installed from the background, recomputed at the end

    # ------------------------------------------------------------------------- input
    def add_measurement(self, m: Measurement) -> list[UpdateResult]:
        """Add one measurement; returns the updates it triggered (a track end), if any.

        Raises :class:`InputError` (and counts it by reason in :attr:`stats`) on a measurement the
        policy in the module docstring rejects; the state is then unchanged.
        """
        return self._add(m, None)

    def add_measurements(self, ms) -> BatchResult:
        """Add many measurements in order (a journal replay, a recorded survey): exactly what
        calling :meth:`add_measurement` on each would do, rejections included, but with the
        covariances validated together in one vectorised pass. Window updates run at track
        ends only, as they would live. Never raises for a rejected measurement: see the result.
        """
        ms = list(ms)
        sym = self._check_covariances_batch(ms)
        updates, rejected = [], {}
        for k, m in enumerate(ms):
            try:
                updates += self._add(m, None if sym is None or np.isnan(sym[k, 0, 0])
                                     else sym[k])
            except GaError as exc:
                reason = getattr(exc, 'reason', 'invalid')
                rejected[reason] = rejected.get(reason, 0) + 1
        n_rej = sum(rejected.values())
        return BatchResult(updates, len(ms) - n_rej, n_rej, rejected)

    def _check_covariances_batch(self, ms) -> FloatArray | None:
        """Symmetrised covariances of ``ms`` that pass every covariance check, NaN-filled rows
        for the others (checked again one by one, for the exact reason); ``None`` if the stack
        cannot be formed."""
        cfg = self.config
        try:
            cov = np.array([m.cov for m in ms], dtype=float).reshape(len(ms), 6, 6)
        except (TypeError, ValueError):
            return None
        with np.errstate(all='ignore'):
            amax = np.abs(cov).max(axis=(1, 2), initial=0.0)
            ok = np.isfinite(cov).all(axis=(1, 2)) & (amax <= cfg.cov_max_eigenvalue)
            ok &= (np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2), initial=0.0)
                   <= 1e-6 * np.maximum(amax, 1e-300))
            sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
            sym[~ok] = np.eye(6)
            ev = np.linalg.eigvalsh(sym)
            ok &= (ev[:, 0] > 1e-12 * np.maximum(amax, 1e-300))
            ok &= (ev[:, 0] >= cfg.cov_min_eigenvalue)
            ok &= (ev[:, -1] <= cfg.cov_max_condition * ev[:, 0])
        sym[~ok] = np.nan
        return sym

    def _add(self, m: Measurement, checked_cov: FloatArray | None) -> list[UpdateResult]:
        try:
            plan = self._check(m, checked_cov)
        except GaError as exc:
            reason = getattr(exc, 'reason', 'invalid')
            self._rejected[reason] = self._rejected.get(reason, 0) + 1
            raise
        except Exception as exc:  # noqa: BLE001 - whatever the input, only GaError escapes
            self._rejected['invalid'] = self._rejected.get('invalid', 0) + 1
            err = InputError(f'invalid measurement ({type(exc).__name__}: {exc})')
            err.reason = 'invalid'
            raise err from None
        updates = []
        if plan['ends_track']:
            up = self.finish_track()
            if up is not None:
                updates.append(up)
        self._apply(m, plan)
        return updates

    def _check(self, m: Measurement, checked_cov: FloatArray | None = None) -> dict:
        def bad(reason: str, text: str) -> InputError:
            err = InputError(text)
            err.reason = reason
            return err

        for name in ('src_id', 'dst_id', 'src_track', 'dst_track'):
            v = getattr(m, name)
            try:
                ok = int(v) == v and 0 <= int(v) < 2**63
            except (TypeError, ValueError, OverflowError):
                ok = False
            if not ok:
                raise bad('bad_id', f'{name} must be an integer in [0, 2**63), got {v!r}')
        src, dst = int(m.src_id), int(m.dst_id)
        try:
            ok = int(m.stamp_ns) == m.stamp_ns and -2**63 <= int(m.stamp_ns) < 2**63
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise bad('bad_stamp', f'stamp_ns must be an integer (ns), got {m.stamp_ns!r}')
        if m.kind not in KINDS:
            raise bad('bad_kind', f'kind must be one of {KINDS}, got {m.kind!r}')
        z = np.asarray(m.z, dtype=float).reshape(-1)
        cov = np.asarray(m.cov, dtype=float)
        if z.shape != (6,) or cov.shape != (6, 6):
            raise bad('bad_shape', 'a measurement needs z of 6 values and a 6x6 covariance')
        if not np.isfinite(z).all():
            raise bad('non_finite', f'measurement {src}->{dst} has NaN or inf values')
        if checked_cov is None:
            cov = self._check_covariance(cov, f'covariance of {src}->{dst}', bad)
        else:
            cov = checked_cov
        if src == dst:
            raise bad('self_loop', f'measurement from node {src} to itself')
        index, tracks = self._index, self._trackarr.a
        i_src, i_dst = index.get(src), index.get(dst)
        if i_src is not None and int(m.src_track) != tracks[i_src]:
            raise bad('track_mismatch', f'node {src} belongs to track '
                      f'{tracks[i_src]}, not {m.src_track}')
        if i_dst is not None and int(m.dst_track) != tracks[i_dst]:
            raise bad('track_mismatch', f'node {dst} belongs to track '
                      f'{tracks[i_dst]}, not {m.dst_track}')
        first = self._idarr.n == 0
        if not first and i_src is None:
            raise bad('unknown_source', f'source node {src} is unknown: every measurement must '
                      'start at a node that an earlier measurement introduced')
        for node, k in ((src, i_src), (dst, i_dst)):
            if k is not None and self._frozen[k]:
                raise bad('frozen', f'node {node} belongs to a frozen track (outside the window '
                          f'of {self.config.window_tracks} tracks)')
        ends_track = False
        new_nodes = ([src] if first and i_src is None else []) + ([dst] if i_dst is None else [])
        for node in new_nodes:
            track = int(m.dst_track) if node == dst else int(m.src_track)
            if track in self._finished:
                raise bad('out_of_order', f'new node {node} of track {track} is out of order: '
                          'that track has finished')
            if self._open_track is not None and track != self._open_track:
                if track in self._track_nodes or track < self._open_track:
                    raise bad('out_of_order', f'new node {node} of track {track} arrives after '
                              f'track {self._open_track} began (out of order)')
                ends_track = True
        self._check_jumps(m, new_nodes, bad)
        key = (min(src, dst), max(src, dst), zlib.crc32(z.tobytes() + cov.tobytes()))
        if key in self._pairs:
            raise bad('duplicate', f'measurement {src}->{dst} was already received')
        return {'src': src, 'dst': dst, 'z': z, 'cov': cov, 'first': first,
                'ends_track': ends_track, 'key': key, 'rows': (i_src, i_dst)}

    def _check_covariance(self, cov: FloatArray, what: str, bad) -> FloatArray:
        """Finite, symmetric, positive definite, and within the configured eigenvalue range and
        condition number (``bad_covariance`` otherwise); returns the symmetrised matrix."""
        sym = self._covariance_within_limits(cov)
        if sym is not None:
            return sym
        cfg = self.config
        if not np.isfinite(cov).all():
            raise bad('bad_covariance', f'{what} has NaN or inf entries')
        if np.abs(cov).max() > cfg.cov_max_eigenvalue:  # >= one eigenvalue that large
            raise bad('bad_covariance', f'{what} has entries up to {np.abs(cov).max():.3g}, above '
                      f'cov_max_eigenvalue {cfg.cov_max_eigenvalue:.3g} (a placeholder for '
                      '"unknown"?); send a real covariance or raise the limit')
        try:
            cov = check_covariances(cov[None], what=what)[0]
        except InputError as exc:
            raise bad('bad_covariance', str(exc)) from None
        ev = np.linalg.eigvalsh(cov)
        if ev[0] < cfg.cov_min_eigenvalue:
            raise bad('bad_covariance', f'{what} has an eigenvalue {ev[0]:.3g} below '
                      f'cov_min_eigenvalue {cfg.cov_min_eigenvalue:.3g}: too small to be '
                      'solved with; check the units or raise the limit')
        if ev[-1] > cfg.cov_max_condition * ev[0]:
            raise bad('bad_covariance', f'{what} has condition number {ev[-1] / ev[0]:.3g}, '
                      f'above cov_max_condition {cfg.cov_max_condition:.3g}')
        return cov

    def _covariance_within_limits(self, cov: FloatArray) -> FloatArray | None:
        """The symmetrised 6x6 covariance if it passes every check of
        :meth:`_check_covariance` with a margin, decided by one Cholesky attempt (a few
        microseconds, against two eigen-decompositions); ``None`` when undecided (the exact
        checks then run and name the reason).

        ``sym - c I`` positive definite means ``eig_min(sym) > c``; with ``c`` the largest of
        the three lower bounds on ``eig_min`` (``1e-12`` of the largest entry,
        ``cov_min_eigenvalue``, and ``6 max|entry| / cov_max_condition``, since ``eig_max`` is
        at most 6 times the largest entry), slightly raised against round-off, every test
        passes.
        """
        cfg = self.config
        amax = abs(cov).max()
        if not amax <= cfg.cov_max_eigenvalue:  # also NaN or inf
            return None
        if not abs(cov - cov.T).max() <= 1e-6 * max(amax, 1e-300):
            return None
        sym = 0.5 * (cov + cov.T)
        # eig_max <= 6 max |entry| bounds the condition number as the trace would
        shift = max(1e-12 * amax, cfg.cov_min_eigenvalue, 6.0 * amax / cfg.cov_max_condition)
        _, info = _potrf(sym - (shift * (1.0 + 1e-9) + 1e-13 * amax) * _EYE6)
        return sym if info == 0 else None

    def _check_jumps(self, m: Measurement, new_nodes: list[int], bad) -> None:
        """New node and track ids must be within the configured jump of the largest seen."""
        cfg = self.config
        max_id, max_track = self._seen_max()
        ref_id = max(max_id, int(m.src_id))
        for node in new_nodes:
            if cfg.max_node_id_jump and node - ref_id > cfg.max_node_id_jump:
                raise bad('id_jump', f'new node id {node} is {node - ref_id} above the largest '
                          f'seen ({ref_id}); max_node_id_jump is {cfg.max_node_id_jump}')
        ref_track = max_track if max_track >= 0 else int(m.src_track)
        for track in {int(m.src_track), int(m.dst_track)}:
            if cfg.max_track_jump and track - ref_track > cfg.max_track_jump:
                raise bad('track_jump', f'track id {track} is {track - ref_track} above the '
                          f'largest seen ({ref_track}); max_track_jump is {cfg.max_track_jump}')

    def _seen_max(self) -> tuple[int, int]:
        """Largest node id and track id seen so far (-1 before the first measurement); kept
        up to date incrementally."""
        n = self._idarr.n
        done, max_id, max_track = getattr(self, '_seen_cache', (0, -1, -1))
        if done != n:
            if done > n:
                done, max_id, max_track = 0, -1, -1
            max_id = max(max_id, int(self._idarr.a[done:].max()))
            max_track = max(max_track, int(self._trackarr.a[done:].max()))
            self._seen_cache = (n, max_id, max_track)
        return max_id, max_track

    def _apply(self, m: Measurement, plan: dict) -> None:
        src, dst = plan['src'], plan['dst']
        i, j = plan['rows']  # None: a new node (finish_track, run between, adds none)
        if plan['first']:
            i = self._add_node(src, int(m.src_track), int(m.stamp_ns), self._T_first)
        if j is None:
            T_src = self._T[i]
            T_meas = se3.from_translation_rotvec(plan['z'][:3], plan['z'][3:])
            j = self._add_node(dst, int(m.dst_track), int(m.stamp_ns), T_src @ T_meas)
        k = self._src.append(i)
        self._dst.append(j)
        self._z.append(plan['z'])
        self._ccov.append(plan['cov'])
        self._cross.append(m.kind == 'cross')  # a bridge is a (predicted) motion
        self._status.append(0)
        self._fp.append(plan['key'][2])
        self._track_conns.add({int(self._track[i]), int(self._track[j])}, k)
        self._pairs.add(plan['key'])
        if len(self._pairs) > max(self._PAIRS_MIN, 2 * self._pairs_kept):
            self._prune_pairs()

    def _prune_pairs(self) -> None:
        """Keep only the duplicate keys of connections whose two nodes are not frozen (a
        measurement that touches a frozen node is refused before the duplicate test). Such
        connections come after the first connection that can touch the first unfrozen node
        (:meth:`_rows_from`): only those rows are scanned."""
        _, r0 = self._rows_from(self._first_unfrozen())
        frozen = self._frozen[:self._idarr.n]
        src, dst = self._src.a[r0:], self._dst.a[r0:]
        live = r0 + np.flatnonzero(~frozen[src] & ~frozen[dst])
        ids = self._idarr.a
        a, b = ids[self._src.a[live]], ids[self._dst.a[live]]
        self._pairs = set(zip(np.minimum(a, b).tolist(), np.maximum(a, b).tolist(),
                              self._fp.a[live].tolist()))
        self._pairs_kept = len(self._pairs)

    def _add_node(self, node_id: int, track: int, stamp_ns: int, T: FloatArray) -> int:
        """Store a new node; returns its row."""
        k = self._idarr.append(node_id)
        self._trackarr.append(track)
        self._stamparr.append(stamp_ns)
        self._index.add(node_id, k)
        if k >= self._T.shape[0]:  # amortised growth; the spare rows stay untouched
            self._T = grow_rows(self._T, k + 1)
            self._cov.grow(self._T.shape[0])
            self._frozen = grow_rows(self._frozen, self._T.shape[0])
        self._T[k] = T
        self._cov[k] = 0.0
        self._frozen[k] = False
        if track not in self._track_nodes:
            self._tracks.append(track)
        self._track_nodes.add(track, k)
        self._open_track = track
        return k

    @property
    def _ids(self) -> IntArray:
        """Node ids by row (a view of the storage)."""
        return self._idarr.a

    @property
    def _track(self) -> IntArray:
        """Track id of each node row (a view of the storage)."""
        return self._trackarr.a

    @property
    def _stamp(self) -> IntArray:
        """Stamp (ns) of each node row (a view of the storage)."""
        return self._stamparr.a

    def finish_track(self) -> UpdateResult | None:
        """End the open track and adjust the window (returns ``None`` if there is no open
        track).

        If the update fails for any reason (a solver failure, a numerical error while freezing),
        every estimate (poses, covariances, frozen flags, connection status, priors) is put back
        as it was before the call, the track stays finished (the next update retries it inside
        its window) and the returned result's ``reason`` starts with ``'failed'``. Only
        :class:`~ga_ros.errors.GaError` can escape."""
        if self._open_track is None or self._open_track in self._finished:
            return None
        last = {k: self.__dict__[k] for k in ('_last_result', '_last_pending')
                if k in self.__dict__}      # as stored: a pending recomputation stays pending
        saved = _Rollback.of(self)
        track, t0 = self._open_track, time.perf_counter()
        try:
            up = self._finish_track()
            if not str(up.reason).startswith('failed'):
                self._start_refinement()
                self._freeze_ahead()
                return up
            error = up.reason[len('failed: '):]
        except Exception as exc:  # noqa: BLE001 - a failed update must not end the survey
            error = f'{type(exc).__name__}: {exc}'
        saved.restore(self)
        self._last = None
        self.__dict__.update(last)
        self.__dict__.pop('_smoothing', None)  # of a refinement installed by the failed update
        self._finished.add(track)
        self._n_updates += 1
        up = UpdateResult(track, 0, False, float('nan'), 1e3 * (time.perf_counter() - t0), 0, 0,
                          min(len(self._finished), self.config.window_tracks), 0,
                          f'failed: {error}')
        self._last_update = up
        return up

    def _mutable_rows(self) -> tuple[int, int]:
        """``(node row, connection row)`` from which a window update can change the tables.

        An update changes the poses, covariances and frozen flags of the unfrozen tracks
        (window and leaving tracks: the adjustment, the freezes) and of the horizon of the
        refinement it may install (:meth:`_install`, :meth:`_smooth`: rows from the snapshot's
        ``first_node``), and the status of connections touching those nodes (gate,
        re-admission, absorption): the rows from the first unfrozen node, or from the
        snapshot's first node if lower (:meth:`_rows_from`). Everything before stays as it is
        (retired and long-frozen tracks), whatever the survey's length (tested in
        ``test/test_window_scale.py``)."""
        lo, snap = self._first_unfrozen(), self._refine_snap
        return self._rows_from(lo if snap is None else min(lo, int(snap.first_node)))

    def _first_unfrozen(self) -> int:
        """Row of the first node that is not frozen (the node count if every one is)."""
        n = self._idarr.n
        frozen = self._frozen[:n]
        lo = int(np.argmin(frozen)) if n else 0  # the first False (a scan, no copy)
        return n if n and frozen[lo] else lo

    def _rows_from(self, lo: int) -> tuple[int, int]:
        """``(lo, r0)``: node row ``lo`` (clipped to the node count) and the first connection
        row that can touch a node ``>= lo``. Node rows follow creation order and a track's rows
        are contiguous; a connection is stored after both its nodes, so every connection
        touching a node ``>= lo`` comes at or after the first connection of ``lo``'s track."""
        n = self._idarr.n
        if lo >= n:
            return n, self._src.n
        first = self._track_conns.get(int(self._trackarr.a[lo]))
        return lo, (int(first[0]) if first is not None and len(first) else 0)

    # ------------------------------------------------------------ background refinement
    def _start_refinement(self) -> None:
        """Hand a snapshot to the refinement worker after every ``refine_every_tracks``-th
        track (once a track will be frozen at the hand-off; one refinement in flight at most);
        it is installed in the update of the track ``refine_lag_tracks`` later, after that
        update's freezes (:meth:`_install_due`)."""
        cfg = self.config
        n_done = len(self._finished)
        n = len(self._ids)
        if (cfg.refine_every_tracks <= 0 or n_done % cfg.refine_every_tracks
                or self._refiner.pending_due is not None
                or self._open_track not in self._finished):
            return
        due = n_done + cfg.refine_lag_tracks
        order = [t for t in self._tracks if t in self._finished]
        leaving = tuple(int(t) for t in order[:max(0, due - cfg.window_tracks)]
                        if not self._frozen[self._track_nodes[t][0]])
        if not leaving and not self._frozen[:n].any():
            return  # nothing will be frozen at the hand-off: the window is the batch solution
        self._refine_snap = replace(self._snapshot(), leaving=leaving)
        self._refine_updates = self._n_updates
        self._refiner.submit(self._refine_snap, due)

    def _snapshot(self, n_nodes: int | None = None, n_conns: int | None = None,
                  whole: bool = False) -> RefinementSnapshot:
        """Copy of the data a refinement needs: the horizon's nodes (every one whose track has
        not been retired, or all of them if ``whole``), the connections between them and the
        past prior; only the first ``n_nodes`` nodes and ``n_conns`` connections (default all:
        a restored aligner's pending refinement saw fewer)."""
        n = len(self._ids) if n_nodes is None else int(n_nodes)
        m = len(self._src) if n_conns is None else int(n_conns)
        cfg = self.config
        scfg = cfg.solver_config()
        order = [t for t in self._tracks if t in self._finished
                 and self._track_nodes[t][0] < n]
        retired = 0 if whole else min(self._retired, len(order))
        f, rows, past = 0, None, ()
        if retired:
            f = int(self._track_nodes[order[retired]][0])
            rows = self._horizon_rows(f, m)
            past = tuple(AbsorbedPrior(idx - f, mean, info) for idx, mean, info in self._past)
        sel = slice(0, m) if rows is None else rows
        # a slice is a view, to be copied; a row array (fancy indexing) gives a copy already
        take = (lambda a: a[sel].copy()) if rows is None else (lambda a: a[sel])
        horizon = int(cfg.refine_horizon_tracks)
        return RefinementSnapshot(
            after_tracks=len(order), node_ids=self._idarr.a[f:n].copy(),
            track_ids=self._trackarr.a[f:n].copy(), T_world_node=self._T[f:n].copy(),
            frozen=self._frozen[f:n].copy(), track_order=tuple(int(t) for t in order[retired:]),
            src=self._src.a[sel] - f, dst=self._dst.a[sel] - f, z=take(self._z.a),
            cov21=take(self._ccov.packed), status=take(self._status.a),
            freeze_policy=cfg.freeze_policy,
            solver=replace(scfg, max_iterations=max(20, scfg.max_iterations)),
            prior_band=int(cfg.prior_band), prior_hubs=int(cfg.prior_hubs), first_node=f,
            past=past, retire_max=max(0, len(order) - retired - horizon) if horizon else 0,
            conn_rows=rows, connections_total=m)

    def _horizon_rows(self, f: int, m: int | None = None) -> IntArray:
        """Rows of the connections between nodes ``>= f`` among the first ``m`` (default all),
        sorted.

        A connection is stored after both its nodes, and node rows follow creation order, so
        every such connection comes at or after the one that created node ``f``, hence at or
        after the first connection of ``f``'s track: only the rows from there are scanned (of
        the horizon's size, whatever the survey's length; a gather of the horizon tracks'
        connection lists took ~20 ms per call at a horizon of 30 tracks of 200 poses)."""
        m = self._src.n if m is None else int(m)
        if f >= self._idarr.n:
            return np.zeros(0, dtype=np.int64)
        r0 = min(self._rows_from(f)[1], m)
        ends = (self._src.a[r0:m] >= f) & (self._dst.a[r0:m] >= f)
        return r0 + np.flatnonzero(ends)

    def _install_due(self) -> tuple[int, str, float] | None:
        """Install the refinement due at this update (waiting for it); returns ``(after_tracks,
        reason, wait + install ms)`` or ``None`` if none was due. A failed refinement, or one
        that cannot be installed, leaves the state as it was."""
        t0 = time.perf_counter()
        res = self._refiner.take(len(self._finished))
        if res is None:
            return None
        snap, self._refine_snap = self._refine_snap, None
        reason = res.reason
        if res.ok and snap is not None:
            try:
                with blas_threads():
                    self._install(snap, res)
                self._n_refinements += 1
            except (GaError, np.linalg.LinAlgError, ValueError) as exc:
                reason = f'not installed: {type(exc).__name__}: {exc}'
        elif not reason.startswith('failed'):
            reason = f'failed: {reason}'
        return res.after_tracks, reason, 1e3 * (time.perf_counter() - t0)

    def _install(self, snap: RefinementSnapshot, res: RefinementResult) -> None:
        """The refined estimate becomes the frozen one (after this update's freezes, before its
        window adjustment).

        The result was computed for the state predicted at this point
        (:func:`~ga_ros.core.refinement.predict_freezes`); if the frozen nodes or the absorbed
        connections differ, nothing is installed. Otherwise the frozen nodes take the refined
        poses and covariances and the joint priors are the rebuilt ones (relinearised at the
        refined estimate, each absorbed connection in exactly one). If no update ran since the
        snapshot (``refine_lag_tracks = 1``) the window nodes also start from the refined poses.
        After the adjustment :meth:`_smooth` carries the window's correction of the prior nodes
        back to every frozen node.
        """
        f, n_s = snap.first_node, snap.node_ids.size
        n = len(self._ids)
        rows = (np.arange(snap.src.size) if snap.conn_rows is None else snap.conn_rows)
        # the horizon's connections now: the snapshot's and those that arrived since
        now = np.arange(len(self._src)) if f == 0 else self._horizon_rows(f)
        status = self._status.a[now]
        predicted = np.zeros(now.size, dtype=bool)
        predicted[np.searchsorted(now, rows[res.absorbed])] = True
        if (not np.array_equal(self._frozen[f:f + n_s], res.frozen)
                or self._frozen[f + n_s:n].any() or not np.array_equal(status == 1, predicted)):
            raise InputError('the frozen nodes or absorbed connections changed since the '
                             'snapshot')
        past = np.concatenate([p.nodes for p in snap.past] or [np.zeros(0, np.int64)])
        need = prior_nodes(self._frozen[f:n], self._src.a[now] - f, self._dst.a[now] - f,
                           status, self.config.freeze_policy, past, f == 0)
        have = np.zeros(n - f, dtype=bool)
        for p in res.priors:
            have[p.nodes] = True
        if (need & ~have).any():
            raise InputError('a node eliminated by the refinement has a connection to the window '
                             'that arrived after the snapshot (refine_lag_tracks too large for '
                             'this survey)')
        frozen = np.nonzero(res.frozen)[0]
        if self._n_updates == getattr(self, '_refine_updates', -1):
            # the newer nodes (the track being finished) follow the last snapshot node rigidly:
            # their frame-to-frame chain starts there
            last = f + n_s - 1
            move = res.T_world_node[n_s - 1] @ se3.inverse(self._T[last])
            self._T[last + 1:n] = move @ self._T[last + 1:n]
            self._T[f:f + n_s] = res.T_world_node
        else:
            self._T[f + frozen] = res.T_world_node[frozen]
        self._cov[f + frozen] = res.frozen_cov
        self._priors = [JointPrior.absorbed(p, f) for p in res.priors]
        self._T_weighted = _no_weighted()  # refined instead
        self._smoothing = (res, f)
        # bounded refinement: the tracks it retired leave the horizon, with their prior
        self._retired += res.retired
        self._past = [JointPrior.absorbed(p, f) for p in res.past]

    def _smooth(self) -> str | None:
        """Carry the window's correction of the prior nodes back to every frozen node of the
        installed refinement's horizon.

        The installed refinement kept the back substitution of its eliminations
        (:class:`~ga_ros.core.refinement.SmoothingStep`); the window adjustment just moved the
        prior nodes from the refined estimate ``T_r`` by ``d_S = log(T_r^-1 T)``; each frozen node
        then moves to its conditional mean ``T_r exp(d)`` under the absorbed connections (the
        batch solution of all data received, in the linear limit; of the horizon's data and the
        past prior under a bounded refinement). A process worker applies the steps it kept
        (:meth:`~ga_ros.core.refinement.RefinementWorker.smooth`); returns why the smoothing
        could not be done (that worker died), else ``None``.
        """
        refined, f = self.__dict__.pop('_smoothing', (None, 0))
        res = self._last
        if refined is None or res is None:
            return None
        T_lin = refined.T_world_node
        where = {int(i): k for k, i in enumerate(res.node_ids.tolist())}
        idx = np.unique(np.concatenate([p[0] for p in self._priors]
                                       or [np.zeros(0, np.int64)]))
        k = np.array([where.get(int(i), -1) for i in self._ids[idx].tolist()], dtype=np.int64)
        idx, k = idx[k >= 0], k[k >= 0]
        d_idx = se3.local(T_lin[idx - f], res.T_world_node[k])  # one batched call
        try:
            nodes, d = self._refiner.smooth(refined, idx - f, d_idx)
        except InputError as exc:  # the worker died: the refined poses stand, unsmoothed
            return str(exc)
        sel = self._frozen[f + nodes] & ((nodes > 0) | (f > 0))  # the datum stays
        nodes, d = nodes[sel], d[sel]
        if nodes.size:
            self._T[f + nodes] = T_lin[nodes] @ se3.exp(d)
        return None

    def refinement_state(self) -> dict | None:
        """What a snapshot file needs to restart the pending refinement exactly: its hand-off
        track count, and the number of nodes and connections its snapshot held (the state is
        that of the last update plus the measurements received since). ``None`` if there is
        none, or if an update ran since its snapshot (``refine_lag_tracks > 1``: a restored
        aligner then starts the next refinement at its next trigger)."""
        snap, due = self._refine_snap, self._refiner.pending_due
        if snap is None or due is None or self._n_updates != getattr(self, '_refine_updates', -1):
            return None
        return {'due': int(due), 'nodes': int(snap.first_node + snap.node_ids.size),
                'connections': int(snap.connections_total),
                'leaving': [int(t) for t in snap.leaving]}

    def resume_refinement(self, state: dict | None) -> None:
        """Restart the refinement described by :meth:`refinement_state` (a restored aligner),
        from the same data, so the path continues as without the interruption."""
        if not state or self.config.refine_every_tracks <= 0:
            return
        self._refine_snap = replace(self._snapshot(int(state['nodes']),
                                                   int(state['connections'])),
                                    leaving=tuple(int(t) for t in state['leaving']))
        self._refine_updates = self._n_updates
        self._refiner.drop()
        self._refiner.submit(self._refine_snap, int(state['due']))

    def close(self) -> None:
        """Stop the background refinement (a pending result is dropped) and wait for a freeze
        being computed ahead (kept); the aligner stays usable (a later refinement starts a new
        worker)."""
        self._refiner.close()
        self.wait_background()

    # ---------------------------------------------------------- freezing ahead of time
    def wait_background(self) -> float:
        """Wait until the freeze being computed ahead (``freeze_ahead``) is ready; returns the
        CPU milliseconds it took (0 if none). Never needed for correctness: the next update
        waits for it anyway. A replay calls it to model the time a live survey has between
        track ends."""
        job = self._ahead
        if job is None:
            return 0.0
        job.wait()
        return job.cpu_ms

    def _freeze_ahead(self) -> None:
        """After a successful update: start computing the freeze of the track that the next
        update will freeze (the oldest of a full window), in a background thread. It reads the
        state this update left; :meth:`_ahead_plan` checks at the next update that nothing it
        depends on changed meanwhile."""
        self._drop_ahead()
        if not self.config.freeze_ahead:
            return
        finished = [t for t in self._tracks if t in self._finished]
        K = self.config.window_tracks
        res = self._last
        if len(finished) < K or res is None:
            return
        track = finished[-K]
        rows = self._track_nodes[track]
        if self._frozen[rows[0]]:
            return
        job = _AheadFreeze(track, res, self._last_window, list(self._priors), len(self._ids),
                           self._src.n)
        global _BLAS_LIMIT
        if _BLAS_LIMIT is None:  # from now on (set here, outside any blas_threads() context)
            _BLAS_LIMIT = limit_blas_threads()
        job.thread = threading.Thread(target=job.run, args=(self._plan_freeze,), daemon=True,
                                      name=f'ga_ros-freeze-track-{track}')
        self._ahead = job
        job.thread.start()

    def _drop_ahead(self) -> None:
        """Forget the freeze computed ahead (after waiting for its thread: it may be using the
        last adjustment's factor)."""
        job, self._ahead = self._ahead, None
        if job is not None:
            job.wait()

    def _ahead_plan(self, track: int) -> _FreezePlan | None:
        """The freeze of ``track`` computed ahead, if it was and still applies: same last
        adjustment and priors, and no connection added since touches the track (the nodes and
        connections added since are outside what it read). ``None``: compute it now."""
        job, self._ahead = self._ahead, None
        if job is None:
            return None
        job.wait()
        plan = job.plan
        valid = (plan is not None and job.track == track and job.res is self.__dict__.get(
            '_last_result') and '_last_pending' not in self.__dict__
                 and job.window is self._last_window and len(job.priors) == len(self._priors)
                 and all(a[0] is b[0] for a, b in zip(job.priors, self._priors)))
        if valid:
            nc = job.n_conns
            mine = np.zeros(len(self._ids), dtype=bool)
            mine[plan.nodes] = True
            valid = not (mine[self._src.a[nc:]] | mine[self._dst.a[nc:]]).any()
        self._n_ahead[0 if valid else 1] += 1
        return plan if valid else None

    # ----------------------------------------------------------------------- updates
    def _finish_track(self) -> UpdateResult | None:
        """End the open track and adjust the window (returns ``None`` if there is no open
        track). On a solver failure the previous estimate stands and the result says why."""
        if self._open_track is None or self._open_track in self._finished:
            return None
        t0 = time.perf_counter()  # the update's time includes waiting for a freeze ahead
        self.wait_background()  # before the BLAS limit below (a process-wide setting)
        with blas_threads():  # small dense blocks: threads only spin (ga_ros.runtime)
            return self._update(t0)

    def _update(self, t0: float | None = None) -> UpdateResult:
        track = self._open_track
        self._finished.add(track)
        t0 = time.perf_counter() if t0 is None else t0
        finished = [t for t in self._tracks if t in self._finished]
        window = finished[-self.config.window_tracks:]
        leaving = [t for t in finished[:-self.config.window_tracks]
                   if not self._frozen[self._track_nodes[t][0]]]
        for t in leaving:
            self._freeze(t)
        refined = self._install_due()  # background refinement due now (replaces the priors)
        try:
            up = self._adjust(window, track, t0)
            if refined is not None and not str(up.reason).startswith('failed'):
                error = self._smooth()
                (up.refined_after_tracks, up.refine_reason, up.refine_wait_ms) = refined
                if error:
                    up.refine_reason += f'; not smoothed: {error}'
        except GaError as exc:
            up = UpdateResult(track, 0, False, float('nan'), 1e3 * (time.perf_counter() - t0),
                              0, 0, len(window), 0, f'failed: {exc}')
        self._n_updates += 1
        self._last_update = up
        return up

    def _track_connections(self, tracks: list[int]) -> IntArray:
        """Sorted rows of the connections that touch any of ``tracks``."""
        none = np.zeros(0, dtype=np.int64)
        return np.unique(np.concatenate([np.asarray(self._track_conns.get(t, none), np.int64)
                                         for t in tracks] or [none]))

    def _window_problem(self, window_tracks: list[int]):
        win_nodes = np.sort(np.concatenate([self._track_nodes[t] for t in window_tracks]
                                           or [np.zeros(0, dtype=np.int64)]))
        in_win = np.zeros(len(self._ids), dtype=bool)
        in_win[win_nodes] = True
        conns = self._track_connections(window_tracks)
        conns = conns[self._status.a[conns] == 0]
        # nodes of a track still open (after a reload) are not part of this adjustment
        known = in_win | self._frozen[:len(self._ids)]
        conns = conns[known[self._src.a[conns]] & known[self._dst.a[conns]]]
        src, dst = self._src.a[conns], self._dst.a[conns]
        ids = self._idarr.a
        ext = np.unique(np.concatenate([src[~in_win[src]], dst[~in_win[dst]]]))
        # joint priors (Schur complements of frozen terms) touching the window or its frozen
        # neighbours; under the weighted policy their nodes are frozen boundary nodes
        priors_idx = []
        touched = in_win.copy()
        touched[ext] = True
        for p, (idx, _, _) in enumerate(self._priors):
            if touched[idx].any():
                priors_idx.append(p)
                ext = np.union1d(ext, idx[~in_win[idx]])
        nodes = np.concatenate([win_nodes, ext])
        net = self._subnetwork(nodes, conns, self._connection_terms(conns).cov)
        fixed = [self._ids[0]] if (nodes == 0).any() else []
        priors = []
        # Frozen nodes touched by window connections are weighted parameters (Sec. III-E): they
        # stay unknowns of the adjustment, with a joint prior that carries only the information
        # of the connections absorbed when they froze (see :meth:`_marginalise`), so nothing
        # is counted twice; they are not written back. A frozen node outside every joint prior
        # (a state saved by an older version) falls back to its marginal covariance.
        covered = np.concatenate([self._priors[p][0] for p in priors_idx]
                                 or [np.zeros(0, np.int64)])
        weighted = ext[(ext != 0) & ~np.isin(ext, covered)]
        if weighted.size:
            priors.append(GaussianPrior.from_covariances(ids[weighted], self._T[weighted],
                                                         self._cov[weighted]))
        for p in priors_idx:
            idx, mean, info = prior = self._ranked(p)
            priors.append(GaussianPrior(ids[idx], mean, info, rank=prior.rank))
        return net, nodes, win_nodes, conns, fixed, priors

    def _ranked(self, p: int) -> JointPrior:
        """Prior ``p`` with its rank (determined here once if it came without one: a state
        file, a dense prior)."""
        prior = self._priors[p]
        if getattr(prior, 'rank', None) is None:
            prior = self._priors[p] = JointPrior(*prior, rank=information_rank(prior[2], 6))
        return prior

    def _subnetwork(self, nodes: IntArray, conns: IntArray,
                    cov: FloatArray | None = None) -> ConnectionNetwork:
        """Network of some nodes (by index, distinct) and connections among them (already
        validated); ``cov``: the connections' (m, 6, 6) covariances if the caller has them
        unpacked. The connections' ends are located by a binary search among ``nodes`` (no
        index array over all the survey's nodes)."""
        order = np.argsort(nodes, kind='stable')
        srt = nodes[order]

        def local(rows: IntArray) -> IntArray:
            return order[np.searchsorted(srt, rows)]

        return ConnectionNetwork.from_arrays(
            self._idarr.a[nodes], self._trackarr.a[nodes],
            local(self._src.a[conns]), local(self._dst.a[conns]), self._z.a[conns],
            self._ccov.a[conns] if cov is None else cov)

    def _adjust(self, window_tracks: list[int], track: int, t0: float) -> UpdateResult:
        cfg = self.config
        scfg = cfg.solver_config()
        n_out = 0
        readmitted: set[int] = set()
        # the sequential update (paper Sec. III-D): start from the previous estimate, at its
        # optimum for the old connections (window nodes and the frozen nodes it adjusted as
        # weighted parameters), the new track from its chained consecutive motions
        res, (prev_nodes, T_prev) = None, self._T_weighted
        while True:
            net, nodes, win_nodes, conns, fixed, priors = self._window_problem(window_tracks)
            # (after the gate changed the problem: from the current estimate)
            T_init = _carry_over(self._T[nodes], nodes, prev_nodes, T_prev)
            terms = self._connection_terms(conns)
            weights, measured = terms.weights, (terms.T_meas, terms.T_meas_inv)
            if res is None:
                # the nodes no adjustment has seen yet (the new track's dead-reckoned chain)
                # first at their optimum given the others (prealign, paper Sec. III-D)
                fresh = np.nonzero(~np.isin(win_nodes, self._last_window))[0]
                if 0 < fresh.size < win_nodes.size:
                    pre = prealign(net, T_init, fresh, weights=weights, jit=True,
                                   factor=self.__dict__.pop('_prealign_factor', None),
                                   measured=measured)
                    T_init = pre.T_world_node
                    self.__dict__['_prealign_factor'] = pre.factor  # the next track's
            # the factor of the last solve (its symbolic analysis): same pattern as a rule
            donor = res if res is not None else self.__dict__.get('_last_result')
            res = solve(net, T_init, scfg, fixed=fixed, priors=priors, jit=True,
                        weights=weights, measured=measured,
                        factor_at_solution=not scfg.cost_tolerance > 0,
                        factor=donor.release_factor() if donor is not None else None)
            prev_nodes, T_prev = nodes, res.T_world_node
            bad = self._outliers(res, conns, net, priors)
            if bad.size == 0:
                back = self._readmissible(window_tracks, nodes, res, readmitted)
                if back.size == 0:
                    break
                self._status.a[back] = 0  # consistent now: back into the adjustment
                readmitted.update(back.tolist())
                continue
            if n_out >= 50:
                break
            self._status.a[bad] = 2
            n_out += int(bad.size)
        n_win = win_nodes.size
        self._T[win_nodes] = res.T_world_node[:n_win]
        self._T_weighted = (nodes[n_win:].copy(), res.T_world_node[n_win:].copy())
        self._last = res
        self._last_window = win_nodes
        self._n_outliers += n_out - len(readmitted)
        return UpdateResult(
            track_id=track, iterations=res.iterations, converged=res.converged,
            sigma0_sq=res.sigma0_sq, update_ms=1e3 * (time.perf_counter() - t0),
            n_window_nodes=int(n_win), n_window_connections=int(conns.size),
            n_tracks_in_window=len(window_tracks), n_outliers=n_out, reason=res.reason,
            n_priors=len(priors), n_unknowns=res.n_unknowns, n_readmitted=len(readmitted),
            quality=self._quality_summary(net, res, priors, conns))

    def _connection_terms(self, conns: IntArray) -> _ConnectionTerms:
        """The covariances, weights and measured motions of connections (sorted rows), those
        of the last call reused (a window keeps most of its connections from one update to the
        next)."""
        kept = self._conn_terms
        if conns is kept.rows:  # the same rows again (the gate after the adjustment)
            return kept
        pos = np.searchsorted(kept.rows, conns)
        hit = pos < kept.rows.size
        hit[hit] = kept.rows[pos[hit]] == conns[hit]
        at = pos[hit]
        out = _ConnectionTerms(conns, np.empty((conns.size, 6, 6)), np.empty((conns.size, 6, 6)),
                               np.empty((conns.size, 4, 4)), np.empty((conns.size, 4, 4)))
        out.cov[hit], out.weights[hit], out.T_meas[hit], out.T_meas_inv[hit] = (
            kept.cov[at], kept.weights[at], kept.T_meas[at], kept.T_meas_inv[at])
        if not hit.all():
            new = conns[~hit]
            out.cov[~hit] = cov = self._ccov.a[new]
            out.weights[~hit] = spd_inverse(cov,
                                            "a connection's covariance is not positive definite")
            z = self._z.a[new]
            T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
            out.T_meas[~hit], out.T_meas_inv[~hit] = T_meas, se3.inverse(T_meas)
        self._conn_terms = out
        return out

    def _quality_report(self, net: ConnectionNetwork, res: SolveResult,
                        priors: list[GaussianPrior]) -> tuple[QualityReport, float]:
        """Quality control of a window adjustment (computed once per solution) and its time (s).
        The per-connection ``max |w|`` is kept for :meth:`connection_w`."""
        cached = self.__dict__.get('_qc')
        if cached is not None and cached[0] is res:
            return cached[1], cached[2]
        t0 = time.perf_counter()
        rep = quality_control(net, res, priors, self.config.quality_config())
        seconds = time.perf_counter() - t0
        self.__dict__['_qc'] = (res, rep, seconds)
        return rep, seconds

    def _quality_summary(self, net: ConnectionNetwork, res: SolveResult,
                         priors: list[GaussianPrior], conns: IntArray) -> QualitySummary | None:
        """The QC summary of the final window adjustment (``None`` when ``quality`` is off)."""
        cached = self.__dict__.get('_qc')
        due = (self._n_updates + 1) % int(self.config.quality_every) == 0
        if not self.config.quality or not (due or (cached is not None and cached[0] is res)):
            return None
        rep, seconds = self._quality_report(net, res, priors)
        w = np.where(rep.redundancy_numbers >= rep.config.min_redundancy, rep.w_max, np.nan)
        self.__dict__.setdefault('_conn_w', {}).update(zip(conns.tolist(), w.tolist()))
        return summarise(rep, net, seconds=seconds)

    def connection_w(self) -> FloatArray:
        """(m,) largest ``|w|`` (Baarda's w-test statistic) of every connection at the last
        window adjustment that contained it, in the order of :meth:`connection_arrays`; NaN
        when never tested (``quality`` off, untestable, or not adjusted since a reload)."""
        w = self.__dict__.get('_conn_w', {})
        out = np.full(self._src.n, np.nan)
        if w:
            k = np.fromiter(w.keys(), np.int64, len(w))
            out[k[k < out.size]] = np.fromiter(w.values(), float, len(w))[k < out.size]
        return out

    def _outliers(self, res: SolveResult, conns: IntArray, net: ConnectionNetwork,
                  priors: list[GaussianPrior]) -> IntArray:
        """Cross connections the gate excludes after an adjustment.

        ``'chi2'``: every one whose squared Mahalanobis misclosure at the solution exceeds the
        chi-square quantile (6 dof); for the se3 model ``v' P v = w' M^-1 w``. ``'w-test'``:
        the worst cross connections whose w-test rejects (data snooping, see
        :class:`AlignerConfig`)."""
        prob = self.config.outlier_chi2_prob
        cross = self._cross.a[conns]
        if prob <= 0 or not cross.any():
            return np.zeros(0, dtype=np.int64)
        if self.config.gate == 'w-test':
            rep, _ = self._quality_report(net, res, priors)
            ratio = np.where(cross, np.nan_to_num(rep.test_ratio('w'), nan=0.0), 0.0)
            return conns[ratio > 1.0]
        P = self._connection_terms(conns).weights
        v = res.residuals
        maha2 = np.einsum('mi,mij,mj->m', v, P, v)
        return conns[cross & (maha2 > chi2.ppf(prob, 6))]

    def _readmissible(self, window_tracks: list[int], nodes: IntArray, res: SolveResult,
                      tried: set[int]) -> IntArray:
        """Excluded connections of the window that the new estimate agrees with.

        A connection excluded by the gate (status 2) whose two ends are unknowns of this
        adjustment is re-tested at its estimate: the misclosure ``e = log(T_meas^-1 T_i^-1
        T_j)`` with covariance ``S + J Q_x J'`` (the connection's own plus the propagated
        uncertainty of the two poses, ``J = [-Ad(T_ij^-1), I]``, small-misclosure Jacobian)
        must pass the same chi-square quantile (6 dof) as the gate. Each connection is
        re-admitted at most once per update, so the gate cannot oscillate.
        """
        prob = self.config.outlier_chi2_prob
        if prob <= 0:
            return np.zeros(0, dtype=np.int64)
        conns = self._track_connections(window_tracks)
        conns = conns[self._status.a[conns] == 2]
        if tried:
            conns = conns[~np.isin(conns, np.fromiter(tried, np.int64))]
        local = np.full(len(self._ids), -1, dtype=np.int64)
        local[nodes] = np.arange(nodes.size)
        conns = conns[(local[self._src.a[conns]] >= 0) & (local[self._dst.a[conns]] >= 0)]
        if conns.size == 0:
            return conns
        i, j = local[self._src.a[conns]], local[self._dst.a[conns]]
        T = res.T_world_node
        T_ij = se3.inverse(T[i]) @ T[j]
        z = self._z.a[conns]
        e = se3.log(se3.inverse(se3.from_translation_rotvec(z[:, :3], z[:, 3:])) @ T_ij)
        J = np.zeros((conns.size, 6, 12))
        J[:, :, :6] = -se3.adjoint(se3.inverse(T_ij))
        J[:, :, 6:] = np.eye(6)
        Q = np.zeros((conns.size, 12, 12))
        ids = res.node_ids
        free = np.isin(ids, res.free_node_ids)
        ends = np.stack([i, j], axis=1)
        for start in range(0, conns.size, 64):  # the joint covariance of <= 128 nodes at once
            part = ends[start:start + 64]
            nodes_free = np.unique(part[free[part]])
            if nodes_free.size == 0:
                continue
            cov = res._system.joint_covariance(ids[nodes_free])
            cov = cov.reshape(nodes_free.size, 6, nodes_free.size, 6).transpose(0, 2, 1, 3)
            pos = np.searchsorted(nodes_free, part)
            for a in range(2):
                for b in range(2):
                    both = free[part[:, a]] & free[part[:, b]]
                    Q[start:start + 64][both, 6 * a:6 * a + 6, 6 * b:6 * b + 6] = \
                        cov[pos[both, a], pos[both, b]]
        C = self._ccov.a[conns] + J @ Q @ np.swapaxes(J, 1, 2)
        maha2 = np.einsum('mi,mi->m', e, np.linalg.solve(C, e[:, :, None])[:, :, 0])
        return conns[maha2 <= chi2.ppf(prob, 6)].astype(np.int64)

    def _freeze(self, track: int) -> None:
        """Freeze a track leaving the window, using the last adjustment's estimate (the plan
        computed ahead in the background if it still applies, else computed now)."""
        plan = self._ahead_plan(track)
        if plan is None:
            plan = self._plan_freeze(track, self._last, self._last_window, self._priors,
                                     len(self._ids), self._src.n)
        self._install_freeze(plan)

    def _install_freeze(self, plan: _FreezePlan) -> None:
        """Apply a freeze (:class:`_FreezePlan`): covariances, absorbed connections, priors,
        frozen flags."""
        if plan.cov_rows.size:
            self._cov[plan.cov_rows] = plan.cov
        self._status.a[plan.absorbed] = 1
        dropped = set(plan.dropped)
        self._priors = [p for q, p in enumerate(self._priors) if q not in dropped]
        if plan.prior is not None:
            self._priors.append(plan.prior)
        self._frozen[plan.nodes] = True

    def _plan_freeze(self, track: int, res: SolveResult | None, last_window: IntArray,
                     priors: list, n: int, nc: int) -> _FreezePlan:
        """The freeze of ``track`` (:class:`_FreezePlan`) from the last adjustment ``res`` (of
        the nodes ``last_window``), the joint priors ``priors``, the first ``n`` nodes and
        ``nc`` connections; reads the aligner's tables and changes nothing in them (it may run
        in a background thread while measurements are added: those rows come after ``n``,
        ``nc``)."""
        nodes = np.array(self._track_nodes[track], dtype=np.int64)
        # the new prior first: a covariance asked for right after an update (the node's newest
        # pose) factors the last adjustment's system meanwhile, and the selected inversion
        # below then reuses that factorisation
        absorbed, dropped, prior = self._marginalise(nodes, priors, n, nc)
        cov_rows, cov = np.zeros(0, np.int64), np.zeros((0, 6, 6))
        if res is not None:
            inside = nodes[np.isin(nodes, last_window)]
            if inside.size:
                ids = self._idarr.a[inside]
                sel = np.isin(ids, res.free_node_ids)
                if sel.any():
                    banded = self.config.prior_band >= 0 and sel.sum() >= _BANDED_MIN_NODES
                    with self._factor_lock:  # res's factor, shared with covariances()
                        cov = _marginal_covariances(res, ids[sel], banded)
                    cov_rows = inside[sel]
        return _FreezePlan(int(track), nodes, cov_rows, cov, absorbed, dropped, prior)

    def _marginalise(self, L: IntArray, priors: list, n: int, nc: int
                     ) -> tuple[IntArray, tuple[int, ...], JointPrior | None]:
        """Absorb the terms of the leaving nodes ``L`` into one joint Gaussian prior.

        ``'marginal'``: every active connection of ``L`` is absorbed and ``L`` is eliminated
        (Schur complement) onto the window nodes it touched. ``'weighted'``: only connections
        whose two ends are frozen (after this freeze) are absorbed; frozen nodes that keep an
        active connection to the window stay in the prior (the paper's weighted parameters, with
        their joint covariance), every other frozen node of the absorbed terms is eliminated.
        In both cases each connection enters either the window problem or one prior, never
        both, so the prior is the exact marginal in the linear limit and covariances are not
        overconfident. Priors (of ``priors``) that share nodes with the absorbed terms are
        merged in. Returns the absorbed connection rows, the indices of the merged priors and
        the new prior (``None`` if no node is kept); changes nothing.
        """
        src, dst, status0 = self._src.a[:nc], self._dst.a[:nc], self._status.a[:nc]
        in_L = np.zeros(n, dtype=bool)
        in_L[L] = True
        frozen_after = self._frozen[:n] | in_L
        conns = self._track_connections(np.unique(self._trackarr.a[L]).tolist())
        conns = conns[conns < nc]
        conns = conns[(status0[conns] == 0) & (in_L[src[conns]] | in_L[dst[conns]])]
        if self.config.freeze_policy == 'weighted':
            conns = conns[frozen_after[src[conns]] & frozen_after[dst[conns]]]
        involved = in_L.copy()
        involved[src[conns]] = True
        involved[dst[conns]] = True
        touching = [p for p, (idx, _, _) in enumerate(priors) if involved[idx].any()]
        for p in touching:
            involved[priors[p][0]] = True
        involved[0] = False  # the datum is fixed, never a prior node
        allnodes = np.nonzero(involved)[0]
        # nodes that keep an active connection (other than the absorbed ones) to a node that is
        # not frozen stay in the prior; the others are eliminated
        status = status0.copy()
        status[conns] = 1
        act = np.nonzero(status == 0)[0]
        s_, d_ = src[act], dst[act]
        keep = ~frozen_after.copy()
        keep[s_[~frozen_after[d_]]] = True
        keep[d_[~frozen_after[s_]]] = True
        ids = self._idarr.a[:n]
        merged = [GaussianPrior(ids[priors[p][0]], priors[p][1], priors[p][2]) for p in touching]
        dropped = tuple(touching)
        datum = bool(((src[conns] == 0) | (dst[conns] == 0)).any())
        net_nodes = np.concatenate([[0], allnodes]) if datum else allnodes
        net = self._subnetwork(net_nodes, conns)
        fixed = [ids[0]] if datum else []
        T = self._T  # rows below n: not changed by adding measurements
        N, free_ids, u = normal_matrix_at(net, T[net_nodes], 'se3', fixed, merged)
        row_of = dict(zip(ids[net_nodes].tolist(), net_nodes.tolist()))
        free_idx = np.array([row_of[int(i)] for i in free_ids], dtype=np.int64)
        kept = keep[free_idx]
        if not kept.any():
            return conns, dropped, None
        p = marginal_prior(free_idx, N, u, kept, T[free_idx[kept]], int(self.config.prior_band),
                           int(self.config.prior_hubs), coords=T[free_idx, :3, 3])
        return conns, dropped, JointPrior.absorbed(p)

    # ------------------------------------------------------------------------ output
    def corrected_path(self) -> CorrectedPath:
        n = len(self._ids)
        return CorrectedPath(self._idarr.a.copy(), self._trackarr.a.copy(),
                             self._stamparr.a.copy(), self._T[:n].copy(),
                             self._frozen[:n].copy())

    def covariance(self, node_id: int) -> FloatArray:
        """6x6 covariance ``[x y z rx ry rz]`` of a node's pose (right perturbation).

        Frozen nodes: the block stored when they froze. Window nodes: from the last
        adjustment. Nodes of the open track (not adjusted yet): the last adjusted covariance of
        their chain's start, propagated is not attempted; ``InputError`` is raised instead.
        """
        try:
            k = self._index[int(node_id)]
        except (KeyError, TypeError, ValueError):
            raise InputError(f'unknown node {node_id}') from None
        if self._frozen[k]:
            return self._cov[k].copy()
        if self._last is not None and k in set(self._last_window.tolist()):
            if k == 0:
                return np.zeros((6, 6))
            with self._factor_lock:  # after a freeze being computed ahead, which shares it
                return self._last.covariance([self._ids[k]])[0]
        raise InputError(f'node {node_id} has not been adjusted yet (its track is still open)')

    def covariances(self, node_ids) -> FloatArray:
        """``(k, 6, 6)`` covariances of many nodes at once (see :meth:`covariance`).

        Window nodes are computed together from the last adjustment (selected inversion rather
        than one solve per node). Raises :class:`InputError` for an unknown node or one whose
        track is still open.
        """
        ids = np.atleast_1d(np.asarray(node_ids, dtype=np.int64))
        out = np.zeros((ids.size, 6, 6))
        in_window = set(self._last_window.tolist())
        from_window = []
        for k, node in enumerate(ids.tolist()):
            i = self._index.get(int(node))
            if i is None:
                raise InputError(f'unknown node {node}')
            if self._frozen[i]:
                out[k] = self._cov[i]
            elif i in in_window:
                if i != 0:
                    from_window.append(k)
            else:
                raise InputError(f'node {node} has not been adjusted yet (its track is still '
                                 'open)')
        if from_window:
            with self._factor_lock:  # after a freeze being computed ahead, which shares it
                out[from_window] = self._last.covariance(ids[from_window])  # in blas_threads()
        return out

    @property
    def newest_node_id(self) -> int | None:
        return int(self._idarr.a[-1]) if self._idarr.n else None

    @property
    def open_track(self) -> int | None:
        return None if self._open_track in self._finished else self._open_track

    @property
    def stats(self) -> AlignerStats:
        finished = [t for t in self._tracks if t in self._finished]
        return AlignerStats(len(self._ids), self._src.n, dict(self._rejected),
                            finished[-self.config.window_tracks:], self._n_updates,
                            self._n_outliers, self._last_update)

    def connection_arrays(self) -> tuple[IntArray, IntArray, FloatArray, BoolArray, IntArray]:
        """``(src_id, dst_id, z, cross, status)`` of every connection (status 0 active,
        1 absorbed into a marginal prior, 2 excluded as an outlier)."""
        ids = self._idarr.a
        return (ids[self._src.a], ids[self._dst.a], self._z.a.copy(), self._cross.a.copy(),
                self._status.a.astype(np.int64))

    def connection_covariances(self) -> FloatArray:
        """(m, 6, 6) covariance of every connection, in the order of :meth:`connection_arrays`."""
        return self._ccov.full()

    # --------------------------------------------------------------- batch refinement
    def refine_batch(self, max_iterations: int | None = None) -> UpdateResult:
        """Full batch adjustment of every node with every kept connection (end of a survey).

        The open track is finished first. Outliers stay excluded. The covariances published
        afterwards come from this adjustment: frozen nodes get their marginal blocks from it
        (selected inversion), window nodes are answered from it like after a window update.
        The joint priors of the absorbed connections are rebuilt at the refined estimate
        (:func:`~ga_ros.core.refinement.absorbed_priors`), so the next window update continues
        from it consistently; a pending background refinement is dropped.
        """
        self.finish_track()
        self._drop_ahead()  # its inputs (estimate, priors) are replaced below
        t0 = time.perf_counter()
        keep = np.nonzero(self._status.a != 2)[0]
        n = len(self._ids)
        # from the aligner's arrays, checked at insertion (no per-connection validation and
        # duplicate bookkeeping: ~0.5 GB and minutes less at 100,000 poses)
        net = self._subnetwork(np.arange(n), keep)
        scfg = self.config.solver_config()
        if max_iterations is not None:
            scfg = SolverConfig(**{**asdict(scfg), 'max_iterations': int(max_iterations)})
        res = solve(net, self._T[:n], scfg, fixed=[self._ids[0]])
        del net
        self._T[:n] = res.T_world_node
        frozen = np.nonzero(self._frozen[:n] & (np.arange(n) != 0))[0]
        if frozen.size:
            self._cov[frozen] = res.covariance(self._idarr.a[frozen])
        # the joint priors of the absorbed connections, relinearised at the refined estimate
        # (their old means would pull the next window update back to the online estimate)
        self._refiner.drop()
        self._refine_snap = None
        # the next refinement starts from the whole survey again (a past prior linearised at
        # the old estimate would pull the retired tracks' boundary back)
        self._retired, self._past = 0, []
        with blas_threads():
            self._priors = [JointPrior.absorbed(p) for p in
                            absorbed_priors(self._snapshot(whole=True), self._T[:n])]
        self._last = res
        self._last_window = np.nonzero(~self._frozen[:n])[0]
        self._T_weighted = _no_weighted()
        return UpdateResult(-1, res.iterations, res.converged, res.sigma0_sq,
                            1e3 * (time.perf_counter() - t0), n, int(keep.size),
                            len(self._tracks), 0, res.reason, 0, res.n_unknowns)

    # ------------------------------------------------------------------- persistence
    @property
    def _last(self) -> SolveResult | None:
        """The last window adjustment. A restored state recomputes it on first use (its
        covariances are needed only to freeze the next leaving track or to answer
        :meth:`covariances`), so loading a snapshot does not solve anything."""
        pending = self.__dict__.pop('_last_pending', None)
        if pending is not None:
            net, nodes, _, _, fixed, priors = self._window_problem(pending)
            self.__dict__['_last_result'] = solve(net, self._T[nodes],
                                                  self.config.solver_config(), fixed=fixed,
                                                  priors=priors, jit=True)
        return self.__dict__.get('_last_result')

    @_last.setter
    def _last(self, value: SolveResult | None) -> None:
        self.__dict__.pop('_last_pending', None)
        self.__dict__['_last_result'] = value
