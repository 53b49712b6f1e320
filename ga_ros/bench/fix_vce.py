"""``ga-ros bench nees --fix-vce``: a GNSS whose stated covariance is too small, with and without
the variance factor per fix source.

A lawnmower survey (``--tracks`` swaths of ``--per-swath`` 1 m steps, turning at the ends)
measured by odometry stated right (2 cm and 3 mrad per step, drawn from that covariance) and a
position fix (source ``gnss``) every ``--fix-every`` nodes that states ``--fix-stated`` m per
axis where its true errors are ``--fix-true`` m (a list: one case each; the true factor is
``(true / stated)^2``). The map frame is the fixes' (``datum='fixes'``). Four estimators on the
same draws: ``online`` (track-window aligner, ``variance_components='off'``), ``online vce``
(``'apply'``: the fixes weighted by their source's online factor), ``batch``
(:meth:`~ga_ros.core.window.TrackWindowAligner.refine_batch`, stated covariances) and ``batch
vce`` (the same with the variance components, the fixes one group). Printed per case and
estimator: the mean position NEES over nodes and runs (expected 3) and whether it lies in the
two-sided 95 % band of the run average, the position RMSE against the truth in the map frame
(m, mean over runs), the estimated factor of the fixes (mean over runs) and the process CPU.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.core.quality.variance_components import SourceGroups
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.eval import position_nees
from ga_ros.geometry import se3

ESTIMATORS = ('online', 'online vce', 'batch', 'batch vce')
#: the odometry's covariance per 1 m step, ``[x y z rx ry rz]`` (m^2, rad^2)
C_ODOM = np.diag([0.02 ** 2] * 3 + [0.003 ** 2] * 3)


@dataclass(frozen=True)
class GnssSurvey:
    """The setting of one case (module doc)."""

    tracks: int = 6
    per_swath: int = 30
    fix_every: int = 5
    fix_stated_m: float = 0.5
    fix_true_m: float = 2.0

    @property
    def n(self) -> int:
        """Number of nodes."""
        return self.tracks * self.per_swath

    def truth(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """``(T_world_node (n, 4, 4), steps (n - 1) x (4, 4))`` of the lawnmower (first node at
        the origin, heading +x)."""
        T, steps = [se3.identity()], []
        for i in range(self.n - 1):
            turn = np.pi / 2 if (i % self.per_swath) in (self.per_swath - 2,
                                                         self.per_swath - 1) else 0.0
            steps.append(se3.from_translation_rotvec(np.array([1.0, 0.0, 0.0]),
                                                     np.array([0.0, 0.0, turn])))
            T.append(T[-1] @ steps[-1])
        return np.array(T), steps

    def draw(self, rng: np.random.Generator) -> list[tuple[str, Measurement | FixTerm]]:
        """The inputs of one run in arrival order: ``('m', Measurement)`` (odometry, node i to
        i + 1, stamp i + 1 s, track ``i // per_swath``) and ``('f', FixTerm)`` (a ``gnss``
        position fix right after the measurement that introduces its node)."""
        T_true, steps = self.truth()
        L = np.linalg.cholesky(C_ODOM)
        cov_fix = np.diag([self.fix_stated_m ** 2] * 3 + [-1.0] * 3)
        per = self.per_swath
        out: list = []
        for i in range(self.n - 1):
            T_m = steps[i] @ se3.exp(L @ rng.normal(size=6))
            out.append(('m', Measurement.from_pose(i, i + 1, i // per, (i + 1) // per, T_m,
                                                   C_ODOM, (i + 1) * 10 ** 9)))
            k = i + 1
            if k % self.fix_every == 0:
                p = T_true[k, :3, 3] + rng.normal(0, self.fix_true_m, 3)
                out.append(('f', FixTerm(k, se3.identity(), AbsoluteFix.from_covariance(
                    k * 10 ** 9, se3.from_translation_rotvec(p, np.zeros(3)), cov_fix,
                    'gnss'))))
        return out


def align(sv: GnssSurvey, inputs: list, mode: str, window: int = 2) -> TrackWindowAligner:
    """The track-window aligner (``variance_components=mode``) fed ``inputs`` (
    :meth:`GnssSurvey.draw`), its last track finished."""
    al = TrackWindowAligner(AlignerConfig(window_tracks=window, datum='fixes',
                                          refine_executor='inline', variance_components=mode),
                            T_world_first=sv.truth()[0][0])
    for kind, x in inputs:
        if kind == 'm':
            al.add_measurement(x)
        else:
            al.add_fix(x)
    al.finish_track()
    return al


@dataclass
class FixVceCell:
    """One (case, estimator): per run the mean NEES over nodes, RMSE (m), fix factor; CPU s."""

    nees: list = field(default_factory=list)
    rmse: list = field(default_factory=list)
    factor: list = field(default_factory=list)
    cpu_s: float = 0.0

    def add(self, al: TrackWindowAligner, T_true: np.ndarray) -> None:
        """Record the aligner's corrected path and published covariances."""
        n = T_true.shape[0]
        T = al.corrected_path().T_world_node
        self.nees.append(float(position_nees(T[1:], al.covariances(np.arange(1, n)),
                                             T_true[1:]).mean()))
        self.rmse.append(float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2,
                                                      axis=1)))))


def run_fix_vce(base: GnssSurvey, true_m: list[float], runs: int, seed: int, window: int = 2
                ) -> dict[float, dict[str, FixVceCell]]:
    """The Monte-Carlo of the module doc: ``{true sigma: {estimator: FixVceCell}}`` (the same
    seeds in every case)."""
    out: dict[float, dict[str, FixVceCell]] = {}
    for t in true_m:
        sv = GnssSurvey(base.tracks, base.per_swath, base.fix_every, base.fix_stated_m, t)
        T_true = sv.truth()[0]
        cells = out[t] = {e: FixVceCell() for e in ESTIMATORS}
        for r in range(runs):
            inputs = sv.draw(np.random.default_rng(seed + r))
            t0 = time.process_time()
            on = align(sv, inputs, 'apply', window)
            cells['online vce'].cpu_s += time.process_time() - t0
            cells['online vce'].add(on, T_true)
            f = {c.group: c.factor for c in on.online_variance.components()}
            cells['online vce'].factor.append(f.get('gnss', np.nan))
            on.close()
            t0 = time.process_time()
            off = align(sv, inputs, 'off', window)
            cells['online'].cpu_s += time.process_time() - t0
            cells['online'].add(off, T_true)
            t0 = time.process_time()
            off.refine_batch()
            cells['batch'].cpu_s += time.process_time() - t0
            cells['batch'].add(off, T_true)
            groups = SourceGroups()
            for kind, x in inputs:
                if kind == 'm':
                    groups.add(x)
            t0 = time.process_time()
            off.refine_batch(variance_groups=groups)
            cells['batch vce'].cpu_s += time.process_time() - t0
            cells['batch vce'].add(off, T_true)
            cells['batch vce'].factor.append(off.variance_components.factor('fixes'))
            off.close()
    return out


def fix_vce_lines(base: GnssSurvey, result: dict[float, dict[str, FixVceCell]], runs: int
                  ) -> list[str]:
    """The table of :func:`run_fix_vce`."""
    from scipy.stats import chi2

    lo, hi = (float(chi2.ppf(q, 3 * runs) / runs) for q in (0.025, 0.975))
    out = [f'GNSS stated {base.fix_stated_m:g} m per axis, true noise per case; '
           f'{base.tracks} swaths of {base.per_swath} 1 m steps, a fix every '
           f'{base.fix_every} nodes, odometry stated right; {runs} runs (same seeds per case)',
           f'NEES: mean position NEES over nodes and runs (expected 3; "in": within the 95 % '
           f'band [{lo:.2f}, {hi:.2f}] of a {runs}-run average of one node); RMSE: position '
           "error in the map frame (m, mean over runs); f: the fixes' estimated variance "
           'factor (mean over runs)',
           f'{"true m":>6s} {"truth f":>7s} ' + ' '.join(f'{e:>28s}' for e in ESTIMATORS)]
    for t, cells in result.items():
        row = []
        for e in ESTIMATORS:
            c = cells[e]
            m = float(np.mean(c.nees))
            mark = 'in' if lo <= m <= hi else 'out'
            f = f' f={np.mean(c.factor):.2f}' if c.factor else ''
            row.append(f'{m:6.2f} {mark:3s} {np.mean(c.rmse):5.3f} m{f:>9s}')
        truth = (t / base.fix_stated_m) ** 2
        out.append(f'{t:6.2f} {truth:7.3g} ' + ' '.join(f'{x:>28s}' for x in row))
    cpu = {e: sum(cells[e].cpu_s for cells in result.values()) for e in ESTIMATORS}
    out.append('process CPU s, all cases and runs: ' +
               ', '.join(f'{e} {s:.1f}' for e, s in cpu.items()))
    return out
