"""Sections of the aerial survey: ATE and gaps, update times, memory, quality control."""

from __future__ import annotations

from ga_ros.report.markdown.policies import policy_seeds_markdown


def aerial_markdown(r: dict) -> list[str]:
    """The aerial survey: counts, gains and the ATE table of batch and window."""
    cfg = r['config']
    L: list[str] = []
    add = L.append
    a = r['aerial']
    add('## Aerial survey (Sec. IV, V-B): Fig. 7/8, window vs batch, timings\n')
    add(f'{a["tracks"]} double tracks, {a["nodes"]} nodes, {a["connections"]} connections '
        f'({a["cross_connections"]} cross-swath) at {a["noise_pct"]:g} % noise; se3 model: '
        f'{a["se3"]["equations"]} equations, {a["se3"]["observations"]} observations, '
        f'{a["se3"]["unknowns"]} unknowns (paper model: {a["paper_model_counts"]["equations"]} / '
        f'{a["paper_model_counts"]["observations"]} / {a["paper_model_counts"]["unknowns"]}; the '
        'paper quotes ~51,000 equations for ~17,000 connections and 15,300 unknowns).\n')
    gains = [f'batch GA {a["improvement_pct"]["batch"]:.1f} %']
    gains += [f'window ({p}) {v:.1f} %' for p, v in a['improvement_pct'].items() if p != 'batch']
    add('Mean position error improvement over F2F on this survey: ' + ', '.join(gains)
        + ' (compare Table I, on one double track or two loops: F2F drift grows with the '
        'length of the path, so the gain grows with the survey).\n')
    add('ATE = RMSE of position errors, raw (first pose anchored) and after a rigid '
        '(Horn/Umeyama) alignment. Gap = ATE(window) / ATE(batch) - 1.\n')
    add('| estimate | ATE raw (m) | ATE aligned (m) | mean error (m) | gap aligned % '
        '| gap raw % |')
    add('|---|---|---|---|---|---|')
    add(f'| F2F | {a["f2f"]["raw_rmse_m"]:.3f} | {a["f2f"]["aligned_rmse_m"]:.3f} | '
        f'{a["f2f"]["mean_error_m"]:.3f} | | |')
    add(f'| batch GA ({a["batch"]["seconds"]:.1f} s) | {a["batch"]["raw_rmse_m"]:.3f} | '
        f'{a["batch"]["aligned_rmse_m"]:.3f} | {a["batch"]["mean_error_m"]:.3f} | 0 | 0 |')
    for p, v in a['policies'].items():
        w, rf = v['window'], v['refined']
        add(f'| window K={cfg["window_tracks"]}, {p} | {w["raw_rmse_m"]:.3f} | '
            f'{w["aligned_rmse_m"]:.3f} | {w["mean_error_m"]:.3f} | {v["gap_aligned_pct"]:.1f} | '
            f'{v["gap_raw_pct"]:.1f} |')
        add(f'| window {p} + final batch refinement ({v["refine_s"]:.1f} s) | '
            f'{rf["raw_rmse_m"]:.3f} | {rf["aligned_rmse_m"]:.3f} | {rf["mean_error_m"]:.3f} | '
            f'{100 * (rf["aligned_rmse_m"] / a["batch"]["aligned_rmse_m"] - 1):.1f} | '
            f'{100 * (rf["raw_rmse_m"] / a["batch"]["raw_rmse_m"] - 1):.1f} |')
    add('')
    return L


def aerial_updates_markdown(r: dict) -> list[str]:
    """The aerial survey: policy seeds, per-track update times, Fig. 7/8."""
    a = r['aerial']
    L: list[str] = []
    add = L.append
    add(policy_seeds_markdown(r))
    if not a['window_available']:
        add('**The track-window aligner (`ga_ros.core.window`) was not available when this report '
            'was generated: the window rows, Fig. 8, the update timings and the memory '
            'comparison are missing.**\n')
    if a['policies']:
        add("Per-track update time (the aligner's own `update_ms`, all "
            f'{a["tracks"]} tracks online):\n')
        add('| policy | p50 (ms) | p95 (ms) | max (ms) | whole online run (s) | updates '
            '| converged | outliers rejected |')
        add('|---|---|---|---|---|---|---|---|')
        for p, v in a['policies'].items():
            u = v['update_ms']
            add(f'| {p} | {u["p50"]:.1f} | {u["p95"]:.1f} | {u["max"]:.1f} | {v["run_s"]:.2f} '
                f'| {v["updates"]} | {v["converged_updates"]} | {v["outliers"]} |')
        add('\nTargets: p95 < 150 ms and the whole run < 5 s on a 2-core machine; the machine '
            'that wrote this report was shared with other jobs, so times are upper bounds.\n')
    add('![Fig. 7](fig7_aerial_error.png)\n')
    add('Fig. 7: position error versus frame number (log scale).\n')
    if 'fig8_tracks.png' in r['images']:
        add('![Fig. 8](fig8_tracks.png)\n')
        add("Fig. 8: errors of the window's tracks before (thin: the previous estimate, the new "
            'track chained by F2F) and after (thick) the GA at the end of each shown track.\n')
    return L


def memory_markdown(r: dict) -> list[str]:
    """Memory versus number of tracks, when it was measured."""
    L: list[str] = []
    add = L.append
    mem = r['memory']
    if mem.get('available'):
        add('## Memory versus number of tracks\n')
        add('| tracks | nodes | connections | peak of one update, full window (MiB) | '
            'largest update peak (MiB) | retained by the aligner (MiB) |')
        add('|---|---|---|---|---|---|')
        for n, v in mem['sizes'].items():
            add(f'| {n} | {v["nodes"]} | {v["connections"]} | '
                f'{v["update_peak_mib_full_window_mean"]:.2f} | {v["update_peak_mib_max"]:.2f} | '
                f'{v["retained_mib"]:.2f} |')
        add('\nThe update peak is the memory allocated during one `finish_track` (tracemalloc), '
            'averaged over the updates whose window holds K tracks; it should depend on the '
            'window only. The retained memory includes the whole corrected path and '
            'all connections (kept for the final batch refinement and the published path), '
            'which grows linearly with the survey.\n')
    return L


def ate_rows(a: dict, window_tracks: int) -> list[str]:
    """ATE table rows: F2F, batch, and window / refined per policy with the gap to batch."""
    b = a['batch']
    out = ['| estimate | ATE raw (m) | ATE aligned (m) | mean error (m) | gap aligned % '
           '| gap raw % |', '|---|---|---|---|---|---|',
           f'| F2F | {a["f2f"]["raw_rmse_m"]:.3f} | {a["f2f"]["aligned_rmse_m"]:.3f} | '
           f'{a["f2f"]["mean_error_m"]:.3f} | | |',
           f'| batch GA | {b["raw_rmse_m"]:.3f} | {b["aligned_rmse_m"]:.3f} | '
           f'{b["mean_error_m"]:.3f} | 0 | 0 |']
    for p, v in a['policies'].items():
        w = v['window']
        out.append(f'| window K={window_tracks}, {p} | {w["raw_rmse_m"]:.3f} | '
                   f'{w["aligned_rmse_m"]:.3f} | {w["mean_error_m"]:.3f} | '
                   f'{v["gap_aligned_pct"]:.1f} | {v["gap_raw_pct"]:.1f} |')
    return out


def quality_markdown(q: dict | None, what: str, image: str, images: list[str]) -> str:
    """Section: quality control (Baarda) of a batch adjustment."""
    if not q:
        return ''
    L = [f'### Quality control of the batch adjustment of {what}\n',
         '`ga_ros.core.quality.quality_control` on the batch solution (formulas in '
         'docs/quality.md).\n',
         '| figure | value |', '|---|---|',
         f'| global test `v\'Pv` / critical (alpha {q["global_alpha"]:g}) | {q["cost"]:.1f} / '
         f'{q["global_critical"]:.1f}: {"passed" if q["global_passed"] else "**failed**"} |',
         f'| variance factor sigma0^2 (redundancy {q["redundancy"]}) | {q["sigma0_sq"]:.3f} |',
         f'| sum of redundancy numbers (= r - u) | {q["redundancy_numbers_sum"]:.1f} |',
         f'| untestable connections (r_i ~ 0) | {q["untestable_connections"]} |',
         f'| w-test critical value (alpha0 {q["alpha0"]:g}) / largest |w| | '
         f'{q["w_critical"]:.2f} / {q["w_max"]:.2f} |',
         f'| w statistics: mean / std (N(0, 1) when the covariances are honest) | '
         f'{q["w_mean"]:.3f} / {q["w_std"]:.3f} |',
         f'| connections rejected by the test | {q["rejected_connections"]} |']
    for kind in ('consecutive', 'cross'):
        k = q.get(kind)
        if k:
            L.append(f'| {kind} ({k["connections"]}): median r_i, median MDB | '
                     f'{k["redundancy_number_median"]:.2f} of 6, '
                     f'{k["mdb_translation_median_m"]:.2f} m / '
                     f'{k["mdb_rotation_median_deg"]:.2f} deg |')
    L.append(f'\nComputed in {q["seconds"]:.1f} s.\n')
    if image in images:
        L.append(f'![quality control]({image})\n')
        L.append('Left: redundancy numbers (how much each connection is checked by the others: '
                 'a consecutive motion across a turn has few checks, a cross-track one in the '
                 'middle of the grid many). Middle: w-statistics against N(0, 1) and the '
                 'critical values (red); a wider histogram means over-confident covariances. '
                 'Right: the smallest error per component that the test finds with 80 % '
                 'power.\n')
    return '\n'.join(L) + '\n'
