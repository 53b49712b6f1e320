"""Several relative sources on one keyframe graph (:mod:`ga_ros.inputs.secondary`).

A ground robot drives a gently weaving path at 1 m/s. Its wheel odometry (50 Hz) measures the
travel well and the heading poorly; a visual odometry (10 Hz, its own odom frame) measures the
heading well and the travel poorly, starts 20 s late and drops out for 10 s. The wheel
odometry also drifts in heading (a yaw-rate bias) in the bag of the accuracy test; the
Monte-Carlo of the covariances has white noise only. Both publish
``nav_msgs/Odometry`` with the twist covariance of the noise they were made with; the bags are
written here with rosbags, as a robot records them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_STAMPED,
    odometry_msg,
    ros1_pose_stamped_msg,
    write_bag,
    write_ros1_bag,
)
from scipy import stats

from ga_ros import domains
from ga_ros.core.tracks import TrackRules
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import GaError
from ga_ros.geometry import se3
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.inputs.secondary import KeyframeInterval, SecondaryInput
from ga_ros.io.trajectory import write_tum
from ga_ros.pipeline.inputs import InputFrontEnd, InputSpec
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.inputs import InputTopics
from ga_ros.replay.pipeline import replay

T0_NS = 1_700_000_000_000_000_000
WHEEL_HZ, VISUAL_HZ = 50, 10
#: per-sample velocity noise (twist covariance sigmas [vx vy vz wx wy wz], m/s and rad/s)
WHEEL_SIGMA = np.array([0.05, 0.05, 0.02, 0.01, 0.01, 0.04])
VISUAL_SIGMA = np.array([2.0, 2.0, 1.0, 0.005, 0.005, 0.005])


@dataclass
class Streams:
    """Ground truth and the two odometry streams (stamps in ns)."""

    stamps: np.ndarray       # wheel stamps = ground-truth stamps
    gt: np.ndarray           # (n, 4, 4) T_world_base
    wheel: np.ndarray        # (n, 4, 4) wheel T_odom_base
    v_stamps: np.ndarray     # visual stamps (published ones only)
    visual: np.ndarray       # (m, 4, 4) visual T_odom_base


def simulate(rng: np.random.Generator, duration_s: float = 120.0, start_s: float = 20.0,
             dropout_s: tuple[float, float] = (60.0, 70.0), yaw_bias: float = 0.0) -> Streams:
    """The two streams of one run (module doc); ``yaw_bias`` (rad/s) is a heading drift of
    the wheel odometry on top of its white noise (not in its covariance)."""
    dt = 1.0 / WHEEL_HZ
    n = int(duration_s * WHEEL_HZ) + 1
    t = np.arange(n) * dt
    xi = np.zeros((n, 6))
    xi[:, 0] = 1.0
    xi[:, 5] = 0.25 * np.sin(2 * np.pi * t / 30.0)
    gt = np.empty((n, 4, 4))
    wheel = np.empty((n, 4, 4))
    gt[0] = se3.from_translation_rotvec(np.array([5.0, -3.0, 0.0]), np.array([0, 0, 0.4]))
    wheel[0] = np.eye(4)
    bias = np.array([0, 0, 0, 0, 0, yaw_bias])
    for k in range(n - 1):
        gt[k + 1] = gt[k] @ se3.exp(dt * xi[k])
        wheel[k + 1] = wheel[k] @ se3.exp(dt * (xi[k] + bias + rng.normal(0.0, WHEEL_SIGMA)))
    step = WHEEL_HZ // VISUAL_HZ
    idx = np.arange(int(start_s * WHEEL_HZ), n, step)
    visual = [se3.from_translation_rotvec(np.array([-1.0, 2.0, 0.5]), np.array([0, 0, -1.0]))]
    for a, b in zip(idx[:-1], idx[1:]):
        motion = se3.log(se3.relative(gt[a], gt[b]))
        noise = rng.normal(0.0, VISUAL_SIGMA) * (step * dt)
        visual.append(visual[-1] @ se3.exp(motion + noise))
    keep = ~((t[idx] >= dropout_s[0]) & (t[idx] < dropout_s[1]))
    stamps = T0_NS + np.round(t * 1e9).astype(np.int64)
    return Streams(stamps, gt, wheel, stamps[idx][keep], np.array(visual)[keep])


def _odometry(T: np.ndarray, stamp: int, twist_sigma: np.ndarray, frame: str) -> object:
    """Odometry at 1 m/s forward with the twist covariance of the stream's noise."""
    return odometry_msg(T, int(stamp), frame=frame, twist_cov=np.diag(twist_sigma ** 2),
                        linear_x=1.0)


def messages(s: Streams) -> list[tuple[int, str, object]]:
    """(log time, topic, message) of both streams in log order (the visual 5 ms late)."""
    out = [(int(st), '/wheel/odom', _odometry(T, st, WHEEL_SIGMA, 'odom'))
           for st, T in zip(s.stamps, s.wheel)]
    out += [(int(st) + 5_000_000, '/vo/odom', _odometry(T, st, VISUAL_SIGMA, 'vo_odom'))
            for st, T in zip(s.v_stamps, s.visual)]
    out.sort(key=lambda x: x[0])
    return out


def config(name: str) -> OdometryInputConfig:
    return OdometryInputConfig(name, keyframe_travel_m=1.0,
                               track=TrackRules('time', duration_s=20.0))


def replay_config(topics: list[str], gt_file: Path) -> ReplayConfig:
    specs = tuple(InputSpec(t, 'odometry', config(f'odom{k}')) for k, t in enumerate(topics))
    return ReplayConfig(inputs=InputTopics(specs), plot=False, ground_truth_file=str(gt_file))


@pytest.fixture(scope='module')
def two_stream_bag(tmp_path_factory) -> tuple[Path, Path, Streams]:
    tmp = tmp_path_factory.mktemp('two_streams')
    s = simulate(np.random.default_rng(7), yaw_bias=0.002)
    write_bag(tmp / 'in', [(log, topic, ODOMETRY, msg) for log, topic, msg in messages(s)])
    write_tum(tmp / 'gt.tum', s.stamps, s.gt)
    return tmp / 'in', tmp / 'gt.tum', s


def test_two_odometry_streams_fuse_without_rejection(two_stream_bag, tmp_path: Path) -> None:
    bag, gt_file, s = two_stream_bag
    both = replay(bag, tmp_path / 'both', replay_config(['/wheel/odom', '/vo/odom'], gt_file))
    assert both.rejected == {}, both.rejected_examples
    wheel_st, vo_st = both.source_stats['odom0'], both.source_stats['odom1']
    # the visual stream measured every keyframe interval it brackets, and only those: the
    # first 20 s and the 10 s dropout (plus the intervals around its edges) are not covered
    assert vo_st['samples'] == len(s.v_stamps)
    n_intervals = wheel_st['keyframes'] - 1
    assert vo_st['measurements'] + vo_st['not_covered'] <= n_intervals
    assert 0.6 * n_intervals < vo_st['measurements'] < 0.8 * n_intervals
    assert vo_st['not_covered'] >= 9  # the dropout: ~10 keyframes at 1 m per keyframe
    assert both.n_measurements == wheel_st['measurements'] + vo_st['measurements']
    assert vo_st['default_covariances'] == 0
    wheel = replay(bag, tmp_path / 'wheel', replay_config(['/wheel/odom'], gt_file))
    visual = replay(bag, tmp_path / 'vo', replay_config(['/vo/odom'], gt_file))
    rmse = {k: r.errors['ga'].ate_raw for k, r in
            (('both', both), ('wheel', wheel), ('visual', visual))}
    # (measured 3.2 m fused, 5.6 m wheel, 6.2 m visual: the first 20 s and the dropout are
    # the wheel's alone)
    assert rmse['both'] < 0.8 * min(rmse['wheel'], rmse['visual']), rmse


def test_ros1_bag_with_two_slam_outputs_rejects_nothing(tmp_path: Path) -> None:
    """Two SLAM systems' ``geometry_msgs/PoseStamped`` in a ROS 1 bag, at 20 Hz and 15 Hz."""
    s = simulate(np.random.default_rng(3), duration_s=40.0, start_s=0.0, dropout_s=(0, 0))
    rows = [(int(st), '/slam_a/pose', POSE_STAMPED, ros1_pose_stamped_msg(T, int(st)))
            for st, T in zip(s.stamps[::2], s.wheel[::2])]
    rows += [(int(st) + 1_000_000, '/slam_b/pose', POSE_STAMPED, ros1_pose_stamped_msg(T, int(st)))
             for st, T in zip(s.stamps[1::3], s.gt[1::3])]
    path = write_ros1_bag(tmp_path / 'slam.bag', rows)
    specs = tuple(InputSpec(t, 'pose', config(f'odom{k}'))
                  for k, t in enumerate(['/slam_a/pose', '/slam_b/pose']))
    res = replay(path, tmp_path / 'out', ReplayConfig(inputs=InputTopics(specs), plot=False))
    assert res.rejected == {}, res.rejected_examples
    b = res.source_stats['odom1']
    # every keyframe interval measured but the first (slam_b starts 20 ms after it) and at
    # most one after slam_b's last pose (still waiting)
    assert (b['measurements'] + b['not_covered'] + b['pending']
            == res.source_stats['odom0']['keyframes'] - 1)
    assert b['measurements'] > 30 and b['pending'] <= 1 and b['not_covered'] == 1
    assert res.n_measurements == res.source_stats['odom0']['measurements'] + b['measurements']


def _fused_run(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, int]:
    """One Monte-Carlo run through the input front end and the live aligner: the 6-dof NEES
    of the last node and of the node nearest the middle, and the rejections."""
    s = simulate(rng, duration_s=60.0, start_s=10.0, dropout_s=(30.0, 35.0))
    front = InputFrontEnd([InputSpec('/wheel/odom', 'odometry', config('odom0')),
                           InputSpec('/vo/odom', 'odometry', config('odom1'))])
    aligner = TrackWindowAligner(AlignerConfig(), T_world_first=s.gt[0])
    node_stamps, rejected = {}, 0
    for _, topic, msg in messages(s):
        step = front.sample('odom0' if topic == '/wheel/odom' else 'odom1', msg)
        assert not step.error, step.error
        node_stamps.update(step.node_stamps)
        for m in step.measurements:
            try:
                aligner.add_measurement(m)
            except GaError:
                rejected += 1
    aligner.finish_track()
    ids = np.array(sorted(node_stamps)[1:])
    ids = ids[[len(ids) // 2, -1]]
    path = aligner.corrected_path()
    row = {int(n): k for k, n in enumerate(path.node_ids)}
    T_est = path.T_world_node[[row[int(n)] for n in ids]]
    T_true = s.gt[np.searchsorted(s.stamps, [node_stamps[int(n)] for n in ids])]
    cov = aligner.covariances(ids)
    e = se3.log(se3.inverse(T_est) @ T_true)
    nees = np.einsum('ni,ni->n', e, np.linalg.solve(cov, e[:, :, None])[:, :, 0])
    return nees[0], nees[1], rejected


def test_published_covariances_of_the_fused_graph_are_honest() -> None:
    """6-dof NEES of the last node over a small Monte-Carlo: the sum over ``R`` runs is
    chi-square with ``6 R`` degrees of freedom; the middle node alike."""
    rng = np.random.default_rng(11)
    runs = 12
    out = [_fused_run(rng) for _ in range(runs)]
    assert sum(r[2] for r in out) == 0
    lo, hi = stats.chi2.ppf([0.005, 0.995], 6 * runs)
    for k in (0, 1):
        total = sum(r[k] for r in out)
        assert lo < total < hi, (k, total / runs, lo / runs, hi / runs)


def test_secondary_interval_motion_and_coverage() -> None:
    """The motion between two keyframe stamps from a stream sampled off those stamps is the
    SE(3) interpolation of its poses; intervals before its start or across a gap are not
    covered, and an interval waits until a sample reaches its end."""
    w = np.array([0.0, 0.0, 0.3])
    v = np.array([1.0, 0.2, 0.0])

    def pose(t: float) -> np.ndarray:  # constant twist: interpolation is exact
        return se3.from_translation_rotvec(np.zeros(3), np.zeros(3)) @ se3.exp(
            t * np.concatenate([v, w]))

    sec = SecondaryInput(OdometryInputConfig('odom1', max_gap_s=0.5,
                                             covariance_source='default'))
    ns = 1_000_000_000
    iv0 = KeyframeInterval(0, 1, 0, 0, 0, int(0.55 * ns))  # before the stream starts
    iv1 = KeyframeInterval(1, 2, 0, 0, int(0.55 * ns), int(1.33 * ns))
    iv2 = KeyframeInterval(2, 3, 0, 0, int(1.33 * ns), int(2.85 * ns))  # across the gap
    iv3 = KeyframeInterval(3, 4, 0, 1, int(2.85 * ns), int(3.04 * ns))
    got = []
    for t in (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2):
        got += sec.add_sample(int(t * ns), pose(t))
    assert sec.add_interval(iv0) == [] and sec.stats.not_covered == 1
    assert sec.add_interval(iv1) == [] and sec.stats.pending == 1  # waits for a sample >= 1.33 s
    for t in (1.3, 1.4, 2.0, 2.2, 2.8, 2.9, 3.0):
        got += sec.add_sample(int(t * ns), pose(t))
    got += sec.add_interval(iv2)
    got += sec.add_interval(iv3)
    assert sec.stats.pending == 1  # iv3 waits
    got += sec.add_sample(int(3.1 * ns), pose(3.1))
    assert [(m.src_id, m.dst_id) for m in got] == [(1, 2), (3, 4)]
    assert got[1].dst_track == 1 and got[1].kind == 'consecutive'
    for m, (a, b) in zip(got, ((0.55, 1.33), (2.85, 3.04))):
        expected = se3.to_translation_rotvec(se3.relative(pose(a), pose(b)))
        np.testing.assert_allclose(m.z, expected, atol=1e-9)
        assert m.stamp_ns == int(b * ns)
    st = sec.stats
    assert (st.measurements, st.not_covered, st.default_covariances) == (2, 2, 2)


def test_secondary_twist_covariance_matches_the_primary_integration() -> None:
    """Over an interval whose ends are samples, the secondary's integrated twist covariance
    equals the primary's own (:class:`OdometryInput`), computed independently."""
    from ga_ros.inputs.odometry import OdometryInput

    rng = np.random.default_rng(5)
    ns = 100_000_000
    cfg = OdometryInputConfig('odom0', keyframe_interval_s=1.0, keyframe_travel_m=0.0,
                              keyframe_rotation_deg=0.0)
    prim, sec = OdometryInput(cfg), SecondaryInput(cfg)
    T = np.eye(4)
    kf, got = [], []
    for k in range(25):
        Sigma = np.diag(rng.uniform(0.01, 0.1, 6) ** 2)
        T = T @ se3.exp(rng.normal(0, 0.1, 6))
        up = prim.add_sample(k * ns, T, None, Sigma)
        got += sec.add_sample(k * ns, T, None, Sigma)
        if up.measurement is not None:
            kf.append(up.measurement)
            got += sec.add_interval(KeyframeInterval(up.measurement.src_id,
                                                     up.measurement.dst_id, 0, 0,
                                                     int(up.stamp_ns - 10 * ns),
                                                     int(up.stamp_ns)))
    assert len(kf) == len(got) == 2
    for a, b in zip(kf, got):
        np.testing.assert_allclose(b.z, a.z, atol=1e-12)
        np.testing.assert_allclose(b.cov, a.cov, rtol=1e-9, atol=1e-15)


def test_alignment_node_takes_two_odometry_inputs(tmp_path: Path) -> None:
    """The node with ``inputs: odom0,odom1`` (in-process callbacks): the second stream's
    measurements are accepted on the first one's keyframes."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.parameter import Parameter

    from ga_ros.ros.alignment_node import AlignmentNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domains.domain_id('multiple_sources'))
    params = {'inputs': 'odom0,odom1', 'odom0.topic': 'wheel/odom', 'odom1.topic': 'vo/odom',
              'odom0.track.mode': 'time', 'odom0.track.duration_s': 10.0,
              'publish_markers': False, 'diagnostics_period_sec': 0.0,
              'transform_publish_period_sec': 0.0}
    node = AlignmentNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                           for k, v in params.items()])
    try:
        s = simulate(np.random.default_rng(2), duration_s=30.0, start_s=5.0,
                     dropout_s=(15.0, 18.0))
        for _, topic, msg in messages(s):
            node._on_input('odom0' if topic == '/wheel/odom' else 'odom1', msg)
        wheel, vo = node.front.inputs['odom0'].stats, node.front.inputs['odom1'].stats
        assert vo.measurements > 10 and vo.not_covered > 0
        assert sum(node.session.counts.rejected.values()) == 0
        assert node.session.counts.accepted == wheel.measurements + vo.measurements
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
