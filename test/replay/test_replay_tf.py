"""The output ``/tf`` of a stereo replay is complete: ``map -> odom``, ``odom -> base_link`` from
the VO, and the input's ``/tf_static`` (the camera's extrinsic) carried.

Checked as a TF user would: the last ``map -> odom`` composed with the ``odom -> base_link`` of
the newest keyframe is the newest corrected pose on ``/ga/corrected_path``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import pose_msg_to_matrix, stamp_to_ns
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.pipeline import replay
from ga_ros.replay.samples import StereoSampleConfig, make_stereo_bag


def _transform(t) -> np.ndarray:
    from ga_ros.geometry import se3

    r, p = t.transform.rotation, t.transform.translation
    return se3.from_pos_quat(np.array([p.x, p.y, p.z]), np.array([r.x, r.y, r.z, r.w]))


@pytest.fixture(scope='module')
def stereo_replay(tmp_path_factory):
    d = tmp_path_factory.mktemp('tf')
    bag = make_stereo_bag(d / 'in', StereoSampleConfig(n_tracks=1, positions_per_swath=20))
    return replay(bag, d / 'out', ReplayConfig(plot=False))


def test_stereo_replay_tf_is_complete(stereo_replay):
    r = stereo_replay
    static, odom_base, map_odom = [], [], []
    with BagReader(r.files['bag']) as b:
        for m in b.messages(['/tf', '/tf_static', '/ga/corrected_path']):
            if m.topic == '/ga/corrected_path':
                last_path = m.msg
                continue
            for t in m.msg.transforms:
                edge = (t.header.frame_id, t.child_frame_id)
                if m.topic == '/tf_static':
                    static.append(edge)
                elif edge == ('odom', 'base_link'):
                    odom_base.append((stamp_to_ns(t.header.stamp), _transform(t)))
                elif edge == ('map', 'odom'):
                    map_odom.append(_transform(t))
    assert static == [('base_link', 'stereo_left')]  # the input's extrinsic, carried
    assert len(odom_base) == r.n_nodes - 1  # every keyframe the VO chain reached
    stamps = [s for s, _ in odom_base]
    assert stamps == sorted(set(stamps))
    newest = last_path.poses[-1]
    assert stamp_to_ns(newest.header.stamp) == stamps[-1]
    np.testing.assert_allclose(map_odom[-1] @ odom_base[-1][1],
                               pose_msg_to_matrix(newest.pose), atol=1e-6)


def test_no_tf_option_writes_none(tmp_path: Path):
    bag = make_stereo_bag(tmp_path / 'in', StereoSampleConfig(n_tracks=1, positions_per_swath=6,
                                                              turn_positions=2))
    r = replay(bag, tmp_path / 'out', ReplayConfig(plot=False, tf=False))
    with BagReader(r.files['bag']) as b:
        assert b.info.topic('/tf') is None and b.info.topic('/tf_static') is None
