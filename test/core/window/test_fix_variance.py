"""Online variance factor of an absolute-fix source (:mod:`ga_ros.core.quality.online_variance`,
fixes of :mod:`ga_ros.core.fixes`): a GNSS that states 0.5 m where its errors are 2 m (true
factor 16) beside odometry stated right.

Checked over a Monte-Carlo against the truth, against the batch variance components of the
same data (:func:`~ga_ros.core.quality.variance_components.solve_with_variance_components`, an
independent computation of the redundancy numbers), by the published covariances' NEES, the
WARN naming the source, the book's per-fix values against a direct recomputation and a restart
from a snapshot.
"""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.bench.fix_vce import GnssSurvey, align
from ga_ros.core.fixes import sensor_misclosure
from ga_ros.core.quality.variance_components import SourceGroups
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import load_state, save_state

SV = GnssSurvey(tracks=6, per_swath=30, fix_every=5, fix_stated_m=0.5, fix_true_m=2.0)
N, PER = SV.n, SV.per_swath
STATED_M, TRUE_M = SV.fix_stated_m, SV.fix_true_m
T_TRUE = SV.truth()[0]


def _draw(seed: int) -> list:
    """The inputs of one run, in order: ``('m', Measurement)`` and ``('f', FixTerm)``."""
    return SV.draw(np.random.default_rng(seed))


def _run(inputs: list, mode: str) -> TrackWindowAligner:
    return align(SV, inputs, mode)


def _nees(al: TrackWindowAligner) -> float:
    T = al.corrected_path().T_world_node
    cov = al.covariances(np.arange(N))
    e = np.einsum('kji,kj->ki', T[:, :3, :3], T_TRUE[:, :3, 3] - T[:, :3, 3])
    return float(np.einsum('ki,ki->k', e, np.linalg.solve(cov[:, :3, :3],
                                                          e[:, :, None])[:, :, 0])[1:].mean())


@pytest.fixture(scope='module')
def runs() -> list[dict]:
    out = []
    for seed in range(4):
        inputs = _draw(200 + seed)
        on = _run(inputs, 'apply')
        C, R, _ = on.online_variance.sums()
        k = on.online_variance.names.index('gnss')
        comp = {c.group: c for c in on.online_variance.components()}
        off = _run(inputs, 'off')
        groups = SourceGroups()
        for kind, x in inputs:
            if kind == 'm':
                groups.add(x)
        off_nees = _nees(off)
        off.refine_batch(variance_groups=groups)
        out.append({'raw': C[k] / R[k], 'gnss': comp['gnss'], 'motion': comp['motion'],
                    'batch': off.variance_components.factor('fixes'), 'nees_on': _nees(on),
                    'nees_off': off_nees, 'warnings': on.online_variance.warnings(), 'al': on,
                    'inputs': inputs})
        off.close()
    return out


def test_fix_factor_matches_the_truth_and_the_batch(runs) -> None:
    truth = (TRUE_M / STATED_M) ** 2
    raw = np.array([r['raw'] for r in runs])
    # each run's (undamped) estimate within 3 of its sigmas sqrt(2 / R) of the truth, the mean
    # of the runs within 10 %
    for r in runs:
        assert abs(r['raw'] / truth - 1) < 3 * np.sqrt(2 / r['gnss'].redundancy), r['raw']
    assert abs(raw.mean() / truth - 1) < 0.1, raw
    # the batch estimate of the same data (the fixes one group), an independent computation
    batch = np.array([r['batch'] for r in runs])
    assert np.all(np.abs(np.log(raw / batch)) < 0.2), (raw, batch)
    # the odometry, stated right: no factor far from 1
    for r in runs:
        m = r['motion']
        assert not m.estimated or abs(m.factor - 1) < 3 * m.sigma + 0.1, m


def test_fix_factor_is_damped_and_applied(runs) -> None:
    for r in runs:
        g = r['gnss']
        assert g.estimated and g.applied and g.significant
        assert g.factor == pytest.approx(r['raw'] ** (g.redundancy / (g.redundancy + 10.0)))


def test_published_covariances_become_honest(runs) -> None:
    on = np.mean([r['nees_on'] for r in runs])
    off = np.mean([r['nees_off'] for r in runs])
    assert 2.0 < on < 4.5, on  # expected 3 (nodes of a run correlated: a loose band)
    assert off > 8.0, off


def test_warning_names_the_fix_source(runs) -> None:
    diag = runs[0]['al'].online_variance.diagnostic_values()
    assert diag['variance/gnss/factor'] == f"{runs[0]['gnss'].factor:.4g}"
    for r in runs:
        assert any(w.startswith("gnss's stated covariance is") and 'too small' in w
                   for w in r['warnings']), r['warnings']


def test_book_values_against_a_direct_recomputation(runs) -> None:
    """The last window's fixes: cost ``e' L e`` at the adjusted poses, redundancy numbers in
    (0, 3] (position fixes)."""
    al = runs[0]['al']
    st, book = al.state, al.online_variance
    fixes = [f for f in st.fixes.of_rows(st.last_window) if st.fixes.gated[f]]
    assert fixes
    vals = book.arrays()
    for f in fixes:
        term = st.fixes.terms[f]
        e = sensor_misclosure(st.T[st.fixes.rows[f]], term.T_node_sensor, term.fix)[:3]
        assert vals['fix_cost'][f] == pytest.approx(e @ e / STATED_M ** 2, rel=1e-9)
        assert 0.0 < vals['fix_redundancy'][f] <= 3.0
    assert vals['fix_group'][0] == -1  # the gauge prior: no group


def test_a_restart_keeps_the_fix_factor(runs, tmp_path) -> None:
    inputs = runs[1]['inputs']
    cut = next(i for i, (kind, x) in enumerate(inputs) if kind == 'm' and x.src_id == 3 * PER)
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, datum='fixes',
                                          refine_executor='inline', variance_components='apply'),
                            T_world_first=T_TRUE[0])
    for kind, x in inputs[:cut]:
        al.add_measurement(x) if kind == 'm' else al.add_fix(x)
    before = {c.group: c.factor for c in al.online_variance.components()}
    path = tmp_path / 'state.gastate'
    save_state(al, path)
    al.close()
    back = load_state(path, al.config).aligner
    assert {c.group: c.factor for c in back.online_variance.components()} == before
    assert back.state.fixes.info_factors is not None
    back.close()
