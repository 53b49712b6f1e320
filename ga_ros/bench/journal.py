"""Benchmark: the journal's cost (append, fsync policy, compaction) and recovery from the
journal alone at survey scale.

1. Append cost: ``--records`` measurement records appended to a journal in a temporary
   directory (of the file system ``--dir`` names, default the system's temporary one), one
   system call each as the node does, with ``fsync`` after every record (``fsync_period_sec:
   0``), at most once a second (the default, 1.0) and never: microseconds per record (wall and
   CPU).
2. Recovery: the stream of ``bags/aerial_measurements`` (``aerial_sample(n_tracks=25)``:
   29,896 measurements, 5,100 nodes) through :class:`~ga_ros.pipeline.session.AlignmentSession`
   with a state file (defaults: journal, snapshot after every window update, compaction every
   ``--compact-records``), ended by the end of input (a journaled track end). Then the process
   is "killed" (nothing more written), the snapshot deleted, and the state recovered from the
   journal alone (:func:`~ga_ros.pipeline.journal.recover`). Prints the run's CPU (this
   process, its threads and its worker processes: the background refinement), the journal's
   size, the recovery's wall and CPU time, the nodes within 1 mm of the uninterrupted run, the
   largest position difference and whether every array of the state is identical (rejection
   counters aside).

Run: ``ga-ros bench journal [--compact-records 1000] [--records 20000] [--tracks 25]``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ga_ros.bench.cpu import all_cpu_seconds
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig
from ga_ros.core.window.persistence import state_arrays
from ga_ros.pipeline.journal import MeasurementJournal, journal_path, recover
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample


def _comparable(al) -> tuple[dict, dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """A copy of an aligner's state (rejection counters aside: refused inputs are not
    journaled) and its corrected path (node ids, positions)."""
    meta, arrays = state_arrays(al.state)
    meta = dict(meta, rejected=None)
    if 'fixes' in meta:
        meta['fixes'] = dict(meta['fixes'], stats=None)
    cp = al.corrected_path()
    return (meta, {k: np.array(v, copy=True) for k, v in arrays.items()},
            np.array(cp.node_ids), np.array(cp.T_world_node[:, :3, 3]))


def compare(ref: tuple, al) -> str:
    """Nodes within 1 mm, largest difference and which state arrays differ, of ``al`` against
    ``ref`` (:func:`_comparable`)."""
    meta_a, arr_a, ids_a, p_a = ref
    meta_b, arr_b, ids_b, p_b = _comparable(al)
    if not np.array_equal(ids_a, ids_b):
        return f'{ids_b.size} nodes against {ids_a.size}: not the same nodes'
    d = np.linalg.norm(p_a - p_b, axis=1)
    diff = ['meta'] if meta_a != meta_b else []
    diff += [k for k in sorted(set(arr_a) | set(arr_b))
             if k not in arr_a or k not in arr_b or arr_a[k].shape != arr_b[k].shape
             or not np.array_equal(arr_a[k], arr_b[k])]
    return (f'{int(np.count_nonzero(d <= 1e-3))} of {ids_a.size} nodes within 1 mm of the '
            f'uninterrupted run (largest difference {d.max():.3g} m); state arrays '
            f'{"identical" if not diff else "differ: " + ", ".join(diff)}')


def append_cost(n: int, directory: str | None) -> None:
    m = Measurement(0, 1, 0, 0, np.zeros(6), np.eye(6) * 1e-4, 1, 'consecutive')
    print(f'journal append, {n} records of 381 bytes, one write() each '
          f'(file system of {directory or tempfile.gettempdir()}):')
    for label, period in (('fsync every record (fsync_period_sec 0)', 0.0),
                          ('fsync at most every 1 s (default)', 1.0),
                          ('no fsync (OS cache only)', None)):
        with tempfile.TemporaryDirectory(dir=directory) as tmp:
            j = MeasurementJournal(Path(tmp) / 'state.journal')
            j.open()
            next_sync = 0.0
            w0, c0 = time.perf_counter(), all_cpu_seconds()
            for _ in range(n):
                j.append(m)
                if period is not None:
                    now = time.monotonic()
                    if now >= next_sync:
                        j.sync()
                        next_sync = now + period
            wall, cpu = time.perf_counter() - w0, all_cpu_seconds() - c0
            j.close()
        print(f'  {label:<42} {1e6 * wall / n:8.1f} us/record wall, '
              f'{1e6 * cpu / n:7.1f} us CPU')


def _recover_alone(label: str, journal: Path, ref: tuple, cfg: AlignerConfig) -> None:
    """Recover from ``journal`` alone (no snapshot) and print the figures against ``ref``."""
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / 'state'
        shutil.copyfile(journal, journal_path(state))
        w0, c0 = time.perf_counter(), all_cpu_seconds()
        res = recover(state, cfg, checkpoint=False)
        wall, cpu = time.perf_counter() - w0, all_cpu_seconds() - c0
        print(f'{label}: recovery from the journal alone (snapshot deleted) {wall:.2f} s wall, '
              f'{cpu:.2f} s CPU; source {res.source}, {res.records_replayed} entries replayed; '
              f'{compare(ref, res.aligner)}')
        res.aligner.close()


def recovery(n_tracks: int, compact: int) -> None:
    ms = aerial_sample(n_tracks=n_tracks).measurements
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / 'state'
        cfg = AlignerConfig()
        live = AlignmentSession(cfg, SessionConfig(str(state), compact_records=compact))
        live.resume()
        spent = {'save': [0, 0.0], 'compact': [0, 0.0]}
        for name in spent:   # time the snapshots and the compactions of the run
            def timed(*args, _name=name, _call=getattr(live, name), **kwargs):
                t = time.perf_counter()
                out = _call(*args, **kwargs)
                spent[_name][0] += 1 if out is not False else 0
                spent[_name][1] += time.perf_counter() - t
                return out
            setattr(live, name, timed)
        w0, c0 = time.perf_counter(), all_cpu_seconds()
        for m in ms:
            live.step(m)
        wall, cpu = time.perf_counter() - w0, all_cpu_seconds() - c0
        # killed before the end of input: the last track open, all of it after the base
        before = Path(tmp) / 'before.journal'
        shutil.copyfile(journal_path(state), before)
        ref_before, n_before = _comparable(live.aligner), live.journal.since_base
        live.finish_track('end_of_input')
        live.journal.close()  # killed after the end of input: nothing more is written
        print(f'uninterrupted run: {len(ms)} measurements, {live.n_nodes()} nodes, '
              f'{wall:.1f} s wall, {cpu:.1f} s CPU (this process, its threads and its worker '
              f'processes); journal {os.path.getsize(journal_path(state)) / 1e6:.1f} MB '
              f'(compact_records {compact}); {spent["save"][0]} snapshots '
              f'{spent["save"][1]:.1f} s wall, {spent["compact"][0]} compactions '
              f'{spent["compact"][1]:.1f} s wall in all')
        _recover_alone(f'killed before the end of input ({n_before} records after the base)',
                       before, ref_before, cfg)
        _recover_alone(f'killed after the end of input ({live.journal.since_base} records after '
                       'the base)', journal_path(state), _comparable(live.aligner), cfg)
        live.close()


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench journal``: print the figures of the module docstring."""
    ap = argparse.ArgumentParser(prog='ga-ros bench journal', description=__doc__.split('\n')[0],
                                 allow_abbrev=False)
    ap.add_argument('--records', type=int, default=20000, help='records of the append test')
    ap.add_argument('--dir', default=None, help='directory of the append test')
    ap.add_argument('--tracks', type=int, default=25, help='tracks of the aerial survey (25)')
    ap.add_argument('--compact-records', type=int, default=SessionConfig().compact_records,
                    help='SessionConfig.compact_records of the run (0: never compact)')
    ap.add_argument('--skip-append', action='store_true', help='only the recovery')
    args = ap.parse_args(argv)
    if not args.skip_append:
        append_cost(args.records, args.dir)
    recovery(args.tracks, args.compact_records)
    return 0
