"""Corrections as a topic (:mod:`ga_ros.pipeline.corrections`): a consumer that applies the
messages (entries and interpolated spans) ends within the thresholds of the corrected path, bit
for bit what the tracker says it holds, and exactly the corrected path with thresholds 0;
nothing above the thresholds is missed.

The survey goes through :class:`~ga_ros.pipeline.session.AlignmentSession` as in the node and
the replay (window updates, freezes, background refinements that move frozen tracks).
"""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros import topics
from ga_ros.core.window import AlignerConfig
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.io.bag_messages import PATH, trajectory_to_path_msg, typestore
from ga_ros.io.trajectory import Trajectory
from ga_ros.pipeline.corrections import (
    CorrectionMessage,
    Corrections,
    CorrectionThresholds,
    CorrectionTracker,
    HeldPoses,
    corrections_cdr,
    decoded,
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
          reference: CorrectionTracker | None = None, held: list | None = None
          ) -> tuple[AlignmentSession, list]:
    """Run the survey through a session; after every ``every``-th update (and every 7th
    measurement, as the node's path timer does) ask ``tracker`` (and ``reference`` on the
    whole path) for the corrections. Returns the session and the ``(corrections, reference
    corrections, corrected path)`` of every call; ``held`` gets what the tracker says a
    consumer holds after each call."""
    session = AlignmentSession(CONFIG)
    calls, n_updates = [], 0

    def call() -> None:
        cp = session.aligner.corrected_path()
        c = tracker.after_update(session.aligner, cp)
        r = None if reference is None else reference.compare(cp, 0)
        calls.append((c, r, cp))
        if held is not None:
            held.append(tracker.held())

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
    """Re-anchors only what the corrections say: keyframe (named by its stamp) -> pose, for a
    message without spans (thresholds 0), reading the deserialized message as any ROS consumer
    would. A stamp named twice in a message is two keyframes (in order); named once, it is the
    last keyframe of that stamp (docs/node.md)."""

    def __init__(self) -> None:
        self.poses: dict[int, list[tuple]] = {}
        self.full_messages = 0

    def apply(self, msg) -> None:
        poses = list(msg.poses)
        if poses and poses[0].header.frame_id == topics.CORRECTIONS_FULL_FRAME:
            self.poses.clear()
            self.full_messages += 1
            poses = poses[1:]
        stamp = [ps.header.stamp.sec * 10**9 + ps.header.stamp.nanosec for ps in poses]
        twice: dict[int, list[tuple]] = {}
        for ps, s in zip(poses, stamp):
            assert ps.header.frame_id == 'map'   # the map frame, no span
            p, o = ps.pose.position, ps.pose.orientation
            pose = (p.x, p.y, p.z, o.x, o.y, o.z, o.w)
            if stamp.count(s) == 2:
                twice.setdefault(s, []).append(pose)
                self.poses[s] = twice[s]
            elif s in self.poses:
                self.poses[s][-1] = pose
            else:
                self.poses[s] = [pose]


def read(data: bytes) -> CorrectionMessage:
    """A serialized corrections message as a consumer reads it: deserialized (rosbags),
    poses decoded from position and quaternion, the marker and the span endings read."""
    msg = typestore().deserialize_cdr(data, PATH)
    p = np.array([[ps.pose.position.x, ps.pose.position.y, ps.pose.position.z]
                  for ps in msg.poses]).reshape(-1, 3)
    q = np.array([[ps.pose.orientation.x, ps.pose.orientation.y, ps.pose.orientation.z,
                   ps.pose.orientation.w] for ps in msg.poses]).reshape(-1, 4)
    stamps = np.array([ps.header.stamp.sec * 10**9 + ps.header.stamp.nanosec
                       for ps in msg.poses], np.int64)
    T = se3.from_pos_quat(p, q) if len(p) else np.zeros((0, 4, 4))
    return CorrectionMessage.from_poses([ps.header.frame_id for ps in msg.poses], stamps, T)


def as_tuples(path_msg) -> dict[int, list[tuple]]:
    out: dict[int, list[tuple]] = {}
    for ps in path_msg.poses:
        p, o = ps.pose.position, ps.pose.orientation
        out.setdefault(ps.header.stamp.sec * 10**9 + ps.header.stamp.nanosec, []).append(
            (p.x, p.y, p.z, o.x, o.y, o.z, o.w))
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
                                              cp.track_ids, 'map'))
    assert consumer.full_messages == 1
    assert consumer.poses == as_tuples(final)          # bit-identical poses and stamps
    assert sum(map(len, consumer.poses.values())) == len(cp.node_ids) > 100
    # and less than the whole path after every call
    assert sent < sum(len(p.node_ids) for _, _, p in calls)


def angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of (k, 3, 3) rotations, by the trace (independent of the
    implementation's chord formula)."""
    return np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))


@pytest.fixture(scope='module')
def aerial() -> list:
    """The paper's aerial survey at its own keyframe spacing (204 keyframes a track), 7 tracks:
    the window's corrections vary smoothly along the tracks."""
    return aerial_sample(n_tracks=7).measurements


@pytest.mark.parametrize('which, th', [
    ('survey', CorrectionThresholds()),
    ('aerial', CorrectionThresholds()),
    ('aerial', CorrectionThresholds(translation_m=0.05, rotation_rad=0.002))])
def test_consumer_holds_the_path_within_the_thresholds_at_every_call(which, th, request) -> None:
    """A consumer that reads the serialized messages and applies them (entries and spans,
    :class:`HeldPoses`) holds, after every call of a whole run, every keyframe within the
    thresholds of the corrected path (checked with an angle from the trace, independent of the
    implementation's chord), bit for bit what the tracker says it holds; spans carry most of
    the moved keyframes, so fewer entries are sent than keyframes moved."""
    tracker, held = CorrectionTracker(th), []
    _, calls = drive(request.getfixturevalue(which), tracker, held=held)
    consumer = HeldPoses()
    entries = moved_total = interpolated = spans = 0
    for (c, _, cp), tracker_held in zip(calls, held):
        if c is not None:
            consumer.apply(read(corrections_cdr(c, 'map', int(cp.stamps_ns[-1]))))
            entries += len(c) - c.n_added
            moved_total += c.n_moved
            interpolated += c.n_interpolated
            spans += int(c.span.sum())
        np.testing.assert_array_equal(consumer.stamps_ns, cp.stamps_ns)
        np.testing.assert_array_equal(consumer.T_map_base, tracker_held)
        now, want = consumer.T_map_base, cp.T_world_node
        assert np.linalg.norm(now[:, :3, 3] - want[:, :3, 3], axis=1).max() \
            <= th.translation_m * (1 + 1e-9) + 1e-12
        assert angle(np.einsum('kji,kjl->kil', now[:, :3, :3], want[:, :3, :3])).max() \
            <= th.rotation_rad * 1.0001 + 1e-7
    assert spans > 0 and interpolated > 0 and moved_total > 0
    if which == 'aerial':
        assert entries < 0.6 * moved_total


def test_consumer_of_every_change_holds_the_decoded_path_bit_for_bit(aerial) -> None:
    """Thresholds 0: no span (no interpolation is exact); the consumer holds what the whole
    path's message decodes to, bit for bit."""
    tracker = CorrectionTracker(CorrectionThresholds(0.0, 0.0))
    _, calls = drive(aerial[:len(aerial) // 2], tracker)
    consumer = HeldPoses()
    for c, _, cp in calls:
        if c is not None:
            assert not c.span.any()
            consumer.apply(read(corrections_cdr(c, 'map', int(cp.stamps_ns[-1]))))
        np.testing.assert_array_equal(consumer.T_map_base, decoded(cp.T_world_node))


def test_a_span_interpolates_the_correction_as_documented() -> None:
    """Three keyframes held, a message of the two ends as a span: the middle one gets the
    correction interpolated by stamp, computed here from the documented formula with SciPy's
    slerp-free quaternion arithmetic (normalised linear)."""
    from scipy.spatial.transform import Rotation

    held = np.array([se3.from_translation_rotvec(np.array([10.0 * k, 5.0, 1.0]),
                                                 np.array([0.0, 0.0, 0.1 * k])) for k in range(3)])
    consumer = HeldPoses()
    consumer.apply(CorrectionMessage(True, np.array([100, 130, 200]), held, np.zeros(3, bool)))
    dA = se3.from_translation_rotvec(np.array([0.2, -0.1, 0.0]), np.array([0.0, 0.0, 0.01]))
    dB = se3.from_translation_rotvec(np.array([0.5, 0.3, 0.1]), np.array([0.01, 0.0, -0.02]))
    new = np.array([dA @ held[0], dB @ held[2]])
    stamps, T = consumer.apply(CorrectionMessage(False, np.array([100, 200]), new,
                                                 np.array([False, True])))
    np.testing.assert_array_equal(stamps, [100, 130, 200])
    f = 0.3
    qa, qb = Rotation.from_matrix(dA[:3, :3]).as_quat(), Rotation.from_matrix(dB[:3, :3]).as_quat()
    qb = qb if qa @ qb >= 0 else -qb
    q = (1 - f) * qa + f * qb
    R = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
    t = (1 - f) * dA[:3, 3] + f * dB[:3, 3]
    want = np.eye(4)
    want[:3, :3], want[:3, 3] = R @ held[1][:3, :3], R @ held[1][:3, 3] + t
    np.testing.assert_allclose(T[1], want, atol=1e-12)
    np.testing.assert_array_equal(T[[0, 2]], new)
    # a span whose anchor is not held is refused, nothing changed
    before = consumer.T_map_base.copy()
    with pytest.raises(InputError, match='span'):
        consumer.apply(CorrectionMessage(False, np.array([150, 200]), new,
                                         np.array([False, True])))
    np.testing.assert_array_equal(consumer.T_map_base, before)
    with pytest.raises(InputError, match='span'):   # a full message too: nothing dropped
        consumer.apply(CorrectionMessage(True, np.array([100, 200]), new,
                                         np.array([False, True])))
    np.testing.assert_array_equal(consumer.T_map_base, before)
    with pytest.raises(InputError, match='first entry'):
        CorrectionMessage(False, np.array([100]), new[:1], np.array([True]))


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
        frames, stamps, T = message_poses(first, 'map', 123)
        assert frames[0] == topics.CORRECTIONS_FULL_FRAME and stamps[0] == 123
        assert len(frames) == len(first) + 1
        np.testing.assert_array_equal(T[0], T[1])   # the marker sits on the first keyframe
        assert frames[1:] == ['map'] * len(first)   # the map frame: 72 bytes a pose
        assert not first.span.any()
        assert tracker.after_update(session.aligner) is None   # nothing moved or was added
        session.reset()                                        # a new aligner: full, empty
        empty = tracker.after_update(session.aligner)
        assert empty.full and len(empty) == 0
        frames, _, T = message_poses(empty, 'map', 5)
        assert frames == [topics.CORRECTIONS_FULL_FRAME] and np.array_equal(T[0], np.eye(4))
        for m in survey[:30]:
            session.step(m)
        again = tracker.after_update(session.aligner)
        assert not again.full and again.n_added == session.n_nodes()
        tracker.restart()                                      # e.g. load_state
        assert tracker.after_update(session.aligner).full
    finally:
        session.close()


class _Aligner:
    """An aligner as the tracker sees it: no update counter, every row mutable."""


def test_a_replaced_aligner_at_the_address_of_the_old_one_gives_a_full_message(survey) -> None:
    """A new aligner object (a reset, ``load_state``) gives a full message even when it sits
    where the old one was (CPython reuses a freed object's address, so its ``id``)."""
    session = AlignmentSession(CONFIG)
    try:
        for m in survey[:60]:
            session.step(m)
        path = session.aligner.corrected_path()
    finally:
        session.close()
    tracker = CorrectionTracker()
    old = _Aligner()
    address = id(old)
    assert tracker.after_update(old, path).full
    assert tracker.after_update(old, path) is None   # the same aligner: nothing moved
    del old
    new = [_Aligner() for _ in range(100)]   # one of them at the freed address, as a rule
    first = next((a for a in new if id(a) == address), new[0])
    for a in (first, next(a for a in new if a is not first)):
        c = tracker.after_update(a, path)
        assert c is not None and c.full and len(c) == len(path.node_ids)


def test_thresholds_are_checked() -> None:
    with pytest.raises(InputError, match='translation_m'):
        CorrectionThresholds(translation_m=-1.0)
    with pytest.raises(InputError, match='rotation_rad'):
        CorrectionThresholds(rotation_rad=float('nan'))


def test_corrections_len() -> None:
    z = np.zeros(0, dtype=np.int64)
    assert len(Corrections(False, z, z, z, z, np.zeros((0, 4, 4)), np.zeros(0, bool), 0, 0,
                           0)) == 0


def test_keyframes_sharing_a_stamp_are_named_together() -> None:
    """The first two keyframes share a stamp: whenever one of them is sent (added, moved), both
    are, so a consumer that names keyframes by stamp (twice: the first is the keyframe
    before) holds what the tracker holds."""
    rng = np.random.default_rng(1)
    T = se3.from_translation_rotvec(rng.normal(0, 10, (5, 3)), rng.normal(0, 1, (5, 3)))
    stamps = np.array([5, 5, 6, 7, 8]) * 10**9

    def path(n: int, T: np.ndarray) -> Trajectory:
        return Trajectory(stamps[:n], T[:n], np.arange(n), np.zeros(n, np.int64), 'map')

    tracker, consumer = CorrectionTracker(), HeldPoses()
    for n, moved_row in ((1, None), (2, None), (4, 0), (5, 1)):
        if moved_row is not None:
            T = T.copy()
            T[moved_row, :3, 3] += 0.5
        c = tracker.compare(path(n, T))
        sent = set(c.rows.tolist())
        assert (0 in sent) == (1 in sent) or n == 1
        consumer.apply(read(corrections_cdr(c, 'map', int(stamps[n - 1]))))
        np.testing.assert_array_equal(consumer.T_map_base, tracker.held())
        np.testing.assert_array_equal(consumer.T_map_base, decoded(T[:n]))


def random_updates(rng: np.random.Generator, n_tracks: int = 6, per_track: int = 40
                   ) -> list[Trajectory]:
    """Corrected paths of a random survey after each of ``n_tracks`` updates: straight tracks
    of ``per_track`` keyframes (stamps 1 s apart, jittered), each update adding a track and
    moving every held keyframe by a smooth random correction (a rotation of a few mrad about a
    random point, drifting along the path) plus keyframe-by-keyframe noise of 0-3 cm on the
    newest tracks, as a window update does."""
    paths, T = [], np.zeros((0, 4, 4))
    stamps = np.zeros(0, np.int64)
    for u in range(n_tracks):
        x = np.arange(per_track) * 10.0 * (1 if u % 2 == 0 else -1) + (0 if u % 2 == 0 else 400)
        new = se3.from_translation_rotvec(
            np.stack([x, np.full(per_track, 40.0 * u), rng.normal(50.0, 0.5, per_track)], 1),
            rng.normal(0.0, 0.05, (per_track, 3)))
        s0 = int(stamps[-1]) + 10**9 if stamps.size else 10**9
        new_stamps = s0 + 10**9 * np.arange(per_track) + rng.integers(0, 10**8, per_track)
        n = len(T)
        if n:
            f = np.linspace(0.0, 1.0, n)[:, None]
            rot = rng.normal(0.0, 0.003, 3) * f + rng.normal(0.0, 0.001, 3)
            pivot = rng.normal(0.0, 200.0, 3)
            d = se3.from_translation_rotvec(rng.normal(0.0, 0.1, 3) * f, rot)
            d[:, :3, 3] += pivot - np.einsum('kij,j->ki', d[:, :3, :3], pivot)
            T = np.einsum('kij,kjl->kil', d, T)
            recent = np.arange(n) >= n - 2 * per_track
            T[recent, :3, 3] += rng.normal(0.0, rng.uniform(0.0, 0.03), (recent.sum(), 3))
        T = np.concatenate([T, new])
        stamps = np.concatenate([stamps, new_stamps])
        ids = np.arange(len(T))
        paths.append(Trajectory(stamps.copy(), T.copy(), ids, ids // per_track, 'map'))
    return paths


def strip_spans(data: bytes) -> CorrectionMessage:
    """A consumer that does not read the span endings: every entry a plain one."""
    msg = read(data)
    return CorrectionMessage(msg.full, msg.stamps_ns, msg.T_map_base,
                             np.zeros_like(msg.span))


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_random_corrections_decode_within_the_thresholds(seed) -> None:
    """decode(encode(x)) on random correction fields: the serialized messages (entries named by
    stamp, in the map frame, 72 bytes each but a span's 80), read back and applied, leave the
    consumer within the thresholds of every corrected path and bit for bit what the tracker
    holds; spans carry keyframes. A consumer that reads the spans as plain entries (the failing
    case) leaves keyframes beyond the thresholds."""
    th = CorrectionThresholds()
    tracker, good, naive = CorrectionTracker(th), HeldPoses(), HeldPoses()
    interpolated, worst_naive = 0, 0.0
    for traj in random_updates(np.random.default_rng(seed)):
        c = tracker.compare(traj)
        data = corrections_cdr(c, 'map', int(traj.stamps_ns[-1]))
        n_span = int(c.span.sum())
        # CDR: 4 encapsulation + 20 header, up to 4 of alignment before the first pose, the
        # marker 88 at most, 72 a pose, 8 more a span's ('map/span')
        assert len(data) <= 28 + 88 * c.full + 72 * len(c) + 8 * n_span
        good.apply(read(data))
        naive.apply(strip_spans(data))
        interpolated += c.n_interpolated
        np.testing.assert_array_equal(good.T_map_base, tracker.held())
        want = traj.T_world_node
        for held, ok in ((good, True), (naive, False)):
            dt = np.linalg.norm(held.T_map_base[:, :3, 3] - want[:, :3, 3], axis=1).max()
            dr = angle(np.einsum('kji,kjl->kil', held.T_map_base[:, :3, :3],
                                 want[:, :3, :3])).max()
            if ok:
                assert dt <= th.translation_m * (1 + 1e-9) and dr <= th.rotation_rad * 1.0001
            else:
                worst_naive = max(worst_naive, dt / th.translation_m, dr / th.rotation_rad)
    assert interpolated > 0
    assert worst_naive > 2.0   # the spans matter: without them keyframes are far beyond
