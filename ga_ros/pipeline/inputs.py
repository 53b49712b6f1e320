"""Standard inputs front end: odometry / pose messages and external constraints -> measurements.

One ROS-free object (:class:`InputFrontEnd`) that the alignment node and the replay both drive,
message by message, so that live and offline runs make the same measurements:

* :meth:`InputFrontEnd.sample` ``(name, msg, msgtype)``: one ``nav_msgs/Odometry``,
  ``PoseWithCovarianceStamped`` or ``PoseStamped`` of input ``name``. The first (primary)
  input defines the keyframes (:class:`ga_ros.inputs.odometry.OdometryInput`: keyframes,
  covariance policy, track rule); every further input measures the motion between those
  keyframes from its own poses (:class:`ga_ros.inputs.secondary.SecondaryInput`), so several
  relative sources make connections on one keyframe graph;
* :meth:`InputFrontEnd.constraint` ``(msg)``: an external constraint (encoding in
  :mod:`ga_ros.inputs.messages`) on the first input's keyframes, its stamps tied to them by the
  odometry in between;
* :meth:`InputFrontEnd.image` / :meth:`InputFrontEnd.camera_info` ``(side, msg)``: a stereo
  camera beside the odometry (:class:`ga_ros.pipeline.keyframe_camera.KeyframeCamera`): images
  matched to the first input's keyframes, cross-track connections tied to them as external
  constraints are; :meth:`InputFrontEnd.set_corrected` gives it the corrected path;
* :meth:`InputFrontEnd.track_boundary`: a new track at the next keyframe (a topic);
* :meth:`InputFrontEnd.map_to_odom`: the REP 105 ``map -> odom`` correction from the corrected
  path and the odometry poses of the same keyframes.

Every call returns an :class:`InputStep` (measurements, node stamps, a warning to show); a
throttled warning says when the default covariance replaced a missing one (zeros, ``-1``).

Measurement encoding with a covariance policy
    :func:`decode_measurement` decodes the ga_ros measurement encoding with a policy for
    covariances that are not positive definite: ``'reject'`` (the live default) or
    ``'repair'`` (eigenvalue clipping, :func:`ga_ros.core.covariance.nearest_positive_definite`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import encoding
from ga_ros.core.covariance import nearest_positive_definite
from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError, InputError, UsageError
from ga_ros.geometry import se3
from ga_ros.inputs.messages import decode_constraint, decode_sample, input_type
from ga_ros.inputs.odometry import OdometryInput, OdometryInputConfig
from ga_ros.inputs.secondary import KeyframeInterval, SecondaryInput
from ga_ros.pipeline.keyframe_camera import CameraConnection, KeyframeCamera

#: Policies for a measurement covariance that is not positive definite.
COVARIANCE_POLICIES = ('reject', 'repair')


@dataclass(frozen=True)
class InputSpec:
    """One standard input: where it comes from and how it becomes measurements.

    Attributes
    ----------
    topic : topic name (relative for a node, absolute in a bag).
    msgtype : ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseWithCovarianceStamped`` or
        ``geometry_msgs/msg/PoseStamped`` (or an alias,
        :data:`ga_ros.inputs.messages.TYPE_ALIASES`).
    config : keyframe, covariance and track settings (its ``name`` names the input).
    """

    topic: str
    msgtype: str = 'nav_msgs/msg/Odometry'
    config: OdometryInputConfig = field(default_factory=OdometryInputConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, 'msgtype', input_type(self.msgtype))

    @property
    def name(self) -> str:
        """The input's name (``odom0``, ...)."""
        return self.config.name


@dataclass(frozen=True)
class InputStep:
    """What one input message did.

    Attributes
    ----------
    measurements : measurements to give the alignment session, in order.
    node_stamps : acquisition time (ns) of keyframes made by this message, by node id.
    warning : a (throttled) warning to show, else ''.
    error : why the message was rejected ('' when it was used).
    """

    measurements: tuple[Measurement, ...] = ()
    node_stamps: dict[int, int] = field(default_factory=dict)
    warning: str = ''
    error: str = ''


class Throttle:
    """At most one event per ``period_s`` seconds (``period_s <= 0``: every event).

    Parameters
    ----------
    period_s : the smallest interval between two passed events (s); may be changed at run time.
    clock : monotonic clock in seconds (injectable for tests).
    """

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s = float(period_s)
        self._clock = clock
        self._next = -np.inf

    def ready(self) -> bool:
        """True if an event may pass now (and then starts a new period)."""
        now = self._clock()
        if now < self._next:
            return False
        self._next = now + self.period_s
        return True


def decode_measurement(msg: Any, policy: str = 'reject') -> Measurement:
    """Decode the ga_ros measurement encoding with a covariance policy (module doc).

    Raises
    ------
    InputError
        As :func:`ga_ros.core.encoding.decode_measurement`; with ``'repair'`` a finite,
        symmetric covariance that is not positive definite is repaired instead.
    """
    if policy not in COVARIANCE_POLICIES:
        raise InputError(f'covariance policy must be one of {COVARIANCE_POLICIES}, '
                         f'got {policy!r}')
    try:
        return encoding.decode_measurement(msg)
    except InputError as exc:
        if policy != 'repair' or getattr(exc, 'reason', None) != 'bad_covariance':
            raise
        cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
        if not np.isfinite(cov).all() or not np.allclose(cov, cov.T, rtol=0.0,
                                                         atol=1e-6 * np.abs(cov).max()):
            raise
        fixed = nearest_positive_definite(0.5 * (cov + cov.T)[None])[0]
        proxy = SimpleNamespace(header=msg.header, child_frame_id=msg.child_frame_id,
                                twist=msg.twist,
                                pose=SimpleNamespace(pose=msg.pose.pose,
                                                     covariance=fixed.reshape(36)))
        return encoding.decode_measurement(proxy)


class InputFrontEnd:
    """Odometry / pose inputs + external constraints + track boundaries (module doc).

    Parameters
    ----------
    inputs : the inputs; their names must differ. The first one defines the keyframes (its
        ``first_node_id`` numbers them); the others measure the motion between them.
    warn_throttle_s : smallest interval between two default-covariance warnings (s).
    clock : monotonic clock in seconds for the throttle.
    camera : a stereo camera beside the odometry (None: none).

    Raises
    ------
    InputError
        Duplicate names or no input.
    """

    def __init__(self, inputs: Sequence[InputSpec], warn_throttle_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic,
                 camera: KeyframeCamera | None = None) -> None:
        if not inputs:
            raise InputError('no standard input configured: give at least one odometry or '
                             'pose topic')
        names = [s.name for s in inputs]
        if len(set(names)) != len(names):
            raise InputError(f'input names must differ, got {names}')
        self.specs = {s.name: s for s in inputs}
        self.primary = names[0]
        #: the keyframe input and the further ones measured on its keyframes
        self.inputs: dict[str, OdometryInput | SecondaryInput] = {
            s.name: OdometryInput(s.config) if s.name == self.primary
            else SecondaryInput(s.config) for s in inputs}
        self._kf_stamp_ns: int | None = None
        self.camera = camera
        #: camera connections whose image stamps the odometry does not cover yet
        self._camera_waiting: list[CameraConnection] = []
        self.camera_rejected = 0
        self.throttle = Throttle(warn_throttle_s, clock)
        self.constraints_rejected = 0
        #: stamp (ns) of the first input's newest sample (0 before any)
        self.latest_stamp_ns = 0
        #: ``(rows, id of the last)``: the corrected path's first rows hold no keyframe of the
        #: first input and never will (ids below its first keyframe's,
        #: ``_no_keyframe_first``): :meth:`map_to_odom` reads only the rows after them
        self._no_keyframe_rows: tuple[int, int] = (0, -1)
        self._no_keyframe_first = -1

    def by_topic(self, topic: str) -> InputSpec | None:
        """The input reading ``topic`` (None if none)."""
        return next((s for s in self.specs.values() if s.topic == topic), None)

    # ----------------------------------------------------------------- messages
    def sample(self, name: str, msg: Any, msgtype: str | None = None) -> InputStep:
        """One odometry / pose message of input ``name`` (type: the input's by default).

        Malformed messages and stamps that go back in time come back as ``error`` (nothing
        changed); this never raises on a message.
        """
        spec = self.specs[name]
        inp = self.inputs[name]
        defaults = inp.stats.default_covariances
        try:
            s = decode_sample(msg, msgtype or spec.msgtype)
            if spec.config.frame_id and s.frame_id.lstrip('/') != spec.config.frame_id.lstrip(
                    '/'):
                raise InputError(f'{name}: frame {s.frame_id!r}, expected '
                                 f'{spec.config.frame_id!r}')
            if isinstance(inp, SecondaryInput):
                meas = tuple(inp.add_sample(s.stamp_ns, s.T_odom_base, s.pose_cov,
                                            s.twist_cov))
                warn = inp.stats.default_covariances > defaults
                return InputStep(meas, warning=self._default_warning(name) if warn else '')
            up = inp.add_sample(s.stamp_ns, s.T_odom_base, s.pose_cov, s.twist_cov)
        except InputError as exc:
            return InputStep(error=f'{name}: {exc}')
        self.latest_stamp_ns = s.stamp_ns
        stamps = {up.keyframe_id: up.stamp_ns} if up.new_keyframe else {}
        meas = (up.measurement,) if up.measurement is not None else ()
        warning = self._default_warning(name) if up.default_covariance else ''
        if up.new_keyframe:
            meas += self._measure_interval(up.measurement, up.stamp_ns)
            self._kf_stamp_ns = up.stamp_ns
            if self.camera is not None:
                self._camera_waiting += self.camera.add_keyframe(
                    up.keyframe_id, up.track_id, inp.segmenter.segment, up.stamp_ns,
                    s.T_odom_base)
        meas += self._camera_measurements()
        return InputStep(meas, stamps, warning)

    # ------------------------------------------------------------------ camera
    def camera_info(self, side: str, msg: Any) -> InputStep:
        """A ``CameraInfo`` of the camera beside the odometry; a rejection comes back as
        ``error`` (the previous calibration stays)."""
        if self.camera is None:
            return InputStep(error='camera: no camera configured')
        try:
            self.camera.set_camera_info(side, msg)
        except InputError as exc:
            return InputStep(error=f'camera: CameraInfo rejected: {exc}')
        return InputStep()

    def image(self, side: str, msg: Any) -> InputStep:
        """An image of the camera beside the odometry (``side``: ``'left'`` / ``'right'``);
        the cross-track connections of the keyframes it completes."""
        if self.camera is None:
            return InputStep(error='camera: no camera configured')
        try:
            self._camera_waiting += self.camera.add_image(side, msg)
        except GaError as exc:
            return InputStep(error=f'camera: {exc}')
        return InputStep(self._camera_measurements())

    def set_corrected(self, node_ids: IntArray, T_map_node: FloatArray) -> None:
        """The corrected path (node ids, ``(n, 4, 4)`` base poses) for the camera's overlap
        prediction."""
        if self.camera is not None and len(node_ids):
            self.camera.set_corrected(node_ids, T_map_node)

    def _camera_measurements(self) -> tuple[Measurement, ...]:
        """Camera connections tied to their keyframes by the odometry between each image and
        the keyframe it was taken for (:meth:`OdometryInput.constraint_from_stamps`), named by
        the camera (:attr:`KeyframeCamera.source`); those whose later image is newer than the
        odometry wait for it."""
        out, waiting = [], []
        inp = self._primary()
        source = self.camera.source if self.camera is not None else ''
        for c in self._camera_waiting:
            if c.dst_stamp_ns > self.latest_stamp_ns:
                waiting.append(c)
                continue
            try:
                m = inp.constraint_from_stamps(c.src_stamp_ns, c.dst_stamp_ns, c.T_src_dst,
                                               c.cov, nodes=(c.src_id, c.dst_id))
                out.append(replace(m, source=source))
            except InputError:
                self.camera_rejected += 1
        self._camera_waiting = waiting
        return tuple(out)

    def _measure_interval(self, m: Measurement | None, stamp_ns: int) -> tuple[Measurement, ...]:
        """The further inputs' measurements of the primary's new keyframe interval ``m``
        (those that already cover it; the others measure it when their samples do)."""
        if m is None or self._kf_stamp_ns is None:
            return ()
        iv = KeyframeInterval(m.src_id, m.dst_id, m.src_track, m.dst_track, self._kf_stamp_ns,
                              int(stamp_ns))
        out: list[Measurement] = []
        for inp in self.inputs.values():
            if isinstance(inp, SecondaryInput):
                out += inp.add_interval(iv)
        return tuple(out)

    def constraint(self, msg: Any) -> InputStep:
        """An external constraint (``nav_msgs/Odometry``, :mod:`ga_ros.inputs.messages`) on the
        keyframes of the first input. Rejections come back as ``error``; never raises."""
        inp = self._primary()
        before = inp.stats.default_covariances
        try:
            c = decode_constraint(msg)
            if c.by == 'stamp':
                m = inp.constraint_from_stamps(c.a, c.b, c.T_a_b, c.cov)
            else:
                m = inp.constraint_from_nodes(c.a, c.b, c.T_a_b, c.cov)
        except InputError as exc:
            self.constraints_rejected += 1
            return InputStep(error=f'constraint: {exc}')
        warning = ''
        if inp.stats.default_covariances > before:
            warning = self._default_warning(self.primary)
        return InputStep((m,), warning=warning)

    def track_boundary(self) -> None:
        """Start a new track at the next keyframe of every input."""
        self._primary().request_track_boundary()

    def continue_from(self, node_id: int, track_id: int) -> None:
        """Number the first input's keyframes from ``node_id``, on a new track ``track_id``
        (:meth:`OdometryInput.continue_from <ga_ros.inputs.odometry.OdometryInput.continue_from>`):
        a node restarted on a restored state continues its survey after the nodes and tracks
        it holds (:meth:`AlignmentSession.next_ids
        <ga_ros.pipeline.session.AlignmentSession.next_ids>`) instead of numbering from 0
        again, which would read as another survey.

        After samples (``~/load_state`` replaced the state under running inputs) the first
        input starts a fresh keyframe chain at its next sample, and everything tied to the
        keyframes so far, whose ids no longer name the state's nodes, is dropped: the further
        inputs' keyframe intervals still waiting for a sample, the camera's keyframes and
        records and its connections waiting for the odometry. The samples, the calibration and
        the counters stay.
        """
        self._primary().continue_from(node_id, track_id)
        for inp in self.inputs.values():
            if isinstance(inp, SecondaryInput):
                inp.forget_intervals()
        self._kf_stamp_ns = None
        self._camera_waiting = []
        if self.camera is not None:
            self.camera.forget_keyframes()
        self._no_keyframe_rows, self._no_keyframe_first = (0, -1), -1

    def new_survey(self) -> None:
        """The alignment state was emptied under running inputs (``~/reset``): the first input
        starts a fresh keyframe chain at its next sample, numbered from its ``first_node_id``
        on track 0 as at a start, and everything tied to the keyframes so far is dropped, as
        by :meth:`continue_from` (the further inputs' waiting intervals, the camera's
        keyframes, records and waiting connections). The samples, the calibration and the
        counters stay. Before the first sample only the numbering goes back to the start's
        (a restored state's numbering, :meth:`continue_from`, went with the state)."""
        primary = self._primary()
        self.continue_from(int(primary.config.first_node_id), 0)

    # ------------------------------------------------------------------ TF
    def map_to_odom(self, node_ids: IntArray, T_map_node: FloatArray) -> FloatArray | None:
        """REP 105 ``T_map_odom`` of the first input: ``T_map_k T_odom_k^-1`` at the newest
        node ``k`` of the corrected path that is a keyframe of that input (None if none).

        Cost: the rows after ``k`` (back from the newest, in doubling chunks), not the path.
        Rows that can never be keyframes of the input (ids below its first keyframe's: a
        restored state's nodes, which the input numbers after, :meth:`continue_from`) are read
        once, at the first call that finds none, and never again while the path keeps them.

        Parameters
        ----------
        node_ids : (n,) node ids of the corrected path (rows append-only between calls).
        T_map_node : (n, 4, 4) their corrected poses in the map frame.
        """
        inp = self._primary()
        first, end = inp.keyframe_ids
        ids = np.asarray(node_ids).reshape(-1)
        n = ids.size
        floor, last = self._no_keyframe_rows
        if not (0 < floor <= n and ids[floor - 1] == last and first == self._no_keyframe_first):
            floor = 0   # another path or another numbering: read it all once
        hi, step = n, 8   # back from the newest row, in doubling chunks
        while hi > floor and end > first:
            lo = max(hi - step, floor)
            chunk = ids[lo:hi]
            hit = np.flatnonzero((chunk >= first) & (chunk < end))
            if hit.size:
                k = lo + int(hit[-1])
                return np.asarray(T_map_node[k], float) @ se3.inverse(
                    inp.keyframe_pose(int(ids[k])))
            hi, step = lo, 2 * step
        # none: the rows up to the first one whose id is not below the first keyframe's (ids
        # that can never become keyframes of this input) are not read again
        above = np.flatnonzero(ids[floor:n] >= first) if end > first else np.zeros(0, int)
        floor = floor + int(above[0]) if above.size else (n if end > first else floor)
        self._no_keyframe_rows = (floor, int(ids[floor - 1]) if floor else -1)
        self._no_keyframe_first = first
        return None

    def keyframe_pose(self, node_id: int) -> FloatArray:
        """(4, 4) ``T_odom_kf``: the first input's own pose (as recorded) at keyframe
        ``node_id``.

        Raises
        ------
        InputError
            ``node_id`` is not a keyframe of the first input.
        """
        return self._primary().keyframe_pose(node_id)

    def keyframe_stamp(self, node_id: int) -> int:
        """The stamp (ns) of the first input's keyframe ``node_id`` (raises
        :class:`InputError` as :meth:`keyframe_pose`)."""
        return self._primary().keyframe_stamp(node_id)

    def latest_pose(self) -> FloatArray | None:
        """(4, 4) newest ``T_odom_base`` of the first input (None before any sample)."""
        return self._primary().latest_pose()

    def _primary(self) -> OdometryInput:
        inp = self.inputs[self.primary]
        assert isinstance(inp, OdometryInput)
        return inp

    def stats(self) -> dict[str, object]:
        """Counters per input (for diagnostics and the replay summary)."""
        out: dict[str, object] = {n: asdict(i.stats) for n, i in self.inputs.items()}
        out['constraints_rejected'] = self.constraints_rejected
        if self.camera is not None:
            out['camera'] = {**asdict(self.camera.stats), 'rejected': self.camera_rejected,
                             'pairing': self.camera.front.stats.summary()}
        return out

    def _default_warning(self, name: str) -> str:
        if not self.throttle.ready():
            return ''
        return self.default_covariance_message(name)

    def default_covariance_message(self, name: str) -> str:
        """How many of input ``name``'s measurements so far used the default covariance, and
        why ('' if none): the throttled warning and the replay summary say the same."""
        st = self.inputs[name].stats
        if not st.default_covariances:
            return ''
        missing, total = getattr(st, 'missing_covariances', None), st.default_covariances
        if missing is None:  # an input that does not tell the two apart
            why = 'no usable covariance from the stream'
        elif missing == total:
            why = 'the stream has none: zeros, -1 or missing'
        elif missing == 0:
            why = ("the stream's covariances are not usable: the pose covariance does not grow "
                   'from one keyframe to the next, or a covariance is not positive definite')
        else:
            why = (f'{missing} without a covariance in the stream, {total - missing} with one '
                   'that is not usable')
        return (f'{name}: {total} of {st.measurements + st.constraints} measurements used the '
                f'DEFAULT covariance ({why}): '
                f'{self.specs[name].config.default_noise_percent:g} % of the motion; '
                f'set {name}.default_noise_percent or covariance_source to change it')


def specs_from_mapping(sections: Mapping[str, Any], topics: Mapping[str, str] | None = None
                       ) -> tuple[InputSpec, ...]:
    """Inputs from a mapping of named sections (a params file such as ``config/inputs.yaml``).

    The order, and so the input that defines the keyframes (the first), does not depend on the
    sections: the inputs of ``topics`` first, in their order (``--odom-topic``: ``odom0``,
    ``odom1``, ...), then the sections that give their own ``topic``, ``odom0`` first, the
    others in file order.

    Parameters
    ----------
    sections : ``{name: {topic: ..., type: ..., <OdometryInputConfig fields>}}``; ``type`` is
        optional (default ``nav_msgs/msg/Odometry``); a section without ``topic`` sets the
        input of that name in ``topics``.
    topics : ``{name: topic}`` given elsewhere (e.g. ``--odom-topic``), overriding the
        sections' topics; a name without a section gets the default settings.

    Raises
    ------
    UsageError
        A section without ``topic`` for an input that ``topics`` does not give (it would be
        silently unused).
    InputError
        An unknown setting, an invalid value or a section that is not a mapping.
    """
    topics = dict(topics or {})
    for name, sec in sections.items():
        if not isinstance(sec, Mapping):
            raise InputError(f'input {name!r}: expected a mapping of settings, got {sec!r}')
    orphans = [n for n, sec in sections.items() if n not in topics and not sec.get('topic')]
    if orphans:
        given = ', '.join(f'{n} = {t}' for n, t in topics.items()) or 'none'
        raise UsageError(
            f'settings for input {", ".join(map(repr, orphans))}, which is not given '
            f'(inputs given: {given}): add its topic (another --odom-topic, in order odom0, '
            f'odom1, ...; or "topic:" in its section) or remove the section')
    own = [n for n, sec in sections.items() if n not in topics]
    own.sort(key=lambda n: n != 'odom0')  # stable: odom0 first, the others in file order
    specs = []
    for name in list(topics) + own:
        values = dict(sections.get(name, {}))
        topic = str(topics.get(name, values.get('topic', '')))
        values.pop('topic', None)
        msgtype = str(values.pop('type', 'nav_msgs/msg/Odometry'))
        specs.append(InputSpec(topic, msgtype, OdometryInputConfig.from_mapping(name, values)))
    return tuple(specs)
