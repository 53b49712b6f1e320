"""The alignment node on a robot: standard inputs, run-time parameters, lifecycle (in-process),
``/tf`` received by a plain subscriber and two namespaced nodes on one domain (processes)."""

from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('tf2_msgs.msg')

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry, Path  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from ga_ros.core.encoding import pose_to_matrix  # noqa: E402
from ga_ros.geometry import se3  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.alignment_node import AlignmentNode  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import (  # noqa: E402
    NodeClient,
    domain_id,
    ros_context,
    start_node_process,
    stop_process,
)
from ga_ros.ros.lifecycle_alignment_node import LifecycleAlignmentNode  # noqa: E402
from ga_ros.ros.qos import latched_qos  # noqa: E402
from ga_ros.sim.aerial import aerial_scenario  # noqa: E402
from ga_ros.sim.noise import NoiseModel, perturb  # noqa: E402

INPUT_PARAMS = {'inputs': 'odom0', 'odom0.topic': 'odom', 'odom0.track.mode': 'distance',
                'odom0.track.length_m': 5.0, 'publish_markers': False}


def odom_msgs(n: int = 200, step_m: float = 0.1) -> list[Odometry]:
    """A robot driving a 5 m square at ``step_m`` per message, all-zero covariance (Nav2)."""
    out = []
    T = np.eye(4)
    turn = se3.from_translation_rotvec(np.zeros(3), np.array([0, 0, np.pi / 2]))
    for k in range(n):
        msg = conv.odometry_msg(T, np.zeros((6, 6)), 'odom', 'base_link', 10**9 + k * 10**8)
        out.append(msg)
        T = T @ se3.from_translation_rotvec(np.array([step_m, 0, 0]), np.zeros(3))
        if k % 50 == 49:
            T = T @ turn
    return out


@pytest.fixture
def ctx():
    with ros_context(domain_id(21)) as c:
        yield c


def _node(cls, ctx, **extra):
    params = {**INPUT_PARAMS, 'diagnostics_period_sec': 0.0, 'allow_finish_track': True,
              'transform_publish_period_sec': 0.0, **extra}
    return cls(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                 for k, v in params.items()])


def test_odometry_input_in_process_map_to_odom(ctx):
    node = _node(AlignmentNode, ctx)
    try:
        for msg in odom_msgs():
            node._on_input('odom0', msg)
        st = node.front.inputs['odom0'].stats
        assert st.keyframes == 20 and st.default_covariances == st.measurements == 19
        assert node.session.counts.accepted == 19
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        cp = node.aligner.corrected_path()
        assert len(cp.node_ids) == 20
        # map -> odom composes with the odometry pose of the newest node to its corrected pose
        T_odom_k = node.front.inputs['odom0'].keyframe_pose(int(cp.node_ids[-1]))
        np.testing.assert_allclose(node.odom.T_map_odom @ T_odom_k, cp.T_world_node[-1],
                                   atol=1e-9)
    finally:
        node.destroy_node()


def test_runtime_parameters_take_effect_and_read_only_ones_say_why(ctx):
    node = _node(AlignmentNode, ctx)
    try:
        ok = node.set_parameters([Parameter('outlier_chi2_prob', value=0.5),
                                  Parameter('map_frame', value='world'),
                                  Parameter('warn_throttle_sec', value=7)])
        assert all(r.successful for r in ok)
        assert node.aligner.config.outlier_chi2_prob == 0.5
        assert node.session.config.outlier_chi2_prob == 0.5
        assert node.settings.map_frame == 'world' and node.settings.warn_throttle_sec == 7.0
        assert not node.set_parameters([Parameter('window_tracks', value=3)])[0].successful
        assert not node.set_parameters([Parameter('outlier_chi2_prob', value=1.5)])[0].successful
        assert not node.set_parameters([Parameter('covariance_policy', value='x')])[0].successful
        assert node.aligner.config.outlier_chi2_prob == 0.5
        assert 'read-only: ' in node.describe_parameter('window_tracks').description
        # nested solver settings: dotted names, run-time ones applied, read-only ones refused
        ok = node.set_parameters([Parameter('solver.tolerance', value=1e-5),
                                  Parameter('solver.robust_loss', value='huber')])
        assert all(r.successful for r in ok)
        assert node.aligner.config.solver.tolerance == 1e-5
        assert node.session.config.solver.robust_loss == 'huber'
        assert node.aligner.config.solver.max_iterations == 10  # the others are kept
        assert not node.set_parameters([Parameter('solver.damping', value='lm')])[0].successful
        assert not node.set_parameters([Parameter('solver.max_iterations',
                                                  value=0)])[0].successful
        assert not node.set_parameters([Parameter('solver.robust_loss',
                                                  value='zzz')])[0].successful
        assert node.aligner.config.solver.robust_loss == 'huber'
        assert 'SolverConfig.damping' in node.describe_parameter('solver.damping').description
        assert 'read-only: ' in node.describe_parameter('odom0.keyframe_travel_m').description
        assert not node.describe_parameter('map_frame').read_only
        # the new frame is used by the next output
        for msg in odom_msgs(60):
            node._on_input('odom0', msg)
        paths: list = []
        node.pub_window.publish = paths.append
        node._publish_outputs()
        assert paths and paths[-1].header.frame_id == 'world'
    finally:
        node.destroy_node()


def test_lifecycle_node_processes_only_when_active(ctx):
    node = _node(LifecycleAlignmentNode, ctx)
    try:
        msgs = odom_msgs(60)
        for msg in msgs[:20]:
            node._on_input('odom0', msg)
        assert node.dropped_inactive == 20 and node.session.counts.received == 0
        node.trigger_configure()
        node.trigger_activate()
        for msg in msgs[20:]:
            node._on_input('odom0', msg)
        assert node.session.counts.accepted == 3  # keyframes at 21, 31, 41, 51 (1 m apart)
        node.trigger_deactivate()
        node.trigger_cleanup()
        assert node.session.n_nodes() == 0
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_tf_reaches_a_plain_subscriber(tmp_path):
    """Two processes: the node gets /odom and publishes map -> odom on /tf; this process reads
    /tf with a plain subscription (no tf2 listener)."""
    dom = domain_id(22)
    proc = start_node_process(dom, {**INPUT_PARAMS, 'diagnostics_period_sec': 0.2},
                              log_path=tmp_path / 'node.log')
    try:
        with NodeClient(dom) as client:
            pub = client.node.create_publisher(Odometry, '/odom', 100)
            tf = client.record(TFMessage, '/tf')
            client.spin_until(lambda: pub.get_subscription_count() > 0, 30, 'the node', proc)
            for msg in odom_msgs():
                pub.publish(msg)
                client.executor.spin_once(timeout_sec=0.001)
            client.spin_until(lambda: any(t.child_frame_id == 'odom' for m in tf
                                          for t in m.transforms), 30, 'map -> odom on /tf',
                              proc)
            t = next(t for m in tf for t in m.transforms if t.child_frame_id == 'odom')
            assert t.header.frame_id == 'map' and t.header.stamp.sec >= 1
    finally:
        stop_process(proc)


@pytest.mark.ros
def test_two_namespaced_nodes_do_not_hear_each_other(tmp_path):
    dom = domain_id(23)
    rng = np.random.default_rng(3)
    surveys = {}
    for ns, n_tracks in (('robot1', 3), ('robot2', 2)):
        sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=5)
        noisy = perturb(sc.true_motions(), NoiseModel(3.0, sc.depth_m), rng)
        surveys[ns] = list(sc.measurements(noisy.z, noisy.cov))
    procs = [start_node_process(dom, {'diagnostics_period_sec': 0.2, 'publish_markers': False,
                                      'allow_finish_track': True},
                                log_path=tmp_path / f'{ns}.log', ros_args=['-r', f'__ns:=/{ns}'])
             for ns in surveys]
    clients = []
    try:
        for ns in surveys:
            c = NodeClient(dom, node_name=f'{ns}/alignment_node',
                           measurements_topic=f'/{ns}/ga/measurements',
                           path_topic=f'/{ns}/ga/corrected_path')
            clients.append(c)
            c.wait_for_node(proc=procs[len(clients) - 1])
        diags = clients[0].record(DiagnosticArray, '/diagnostics')

        def received(ns: str) -> int:  # from the node's own status (full name in /diagnostics)
            values = [kv.value for d in diags for st in d.status
                      if st.name.startswith(f'/{ns}/alignment_node') for kv in st.values
                      if kv.key == 'measurements_received']
            return int(values[-1]) if values else -1

        for c, (ns, ms) in zip(clients, surveys.items()):
            c.publish(ms)
            clients[0].spin_until(lambda ns=ns, n=len(ms): received(ns) == n, 30,
                                  f'{ns} to receive its measurements')
        assert received('robot1') == len(surveys['robot1'])  # nothing of robot2's
        for c, (ns, ms) in zip(clients, surveys.items()):
            assert c.call('finish_track').success
            n_nodes = len({m.dst_id for m in ms} | {m.src_id for m in ms})
            c.spin_until(lambda c=c, n=n_nodes: bool(c.paths) and len(c.paths[-1][1].poses) == n,
                         30, f'{ns} path of {n_nodes} nodes')
        # each path holds only its own robot's nodes (a leak would add the other's)
        lengths = [len(c.paths[-1][1].poses) for c in clients]
        assert lengths[0] != lengths[1]
        other = clients[0].node.create_subscription(Path, '/ga/corrected_path',
                                                    lambda m: None, latched_qos())
        assert clients[0].node.count_publishers('/ga/corrected_path') == 0
        clients[0].node.destroy_subscription(other)
    finally:
        for c in clients:
            c.close()
        for p in procs:
            stop_process(p)


@pytest.mark.ros
def test_play_publishes_tf_and_latched_tf_static(tmp_path):
    """``ga-ros play`` on a replay output bag (map -> odom on /tf, the input's /tf_static)."""
    import subprocess
    import sys
    import time

    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from test_replay_inputs import write_odom_bag

    from ga_ros.pipeline.inputs import InputSpec
    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.inputs import InputTopics
    from ga_ros.replay.pipeline import replay

    write_odom_bag(tmp_path / 'in')
    cfg = ReplayConfig(inputs=InputTopics((InputSpec('/odom'),)), plot=False)
    out = pathlib.Path(replay(tmp_path / 'in', tmp_path / 'out', cfg).files['bag'])
    dom = domain_id(24)
    c = rclpy.Context()
    rclpy.init(context=c, domain_id=dom)
    node = Node('tf_listener_free', context=c)
    ex = SingleThreadedExecutor(context=c)
    ex.add_node(node)
    tf, static = [], []
    node.create_subscription(TFMessage, '/tf', tf.append, 5000)
    node.create_subscription(TFMessage, '/tf_static', static.append, latched_qos())
    proc = subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.play', str(out), '--rate', '0',
                             '--delay', '0', '--wait-for-subscribers', '20',
                             '--topics', '/tf', '/tf_static'],
                            env={**os.environ, 'ROS_DOMAIN_ID': str(dom)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        def pairs() -> set:
            return {(t.header.frame_id, t.child_frame_id) for m in tf for t in m.transforms}

        end = time.monotonic() + patience(60)
        while time.monotonic() < end and (proc.poll() is None or not static
                                          or ('map', 'odom') not in pairs()):
            ex.spin_once(timeout_sec=0.05)
        _, err = proc.communicate(timeout=patience(10))
        assert proc.returncode == 0, err
        assert {('map', 'odom'), ('odom', 'base_link')} <= pairs()
        assert static and static[0].transforms[0].child_frame_id == 'laser'
    finally:
        if proc.poll() is None:
            proc.kill()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=c)


def test_absolute_fixes_live_parameters_and_effect(ctx):
    """``absolutes: amcl0`` with ``amcl0.*`` parameters: AMCL-like poses (x, y, yaw variances,
    zeros elsewhere) in a map frame rotated and shifted from the odometry's put the corrected
    path and ``map -> odom`` in that frame (the fixes' frame), through the same front end as
    the replay."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    node = _node(AlignmentNode, ctx, absolutes='amcl0', **{
        'amcl0.topic': 'amcl_pose', 'amcl0.type': 'pose_cov', 'amcl0.track_min_interval_s': 2.0,
        'amcl0.T_base_sensor': [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], 'datum': 'fixes'})
    rng = np.random.default_rng(5)
    T_map_odom = se3.from_translation_rotvec(np.array([1.0, 2.0, 0.0]), np.array([0, 0, 0.3]))
    try:
        assert node.get_parameter('amcl0.default_sigma_m').value == 5.0
        assert node.absolute.specs['amcl0'].config.T_base_sensor == (0.0,) * 6 + (1.0,)
        for k, msg in enumerate(odom_msgs()):
            node._on_input('odom0', msg)
            if k % 10 == 5:
                T_m = T_map_odom @ pose_to_matrix(msg.pose.pose)
                T_m[:2, 3] += rng.normal(0, 0.05, 2)
                q = se3.quat_from_matrix(T_m[:3, :3])
                fix = PoseWithCovarianceStamped()
                fix.header.frame_id = 'map'
                fix.header.stamp = msg.header.stamp
                p = fix.pose.pose
                p.position.x, p.position.y, p.position.z = (float(v) for v in T_m[:3, 3])
                p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (
                    float(v) for v in q)
                cov = np.zeros(36)
                cov[0] = cov[7] = 0.05 ** 2
                cov[35] = 0.02 ** 2
                fix.pose.covariance = cov.tolist()
                node._on_absolute('amcl0', fix)
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        st = node.session.aligner.fix_stats
        assert st.added == 20 and st.outliers == 0
        assert node.absolute.stats()['amcl0']['fixes'] == 20
        np.testing.assert_allclose(node.odom.T_map_odom[:3, 3], T_map_odom[:3, 3], atol=0.1)
        np.testing.assert_allclose(node.odom.T_map_odom[:3, :3], T_map_odom[:3, :3], atol=0.02)
    finally:
        node.destroy_node()


def test_a_restarted_node_fed_live_odometry_continues_the_survey(ctx, tmp_path):
    """Killed in the middle of a drive and started again on its state, the node hears the live
    odometry go on (no history re-delivered): its keyframes are numbered after the restored
    ones, on a new track whose first node is bridged to the state's newest at once (measured:
    the odometry went on), so the survey goes on: every restored node kept where it was,
    nothing moved aside, and ``map -> odom`` composes the new odometry with the new nodes'
    corrected poses."""
    msgs = odom_msgs(240)
    state = str(tmp_path / 'state')
    first = _node(AlignmentNode, ctx, state_file=state)
    try:
        for msg in msgs[:120]:
            first._on_input('odom0', msg)
        before = first.aligner.corrected_path()
        n_before = len(before.node_ids)
        assert n_before == 12 and first.session.counts.accepted == 11
    finally:
        first.destroy_node()    # the journal holds every accepted measurement
    node = _node(AlignmentNode, ctx, state_file=state)
    try:
        assert node.session.n_nodes() == n_before
        for msg in msgs[120:]:
            node._on_input('odom0', msg)
        assert not list(tmp_path.glob('state.survey-*')), 'the survey was moved aside'
        assert node.session.counts.rejected == {}
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        cp = node.aligner.corrected_path()
        ids = [int(i) for i in cp.node_ids]
        # every restored node kept, the new keyframes numbered after them
        assert ids == list(range(n_before + 12)), ids
        # the odometry's motion across the restart joins the new piece (no guessed bridge)
        assert node.session.counts.bridges == 0
        assert node.diagnostic_values()['unjoined_nodes'] == 0
        assert node.diagnostic_values()['restart_bridge'] == 'measured'
        assert int(cp.track_ids[n_before]) == int(before.track_ids.max()) + 1
        # the restored nodes did not move (frozen or adjusted with the new ones: within 1 mm
        # of where the first run left them, the bridge weighing nothing against the odometry)
        np.testing.assert_allclose(cp.T_world_node[:n_before, :3, 3],
                                   before.T_world_node[:, :3, 3], atol=1e-3)
        T_odom_k = node.front.inputs['odom0'].keyframe_pose(ids[-1])
        np.testing.assert_allclose(node.odom.T_map_odom @ T_odom_k, cp.T_world_node[-1],
                                   atol=1e-9)
    finally:
        node.destroy_node()


def test_a_restarted_node_sends_the_saved_map_to_odom_until_its_first_update(ctx, tmp_path):
    """Killed mid-drive, the node restarted on its state sends the ``map -> odom`` of its last
    update from the start (Nav2 keeps its ``map -> base_link``), not the identity, says so in
    /diagnostics, and its first update after the restart places the map again where the live
    odometry, which went on, puts it."""
    T0 = se3.from_translation_rotvec(np.array([4.0, -3.0, 0.0]), np.array([0.0, 0.0, 0.8]))
    msgs = _moved(odom_msgs(240), T0)   # the odometry starts away from its origin: map != odom
    state = str(tmp_path / 'state')
    first = _node(AlignmentNode, ctx, state_file=state)
    try:
        for msg in msgs[:120]:
            first._on_input('odom0', msg)
        assert first.session.counts.updates >= 1 and first.odom.placed_by == 'aligner'
        T_before = first.odom.T_map_odom.copy()
        assert np.linalg.norm(T_before[:3, 3]) > 1.0   # not the identity
    finally:
        first.destroy_node()
    node = _node(AlignmentNode, ctx, state_file=state)
    try:
        assert node.odom.placed_by == 'restored'
        assert node.diagnostic_values()['map_to_odom/placed_by'] == 'restored'
        np.testing.assert_array_equal(node.odom.T_map_odom, T_before)
        for msg in msgs[120:]:
            node._on_input('odom0', msg)
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        assert node.odom.placed_by == 'aligner'
        # the odometry went on without a gap: the bridge measures the motion across the
        # restart, and the new correction is the saved one (the odometry is exact here)
        d = se3.inverse(T_before) @ node.odom.T_map_odom
        assert np.linalg.norm(d[:3, 3]) < 1e-6
        np.testing.assert_allclose(d[:3, :3], np.eye(3), atol=1e-9)
    finally:
        node.destroy_node()


def _moved(msgs: list, T: np.ndarray) -> list:
    """The odometry messages ``msgs`` with their poses put behind ``T`` (``T @ pose``)."""
    for msg in msgs:
        p = msg.pose.pose
        P = T @ pose_to_matrix(p)
        p.position.x, p.position.y, p.position.z = (float(v) for v in P[:3, 3])
        q = se3.quat_from_matrix(P[:3, :3])
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v)
                                                                              for v in q)
    return msgs


def _killed_mid_drive(ctx, state: str, msgs: list) -> np.ndarray:
    """A node on ``state`` fed ``msgs`` and killed (no clean shutdown); its last
    ``T_map_odom``."""
    first = _node(AlignmentNode, ctx, state_file=state)
    try:
        for msg in msgs:
            first._on_input('odom0', msg)
        assert first.session.counts.updates >= 1 and first.odom.placed_by == 'aligner'
        return first.odom.T_map_odom.copy()
    finally:
        first.destroy_node()


def test_a_node_restarted_while_the_robot_turned_and_drove_measures_the_motion(ctx, tmp_path):
    """Killed mid-drive; during the 4 s downtime the robot drove round a corner (the
    odometry's messages of the downtime are never heard: the restarted node hears the odometry
    go on from a later pose). The restarted node measures the motion across the restart from
    its saved ``map -> odom`` and the odometry's pose: the new nodes lie on the odometry
    composed with the saved correction (the truth here: the odometry is exact), the new piece
    is joined, and ``map -> odom`` after the first update is the saved one (the guess, straight
    on at constant velocity, puts the new piece ~10 m off and moves it)."""
    T0 = se3.from_translation_rotvec(np.array([4.0, -3.0, 0.0]), np.array([0.0, 0.0, 0.8]))
    msgs = _moved(odom_msgs(260), T0)
    state = str(tmp_path / 'state')
    T_before = _killed_mid_drive(ctx, state, msgs[:120])
    node = _node(AlignmentNode, ctx, state_file=state)
    try:
        restored = node.aligner.corrected_path()
        for msg in msgs[160:]:   # 120..159 (the turn at 149) lost in the downtime
            node._on_input('odom0', msg)
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        values = node.diagnostic_values()
        assert values['restart_bridge'] == 'measured' and values['unjoined_nodes'] == 0
        assert values['bridges'] == 0 and node.session.counts.rejected == {}
        assert node.odom.placed_by == 'aligner' and node.odom.jumps_warned == 0
        cp = node.aligner.corrected_path()
        n = len(restored.node_ids)
        assert len(cp.node_ids) - n >= 9
        for node_id, T_map in zip(cp.node_ids[n:], cp.T_world_node[n:]):
            np.testing.assert_allclose(T_map, T_before @ node.front.keyframe_pose(int(node_id)),
                                       atol=1e-6)
        np.testing.assert_allclose(node.odom.T_map_odom, T_before, atol=1e-6)
        assert node.odom.last_jump_m < 1e-6
    finally:
        node.destroy_node()


def test_a_node_restarted_with_its_odometry_guesses_the_bridge_and_warns(ctx, tmp_path, capfd):
    """The odometry restarted too (its poses start again from the identity, in a new
    ``odom``): the restarted node cannot measure the motion across the restart, bridges by the
    guess as before, says why in a WARN and in /diagnostics, and the survey goes on."""
    msgs = odom_msgs(260)
    state = str(tmp_path / 'state')
    _killed_mid_drive(ctx, state, msgs[:120])
    node = _node(AlignmentNode, ctx, state_file=state)
    try:
        restart = se3.inverse(pose_to_matrix(msgs[160].pose.pose))
        for msg in _moved(msgs[160:], restart):
            node._on_input('odom0', msg)
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        values = node.diagnostic_values()
        assert values['restart_bridge'].startswith('guessed: ')
        assert 'restarted too' in values['restart_bridge']
        assert values['bridges'] == 1 and values['unjoined_nodes'] > 0
        assert node.session.counts.rejected == {} and node.session.counts.accepted >= 9
        assert node.odom.placed_by == 'aligner'
        err = capfd.readouterr().err
        assert '[WARN]' in err and 'bridged to the restored survey by a guess' in err
    finally:
        node.destroy_node()


def test_a_state_loaded_under_running_odometry_continues_after_its_nodes(ctx, tmp_path):
    """``~/load_state`` while the odometry runs (``autosave: false``: saved at 6 keyframes,
    driven on to 12, the save loaded back): the standard inputs number on after the loaded
    nodes on a fresh keyframe chain, its first node joined to the loaded newest by the
    odometry's motion (``restart_bridge: measured``), ``map -> odom`` the loaded state's until
    the next update and the same after it (exact odometry). Before, the running numbering
    (12, 13, ...) was held as unknown sources and bridged by a silent guess."""
    msgs = _moved(odom_msgs(240), se3.from_translation_rotvec(np.array([4.0, -3.0, 0.0]),
                                                              np.array([0.0, 0.0, 0.8])))
    node = _node(AlignmentNode, ctx, state_file=str(tmp_path / 'state'), autosave=False,
                 allow_load_state=True)
    try:
        for msg in msgs[:60]:
            node._on_input('odom0', msg)
        assert node._srv_save(Trigger.Request(), Trigger.Response()).success
        saved = node.aligner.corrected_path()
        n = len(saved.node_ids)
        for msg in msgs[60:120]:
            node._on_input('odom0', msg)
        assert node.session.n_nodes() == 12 and n == 6
        resp = node._srv_load(Trigger.Request(), Trigger.Response())
        assert resp.success, resp.message
        assert node.odom.placed_by == 'restored'
        T_map_odom = saved.T_world_node[-1] @ se3.inverse(pose_to_matrix(msgs[50].pose.pose))
        np.testing.assert_allclose(node.odom.T_map_odom, T_map_odom, atol=1e-9)
        for msg in msgs[120:]:
            node._on_input('odom0', msg)
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        values = node.diagnostic_values()
        assert values['restart_bridge'] == 'measured' and values['unjoined_nodes'] == 0
        assert values['bridges'] == 0 and node.session.counts.rejected == {}
        cp = node.aligner.corrected_path()
        assert [int(i) for i in cp.node_ids] == list(range(n + 12))
        assert int(cp.track_ids[n]) == int(saved.track_ids.max()) + 1
        np.testing.assert_allclose(cp.T_world_node[:n], saved.T_world_node, atol=1e-6)
        np.testing.assert_allclose(node.odom.T_map_odom, T_map_odom, atol=1e-6)
    finally:
        node.destroy_node()


CAMERA_PARAMS = {**{f'camera.{side}_{kind}_topic': f'cam/{side}/{kind}'
                    for side in ('left', 'right') for kind in ('image', 'info')},
                 'camera.assume_identity_extrinsic': True}


def test_a_reset_under_running_odometry_starts_a_fresh_survey_at_the_next_sample(ctx, tmp_path):
    """``~/reset`` while the odometry runs (a camera beside it): the fresh survey starts at the
    next sample as node 0 on track 0, at the map origin; ``map -> odom`` is the identity until
    its first update places it (``inv(T_odom_first)``, not a jump), the camera waits only for
    the new chain's keyframes and nothing is held, bridged or rejected. Before, the fresh
    survey started at the former keyframe 11 on track 1, the camera still waited for the
    former keyframes 0..11 and ``map -> odom`` stayed the former survey's."""
    msgs = odom_msgs(260)
    node = _node(AlignmentNode, ctx, state_file=str(tmp_path / 'state'), allow_reset=True,
                 **CAMERA_PARAMS)
    try:
        for msg in msgs[:120]:
            node._on_input('odom0', msg)
        assert node.session.n_nodes() == 12 and node.odom.placed_by == 'aligner'
        resp = node._srv_reset(Trigger.Request(), Trigger.Response())
        assert resp.success, resp.message
        assert node.odom.placed_by == 'identity' and node.front.camera is not None
        np.testing.assert_array_equal(node.odom.T_map_odom, np.eye(4))
        for msg in msgs[120:]:
            node._on_input('odom0', msg)
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        values = node.diagnostic_values()
        assert values['bridges'] == 0 and values['unjoined_nodes'] == 0
        assert node.session.counts.rejected == {}
        cp = node.aligner.corrected_path()
        assert [int(i) for i in cp.node_ids] == list(range(14)) and int(cp.track_ids[0]) == 0
        assert node.front.keyframe_stamp(0) == conv.stamp_to_ns(msgs[120].header.stamp)
        assert [kf.node_id for kf in node.front.camera._waiting] == list(range(14))
        T_map_odom = se3.inverse(pose_to_matrix(msgs[120].pose.pose))
        np.testing.assert_allclose(cp.T_world_node[0], np.eye(4), atol=1e-9)
        np.testing.assert_allclose(node.odom.T_map_odom, T_map_odom, atol=1e-6)
        assert node.odom.placed_by == 'aligner' and node.odom.jumps_warned == 0
    finally:
        node.destroy_node()


def test_a_lifecycle_cleanup_keeps_the_camera_beside_the_odometry(ctx):
    """``cleanup`` restarts the standard inputs with the configured camera (without its
    former keyframes): after ``configure`` and ``activate`` the odometry's keyframes reach the
    camera again. Before, the rebuilt inputs had no camera: its images were lost."""
    node = _node(LifecycleAlignmentNode, ctx, **CAMERA_PARAMS)
    try:
        msgs = odom_msgs(80)
        camera = node.front.camera
        assert camera is not None
        node.trigger_configure()
        node.trigger_activate()
        for msg in msgs[:40]:
            node._on_input('odom0', msg)
        assert [kf.node_id for kf in camera._waiting] == [0, 1, 2, 3]
        node.trigger_deactivate()
        node.trigger_cleanup()
        assert node.front.camera is camera and not camera._waiting
        node.trigger_configure()
        node.trigger_activate()
        for msg in msgs[40:]:
            node._on_input('odom0', msg)
        assert [kf.node_id for kf in node.front.camera._waiting] == [0, 1, 2, 3]
    finally:
        node.destroy_node()
