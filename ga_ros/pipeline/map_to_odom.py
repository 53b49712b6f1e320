"""The REP 105 ``map -> odom`` correction, its odometry chain and its fixed-period schedule.

One definition for ``alignment_node`` and the replay (ROS-free):

* **odometry chain**: the ``odom`` frame is the first standard input's odometry
  (:meth:`ga_ros.pipeline.inputs.InputFrontEnd.map_to_odom`) or, without standard inputs, the
  frame-to-frame integration of the consecutive measurements
  (:class:`ga_ros.core.integration.F2FIntegrator`, ``odom`` = the first node's frame);
* **placement** (:attr:`MapToOdom.placed_by`): from the first odometry message the identity
  (``map`` = ``odom``, as robot_localization and slam_toolbox start) until something places the
  map (after a restart on a saved state: that state's last correction,
  :meth:`MapToOdom.restore`); with ``datum: fixes`` the fixes place it as soon as they
  determine it and refine it with each fix until the aligner's first window update
  (:mod:`ga_ros.pipeline.map_placement`), then the aligner's corrected path does; with
  ``datum: first_node`` the corrected path places it from the first keyframe on;
* **correction**: ``T_map_odom = T_map_k inv(T_odom_k)`` at the newest node ``k`` of the
  corrected path that the chain reached (:meth:`MapToOdom.update`, after every window update);
* **jumps**: a change of ``map -> odom`` that moves ``map -> base_link`` (at the newest
  odometry pose) by more than ``jump_sigmas`` position sigmas of the newest fix is counted and
  reported (:attr:`MapToOdom.warning`: a WARN in the node's /diagnostics, a warning in the
  replay's summary); the identity's replacement by the first placement is not a jump;
* **stamps**: :meth:`MapToOdom.stamp` never lets a header stamp step back;
* **schedule**: the transform is sent at a fixed period with the latest correction, as
  slam_toolbox and robot_localization do (``transform_publish_period_sec``, default 0.05 s):
  the node with a timer, the replay at the same period of the bag's time
  (:class:`PeriodicSchedule`);
* **one parent**: transforms of other publishers that would give ``odom`` a second parent
  (:func:`foreign_odom_parents`) are detected (the node stops fighting unless told) and not
  copied into a replay's output bag (:func:`without_odom_parent`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.integration import F2FIntegrator
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.pipeline.absolute import ResolvedFix
from ga_ros.pipeline.inputs import InputFrontEnd
from ga_ros.pipeline.map_placement import FixPlacement, PlacementConfig, position_sigma

#: Default period of the ``map -> odom`` transform (s), slam_toolbox's.
TRANSFORM_PERIOD_S = 0.05


class MapToOdom:
    """The odometry chain, the placement of the map and the latest ``T_map_odom`` (module
    docstring).

    Parameters
    ----------
    front : the standard inputs (their first input is ``odom``); None: the measurements'
        frame-to-frame integration is.
    f2f : the integrator to use without standard inputs (default: a new one at the identity;
        the replay passes the one of its F2F path).
    datum : the aligner's datum (``'first_node'`` or ``'fixes'``,
        :class:`~ga_ros.core.window.AlignerConfig`): with ``'fixes'`` the fixes place the map
        until the first window update.
    placement : thresholds of the placement from fixes and of the jump warning.
    """

    def __init__(self, front: InputFrontEnd | None = None,
                 f2f: F2FIntegrator | None = None, datum: str = 'first_node',
                 placement: PlacementConfig = PlacementConfig()) -> None:
        self.front = front
        self.f2f = f2f if f2f is not None else (F2FIntegrator() if front is None else None)
        self.datum = datum
        self.config = placement
        #: (4, 4) the latest correction: the identity until something places the map
        self.T_map_odom: FloatArray = np.eye(4)
        #: what placed the map: ``'identity'`` (nothing yet: map = odom), ``'fixes'``,
        #: ``'aligner'``, ``'restored'`` (a restored state's last correction, :meth:`restore`)
        self.placed_by = 'identity'
        self.fixes = FixPlacement(placement)
        #: changes of ``map -> odom`` beyond the fixes' uncertainty; the text of the newest
        #: (``warning``: '' again after a change within it; ``last_warning``: kept)
        self.jumps_warned = 0
        self.warning = ''
        self.last_warning = ''
        #: how far the last change moved ``map -> base_link`` (m)
        self.last_jump_m = 0.0
        #: position sigma (m) of the newest fix (the jump limit's unit; inf before any)
        self.fix_sigma_m = float('inf')
        self._stamp_ns: int | None = None

    def add(self, m: Measurement) -> None:
        """An accepted measurement: extends the frame-to-frame chain (without standard inputs,
        or when an integrator was given)."""
        if self.f2f is not None:
            self.f2f.add(m)

    def add_fixes(self, fixes: Sequence[ResolvedFix]) -> None:
        """Fixes tied to the first input's keyframes: with ``datum: fixes`` the newest gives
        the jump limit's sigma and, before the aligner has placed the map, each refines the
        placement (:class:`~ga_ros.pipeline.map_placement.FixPlacement`)."""
        if self.datum != 'fixes':
            return
        sigmas = [s for s in (position_sigma(f.term.fix) for f in fixes) if np.isfinite(s)]
        if sigmas:
            self.fix_sigma_m = sigmas[-1]
        if self.placed_by in ('aligner', 'restored') or self.front is None:
            return
        odometry = self.front.inputs[self.front.primary]
        for f in fixes:
            try:
                T_odom_k = odometry.keyframe_pose(int(f.term.node_id))
            except InputError:
                continue   # a keyframe the odometry no longer keeps
            p = self.fixes.add(T_odom_k @ f.term.T_node_sensor, f.term.fix)
            if p is not None:
                self._set(p.T_map_odom, 'fixes')

    def restore(self, T_map_odom: FloatArray | None) -> None:
        """A restored state's last correction (``AlignmentSession.map_odom``, journaled after
        each update): sent from now on instead of the identity, until an update of the path
        recomputes it (that change is checked as a jump). ``None``: nothing changes.

        It is right while the odometry's ``odom`` frame went on across the restart (the
        alignment node alone restarted); an odometry restarted too starts a new ``odom``, which
        the first window update places again."""
        if T_map_odom is None:
            return
        self.T_map_odom = np.array(T_map_odom, dtype=float)
        self.placed_by = 'restored'

    def new_map(self) -> None:
        """The survey was emptied (``~/reset``): the map is placed again as at a start, so
        ``T_map_odom`` is the identity (``placed_by`` ``'identity'``) until the new survey's
        path (:meth:`update`) or its fixes place it; the fix placement, the jump counts and
        warnings start again. The odometry chain (``odom`` goes on, REP 105) and the stamps
        (never back) stay."""
        self.T_map_odom = np.eye(4)
        self.placed_by = 'identity'
        self.fixes = FixPlacement(self.config)
        self.jumps_warned, self.warning, self.last_warning = 0, '', ''
        self.last_jump_m = 0.0
        self.fix_sigma_m = float('inf')

    def update(self, node_ids: IntArray, T_map_node: FloatArray,
               adjusted: bool = True) -> FloatArray:
        """Recompute ``T_map_odom`` from a corrected path; returns it (the previous one if the
        chain reached none of the nodes).

        Parameters
        ----------
        node_ids : (n,) node ids of the corrected path, in path order (newest last).
        T_map_node : (n, 4, 4) their corrected poses in ``map``.
        adjusted : the path comes from a window update (or a restored state); False: the
            aligner's provisional path before any, which places the map only with
            ``datum: first_node``.
        """
        if not adjusted and self.datum == 'fixes':
            return self.T_map_odom
        if self.front is not None:
            T = self.front.map_to_odom(node_ids, T_map_node)
        elif self.f2f is not None:
            T = self.f2f.map_to_odom(node_ids, T_map_node)
        else:
            T = None
        if T is not None:
            self._set(np.asarray(T, float), 'aligner')
        return self.T_map_odom

    def _set(self, T: FloatArray, by: str) -> None:
        """A new ``T_map_odom`` from ``by``; the jump check (module docstring)."""
        before, self.T_map_odom = self.T_map_odom, T
        first, self.placed_by = self.placed_by == 'identity', by
        newest = self.latest()
        if first or newest is None:
            return
        p = newest[0][:, 3]
        self.last_jump_m = float(np.linalg.norm(((T - before) @ p)[:3]))
        limit = self.config.jump_sigmas * self.fix_sigma_m
        if self.last_jump_m > limit:
            self.jumps_warned += 1
            self.warning = (f'map -> odom ({by}) moved map -> base_link by '
                            f'{self.last_jump_m:.2f} m, more than {self.config.jump_sigmas:g} '
                            f'sigma of the fixes ({limit:.2f} m)')
            self.last_warning = self.warning
        elif self.last_jump_m > 0:
            self.warning = ''

    def stamp(self, stamp_ns: int) -> int:
        """The header stamp (ns) to send a transform at ``stamp_ns`` with: never before the
        previous one."""
        s = int(stamp_ns) if self._stamp_ns is None else max(self._stamp_ns, int(stamp_ns))
        self._stamp_ns = s
        return s

    def diagnostic_values(self) -> dict[str, object]:
        """Key/values of the placement for /diagnostics and the replay's summary."""
        p = self.fixes.placement
        out: dict[str, object] = {
            'map_to_odom/placed_by': ('identity (map not placed yet: map = odom)'
                                      if self.placed_by == 'identity' else self.placed_by),
            'map_to_odom/jumps_warned': self.jumps_warned,
            'map_to_odom/last_jump_m': round(self.last_jump_m, 4)}
        if p is not None:
            out['map_to_odom/fixes_used'] = p.n_fixes
            out['map_to_odom/fixes_heading'] = p.heading
        return out

    def latest(self) -> tuple[FloatArray, int] | None:
        """``(T_odom_base, stamp_ns)`` of the newest odometry pose (None before any)."""
        if self.front is not None:
            T = self.front.latest_pose()
            return None if T is None else (T, int(self.front.latest_stamp_ns))
        return self.f2f.newest() if self.f2f is not None else None


class PeriodicSchedule:
    """Times at which a transform is due, every ``period_s`` of a clock (ns).

    Parameters
    ----------
    period_s : the period (s, > 0).
    max_burst : at most this many times from one :meth:`due` call (a jump of the clock sends
        only the newest ones).
    """

    def __init__(self, period_s: float = TRANSFORM_PERIOD_S, max_burst: int = 10000) -> None:
        if not period_s > 0:
            raise InputError(f'transform period must be > 0 s, got {period_s}')
        self.period_ns = int(round(period_s * 1e9))
        self.max_burst = int(max_burst)
        self._next: int | None = None

    def due(self, now_ns: int) -> list[int]:
        """The due times up to ``now_ns`` since the last call (the first call: ``now_ns``)."""
        now_ns = int(now_ns)
        if self._next is None:
            self._next = now_ns
        if now_ns < self._next:
            return []
        n = (now_ns - self._next) // self.period_ns + 1
        first = self._next + max(0, n - self.max_burst) * self.period_ns
        times = list(range(first, now_ns + 1, self.period_ns))
        self._next = times[-1] + self.period_ns
        return times


def foreign_odom_parents(msg: Any, odom_frame: str, own: dict[int, FloatArray],
                         map_frame: str = '', atol: float = 1e-6) -> list[str]:
    """Parents given to ``odom_frame`` by transforms of a ``tf2_msgs/TFMessage`` that are not
    ours (rclpy or rosbags message, read by field name).

    Parameters
    ----------
    msg : the TF message heard.
    odom_frame : our child frame (``odom``).
    own : ``{stamp_ns: T_map_odom}`` of the transforms we sent recently; a transform from
        ``map_frame`` with one of these stamps and the same value is ours.
    map_frame : our parent frame.
    atol : tolerance of the comparison with ours (m, and rotation-matrix entries).

    Returns
    -------
    list[str]
        The parent frame of every foreign transform to ``odom_frame`` (empty: none).
    """
    out = []
    for t in getattr(msg, 'transforms', ()):
        if t.child_frame_id.lstrip('/') != odom_frame.lstrip('/'):
            continue
        parent = t.header.frame_id.lstrip('/')
        stamp = int(t.header.stamp.sec) * 10**9 + int(t.header.stamp.nanosec)
        mine = own.get(stamp)
        if mine is not None and parent == map_frame.lstrip('/'):
            tr, q = t.transform.translation, t.transform.rotation
            T = se3.from_pos_quat(np.array([tr.x, tr.y, tr.z], float),
                                  np.array([q.x, q.y, q.z, q.w], float))
            if np.allclose(T, mine, atol=atol):
                continue
        out.append(parent)
    return out


def without_odom_parent(msg: Any, odom_frame: str) -> tuple[Any, int]:
    """A ``tf2_msgs/TFMessage`` (a dataclass message, e.g. rosbags') without the transforms
    whose child is ``odom_frame``; returns ``(message, how many were removed)`` (the same
    message when none was)."""
    keep = [t for t in msg.transforms
            if t.child_frame_id.lstrip('/') != odom_frame.lstrip('/')]
    removed = len(msg.transforms) - len(keep)
    return (msg, 0) if removed == 0 else (replace(msg, transforms=keep), removed)
