#!/usr/bin/env python3
"""Benchmark on the public g2o pose graphs; same as ``ga-ros bench-g2o [options]``.

Usage: ``.venv/bin/python scripts/bench_g2o.py [--data DIR] [--only NAME ...] [--skip NAME ...]``
prints a Markdown table (dataset, nodes, edges, initial cost, our cost, reference, gap %,
iterations, seconds). Runs every graph in ``../shared/data/pose-graphs`` by default (about a
minute on 2 cores; torus3D alone takes half of it).
"""

from __future__ import annotations

import sys

from ga_ros.cli.main import main

if __name__ == '__main__':
    sys.exit(main(['bench-g2o', *sys.argv[1:]]))
