"""Corrections as a topic (:mod:`ga_ros.pipeline.corrections`): a consumer that re-anchors only
what the corrections say ends with the corrected path; nothing above the thresholds is missed.

The survey goes through :class:`~ga_ros.pipeline.session.AlignmentSession` as in the node and
the replay (window updates, freezes, background refinements that move frozen tracks).
"""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros import topics
from ga_ros.core.frames import parse_node_frame
from ga_ros.core.window import AlignerConfig
from ga_ros.errors import InputError
from ga_ros.io.bag_messages import PATH, trajectory_to_path_msg, typestore
from ga_ros.io.trajectory import Trajectory
from ga_ros.pipeline.corrections import (
    Corrections,
    CorrectionThresholds,
    CorrectionTracker,
    corrections_cdr,
    message_poses,
)
from ga_ros.pipeline.session import AlignmentSession
from ga_ros.replay.samples import aerial_sample

#: 10 tracks (two swaths of 8 keyframes each): more than the window (5), so tracks freeze and the
#: background refinement (every track, its last 3 tracks; thread executor: no process spawn in
#: a test) moves frozen ones.
CONFIG = AlignerConfig(refine_executor='thread', refine_horizon_tracks=3)


@pytest.fixture(scope='module')
def survey() -> list:
    return aerial_sample(n_tracks=10, positions_per_swath=8, noise_pct=5.0, seed=3).measurements


def drive(measurements: list, tracker: CorrectionTracker, every: int = 1,
          reference: CorrectionTracker | None = None) -> tuple[AlignmentSession, list]:
    """Run the survey through a session; after every ``every``-th update (and every 7th
    measurement, as the node's path timer does) ask ``tracker`` (and ``reference`` on the
    whole path) for the corrections. Returns the session and the ``(corrections, reference
    corrections, corrected path)`` of every call."""
    session = AlignmentSession(CONFIG)
    calls, n_updates = [], 0

    def call() -> None:
        cp = session.aligner.corrected_path()
        c = tracker.after_update(session.aligner, cp)
        r = None if reference is None else reference.compare(cp, 0)
        calls.append((c, r, cp))

    try:
        for k, m in enumerate(measurements):
            out = session.step(m)
            n_updates += len(out.updates)
            if (out.updates and n_updates % every == 0) or k % 7 == 0:
                call()
        session.finish_track()
        call()
    finally:
        session.close()
    return session, calls


class Consumer:
    """Re-anchors only what the corrections say: keyframe (node frame) -> pose."""

    def __init__(self) -> None:
        self.poses: dict[str, tuple] = {}
        self.full_messages = 0

    def apply(self, msg) -> None:
        poses = list(msg.poses)
        if poses and poses[0].header.frame_id == topics.CORRECTIONS_FULL_FRAME:
            self.poses.clear()
            self.full_messages += 1
            poses = poses[1:]
        for ps in poses:
            p, o = ps.pose.position, ps.pose.orientation
            self.poses[ps.header.frame_id] = (p.x, p.y, p.z, o.x, o.y, o.z, o.w,
                                             ps.header.stamp.sec, ps.header.stamp.nanosec)


def as_tuples(path_msg) -> dict[str, tuple]:
    out = {}
    for ps in path_msg.poses:
        p, o = ps.pose.position, ps.pose.orientation
        out[ps.header.frame_id] = (p.x, p.y, p.z, o.x, o.y, o.z, o.w, ps.header.stamp.sec,
                                   ps.header.stamp.nanosec)
    return out


def test_consumer_of_every_change_ends_with_the_corrected_path_bit_for_bit(survey) -> None:
    tracker = CorrectionTracker(CorrectionThresholds(0.0, 0.0))
    session, calls = drive(survey, tracker)
    consumer = Consumer()
    sent = 0
    for c, _, cp in calls:
        if c is not None:
            data = corrections_cdr(c, 'map', int(cp.stamps_ns[-1]))   # what DDS carries
            consumer.apply(typestore().deserialize_cdr(data, PATH))
            sent += len(c)
    cp = calls[-1][2]
    final = trajectory_to_path_msg(Trajectory(cp.stamps_ns, cp.T_world_node, cp.node_ids,
                                              cp.track_ids, 'map'), node_frames=True)
    assert consumer.full_messages == 1
    assert consumer.poses == as_tuples(final)          # bit-identical poses and stamps
    assert len(consumer.poses) == len(cp.node_ids) > 100
    # and less than the whole path after every call
    assert sent < sum(len(p.node_ids) for _, _, p in calls)


def angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of (k, 3, 3) rotations, by the trace (independent of the
    implementation's chord formula)."""
    return np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))


def test_nothing_above_the_thresholds_is_missed(survey) -> None:
    """Against an independent full comparison of every keyframe with what the consumer holds:
    every keyframe moved beyond a threshold is sent, none below is, and the consumer stays
    within the thresholds of the corrected path at every call."""
    th = CorrectionThresholds(translation_m=0.05, rotation_rad=0.002)
    _, calls = drive(survey, CorrectionTracker(th))
    held: dict[int, np.ndarray] = {}
    moved_total = 0
    for c, _, cp in calls:
        ids = [int(i) for i in cp.node_ids]
        old = np.array([held.get(i, np.full((4, 4), np.nan)) for i in ids])
        dt = np.linalg.norm(cp.T_world_node[:, :3, 3] - old[:, :3, 3], axis=1)
        dr = angle(np.einsum('kji,kjl->kil', old[:, :3, :3], cp.T_world_node[:, :3, :3]))
        new = np.isnan(dt)
        clearly = ~new & ((dt > th.translation_m * (1 + 1e-6))
                          | (dr > th.rotation_rad * (1 + 1e-6)))
        surely_not = ~new & (dt < th.translation_m * (1 - 1e-6)) & (
            dr < th.rotation_rad * (1 - 1e-6))
        got = set() if c is None else {int(i) for i in c.node_ids}
        want = {i for i, f in zip(ids, clearly) if f} | {i for i, f in zip(ids, new) if f}
        assert want <= got
        assert not ({i for i, f in zip(ids, surely_not) if f} & got)
        if c is not None:
            for i, T in zip(c.node_ids.tolist(), c.T_world_node):
                held[i] = T
            moved_total += c.n_moved
        # the consumer is within the thresholds of the corrected path
        now = np.array([held[i] for i in ids])
        assert np.linalg.norm(now[:, :3, 3] - cp.T_world_node[:, :3, 3], axis=1).max() \
            <= th.translation_m
        assert angle(np.einsum('kji,kjl->kil', now[:, :3, :3],
                               cp.T_world_node[:, :3, :3])).max() <= th.rotation_rad * 1.0001
    assert moved_total > 0


@pytest.mark.parametrize('every', [1, 2])
def test_window_bound_gives_what_the_whole_comparison_gives(survey, every) -> None:
    """Comparing from the aligner's first mutable row (the window and the refinement's horizon)
    sends exactly what comparing every row sends, with one or several updates between calls,
    and compares fewer keyframes."""
    th = CorrectionThresholds(0.0, 0.0)
    _, calls = drive(survey, CorrectionTracker(th), every=every,
                     reference=CorrectionTracker(th))
    compared = whole = 0
    for c, r, _ in calls:
        assert (c is None) == (r is None)
        if c is None:
            continue
        assert c.full == r.full
        np.testing.assert_array_equal(c.rows, r.rows)
        np.testing.assert_array_equal(c.T_world_node, r.T_world_node)
        compared += c.n_compared
        whole += r.n_compared
    assert compared < whole


def test_full_message_at_start_reset_and_replacement(survey) -> None:
    session = AlignmentSession(CONFIG)
    tracker = CorrectionTracker()
    try:
        for m in survey[:60]:
            session.step(m)
        first = tracker.after_update(session.aligner)
        assert first.full and len(first) == session.n_nodes() and first.n_moved == 0
        frames, stamps, T = message_poses(first, 123)
        assert frames[0] == topics.CORRECTIONS_FULL_FRAME and stamps[0] == 123
        assert len(frames) == len(first) + 1
        np.testing.assert_array_equal(T[0], T[1])   # the marker sits on the first keyframe
        assert [parse_node_frame(f)[1] for f in frames[1:]] == first.node_ids.tolist()
        assert tracker.after_update(session.aligner) is None   # nothing moved or was added
        session.reset()                                        # a new aligner: full, empty
        empty = tracker.after_update(session.aligner)
        assert empty.full and len(empty) == 0
        frames, _, T = message_poses(empty, 5)
        assert frames == [topics.CORRECTIONS_FULL_FRAME] and np.array_equal(T[0], np.eye(4))
        for m in survey[:30]:
            session.step(m)
        again = tracker.after_update(session.aligner)
        assert not again.full and again.n_added == session.n_nodes()
        tracker.restart()                                      # e.g. load_state
        assert tracker.after_update(session.aligner).full
    finally:
        session.close()


def test_thresholds_are_checked() -> None:
    with pytest.raises(InputError, match='translation_m'):
        CorrectionThresholds(translation_m=-1.0)
    with pytest.raises(InputError, match='rotation_rad'):
        CorrectionThresholds(rotation_rad=float('nan'))


def test_corrections_len() -> None:
    z = np.zeros(0, dtype=np.int64)
    assert len(Corrections(False, z, z, z, z, np.zeros((0, 4, 4)), 0, 0, 0)) == 0
