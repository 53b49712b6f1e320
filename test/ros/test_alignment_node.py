"""The alignment node: ROS-free helpers, the node in-process, and the node as a real process.

The two-process tests start ``python -m ga_ros.ros.alignment_node`` with their own
``ROS_DOMAIN_ID``, publish a small simulated aerial survey from this process and compare the
received path with :class:`TrackWindowAligner` run directly on the same measurements.
"""

from __future__ import annotations

import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from live_node import live_node  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from ga_ros.core.gaps import GapConfig  # noqa: E402
from ga_ros.core.measurement import Measurement  # noqa: E402
from ga_ros.core.network import ConnectionNetwork  # noqa: E402
from ga_ros.core.solver import SolverConfig, connection_cost  # noqa: E402
from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner  # noqa: E402
from ga_ros.errors import InputError  # noqa: E402
from ga_ros.geometry import se3  # noqa: E402
from ga_ros.pipeline.corrections import CorrectionThresholds  # noqa: E402
from ga_ros.pipeline.journal import MeasurementJournal, TrackEnd, read_journal  # noqa: E402
from ga_ros.pipeline.params import (  # noqa: E402
    config_from_params,
    parse_override,
    read_params_file,
)
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.alignment_node import AlignmentNode, NodeSettings  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import (  # noqa: E402
    CONFIG,
    domain_id,
    start_node_process,
    stop_process,
)
from ga_ros.ros.qos import latched_qos  # noqa: E402
from ga_ros.ros.view import connection_view, network_view, normalized_residuals  # noqa: E402
from ga_ros.sim.aerial import aerial_scenario  # noqa: E402
from ga_ros.sim.noise import NoiseModel, perturb  # noqa: E402


def survey(rng: np.random.Generator, n_tracks: int = 3, per_swath: int = 6,
           percent: float = 3.0) -> list[Measurement]:
    """Measurements of a small aerial survey in arrival order, already round-tripped through the
    message encoding (so the node and a direct aligner see bit-identical input)."""
    sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=per_swath)
    noisy = perturb(sc.true_motions(), NoiseModel(percent, sc.depth_m), rng)
    return [conv.odometry_to_measurement(conv.measurement_to_odometry(m))
            for m in sc.measurements(noisy.z, noisy.cov)]


def direct(measurements, config: AlignerConfig) -> TrackWindowAligner:
    aligner = TrackWindowAligner(config)
    for m in measurements:
        aligner.add_measurement(m)
    aligner.finish_track()
    return aligner


#: Reasons counted for the messages of :func:`bad_messages`.
BAD_REASONS = {'non_finite': 1, 'bad_covariance': 1, 'self_loop': 1, 'bad_id': 2,
               'duplicate': 1, 'out_of_order': 1}


def bad_messages(ms: list[Measurement], k: int) -> list:
    """Malformed measurement messages, each of which must be rejected without effect, to be sent
    after ``ms[:k]`` (``ms[k - 1]`` must be of a track > 0)."""
    good = conv.measurement_to_odometry(ms[3])
    out = []

    def variant(mutate):
        msg = conv.measurement_to_odometry(ms[3])
        mutate(msg)
        out.append(msg)

    variant(lambda m: setattr(m.pose.pose.position, 'x', float('nan')))
    variant(lambda m: setattr(m.pose, 'covariance', -np.eye(6).reshape(36)))
    variant(lambda m: setattr(m, 'child_frame_id', m.header.frame_id))          # self-loop
    variant(lambda m: setattr(m, 'child_frame_id', 'ga/0/99999999999999999999'))  # absurd id
    variant(lambda m: setattr(m.header, 'frame_id', 'base_link'))
    out.append(good)                                                           # duplicate
    last = ms[k - 1]
    assert last.dst_track > 0
    out.append(conv.measurement_to_odometry(Measurement(                       # out of order
        last.dst_id, 10**9, last.dst_track, last.dst_track - 1, last.z, last.cov,
        last.stamp_ns, 'consecutive')))
    return out


# ------------------------------------------------------------------ ROS-free helpers
def test_yaml_mirrors_config_defaults():
    params = read_params_file(CONFIG, 'alignment_node')  # the solver: mapping -> solver.<name>
    expected = {f.name: getattr(AlignerConfig(), f.name) for f in fields(AlignerConfig)
                if f.name != 'solver'}
    expected.update({f'solver.{f.name}': getattr(ALIGNER_SOLVER, f.name)
                     for f in fields(SolverConfig)})
    expected.update({f.name: getattr(NodeSettings(), f.name) for f in fields(NodeSettings)
                     if f.name not in ('gaps', 'corrections')})
    expected.update({f'gaps.{f.name}': getattr(GapConfig(), f.name) for f in fields(GapConfig)})
    expected.update({f'corrections.{f.name}': getattr(CorrectionThresholds(), f.name)
                     for f in fields(CorrectionThresholds)})
    assert config_from_params(AlignerConfig, params)[0] == AlignerConfig()
    # a ROS parameter file cannot hold an empty list: such a default is there as a comment
    empty = {k for k, v in expected.items() if isinstance(v, tuple) and not v}
    text = Path(CONFIG).read_text()
    for key in empty:
        assert f'# {key}: [' in text, key
    assert set(params) == set(expected) - empty
    for key, value in expected.items():
        assert key in empty or params[key] == value, key


def test_dotted_solver_parameters_from_files_and_overrides(tmp_path):
    """The replay's parameter reading (ROS-free) nests the solver settings as the node does."""
    f = tmp_path / 'a.yaml'
    f.write_text('alignment_node:\n  ros__parameters:\n    window_tracks: 3\n'
                 '    solver:\n      max_iterations: 7\n      damping: lm\n')
    params = read_params_file(f)
    assert params == {'window_tracks': 3, 'solver.max_iterations': 7, 'solver.damping': 'lm'}
    params.update(parse_override(t) for t in ('solver.tolerance=1e-7', 'solver.robust_scale=2'))
    cfg, used = config_from_params(AlignerConfig, params)
    assert cfg == AlignerConfig(window_tracks=3, solver=replace(
        ALIGNER_SOLVER, max_iterations=7, damping='lm', tolerance=1e-7, robust_scale=2.0))
    assert used == set(params)
    assert config_from_params(AlignerConfig, {'x.tolerance': 1.0})[0] == AlignerConfig()
    with pytest.raises(InputError, match='solver.max_iterations'):
        config_from_params(AlignerConfig, {'solver.max_iterations': 'many'})
    with pytest.raises(InputError, match='se3'):
        config_from_params(AlignerConfig, {'solver.model': 'paper'})


def test_journal_round_trip(tmp_path, rng):
    ms = survey(rng, n_tracks=1, per_swath=4)
    j = MeasurementJournal(tmp_path / 's.npz.journal')
    for m in ms:
        j.append(m)
    back = read_journal(tmp_path / 's.npz.journal')
    assert len(back) == len(ms)
    for a, b in zip(ms, back):
        assert (a.src_id, a.dst_id, a.src_track, a.dst_track, a.stamp_ns, a.kind) == \
            (b.src_id, b.dst_id, b.src_track, b.dst_track, b.stamp_ns, b.kind)
        np.testing.assert_array_equal(a.z, b.z)
        np.testing.assert_array_equal(a.cov, b.cov)
    j.close()
    # a record cut short by a crash is ignored, the complete ones survive
    with open(tmp_path / 's.npz.journal', 'ab') as f:
        f.write(b'\x01' * 100)
    assert len(read_journal(tmp_path / 's.npz.journal')) == len(ms)
    j.clear()
    assert read_journal(tmp_path / 's.npz.journal') == []


def test_view_residuals_match_connection_cost(rng):
    """The markers' residuals, squared and summed, equal the solver's connection cost."""
    ms = survey(rng, n_tracks=2, per_swath=5, percent=5.0)
    aligner = direct(ms, AlignerConfig())
    cp = aligner.corrected_path()
    net = ConnectionNetwork()
    for node, track in zip(cp.node_ids.tolist(), cp.track_ids.tolist()):
        net.add_node(node, track)
    for m in ms:
        net.add_connection(m.src_id, m.dst_id, m.z, m.cov)
    T = cp.T_world_node[net.indices_of(cp.node_ids)]
    r = normalized_residuals(net, T)
    assert r.shape == (len(ms),)
    np.testing.assert_allclose(np.sum(r ** 2), connection_cost(net, T), rtol=1e-9)
    view = connection_view(aligner)
    np.testing.assert_allclose(view.p_world_node, cp.T_world_node[:, :3, 3])
    assert view.src_index.size == len(ms)
    np.testing.assert_allclose(np.sort(view.normalized_residual), np.sort(r), rtol=1e-9)
    # by hand: poses that close every connection exactly give zero residuals
    ids = np.array([5, 9])
    T2 = se3.exp(rng.normal(size=(2, 6)))
    z = se3.to_translation_rotvec(se3.relative(T2[0], T2[1]))[None]
    v = network_view(ids[::-1], T2[::-1], [5], [9], z, np.eye(6)[None])
    assert (v.src_index[0], v.dst_index[0]) == (1, 0)
    np.testing.assert_allclose(v.normalized_residual, [0.0], atol=1e-9)


# ------------------------------------------------------------------ node in this process
@pytest.fixture
def node_in_process(tmp_path):
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(7))
    node = AlignmentNode(context=ctx, parameter_overrides=[
        Parameter('state_file', value=str(tmp_path / 'state.npz')),
        Parameter('window_tracks', value=2), Parameter('allow_reset', value=True),
        Parameter('allow_finish_track', value=True), Parameter('allow_load_state', value=True),
        Parameter('diagnostics_period_sec', value=0.0)])
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_node_in_process_matches_direct(node_in_process, rng, tmp_path):
    node = node_in_process
    assert node.aligner_config.window_tracks == 2
    ms = survey(rng, n_tracks=4, per_swath=5)
    k_bad = next(k for k, m in enumerate(ms) if m.dst_track == 1) + 3
    bad = bad_messages(ms, k_bad)
    k3 = next(k for k, m in enumerate(ms) if m.dst_track == 3) + 2
    assert ms[k3 - 1].dst_track == 3
    for k, m in enumerate(ms):
        if k == k_bad:
            for msg in bad:
                node._on_measurement(msg)
        if k == k3:   # track 0 is frozen now (window of 2 finished tracks: 1, 2)
            old = ms[0]
            node._on_measurement(conv.measurement_to_odometry(Measurement(
                old.src_id, ms[k3 - 1].dst_id, 0, 3, old.z, old.cov, 0, 'cross')))
        node._on_measurement(conv.measurement_to_odometry(m))
    resp = node._srv_finish_track(Trigger.Request(), Trigger.Response())
    assert resp.success, resp.message
    assert node.session.counts.received == len(ms) + len(bad) + 1
    assert node.session.counts.accepted == len(ms)
    assert dict(node.session.counts.rejected) == {**BAD_REASONS, 'frozen': 1}
    values = node.diagnostic_values()
    assert values['rejected'] == len(bad) + 1
    assert values['rejected/frozen'] == 1
    assert values['updates'] == 4 and values['nodes'] == 40
    assert values['tracks_in_window'] == 2
    ref = direct(ms, AlignerConfig(window_tracks=2)).corrected_path()
    got = node.aligner.corrected_path()
    np.testing.assert_array_equal(got.node_ids, ref.node_ids)
    np.testing.assert_allclose(got.T_world_node, ref.T_world_node, atol=1e-12)
    # save / load / reset through the services
    assert node._srv_save(Trigger.Request(), Trigger.Response()).success
    resp = node._srv_load(Trigger.Request(), Trigger.Response())
    assert resp.success, resp.message
    np.testing.assert_allclose(node.aligner.corrected_path().T_world_node, ref.T_world_node,
                               atol=1e-9)
    assert node._srv_reset(Trigger.Request(), Trigger.Response()).success
    assert len(node.aligner.corrected_path().node_ids) == 0
    assert not (tmp_path / 'state.npz').exists()          # a restart does not resurrect it
    assert not node._srv_load(Trigger.Request(), Trigger.Response()).success


def test_solver_failure_keeps_previous_estimate(node_in_process, rng, monkeypatch):
    import ga_ros.core.window.update as window
    from ga_ros.errors import SolverError

    node = node_in_process
    ms = survey(rng, n_tracks=3, per_swath=5)
    k2 = next(k for k, m in enumerate(ms) if m.dst_track == 2)
    for m in ms[:k2]:
        node._on_measurement(conv.measurement_to_odometry(m))
    before = node.aligner.corrected_path()

    def failing_solve(*args, **kwargs):
        raise SolverError('diverged (injected)')

    monkeypatch.setattr(window, 'solve', failing_solve)
    node._on_measurement(conv.measurement_to_odometry(ms[k2]))      # ends track 1
    values = node.diagnostic_values()
    assert values['solver_failures'] == 1 and values['updates'] == 2
    assert 'diverged' in values['last_error']
    after = node.aligner.corrected_path()
    n = len(before.node_ids)
    np.testing.assert_array_equal(after.T_world_node[:n], before.T_world_node)
    monkeypatch.undo()
    for m in ms[k2 + 1:]:                                             # and it carries on
        node._on_measurement(conv.measurement_to_odometry(m))
    assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
    assert node.diagnostic_values()['updates'] == 3


def test_wrong_cross_track_match_is_excluded(node_in_process, rng):
    node = node_in_process
    ms = survey(rng, n_tracks=2, per_swath=6)
    clean = direct(ms, AlignerConfig(window_tracks=2)).corrected_path()
    # a wrong match: a cross connection from track 0 to track 1 that is 25 m off
    k = max(i for i, m in enumerate(ms) if m.kind == 'cross' and m.src_track == 0
            and m.dst_track == 1)
    wrong = ms[k]
    z = wrong.z.copy()
    z[:2] += 25.0
    bad = Measurement(wrong.src_id, wrong.dst_id, 0, 1, z, wrong.cov, wrong.stamp_ns, 'cross')
    for i, m in enumerate(ms):
        node._on_measurement(conv.measurement_to_odometry(m))
        if i == k:
            node._on_measurement(conv.measurement_to_odometry(bad))
    assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
    values = node.diagnostic_values()
    assert values['outliers_excluded'] >= 1
    assert values['rejected'] == 0                       # accepted, then excluded by the test
    got = node.aligner.corrected_path()
    err = np.linalg.norm(got.T_world_node[:, :3, 3] - clean.T_world_node[:, :3, 3], axis=1)
    assert err.max() < 0.5                               # the 25 m error did not leak in


def test_node_survives_internal_error(node_in_process, rng):
    node = node_in_process

    class Broken:
        def add_measurement(self, m):
            raise RuntimeError('boom')

    real = node.aligner
    node.aligner = Broken()
    node._on_measurement(conv.measurement_to_odometry(survey(rng, 1, 3)[0]))
    node.aligner = real
    assert node.session.counts.rejected['internal'] == 1


def _journaled_measurements(state) -> int:
    """The measurement records of ``state``'s journal (its events aside: track ends, the
    ``map -> odom`` of each update)."""
    return sum(isinstance(e, Measurement) for e in read_journal(str(state) + '.journal'))


@pytest.mark.parametrize('damage', ['none', 'corrupt_snapshot', 'no_snapshot', 'torn_record'])
def test_resume_from_snapshot_and_journal(tmp_path, rng, damage):
    """A node stopped mid-track (no clean shutdown) resumes the exact state from its files,
    through the snapshot or, when that is unusable, by replaying the journal."""
    ms = survey(rng, n_tracks=3, per_swath=5)
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 2) + 5
    state = tmp_path / 'state.npz'
    params = [Parameter('state_file', value=str(state)), Parameter('window_tracks', value=2),
              Parameter('allow_finish_track', value=True),
              Parameter('diagnostics_period_sec', value=0.0)]
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(11))
    try:
        first = AlignmentNode(context=ctx, parameter_overrides=params)
        for m in ms[:cut]:
            first._on_measurement(conv.measurement_to_odometry(m))
        assert state.exists() and _journaled_measurements(state) == cut
        first.session.journal.close()            # what the OS has when the process is killed
        first.destroy_node()
        if damage == 'corrupt_snapshot':
            data = bytearray(state.read_bytes())   # a ga_ros header, a bad CRC
            data[len(data) // 2] ^= 0xFF
            state.write_bytes(bytes(data))
        elif damage == 'no_snapshot':
            state.unlink()
        elif damage == 'torn_record':
            with open(str(state) + '.journal', 'ab') as f:
                f.write(b'\x00' * 50)
        second = AlignmentNode(context=ctx, parameter_overrides=params)
        ref = TrackWindowAligner(AlignerConfig(window_tracks=2))
        for m in ms[:cut]:
            ref.add_measurement(m)
        got = second.aligner.corrected_path()
        np.testing.assert_array_equal(got.node_ids, ref.corrected_path().node_ids)
        np.testing.assert_allclose(got.T_world_node, ref.corrected_path().T_world_node,
                                   atol=1e-9)
        # and it carries on exactly like an uninterrupted run
        for m in ms[cut:]:
            second._on_measurement(conv.measurement_to_odometry(m))
        assert second._srv_finish_track(Trigger.Request(), Trigger.Response()).success
        assert _journaled_measurements(state) == len(ms)
        assert TrackEnd(2) in read_journal(str(state) + '.journal')
        np.testing.assert_allclose(second.aligner.corrected_path().T_world_node,
                                   direct(ms, AlignerConfig(window_tracks=2)).corrected_path()
                                   .T_world_node, atol=1e-9)
        second.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_parameters_have_descriptors(node_in_process):
    node = node_in_process
    names = [f.name for f in fields(AlignerConfig) if f.name != 'solver']
    names += [f'solver.{f.name}' for f in fields(SolverConfig)]
    names += [f.name for f in fields(NodeSettings) if f.name not in ('gaps', 'corrections')]
    names += [f'gaps.{f.name}' for f in fields(GapConfig)]
    names += [f'corrections.{f.name}' for f in fields(CorrectionThresholds)]
    for name in names:
        d = node.describe_parameter(name)
        assert d.description, name
    assert node.describe_parameter('window_tracks').integer_range[0].from_value == 1
    assert node.describe_parameter('solver.max_iterations').integer_range[0].from_value == 1
    assert node.aligner_config == AlignerConfig(window_tracks=2)  # solver: the defaults
    assert node.settings.state_file.endswith('state.npz')
    assert node.settings.map_frame == 'map'


def test_out_of_range_parameter_is_refused():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(9))
    try:
        with pytest.raises(InputError, match=r'AlignerConfig.window_tracks = 0 is outside'):
            AlignmentNode(context=ctx, parameter_overrides=[Parameter('window_tracks', value=0)])
        with pytest.raises(InputError, match='freeze_policy'):
            AlignmentNode(context=ctx, parameter_overrides=[Parameter('freeze_policy',
                                                                      value='zzz')])
        with pytest.raises(InputError, match='robust_scale'):
            AlignmentNode(context=ctx, parameter_overrides=[Parameter('solver.robust_scale',
                                                                      value='big')])
        node = AlignmentNode(context=ctx, parameter_overrides=[     # an int for a float is fine
            Parameter('solver.robust_scale', value=4),
            Parameter('diagnostics_period_sec', value=0)])
        assert node.aligner_config.solver.robust_scale == 4.0
        assert isinstance(node.aligner_config.solver.robust_scale, float)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


# ------------------------------------------------------------------ node as a real process
@pytest.mark.ros
def test_bad_parameter_exits_with_one_line_error(tmp_path):
    proc = start_node_process(domain_id(3), {'solver.tolerance': -1.0}, log_path=tmp_path / 'log')
    try:
        assert proc.wait(timeout=patience(30)) == 1
    finally:
        stop_process(proc)
    text = (tmp_path / 'log').read_text()
    assert 'alignment_node: error:' in text and 'Traceback' not in text, text

@pytest.mark.ros
def test_two_processes_late_subscriber_kill_restart(tmp_path, rng):
    """Publish a survey to a node process, kill -9 it mid-track, restart it from the state file,
    publish the rest: the final path equals the aligner run directly (no node lost), bad
    messages are counted, and a late subscriber gets the path at once."""
    dom = domain_id()
    ms = survey(rng, n_tracks=3, per_swath=6)
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 1) + 12   # inside track 1
    bad = bad_messages(ms, cut)
    state = tmp_path / 'state.npz'
    params = {'state_file': str(state), 'window_tracks': 2, 'diagnostics_period_sec': 0.1,
              'allow_finish_track': True}
    with live_node(dom, params, tmp_path / 'node.log') as node:
        client = node.client
        client.publish(ms[:cut])
        client.publish_raw(bad)
        client.wait_received(cut + len(bad), proc=node.proc)
        assert client.diag_int('rejected') == len(bad), client.diagnostics
        for reason, n in BAD_REASONS.items():
            assert client.diag_int(f'rejected/{reason}') == n, client.diagnostics
        assert client.diag_int('measurements_accepted') == cut
        nodes_before = client.diag_int('nodes')
        assert node.proc.poll() is None                    # bad input did not kill it

        node.kill_and_restart()                            # no chance to save anything
        assert client.diag_int('nodes') == nodes_before    # resumed with no lost node

        late: list = []
        client.subscribe_path(late)                        # late joiner: latched path
        client.spin_until(lambda: len(late) > 0, 15, 'the latched path', node.proc)

        poses = client.record(PoseWithCovarianceStamped, '/ga/corrected_pose')
        odoms = client.record(Odometry, '/ga/corrected_odom')
        markers = client.record(MarkerArray, '/ga/network_markers', latched_qos())
        client.publish(ms[cut:])
        client.wait_received(len(ms) - cut, proc=node.proc)
        resp = client.call('finish_track')
        assert resp.success, resp.message
        ref = direct(ms, AlignerConfig(window_tracks=2)).corrected_path()
        client.spin_until(lambda: len(late) > 1 and
                          len(late[-1][1].poses) == len(ref.node_ids), 20, 'the final path',
                          node.proc)
        got = conv.path_msg_to_poses(late[-1][1])
        np.testing.assert_allclose(got, ref.T_world_node, atol=1e-9)
        assert late[-1][1].header.frame_id == 'map'
        # newest adjusted node with its covariance, odometry stream, markers
        client.spin_until(lambda: poses and odoms and markers and
                          len(markers[-1].markers[1].points) == len(ref.node_ids), 20,
                          'pose, odometry and markers', node.proc)
        pc = poses[-1]
        assert pc.header.frame_id == 'map'
        np.testing.assert_allclose(conv.msg_to_pose(pc.pose.pose), ref.T_world_node[-1],
                                   atol=1e-9)
        cov = conv.msg_to_covariance(pc.pose.covariance)       # raises unless SPD
        assert np.all(np.diag(cov) > 0)
        assert (odoms[-1].header.frame_id, odoms[-1].child_frame_id) == ('map', 'base_link')
        assert len(markers[-1].markers[2].points) == 2 * len(ms)
        assert node.proc.poll() is None


def test_map_to_odom_from_measurements_without_standard_inputs(node_in_process, rng):
    """With VO / measurement-encoding input, ``map -> odom`` is the correction of the newest
    node relative to the frame-to-frame chain of the consecutive motions (REP 105)."""
    node = node_in_process
    sent = []
    node.pub_tf.publish = sent.append                       # capture what goes to /tf
    ms = survey(rng, n_tracks=3, per_swath=5)
    for m in ms:
        node._on_measurement(conv.measurement_to_odometry(m))
    assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
    # the odometry frame, chained independently: T_odom_dst = T_odom_src @ T_src_dst
    T_odom = {ms[0].src_id: np.eye(4)}
    for m in ms:
        if m.kind == 'consecutive' and m.src_id in T_odom and m.dst_id not in T_odom:
            T_odom[m.dst_id] = T_odom[m.src_id] @ m.T_src_dst
    cp = node.aligner.corrected_path()
    newest = int(cp.node_ids[-1])
    want = cp.T_world_node[-1] @ np.linalg.inv(T_odom[newest])
    assert sent, 'no TF published after the updates'
    tf = sent[-1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ('map', 'odom')
    got_t = [tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z]
    np.testing.assert_allclose(got_t, want[:3, 3], atol=1e-9)
    assert np.linalg.norm(want[:3, 3]) > 1e-6   # a real correction, not the identity


def test_defaults_protect_data_and_name_a_volatile_publisher(tmp_path):
    """Defaults: transient-local measurements, the data-destroying services refused; a volatile
    publisher (which a transient-local subscription cannot match) is named in an error, and the
    diagnostics say ERROR."""
    from rclpy.executors import SingleThreadedExecutor

    from ga_ros.ros.qos import measurement_qos

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(9))
    node = AlignmentNode(context=ctx)
    pub_node = rclpy.create_node('volatile_pub', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        assert node.settings.measurement_durability == 'transient_local'
        for srv in (node._srv_finish_track, node._srv_load, node._srv_reset):
            resp = srv(Trigger.Request(), Trigger.Response())
            assert not resp.success and 'allow_' in resp.message
        pub_node.create_publisher(Odometry, '/ga/measurements', measurement_qos())  # volatile
        end = time.monotonic() + patience(20)
        while node.incompatible_publishers == 0 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        assert node.incompatible_publishers >= 1
        diags = []
        node.pub_diag.publish = diags.append
        node._publish_diagnostics()
        assert diags[-1].status[0].level in (b'\x02', 2)
    finally:
        ex.shutdown()
        pub_node.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_persistence_is_on_by_default_under_ros_home_and_never_shared(tmp_path, monkeypatch, rng):
    """Defaults: the state under ``$ROS_HOME/ga_ros/<namespace>/<name>/`` (journal written from
    the first measurement, resumed by the next node of that name); a second node of the same
    name and namespace gets the lock's error, naming the first, and runs without persistence;
    ``state_file: ''`` keeps nothing."""
    monkeypatch.setenv('ROS_HOME', str(tmp_path))
    ms = survey(rng, n_tracks=2, per_swath=4)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(13))
    try:
        node = AlignmentNode(context=ctx, parameter_overrides=[
            Parameter('diagnostics_period_sec', value=0.0)])
        state = tmp_path / 'ga_ros' / 'alignment_node' / 'state'
        assert node.settings.state_file == str(state)
        for m in ms:
            node._on_measurement(conv.measurement_to_odometry(m))
        assert len(read_journal(str(state) + '.journal')) == len(ms)
        twin = AlignmentNode(context=ctx, parameter_overrides=[
            Parameter('diagnostics_period_sec', value=0.0)])
        assert 'in use by' in twin.session.persistence_off
        assert '/alignment_node' in twin.session.persistence_off
        assert twin.session.journal is None and twin.session.n_nodes() == 0
        twin.destroy_node()
        other = AlignmentNode(context=ctx, parameter_overrides=[
            Parameter('diagnostics_period_sec', value=0.0)],
            cli_args=['--ros-args', '-r', '__ns:=/robot2'])
        assert other.settings.state_file == str(tmp_path / 'ga_ros/robot2/alignment_node/state')
        assert other.session.journal is not None
        other.destroy_node()
        n = node.session.n_nodes()
        node.destroy_node()
        again = AlignmentNode(context=ctx, parameter_overrides=[
            Parameter('diagnostics_period_sec', value=0.0)])
        assert again.session.n_nodes() == n > 0   # resumed from the default state
        again.destroy_node()
        none = AlignmentNode(context=ctx, parameter_overrides=[
            Parameter('state_file', value=''), Parameter('diagnostics_period_sec', value=0.0)])
        assert none.session.journal is None and none.session.n_nodes() == 0
        none.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_online_variance_factors_in_diagnostics(tmp_path):
    """``variance_components: apply``: measurements of an odometry source stated 4x too
    confident come in over the ROS encoding with their source; ``/diagnostics`` shows the
    source's factor and dof, a WARN names it, and the node's path is the direct aligner's."""
    from ga_ros.sim.sources import SourceSpec, multi_source_survey

    sv = multi_source_survey(np.random.default_rng(3), (SourceSpec('odom0', 10.0),),
                             n_nodes=400, loop=SourceSpec('cross', 1.0, 1.0), loop_every=5)
    ms = sorted(sv.measurements, key=lambda m: (m.dst_id, m.src_id))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(15))
    node = AlignmentNode(context=ctx, parameter_overrides=[
        Parameter('state_file', value=''), Parameter('allow_finish_track', value=True),
        Parameter('variance_components', value='apply'),
        Parameter('refine_executor', value='inline'),
        Parameter('diagnostics_period_sec', value=0.0)])
    try:
        for m in ms:
            node._on_measurement(conv.measurement_to_odometry(m))
        assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
        values = node.diagnostic_values()
        ref = direct(ms, node.aligner_config)
        want = {c.group: c for c in ref.online_variance.components()}
        assert set(want) == {'odom0', 'cross'}
        assert values['variance/odom0/factor'] == f"{want['odom0'].factor:.4g}"
        assert float(values['variance/odom0/dof']) > 20
        assert 2.5 < want['odom0'].factor < 6
        np.testing.assert_allclose(node.aligner.corrected_path().T_world_node,
                                   ref.corrected_path().T_world_node, atol=1e-12)
        diags = []
        node.pub_diag.publish = diags.append
        node._publish_diagnostics()
        status = diags[-1].status[0]
        assert status.level in (b'\x01', 1)
        assert "odom0's stated covariance is" in status.message and 'too small' in status.message
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_online_calibration_in_diagnostics(tmp_path):
    """``calibrate``: ``/diagnostics`` shows each odometry parameter's online estimate (or why
    it is not estimated) with its sigma, the direct aligner's, and the node's path is the
    direct aligner's."""
    from ga_ros.sim.sources import SourceSpec, multi_source_survey

    sv = multi_source_survey(np.random.default_rng(3), (SourceSpec('odom0', 1.0),),
                             n_nodes=160, loop=SourceSpec('cross', 1.0, 1.0), loop_every=5)
    ms = sorted(sv.measurements, key=lambda m: (m.dst_id, m.src_id))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(15))
    node = AlignmentNode(context=ctx, parameter_overrides=[
        Parameter('state_file', value=''), Parameter('allow_finish_track', value=True),
        Parameter('calibrate', value=True), Parameter('refine_executor', value='inline'),
        Parameter('diagnostics_period_sec', value=0.0)])
    try:
        for m in ms:
            node._on_measurement(conv.measurement_to_odometry(m))
        assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
        values = node.diagnostic_values()
        ref = direct(ms, node.aligner_config)
        book = ref.online_calibration
        assert book.n_estimates > 0
        for p in book.report.parameters:
            key = f'calibration/{p.source}/{p.name}'
            assert values[key] == (f'{p.value:.6g} {p.unit}' if p.estimated
                                   else f'0 (not estimated: {p.reason})'), key
            assert values[key + '/sigma'] == f'{p.sigma:.3g}', key
        assert 'calibration/odom0/yaw_rate' in values and 'calibration/odom0/scale' in values
        np.testing.assert_allclose(node.aligner.corrected_path().T_world_node,
                                   ref.corrected_path().T_world_node, atol=1e-12)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _camera_swaths(phi) -> list:
    """A swath survey (:func:`ga_ros.sim.camera_survey.swath_survey`) as a live stream: each
    keyframe's ``odom0`` motion, then the ``cam0`` cross-track connections (conjugated by the
    extrinsic's rotation error ``phi``) that end at it."""
    from ga_ros.sim.camera_survey import live_measurements, swath_survey

    per = 30
    s = swath_survey(np.random.default_rng(4), np.asarray(phi, float), per_swath=per)
    return live_measurements(s, per)


def test_calibrate_cameras_in_diagnostics(tmp_path):
    """``calibrate_cameras``: the camera named by its measurements' source (carried by the
    encoding) gets its extrinsic rotation in the online estimate; ``/diagnostics`` shows it
    with its sigma (within 3 sigma of the truth), the direct aligner's, and the rotation
    applied to the camera's connections; a camera no measurement names is reported with the
    sources seen."""
    phi = (0.02, -0.01, 0.03)
    ms = _camera_swaths(phi)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(15))
    node = AlignmentNode(context=ctx, parameter_overrides=[
        Parameter('state_file', value=''), Parameter('allow_finish_track', value=True),
        Parameter('calibrate', value=True), Parameter('calibrate_cameras', value='cam0,cam9'),
        Parameter('refine_executor', value='inline'),
        Parameter('diagnostics_period_sec', value=0.0)])
    try:
        for m in ms:
            node._on_measurement(conv.measurement_to_odometry(m))
        assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
        values = node.diagnostic_values()
        # the measurements as the node decodes them (the applied estimate is iterated from
        # them: a motion rounded by the encoding moves it within the solver's tolerance)
        ref = direct([conv.odometry_to_measurement(conv.measurement_to_odometry(m))
                      for m in ms], node.aligner_config)
        cam = [p for p in ref.online_calibration.report.parameters if p.source == 'cam0']
        assert [p.name for p in cam] == ['extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz']
        for p, truth in zip(cam, phi):
            assert p.estimated and abs(p.value - truth) < 3 * p.sigma, p
            key = f'calibration/cam0/{p.name}'
            assert values[key] == f'{p.value:.6g} {p.unit}', key
            assert values[key + '/sigma'] == f'{p.sigma:.3g}', key
        applied = ref.online_calibration.diagnostic_values()['calibration/cam0/applied']
        assert values['calibration/cam0/applied'] == applied and applied.startswith('yes')
        assert values['calibration/cam9'] == ('no such source so far; the sources: cam0, '
                                              'odom0'), values
        np.testing.assert_allclose(node.aligner.corrected_path().T_world_node,
                                   ref.corrected_path().T_world_node, atol=1e-12)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_a_strict_update_bug_is_reported_and_the_node_goes_on(tmp_path, rng, monkeypatch):
    """With ``GA_ROS_STRICT_UPDATES`` (set for the suite) a bug in a window update (not a
    numerical failure) reaches the node as an UpdateBug: reported (one ERROR line, the
    diagnostics' ``failed_updates`` and ``last_error``), never a dead node or a lost
    measurement, whether a measurement, the in-band end of input or ``~/finish_track`` ended
    the track; a node restarted on the state (snapshot or journal alone) holds the same
    state and count."""
    from ga_ros import topics
    from ga_ros.core.window.update import WindowUpdate

    real = WindowUpdate.adjust

    def buggy(self, window_tracks, track, *args, **kwargs):
        if track in (1, 3):
            raise AttributeError(f"'NoneType' object has no attribute 'w' (track {track})")
        return real(self, window_tracks, track, *args, **kwargs)

    monkeypatch.setattr(WindowUpdate, 'adjust', buggy)
    ms = survey(rng, n_tracks=4, per_swath=5)
    k3 = next(k for k, m in enumerate(ms) if m.dst_track == 3)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(7))
    params = [Parameter('state_file', value=str(tmp_path / 'state')),
              Parameter('window_tracks', value=2), Parameter('allow_finish_track', value=True),
              Parameter('diagnostics_period_sec', value=0.0)]
    try:
        node = AlignmentNode(context=ctx, parameter_overrides=params)
        try:
            assert node.aligner.strict
            for m in ms[:k3]:                      # the update of track 1 fails
                node._on_measurement(conv.measurement_to_odometry(m))
            values = node.diagnostic_values()
            assert values['failed_updates'] == 1 and 'strict updates' in values['last_error']
            node._srv_finish_track(Trigger.Request(), Trigger.Response())   # track 2: fine
            for m in ms[k3:]:
                node._on_measurement(conv.measurement_to_odometry(m))
            end = Odometry()
            end.child_frame_id = topics.TRACK_END_FRAME
            node._on_measurement(end)              # the in-band end: track 3 fails
            values = node.diagnostic_values()
            assert values['failed_updates'] == 2 and values['measurements_accepted'] == len(ms)
            assert values['rejected'] == 0
            assert node.aligner.open_track is None          # every track ended
            want = node.aligner.corrected_path()
        finally:
            node.destroy_node()
        for lose_snapshot in (False, True):
            if lose_snapshot:
                (tmp_path / 'state').unlink()
            again = AlignmentNode(context=ctx, parameter_overrides=params)
            try:
                assert again.diagnostic_values()['failed_updates'] == 2
                got = again.aligner.corrected_path()
                np.testing.assert_array_equal(got.node_ids, want.node_ids)
                np.testing.assert_array_equal(got.T_world_node, want.T_world_node)
            finally:
                again.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
