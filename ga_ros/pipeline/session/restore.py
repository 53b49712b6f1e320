"""A session restored from its state file: the gap healer rebuilt for the recovered aligner, and
the line that says how the state was recovered."""

from __future__ import annotations

from typing import Any

from ga_ros.core.gaps import Bridge, GapConfig, GapHealer, fingerprint
from ga_ros.pipeline.journal import RecoveryResult


def rebuild_gaps(config: GapConfig, aligner: Any, result: RecoveryResult) -> GapHealer:
    """The gap healer of a restored aligner: its nodes and real connections (the journal's
    bridges excepted), its fixes' nodes (joined as when the fixes came), and the held
    measurements the journal still holds (``result``: the recovery of that aligner)."""
    gaps = GapHealer(config)
    gaps.bridges = [Bridge(a, b, float('nan'), float('nan'), float('nan'))
                    for a, b in result.bridges]
    if result.source != 'empty':
        cp = aligner.corrected_path()
        src, dst, z, cross = aligner.connection_arrays()[:4]
        pairs = set(result.bridges)
        kinds = ['bridge' if p in pairs else ('cross' if c else 'consecutive')
                 for p, c in zip(zip(src.tolist(), dst.tolist()), cross.tolist())]
        fixed = getattr(aligner, 'fix_node_ids', None)
        gaps.rebuild(src, dst, z, kinds, cp.node_ids, cp.track_ids, cp.stamps_ns,
                     anchored=fixed() if fixed is not None else None)
    gaps.reversed = {fingerprint(m) for m in result.reversed}
    for m, seq in result.held.held:
        gaps.hold(m, seq)
    gaps.restore_waits(result.held.arrivals, result.held.newest_stamp_ns)
    return gaps


def how(result: RecoveryResult) -> str:
    """One line on a recovery: source, records replayed, files moved aside, seconds."""
    what = 'base' if result.source == 'journal' else 'snapshot'
    text = (f'{result.source}: {what} of {result.snapshot_records} journal records + '
            f'{result.records_replayed} replayed in {result.seconds:.2f} s')
    if result.moved_aside:
        text += '; moved aside: ' + ', '.join(str(p) for p in result.moved_aside)
    return text


def continue_inputs(session: Any, front: Any) -> tuple[int, int] | None:
    """After a restore: the standard inputs ``front`` (an
    :class:`~ga_ros.pipeline.inputs.InputFrontEnd`, before its first sample) number their
    keyframes on after the nodes and tracks of ``session``'s state, on a new track, and the
    session bridges the first new node to the state's newest at once (the motion across the
    restart was never measured). Live odometry after a restart thus continues the survey
    instead of reading as another one (:mod:`~ga_ros.pipeline.session.survey_identity`).
    Returns ``(node id, track id)`` of the first new keyframe (``None``: an empty state, the
    numbering is left as it is)."""
    node_id, track_id = session.next_ids()
    if node_id == 0:
        return None
    front.continue_from(node_id, track_id)
    session.bridge_at_once(node_id)
    return node_id, track_id
