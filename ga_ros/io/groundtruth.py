"""Ground-truth files of public datasets: EuRoC CSV and TUM, read into a :class:`Trajectory`.

* EuRoC MAV (``mav0/state_groundtruth_estimate0/data.csv``, also the Vicon/Leica files):
  comma-separated, ``#timestamp [ns], p_RS_R_x [m], p_RS_R_y, p_RS_R_z, q_RS_w [], q_RS_x,
  q_RS_y, q_RS_z`` then optional velocities and biases (ignored); the quaternion is
  ``w x y z``. Lines starting with ``#`` are comments.
* TUM RGB-D (``timestamp x y z qx qy qz qw``, seconds): :func:`ga_ros.io.trajectory.read_tum`.

:func:`read_ground_truth_file` tells them apart by the first field of the first data line: an
integer of 13 or more digits (nanoseconds) is EuRoC, anything else TUM.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ga_ros.errors import FormatError
from ga_ros.geometry import se3
from ga_ros.io.trajectory import Trajectory, read_tum

_QUAT_TOL = 1e-3


def read_euroc_csv(path: str | os.PathLike) -> Trajectory:
    """Read an EuRoC ground-truth CSV (module doc) into a :class:`Trajectory` (frame ``world``).

    Raises
    ------
    FormatError
        ``file:line`` of a line with fewer than 8 fields, a non-number or a non-unit quaternion.
    """
    name = str(path)
    stamps: list[int] = []
    rows: list[list[float]] = []
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise FormatError(f'cannot read ground truth: {exc}', name) from exc
    for k, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith('#'):
            continue
        fields = [f.strip() for f in text.split(',')]
        if len(fields) < 8:
            raise FormatError('expected at least 8 comma-separated fields '
                              '(timestamp, p x y z, q w x y z)', name, k)
        try:
            stamps.append(int(fields[0]))
            rows.append([float(f) for f in fields[1:8]])
        except ValueError:
            raise FormatError(f'not a number in {text[:60]!r}', name, k) from None
    if not rows:
        raise FormatError('no poses', name)
    a = np.asarray(rows)
    q = a[:, [4, 5, 6, 3]]  # w x y z -> x y z w
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > _QUAT_TOL)
    if bad.size:
        raise FormatError(f'{name}: quaternion of pose {bad[0] + 1} is not unit length '
                          f'(norm {norm[bad[0]]:.6g})', name)
    T = se3.from_pos_quat(a[:, :3], q / norm[:, None])
    return Trajectory(np.asarray(stamps, dtype=np.int64), T, frame_id='world')


def read_ground_truth_file(path: str | os.PathLike) -> Trajectory:
    """EuRoC CSV (first field in integer ns) or TUM file -> :class:`Trajectory`.

    Raises
    ------
    FormatError
        An unreadable or malformed file (naming the line).
    """
    try:
        with open(path) as f:
            first = next((ln for ln in f if ln.strip() and not ln.startswith('#')), '')
    except OSError as exc:
        raise FormatError(f'cannot read ground truth: {exc}', str(path)) from exc
    head = first.replace(',', ' ').split()[:1]
    euroc = bool(head) and head[0].isdigit() and len(head[0]) >= 13
    return read_euroc_csv(path) if euroc else read_tum(path)
