"""Table I and Fig. 5 (Sec. V-A): F2F vs GA on the synthetic trajectories.

The mean position error of F2F and of the batch GA on the four synthetic trajectories at each
noise level, ``runs`` Monte-Carlo runs each, with the se3 model and (``paper_model_runs``) the
paper's position model (eq. 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.eval.metrics import improvement_pct, position_errors
from ga_ros.geometry import se3
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.seeds import (
    EXP_PAPER_MODEL,
    EXP_TABLE1,
    FAMILIES,
    noise_key,
    run_rng,
)
from ga_ros.sim.noise import NoiseModel, perturb
from ga_ros.sim.scenario import Scenario
from ga_ros.sim.trajectories import synthetic_scenario


@dataclass
class SyntheticRun:
    """Per-node position errors (m) of one Monte-Carlo run."""

    f2f: FloatArray
    ga: FloatArray
    converged: bool
    iterations: int
    n_equations: int
    n_observations: int
    n_unknowns: int


def synthetic_run(sc: Scenario, percent: float, rng: np.random.Generator,
                  model: str = 'se3') -> SyntheticRun:
    """One run: noisy motions, F2F from the known first pose, GA (batch, first node fixed)."""
    noise = NoiseModel(percent, sc.depth_m)
    nm = perturb(sc.true_motions(model), noise, rng, model='se3' if model == 'se3' else 'paper')
    if model == 'se3':
        T0 = sc.f2f(nm.z)
    else:
        T0 = se3.identity(sc.n_nodes)
        T0[:, :3, 3] = sc.f2f_positions(nm.z, model)
    # the paper model's rotation acts on world coordinates (hundreds of m), so its corrections
    # converge linearly near the end: a looser tolerance (1e-6 m) and more iterations
    scfg = SolverConfig() if model == 'se3' else SolverConfig(model=model, max_iterations=50,
                                                                tolerance=1e-6)
    res = solve(sc.network(nm.z, nm.cov), T0, scfg)
    return SyntheticRun(position_errors(T0, sc.T_world_node),
                        position_errors(res.T_world_node, sc.T_world_node), res.converged,
                        res.iterations, res.n_equations, res.n_observations, res.n_unknowns)


@dataclass
class Table1Result:
    rows: list[dict]
    improvement_pct: dict[str, dict[str, float]]
    profiles: dict[str, dict[str, FloatArray]] = field(default_factory=dict)
    paper_model: list[dict] = field(default_factory=list)


def table1(cfg: ReproduceConfig) -> Table1Result:
    """Table I and Fig. 5: mean position error of F2F and GA per trajectory and noise level."""
    rows: list[dict] = []
    improvement: dict[str, dict[str, float]] = {}
    profiles: dict[str, dict[str, FloatArray]] = {}
    paper_rows: list[dict] = []
    for name in cfg.trajectories:
        j = FAMILIES.index(name.split('_')[0])
        sc = synthetic_scenario(name)
        improvement[name] = {}
        for i, pct in enumerate(cfg.noise_levels):
            runs = [synthetic_run(sc, pct, run_rng(cfg.seed, EXP_TABLE1, j, i, r))
                    for r in range(cfg.runs)]
            f2f = np.array([r.f2f.mean() for r in runs])
            ga = np.array([r.ga.mean() for r in runs])
            imp = improvement_pct(float(f2f.mean()), float(ga.mean()))
            improvement[name][noise_key(pct)] = imp
            rows.append({
                'trajectory': name, 'noise_pct': pct, 'runs': cfg.runs,
                'nodes': sc.n_nodes, 'connections': sc.n_connections,
                'equations': runs[0].n_equations, 'observations': runs[0].n_observations,
                'unknowns': runs[0].n_unknowns,
                'paper_equations': 3 * sc.n_connections,
                'paper_observations': 6 * sc.n_connections,
                'paper_unknowns': 3 * (sc.n_nodes - 1),
                'f2f_mean_m': float(f2f.mean()), 'ga_mean_m': float(ga.mean()),
                'ga_std_m': float(ga.std()),
                'f2f_mse_m2': float(np.mean([np.mean(r.f2f ** 2) for r in runs])),
                'ga_mse_m2': float(np.mean([np.mean(r.ga ** 2) for r in runs])),
                'improvement_pct': imp,
                'converged': int(sum(r.converged for r in runs)),
                'mean_iterations': float(np.mean([r.iterations for r in runs])),
            })
            if pct == cfg.profile_noise:
                profiles[name] = {'f2f': np.mean([r.f2f for r in runs], axis=0),
                                  'ga': np.mean([r.ga for r in runs], axis=0)}
            if cfg.paper_model_runs:
                pr = [synthetic_run(sc, pct, run_rng(cfg.seed, EXP_PAPER_MODEL, j, i, r),
                                    model='paper') for r in range(cfg.paper_model_runs)]
                pf = float(np.mean([r.f2f.mean() for r in pr]))
                pg = float(np.mean([r.ga.mean() for r in pr]))
                paper_rows.append({
                    'trajectory': name, 'noise_pct': pct, 'runs': cfg.paper_model_runs,
                    'equations': pr[0].n_equations, 'observations': pr[0].n_observations,
                    'unknowns': pr[0].n_unknowns, 'f2f_mean_m': pf, 'ga_mean_m': pg,
                    'improvement_pct': improvement_pct(pf, pg),
                    'converged': int(sum(r.converged for r in pr)),
                })
    return Table1Result(rows, improvement, profiles, paper_rows)
