"""Ground truth from anything (files and topics), matched in time, and the replay's one time base.

The fixture bag is shaped like a robot's recording in simulation: header stamps in simulation
time (~900 s) and log times on the recorder's wall clock (~1.78e9 s); ``/odom`` at 10 Hz with no
covariance, ``/tf`` (``odom -> base_link``, and the true pose ``world -> base_truth`` at 100 Hz),
``/tf_static`` and a ground-truth ``PoseStamped`` topic at 100 Hz, 3 ms off the odometry stamps so
that every keyframe falls between two ground-truth samples.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_STAMPED,
    drifting_odometry,
    odometry_msg,
    pose_stamped_msg,
    rectangle,
    write_tf,
    write_tf_static,
)

from ga_ros.cli.main import main as cli_main
from ga_ros.errors import FormatError, InputError
from ga_ros.eval.metrics import trajectory_error
from ga_ros.geometry import se3, so3
from ga_ros.io.bag_messages import typestore
from ga_ros.io.bag_writer import BagWriter
from ga_ros.io.groundtruth import match_stamps, read_ground_truth_file
from ga_ros.io.trajectory import Trajectory, read_tum, write_kitti, write_tum

SIM_T0_NS = 900_000_000_000           # simulation time of the first message
WALL_T0_NS = 1_780_000_000_000_000_000  # the recorder's clock
ODOM_HZ = 10.0
GT_HZ = 100.0
GT_OFFSET_NS = 3_000_000
DURATION_S = 60.0


def sim_time_bag(path: Path) -> dict[str, np.ndarray]:
    """Write the fixture bag (module doc); returns the ground-truth stamps and poses."""
    rng = np.random.default_rng(7)
    t_odom = np.arange(0.0, DURATION_S, 1.0 / ODOM_HZ)
    odom = drifting_odometry(rectangle(t_odom), 8e-4)
    t_gt = np.arange(0.0, DURATION_S, 1.0 / GT_HZ) + GT_OFFSET_NS * 1e-9
    T_gt = rectangle(t_gt)
    events = []  # (sim stamp ns, order, kind, index)
    events += [(SIM_T0_NS + int(round(t * 1e9)), 0, 'odom', k) for k, t in enumerate(t_odom)]
    events += [(SIM_T0_NS + int(round(t * 1e9)), 1, 'gt', k) for k, t in enumerate(t_gt)]
    events.sort()
    delay = 0
    with BagWriter(path) as bag:
        write_tf_static(bag, [('base_link', 'laser', np.eye(4))], SIM_T0_NS, WALL_T0_NS)
        last_log = WALL_T0_NS
        for stamp, _, kind, k in events:
            delay = int(rng.integers(2_000_000, 30_000_000))  # transport delay, 2-30 ms
            log = max(last_log, WALL_T0_NS + (stamp - SIM_T0_NS) + delay)
            last_log = log
            if kind == 'odom':
                bag.write('/odom', ODOMETRY, odometry_msg(odom[k], stamp), log)
                write_tf(bag, 'odom', 'base_link', odom[k], stamp, log)
            else:
                bag.write('/gt', POSE_STAMPED, pose_stamped_msg(T_gt[k], stamp, 'world'), log)
                write_tf(bag, 'world', 'base_truth', T_gt[k], stamp, log)
    return {'stamps_ns': SIM_T0_NS + np.round(t_gt * 1e9).astype(np.int64), 'T': T_gt}


@pytest.fixture(scope='module')
def sim_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    d = tmp_path_factory.mktemp('simtime')
    gt = sim_time_bag(d / 'robot')
    return d / 'robot', gt


def _log_times_in_file_order(bag_dir: Path) -> dict[str, list[int]]:
    """Topic -> log times in the order the messages are stored (the mcap library's reader,
    independent of ga_ros and rosbags)."""
    from mcap.reader import make_reader

    (f,) = bag_dir.glob('*.mcap')
    out: dict[str, list[int]] = {}
    with open(f, 'rb') as fh:
        for _, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append(int(message.log_time))
    return out


def _replay(bag: Path, out: Path, capsys: pytest.CaptureFixture, *extra: str) -> tuple[
        dict, str]:
    code = cli_main(['replay', str(bag), '--out', str(out), '--odom-topic', '/odom',
                     '--no-plot', '--no-progress', *extra])
    text = capsys.readouterr()
    assert code == 0, text.err
    return json.loads((out / 'summary.json').read_text()), text.out


def _expected_ate(out: Path) -> float:
    """RMSE of the corrected keyframe positions against the true rectangle at their stamps
    (computed here from the analytic ground truth, not from any ground-truth file or topic)."""
    est = read_tum(out / 'trajectory_ga.tum')
    t = (est.stamps_ns - SIM_T0_NS) * 1e-9
    return trajectory_error(est.T_world_node[:, :3, 3], rectangle(t)[:, :3, 3]).ate_raw


# --------------------------------------------------------------------------- one time base
def test_output_bag_stays_on_the_recorders_clock(sim_bag, tmp_path: Path, capsys) -> None:
    bag, _ = sim_bag
    _replay(bag, tmp_path / 'out', capsys, '--ground-truth-topic', '/gt')
    inp = _log_times_in_file_order(bag)
    lo = min(min(v) for v in inp.values())
    hi = max(max(v) for v in inp.values())
    out = _log_times_in_file_order(tmp_path / 'out' / 'replay_bag')
    assert {'/tf', '/tf_static', '/ga/corrected_path', '/ga/corrected_pose'} <= set(out)
    every = []
    for topic, times in out.items():
        assert lo <= min(times) and max(times) <= hi, topic
        assert (np.diff(times) >= 0).all(), f'{topic}: a log time steps backwards'
    from mcap.reader import make_reader

    (f,) = (tmp_path / 'out' / 'replay_bag').glob('*.mcap')
    with open(f, 'rb') as fh:
        every = [int(m.log_time) for _, _, m in make_reader(fh).iter_messages(
            log_time_order=False)]
    assert (np.diff(every) >= 0).all(), 'log times step backwards in file order'
    # header stamps stay on the input's header clock (simulation time)
    types = {'/ga/corrected_path': 'nav_msgs/msg/Path', '/ga/f2f_path': 'nav_msgs/msg/Path',
             '/ga/corrected_pose': 'geometry_msgs/msg/PoseWithCovarianceStamped',
             '/ga/corrected_odom': 'nav_msgs/msg/Odometry',
             '/ga/measurements': 'nav_msgs/msg/Odometry', '/ga/ground_truth': 'nav_msgs/msg/Path',
             '/ga/network_markers': 'visualization_msgs/msg/MarkerArray'}
    store = typestore()
    seen = set()
    with open(f, 'rb') as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            if channel.topic not in types:
                continue
            msg = store.deserialize_cdr(message.data, types[channel.topic])
            for h in ([m.header for m in msg.markers[1:]] if channel.topic.endswith('markers')
                      else [msg.header]):
                stamp = h.stamp.sec * 10**9 + h.stamp.nanosec
                assert SIM_T0_NS <= stamp <= SIM_T0_NS + int(DURATION_S * 1e9), channel.topic
            seen.add(channel.topic)
    assert seen == set(types)


# --------------------------------------------------------------------------- matching
def test_interpolation_matches_a_constant_velocity_motion() -> None:
    """Translation linear and rotation slerp are exact for p(t) = p0 + v t, R(t) = R0 exp(w t);
    samples at 100 Hz, queries anywhere between them, at a sample, and outside."""
    rng = np.random.default_rng(3)
    v, w = rng.normal(size=3), rng.normal(size=3) * 0.5
    R0 = so3.exp(rng.normal(size=3))

    def pose(t: np.ndarray) -> np.ndarray:
        T = np.zeros((t.size, 4, 4))
        T[:, :3, :3] = R0 @ so3.exp(t[:, None] * w)
        T[:, :3, 3] = np.array([1.0, 2.0, 3.0]) + t[:, None] * v
        T[:, 3, 3] = 1
        return T

    t_s = 1.0 + np.arange(0, 200) * 0.01  # samples over [1, 2.99] s
    gt = Trajectory(np.round(t_s * 1e9).astype(np.int64), pose(t_s))
    between = 1.0 + (rng.integers(0, 199, 50) + rng.uniform(0.2, 0.8, 50)) * 0.01
    q_s = np.concatenate([between, [1.5, 2.99 + 0.05, 0.95, 3.5]])
    q_ns = np.round(q_s * 1e9).astype(np.int64)
    hit = match_stamps(gt, q_ns, tolerance_s=0.1)
    np.testing.assert_array_equal(hit.i_est, np.arange(53))  # 3.5 s is 0.51 s past the end
    np.testing.assert_allclose(hit.T_world_gt[:51], pose(q_ns[:51] * 1e-9), atol=1e-9)
    # held at the ends: the last / first sample
    np.testing.assert_allclose(hit.T_world_gt[51], gt.T_world_node[-1], atol=0)
    np.testing.assert_allclose(hit.T_world_gt[52], gt.T_world_node[0], atol=0)
    assert (hit.n_exact, hit.n_held, hit.n_interpolated) == (1, 2, 50)
    # a gap wider than the tolerance is not interpolated across
    holey = Trajectory(gt.stamps_ns[[0, 100]], gt.T_world_node[[0, 100]])
    assert match_stamps(holey, np.array([1_500_000_000]), 0.5).n_matched == 0
    assert match_stamps(holey, np.array([1_500_000_000]), 1.0).n_matched == 1
    with pytest.raises(InputError, match='tolerance'):
        match_stamps(gt, q_ns, -1.0)


def test_ground_truth_topic_at_100_hz_is_interpolated(sim_bag, tmp_path: Path, capsys) -> None:
    bag, _ = sim_bag
    summary, text = _replay(bag, tmp_path / 'out', capsys, '--ground-truth-topic', '/gt')
    n = summary['n_nodes']
    assert f'ground truth: {n} of {n} nodes matched from /gt (PoseStamped, 100 Hz), ' \
           'interpolated' in text
    ate = summary['errors_vs_ground_truth']['ga']['ate_raw_m']
    assert ate == pytest.approx(_expected_ate(tmp_path / 'out'), abs=0.01)


def test_tum_file_at_100_hz_against_keyframe_stamps(sim_bag, tmp_path: Path, capsys) -> None:
    bag, gt = sim_bag
    write_tum(tmp_path / 'gt.txt', gt['stamps_ns'], gt['T'])
    summary, text = _replay(bag, tmp_path / 'out', capsys, '--ground-truth',
                            str(tmp_path / 'gt.txt'))
    n = summary['n_nodes']
    assert f'{n} of {n} nodes matched from gt.txt (TUM, 100 Hz), interpolated' in text
    assert summary['errors_vs_ground_truth']['ga']['ate_raw_m'] == pytest.approx(
        _expected_ate(tmp_path / 'out'), abs=0.01)
    # a file on another clock matches nothing, and the text says so (not "none in the bag")
    write_tum(tmp_path / 'late.txt', gt['stamps_ns'] + 10**12, gt['T'])
    summary, text = _replay(bag, tmp_path / 'late', capsys, '--ground-truth',
                            str(tmp_path / 'late.txt'))
    assert f'ground truth: 0 of {n} nodes matched from late.txt (TUM, 100 Hz): no error' in text
    assert 'in the bag' not in text and not summary['errors_vs_ground_truth']


def test_tf_frame_pair(sim_bag, tmp_path: Path, capsys) -> None:
    bag, _ = sim_bag
    summary, text = _replay(bag, tmp_path / 'out', capsys, '--ground-truth-topic',
                            'tf:world:base_truth')
    n = summary['n_nodes']
    assert f'{n} of {n} nodes matched from tf world -> base_truth (TF, 100 Hz)' in text
    assert summary['errors_vs_ground_truth']['ga']['ate_raw_m'] == pytest.approx(
        _expected_ate(tmp_path / 'out'), abs=0.01)
    assert cli_main(['replay', str(bag), '--out', str(tmp_path / 'x'), '--odom-topic', '/odom',
                     '--ground-truth-topic', 'tf:world']) == 1
    assert 'tf:PARENT:CHILD' in capsys.readouterr().err


def test_file_formats_agree(tmp_path: Path) -> None:
    """TUM, EuRoC and KITTI (times file or rate) of the same poses read back alike."""
    t = np.arange(0, 5.0, 0.1)
    T = rectangle(t)
    stamps = SIM_T0_NS + np.round(t * 1e9).astype(np.int64)
    write_tum(tmp_path / 'a.tum', stamps, T)
    p, q = se3.to_pos_quat(T)
    (tmp_path / 'data.csv').write_text('#timestamp [ns],x,y,z,qw,qx,qy,qz\n' + ''.join(
        f'{s},' + ','.join(repr(float(x)) for x in (*a, b[3], b[0], b[1], b[2])) + '\n'
        for s, a, b in zip(stamps, p, q)))
    write_kitti(tmp_path / '00.txt', T)
    (tmp_path / 'times.txt').write_text(''.join(f'{x:.6e}\n' for x in t))
    reads = [read_ground_truth_file(tmp_path / 'a.tum'),
             read_ground_truth_file(tmp_path / 'data.csv'),
             read_ground_truth_file(tmp_path / '00.txt', times=tmp_path / 'times.txt',
                                    start_s=SIM_T0_NS * 1e-9),
             read_ground_truth_file(tmp_path / '00.txt', rate_hz=10.0,
                                    start_s=SIM_T0_NS * 1e-9)]
    assert [g.source for g in reads] == ['a.tum (TUM)', 'data.csv (EuRoC)', '00.txt (KITTI)',
                                         '00.txt (KITTI)']
    for g in reads:
        np.testing.assert_allclose(g.trajectory.stamps_ns, stamps, atol=1000)
        np.testing.assert_allclose(g.trajectory.T_world_node, T, atol=1e-9)
    with pytest.raises(InputError, match='--ground-truth-times'):
        read_ground_truth_file(tmp_path / '00.txt')
    (tmp_path / 'short.txt').write_text('0.0\n')
    with pytest.raises(InputError, match='1 times for the 50 poses'):
        read_ground_truth_file(tmp_path / '00.txt', times=tmp_path / 'short.txt')
    (tmp_path / 'bad.csv').write_text('1' * 5000 + ',0,0,0,1,0,0,0\n')
    with pytest.raises(FormatError, match='not a time'):
        read_ground_truth_file(tmp_path / 'bad.csv')
