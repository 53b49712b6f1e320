"""Benchmark: a gap in the measurement stream at survey scale, with and without gap healing.

The paper's aerial survey (``aerial_sample(n_tracks=25)``: 5,100 nodes, 29,896 measurements,
the stream of ``bags/aerial_measurements``) is fed to
:class:`~ga_ros.pipeline.session.AlignmentSession` with the measurements
``[start, start + lost)`` removed (what a node misses while it restarts without a transient-local
history), once with the aligner alone (``gaps.enabled: false``: the
``unknown_source`` cascade) and once with the default :class:`~ga_ros.core.gaps.GapConfig`, and
once whole (the gap-free reference). Prints per run: nodes kept, rejections by reason, bridges,
reversed measurements, nodes left unjoined, and the position difference to the gap-free run
(median / max over the nodes both hold), and the wall time.
Run: ``ga-ros bench gaps [--lost 200 2000] [--start 12022]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ga_ros.core.gaps import GapConfig
from ga_ros.core.window import AlignerConfig
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample


def _run(stream: list, enabled: bool) -> tuple[AlignmentSession, float]:
    t0 = time.perf_counter()
    session = AlignmentSession(AlignerConfig(), SessionConfig(gaps=GapConfig(enabled=enabled)))
    for m in stream:
        session.step(m)
    session.finish_track()
    return session, time.perf_counter() - t0


def _line(label: str, session: AlignmentSession, seconds: float, ref_ids: np.ndarray,
          ref_p: np.ndarray) -> str:
    v = session.diagnostic_values()
    cp = session.aligner.corrected_path()
    pos = {int(k): i for i, k in enumerate(ref_ids)}
    rows = [pos[int(k)] for k in cp.node_ids]
    d = np.linalg.norm(ref_p[rows] - cp.T_world_node[:, :3, 3], axis=1)
    rej = {k[len('rejected/'):]: v[k] for k in v if k.startswith('rejected/')}
    return (f'{label:<22} {v["nodes"]:>6} {v["rejected"]:>8} {str(rej or "-"):<28} '
            f'{v["bridges"]:>7} {v["reversed_measurements"]:>8} {v["unjoined_nodes"]:>8} '
            f'{np.median(d):>9.3f} {d.max():>9.3f} {seconds:>6.0f}')


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench gaps``: print the table of the module docstring."""
    ap = argparse.ArgumentParser(prog='ga-ros bench gaps', description=__doc__.split('\n')[0],
                                 allow_abbrev=False)
    ap.add_argument('--lost', type=int, nargs='+', default=[200, 2000],
                    help='measurements lost, one run pair each (default: 200 2000)')
    ap.add_argument('--start', type=int, default=12022,
                    help='index of the first lost measurement (default: 12022)')
    ap.add_argument('--tracks', type=int, default=25, help='tracks of the survey (default 25)')
    args = ap.parse_args(argv)
    ms = aerial_sample(n_tracks=args.tracks).measurements
    ref, t_ref = _run(ms, True)
    cp = ref.aligner.corrected_path()
    ref_ids, ref_p = cp.node_ids, cp.T_world_node[:, :3, 3].copy()
    print(f'{len(ms)} measurements, {ref_ids.size} nodes; lost: [{args.start}, start + N)')
    print(f'{"run":<22} {"nodes":>6} {"rejected":>8} {"by reason":<28} {"bridges":>7} '
          f'{"reversed":>8} {"unjoined":>8} {"d_med(m)":>9} {"d_max(m)":>9} {"s":>6}')
    print(_line('gap-free', ref, t_ref, ref_ids, ref_p))
    for lost in args.lost:
        stream = ms[:args.start] + ms[args.start + lost:]
        for enabled in (False, True):
            session, t = _run(stream, enabled)
            label = f'{lost} lost, ' + ('gaps healed' if enabled else 'aligner alone')
            print(_line(label, session, t, ref_ids, ref_p), flush=True)
    return 0
