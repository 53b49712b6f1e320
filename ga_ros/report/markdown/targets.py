"""The summary table of the issue's targets, each checked against the run's numbers."""

from __future__ import annotations

import numpy as np

from ga_ros.report.markdown.cells import interval


def targets_markdown(r: dict) -> str:
    """The summary table of the issue's targets, each checked against this run's numbers."""
    rows = []
    t1 = r['table1']
    for kind in ('lawnmower', 'looping'):
        o = {x['noise_pct']: x['ga_mean_m'] for x in t1 if x['trajectory'] == f'{kind}_open'}
        c = {x['noise_pct']: x['ga_mean_m'] for x in t1 if x['trajectory'] == f'{kind}_closed'}
        common = sorted(set(o) & set(c))
        if common:
            ok = all(c[p] < o[p] for p in common)
            rows.append((f'{kind}: closed path better than open (GA mean error)',
                         f'{sum(c[p] < o[p] for p in common)}/{len(common)} noise levels', ok))
    a = r['aerial']
    for p, v in a['policies'].items():
        rows.append((f'window K vs batch, aligned-ATE gap < 20 % ({p})',
                     f'{v["gap_aligned_pct"]:.1f} %', v['gap_aligned_pct'] < 20.0))
    ps = r.get('policy_seeds') or {}
    if ps.get('available') and len(ps['policies']) > 1:
        rows.append(policy_target_row(ps))
    u = r['per_track_update_ms']
    if u:
        rows.append(('per-track update p95 < 150 ms', f'{u["p95"]:.1f} ms', u['p95'] < 150.0))
        first = next(iter(a['policies'].values()))
        rows.append((f'whole online run ({a["tracks"]} tracks) < 5 s',
                     f'{first["run_s"]:.2f} s', first['run_s'] < 5.0))
    e2 = r.get('experiment2')
    if e2:
        f, b = e2['f2f']['raw_rmse_m'], e2['batch']['raw_rmse_m']
        rows.append(('experiment 2 (VO motions): batch GA ATE below F2F', f'{b:.3f} m vs '
                     f'{f:.3f} m', b < f))
        for p, v in e2['policies'].items():
            rows.append((f'experiment 2: window K vs batch, aligned-ATE gap < 20 % ({p})',
                         f'{v["gap_aligned_pct"]:.1f} %', v['gap_aligned_pct'] < 20.0))
        regs = [x for x in e2.get('fig12', []) if np.isfinite(x['window_ncc'] or np.nan)]
        if regs:
            better = sum((x['window_ncc'] or 0) >= (x['f2f_ncc'] or 0) for x in regs)
            rows.append(('Fig. 12: NCC after GA >= before (F2F)', f'{better}/{len(regs)} pairs',
                         better == len(regs)))
    mem = r['memory']
    if mem.get('available'):
        sizes = list(mem['sizes'].items())
        (n0, v0), (n1, v1) = sizes[0], sizes[-1]
        ratio = (v1['update_peak_mib_full_window_mean']
                 / max(v0['update_peak_mib_full_window_mean'], 1e-9))
        rows.append((f'per-update memory flat: {n1} vs {n0} tracks', f'ratio {ratio:.2f}',
                     ratio < 1.5))
    if not rows:
        return ''
    out = ['## Targets checked in this run\n', '| target | measured | met |', '|---|---|---|']
    out += [f'| {t} | {m} | {"n/a" if ok is None else "yes" if ok else "**no**"} |'
            for t, m, ok in rows]
    return '\n'.join(out) + '\n'


def policy_target_row(ps: dict) -> tuple[str, str, bool | None]:
    """The target "no policy worse than weighted" from :func:`ga_ros.report.experiments.
    policies.policy_seeds`: met when no policy's paired difference of gap to batch (raw or
    aligned) has its confidence interval entirely above 0; ``None`` (not testable) with a
    single draw. The measured column gives every policy's mean difference and interval either
    way."""
    ref, n = ps['reference'], ps['n']
    level = f'{100 * ps["confidence"]:g} %'
    parts = [f'{p}: raw {interval(v["vs_reference"]["raw"])}, aligned '
             f'{interval(v["vs_reference"]["aligned"])} pp'
             for p, v in ps['policies'].items() if p != ref]
    label = (f'no policy worse than {ref} (gap difference to {ref} on the same draw, '
             f'{n} noise draws, mean [{level} CI])')
    if n < 2:
        return label, '; '.join(parts), None
    return label, '; '.join(parts), not ps['worse']
