"""Track boundaries of a keyframe stream (ROS-free): :class:`TrackSegmenter`.

A track is the unit the alignment window works on (the paper's double swath). Whatever makes
the keyframes -- the stereo VO (:mod:`ga_ros.vo.odometry`) or a standard odometry input
(:mod:`ga_ros.inputs.odometry`) -- asks one :class:`TrackSegmenter` at every new keyframe
whether a new track starts there. The rules (:class:`TrackRules`):

* ``'none'``: one track;
* ``'frames'``: a fixed number (``keyframes``) of keyframes per track;
* ``'heading'``: a reversal of the horizontal travel direction ends a swath, and every
  ``swaths`` swaths a track;
* ``'distance'`` / ``'time'``: a track ends after ``length_m`` of travel or ``duration_s`` of
  time;
* ``'external'``: only on request (:meth:`TrackSegmenter.request_boundary`, honoured in every
  mode).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.config_ranges import check_ranges, ranged
from ga_ros.errors import InputError

TRACK_MODES = ('none', 'frames', 'heading', 'distance', 'time', 'external')


@dataclass(frozen=True)
class TrackRules:
    """When a new track starts: the ``track`` settings of every keyframe source (parameters
    ``track.<field>`` of the VO, ``<input>.track.<field>`` of an odometry input).

    Attributes
    ----------
    mode : ``'none'`` (one track), ``'frames'``, ``'heading'``, ``'distance'``, ``'time'`` or
        ``'external'`` (see the module doc).
    keyframes : keyframes per track in ``'frames'`` mode.
    swaths : swaths per track in ``'heading'`` mode (a track is a double swath with 2).
    heading_reversal_deg : turn of the travel direction that ends a swath (deg).
    heading_min_step_m : travel between keyframes below which the travel direction is not
        updated (m; a hovering platform does not start swaths). The VO replaces it by a
        fraction of the scene depth (``VoConfig.heading_min_step_depth_ratio``) unless that is 0.
    length_m : travel (m, along the keyframe positions) per track in ``'distance'`` mode.
    duration_s : time (s) per track in ``'time'`` mode.
    """

    mode: str = 'none'
    keyframes: int = ranged(0, 0, 1_000_000)
    swaths: int = ranged(2, 1, 1000)
    heading_reversal_deg: float = ranged(135.0, 0.0, 180.0)
    heading_min_step_m: float = ranged(0.5, 0.0, 1e6)
    length_m: float = ranged(0.0, 0.0, 1e9)
    duration_s: float = ranged(0.0, 0.0, 1e9)

    #: Former flat names of these settings in the enclosing config (``odom0.track_mode``):
    #: ``{former name: field}``; a former name is refused with the new one
    #: (:func:`refuse_former_names`).
    FORMER_NAMES: ClassVar[dict[str, str]] = {
        'track_mode': 'mode', 'keyframes_per_track': 'keyframes',
        'swaths_per_track': 'swaths', 'heading_reversal_deg': 'heading_reversal_deg',
        'heading_min_step_m': 'heading_min_step_m', 'track_length_m': 'length_m',
        'track_duration_s': 'duration_s'}

    def __post_init__(self) -> None:
        if self.mode not in TRACK_MODES:
            raise InputError(f'unknown track.mode {self.mode!r}; use one of {TRACK_MODES}')
        check_ranges(self)
        if self.mode == 'frames' and self.keyframes < 1:
            raise InputError('track.mode "frames" needs track.keyframes >= 1')
        if self.mode == 'distance' and not self.length_m > 0:
            raise InputError('track.mode "distance" needs track.length_m > 0')
        if self.mode == 'time' and not self.duration_s > 0:
            raise InputError('track.mode "time" needs track.duration_s > 0')

    @classmethod
    def from_mapping(cls, values: object, where: str = 'track') -> TrackRules:
        """The rules of a ``track:`` mapping of a settings file (``where`` names it in errors).

        Raises
        ------
        InputError
            Not a mapping, an unknown key or an invalid value.
        """
        if not isinstance(values, Mapping):
            raise InputError(f'{where}: expected a mapping of track settings, got {values!r}')
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise InputError(f'{where}: unknown track settings {unknown}; known: {sorted(known)}')
        return cls(**dict(values))


def refuse_former_names(names: Iterable[str], prefix: str = '', field_name: str = 'track') -> None:
    """Refuse a former flat track setting among parameter ``names`` (``prefix`` + former name,
    e.g. ``odom0.track_mode``), naming its new place (``odom0.track.mode``).

    Raises
    ------
    InputError
        A former name is present.
    """
    for name in names:
        old = name[len(prefix):] if name.startswith(prefix) else None
        if old in TrackRules.FORMER_NAMES:
            raise InputError(f'parameter {name} was renamed to '
                             f'{prefix}{field_name}.{TrackRules.FORMER_NAMES[old]}')


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
        elif rules.mode == 'frames' and self._frames > rules.keyframes:
            new = True
        elif rules.mode == 'distance' and self._length_m > rules.length_m:
            new = True
        elif (rules.mode == 'time'
              and (int(stamp_ns) - self._start_ns) * 1e-9 > rules.duration_s):
            new = True
        elif rules.mode == 'heading':
            step_m = rules.heading_min_step_m if min_step_m is None else float(min_step_m)
            if self._heading_reversed(xyz[:2], step_m):
                self._swath += 1
                self.segment += 1
                self._start_xy, self._ref_dir = xyz[:2], None
                if self._swath % rules.swaths == 0:
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
