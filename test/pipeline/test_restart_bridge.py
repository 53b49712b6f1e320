"""The bridge across a restart of the alignment node (:mod:`ga_ros.pipeline.session.restore`):
measured from the odometry when its ``odom`` frame went on, guessed (with a warning) when the
odometry restarted too; journaled like any measurement, so a crash at every cut after the
restart recovers the same state."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import odometry_msg

from ga_ros.core.gaps import GapConfig
from ga_ros.core.measurement import Measurement
from ga_ros.core.tracks import TrackRules
from ga_ros.core.window import AlignerConfig
from ga_ros.geometry import se3
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.inputs import InputFrontEnd, InputSpec
from ga_ros.pipeline.map_to_odom import MapToOdom
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.pipeline.session.restore import (
    RestartOrigin,
    continue_inputs,
    restart_motion,
)

CFG = AlignerConfig(window_tracks=2)
#: the odometry frame's pose in map (the first keyframe's frame): map != odom
T0 = se3.from_translation_rotvec(np.array([4.0, -3.0, 0.0]), np.array([0.0, 0.0, 0.8]))


def _drive(n: int) -> list[tuple[np.ndarray, int]]:
    """``(T_odom_base, stamp_ns)`` of a robot at 1 m/s (10 Hz) turning 90 degrees left every
    50 samples, its odometry starting at ``T0``."""
    out, T = [], T0.copy()
    step = se3.from_translation_rotvec(np.array([0.1, 0.0, 0.0]), np.zeros(3))
    turn = se3.from_translation_rotvec(np.zeros(3), np.array([0.0, 0.0, np.pi / 2]))
    for k in range(n):
        out.append((T.copy(), 10**9 + k * 10**8))
        T = T @ step
        if k % 50 == 49:
            T = T @ turn
    return out


def _front() -> InputFrontEnd:
    return InputFrontEnd([InputSpec('/odom', 'odometry', OdometryInputConfig(
        'odom0', keyframe_travel_m=1.0, track=TrackRules(mode='distance', length_m=5.0)))])


class _Node:
    """What ``alignment_node`` does with standard inputs and a state file (ROS-free): the
    session, the front end, ``map -> odom`` journaled after each update, the restart."""

    def __init__(self, state: Path, compact: int = 1000, autosave: bool = True) -> None:
        self.warnings: list[str] = []
        self.session = AlignmentSession(CFG, SessionConfig(str(state), autosave,
                                                           compact_records=compact),
                                        warn=self.warnings.append)
        self.front = _front()
        self.odom = MapToOdom(self.front)
        self.journal_map_odom = True   # False: a crash comes before each update's record
        if self.session.resume() is not None:
            self.odom.restore(self.session.map_odom)
        continue_inputs(self.session, self.front)

    def load(self) -> str:
        """``~/load_state``: the state file's state, the inputs continued after it and its
        ``map -> odom`` restored, as at a start."""
        how = self.session.load()
        continue_inputs(self.session, self.front)
        self.odom.restore(self.session.map_odom)
        return how

    def sample(self, T: np.ndarray, stamp_ns: int) -> None:
        step = self.front.sample('odom0', odometry_msg(T, stamp_ns))
        assert not step.error, step.error
        for m in step.measurements:
            out = self.session.step(m)
            assert out.accepted, out.error
            if out.updates:
                cp = self.session.aligner.corrected_path()
                self.odom.update(cp.node_ids, cp.T_world_node)
                if self.odom.placed_by == 'aligner' and self.journal_map_odom:
                    self.session.journal_map_odom(self.odom.T_map_odom)

    def loop_closure(self, src: int, dst: int) -> None:
        """A cross-track connection from node ``src`` to ``dst``, 0.5 m off the odometry's
        (the update that takes it moves the nodes)."""
        path = self.session.aligner.corrected_path()
        at = {int(i): k for k, i in enumerate(path.node_ids)}
        T = se3.relative(path.T_world_node[at[src]], path.T_world_node[at[dst]])
        T = T @ se3.from_translation_rotvec(np.array([0.5, 0.0, 0.0]), np.zeros(3))
        m = Measurement.from_pose(src, dst, int(path.track_ids[at[src]]),
                                  int(path.track_ids[at[dst]]), T, np.eye(6) * 1e-2,
                                  int(path.stamps_ns[at[dst]]), 'cross')
        assert self.session.step(m).accepted

    def crash(self) -> None:
        """What the files hold when the process is killed."""
        self.session.journal.close()
        self.session.aligner.close()


def _first_run(tmp_path: Path, drive, compact: int = 1000, unjournaled_from: int = 120,
               stop: int = 120) -> tuple[Path, np.ndarray]:
    """The first run over ``drive[:stop]``, killed; from sample ``unjournaled_from`` on, a
    loop closure comes and the ``map -> odom`` of the updates is never journaled. Returns the
    state and the last ``T_map_odom`` sent."""
    state = tmp_path / 'state'
    first = _Node(state, compact)
    for k, (T, stamp) in enumerate(drive[:stop]):
        if k == unjournaled_from:
            first.journal_map_odom = False
            first.loop_closure(0, first.session.newest_node_id)
        first.sample(T, stamp)
    assert first.odom.placed_by == 'aligner'
    T_before = first.odom.T_map_odom.copy()
    assert np.linalg.norm(T_before[:3, 3]) > 1.0   # map != odom
    first.crash()
    return state, T_before


def test_the_bridge_across_a_restart_is_measured_when_the_odometry_went_on(tmp_path) -> None:
    """Restarted after a downtime in which the robot turned 90 degrees and drove 4 m (the
    odometry's messages of the downtime never heard), the first new node is placed by the
    odometry: every new node at ``T_map_odom T_odom_node`` of the restored correction (the
    odometry is exact here, so the exact chain is the truth), the new piece joined, and the
    first update after the restart leaves ``map -> odom`` where it was. The constant-velocity
    guess would put it 4 m ahead, straight on."""
    drive = _drive(260)
    state, T_before = _first_run(tmp_path, drive)
    node = _Node(state)
    assert node.odom.placed_by == 'restored'
    restored = node.session.aligner.corrected_path()
    for T, stamp in drive[160:]:   # samples 120..159 (the turn at 149) never heard
        node.sample(T, stamp)
    node.session.finish_track()
    assert node.session.restart_bridge == 'measured' and not node.warnings
    assert node.session.counts.bridges == 0 and node.session.gaps.n_unjoined == 0
    assert node.session.diagnostic_values()['restart_bridge'] == 'measured'
    cp = node.session.aligner.corrected_path()
    n = len(restored.node_ids)
    new = cp.node_ids[n:]
    assert len(new) >= 9
    for node_id, T_map in zip(new, cp.T_world_node[n:]):
        truth = T_before @ node.front.keyframe_pose(int(node_id))
        np.testing.assert_allclose(T_map, truth, atol=1e-6)
    np.testing.assert_allclose(cp.T_world_node[:n], restored.T_world_node, atol=1e-6)
    cp_after = node.session.aligner.corrected_path()
    node.odom.update(cp_after.node_ids, cp_after.T_world_node)
    assert node.odom.placed_by == 'aligner'
    np.testing.assert_allclose(node.odom.T_map_odom, T_before, atol=1e-6)


def test_an_odometry_restarted_too_gets_the_guess_with_a_warning(tmp_path) -> None:
    """The odometry restarted with the node (its poses start again from the identity): the
    bridge is the constant-velocity guess, a warning says why, and the survey goes on as
    without the measured bridge (the new piece hangs off the bridge)."""
    drive = _drive(260)
    state, _ = _first_run(tmp_path, drive)
    node = _Node(state)
    restart = se3.inverse(drive[160][0])
    for T, stamp in drive[160:]:
        node.sample(restart @ T, stamp)
    node.session.finish_track()
    assert node.session.restart_bridge.startswith('guessed: ')
    assert 'restarted too' in node.session.restart_bridge
    assert len(node.warnings) == 1 and 'by a guess' in node.warnings[0]
    assert node.session.counts.bridges == 1
    assert node.session.gaps.n_unjoined == len(node.session.aligner.corrected_path().node_ids
                                               ) - 12
    assert node.session.counts.rejected == {}


def test_a_restart_whose_map_to_odom_is_older_than_the_state_gets_the_guess(tmp_path) -> None:
    """The crash came between the last update and its ``map -> odom`` record: the node the
    last record names moved since, so the record does not place the state, and the bridge is
    the guess, with a warning saying why."""
    drive = _drive(260)
    state, _ = _first_run(tmp_path, drive, unjournaled_from=95, stop=140)
    node = _Node(state)
    entry = node.session.map_odom_entry
    assert entry is not None and entry.node_id < node.session.newest_node_id
    for T, stamp in drive[180:220]:
        node.sample(T, stamp)
    assert node.session.restart_bridge.startswith(f'guessed: node {entry.node_id} moved')
    assert len(node.warnings) == 1 and node.session.counts.bridges == 1


def test_restart_motion_tells_an_odometry_that_restarted() -> None:
    """:func:`restart_motion`: the odometry's motion from the restored node, or why its frame
    reset: stamps back, a speed or turn rate beyond the limits, at its origin while the saved
    state puts it far away; a robot that stood still at its origin is measured."""
    cfg = GapConfig()
    T_n = se3.from_translation_rotvec(np.array([20.0, 5.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    origin = RestartOrigin(7, 10**9, T_n)
    moved = T_n @ se3.from_translation_rotvec(np.array([3.0, 1.0, 0.0]),
                                              np.array([0.0, 0.0, 1.5]))
    T = restart_motion(origin, moved, 10**9 + 2 * 10**9, cfg)
    np.testing.assert_allclose(se3.inverse(T_n) @ moved, T, atol=1e-12)
    assert 'went back' in restart_motion(origin, moved, 10**9, cfg)
    assert 'implies' in restart_motion(origin, moved, 10**9 + 2 * 10**8, cfg)   # 16 m/s
    assert 'implies' in restart_motion(origin, moved, 10**9 + 4 * 10**8, cfg)   # 3.75 rad/s
    assert 'at its origin' in restart_motion(origin, np.eye(4), 10**9 + 20 * 10**9, cfg)
    home = RestartOrigin(7, 10**9, se3.from_translation_rotvec(np.array([0.1, 0.0, 0.0]),
                                                               np.zeros(3)))
    assert not isinstance(restart_motion(home, np.eye(4), 10**9 + 10**9, cfg), str)


@pytest.mark.parametrize('compact', [1000, 5])
def test_a_crash_at_every_cut_after_the_restart_recovers_the_same_state(tmp_path,
                                                                         compact) -> None:
    """The measured bridge is journaled like any measurement: after each post-restart sample
    (right after the bridge included), the files recover the live state exactly (from the
    snapshot and the journal, and from the journal alone), and the recovered session marks the
    same nodes unjoined (none) and restores the same ``map -> odom``; with a journal compacted
    at every update too."""
    from test_journal_events import _lose_snapshot, assert_same_state

    drive = _drive(230)
    state, T_before = _first_run(tmp_path, drive, compact)
    node = _Node(state, compact)
    cuts = 0
    for k, (T, stamp) in enumerate(drive[160:]):
        before = node.session.journal.count
        node.sample(T, stamp)
        if node.session.journal.count == before:
            continue
        cuts += 1
        copy = tmp_path / f'cut{k}'
        copy.mkdir()
        for f in tmp_path.glob('state*'):
            if f.is_file():
                shutil.copy(f, copy / f.name.replace('state', 'copy', 1))
        for lose in (False, True):
            if lose:
                _lose_snapshot(copy / 'copy')
            again = AlignmentSession(CFG, SessionConfig(str(copy / 'copy'), autosave=False))
            assert again.resume() is not None
            assert_same_state(again.aligner, node.session.aligner)
            assert again.gaps.n_unjoined == node.session.gaps.n_unjoined == 0
            np.testing.assert_array_equal(again.map_odom, node.session.map_odom
                                          if node.odom.placed_by == 'restored'
                                          else node.odom.T_map_odom)
            again.close()
    assert node.session.restart_bridge == 'measured' and cuts >= 5
    np.testing.assert_allclose(node.odom.T_map_odom, T_before, atol=1e-6)


def test_a_map_odom_record_keeps_its_node_and_pose_exactly() -> None:
    """The ``map -> odom`` record holds the newest node and its pose bit for bit (what a
    restart checks); a record without a node reads back without one."""
    from ga_ros.pipeline.journal import RECORD, MapOdom
    from ga_ros.pipeline.journal.records import encode_map_odom, last_map_odom_entry

    rng = np.random.default_rng(3)
    T = se3.from_translation_rotvec(rng.normal(size=3), rng.normal(size=3))
    N = se3.from_translation_rotvec(rng.normal(size=3) * 100, rng.normal(size=3))
    recs = np.frombuffer(encode_map_odom(MapOdom(T, 41, N)) + encode_map_odom(MapOdom(N)),
                         RECORD)
    first, last = last_map_odom_entry(recs[:1]), last_map_odom_entry(recs)
    assert first.node_id == 41 and last.node_id == -1 and last.T_map_node is None
    np.testing.assert_array_equal(first.T_map_odom, T)
    np.testing.assert_array_equal(first.T_map_node, N)
    np.testing.assert_array_equal(last.T_map_odom, N)
