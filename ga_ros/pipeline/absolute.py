"""Absolute inputs front end: fix messages -> fixes tied to the keyframe graph (ROS-free).

The alignment node and the replay both drive one :class:`AbsoluteFrontEnd` beside the
:class:`~ga_ros.pipeline.inputs.InputFrontEnd`, message by message, so that live and offline runs
make the same fixes:

* :meth:`AbsoluteFrontEnd.message` ``(name, msg)``: one fix message of absolute input ``name``
  (:class:`~ga_ros.inputs.absolute.AbsoluteDecoder`), queued until the odometry covers its
  stamp; every NavSatFix input without its own ``datum`` shares one ENU origin (the map
  frame): the first datum any of them has (:meth:`AbsoluteFrontEnd.earth_datum`);
* :meth:`AbsoluteFrontEnd.resolve` ``(odometry)``: after each odometry sample, the queued fixes
  whose stamp the odometry now covers, each tied to the keyframe at or before its stamp
  (:meth:`~ga_ros.inputs.odometry.OdometryInput.offset_at`: the offset ``T_k_base(t)`` and its
  covariance from the odometry's noise model), the sensor's lever arm appended; a fix still
  uncovered when a fix ``tolerance_s`` newer has arrived is dropped (``fix_no_odometry``)
  (:class:`~ga_ros.core.fixes.FixTerm`); a fix older than the odometry kept, or before the first
  keyframe, is dropped (``fix_no_keyframe``). A used fix may end the track at the next keyframe
  (``ends_track``, at most every ``track_min_interval_s``), so the window update that uses it
  runs then and the published estimate follows the fixes.

Every call returns an :class:`AbsoluteStep`; counters per input and reason in :meth:`stats`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.extrinsic import TransformTree
from ga_ros.core.fixes import FixTerm
from ga_ros.errors import InputError
from ga_ros.inputs.absolute import (
    NAVSAT,
    AbsoluteDecoder,
    AbsoluteInputConfig,
    absolute_type,
)
from ga_ros.inputs.odometry import OdometryInput
from ga_ros.pipeline.inputs import Throttle

#: At most this many fixes wait for the odometry (the oldest is dropped beyond).
MAX_PENDING = 1000


@dataclass(frozen=True)
class AbsoluteSpec:
    """One absolute input: where it comes from and how it becomes fixes.

    Attributes
    ----------
    topic : topic name.
    msgtype : ``geometry_msgs/msg/PoseWithCovarianceStamped``, ``nav_msgs/msg/Odometry`` or
        ``sensor_msgs/msg/NavSatFix`` (or an alias,
        :data:`ga_ros.inputs.absolute.ABSOLUTE_ALIASES`).
    config : its settings (its ``name`` names the input).
    """

    topic: str
    msgtype: str = 'geometry_msgs/msg/PoseWithCovarianceStamped'
    config: AbsoluteInputConfig = field(default_factory=AbsoluteInputConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, 'msgtype', absolute_type(self.msgtype))

    @property
    def name(self) -> str:
        return self.config.name


@dataclass(frozen=True)
class ResolvedFix:
    """A fix ready for the aligner: the term and the covariance (6, 6) of its odometry offset
    (``TrackWindowAligner.add_fix(term, C_offset)``)."""

    term: FixTerm
    C_offset: FloatArray


@dataclass(frozen=True)
class AbsoluteStep:
    """What one call did.

    Attributes
    ----------
    fixes : fixes to give the aligner, in order.
    end_track : a used fix asks for a track boundary at the next keyframe.
    warning : a (throttled) warning to show, else ''.
    error : why a message was dropped ('' when it was queued or used).
    """

    fixes: tuple[ResolvedFix, ...] = ()
    end_track: bool = False
    warning: str = ''
    error: str = ''


class AbsoluteFrontEnd:
    """Absolute inputs -> fixes on the keyframes of one odometry input (module doc).

    Parameters
    ----------
    specs : the absolute inputs (names must differ).
    warn_throttle_s : smallest interval between two default-covariance warnings (s).
    clock : monotonic clock (s) for the throttle.
    """

    def __init__(self, specs: Sequence[AbsoluteSpec], warn_throttle_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise InputError(f'absolute input names must differ, got {names}')
        self.specs = {s.name: s for s in specs}
        self.decoders = {s.name: AbsoluteDecoder(s.config, s.msgtype) for s in specs}
        self.throttle = Throttle(warn_throttle_s, clock)
        self._pending: list[tuple[str, Any, str]] = []  # (input, AbsoluteFix, sensor frame)
        #: the static transforms (``/tf_static``) for the lever arms (:meth:`static_transform`)
        self.static = TransformTree()
        self._last_boundary_ns: int | None = None
        self._newest_fix_ns = 0

    def by_topic(self, topic: str) -> AbsoluteSpec | None:
        """The absolute input reading ``topic`` (None if none)."""
        return next((s for s in self.specs.values() if s.topic == topic), None)

    def message(self, name: str, msg: Any) -> AbsoluteStep:
        """One message of absolute input ``name``: decoded and queued (never raises)."""
        dec = self.decoders[name]
        if dec.msgtype == NAVSAT and dec.datum is None:
            dec.datum = self.earth_datum()  # one ENU origin (map frame) for every NavSatFix
        try:
            fix, default = dec.decode(msg)
        except InputError as exc:
            dec.drop(getattr(exc, 'fix_reason', 'fix_bad_message'))
            return AbsoluteStep(error=f'{name}: {exc}')
        self._pending.append((name, fix, dec.sensor_frame(msg)))
        self._newest_fix_ns = max(self._newest_fix_ns, fix.stamp_ns)
        if len(self._pending) > MAX_PENDING:
            old = self._pending.pop(0)[0]
            self.decoders[old].drop('fix_no_odometry')
        warning = ''
        if default and self.throttle.ready():
            st = dec.stats
            warning = (f'{name}: {st.default_covariances} of {st.fixes} fixes used the DEFAULT '
                       f'covariance (the message has none): {dec.config.default_sigma_m:g} m per '
                       f'axis; set {name}.default_sigma_m to change it')
        return AbsoluteStep(warning=warning)

    def resolve(self, odometry: OdometryInput) -> AbsoluteStep:
        """The queued fixes that ``odometry`` now covers, tied to its keyframes (module doc)."""
        newest = odometry.latest_stamp_ns
        if newest is None or not self._pending:
            return AbsoluteStep()
        out, keep, end, errors = [], [], False, []
        for name, fix, frame in self._pending:
            if newest is None or fix.stamp_ns > newest:
                if (self._newest_fix_ns - fix.stamp_ns
                        > self.specs[name].config.tolerance_s * 1e9):
                    self.decoders[name].drop('fix_no_odometry')  # the odometry lags too much
                else:
                    keep.append((name, fix, frame))
                continue
            spec = self.specs[name]
            try:
                node, T_k_base, C = odometry.offset_at(fix.stamp_ns)
            except InputError as exc:
                self.decoders[name].drop('fix_no_keyframe')
                errors.append(f'{name}: {exc}')
                continue
            T_base_sensor = self.decoders[name].T_base_sensor(frame, self.static)
            term = FixTerm(node, T_k_base @ T_base_sensor, fix)
            out.append(ResolvedFix(term, C))
            if self._last_boundary_ns is None:  # the first track starts with the first fix
                self._last_boundary_ns = fix.stamp_ns
            elif spec.config.ends_track and (fix.stamp_ns - self._last_boundary_ns
                                             >= spec.config.track_min_interval_s * 1e9):
                end = True
                self._last_boundary_ns = fix.stamp_ns
        self._pending = keep
        return AbsoluteStep(tuple(out), end, error='; '.join(errors))

    def static_transform(self, msg: Any) -> None:
        """A ``/tf_static`` message (``tf2_msgs/TFMessage``): the sensors' lever arms."""
        self.static.add_message(msg)

    def datums(self) -> dict[str, list[float]]:
        """``{input: [lat_deg, lon_deg, alt_m]}``: the ENU origin of each NavSatFix input that
        has one (the map frame of its fixes)."""
        return {n: list(d.datum) for n, d in self.decoders.items() if d.datum is not None}

    def earth_datum(self) -> tuple[float, float, float] | None:
        """The ENU origin ``[lat_deg, lon_deg, alt_m]`` of the first NavSatFix input that has
        one (the ``datum`` parameter, or its first fix), ``None`` before (or without any):
        ``earth -> map`` is then :func:`~ga_ros.inputs.absolute.T_earth_enu` of it."""
        for d in self.decoders.values():
            if d.msgtype == NAVSAT and d.datum is not None:
                return d.datum
        return None

    def restore_datum(self, datum_lla: Sequence[float]) -> list[str]:
        """Give every NavSatFix input without its own ``datum`` the origin
        ``[lat_deg, lon_deg, alt_m]`` of a restored state (the map frame its poses and fixes are
        in), before any fix sets one. Returns the names of the inputs whose configured datum
        differs from it (their fixes stay in their own frame: the caller warns)."""
        d = tuple(float(v) for v in datum_lla)
        differ = []
        for name, dec in self.decoders.items():
            if dec.msgtype != NAVSAT:
                continue
            if dec.config.use_datum:
                if not np.allclose(dec.datum, d, rtol=0.0, atol=1e-9):
                    differ.append(name)
            else:
                dec.datum = d  # type: ignore[assignment]
        return differ

    def stats(self) -> dict[str, object]:
        """Counters per input (for diagnostics and the replay summary)."""
        out: dict[str, object] = {n: asdict(d.stats) for n, d in self.decoders.items()}
        out['pending'] = len(self._pending)
        return out


class FixFeeder:
    """Resolved fixes -> the aligner, each once its node exists (a fix on the first keyframe
    arrives before the first measurement brings that node). The node and the replay share it."""

    def __init__(self) -> None:
        self.waiting: list[ResolvedFix] = []

    def add(self, fixes: Sequence[ResolvedFix]) -> None:
        """Queue fixes for :meth:`flush`."""
        self.waiting.extend(fixes)

    def forget(self) -> int:
        """Drop the fixes still waiting (tied to keyframes whose ids no longer name the state's
        nodes: ``~/load_state`` replaced it); returns how many."""
        n = len(self.waiting)
        self.waiting = []
        return n

    def flush(self, aligner: Any) -> list[str]:
        """Give ``aligner`` (``add_fix``, ``newest_node_id``: an aligner, or an
        :class:`~ga_ros.pipeline.session.AlignmentSession`, which also journals them and joins
        the piece of their nodes in its gap healer; the node and the replay give the session)
        the queued fixes whose node it has; returns the messages of the ones it refused
        (counted there by reason)."""
        add = getattr(aligner, 'add_fix', None)
        if add is None or not self.waiting:
            return []
        newest = aligner.newest_node_id
        wait, errors = [], []
        for f in self.waiting:
            if newest is None or f.term.node_id > newest:
                wait.append(f)
                continue
            try:
                add(f.term, f.C_offset)
            except InputError as exc:
                errors.append(str(exc))
        self.waiting = wait
        return errors


def absolute_specs_from_mapping(sections: Mapping[str, Any],
                                topics: Mapping[str, str] | None = None
                                ) -> tuple[AbsoluteSpec, ...]:
    """Absolute inputs from named sections (``{name: {topic, type, <AbsoluteInputConfig
    fields>}}``, e.g. the ``absolutes`` mapping of ``config/inputs.yaml``), ``topics``
    overriding the sections' topics (``--absolute-topic``).

    Raises
    ------
    InputError
        An unknown setting, a bad value, or a section that is not a mapping.
    """
    topics = dict(topics or {})
    specs = []
    for name in list(sections) + [n for n in topics if n not in sections]:
        sec = sections.get(name, {})
        if not isinstance(sec, Mapping):
            raise InputError(f'absolute input {name!r}: expected a mapping, got {sec!r}')
        values = dict(sec)
        topic = str(topics.get(name, values.pop('topic', '')))
        values.pop('topic', None)
        msgtype = str(values.pop('type', 'geometry_msgs/msg/PoseWithCovarianceStamped'))
        for key in ('datum', 'T_base_sensor'):
            if key in values:
                values[key] = tuple(np.asarray(values[key], float).ravel().tolist())
        if topic:
            specs.append(AbsoluteSpec(topic, msgtype,
                                      AbsoluteInputConfig.from_mapping(name, values)))
    return tuple(specs)
