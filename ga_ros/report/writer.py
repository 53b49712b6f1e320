"""Run the reproduction and write ``report.md``, ``report.json`` and the PNG plots.

Every number in the report comes from the run that writes it; the only constants in the text are
the paper's own figures, quoted for comparison.
"""

from __future__ import annotations

import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from ga_ros.errors import InputError
from ga_ros.report import plots
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.experiment2 import StereoExperiment, stereo_experiment
from ga_ros.report.experiments.future_tracks import FutureTracksResult, future_tracks
from ga_ros.report.experiments.memory import memory_profile
from ga_ros.report.experiments.policies import policy_seeds
from ga_ros.report.experiments.survey import AerialResult, aerial_window
from ga_ros.report.experiments.table1 import Table1Result, table1
from ga_ros.report.experiments.wrong_connections import wrong_connections
from ga_ros.report.markdown.document import render_markdown
from ga_ros.report.stereo_survey import CACHE_NAME
from ga_ros.safe_write import check_destinations, write_json, write_text

T = TypeVar('T')


@dataclass
class ReproductionResults:
    """What one reproduction run computed, experiment by experiment.

    Attributes
    ----------
    table1 : Table I and Fig. 5.
    future_tracks, future_tracks_positions_only : Fig. 2/3, se3 and positions-only models.
    aerial : the aerial survey with synthetic noise (Figs. 7/8, window versus batch).
    policy_seeds : the policies on several noise draws (JSON-ready dict).
    memory : per-update memory for two survey sizes (JSON-ready dict).
    experiment2 : experiment 2 from rendered stereo; None when ``stereo_tracks`` is 0.
    wrong_connections : the wrong-connection table; None when ``outlier_tracks`` is 0.
    timings : wall-clock seconds per experiment, keys ``<experiment>_s``.
    """

    table1: Table1Result
    future_tracks: FutureTracksResult
    future_tracks_positions_only: FutureTracksResult
    aerial: AerialResult
    policy_seeds: dict
    memory: dict
    experiment2: StereoExperiment | None
    wrong_connections: dict | None
    timings: dict[str, float]


def run_reproduction(cfg: ReproduceConfig, out_dir: str | Path, log=None) -> dict:
    """Run every experiment of ``cfg`` and write DIR/report.md, DIR/report.json and PNGs.

    Parameters
    ----------
    cfg : what to run (see :func:`ga_ros.report.config.preset`).
    out_dir : output directory (created if missing).
    log : optional ``callable(str)`` for progress lines.

    Returns
    -------
    The report as a dict (the content of report.json).
    """
    out = _output_dir(out_dir)
    say = log or (lambda s: None)
    t_start = time.perf_counter()
    res = run_experiments(cfg, out, say)
    images = make_plots(cfg, res, out)
    res.timings['total_s'] = time.perf_counter() - t_start
    report = report_dict(cfg, res, images)
    write_json(out / 'report.json', _jsonable(report), indent=1, allow_nan=False)
    write_text(out / 'report.md', render_markdown(report))
    return report


def _output_dir(out_dir: str | Path) -> Path:
    """The output directory, created if missing; refused when it or its report files cannot
    be written."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f'{out} exists and is not a directory')
    out.mkdir(parents=True, exist_ok=True)
    check_destinations(out / 'report.json', out / 'report.md', out / CACHE_NAME)
    return out


def _timed(timings: dict[str, float], key: str, run: Callable[[], T]) -> T:
    """``run()``, its wall-clock seconds stored in ``timings[key]``."""
    t0 = time.perf_counter()
    value = run()
    timings[key] = time.perf_counter() - t0
    return value


def run_experiments(cfg: ReproduceConfig, out: Path,
                    say: Callable[[str], None]) -> ReproductionResults:
    """Every experiment of ``cfg`` in turn, each timed; experiment 2 caches its VO survey in
    ``out``; progress lines go to ``say``."""
    timings: dict[str, float] = {}
    say(f'Table I: {len(cfg.trajectories)} trajectories x {len(cfg.noise_levels)} noise levels '
        f'x {cfg.runs} runs')
    t1 = _timed(timings, 'table1_s', lambda: table1(cfg))
    say(f'Fig. 2/3: tracks 1..{cfg.fig3_tracks}, {cfg.fig3_runs} run(s) per noise level')
    ft, ft_lin = _timed(timings, 'future_tracks_s', lambda: (
        future_tracks(cfg), future_tracks(cfg, model='linear')))
    say(f'aerial survey: {cfg.aerial_tracks} tracks, batch + online window '
        f'({", ".join(cfg.policies)})')
    ae = _timed(timings, 'aerial_s', lambda: aerial_window(cfg))
    say(f'policies on {cfg.policy_seeds} noise draws of the aerial survey (draw 0 above)')
    ps = _timed(timings, 'policy_seeds_s', lambda: policy_seeds(cfg, ae, say))
    say(f'memory: {cfg.memory_tracks[0]} vs {cfg.memory_tracks[1]} tracks (tracemalloc)')
    mem = _timed(timings, 'memory_s', lambda: memory_profile(cfg))
    exp2 = None
    if cfg.stereo_tracks:
        say(f'experiment 2: rendered stereo, {cfg.stereo_tracks} tracks x '
            f'{2 * cfg.stereo_positions_per_swath} positions, VO + cross-track matching '
            f'(cached in {out / CACHE_NAME}), window + batch')
        exp2 = _timed(timings, 'stereo_s', lambda: stereo_experiment(cfg, out, say))
    outliers = None
    if cfg.outlier_tracks:
        say(f'wrong connections: {cfg.outlier_tracks} tracks, fractions '
            f'{list(cfg.outlier_fractions)}, methods {list(cfg.outlier_methods)}')
        outliers = _timed(timings, 'wrong_connections_s', lambda: wrong_connections(cfg))
    return ReproductionResults(t1, ft, ft_lin, ae, ps, mem, exp2, outliers, timings)


def make_plots(cfg: ReproduceConfig, res: ReproductionResults, out: Path) -> list[str]:
    """Write the PNG plots of ``res`` into ``out``; their file names (those drawn)."""
    ae, exp2 = res.aerial, res.experiment2
    images = [plots.plot_fig5(res.table1, cfg.noise_levels, out),
              plots.plot_fig3(res.future_tracks, res.future_tracks_positions_only, out),
              plots.plot_fig7(ae, out)]
    extra = [plots.plot_fig8(ae, out), plots.plot_quality(ae, out)]
    if exp2 is not None:
        f = exp2.survey.fig12
        extra += [plots.plot_fig7_9(exp2.result, ae, out),
                  plots.plot_fig8(exp2.result, out, 'fig8_exp2_tracks.png'),
                  plots.plot_fig12(exp2.registrations, exp2.summary['fig12'],
                                   f.get('img_a', []), f.get('img_b', []), out),
                  plots.plot_quality(exp2.result, out, 'fig_quality_exp2.png')]
    return images + [x for x in extra if x]


def report_dict(cfg: ReproduceConfig, res: ReproductionResults, images: list[str]) -> dict:
    """The report (the content of report.json, before :func:`_jsonable`): headline figures,
    every experiment's summary, timings, the configuration and the machine."""
    ae = res.aerial
    pol = ae.summary['policies']
    first = cfg.policies[0] if cfg.policies else None
    return {
        'preset': cfg.preset,
        'runs': cfg.runs,
        'improvement_pct': res.table1.improvement_pct,
        'window_vs_batch_gap_pct': {p: v['gap_aligned_pct'] for p, v in pol.items()},
        'window_vs_batch_gap_raw_pct': {p: v['gap_raw_pct'] for p, v in pol.items()},
        'per_track_update_ms': pol[first]['update_ms'] if first in pol else None,
        'table1': res.table1.rows,
        'table1_paper_model': res.table1.paper_model,
        'future_tracks': asdict(res.future_tracks),
        'future_tracks_positions_only': asdict(res.future_tracks_positions_only),
        'aerial': ae.summary,
        'policies': list(cfg.policies),
        'policy_seeds': res.policy_seeds,
        'quality_control': ae.summary.get('quality'),
        'experiment2': None if res.experiment2 is None else res.experiment2.summary,
        'wrong_connections': res.wrong_connections,
        'memory': res.memory,
        'timings_s': res.timings,
        'config': asdict(cfg),
        'machine': {'python': platform.python_version(), 'platform': platform.platform()},
        'images': images,
    }


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None  # strict JSON has no NaN/inf
    return x
