"""Sparse joint priors against the dense ones: published covariances, positions, NEES, CPU.

The aerial survey is aligned track by track (refinement off) once with dense priors
(``prior_band = -1``) and once per ``band:hubs`` setting; per setting it prints the total CPU,
the mean position NEES against ground truth, the largest and median position difference to the
dense run in its standard deviations, and the worst and median ratio of the published position
variances to the dense run's (below 1: overconfident).

    ga-ros bench prior --tracks 10 --settings 4:0 4:8 8:8 16:16
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ga_ros.bench.survey import add_survey_arguments, noisy_survey
from ga_ros.core.window import FREEZE_POLICIES, AlignerConfig, TrackWindowAligner
from ga_ros.geometry import se3


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog='ga-ros bench prior', description=__doc__.splitlines()[0], allow_abbrev=False)
    add_survey_arguments(ap, tracks=10)
    ap.add_argument('--policy', default='weighted', choices=tuple(FREEZE_POLICIES))
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--settings', nargs='+', default=['4:0', '4:8', '8:8', '16:16'],
                    help='band:hubs pairs (prior_band, prior_hubs)')
    args = ap.parse_args(argv)
    sc, nm = noisy_survey(args.tracks, args.noise, args.seed, args.positions)
    ms = sc.measurements(nm.z, nm.cov)
    ids, truth = sc.node_ids[1:], sc.T_world_node[1:]
    ref = None
    for setting in ['-1:0'] + list(args.settings):
        band, hubs = (int(x) for x in setting.split(':'))
        al = TrackWindowAligner(AlignerConfig(window_tracks=args.window,
                                              freeze_policy=args.policy, refine_every_tracks=0,
                                              prior_band=band, prior_hubs=hubs),
                                sc.T_world_node[0])
        c0 = time.process_time()
        al.add_measurements(ms)
        al.finish_track()
        cpu = time.process_time() - c0
        T, C = al.corrected_path().T_world_node[1:], al.covariances(ids)
        e = se3.log(se3.inverse(T) @ truth)[:, :3]
        nees = np.einsum('ni,ni->n', e, np.linalg.solve(C[:, :3, :3], e[:, :, None])[:, :, 0])
        line = f'band {band:3d} hubs {hubs:3d}: CPU {cpu:6.1f} s, NEES {nees.mean():5.2f}'
        if ref is None:
            ref = (T, C)
        else:
            var, var_ref = (np.diagonal(c, axis1=1, axis2=2)[:, :3] for c in (C, ref[1]))
            gap = np.abs(T[:, :3, 3] - ref[0][:, :3, 3]) / np.sqrt(var_ref)
            r = var / var_ref
            line += (f', to dense: position max {gap.max():.3f} sd (median {np.median(gap):.3f}),'
                     f' variance ratio worst {r.min():.3f} median {np.median(r):.3f}')
        print(line, flush=True)
    return 0
