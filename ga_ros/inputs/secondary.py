"""A further odometry / pose stream measured on the primary input's keyframes (ROS-free).

With several relative sources (wheel + visual odometry, two SLAM systems, DVL + INS) the first
(primary) input defines the keyframes, the nodes of the one keyframe graph
(:class:`ga_ros.inputs.odometry.OdometryInput`). Every other stream is a
:class:`SecondaryInput`: for each pair of consecutive keyframes ``(a, b)`` whose stamps its own
samples bracket, it measures the motion ``T_a_b = T_odom_a^-1 T_odom_b`` from its own poses
interpolated on SE(3) at the two keyframe stamps, a ``'consecutive'``
:class:`~ga_ros.core.measurement.Measurement` between the same two node ids as the primary's.
Two measurements of one pair are independent observations (the aligner keeps both: its
duplicate test only refuses a repeated message with the same values).

Coverage
    An interval is measured once the stream has a sample at or after its end stamp; it is not
    measured (counted in :attr:`SecondaryStats.not_covered`) when the stream's first sample is
    after its start (a stream that starts later), when two successive samples around or inside
    it are more than ``max_gap_s`` apart (a dropout), or when its start is older than the
    stream's history (``history_s``). A stream thus joins and leaves without any rejection.

Motion covariance
    The policy of :mod:`ga_ros.inputs.odometry` (``covariance_source``) on the samples from the
    interval's start to its end: ``'twist'`` integrates the twist covariance over the pieces
    between the two interpolated ends and the samples in between (a piece of length ``dt``
    adds ``dt^2 Sigma_v`` of the sample ending it); ``'pose_difference'`` /
    ``'pose_independent'`` use the pose covariances of the samples nearest the two stamps;
    otherwise, or when those are unusable, the input's default covariance (counted).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.inputs.odometry import (
    OdometryInputConfig,
    body_pose_covariance,
    check_pose,
    interpolate_pose,
    transport_covariance,
    usable_covariance,
)


@dataclass(frozen=True)
class KeyframeInterval:
    """Two consecutive keyframes of the primary input.

    Attributes
    ----------
    src_id, dst_id : node ids of the earlier and the later keyframe.
    src_track, dst_track : their tracks.
    src_stamp_ns, dst_stamp_ns : their acquisition times (ns).
    """

    src_id: int
    dst_id: int
    src_track: int
    dst_track: int
    src_stamp_ns: int
    dst_stamp_ns: int


@dataclass(frozen=True)
class SecondaryStats:
    """Counters of a :class:`SecondaryInput`.

    Attributes
    ----------
    samples : samples accepted.
    measurements : keyframe intervals measured.
    not_covered : keyframe intervals the stream could not bracket (late start, dropout).
    default_covariances : measurements whose covariance was the default.
    pending : keyframe intervals still waiting for a sample at or after their end (at the end
        of a recording: those after the stream's last sample).
    constraints : always 0 (external constraints use the primary input).
    """

    samples: int
    measurements: int
    not_covered: int
    default_covariances: int
    pending: int = 0
    constraints: int = 0


class SecondaryInput:
    """A further relative stream measured on the primary's keyframe intervals (module doc).

    Parameters
    ----------
    config : the stream's settings (covariance policy, default noise, ``max_gap_s``,
        ``history_s``; the keyframe and track settings are the primary's and unused here).
    """

    def __init__(self, config: OdometryInputConfig = OdometryInputConfig()) -> None:
        self.config = config
        self._stamps: list[int] = []
        self._poses: list[FloatArray] = []
        self._pose_covs: list[FloatArray | None] = []
        self._twist_covs: list[FloatArray | None] = []
        self._pending: list[KeyframeInterval] = []
        self._n = dict(samples=0, measurements=0, not_covered=0, default_covariances=0)

    @property
    def stats(self) -> SecondaryStats:
        """Counters so far."""
        return SecondaryStats(**self._n, pending=len(self._pending))

    def add_sample(self, stamp_ns: int, T_odom_base: FloatArray,
                   pose_cov: FloatArray | None = None,
                   twist_cov: FloatArray | None = None) -> list[Measurement]:
        """Feed one sample (arguments as :meth:`OdometryInput.add_sample`); the measurements of
        the pending keyframe intervals it completes, in order.

        Raises
        ------
        InputError
            A malformed pose or a stamp not after the previous one (nothing changed).
        """
        T = check_pose(T_odom_base, f'{self.config.name}: T_odom_base')
        stamp = int(stamp_ns)
        if self._stamps and stamp <= self._stamps[-1]:
            raise InputError(f'{self.config.name}: stamp {stamp} ns is not after the previous '
                             f'sample ({self._stamps[-1]} ns); restart the input on a loop')
        self._stamps.append(stamp)
        self._poses.append(T)
        self._pose_covs.append(body_pose_covariance(T, pose_cov,
                                                    self.config.pose_covariance_frame))
        self._twist_covs.append(np.asarray(twist_cov, float)
                                if usable_covariance(twist_cov) else None)
        self._n['samples'] += 1
        self._forget(stamp)
        return self._resolve()

    def add_interval(self, interval: KeyframeInterval) -> list[Measurement]:
        """A new keyframe interval of the primary; its measurement if the stream already
        covers it (else it waits for a later sample or is counted as not covered)."""
        self._pending.append(interval)
        return self._resolve()

    def forget_intervals(self) -> int:
        """Drop the keyframe intervals still waiting for a sample (the primary started a fresh
        keyframe chain, whose ids name other nodes); returns how many. Its samples stay."""
        n = len(self._pending)
        self._pending.clear()
        return n

    # ----------------------------------------------------------------- helpers
    def _forget(self, stamp: int) -> None:
        """Drop samples older than ``history_s`` (keeping two), and intervals they started."""
        horizon = stamp - int(self.config.history_s * 1e9)
        drop = 0
        while drop < len(self._stamps) - 2 and self._stamps[drop + 1] < horizon:
            drop += 1
        if drop:
            del self._stamps[:drop], self._poses[:drop]
            del self._pose_covs[:drop], self._twist_covs[:drop]

    def _resolve(self) -> list[Measurement]:
        out = []
        while self._pending and self._stamps and (
                self._stamps[-1] >= self._pending[0].dst_stamp_ns):
            m = self._measure(self._pending.pop(0))
            if m is None:
                self._n['not_covered'] += 1
            else:
                self._n['measurements'] += 1
                out.append(m)
        return out

    def _measure(self, iv: KeyframeInterval) -> Measurement | None:
        s = self._stamps
        ta, tb = iv.src_stamp_ns, iv.dst_stamp_ns
        if not s or s[0] > ta or tb <= ta:
            return None
        s_arr = np.asarray(s, dtype=np.int64)
        i0 = int(np.searchsorted(s_arr, ta, side='right')) - 1  # last sample <= ta
        i1 = int(np.searchsorted(s_arr, tb, side='left'))  # first sample >= tb
        span = s_arr[i0:i1 + 1]
        if len(span) > 1 and np.diff(span).max() * 1e-9 > self.config.max_gap_s:
            return None
        T_a = self._pose_at(i0, ta)
        T_b = self._pose_at(i1 - 1, tb) if s[i1] != tb else self._poses[i1]
        T_rel = se3.relative(T_a, T_b)
        cov, default = self._covariance(i0, i1, ta, tb, T_a, T_b, T_rel)
        if default:
            self._n['default_covariances'] += 1
        return Measurement.from_pose(iv.src_id, iv.dst_id, iv.src_track, iv.dst_track, T_rel,
                                     cov, tb, 'consecutive', self.config.name)

    def _pose_at(self, i: int, t: int) -> FloatArray:
        """Pose at ``t`` between samples ``i`` and ``i + 1`` (sample ``i`` if at its stamp)."""
        s = self._stamps
        if s[i] == t or i + 1 >= len(s):
            return self._poses[i]
        alpha = (t - s[i]) / (s[i + 1] - s[i])
        return interpolate_pose(self._poses[i], self._poses[i + 1], alpha)

    def _covariance(self, i0: int, i1: int, ta: int, tb: int, T_a: FloatArray,
                    T_b: FloatArray, T_rel: FloatArray) -> tuple[FloatArray, bool]:
        """Covariance of the interval's motion and whether it is the default."""
        src = self.config.covariance_source
        if src in ('auto', 'twist'):
            C = self._twist_covariance(i0, i1, ta, tb, T_a, T_b)
            if C is not None and usable_covariance(C):
                return C, False
        if src in ('auto', 'pose_difference', 'pose_independent'):
            C_a = self._pose_covs[i0 if ta - self._stamps[i0] <= self._stamps[i0 + 1] - ta
                                  else i0 + 1]
            C_b = self._pose_covs[i1 if self._stamps[i1] - tb <= tb - self._stamps[i1 - 1]
                                  else i1 - 1]
            if C_a is not None and C_b is not None:
                prior = transport_covariance(T_rel, C_a)
                C = C_b + prior if src == 'pose_independent' else C_b - prior
                C = 0.5 * (C + C.T)
                if usable_covariance(C):
                    return C, False
        return self.config.default_covariance(se3.to_translation_rotvec(T_rel)), True

    def _twist_covariance(self, i0: int, i1: int, ta: int, tb: int, T_a: FloatArray,
                          T_b: FloatArray) -> FloatArray | None:
        """Twist covariance integrated from ``ta`` to ``tb`` (None if a sample lacks one)."""
        times = [ta] + self._stamps[i0 + 1:i1] + [tb]
        poses = [T_a] + self._poses[i0 + 1:i1] + [T_b]
        C = np.zeros((6, 6))
        for k in range(1, len(times)):
            Sigma = self._twist_covs[i0 + k]  # the sample ending this piece
            if Sigma is None:
                return None
            dt = (times[k] - times[k - 1]) * 1e-9
            C = transport_covariance(se3.relative(poses[k - 1], poses[k]), C) + dt * dt * Sigma
        return 0.5 * (C + C.T)
