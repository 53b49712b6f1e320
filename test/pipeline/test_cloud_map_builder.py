"""CloudMapBuilder (ga_ros.pipeline.cloud_map), what map_node and replay --map drive: clouds in a
camera frame placed with the extrinsic (waiting for /tf_static), the first two keyframes'
shared stamp, full and empty corrections, the path used only until corrections come."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ga_ros.core.extrinsic import ExtrinsicConfig
from ga_ros.geometry import se3
from ga_ros.mapping.cloud_map import CloudMapConfig
from ga_ros.pipeline.cloud_map import CloudMapBuilder
from ga_ros.pipeline.corrections import (
    CorrectionMessage,
    CorrectionThresholds,
    CorrectionTracker,
    decoded,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'mapping'))
from test_cloud_map import VOXEL, assert_same_map, random_cloud, reference_map  # noqa: E402
from test_cloud_map import Path as KeyPath  # noqa: E402

EXACT = CloudMapConfig(voxel_m=VOXEL, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                       max_live_keyframes=0)
T_BASE_CAM = se3.from_translation_rotvec(np.array([0.2, 0.0, 0.5]),
                                         np.array([-1.2091996, 1.2091996, -1.2091996]))


def tf_static(parent: str, child: str, T: np.ndarray) -> SimpleNamespace:
    """A tf2_msgs/TFMessage as TransformTree reads it (fields by name)."""
    p, q = se3.to_pos_quat(T)
    tr = SimpleNamespace(translation=SimpleNamespace(x=p[0], y=p[1], z=p[2]),
                         rotation=SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3]))
    return SimpleNamespace(transforms=[SimpleNamespace(
        header=SimpleNamespace(frame_id=parent), child_frame_id=child, transform=tr)])


def message(full: bool, stamps: list, T) -> CorrectionMessage:
    """A corrections message of entries only (no span)."""
    return CorrectionMessage(full, np.array(stamps, np.int64),
                             np.array(T, float).reshape(-1, 4, 4), np.zeros(len(stamps), bool))


def test_clouds_wait_for_the_extrinsic_then_follow_the_corrections(rng) -> None:
    b = CloudMapBuilder(EXACT, ExtrinsicConfig(base_frame='base_link'))
    stamps = [100, 200, 300]
    clouds = {s: random_cloud(rng, 80) for s in stamps}
    T = {s: se3.from_translation_rotvec(rng.normal(0, 2, 3), rng.normal(0, 0.2, 3))
         for s in stamps}
    for s in stamps[:2]:
        assert not b.add_cloud(s, 'cam_optical', *clouds[s])
    assert len(b.waiting) == 2 and 'extrinsic unknown' in b.extrinsic_error
    b.add_tf_static(tf_static('base_link', 'cam_optical', T_BASE_CAM))
    assert not b.waiting and b.extrinsic_error == ''
    b.on_corrections(message(True, stamps, [T[s] for s in stamps]))
    b.add_cloud(300, 'cam_optical', *clouds[300])
    want = lambda T: reference_map({s: T[s] @ T_BASE_CAM for s in stamps}, clouds)
    assert_same_map(b.cloud(), want(T))
    assert b.take_changed() and not b.take_changed()
    # the path is ignored once corrections came
    assert b.on_path(np.array([100]), np.eye(4)[None]) is None
    T[200] = se3.from_translation_rotvec(np.array([1.0, 0, 0]), np.zeros(3)) @ T[200]
    up = b.on_corrections(message(False, [200], T[200][None])).update
    assert up.moved == 1 and b.take_changed()
    assert_same_map(b.cloud(), want(T))
    # a full message unplaces everything first; an empty one (a reset) empties the map
    b.on_corrections(message(True, [100], T[100][None]))
    assert_same_map(b.cloud(), reference_map({100: T[100] @ T_BASE_CAM}, clouds))
    b.on_corrections(message(True, [], np.zeros((0, 4, 4))))
    assert len(b.cloud()) == 0 and b.counts.full == 3


def test_the_first_two_keyframes_sharing_a_stamp(rng) -> None:
    """The path stamps the first keyframe with the second's stamp: its pose goes to the cloud
    stamped before (the first keyframe's), in this message and the later ones."""
    b = CloudMapBuilder(EXACT, ExtrinsicConfig(assume_identity_extrinsic=True))
    clouds = {s: random_cloud(rng, 60) for s in (10, 20, 30)}
    for s in clouds:
        b.add_cloud(s, 'cam', *clouds[s])
    T = [se3.from_translation_rotvec(np.array([3.0 * k, 0, 0]), np.zeros(3)) for k in range(3)]
    b.on_path(np.array([20, 20, 30]), np.array(T))
    assert_same_map(b.cloud(), reference_map({10: T[0], 20: T[1], 30: T[2]}, clouds))
    T[0] = T[0] @ se3.from_translation_rotvec(np.array([0, 0.5, 0]), np.zeros(3))
    b.on_corrections(message(False, [20, 20], T[:2]))
    assert_same_map(b.cloud(), reference_map({10: T[0], 20: T[1], 30: T[2]}, clouds))


def test_a_malformed_cloud_changes_nothing(rng) -> None:
    b = CloudMapBuilder(EXACT, ExtrinsicConfig(assume_identity_extrinsic=True))
    b.on_path(np.array([1]), np.eye(4)[None])
    import pytest

    from ga_ros.errors import InputError

    with pytest.raises(InputError):
        b.add_cloud(1, 'cam', np.zeros((4, 2)), np.zeros(4))
    b.add_cloud(1, 'cam', *random_cloud(rng, 30))
    before = b.cloud()
    with pytest.raises(InputError):   # a full message with a NaN pose: nothing unplaced
        b.on_corrections(message(True, [1], np.full((1, 4, 4), np.nan)))
    np.testing.assert_array_equal(b.cloud().points, before.points)
    assert len(before) > 0 and b.counts.clouds == 1 and b.counts.corrections == 0


def test_map_from_interpolated_corrections_equals_the_map_from_scratch(rng) -> None:
    """A line of keyframes whose poses move smoothly at every update (a slowly growing rotation
    and a bend, as a window update moves a track), sent with the default thresholds: most
    keyframes are re-anchored inside spans. The map built from the messages equals, voxel for
    voxel, the map built from scratch at the poses the consumer holds, and those are within the
    thresholds of the final path."""
    th = CorrectionThresholds()
    n = 120
    stamps = 10**9 * (1 + np.arange(n, dtype=np.int64))
    base = np.array([se3.from_translation_rotvec(np.array([5.0 * k, 0.0, 30.0]),
                                                 np.array([0.0, 0.0, 0.01 * k]))
                     for k in range(n)])
    clouds = {int(s): random_cloud(rng, 40) for s in stamps}
    b = CloudMapBuilder(EXACT, ExtrinsicConfig(assume_identity_extrinsic=True))
    for s in stamps:
        b.add_cloud(int(s), 'cam', *clouds[int(s)])
    tracker = CorrectionTracker(th)
    interpolated = 0
    for u in range(1, 7):
        upto = 20 * u
        x = np.arange(upto) / n
        T = np.array([se3.from_translation_rotvec(
            np.array([0.3 * u * xi, 0.5 * u * xi ** 2, -0.2 * u * xi]),
            np.array([0.0, 0.002 * u * xi, 0.004 * u * xi])) @ base[k]
            for k, xi in enumerate(x)])
        c = tracker.compare(KeyPath(stamps[:upto], T))
        interpolated += c.n_interpolated
        b.on_corrections(c.message())
    assert interpolated > n // 2
    held = b.held.T_map_base
    np.testing.assert_array_equal(held, tracker.held())
    assert_same_map(b.cloud(), reference_map({int(s): held[k] for k, s in enumerate(stamps)},
                                             clouds))
    final = decoded(T)
    assert np.linalg.norm(held[:, :3, 3] - final[:, :3, 3], axis=1).max() <= th.translation_m
    cos = (np.trace(np.einsum('kji,kjl->kil', held[:, :3, :3], final[:, :3, :3]),
                    axis1=1, axis2=2) - 1) / 2
    assert np.arccos(np.clip(cos, -1, 1)).max() <= th.rotation_rad * 1.0001 + 1e-7
