"""Benchmark: aligner snapshot save/load and crash recovery at survey scale.

Prints, for the paper's aerial survey (5,100 nodes, 29,896 connections) and a scaled one
(~100k nodes), the time to save and to load a snapshot, its size, and the time of
``ga_ros.pipeline.journal.recover`` for a snapshot plus the whole measurement journal (the node's
restart after ``kill -9``), and the rate of the batched journal replay.

The states are filled by a stand-in for the window updates (tracks marked finished, leaving
tracks frozen with a fixed covariance, no solve), so the figures measure persistence and
replay only; ``--full-replay`` also times recovery from the journal alone with real window
updates (one per track, as live). Run: ``ga-ros bench persistence [--full-replay]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from ga_ros.bench.core import NoSolveAligner
from ga_ros.bench.survey import noisy_survey
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import load_state, save_state
from ga_ros.pipeline.journal import MeasurementJournal, journal_path, recover


def _measurements(n_tracks: int, per_swath: int):
    sc, nm = noisy_survey(n_tracks, 2.0, 0, per_swath)
    return sc.measurements(nm.z, nm.cov)


def _bench(label: str, n_tracks: int, per_swath: int, full_replay: bool) -> None:
    t0 = time.perf_counter()
    ms = _measurements(n_tracks, per_swath)
    t_sim = time.perf_counter() - t0
    last_track = max(m.dst_track for m in ms)
    cut = next(k for k, m in enumerate(ms) if m.dst_track == last_track)
    al = NoSolveAligner(AlignerConfig())
    t0 = time.perf_counter()
    batch = al.add_measurements(ms[:cut + 1])   # the last track begins: the one before ends
    t_fill = time.perf_counter() - t0
    al.__class__ = TrackWindowAligner
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / 'state'
        t0 = time.perf_counter()
        save_state(al, state, journal_records=cut + 1)
        t_save = time.perf_counter() - t0
        t0 = time.perf_counter()
        back = load_state(state).aligner
        t_load = time.perf_counter() - t0
        assert back.stats.n_connections == al.stats.n_connections
        journal = MeasurementJournal(journal_path(state))
        t0 = time.perf_counter()
        for k in range(0, len(ms), 4096):
            journal.append_many(ms[k:k + 4096])
        journal.close()
        t_journal = time.perf_counter() - t0
        res = recover(state, AlignerConfig(), checkpoint=False)
        print(f'{label}: {al.stats.n_nodes:,} nodes, {al.stats.n_connections:,} connections in '
              f'the snapshot, {len(ms):,} journal records (simulated in {t_sim:.1f} s; state '
              f'filled at {batch.n_accepted / t_fill:,.0f} measurements/s)')
        print(f'  snapshot: save {t_save * 1e3:7.1f} ms, load {t_load * 1e3:7.1f} ms, '
              f'save+load {(t_save + t_load) * 1e3:7.1f} ms, '
              f'{state.stat().st_size / 2**20:.1f} MiB')
        print(f'  journal write (batched): {t_journal * 1e3:.1f} ms')
        print(f'  recover (snapshot + {res.records_replayed:,} journal records replayed, '
              f'{res.records_rejected} rejected): {res.seconds:.2f} s  [{res.source}]')
        if full_replay:
            state.unlink()
            res = recover(state, AlignerConfig(), checkpoint=False)
            print(f'  recover from the journal alone ({res.records_replayed:,} records, '
                  f'{len(res.aligner.state.finished)} window updates): {res.seconds:.1f} s')


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog='ga-ros bench persistence', description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument('--full-replay', action='store_true',
                    help='also recover the aerial survey from its journal alone (real updates)')
    ap.add_argument('--no-large', action='store_true', help='skip the ~100k-node survey')
    args = ap.parse_args(argv)
    _bench('aerial survey', 25, 102, args.full_replay)
    if not args.no_large:
        _bench('scaled survey', 100, 500, False)
    return 0
