"""Benchmark: bytes per update of ``ga/corrections`` against republishing the whole path.

The paper's aerial survey (``aerial_sample(n_tracks=25)``: 5,100 keyframes, 29,896
measurements, the stream of ``bags/aerial_measurements``) goes through
:class:`~ga_ros.pipeline.session.AlignmentSession` (window updates, freezes, background
refinement; ``--refine-every``, ``--window-tracks`` change the aligner). After every window
update it serializes (CDR, what DDS sends) the whole corrected path as the node publishes it on
``ga/corrected_path`` (:func:`ga_ros.io.cdr.path_cdr`) and the corrections message of a
:class:`~ga_ros.pipeline.corrections.CorrectionTracker` (``ga/corrections``, the bytes of
:func:`~ga_ros.pipeline.corrections.corrections_cdr` that the node publishes), one tracker per
pair of thresholds on the same run (0:0: every change, bit-exact). Prints, per message, the
bytes per update (mean over the updates, and at the last one), the ratio to the whole path
(target <= 10 %), the entries (poses) sent per update, the keyframes compared per update, the
CPU time per update to build the message (compare the poses, choose the spans) and to serialize
it (CPU time of the calling thread: neither the survey's own work nor a background refinement
running meanwhile in another thread is counted), and the keyframes a consumer re-anchors per
update: the entries that were held before plus those interpolated inside spans; then the
keyframes added per update and their bytes as poses (the floor of one pose per keyframe).

Run: ``ga-ros bench corrections [--tracks 25] [--thresholds M:RAD ...] [--refine-every 0]
[--window-tracks 5]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

from ga_ros.core.window import AlignerConfig
from ga_ros.io.cdr import path_cdr
from ga_ros.pipeline.corrections import (
    ROTATION_RAD,
    TRANSLATION_M,
    CorrectionThresholds,
    CorrectionTracker,
    corrections_cdr,
)
from ga_ros.pipeline.session import AlignmentSession
from ga_ros.replay.samples import aerial_sample

#: Thresholds of the default run (m:rad), the node's default first, 0:0 (every change) last.
SWEEP = [f'{TRANSLATION_M:g}:{ROTATION_RAD:g}', '0.05:0.002', '0.1:0.005', '0.2:0.01', '0:0']


@dataclass
class Tally:
    """What one tracker sent over the survey."""

    label: str
    tracker: CorrectionTracker
    bytes: list[int] = field(default_factory=list)
    keyframes: list[int] = field(default_factory=list)
    compared: list[int] = field(default_factory=list)
    reanchored: list[int] = field(default_factory=list)
    cpu_s: float = 0.0
    cdr_cpu_s: float = 0.0


def _corrections_bytes(tally: Tally, aligner, cp, stamp_ns: int) -> None:
    t0 = time.thread_time()
    c = tally.tracker.after_update(aligner, cp)
    t1 = time.thread_time()
    n = 0
    if c is not None:
        n = len(corrections_cdr(c, 'map', stamp_ns))
    tally.cpu_s += t1 - t0
    tally.cdr_cpu_s += time.thread_time() - t1
    tally.bytes.append(n)
    tally.keyframes.append(0 if c is None else len(c))
    tally.compared.append(0 if c is None else c.n_compared)
    tally.reanchored.append(0 if c is None or c.full
                            else len(c) - c.n_added + c.n_interpolated)


def run(n_tracks: int, thresholds: list[CorrectionThresholds], refine_every: int = 1,
        window_tracks: int = 5) -> tuple[list[int], list[int], float, list[Tally]]:
    """The survey through a session; returns the whole path's bytes and keyframes per update,
    the CPU of serializing it, and one tally per thresholds (side by side on the same run)."""
    ms = aerial_sample(n_tracks=n_tracks).measurements
    session = AlignmentSession(AlignerConfig(refine_every_tracks=refine_every,
                                             window_tracks=window_tracks))
    default = CorrectionThresholds()
    tallies = [Tally(f'corrections ({t.translation_m:g} m, {t.rotation_rad:g} rad'
                     + (', the default)' if t == default else
                        ': every change)' if t.translation_m == t.rotation_rad == 0 else ')'),
                     CorrectionTracker(t)) for t in thresholds]
    full: list[int] = []
    full_kf: list[int] = []
    full_cpu = 0.0

    def after_update() -> None:
        nonlocal full_cpu
        cp = session.aligner.corrected_path()
        stamp = int(cp.stamps_ns[-1])
        t0 = time.thread_time()
        full.append(len(path_cdr(cp.T_world_node, cp.stamps_ns, 'map', stamp)))
        full_kf.append(len(cp.node_ids))
        full_cpu += time.thread_time() - t0
        for t in tallies:
            _corrections_bytes(t, session.aligner, cp, stamp)

    try:
        for m in ms:
            if session.step(m).updates:
                after_update()
        if session.finish_track() is not None:
            after_update()
        n_nodes = session.n_nodes()
    finally:
        session.close()
    print(f'aerial survey: {n_tracks} double tracks, {len(ms):,} measurements, '
          f'{n_nodes:,} keyframes, {len(full)} window updates (aligner: window_tracks '
          f'{window_tracks}, refine_every_tracks {refine_every}; the defaults 5 and 1)')
    return full, full_kf, full_cpu, tallies


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench corrections``: print the table of the module docstring."""
    ap = argparse.ArgumentParser(prog='ga-ros bench corrections',
                                 description=__doc__.split('\n')[0], allow_abbrev=False)
    ap.add_argument('--tracks', type=int, default=25,
                    help='double tracks of the survey (default 25: 5,100 keyframes)')
    ap.add_argument('--thresholds', nargs='+', default=SWEEP, metavar='M:RAD',
                    help='translation (m) and rotation (rad) thresholds, one tracker each on '
                         f'the same run (default: {" ".join(SWEEP)}; the node\'s default is '
                         f'{TRANSLATION_M:g}:{ROTATION_RAD:g})')
    ap.add_argument('--refine-every', type=int, default=1,
                    help='refine_every_tracks of the aligner (default 1, the default; 0: no '
                         'background refinement, only the window moves keyframes)')
    ap.add_argument('--window-tracks', type=int, default=5,
                    help='window_tracks of the aligner (default 5, the default)')
    a = ap.parse_args(argv)
    try:
        thresholds = [CorrectionThresholds(*(float(v) for v in t.split(':')))
                      for t in a.thresholds]
    except (TypeError, ValueError) as exc:
        ap.error(f'--thresholds: M:RAD pairs such as 0.01:0.001 ({exc})')
    full, full_kf, full_cpu, tallies = run(a.tracks, thresholds, a.refine_every,
                                           a.window_tracks)
    n = len(full)
    mean_full = sum(full) / n
    print('CDR bytes of one message after each window update (what DDS sends); CPU: thread '
          'time to build it (compare the poses, choose the spans) and to serialize it, ms per '
          'update (machine shared, figures noisy); '
          're-anchored: keyframes held before that the message moves (entries and inside spans)')
    print('| message | mean bytes / update | ratio to whole path | bytes at last update | '
          'ratio at last | poses sent / update (mean, max) | compared / update | '
          'CPU ms / update: compare + spans | CPU ms / update: serialize | '
          're-anchored / update |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|')
    print(f'| whole path (ga/corrected_path) | {mean_full:,.0f} | 100 % | {full[-1]:,} | 100 % | '
          f'{sum(full_kf) / n:,.0f}, {max(full_kf):,} | - | - | {1e3 * full_cpu / n:.2f} | - |')
    for t in tallies:
        mean = sum(t.bytes) / n
        print(f'| {t.label} | {mean:,.0f} | {100 * mean / mean_full:.1f} % | {t.bytes[-1]:,} | '
              f'{100 * t.bytes[-1] / full[-1]:.1f} % | {sum(t.keyframes) / n:,.0f}, '
              f'{max(t.keyframes):,} | {sum(t.compared) / n:,.0f} | {1e3 * t.cpu_s / n:.2f} | '
              f'{1e3 * t.cdr_cpu_s / n:.2f} | '
              f'{sum(t.reanchored) / n:,.0f} |')
    added = full_kf[-1] / n            # keyframes added per update, the same for every message
    per_pose = full[-1] / full_kf[-1]  # the whole path's bytes per pose
    floor = added * per_pose
    print(f'keyframes added per update: {added:,.0f} (mean); at the whole path of '
          f'{per_pose:.0f} bytes a pose, {floor:,.0f} bytes, {100 * floor / mean_full:.1f} % of '
          'the whole path: the floor of any message of one pose per keyframe')
    return 0
