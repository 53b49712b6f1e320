"""Record the outputs of the sample bags, and compare two recordings to the float.

Used to check that a restructuring changes no figure::

    python scripts/compare_outputs.py record /tmp/pipeline_before   # with the old code
    python scripts/compare_outputs.py record /tmp/pipeline_after    # with the new code
    python scripts/compare_outputs.py compare /tmp/pipeline_before /tmp/pipeline_after

``record`` runs ``ga-ros replay --json`` on every bag of ``bags/`` and ``ga-ros demo``.
``compare`` checks, for every run: ``summary.json`` (all values except wall-clock times and
paths), the TUM files (byte for byte) and every message of the output bag (topic, log time and
the serialised CDR bytes, so every float of every message). It prints one line per difference
and exits 1 if there is any.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
#: summary.json keys that depend on the clock or the output location, not on the computation.
VOLATILE = {'seconds', 'inputs_per_s', 'out_dir', 'files', 'update_ms', 'solve_ms',
            'time_ms', 'bag'}


def _ga_ros(args: list[str], log: Path) -> None:
    cmd = [sys.executable, '-c', 'import sys; from ga_ros.cli.main import main; '
           'sys.exit(main())', *args]
    with log.open('w') as f:
        subprocess.run(cmd, check=False, stdout=f, stderr=subprocess.STDOUT, cwd=REPO)


def record(out: Path) -> None:
    """Replay every sample bag and run the demo into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    for bag in sorted(p for p in (REPO / 'bags').iterdir() if (p / 'metadata.yaml').exists()):
        _ga_ros(['replay', str(bag), '--out', str(out / 'replay' / bag.name), '--json',
                 '--no-progress'], out / f'replay_{bag.name}.log')
    _ga_ros(['demo', '--out', str(out / 'demo'), '--no-progress'], out / 'demo.log')


def _strip(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _strip(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [_strip(v) for v in value]
    return value


def _bag_messages(folder: Path) -> list[tuple[str, int, bytes]]:
    from rosbags.rosbag2 import Reader

    with Reader(folder) as reader:
        return [(c.topic, int(t), bytes(d)) for c, t, d in reader.messages()]


def compare(before: Path, after: Path) -> list[str]:
    """Differences between two recordings (empty: identical to the float)."""
    diffs: list[str] = []
    runs = sorted(p.parent for p in before.rglob('summary.json'))
    if not runs:
        return [f'{before}: no summary.json found']
    for run in runs:
        rel = run.relative_to(before)
        other = after / rel
        if not (other / 'summary.json').exists():
            diffs.append(f'{rel}: missing in {after}')
            continue
        a = _strip(json.loads((run / 'summary.json').read_text()))
        b = _strip(json.loads((other / 'summary.json').read_text()))
        if a != b:
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            diffs.append(f'{rel}/summary.json differs in {keys}')
        for tum in sorted(run.glob('*.tum')):
            o = other / tum.name
            if not o.exists() or o.read_bytes() != tum.read_bytes():
                diffs.append(f'{rel}/{tum.name} differs')
        if (run / 'replay_bag').exists():
            ma, mb = _bag_messages(run / 'replay_bag'), _bag_messages(other / 'replay_bag')
            if len(ma) != len(mb):
                diffs.append(f'{rel}/replay_bag: {len(ma)} vs {len(mb)} messages')
            bad = [k for k, (x, y) in enumerate(zip(ma, mb)) if x != y]
            if bad:
                k = bad[0]
                diffs.append(f'{rel}/replay_bag: {len(bad)} messages differ, first #{k} on '
                             f'{ma[k][0]} vs {mb[k][0]}')
        print(f'compared {rel}')
    return diffs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    sub = p.add_subparsers(dest='cmd', required=True)
    r = sub.add_parser('record', allow_abbrev=False)
    r.add_argument('out', type=Path)
    c = sub.add_parser('compare', allow_abbrev=False)
    c.add_argument('before', type=Path)
    c.add_argument('after', type=Path)
    args = p.parse_args(argv)
    if args.cmd == 'record':
        record(args.out)
        return 0
    diffs = compare(args.before, args.after)
    for d in diffs:
        print(d)
    print('identical' if not diffs else f'{len(diffs)} difference(s)')
    return 1 if diffs else 0


if __name__ == '__main__':
    sys.exit(main())
