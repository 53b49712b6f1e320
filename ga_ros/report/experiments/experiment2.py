"""Experiment 2 (Sec. V-B) from rendered stereo: our VO's motions through the window and batch.

The VO survey itself (rendering, VO, cross-track matching, cache) is
:mod:`ga_ros.report.stereo_survey`; here it goes through :func:`~ga_ros.report.experiments.
survey.survey_window`, with the VO's NEES and Fig. 12's registration of neighbouring swaths.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ga_ros.geometry import se3
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.survey import AerialResult, survey_window
from ga_ros.report.stereo_survey import (
    CACHE_NAME,
    Registration,
    StereoSurveyConfig,
    VoSurvey,
    ground_homography,
    register_pair,
    render_vo_survey,
)


@dataclass
class StereoExperiment:
    """Experiment 2 from rendered stereo: the VO survey, its window / batch results and the
    Fig. 12 registrations."""

    survey: VoSurvey
    result: AerialResult
    summary: dict
    registrations: list[dict[str, Registration]]


def stereo_experiment(cfg: ReproduceConfig, out_dir: Path | None = None,
                      log=None) -> StereoExperiment:
    """The paper's experiment 2 as the paper ran it: motions (consecutive and cross-track) from
    rendered 320x240 stereo by our VO with its own covariances (:func:`render_vo_survey`,
    cached in ``out_dir``), then F2F, the track window (every policy of ``cfg.policies``) and
    batch GA (:func:`survey_window`), the VO's covariance consistency (NEES of the motions),
    and Fig. 12: images of neighbouring swaths registered with the relative motion of F2F, of
    the VO's own cross-track measurement, of the window, of the batch and of the truth."""
    scfg = StereoSurveyConfig(n_tracks=cfg.stereo_tracks,
                              positions_per_swath=cfg.stereo_positions_per_swath)
    cache = None if out_dir is None else Path(out_dir) / CACHE_NAME
    t0 = time.perf_counter()
    vs = render_vo_survey(scfg, cache, log)
    vo_s = time.perf_counter() - t0
    sc = vs.scenario()
    sub = replace(cfg, fig8_tracks=cfg.stereo_fig8_tracks)
    res = survey_window(sub, sc, vs.z, vs.cov)
    nees = vs.nees()
    summary = {
        'survey': {'tracks': scfg.n_tracks, 'positions_per_swath': scfg.positions_per_swath,
                   'step_m': scfg.step_m, 'image_size': f'{scfg.width}x{scfg.height}',
                   'median_depth_m': vs.depth_m, **vs.stats},
        'seconds_this_run': vo_s, 'cached': bool(cache is not None and vo_s < 0.5 * vs.stats[
            'seconds']['total']),
        'nees': nees, **res.summary}
    regs: list[dict[str, Registration]] = []
    f = vs.fig12
    first = f'window_{cfg.policies[0]}' if cfg.policies else 'batch'
    est = {'f2f': res.paths['f2f'], 'window': res.paths.get(first, res.paths['batch']),
           'batch': res.paths['batch'], 'truth': vs.T_true}
    rows = []
    for j, (a, b) in enumerate(zip(f.get('a', []), f.get('b', []))):
        a, b = int(a), int(b)
        h = f['plane'][j]
        reg: dict[str, Registration] = {}
        for name, T in est.items():
            H = ground_homography(vs.K, T[a], T[b], h)
            reg[name] = register_pair(f['img_a'][j], f['img_b'][j], H)
        k = int(np.nonzero((vs.src == a) & (vs.dst == b))[0][0])
        T_a = est['window'][a]
        T_b = T_a @ se3.from_translation_rotvec(vs.z[k, :3], vs.z[k, 3:])
        reg['measured'] = register_pair(f['img_a'][j], f['img_b'][j],
                                        ground_homography(vs.K, T_a, T_b, h))
        regs.append(reg)
        rows.append({'node_a': a, 'node_b': b, 'swath_a': int(vs.swath[a]),
                     'swath_b': int(vs.swath[b]),
                     'plane_height_m': float(f['plane_height_m'][j]),
                     'plane_slope_deg': float(np.degrees(np.arccos(np.clip(h[2], -1, 1)))),
                     **{f'{n}_{m}': getattr(r, m) for n, r in reg.items()
                        for m in ('overlap', 'mean_abs_diff', 'ncc')}})
    summary['fig12'] = rows
    return StereoExperiment(vs, res, summary, regs)
