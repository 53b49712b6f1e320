"""Self-calibration online: each odometry source's additional parameters (scale and yaw-rate
corrections, :mod:`ga_ros.core.calibration`) and each fix source's (time offset, offsets:
``AlignerConfig.calibration_fix_parameters``) estimated while the survey runs and applied to
the source's motions and fixes as they enter the window.

The scheme (``docs/calibration.md``, *Online*). After each successful window update the
parameters are estimated again (:class:`HorizonEstimate`, off the update's critical path) by
the batch self-calibration,
:func:`~ga_ros.core.calibration.solve_with_calibration` (the same estimate and the same tests
of what the network determines and what is significant), on a horizon of the latest
``calibration_horizon_tracks`` finished tracks: their nodes at their current estimates, the
connections among them with the motions *as measured*, the absolute fixes on those nodes and a
weak gauge prior on the horizon's first node (the ``gauge_*`` sigmas of ``datum='fixes'``).
The estimate replaces the previous one (the horizon is the estimator's memory: a parameter
that drifts slowly is followed with the horizon's lag, the role a random walk's process noise
plays in a filter; estimates of overlapping horizons are not fused, which would count the
same motions twice). Each measured motion ``z`` of a source (its consecutive motions only:
cross-track connections and bridges have no parameters) that enters the window afterwards is
stored corrected, ``T_corr = [R Rz(omega dt), (1 + k) t]`` with the source's estimated
parameters (0 where not estimated), and its applied ``(k, omega)`` is kept per connection, so
the motion as measured is always recoverable (:meth:`OnlineCalibration.measured`): the next
horizon estimate and the final batch's calibration start from it.

The fixes alike. The horizon's fixes enter the estimate one by one and as measured
(:func:`~ga_ros.core.calibration.book_observations` with the booked shifts undone), with the
fix parameters of :func:`online_calibration_config`. A fix that enters the window afterwards
is stored with the batch's correction
(:func:`~ga_ros.core.calibration.fix_parameters.fix_shift`), ``p_fix - b + v tau`` with its
source's estimated offset ``b`` and time offset ``tau`` and its node's velocity ``v`` by the
batch's definition over the nodes there are (:meth:`OnlineCalibration.corrected_fix`); the
applied parameters and the shift are kept per fix (:attr:`OnlineCalibration.fix_shift`).

The cameras, with ``calibrate_cameras``: the estimate includes each named camera's extrinsic
rotation ``phi`` (:func:`camera_estimate_inputs`, every connection of its source, consecutive
and cross-track), and a connection of the camera that enters afterwards is stored conjugated,
``X T X^-1`` with ``X = [exp(phi), 0]`` after the odometry's correction (the batch's
``X S(T_meas) X^-1``, :meth:`OnlineCalibration.camera_corrected`); the applied ``phi`` is kept
per connection (:attr:`OnlineCalibration.camera_applied`, booked only with cameras named) and
undone first by :meth:`OnlineCalibration.measured`. Its covariance is transformed alike,
``Ad_X C Ad_X^T`` (:meth:`OnlineCalibration.camera_cov`; undone by
:meth:`OnlineCalibration.stated`). At the next update after an estimate that changed the
rotation (:attr:`OnlineCalibration.camera_step`) the camera's connections stored before, as
far as they have not retired from the refinement's horizon, are corrected with it too
(:meth:`OnlineCalibration.recorrect_cameras`, called by the aligner, which also asks the
refinement to rebuild the frozen tracks' priors from them).

The noise, with ``calibration_noise``: the estimate re-estimates the calibrated sources'
variance factors (the batch's ``CalibrationConfig.noise``) from the stated covariances (the
applied factors undone, :meth:`OnlineCalibration.stated`), and a motion that enters afterwards
is stored with its stated covariance scaled by them (:meth:`OnlineCalibration.scaled_cov`),
the factors kept per connection (:attr:`OnlineCalibration.noise_applied`).

Where the estimate runs (:meth:`OnlineCalibration.start`, :meth:`OnlineCalibration.install`).
Its inputs are copied right after the update ``k`` that triggers it; it is solved in a
background thread (``executor='thread'``) or at the installation (``'inline'``), and installed
when the first odometry motion (or fix, with fix parameters) after that update enters (or at
the next update's start if none did), waiting for it there if it is not ready. Every motion
(and fix) is thus corrected with the estimate of the last update before it, as if the estimate
had run inside the update, and which estimate that is depends on the order of the data only,
never on the thread's timing: a replay and a live node, and both executors, give the same path
bit for bit. The update returns (and is
published) before the estimate is solved; a track that ends at a fix gives the estimate the
time until the next motion.

Everything here is part of the window state: a snapshot saves it (an estimate still pending
is finished and saved with its result, installed at the same update after a restart) and a
journal replay reproduces it (the estimate runs at the same track ends from the same state).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, fields, replace

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.calibration import (
    FIX_PARAMETERS,
    AdditionalParameter,
    CalibrationConfig,
    CalibrationReport,
    FixObservations,
    NoiseFactor,
    book_observations,
    corrected_motions,
    solve_with_calibration,
)
from ga_ros.core.calibration.camera_parameters import (
    CAMERA_PARAMETERS,
    conjugated_covariances,
    conjugations,
)
from ga_ros.core.calibration.fix_parameters import node_velocity
from ga_ros.core.fixes import FixTerm, gauge_information
from ga_ros.core.measurement import Measurement, variance_group
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior, SolverConfig
from ga_ros.core.window.storage import Rows, pack_sym6
from ga_ros.errors import GaError, InputError
from ga_ros.geometry import se3
from ga_ros.runtime import background_blas_limit, blas_threads

#: Where a horizon estimate is solved (:meth:`OnlineCalibration.start`): in a background thread
#: while the next track is flown, or inline at its installation (before the next odometry motion).
CALIBRATION_EXECUTORS = ('thread', 'inline')

#: The failures of the data that keep the previous estimate (counted, :attr:`OnlineCalibration.
#: n_failed`); any other exception is a bug, counted alike, and re-raised at the installation
#: by a strict aligner (``GA_ROS_STRICT_UPDATES``).
DATA_FAILURES = (GaError, np.linalg.LinAlgError, FloatingPointError)

#: The online estimate's settings: the batch's tests; the stated noise kept unless
#: ``calibration_noise`` (:func:`online_calibration_config`); the parameters' steps stop
#: once every one moves less than 1 % of its sigma (the batch: 0.1 %): the test statistic
#: ``|value| / (sigma0 sigma)`` moves by 0.01 at most against a critical value of ~3.3, and a
#: horizon estimate takes ~10 % fewer solves (``docs/calibration.md``).
ONLINE_CALIBRATION = CalibrationConfig(noise=False, tolerance=1e-2)

#: The fix parameters of a fix source's book row (:attr:`OnlineCalibration.fix_applied`): the
#: offset ``b`` (m, map) per axis, then the time offset ``tau`` (s).
FIX_SLOTS = ('offset_x', 'offset_y', 'offset_z', 'time_offset')


def online_calibration_config(config) -> CalibrationConfig:
    """The horizon estimate's settings for an aligner ``config``
    (:class:`~ga_ros.core.window.AlignerConfig`): :data:`ONLINE_CALIBRATION` with the fix
    sources' parameters and references of ``calibration_fix_parameters`` and
    ``calibration_fix_reference``."""
    fix, ref = config.calibration_fix_config()
    return replace(ONLINE_CALIBRATION, fix_parameters=fix, fix_reference=ref,
                   noise=bool(config.calibration_noise))


def noise_scale(factors: FloatArray) -> FloatArray:
    """(m, 6) the square roots of the variance factors ``(s_t, s_r)`` (m, 2) on the rows
    ``[x y z rx ry rz]``: a covariance ``C`` scaled is ``D C D``, ``D = diag(d)``."""
    f = np.sqrt(np.asarray(factors, dtype=float).reshape(-1, 2))
    return np.repeat(f, 3, axis=1)


def calibration_source(m: Measurement) -> str | None:
    """The odometry source whose parameters correct a measurement: its source for a
    consecutive motion (``motion`` when unnamed, as
    :func:`~ga_ros.core.measurement.variance_group` names it); ``None`` for cross-track
    connections and bridges."""
    return variance_group(m) if m.kind == 'consecutive' else None


@dataclass
class HorizonEstimate:
    """One horizon estimate: its inputs, copied from the state after the update that started
    it (nothing here refers to the state's arrays), and, once :meth:`run`, its result.

    Attributes
    ----------
    network, T_init, sources, dt_s, solver, priors, fixes, calibration : the arguments of
        :func:`~ga_ros.core.calibration.solve_with_calibration` (the horizon's connections with
        their motions as measured, its poses at their current estimates, each connection's
        source, durations in s, the solver's settings, the gauge prior (and the fixes' priors
        when no fix parameter is a candidate), the fixes one by one as measured (``None``: in
        ``priors``) and the settings, :func:`online_calibration_config`).
    cameras, groups : the cameras whose extrinsic rotation the estimate includes and every
        connection's source (cross-track ones too: :func:`camera_estimate_inputs`); ``()``,
        ``None``: none.
    report : the estimate (``None`` before :meth:`run`, or if it failed).
    error : why it failed (a data failure, :data:`DATA_FAILURES`, or another error);
        ``None`` if it did not.
    done : whether :meth:`run` finished; cpu_ms : the CPU milliseconds it took (its thread).
    """

    network: ConnectionNetwork
    T_init: FloatArray
    sources: list
    dt_s: FloatArray
    solver: SolverConfig
    priors: list
    fixes: FixObservations | None = None
    calibration: CalibrationConfig = ONLINE_CALIBRATION
    report: CalibrationReport | None = None
    error: BaseException | None = None
    done: bool = False
    cpu_ms: float = 0.0
    thread: threading.Thread | None = field(default=None, repr=False)
    cameras: tuple[str, ...] = ()
    groups: list | None = None

    def run(self) -> None:
        """Solve the estimate (in the calling thread; BLAS as that thread has it)."""
        c0 = time.thread_time()
        cal = (replace(self.calibration, cameras=self.cameras) if self.cameras
               else self.calibration)
        try:
            _, self.report = solve_with_calibration(
                self.network, self.T_init, self.sources, self.dt_s, self.solver, fixed=[],
                priors=self.priors, calibration=cal, fixes=self.fixes, groups=self.groups)
        except BaseException as exc:  # noqa: BLE001 - judged at the installation
            self.error = exc
        self.cpu_ms = 1e3 * (time.thread_time() - c0)
        self.done = True

    def wait(self) -> None:
        """Until the result is there: the thread joined, or (inline, or a thread never
        started) solved now under the update's BLAS limit."""
        if self.thread is not None:
            self.thread.join()
        if not self.done:
            with blas_threads():
                self.run()

    @classmethod
    def finished(cls, report: CalibrationReport | None) -> HorizonEstimate:
        """A finished estimate restored from a state file (``None``: one that failed)."""
        est = cls(None, np.zeros((0, 4, 4)), [], np.zeros(0), SolverConfig(), [],
                  report=report,
                  error=None if report is not None else GaError('the saved estimate failed'))
        est.done = True
        return est


class OnlineCalibration:
    """The online calibration's book (module doc): per connection row the source it belongs to
    (``-1``: no parameters) and the ``(k, omega)`` applied when it entered; the last estimate
    (:attr:`report`), the number of estimates and of failed ones.

    Attributes
    ----------
    names : the odometry sources, in the order they appeared.
    report : the last horizon estimate (:class:`~ga_ros.core.calibration.CalibrationReport`:
        every parameter's value, sigma, test, or why it is not estimated); ``None`` before the
        first.
    n_estimates : horizon estimates started; n_failed : those that failed (the previous
        estimate kept).
    pending : the estimate started after the last update, installed before the next odometry
        motion (:meth:`install`); ``None``: none.
    last_conns, last_horizon : the connection rows when the last estimate ran and the
        connections its horizon held (when the next one is due,
        ``AlignerConfig.calibration_refresh``).
    fix_applied, fix_shift : per fix of the aligner's fix book (its index; the gauge prior
        and fixes added before any correction: zeros) the fix parameters applied when it
        entered (``b_x, b_y, b_z`` m, ``tau`` s: :data:`FIX_SLOTS`) and the resulting shift of
        its position (m, map): stored ``p_fix - b + v tau``, ``v`` its node's velocity then
        (:meth:`corrected_fix`).
    noise_applied : per connection row the variance factors ``(s_t, s_r)`` of its source's
        translation and rotation (both the same for a ``motion`` part) its stored covariance
        was scaled with when it entered (1, 1: as stated; ``calibration_noise``).
    """

    def __init__(self) -> None:
        self.names: list[str] = []
        self.source = Rows((), np.int64)
        self.applied = Rows((2,), np.float64)
        self.noise_applied = Rows((2,), np.float64)
        self._noise_current: dict[str, tuple[float, float]] = {}
        self.report: CalibrationReport | None = None
        self.n_estimates = 0
        self.n_failed = 0
        self.last_conns = 0  # connection rows at the last estimate
        self.last_horizon = 0  # the connections its horizon held
        self._current: dict[str, tuple[float, float]] = {}
        self.fix_applied = Rows((4,), np.float64)
        self.fix_shift = Rows((3,), np.float64)
        self._fix_current: dict[str, FloatArray] = {}
        self.pending: HorizonEstimate | None = None
        #: the cameras the estimates include (``AlignerConfig.calibrate_cameras``; set by the
        #: aligner, not saved) and every connection's source, cross-track ones too
        #: (:func:`camera_estimate_inputs`)
        self.cameras: tuple[str, ...] = ()
        self.group_names: list[str] = []
        self.group = Rows((), np.int64)
        #: per connection row (booked only with cameras named) the extrinsic rotation ``phi``
        #: (rad, body frame) of its camera it was stored corrected with (zeros: as measured;
        #: :meth:`camera_corrected`)
        self.camera_applied = Rows((3,), np.float64)
        self._camera_current: dict[str, FloatArray] = {}
        #: the change of the cameras' applied rotation at the installations since the last
        #: update, in the estimates' sigmas (the largest over the axes; 0: unchanged), until
        #: the next update corrects the connections stored before (:meth:`recorrect_cameras`)
        self.camera_step = 0.0

    # ----------------------------------------------------------------------- input
    def correction(self, source: str | None) -> tuple[float, float]:
        """``(k, omega)`` (1, rad/s) applied to a motion of ``source`` now (0 where not
        estimated; ``None``: a connection without parameters)."""
        if source is None:
            return 0.0, 0.0
        return self._current.get(source, (0.0, 0.0))

    def corrected(self, z: FloatArray, dt_s: float, source: str | None
                  ) -> tuple[FloatArray, tuple[float, float]]:
        """``(z_corr, (k, omega))``: the measured motion ``z`` (6,) ``[t, rotvec]`` of
        ``T_src_dst`` over ``dt_s`` seconds corrected by ``source``'s current estimate
        (``z`` itself, unchanged, where nothing is estimated)."""
        k, w = self.correction(source)
        if k == 0.0 and w == 0.0:
            return z, (0.0, 0.0)
        T = corrected_motions(np.asarray(z, float)[None], np.array([max(dt_s, 0.0)]),
                              np.array([k]), np.array([w]))
        return se3.to_translation_rotvec(T)[0], (k, w)

    def camera_correction(self, camera: str | None) -> FloatArray:
        """(3,) the extrinsic rotation ``phi`` (rad, body frame) applied to a connection of
        ``camera`` now (zeros where not estimated; ``None``: not a named camera)."""
        cur = None if camera is None else self._camera_current.get(camera)
        return np.zeros(3) if cur is None else cur.copy()

    def camera_corrected(self, z: FloatArray, camera: str | None
                         ) -> tuple[FloatArray, FloatArray]:
        """``(z_corr, phi)``: a connection's motion ``z`` (6,) ``[t, rotvec]`` (as measured, or
        already corrected by :meth:`corrected`) conjugated by its camera's current extrinsic
        rotation, ``X T X^-1`` with ``X = [exp(phi), 0]``
        (:mod:`~ga_ros.core.calibration.camera_parameters`), the batch's ``X S(T_meas) X^-1``;
        ``z`` itself where nothing is estimated."""
        phi = self.camera_correction(camera)
        if not phi.any():
            return z, phi
        X = conjugations(phi)[0]
        T = X @ se3.from_translation_rotvec(np.asarray(z, float)[None, :3],
                                            np.asarray(z, float)[None, 3:])[0] @ se3.inverse(X)
        return se3.to_translation_rotvec(T[None])[0], phi

    def camera_cov(self, cov: FloatArray, phi: FloatArray) -> FloatArray:
        """(6, 6) the covariance of a connection conjugated by ``X = [exp(phi), 0]``
        (:meth:`camera_corrected`): ``Ad_X C Ad_X^T``
        (:func:`~ga_ros.core.calibration.camera_parameters.conjugated_covariances`); ``cov``
        itself where ``phi`` is zero."""
        if not np.asarray(phi).any():
            return cov
        return conjugated_covariances(cov, phi)[0]

    def recorrect_cameras(self, state, rows: IntArray) -> IntArray:
        """Correct the stored connections of the named cameras among the connection rows
        ``rows`` of ``state`` with their camera's current rotation: each one's motion as its
        booked rotation left it is brought back (``X_old^-1 T X_old``) and conjugated by the
        current ``X`` (its covariance alike, :meth:`camera_cov`), and the current ``phi``
        booked for it. Rows already at the current rotation are left as they are. Returns the
        rows changed."""
        rows = np.asarray(rows, dtype=np.int64)
        rows = rows[rows < min(self.group.n, self.camera_applied.n)]
        if not rows.size or not self.cameras:
            return np.zeros(0, dtype=np.int64)
        g = self.group.a[rows]
        phi = np.zeros((rows.size, 3))
        mine = np.zeros(rows.size, dtype=bool)
        for cam in self.cameras:
            if cam in self.group_names:
                sel = g == self.group_names.index(cam)
                phi[sel] = self.camera_correction(cam)
                mine |= sel
        old = self.camera_applied.a[rows]
        sel = np.nonzero(mine & (phi != old).any(axis=1))[0]
        if not sel.size:
            return np.zeros(0, dtype=np.int64)
        r, phi, old = rows[sel], phi[sel], old[sel]
        X_old, X_new = conjugations(old), conjugations(phi)
        T = se3.from_translation_rotvec(state.z.a[r, :3], state.z.a[r, 3:])
        T = X_new @ se3.inverse(X_old) @ T @ X_old @ se3.inverse(X_new)
        state.z.a[r] = se3.to_translation_rotvec(T)
        cov = conjugated_covariances(state.ccov.a[r], old, inverse=True)
        state.ccov.packed[r] = pack_sym6(conjugated_covariances(cov, phi))
        self.camera_applied.a[r] = phi
        return r

    def register_camera(self, phi: FloatArray) -> None:
        """Book a new connection row's applied extrinsic rotation (with cameras named, after
        :meth:`register`; the rows before it that were not booked: zeros)."""
        while self.camera_applied.n < self.source.n - 1:
            self.camera_applied.append(np.zeros(3))
        self.camera_applied.append(np.asarray(phi, dtype=float))

    def noise_factors(self, source: str | None) -> tuple[float, float]:
        """``(s_t, s_r)``: the variance factors of ``source``'s translation and rotation
        applied to its motions now (1 where not re-estimated; ``None``: none)."""
        if source is None:
            return 1.0, 1.0
        return self._noise_current.get(source, (1.0, 1.0))

    def scaled_cov(self, cov: FloatArray, source: str | None
                   ) -> tuple[FloatArray, tuple[float, float]]:
        """``(cov_used, (s_t, s_r))``: a motion's stated covariance (6, 6) scaled by its
        source's current variance factors (``D C D``, :func:`noise_scale`; ``cov`` itself
        where they are 1)."""
        s = self.noise_factors(source)
        if s == (1.0, 1.0):
            return cov, s
        d = noise_scale(np.array(s))[0]
        return d[:, None] * np.asarray(cov, dtype=float) * d[None, :], s

    def covs_changed(self) -> bool:
        """Whether a stored covariance differs from its stated one (a variance factor, or a
        camera's rotation, applied): :meth:`stated` then recovers them."""
        return bool((self.noise_applied.a != 1.0).any() or self.camera_applied.a.any())

    def _camera_rows(self, conns: IntArray) -> IntArray:
        """Positions in ``conns`` of the connection rows stored with a camera's rotation
        applied (a non-zero booked rotation)."""
        if not self.camera_applied.n:
            return np.zeros(0, dtype=np.intp)
        inside = np.nonzero(conns < self.camera_applied.n)[0]
        phi = self.camera_applied.a[conns[inside]]
        return inside[(phi != 0.0).any(axis=1)]

    def stated(self, cov: FloatArray, conns: IntArray) -> FloatArray:
        """(m, 6, 6) the stated covariances of connection rows ``conns`` from their stored
        ones ``cov`` (m, 6, 6): the applied variance factors and a camera's applied rotation
        undone (``D`` and ``Ad_X`` commute: ``D`` is a scalar per 3x3 block; rows stored as
        stated are returned as stored)."""
        conns = np.asarray(conns)
        sel = self._camera_rows(conns)
        if sel.size:
            cov = np.array(cov, dtype=float)
            cov[sel] = conjugated_covariances(cov[sel], self.camera_applied.a[conns[sel]],
                                              inverse=True)
        n = self.noise_applied.n
        fac = np.ones((len(conns), 2))
        inside = np.asarray(conns) < n
        fac[inside] = self.noise_applied.a[np.asarray(conns)[inside]]
        sel = np.nonzero((fac != 1.0).any(axis=1))[0]
        if not sel.size:
            return cov
        out = np.array(cov, dtype=float)
        d = 1.0 / noise_scale(fac[sel])
        out[sel] = d[:, :, None] * out[sel] * d[:, None, :]
        return out

    def register(self, source: str | None, applied: tuple[float, float],
                 noise: tuple[float, float] = (1.0, 1.0)) -> None:
        """Book a new connection row: its source (``None``: no parameters), the correction
        it was stored with and the variance factors its covariance was scaled with."""
        while self.noise_applied.n < self.source.n:  # a book saved without them: as stated
            self.noise_applied.append((1.0, 1.0))
        self.noise_applied.append(noise)
        if source is None:
            g = -1
        else:
            if source not in self.names:
                self.names.append(source)
            g = self.names.index(source)
        self.source.append(g)
        self.applied.append(applied)

    def register_group(self, name: str) -> None:
        """Book a new connection row's source, consecutive or cross-track
        (:func:`~ga_ros.core.measurement.source_or_group`; '' unknown), after :meth:`register`:
        the camera connections of :func:`camera_estimate_inputs`."""
        if name and name not in self.group_names:
            self.group_names.append(name)
        self.group.append(self.group_names.index(name) if name else -1)

    def sources_of(self, conns: IntArray) -> list[str | None]:
        """The source of each connection row (``None``: no parameters)."""
        g = self.source.a[conns]
        return [self.names[i] if i >= 0 else None for i in g.tolist()]

    def measured(self, z: FloatArray, dt_s: FloatArray, conns: IntArray) -> FloatArray:
        """(m, 6) the motions as measured of connection rows ``conns`` from their stored
        (corrected) ``z`` (m, 6) and durations ``dt_s`` (m,) s: the applied correction undone
        (a camera's extrinsic rotation first, ``X^-1 T X``; then ``t / (1 + k)``,
        ``R Rz(-omega dt)``; rows stored uncorrected are returned as stored)."""
        z = np.array(z, dtype=float)
        conns = np.asarray(conns)
        sel = self._camera_rows(conns)
        if sel.size:
            X = conjugations(self.camera_applied.a[conns[sel]])
            T = se3.from_translation_rotvec(z[sel, :3], z[sel, 3:])
            z[sel] = se3.to_translation_rotvec(se3.inverse(X) @ T @ X)
        kw = self.applied.a[conns]
        sel = np.nonzero((kw != 0.0).any(axis=1))[0]
        if sel.size:
            k, w = kw[sel, 0], kw[sel, 1]
            T = corrected_motions(z[sel], np.maximum(dt_s[sel], 0.0), 1.0 / (1.0 + k) - 1.0,
                                  -w)
            z[sel] = se3.to_translation_rotvec(T)
        return z

    def fix_correction(self, source: str) -> FloatArray:
        """(4,) the fix parameters ``b_x, b_y, b_z`` (m) and ``tau`` (s) applied to a fix of
        ``source`` now (0 where not estimated)."""
        cur = self._fix_current.get(source)
        return np.zeros(4) if cur is None else cur.copy()

    def corrected_fix(self, term: FixTerm, T_world_node: FloatArray, stamps_s: FloatArray,
                      row: int) -> tuple[FixTerm, FloatArray, FloatArray]:
        """``(term_corr, shift (3,), applied (4,))``: a fix entering the window corrected by its
        source's current estimate, as the batch corrects it
        (:func:`~ga_ros.core.calibration.fix_parameters.fix_shift`): its measured position
        moved by ``shift = -b + v tau``, ``v`` (m/s, map) its node's velocity from the node's
        neighbours in time at their current estimates
        (:func:`~ga_ros.core.calibration.fix_parameters.node_velocity` of the node ``row`` over
        the poses ``T_world_node`` (n, 4, 4) and stamps ``stamps_s`` (n,) s of every node so
        far: one-sided for the newest node). ``term`` itself where nothing is estimated."""
        c = self.fix_correction(term.fix.source)
        if not c.any():
            return term, np.zeros(3), c
        shift = -c[:3]
        if c[3] != 0.0:
            shift = shift + node_velocity(T_world_node, stamps_s, row) * c[3]
        if not shift.any():
            return term, shift, c
        T = np.array(term.fix.T_map_sensor, dtype=float)
        T[:3, 3] += shift
        return replace(term, fix=replace(term.fix, T_map_sensor=T)), shift, c

    def register_fix(self, index: int, shift: FloatArray, applied: FloatArray) -> None:
        """Book the fix of index ``index`` in the aligner's fix book with the shift and
        parameters it was stored with (the rows before it that were not booked: zeros)."""
        self._pad_fixes(index)
        self.fix_shift.append(np.asarray(shift, dtype=float))
        self.fix_applied.append(np.asarray(applied, dtype=float))

    def _pad_fixes(self, n: int) -> None:
        while self.fix_shift.n < n:
            self.fix_shift.append(np.zeros(3))
            self.fix_applied.append(np.zeros(4))

    def fix_shifts(self, n: int) -> FloatArray:
        """(n, 3) the shift each of the first ``n`` fixes of the fix book was stored with
        (zeros for those not booked)."""
        out = np.zeros((n, 3))
        m = min(n, self.fix_shift.n)
        out[:m] = self.fix_shift.a[:m]
        return out

    # -------------------------------------------------------------------- estimate
    def start(self, state, config, executor: str = 'thread') -> HorizonEstimate | None:
        """After a successful update: if due (``config.calibration_refresh``), copy the inputs
        of a new estimate on the horizon of ``config.calibration_horizon_tracks`` finished
        tracks of ``state`` (module doc) and start it: in a background thread
        (``executor='thread'``) or left for :meth:`install` (``'inline'``). It is used from
        the next odometry motion on (:meth:`install`). Returns it (``None``: none due)."""
        if executor not in CALIBRATION_EXECUTORS:
            raise InputError(f'the online calibration runs in one of {CALIBRATION_EXECUTORS}, '
                             f'not {executor!r}')
        if self.pending is not None:
            self.install()  # never more than one (a caller that skipped an installation)
        job = self._inputs(state, config)
        if job is None:
            return None
        self.pending = job
        if executor == 'thread':
            background_blas_limit()
            job.thread = threading.Thread(target=job.run, daemon=True,
                                          name='ga_ros-calibration')
            job.thread.start()
        return job

    def _inputs(self, state, config) -> HorizonEstimate | None:
        """The inputs of the estimate due now (copies), counted; ``None`` if none is due."""
        if state.src.n - self.last_conns < config.calibration_refresh * self.last_horizon:
            return None
        finished = state.finished_order()
        horizon = finished[-int(config.calibration_horizon_tracks):]
        if not horizon or self.source.n == 0 or not (self.source.a >= 0).any():
            return None
        rows = _track_rows(state, horizon)
        if rows.size < 2:
            return None
        lo = int(rows[0])
        conns = state.horizon_rows(lo)
        conns = conns[np.isin(state.src.a[conns], rows) & np.isin(state.dst.a[conns], rows)
                      & (state.status.a[conns] != 2)]
        if not conns.size:
            return None
        stamp = state.stamp.astype(np.float64)
        dt_s = (stamp[state.dst.a[conns]] - stamp[state.src.a[conns]]) * 1e-9
        z = self.measured(state.z.a[conns], dt_s, conns)
        cov = None
        if self.covs_changed():  # the stated covariances (factors relative)
            cov = self.stated(state.ccov.a[conns], conns)
        net = state.subnetwork(rows, conns, cov=cov, z=z)
        ids = state.idarr.a
        cal = online_calibration_config(config)
        fixes = None
        if cal.fix_parameters and len(state.fixes):
            # the fixes one by one, as measured (their applied shifts undone): their
            # sources' parameters are estimated whole, as the motions' are
            fixes = book_observations(state.fixes, rows, stamp[rows] * 1e-9,
                                      self.fix_shifts(len(state.fixes)))
            fixes = fixes if len(fixes) else None
        if fixes is None:
            priors = [p for p in state.fixes.priors(rows, state.T, ids) if not p.weak]
        else:
            priors = []  # the fixes' priors: fix_priors(fixes) of the same terms, bit for bit
        priors.append(GaussianPrior(ids[[lo]], state.T[[lo]].copy(),
                                    gauge_information(config.gauge_sigma_m,
                                                      config.gauge_sigma_tilt_rad,
                                                      config.gauge_sigma_yaw_rad), weak=True))
        self.n_estimates += 1
        self.last_conns, self.last_horizon = int(state.src.n), int(conns.size)
        return camera_estimate_inputs(
            self, conns, HorizonEstimate(net, state.T[rows].copy(), self.sources_of(conns),
                                         dt_s, config.solver_config(), priors, fixes, cal))

    def install(self, strict: bool = False) -> float:
        """Use the pending estimate (waiting for it, or solving it inline) for the motions that
        enter from now on: before the first odometry motion after the update that started it,
        or at the start of the next update. A failure (of the data: too few nodes, a singular
        horizon; or any other error, re-raised if ``strict``) keeps the previous estimate and
        counts it (:attr:`n_failed`). Returns the milliseconds spent (waiting or solving; 0 if
        nothing was pending)."""
        job = self.pending
        if job is None:
            return 0.0
        t0 = time.perf_counter()
        self.pending = None
        job.wait()
        if job.error is not None:
            self.n_failed += 1
            if strict and not isinstance(job.error, DATA_FAILURES):
                raise job.error
        else:
            before = {c: self.camera_correction(c) for c in self.cameras}
            self._use(job.report)
            if self.cameras:
                self.camera_step = max(self.camera_step, self._camera_change(before))
        return 1e3 * (time.perf_counter() - t0)

    def _camera_change(self, before: dict[str, FloatArray]) -> float:
        """The largest change of a camera's applied rotation from ``before`` (per camera, (3,)
        rad) to the current one, in the sigmas of the current estimate (``inf`` where an axis
        changed without a finite sigma; 0: no change)."""
        sig = {(p.source, p.name): p.sigma for p in
               ([] if self.report is None else self.report.parameters)}
        step = 0.0
        for cam in self.cameras:
            d = np.abs(self.camera_correction(cam) - before[cam])
            for name, par in CAMERA_PARAMETERS.items():
                if d[par.axis] == 0.0:
                    continue
                s = float(sig.get((cam, name), np.nan))
                step = max(step, d[par.axis] / s if np.isfinite(s) and s > 0 else np.inf)
        return step

    def wait(self) -> float:
        """Wait for an estimate running in the background; returns its CPU milliseconds (0 if
        none runs; an inline one is left for :meth:`install`)."""
        job = self.pending
        if job is None or job.thread is None:
            return 0.0
        job.thread.join()
        return job.cpu_ms

    def _use(self, report: CalibrationReport) -> None:
        self.report = report
        cur: dict[str, tuple[float, float]] = {}
        fix: dict[str, FloatArray] = {}
        cam: dict[str, FloatArray] = {}
        for p in report.estimated():
            if p.name in CAMERA_PARAMETERS:   # only the named cameras have them
                cam.setdefault(p.source, np.zeros(3))[CAMERA_PARAMETERS[p.name].axis] = p.value
            elif p.name in FIX_PARAMETERS:
                fix.setdefault(p.source, np.zeros(4))[FIX_SLOTS.index(p.name)] = p.value
            elif p.name in ('scale', 'yaw_rate'):
                k, w = cur.get(p.source, (0.0, 0.0))
                cur[p.source] = (p.value, w) if p.name == 'scale' else (k, p.value)
        self._current = cur
        self._fix_current = fix
        self._camera_current = cam
        noise: dict[str, list[float]] = {}
        for f in report.noise:
            if not f.applied:
                continue
            s = noise.setdefault(f.source, [1.0, 1.0])
            if f.part in ('translation', 'motion'):
                s[0] = float(f.factor)
            if f.part in ('rotation', 'motion'):
                s[1] = float(f.factor)
        self._noise_current = {k: (v[0], v[1]) for k, v in noise.items()}

    # -------------------------------------------------------------------- outputs
    def as_dict(self) -> dict:
        """Plain data (``summary.json``'s ``online_calibration``): the last estimate
        (:meth:`CalibrationReport.as_dict <ga_ros.core.calibration.CalibrationReport.as_dict>`;
        empty before the first) with the counts of estimates and failed ones."""
        rep = {} if self.report is None else self.report.as_dict()
        return {**rep, 'estimates': int(self.n_estimates), 'failed': int(self.n_failed)}

    def diagnostic_values(self) -> dict[str, str]:
        """``/diagnostics`` key/values: ``calibration/<source>/<parameter>`` (the value
        applied, with its unit, or ``0 (not estimated: <reason>)``) and ``.../sigma``, for
        the odometry and the fix sources alike; with ``calibration_noise``,
        ``calibration/<source>/<part>_noise`` (the variance factor applied, or ``1
        (stated)``) and ``.../sigma``."""
        out = {'calibration/estimates': str(self.n_estimates)}
        for p in [] if self.report is None else self.report.parameters:
            key = f'calibration/{p.source}/{p.name}'
            out[key] = (f'{p.value:.6g} {p.unit}' if p.estimated
                        else f'0 (not estimated: {p.reason})')
            out[key + '/sigma'] = f'{p.sigma:.3g}'
        for f in [] if self.report is None else self.report.noise:
            key = f'calibration/{f.source}/{f.part}_noise'
            out[key] = f'{f.factor:.4g}' if f.applied else '1 (stated)'
            out[key + '/sigma'] = f'{f.sigma:.3g}'
        out.update(camera_diagnostic_values(self))
        return out

    # ---------------------------------------------------------------- persistence
    def arrays(self) -> tuple[dict, dict[str, np.ndarray]]:
        """Header fields (JSON) and arrays of the book (inverse: :meth:`from_arrays`)."""
        meta = {'names': list(self.names), 'n_estimates': int(self.n_estimates),
                'n_failed': int(self.n_failed), 'last_conns': int(self.last_conns),
                'last_horizon': int(self.last_horizon),
                'report': None if self.report is None else self.report.as_dict()}
        job = self.pending
        if job is not None:  # finished now, saved with its result (installed as without a cut)
            job.wait()
            meta['pending'] = {'report': None if job.report is None else job.report.as_dict()}
        arrays = {'cal_source': self.source.a.copy(), 'cal_applied': self.applied.a.copy(),
                  'cal_fix_shift': self.fix_shift.a.copy(),
                  'cal_noise': self.noise_applied.a.copy(),
                  'cal_fix_applied': self.fix_applied.a.copy()}
        if self.group_names:   # every connection's source (the cameras' estimates)
            meta['group_names'] = list(self.group_names)
            meta['camera_step'] = float(self.camera_step)
            arrays['cal_group'] = self.group.a.copy()
            arrays['cal_camera'] = self.camera_applied.a.copy()
        return meta, arrays

    @classmethod
    def from_arrays(cls, meta: dict, arrays: dict[str, np.ndarray]) -> OnlineCalibration:
        """The book :meth:`arrays` saved."""
        book = cls()
        book.names = [str(s) for s in meta.get('names', [])]
        book.n_estimates = int(meta.get('n_estimates', 0))
        book.n_failed = int(meta.get('n_failed', 0))
        book.last_conns = int(meta.get('last_conns', 0))
        book.last_horizon = int(meta.get('last_horizon', 0))
        book.source = Rows.of(np.asarray(arrays['cal_source'], dtype=np.int64), np.int64)
        book.applied = Rows.of(np.asarray(arrays['cal_applied'], dtype=np.float64)
                               .reshape(-1, 2), np.float64)
        book.group_names = [str(s) for s in meta.get('group_names', [])]
        book.camera_step = float(meta.get('camera_step', 0.0))
        group = arrays.get('cal_group') if book.group_names else None
        book.group = Rows.of(np.asarray(group, dtype=np.int64) if group is not None
                             else np.full(book.source.n, -1, dtype=np.int64), np.int64)
        if 'cal_camera' in arrays:  # files without: no camera connection corrected
            book.camera_applied = Rows.of(np.asarray(arrays['cal_camera'], dtype=np.float64)
                                          .reshape(-1, 3), np.float64)
        if 'cal_noise' in arrays:  # files without: every covariance as stated
            book.noise_applied = Rows.of(np.asarray(arrays['cal_noise'], dtype=np.float64)
                                         .reshape(-1, 2), np.float64)
        if 'cal_fix_shift' in arrays:  # files without: no fix corrected
            book.fix_shift = Rows.of(np.asarray(arrays['cal_fix_shift'], dtype=np.float64)
                                     .reshape(-1, 3), np.float64)
            book.fix_applied = Rows.of(np.asarray(arrays['cal_fix_applied'], dtype=np.float64)
                                       .reshape(-1, 4), np.float64)
        rep = meta.get('report')
        if rep is not None:
            book._use(report_of_dict(rep))
        pending = meta.get('pending')
        if pending is not None:
            rep = pending.get('report')
            book.pending = HorizonEstimate.finished(None if rep is None
                                                    else report_of_dict(rep))
        return book


def _track_rows(state, tracks: list[int]) -> IntArray:
    """Sorted node rows of ``tracks`` (each track's rows are contiguous)."""
    parts = [np.asarray(state.track_nodes[t], dtype=np.int64) for t in tracks
             if t in state.track_nodes]
    return np.sort(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)


def report_of_dict(d: dict) -> CalibrationReport:
    """The :class:`~ga_ros.core.calibration.CalibrationReport` of its ``as_dict`` (the
    parameters and the noise factors)."""
    nan = float('nan')

    def plain(v):
        return nan if v is None else v

    names = {f.name for f in fields(AdditionalParameter)}
    params = [AdditionalParameter(**{k: plain(v) for k, v in p.items() if k in names})
              for p in d.get('parameters', [])]
    noise_names = {f.name for f in fields(NoiseFactor)}
    noise = [NoiseFactor(**{k: (tuple(plain(x) for x in v) if isinstance(v, list) else plain(v))
                            for k, v in f.items() if k in noise_names})
             for f in d.get('noise', [])]
    return replace(CalibrationReport(params, noise=noise), alpha=plain(d.get('alpha')),
                   sigma0_sq=plain(d.get('sigma0_sq')), iterations=int(d.get('iterations', 0)),
                   solves=int(d.get('solves', 0)),
                   noise_iterations=int(d.get('noise_iterations', 0)))


# ------------------------------------------------------------------------- cameras online
def camera_estimate_inputs(book: OnlineCalibration, conns: IntArray,
                           job: HorizonEstimate) -> HorizonEstimate:
    """``job`` with the book's cameras (``AlignerConfig.calibrate_cameras``) and the source of
    each of its connection rows ``conns`` (consecutive and cross-track:
    :meth:`OnlineCalibration.register_group`), so the estimate includes each camera's
    extrinsic rotation where the horizon determines it (``docs/calibration.md``); ``job`` as
    it is without cameras. The estimate is published (:attr:`OnlineCalibration.report`,
    :func:`camera_diagnostic_values`) and applied to the camera's connections that enter
    afterwards (:meth:`OnlineCalibration.camera_corrected`)."""
    if not book.cameras:
        return job
    g = book.group.a[conns]
    groups = [book.group_names[i] if i >= 0 else None for i in g.tolist()]
    return replace(job, cameras=tuple(book.cameras), groups=groups)


def camera_diagnostic_values(book: OnlineCalibration) -> dict[str, str]:
    """``/diagnostics`` of the cameras (beside :meth:`OnlineCalibration.diagnostic_values`):
    ``calibration/<camera>/applied`` (``yes: [phi_x, phi_y, phi_z] rad``, the extrinsic
    rotation applied to the camera's connections entering now, 0 on an axis not estimated;
    or ``no: not estimated``) and, for a camera that no measurement named so far,
    ``calibration/<camera>`` (``no such source so far; the sources: ...``)."""
    out: dict[str, str] = {}
    for cam in book.cameras:
        if cam in book.group_names:
            phi = book.camera_correction(cam)
            out[f'calibration/{cam}/applied'] = (
                'yes: [' + ', '.join(f'{v:.4g}' for v in phi) + '] rad' if phi.any()
                else 'no: not estimated')
        else:
            seen = ', '.join(sorted(book.group_names)) or 'none yet'
            out[f'calibration/{cam}'] = f'no such source so far; the sources: {seen}'
    return out
