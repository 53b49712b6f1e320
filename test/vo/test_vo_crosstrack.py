"""Cross-track connections on simulated swaths: correct when accepted, wrong pairs rejected."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import StereoCalibration
from ga_ros.vo.crosstrack import CrossTrackConfig, CrossTrackMatcher, predicted_overlap
from ga_ros.vo.evaluate import motion_errors
from ga_ros.vo.odometry import StereoFrame, StereoOdometry, VoConfig

RIG = StereoRig()


@pytest.fixture(scope='module')
def two_swaths():
    """One track (up and down swath) through the odometry; keyframes and their true frames."""
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=14, turn_positions=12,
                                       seed=6))
    scene = make_scene(survey, RIG, seed=6)
    cal = StereoCalibration.rectified(RIG.width, RIG.height, RIG.K, RIG.baseline_m)
    vo = StereoOdometry(cal, VoConfig())
    rng = np.random.default_rng(6)
    keyframes, kf_frame, results = [], {}, []
    for i, T in enumerate(survey.T_world_cam):
        res = vo.process(StereoFrame(*scene.render_pair(T, rng), int(survey.stamps_ns[i])))
        results.append(res)
        if res.keyframe is not None:
            keyframes.append(res.keyframe)
            kf_frame[res.keyframe.node_id] = i
    return survey, scene, keyframes, kf_frame, results


def test_predicted_overlap():
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[2, 3] = 110.0
    assert predicted_overlap(T, 75.0, T, RIG.K, 320, 240) == pytest.approx(1.0, abs=1e-3)
    shifted = T @ se3.from_rt(np.eye(3), [25.0, 0.0, 0.0])  # a quarter of the 100 m width
    assert predicted_overlap(T, 75.0, shifted, RIG.K, 320, 240) == pytest.approx(0.75, abs=0.01)
    away = T @ se3.from_rt(np.eye(3), [500.0, 0.0, 0.0])
    assert predicted_overlap(T, 75.0, away, RIG.K, 320, 240) == 0.0


def test_heading_reversal_starts_a_new_segment(two_swaths):
    survey, _, keyframes, kf_frame, _ = two_swaths
    segs = np.array([k.segment for k in keyframes])
    assert segs[0] == 0 and segs[-1] == 1 and np.all(np.diff(segs) >= 0)
    # The segment changes inside the turn, after the first swath ended.
    first_new = keyframes[int(np.argmax(segs == 1))]
    assert survey.in_turn[kf_frame[first_new.node_id]]
    assert all(k.track_id == 0 for k in keyframes)  # two swaths = one track


def test_accepted_connections_are_correct(two_swaths):
    survey, _, keyframes, kf_frame, _ = two_swaths
    matcher = CrossTrackMatcher(RIG.K, RIG.width, RIG.height)
    attempts = []
    for kf in keyframes:
        attempts += matcher.add(kf)
    accepted = [a for a in attempts if a.accepted]
    assert len(accepted) >= 5
    for a in accepted:
        m = a.measurement
        assert m.kind == 'cross' and m.src_id < m.dst_id
        T_true = se3.relative(survey.T_world_cam[kf_frame[m.src_id]],
                              survey.T_world_cam[kf_frame[m.dst_id]])
        dt, dr, _ = motion_errors(T_true, m)
        assert dt < 0.5 and dr < 0.5, (a, dt, dr)
        assert a.n_inliers >= matcher.config.min_inliers
        assert np.all(np.linalg.eigvalsh(m.cov) > 0)
    assert len(matcher) == len(keyframes)


def test_wrong_pairs_are_rejected(two_swaths):
    """Keyframes of another terrain, placed where a true overlap is predicted: no connection."""
    survey, _, keyframes, _, _ = two_swaths
    other_survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=14,
                                             turn_positions=12, seed=6))
    other = make_scene(other_survey, RIG, seed=99)  # same flight, different terrain
    cal = StereoCalibration.rectified(RIG.width, RIG.height, RIG.K, RIG.baseline_m)
    vo = StereoOdometry(cal, VoConfig(first_node_id=1000))
    rng = np.random.default_rng(7)
    fakes = []
    for i, T in enumerate(other_survey.T_world_cam[-14:]):
        res = vo.process(StereoFrame(*other.render_pair(T, rng), i))
        if res.keyframe is not None:
            fakes.append(res.keyframe)
    matcher = CrossTrackMatcher(RIG.K, RIG.width, RIG.height)
    for kf in keyframes:
        if kf.segment == 0:
            matcher.add(kf)
    attempts = []
    for fake in fakes:
        # Claim the pose of the true keyframe at the same place in the down swath.
        attempts += matcher.add(dataclasses.replace(fake, segment=1))
    assert len(attempts) >= 5
    assert not any(a.accepted for a in attempts)


def test_store_is_bounded_and_uses_corrected_poses(two_swaths):
    _, _, keyframes, _, _ = two_swaths
    matcher = CrossTrackMatcher(RIG.K, RIG.width, RIG.height,
                                CrossTrackConfig(max_keyframes=5))
    for kf in keyframes:
        matcher.add(kf)
    assert len(matcher) == 5 and matcher.node_ids == [k.node_id for k in keyframes[-5:]]
    # Later tracks evict the ones outside the window.
    m2 = CrossTrackMatcher(RIG.K, RIG.width, RIG.height, CrossTrackConfig(window_tracks=1))
    m2.add(keyframes[0])
    m2.add(dataclasses.replace(keyframes[1], track_id=1))
    assert m2.node_ids == [keyframes[1].node_id]
    # A corrected pose of an earlier keyframe moves the prediction of later ones with it.
    ids = matcher.node_ids
    shift = se3.from_rt(np.eye(3), [5.0, 0.0, 0.0])
    T0 = shift @ keyframes[-5].T_world_kf
    matcher.set_corrected_poses(np.array([ids[0]]), T0[None])
    np.testing.assert_allclose(matcher.predicted_pose(ids[0]), T0)
    np.testing.assert_allclose(matcher.predicted_pose(ids[2]),
                               shift @ keyframes[-3].T_world_kf, atol=1e-9)
    with pytest.raises(InputError):
        matcher.set_corrected_poses(np.array([1, 2]), np.eye(4)[None])
