"""CPU of each stage of a track freeze and of the window update, per track (aerial survey).

The aerial survey is aligned track by track; the CPU milliseconds (``time.thread_time`` of the
thread that runs each stage) spent in the stages of each update are recorded (nested stages
count in their own line and in the enclosing one), and the median over the updates with a full
window (after the first ``window + 1`` tracks) is printed per stage, then one line per update.
With ``freeze_ahead`` (default) the next freeze runs in a background thread after each update;
the script waits for it after each track end (a live survey flies the next track meanwhile)
and prints apart: the track end (update call: wall and CPU of this thread), the background
freeze's CPU, and their sum, the CPU a track costs. ``--no-ahead``: freezes at the track end.
Run it on two checkouts at the same time to compare them under the same machine load:

    ga-ros bench freeze --tracks 12 --refine 0
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ga_ros.bench.survey import add_survey_arguments, noisy_survey
from ga_ros.core.linalg import completion, selinv, skeleton
from ga_ros.core.linalg.cholmod import SparseCholesky
from ga_ros.core.solver.problem import _Problem
from ga_ros.core.window import aligner, freeze, handoff, update

#: (owner, attribute) of each timed stage.
STAGES = (
    (aligner.TrackWindowAligner, '_freeze'),
    (aligner.TrackWindowAligner, '_plan_freeze'),
    (freeze, 'marginal_covariances'),
    (freeze.FreezePolicy, 'marginalise'),
    (freeze, 'normal_matrix_at'),
    (skeleton, 'sparse_skeleton'),
    (freeze, 'marginal_prior'),
    (freeze, 'band_prior'),
    (completion, '_completion'),
    (selinv.SelectedInverse, '__init__'),
    (SparseCholesky, 'refactor'),
    (SparseCholesky, '_analyse'),
    (aligner.TrackWindowAligner, '_adjust'),
    (update, 'solve'),
    (_Problem, 'linear_system'),
    (handoff.RefinementHandoff, 'install_due'),
    (handoff.RefinementHandoff, 'smooth'),
    (handoff.RefinementHandoff, 'start'),
)

def _name(owner, attr: str) -> str:
    return f'{getattr(owner, "__name__", "").split(".")[-1]}.{attr}'


def _timed(owner, attr: str, totals: dict[str, float]) -> None:
    fn = getattr(owner, attr)
    label = _name(owner, attr)

    def timed(*args, **kwargs):
        c0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            totals[label] = totals.get(label, 0.0) + 1e3 * (time.thread_time() - c0)

    setattr(owner, attr, timed)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog='ga-ros bench freeze', description=__doc__.splitlines()[0], allow_abbrev=False)
    add_survey_arguments(ap, tracks=12, positions=False)
    ap.add_argument('--refine', type=int, default=0, help='refine_every_tracks (0: off)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--no-ahead', action='store_true', help='freeze at the track end')
    args = ap.parse_args(argv)
    totals: dict[str, float] = {}
    stages = [(o, a) for o, a in STAGES if hasattr(o, a)]  # an older checkout lacks some
    for owner, attr in stages:
        _timed(owner, attr, totals)
    sc, nm = noisy_survey(args.tracks, args.noise, args.seed)
    cfg = aligner.AlignerConfig(window_tracks=args.window, refine_every_tracks=args.refine,
                               freeze_ahead=not args.no_ahead)
    al = aligner.TrackWindowAligner(cfg, sc.T_world_node[0])
    rows = []
    for m in list(sc.measurements(nm.z, nm.cov)) + [None]:
        totals.clear()
        c0, w0 = time.thread_time(), time.perf_counter()
        new = al.add_measurement(m) if m is not None else [al.finish_track()]
        if any(u is not None for u in new):
            cpu, wall = 1e3 * (time.thread_time() - c0), 1e3 * (time.perf_counter() - w0)
            background = al.wait_background()  # the next freeze, while the next track is flown
            rows.append((cpu, wall, background, dict(totals)))
    al.close()
    full = rows[args.window + 1:]
    labels = [_name(o, a) for o, a in stages]
    ahead = 'at the track end' if args.no_ahead else 'ahead, in the background'
    print(f'freeze {ahead}; p50 over tracks {args.window + 2}-{len(rows)}, ms:')
    for what, k in (('track end: update CPU', 0), ('track end: update wall', 1),
                    ('background freeze CPU', 2)):
        print(f'  {what:38s} {np.median([r[k] for r in full]):8.1f} '
              f'(p95 {np.percentile([r[k] for r in full], 95):.1f})')
    total = [r[0] + r[2] for r in full]
    print(f'  {"CPU per track (both)":38s} {np.median(total):8.1f} '
          f'(p95 {np.percentile(total, 95):.1f})')
    print('CPU ms p50 by stage (the thread that runs it):')
    for label in labels:
        print(f'  {label:38s} {np.median([r[3].get(label, 0.0) for r in full]):8.1f}')
    for k, (cpu, wall, background, parts) in enumerate(rows, start=1):
        print(f'track {k:3d}: update {cpu:6.0f} ms CPU {wall:6.0f} ms wall  background '
              f'{background:5.0f}  solve {parts.get(_name(update, "solve"), 0.0):6.0f}')
    return 0
