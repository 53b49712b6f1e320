"""Fault cases run on the alignment session in process (the ROS-free object the node drives,
:class:`~ga_ros.pipeline.session.AlignmentSession`, with the node's default settings): recovery
from the journal alone of a survey with absolute fixes of two sources and two odometry
sources, compared with the uninterrupted run bit for bit."""

from __future__ import annotations

import time

import numpy as np

from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig
from ga_ros.core.window.persistence import state_arrays
from ga_ros.pipeline.journal import recover
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.ros.fault_catalogue.survey import Ctx, Row, nodes_kept
from ga_ros.sim.fix_survey import feed_entries, line_fix_survey


def fixes_survey(rng: np.random.Generator, n_tracks: int = 5, per: int = 8) -> list:
    """A line survey of ``n_tracks * per`` nodes (:func:`~ga_ros.sim.fix_survey.line_fix_survey`):
    frame-to-frame measurements of two odometry sources (``odom0`` on even nodes, ``odom1``,
    noisier, on odd ones) and absolute fixes of two sources (``gnss0`` every third node,
    ``usbl1`` every fifth), each with a lever arm and the odometry offset's covariance."""
    return line_fix_survey(rng, n_tracks, per, odometry=(('odom0', 0.05), ('odom1', 0.1)))


def feed(session: AlignmentSession, entries: list) -> int:
    """Feed the entries, then the end of input; returns the fixes the aligner refused."""
    refused = feed_entries(session, entries)
    session.finish_track('end_of_input')
    return refused


def differing_arrays(a, b) -> list[str]:
    """Names of the window-state arrays and scalars that differ between two aligners (bit
    for bit; the rejection counters aside: refused inputs are not journaled)."""
    meta_a, arr_a = state_arrays(a.state)
    meta_b, arr_b = state_arrays(b.state)
    out = [k for k in sorted(set(meta_a) | set(meta_b))
           if k != 'rejected' and k != 'fixes' and meta_a.get(k) != meta_b.get(k)]
    fa, fb = dict(meta_a.get('fixes') or {}), dict(meta_b.get('fixes') or {})
    for f in (fa, fb):
        if 'stats' in f:
            f['stats'] = dict(f['stats'], rejected=None)
    if fa != fb:
        out.append('fixes')
    for name in sorted(set(arr_a) | set(arr_b)):
        if name not in arr_a or name not in arr_b or not np.array_equal(arr_a[name], arr_b[name]):
            out.append(name)
    return out


def case_journal_only_fixes(ctx: Ctx) -> Row:
    """The whole survey, the end of input, then the process is killed (the journal closed,
    nothing else written), the snapshot emptied and no publisher history: the state recovered
    from the journal alone against the uninterrupted run."""
    entries = fixes_survey(np.random.default_rng(11))
    config = AlignerConfig()
    state = ctx.work / 'state'
    live = AlignmentSession(config, SessionConfig(str(state)))
    live.resume()
    refused = feed(live, entries)
    ref = live.aligner.corrected_path()
    live.journal.close()                       # killed: nothing else written
    state.write_bytes(b'')
    t0 = time.monotonic()
    res = recover(state, config)
    recover_s = time.monotonic() - t0
    try:
        got = res.aligner.corrected_path()
        same = (np.array_equal(got.node_ids, ref.node_ids)
                and np.array_equal(got.T_world_node, ref.T_world_node))
        diff = differing_arrays(res.aligner, live.aligner)
        n_fixes = sum(not isinstance(e, Measurement) for e in entries)
        return Row('journal only (snapshot emptied, no history): fixes of 2 sources, 2 odometry '
                   'sources (session in process)', 'yes', f'{res.source}; {n_fixes - refused}/'
                   f'{n_fixes} fixes taken; path {"bit-identical" if same else "DIFFERS"}; '
                   f'state {"bit-identical" if not diff else "DIFFERS: " + ",".join(diff)[:40]}',
                   len(ref.node_ids), nodes_kept(ref.T_world_node, got.T_world_node), recover_s,
                   f'{res.records_replayed} records replayed')
    finally:
        res.aligner.close()
        live.aligner.close()
