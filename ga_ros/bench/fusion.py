"""``ga-ros bench fusion``: several relative sources of different noise, all stated alike.

Simulated sources (:mod:`ga_ros.sim.sources`) measure every keyframe motion of one weaving path
with their own true noise (``--sources``, percent of the motion) and state the inputs' default
(``--stated``, 5 %). For two and for all the sources, over ``--runs`` Monte-Carlo runs, the
batch adjustment of: each source alone, all fused with the stated covariances (what ga-ros did
before variance components), all fused with a variance factor per source estimated from the
adjustment alone (``fused adj-only``), and with the sources tied by their own consistency
(``fused vce``: :func:`~ga_ros.core.quality.variance_components.solve_with_variance_components`
with the split of :func:`~ga_ros.core.quality.source_consistency.consistency_split`, as the
replay and the aligner run it). Printed:
the mean position RMSE against the truth (raw, first node anchored, and after rigid
alignment), the estimated factors against the true ``(true / stated)^2`` (mean and spread over
the runs beside the mean sigma the estimate states), and the CPU time of the estimation.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ga_ros.core.measurement import variance_group
from ga_ros.core.quality.source_consistency import consistency_split
from ga_ros.core.quality.variance_components import solve_with_variance_components
from ga_ros.core.solver import solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import UsageError
from ga_ros.eval.metrics import trajectory_error
from ga_ros.sim.sources import (
    SourceSpec,
    chained_poses,
    multi_source_survey,
    sources_network,
)


@dataclass
class FusionFigures:
    """Figures of one set of sources (means over the runs).

    Attributes
    ----------
    sources : the sources' names.
    rmse_raw_m, rmse_aligned_m : position RMSE (m) by estimate (``alone <name>``,
        ``fused stated``, ``fused adj-only``, ``fused vce``, ``online stated``, ``online vce``),
        raw (first node
        anchored) and after rigid alignment.
    online_factor_mean : per source, the online factors' mean over the runs.
    factor_true, factor_mean, factor_spread, factor_sigma : per source, the true factor, the
        estimates' mean and standard deviation over the runs and the mean stated sigma.
    vce_cpu_s, plain_cpu_s : process CPU (s) of one fused adjustment with and without the
        estimation (mean over the runs).
    iterations : adjustments of the estimation (mean).
    """

    sources: list[str]
    rmse_raw_m: dict[str, float] = field(default_factory=dict)
    rmse_aligned_m: dict[str, float] = field(default_factory=dict)
    factor_true: dict[str, float] = field(default_factory=dict)
    factor_mean: dict[str, float] = field(default_factory=dict)
    factor_spread: dict[str, float] = field(default_factory=dict)
    factor_sigma: dict[str, float] = field(default_factory=dict)
    online_factor_mean: dict[str, float] = field(default_factory=dict)
    vce_cpu_s: float = 0.0
    plain_cpu_s: float = 0.0
    iterations: float = 0.0


def bench_fusion(sources: tuple[SourceSpec, ...], n_nodes: int, runs: int, seed: int
                 ) -> FusionFigures:
    """The figures of one set of sources (module doc)."""
    fig = FusionFigures([s.name for s in sources])
    raw: dict[str, list[float]] = {}
    ali: dict[str, list[float]] = {}
    est: dict[str, list[float]] = {s.name: [] for s in sources}
    sig: dict[str, list[float]] = {s.name: [] for s in sources}
    cpu_v, cpu_p, its = [], [], []
    online: dict[str, list[float]] = {}

    def record(key: str, T: np.ndarray, T_true: np.ndarray) -> None:
        e = trajectory_error(T[:, :3, 3], T_true[:, :3, 3])
        raw.setdefault(key, []).append(e.ate_raw)
        ali.setdefault(key, []).append(e.ate_aligned)

    for r in range(runs):
        sv = multi_source_survey(np.random.default_rng(seed + r), sources, n_nodes=n_nodes)
        for s in sources:
            mine = sv.of(s.name)
            record(f'alone {s.name}',
                   solve(sources_network(n_nodes, mine), chained_poses(n_nodes, mine),
                         fixed=[0]).T_world_node, sv.T_true)
        ms = list(sv.measurements)
        net, T0 = sources_network(n_nodes, ms), chained_poses(n_nodes, ms)
        t0 = time.process_time()
        plain = solve(net, T0, fixed=[0])
        cpu_p.append(time.process_time() - t0)
        record('fused stated', plain.T_world_node, sv.T_true)
        adj, _ = solve_with_variance_components(net, T0, [variance_group(m) for m in ms],
                                                fixed=[0])
        record('fused adj-only', adj.T_world_node, sv.T_true)
        t0 = time.process_time()
        res, vc = solve_with_variance_components(net, T0, [variance_group(m) for m in ms],
                                                 fixed=[0], split=consistency_split(ms))
        cpu_v.append(time.process_time() - t0)
        its.append(vc.iterations)
        record('fused vce', res.T_world_node, sv.T_true)
        for c in vc.components:
            est[c.group].append(c.factor)
            sig[c.group].append(c.sigma)
        in_order = sorted(ms, key=lambda m: (m.dst_id, m.src_id))
        for name, mode in (('online stated', 'off'), ('online vce', 'apply')):
            al = TrackWindowAligner(AlignerConfig(variance_components=mode,
                                                  refine_executor='inline'))
            al.add_measurements(in_order)
            al.finish_track()
            record(name, al.corrected_path().T_world_node, sv.T_true)
            if al.online_variance is not None:
                for c in al.online_variance.components():
                    online.setdefault(c.group, []).append(c.factor)
            al.close()
    fig.rmse_raw_m = {k: float(np.mean(v)) for k, v in raw.items()}
    fig.rmse_aligned_m = {k: float(np.mean(v)) for k, v in ali.items()}
    for s in sources:
        fig.factor_true[s.name] = s.true_factor
        fig.factor_mean[s.name] = float(np.mean(est[s.name]))
        fig.factor_spread[s.name] = float(np.std(est[s.name], ddof=1)) if runs > 1 else 0.0
        fig.factor_sigma[s.name] = float(np.mean(sig[s.name]))
        fig.online_factor_mean[s.name] = float(np.mean(online.get(s.name, [np.nan])))
    fig.vce_cpu_s, fig.plain_cpu_s = float(np.mean(cpu_v)), float(np.mean(cpu_p))
    fig.iterations = float(np.mean(its))
    return fig


def figure_lines(fig: FusionFigures, n_nodes: int, runs: int) -> list[str]:
    """The printed table of one set of sources."""
    lines = [f'{len(fig.sources)} sources ({", ".join(fig.sources)}), {n_nodes} keyframes, '
             f'mean of {runs} runs: position RMSE against the truth, m (raw: first node '
             'anchored / after rigid alignment)']
    for k in fig.rmse_raw_m:
        lines.append(f'  {k:<14} {fig.rmse_raw_m[k]:8.3f} / {fig.rmse_aligned_m[k]:.3f}')
    best = min(v for k, v in fig.rmse_raw_m.items() if k.startswith('alone'))
    lines.append(f'  fused vce / best alone (raw): {fig.rmse_raw_m["fused vce"] / best:.2f}; '
                 f'fused stated / best alone: {fig.rmse_raw_m["fused stated"] / best:.2f}')
    lines.append(f'  online vce / best alone (raw): {fig.rmse_raw_m["online vce"] / best:.2f}; '
                 f'online stated / best alone: {fig.rmse_raw_m["online stated"] / best:.2f}')
    lines.append('  variance factor (estimated / stated variance): true, estimated mean +- '
                 'spread over the runs (mean stated sigma); online mean')
    for s in fig.sources:
        lines.append(f'  {s:<14} {fig.factor_true[s]:.3f}  {fig.factor_mean[s]:.3f} +- '
                     f'{fig.factor_spread[s]:.3f} ({fig.factor_sigma[s]:.3f}); '
                     f'estimated / true {fig.factor_mean[s] / fig.factor_true[s]:.2f}; online '
                     f'{fig.online_factor_mean[s]:.3f} '
                     f'({fig.online_factor_mean[s] / fig.factor_true[s]:.2f} x true)')
    lines.append(f'  CPU per fused adjustment: {fig.vce_cpu_s:.2f} s with the estimation '
                 f'({fig.iterations:.1f} adjustments), {fig.plain_cpu_s:.2f} s without')
    return lines


def parse_sources(text: str, stated: float) -> tuple[SourceSpec, ...]:
    """``'1,4,2'`` -> sources ``odom0..`` with those true percentages."""
    try:
        pcts = [float(x) for x in text.split(',') if x.strip()]
    except ValueError:
        raise UsageError(f'--sources: comma-separated percentages, got {text!r}') from None
    if len(pcts) < 2 or min(pcts) <= 0:
        raise UsageError('--sources: at least two positive percentages')
    return tuple(SourceSpec(f'odom{k}', p, stated) for k, p in enumerate(pcts))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='ga-ros bench fusion', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument('--sources', default='1,4,2',
                    help='true noise of each source, %% of the motion (default 1,4,2); the '
                    'first two alone, then all')
    ap.add_argument('--stated', type=float, default=5.0,
                    help="the noise every source states, %% (default 5: the inputs' default)")
    ap.add_argument('--nodes', type=int, default=300, help='keyframes (300)')
    ap.add_argument('--runs', type=int, default=4, help='Monte-Carlo runs (4)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    sources = parse_sources(args.sources, args.stated)
    sets = [sources[:2]] + ([sources] if len(sources) > 2 else [])
    figs = [bench_fusion(s, args.nodes, args.runs, args.seed) for s in sets]
    if args.json:
        print(json.dumps([asdict(f) for f in figs]))
        return 0
    for f in figs:
        print('\n'.join(figure_lines(f, args.nodes, args.runs)))
    return 0
