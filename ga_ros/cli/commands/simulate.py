"""``ga-ros simulate``: write a simulated survey (noisy measurements + ground truth) to files.

Output in DIR:

* ``measurements.g2o``: every connection as ``EDGE_SE3:QUAT`` (``T_src_dst``, information = inverse
  of the noise covariance), vertices at the F2F initial guess, ``FIX 0`` (the known first pose);
  ``measurements.npz`` (``src, dst, z, cov``) instead when :mod:`ga_ros.io.g2o` is unavailable;
* ``ground_truth.tum``: true poses, ``timestamp x y z qx qy qz qw`` (one frame per second);
* ``tracks.csv``: ``node_id,track_id``;
* ``scenario.json``: the settings (scenario, seed, noise model) and the counts.
"""

from __future__ import annotations

import argparse
from pathlib import Path

SCENARIOS = ('aerial', 'lawnmower_open', 'lawnmower_closed', 'looping_open', 'looping_closed')


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'simulate', help="simulate one of the paper's surveys with ground truth",
        description="Simulate one of the paper's surveys (noisy motions between overlapping "
                    'frames) and write the measurements (g2o), the ground truth (TUM) and the '
                    'track ids (CSV).')
    p.add_argument('scenario', choices=SCENARIOS)
    p.add_argument('--seed', type=int, default=0, help='seed of the noise (default 0)')
    p.add_argument('--noise', type=float, default=10.0,
                   help='noise in percent of the true motion (default 10)')
    p.add_argument('--tracks', type=int, default=25,
                   help='aerial only: number of double tracks (default 25)')
    p.add_argument('--out', required=True, help='output directory')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ga_ros.errors import InputError
    from ga_ros.safe_write import check_destinations, write_json, write_npz, write_text
    from ga_ros.sim.aerial import aerial_scenario
    from ga_ros.sim.noise import NoiseModel, perturb
    from ga_ros.sim.trajectories import synthetic_scenario

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f'{out} exists and is not a directory')
    check_destinations(*(out / name for name in ('measurements.g2o', 'measurements.npz',
                                                  'ground_truth.tum', 'tracks.csv',
                                                  'scenario.json')))
    if args.scenario == 'aerial':
        sc = aerial_scenario(n_tracks=args.tracks)
    else:
        sc = synthetic_scenario(args.scenario)
    noise = NoiseModel(args.noise, sc.depth_m)
    nm = perturb(sc.true_motions(), noise, np.random.default_rng(args.seed))
    out.mkdir(parents=True, exist_ok=True)
    net = sc.network(nm.z, nm.cov)
    f2f = sc.f2f(nm.z)
    try:
        from ga_ros.io.g2o import PoseGraph, write_g2o
    except ImportError:
        meas_file = 'measurements.npz'
        write_npz(out / meas_file, src=sc.src, dst=sc.dst, z=nm.z, cov=nm.cov)
    else:
        meas_file = 'measurements.g2o'
        write_g2o(out / meas_file, PoseGraph.from_network(net, f2f, fixed=(0,)))
    _write_tum(out / 'ground_truth.tum', sc.stamps_ns, sc.T_world_node)
    lines = ['node_id,track_id'] + [f'{i},{t}' for i, t in zip(sc.node_ids, sc.track_ids)]
    write_text(out / 'tracks.csv', '\n'.join(lines) + '\n')
    meta = {'scenario': args.scenario, 'seed': args.seed, 'noise_pct': args.noise,
            'noise_depth_m': sc.depth_m, 'footprint_m': sc.footprint_m,
            'nodes': sc.n_nodes, 'connections': sc.n_connections,
            'cross_connections': int((~sc.consecutive).sum()), 'tracks': sc.n_tracks,
            'measurements': meas_file,
            'noise_model': 'per axis: sigma_t = pct |t|, sigma_w = pct max(|w|, |t| / depth); '
                           'right perturbation T_true exp(xi); covariance = diag(sigma^2)'}
    write_json(out / 'scenario.json', meta, indent=1)
    print(f'{args.scenario}: {sc.n_nodes} nodes, {sc.n_connections} connections -> {out}/'
          f'{{{meas_file}, ground_truth.tum, tracks.csv, scenario.json}}')
    return 0


def _write_tum(path: Path, stamps_ns, T) -> None:
    try:
        from ga_ros.io.trajectory import write_tum
    except ImportError:
        from ga_ros.geometry import se3

        p, q = se3.to_pos_quat(T)
        rows = [f'{s / 1e9:.9f} ' + ' '.join(repr(float(v)) for v in (*p[k], *q[k]))
                for k, s in enumerate(stamps_ns)]
        from ga_ros.safe_write import write_text

        write_text(path, '# timestamp x y z qx qy qz qw\n' + '\n'.join(rows) + '\n')
    else:
        write_tum(path, stamps_ns, T)
