"""``ga-ros bench vo``: stereo odometry and cross-track matching on the stereo simulator.

Prints the accuracy of the consecutive motions (translation error relative to the distance
travelled, rotation error), the NEES of their covariance (6 when honest), the precision and
recall of the cross-track connections against the ground truth, and the odometry throughput
(stereo pairs per second, rendering excluded). See :mod:`ga_ros.vo.evaluate`.
"""

from __future__ import annotations

import argparse
import json
import math

from ga_ros.errors import InputError

TARGETS = {'translation_error_pct': 1.0, 'rotation_error_deg': 0.1, 'precision': 0.99,
           'recall': 0.8, 'fps': {'320x240': 30.0, '640x480': 15.0}, 'nees': (4.2, 7.8)}


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``ga-ros bench vo``."""
    p = argparse.ArgumentParser(
        prog='ga-ros bench vo',
        description='Render a seeded lawnmower survey over a textured terrain, run the stereo '
                    'odometry and the cross-track matcher, and compare with the ground truth.',
        allow_abbrev=False)
    p.add_argument('--size', default='320x240', help='image size WxH (default 320x240)')
    p.add_argument('--frames', type=int, default=None,
                   help='stereo pairs to process (default: the whole survey)')
    p.add_argument('--tracks', type=int, default=2, help='double swaths (default 2)')
    p.add_argument('--positions', type=int, default=40, help='frames per swath (default 40)')
    p.add_argument('--seed', type=int, default=0, help='seed of terrain, flight and noise')
    p.add_argument('--no-cross', action='store_true', help='skip cross-track matching')
    p.add_argument('--json', action='store_true', help='print the figures as JSON')
    return p


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split('x'))
    except ValueError as exc:
        raise InputError(f'--size must look like 320x240, got {text!r}') from exc
    if w < 64 or h < 48:
        raise InputError(f'--size {text} is too small (at least 64x48)')
    return w, h


def _fmt(x: object, spec: str = '.3f') -> str:
    return format(x, spec) if isinstance(x, float) and math.isfinite(x) else str(x)


def run(args: argparse.Namespace) -> int:
    from ga_ros.vo.evaluate import BenchConfig, run_benchmark

    w, h = _parse_size(args.size)
    if args.frames is not None and args.frames < 2:
        raise InputError('--frames must be at least 2')
    cfg = BenchConfig(width=w, height=h, n_tracks=args.tracks,
                      positions_per_swath=args.positions, seed=args.seed,
                      cross=not args.no_cross)
    out = run_benchmark(cfg, frames=args.frames)
    out['targets'] = TARGETS
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    c = out['consecutive']
    print(f"stereo VO on the simulator, {out['size']}, {out['frames']} pairs, "
          f"{out['keyframes']} keyframes, status {out['status']}")
    print(f"  throughput               {_fmt(out['vo_pairs_per_s'], '.1f')} pairs/s "
          f"(target >= {TARGETS['fps'].get(out['size'], '-')}); "
          f"{_fmt(out['vo_pairs_per_cpu_s'], '.1f')} pairs per CPU second")
    if c['translation_error_pct'].get('n', 0):
        print(f"  consecutive motions      {c['translation_error_pct']['n']}")
        print(f"  translation error        median {_fmt(c['translation_error_pct']['median'])} % "
              f"of travel, p90 {_fmt(c['translation_error_pct']['p90'])} % (target < 1 %)")
        print(f"  rotation error           median {_fmt(c['rotation_error_deg']['median'])} deg, "
              f"p90 {_fmt(c['rotation_error_deg']['p90'])} deg (target < 0.1 deg)")
        print(f"  NEES                     mean {_fmt(c['nees']['mean'], '.2f')}, median "
              f"{_fmt(c['nees']['median'], '.2f')} (target mean 6 +- 30 %)")
        for key, label in (('nees_swaths', 'along swaths'), ('nees_turns', 'in turns')):
            if c[key].get('n', 0):
                print(f"    NEES {label:<19} mean {_fmt(c[key]['mean'], '.2f')}, median "
                      f"{_fmt(c[key]['median'], '.2f')} ({c[key]['n']} motions)")
    x = out.get('cross')
    if x:
        print(f"  cross-track attempts     {x['attempts']}, accepted {x['accepted']}, "
              f"correct {x['correct']}")
        print(f"  precision                {_fmt(x['precision'])} (target >= 0.99)")
        print(f"  recall                   {_fmt(x['recall'])} ({x['found_pairs']} of "
              f"{x['true_pairs']} pairs with true overlap >= 70 %; target >= 0.8)")
        te = x['translation_error_m']
        if te.get('n', 0):
            print(f"  cross translation error  median {_fmt(te['median'])} m, "
                  f"p90 {_fmt(te['p90'])} m")
        ne = x['nees_correct']
        if ne.get('n', 0):
            print(f"  cross NEES               mean {_fmt(ne['mean'], '.2f')}, median "
                  f"{_fmt(ne['median'], '.2f')}")
        print(f"  rejections               {x['rejections']}")
        print(f"  matching time            {_fmt(1e3 * x['seconds_per_keyframe'], '.1f')} ms "
              'per keyframe')
    return 0


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench vo [options]``."""
    return run(build_parser().parse_args(argv))
