"""Freezing ahead (``AlignerConfig.freeze_ahead``): the next leaving track's freeze computed in a
background thread right after an update gives exactly what freezing at the track end gives, and
is recomputed whenever what it depends on changed in between."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from solver_problems import noisy_aerial_survey

from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import load_state, save_state
from ga_ros.geometry import se3


def _config(ahead: bool, **kw) -> AlignerConfig:
    base = dict(window_tracks=2, prior_band=3, prior_hubs=2, refine_every_tracks=0,
                refine_executor='inline')
    base.update(kw)
    return AlignerConfig(freeze_ahead=ahead, **base)


def _dense(info) -> np.ndarray:
    return info.toarray() if hasattr(info, 'toarray') else np.asarray(info)


def _assert_same_state(a: TrackWindowAligner, b: TrackWindowAligner) -> None:
    """Bit for bit: poses, frozen flags and covariances, connection status, joint priors."""
    n = len(a.state.ids)
    assert n == len(b.state.ids)
    np.testing.assert_array_equal(a.state.T[:n], b.state.T[:n])
    np.testing.assert_array_equal(a.state.frozen[:n], b.state.frozen[:n])
    np.testing.assert_array_equal(a.state.cov[:n], b.state.cov[:n])
    np.testing.assert_array_equal(a.state.status.a, b.state.status.a)
    assert len(a.state.priors) == len(b.state.priors)
    for p, q in zip(a.state.priors, b.state.priors):
        np.testing.assert_array_equal(p[0], q[0])
        np.testing.assert_array_equal(p[1], q[1])
        np.testing.assert_array_equal(_dense(p[2]), _dense(q[2]))


def _feed(al: TrackWindowAligner, ms, between=None) -> None:
    """Feed ``ms`` and finish the last track; ``between(al)`` after each track end."""
    for m in list(ms) + [None]:
        ups = al.add_measurement(m) if m is not None else [al.finish_track()]
        for up in ups:
            assert up is None or not str(up.reason).startswith('failed'), up.reason
        if ups and between is not None:
            between(al)


@pytest.mark.parametrize('policy,refine', [('weighted', 0), ('marginal', 0), ('weighted', 1)])
def test_a_freeze_computed_ahead_in_a_thread_equals_the_freeze_at_the_track_end(
        monkeypatch, policy, refine):
    """Same survey twice: freezes at the track end, and computed in the background right after
    each update. Every freeze with a full window came from the background thread (not silently
    recomputed), and the states are identical bit for bit after every update."""
    sc, nm, ms = noisy_aerial_survey(6, 12, 5.0, 4)
    threads = []
    plan = TrackWindowAligner._plan_freeze

    def recorded(self, *args):
        threads.append(threading.current_thread() is threading.main_thread())
        return plan(self, *args)

    monkeypatch.setattr(TrackWindowAligner, '_plan_freeze', recorded)
    cfg = dict(freeze_policy=policy, refine_every_tracks=refine)
    ref = TrackWindowAligner(_config(False, **cfg), sc.T_world_node[0])
    _feed(ref, ms)
    assert threads and all(threads)  # at the track end: in the caller's thread
    threads.clear()
    al = TrackWindowAligner(_config(True, **cfg), sc.T_world_node[0])
    _feed(al, ms)
    al.close()
    ref.close()
    _assert_same_state(al, ref)
    used, recomputed = al.ahead.n_ahead
    assert used == 6 - 2 and recomputed == 0
    assert threads.count(False) == used + 1  # the last one ahead of an update never run
    assert al.wait_background() > 0.0


def test_a_freeze_that_failed_in_the_background_is_recomputed_at_the_track_end(monkeypatch):
    """An error in the background thread (here: every freeze computed there fails) loses
    nothing: each update recomputes its freeze and the survey equals the one without thread."""
    sc, nm, ms = noisy_aerial_survey(4, 10, 5.0, 1)
    plan = TrackWindowAligner._plan_freeze

    def flaky(self, *args):
        if threading.current_thread() is not threading.main_thread():
            raise MemoryError('the background thread ran out of memory')
        return plan(self, *args)

    monkeypatch.setattr(TrackWindowAligner, '_plan_freeze', flaky)
    ref = TrackWindowAligner(_config(False), sc.T_world_node[0])
    al = TrackWindowAligner(_config(True), sc.T_world_node[0])
    for x in (ref, al):
        _feed(x, ms)
        x.close()
    _assert_same_state(al, ref)
    assert al.ahead.n_ahead == [0, 4 - 2]


def test_a_new_connection_to_the_leaving_track_makes_the_update_recompute_its_freeze():
    """A cross connection from the leaving track to the window, added after the freeze was
    computed ahead, keeps a node in the prior that the plan computed ahead eliminated: the plan
    is discarded and the result equals freezing at the track end."""
    sc, nm, ms = noisy_aerial_survey(5, 12, 5.0, 2)
    start = next(k for k, m in enumerate(ms) if m.src_track == 3 or m.dst_track == 3)
    results, extra, plan, kept = [], None, None, []
    for ahead in (True, False):
        al = TrackWindowAligner(_config(ahead), sc.T_world_node[0])
        _feed(al, ms[:start])  # tracks 0-2 finished; track 1 leaves at the next update
        al.wait_background()
        if ahead:
            plan = al.ahead.job.plan
            assert plan is not None and plan.track == 1
            a = int(plan.nodes[~np.isin(plan.nodes, plan.prior[0])][0])  # eliminated by it
            b = int(np.nonzero(al.state.trackarr.a == 2)[0][-1])  # a node of the newest track
            T_ab = se3.inverse(al.state.T[a]) @ al.state.T[b]
            extra = Measurement(int(al.state.idarr.a[a]), int(al.state.idarr.a[b]), 1, 2,
                                se3.to_translation_rotvec(T_ab),
                                np.diag([0.01] * 3 + [1e-4] * 3), 0, 'cross')
        al.add_measurement(extra)
        _feed(al, ms[start:], lambda x: kept.append([p[0].copy() for p in x.state.priors]))
        al.close()
        results.append(al)
    al, ref = results
    _assert_same_state(al, ref)
    assert al.ahead.n_ahead[1] == 1
    a = al.state.index[extra.src_id]
    assert any(a in idx for idx in kept[len(kept) // 2])  # ref, track 1 frozen: a is kept
    assert a not in plan.prior[0]


def test_state_files_refinement_and_covariances_do_not_depend_on_the_thread(tmp_path):
    """A state saved while a freeze is being computed ahead, restored and continued, equals the
    uninterrupted survey frozen at the track ends (to 1e-12: the restored aligner re-solves its
    last window); covariances asked for between updates equal those of the aligner without
    the thread; ``refine_batch`` drops a plan computed ahead of it."""
    sc, nm, ms = noisy_aerial_survey(6, 12, 5.0, 5)
    ref = TrackWindowAligner(_config(False), sc.T_world_node[0])
    al = TrackWindowAligner(_config(True), sc.T_world_node[0])
    cut = next(k for k, m in enumerate(ms) if 4 in (m.src_track, m.dst_track))
    covs = []

    def ask(a):
        done = np.nonzero(a.state.trackarr.a <= max(a.state.finished))[0]
        covs.append(a.covariances(a.state.idarr.a[done[1:]]))

    _feed(ref, ms[:cut], ask)
    _feed(al, ms[:cut], ask)
    assert al.ahead.job is not None
    save_state(al, tmp_path / 's.ga')  # while its thread may still run
    back = load_state(tmp_path / 's.ga').aligner
    for a, b in zip(covs[:len(covs) // 2], covs[len(covs) // 2:]):
        np.testing.assert_array_equal(a, b)
    for x in (ref, back, al):
        _feed(x, ms[cut:])
    np.testing.assert_allclose(back.corrected_path().T_world_node,
                               ref.corrected_path().T_world_node, rtol=0, atol=1e-12)
    for x in (ref, al):
        x.refine_batch()
        assert x.ahead.job is None
    _assert_same_state(al, ref)
    for x in (ref, al, back):
        x.close()


@pytest.mark.parametrize('ahead', [True, False])
def test_a_freeze_leaves_its_covariances_to_a_refinement_installed_with_it(monkeypatch, ahead):
    """With the background refinement every track (lag 1), the leaving track's covariances are
    replaced by the refined ones in the very update that freezes it: the freeze does not
    compute them (no selected inversion of the window's factor), and every state equals the
    one of freezes that compute them, bit for bit; if the refinement is not installed (here:
    its installation fails at one update), the freeze's covariances are computed then."""
    from ga_ros.core.window import aligner as aligner_mod
    from ga_ros.core.window import freeze
    from ga_ros.core.window.handoff import RefinementHandoff
    from ga_ros.errors import InputError

    sc, nm, ms = noisy_aerial_survey(6, 12, 5.0, 2)
    cfg = _config(ahead, refine_every_tracks=1, refine_relinearize_sigma=0.0)
    calls = []
    computed = freeze.marginal_covariances

    def counted(*args, **kwargs):
        calls.append(1)
        return computed(*args, **kwargs)

    monkeypatch.setattr(freeze, 'marginal_covariances', counted)
    install = RefinementHandoff.install
    fail_at = [4]

    def install_or_fail(self, snap, res):  # the 4th installation fails: nothing installed
        fail_at[0] -= 1
        if fail_at[0] == 0:
            raise InputError('not installed (test)')
        return install(self, snap, res)

    monkeypatch.setattr(RefinementHandoff, 'install', install_or_fail)
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    states = []
    _feed(al, ms, between=lambda a: states.append(a.state.cov[:len(a.state.ids)].copy()))
    deferred = len(calls)
    calls.clear()
    fail_at[0] = 4
    monkeypatch.setattr(aligner_mod.TrackWindowAligner, '_refinement_due', lambda self, n: False)
    ref = TrackWindowAligner(cfg, sc.T_world_node[0])
    ref_states = []
    _feed(ref, ms, between=lambda a: ref_states.append(a.state.cov[:len(a.state.ids)].copy()))
    for x in (al, ref):
        x.close()
    _assert_same_state(al, ref)
    assert len(states) == len(ref_states)
    for a, b in zip(states, ref_states):
        np.testing.assert_array_equal(a, b)
    # 6 tracks, window 2: 4 freezes, each with its covariances in the reference (ahead: one
    # more, computed after the last update for an update never run); with the refinement
    # installed at 3 of them, only the one whose refinement failed computes them
    assert len(calls) == 4 + ahead and deferred == 1
