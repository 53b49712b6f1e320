"""Multi-host demo and test (issue 14): the nodes on three network stacks joined by DDS.

Three Linux network namespaces stand for three hosts, each with one interface ``eth0`` on a
private subnet (:data:`SUBNET`) plugged into a bridge that lives in a fourth namespace (the
"switch"). The veth pairs are created directly inside the namespaces: no interface, address or
packet ever appears in the machine's own network stack, and deleting the namespaces at the end
(also after a failure or Ctrl-C) removes everything.

* host 1: ``ga-ros play`` of the stereo sample bag and ``vo_node`` (camera driver + VO);
* host 2: ``alignment_node``;
* host 3: ``python -m ga_ros.ros.mapping_node`` (the consumer of the corrected path), which
  also ends the survey (``finish_track``) once the measurements stop.

Fast DDS runs with UDPv4 only (an XML profile with the built-in transports off: no
shared-memory shortcut between processes of one machine), so every byte between the hosts
crosses the bridge (the interface counters are reported). Discovery is either multicast (SPDP
on 239.255.0.1, the default of DDS) or an explicit peers list (``discovery='peers'``:
``ROS_STATIC_PEERS`` holds the other hosts' addresses, ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is
``LOCALHOST``, and the switch floods no multicast frame to its ports, as on networks that drop
multicast; with multicast discovery the hosts then do not find each other, checked by hand).

After the run, the path received on host 3 is compared with ``ga-ros replay`` of the
measurements host 3 received (same input: must be identical) and with ``ga-ros replay`` of the
stereo bag itself (the VO's cross-track matches depend on when the corrected path reaches it,
so the live measurements can differ slightly from the in-process ones). Where the kernel has
``sch_netem``, ``impair=True`` adds 5 % loss and 20 ms delay on every host's interface; the
reliable measurement QoS must then lose nothing.

This module never imports ROS: it starts processes with ``ip netns exec``.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ga_ros.errors import GaError
from ga_ros.safe_write import check_destinations, open_log, write_json, write_text

REPO = Path(__file__).resolve().parents[2]
STEREO_BAG = REPO / 'bags' / 'stereo_sample'
SUBNET = '10.214.14'  # hosts .1 .2 .3 /24: exists only inside the namespaces
HOSTS = ('h1', 'h2', 'h3')
# the mapping node ends the survey after this many seconds without a message: long enough for
# a loaded 2-core machine (the last update, with the background refinement's hand-off, or a
# stalled replay can stay silent for several seconds)
IDLE_FINISH_S = 10.0

PROFILE_TEMPLATE = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>ga_udp</transport_id>
        <type>UDPv4</type>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="ga_multihost" is_default_profile="true">
      <rtps>
        <userTransports><transport_id>ga_udp</transport_id></userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
    <data_writer profile_name="ga_multihost_writer" is_default_profile="true">
      <times><heartbeatPeriod><sec>0</sec><nanosec>20000000</nanosec></heartbeatPeriod></times>
    </data_writer>
  </profiles>
</dds>
"""
class MultihostUnavailable(GaError):
    """Network namespaces cannot be created here (not root, no iproute2, no CAP_NET_ADMIN)."""


def fastdds_profile() -> str:
    """The Fast DDS XML profile of every host: UDPv4 only (no shared memory between processes
    of one machine, so all traffic between hosts crosses the bridge) and a 20 ms heartbeat."""
    return PROFILE_TEMPLATE


def discovery_env(discovery: str, peers: list[str]) -> dict[str, str]:
    """Environment of a host's ROS processes for a discovery mode.

    ``'multicast'``: DDS's default SPDP multicast on the subnet. ``'peers'``: Jazzy's
    ``ROS_STATIC_PEERS`` (``;``-separated addresses of the other hosts) with
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: unicast discovery of the listed hosts only,
    for networks without multicast.
    """
    if discovery == 'multicast':
        return {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET', 'ROS_STATIC_PEERS': ''}
    if discovery == 'peers':
        return {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST', 'ROS_STATIC_PEERS': ';'.join(peers)}
    raise GaError(f"discovery must be 'multicast' or 'peers', got {discovery!r}")


def unavailable_reason() -> str | None:
    """Why namespaces cannot be used here, or None if they can (checked by creating one)."""
    if shutil.which('ip') is None:
        return ('iproute2 (the `ip` command) is not installed: apt-get install -y iproute2 '
                '(scripts/multihost.sh does it when run as root)')
    if os.geteuid() != 0:
        return 'creating network namespaces needs root (CAP_NET_ADMIN, CAP_SYS_ADMIN)'
    name = f'gaprobe{os.getpid()}'
    res = subprocess.run(['ip', 'netns', 'add', name], capture_output=True, text=True)
    if res.returncode != 0:
        return f'`ip netns add` failed: {res.stderr.strip()}'
    subprocess.run(['ip', 'netns', 'del', name], capture_output=True)
    return None


def netem_unavailable_reason() -> str | None:
    """Why ``tc netem`` cannot impair a link here, or None if it can (probed on a
    veth in a throw-away namespace)."""
    reason = unavailable_reason()
    if reason:
        return reason
    if shutil.which('tc') is None:
        return 'the `tc` command (iproute2) is missing'
    if shutil.which('modprobe'):
        subprocess.run(['modprobe', 'sch_netem'], capture_output=True)
    name = f'ganetem{os.getpid()}'
    _ip('netns', 'add', name)
    try:
        _ip('-n', name, 'link', 'add', 'd0', 'type', 'veth', 'peer', 'name', 'd1')
        res = subprocess.run(['ip', 'netns', 'exec', name, 'tc', 'qdisc', 'add', 'dev', 'd0',
                              'root', 'netem', 'delay', '1ms'], capture_output=True, text=True)
        if res.returncode != 0:
            return (f'`tc qdisc add ... netem` failed ({res.stderr.strip()}): this kernel has no '
                    'sch_netem module')
        return None
    finally:
        _ip('netns', 'del', name, check=False)


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    res = subprocess.run(['ip', *args], capture_output=True, text=True)
    if check and res.returncode != 0:
        raise MultihostUnavailable(f'ip {" ".join(args)}: {res.stderr.strip()}')
    return res


@dataclass
class Network:
    """The namespaces of one run: ``ns[host]``, the switch, and each host's address."""

    prefix: str
    ns: dict[str, str]
    switch: str
    address: dict[str, str]
    netem: str = 'not tried'

    def exec_prefix(self, host: str) -> list[str]:
        return ['ip', 'netns', 'exec', self.ns[host]]

    def counters(self) -> dict[str, dict[str, int]]:
        """Bytes and packets through each host's ``eth0`` (``ip -s -j link``)."""
        out = {}
        for h in HOSTS:
            res = _ip('-n', self.ns[h], '-s', '-j', 'link', 'show', 'eth0', check=False)
            try:
                st = json.loads(res.stdout)[0]['stats64']
                out[h] = {'rx_bytes': st['rx']['bytes'], 'tx_bytes': st['tx']['bytes'],
                          'rx_packets': st['rx']['packets'], 'tx_packets': st['tx']['packets']}
            except (ValueError, KeyError, IndexError):
                out[h] = {}
        return out


@contextmanager
def namespaces(discovery: str = 'multicast', impair: bool = False) -> Iterator[Network]:
    """Create the three hosts and the switch; delete them all on exit, whatever happens."""
    reason = unavailable_reason()
    if reason:
        raise MultihostUnavailable(reason)
    prefix = f'ga{os.getpid()}'
    net = Network(prefix, {h: f'{prefix}{h}' for h in HOSTS}, f'{prefix}sw',
                  {h: f'{SUBNET}.{k + 1}' for k, h in enumerate(HOSTS)})
    created: list[str] = []
    try:
        for name in [net.switch, *net.ns.values()]:
            _ip('netns', 'add', name)
            created.append(name)
            # IPv4 only: no IPv6 link-local addresses, neighbour discovery or MLD chatter
            subprocess.run(['ip', 'netns', 'exec', name, 'sh', '-c',
                            'echo 1 > /proc/sys/net/ipv6/conf/all/disable_ipv6; '
                            'echo 1 > /proc/sys/net/ipv6/conf/default/disable_ipv6'],
                           capture_output=True)
        sw = net.switch
        _ip('-n', sw, 'link', 'add', 'br0', 'type', 'bridge', 'mcast_snooping', '0')
        _ip('-n', sw, 'link', 'set', 'br0', 'up')
        for h in HOSTS:
            ns, port = net.ns[h], f'p{h}'
            # the veth pair is born inside the switch namespace, its peer moved straight into the
            # host's namespace: it never exists in the machine's own stack
            _ip('-n', sw, 'link', 'add', port, 'type', 'veth', 'peer', 'name', 'eth0',
                'netns', ns)
            _ip('-n', sw, 'link', 'set', port, 'master', 'br0', 'up')
            if discovery == 'peers':
                # the switch drops every multicast frame: discovery must work without it
                _ip('-n', sw, 'link', 'set', port, 'type', 'bridge_slave', 'mcast_flood', 'off')
            _ip('-n', ns, 'addr', 'add', f'{net.address[h]}/24', 'dev', 'eth0')
            _ip('-n', ns, 'link', 'set', 'eth0', 'up')
            _ip('-n', ns, 'link', 'set', 'lo', 'up')
            if discovery == 'multicast':
                _ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', 'eth0')
        if impair:
            net.netem = try_netem(net)
        yield net
    finally:
        for name in created:
            _ip('netns', 'del', name, check=False)


def try_netem(net: Network, loss_pct: float = 5.0, delay_ms: float = 20.0) -> str:
    """Add ``loss_pct`` % loss and ``delay_ms`` delay on every host's eth0; returns 'on' or why
    not (this kernel may lack ``sch_netem``)."""
    if shutil.which('tc') is None:
        return 'unavailable: the `tc` command (iproute2) is missing'
    if shutil.which('modprobe'):
        subprocess.run(['modprobe', 'sch_netem'], capture_output=True)
    for h in HOSTS:
        res = subprocess.run(['ip', 'netns', 'exec', net.ns[h], 'tc', 'qdisc', 'add', 'dev',
                              'eth0', 'root', 'netem', 'loss', f'{loss_pct}%', 'delay',
                              f'{delay_ms}ms'], capture_output=True, text=True)
        if res.returncode != 0:
            return (f'unavailable: `tc qdisc add ... netem` failed ({res.stderr.strip()}); the '
                    'kernel has no sch_netem module')
    return f'on: {loss_pct:g} % loss, {delay_ms:g} ms delay on every host'


@dataclass
class MultihostResult:
    """Figures of one run (``summary.json``)."""

    discovery: str
    netem: str
    ok: bool = False
    errors: list[str] = field(default_factory=list)
    seconds: float = 0.0
    measurements_received: int = 0
    measurements_by_alignment: int | None = None
    path_poses: int = 0
    paths_received: int = 0
    max_diff_vs_replay_m: float | None = None
    max_rot_diff_vs_replay_rad: float | None = None
    replay_poses: int | None = None
    stereo_replay_poses: int | None = None
    stereo_replay_measurements: int | None = None
    max_diff_vs_stereo_replay_m: float | None = None
    latency_from_trigger_s: list[float] = field(default_factory=list)
    latency_from_last_s: list[float] = field(default_factory=list)
    latency_median_s: float | None = None
    finish_latency_s: float | None = None
    counters: dict = field(default_factory=dict)
    out_dir: str = ''


def _python() -> str:
    return sys.executable


def _spawn(net: Network, host: str, argv: list[str], env: dict[str, str],
           log: Path) -> subprocess.Popen:
    out = open_log(log)  # closed with the process by the caller
    return subprocess.Popen([*net.exec_prefix(host), 'env', *[f'{k}={v}' for k, v in env.items()],
                             *argv], stdout=out, stderr=subprocess.STDOUT,
                            start_new_session=True)


def _stop_all(procs: list[subprocess.Popen], timeout: float = 8.0) -> None:
    """SIGINT to every still running process group, then SIGKILL after ``timeout`` s."""
    alive = [p for p in procs if p.poll() is None]
    for p in alive:
        try:
            os.killpg(p.pid, signal.SIGINT)
        except ProcessLookupError:
            pass
    end = time.monotonic() + timeout
    for p in alive:
        try:
            p.wait(timeout=max(0.1, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(timeout=timeout)


def _wait_line(log: Path, text: str, proc: subprocess.Popen, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if log.exists() and text in log.read_text(errors='replace'):
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.1)
    return False


def _replay(bag: Path, out: Path, *extra: str) -> Path:
    """``ga-ros replay BAG --no-anchor`` (the node's datum is the identity); its GA TUM file."""
    cmd = [_python(), '-m', 'ga_ros.cli.main', 'replay', str(bag), '--out', str(out),
           '--no-anchor', '--no-plot', '--no-progress', '--no-covariance', *extra]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if res.returncode != 0:
        raise GaError(f'ga-ros replay {bag} failed: {res.stderr.strip()[-500:]}')
    return out / 'trajectory_ga.tum'


def compare_paths(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Largest position (m) and rotation (rad) difference between two (n, 4, 4) pose arrays."""
    from ga_ros.geometry import so3

    dp = float(np.abs(T_a[:, :3, 3] - T_b[:, :3, 3]).max()) if len(T_a) else 0.0
    R = np.swapaxes(T_a[:, :3, :3], 1, 2) @ T_b[:, :3, :3]
    dr = float(np.linalg.norm(so3.log(R), axis=1).max()) if len(T_a) else 0.0
    return dp, dr


def run_demo(out_dir: str | Path, discovery: str = 'multicast', impair: bool = False,
             rate: float = 5.0, bag: Path = STEREO_BAG, stereo_replay: bool = True,
             timeout_s: float = 180.0, log=print) -> MultihostResult:
    """Run the three-host pipeline once and compare its output; see the module docstring.

    Parameters
    ----------
    out_dir : logs, the mapping node's outputs, replays and ``summary.json``.
    discovery : ``'multicast'`` or ``'peers'`` (``ROS_STATIC_PEERS``; the switch drops multicast).
    impair : also try ``tc netem`` 5 % loss + 20 ms delay (reported in ``netem``).
    rate : ``ga-ros play --rate`` (the stereo sample has 2 pairs/s of bag time).
    stereo_replay : also replay the stereo bag in-process and compare (adds ~10-20 s).
    timeout_s : longest wait for the survey to go through.
    """
    from ga_ros.io.trajectory import read_tum

    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    check_destinations(out / 'summary.json', out / 'fastdds_udp.xml')
    res = MultihostResult(discovery, 'not requested', out_dir=str(out))
    t0 = time.monotonic()
    procs: dict[str, subprocess.Popen] = {}
    with namespaces(discovery, impair) as net:
        res.netem = net.netem if impair else 'not requested'
        log('hosts: ' + ', '.join(f'{h} {net.ns[h]} {net.address[h]}' for h in HOSTS)
            + f'; switch {net.switch}; discovery {discovery}; netem {res.netem}')
        prof = out / 'fastdds_udp.xml'
        write_text(prof, fastdds_profile())
        envs = _host_envs(net, discovery, prof)
        try:
            _start_nodes(net, envs, out, timeout_s, procs)
            _run_survey(net, envs, out, bag, rate, timeout_s, procs, res, t0, log)
        finally:
            _stop_all(list(procs.values()))
    res.seconds = time.monotonic() - t0
    _collect(res, out, read_tum, stereo_replay, bag, log)
    res.ok = not res.errors
    write_json(out / 'summary.json', asdict(res), indent=1)
    return res


def _host_envs(net: Network, discovery: str, profile: Path) -> dict[str, dict[str, str]]:
    """Each host's environment: one ROS domain, Fast DDS over UDP only (``profile``), and the
    discovery settings that reach the other hosts."""
    env_base = {'ROS_DOMAIN_ID': str(17 + os.getpid() % 80), 'PYTHONUNBUFFERED': '1',
                'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp',
                'FASTDDS_DEFAULT_PROFILES_FILE': str(profile)}
    return {h: {**env_base, **discovery_env(discovery, [net.address[o] for o in HOSTS
                                                        if o != h])} for h in HOSTS}


def _start_nodes(net: Network, envs: dict[str, dict[str, str]], out: Path, timeout_s: float,
                 procs: dict[str, subprocess.Popen]) -> None:
    """Start the mapping node on host 3, the alignment node on host 2 and the VO node on host
    1, each logging to ``out/<name>.log``; into ``procs`` as they start (stopped by the
    caller)."""
    py = _python()
    procs['mapping'] = _spawn(net, 'h3', [
        py, '-m', 'ga_ros.ros.mapping_node', '--out', str(out / 'mapping'),
        '--finish-after-idle', str(IDLE_FINISH_S), '--finish-armed-by',
        str(out / 'player_done'), '--timeout', str(timeout_s)],
        envs['h3'],
        out / 'mapping.log')
    procs['alignment'] = _spawn(net, 'h2', [
        py, '-m', 'ga_ros.ros.alignment_node', '--ros-args', '--params-file',
        str(REPO / 'config' / 'alignment.yaml'), '-p', 'use_sim_time:=true',
        '-p', 'autosave:=false', '-p', 'measurement_durability:=transient_local',
        '-p', 'allow_finish_track:=true'],
        envs['h2'], out / 'alignment.log')
    procs['vo'] = _spawn(net, 'h1', [
        py, '-m', 'ga_ros.ros.vo_node', '--ros-args', '--params-file',
        str(REPO / 'config' / 'vo.yaml'), '-p', 'use_sim_time:=true',
        '-p', 'compressed:=true', '-p', 'image_queue:=200', '-p', 'pair_queue:=1000',
        '-p', 'left_image_topic:=/stereo/left/image_raw/compressed',
        '-p', 'right_image_topic:=/stereo/right/image_raw/compressed'], envs['h1'],
        out / 'vo.log')


def _run_survey(net: Network, envs: dict[str, dict[str, str]], out: Path, bag: Path,
                rate: float, timeout_s: float, procs: dict[str, subprocess.Popen],
                res: MultihostResult, t0: float, log) -> None:
    """Once host 3 has discovered the others, play ``bag`` on host 1 and wait (at most
    ``timeout_s``) for the mapping node to finish; the interface counters into ``res``."""
    # host 3 has discovered the VO's measurement publisher and the alignment's path
    # publisher across the bridge: the graph is connected
    if not _wait_line(out / 'mapping.log', 'mapping_node: ready', procs['mapping'], 60.0):
        raise GaError('the mapping node did not discover the other hosts within 60 s '
                      f'(see {out / "mapping.log"})')
    log(f'discovery across the bridge after {time.monotonic() - t0:.1f} s')
    time.sleep(1.0)
    procs['play'] = _spawn(net, 'h1', [
        _python(), '-m', 'ga_ros.ros.play', str(bag), '--rate', str(rate),
        '--wait-for-subscribers', '30'], envs['h1'], out / 'play.log')
    end = time.monotonic() + timeout_s
    while procs['mapping'].poll() is None and time.monotonic() < end:
        if procs['play'].poll() is not None:
            (out / 'player_done').touch()  # arms the mapping node's idle finish
        time.sleep(0.2)
    log(f'survey through after {time.monotonic() - t0:.1f} s')
    if procs['mapping'].poll() is None:
        res.errors.append(f'the mapping node did not finish within {timeout_s:.0f} s')
    res.counters = net.counters()


def _collect(res: MultihostResult, out: Path, read_tum, stereo_replay: bool, bag: Path,
             log) -> None:
    summary_path = out / 'mapping' / 'mapping.json'
    if not summary_path.exists():
        res.errors.append('the mapping node wrote no outputs')
        return
    summ = json.loads(summary_path.read_text())
    res.measurements_received = summ['measurements']
    res.paths_received = summ['paths']
    res.path_poses = summ['last_path_poses']
    lat = summ['track_latencies']
    res.latency_from_trigger_s = [x['from_trigger_s'] for x in lat]
    res.latency_from_last_s = [x['from_last_s'] for x in lat]
    if lat:
        res.latency_median_s = float(np.median(res.latency_from_trigger_s))
    if summ['finish_called_ns'] and summ['path_receive_ns']:
        res.finish_latency_s = (summ['path_receive_ns'][-1] - summ['finish_called_ns']) * 1e-9
    if summ['status'] != 'finished':
        res.errors.append(f'mapping node status {summ["status"]!r}')
    if not (out / 'mapping' / 'path.npz').exists() or not res.measurements_received:
        res.errors.append('no path or no measurements reached host 3')
        return
    got = np.load(out / 'mapping' / 'path.npz')
    T_live, stamps_live = got['T_world_node'], got['stamps_ns']
    # reference 1: the same measurements, replayed in-process
    ref = read_tum(_replay(out / 'mapping' / 'measurements', out / 'replay_measurements'))
    res.replay_poses = len(ref.T_world_cam)
    # node 0 has no stamp of its own in the measurement encoding: the replay estimates it (from
    # ground truth or one median interval before node 1), the live path carries node 1's
    if res.replay_poses != len(T_live) or not np.array_equal(ref.stamps_ns[1:], stamps_live[1:]):
        res.errors.append(f'host 3 path has {len(T_live)} poses, the replay of the same '
                          f'measurements {res.replay_poses} (or other stamps)')
    else:
        res.max_diff_vs_replay_m, res.max_rot_diff_vs_replay_rad = compare_paths(
            T_live, ref.T_world_cam)
        if res.max_diff_vs_replay_m > 1e-6 or res.max_rot_diff_vs_replay_rad > 1e-8:
            res.errors.append(f'host 3 path differs from the replay of the same measurements '
                              f'by {res.max_diff_vs_replay_m:.3g} m')
    log(f'host 3: {res.measurements_received} measurements, {res.paths_received} paths, last '
        f'{res.path_poses} poses; vs replay of the same measurements: max '
        f'{res.max_diff_vs_replay_m} m')
    # reference 2: the stereo bag itself, replayed in-process (VO included)
    if stereo_replay:
        sref = read_tum(_replay(bag, out / 'replay_stereo'))
        info = json.loads((out / 'replay_stereo' / 'summary.json').read_text())
        res.stereo_replay_poses = len(sref.T_world_cam)
        res.stereo_replay_measurements = _find_count(info)
        # nodes by stamp; the first node is the datum (identity) in both, and its stamp is not
        # carried by any measurement (a measurement has its destination's stamp)
        common, ia, ib = np.intersect1d(stamps_live[1:], sref.stamps_ns[1:],
                                        return_indices=True)
        if common.size >= 3:
            # rigidly aligned: when the first frames are dropped before the CameraInfo arrives,
            # the live VO's first keyframe (the datum) is a later frame than the replay's
            from ga_ros.eval.metrics import ate

            res.max_diff_vs_stereo_replay_m = ate(T_live[ia + 1], sref.T_world_cam[ib + 1],
                                                  'rigid').max
        log(f'stereo bag replayed in-process: {res.stereo_replay_poses} poses, '
            f'{res.stereo_replay_measurements} measurements; live {len(T_live)} poses, '
            f'{res.measurements_received} measurements; largest difference at common stamps '
            '(rigidly aligned) '
            f'{res.max_diff_vs_stereo_replay_m} m')


def _find_count(info: dict) -> int | None:
    for key in ('measurements', 'n_measurements', 'measurements_used'):
        v = info.get(key)
        if isinstance(v, int):
            return v
        if isinstance(v, dict):
            for k2 in ('accepted', 'used', 'total'):
                if isinstance(v.get(k2), int):
                    return v[k2]
    return None


def format_result(res: MultihostResult) -> str:
    """A short human-readable report of a run."""
    lat = res.latency_from_trigger_s
    lines = [
        f'multi-host run ({res.discovery} discovery, netem {res.netem}): '
        f'{"OK" if res.ok else "FAILED"} in {res.seconds:.0f} s',
        f'  host 3 received {res.measurements_received} measurements and '
        f'{res.paths_received} paths (last: {res.path_poses} poses)',
        f'  vs ga-ros replay of the same measurements: {res.replay_poses} poses, max difference '
        f'{res.max_diff_vs_replay_m} m / {res.max_rot_diff_vs_replay_rad} rad',
    ]
    if res.stereo_replay_poses is not None:
        lines.append(f'  vs ga-ros replay of the stereo bag: {res.stereo_replay_poses} poses; '
                     f'largest difference at common stamps (rigidly aligned) '
                     f'{res.max_diff_vs_stereo_replay_m} m')
    if lat:
        lines.append(f'  end-of-track latency (track-ending measurement published on host 1 -> '
                     f'path on host 3): median {np.median(lat):.3f} s, max {max(lat):.3f} s '
                     f"over {len(lat)} tracks; from the track's last measurement: median "
                     f'{np.median(res.latency_from_last_s):.3f} s')
    if res.finish_latency_s is not None:
        lines.append(f'  finish_track call on host 3 -> final path on host 3: '
                     f'{res.finish_latency_s:.3f} s')
    for h, c in res.counters.items():
        if c:
            lines.append(f'  {h} eth0: rx {c["rx_bytes"] / 1e6:.2f} MB, '
                         f'tx {c["tx_bytes"] / 1e6:.2f} MB')
    lines += [f'  error: {e}' for e in res.errors]
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m ga_ros.tools.multihost [--out DIR] [--discovery multicast|peers]
    [--netem] [--rate R] [--no-stereo-replay]``."""
    import argparse

    p = argparse.ArgumentParser(description='Three-host DDS demo in network namespaces.')
    p.add_argument('--out', default=str(REPO / 'out' / 'multihost'))
    p.add_argument('--discovery', choices=('multicast', 'peers'), default='multicast')
    p.add_argument('--netem', action='store_true',
                   help='also try 5 %% loss + 20 ms delay (tc netem), if the kernel has it')
    p.add_argument('--rate', type=float, default=5.0, help='ga-ros play --rate')
    p.add_argument('--no-stereo-replay', action='store_true')
    p.add_argument('--json', action='store_true')
    a = p.parse_args(argv)
    try:
        res = run_demo(a.out, a.discovery, a.netem, a.rate,
                       stereo_replay=not a.no_stereo_replay,
                       log=lambda s: print(s, file=sys.stderr, flush=True))
    except MultihostUnavailable as exc:
        print(f'multihost: cannot run here: {exc}', file=sys.stderr)
        return 2
    except GaError as exc:
        print(f'multihost: {exc}', file=sys.stderr)
        return 1
    print(json.dumps(asdict(res), indent=1) if a.json else format_result(res))
    return 0 if res.ok else 1


if __name__ == '__main__':
    sys.exit(main())
