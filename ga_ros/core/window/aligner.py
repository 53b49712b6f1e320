"""The track-window aligner: a thin facade over the parts of :mod:`ga_ros.core.window`.

:class:`TrackWindowAligner` is fed one :class:`~ga_ros.core.measurement.Measurement` at a time
(:mod:`~ga_ros.core.window.admission` validates and stores it in the
:class:`~ga_ros.core.window.state.WindowState`); at each track end it freezes the tracks that
leave the window (:mod:`~ga_ros.core.window.freeze`, computed ahead by
:mod:`~ga_ros.core.window.freeze_ahead`), installs a background refinement that is due
(:mod:`~ga_ros.core.window.handoff`), adjusts the window (:mod:`~ga_ros.core.window.update`,
with the outlier gate of :mod:`~ga_ros.core.window.gate`), and puts every estimate back if that
fails. See the package docstring for the method.
"""

from __future__ import annotations

import os
import threading
import time
import traceback
from dataclasses import asdict, replace

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.calibration import (
    CalibrationConfig,
    CalibrationReport,
    book_observations,
    solve_with_calibration,
)
from ga_ros.core.fixes import (
    FixStats,
    FixTerm,
    gauge_information,
    offset_information,
    sensor_jacobian,
    sensor_misclosure,
)
from ga_ros.core.measurement import Measurement, source_or_group, variance_group
from ga_ros.core.quality.control import connection_redundancy
from ga_ros.core.quality.online_variance import OnlineVarianceComponents
from ga_ros.core.quality.variance_components import (
    SourceGroups,
    VarianceComponentConfig,
    VarianceComponents,
    solve_with_variance_components,
)
from ga_ros.core.solver import SolverConfig, SolveResult, solve
from ga_ros.core.window.admission import (
    apply_measurement,
    check_covariances_batch,
    check_measurement,
)
from ga_ros.core.window.calibration import OnlineCalibration, calibration_source
from ga_ros.core.window.config import (
    AlignerConfig,
    AlignerStats,
    BatchResult,
    CorrectedPath,
    UpdateResult,
)
from ga_ros.core.window.freeze import FreezePlan, JointPrior, freeze_policy, install_freeze
from ga_ros.core.window.freeze_ahead import FreezeAhead
from ga_ros.core.window.handoff import RefinementHandoff
from ga_ros.core.window.queries import covariance, covariances
from ga_ros.core.window.refinement import absorbed_priors
from ga_ros.core.window.state import LAST_FAILURE_CHARS, Rollback, WindowState, no_weighted
from ga_ros.core.window.update import (
    ConnectionTerms,
    WindowUpdate,
    connection_terms,
    scaled_terms,
)
from ga_ros.core.window.variance_handoff import ScaledRefinementHandoff
from ga_ros.errors import GaError, InputError
from ga_ros.geometry import so3
from ga_ros.runtime import blas_threads

#: Environment variable that makes a window update failing with anything but one of
#: :data:`NUMERICAL_FAILURES` (a bug) raise after its state is put back, instead of being
#: reported in the result only (set by the test suite, ``test/conftest.py``).
STRICT_UPDATES_ENV = 'GA_ROS_STRICT_UPDATES'
#: Exceptions of a window update that are numerical failures of the data, never raised by
#: :attr:`TrackWindowAligner.strict`.
NUMERICAL_FAILURES = (GaError, np.linalg.LinAlgError, FloatingPointError)


def strict_updates_from_env() -> bool:
    """Whether :data:`STRICT_UPDATES_ENV` is set to anything but ``''`` or ``'0'``."""
    return os.environ.get(STRICT_UPDATES_ENV, '') not in ('', '0')


def factor_drift(before: FloatArray, after: FloatArray) -> float:
    """How much a change of the variance factors (per group, ``before`` -> ``after``; groups
    new in ``after`` had 1) counts towards the refinement's drift
    (:meth:`RefinementHandoff.measure <ga_ros.core.window.handoff.RefinementHandoff.measure>`),
    in standard deviations: the largest relative change of a group's standard deviations,
    ``|sqrt(after / before) - 1|``. A joint prior weighting the group with the old factor has
    standard deviations off by that fraction, so it can misplace its nodes by about that many
    of them."""
    after = np.asarray(after, float)
    old = np.ones(after.size)
    k = min(after.size, np.size(before))
    old[:k] = np.asarray(before, float)[:k]
    if after.size == 0:
        return 0.0
    return float(np.abs(np.sqrt(after / old) - 1.0).max())


class TrackWindowAligner:
    """Online sliding-window global alignment, fed one :class:`Measurement` at a time.

    Parameters
    ----------
    config : settings (window size, freezing policy, solver tolerances).
    T_world_first : pose of the first node (the datum), identity by default.

    Attributes
    ----------
    config : the settings.
    state : everything kept between calls (:class:`~ga_ros.core.window.state.WindowState`;
        a snapshot file saves and restores it, :meth:`from_state`).
    policy : the freeze policy of ``config.freeze_policy``
        (:class:`~ga_ros.core.window.freeze.FreezePolicy`).
    updater : the window update (:class:`~ga_ros.core.window.update.WindowUpdate`).
    handoff : the background refinement
        (:class:`~ga_ros.core.window.handoff.RefinementHandoff`).
    ahead : the freeze computed ahead (:class:`~ga_ros.core.window.freeze_ahead.FreezeAhead`).
    variance_components : the variance factors per source of the last :meth:`refine_batch`
        that estimated them (None before).
    calibration : the additional parameters per source of the last :meth:`refine_batch`
        that estimated them (:class:`~ga_ros.core.calibration.CalibrationReport`; None
        before).
    online_variance : the online variance factors per source
        (:class:`~ga_ros.core.quality.online_variance.OnlineVarianceComponents`, updated after
        each window adjustment; ``None`` with ``variance_components='off'``).
    online_calibration : the odometry's corrections estimated online and applied to the
        motions as they enter (:class:`~ga_ros.core.window.calibration.OnlineCalibration`;
        ``None`` with ``calibrate`` off).
    """

    def __init__(self, config: AlignerConfig | None = None,
                 T_world_first: FloatArray | None = None) -> None:
        self.config = config or AlignerConfig()
        T_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first, float)
        if T_first.shape != (4, 4) or not np.isfinite(T_first).all():
            raise InputError('T_world_first must be a finite 4x4 pose')
        self._attach(WindowState(T_first=T_first))

    @classmethod
    def from_state(cls, config: AlignerConfig, state: WindowState) -> TrackWindowAligner:
        """An aligner continuing from ``state`` (a restored snapshot,
        :func:`~ga_ros.core.window.persistence.load_state`)."""
        al = cls.__new__(cls)
        al.config = config
        al._attach(state)
        return al

    def _attach(self, state: WindowState) -> None:
        self.state = state
        self.variance_components: VarianceComponents | None = None
        self.calibration: CalibrationReport | None = None
        state.fixes.gate_prob = float(self.config.fix_gate_prob)
        self.policy = freeze_policy(self.config.freeze_policy)
        self.updater = WindowUpdate(state, self.config)
        self.ahead = FreezeAhead(state)
        # guards the last adjustment's factor, which a freeze computed ahead shares with the
        # covariance queries
        self._factor_lock = threading.Lock()
        self._last_update: UpdateResult | None = None
        self._factor_step = 0.0  # the last adjustment's change of the variance factors
        self.strict = strict_updates_from_env()
        # (config, covariance bytes, its checked symmetric form): _admitted_covariance
        self._cov_memo: tuple[AlignerConfig, bytes, FloatArray] | None = None
        vcfg = self.config.online_variance_config()
        self.online_variance: OnlineVarianceComponents | None = None
        if vcfg.mode != 'off':
            book = state.variance
            if book is None or book.n != state.src.n:
                # a state saved without the book: the restored connections keep factor 1
                book = OnlineVarianceComponents(vcfg)
                for _ in range(state.src.n):
                    book.register('unknown')
            book.config = vcfg
            state.variance = self.online_variance = book
        self.online_calibration: OnlineCalibration | None = None
        if self.config.calibrate:
            book = state.calibration
            if book is None or book.source.n != state.src.n:
                # a state saved without the book: the restored motions count as measured
                book = OnlineCalibration()
                for _ in range(state.src.n):
                    book.register(None, (0.0, 0.0))
            for _ in range(state.src.n - book.group.n):   # a book saved without the sources
                book.register_group('')
            book.cameras = self.config.camera_names
            if book.cameras:   # a book saved without the applied rotations: as measured
                for _ in range(state.src.n - book.camera_applied.n):
                    book.camera_applied.append(np.zeros(3))
            state.calibration = self.online_calibration = book
        else:
            state.calibration = None  # a book restored with calibrate on is not kept
        if self.online_variance is None:
            self.handoff = RefinementHandoff(state, self.config)
        else:
            # the refinement weights the sources as the window adjustments do
            self.handoff = ScaledRefinementHandoff(state, self.config,
                                                   lambda rows: self._factors_of(rows))
            self._use_variance_factors()

    # ------------------------------------------------------------------------- input
    def add_measurement(self, m: Measurement) -> list[UpdateResult]:
        """Add one measurement; returns the updates it triggered (a track end), if any.

        Raises :class:`InputError` (and counts it by reason in :attr:`stats`) on a measurement
        the policy of :mod:`ga_ros.core.window.admission` rejects; the state is then unchanged.
        A covariance equal, byte for byte, to the last one admitted (a source's stated
        covariance rarely changes) is not checked again: it is the same matrix.
        """
        return self._add(m, self._admitted_covariance(m.cov))

    def _admitted_covariance(self, cov) -> FloatArray | None:
        """The symmetrised covariance of the last admitted measurement if ``cov`` is the same
        (6, 6) float64 matrix, byte for byte, under the same configuration; else ``None``."""
        memo = self._cov_memo
        if (memo is not None and type(cov) is np.ndarray and cov.dtype == np.float64
                and cov.shape == (6, 6) and memo[0] is self.config
                and memo[1] == cov.tobytes()):
            return memo[2]
        return None

    def add_fix(self, term: FixTerm, C_offset: FloatArray | None = None) -> FloatArray:
        """Add an absolute fix tied to a node by the odometry
        (:class:`~ga_ros.core.fixes.FixTerm`); it enters the next adjustment of that node as a
        weighted parameter.

        Parameters
        ----------
        term : the fix, its node and the offset from the node to the sensor.
        C_offset : (6, 6) covariance of that offset (odometry between the node and the fix's
            stamp, right perturbation in the node frame), added to the fix's covariance in its
            known dimensions; ``None``: an exact offset.

        With the online calibration (``calibrate``) the fix is stored corrected by its
        source's current estimate of ``calibration_fix_parameters`` (time offset, offsets;
        :meth:`OnlineCalibration.corrected_fix
        <ga_ros.core.window.calibration.OnlineCalibration.corrected_fix>`), installed first as
        before an odometry motion; the shift applied is booked per fix.

        Returns
        -------
        (6, 6) the information the fix entered with (map frame, the offset's covariance
        included): a journal records the fix (as measured) with it, so a replay
        (``C_offset=None``) adds the same term with the same correction.

        Raises
        ------
        InputError
            An unknown node (counted ``fix_no_keyframe``) or a frozen one (``fix_frozen_node``:
            its estimate and prior are final; send fixes before the node's track leaves the
            window), nothing changed.
        """
        st = self.state
        k = st.index.get(int(term.node_id))
        if k is None:
            st.fixes.reject('fix_no_keyframe')
            raise InputError(f'{term.fix.source}: fix on unknown node {term.node_id}',
                             reason='unknown_source')
        if st.frozen[k]:
            st.fixes.reject('fix_frozen_node')
            raise InputError(f'{term.fix.source}: fix on node {term.node_id}, whose track is '
                             'frozen already', reason='frozen')
        info = term.fix.information
        if C_offset is not None:
            info = offset_information(term.fix, st.T[k], C_offset)
        cal = self.online_calibration
        if cal is not None and self.config.calibration_fix_parameters.strip():
            # the estimate started by the last update: used from now on (as for a motion)
            cal.install(self.strict)
            stamp = st.stamp
            term, shift, applied = cal.corrected_fix(term, st.T[:stamp.size],
                                                     stamp.astype(np.float64) * 1e-9, k)
            cal.register_fix(len(st.fixes), shift, applied)
        st.fixes.add(k, term, info)
        return info

    @property
    def fix_stats(self) -> FixStats:
        """Counters of the absolute fixes (:class:`~ga_ros.core.fixes.FixStats`)."""
        return self.state.fixes.stats

    def fix_node_ids(self) -> IntArray:
        """Ids of the nodes that hold an absolute fix (the gauge prior's node included), in the
        order the fixes came (a restored aligner: its snapshot's and its journal's fixes)."""
        return np.array([int(t.node_id) for t in self.state.fixes.terms], dtype=np.int64)

    @property
    def uses_fixes(self) -> bool:
        """Whether fixes (or the gauge prior of ``datum='fixes'``) take part."""
        return self.config.datum == 'fixes' or len(self.state.fixes) > 0

    def add_measurements(self, ms) -> BatchResult:
        """Add many measurements in order (a journal replay, a recorded survey): exactly what
        calling :meth:`add_measurement` on each would do, rejections included, but with the
        covariances validated together in one vectorised pass. Window updates run at track
        ends only, as they would live. Never raises for a rejected measurement: see the result.
        """
        ms = list(ms)
        sym = check_covariances_batch(self.config, ms)
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

    def _add(self, m: Measurement, checked_cov: FloatArray | None) -> list[UpdateResult]:
        rejected = self.state.rejected
        try:
            plan = check_measurement(self.state, self.config, m, checked_cov)
        except GaError as exc:
            reason = getattr(exc, 'reason', 'invalid')
            rejected[reason] = rejected.get(reason, 0) + 1
            raise
        except Exception as exc:  # noqa: BLE001 - whatever the input, only GaError escapes
            rejected['invalid'] = rejected.get('invalid', 0) + 1
            err = InputError(f'invalid measurement ({type(exc).__name__}: {exc})')
            err.reason = 'invalid'
            raise err from None
        if checked_cov is None and type(m.cov) is np.ndarray and m.cov.dtype == np.float64:
            sym = plan.cov.copy()
            sym.setflags(write=False)  # shared by the measurements that reuse it
            self._cov_memo = (self.config, m.cov.tobytes(), sym)
        updates = []
        if plan.ends_track:
            up = self.finish_track()
            if up is not None:
                updates.append(up)
        n_conn = self.state.src.n
        cal = self.online_calibration
        if cal is not None:
            source = calibration_source(m)
            # a named camera's connection, consecutive or cross-track (its extrinsic rotation)
            camera = (source_or_group(m) if cal.cameras and source_or_group(m) in cal.cameras
                      else None)
            if source is not None or camera is not None:
                cal.install(self.strict)  # the estimate started by the last update: from now on
            z, applied = cal.corrected(plan.z, self._duration_s(m, plan), source)
            z, phi = cal.camera_corrected(z, camera)
            if z is not plan.z:
                plan = replace(plan, z=z, cov=cal.camera_cov(plan.cov, phi))
            cov, noise = cal.scaled_cov(plan.cov, source)  # calibration_noise's factors
            if cov is not plan.cov:
                plan = replace(plan, cov=cov)
        apply_measurement(self.state, m, plan)
        if self.state.src.n > n_conn:
            if cal is not None:
                cal.register(source, applied, noise)
                if cal.cameras:
                    cal.register_group(source_or_group(m))
                    cal.register_camera(phi)
                else:
                    cal.register_group('')
            if self.online_variance is not None:
                self.online_variance.register(variance_group(m))
                self.online_variance.observe(m)
        if plan.first and int(m.src_track) != int(m.dst_track):
            # the datum alone in its track (a session ends a track at a fix on the first
            # keyframe): that track ended before the destination's began, with nothing to
            # adjust. Finished, it takes part in the window and freezes like any track;
            # left open, its node stayed unfrozen forever, so no track could retire from
            # the refinement's horizon and every update copied and scanned the whole survey.
            self.state.finished.add(int(m.src_track))
        if plan.first and self.config.datum == 'fixes':  # the weak gauge prior, row 0
            cfg = self.config
            self.state.fixes.add_gauge(0, plan.src, m.stamp_ns, self.state.T_first,
                                       gauge_information(cfg.gauge_sigma_m,
                                                         cfg.gauge_sigma_tilt_rad,
                                                         cfg.gauge_sigma_yaw_rad))
        return updates

    def _recorrect_cameras(self) -> None:
        """At the start of an update after an estimate that changed a named camera's rotation
        (installed before a connection that entered since, or just now): the camera's
        connections stored so far, corrected with the current rotation (``docs/calibration.md``,
        *Cameras online*). Here, not at the installation: the refinement's snapshot taken at
        the end of the last update holds the connections as they are until this update, so a
        snapshot file's pending refinement restarts from the same data. Every one whose two
        nodes are
        in the refinement's horizon (not retired: window, leaving and frozen tracks alike;
        consecutive and cross-track, active, absorbed or excluded), its motion and covariance
        and its booked rotation (:meth:`OnlineCalibration.recorrect_cameras
        <ga_ros.core.window.calibration.OnlineCalibration.recorrect_cameras>`). The window
        adjustments see them at once; the joint priors hold the absorbed ones as they were
        when absorbed, so the change (in the estimate's sigmas) is added to the refinement's
        drift: a change of ``refine_relinearize_sigma`` or more starts a refinement at the next
        trigger, whose rebuilt priors hold the corrected connections, and drops the pending one
        (due at this update or later) whose snapshot holds them uncorrected; a smaller change
        lets it be installed, as does ``refine_relinearize_sigma = 0`` (every trigger refines:
        the next refinement holds them; dropping would drop every one while the estimate
        moves). The retired tracks' connections (eliminated
        into the past prior) keep theirs. The freeze computed ahead is dropped (it read the
        connections before)."""
        cal, st = self.online_calibration, self.state
        step, cal.camera_step = cal.camera_step, 0.0
        order = st.finished_order()
        retired = min(st.retired, len(order))
        if not retired:
            first = 0
        elif retired < len(order):
            first = int(st.track_nodes.start(order[retired]))
        else:
            first = len(st.ids)
        rows = np.arange(st.src.n) if first == 0 else st.horizon_rows(first)
        self.ahead.drop()   # waits for its thread: it may be reading the connections
        if not cal.recorrect_cameras(st, rows).size:
            return
        self.updater.terms = ConnectionTerms.empty()   # they held the motions as they were
        st.refine_drift = st.refine_drift + step
        sigma = self.config.refine_relinearize_sigma
        if 0.0 < sigma <= step and self.handoff.snap is not None:
            self.handoff.drop()

    def _duration_s(self, m: Measurement, plan) -> float:
        """Seconds between a measurement's source and destination nodes (their stamps; a new
        destination node gets the measurement's stamp, a new first node too)."""
        i, j = plan.rows
        if i is None:
            return 0.0
        st = self.state
        end = int(m.stamp_ns) if j is None else int(st.stamparr.a[j])
        return (end - int(st.stamparr.a[i])) * 1e-9

    # ----------------------------------------------------------------------- updates
    def finish_track(self) -> UpdateResult | None:
        """End the open track and adjust the window (returns ``None`` if there is no open
        track).

        If the update fails for any reason (a solver failure, a numerical error while freezing),
        every estimate (poses, covariances, frozen flags, connection status, priors) is put back
        as it was before the call, the track stays finished (the next update retries it inside
        its window: its measurements stay), the failure is counted
        (:attr:`n_failed_updates`, :attr:`stats`), its traceback kept (:attr:`last_failure`)
        and the returned result's ``reason`` starts with ``'failed'``. Only
        :class:`~ga_ros.errors.GaError` can escape, except with :attr:`strict`, where an
        exception that is not one of :data:`NUMERICAL_FAILURES` (a bug) is re-raised once the
        state is put back."""
        st = self.state
        if st.open_track is None or st.open_track in st.finished:
            return None
        # as stored: a pending recomputation of the last adjustment stays pending
        saved = Rollback.of(st, self.mutable_rows())
        fix_state = st.fixes.state()
        track, t0 = st.open_track, time.perf_counter()
        try:
            up = self._finish_track()
            if not str(up.reason).startswith('failed'):
                self.handoff.start()
                if self.online_calibration is not None:  # used by the next motions
                    self.online_calibration.start(st, self.config, self._calibration_executor())
                if self.config.freeze_ahead:
                    # computed for the next update: without the covariances if a refinement
                    # installed by that update replaces them
                    covs = not self._refinement_due(len(st.finished) + 1)
                    self.ahead.start(self.config.window_tracks, self._last(),
                                     lambda *a: self._plan_freeze(*a, covs))
                else:
                    self.ahead.drop()
                return up
            error = up.reason[len('failed: '):]
            trace = error
            bug = None
        except Exception as exc:  # noqa: BLE001 - a failed update must not end the survey
            error = f'{type(exc).__name__}: {exc}'
            trace = ''.join(traceback.format_exception(exc)).rstrip()
            bug = None if isinstance(exc, NUMERICAL_FAILURES) else exc
        saved.restore(st)
        st.n_failed_updates += 1
        st.last_failure = trace[-LAST_FAILURE_CHARS:]
        st.fixes.restore(fix_state)
        self.handoff.smoothing = None  # of a refinement installed by the failed update
        st.finished.add(track)
        st.n_updates += 1
        up = UpdateResult(track, 0, False, float('nan'), 1e3 * (time.perf_counter() - t0), 0, 0,
                          min(len(st.finished), self.config.window_tracks), 0,
                          f'failed: {error}')
        self._last_update = up
        if bug is not None and self.strict:
            raise bug
        return up

    def mutable_rows(self) -> tuple[int, int]:
        """``(node row, connection row)`` from which a window update can change the tables.

        An update changes the poses, covariances and frozen flags of the unfrozen tracks
        (window and leaving tracks: the adjustment, the freezes) and of the horizon of the
        refinement it may install (rows from the snapshot's ``first_node``), and the status of
        connections touching those nodes (gate, re-admission, absorption): the rows from the
        first unfrozen node, or from the snapshot's first node if lower
        (:meth:`WindowState.rows_from <ga_ros.core.window.state.WindowState.rows_from>`).
        Everything before stays as it is (retired and long-frozen tracks), whatever the
        survey's length (tested in ``test/core/window/test_window_scale.py``)."""
        lo, first = self.state.first_unfrozen(), self.handoff.first_row()
        return self.state.rows_from(lo if first is None else min(lo, first))

    def _finish_track(self) -> UpdateResult | None:
        """End the open track and adjust the window (returns ``None`` if there is no open
        track). On a solver failure the previous estimate stands and the result says why."""
        st = self.state
        if st.open_track is None or st.open_track in st.finished:
            return None
        t0 = time.perf_counter()  # the update's time includes waiting for a freeze ahead
        self.wait_background()  # before the BLAS limit below (a process-wide setting)
        if self.online_calibration is not None:
            # the estimate started by the last update if no motion has used it yet
            self.online_calibration.install(self.strict)
            if self.online_calibration.camera_step > 0.0:
                self._recorrect_cameras()
        with blas_threads():  # small dense blocks: threads only spin (ga_ros.runtime)
            return self._update(t0)

    def _update(self, t0: float | None = None) -> UpdateResult:
        st = self.state
        track = st.open_track
        st.finished.add(track)
        t0 = time.perf_counter() if t0 is None else t0
        finished = st.finished_order()
        window = finished[-self.config.window_tracks:]
        leaving = st.unfrozen_tail(finished[:-self.config.window_tracks])
        # a freeze's prior may be left to the refinement installed now (it replaces every
        # prior); only the last freeze's: the next freeze reads the priors
        plans: list[FreezePlan] = []
        for t in leaving:
            if plans:
                plans[-1] = self._prior_now(plans[-1])
            plans.append(self._freeze(t))
        installed = self.handoff.n_refinements
        refined = self.handoff.install_due()  # refinement due now (replaces the priors)
        self._deferred_priors(plans, self.handoff.n_refinements > installed)
        self._deferred_covariances(plans, self.handoff.n_refinements > installed)
        prev_weighted = st.T_weighted
        try:
            up = self._adjust(window, track, t0)
            if not str(up.reason).startswith('failed'):
                # before the smoothing moves the frozen nodes: whether the next refinement runs
                self.handoff.measure(prev_weighted, self.handoff.n_refinements > installed,
                                     self._factor_step)
            if refined is not None and not str(up.reason).startswith('failed'):
                error = self.handoff.smooth(self._last())
                (up.refined_after_tracks, up.refine_reason, up.refine_wait_ms) = refined
                if error:
                    up.refine_reason += f'; not smoothed: {error}'
        except GaError as exc:
            up = UpdateResult(track, 0, False, float('nan'), 1e3 * (time.perf_counter() - t0),
                              0, 0, len(window), 0, f'failed: {exc}')
        st.n_updates += 1
        self._last_update = up
        return up

    def _adjust(self, window_tracks: list[int], track: int, t0: float) -> UpdateResult:
        """The window adjustment (:meth:`WindowUpdate.adjust
        <ga_ros.core.window.update.WindowUpdate.adjust>`)."""
        book = self.online_variance
        self._factor_step = 0.0
        if book is not None:
            self._sync_fix_groups()  # the fixes added since: their source's factor
        up = self.updater.adjust(window_tracks, track, t0, self._factor_lock)
        if book is None:
            return up
        used = first = book.factors()  # those this adjustment used ('apply')
        new = self._record_variance()
        # the window is adjusted again with the new factors until they settle
        # (Förstner's iteration, one adjustment a step; the absorbed tracks' values stay those
        # of their last window)
        for _ in range(book.config.max_inner_iterations):
            if np.abs(np.log(new / used)).max(initial=0.0) < book.config.tolerance:
                break
            used = new
            up = self.updater.adjust(window_tracks, track, t0, self._factor_lock)
            new = self._record_variance()
        self._factor_step = factor_drift(first, new)
        return up

    def _record_variance(self) -> FloatArray:
        """Store the last window adjustment's weighted squared residuals (under the stated
        covariances) and redundancy numbers of its connections in :attr:`online_variance`
        (the quality control's, when it ran on this solution), then update the factors the
        next adjustments use (``'apply'``); returns them."""
        net, conns, priors = self.updater.problem
        res = self.updater.last()
        cached = self.updater.quality.last
        if cached is not None and cached[0] is res:
            red = cached[1].redundancy_numbers
        else:
            red = connection_redundancy(net, res, priors)
        W = self.updater.stated_terms(conns).weights
        v = res.residuals
        self.online_variance.record(conns, np.einsum('mi,mij,mj->m', v, W, v), red)
        self._record_fix_variance(res)
        return self._use_variance_factors()

    def _record_fix_variance(self, res: SolveResult) -> None:
        """Store the last window adjustment's values of the absolute fixes of its window nodes
        (:meth:`OnlineVarianceComponents.record_fixes
        <ga_ros.core.quality.online_variance.OnlineVarianceComponents.record_fixes>`): the
        weighted squared misclosure under the stated information and the redundancy number
        under the information used (0, 0 for an excluded fix)."""
        st, book = self.state, self.online_variance
        self._sync_fix_groups()
        fixes = [f for f in st.fixes.of_rows(st.last_window) if st.fixes.gated[f]]
        if not fixes:
            return
        rows = np.unique([st.fixes.rows[f] for f in fixes])
        with self._factor_lock:
            Q = res.covariance(st.idarr.a[rows])
        at = {int(r): a for a, r in enumerate(rows.tolist())}
        used = st.fixes.information_used(fixes)
        cost, red = np.zeros(len(fixes)), np.zeros(len(fixes))
        for i, f in enumerate(fixes):
            if st.fixes.status[f] != 0:
                continue
            r = st.fixes.rows[f]
            term = st.fixes.terms[f]
            known = term.fix.known
            e = sensor_misclosure(st.T[r], term.T_node_sensor, term.fix)[known]
            cost[i] = e @ st.fixes.info[f][np.ix_(known, known)] @ e
            J = sensor_jacobian(st.T[r], term.T_node_sensor)
            P = (J @ Q[at[r]] @ J.T)[np.ix_(known, known)]
            red[i] = known.sum() - np.trace(P @ used[i][np.ix_(known, known)])
        book.record_fixes(np.asarray(fixes, np.int64), cost, red)

    def _sync_fix_groups(self) -> None:
        """Register the fixes added since in the variance book (their source's group; the
        gauge prior none)."""
        book, fixes = self.online_variance, self.state.fixes
        for f in range(book.n_fixes, len(fixes)):
            book.register_fix(fixes.terms[f].fix.source if fixes.gated[f] else None)

    def _use_variance_factors(self) -> FloatArray:
        """The window adjustments and the refinements started from now on weight each
        connection by its group's current factor (fixed until the next adjustment). Returns
        the factors (per group)."""
        book = self.online_variance
        self._sync_fix_groups()
        factors = book.factors()
        self._factors_of = lambda rows: book.factors_of(rows, factors)
        self.updater.weight_factors = self._factors_of
        # the fixes' information divided by their source's factor (window, freeze, refinement)
        self.state.fixes.info_factors = lambda fixes: book.fix_factors_of(fixes, factors)
        return factors

    def _last(self) -> SolveResult | None:
        """The last window adjustment (recomputed on first use after a restore)."""
        return self.updater.last()

    @property
    def last_adjustment(self) -> SolveResult | None:
        """The last window adjustment (its estimate, normal system and covariances; ``None``
        before the first update)."""
        return self._last()

    # ---------------------------------------------------------------------- freezing
    def _freeze(self, track: int) -> FreezePlan:
        """Freeze a track leaving the window, using the last adjustment's estimate (the plan
        computed ahead in the background if it still applies, else computed now). A prior the
        plan left uncomputed (a refinement due now replaces it) is left to
        :meth:`_deferred_priors` (or :meth:`_prior_now`)."""
        plan = self.ahead.take(track)
        if plan is None:
            st = self.state
            plan = self._plan_freeze(track, self._last(), st.last_window, st.priors,
                                     len(st.ids), st.src.n,
                                     not self._refinement_due(len(st.finished)))
        install_freeze(self.state, plan)
        return plan

    def _prior_now(self, plan: FreezePlan) -> FreezePlan:
        """``plan`` with the prior it left uncomputed computed and added to the priors where
        :func:`~ga_ros.core.window.freeze.install_freeze` would have put it (nothing changed
        them since: called right after it)."""
        if plan.later_prior is None:
            return plan
        prior = plan.later_prior()
        self.state.priors.append(prior)
        return replace(plan, prior=prior, later_prior=None)

    def _plan_freeze(self, track: int, res: SolveResult | None, last_window: IntArray,
                     priors: list, n: int, nc: int, covariances: bool = True) -> FreezePlan:
        """The freeze of ``track`` under the configured policy
        (:meth:`FreezePolicy.plan <ga_ros.core.window.freeze.FreezePolicy.plan>`); changes
        nothing (it may run in the background thread of :attr:`ahead`). ``covariances=False``:
        the leaving nodes' covariances and the new prior are left to
        :meth:`_deferred_covariances` and :meth:`_deferred_priors`."""
        cfg = self.config
        # the last window's connections' terms, weighted as the window weighted them
        st, kept, factors = self.state, self.updater.terms, self.updater.weight_factors
        return self.policy.plan(st, track, res, last_window, priors, n, nc,
                                int(cfg.prior_band), int(cfg.prior_hubs), self._factor_lock,
                                covariances,
                                lambda rows: scaled_terms(connection_terms(st, kept, rows),
                                                          factors))

    def _refinement_due(self, n_finished: int) -> bool:
        """Whether a background refinement is due at the update of the ``n_finished``-th
        track: it is installed right after that update's freezes and replaces the covariances
        of every frozen node of its horizon (the leaving tracks' included), so those freezes
        need not compute them."""
        due = self.handoff.refiner.pending_due
        return due is not None and due <= n_finished

    def _deferred_priors(self, plans: list[FreezePlan], installed: bool) -> None:
        """The joint priors the freezes ``plans`` left uncomputed: nothing if a refinement
        was ``installed`` (its rebuilt priors replaced every prior, this freeze's absorbed terms
        included), else computed now and added where :func:`install_freeze
        <ga_ros.core.window.freeze.install_freeze>` would have put them (the last of the
        priors: only the update's last freeze defers), from the same rows and merged priors
        (the hand-off that did not install changed nothing)."""
        if not installed:
            for plan in plans:
                self._prior_now(plan)

    def _deferred_covariances(self, plans: list[FreezePlan], installed: bool) -> None:
        """The covariances the freezes ``plans`` left uncomputed (a refinement was due to
        replace them): kept from the refinement if it was ``installed`` and covers their nodes,
        else computed now from the last adjustment's factor (the same values a freeze computes:
        that factor is unchanged until this update's adjustment)."""
        res, f = self.handoff.smoothing or (None, 0)
        for plan in plans:
            rows = plan.cov_rows
            if plan.cov is not None or not rows.size:
                continue
            if (installed and res is not None and rows.min() >= f
                    and rows.max() < f + res.frozen.size and res.frozen[rows - f].all()):
                continue  # the refined covariances are installed
            self.state.cov[rows] = plan.covariances()

    def wait_background(self) -> float:
        """Wait until the freeze being computed ahead (``freeze_ahead``) and the online
        calibration's estimate running in a thread (``calibrate``) are ready; returns the CPU
        milliseconds they took (0 if none). Never needed for correctness: the next update
        waits for them anyway. A replay calls it to model the time a live survey has between
        track ends."""
        cal = 0.0 if self.online_calibration is None else self.online_calibration.wait()
        return self.ahead.wait() + cal

    def _calibration_executor(self) -> str:
        """Where the online calibration's estimate is solved: inline (at its installation) with
        ``refine_executor='inline'``, else in a background thread (the result is the same,
        :mod:`~ga_ros.core.window.calibration`)."""
        return 'inline' if self.config.refine_executor == 'inline' else 'thread'

    # ------------------------------------------------------------ background refinement
    def refinement_state(self) -> dict | None:
        """What a snapshot file needs to restart the pending refinement exactly (see
        :meth:`RefinementHandoff.pending <ga_ros.core.window.handoff.RefinementHandoff.pending>`;
        ``None`` if there is none to restart)."""
        return self.handoff.pending()

    def resume_refinement(self, state: dict | None) -> None:
        """Restart the refinement described by :meth:`refinement_state` (a restored aligner),
        from the same data, so the path continues as without the interruption."""
        self.handoff.resume(state)

    def close(self) -> None:
        """Stop the background refinement (a pending result is dropped) and wait for a freeze
        being computed ahead (kept); the aligner stays usable (a later refinement starts a new
        worker)."""
        self.handoff.close()
        self.wait_background()

    # ------------------------------------------------------------------------ output
    def corrected_path(self, from_row: int = 0) -> CorrectedPath:
        """Every node at its current estimate (frozen, window, or the open track's chain);
        ``from_row``: only the rows from it on (a copy of those rows alone, e.g. from
        :meth:`mutable_rows`, :class:`~ga_ros.pipeline.path_mirror.PathMirror`)."""
        st = self.state
        n = len(st.ids)
        lo = min(max(int(from_row), 0), n)
        return CorrectedPath(st.idarr.a[lo:].copy(), st.trackarr.a[lo:].copy(),
                             st.stamparr.a[lo:].copy(), st.T[lo:n].copy(),
                             st.frozen[lo:n].copy())

    def pose(self, node_id: int) -> FloatArray:
        """(4, 4) ``T_world_node`` of one node at its current estimate (a copy): what
        :meth:`corrected_path` holds for it, without copying the whole path."""
        k = self.state.index.get(int(node_id))
        if k is None:
            raise InputError(f'unknown node {node_id}')
        return self.state.T[k].copy()

    def covariance(self, node_id: int) -> FloatArray:
        """6x6 covariance ``[x y z rx ry rz]`` of a node's pose (right perturbation).

        Frozen nodes: the block stored when they froze. Window nodes: from the last
        adjustment. Nodes of the open track (not adjusted yet): the last adjusted covariance of
        their chain's start, propagated is not attempted; ``InputError`` is raised instead.
        """
        return covariance(self.state, self._last, node_id, self._factor_lock)

    def covariances(self, node_ids) -> FloatArray:
        """``(k, 6, 6)`` covariances of many nodes at once (see :meth:`covariance`).

        Window nodes are computed together from the last adjustment (selected inversion rather
        than one solve per node). Raises :class:`InputError` for an unknown node or one whose
        track is still open.
        """
        return covariances(self.state, self._last, node_ids, self._factor_lock)

    @property
    def newest_node_id(self) -> int | None:
        """Id of the newest node (``None`` before the first measurement)."""
        return int(self.state.idarr.a[-1]) if self.state.idarr.n else None

    @property
    def open_track(self) -> int | None:
        """The track being received (``None`` if none, or if it has finished)."""
        st = self.state
        return None if st.open_track in st.finished else st.open_track

    @property
    def n_failed_updates(self) -> int:
        """Window updates that failed over the whole survey (:meth:`finish_track`), kept in
        the state: a restart from the snapshot or the journal continues the count."""
        return self.state.n_failed_updates

    @property
    def last_failure(self) -> str:
        """The last failed update's exception and traceback (its last
        :data:`~ga_ros.core.window.state.LAST_FAILURE_CHARS` characters; ``''`` if none)."""
        return self.state.last_failure

    @property
    def stats(self) -> AlignerStats:
        """Counters and the last update's result."""
        st = self.state
        return AlignerStats(len(st.ids), st.src.n, dict(st.rejected),
                            st.finished_order()[-self.config.window_tracks:], st.n_updates,
                            st.n_outliers, self._last_update, self.n_failed_updates,
                            self.last_failure)

    def connection_arrays(self) -> tuple[IntArray, IntArray, FloatArray, BoolArray, IntArray]:
        """``(src_id, dst_id, z, cross, status)`` of every connection (status 0 active,
        1 absorbed into a marginal prior, 2 excluded as an outlier)."""
        st = self.state
        ids = st.idarr.a
        return (ids[st.src.a], ids[st.dst.a], st.z.a.copy(), st.cross.a.copy(),
                st.status.a.astype(np.int64))

    def connection_covariances(self) -> FloatArray:
        """(m, 6, 6) covariance of every connection, in the order of :meth:`connection_arrays`."""
        return self.state.ccov.full()

    def connection_w(self) -> FloatArray:
        """(m,) largest ``|w|`` (Baarda's w-test statistic) of every connection at the last
        window adjustment that contained it, in the order of :meth:`connection_arrays`; NaN
        when never tested (``quality`` off, untestable, or not adjusted since a reload)."""
        return self.updater.quality.connection_w(self.state.src.n)

    # --------------------------------------------------------------- batch refinement
    def refine_batch(self, max_iterations: int | None = None,
                     variance_groups: SourceGroups | None = None,
                     variance_config: VarianceComponentConfig | None = None,
                     calibration: CalibrationConfig | None = None) -> UpdateResult:
        """Full batch adjustment of every node with every kept connection (end of a survey).

        With ``variance_groups`` (the group of every measurement, by source), the variance
        factor of each group is estimated with the adjustment
        (:func:`~ga_ros.core.quality.variance_components.solve_with_variance_components`; the
        fixes are one group, ``fixes``) and the solution, its published covariances and
        :attr:`variance_components` use them; the connections' stored covariances, and so
        the later window updates, keep their stated values.

        With ``calibration``, each odometry source's additional parameters (scale, yaw rate)
        and each fix source's (:attr:`CalibrationConfig.fix_parameters`: time offset, offsets;
        the fixes then enter one by one) are estimated with the adjustment where the network
        determines them
        (:func:`~ga_ros.core.calibration.solve_with_calibration`; the sources of the
        consecutive motions from ``variance_groups`` if given, else one source ``motion``;
        cross-track connections get none, except those of a camera named in
        :attr:`CalibrationConfig.cameras`: every connection of its source gets its
        extrinsic's rotation) and :attr:`calibration` reports them; the refined
        poses use the corrected motions, the stored connections keep their measured ones.
        It takes the place of the variance components.

        The absolute fixes enter as weighted parameters relinearised at the solution until
        they stand (:meth:`_relinearized`), so a second call moves no pose by more than the
        solver's ``tolerance``. The open track is finished first. Outliers stay excluded. The
        covariances published afterwards come from this adjustment: frozen nodes get their
        marginal blocks from it (selected inversion), window nodes are answered from it like
        after a window update. The joint priors of the absorbed connections are rebuilt at the
        refined estimate (:func:`~ga_ros.core.window.refinement.absorbed_priors`), so the next
        window update continues from it consistently; a pending background refinement is
        dropped.
        """
        self.finish_track()
        self.ahead.drop()  # its inputs (estimate, priors) are replaced below
        st = self.state
        t0 = time.perf_counter()
        keep = np.nonzero(st.status.a != 2)[0]
        n = len(st.ids)
        z_net = None   # the stored motions, or with calibration the motions as measured
        scfg = self.config.solver_config()
        if max_iterations is not None:
            scfg = SolverConfig(**{**asdict(scfg), 'max_iterations': int(max_iterations)})
        free_datum = self.config.datum == 'fixes'
        fixed = [] if free_datum else [st.ids[0]]
        ids = st.idarr.a
        if calibration is not None:
            stamp = st.stamp.astype(np.float64)
            dt_s = (stamp[st.dst.a[keep]] - stamp[st.src.a[keep]]) * 1e-9
            if self.online_calibration is not None:  # the motions as measured
                z_net = self.online_calibration.measured(st.z.a[keep], dt_s, keep)
            cross = st.cross.a[keep]
            # each connection's source (a camera's cross-track connections are the camera's)
            names = (variance_groups.sources(ids[st.src.a[keep]], ids[st.dst.a[keep]],
                                             st.z.a[keep])
                     if variance_groups is not None else ['motion'] * keep.size)
            book = self.online_calibration
            if book is not None and book.source.n == st.src.n:
                # the odometry sources as booked: a motion the online calibration stored
                # corrected is not found by the groups' lookup by its stored motion
                names = [b if b is not None else n
                         for b, n in zip(book.sources_of(keep), names)]
            if book is not None and book.cameras and book.group.n == st.src.n:
                # the sources as booked (a camera's connections are stored corrected, so the
                # groups' lookup by the stored motion does not find them)
                g = book.group.a[keep]
                names = [book.group_names[i] if i >= 0 else n
                         for i, n in zip(g.tolist(), names)]
            sources = [None if c else g for g, c in zip(names, cross.tolist())]
            # the fixes one by one for their sources' parameters (offset, time offset): their
            # priors are the book's bit for bit, so nothing changes where none is estimated
            # (as measured: the online calibration's shifts undone, so the whole correction is
            # estimated)
            fix_obs = (book_observations(st.fixes, np.arange(n), stamp[:n] * 1e-9,
                                         None if self.online_calibration is None else
                                         self.online_calibration.fix_shifts(len(st.fixes)))
                       if calibration.fix_parameters and st.fixes.terms else None)
        elif variance_groups is not None:
            groups = variance_groups.of(ids[st.src.a[keep]], ids[st.dst.a[keep]], st.z.a[keep])
        cov_net = None  # with calibration, the stated covariances (its noise factors relative)
        if (calibration is not None and self.online_calibration is not None
                and self.online_calibration.covs_changed()):
            cov_net = self.online_calibration.stated(st.ccov.a[keep], keep)
        # from the aligner's arrays, checked at insertion (no per-connection validation and
        # duplicate bookkeeping: ~0.5 GB and minutes less at 100,000 poses)
        net = st.subnetwork(np.arange(n), keep, cov=cov_net, z=z_net)

        def adjust(T0: FloatArray, priors: list) -> SolveResult:
            """One adjustment from ``T0`` with the fixes' priors ``priors``."""
            if calibration is not None:
                if fix_obs is not None:   # the fixes as observations, the gauge a prior
                    priors = [p for p in priors if p.weak]
                res, self.calibration = solve_with_calibration(
                    net, T0, sources, dt_s, scfg, fixed=fixed, priors=priors,
                    calibration=calibration, fixes=fix_obs, groups=names,
                    stamps_s=stamp[st.src.a[keep]] * 1e-9)
                return res
            if variance_groups is None:
                return solve(net, T0, scfg, fixed=fixed, priors=priors)
            res, self.variance_components = solve_with_variance_components(
                net, T0, groups, scfg, fixed=fixed, priors=priors,
                prior_groups=['fixes'] * len(priors), config=variance_config,
                split=variance_groups.split())
            return res

        res = self._relinearized(adjust, st.T[:n].copy(), scfg, n)
        net = None  # its arrays freed before the covariances (the closure holds the name)
        st.T[:n] = res.T_world_node
        frozen = np.nonzero(st.frozen[:n] & ((np.arange(n) != 0) | free_datum))[0]
        if frozen.size:
            st.cov[frozen] = res.covariance(st.idarr.a[frozen])
        # the joint priors of the absorbed connections, relinearised at the refined estimate
        # (their old means would pull the next window update back to the online estimate)
        self.handoff.drop()
        # the next refinement starts from the whole survey again (a past prior linearised at
        # the old estimate would pull the retired tracks' boundary back)
        st.retired, st.past, st.refine_drift = 0, [], 0.0
        with blas_threads():
            st.priors = [JointPrior.absorbed(p) for p in
                         absorbed_priors(self.handoff.snapshot(whole=True), st.T[:n])]
        self.updater.set_last(res)
        st.last_window = np.nonzero(~st.frozen[:n])[0]
        st.T_weighted = no_weighted()
        return UpdateResult(-1, res.iterations, res.converged, res.sigma0_sq,
                            1e3 * (time.perf_counter() - t0), n, int(keep.size),
                            len(st.tracks), 0, res.reason, 0, res.n_unknowns)

    def _relinearized(self, adjust, T0: FloatArray, scfg: SolverConfig, n: int) -> SolveResult:
        """``adjust(T, priors)`` (one batch adjustment of the ``n`` nodes from ``T``) with the
        fixes' priors relinearised at its solution until they stand: a fix's prior
        (:func:`~ga_ros.core.fixes.node_prior`) is linear about the pose it was computed at
        (its mean and, with an offset to the sensor or a partial information, its information
        depend on it), so the adjustment is repeated from its own solution with the priors
        recomputed there until the largest change of a pose (m, rad) is below the solver's
        ``tolerance`` (at most ``max_iterations`` times). Without fixes: one adjustment.
        The result's ``iterations`` count every Gauss-Newton iteration of them."""
        st = self.state
        rows = np.arange(n)
        priors = st.fixes.priors(rows, T0, st.idarr.a)
        res = adjust(T0, priors)
        if not priors:
            return res
        iterations = res.iterations
        for _ in range(scfg.max_iterations):
            T1 = res.T_world_node
            priors = st.fixes.priors(rows, T1, st.idarr.a)
            nxt = adjust(T1.copy(), priors)
            iterations += nxt.iterations
            T2 = nxt.T_world_node
            dR = np.einsum('nji,njk->nik', T1[:, :3, :3], T2[:, :3, :3])
            moved = max(np.abs(T2[:, :3, 3] - T1[:, :3, 3]).max(initial=0.0),
                        np.abs(so3.log(dR)).max(initial=0.0))
            res = nxt
            if moved < scfg.tolerance:
                break
        res.iterations = iterations
        return res

