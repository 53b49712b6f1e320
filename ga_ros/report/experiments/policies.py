"""The freeze policies compared on several noise draws of the aerial survey.

:func:`policy_seeds` runs every policy on ``ReproduceConfig.policy_seeds`` noise draws and
:func:`policy_statistics` compares each with the reference (weighted) by the paired difference
of their gaps to batch on the same draws (:func:`paired_difference`: mean, sd, t interval).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.seeds import EXP_AERIAL, run_rng
from ga_ros.report.experiments.survey import (
    AerialResult,
    ates,
    batch_solve,
    gaps_pct,
    run_aligner,
    window_available,
)
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb
from ga_ros.sim.scenario import Scenario


def policy_gaps(cfg: ReproduceConfig, sc: Scenario, z: FloatArray,
                cov: FloatArray) -> dict[str, dict[str, float]]:
    """Gap to batch (%) at the end of the survey of every policy of ``cfg.policies`` on one
    noise draw: the measured motions ``z`` (m, 6) with covariances ``cov`` (m, 6, 6) fed track by
    track into the window (no snapshots, no final refinement), against the batch GA of the same
    motions. The same numbers as :func:`survey_window`'s ``gap_raw_pct`` / ``gap_aligned_pct``,
    without the rest of its figures. A policy with the background refinement runs it inline
    (``'<policy>+inline'``): the same path bit for bit as the other executors (the hand-off
    depends on track counts only), without a worker process started per draw. Keys per
    policy: ``raw``, ``aligned`` (%)."""
    f2f = sc.f2f(z)
    b = ates(batch_solve(sc.network(z, cov), f2f).T_world_node, sc.T_world_node)
    out = {}
    for policy in cfg.policies:
        base, _, executor = policy.partition('+')
        run_as = f'{base}+inline' if executor else base
        path = run_aligner(sc, z, cov, run_as, cfg.window_tracks, set(), f2f,
                           final_refine=False)['path']
        g = gaps_pct(ates(path, sc.T_world_node), b)
        out[policy] = {'raw': g['gap_raw_pct'], 'aligned': g['gap_aligned_pct']}
    return out


@dataclass(frozen=True)
class PairedDifference:
    """Paired difference ``d_r = x_r - ref_r`` of two methods on the same ``n`` draws.

    Attributes
    ----------
    n : number of draws.
    mean, sd : mean and sample standard deviation (``ddof=1``; NaN for ``n = 1``) of ``d``,
        in the unit of ``x`` (here percentage points of gap to batch).
    ci_low, ci_high : two-sided Student-t confidence interval of the mean difference,
        ``mean -+ t(1/2 + confidence/2, n - 1) sd / sqrt(n)`` (NaN for ``n = 1``).
    confidence : level of the interval (0.95: 95 %).
    """

    n: int
    mean: float
    sd: float
    ci_low: float
    ci_high: float
    confidence: float

    @property
    def worse(self) -> bool:
        """``x`` is significantly larger than ``ref`` (the whole interval above 0)."""
        return bool(self.ci_low > 0.0)

    @property
    def better(self) -> bool:
        """``x`` is significantly smaller than ``ref`` (the whole interval below 0)."""
        return bool(self.ci_high < 0.0)


def paired_difference(x: FloatArray, ref: FloatArray,
                      confidence: float = 0.95) -> PairedDifference:
    """Mean, sd and t confidence interval of ``x - ref`` over paired draws (same noise draw in
    ``x[r]`` and ``ref[r]``): the draw's own difficulty, shared by both, cancels.

    Parameters
    ----------
    x, ref : (n,) finite values of the two methods, draw by draw.
    confidence : two-sided level of the interval, in (0, 1).

    Raises
    ------
    InputError : shapes differ, no draw, a non-finite value, or ``confidence`` outside (0, 1).
    """
    from scipy.stats import t as student_t

    x, ref = np.asarray(x, dtype=float), np.asarray(ref, dtype=float)
    if x.shape != ref.shape or x.ndim != 1 or x.size == 0:
        raise InputError(f'paired values must be two (n,) arrays, n >= 1; got {x.shape} and '
                         f'{ref.shape}')
    if not (np.isfinite(x).all() and np.isfinite(ref).all()):
        raise InputError('paired values must be finite; drop the failed draws first')
    if not 0.0 < confidence < 1.0:
        raise InputError(f'confidence must be in (0, 1), got {confidence}')
    d = x - ref
    n = d.size
    if n < 2:
        nan = float('nan')
        return PairedDifference(1, float(d[0]), nan, nan, nan, confidence)
    sd = float(d.std(ddof=1))
    half = float(student_t.ppf(0.5 + confidence / 2, n - 1)) * sd / np.sqrt(n)
    mean = float(d.mean())
    return PairedDifference(n, mean, sd, mean - half, mean + half, confidence)


def policy_statistics(gaps: dict[str, dict[str, list[float]]], reference: str,
                      confidence: float = 0.95) -> dict:
    """Multi-draw comparison of freeze policies (issue 15: "no policy worse than weighted").

    Parameters
    ----------
    gaps : per policy, ``{'raw': [...], 'aligned': [...]}``: the gap to batch (%) on each noise
        draw, the draws in the same order for every policy.
    reference : the policy the others are compared with (a key of ``gaps``).
    confidence : level of the paired intervals.

    Returns
    -------
    JSON-ready dict: ``reference``, ``confidence``, ``n`` (draws), ``policies`` (per policy:
    ``raw`` / ``aligned`` with the per-draw ``values``, their ``mean`` and ``sd``; and for every
    policy but the reference ``vs_reference``: per metric the :class:`PairedDifference` fields,
    ``worse`` and ``better``; ``worse``: either metric significantly worse) and ``worse`` (the
    policies significantly worse than the reference on either metric).
    """
    if reference not in gaps:
        raise InputError(f'reference policy {reference!r} is not among {sorted(gaps)}')
    ref = gaps[reference]
    out: dict = {'reference': reference, 'confidence': confidence,
                 'n': len(ref['raw']), 'policies': {}, 'worse': []}
    for policy, g in gaps.items():
        row: dict = {}
        for metric in ('raw', 'aligned'):
            v = np.asarray(g[metric], dtype=float)
            row[metric] = {'values': v.tolist(), 'mean': float(v.mean()),
                           'sd': float(v.std(ddof=1)) if v.size > 1 else float('nan')}
        if policy != reference:
            vs = {}
            for metric in ('raw', 'aligned'):
                d = paired_difference(g[metric], ref[metric], confidence)
                vs[metric] = {**asdict(d), 'worse': d.worse, 'better': d.better}
            vs['worse'] = vs['raw']['worse'] or vs['aligned']['worse']
            row['vs_reference'] = vs
            if vs['worse']:
                out['worse'].append(policy)
        out['policies'][policy] = row
    return out


def policy_seeds(cfg: ReproduceConfig, first: AerialResult | None = None, log=None) -> dict:
    """The freeze policies on ``cfg.policy_seeds`` independent noise draws of the aerial survey
    (draw ``r`` from ``run_rng(cfg.seed, EXP_AERIAL, r)``; draw 0 is the one of
    :func:`aerial_window`, whose gaps are taken from ``first`` when given), with
    :func:`policy_statistics` against ``'weighted'`` (else the first policy).

    Returns
    -------
    JSON-ready dict: ``available`` (False without the window aligner or policies), ``draws``
    (the ``r`` keys), ``tracks``, ``noise_pct``, ``seconds`` and the keys of
    :func:`policy_statistics`.
    """
    if not window_available() or not cfg.policies:
        return {'available': False}
    say = log or (lambda s: None)
    t0 = time.perf_counter()
    sc = aerial_scenario(cfg.aerial_tracks, cfg.aerial_positions_per_swath)
    gaps: dict[str, dict[str, list[float]]] = {p: {'raw': [], 'aligned': []}
                                               for p in cfg.policies}
    for r in range(cfg.policy_seeds):
        if r == 0 and first is not None:
            pol = {p: {'raw': v['gap_raw_pct'], 'aligned': v['gap_aligned_pct']}
                   for p, v in first.summary['policies'].items()}
        else:
            say(f'  policy comparison: noise draw {r + 1}/{cfg.policy_seeds}')
            nm = perturb(sc.true_motions(), NoiseModel(cfg.aerial_noise, sc.depth_m),
                         run_rng(cfg.seed, EXP_AERIAL, r))
            pol = policy_gaps(cfg, sc, nm.z, nm.cov)
        for p in cfg.policies:
            gaps[p]['raw'].append(pol[p]['raw'])
            gaps[p]['aligned'].append(pol[p]['aligned'])
    reference = 'weighted' if 'weighted' in cfg.policies else cfg.policies[0]
    stats = policy_statistics(gaps, reference)
    return {'available': True, 'draws': list(range(cfg.policy_seeds)),
            'tracks': cfg.aerial_tracks, 'noise_pct': cfg.aerial_noise,
            'seconds': time.perf_counter() - t0, **stats}
