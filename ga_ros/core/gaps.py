"""Gaps in the measurement stream: measurements held until their source node is known, bridges
over gaps that were never filled, and the mark of nodes not yet joined to the datum (ROS-free).

A node that restarts, a dropped message or a lossy link leave a *gap*: a measurement arrives
whose source node no measurement has introduced (the aligner alone rejects it as
``unknown_source``, and with it everything that continues from it). :class:`GapHealer` decides,
for each measurement, what the :class:`~ga_ros.pipeline.session.AlignmentSession` does with it
(:meth:`GapHealer.route`), in this order:

* ``ADMIT``: its source node is known (or nothing is known yet: the datum) -> the aligner.
* ``REVERSE``: its source is unknown but its destination is known, and the source may still join
  the open track -> the aligner takes the same measurement read backwards (``T_dst_src`` with
  the covariance carried by the adjoint, :func:`reversed_measurement`): exactly the same
  information, and the unknown node enters the graph.
* ``HOLD``: neither end is known (or it would start a new track while earlier measurements are
  held) -> kept in arrival order in the held queue, bounded by
  :attr:`GapConfig.wait_measurements` and :attr:`GapConfig.wait_sec` of stamps.
* ``HOPELESS``: its source is unknown and belongs to a track older than the open one, which can
  no longer take new nodes -> rejected (``unknown_source``).
* ``DUPLICATE``: a re-delivery of a measurement the aligner took reversed (the aligner's own
  duplicate test, on the measured values, does not recognise it) -> rejected (``duplicate``).

After every admission the held queue is passed over in order, admitting what became admissible
(a re-delivered motion filled the gap), while a pass makes progress: the held measurements reach
the aligner in their order of arrival, and since held measurements also hold back the end of the
open track, the window updates see the same connections as without the gap. The result equals
the gap-free run to the solver's tolerance.

When the first held measurement has waited too long (:meth:`GapHealer.overdue`), or the track or
the stream ends (:meth:`~ga_ros.pipeline.session.AlignmentSession.flush_gaps`: every one), a
measurement with both ends unknown gets a **bridge** first: a motion of kind ``'bridge'`` from the
last node of its source's track (or of the open track, for a new track) to its source node,
predicted at constant velocity from the last frame-to-frame motion of that track (zero motion
without one), with a covariance that grows with the gap's duration
(:meth:`GapConfig.bridge_sigmas`). The bridge gives the piece after the gap a stated datum while
the aligner's maths stay unchanged; its weight is negligible against any real connection.

After a restart of the alignment node, the session bridges the first new keyframe at once; when
the odometry went on across the restart that motion is measured instead
(:mod:`ga_ros.pipeline.session.restore`, :meth:`GapHealer.bridge_origin` and the ``restart_*``
settings of :class:`GapConfig`): an ordinary measurement, which joins.

Joined nodes: every node connected to the datum (the first node) or to a node with an absolute
fix (:meth:`GapHealer.anchor`) through real connections (not bridges) is *joined*; the others hang
off a bridge and are *not yet joined* (:meth:`GapHealer.unjoined`). A later real connection (a
cross-track connection, a re-delivered motion) or an absolute fix on one of them joins their
whole piece. The bookkeeping is a union-find over node ids (near-constant time per measurement).
"""

from __future__ import annotations

import enum
import math
import zlib
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3


@dataclass(frozen=True)
class GapConfig:
    """How long a gap may wait for its measurements, and how a bridge is weighted.

    Attributes
    ----------
    enabled : hold and bridge (False: a measurement from an unknown node is rejected as
        ``unknown_source``, as the aligner alone does).
    wait_measurements : the held queue is emptied (bridging what is still unjoined) when it holds
        this many measurements.
    wait_sec : ... or when the newest measurement's stamp is this many seconds after the first
        held one's.
    bridge_sigma_m, bridge_sigma_rad : standard deviation of a bridge's translation (m, per
        axis) and rotation (rad, per axis) over a gap of zero duration.
    bridge_growth_m_per_s, bridge_growth_rad_per_s : added per second of the gap's duration
        (the difference of stamps between the last node before the gap and the bridged node).
    bridge_max_sigma_m, bridge_max_sigma_rad : caps of the two standard deviations (the aligner
        refuses covariances above its ``cov_max_eigenvalue``, 1e6 by default).
    restart_sigma_m, restart_sigma_rad : standard deviation (m, rad per axis) added to the
        odometry's own noise of a *measured* bridge across a restart of the alignment node (the
        odometry went on: its motion over the downtime is measured,
        :mod:`ga_ros.pipeline.session.restore`).
    restart_max_speed_mps, restart_max_rate_rad_per_s : a motion over the downtime implying a
        faster mean speed or turn rate means the odometry restarted too (its ``odom`` frame
        reset): the bridge is then the constant-velocity guess.
    restart_origin_m, restart_origin_rad : the odometry's first pose after the restart within
        this distance and angle of its own origin, while the saved state places it further from
        its last node, also means the odometry restarted.
    """

    enabled: bool = True
    wait_measurements: int = 300
    wait_sec: float = 30.0
    bridge_sigma_m: float = 100.0
    bridge_sigma_rad: float = 1.0
    bridge_growth_m_per_s: float = 5.0
    bridge_growth_rad_per_s: float = 0.1
    bridge_max_sigma_m: float = 700.0
    bridge_max_sigma_rad: float = 1.5
    restart_sigma_m: float = 0.05
    restart_sigma_rad: float = 0.01
    restart_max_speed_mps: float = 10.0
    restart_max_rate_rad_per_s: float = 3.0
    restart_origin_m: float = 0.5
    restart_origin_rad: float = 0.2

    def __post_init__(self) -> None:
        if self.wait_measurements < 1 or not self.wait_sec >= 0:
            raise InputError('wait_measurements must be >= 1 and wait_sec >= 0')
        restart = (self.restart_sigma_m, self.restart_sigma_rad, self.restart_max_speed_mps,
                   self.restart_max_rate_rad_per_s, self.restart_origin_m,
                   self.restart_origin_rad)
        if not all(math.isfinite(s) and s > 0 for s in restart):
            raise InputError('restart_* settings of the gaps must be positive and finite, got '
                             f'{restart}')
        sig = (self.bridge_sigma_m, self.bridge_sigma_rad, self.bridge_max_sigma_m,
               self.bridge_max_sigma_rad)
        if not all(math.isfinite(s) and s > 0 for s in sig) or not (
                self.bridge_growth_m_per_s >= 0 and self.bridge_growth_rad_per_s >= 0):
            raise InputError('bridge standard deviations must be positive and finite, growths '
                             '>= 0')

    def bridge_sigmas(self, gap_sec: float) -> tuple[float, float]:
        """``(sigma_m, sigma_rad)`` of a bridge over a gap of ``gap_sec`` seconds:
        ``min(sigma + growth * gap_sec, max_sigma)`` each."""
        gap = max(float(gap_sec), 0.0)
        return (min(self.bridge_sigma_m + self.bridge_growth_m_per_s * gap,
                    self.bridge_max_sigma_m),
                min(self.bridge_sigma_rad + self.bridge_growth_rad_per_s * gap,
                    self.bridge_max_sigma_rad))


class Held(NamedTuple):
    """A held measurement and its arrival number (the measurements held or taken on arrival
    since the start, itself included)."""

    m: Measurement
    seq: int


class Route(enum.Enum):
    """What the session does with a measurement (:meth:`GapHealer.route`)."""

    ADMIT = 'admit'
    REVERSE = 'reverse'
    HOLD = 'hold'
    HOPELESS = 'hopeless'
    DUPLICATE = 'duplicate'


@dataclass(frozen=True)
class Bridge:
    """A bridge the healer made: ``T_from_to`` predicted over ``gap_sec`` seconds."""

    from_id: int
    to_id: int
    gap_sec: float
    sigma_m: float
    sigma_rad: float


def _well_formed(m: Measurement) -> bool:
    """Integer ids, tracks and stamp, a known kind, and finite ``z`` (6,) and ``cov`` (6, 6):
    what holding, reversing and bridging rely on (the aligner checks the rest)."""
    try:
        for v in (m.src_id, m.dst_id, m.src_track, m.dst_track, m.stamp_ns):
            if int(v) != v or not -2**63 <= int(v) < 2**63:
                return False
        z = np.asarray(m.z, dtype=float)
        cov = np.asarray(m.cov, dtype=float)
    except (TypeError, ValueError, OverflowError):
        return False
    return (m.kind in KINDS and z.shape == (6,) and cov.shape == (6, 6)
            and bool(np.isfinite(z).all() and np.isfinite(cov).all()))


def fingerprint(m: Measurement) -> tuple[int, int, int]:
    """``(src_id, dst_id, CRC-32 of z and cov)``: what tells a re-delivery of ``m``."""
    data = (np.asarray(m.z, dtype=float).tobytes()
            + np.asarray(m.cov, dtype=float).tobytes())
    return int(m.src_id), int(m.dst_id), zlib.crc32(data)


def reversed_measurement(m: Measurement) -> Measurement:
    """The same measurement read backwards: ``T_dst_src = T_src_dst^-1``.

    With the covariance ``C`` of the right perturbation of ``T = T_src_dst``
    (``T exp(d)``, ``d`` in ``[x y z rx ry rz]``), ``(T exp(d))^-1 = T^-1 exp(-Ad(T) d)``, so
    the reversed covariance is ``Ad(T) C Ad(T)^T``: the same information about the two poses.
    The stamp stays (it is the original destination's acquisition time).
    """
    T = m.T_src_dst
    Ad = se3.adjoint(T)
    cov = Ad @ np.asarray(m.cov, dtype=float) @ Ad.T
    return Measurement(int(m.dst_id), int(m.src_id), int(m.dst_track), int(m.src_track),
                       se3.to_translation_rotvec(se3.inverse(T)), 0.5 * (cov + cov.T),
                       int(m.stamp_ns), m.kind)


class GapHealer:
    """Held measurements, bridges and the joined / not-yet-joined marks of a session's nodes.

    The healer sees every measurement the aligner takes (:meth:`admitted`), so it knows the
    aligner's nodes without asking it; :meth:`rebuild` restores that knowledge from an aligner's
    tables after a restore.

    Parameters
    ----------
    config : waiting and bridge settings.
    """

    def __init__(self, config: GapConfig | None = None) -> None:
        self.config = config or GapConfig()
        self.held: deque[Held] = deque()
        self._seq = 0
        self.bridges: list[Bridge] = []
        self.open_track: int | None = None
        self._newest_stamp = -2**63
        # union-find over node ids: parent, component size, anchored roots
        self._parent: dict[int, int] = {}
        self._size: dict[int, int] = {}
        self._anchored: set[int] = set()
        self._n_unjoined = 0
        # per track: last node (id, stamp) and last frame-to-frame motion (z, duration ns)
        self._last_node: dict[int, tuple[int, int]] = {}
        self._last_motion: dict[int, tuple[FloatArray, int]] = {}
        self._stamp: dict[int, int] = {}
        #: fingerprints of the measurements taken reversed (:func:`fingerprint`, as they came)
        self.reversed: set[tuple[int, int, int]] = set()

    # ------------------------------------------------------------------ nodes
    def knows(self, node_id: int) -> bool:
        """The aligner holds this node."""
        return int(node_id) in self._parent

    @property
    def n_nodes(self) -> int:
        """Nodes the aligner holds."""
        return len(self._parent)

    @property
    def n_unjoined(self) -> int:
        """Nodes not yet joined to the datum or to an absolute fix (they hang off a bridge)."""
        return self._n_unjoined

    def _find(self, node: int) -> int:
        parent = self._parent
        root = node
        while parent[root] != root:
            root = parent[root]
        while parent[node] != root:  # path compression
            parent[node], node = root, parent[node]
        return root

    def _add_node(self, node: int, anchored: bool) -> None:
        self._parent[node] = node
        self._size[node] = 1
        if anchored:
            self._anchored.add(node)
        else:
            self._n_unjoined += 1

    def _union(self, a: int, b: int) -> None:
        ra, rb = self._find(a), self._find(b)
        if ra == rb:
            return
        if self._size[ra] < self._size[rb]:
            ra, rb = rb, ra
        in_a, in_b = ra in self._anchored, rb in self._anchored
        if in_a != in_b:  # the unanchored piece becomes joined
            self._n_unjoined -= self._size[rb] if in_a else self._size[ra]
        self._parent[rb] = ra
        self._size[ra] += self._size.pop(rb)
        self._anchored.discard(rb)
        if in_a or in_b:
            self._anchored.add(ra)

    def anchor(self, node_id: int) -> bool:
        """Mark the piece of a node as joined because the node got an absolute prior (a fix).

        Returns False (and changes nothing) if the aligner does not hold the node: a fix on a
        node that is still held cannot be applied before its measurements are admitted.
        """
        node = int(node_id)
        if node not in self._parent:
            return False
        root = self._find(node)
        if root not in self._anchored:
            self._anchored.add(root)
            self._n_unjoined -= self._size[root]
        return True

    def unjoined(self, node_ids: IntArray) -> BoolArray:
        """For each node id: True if the aligner holds it and it is not yet joined."""
        out = np.zeros(len(node_ids), dtype=bool)
        if not self._n_unjoined:
            return out
        for k, node in enumerate(np.asarray(node_ids, dtype=np.int64).tolist()):
            if node in self._parent:
                out[k] = self._find(node) not in self._anchored
        return out

    # ------------------------------------------------------------------ routing
    def route(self, m: Measurement, front: bool = False) -> Route:
        """What to do with ``m`` now (see the module docstring).

        ``front``: ``m`` is the first of the held queue (nothing held before it, so it may start
        a new track).
        """
        if not self.config.enabled or not self._parent or not _well_formed(m):
            return Route.ADMIT  # malformed: the aligner rejects it with the exact reason
        if self.reversed and fingerprint(m) in self.reversed:
            return Route.DUPLICATE
        src_known, dst_known = self.knows(m.src_id), self.knows(m.dst_id)
        open_track = self.open_track if self.open_track is not None else -1
        new_track = max(int(m.src_track), int(m.dst_track)) > open_track
        blocked = new_track and bool(self.held) and not front
        if src_known:
            return Route.HOLD if blocked else Route.ADMIT
        if int(m.src_track) < open_track:
            return Route.HOPELESS
        if dst_known and not blocked:
            return Route.REVERSE
        return Route.HOLD

    def hold(self, m: Measurement, seq: int | None = None) -> None:
        """Keep ``m`` at the end of the held queue (an arrival; ``seq``: its arrival number
        when restoring a queue)."""
        self.arrived(m)
        self.held.append(Held(m, self._seq if seq is None else int(seq)))

    def arrived(self, m: Measurement) -> None:
        """Count an arrival (a measurement held, or taken on arrival) and note its stamp (the
        waits of :meth:`overdue`)."""
        self._seq += 1
        self._newest_stamp = max(self._newest_stamp, int(m.stamp_ns))

    def restore_waits(self, arrivals: int, newest_stamp_ns: int) -> None:
        """Set the arrival count and the newest stamp (after a restore)."""
        self._seq, self._newest_stamp = int(arrivals), int(newest_stamp_ns)

    def waits(self) -> tuple[int, int]:
        """``(arrivals, newest_stamp_ns)``: what :meth:`restore_waits` sets (a journal keeps
        them when it is compacted)."""
        return self._seq, self._newest_stamp

    def overdue(self) -> bool:
        """The first held measurement has waited long enough (:class:`GapConfig`) to be
        bridged: ``wait_measurements`` measurements arrived since it, or its stamp is
        ``wait_sec`` older than the newest one."""
        if not self.held:
            return False
        cfg, first = self.config, self.held[0]
        waited = (self._newest_stamp - int(first.m.stamp_ns)) * 1e-9
        return self._seq - first.seq >= cfg.wait_measurements or waited >= cfg.wait_sec

    # ------------------------------------------------------------------ bookkeeping
    def admitted(self, m: Measurement) -> None:
        """Record a measurement the aligner took (a bridge joins nothing)."""
        src, dst = int(m.src_id), int(m.dst_id)
        first = not self._parent
        for node, track in ((src, int(m.src_track)), (dst, int(m.dst_track))):
            if node not in self._parent:
                self._add_node(node, anchored=first and node == src)
                stamp = int(m.stamp_ns)
                self._stamp[node] = stamp
                self._last_node[track] = (node, stamp)
                self.open_track = (track if self.open_track is None
                                   else max(self.open_track, track))
        if m.kind == 'bridge':
            return
        self._union(src, dst)
        if m.kind == 'consecutive':
            self._motion(src, dst, int(m.src_track), int(m.dst_track), m.z)

    def _motion(self, src: int, dst: int, src_track: int, dst_track: int, z) -> None:
        """Note a frame-to-frame motion (the constant velocity of :meth:`bridge_to`)."""
        dt = self._stamp[dst] - self._stamp[src]
        if src_track == dst_track and dt > 0:
            self._last_motion[dst_track] = (np.asarray(z, dtype=float), dt)

    def bridge_origin(self, m: Measurement) -> tuple[int, int, int] | None:
        """``(node id, track id, stamp ns)`` of the node a bridge letting ``m`` in starts from:
        the last node of its source's track (of the open track if its source starts a new
        one); ``None`` if there is no such node."""
        track = int(m.src_track)
        last = self._last_node.get(track)
        if last is None and self.open_track is not None and track > self.open_track:
            last = self._last_node.get(self.open_track)
        if last is None:
            return None
        track_a = int(self.open_track if track not in self._last_node else track)
        return int(last[0]), track_a, int(last[1])

    def bridge_to(self, m: Measurement) -> Measurement | None:
        """The bridge that lets ``m`` (whose two ends are unknown) in, from
        :meth:`bridge_origin` to its source node, predicted at constant velocity; ``None`` if
        there is no node to start from."""
        origin = self.bridge_origin(m)
        if origin is None:
            return None
        a, track_a, stamp_a = origin
        track = int(m.src_track)
        motion = self._last_motion.get(track_a)
        period = motion[1] if motion is not None else 0
        # the stamp is the destination's; its source came about one frame period earlier
        stamp_s = max(int(m.stamp_ns) - period, stamp_a)
        gap_sec = (stamp_s - stamp_a) * 1e-9
        if motion is not None:  # constant velocity: the last motion, scaled to the gap
            r = (stamp_s - stamp_a) / motion[1]
            z = np.concatenate([motion[0][:3] * r, motion[0][3:] * r])
            if np.linalg.norm(z[3:]) > math.pi:  # more than half a turn: do not guess
                z = np.zeros(6)
        else:
            z = np.zeros(6)
        sig_m, sig_rad = self.config.bridge_sigmas(gap_sec)
        cov = np.diag([sig_m**2] * 3 + [sig_rad**2] * 3)
        self.bridges.append(Bridge(a, int(m.src_id), gap_sec, sig_m, sig_rad))
        return Measurement(a, int(m.src_id), track_a, track, z, cov, stamp_s, 'bridge')

    def rebuild(self, src_ids: IntArray, dst_ids: IntArray, z: FloatArray, kinds: list[str],
                node_ids: IntArray, track_ids: IntArray, stamps_ns: IntArray,
                anchored: IntArray | None = None) -> None:
        """Restore the node bookkeeping from an aligner's tables (after a restore).

        Parameters
        ----------
        src_ids, dst_ids, z, kinds : the aligner's connections, in order (``kinds`` as in
            :data:`~ga_ros.core.measurement.KINDS`).
        node_ids, track_ids, stamps_ns : its nodes in arrival order (the first is the datum).
        anchored : nodes with an absolute fix (joined whatever their connections).
        """
        held, cfg, bridges, rev = self.held, self.config, self.bridges, self.reversed
        self.__init__(cfg)
        self.held, self.bridges, self.reversed = held, bridges, rev
        ids = np.asarray(node_ids, dtype=np.int64).tolist()
        tracks = np.asarray(track_ids, dtype=np.int64).tolist()
        stamps = np.asarray(stamps_ns, dtype=np.int64).tolist()
        for k, (node, track, stamp) in enumerate(zip(ids, tracks, stamps)):
            self._add_node(node, anchored=k == 0)
            self._stamp[node] = stamp
            self._last_node[track] = (node, stamp)
            self.open_track = track if self.open_track is None else max(self.open_track, track)
        track_of = dict(zip(ids, tracks))
        for k, (a, b, kind) in enumerate(zip(np.asarray(src_ids).tolist(),
                                             np.asarray(dst_ids).tolist(), kinds)):
            if kind != 'bridge' and a in self._parent and b in self._parent:
                self._union(a, b)
                if kind == 'consecutive':
                    self._motion(a, b, track_of[a], track_of[b], z[k])
        for node in [] if anchored is None else np.asarray(anchored).tolist():
            self.anchor(node)
