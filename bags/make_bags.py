#!/usr/bin/env python3
"""Regenerate the sample bags of this folder deterministically (same as ``ga-ros make-bags``).

    .venv/bin/python bags/make_bags.py [measurements] [stereo]

See :mod:`ga_ros.replay.samples` for what each bag holds.
"""

from __future__ import annotations

import sys
from pathlib import Path

from ga_ros.replay.samples import make_sample_bags


def main(argv: list[str]) -> int:
    which = tuple(argv) or ('measurements', 'stereo')
    for kind, path in make_sample_bags(Path(__file__).resolve().parent, which).items():
        size = sum(f.stat().st_size for f in path.iterdir()) / 1e6
        print(f'{kind:<13} {path} ({size:.1f} MB)')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
