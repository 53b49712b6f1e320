"""Sections of the synthetic experiments: Table I (Sec. V-A) and Fig. 2/3 (Sec. IV)."""

from __future__ import annotations

import numpy as np

#: The paper's stated improvement of GA over F2F (Sec. V-A): ~80 % at 1 % noise, ~45 % at 25 %.
PAPER_IMPROVEMENT = {'1': 80.0, '25': 45.0}


def table1_markdown(r: dict) -> list[str]:
    """Table I: F2F versus GA per trajectory and noise level."""
    L: list[str] = []
    add = L.append
    add('## Table I: F2F vs GA, synthetic trajectories (Sec. V-A)\n')
    add('Counts are for the `se3` model (6 equations and 6 observations per connection, 6 '
        "unknowns per free node); the paper's position model (eq. 1) has 3 / 6 / 3. Errors are "
        f'mean position errors over all nodes, averaged over {r["runs"]} runs.\n')
    add('| trajectory | noise % | nodes | connections | equations | observations | unknowns '
        '| paper-model eq. / obs. / unk. | F2F mean (m) | GA mean (m) | improvement % '
        '| paper % |')
    add('|---|---|---|---|---|---|---|---|---|---|---|---|')
    for row in r['table1']:
        paper = PAPER_IMPROVEMENT.get(f'{row["noise_pct"]:g}')
        add(f'| {row["trajectory"]} | {row["noise_pct"]:g} | {row["nodes"]} | '
            f'{row["connections"]} | {row["equations"]} | {row["observations"]} | '
            f'{row["unknowns"]} | {row["paper_equations"]} / {row["paper_observations"]} / '
            f'{row["paper_unknowns"]} | {row["f2f_mean_m"]:.3f} | {row["ga_mean_m"]:.3f} | '
            f'{row["improvement_pct"]:.1f} | {f"~{paper:.0f}" if paper else "-"} |')
    add('')
    return L


def table1_discussion_markdown(r: dict) -> list[str]:
    """Table I's discussion: closed versus open, the mean improvement, its spread."""
    L: list[str] = []
    add = L.append
    imp = r['improvement_pct']
    closed_better = []
    for kind in ('lawnmower', 'looping'):
        o, c = f'{kind}_open', f'{kind}_closed'
        ro = {x['noise_pct']: x['ga_mean_m'] for x in r['table1'] if x['trajectory'] == o}
        rc = {x['noise_pct']: x['ga_mean_m'] for x in r['table1'] if x['trajectory'] == c}
        common = sorted(set(ro) & set(rc))
        if common:
            n_better = sum(rc[p] < ro[p] for p in common)
            closed_better.append(f'{kind}: closed has the smaller GA error at {n_better} of '
                                 f'{len(common)} noise levels')
    if closed_better:
        add('Closed vs open: ' + '; '.join(closed_better) + '.\n')
    levels = sorted({float(k) for v in imp.values() for k in v})
    if levels:
        lo, hi = f'{levels[0]:g}', f'{levels[-1]:g}'
        mean_lo = np.mean([v[lo] for v in imp.values() if lo in v])
        mean_hi = np.mean([v[hi] for v in imp.values() if hi in v])
        add(f'Mean improvement over the trajectories: {mean_lo:.1f} % at {lo} % noise and '
            f'{mean_hi:.1f} % at {hi} % noise; the paper reports ~80 % at 1 % falling to ~45 % '
            'at 25 %.\n')
    spans = {name: max(v.values()) - min(v.values()) for name, v in imp.items() if v}
    if spans:
        add('**Improvement versus noise level.** In this run the improvement varies by at most '
            f'{max(spans.values()):.1f} percentage points across the noise levels of one '
            'trajectory. With noise proportional to the motion, F2F and GA errors both grow '
            'about linearly with the noise level (the problem stays close to linear: see the '
            "mean iterations in `report.json`), so their ratio changes little. The paper's "
            'drop to ~45 % at 25 % suggests that its high-noise observations were further from '
            'this model (the paper: observations "become less consistent with the rigid body '
            'motion constraint"); we did not tune the noise to reproduce it. F2F drift is '
            'dominated by the rotation noise (a heading error turns the rest of the path); '
            'cross-track connections remove most of it, so the gain grows with the survey '
            '(compare the aerial survey below).\n')
    return L


def paper_model_markdown(r: dict) -> list[str]:
    """Table I for the paper's position model (eq. 1), when it was run."""
    L: list[str] = []
    add = L.append
    if r['table1_paper_model']:
        pm = r['table1_paper_model']
        add(f'### Paper model (eq. 1, positions only), {pm[0]["runs"]} run(s) per cell\n')
        add('| trajectory | noise % | equations | observations | unknowns | F2F mean (m) '
            '| GA mean (m) | improvement % | converged |')
        add('|---|---|---|---|---|---|---|---|---|')
        for row in pm:
            add(f'| {row["trajectory"]} | {row["noise_pct"]:g} | {row["equations"]} | '
                f'{row["observations"]} | {row["unknowns"]} | {row["f2f_mean_m"]:.3f} | '
                f'{row["ga_mean_m"]:.3f} | {row["improvement_pct"]:.1f} | '
                f'{row["converged"]}/{row["runs"]} |')
        add('\nIn eq. 1 the rotation acts on absolute world positions (`p_j = R(w) p_i + t`), so '
            'rotation noise perturbs a connection in proportion to the distance of its nodes '
            'from the origin; the se3 model (relative motion in the sensor frame) does not have '
            'this property.\n')
    return L


def future_tracks_markdown(r: dict) -> list[str]:
    """Fig. 2/3: the effect of future tracks on track 1."""
    cfg = r['config']
    L: list[str] = []
    add = L.append
    ft = r['future_tracks']
    add('## Fig. 2/3: effect of future tracks on track 1 (Sec. IV, Appendix)\n')
    add(f'Aerial survey, tracks 1..k for k = 1..{cfg["fig3_tracks"]} ({ft["n_nodes"]} nodes, '
        f'{ft["n_connections"]} connections for all {cfg["fig3_tracks"]}); GA over tracks 1..k; '
        'the value at k is the mean change of the track-1 positions caused by adding track k, '
        'normalised by the largest (k = 2).\n')
    add("The adjustment is linearised at the truth, as in the paper's Appendix (eq. Avii): the "
        "correction is then linear in the noise, `d = N^-1 A' P xi`, evaluated for "
        f'{cfg["fig3_runs"]} noise draws per level (first node fixed).\n')
    fl = r['future_tracks_positions_only']
    add('| model | noise % | ' + ' | '.join(f'k={k}' for k in ft['tracks']) + ' |')
    add('|---|---|' + '---|' * len(ft['tracks']))
    for name, res in (('se3', ft), ('positions only', fl)):
        for key, vals in res['normalised'].items():
            add(f'| {name} | {key} | ' + ' | '.join(f'{100 * v:.1f} %' for v in vals) + ' |')
    add('\nAbsolute values (m, Fig. 2), se3: ' + '; '.join(
        f'{k} %: ' + ', '.join(f'{v:.3f}' for v in vals) for k, vals in ft['absolute_m'].items())
        + '.\n')
    add('The paper: ~5 % once tracks 1-5 are in, ~1 % with tracks 1-6, independent of the noise '
        'level.')
    if 5 in ft['tracks']:
        k5 = max(v[ft['tracks'].index(5)] for v in ft['normalised'].values())
        if k5 > 0.10:
            add(f'Here the value at k = 5 is up to {100 * k5:.1f} %: the decay is slower than '
                "the paper's, with full poses and with positions only alike. With 20 m between "
                'swaths and a 100 m footprint each swath connects only to its neighbours, so the '
                'network is a 2-D grid, in which the influence of new observations on distant '
                'nodes decays slowly (like a discrete harmonic function). The window-versus-'
                'batch gap below measures what this costs a K-track window.')
        else:
            add(f'Here the value at k = 5 is at most {100 * k5:.1f} %.')
    add('')
    add('![Fig. 3](fig3_future_tracks.png)\n')
    return L
