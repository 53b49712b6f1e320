"""CPU of each stage of a track freeze and of the window update, per track (aerial survey).

The aerial survey is aligned track by track; the CPU milliseconds (``time.process_time``, all
threads of this process) spent in the stages of each update are recorded (nested stages count
in their own line and in the enclosing one), and the median over the updates with a full
window (after the first ``window + 1`` tracks) is printed per stage, then one line per update.
Run it on two checkouts at the same time to compare them under the same machine load:

    .venv/bin/python scripts/bench_freeze.py --tracks 12 --refine 0
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ga_ros.core import selinv, solver, sparse, window
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

#: (owner, attribute) of each timed stage.
STAGES = (
    (window.TrackWindowAligner, '_freeze'),
    (window, '_marginal_covariances'),
    (window.TrackWindowAligner, '_marginalise'),
    (window, 'normal_matrix_at'),
    (selinv, 'sparse_skeleton'),
    (window, 'band_prior'),
    (sparse, '_completion'),
    (selinv.SelectedInverse, '__init__'),
    (sparse.SparseCholesky, 'refactor'),
    (sparse.SparseCholesky, '_analyse'),
    (window.TrackWindowAligner, '_adjust'),
    (window, 'solve'),
    (solver._Problem, 'linear_system'),
    (window.TrackWindowAligner, '_install_due'),
    (window.TrackWindowAligner, '_smooth'),
    (window.TrackWindowAligner, '_start_refinement'),
)


def _name(owner, attr: str) -> str:
    return f'{getattr(owner, "__name__", "").split(".")[-1]}.{attr}'


def _timed(owner, attr: str, totals: dict[str, float]) -> None:
    fn = getattr(owner, attr)
    label = _name(owner, attr)

    def timed(*args, **kwargs):
        c0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            totals[label] = totals.get(label, 0.0) + 1e3 * (time.process_time() - c0)

    setattr(owner, attr, timed)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--tracks', type=int, default=12, help='double tracks of the survey')
    ap.add_argument('--noise', type=float, default=10.0, help='noise (percent)')
    ap.add_argument('--window', type=int, default=5)
    ap.add_argument('--refine', type=int, default=0, help='refine_every_tracks (0: off)')
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    totals: dict[str, float] = {}
    stages = [(o, a) for o, a in STAGES if hasattr(o, a)]  # an older checkout lacks some
    for owner, attr in stages:
        _timed(owner, attr, totals)
    sc = aerial_scenario(n_tracks=args.tracks)
    nm = perturb(sc.true_motions(), NoiseModel(args.noise, sc.depth_m),
                 np.random.default_rng(args.seed))
    cfg = window.AlignerConfig(window_tracks=args.window, refine_every_tracks=args.refine)
    al = window.TrackWindowAligner(cfg, sc.T_world_node[0])
    rows = []
    for m in list(sc.measurements(nm.z, nm.cov)) + [None]:
        totals.clear()
        c0 = time.process_time()
        new = al.add_measurement(m) if m is not None else [al.finish_track()]
        if any(u is not None for u in new):
            rows.append((1e3 * (time.process_time() - c0), dict(totals)))
    al.close()
    full = rows[args.window + 1:]
    labels = [_name(o, a) for o, a in stages]
    print(f'update CPU ms p50 (tracks {args.window + 2}-{len(rows)}): '
          f'{np.median([c for c, _ in full]):.0f}')
    for label in labels:
        print(f'  {label:38s} {np.median([t.get(label, 0.0) for _, t in full]):8.1f}')
    for k, (cpu, parts) in enumerate(rows, start=1):
        print(f'track {k:3d}: {cpu:7.0f} ms  freeze {parts.get(labels[0], 0.0):6.0f}  '
              f'solve {parts.get(_name(window, "solve"), 0.0):6.0f}')


if __name__ == '__main__':
    main()
