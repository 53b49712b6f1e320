"""Trajectory error metrics: ATE (raw and rigidly aligned), per-node and per-track errors."""

from ga_ros.eval.metrics import (
    AteResult,
    RigidAlignment,
    TrajectoryError,
    align_rigid,
    anchor_first,
    ate,
    improvement_pct,
    per_track_mean,
    position_errors,
    position_nees,
    trajectory_error,
)

__all__ = ['AteResult', 'RigidAlignment', 'align_rigid', 'anchor_first', 'ate',
           'improvement_pct', 'per_track_mean', 'position_errors', 'position_nees',
           'TrajectoryError', 'trajectory_error']
