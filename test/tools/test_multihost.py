"""Nodes on three network stacks (issue 14): ``ga-ros play`` + ``vo_node`` on host 1,
``alignment_node`` on host 2, the mapping node on host 3, Linux network namespaces joined by a
bridge, Fast DDS over UDP only. Skipped with the reason where namespaces cannot be created
(not root, no iproute2)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from ga_ros.tools import multihost as mh

NS = '{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}'


def test_fastdds_profile_is_udp_only() -> None:
    root = ET.fromstring(mh.fastdds_profile())
    rtps = root.find(f'.//{NS}participant/{NS}rtps')
    assert rtps.find(f'{NS}useBuiltinTransports').text == 'false'  # no shared memory
    assert [t.text for t in root.iter(f'{NS}type')] == ['UDPv4']


def test_discovery_environment() -> None:
    env = mh.discovery_env('peers', ['10.214.14.1', '10.214.14.3'])
    assert env == {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
                   'ROS_STATIC_PEERS': '10.214.14.1;10.214.14.3'}
    assert mh.discovery_env('multicast', ['x'])['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
    with pytest.raises(mh.GaError):
        mh.discovery_env('broadcast', [])


def test_track_latencies_from_recorded_times() -> None:
    mapping = pytest.importorskip('ga_ros.ros.mapping_node')
    # measurements (source ns, destination track); paths arrive at 150 and 420
    src = [0, 10, 100, 110, 300, 400]
    trk = [0, 0, 0, 1, 1, 2]
    lat = mapping.track_latencies(src, trk, [150, 420])
    assert [(x.track_id, round(x.from_trigger_s * 1e9), round(x.from_last_s * 1e9))
            for x in lat] == [(0, 40, 50), (1, 20, 120)]
    assert mapping.track_latencies(src, trk, []) == []


@pytest.fixture(scope='module')
def namespaces_ok() -> None:
    reason = mh.unavailable_reason()
    if reason:
        pytest.skip(f'multi-host test needs network namespaces: {reason}')


@pytest.mark.multihost
@pytest.mark.ros
@pytest.mark.slow
def test_three_hosts_path_equals_the_replay(tmp_path: Path, namespaces_ok) -> None:
    """Multicast discovery; the path on host 3 equals ``ga-ros replay`` of the measurements
    host 3 received, bit for bit up to the text formats; traffic crossed the bridge."""
    from ga_ros.tools.fleet import make_second_bag

    # a short generated stereo survey (~40 poses): the bundled sample only makes it slower
    bag = make_second_bag(tmp_path / 'bag', 0.0, positions_per_swath=10, seed=4)
    res = mh.run_demo(tmp_path / 'run', 'multicast', rate=10.0, bag=bag, stereo_replay=False,
                      timeout_s=300)
    print(mh.format_result(res))
    assert res.ok, res.errors
    assert res.measurements_received > 100
    assert res.path_poses == res.replay_poses > 30
    assert res.max_diff_vs_replay_m <= 1e-6
    assert len(res.latency_from_trigger_s) >= 1
    assert np.isfinite(res.latency_from_trigger_s).all()
    # every host exchanged data over its eth0 (no shared-memory shortcut): host 3 got at
    # least the measurements (~600 B each) and paths
    for h in mh.HOSTS:
        assert res.counters[h]['rx_bytes'] > 100_000, res.counters


@pytest.mark.multihost
@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.skipif(os.environ.get('GA_ROS_MULTIHOST_PEERS') != '1',
                    reason='a second ~60 s run; set GA_ROS_MULTIHOST_PEERS=1 to run it')
def test_three_hosts_with_a_peers_list_and_no_multicast(tmp_path: Path, namespaces_ok) -> None:
    """Unicast discovery from ROS_STATIC_PEERS; the switch drops every multicast frame."""
    res = mh.run_demo(tmp_path, 'peers', rate=5.0, stereo_replay=False, timeout_s=300)
    print(mh.format_result(res))
    assert res.ok, res.errors
    assert res.max_diff_vs_replay_m <= 1e-6
    for h in mh.HOSTS:
        assert res.counters[h]['rx_bytes'] > 100_000, res.counters


@pytest.mark.multihost
@pytest.mark.ros
@pytest.mark.slow
def test_three_hosts_with_loss_and_delay(tmp_path: Path, namespaces_ok) -> None:
    """5 % loss and 20 ms delay on every link: the reliable measurements all arrive."""
    reason = mh.netem_unavailable_reason()
    if reason:
        pytest.skip(f'tc netem unavailable: {reason}')
    res = mh.run_demo(tmp_path, 'multicast', impair=True, rate=5.0, stereo_replay=False,
                      timeout_s=300)
    print(mh.format_result(res))
    assert res.ok, res.errors
    assert res.netem.startswith('on')
    assert res.max_diff_vs_replay_m <= 1e-6


@pytest.mark.ros
@pytest.mark.slow
def test_mapping_node_on_one_host(tmp_path: Path) -> None:
    """No namespaces: the mapping node beside an alignment node on loopback records what it
    received, ends the survey after the idle time, and its path equals TrackWindowAligner fed
    the same measurements in-process and finished."""
    harness = pytest.importorskip('ga_ros.ros.harness')
    from ga_ros.core.window import AlignerConfig, TrackWindowAligner
    from ga_ros.replay.samples import aerial_sample

    domain = 40 + (os.getpid() + 77) % 150
    ms = aerial_sample(n_tracks=2, positions_per_swath=10, seed=3).measurements
    want = TrackWindowAligner(AlignerConfig())
    for m in ms:
        want.add_measurement(m)
    want.finish_track()
    env = {**os.environ, 'ROS_DOMAIN_ID': str(domain), 'PYTHONUNBUFFERED': '1'}
    node = harness.start_node_process(domain, {'autosave': False, 'allow_finish_track': True},
                                      log_path=tmp_path / 'node.log')
    armed = tmp_path / 'player_done'
    mapper = subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.mapping_node', '--out',
                               str(tmp_path / 'out'), '--finish-after-idle', '3',
                               '--finish-armed-by', str(armed), '--timeout', '60'], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        with harness.NodeClient(domain) as client:
            client.wait_for_node(timeout=30, proc=node)
            client.spin_until(lambda: client.pub.get_subscription_count() >= 2, 30,
                              'the mapping node to subscribe', mapper)
            client.publish(ms)
            time.sleep(5.0)  # longer than the idle time: not armed yet, so still running
            assert mapper.poll() is None, mapper.communicate(timeout=10)[0]
            armed.touch()
            client.spin_until(lambda: mapper.poll() is not None, 60, 'the mapping node')
    finally:
        if mapper.poll() is None:
            mapper.kill()
        harness.stop_process(node)
    out = mapper.communicate(timeout=10)[0]
    assert mapper.returncode == 0, out
    got = np.load(tmp_path / 'out' / 'path.npz')
    cp = want.corrected_path()
    np.testing.assert_array_equal(got['stamps_ns'], cp.stamps_ns)
    np.testing.assert_allclose(got['T_world_node'], cp.T_world_node, atol=1e-9)
    summary = json.loads((tmp_path / 'out' / 'mapping.json').read_text())
    assert summary['measurements'] == len(ms) and summary['status'] == 'finished'
    assert [x['track_id'] for x in summary['track_latencies']] == [0]
    assert (tmp_path / 'out' / 'measurements').is_dir()
