"""Settings and results of :class:`~ga_ros.core.window.TrackWindowAligner`.

:class:`AlignerConfig` mirrors the alignment node's parameters one to one; the results are
plain dataclasses (:class:`UpdateResult` of a window update, :class:`CorrectedPath`,
:class:`AlignerStats`, :class:`BatchResult` of :meth:`add_measurements
<ga_ros.core.window.TrackWindowAligner.add_measurements>`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.calibration.fix_parameters import fix_parameter
from ga_ros.core.config_ranges import check_ranges, names_of, ranged, string_list
from ga_ros.core.fixes import DATUMS, gauge_information
from ga_ros.core.quality import QualityConfig, QualitySummary
from ga_ros.core.quality.online_variance import OnlineVarianceConfig
from ga_ros.core.solver import SolverConfig
from ga_ros.core.window.freeze import FREEZE_POLICIES
from ga_ros.core.window.worker import REFINE_EXECUTORS
from ga_ros.errors import InputError

#: The outlier gates (``AlignerConfig.gate``, :mod:`ga_ros.core.window.gate`).
GATES = ('chi2', 'w-test')


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
#: ``factor='auto'``: a window below ~6,000 unknowns whose factor has few flops per entry (a
#: window of odometry tracks and fixes: a block chain) gets CHOLMOD's simplicial factor, which
#: there factors in under half the time of the supernodal one (its thousands of tiny BLAS
#: calls) and solves in half; the freeze's selected inversion reads it through a copy. A
#: window with joint priors over long boundaries (the aerial survey) stays supernodal, its
#: factor inverted in place.
ALIGNER_SOLVER = SolverConfig(max_iterations=10, tolerance=1e-6, cost_tolerance=1e-6,
                              reuse_factor_below=20.0, factor='auto')


@dataclass(frozen=True)
class AlignerConfig:
    """Settings of :class:`TrackWindowAligner` (mirrors the alignment node's parameters).

    Numeric fields carry their allowed interval (``metadata['range']``,
    :mod:`ga_ros.core.config_ranges`), which the node's parameters and the replay share.

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
        update at 20 % wrong connections: docs/benchmarks.md, "Wrong connections").
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
    refine_every_tracks : background refinement (:mod:`ga_ros.core.window.refinement`): after every
        this many tracks (counted when at least one track is frozen) the survey (its last
        ``refine_horizon_tracks`` tracks) is solved in batch off the update path and handed back
        as the new frozen estimate (poses, published covariances, relinearised priors). 0
        disables it.
    refine_lag_tracks : a refinement started after track ``k`` is installed at the start of the
        update of track ``k + refine_lag_tracks`` (waiting for it there if it is not ready), so
        the result does not depend on timing: a replay and a live node give the same path.
    refine_executor : where the refinement runs: ``'auto'`` (default: inline for a snapshot of
        fewer than :data:`~ga_ros.core.window.worker.INLINE_BELOW_CONNECTIONS` connections,
        where a worker process costs more CPU than the work, else in the process),
        ``'process'`` (a separate process, 'spawn' start method; truly parallel), ``'thread'``
        or ``'inline'`` (solved at the hand-off; same result, for tests and single-core
        machines).
    refine_horizon_tracks : ``H``, tracks a refinement re-solves
        (:mod:`ga_ros.core.window.refinement`,
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
    refine_relinearize_sigma : a refinement starts (at its ``refine_every_tracks`` trigger) only
        when the frozen nodes the window adjusts as weighted parameters may have moved from
        their priors' linearisation points by this many of their standard deviations (in some
        coordinate, summed over the updates since the last installed refinement; with
        ``variance_components='apply'`` each update's change of the variance factors adds the
        largest relative change of a source's standard deviations, ``|sqrt(f_new / f_old) -
        1|``), or when the
        tracks not retired reach ``2 refine_horizon_tracks``; otherwise the window's own priors
        stand, as iSAM2 relinearises only variables whose change exceeds a threshold
        (``docs/window-design.md``, "When a refinement runs"). 0: after every trigger.
    prior_band : half-bandwidth ``w`` (nodes, along the trajectory) of the joint priors'
        information (:func:`~ga_ros.core.window.freeze.band_prior`): the exact marginal
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
    datum : ``'first_node'`` (the first node held fixed at ``T_world_first``) or ``'fixes'``
        (absolute fixes define the map frame, :mod:`ga_ros.core.fixes`: nothing is held fixed,
        the first node gets a weak gauge prior at ``T_world_first`` with the ``gauge_*``
        sigmas, so the normal matrix stays regular until the fixes constrain every degree of
        freedom). Frozen nodes keep their fixes in the joint priors absorbed at the freeze and
        in those a refinement or :meth:`~ga_ros.core.window.aligner.TrackWindowAligner.
        refine_batch` rebuilds; the background refinement's snapshots carry the fixes.
    fix_gate_prob : chi-square probability of the fixes' gate (:meth:`FixBook.gate
        <ga_ros.core.fixes.FixBook.gate>`); 0 disables it.
    gauge_sigma_m : position sigma (m, per axis) of the gauge prior of ``datum='fixes'``.
    gauge_sigma_tilt_rad : roll and pitch sigma (rad) of the gauge prior (an odometry frame is
        level, REP 105, so the default is tight-ish: 0.05 rad).
    gauge_sigma_yaw_rad : yaw sigma (rad) of the gauge prior (the odometry's heading in the map
        frame is unknown: 3 rad).
    variance_components : online variance factor per source
        (:mod:`ga_ros.core.quality.online_variance`): ``'off'`` (default: nothing estimated,
        no cost, the stated covariances) or ``'apply'`` (estimated after each track; the window
        adjustments weight each connection by its source's factor and the published
        covariances follow). Each update then adjusts the window again until the factors
        settle (at most ``max_inner_iterations``, usually 1 to 3 more) and computes the
        redundancy numbers of its window each time (about the cost of the quality control,
        shared with it when ``quality`` is on).
    variance_min_redundancy : a source's factor is used only once its accumulated redundancy
        (degrees of freedom) reaches this; until then it stays 1.
    variance_prior_dof : the factor is shrunk towards 1 with a prior of this many degrees of
        freedom.
    calibrate : self-calibration online (:mod:`ga_ros.core.window.calibration`): after each
        window update each odometry source's scale and yaw-rate corrections (and each fix
        source's ``calibration_fix_parameters``) are estimated again where the network
        determines them and they are significant (in a background thread, inline with
        ``refine_executor='inline'``), installed before the next odometry motion or fix, and
        the source's motions and fixes that enter from then on are stored corrected.
        ``False`` (default): nothing estimated, the motions and fixes as measured.
    calibration_fix_parameters : with ``calibrate``, the parameters estimated online per fix
        source, comma-separated (``time_offset``, ``offset_x``, ``offset_y``, ``offset_z``;
        ``''``: none, the fixes as measured): by default the time offset (s), the batch's
        default (``CalibrationConfig.fix_parameters``). An offset needs a
        ``calibration_fix_reference``.
    calibration_noise : with ``calibrate``, the noise of each calibrated odometry source
        re-estimated online too (the batch's ``CalibrationConfig.noise``: damped variance
        factors of its translation and rotation, where the horizon has the redundancy), and
        the source's motions that enter from then on stored with their stated covariance
        scaled by them (default; docs/benchmarks.md: the online RMSE on the Plaza run 0.94x
        and 1.00x at fixes every 10 and 60 s); ``False``: the stated covariances kept.
    calibration_fix_reference : the fix sources that define the map frame online,
        comma-separated (no offset estimated for them). Required with an offset: online, the
        reference the batch would otherwise choose (the better-determined source) could change
        from one horizon to the next and move the frame with it.
    calibrate_cameras : with ``calibrate``, the cameras (their sources: ``('cam0',)``; a ROS
        string array, ``[cam0]`` in YAML; one comma-separated string is accepted too) whose
        extrinsic rotation the online estimate includes
        (:mod:`ga_ros.core.calibration.camera_parameters`, on every connection of the source):
        estimated and published with its sigma, and applied to the camera's connections
        (consecutive and cross-track) as they enter, ``X T X^-1`` with the rotation booked per
        connection (``docs/calibration.md``), the connections stored before an estimate
        corrected again at the next update. ``()`` (default): none.
    calibration_horizon_tracks : the latest finished tracks the online estimate is made on
        (its memory: a slowly varying parameter is followed with this lag).
    calibration_refresh : the online estimate runs at a track end once the connections
        admitted since the last one reach this fraction of the last one's horizon (each
        estimate costs a batch adjustment of the horizon, a few solves); 0: at every track end.
    """

    window_tracks: int = ranged(5, 1, 1000)
    freeze_policy: str = 'weighted'
    freeze_ahead: bool = True
    solver: SolverConfig = ALIGNER_SOLVER
    outlier_chi2_prob: float = ranged(0.99999, 0.0, 1.0)
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
    refine_every_tracks: int = ranged(1, 0, 1000)
    refine_lag_tracks: int = ranged(1, 1, 1000)
    refine_executor: str = 'auto'
    refine_horizon_tracks: int = ranged(20, 0, 100_000)
    refine_relinearize_sigma: float = ranged(1.0, 0.0, 1e6)
    prior_band: int = ranged(8, -1, 100_000)
    prior_hubs: int = ranged(8, 0, 1000)
    datum: str = 'first_node'
    fix_gate_prob: float = ranged(0.9999, 0.0, 1.0)
    gauge_sigma_m: float = ranged(1000.0, 1e-9, 1e9)
    gauge_sigma_tilt_rad: float = ranged(0.05, 1e-12, 10.0)
    gauge_sigma_yaw_rad: float = ranged(3.0, 1e-12, 10.0)
    variance_components: str = 'off'
    variance_min_redundancy: float = 20.0
    variance_prior_dof: float = 10.0
    calibrate: bool = False
    calibrate_cameras: tuple[str, ...] = string_list()
    calibration_horizon_tracks: int = ranged(30, 1, 100_000)
    calibration_refresh: float = ranged(0.1, 0.0, 10.0)
    calibration_fix_parameters: str = 'time_offset'
    calibration_fix_reference: str = ''
    calibration_noise: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, 'calibrate_cameras', names_of(self.calibrate_cameras))
        check_ranges(self)
        self.online_variance_config()  # checks the mode and levels
        self.calibration_fix_config()  # checks the online fix parameters
        if self.freeze_policy not in FREEZE_POLICIES:
            raise InputError(f'freeze_policy must be one of {tuple(FREEZE_POLICIES)}, '
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

        if self.refine_executor not in REFINE_EXECUTORS:
            raise InputError(f'refine_executor must be one of {REFINE_EXECUTORS}, '
                             f'got {self.refine_executor!r}')
        if self.datum not in DATUMS:
            raise InputError(f'datum must be one of {DATUMS}, got {self.datum!r}')
        if not self.fix_gate_prob < 1.0:
            raise InputError(f'fix_gate_prob must be in [0, 1), got {self.fix_gate_prob}')
        gauge_information(self.gauge_sigma_m, self.gauge_sigma_tilt_rad,
                          self.gauge_sigma_yaw_rad)  # range checks
        if self.camera_names and not self.calibrate:
            raise InputError(f'calibrate_cameras {self.calibrate_cameras!r} needs calibrate: '
                             'true (the online estimate it joins)')

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The cameras of ``calibrate_cameras``, in order."""
        return self.calibrate_cameras

    def quality_config(self) -> QualityConfig:
        """The test settings of the quality control and of the ``'w-test'`` gate."""
        return QualityConfig(alpha=self.quality_alpha, alpha0=self.quality_alpha0,
                             snoop_test='w')

    def online_variance_config(self) -> OnlineVarianceConfig:
        """The settings of the online variance components (``variance_*``)."""
        return OnlineVarianceConfig(mode=self.variance_components,
                                    min_redundancy=float(self.variance_min_redundancy),
                                    prior_dof=float(self.variance_prior_dof))

    def calibration_fix_config(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """``(fix parameters, fix reference sources)`` of the online calibration
        (:attr:`calibration_fix_parameters`, :attr:`calibration_fix_reference`), checked.

        Raises
        ------
        InputError
            An unknown parameter, or an offset without a reference source.
        """
        names = tuple(x.strip() for x in self.calibration_fix_parameters.split(',')
                      if x.strip())
        ref = tuple(x.strip() for x in self.calibration_fix_reference.split(',') if x.strip())
        for name in names:
            fix_parameter(name)
        if any(name.startswith('offset_') for name in names) and not ref:
            raise InputError('calibration_fix_parameters with an offset needs a '
                             'calibration_fix_reference (the fix source that defines the map '
                             'frame)')
        return names, ref

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
    """Counters of an aligner (:attr:`TrackWindowAligner.stats
    <ga_ros.core.window.aligner.TrackWindowAligner.stats>`).

    ``n_updates`` counts the window updates, failed ones included; ``n_failed_updates`` those
    that failed (state put back, see :meth:`TrackWindowAligner.finish_track
    <ga_ros.core.window.aligner.TrackWindowAligner.finish_track>`) over the whole survey (kept
    in the state: restarts from the snapshot or the journal included); ``last_failure`` the
    last one's exception and traceback (``''`` if none).
    """

    n_nodes: int
    n_connections: int
    n_rejected: dict[str, int]
    tracks_in_window: list[int]
    n_updates: int
    n_outliers: int
    last_update: UpdateResult | None = None
    n_failed_updates: int = 0
    last_failure: str = ''


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
