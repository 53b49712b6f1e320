"""``ga-ros bench nees --vce``: position NEES over a Monte-Carlo whose stated covariances are
wrong, with and without variance components.

An aerial survey (:func:`ga_ros.sim.aerial.aerial_scenario`) gets noise at ``--noise`` percent
of the true motion on every connection (:mod:`ga_ros.sim.noise`). The covariances its
consecutive motions (the odometry, group ``motion``) state are wrong in four cases:

* ``right``: stated as they are;
* ``small``: 4x too small (the stated sigmas 2x);
* ``large``: 4x too large;
* ``bias``: stated right, but every consecutive motion also carries a constant yaw bias of
  ``--bias-sigmas`` of its yaw sigma (a systematic error the white-noise model does not have);

the cross-track connections always state theirs right. Four estimators on the same draws:
``batch`` (:func:`~ga_ros.core.solver.solve`, stated covariances), ``batch vce``
(:func:`~ga_ros.core.quality.variance_components.solve_with_variance_components`, factors
applied), ``online`` (the track-window aligner, ``variance_components='off'``) and ``online
vce`` (``'apply'``). Printed per case and estimator: the mean position NEES (over nodes of the
run-averaged NEES; expected 3), whether it lies in the two-sided 95 % band of the run average
(``chi2(3 M) / M`` quantiles, ``M`` runs), the share of nodes whose run average is in that band
(95 % expected), and the estimated factor of ``motion`` (truth: 4, 1/4, 1, -).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from ga_ros.core.measurement import variance_group
from ga_ros.core.quality.variance_components import solve_with_variance_components
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.eval import position_nees
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

CASES = {'right': 1.0, 'small': 1 / 4, 'large': 4.0, 'bias': 1.0}  # stated / true variance
ESTIMATORS = ('batch', 'batch vce', 'online', 'online vce')


@dataclass
class VceCell:
    """One (case, estimator): per-run NEES per node, the motion factor per run, CPU s."""

    nees: list = field(default_factory=list)
    factor: list = field(default_factory=list)
    cpu_s: float = 0.0

    def mean(self) -> float:
        """Mean over nodes of the run-averaged NEES."""
        return float(np.mean(np.stack(self.nees)))

    def share_in_band(self, band: tuple[float, float]) -> float:
        """Share of the nodes whose run-averaged NEES lies in ``band``."""
        avg = np.stack(self.nees).mean(axis=0)
        return float(np.mean((avg >= band[0]) & (avg <= band[1])))


def band95(runs: int, dof: int = 3) -> tuple[float, float]:
    """Two-sided 95 % band of the average of ``runs`` independent ``chi2(dof)`` NEES values."""
    return (float(chi2.ppf(0.025, dof * runs) / runs), float(chi2.ppf(0.975, dof * runs) / runs))


def run_vce_nees(tracks: int, per_swath: int, percent: float, runs: int, window: int,
                 seed: int, bias_sigmas: float = 1.0, cases=tuple(CASES)
                 ) -> dict[str, dict[str, VceCell]]:
    """The Monte-Carlo of the module doc: ``{case: {estimator: VceCell}}``."""
    sc = aerial_scenario(n_tracks=tracks, positions_per_swath=per_swath)
    ids, truth = sc.node_ids[1:], sc.T_world_node[1:]
    cons = sc.consecutive
    scfg = SolverConfig(tolerance=1e-8, max_iterations=50)
    out = {c: {e: VceCell() for e in ESTIMATORS} for c in cases}
    for r in range(runs):
        for case in cases:
            rng = np.random.default_rng(seed + r)  # the same noise draw in every case
            nm = perturb(sc.true_motions(), NoiseModel(percent, sc.depth_m), rng)
            z, cov = nm.z.copy(), nm.cov.copy()
            cov[cons] *= CASES[case]
            if case == 'bias':
                z[cons, 5] += bias_sigmas * np.sqrt(nm.cov[cons, 5, 5])
            ms = sc.measurements(z, cov)
            net, T0 = sc.network(z, cov), sc.f2f(z)
            cells = out[case]
            t0 = time.process_time()
            b = solve(net, T0, scfg)
            cells['batch'].nees.append(position_nees(b.T_world_node[1:], b.covariance(ids),
                                                     truth))
            cells['batch'].cpu_s += time.process_time() - t0
            t0 = time.process_time()
            groups = ['motion' if c else 'cross' for c in cons]
            v, vc = solve_with_variance_components(net, T0, groups, scfg)
            cells['batch vce'].nees.append(position_nees(v.T_world_node[1:], v.covariance(ids),
                                                         truth))
            cells['batch vce'].factor.append(vc.factor('motion'))
            cells['batch vce'].cpu_s += time.process_time() - t0
            for name, mode in (('online', 'off'), ('online vce', 'apply')):
                t0 = time.process_time()
                al = TrackWindowAligner(AlignerConfig(window_tracks=window,
                                                      variance_components=mode,
                                                      refine_executor='inline'),
                                        sc.T_world_node[0])
                al.add_measurements(ms)
                al.finish_track()
                path = al.corrected_path()
                cells[name].nees.append(position_nees(path.T_world_node[1:],
                                                      al.covariances(ids), truth))
                if al.online_variance is not None:
                    f = {c.group: c.factor for c in al.online_variance.components()}
                    cells[name].factor.append(f.get(variance_group(ms[0]), np.nan))
                cells[name].cpu_s += time.process_time() - t0
                al.close()
    return out


def vce_lines(result: dict[str, dict[str, VceCell]], runs: int) -> list[str]:
    """The table of :func:`run_vce_nees`."""
    lo, hi = band95(runs)
    out = [f'mean position NEES (expected 3; 95 % band of the {runs}-run average '
           f'[{lo:.2f}, {hi:.2f}]): "in" = the mean lies in the band, then the share of nodes '
           'whose run average does; f = estimated motion factor (mean over runs)',
           f'{"case":6s} {"truth f":>7s} ' + ' '.join(f'{e:>24s}' for e in ESTIMATORS)]
    for case, cells in result.items():
        truth = '-' if case == 'bias' else f'{1 / CASES[case]:.3g}'
        row = []
        for e in ESTIMATORS:
            c = cells[e]
            m = c.mean()
            mark = 'in' if lo <= m <= hi else 'out'
            f = f' f={np.mean(c.factor):.2f}' if c.factor else ''
            row.append(f'{m:6.2f} {mark:3s} {100 * c.share_in_band((lo, hi)):3.0f}%{f:>8s}')
        out.append(f'{case:6s} {truth:>7s} ' + ' '.join(f'{x:>24s}' for x in row))
    cpu = {e: sum(cells[e].cpu_s for cells in result.values()) for e in ESTIMATORS}
    out.append('process CPU s, all cases and runs: ' +
               ', '.join(f'{e} {s:.1f}' for e, s in cpu.items()))
    return out
