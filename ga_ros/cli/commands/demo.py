"""``ga-ros demo``: the README's main command -- replay the bundled sample bags end to end.

1. ``bags/stereo_sample``: compressed stereo images -> stereo VO (+ cross-track matching) ->
   track-window alignment (skipped, with a note, if the VO modules are not installed);
2. ``bags/aerial_measurements``: the paper's aerial scenario as measurements -> alignment.

Outputs go to ``out/demo/<bag>/`` (output mcap bag for Foxglove, TUM trajectories, PNG plot,
``summary.json``; for the stereo bag also the mosaic before and after the alignment,
``mosaic_f2f.png`` / ``mosaic_ga.png`` and ``mosaic_compare.png``); the command prints where they
are, the F2F vs GA error against the ground truth and the mosaics' seam misregistration. If
the bundled bags are missing they are regenerated first (deterministic simulators).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
from pathlib import Path

from ga_ros.cli.commands import SUMMARIES
from ga_ros.cli.commands.replay import add_replay_arguments, replay_config
from ga_ros.errors import GaError, InputError
from ga_ros.replay.pipeline import replay
from ga_ros.replay.samples import MEASUREMENTS_BAG, STEREO_BAG, make_sample_bags
from ga_ros.replay.text import plan_lines, result_text

#: ``bags/`` of the source tree this package runs from (editable install), else of the cwd.
REPO_BAGS = Path(__file__).resolve().parents[3] / 'bags'


def find_bags_dir() -> Path | None:
    """The folder holding the sample bags, or None."""
    for d in (REPO_BAGS, Path.cwd() / 'bags'):
        if (d / MEASUREMENTS_BAG / 'metadata.yaml').exists() or (
                d / STEREO_BAG / 'metadata.yaml').exists():
            return d
    return None


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'demo', help=SUMMARIES['demo'],
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False)
    p.add_argument('--out', type=Path, default=Path('out') / 'demo',
                   help='output folder (default out/demo)')
    p.add_argument('--only', choices=('stereo', 'measurements'),
                   help='replay only one of the two sample bags')
    p.add_argument('--bags', type=Path, help='folder of the sample bags (default: bags/)')
    add_replay_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    bags = args.bags or find_bags_dir()
    if bags is None:
        bags = args.out / 'bags'
        print(f'sample bags not found: regenerating them into {bags} ...', flush=True)
        make_sample_bags(bags)
    runs: list[tuple[str, Path]] = []
    if args.only in (None, 'stereo'):
        if importlib.util.find_spec('ga_ros.vo.odometry') is None:
            print('note: the stereo VO modules are not installed; skipping the stereo bag')
        else:
            runs.append(('stereo', bags / STEREO_BAG))
    if args.only in (None, 'measurements'):
        runs.append(('measurements', bags / MEASUREMENTS_BAG))
    missing = [str(b) for _, b in runs if not b.exists()]
    if missing:
        raise InputError('sample bag(s) not found: ' + ', '.join(missing)
                         + ' (regenerate with `ga-ros make-bags`)')
    failures = 0
    summary: list[str] = []
    mosaics: list[str] = []
    for kind, bag in runs:
        print(f'\n=== {bag.name}: '
              + ('stereo images -> VO -> track-window alignment' if kind == 'stereo'
                 else "the paper's aerial scenario, measurements -> track-window alignment"),
              flush=True)
        config = replay_config(args, progress=sys.stderr.isatty())
        if kind == 'stereo':  # the mosaic before and after
            config = dataclasses.replace(config, mosaic=True)
        try:
            result = replay(bag, args.out / bag.name, config,
                            on_plan=lambda plan: print('\n'.join(plan_lines(plan))))
        except GaError as exc:
            print(f'ga-ros demo: error on {bag}: {exc}', file=sys.stderr)
            failures += 1
            continue
        print(result_text(result))
        how = result.errors_compared
        if 'ga' in result.errors and 'f2f' in result.errors:
            summary.append(f'  {bag.name:<22} F2F {result.errors["f2f"].compared(how):9.3f} m   '
                           f'GA {result.errors["ga"].compared(how):9.3f} m   '
                           f'({result.n_nodes} nodes; plot {result.files.get("plot", "-")})')
        if 'ga' in result.mosaic and 'f2f' in result.mosaic:
            mosaics.append(mosaic_summary(bag.name, result.mosaic))
    if summary:
        what = 'after rigid alignment, each its own' if args.no_anchor else 'first pose anchored'
        ga = 'online' if args.no_final_batch else 'the final batch'
        print(f'\nposition RMSE against ground truth ({what}; GA: {ga}):')
        print('\n'.join(summary))
    if mosaics:
        print('\nmosaic before (F2F) and after (GA) the alignment, seam misregistration '
              'between neighbouring tracks (median / p95, mosaic px):')
        print('\n'.join(mosaics))
    print(f'\nopen the output bags in Foxglove: {args.out}/<bag>/replay_bag/*.mcap')
    return 1 if failures else 0


def mosaic_summary(name: str, mosaic: dict) -> str:
    """One line: the F2F and GA mosaics' seam misregistration and the before / after figure."""
    f, g = mosaic['f2f']['seams'], mosaic['ga']['seams']
    fig = mosaic.get('compare', {}).get('png', mosaic['ga']['png'])
    mpp = mosaic['ga']['metres_per_pixel']
    return (f"  {name:<22} F2F {f['median_px']:5.2f} / {f['p95_px']:4.2f} px   GA "
            f"{g['median_px']:5.2f} / {g['p95_px']:4.2f} px   ({mpp:.3g} m/px; {fig})")
