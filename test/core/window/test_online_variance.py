"""Online variance components per source (:mod:`ga_ros.core.quality.online_variance`) in the
track-window aligner.

The online factors are checked against their truth over a Monte-Carlo of simulated sources
(:mod:`ga_ros.sim.sources`, the true factor is ``(true / stated)^2``), against the batch
estimate of :func:`~ga_ros.core.quality.variance_components.solve_with_variance_components`
on the same data, and the book's sums against a direct recomputation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ga_ros.bench.nees_vce import band95, run_vce_nees
from ga_ros.core.measurement import variance_group
from ga_ros.core.quality.online_variance import (
    OnlineVarianceComponents,
    OnlineVarianceConfig,
)
from ga_ros.core.quality.variance_components import (
    solve_with_variance_components,
)
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.sim.sources import SourceSpec, chained_poses, multi_source_survey, sources_network


def _in_order(sv):
    return sorted(sv.measurements, key=lambda m: (m.dst_id, m.src_id))


def _aligner(mode: str = 'apply', **kw) -> TrackWindowAligner:
    return TrackWindowAligner(AlignerConfig(variance_components=mode, refine_executor='inline',
                                            **kw))


def _online(sv, mode: str = 'apply') -> TrackWindowAligner:
    al = _aligner(mode)
    res = al.add_measurements(_in_order(sv))
    assert res.n_rejected == 0
    al.finish_track()
    return al


def _factors(al: TrackWindowAligner) -> dict[str, float]:
    return {c.group: c.factor for c in al.online_variance.components()}


@pytest.fixture(scope='module')
def one_source_runs() -> list[tuple[dict, dict]]:
    """Odometry with 10 % noise stated as 5 % (true factor 4) and loop closures stated right
    (1 %, stated right: true factor 1): the online factors and the batch ones, per run."""
    out = []
    for seed in range(6):
        sv = multi_source_survey(np.random.default_rng(100 + seed), (SourceSpec('odom0', 10.0),),
                                 n_nodes=600, loop=SourceSpec('cross', 1.0, 1.0), loop_every=5)
        al = _online(sv)
        ms = list(sv.measurements)
        _, vc = solve_with_variance_components(
            sources_network(600, ms), chained_poses(600, ms), [variance_group(m) for m in ms],
            fixed=[0])
        out.append((_factors(al), {c.group: c.factor for c in vc.components}))
    return out


def test_online_factors_match_the_truth_over_a_monte_carlo(one_source_runs) -> None:
    for group, truth in (('odom0', 4.0), ('cross', 1.0)):
        f = np.array([on[group] for on, _ in one_source_runs])
        sem = f.std(ddof=1) / np.sqrt(f.size)
        assert abs(f.mean() - truth) <= max(3 * sem, 0.0), (group, f)
        assert abs(f.mean() / truth - 1) < 0.15, (group, f)


def test_online_factors_agree_with_the_batch_estimate(one_source_runs) -> None:
    on = np.array([[o['odom0'], o['cross']] for o, _ in one_source_runs])
    ba = np.array([[b['odom0'], b['cross']] for _, b in one_source_runs])
    # same data, different adjustments (windows vs one batch): close, run by run
    assert np.all(np.abs(on / ba - 1) < 0.3), (on, ba)
    assert np.all(np.abs(on.mean(0) / ba.mean(0) - 1) < 0.15), (on, ba)


def test_three_sources_are_told_apart() -> None:
    """Three sources of 2.5 / 5 / 10 % noise, all stated as 5 % (true factors 0.25, 1, 4):
    each source's factor on its own side of 1 and ordered, within 40 % of the truth, and the
    fused path no worse than the batch with the stated covariances."""
    srcs = (SourceSpec('odom0', 2.5), SourceSpec('odom1', 5.0), SourceSpec('odom2', 10.0))
    sv = multi_source_survey(np.random.default_rng(7), srcs, n_nodes=600,
                             loop=SourceSpec('cross', 5.0), loop_every=10)
    f = _factors(_online(sv))
    assert f['odom0'] < f['odom1'] < f['odom2']
    for s in srcs:
        assert abs(np.log(f[s.name] / s.true_factor)) < np.log(1.4), (s.name, f)


def test_the_book_sums_what_it_recorded() -> None:
    book = OnlineVarianceComponents(OnlineVarianceConfig(mode='apply', min_redundancy=2,
                                                         prior_dof=0))
    groups = ['a', 'b', 'a', 'c', 'a']
    for g in groups:
        book.register(g)
    rng = np.random.default_rng(0)
    cost, red = rng.uniform(1, 5, 5), rng.uniform(0.5, 1.5, 5)
    book.record(np.arange(5), cost, red)
    book.record(np.array([1]), np.array([9.0]), np.array([3.0]))  # the latest values count
    cost[1], red[1] = 9.0, 3.0
    C, R, n = book.sums()
    for k, g in enumerate(book.names):
        sel = np.array(groups) == g
        assert C[k] == pytest.approx(cost[sel].sum()) and R[k] == pytest.approx(red[sel].sum())
        assert n[k] == sel.sum()
    f = book.factors()
    assert f[0] == pytest.approx(C[0] / R[0])  # a: R >= 2
    assert f[2] == 1.0  # c: one connection, R < 2: not estimated
    assert book.factors_of(np.array([0, 3, 99])).tolist() == [f[0], 1.0, 1.0]
    restored = OnlineVarianceComponents.from_arrays(book.config, book.arrays())
    assert restored.factors().tolist() == f.tolist()


def test_damping_shrinks_towards_one_until_determined() -> None:
    book = OnlineVarianceComponents(OnlineVarianceConfig(mode='apply', min_redundancy=20,
                                                         prior_dof=10))
    for _ in range(30):
        book.register('odom0')
    book.record(np.arange(15), np.full(15, 4.0), np.ones(15))  # R = 15 < 20
    assert book.factors()[0] == 1.0
    book.record(np.arange(30), np.full(30, 4.0), np.ones(30))  # R = 30
    assert book.factors()[0] == pytest.approx(4.0 ** (30 / (30 + 10)))


def test_warning_names_the_source_and_how_far() -> None:
    srcs = (SourceSpec('odom0', 10.0),)
    sv = multi_source_survey(np.random.default_rng(3), srcs, n_nodes=600,
                             loop=SourceSpec('cross', 1.0, 1.0), loop_every=5)
    warn = _online(sv).online_variance.warnings()
    assert len(warn) == 1 and warn[0].startswith("odom0's stated covariance is ")
    assert 'too small' in warn[0]


def test_off_is_the_default_and_unchanged() -> None:
    sv = multi_source_survey(np.random.default_rng(5), (SourceSpec('odom0', 10.0),),
                             n_nodes=300, loop=SourceSpec('cross', 1.0, 1.0), loop_every=5)
    assert AlignerConfig().variance_components == 'off'
    al = TrackWindowAligner(AlignerConfig(refine_executor='inline'))
    al.add_measurements(_in_order(sv))
    al.finish_track()
    assert al.online_variance is None
    on = _online(sv)
    # the factors change the solution (odometry 4x too confident)
    assert not np.allclose(on.corrected_path().T_world_node, al.corrected_path().T_world_node)
    with pytest.raises(InputError):
        AlignerConfig(variance_components='sometimes')


def test_applied_factors_make_the_published_covariances_honest() -> None:
    """Position NEES of the published covariances over a Monte-Carlo of an aerial survey whose
    odometry states covariances 4x too small / 4x too large: outside the 95 % band without the
    factors (too small), inside with them, like the batch estimate with its factors."""
    runs = 3
    res = run_vce_nees(4, 40, 5.0, runs, 2, 1, cases=('small', 'large'))
    lo, hi = band95(runs)
    assert res['small']['online'].mean() > hi
    for case in ('small', 'large'):
        on, ba = res[case]['online vce'], res[case]['batch vce']
        assert lo <= on.mean() <= hi, (case, on.mean())
        assert abs(np.log(on.mean() / ba.mean())) < np.log(1.25), (on.mean(), ba.mean())
        # the same factor as the batch estimate (the online one is shrunk towards 1 with
        # variance_prior_dof = 10 dof; this small survey has ~100 dof of odometry a run)
        assert abs(np.log(np.mean(on.factor) / np.mean(ba.factor))) < np.log(1.15), \
            (case, on.factor, ba.factor)


def test_a_source_without_covariance_converges_to_its_own_factor() -> None:
    """A stream with no covariance gets the inputs' default model
    (:meth:`OdometryInputConfig.default_covariance`, 5 % of the motion, the simulator's depth);
    its true noise is 10 %: its factor starts at 1 (undetermined) and converges to
    (10 / 5)^2 = 4 over the tracks."""
    sv = multi_source_survey(np.random.default_rng(11), (SourceSpec('odom0', 10.0),),
                             n_nodes=600, loop=SourceSpec('cross', 1.0, 1.0), loop_every=5)
    default = OdometryInputConfig(default_noise_percent=5.0, default_depth_m=10.0)
    ms = [replace(m, cov=default.default_covariance(m.z)) if m.kind == 'consecutive' else m
          for m in _in_order(sv)]
    al = _aligner()
    seen = [1.0]
    for m in ms:
        if al.add_measurement(m):
            seen.append(_factors(al).get('odom0', 1.0))
    al.finish_track()
    seen.append(_factors(al)['odom0'])
    assert seen[-1] > 2.5 and abs(seen[-1] / 4.0 - 1) < 0.3, seen


def test_a_restart_from_a_snapshot_keeps_the_factors_and_the_path(tmp_path) -> None:
    """Saved mid-survey and restored, the aligner continues with the same groups, factors and
    path as the uninterrupted one (the book is part of the snapshot)."""
    from ga_ros.core.window.persistence import load_state, save_state

    srcs = (SourceSpec('odom0', 10.0), SourceSpec('odom1', 5.0))
    sv = multi_source_survey(np.random.default_rng(21), srcs, n_nodes=500,
                             loop=SourceSpec('cross', 1.0, 1.0), loop_every=5)
    ms = _in_order(sv)
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 3) + 5
    live = _aligner()
    live.add_measurements(ms[:cut])
    save_state(live, tmp_path / 'state')
    back = load_state(tmp_path / 'state').aligner
    assert _factors(back) == _factors(live) and back.online_variance.names == \
        live.online_variance.names
    for al in (live, back):
        al.add_measurements(ms[cut:])
        al.finish_track()
    assert _factors(back) == pytest.approx(_factors(live), rel=1e-6)
    np.testing.assert_allclose(back.corrected_path().T_world_node,
                               live.corrected_path().T_world_node, atol=1e-6)
