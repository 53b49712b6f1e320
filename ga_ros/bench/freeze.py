"""CPU of each stage of a track freeze and of the window update, per track (aerial survey).

The aerial survey is aligned track by track; the CPU milliseconds (``time.thread_time`` of the
thread that runs each stage) spent in the stages of each update are recorded (nested stages
count in their own line and in the enclosing one), and the median over the updates with a full
window (after the first ``window + 1`` tracks) is printed per stage, then one line per update.
With ``freeze_ahead`` (default) the next freeze runs in a background thread after each update;
the script waits for it after each track end (a live survey flies the next track meanwhile)
and prints apart: the track end (update call: wall and CPU of this thread), the background
freeze's CPU, and their sum, the CPU a track costs. ``--no-ahead``: freezes at the track end.
Beside the CPU, the floating-point operations of the dense arithmetic (GFlop per stage, p50):
every numeric factorisation (CHOLMOD's supernodal blocks, :func:`~ga_ros.core.linalg.selinv.
supernodal_flops`) and every selected inversion (the supernodes it inverted), counted in the
stages that enclose them; CPU over GFlop says whether a stage is arithmetic or overhead.
Run it on two checkouts at the same time to compare them under the same machine load:

    ga-ros bench freeze --tracks 12 --refine 0
"""

from __future__ import annotations

import argparse
import threading
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


class _Open(threading.local):
    """The timed stages open on this thread (innermost last)."""

    def __init__(self) -> None:
        self.stages: list[str] = []


_OPEN = _Open()


def _timed(owner, attr: str, totals: dict[str, float]) -> None:
    fn = getattr(owner, attr)
    label = _name(owner, attr)

    def timed(*args, **kwargs):
        c0 = time.thread_time()
        _OPEN.stages.append(label)
        try:
            return fn(*args, **kwargs)
        finally:
            _OPEN.stages.pop()
            totals[label] = totals.get(label, 0.0) + 1e3 * (time.thread_time() - c0)

    setattr(owner, attr, timed)


def _count(flops: dict[str, float], amount: float) -> None:
    """Add ``amount`` flops to every stage open on this thread (and to the total)."""
    for label in ['all', *_OPEN.stages]:
        flops[label] = flops.get(label, 0.0) + amount


def _counted(flops: dict[str, float]) -> None:
    """Count the flops of every numeric factorisation (:meth:`SparseCholesky.refactor`, from
    the supernodal factor it leaves) and every selected inversion
    (:class:`selinv.SelectedInverse`) into ``flops`` by open stage."""
    from ga_ros.core.linalg.cholmod_ctypes import _supernodal_layout

    refactor, inverse = SparseCholesky.refactor, selinv.SelectedInverse.__init__

    def counted_refactor(self, data):
        refactor(self, data)
        lay = None if self._F is None else _supernodal_layout(self._F, self.n)
        if lay is not None:
            _count(flops, selinv.supernodal_flops(lay.starts, lay.nrows)[0])

    def counted_inverse(self, *args, **kwargs):
        inverse(self, *args, **kwargs)
        _count(flops, self.flops[1])

    SparseCholesky.refactor = counted_refactor
    selinv.SelectedInverse.__init__ = counted_inverse


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog='ga-ros bench freeze', description=__doc__.splitlines()[0], allow_abbrev=False)
    add_survey_arguments(ap, tracks=12, positions=False)
    ap.add_argument('--refine', type=int, default=0, help='refine_every_tracks (0: off)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--no-ahead', action='store_true', help='freeze at the track end')
    args = ap.parse_args(argv)
    totals: dict[str, float] = {}
    flops: dict[str, float] = {}
    _counted(flops)
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
        flops.clear()
        c0, w0 = time.thread_time(), time.perf_counter()
        new = al.add_measurement(m) if m is not None else [al.finish_track()]
        if any(u is not None for u in new):
            cpu, wall = 1e3 * (time.thread_time() - c0), 1e3 * (time.perf_counter() - w0)
            background = al.wait_background()  # the next freeze, while the next track is flown
            rows.append((cpu, wall, background, dict(totals), dict(flops)))
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
    print('p50 by stage (the thread that runs it): CPU ms, GFlop (factorisations and selected '
          'inversions), GFlop/s')
    for label in labels:
        ms = np.median([r[3].get(label, 0.0) for r in full])
        gf = np.median([r[4].get(label, 0.0) for r in full]) / 1e9
        rate = f'{gf / ms * 1e3:8.1f}' if gf > 0 and ms > 0 else ''
        print(f'  {label:38s} {ms:8.1f} {gf:8.3f} {rate}')
    print(f'  {"all factorisations and inversions":38s} {"":8s} '
          f'{np.median([r[4].get("all", 0.0) for r in full]) / 1e9:8.3f}')
    for k, (cpu, wall, background, parts, _) in enumerate(rows, start=1):
        print(f'track {k:3d}: update {cpu:6.0f} ms CPU {wall:6.0f} ms wall  background '
              f'{background:5.0f}  solve {parts.get(_name(update, "solve"), 0.0):6.0f}')
    return 0
