"""The issue's "done when" without a screen: ``ga-ros play`` of ``bags/stereo_sample`` into
``vo_node``, ``alignment_node`` and ``map_node`` (separate processes, with ``config/*.yaml`` as
``ros2 launch ga_ros play_bag.launch.py map:=true`` starts them; a mapping node ends the last
track). After the last track, ``map_node``'s mosaic (``~/save_map``: what ``ga/mosaic`` shows)
is seen from above although the live ``map`` has ``z`` down (the sample's ``base_link`` is the
camera), and the seams of the live final poses match those of the offline mosaic
(``ga-ros replay --mosaic``) within 0.1 px of median and below the issue's 1 px."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from ga_ros.io.bag import BagReader  # noqa: E402
from ga_ros.io.trajectory import Trajectory  # noqa: E402
from ga_ros.mapping.replay_mosaic import read_keyframe_images, write_mosaics  # noqa: E402
from ga_ros.replay.config import ReplayConfig  # noqa: E402
from ga_ros.replay.pipeline import replay  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import domain_id, start_node_process, stop_process  # noqa: E402
from ga_ros.ros.qos import stream_qos  # noqa: E402
from ga_ros.vo.calibration import StereoCalibration  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / 'bags' / 'stereo_sample'
CONFIG = REPO / 'config'
LEFT, RIGHT = '/stereo/left/image_raw/compressed', '/stereo/right/image_raw/compressed'

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def wait_for(cond, what: str, seconds: float, procs: dict, spin=None) -> None:
    """Wait (``spin`` or a short pause between checks) until ``cond()``; fail naming ``what``
    at the deadline or when a node process died."""
    deadline = time.monotonic() + patience(seconds)
    while not cond():
        for name, p in procs.items():
            if name in ('map', 'alignment', 'vo') and p.poll() is not None:
                pytest.fail(f'{name} exited ({p.returncode}) while waiting for {what}')
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        if spin is not None:
            spin()
        else:
            time.sleep(0.2)


def calibration_of(bag: BagReader) -> StereoCalibration:
    """The rectified stereo calibration from the bag's first CameraInfo of each side."""
    from ga_ros.vo.messages import camera_info_to_model

    models = {}
    for side in ('left', 'right'):
        for bm in bag.messages([f'/stereo/{side}/camera_info']):
            models[side] = camera_info_to_model(bm.msg)
            break
    return StereoCalibration.from_camera_models(models['left'], models['right'])


def test_stereo_sample_played_into_the_nodes_gives_the_offline_mosaic_seams(
        tmp_path: Path) -> None:
    res = replay(BAG, tmp_path / 'offline', ReplayConfig(mosaic=True))
    offline = res.mosaic['ga']['seams']
    ga: Trajectory = res.corrected
    track_of = dict(zip(np.asarray(ga.stamps_ns).tolist(), np.asarray(ga.track_ids).tolist()))

    dom = domain_id('live-mosaic-sample')
    live = tmp_path / 'live'
    procs: dict[str, subprocess.Popen] = {}
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=dom)
    peer = Node('live_mosaic_sample_peer', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(peer)
    corrections: list[PathMsg] = []
    map_diag: dict[str, str] = {}

    def on_diag(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.endswith('map_node: map'):
                map_diag.update(conv.diagnostics_to_dict(msg))

    peer.create_subscription(PathMsg, '/ga/corrections', corrections.append, stream_qos(100))
    peer.create_subscription(DiagnosticArray, '/diagnostics', on_diag, stream_qos())
    spin = lambda: executor.spin_once(timeout_sec=0.1)  # noqa: E731
    try:
        procs['map'] = start_node_process(
            dom, {'use_sim_time': True, 'map_file': str(live / 'map.ply'),
                  'mosaic_file': str(live / 'mosaic.png')},
            params_file=CONFIG / 'map.yaml', log_path=tmp_path / 'map.log',
            module='ga_ros.ros.map_node')
        procs['alignment'] = start_node_process(
            dom, {'use_sim_time': True, 'autosave': False,
                  'measurement_durability': 'transient_local', 'allow_finish_track': True},
            params_file=CONFIG / 'alignment.yaml', log_path=tmp_path / 'alignment.log')
        procs['vo'] = start_node_process(
            dom, {'use_sim_time': True, 'compressed': True, 'image_queue': 200,
                  'pair_queue': 1000, 'left_image_topic': LEFT, 'right_image_topic': RIGHT},
            params_file=CONFIG / 'vo.yaml', log_path=tmp_path / 'vo.log',
            module='ga_ros.ros.vo_node')
        env = {**__import__('os').environ, 'ROS_DOMAIN_ID': str(dom), 'PYTHONUNBUFFERED': '1'}
        mapping_log = tmp_path / 'mapping.log'
        armed = tmp_path / 'player_done'
        with open(mapping_log, 'w') as log:
            procs['mapping'] = subprocess.Popen(
                [sys.executable, '-m', 'ga_ros.ros.mapping_node', '--out',
                 str(tmp_path / 'mapping'), '--finish-after-idle', '10', '--finish-armed-by',
                 str(armed), '--timeout', str(patience(900))],
                env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        wait_for(lambda: 'mapping_node: ready' in mapping_log.read_text(), 'the mapping node',
                 120, procs, spin)
        with open(tmp_path / 'play.log', 'w') as log:
            procs['play'] = subprocess.Popen(
                [sys.executable, '-m', 'ga_ros.ros.play', str(BAG), '--wait-for-subscribers',
                 '60'], env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        wait_for(lambda: procs['play'].poll() is not None, 'the bag played', 900, procs, spin)
        assert procs['play'].returncode == 0, (tmp_path / 'play.log').read_text()
        armed.touch()
        wait_for(lambda: procs['mapping'].poll() is not None, 'the last track', 900, procs,
                 spin)
        # map_node has taken every corrections message, the last track's included
        n = len(corrections)
        assert n >= 3
        wait_for(lambda: int(float(map_diag.get('corrections', -1))) >= n
                 and int(float(map_diag.get('mosaic_live_keyframes', 0))) > 0,
                 'map_node to take the last corrections', 120, procs, spin)
        client = peer.create_client(Trigger, '/map_node/save_map')
        wait_for(client.service_is_ready, 'save_map', 60, procs, spin)
        future = client.call_async(Trigger.Request())
        wait_for(future.done, 'save_map answer', 120, procs, spin)
        assert future.result().success, future.result().message
    except Exception:
        for name in ('map', 'alignment', 'vo', 'mapping', 'play'):
            f = tmp_path / f'{name}.log'
            print(f'--- {name}\n' + (f.read_text()[-4000:] if f.exists() else '(no log)'))
        raise
    finally:
        for p in procs.values():
            stop_process(p)
        executor.shutdown()
        peer.destroy_node()
        rclpy.try_shutdown(context=ctx)

    # the live mosaic: the ground seen from above in a map whose z points down
    meta = json.loads((live / 'mosaic.json').read_text())
    assert meta['z_up'] is False and (live / 'mosaic.png').exists()
    # the seams of the live final poses, measured as the offline mosaic's
    got = np.load(tmp_path / 'mapping' / 'path.npz')
    stamps = np.asarray(got['stamps_ns'], np.int64)
    known = np.array([int(s) in track_of for s in stamps])
    assert known.mean() > 0.9  # the same keyframes as offline
    traj = Trajectory(stamps[known], np.asarray(got['T_world_node'])[known],
                      track_ids=np.array([track_of[int(s)] for s in stamps[known]]))
    with BagReader(BAG) as bag:
        images = read_keyframe_images(bag, LEFT, RIGHT, calibration_of(bag), traj.stamps_ns)
    live_seams = write_mosaics(tmp_path / 'live_seams', images, {'live': traj})['live']['seams']
    print(f"seams, median / p95 px: live {live_seams['median_px']:.3f} / "
          f"{live_seams['p95_px']:.3f}, offline {offline['median_px']:.3f} / "
          f"{offline['p95_px']:.3f} ({live_seams['measured']} pairs)")
    assert live_seams['measured'] >= 0.8 * offline['measured']
    assert live_seams['median_px'] <= offline['median_px'] + 0.1
    assert live_seams['p95_px'] < 1.0
