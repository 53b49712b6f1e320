"""A relative-motion measurement between two nodes: the unit the live pipeline exchanges.

This is the core type behind the ROS measurement encoding (``nav_msgs/Odometry``, see
:mod:`ga_ros.ros.conversions` and the README): the visual odometry produces it, the alignment node
and the offline replay consume it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.geometry import se3

#: Kinds of measurement: a frame-to-frame motion, an overlap between swaths or tracks, and a
#: motion predicted over a gap in the stream (made by :class:`ga_ros.core.gaps.GapHealer`, with a
#: large covariance: it gives the nodes after the gap a datum until a real connection joins them).
KINDS = ('consecutive', 'cross', 'bridge')


@dataclass(frozen=True)
class Measurement:
    """Motion ``T_src_dst`` of node ``dst`` in the frame of node ``src``, with covariance.

    Attributes
    ----------
    src_id, dst_id : node ids (non-negative integers, unique over a survey).
    src_track, dst_track : track ids of the two nodes (a track = one double swath, increasing).
    z : (6,) ``[t, w]``: translation (m) and rotation vector (rad) of ``T_src_dst``.
    cov : (6, 6) covariance of the right perturbation of ``T_src_dst``, order ``[x y z rx ry rz]``.
    stamp_ns : acquisition time of the ``dst`` frame (ns since the epoch, or bag time).
    kind : ``'consecutive'`` (frame to frame), ``'cross'`` (overlap between swaths / tracks) or
        ``'bridge'`` (predicted over a gap, see :data:`KINDS`).
    source : name of the input that measured it (``odom0``, ``odom1``, ...; '' when unknown):
        the group whose variance factor it shares (:func:`variance_group`).
    """

    src_id: int
    dst_id: int
    src_track: int
    dst_track: int
    z: FloatArray
    cov: FloatArray
    stamp_ns: int = 0
    kind: str = field(default='consecutive')
    source: str = ''

    @property
    def T_src_dst(self) -> FloatArray:
        """The motion as a 4x4 pose."""
        return se3.from_translation_rotvec(np.asarray(self.z[:3]), np.asarray(self.z[3:]))

    @staticmethod
    def from_pose(src_id: int, dst_id: int, src_track: int, dst_track: int, T_src_dst: FloatArray,
                  cov: FloatArray, stamp_ns: int = 0, kind: str = 'consecutive',
                  source: str = '') -> Measurement:
        """Build from a 4x4 motion ``T_src_dst``."""
        return Measurement(int(src_id), int(dst_id), int(src_track), int(dst_track),
                           se3.to_translation_rotvec(np.asarray(T_src_dst, dtype=float)),
                           np.asarray(cov, dtype=float).reshape(6, 6), int(stamp_ns), kind,
                           source)


#: Appended to a source's name for the group of its cross-track connections
#: (:func:`variance_group`: ``cam0.cross``).
CROSS_GROUP_SUFFIX = '.cross'


def variance_group(m: Measurement) -> str:
    """The group whose variance factor a measurement shares
    (:mod:`ga_ros.core.quality.variance_components`): its source's consecutive motions
    (``odom0``; ``motion`` when the source is unknown), the cross-track connections (``cross``,
    also for a source named ``cross``; ``<source>.cross`` for those of a named source, e.g. a
    camera's ``cam0.cross`` or a loop-closure source's ``loops.cross``, apart from its
    consecutive motions: matching across tracks and tracking frame to frame err differently)
    and the bridges over gaps (``bridge``)."""
    if m.kind == 'consecutive':
        return m.source or 'motion'
    if m.kind == 'cross':
        return m.source + CROSS_GROUP_SUFFIX if m.source not in ('', 'cross') else 'cross'
    return m.kind


def source_or_group(m: Measurement) -> str:
    """The measurement's source where it has one, else its :func:`variance_group`: the name a
    source's additional parameters go by (``docs/calibration.md``), for its consecutive
    motions and cross-track connections alike."""
    return m.source or variance_group(m)
