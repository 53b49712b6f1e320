"""Track boundaries of a keyframe stream (ROS-free): :class:`TrackSegmenter`.

A track is the unit the alignment window works on (the paper's double swath). Whatever makes
the keyframes -- the stereo VO (:mod:`ga_ros.vo.odometry`) or a standard odometry input
(:mod:`ga_ros.inputs.odometry`) -- asks one :class:`TrackSegmenter` at every new keyframe
whether a new track starts there. The rules (:class:`TrackRules`):

* ``'none'``: one track;
* ``'frames'``: a fixed number of keyframes per track;
* ``'heading'``: a reversal of the horizontal travel direction ends a swath, and every
  ``swaths_per_track`` swaths a track;
* ``'distance'`` / ``'time'``: a track ends after ``track_length_m`` of travel or
  ``track_duration_s`` of time;
* ``'external'``: only on request (:meth:`TrackSegmenter.request_boundary`, honoured in every
  mode).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError

TRACK_MODES = ('none', 'frames', 'heading', 'distance', 'time', 'external')


@dataclass(frozen=True)
class TrackRules:
    """When a new track starts.

    Attributes
    ----------
    track_mode : one of ``'none'``, ``'frames'``, ``'heading'``, ``'distance'``, ``'time'``,
        ``'external'`` (see the module doc).
    keyframes_per_track : keyframes per track in ``'frames'`` mode.
    swaths_per_track : swaths per track in ``'heading'`` mode.
    heading_reversal_deg : turn of the travel direction that ends a swath (deg).
    heading_min_step_m : travel between keyframes below which the direction is not updated (m;
        a hovering platform does not start swaths).
    track_length_m : travel (m, along the keyframe positions) per track in ``'distance'`` mode.
    track_duration_s : time (s) per track in ``'time'`` mode.
    """

    track_mode: str = 'heading'
    keyframes_per_track: int = 0
    swaths_per_track: int = 2
    heading_reversal_deg: float = 135.0
    heading_min_step_m: float = 2.0
    track_length_m: float = 0.0
    track_duration_s: float = 0.0

    def __post_init__(self) -> None:
        if self.track_mode not in TRACK_MODES:
            raise InputError(f'unknown track_mode {self.track_mode!r}; use one of {TRACK_MODES}')
        if self.track_mode == 'frames' and self.keyframes_per_track < 1:
            raise InputError('track_mode "frames" needs keyframes_per_track >= 1')
        if self.track_mode == 'distance' and not self.track_length_m > 0:
            raise InputError('track_mode "distance" needs track_length_m > 0')
        if self.track_mode == 'time' and not self.track_duration_s > 0:
            raise InputError('track_mode "time" needs track_duration_s > 0')
        if self.swaths_per_track < 1:
            raise InputError('swaths_per_track must be >= 1')


class TrackSegmenter:
    """Track (and swath) ids of successive keyframes under :class:`TrackRules`.

    Attributes
    ----------
    track_id : track of the latest keyframe (starts at 0).
    segment : swath counter (``'heading'`` mode) or track counter; cross-track candidates must
        come from another segment.
    """

    def __init__(self, rules: TrackRules) -> None:
        self.rules = rules
        self.track_id = 0
        self.segment = 0
        self._frames = 0
        self._swath = 0
        self._ref_dir: FloatArray | None = None
        self._ref_xy = np.zeros(2)
        self._start_xy: FloatArray | None = None
        self._pending = False
        self._length_m = 0.0
        self._last_xyz: FloatArray | None = None
        self._start_ns: int | None = None

    def request_boundary(self) -> None:
        """Start a new track at the next keyframe (``'external'`` mode; honoured in every mode)."""
        self._pending = True

    def update(self, T_world_kf: FloatArray, stamp_ns: int = 0,
               min_step_m: float | None = None) -> bool:
        """Advance by one keyframe; True when a new track starts at it.

        Parameters
        ----------
        T_world_kf : (4, 4) pose of the keyframe in the stream's own world frame.
        stamp_ns : its time (ns); used by the ``'time'`` rule.
        min_step_m : overrides ``heading_min_step_m`` for this call (e.g. scaled by the scene
            depth the VO measures).
        """
        rules = self.rules
        xyz = np.asarray(T_world_kf, float)[:3, 3]
        if self._last_xyz is not None:
            self._length_m += float(np.linalg.norm(xyz - self._last_xyz))
        self._last_xyz = xyz
        if self._start_ns is None:
            self._start_ns = int(stamp_ns)
        self._frames += 1
        new = False
        if self._pending:
            self._pending = False
            new = True
        elif rules.track_mode == 'frames' and self._frames > rules.keyframes_per_track:
            new = True
        elif rules.track_mode == 'distance' and self._length_m > rules.track_length_m:
            new = True
        elif (rules.track_mode == 'time'
              and (int(stamp_ns) - self._start_ns) * 1e-9 > rules.track_duration_s):
            new = True
        elif rules.track_mode == 'heading':
            step_m = rules.heading_min_step_m if min_step_m is None else float(min_step_m)
            if self._heading_reversed(xyz[:2], step_m):
                self._swath += 1
                self.segment += 1
                self._start_xy, self._ref_dir = xyz[:2], None
                if self._swath % rules.swaths_per_track == 0:
                    self.track_id += 1
                    return True
                return False
        if new:
            self.track_id += 1
            self.segment += 1
            self._restart(stamp_ns)
        return new

    def _restart(self, stamp_ns: int) -> None:
        self._frames = 1
        self._length_m = 0.0
        self._start_ns = int(stamp_ns)

    def _heading_reversed(self, xy: FloatArray, step_m: float) -> bool:
        """Update the travel direction with the keyframe position ``xy``; True on a reversal."""
        if self._start_xy is None:
            self._start_xy = xy
        if self._ref_dir is None:
            travel = xy - self._start_xy
            dist = float(np.linalg.norm(travel))
            if dist >= step_m and self._frames >= 3:
                self._ref_dir = travel / dist
                self._ref_xy = xy
            return False
        step = xy - self._ref_xy
        ds = float(np.linalg.norm(step))
        if ds < step_m:
            return False
        if float(step @ self._ref_dir) / ds < np.cos(np.deg2rad(self.rules.heading_reversal_deg)):
            return True
        self._ref_xy = xy
        return False
