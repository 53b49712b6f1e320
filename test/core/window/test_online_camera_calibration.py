"""A camera's extrinsic rotation in the online estimate (``AlignerConfig.calibrate_cameras``,
:func:`ga_ros.core.window.calibration.camera_estimate_inputs`): the swath survey of
:mod:`ga_ros.sim.camera_survey` flown live, its camera's cross-track connections named
``cam0``. The estimate is applied to the camera's connections as they enter (booked per
connection, undone for the next estimate and the final batch); a snapshot restart continues
it exactly; where nothing is significant, and without cameras, nothing changes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.calibration import OnlineCalibration
from ga_ros.core.window.persistence import load_state, save_state, state_arrays
from ga_ros.errors import InputError
from ga_ros.sim.camera_survey import live_measurements, swath_survey

PHI = np.array([0.02, -0.01, 0.03])
PER = 30
CAMERAS = AlignerConfig(calibrate=True, calibrate_cameras='cam0', refine_executor='inline')


def _stream(seed: int = 4, phi: np.ndarray = PHI) -> tuple[list[Measurement], np.ndarray]:
    """Each keyframe's ``odom0`` motion, then the ``cam0`` cross-track connections ending at
    it (one track per swath); and the true poses (``phi``: the camera's rotation error)."""
    s = swath_survey(np.random.default_rng(seed), phi, per_swath=PER)
    return live_measurements(s, PER), s.T_true


def _anisotropic(ms: list[Measurement]) -> list[Measurement]:
    """The camera's connections with a stated covariance that is not isotropic per block
    (axes scaled 0.7 / 1 / 1.5, x and y correlated 0.5; a rotation changes it)."""
    d = np.array([0.7, 1.0, 1.5, 0.7, 1.0, 1.5])
    corr = np.eye(6)
    corr[0, 1] = corr[1, 0] = corr[3, 4] = corr[4, 3] = 0.5
    return [replace(m, cov=d[:, None] * m.cov * d[None, :] * corr) if m.kind == 'cross' else m
            for m in ms]


def _run(config: AlignerConfig, cut: int | None = None, path=None, phi: np.ndarray = PHI,
         live: list | None = None, anisotropic: bool = False) -> TrackWindowAligner:
    """The stream flown live; ``live`` (if given) gets the position error (m) of the newest
    node after each measurement (what the node publishes); ``anisotropic``: the camera's
    covariances of :func:`_anisotropic`."""
    ms, T_true = _stream(phi=phi)
    if anisotropic:
        ms = _anisotropic(ms)
    al = TrackWindowAligner(config, T_world_first=T_true[0])
    for k, m in enumerate(ms):
        if k == cut:
            save_state(al, path)
            al.close()
            al = load_state(path, config).aligner
        al.add_measurement(m)
        if live is not None:
            i = al.newest_node_id
            live.append(float(np.linalg.norm(al.pose(i)[:3, 3] - T_true[i][:3, 3])))
    al.finish_track()
    return al


def _published_only(book: OnlineCalibration, camera: str | None) -> np.ndarray:
    """The camera's estimate published but never applied (the behaviour to compare with)."""
    return np.zeros(3)


def _rmse(errors: list) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def test_the_online_estimate_is_applied_to_the_camera_connections() -> None:
    """The last estimate: every axis of ``cam0`` within 3 sigma, and applied: each stored
    connection is its measured motion conjugated by the rotation booked for it
    (``X T X^-1``, an independent computation), the odometry's motions as the book's
    odometry correction leaves them; the motions as measured are recovered to 1e-12."""
    al = _run(CAMERAS)
    cal = al.online_calibration
    cam = [p for p in cal.report.parameters if p.source == 'cam0']
    assert [p.name for p in cam] == ['extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz']
    for p, truth in zip(cam, PHI):
        assert p.estimated and abs(p.value - truth) < 3 * p.sigma, p
    ms, _ = _stream()
    cross = {(m.src_id, m.dst_id): m.z for m in ms if m.kind == 'cross'}
    src, dst, z, is_cross, _ = al.connection_arrays()
    booked = cal.camera_applied.a
    assert booked.shape == (len(z), 3)
    assert not booked[~is_cross].any()          # odom0 is no camera
    assert booked[is_cross].any(axis=1).sum() > 10   # applied once estimated
    for r in np.nonzero(is_cross)[0]:
        zm = cross[(int(src[r]), int(dst[r]))]
        R = Rotation.from_rotvec(booked[r]).as_matrix()
        R_meas = Rotation.from_rotvec(zm[3:]).as_matrix()
        np.testing.assert_allclose(z[r, :3], R @ zm[:3], atol=1e-12)
        np.testing.assert_allclose(Rotation.from_rotvec(z[r, 3:]).as_matrix(),
                                   R @ R_meas @ R.T, atol=1e-12)
    dt_s = np.ones(len(z))   # one second a keyframe: only the cross rows are compared
    back = cal.measured(z, dt_s, np.arange(len(z)))
    for r in np.nonzero(is_cross)[0]:
        np.testing.assert_allclose(back[r], cross[(int(src[r]), int(dst[r]))], atol=1e-12)
    assert cal.diagnostic_values()['calibration/cam0/applied'].startswith('yes')
    al.close()


def _conjugated_z(z: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """``[t, rotvec]`` of ``X T(z) X^-1``, ``X = [exp(phi), 0]``, by scipy's rotations."""
    R = Rotation.from_rotvec(phi)
    rot = R * Rotation.from_rotvec(z[3:]) * R.inv()
    return np.concatenate([R.apply(z[:3]), rot.as_rotvec()])


def test_every_stored_connection_of_the_camera_takes_the_current_rotation() -> None:
    """The connections that entered before an estimate (before the first one too) are
    corrected with it at the next update: at the end every ``cam0`` connection is booked with
    the rotation applied now, its motion the measured one conjugated by it and its covariance
    ``J C J^T`` with ``J`` the central-difference Jacobian of that conjugation (an independent
    computation of ``Ad_X C Ad_X^T``). The window's final path is then within 0.1 m of the
    truth (1.47 m when only the connections entering after an estimate are corrected, 1.53 m
    published only), 0.06 m after a rigid alignment."""
    from ga_ros.eval import ate

    al = _run(CAMERAS, anisotropic=True)
    cal = al.online_calibration
    phi = cal.camera_correction('cam0')
    assert phi.any()
    ms, T_true = _stream()
    ms = _anisotropic(ms)
    meas = {(m.src_id, m.dst_id): m for m in ms if m.kind == 'cross'}
    src, dst, z, is_cross, _ = al.connection_arrays()
    cov = al.state.ccov.a[np.arange(len(z))]
    rows = np.nonzero(is_cross)[0]
    np.testing.assert_array_equal(cal.camera_applied.a[rows], np.tile(phi, (rows.size, 1)))
    h = 1e-6
    for r in rows:
        m = meas[(int(src[r]), int(dst[r]))]
        np.testing.assert_allclose(z[r], _conjugated_z(m.z, phi), atol=1e-12)
        J = np.stack([(_conjugated_z(m.z + h * e, phi) - _conjugated_z(m.z - h * e, phi))
                      / (2 * h) for e in np.eye(6)], axis=1)
        np.testing.assert_allclose(cov[r], J @ m.cov @ J.T, rtol=1e-6,
                                   atol=1e-8 * np.abs(m.cov).max())
    n = len(al.state.ids)
    T = al.state.T[:n]
    assert ate(T, T_true[:n], 'none').rmse < 0.1
    assert ate(T, T_true[:n], 'rigid').rmse < 0.06
    al.close()


def test_the_retired_tracks_keep_the_rotation_they_were_booked_with() -> None:
    """A bounded refinement (horizon 1 track, window 2, refining at every trigger): the
    connections of the tracks retired (eliminated into the past prior) before the rotation
    changed keep their booked rotation, the others take the current one, and every one gives
    its motion as measured back (1e-12); refinements are installed (none dropped at
    ``refine_relinearize_sigma`` 0) and the path stays within 0.15 m of the truth."""
    from ga_ros.eval import ate

    cfg = replace(CAMERAS, refine_horizon_tracks=1, window_tracks=2,
                  refine_relinearize_sigma=0.0)
    al = _run(cfg)
    st, cal = al.state, al.online_calibration
    assert st.retired >= 2 and al.handoff.n_refinements >= 3
    src, dst, z, is_cross, _ = al.connection_arrays()
    rows = np.nonzero(is_cross)[0]
    phi = cal.camera_correction('cam0')
    order = st.finished_order()
    first = int(st.track_nodes.start(order[st.retired]))
    live = st.horizon_rows(first)
    inside = np.isin(rows, live)
    assert inside.any() and (~inside).any()
    booked = cal.camera_applied.a[rows]
    assert (booked[inside] == phi).all()
    # retired before the last change: the rotation of their time (those retired since were
    # corrected before they retired)
    assert (booked[~inside] != phi).any(axis=1).sum() >= 10
    ms, T_true = _stream()
    meas = {(m.src_id, m.dst_id): m.z for m in ms if m.kind == 'cross'}
    back = cal.measured(z, np.ones(len(z)), np.arange(len(z)))
    for r in rows:
        np.testing.assert_allclose(back[r], meas[(int(src[r]), int(dst[r]))], atol=1e-12)
    n = len(st.ids)
    assert ate(st.T[:n], T_true[:n], 'none').rmse < 0.15
    al.close()


def test_applying_the_rotation_improves_the_live_path() -> None:
    """The live path (the newest node after each measurement) and the window's final path are
    closer to the truth with the estimate applied than with it published only."""
    live_applied, live_published = [], []
    al = _run(CAMERAS, live=live_applied)
    final_applied = al.state.T[:len(al.state.ids), :3, 3].copy()
    al.close()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(OnlineCalibration, 'camera_correction', _published_only)
        po = _run(CAMERAS, live=live_published)
        final_published = po.state.T[:len(po.state.ids), :3, 3].copy()
        po.close()
    assert _rmse(live_applied) < 0.97 * _rmse(live_published)
    _, T_true = _stream()
    err_a = np.linalg.norm(final_applied - T_true[:len(final_applied), :3, 3], axis=1)
    err_p = np.linalg.norm(final_published - T_true[:len(final_published), :3, 3], axis=1)
    assert _rmse(err_a) < _rmse(err_p)


def test_where_nothing_is_significant_nothing_changes() -> None:
    """No rotation error: no camera parameter significant, so the state is bit for bit the
    one of the estimate published only (the booked rotations all zero)."""
    real = _run(CAMERAS, phi=np.zeros(3))
    assert not any(p.estimated for p in real.online_calibration.report.parameters
                   if p.source == 'cam0')
    assert real.online_calibration.diagnostic_values()['calibration/cam0/applied'].startswith(
        'no')
    meta, arrays = state_arrays(real.state)
    real.close()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(OnlineCalibration, 'camera_correction', _published_only)
        po = _run(CAMERAS, phi=np.zeros(3))
    meta2, arrays2 = state_arrays(po.state)
    po.close()
    assert meta2['calibration'] == meta['calibration'] and arrays.keys() == arrays2.keys()
    for name in arrays:
        np.testing.assert_array_equal(arrays2[name], arrays[name], err_msg=name)
    assert not arrays['cal_camera'].any()


def test_without_cameras_nothing_changes() -> None:
    """``calibrate`` alone: the same path and state as before the cameras existed (no source
    book saved), and the estimate has no camera parameter."""
    plain = _run(AlignerConfig(calibrate=True, refine_executor='inline'))
    assert not any(p.source == 'cam0' for p in plain.online_calibration.report.parameters)
    meta, arrays = state_arrays(plain.state)
    assert 'cal_group' not in arrays and 'group_names' not in meta['calibration']
    assert 'cal_camera' not in arrays and plain.online_calibration.camera_applied.n == 0
    plain.close()


def test_a_restart_from_the_snapshot_continues_the_camera_estimate_exactly(tmp_path) -> None:
    al = _run(CAMERAS)
    back = _run(CAMERAS, cut=3 * PER + 7, path=tmp_path / 'state')
    meta, arrays = state_arrays(al.state)
    meta2, arrays2 = state_arrays(back.state)
    assert meta2['calibration'] == meta['calibration']
    assert 'cal_group' in arrays and arrays.keys() == arrays2.keys()
    assert arrays['cal_camera'].any()   # the restart continues the applied rotations
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
