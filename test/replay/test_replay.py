"""Offline replay: outputs, bad bags, metrics; and agreement with the in-process pipeline."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from ga_ros.cli.main import main as cli_main
from ga_ros.core.integration import F2FIntegrator
from ga_ros.core.measurement import Measurement
from ga_ros.core.quality.variance_components import SourceGroups, VarianceComponentConfig
from ga_ros.errors import FormatError, InputError
from ga_ros.eval.metrics import trajectory_error
from ga_ros.geometry import se3, so3
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import ODOMETRY, measurement_to_odometry, typestore
from ga_ros.io.bag_writer import BagWriter
from ga_ros.io.trajectory import read_tum
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.pipeline import replay
from ga_ros.replay.samples import aerial_sample, write_measurement_bag

REPO = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- a stand-in aligner
@dataclass
class _Update:
    track_id: int
    iterations: int = 1
    converged: bool = True


@dataclass
class _Path:
    node_ids: np.ndarray
    track_ids: np.ndarray
    stamps_ns: np.ndarray
    T_world_node: np.ndarray
    frozen: np.ndarray


class DeadReckoning:
    """The aligner's interface over plain dead reckoning: tests the replay's plumbing alone."""

    def __init__(self, T_world_first: np.ndarray | None = None) -> None:
        self.T0 = np.eye(4) if T_world_first is None else np.asarray(T_world_first)
        self.poses: dict[int, np.ndarray] = {}
        self.tracks: dict[int, int] = {}
        self.track: int | None = None

    def add_measurement(self, m: Measurement) -> list[_Update]:
        if self.poses and m.src_id not in self.poses:
            raise InputError(f'unknown node {m.src_id}')
        out = []
        if self.track is not None and m.dst_track != self.track:
            out.append(self.finish_track())
        self.track = m.dst_track
        if not self.poses:
            self.poses[m.src_id], self.tracks[m.src_id] = self.T0, m.src_track
        if m.kind == 'consecutive' and m.dst_id not in self.poses:
            self.poses[m.dst_id] = self.poses[m.src_id] @ m.T_src_dst
            self.tracks[m.dst_id] = m.dst_track
        return out

    def finish_track(self) -> _Update:
        return _Update(self.track)

    def refine_batch(self) -> _Update:
        return _Update(self.track)

    def corrected_path(self) -> _Path:
        ids = np.array(sorted(self.poses))
        return _Path(ids, np.array([self.tracks[i] for i in ids]), np.full(len(ids), -1),
                     np.array([self.poses[i] for i in ids]), np.zeros(len(ids), bool))

    def covariance(self, node_id: int) -> np.ndarray:
        return np.eye(6) * (1.0 + node_id)


@pytest.fixture(scope='module')
def sample() -> object:
    return aerial_sample(n_tracks=3, positions_per_swath=12, noise_pct=5.0, seed=11)


@pytest.fixture
def measurement_bag(tmp_path: Path, sample: object) -> Path:
    return write_measurement_bag(tmp_path / 'in', sample.measurements, sample.ground_truth)


def mcap_counts(bag_dir: Path) -> dict[str, int]:
    """Topic -> message count, read with the mcap library (independent of rosbags)."""
    from mcap.reader import make_reader

    (f,) = bag_dir.glob('*.mcap')
    with open(f, 'rb') as fh:
        s = make_reader(fh).get_summary()
    return {c.topic: s.statistics.channel_message_counts.get(cid, 0)
            for cid, c in s.channels.items()}


def last_path(bag_dir: Path, topic: str = '/ga/corrected_path') -> np.ndarray:
    """Positions of the last nav_msgs/Path on ``topic``, read with the mcap library."""
    from mcap.reader import make_reader

    (f,) = bag_dir.glob('*.mcap')
    with open(f, 'rb') as fh:
        data = [m.data for _, _, m in make_reader(fh).iter_messages(topics=[topic])]
    msg = typestore().deserialize_cdr(data[-1], 'nav_msgs/msg/Path')
    return np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                     for p in msg.poses])


# --------------------------------------------------------------------------- metrics
def test_trajectory_error_of_a_known_motion(rng: np.random.Generator) -> None:
    p = rng.normal(size=(40, 3)) * 10
    R, t = so3.exp(rng.normal(size=3)), rng.normal(size=3) * 5
    err = trajectory_error(p, p @ R.T + t)
    assert err.ate_aligned < 1e-9
    np.testing.assert_allclose(err.ate_raw, np.sqrt(np.mean(np.sum((p @ R.T + t - p) ** 2, 1))))


def test_f2f_integrator_matches_se3_integrate(rng: np.random.Generator) -> None:
    T0 = se3.exp(rng.normal(size=6))
    motions = se3.exp(rng.normal(size=(20, 6)) * 0.3)
    f2f = F2FIntegrator(T0)
    for k in range(20):
        f2f.add(Measurement.from_pose(k, k + 1, 0, 0, motions[k], np.eye(6), k + 1))
        f2f.add(Measurement.from_pose(0, k + 1, 0, 0, np.eye(4), np.eye(6), k + 1, 'cross'))
    expected = se3.integrate(T0, motions)
    np.testing.assert_allclose(np.array([f2f.poses[k] for k in range(21)]), expected,
                               atol=1e-12)


# --------------------------------------------------------------------------- outputs
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_replay_outputs(tmp_path: Path, sample: object, storage: str) -> None:
    bag = write_measurement_bag(tmp_path / 'in', sample.measurements, sample.ground_truth,
                                storage=storage)
    r = replay(bag, tmp_path / 'out', ReplayConfig(), aligner_factory=DeadReckoning)
    n_nodes = sample.ground_truth.node_ids.size
    assert r.error is None and r.n_inputs == len(sample.measurements)
    assert r.n_measurements == len(sample.measurements) and r.n_nodes == n_nodes
    assert r.n_tracks == 3 and len(r.updates) == 3
    counts = mcap_counts(tmp_path / 'out' / 'replay_bag')
    assert counts.pop('/tf') > 3  # map -> odom at a fixed period (test_replay_tf.py)
    # a path and markers per track update, then the final batch's path and markers, then the
    # final markers of everything; corrections after each track update (the first one full,
    # then each new track's keyframes: dead reckoning moves none), none after the final batch
    # (nothing moved)
    assert counts.pop('/ga/corrections') == 3
    assert counts == {'/ga/measurements': len(sample.measurements), '/ga/corrected_path': 4,
                      '/ga/network_markers': 5, '/ga/corrected_pose': n_nodes, '/ga/f2f_path': 1,
                      '/ga/ground_truth': 1, '/ga/corrected_odom': n_nodes}
    # dead reckoning along consecutive motions == F2F: same errors, same final path
    assert r.errors['ga'].ate_raw == pytest.approx(r.errors['f2f'].ate_raw, rel=1e-12)
    assert r.errors['ga'].n == n_nodes
    T_gt = sample.ground_truth.T_world_node
    chain = [m for m in sample.measurements if m.kind == 'consecutive']
    f2f = se3.integrate(T_gt[0], np.array([m.T_src_dst for m in chain]))
    np.testing.assert_allclose(last_path(tmp_path / 'out' / 'replay_bag'), f2f[:, :3, 3],
                               atol=1e-9)
    tum = np.loadtxt(tmp_path / 'out' / 'trajectory_ga.tum')
    assert tum.shape == (n_nodes, 8)
    np.testing.assert_allclose(tum[:, 1:4], f2f[:, :3, 3], atol=1e-6)
    # every node's stamp, node 0's too (no measurement carries it: from the ground truth)
    np.testing.assert_allclose(tum[:, 0], sample.ground_truth.stamps_ns * 1e-9, rtol=0,
                               atol=1e-6)
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['n_measurements'] == len(sample.measurements) and summary['error'] is None
    assert (tmp_path / 'out' / 'trajectory.png').stat().st_size > 10_000
    with BagReader(tmp_path / 'out' / 'replay_bag') as out:
        poses = [m.msg for m in out.messages(['/ga/corrected_pose'])]
    np.testing.assert_allclose(np.asarray(poses[5].pose.covariance).reshape(6, 6),
                               np.eye(6) * (1.0 + 5))


def test_bad_measurements_are_counted_not_fatal(tmp_path: Path, sample: object) -> None:
    ms = sample.measurements
    cross = [k for k, m in enumerate(ms) if m.kind == 'cross']
    with BagWriter(tmp_path / 'in') as bag:
        for k, m in enumerate(ms):
            msg = measurement_to_odometry(m)
            if k == cross[0]:
                msg.header.frame_id = 'camera'
            if k == cross[5]:
                msg.pose.covariance[:] = 0.0
            bag.write('/ga/measurements', ODOMETRY, msg, m.stamp_ns)
    r = replay(tmp_path / 'in', tmp_path / 'out', ReplayConfig(plot=False),
               aligner_factory=DeadReckoning)
    assert r.rejected.get('decode') == 2 and r.n_measurements == len(ms) - 2


def test_corrupt_bag_mid_stream_flushes_partial_outputs(tmp_path: Path, sample: object) -> None:
    ms = sample.measurements
    cut = len(ms) // 2
    with BagWriter(tmp_path / 'in') as bag:
        for k, m in enumerate(ms):
            if k == cut:
                bag.write_raw('/ga/measurements', ODOMETRY, b'\x00\x01\x00\x00\xff', m.stamp_ns)
            bag.write('/ga/measurements', ODOMETRY, measurement_to_odometry(m), m.stamp_ns)
    with pytest.raises(FormatError, match='cannot deserialise') as info:
        replay(tmp_path / 'in', tmp_path / 'out', ReplayConfig(), aligner_factory=DeadReckoning)
    r = info.value.result
    assert r.n_measurements == cut and 'partial outputs' in str(info.value)
    counts = mcap_counts(tmp_path / 'out' / 'replay_bag')  # the partial bag is a valid mcap
    assert counts['/ga/measurements'] == cut and counts['/ga/corrected_path'] >= 1
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert 'cannot deserialise' in summary['error']
    assert (tmp_path / 'out' / 'trajectory_ga.tum').exists()


def _raw(bag: Path, topic: str) -> list[bytes]:
    with BagReader(bag) as b:
        return [m.data for m in b.messages([topic], raw=True)]


@pytest.mark.parametrize('keep_metadata', [False, True])
def test_truncated_bag_replays_what_is_there(tmp_path: Path, capsys, keep_metadata: bool) -> None:
    """A bag cut at 60 % of its bytes (with or without its metadata.yaml): the replay uses the
    messages before the cut (also those of the chunk the cut goes through), warns, exits 0."""
    s = aerial_sample(n_tracks=4, positions_per_swath=40, seed=2)
    bag = write_measurement_bag(tmp_path / 'in', s.measurements, s.ground_truth)
    data = (bag / 'in.mcap').read_bytes()
    cut = tmp_path / 'cut'
    cut.mkdir()
    name = 'in.mcap' if keep_metadata else 'cut.mcap'
    (cut / name).write_bytes(data[:len(data) * 6 // 10])
    if keep_metadata:
        (cut / 'metadata.yaml').write_bytes((bag / 'metadata.yaml').read_bytes())
    out = tmp_path / 'out'
    assert cli_main(['replay', str(cut), '--out', str(out), '--no-plot', '--aligner',
                     'batch']) == 0
    err = capsys.readouterr().err
    assert 'warning:' in err and 'truncated' in err and 'Traceback' not in err
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['error'] is None and 'truncated' in summary['warnings'][0]
    original = _raw(bag, '/ga/measurements')
    used = _raw(out / 'replay_bag', '/ga/measurements')
    # every message up to the cut (most of the first 60 % of the bytes), in order, unchanged
    assert summary['n_inputs'] == summary['n_measurements'] == len(used)
    assert 0.5 * len(original) < len(used) < len(original)
    assert used == original[:len(used)]


def test_bad_inputs_change_nothing(tmp_path: Path, measurement_bag: Path, capsys) -> None:
    out = tmp_path / 'out'
    with pytest.raises(FormatError, match='missing topic /other'):
        replay(measurement_bag, out, ReplayConfig(
            topics=ReplayConfig().topics.__class__(measurements='/other', source='measurements')),
            aligner_factory=DeadReckoning)
    assert not out.exists()
    assert cli_main(['replay', str(tmp_path / 'nope'), '--out', str(out)]) == 1
    assert 'bag not found' in capsys.readouterr().err
    assert not out.exists()


def test_info_mode(measurement_bag: Path, capsys) -> None:
    assert cli_main(['replay', str(measurement_bag), '--info']) == 0
    text = capsys.readouterr().out
    assert '/ga/measurements' in text and 'nav_msgs/msg/Odometry' in text
    assert 'source: measurements' in text and 'ground truth: /ga/ground_truth' in text
    assert cli_main(['replay', str(measurement_bag), '--info', '--source', 'stereo']) == 1
    assert 'cannot replay' in capsys.readouterr().out


def test_committed_measurement_bag_matches_its_generator() -> None:
    """bags/aerial_measurements holds exactly what the generator makes (first messages)."""
    path = REPO / 'bags' / 'aerial_measurements'
    if not path.exists():
        pytest.skip('sample bag not generated')
    from ga_ros.io.bag_messages import odometry_to_measurement

    s = aerial_sample(n_tracks=25)
    with BagReader(path) as bag:
        assert bag.info.topic('/ga/measurements').count == len(s.measurements)
        for k, m in enumerate(bag.messages(['/ga/measurements'])):
            got, want = odometry_to_measurement(m.msg), s.measurements[k]
            assert (got.src_id, got.dst_id, got.kind, got.stamp_ns) == (
                want.src_id, want.dst_id, want.kind, want.stamp_ns)
            np.testing.assert_allclose(got.z, want.z, atol=1e-12)
            if k == 200:
                break


# --------------------------------------------------------------------------- real aligner
def test_replay_reproduces_the_in_process_pipeline(tmp_path: Path, sample: object) -> None:
    """The replay's online path equals TrackWindowAligner fed the same measurements, its GA
    path the same aligner's final batch (``refine_batch``); each RMSE as computed here."""
    window = pytest.importorskip('ga_ros.core.window')
    T0 = sample.ground_truth.T_world_node[0]
    aligner = window.TrackWindowAligner(window.AlignerConfig(), T_world_first=T0)
    for m in sample.measurements:
        aligner.add_measurement(m)
    aligner.finish_track()
    online = np.asarray(aligner.corrected_path().T_world_node).copy()
    groups = SourceGroups()  # the final batch estimates a variance factor per source
    for m in sample.measurements:
        groups.add(m)
    aligner.refine_batch(variance_groups=groups,
                         variance_config=VarianceComponentConfig(apply=False))
    cp = aligner.corrected_path()
    bag = write_measurement_bag(tmp_path / 'in', sample.measurements, sample.ground_truth)
    r = replay(bag, tmp_path / 'out', ReplayConfig())
    np.testing.assert_array_equal(r.corrected.node_ids, cp.node_ids)
    np.testing.assert_allclose(r.corrected.T_world_node, cp.T_world_node, atol=1e-9)
    np.testing.assert_allclose(r.online.T_world_node, online, atol=1e-9)
    np.testing.assert_allclose(last_path(tmp_path / 'out' / 'replay_bag'),
                               np.asarray(cp.T_world_node)[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(read_tum(r.files['trajectory_online']).T_world_node[:, :3, 3],
                               online[:, :3, 3], atol=1e-6)
    p_gt = sample.ground_truth.T_world_node[:, :3, 3]

    def rmse(T: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((np.asarray(T)[:, :3, 3] - p_gt) ** 2, 1))))

    assert r.errors['ga'].ate_raw == pytest.approx(rmse(cp.T_world_node), rel=1e-9)
    assert r.errors['online'].ate_raw == pytest.approx(rmse(online), rel=1e-9)
    assert r.errors['ga'].ate_raw <= r.errors['online'].ate_raw * (1 + 1e-9)
    assert r.errors['ga'].ate_raw < r.errors['f2f'].ate_raw


def test_cli_replay_demo_and_exit_codes(tmp_path: Path, sample: object, capsys) -> None:
    """`ga-ros demo` on small sample bags end to end; `ga-ros replay` exit codes."""
    pytest.importorskip('ga_ros.core.window')
    from ga_ros.replay.samples import MEASUREMENTS_BAG

    bags = tmp_path / 'bags'
    write_measurement_bag(bags / MEASUREMENTS_BAG, sample.measurements, sample.ground_truth)
    code = cli_main(['demo', '--bags', str(bags), '--out', str(tmp_path / 'demo'),
                     '--only', 'measurements', '--no-progress'])
    out = capsys.readouterr().out
    assert code == 0
    assert 'position RMSE against ground truth' in out and 'F2F' in out and 'GA' in out
    summary = json.loads((tmp_path / 'demo' / MEASUREMENTS_BAG / 'summary.json').read_text())
    assert summary['errors_vs_ground_truth']['ga']['ate_raw_m'] < (
        summary['errors_vs_ground_truth']['f2f']['ate_raw_m'])
    assert str(tmp_path / 'demo' / MEASUREMENTS_BAG / 'trajectory.png') in out
    # replay --json; then a truncated copy exits 1 with the partial outputs
    assert cli_main(['replay', str(bags / MEASUREMENTS_BAG), '--out', str(tmp_path / 'r'),
                     '--json', '--window', '2']) == 0
    assert json.loads(capsys.readouterr().out)['n_measurements'] == len(sample.measurements)
    data = (bags / MEASUREMENTS_BAG / f'{MEASUREMENTS_BAG}.mcap').read_bytes()
    (tmp_path / 'cut.mcap').write_bytes(data[:len(data) - 200])
    # cut in its summary section: every message is there; a warning says the file is damaged
    assert cli_main(['replay', str(tmp_path / 'cut.mcap'), '--out', str(tmp_path / 'c')]) == 0
    assert 'warning:' in capsys.readouterr().err
    summary = json.loads((tmp_path / 'c' / 'summary.json').read_text())
    assert 'truncated' in summary['warnings'][0]
    assert summary['n_measurements'] == len(sample.measurements)


def test_batch_aligner_equals_one_batch_solve(tmp_path: Path, sample: object) -> None:
    """--aligner batch: the final path is the batch solution over every measurement."""
    from ga_ros.core.network import ConnectionNetwork
    from ga_ros.core.solver import SolverConfig, solve

    bag = write_measurement_bag(tmp_path / 'in', sample.measurements, sample.ground_truth)
    r = replay(bag, tmp_path / 'out', ReplayConfig(aligner_kind='batch', plot=False,
                                                   variance_components='off'))
    gt = sample.ground_truth
    net = ConnectionNetwork()
    for n, t in zip(gt.node_ids, gt.track_ids):
        net.add_node(int(n), int(t))
    for m in sample.measurements:
        net.add_connection(m.src_id, m.dst_id, m.z, m.cov)
    chain = [m.T_src_dst for m in sample.measurements if m.kind == 'consecutive']
    res = solve(net, se3.integrate(gt.T_world_node[0], np.array(chain)), SolverConfig(),
                fixed=[0])
    np.testing.assert_array_equal(r.corrected.node_ids, gt.node_ids)
    np.testing.assert_allclose(r.corrected.T_world_node, res.T_world_node, atol=1e-6)
    assert r.errors['ga'].ate_raw < 0.5 * r.errors['f2f'].ate_raw
    cov = res.covariance([5])[0]
    with BagReader(tmp_path / 'out' / 'replay_bag') as out:
        poses = [m.msg for m in out.messages(['/ga/corrected_pose'])]
    np.testing.assert_allclose(np.asarray(poses[5].pose.covariance).reshape(6, 6), cov,
                               rtol=1e-6, atol=1e-12)
