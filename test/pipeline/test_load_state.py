"""``~/load_state`` under running standard inputs (:func:`ga_ros.pipeline.session.restore.
continue_inputs` after :meth:`AlignmentSession.load`): the inputs number on after the loaded
nodes and tracks on a fresh keyframe chain, bridged to the loaded newest node by the
odometry's motion, as after a start; their former numbering never reaches the loaded state."""

from __future__ import annotations

import shutil

import numpy as np
from bag_fixtures import odometry_msg
from test_restart_bridge import _drive, _first_run, _Node

from ga_ros.geometry import se3
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.inputs import InputFrontEnd, InputSpec
from ga_ros.pipeline.keyframe_camera import KeyframeCamera


def test_an_older_save_loaded_under_running_odometry_continues_after_it(tmp_path) -> None:
    """``autosave: false``: saved at 6 nodes, driven on to 12, the save loaded back while the
    odometry runs on. The inputs number on after the loaded nodes (6, on a new track), the
    first new node is joined to the loaded newest one by the odometry's own motion between
    them (its keyframe of that node: no journal, so no ``map -> odom`` record), nothing is
    held, bridged by a guess or rejected, and the new nodes lie on the odometry composed
    with the loaded state's ``map -> odom`` (exact odometry: the truth). Before, the running
    numbering (12, 13, ...) was held as unknown sources and bridged by a guess, silently."""
    drive = _drive(300)
    node = _Node(tmp_path / 'state', autosave=False)
    for T, stamp in drive[:60]:
        node.sample(T, stamp)
    node.session.save()
    saved = node.session.aligner.corrected_path()
    n = len(saved.node_ids)
    assert n == 6
    for T, stamp in drive[60:120]:
        node.sample(T, stamp)
    assert node.session.n_nodes() == 12
    node.load()
    assert node.session.n_nodes() == n and node.session.restart_bridge == 'pending'
    # the loaded state's map -> odom, from the odometry's own keyframe of its newest node
    T_map_odom = saved.T_world_node[-1] @ se3.inverse(drive[50][0])
    np.testing.assert_allclose(node.odom.T_map_odom, T_map_odom, atol=1e-9)
    assert node.odom.placed_by == 'restored'
    for T, stamp in drive[120:260]:
        node.sample(T, stamp)
        assert not node.session.gaps.held
    node.session.finish_track()
    s = node.session
    assert s.restart_bridge == 'measured' and not node.warnings
    assert s.counts.bridges == 0 and s.gaps.n_unjoined == 0 and s.counts.rejected == {}
    cp = s.aligner.corrected_path()
    assert [int(i) for i in cp.node_ids] == list(range(len(cp.node_ids)))
    assert len(cp.node_ids) - n >= 12
    assert int(cp.track_ids[n]) == int(saved.track_ids.max()) + 1
    np.testing.assert_allclose(cp.T_world_node[:n], saved.T_world_node, atol=1e-6)
    for node_id, T_map in zip(cp.node_ids[n:], cp.T_world_node[n:]):
        np.testing.assert_allclose(T_map, T_map_odom @ node.front.keyframe_pose(int(node_id)),
                                   atol=1e-6)
    node.odom.update(cp.node_ids, cp.T_world_node)
    np.testing.assert_allclose(node.odom.T_map_odom, T_map_odom, atol=1e-6)


def test_a_larger_state_loaded_under_running_odometry_never_collides_with_it(tmp_path) -> None:
    """A node started without a state drove 5 keyframes (nodes 0..4); the state of an earlier
    run of the same robot (12 nodes, its ``map -> odom`` journaled) is then put in its state
    file and loaded, and the odometry, the same ``odom`` frame, goes on. The running inputs
    number on after the loaded nodes: no measurement of theirs reaches a loaded node (before,
    their 5->6, 6->7, ... were taken between the loaded nodes with the running motions, or
    rejected), and the first new node is bridged by the motion the journaled ``map -> odom``
    measures."""
    drive = _drive(300)
    state, T_before = _first_run(tmp_path, drive)
    other = tmp_path / 'other'
    other.mkdir()
    node = _Node(other / 'state')
    for T, stamp in drive[:50]:
        node.sample(T, stamp)
    assert node.session.newest_node_id == 4
    node.session.journal.close()
    for f in tmp_path.glob('state*'):
        shutil.copy(f, other / f.name)
    node.load()
    loaded = node.session.aligner.corrected_path()
    n = len(loaded.node_ids)
    assert n == 12
    src, dst = node.session.aligner.connection_arrays()[:2]
    before = sorted(zip(src.tolist(), dst.tolist()))
    np.testing.assert_array_equal(node.odom.T_map_odom, T_before)
    for T, stamp in drive[160:260]:
        node.sample(T, stamp)
    node.session.finish_track()
    s = node.session
    assert s.restart_bridge == 'measured' and not node.warnings
    assert s.counts.rejected == {} and s.counts.bridges == 0 and s.gaps.n_unjoined == 0
    cp = s.aligner.corrected_path()
    assert [int(i) for i in cp.node_ids] == list(range(len(cp.node_ids)))
    src, dst = s.aligner.connection_arrays()[:2]
    among = sorted(zip(src[(src < n) & (dst < n)].tolist(), dst[(src < n) & (dst < n)].tolist()))
    assert among == before, 'a running measurement between loaded nodes'
    np.testing.assert_allclose(cp.T_world_node[:n], loaded.T_world_node, atol=1e-6)
    for node_id, T_map in zip(cp.node_ids[n:], cp.T_world_node[n:]):
        np.testing.assert_allclose(T_map, T_before @ node.front.keyframe_pose(int(node_id)),
                                   atol=1e-6)


def test_a_running_front_end_continued_forgets_its_former_keyframes() -> None:
    """:meth:`InputFrontEnd.continue_from` after samples: the next sample of the first input is
    keyframe ``node_id`` on the new track with no motion from before; the further input's
    keyframe intervals still waiting (its samples lag) and the camera's keyframes waiting for
    images are dropped, so nothing comes out with a former id; the further input measures the
    new chain's intervals."""
    specs = [InputSpec('/a', 'odometry', OdometryInputConfig('odom0', keyframe_travel_m=1.0)),
             InputSpec('/b', 'odometry', OdometryInputConfig('odom1'))]
    front = InputFrontEnd(specs, camera=KeyframeCamera())
    drive = _drive(120)
    out = []
    for T, stamp in drive[:40]:
        out += front.sample('odom0', odometry_msg(T, stamp)).measurements
    assert [m.dst_id for m in out] == [1, 2, 3]
    assert front.inputs['odom1'].stats.pending == 3
    assert front.camera is not None and len(front.camera._waiting) == 4
    front.continue_from(30, 5)
    assert front.inputs['odom1'].stats.pending == 0 and not front.camera._waiting
    out = []
    for k, (T, stamp) in enumerate(drive[40:80]):
        step = front.sample('odom0', odometry_msg(T, stamp))
        if k == 0:   # the next sample is the new chain's first keyframe, with no motion
            assert step.node_stamps == {30: stamp} and not step.measurements
        out += step.measurements
        out += front.sample('odom1', odometry_msg(T, stamp - 1)).measurements
    pairs = {(m.source, m.src_id, m.dst_id, m.src_track, m.dst_track) for m in out}
    assert pairs == {(name, 30 + k, 31 + k, 5, 5) for name in ('odom0', 'odom1')
                     for k in range(3)}
    assert front.keyframe_stamp(30) == drive[40][1]
    np.testing.assert_allclose(front.keyframe_pose(30), drive[40][0], atol=1e-12)
