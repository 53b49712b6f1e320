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

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'mapping'))
from test_cloud_map import VOXEL, assert_same_map, random_cloud, reference_map  # noqa: E402

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
    b.on_corrections(True, np.array(stamps), np.array([T[s] for s in stamps]))
    b.add_cloud(300, 'cam_optical', *clouds[300])
    want = lambda T: reference_map({s: T[s] @ T_BASE_CAM for s in stamps}, clouds)
    assert_same_map(b.cloud(), want(T))
    assert b.take_changed() and not b.take_changed()
    # the path is ignored once corrections came
    assert b.on_path(np.array([100]), np.eye(4)[None]) is None
    T[200] = se3.from_translation_rotvec(np.array([1.0, 0, 0]), np.zeros(3)) @ T[200]
    up = b.on_corrections(False, np.array([200]), T[200][None])
    assert up.moved == 1 and b.take_changed()
    assert_same_map(b.cloud(), want(T))
    # a full message unplaces everything first; an empty one (a reset) empties the map
    b.on_corrections(True, np.array([100]), T[100][None])
    assert_same_map(b.cloud(), reference_map({100: T[100] @ T_BASE_CAM}, clouds))
    b.on_corrections(True, np.zeros(0, np.int64), np.zeros((0, 4, 4)))
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
    b.on_corrections(False, np.array([20, 20]), np.array(T[:2]))
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
        b.on_corrections(True, np.array([1]), np.full((1, 4, 4), np.nan))
    np.testing.assert_array_equal(b.cloud().points, before.points)
    assert len(before) > 0 and b.counts.clouds == 1 and b.counts.corrections == 0
