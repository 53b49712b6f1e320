"""Trajectory errors of the replay against ground truth, and frame-to-frame integration.

Kept small and self-contained (the replay must report F2F vs GA errors even when no other
evaluation module is installed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError


def rigid_alignment(p_est: FloatArray, p_ref: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation ``R`` and translation ``t`` minimising ``sum |R p_est + t - p_ref|^2``.

    Umeyama (1991) / Horn (1987) without scale: SVD of the cross-covariance, with the sign
    correction that keeps ``det R = +1``.

    Parameters
    ----------
    p_est, p_ref : (n, 3) corresponding positions (m), n >= 3 and not collinear for a unique
        rotation (degenerate sets still return a valid rotation).

    Returns
    -------
    (R (3, 3), t (3,))
    """
    p_est = np.asarray(p_est, dtype=float).reshape(-1, 3)
    p_ref = np.asarray(p_ref, dtype=float).reshape(-1, 3)
    if p_est.shape != p_ref.shape or p_est.shape[0] == 0:
        raise InputError(f'need matching non-empty point sets, got {p_est.shape}, {p_ref.shape}')
    mu_e, mu_r = p_est.mean(axis=0), p_ref.mean(axis=0)
    H = (p_ref - mu_r).T @ (p_est - mu_e) / p_est.shape[0]
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    return R, mu_r - R @ mu_e


@dataclass(frozen=True)
class TrajectoryError:
    """Position errors of an estimate against ground truth (m).

    Attributes
    ----------
    ate_raw : RMSE of position errors as estimated (the first pose is the datum).
    ate_aligned : RMSE after the best rigid alignment (:func:`rigid_alignment`).
    max_raw : largest raw position error.
    n : number of matched poses.
    """

    ate_raw: float
    ate_aligned: float
    max_raw: float
    n: int

    def as_dict(self) -> dict[str, float]:
        return {'ate_raw_m': self.ate_raw, 'ate_aligned_m': self.ate_aligned,
                'max_raw_m': self.max_raw, 'n': self.n}


def trajectory_error(p_est: FloatArray, p_ref: FloatArray) -> TrajectoryError:
    """Raw and rigidly aligned position RMSE of ``p_est`` (n, 3) against ``p_ref`` (n, 3), m."""
    p_est = np.asarray(p_est, dtype=float).reshape(-1, 3)
    p_ref = np.asarray(p_ref, dtype=float).reshape(-1, 3)
    err = np.linalg.norm(p_est - p_ref, axis=1)
    R, t = rigid_alignment(p_est, p_ref)
    err_al = np.linalg.norm(p_est @ R.T + t - p_ref, axis=1)
    return TrajectoryError(float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(err_al**2))),
                           float(err.max()), int(err.size))


class F2FIntegrator:
    """Frame-to-frame (dead-reckoning) poses: each new node = its source's pose times the
    consecutive motion ``T_src_dst``; cross-track connections are ignored.

    Parameters
    ----------
    T_world_first : (4, 4) pose of the first source node (default identity).
    """

    def __init__(self, T_world_first: FloatArray | None = None) -> None:
        self.T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first)
        self.poses: dict[int, FloatArray] = {}
        self.stamps: dict[int, int] = {}
        self.tracks: dict[int, int] = {}

    def add(self, m: Measurement) -> None:
        """Use ``m`` if it is a consecutive motion from a known node (or the first one)."""
        if m.kind != 'consecutive':
            return
        if not self.poses:
            self.poses[m.src_id] = self.T_world_first.copy()
            self.tracks[m.src_id] = m.src_track
        if m.src_id in self.poses and m.dst_id not in self.poses:
            self.poses[m.dst_id] = self.poses[m.src_id] @ m.T_src_dst
            self.stamps[m.dst_id] = int(m.stamp_ns)
            self.tracks[m.dst_id] = m.dst_track
