"""``ga-ros bench faults``: the fault catalogue against live alignment nodes, as a table.

Every case (:mod:`ga_ros.ros.fault_catalogue`) starts ``alignment_node`` with its default
settings (plus what the case is about), injects the fault (kill -9 or SIGTERM during ``ga-ros
play``, a kill during recovery, a full disk, unusable or damaged state files, hostile service
calls, floods, bad inputs) and compares the final path with the aligner fed the clean
measurements: nodes expected, nodes kept, time to recover. ``--bag`` runs the cases on a
measurements bag (e.g. ``bags/aerial_measurements``: 29,896 measurements, 5,100 nodes) instead
of the small simulated survey. Exit code 0 when no case lost a node. ROS is imported lazily.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``ga-ros bench faults``."""
    p = argparse.ArgumentParser(prog='ga-ros bench faults', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument('--bag', type=Path, default=None,
                   help='measurements bag to run the cases on (default: a small simulated '
                        'survey of 48 nodes)')
    p.add_argument('--only', nargs='+', default=[], metavar='CASE',
                   help='only these cases (names as listed by --list)')
    p.add_argument('--list', action='store_true', help='list the case names and exit')
    p.add_argument('--out', type=Path, default=None, help='also write the table to this file')
    p.add_argument('--domain-base', type=int, default=None, metavar='ID',
                   help='ROS_DOMAIN_ID of the first case, the others follow, 30 domains in '
                        'turn (at most 232 - 29; default: each case a domain id claimed '
                        'machine-wide, never one a concurrent test run or benchmark holds)')
    return p


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench faults [options]``."""
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    from ga_ros.domains import claimed
    from ga_ros.errors import InputError
    from ga_ros.ros import fault_catalogue as fc
    from ga_ros.safe_write import atomic_write

    cases = fc.catalogue()
    if args.list:
        print('\n'.join(cases))
        return 0
    unknown = [n for n in args.only if n not in cases]
    if unknown:
        raise InputError(f'unknown case(s) {", ".join(unknown)}; see --list')
    survey = fc.bag_survey(args.bag) if args.bag is not None else None
    size = (f'{len(survey.measurements)} measurements, {survey.n_nodes} nodes'
            if survey is not None else 'small simulated survey')
    rows = []
    t0 = time.monotonic()
    for k, (name, case) in enumerate(cases.items()):
        if args.only and name not in args.only:
            continue
        if args.domain_base is not None:
            row = fc.run_case(name, case, survey, args.domain_base + k % 30)  # one at a time
        else:
            with claimed() as dom:
                row = fc.run_case(name, case, survey, dom)
        rows.append(row)
        print(f'  {name}: {row.survived}, {row.counted}, kept {row.kept}/{row.expected}'
              + (f', recovered in {row.recover_s:.1f} s' if row.recover_s is not None else ''),
              flush=True)
    text = (f'{size}; {time.monotonic() - t0:.0f} s\n\n' + fc.table(rows) + '\n')
    print('\n' + text)
    if args.out is not None:
        atomic_write(args.out, text.encode())
    return 0 if all(r.lost == 0 and r.survived != 'ERROR' for r in rows) else 1
