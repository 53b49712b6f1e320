"""Section of experiment 2 from rendered stereo (Figs. 7-9, NEES, Fig. 12)."""

from __future__ import annotations

from ga_ros.report.markdown.aerial import ate_rows, quality_markdown
from ga_ros.report.markdown.cells import fixed


def experiment2_markdown(r: dict) -> str:
    """Section: experiment 2 from rendered stereo (Figs. 7-9, NEES, Fig. 12)."""
    e = r.get('experiment2')
    if not e:
        return ''
    imgs = r['images']
    L = _survey_lines(e)
    L += ate_rows(e, r['config']['window_tracks'])
    L += _nees_lines(e['nees'])
    L += _figure_lines(r)
    rows = e.get('fig12') or []
    if rows:
        L += _fig12_lines(rows, imgs)
    q = e.get('quality')
    if q:
        L.append(quality_markdown(q, 'experiment 2 (VO motions)', 'fig_quality_exp2.png',
                                  imgs))
    return '\n'.join(L) + '\n'


def _survey_lines(e: dict) -> list[str]:
    """The rendered survey, the front end's counts and times, the head of the ATE table."""
    sv = e['survey']
    sec = sv['seconds']
    L = ['## Experiment 2 from rendered stereo (Sec. V-B, Figs. 7-9 and 12)\n',
         f'The aerial survey rendered as {sv["image_size"]} stereo video '
         f'(`ga_ros.sim.stereo`: 110 m altitude, terrain 5-65 m, {sv["baseline_m"]:g} m '
         f'baseline): {sv["tracks"]} tracks x {2 * sv["positions_per_swath"]} positions, '
         f'{sv["step_m"]:g} m between frames, 20 m between swaths, semicircular turns; '
         f'{sv["frames"]} stereo pairs (median scene depth {sv["median_depth_m"]:.0f} m). The '
         'motions come from the images: the stereo front end of `vo_node` and the replay '
         '(`ga_ros.pipeline.stereo.StereoFrontEnd`: VO, then cross-track matching with the '
         "online window's corrected path fed back), each with the VO's own covariance. "
         f'{sv["keyframes"]} keyframes (nodes), {sv["consecutive"]} consecutive and '
         f'{sv["cross"]} cross-track motions ({sv["cross_attempts"]} matcher attempts). '
         f'Front end: {sv["front_end"]}.\n',
         f'Rendering {sec["render"]:.0f} s, VO {sec["vo"]:.0f} s, cross-track matching '
         f'{sec["cross_track"]:.0f} s, online window (feedback) {sec["online_window"]:.0f} s '
         f'({sec["total"]:.0f} s in all' + (', read from the cache of an earlier run in '
                                             f'{e["seconds_this_run"]:.1f} s'
                                             if e['cached'] else '') + ').\n',
         '### ATE and the window-versus-batch gap (VO motions)\n',
         f'{e["nodes"]} nodes, {e["connections"]} connections; batch sigma0^2 = '
         f'{e["batch"]["sigma0_sq"]:.3f} (1 when the covariances are honest).\n']
    return L


def _nees_lines(n: dict) -> list[str]:
    """The NEES table of the VO's motions, per kind of motion."""
    L = ['', '### Covariance consistency of the VO motions\n',
         "NEES `e' C^-1 e` with `e = log(T_true^-1 T_meas)`: 6 on average when the VO's "
         'covariance is honest (smaller: conservative, larger: over-confident).\n',
         '| motions | count | NEES mean | median | p90 | translation error, median (m) '
         '| rotation error, median (deg) |', '|---|---|---|---|---|---|---|']
    for kind, v in n.items():
        if v.get('n'):
            L.append(f'| {kind} | {v["n"]} | {v["nees_mean"]:.2f} | {v["nees_median"]:.2f} | '
                     f'{v["nees_p90"]:.2f} | {v["translation_error_median_m"]:.3f} | '
                     f'{v["rotation_error_median_deg"]:.3f} |')
    L.append('')
    return L


def _figure_lines(r: dict) -> list[str]:
    """Figs. 7/9 and 8 of experiment 2, when drawn."""
    imgs = r['images']
    L: list[str] = []
    if 'fig7_9_exp2.png' in imgs:
        L += ['![Figs. 7 and 9, experiment 2](fig7_9_exp2.png)\n',
              'Figs. 7 and 9: errors along the trajectory of position (m, log scale), altitude '
              '(m) and heading (rad, rotation error about the vertical); F2F dashed, GA online '
              '(each policy) solid, batch GA dotted. Left: motions from rendered stereo by the '
              'VO; right: the synthetic-noise survey of the previous section '
              f'({r["aerial"].get("noise_pct", 0):g} % noise).\n']
    if 'fig8_exp2_tracks.png' in imgs:
        L += ['![Fig. 8, experiment 2](fig8_exp2_tracks.png)\n',
              "Fig. 8 (VO motions): errors of the window's tracks before (thin) and after "
              '(thick) the GA at the end of each shown track.\n']
    return L


def _fig12_lines(rows: list[dict], imgs: list[str]) -> list[str]:
    """Fig. 12: the registration table of neighbouring swaths and the figure."""
    L = ['### Fig. 12: registration of neighbouring swaths before and after GA\n',
         'An image of the neighbouring swath (b) is warped into the first view (a) by the '
         'homography of the ground plane that a relative motion implies, '
         "`H = K (R + t n' / d) K^-1` (`cv2.warpPerspective`; the plane fitted to the "
         'terrain under a, `n` and `d` from the estimated pose of a). In each part of the '
         'survey the pair whose keyframe chain is the longest is shown (the most F2F drift '
         'between the two views). Registration error in '
         'the overlap: mean absolute grey-level difference (MAD) and normalised cross-'
         "correlation (NCC, 1 = perfect). Motions: F2F chain (before GA), the VO's own "
         'cross-track measurement, GA online window, batch GA, and the truth (what the '
         'relief leaves: the plane model ignores parallax).\n',
         '| pair (nodes) | F2F MAD / NCC | measured | GA window | GA batch | truth |',
         '|---|---|---|---|---|---|']
    for x in rows:
        cells = []
        for k in ('f2f', 'measured', 'window', 'batch', 'truth'):
            cells.append(f'{fixed(x[f"{k}_mean_abs_diff"])} / {fixed(x[f"{k}_ncc"], 2)}')
        L.append(f'| {x["node_a"]} - {x["node_b"]} | ' + ' | '.join(cells) + ' |')
    L.append('')
    if 'fig12_registration.png' in imgs:
        L += ['![Fig. 12](fig12_registration.png)\n',
              'Fig. 12: per row, image a, image b, b warped into a with the F2F motion and '
              'with the GA (online window) motion, and the absolute differences in the '
              'overlap (black outside it).\n']
    return L
