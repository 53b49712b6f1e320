"""``ga-ros bench replay``: replay throughput on the sample bags (measurements/s, stereo pairs/s).

Replays ``bags/aerial_measurements`` (measurements -> alignment) and ``bags/stereo_sample``
(images -> VO -> alignment) into a temporary folder and prints wall time and throughput. With
``--io-only`` the aligner is replaced by dead reckoning, which measures the bag reading, decoding
and output writing alone.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.cli.commands.demo import find_bags_dir
from ga_ros.core.integration import DeadReckoningAligner
from ga_ros.errors import InputError
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.pipeline import replay
from ga_ros.replay.samples import MEASUREMENTS_BAG, STEREO_BAG


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``ga-ros bench replay``."""
    p = argparse.ArgumentParser(
        prog='ga-ros bench replay',
        description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False)
    p.add_argument('--bags', type=Path, help='folder of the sample bags (default bags/)')
    p.add_argument('--only', choices=('stereo', 'measurements'))
    p.add_argument('--io-only', action='store_true',
                   help='dead reckoning instead of the aligner (I/O and decoding only)')
    p.add_argument('--json', action='store_true', help='print one JSON object')
    return p


def run(args: argparse.Namespace) -> int:
    bags = args.bags or find_bags_dir()
    if bags is None:
        raise InputError('sample bags not found (run `ga-ros make-bags`)')
    runs = []
    if args.only in (None, 'measurements'):
        runs.append(('measurements', bags / MEASUREMENTS_BAG))
    if args.only in (None, 'stereo') and importlib.util.find_spec('ga_ros.vo.odometry'):
        runs.append(('stereo', bags / STEREO_BAG))
    factory = DeadReckoningAligner if args.io_only else None
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix='ga_bench_replay_') as tmp:
        for kind, bag in runs:
            # the live pipeline's throughput: without the offline final batch
            r = replay(bag, Path(tmp) / bag.name, ReplayConfig(plot=False, final_batch=False),
                       aligner_factory=factory)
            unit = 'pairs' if kind == 'stereo' else 'measurements'
            update_ms = [u.get('update_ms') for u in r.updates if 'update_ms' in u]
            figures[bag.name] = {
                'inputs': r.n_inputs, 'unit': unit, 'measurements': r.n_measurements,
                'nodes': r.n_nodes, 'seconds': round(r.seconds, 3),
                f'{unit}_per_s': round(r.rate, 1),
                'measurements_per_s': round(r.n_measurements / r.seconds, 1),
                'update_ms_p95': (round(float(np.percentile(update_ms, 95)), 2)
                                  if update_ms else None),
                'align_s': round(sum(update_ms) / 1e3, 3) if update_ms else None,
                'aligner': 'dead-reckoning' if args.io_only else 'TrackWindowAligner'}
    if args.json:
        print(json.dumps(figures))
        return 0
    print('| bag | inputs | measurements | nodes | seconds | of which alignment | throughput |'
          ' aligner |')
    print('|---|---|---|---|---|---|---|---|')
    for name, f in figures.items():
        unit = f['unit']
        rate = f[unit + '_per_s']
        align = f"{f['align_s']:.2f} s" if f['align_s'] is not None else '-'
        print(f"| {name} | {f['inputs']} {unit} | {f['measurements']} | {f['nodes']} | "
              f"{f['seconds']:.2f} | {align} | {rate:.0f} {unit}/s | {f['aligner']} |")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench replay [options]``."""
    return run(build_parser().parse_args(argv))
