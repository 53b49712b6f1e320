"""Wrong cross-track connections: how well each defence rejects them (issue 15, item 5).

A reduced aerial survey (:func:`ga_ros.sim.aerial.aerial_scenario`) is simulated with Gaussian
motion noise; a fraction of its cross-track (overlap) connections is replaced by gross errors,
half in translation (a random direction, ``--gross-m`` metres) and half in rotation (a random
axis, ``--gross-deg`` degrees), applied as a right perturbation of the measured motion. Each
defence is run on the clean and on the contaminated survey:

* ``ls``: batch least squares, no defence;
* ``oracle``: batch least squares without the wrong connections (the best any defence can do);
* ``gate``: the track-window aligner's chi-square gate on the Mahalanobis misclosure of cross
  connections (``AlignerConfig.outlier_chi2_prob``), online, window of 5 tracks;
* ``gate-w``: the same aligner with ``gate='w-test'``: data snooping with Baarda's w-test over
  the window's cross connections after each update (level ``--alpha0``);
* ``snoop-w`` / ``snoop-conn``: batch iterative data snooping
  (:func:`ga_ros.core.quality.data_snooping`) with the 1-D w-test or the 6-D connection test;
* ``huber`` / ``cauchy``: batch robust losses (``SolverConfig.robust_loss``); a connection
  counts as rejected when its final Mahalanobis misclosure exceeds the gate's threshold.

Printed per fraction and method: recall (wrong connections rejected), precision, share of good
connections rejected, ATE after rigid alignment and its change against the clean run of the
same family (batch LS clean for the batch methods, the same gated window on clean data for
``gate`` and ``gate-w``), and for the online methods the per-track update time and the time of
the quality control of its final adjustment (``AlignerConfig.quality``), p50 / p95 ms. The update
time does not include that final quality control; for ``gate-w`` it includes the ones the gate
runs after each re-adjustment.

Run ``python -m ga_ros.bench.outliers`` (``--help`` for the options).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from ga_ros.arrays import BoolArray, FloatArray
from ga_ros.bench.survey import noisy_survey
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.quality import QualityConfig, data_snooping, quality_control
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.solver.losses import ROBUST_LOSSES
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.eval.metrics import ate
from ga_ros.geometry import se3
from ga_ros.runtime import limit_blas_threads
from ga_ros.sim.scenario import Scenario

#: The robust losses of the solver's registry, each a method of its own.
LOSS_METHODS = tuple(name for name in ROBUST_LOSSES if name != 'none')
METHODS = ('ls', 'oracle', 'gate', 'gate-w', 'snoop-w', 'snoop-conn', *LOSS_METHODS)
ONLINE = ('gate', 'gate-w')
GATE_PROB = AlignerConfig().outlier_chi2_prob


@dataclass(frozen=True)
class Outcome:
    """One method on one survey: which connections it rejected and the trajectory error."""

    method: str
    rejected: BoolArray
    ate_m: float
    seconds: float
    update_ms: FloatArray | None = None
    quality_ms: FloatArray | None = None


def inject(sc: Scenario, z: FloatArray, fraction: float, gross_m: tuple[float, float],
           gross_deg: tuple[float, float], rng: np.random.Generator) -> tuple[FloatArray,
                                                                              BoolArray]:
    """Replace ``fraction`` of the cross-track connections by gross errors.

    Returns the contaminated ``z`` (m, 6) and the mask of the wrong connections.
    """
    cross = np.nonzero(~sc.consecutive)[0]
    k = int(round(fraction * cross.size))
    bad = np.zeros(len(z), dtype=bool)
    if k == 0:
        return z.copy(), bad
    pick = rng.choice(cross, size=k, replace=False)
    bad[pick] = True
    axis = rng.normal(size=(k, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    xi = np.zeros((k, 6))
    rot = np.arange(k) % 2 == 1
    xi[~rot, :3] = axis[~rot] * rng.uniform(*gross_m, size=(~rot).sum())[:, None]
    xi[rot, 3:] = axis[rot] * np.radians(rng.uniform(*gross_deg, size=rot.sum()))[:, None]
    T_meas = se3.from_translation_rotvec(z[pick, :3], z[pick, 3:]) @ se3.exp(xi)
    out = z.copy()
    out[pick] = se3.to_translation_rotvec(T_meas)
    return out, bad


def misclosure_rejected(net: ConnectionNetwork, T: FloatArray, prob: float) -> BoolArray:
    """Connections whose Mahalanobis misclosure at ``T`` exceeds ``chi2_6(prob)``."""
    c = net.arrays()
    T_meas = se3.from_translation_rotvec(c.z[:, :3], c.z[:, 3:])
    e = se3.log(se3.inverse(T_meas) @ se3.inverse(T[c.src]) @ T[c.dst])
    maha2 = np.einsum('mi,mij,mj->m', e, np.linalg.inv(c.cov), e)
    return maha2 > chi2.ppf(prob, 6)


def run_method(method: str, sc: Scenario, z: FloatArray, cov: FloatArray, bad: BoolArray,
               snoop_alpha0: float, per_iteration: int) -> Outcome:
    """Run one defence on the survey with measurements ``z`` (``bad``: the wrong ones, used by
    the oracle only)."""
    t0 = time.perf_counter()
    net = sc.network(z, cov)
    T0 = sc.f2f(z)
    rejected = np.zeros(len(z), dtype=bool)
    update_ms = quality_ms = None
    if method == 'ls':
        T = solve(net, T0).T_world_node
    elif method == 'oracle':
        c = net.arrays()
        keep = ~bad
        sub = ConnectionNetwork.from_arrays(net.node_ids, net.track_ids, c.src[keep],
                                            c.dst[keep], c.z[keep], c.cov[keep])
        T = solve(sub, T0).T_world_node
        rejected = bad.copy()
    elif method in ONLINE:
        cfg = AlignerConfig(gate='w-test' if method == 'gate-w' else 'chi2',
                            quality_alpha0=snoop_alpha0, quality=True)
        aligner = TrackWindowAligner(cfg, T_world_first=sc.T_world_node[0])
        meas = sc.measurements(z, cov)
        track_of_dst = np.array([m.dst_track for m in meas])
        ups = []
        for k, m in enumerate(meas):
            aligner.add_measurement(m)
            if k + 1 == len(meas) or track_of_dst[k + 1] != track_of_dst[k]:
                ups.append(aligner.finish_track())
        update_ms = np.array([u.update_ms for u in ups])
        quality_ms = np.array([1e3 * u.quality.seconds for u in ups if u.quality is not None])
        T = aligner.corrected_path().T_world_node
        src_id, dst_id, _, _, status = aligner.connection_arrays()
        index = {(int(s), int(d)): k for k, (s, d) in enumerate(zip(sc.src, sc.dst))}
        for s, d, st in zip(src_id, dst_id, status):
            if st == 2:
                rejected[index[(int(s), int(d))]] = True
    elif method.startswith('snoop'):
        cfg = QualityConfig(alpha0=snoop_alpha0,
                            snoop_test='w' if method == 'snoop-w' else 'connection')
        out = data_snooping(net, T0, config=cfg, per_iteration=per_iteration)
        T = out.result.T_world_node
        rejected = ~out.kept
    elif method in LOSS_METHODS:
        T = solve(net, T0, SolverConfig(robust_loss=method)).T_world_node
        rejected = misclosure_rejected(net, T, GATE_PROB)
    else:
        raise ValueError(f'unknown method {method!r}')
    return Outcome(method, rejected, ate(T, sc.T_world_node).rmse, time.perf_counter() - t0,
                   update_ms, quality_ms)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='ga-ros bench outliers',
                                description=__doc__.split('\n\n')[0], allow_abbrev=False)
    p.add_argument('--tracks', type=int, default=6, help='double tracks (default 6)')
    p.add_argument('--positions', type=int, default=40, help='positions per swath (default 40)')
    p.add_argument('--noise', type=float, default=2.0, help='motion noise %% (default 2)')
    p.add_argument('--fractions', type=float, nargs='+', default=[0.01, 0.05, 0.2])
    p.add_argument('--gross-m', type=float, nargs=2, default=[5.0, 15.0],
                   help='range of translation errors (m)')
    p.add_argument('--gross-deg', type=float, nargs=2, default=[5.0, 15.0],
                   help='range of rotation errors (deg)')
    p.add_argument('--alpha0', type=float, default=1e-4,
                   help='w-test level of data snooping (batch and the gate-w window)')
    p.add_argument('--per-iteration', type=int, default=20,
                   help='connections data snooping may remove per adjustment (default 20)')
    p.add_argument('--methods', nargs='+', default=list(METHODS), choices=METHODS)
    p.add_argument('--seed', type=int, default=0)
    args = p.parse_args(argv)
    _limits = limit_blas_threads()  # noqa: F841  (kept alive for the whole run)

    rng = np.random.default_rng(args.seed)
    sc, nm = noisy_survey(args.tracks, args.noise, rng, args.positions)
    n_cross = int((~sc.consecutive).sum())
    clean_ls = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z))
    qrep = quality_control(sc.network(nm.z, nm.cov), clean_ls,
                           config=QualityConfig(alpha0=args.alpha0))
    cross = ~sc.consecutive
    print(f'aerial survey: {args.tracks} tracks x {2 * args.positions} positions, '
          f'{sc.n_nodes} nodes, {sc.n_connections} connections ({n_cross} cross-track), '
          f'noise {args.noise:g} %, gross errors {args.gross_m[0]:g}-{args.gross_m[1]:g} m or '
          f'{args.gross_deg[0]:g}-{args.gross_deg[1]:g} deg')
    print(f'clean LS: sigma0^2 {qrep.sigma0_sq:.3f}, median redundancy number of cross '
          f'connections {np.median(qrep.redundancy_numbers[cross]):.2f} (of 6), median MDB '
          f'(alpha0 {args.alpha0:g}, power 0.8) {np.median(qrep.mdb[cross, :3]):.2f} m / '
          f'{np.degrees(np.median(qrep.mdb[cross, 3:])):.2f} deg')
    print()
    header = (f'{"wrong":>6} {"method":<11} {"recall %":>9} {"precision %":>12} '
              f'{"good rej. %":>12} {"ATE m":>8} {"dATE %":>8} {"time s":>7}')
    print(header)
    print('-' * len(header))
    clean: dict[str, float] = {}
    for fraction in [0.0] + list(args.fractions):
        z, bad = inject(sc, nm.z, fraction, tuple(args.gross_m), tuple(args.gross_deg),
                        np.random.default_rng(args.seed + 1))
        for method in args.methods:
            out = run_method(method, sc, z, nm.cov, bad, args.alpha0, args.per_iteration)
            family = method if method in ONLINE else 'ls'
            if fraction == 0.0:
                clean.setdefault(method, out.ate_m)
            ref = clean.get(family, out.ate_m)
            tp = int((out.rejected & bad).sum())
            n_rej = int(out.rejected.sum())
            recall = 100.0 * tp / bad.sum() if bad.any() else float('nan')
            precision = 100.0 * tp / n_rej if n_rej else float('nan')
            good_rej = 100.0 * (out.rejected & ~bad).sum() / (~bad).sum()
            print(f'{100 * fraction:5.0f}% {method:<11} {recall:9.1f} {precision:12.1f} '
                  f'{good_rej:12.2f} {out.ate_m:8.3f} {100 * (out.ate_m / ref - 1):+8.1f} '
                  f'{out.seconds:7.1f}' + ('' if out.update_ms is None else
                                           f'  update ms p50 {np.median(out.update_ms):.0f} '
                                           f'p95 {np.percentile(out.update_ms, 95):.0f}, '
                                           f'QC p50 {np.median(out.quality_ms):.0f} '
                                           f'p95 {np.percentile(out.quality_ms, 95):.0f}'),
                  flush=True)
    print('\ndATE: against the clean run of the same family (batch LS on clean data; the same '
          'gated window on clean data for gate and gate-w)')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
