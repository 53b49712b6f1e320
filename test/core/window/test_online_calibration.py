"""Self-calibration online (:mod:`ga_ros.core.window.calibration`): odometry with a known scale
error and yaw-rate bias (:mod:`ga_ros.sim.biased`) fed to the window aligner with position
fixes, as a live survey would."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from ga_ros.core.calibration import corrected_motions
from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window import calibration as online
from ga_ros.core.window.calibration import report_of_dict
from ga_ros.core.window.persistence import load_state, save_state, state_arrays
from ga_ros.geometry import se3
from ga_ros.sim.biased import biased_survey

SCALE, YAW_RATE = 0.03, 0.004  # the true corrections k (1) and omega (rad/s)
FIX_EVERY = 20  # a fix (and a track end) every 20 keyframes


def _survey(seed: int = 0, scale: float = SCALE, yaw_rate: float = YAW_RATE):
    return biased_survey(np.random.default_rng(seed), n_nodes=600, scale=scale,
                         yaw_rate=yaw_rate, fix_every=FIX_EVERY, fix_sigma_m=0.5)


def _steps(s):
    """``(src, dst, z, cov, stamp_ns)`` of each motion and the fixes ``{node: position}`` of
    the survey (its fixes' means)."""
    arr = s.network.arrays()
    stamps = np.concatenate([[0.0], np.cumsum(s.dt_s)])
    fixes = s.priors[1]
    return arr, stamps, {int(i): T[:3, 3] for i, T in zip(fixes.node_ids, fixes.T_world_node)}


def run(s, config: AlignerConfig, cut: int | None = None, path=None, at_track_end=None):
    """Feed the survey to an aligner (a track ends at each fix, right after it); returns the
    aligner and each node's online pose (its estimate when first published). ``cut``: after
    that many motions the aligner is saved to ``path`` and the rest fed to the one loaded.
    ``at_track_end(al)``: called after each track end's update returned."""
    arr, stamps, fixes = _steps(s)
    n = s.T_true.shape[0]
    al = TrackWindowAligner(config, T_world_first=s.T_true[0])
    online = np.zeros((n, 4, 4))
    online[0] = s.T_true[0]
    fix_cov = np.diag([0.5 ** 2] * 3 + [-1.0] * 3)

    def add_fix(i: int) -> None:
        fix = AbsoluteFix.from_covariance(int(stamps[i] * 1e9),
                                          se3.from_translation_rotvec(fixes[i], np.zeros(3)),
                                          fix_cov, 'fix0')
        al.add_fix(FixTerm(i, se3.identity(), fix))

    track = prev = 0
    for c in range(len(arr)):
        if cut is not None and c == cut:
            save_state(al, path)
            al.close()
            al = load_state(path, config).aligner
        i = c + 1
        al.add_measurement(Measurement(c, i, prev, track, arr.z[c], arr.cov[c],
                                       int(stamps[i] * 1e9), 'consecutive', 'odom0'))
        prev = track
        if i == 1:
            add_fix(0)
        if i in fixes:
            add_fix(i)
            al.finish_track()
            if at_track_end is not None:
                at_track_end(al)
            track += 1
        online[i] = al.pose(i)
    al.finish_track()
    if at_track_end is not None:
        at_track_end(al)
    al.wait_background()
    return al, online


def _rmse(T, T_true) -> float:
    return float(np.sqrt(np.mean(np.sum((T[:, :2, 3] - T_true[:, :2, 3]) ** 2, axis=1))))


CAL = AlignerConfig(datum='fixes', calibrate=True, refine_executor='inline')
#: the estimate in a background thread (and the refinement in one too)
THREADED = AlignerConfig(datum='fixes', calibrate=True, refine_executor='thread')
DEADLINE_S = 600.0  # generous: a busy 2-core machine
OFF = AlignerConfig(datum='fixes', refine_executor='inline')


@pytest.mark.parametrize('seed', [0, 1])
def test_the_online_estimate_converges_to_the_truth_and_beats_the_uncalibrated_path(seed):
    s = _survey(seed)
    al, online = run(s, CAL)
    book = al.online_calibration
    est = {p.name: p for p in book.report.parameters}
    assert est['scale'].estimated and est['yaw_rate'].estimated, book.report.lines()
    assert abs(est['scale'].value - SCALE) < 4 * est['scale'].sigma, book.report.lines()
    assert abs(est['yaw_rate'].value - YAW_RATE) < 4 * est['yaw_rate'].sigma, book.report.lines()
    assert book.n_estimates > 1 and book.n_failed == 0
    # the motions that entered after the last estimate carry its correction
    applied = book.applied.a
    assert (applied[:, 1] != 0).any() and (applied[:5] == 0).all()
    off, online_off = run(s, OFF)
    assert off.online_calibration is None and off.state.calibration is None
    meta, arrays = state_arrays(off.state)  # calibration off: the state file as without it
    assert 'calibration' not in meta and not any(k.startswith('cal_') for k in arrays)
    assert _rmse(online, s.T_true) < 0.7 * _rmse(online_off, s.T_true)


def test_stored_motions_are_the_measured_ones_corrected_and_measured_undoes_it():
    s = _survey()
    al, _ = run(s, CAL)
    st, book = al.state, al.online_calibration
    arr = s.network.arrays()
    stamp = st.stamp.astype(float)
    m = st.src.n
    dt = (stamp[st.dst.a] - stamp[st.src.a]) * 1e-9
    # independent: each measured motion corrected by the (k, omega) it was booked with
    want = se3.to_translation_rotvec(corrected_motions(arr.z[:m], dt, book.applied.a[:, 0],
                                                       book.applied.a[:, 1]))
    np.testing.assert_allclose(st.z.a, want, atol=1e-12)
    np.testing.assert_allclose(book.measured(st.z.a, dt, np.arange(m)), arr.z[:m], atol=1e-12)


def test_without_anything_significant_the_results_are_those_without_calibration():
    """No bias and no fixes but the gauge: nothing is determined, nothing applied, and the
    path is the uncalibrated one bit for bit."""
    s = _survey(scale=0.0, yaw_rate=0.0)
    s.priors[1].node_ids[:] = 0  # every fix on the first node
    al, online = run(s, CAL)
    off, online_off = run(s, OFF)
    assert not (al.online_calibration.applied.a != 0).any()
    np.testing.assert_array_equal(online, online_off)
    np.testing.assert_array_equal(al.corrected_path().T_world_node,
                                  off.corrected_path().T_world_node)


def test_a_restart_from_the_snapshot_continues_the_calibration_exactly(tmp_path):
    s = _survey()
    al, online = run(s, CAL)
    # a cut in the middle of a track, after some estimates
    back, online_back = run(s, CAL, cut=10 * FIX_EVERY + 7, path=tmp_path / 'state')
    assert back.online_calibration.n_estimates == al.online_calibration.n_estimates
    meta, arrays = state_arrays(al.state)
    meta2, arrays2 = state_arrays(back.state)
    assert meta2['calibration'] == meta['calibration']
    assert arrays.keys() == arrays2.keys()
    for name in arrays:
        np.testing.assert_array_equal(arrays2[name], arrays[name], err_msg=name)
    np.testing.assert_array_equal(online_back, online)
    assert back.online_calibration.report.lines() == al.online_calibration.report.lines()


def test_the_final_batch_calibrates_the_motions_as_measured():
    """With the online calibration on, the final batch's calibration estimates the whole
    correction (from the measured motions), not what is left after the online one."""
    from ga_ros.core.calibration import CalibrationConfig

    s = _survey()
    al, _ = run(s, CAL)
    al.refine_batch(calibration=CalibrationConfig(noise=False))
    est = {p.name: p for p in al.calibration.parameters}
    lines = al.calibration.lines()
    assert abs(est['yaw_rate'].value - YAW_RATE) < 4 * est['yaw_rate'].sigma, lines
    assert abs(est['scale'].value - SCALE) < 4 * est['scale'].sigma, lines


def test_threaded_and_inline_estimates_give_the_same_path_and_state_bit_for_bit():
    """The estimate solved in a background thread (a live node) or inline at its installation
    (a replay with ``refine_executor='inline'``): installed at the same update, the same path
    and state."""
    s = _survey()
    al, online_inline = run(s, CAL)
    th, online_thread = run(s, THREADED)
    assert al.online_calibration.n_estimates > 2
    np.testing.assert_array_equal(online_thread, online_inline)
    np.testing.assert_array_equal(th.corrected_path().T_world_node,
                                  al.corrected_path().T_world_node)
    meta, arrays = state_arrays(al.state)
    meta2, arrays2 = state_arrays(th.state)
    assert meta2['calibration'] == meta['calibration']
    for name in ('cal_source', 'cal_applied', 'T', 'z'):
        np.testing.assert_array_equal(arrays2[name], arrays[name], err_msg=name)


def test_the_estimate_runs_after_the_update_returned_and_corrects_the_next_motions(
        monkeypatch):
    """With the threaded executor the update returns while its estimate is still being solved
    (held on an event here); the next motion of the source waits for it and is corrected with
    it, as when the estimate ran inside the update, whatever the thread's timing."""
    entered, release = threading.Event(), threading.Event()
    real = online.solve_with_calibration

    def held(*args, **kwargs):
        entered.set()
        if not release.wait(DEADLINE_S):
            raise RuntimeError('never released')
        return real(*args, **kwargs)

    monkeypatch.setattr(online, 'solve_with_calibration', held)
    last = []  # (the estimate started by the last update, connections then)
    checked = []

    def at_track_end(al):
        book = al.online_calibration
        if last:
            job, n_conns = last.pop()
            assert book.report is job.report  # installed by the first motion after its update
            k, w = book.correction('odom0')
            # every motion since then carries it
            assert (book.applied.a[n_conns:n_conns + FIX_EVERY - 1] == (k, w)).all()
            if job.report.estimated():
                checked.append(True)
        if book.pending is not None:
            # the update returned; its estimate has started and is held in the thread
            assert entered.wait(DEADLINE_S)
            assert book.pending.thread is not None and not book.pending.done
            last.append((book.pending, book.applied.n))
            entered.clear()
            release.set()  # the next motion waits for it
            book.pending.thread.join(DEADLINE_S)
            release.clear()

    s = _survey()
    al, online_held = run(s, THREADED, at_track_end=at_track_end)
    assert len(checked) > 2
    monkeypatch.undo()
    _, online_free = run(s, THREADED)
    np.testing.assert_array_equal(online_held, online_free)  # the thread's timing: no matter


def test_an_estimate_pending_at_a_save_is_saved_with_its_result_and_used_after_the_restart(
        tmp_path):
    """A save right after a track end, before the next motion (the estimate that update started
    still pending, in its thread): the file holds its result, the restored aligner uses it for
    the same motions, and the survey continues bit for bit."""
    s = _survey()
    al, online = run(s, THREADED)
    cut = 10 * FIX_EVERY  # the track ending at node 10 * FIX_EVERY has just been adjusted
    saved = {}

    def save_after(c_al):
        if c_al.state.n_updates == 10 and c_al.online_calibration.pending is not None:
            saved['meta'] = state_arrays(c_al.state)[0]['calibration']

    back, online_back = run(s, THREADED, cut=cut, path=tmp_path / 'state',
                            at_track_end=save_after)
    assert saved['meta']['pending']['report'] is not None  # a pending estimate at the cut
    np.testing.assert_array_equal(online_back, online)
    np.testing.assert_array_equal(back.online_calibration.applied.a,
                                  al.online_calibration.applied.a)
    assert back.online_calibration.report.lines() == al.online_calibration.report.lines()
    assert back.online_calibration.n_estimates == al.online_calibration.n_estimates


#: the calibrated source's noise re-estimated online too (the default), and kept as stated
NOISE = AlignerConfig(datum='fixes', calibrate=True, refine_executor='inline',
                      calibration_noise=True)
STATED = AlignerConfig(datum='fixes', calibrate=True, refine_executor='inline',
                       calibration_noise=False)
TRUE_YAW_SIGMA, STATED_YAW_SIGMA = 0.002, 0.008  # the stated yaw variance 16x the true one


def _overstated(seed: int):
    return biased_survey(np.random.default_rng(seed), n_nodes=600, scale=SCALE,
                         yaw_rate=YAW_RATE, fix_every=FIX_EVERY, fix_sigma_m=0.5,
                         sigma_yaw_rad=TRUE_YAW_SIGMA, stated_sigma_yaw_rad=STATED_YAW_SIGMA)


@pytest.mark.parametrize('seed', [0, 1])
def test_the_noise_of_a_calibrated_source_is_re_estimated_online(seed):
    """The stated yaw variance 16x the true one: the online estimate's rotation factor is
    within 3 sigma of 1/16 and 3 sigma below 1 (the translation's, too little redundancy, kept
    at 1); the motions that entered after it are stored with the stated covariance scaled by
    their booked factors (independent computation), ``stated`` undoes it, and the online path
    is closer to the truth than with the stated noise."""
    s = _overstated(seed)
    al, online = run(s, NOISE)
    book = al.online_calibration
    rot = next(f for f in book.report.noise if f.part == 'rotation')
    lines = book.report.lines()
    assert rot.applied and abs(rot.factor - 1 / 16) < 3 * rot.sigma, lines
    assert rot.factor + 3 * rot.sigma < 1.0, lines
    diag = book.diagnostic_values()
    assert diag['calibration/odom0/rotation_noise'] == f'{rot.factor:.4g}'
    assert diag['calibration/odom0/translation_noise'] == '1 (stated)'
    fac = book.noise_applied.a
    assert (fac[:, 0] == 1.0).all() and (fac[:, 1] < 1.0).any() and (fac[:5] == 1.0).all()
    st = al.state
    m = st.src.n
    stated = s.network.arrays().cov[:m]
    d = np.sqrt(np.repeat(fac, 3, axis=1))
    np.testing.assert_allclose(st.ccov.a, d[:, :, None] * stated * d[:, None, :], rtol=1e-12,
                               atol=0.0)
    np.testing.assert_allclose(book.stated(st.ccov.a, np.arange(m)), stated, rtol=1e-12,
                               atol=0.0)
    _, online_stated = run(s, STATED)
    assert _rmse(online, s.T_true) < _rmse(online_stated, s.T_true)


def test_a_restart_continues_the_online_noise_exactly(tmp_path):
    """A snapshot mid-track with noise factors applied: the restored aligner continues to the
    same state (the booked factors and the stored covariances) and online path, bit for
    bit."""
    s = _overstated(0)
    al, online = run(s, NOISE)
    rep = al.online_calibration.report.as_dict()
    assert rep['noise'] and report_of_dict(rep).as_dict() == rep  # saved as it is
    back, online_back = run(s, NOISE, cut=10 * FIX_EVERY + 7, path=tmp_path / 'state')
    meta, arrays = state_arrays(al.state)
    meta2, arrays2 = state_arrays(back.state)
    assert (arrays['cal_noise'][:10 * FIX_EVERY] != 1.0).any()  # applied before the cut
    assert meta2['calibration'] == meta['calibration']
    for name in arrays:
        np.testing.assert_array_equal(arrays2[name], arrays[name], err_msg=name)
    np.testing.assert_array_equal(online_back, online)
