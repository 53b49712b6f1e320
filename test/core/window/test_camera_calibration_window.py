"""A camera's extrinsic rotation estimated by the window aligner's final batch
(``refine_batch(calibration=CalibrationConfig(cameras=...))``,
:mod:`ga_ros.core.calibration.camera_parameters`): a live swath survey whose cross-track
connections come from a camera mounted with a rotation error, told apart by their source;
the parameters in the replay's text block."""

from __future__ import annotations

import numpy as np

from ga_ros.core.calibration import CalibrationConfig
from ga_ros.core.measurement import Measurement
from ga_ros.core.quality.variance_components import SourceGroups
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.replay.text import calibration_lines
from ga_ros.sim.camera_survey import swath_survey

PHI = np.array([0.02, -0.01, 0.03])
PER_SWATH = 30


def _run(seed: int):
    """The swath survey fed to a window aligner as it is flown (one track per swath): each
    keyframe's consecutive motion (``odom0``), then the camera's cross-track connections
    (``cam0``) that end at it."""
    s = swath_survey(np.random.default_rng(seed), PHI, per_swath=PER_SWATH)
    arr = s.network.arrays()
    al = TrackWindowAligner(AlignerConfig(refine_executor='inline'), T_world_first=s.T_true[0])
    groups = SourceGroups()
    cross = {}
    for c in range(len(arr)):
        if s.groups[c] == 'cam0':
            cross.setdefault(int(arr.dst[c]), []).append(c)
    for c in range(len(arr)):
        if s.groups[c] != 'odom0':
            continue
        i, j = int(arr.src[c]), int(arr.dst[c])
        ms = [Measurement(i, j, i // PER_SWATH, j // PER_SWATH, arr.z[c], arr.cov[c],
                          j * 10 ** 9, 'consecutive', 'odom0')]
        ms += [Measurement(int(arr.src[k]), j, int(arr.src[k]) // PER_SWATH, j // PER_SWATH,
                           arr.z[k], arr.cov[k], j * 10 ** 9, 'cross', 'cam0')
               for k in cross.get(j, [])]
        for m in ms:
            groups.add(m)
            al.add_measurement(m)
        if (j + 1) % PER_SWATH == 0:
            al.finish_track()
    al.finish_track()
    return al, groups, s.T_true


def _rmse(al, T_true) -> float:
    T = al.corrected_path().T_world_node
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


def test_the_final_batch_estimates_a_cameras_extrinsic_rotation() -> None:
    """The camera's cross-track connections get its parameters: each axis within 3 sigma of
    the truth, the odometry's scale and yaw rate still candidates of its consecutive motions,
    the path closer to the truth than the final batch without a camera named."""
    al, groups, T_true = _run(4)
    al.refine_batch(variance_groups=groups, calibration=CalibrationConfig())
    plain = _rmse(al, T_true)
    assert not any(p.source == 'cam0' for p in al.calibration.parameters)
    al.refine_batch(variance_groups=groups, calibration=CalibrationConfig(cameras=('cam0',)))
    cam = [p for p in al.calibration.parameters if p.source == 'cam0']
    assert [p.name for p in cam] == ['extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz']
    for p, truth in zip(cam, PHI):
        assert p.estimated and abs(p.value - truth) < 3 * p.sigma, al.calibration.lines()
    assert {p.name for p in al.calibration.parameters if p.source == 'odom0'} == {
        'scale', 'yaw_rate'}
    assert _rmse(al, T_true) < 0.5 * plain, (_rmse(al, T_true), plain)
    # the replay's text block (summary.json's calibration object, as_dict)
    text = calibration_lines(al.calibration.as_dict())
    assert "extrinsic_rx/ry/rz: a camera extrinsic's rotation error" in text[0]
    for p in cam:
        assert any(f'cam0         {p.name} {p.value:.6g} +- ' in line for line in text), text
    al.close()
