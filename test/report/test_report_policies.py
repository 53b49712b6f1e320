"""The multi-draw comparison of the freeze policies (issue 15, "no policy worse than weighted"):
paired statistics against numbers computed by hand, the t interval's coverage in a
Monte-Carlo, the target row failing for a policy made worse on purpose, the config check."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.report import ReproduceConfig, preset
from ga_ros.report.experiments.policies import paired_difference, policy_statistics
from ga_ros.report.markdown.policies import policy_seeds_table
from ga_ros.report.markdown.targets import policy_target_row

#: Student t quantile t(0.975, 4) from a printed table (Abramowitz & Stegun 26.10: 2.776445).
T975_DOF4 = 2.7764451051977987

#: End gaps (%) of the lead's five draws (bench_online_gap.py, 8 tracks, seeds 20051101, 1-4).
WEIGHTED = {'raw': [37.9, -0.8, 5.7, 11.5, 1.5], 'aligned': [33.0, 4.4, 28.8, 9.2, 29.0]}
MARGINAL = {'raw': [40.0, -0.8, 5.7, 10.9, 2.1], 'aligned': [31.9, 4.3, 29.0, 9.5, 26.0]}


def _by_hand(x, ref):
    d = [a - b for a, b in zip(x, ref)]
    n = len(d)
    mean = sum(d) / n
    sd = (sum((v - mean) ** 2 for v in d) / (n - 1)) ** 0.5
    half = T975_DOF4 * sd / n ** 0.5
    return mean, sd, mean - half, mean + half


def test_paired_difference_equals_the_formula_computed_by_hand():
    rng = np.random.default_rng(15)
    ref = rng.normal(10.0, 8.0, 5)
    x = ref + rng.normal(0.5, 1.0, 5)
    d = paired_difference(x, ref)
    mean, sd, lo, hi = _by_hand(x.tolist(), ref.tolist())
    assert d.n == 5 and d.confidence == 0.95
    np.testing.assert_allclose([d.mean, d.sd, d.ci_low, d.ci_high], [mean, sd, lo, hi],
                               rtol=1e-12, atol=1e-12)
    assert d.worse == (lo > 0) and d.better == (hi < 0)
    one = paired_difference(x[:1], ref[:1])  # one draw: a difference, no interval
    assert one.mean == pytest.approx(x[0] - ref[0]) and np.isnan(one.ci_low)
    assert not one.worse and not one.better


def test_paired_interval_covers_the_true_difference_95_percent_of_the_time():
    """Monte-Carlo: draws whose common difficulty (sd 10) dwarfs the policies' difference
    (0.3, sd 1); the paired interval must still cover 0.3 in 95 % of the experiments."""
    rng = np.random.default_rng(7)
    trials, n = 4000, 5
    common = rng.normal(0.0, 10.0, (trials, n))
    ref = common + rng.normal(0.0, 0.7, (trials, n))
    x = common + 0.3 + rng.normal(0.0, 0.7, (trials, n))
    cover = np.mean([(d.ci_low <= 0.3 <= d.ci_high)
                     for d in (paired_difference(a, b) for a, b in zip(x, ref))])
    assert abs(cover - 0.95) < 4 * np.sqrt(0.95 * 0.05 / trials)


@pytest.mark.parametrize('bad', [([np.nan, 1.0], [0.0, 1.0]), ([1.0, 2.0], [1.0]), ([], [])])
def test_paired_difference_rejects_bad_input(bad):
    with pytest.raises(InputError):
        paired_difference(np.array(bad[0]), np.array(bad[1]))


def test_policy_statistics_on_the_leads_five_draws():
    s = policy_statistics({'weighted': WEIGHTED, 'marginal': MARGINAL}, 'weighted')
    assert s['n'] == 5 and s['reference'] == 'weighted' and s['worse'] == []
    for policy, g in (('weighted', WEIGHTED), ('marginal', MARGINAL)):
        for metric in ('raw', 'aligned'):
            v = s['policies'][policy][metric]
            assert v['values'] == g[metric]
            assert v['mean'] == pytest.approx(np.mean(g[metric]), rel=1e-12)
            assert v['sd'] == pytest.approx(np.std(g[metric], ddof=1), rel=1e-12)
    assert 'vs_reference' not in s['policies']['weighted']
    vs = s['policies']['marginal']['vs_reference']
    for metric in ('raw', 'aligned'):
        mean, sd, lo, hi = _by_hand(MARGINAL[metric], WEIGHTED[metric])
        np.testing.assert_allclose([vs[metric][k] for k in ('mean', 'sd', 'ci_low', 'ci_high')],
                                   [mean, sd, lo, hi], rtol=1e-9)
        assert lo < 0 < hi  # equal within the spread: not worse, not better
    label, measured, ok = policy_target_row(s)
    assert ok is True and 'no policy worse than weighted' in label and '5 noise draws' in label
    lo, hi = _by_hand(MARGINAL['raw'], WEIGHTED['raw'])[2:]
    assert f'[{lo:+.1f}, {hi:+.1f}]' in measured


def test_a_policy_made_worse_on_purpose_fails_the_row():
    """Worse by 1.5-2.5 points of aligned gap on every draw: invisible next to the draws' spread
    (sd ~13 points), clear in the paired difference."""
    worse = {'raw': list(WEIGHTED['raw']),
             'aligned': [a + b for a, b in zip(WEIGHTED['aligned'], [2.1, 1.5, 2.4, 1.9, 2.5])]}
    better = {'raw': [a - 1.0 for a in WEIGHTED['raw']], 'aligned': list(WEIGHTED['aligned'])}
    s = policy_statistics({'weighted': WEIGHTED, 'marginal': MARGINAL, 'worse': worse,
                           'better': better}, 'weighted')
    assert s['worse'] == ['worse']
    vs = s['policies']['worse']['vs_reference']
    assert vs['aligned']['worse'] and not vs['raw']['worse'] and vs['worse']
    assert vs['aligned']['ci_low'] == pytest.approx(_by_hand(worse['aligned'],
                                                             WEIGHTED['aligned'])[2])
    assert s['policies']['better']['vs_reference']['raw']['better']
    assert not s['policies']['better']['vs_reference']['worse']
    label, measured, ok = policy_target_row(s)
    assert ok is False and 'worse: raw' in measured
    lines = policy_seeds_table({**s, 'draws': [0, 1, 2, 3, 4]})
    row = next(x for x in lines if x.startswith('| worse |'))
    assert '**worse** (aligned)' in row
    assert 'better (raw)' in next(x for x in lines if x.startswith('| better |'))
    assert 'no significant difference' in next(x for x in lines if x.startswith('| marginal |'))
    # the per-draw table holds every gap of every policy
    draw3 = next(x for x in lines if x.startswith('| 3 |'))
    assert '+11.5 / +9.2' in draw3 and '+10.9 / +9.5' in draw3 and '+11.5 / +11.1' in draw3
    assert any(x.startswith('How to read it') for x in lines)


def test_a_single_draw_cannot_meet_or_fail_the_row():
    one = {k: {m: v[:1] for m, v in g.items()} for k, g in (('weighted', WEIGHTED),
                                                            ('marginal', MARGINAL))}
    s = policy_statistics(one, 'weighted')
    label, measured, ok = policy_target_row(s)
    assert ok is None and '(one draw)' in measured
    assert 'one draw: not testable' in ''.join(policy_seeds_table({**s, 'draws': [0]}))
    with pytest.raises(InputError, match='reference'):
        policy_statistics(one, 'dense')


@pytest.mark.parametrize('value', [0, -1, 2.5, True, '3'])
def test_config_rejects_policy_seeds_below_one_or_not_an_integer(value):
    with pytest.raises(InputError, match='policy_seeds'):
        ReproduceConfig(policy_seeds=value)


def test_presets_compare_the_policies_on_several_draws():
    assert ReproduceConfig(policy_seeds=np.int64(2)).policy_seeds == 2
    assert [preset(p).policy_seeds for p in ('full', 'quick', 'tiny')] == [10, 5, 2]


def test_reproduce_command_rejects_policy_seeds_below_one(tmp_path, capsys):
    from ga_ros.cli.main import main

    assert main(['reproduce', '--preset', 'tiny', '--policy-seeds', '0',
                 '--out', str(tmp_path)]) == 1
    assert 'policy_seeds must be an integer >= 1' in capsys.readouterr().err
    assert not (tmp_path / 'report.md').exists()
