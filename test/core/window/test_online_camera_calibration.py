"""A camera's extrinsic rotation in the online estimate (``AlignerConfig.calibrate_cameras``,
:func:`ga_ros.core.window.calibration.camera_estimate_inputs`): the swath survey of
:mod:`ga_ros.sim.camera_survey` flown live, its camera's cross-track connections named
``cam0``. The estimate is published, not applied; a snapshot restart continues it exactly;
without cameras nothing changes."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import load_state, save_state, state_arrays
from ga_ros.errors import InputError
from ga_ros.sim.camera_survey import swath_survey

PHI = np.array([0.02, -0.01, 0.03])
PER = 30
CAMERAS = AlignerConfig(calibrate=True, calibrate_cameras='cam0', refine_executor='inline')


def _stream(seed: int = 4) -> tuple[list[Measurement], np.ndarray]:
    """Each keyframe's ``odom0`` motion, then the ``cam0`` cross-track connections ending at
    it (one track per swath); and the true poses."""
    s = swath_survey(np.random.default_rng(seed), PHI, per_swath=PER)
    arr = s.network.arrays()
    cross: dict[int, list[int]] = {}
    for c in range(len(arr)):
        if s.groups[c] == 'cam0':
            cross.setdefault(int(arr.dst[c]), []).append(c)
    ms = []
    for c in range(len(arr)):
        if s.groups[c] != 'odom0':
            continue
        i, j = int(arr.src[c]), int(arr.dst[c])
        ms.append(Measurement(i, j, i // PER, j // PER, arr.z[c], arr.cov[c], j * 10 ** 9,
                              'consecutive', 'odom0'))
        ms += [Measurement(int(arr.src[k]), j, int(arr.src[k]) // PER, j // PER, arr.z[k],
                           arr.cov[k], j * 10 ** 9, 'cross', 'cam0') for k in cross.get(j, [])]
    return ms, s.T_true


def _run(config: AlignerConfig, cut: int | None = None, path=None) -> TrackWindowAligner:
    ms, T_true = _stream()
    al = TrackWindowAligner(config, T_world_first=T_true[0])
    for k, m in enumerate(ms):
        if k == cut:
            save_state(al, path)
            al.close()
            al = load_state(path, config).aligner
        al.add_measurement(m)
    al.finish_track()
    return al


def test_the_online_estimate_includes_the_camera_and_applies_only_the_odometry() -> None:
    """The last estimate: every axis of ``cam0`` within 3 sigma; the motions stored as
    without the camera named wherever the odometry's corrections agree (the camera's own
    connections as measured)."""
    al = _run(CAMERAS)
    cam = [p for p in al.online_calibration.report.parameters if p.source == 'cam0']
    assert [p.name for p in cam] == ['extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz']
    for p, truth in zip(cam, PHI):
        assert p.estimated and abs(p.value - truth) < 3 * p.sigma, p
    # the cross-track connections (no odometry parameter) are stored as measured
    ms, _ = _stream()
    cross = {(m.src_id, m.dst_id): m.z for m in ms if m.kind == 'cross'}
    src, dst, z, is_cross, _ = al.connection_arrays()
    for a, b, zz in zip(src[is_cross], dst[is_cross], z[is_cross]):
        np.testing.assert_array_equal(zz, cross[(int(a), int(b))])
    assert al.online_calibration.diagnostic_values()['calibration/cam0/applied'].startswith('no')
    al.close()


def test_without_cameras_nothing_changes() -> None:
    """``calibrate`` alone: the same path and state as before the cameras existed (no source
    book saved), and the estimate has no camera parameter."""
    plain = _run(AlignerConfig(calibrate=True, refine_executor='inline'))
    assert not any(p.source == 'cam0' for p in plain.online_calibration.report.parameters)
    meta, arrays = state_arrays(plain.state)
    assert 'cal_group' not in arrays and 'group_names' not in meta['calibration']
    plain.close()


def test_a_restart_from_the_snapshot_continues_the_camera_estimate_exactly(tmp_path) -> None:
    al = _run(CAMERAS)
    back = _run(CAMERAS, cut=3 * PER + 7, path=tmp_path / 'state')
    meta, arrays = state_arrays(al.state)
    meta2, arrays2 = state_arrays(back.state)
    assert meta2['calibration'] == meta['calibration']
    assert 'cal_group' in arrays and arrays.keys() == arrays2.keys()
    for name in arrays:
        np.testing.assert_array_equal(arrays2[name], arrays[name], err_msg=name)
    assert back.online_calibration.report.lines() == al.online_calibration.report.lines()
    al.close()
    back.close()


def test_calibrate_cameras_needs_calibrate() -> None:
    with pytest.raises(InputError, match='needs calibrate'):
        AlignerConfig(calibrate_cameras='cam0')
    assert AlignerConfig(calibrate=True, calibrate_cameras=' cam0, cam1 ').camera_names == (
        'cam0', 'cam1')
