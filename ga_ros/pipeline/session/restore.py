"""A session restored from its state file: the gap healer rebuilt for the recovered aligner, the
line that says how the state was recovered, and the standard inputs continued after it.

The bridge across a restart of the alignment node (:func:`continue_inputs`)
    The standard inputs of a restarted node number their keyframes on after the restored nodes,
    on a new track; nothing joins the first new keyframe ``new`` to the restored newest node
    ``n``. When the odometry went on across the restart (its ``odom`` frame is the one before),
    that motion is *measured*: the state's last ``map -> odom`` (journaled after each update,
    :class:`~ga_ros.pipeline.journal.MapOdom`) puts the restored node at the odometry pose
    ``T_odom_n = inv(T_map_odom) T_map_n`` (the nodes after the last update are chained by the
    same odometry's motions, so this is the pose the odometry gave ``n``), and the bridge is the
    odometry's motion ``T_n_new = inv(T_odom_n) T_odom_new = inv(T_map_n) T_map_odom T_odom_new``
    (:func:`restart_motion`), an ordinary ``'consecutive'`` measurement of that input: its
    covariance the input's default noise model over that motion
    (:meth:`~ga_ros.inputs.odometry.OdometryInputConfig.default_covariance`) plus
    ``GapConfig.restart_sigma_m`` / ``restart_sigma_rad`` per axis for the restart. It joins the
    new piece, and the first update after the restart leaves ``map -> odom`` where it was
    (within that noise).

    The guess instead (:meth:`~ga_ros.core.gaps.GapHealer.bridge_to`: constant velocity, a
    gap-growing covariance; the new piece not joined), with a warning saying why, when:

    * the state has no ``map -> odom`` (no window update before the restart), or the record
      does not name its node, or that node's restored pose differs from the recorded one (an
      update whose ``map -> odom`` was not journaled: a crash between the two);
    * measurements from before the restart are still held (the bridge would not start at
      ``n``);
    * the odometry restarted too: its stamps went back, the implied mean speed or turn rate over
      the downtime exceeds ``restart_max_speed_mps`` / ``restart_max_rate_rad_per_s``, or its
      first pose is within ``restart_origin_m`` / ``restart_origin_rad`` of its own origin while
      the motion from ``n`` is larger.

    A renamed ``odom`` frame is not told (the state does not hold frame names): set the input's
    ``frame_id`` to refuse another frame.

After ``~/load_state`` under running inputs (the same :func:`continue_inputs`)
    The inputs, which took samples already, start a fresh keyframe chain at their next sample,
    numbered after the loaded nodes on a new track
    (:meth:`~ga_ros.pipeline.inputs.InputFrontEnd.continue_from`), so their former numbering
    never reaches the loaded state. When the first input made the loaded newest node ``n``
    itself (the same id and stamp: a save of this run loaded back), its own pose ``T_odom_n`` of
    that keyframe is the origin, exact and journal-free, and the loaded ``map -> odom`` is
    ``T_map_n inv(T_odom_n)`` (:attr:`AlignmentSession.map_odom_entry
    <ga_ros.pipeline.session.AlignmentSession.map_odom_entry>`); otherwise the loaded journal's
    ``map -> odom`` as above (a state of an earlier run of the same odometry), else the guess.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.gaps import Bridge, GapConfig, GapHealer, fingerprint
from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError
from ga_ros.geometry import se3
from ga_ros.pipeline.journal import MapOdom, RecoveryResult

#: The restored newest node's pose may differ from the one the ``map -> odom`` record holds by
#: this much (m, and rotation-matrix entries) and still count as unmoved (the state is
#: reproduced exactly: this only absorbs rounding).
POSE_ATOL = 1e-6


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


@dataclass(frozen=True)
class RestartOrigin:
    """Where the odometry left the restored survey: its newest node ``node_id`` (stamp
    ``stamp_ns``) at the odometry pose ``T_odom_node`` (4, 4): the one the state's last
    ``map -> odom`` gives it (``by`` ``'map_odom'``), or the running input's own keyframe of
    that node (``by`` ``'keyframe'``, a state loaded under running inputs)."""

    node_id: int
    stamp_ns: int
    T_odom_node: FloatArray
    by: str = 'map_odom'


def restart_origin(session: Any, front: Any = None) -> RestartOrigin | str:
    """The :class:`RestartOrigin` of a restored ``session`` (an
    :class:`~ga_ros.pipeline.session.AlignmentSession`), or why the bridge across the restart
    cannot be measured (module doc). ``front``: the standard inputs (an
    :class:`~ga_ros.pipeline.inputs.InputFrontEnd`, before it forgets its keyframes): when
    their first input made the state's newest node itself (the same id and stamp: a state this
    run saved, loaded back by ``~/load_state``), its own pose of that keyframe is the origin."""
    own = _own_keyframe(session, front)
    if own is not None:
        if session.gaps.held:
            return f'{len(session.gaps.held)} measurements from before the load are still held'
        return own
    entry = getattr(session, 'map_odom_entry', None)
    if entry is None:
        return 'the state holds no map -> odom (no window update before the restart)'
    if entry.node_id < 0 or entry.T_map_node is None:
        return "the state's map -> odom does not name the node it was placed at"
    aligner = session.aligner
    try:
        T_then = aligner.pose(entry.node_id)
    except (GaError, AttributeError) as exc:
        return f"the state's map -> odom names node {entry.node_id}, not in the state ({exc})"
    if not np.allclose(T_then, entry.T_map_node, rtol=0.0, atol=POSE_ATOL):
        return (f'node {entry.node_id} moved after the last journaled map -> odom (an update '
                'whose map -> odom was not saved)')
    if session.gaps.held:
        return f'{len(session.gaps.held)} measurements from before the restart are still held'
    cp = aligner.corrected_path()
    T_odom_n = se3.inverse(np.asarray(entry.T_map_odom, float)) @ np.asarray(
        cp.T_world_node[-1], float)
    return RestartOrigin(int(cp.node_ids[-1]), int(cp.stamps_ns[-1]), T_odom_n)


def _own_keyframe(session: Any, front: Any) -> RestartOrigin | None:
    """The :class:`RestartOrigin` from ``front``'s own keyframe of the state's newest node
    (None: no front end, an empty state, or not its keyframe: another id or stamp)."""
    if front is None:
        return None
    cp = session.aligner.corrected_path()
    if not len(cp.node_ids):
        return None
    node, stamp = int(cp.node_ids[-1]), int(cp.stamps_ns[-1])
    try:
        if front.keyframe_stamp(node) != stamp:
            return None
        T_odom_n = front.keyframe_pose(node)
    except GaError:
        return None
    return RestartOrigin(node, stamp, np.asarray(T_odom_n, float), 'keyframe')


def restart_motion(origin: RestartOrigin, T_odom_new: FloatArray, stamp_ns: int,
                   config: GapConfig) -> FloatArray | str:
    """(4, 4) ``T_n_new``: the odometry's motion from the restored newest node to its first
    keyframe after the restart (pose ``T_odom_new`` at ``stamp_ns``), or why the odometry
    restarted too (its ``odom`` frame reset; module doc)."""
    dt = (int(stamp_ns) - origin.stamp_ns) * 1e-9
    if not dt > 0:
        return (f"the odometry's stamps went back ({dt:.3f} s after node {origin.node_id}): "
                'it restarted too')
    T = se3.relative(origin.T_odom_node, np.asarray(T_odom_new, float))
    z = se3.to_translation_rotvec(T)
    dist, turn = float(np.linalg.norm(z[:3])), float(np.linalg.norm(z[3:]))
    if dist / dt > config.restart_max_speed_mps or turn / dt > config.restart_max_rate_rad_per_s:
        return (f'the odometry implies {dist:.2f} m and {turn:.2f} rad in the {dt:.2f} s since '
                f'node {origin.node_id} (more than gaps.restart_max_speed_mps '
                f'{config.restart_max_speed_mps:g} m/s or restart_max_rate_rad_per_s '
                f'{config.restart_max_rate_rad_per_s:g} rad/s): it restarted too')
    at = se3.to_translation_rotvec(np.asarray(T_odom_new, float))
    near = (np.linalg.norm(at[:3]) <= config.restart_origin_m
            and np.linalg.norm(at[3:]) <= config.restart_origin_rad)
    if near and (dist > config.restart_origin_m or turn > config.restart_origin_rad):
        return (f"the odometry's pose is at its origin while the saved map -> odom puts it "
                f'{dist:.2f} m and {turn:.2f} rad from node {origin.node_id}: it restarted too')
    return T


def measured_bridge(origin: RestartOrigin | str, front: Any, config: GapConfig
                    ) -> Callable[[int, int, int, int], Measurement | str]:
    """The measurement of the bridge across a restart, called by the session when it bridges
    the first new keyframe (``(from node, from track, new node, new track)``): the odometry's
    motion from ``origin`` (:func:`restart_motion`) as a ``'consecutive'`` measurement of the
    first input of ``front`` (an :class:`~ga_ros.pipeline.inputs.InputFrontEnd`), or why the
    bridge is guessed instead."""
    def measure(src_id: int, src_track: int, node_id: int, track_id: int) -> Measurement | str:
        if isinstance(origin, str):
            return origin
        if src_id != origin.node_id:
            return f'the bridge starts at node {src_id}, not the newest restored {origin.node_id}'
        stamp = front.keyframe_stamp(node_id)
        T = restart_motion(origin, front.keyframe_pose(node_id), stamp, config)
        if isinstance(T, str):
            return T
        spec = front.specs[front.primary].config
        cov = spec.default_covariance(se3.to_translation_rotvec(T)) + np.diag(
            [config.restart_sigma_m ** 2] * 3 + [config.restart_sigma_rad ** 2] * 3)
        return Measurement.from_pose(src_id, node_id, src_track, track_id, T, cov, stamp,
                                     'consecutive', spec.name)
    return measure


def continue_inputs(session: Any, front: Any) -> tuple[int, int] | None:
    """After a restore (a start on a state file, or ``~/load_state``): the standard inputs
    ``front`` (an :class:`~ga_ros.pipeline.inputs.InputFrontEnd`; before its first sample, or
    running: it then starts a fresh keyframe chain at its next sample,
    :meth:`~ga_ros.pipeline.inputs.InputFrontEnd.continue_from`) number their keyframes on
    after the nodes and tracks of ``session``'s state, on a new track, and the session bridges
    the first new node to the state's newest at once: measured from the odometry when it went
    on across the restart, else guessed (module doc). Live odometry after a restart thus
    continues the survey instead of reading as another one
    (:mod:`~ga_ros.pipeline.session.survey_identity`), and after a load its numbering never
    collides with the loaded nodes.

    When the origin is the inputs' own keyframe (:func:`restart_origin`), the session's
    :attr:`~ga_ros.pipeline.session.AlignmentSession.map_odom_entry` becomes the
    ``map -> odom`` it gives (``T_map_n inv(T_odom_n)``): what the caller's
    :class:`~ga_ros.pipeline.map_to_odom.MapToOdom` restores, as after a start. Returns
    ``(node id, track id)`` of the first new keyframe (``None``: an empty state, the numbering
    is left as it is)."""
    node_id, track_id = session.next_ids()
    if node_id == 0:
        return None
    session.restart_bridge = 'pending'
    origin = restart_origin(session, front)   # before the inputs forget their keyframes
    if isinstance(origin, RestartOrigin) and origin.by == 'keyframe':
        T_map_n = np.asarray(session.aligner.corrected_path().T_world_node[-1], float)
        session.map_odom_entry = MapOdom(T_map_n @ se3.inverse(origin.T_odom_node),
                                         origin.node_id, T_map_n)
    front.continue_from(node_id, track_id)
    session.bridge_at_once(node_id, measured_bridge(origin, front, session.session.gaps))
    return node_id, track_id
