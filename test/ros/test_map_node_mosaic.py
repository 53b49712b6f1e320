"""``map_node``'s live mosaic in-process: keyframe images (as ``vo_node`` publishes them) and
corrections (the alignment node's own bytes) in; ``ga/mosaic`` (Image) and ``ga/mosaic_info``
(MapMetaData) out, read as RViz and Foxglove read them, equal pixel for pixel to a mosaic built
independently (ga_ros.mapping.mosaic.build_mosaic) from the poses of the moment, re-warping
only the keyframes a correction moved (and, on the keyframe clouds' height model, those whose
ground it changed); bad messages dropped; /diagnostics; ``~/save_map`` writes mosaic.png +
.json + .pgw."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import MapMetaData  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from ga_ros.mapping.mosaic import (  # noqa: E402
    CameraView,
    Georeference,
    MosaicConfig,
    build_mosaic,
)
from ga_ros.mapping.pointcloud2 import decode_pointcloud2  # noqa: E402
from ga_ros.mapping.surface import ground_from_keyframe_points  # noqa: E402
from ga_ros.pipeline import corrections as corr  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import domain_id  # noqa: E402
from ga_ros.ros.map_node import MapNode, corrections_from_msg  # noqa: E402
from ga_ros.ros.qos import latched_qos, stream_qos  # noqa: E402
from ga_ros.ros.vo_node import array_to_image  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'pipeline'))
from test_mosaic_map import (  # noqa: E402
    GROUND_Z,
    MPP,
    T_BASE_CAM,
    drifted,
    flat_scene,
    scratch,
    survey,
)

#: test_mosaic_map.T_BASE_CAM as the node's parameter (x y z roll pitch yaw)
T_BASE_CAM_TEXT = '0.2 0 -0.5 0 0 0'


def read_image_as_viewers_do(msg: Image) -> np.ndarray:
    """Foxglove's / RViz's reading of a mono8 Image: ``height`` rows ``step`` bytes apart."""
    assert msg.encoding == 'mono8' and msg.is_bigendian == 0
    data = np.frombuffer(bytes(msg.data), np.uint8)
    assert data.size == msg.step * msg.height and msg.step >= msg.width
    return data.reshape(msg.height, msg.step)[:, :msg.width]


def georef_of(info: MapMetaData) -> Georeference:
    """The mosaic's grid from MapMetaData as an OccupancyGrid reader takes it: ``origin`` the
    south-west corner, ``resolution`` m per cell, no rotation."""
    q = info.origin.orientation
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    return Georeference(info.origin.position.x,
                        info.origin.position.y + info.height * info.resolution,
                        info.resolution, info.width, info.height)


def ground_cloud(T_map_base: np.ndarray) -> np.ndarray:
    """The flat ground (z = GROUND_Z) under a keyframe, (k, 3) float32 in its camera frame."""
    T = T_map_base @ T_BASE_CAM
    g = np.arange(-70.0, 70.0, 1.0)
    xx, yy = np.meshgrid(T[0, 3] + g, T[1, 3] + g)
    pts = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, GROUND_Z)], axis=1)
    return ((pts - T[:3, 3]) @ T[:3, :3]).astype(np.float32)


@pytest.mark.ros
@pytest.mark.parametrize('ground', ['plane', 'clouds'])
def test_map_node_mosaic_follows_the_corrections(tmp_path: Path, ground: str) -> None:
    scene = flat_scene()
    K = scene.rig.K
    stamps, images, T_true = survey(scene)
    on_clouds = ground == 'clouds'
    clouds = []
    for s, T in zip(stamps, T_true):
        pts = ground_cloud(T)
        clouds.append(conv.cloud_to_pointcloud2(pts, np.full(len(pts), 100, np.float32),
                                                'cam_optical', int(s)))
    #: the clouds as the node decodes them (camera frame, float32)
    clouds_cam = [decode_pointcloud2(c).points for c in clouds]
    T_f2f = drifted(T_true)
    n = len(stamps)
    tracker = corr.CorrectionTracker(corr.CorrectionThresholds(0.0, 0.0))
    held = corr.HeldPoses()

    class P:  # a corrected path as CorrectionTracker reads it
        def __init__(self, T):
            self.node_ids = np.arange(n)
            self.track_ids = np.repeat(np.arange(3), 8)
            self.stamps_ns = stamps
            self.T_world_node = T

    map_file = tmp_path / 'out' / 'map.ply'
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id((43, ground)))
    node = MapNode(context=ctx, parameter_overrides=[
        Parameter('warn_throttle_sec', value=0.0), Parameter('publish_period_sec', value=0.05),
        Parameter('diagnostics_period_sec', value=0.1),
        Parameter('T_base_camera', value=T_BASE_CAM_TEXT),
        Parameter('mosaic_metres_per_pixel', value=MPP),
        Parameter('mosaic_ground_from_clouds', value=on_clouds),
        Parameter('mosaic_ground_z', value=GROUND_Z), Parameter('mosaic_tile_px', value=64),
        Parameter('map_file', value=str(map_file))])
    peer = Node('mosaic_test_peer', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    executor.add_node(peer)
    mosaics: list[Image] = []
    infos: list[MapMetaData] = []
    diags: list[DiagnosticArray] = []
    pub_img = peer.create_publisher(Image, '/ga/keyframe_image', stream_qos(50))
    pub_info = peer.create_publisher(CameraInfo, '/ga/keyframe_camera_info', stream_qos(50))
    pub_corr = peer.create_publisher(PathMsg, '/ga/corrections', stream_qos(100))
    pub_cloud = peer.create_publisher(PointCloud2, '/ga/keyframe_cloud', stream_qos(50))
    peer.create_subscription(Image, '/ga/mosaic', mosaics.append, latched_qos(1))
    peer.create_subscription(MapMetaData, '/ga/mosaic_info', infos.append, latched_qos(1))
    peer.create_subscription(DiagnosticArray, '/diagnostics', diags.append, stream_qos())
    client = peer.create_client(Trigger, '/map_node/save_map')

    def spin_until(cond, what: str, seconds: float = 60) -> None:
        deadline = time.monotonic() + patience(seconds)
        while not cond():
            assert time.monotonic() < deadline, what
            executor.spin_once(timeout_sec=0.05)

    #: the poses as sent (after the message's quaternion round trip), by keyframe index
    T_sent = np.full_like(T_true, np.nan)

    def send_corrections(T_now: np.ndarray) -> None:
        c = tracker.compare(P(T_now))
        assert c is not None
        msg = deserialize_message(corr.corrections_cdr(c, 'map', int(stamps[-1])), PathMsg)
        sent_stamps, T_msg = held.apply(corrections_from_msg(msg))   # what the node holds
        T_sent[np.searchsorted(stamps, sent_stamps)] = T_msg
        pub_corr.publish(msg)

    def info_msg(s: int, K_: np.ndarray) -> CameraInfo:
        msg = CameraInfo()
        msg.header.stamp, msg.header.frame_id = conv.ns_to_stamp(s), 'cam_optical'
        msg.height, msg.width = images[0].shape
        msg.k = np.asarray(K_, float).reshape(-1).tolist()
        return msg

    def send_keyframe(k: int) -> None:
        s = int(stamps[k])
        taken = node.mosaic.counts.images
        if on_clouds:
            got = node.mosaic.counts.clouds
            pub_cloud.publish(clouds[k])
            spin_until(lambda: node.mosaic.counts.clouds == got + 1, f'keyframe cloud {k}')
        pub_info.publish(info_msg(s, K))
        pub_img.publish(array_to_image(images[k], s, 'cam_optical'))
        spin_until(lambda: node.mosaic.counts.images == taken + 1, f'keyframe image {k}')

    def mosaic_equals() -> bool:
        if not mosaics or not infos or mosaics[-1].header.stamp != infos[-1].map_load_time:
            return False
        got, georef = read_image_as_viewers_do(mosaics[-1]), georef_of(infos[-1])
        if on_clouds:  # build_mosaic on the height grid of the same clouds at the same poses
            T_cam = T_sent @ T_BASE_CAM
            ref = build_mosaic([CameraView(img, T, K) for img, T in zip(images, T_cam)],
                               ground_from_keyframe_points(clouds_cam, T_cam),
                               MosaicConfig(MPP, 'last'), georef)
        else:
            ref = scratch(images, T_sent, K, georef)
        # the grid read back from MapMetaData (origin + height * resolution) is the node's to
        # float round-off, so the warp may round a grey level the other way or cover a border
        # pixel differently: equal to 1 grey level, coverage to 0.1 % of the pixels
        diff = np.abs(got.astype(int) - ref.image.astype(int))
        return bool(got.shape == ref.image.shape and (diff > 1).mean() < 1e-3
                    and (diff == 0).mean() > 0.99)

    try:
        spin_until(lambda: pub_img.get_subscription_count() and pub_corr.get_subscription_count()
                   and pub_info.get_subscription_count()
                   and node.pub_mosaic.get_subscription_count(), 'discovery')
        for k in range(n // 2):            # images before their poses
            send_keyframe(k)
        send_corrections(T_f2f)            # full message: every keyframe
        spin_until(lambda: node.builder.counts.corrections == 1, 'the first corrections')
        for k in range(n // 2, n):         # images after their poses
            send_keyframe(k)
        spin_until(lambda: node.mosaic.n_placed == n, 'every keyframe in the mosaic')
        spin_until(mosaic_equals, 'the mosaic of the drifted poses')
        assert mosaics[-1].header.frame_id == 'map'
        assert infos[-1].resolution == pytest.approx(MPP)
        # bad input: an unknown encoding, a short image, an invalid CameraInfo: dropped
        bad = array_to_image(images[0], int(stamps[0]), 'cam_optical')
        bad.encoding = '32FC1'
        pub_img.publish(bad)
        short = array_to_image(images[0], int(stamps[0]), 'cam_optical')
        short.data = bytes(short.data)[:100]
        pub_img.publish(short)
        pub_info.publish(info_msg(int(stamps[0]), np.zeros((3, 3))))
        spin_until(lambda: node.counts['bad_images'] == 3, 'the bad messages counted')
        # the alignment's corrections, track by track: only the keyframes moved are re-warped
        T_now = T_f2f.copy()
        for track in range(3):
            T_before = T_now.copy()
            T_now[:8 * (track + 1)] = T_true[:8 * (track + 1)]
            moved = int(np.any(np.abs(T_now - T_before) > 1e-12, axis=(1, 2)).sum())
            assert moved >= 7  # the first keyframe has no drift
            warps, by_ground = node.mosaic.counts.warps, node.mosaic.counts.ground_rewarps
            send_corrections(T_now)
            spin_until(lambda: node.builder.counts.corrections == track + 2, 'corrections')
            by_ground = node.mosaic.counts.ground_rewarps - by_ground
            assert node.mosaic.counts.warps - warps == moved + by_ground
            assert by_ground <= n - moved
            assert np.allclose(T_sent, T_now, atol=1e-9)
            spin_until(mosaic_equals, f'the mosaic after track {track}')
        spin_until(lambda: any('mosaic_warps' in conv.diagnostics_to_dict(d) for d in diags),
                   '/diagnostics with the mosaic')
        last = conv.diagnostics_to_dict(diags[-1])
        assert int(last['mosaic_live_keyframes']) == n and int(last['bad_images']) == 3
        assert int(last['mosaic_merged_settled']) == int(last['mosaic_merged_forced']) == 0
        assert int(last['static_settled']) == int(last['static_forced']) == 0
        # ~/save_map writes the mosaic beside the map
        spin_until(client.service_is_ready, 'save_map service')
        future = client.call_async(Trigger.Request())
        spin_until(future.done, 'save_map answer')
        assert future.result().success, future.result().message
        png = cv2.imread(str(map_file.with_name('mosaic.png')), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(png[..., 0], read_image_as_viewers_do(mosaics[-1]))
        meta = json.loads(map_file.with_name('mosaic.json').read_text())
        g = georef_of(infos[-1])
        assert (meta['x_min'], meta['y_max']) == pytest.approx((g.x_min, g.y_max))
        assert map_file.with_name('mosaic.pgw').exists()
    finally:
        executor.shutdown()
        peer.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
