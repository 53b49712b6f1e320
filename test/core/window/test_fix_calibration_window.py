"""A fix source's time offset estimated by the window aligner's final batch
(``refine_batch(calibration=...)``, :mod:`ga_ros.core.calibration.fix_parameters`) and online
(``AlignerConfig(calibrate=True)``, :mod:`ga_ros.core.window.calibration`): the fixes of a
live survey, stamped late, as a GNSS receiver with latency delivers them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ga_ros.core.calibration import CalibrationConfig
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import load_state, save_state, state_arrays
from ga_ros.errors import InputError
from ga_ros.sim.biased import FixSource, biased_fixes, biased_survey

TRACK = 25   # keyframes per track


def _run(seed: int, latency_s: float):
    """The survey's motions (no odometry bias) and fixes of one source every 4 keyframes with
    ``latency_s``, fed to a window aligner; returns the aligner and the true poses."""
    rng = np.random.default_rng(seed)
    s = biased_survey(rng, n_nodes=300, scale=0.0, yaw_rate=0.0)
    stamps = np.concatenate([[0.0], np.cumsum(s.dt_s)])
    obs = biased_fixes(rng, s.T_true, stamps,
                       [FixSource('gnss', every=4, sigma_m=0.3, latency_s=latency_s)])
    fixes = {int(t.node_id): t for t in obs.terms}
    arr = s.network.arrays()
    al = TrackWindowAligner(AlignerConfig(datum='fixes', refine_executor='inline'),
                            T_world_first=s.T_true[0])
    track = prev = 0
    for c in range(len(arr)):
        i = c + 1
        al.add_measurement(Measurement(c, i, prev, track, arr.z[c], arr.cov[c],
                                       int(round(stamps[i] * 1e9)), 'consecutive', 'odom0'))
        prev = track
        for node in (c, i) if c == 0 else (i,):
            if node in fixes:
                al.add_fix(fixes[node])
        if i % TRACK == 0:
            al.finish_track()
            track += 1
    al.finish_track()
    return al, s.T_true


def _rmse(al, T_true) -> float:
    T = al.corrected_path().T_world_node
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


@pytest.mark.parametrize('seed', [1, 2])
def test_the_final_batch_estimates_a_fix_sources_latency(seed) -> None:
    """0.5 s of latency: recovered within 3 sigma, and the path closer to the truth than the
    calibration without fix parameters."""
    al, T_true = _run(seed, 0.5)
    al.refine_batch(calibration=CalibrationConfig(fix_parameters=()))
    plain = _rmse(al, T_true)
    al.refine_batch(calibration=CalibrationConfig())   # the default: the time offset
    est = {p.name: p for p in al.calibration.parameters if p.source == 'gnss'}
    tau = est['time_offset']
    assert tau.estimated, al.calibration.lines()
    assert abs(tau.value - 0.5) < 3 * tau.sigma, al.calibration.lines()
    assert _rmse(al, T_true) < 0.8 * plain, (_rmse(al, T_true), plain)
    al.close()


def test_without_latency_nothing_changes() -> None:
    """No latency: the time offset is not significant and the final batch is the one without
    fix parameters bit for bit (the fixes' priors are the book's)."""
    al, _ = _run(3, 0.0)
    for _ in range(2):   # a second batch from the first one's poses, as below
        al.refine_batch(calibration=CalibrationConfig(fix_parameters=()))
    again = al.corrected_path().T_world_node.copy()
    al.close()
    al, _ = _run(3, 0.0)
    al.refine_batch(calibration=CalibrationConfig(fix_parameters=()))
    al.refine_batch(calibration=CalibrationConfig())
    est = {p.name: p for p in al.calibration.parameters if p.source == 'gnss'}
    assert not est['time_offset'].estimated
    np.testing.assert_array_equal(al.corrected_path().T_world_node, again)
    al.close()


# ------------------------------------------------------------------------------ online
ONLINE = AlignerConfig(datum='fixes', calibrate=True, refine_executor='inline')
#: the online calibration of the odometry only (the fixes as measured)
ONLINE_ODOM = replace(ONLINE, calibration_fix_parameters='')


def _survey(seed: int, latency_s: float, offset_m=(0.0, 0.0, 0.0)):
    """The survey of :func:`_run` and its fixes by node (``gnss`` with ``latency_s``; with a
    non-zero ``offset_m`` a second source ``base`` offset by it, between them)."""
    rng = np.random.default_rng(seed)
    s = biased_survey(rng, n_nodes=300, scale=0.0, yaw_rate=0.0)
    stamps = np.concatenate([[0.0], np.cumsum(s.dt_s)])
    sources = [FixSource('gnss', every=4, sigma_m=0.3, latency_s=latency_s)]
    if any(offset_m):
        sources.append(FixSource('base', every=4, first=2, sigma_m=0.3, offset_m=offset_m))
    obs = biased_fixes(rng, s.T_true, stamps, sources)
    fixes: dict[int, list] = {}
    for t in obs.terms:
        fixes.setdefault(int(t.node_id), []).append(t)
    return s, stamps, fixes


def run_online(survey, config: AlignerConfig, cut: int | None = None, path=None):
    """Feed ``survey`` (:func:`_survey`) live (a fix right after its node's motion); returns
    the aligner and each node's online pose. ``cut``: saved after that many motions and the
    rest fed to the aligner loaded from ``path``."""
    s, stamps, fixes = survey
    arr = s.network.arrays()
    al = TrackWindowAligner(config, T_world_first=s.T_true[0])
    online = np.zeros_like(s.T_true)
    online[0] = s.T_true[0]
    track = prev = 0
    for c in range(len(arr)):
        if cut is not None and c == cut:
            save_state(al, path)
            al.close()
            al = load_state(path, config).aligner
        i = c + 1
        al.add_measurement(Measurement(c, i, prev, track, arr.z[c], arr.cov[c],
                                       int(round(stamps[i] * 1e9)), 'consecutive', 'odom0'))
        prev = track
        for node in (c, i) if c == 0 else (i,):
            for term in fixes.get(node, ()):
                al.add_fix(term)
        if i % TRACK == 0:
            al.finish_track()
            track += 1
        online[i] = al.pose(i)
    al.finish_track()
    al.wait_background()
    return al, online


def _online_rmse(online, T_true) -> float:
    return float(np.sqrt(np.mean(np.sum((online[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


def _param(report, source: str, name: str):
    return next(p for p in report.parameters if p.source == source and p.name == name)


@pytest.mark.parametrize('seed', [1, 2])
def test_the_online_calibration_estimates_a_fix_sources_latency(seed) -> None:
    """0.5 s of latency: the last online estimate within 3 sigma, the fixes that entered after
    the first significant estimate stored corrected, and the online path closer to the truth
    than with the odometry's calibration alone."""
    survey = _survey(seed, 0.5)
    al, online = run_online(survey, ONLINE)
    book = al.online_calibration
    tau = _param(book.report, 'gnss', 'time_offset')
    assert tau.estimated, book.report.lines()
    assert abs(tau.value - 0.5) < 3 * tau.sigma, book.report.lines()
    assert book.n_failed == 0
    assert book.diagnostic_values()['calibration/gnss/time_offset'] == f'{tau.value:.6g} s'
    applied = book.fix_applied.a
    assert (applied[:, 3] != 0).sum() > len(applied) // 2 and (applied[:3] == 0).all()
    assert (applied[:, :3] == 0).all()  # no offset: not a candidate without a reference
    plain, online_plain = run_online(survey, ONLINE_ODOM)
    assert not plain.online_calibration.fix_shift.a.any()
    T_true = survey[0].T_true
    assert _online_rmse(online, T_true) < 0.8 * _online_rmse(online_plain, T_true)
    al.close()
    plain.close()


def test_stored_fixes_are_the_measured_ones_shifted_by_the_velocity_times_the_latency() -> None:
    """Each stored fix is its measured position moved by its booked shift, and that shift is
    ``v tau`` with ``tau`` the booked latency and ``v`` its node's velocity when it entered:
    the newest node's, one-sided (here the true one from the previous keyframe, within the
    estimate's heading error over a step)."""
    survey = _survey(1, 0.5)
    s, stamps, fixes = survey
    al, _ = run_online(survey, ONLINE)
    book, fb = al.online_calibration, al.state.fixes
    shift = book.fix_shifts(len(fb))
    v_back = np.zeros((stamps.size, 3))  # each node's velocity from the one before it
    v_back[1:] = np.diff(s.T_true[:, :3, 3], axis=0) / np.diff(stamps)[:, None]
    checked = 0
    for f, term in enumerate(fb.terms):
        if not fb.gated[f]:
            continue
        measured = next(t for t in fixes[term.node_id] if t.fix.source == term.fix.source)
        np.testing.assert_allclose(term.fix.T_map_sensor[:3, 3],
                                   measured.fix.T_map_sensor[:3, 3] + shift[f], atol=1e-12)
        tau = book.fix_applied.a[f, 3]
        if tau != 0.0:
            np.testing.assert_allclose(shift[f], v_back[term.node_id] * tau, atol=0.1 * tau)
            checked += 1
    assert checked > 20


def test_without_latency_the_online_path_is_the_one_without_fix_calibration() -> None:
    """No latency: nothing significant online, nothing applied, and the online path and the
    state are those of the odometry's calibration alone, bit for bit."""
    survey = _survey(3, 0.0)
    al, online = run_online(survey, ONLINE)
    plain, online_plain = run_online(survey, ONLINE_ODOM)
    assert not _param(al.online_calibration.report, 'gnss', 'time_offset').estimated
    assert not al.online_calibration.fix_applied.a.any()
    np.testing.assert_array_equal(online, online_plain)
    np.testing.assert_array_equal(al.state.T, plain.state.T)
    al.close()
    plain.close()


def test_a_restart_continues_the_fix_calibration_exactly(tmp_path) -> None:
    """A snapshot in the middle of a track, after corrected fixes: the restored aligner
    continues to the same state (the fixes' booked shifts included) and online path, bit for
    bit."""
    survey = _survey(2, 0.5)
    al, online = run_online(survey, ONLINE)
    back, online_back = run_online(survey, ONLINE, cut=6 * TRACK + 7, path=tmp_path / 'state')
    meta, arrays = state_arrays(al.state)
    meta2, arrays2 = state_arrays(back.state)
    assert meta2['calibration'] == meta['calibration']
    assert arrays.keys() == arrays2.keys() and 'cal_fix_shift' in arrays
    assert arrays['cal_fix_shift'][:6 * TRACK // 4].any()  # corrected before the cut
    for name in arrays:
        np.testing.assert_array_equal(arrays2[name], arrays[name], err_msg=name)
    np.testing.assert_array_equal(online_back, online)
    al.close()
    back.close()


def test_the_final_batch_estimates_the_whole_latency_after_the_online_one() -> None:
    """The fixes as measured enter the final batch's calibration: it estimates the whole
    latency, not what is left after the online correction."""
    al, _ = run_online(_survey(1, 0.5), ONLINE)
    assert al.online_calibration.fix_shift.a.any()
    al.refine_batch(calibration=CalibrationConfig())
    tau = _param(al.calibration, 'gnss', 'time_offset')
    assert tau.estimated and abs(tau.value - 0.5) < 3 * tau.sigma, al.calibration.lines()
    al.close()


def test_an_offset_online_against_a_named_reference() -> None:
    """Offsets online: refused without a reference; with ``gnss`` named, ``base``'s offset is
    estimated within 3 sigma and applied, ``gnss`` gets none."""
    with pytest.raises(InputError, match='reference'):
        AlignerConfig(calibrate=True, calibration_fix_parameters='offset_x,time_offset')
    cfg = replace(ONLINE, calibration_fix_parameters='offset_x,offset_y,offset_z,time_offset',
                  calibration_fix_reference='gnss')
    offset = (2.0, -1.0, 0.5)
    al, _ = run_online(_survey(1, 0.0, offset), cfg)
    rep = al.online_calibration.report
    for a, b in zip('xyz', offset):
        p = _param(rep, 'base', f'offset_{a}')
        assert p.estimated and abs(p.value - b) < 3 * p.sigma, rep.lines()
    assert not [p for p in rep.parameters if p.source == 'gnss' and p.name.startswith('off')]
    np.testing.assert_array_equal(al.online_calibration.fix_correction('base')[:3],
                                  [_param(rep, 'base', f'offset_{a}').value for a in 'xyz'])
    al.close()
