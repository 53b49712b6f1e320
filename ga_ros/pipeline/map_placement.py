"""Where the ``map`` frame is before the aligner places it: ``T_map_odom`` from absolute fixes
and the odometry (ROS-free; :class:`ga_ros.pipeline.map_to_odom.MapToOdom` drives it, in the
node and the replay alike).

With ``datum: fixes`` the map frame is the fixes' frame, but the aligner's first window update
(the first track end) may come tens of seconds after the first fix. Until then the fixes place
the map directly, as a localiser's first estimate would:

* each fix is paired with the odometry pose of its sensor at the fix's stamp,
  ``T_odom_sensor = T_odom(k) T_k_sensor`` (:class:`~ga_ros.core.fixes.FixTerm`: keyframe ``k``
  and the odometry offset, lever arm included);
* ``T_map_odom = (Rz(psi), t)``: a rotation about z and a translation (both frames are level,
  REP 105);
* **heading** ``psi``: from the fixes that measure an orientation (the inverse-variance circular
  mean of ``yaw(R_map_sensor R_odom_sensor')``), and from the motion once the odometry has moved
  between fixes (the weighted 2-D Procrustes rotation of the odometry positions onto the fix
  positions about their centroids, variance ``1 / sum(w_i |a_i|^2)``, ``w_i`` the fix's
  horizontal information, ``a_i`` the odometry position about the weighted centroid), used once
  its sigma is at most :attr:`PlacementConfig.heading_sigma_max_rad`; both combined by inverse
  variance. Without either the heading is that of ``odom`` (``psi = 0``);
* **position** ``t``: the information-weighted mean of ``p_map_i - Rz(psi) p_odom_i`` over the
  fixes' known position axes (``(sum W_i)^+ sum W_i d_i``; an axis no fix measures, e.g. an
  AMCL pose's z, keeps ``odom``'s: 0); while the heading is not determined, of the newest fix
  alone (the sensor at that fix, whatever the heading turns out to be). With one fix it puts
  the sensor at that fix.

Every fix refines the estimate until the aligner places the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.fixes import AbsoluteFix
from ga_ros.errors import InputError


@dataclass(frozen=True)
class PlacementConfig:
    """Settings of the map placement before the aligner's first update.

    Attributes
    ----------
    heading_sigma_max_rad : the heading from the motion between fixes is used once its sigma
        is at most this (rad).
    jump_sigmas : ``map -> base_link`` may move by this many sigmas of the fixes (their
        largest position sigma) at a change of ``map -> odom`` without a warning.
    """

    heading_sigma_max_rad: float = 0.5
    jump_sigmas: float = 3.0

    def __post_init__(self) -> None:
        if not self.heading_sigma_max_rad > 0 or not self.jump_sigmas > 0:
            raise InputError(f'heading_sigma_max_rad and jump_sigmas must be > 0, got '
                             f'{self.heading_sigma_max_rad}, {self.jump_sigmas}')


@dataclass(frozen=True)
class Placement:
    """One estimate of the map frame from fixes.

    Attributes
    ----------
    T_map_odom : (4, 4) the placement.
    n_fixes : fixes used.
    heading : ``'odom'`` (not determined: the odometry's axes), ``'orientation'`` (from fixes
        with an orientation), ``'motion'`` (from the motion between fixes) or
        ``'orientation+motion'``.
    heading_sigma_rad : sigma of the heading (inf when not determined).
    fix_sigma_m : the largest position sigma (m) of the newest fix's known axes.
    """

    T_map_odom: FloatArray
    n_fixes: int
    heading: str
    heading_sigma_rad: float
    fix_sigma_m: float


def position_sigma(fix: AbsoluteFix) -> float:
    """The largest position sigma (m) of a fix's known position axes (inf: none known)."""
    known = fix.known[:3]
    if not known.any():
        return float('inf')
    C = np.linalg.pinv(fix.information)
    return float(np.sqrt(np.max(np.diag(C)[:3][known])))


def _yaw(R: FloatArray) -> float:
    """Heading (rad) of a rotation matrix: the angle of its x axis in the x-y plane."""
    return float(np.arctan2(R[1, 0], R[0, 0]))


def _rz(psi: float) -> FloatArray:
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class FixPlacement:
    """``T_map_odom`` from fixes paired with the odometry (module docstring).

    Parameters
    ----------
    config : thresholds.
    """

    def __init__(self, config: PlacementConfig = PlacementConfig()) -> None:
        self.config = config
        self._p_odom: list[FloatArray] = []   # sensor positions in odom (3,)
        self._p_map: list[FloatArray] = []    # fix positions in map (3,)
        self._W: list[FloatArray] = []        # position information (3, 3), map axes
        self._yaw: list[tuple[float, float]] = []   # (yaw offset, variance) of oriented fixes
        self._fix_sigma = np.inf
        #: the newest estimate (None before the first fix)
        self.placement: Placement | None = None

    def add(self, T_odom_sensor: FloatArray, fix: AbsoluteFix) -> Placement | None:
        """One fix and the odometry pose (4, 4) of its sensor at the fix's stamp; returns the
        new estimate (None when the fix measures no position axis and none did before)."""
        C = np.linalg.pinv(fix.information)   # covariance of the known axes, 0 elsewhere
        known = fix.known
        C_p = C[:3, :3]
        W = np.linalg.pinv(C_p) if known[:3].any() else np.zeros((3, 3))
        T_o = np.asarray(T_odom_sensor, float)
        if known[:3].any():
            self._p_odom.append(T_o[:3, 3].copy())
            self._p_map.append(fix.T_map_sensor[:3, 3].copy())
            self._W.append(W)
            self._fix_sigma = position_sigma(fix)
        if known[5] and C[5, 5] > 0:
            offset = _yaw(fix.T_map_sensor[:3, :3] @ T_o[:3, :3].T)
            self._yaw.append((offset, float(C[5, 5])))
        if not self._W:
            return None
        self.placement = self._estimate()
        return self.placement

    def _heading_from_orientation(self) -> tuple[float, float] | None:
        if not self._yaw:
            return None
        w = np.array([1.0 / v for _, v in self._yaw])
        a = np.array([o for o, _ in self._yaw])
        return float(np.arctan2(w @ np.sin(a), w @ np.cos(a))), float(1.0 / w.sum())

    def _heading_from_motion(self) -> tuple[float, float] | None:
        if len(self._W) < 2:
            return None
        w = np.array([0.5 * (W[0, 0] + W[1, 1]) for W in self._W])
        if not w.sum() > 0:
            return None
        po = np.array(self._p_odom)[:, :2]
        pm = np.array(self._p_map)[:, :2]
        a = po - (w @ po) / w.sum()
        b = pm - (w @ pm) / w.sum()
        spread = float(w @ np.sum(a * a, axis=1))
        if not spread > 0:
            return None
        cross = float(w @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
        dot = float(w @ np.sum(a * b, axis=1))
        return float(np.arctan2(cross, dot)), 1.0 / spread

    def _estimate(self) -> Placement:
        orient = self._heading_from_orientation()
        motion = self._heading_from_motion()
        if motion is not None and np.sqrt(motion[1]) > self.config.heading_sigma_max_rad:
            motion = None
        parts = [(n, h) for n, h in (('orientation', orient), ('motion', motion))
                 if h is not None]
        if not parts:
            psi, var, how = 0.0, np.inf, 'odom'
        else:
            w = np.array([1.0 / h[1] for _, h in parts])
            a = np.array([h[0] for _, h in parts])
            psi = float(np.arctan2(w @ np.sin(a), w @ np.cos(a)))
            var, how = float(1.0 / w.sum()), '+'.join(n for n, _ in parts)
        R = _rz(psi)
        # with the heading unknown only the newest fix places the position (the robot is near
        # it, whatever the heading turns out to be); with it, every fix
        used = slice(None) if parts else slice(-1, None)
        Ws, pms, pos = self._W[used], self._p_map[used], self._p_odom[used]
        rhs = sum(W @ (pm - R @ po) for W, pm, po in zip(Ws, pms, pos))
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.linalg.pinv(np.sum(Ws, axis=0)) @ rhs
        return Placement(T, len(self._W), how, float(np.sqrt(var)), self._fix_sigma)
