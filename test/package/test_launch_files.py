"""The launch files run by ROS's own launch system, from a colcon-built workspace.

Each launch file of ``launch/`` is looked up in the installed package and run by
``launch.LaunchService`` (``run_launch.py``: what ``ros2 launch ga_ros FILE name:=value`` does) on
its own ``ROS_DOMAIN_ID``; a bag is played into it (the bundled stereo sample, or an odometry bag
with AMCL-like fixes written here) and the corrected path must arrive, subscribed with rclpy;
then SIGINT shuts the launch down and every process it started must be gone. The defaults of the
launch arguments must be those of ``config/`` (and of the nodes).

Needs the Python sources of ROS 2 Jazzy's launch packages (``GA_ROS_SHARED_VENDOR``, else
``shared/vendor`` beside the checkout: ``ros2-launch-jazzy/``), ``osrf-pycommon`` and
``composition_interfaces`` built into the venv (``scripts/venv.sh`` does both); skips, saying
which is missing, otherwise. tf2_ros is not installable here: ``static_transform_publisher.py``
stands in for its ``static_transform_publisher`` (same non-deprecated command line; it refuses
any other), in a temporary ament prefix.
"""

from __future__ import annotations

import importlib.util
import os
import select
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import yaml
from colcon_workspace import REPO, Workspace

pytestmark = [pytest.mark.ros, pytest.mark.slow]

VENDOR = Path(os.environ.get('GA_ROS_SHARED_VENDOR', REPO.parent / 'shared' / 'vendor')) \
    / 'ros2-launch-jazzy'
HERE = Path(__file__).resolve().parent
RUNNER = HERE / 'run_launch.py'
STAND_IN = HERE / 'static_transform_publisher.py'
LAUNCH_FILES = sorted(p.name for p in (REPO / 'launch').glob('*.launch.py'))
STEREO_BAG = REPO / 'bags' / 'stereo_sample'
#: Seconds to wait for an outcome, times the harness's patience (ga_ros.ros.deadlines: 4 by
#: default), within pytest's 600 s per test.
DEADLINE_S = 120.0


def _missing() -> str | None:
    """Why the launch system cannot run here, or None."""
    if not (VENDOR / 'launch' / '__init__.py').is_file():
        return (f'ROS 2 launch sources not found at {VENDOR} (set GA_ROS_SHARED_VENDOR to the '
                'folder holding ros2-launch-jazzy/)')
    for module, how in (('rclpy', 'the ROS 2 wheels (scripts/venv.sh)'),
                        ('osrf_pycommon', 'pip install osrf-pycommon (requirements.txt)'),
                        ('composition_interfaces', 'scripts/venv.sh builds it from the vendor '
                                                   'folder (scripts/build_interfaces.sh)'),
                        ('tf2_msgs', 'scripts/build_tf2_msgs.sh')):
        if importlib.util.find_spec(module) is None:
            return f'{module} is not installed: {how}'
    return None


if (_why := _missing()) is not None:
    pytest.skip(_why, allow_module_level=True)


# --------------------------------------------------------------------------- running launch
@contextmanager
def launched(ws: Workspace, name: str, arguments: list[str], domain: int, log: Path,
             env: dict[str, str] | None = None) -> Iterator[subprocess.Popen]:
    """``ros2 launch ga_ros NAME ARGUMENTS`` (through :data:`RUNNER`) on ``domain`` in the sourced
    workspace, output to ``log``; stopped with SIGINT at exit if still running (then killed)."""
    # ROS_HOME of this test: the alignment node keeps its state there by default, and a node
    # must not resume another test's survey (ws.env is the session's environment)
    full = dict(ws.env, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1',
                ROS_LOG_DIR=str(log.parent / 'ros_log'), ROS_HOME=str(log.parent / 'ros_home'),
                **(env or {}))
    full['PYTHONPATH'] = os.pathsep.join(
        p for p in (str(VENDOR), os.environ.get('PYTHONPATH', '')) if p)
    # sigterm_timeout (launch's own argument, default 5 s): how long a process may take to stop
    # after SIGINT before launch escalates to SIGTERM; on a busy 2-core machine the alignment
    # node can be inside a window update for longer
    command = ' '.join(shlex.quote(a) for a in [sys.executable, str(RUNNER), 'ga_ros', name,
                                                *arguments, 'sigterm_timeout:=60'])
    with open(log, 'ab') as out:
        proc = subprocess.Popen(ws.sourced(f'exec {command}'), env=full, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=30)
        _kill_group(proc.pid)


def _group(pgid: int) -> dict[int, str]:
    """The processes of the process group ``pgid``: pid -> command line."""
    ps = subprocess.run(['ps', '-e', '-o', 'pgid=,pid=,args='], capture_output=True,
                        text=True).stdout.splitlines()
    return {int(f[1]): f[2] if len(f) > 2 else '' for f in (line.split(None, 2) for line in ps)
            if f[0] == str(pgid)}


def _wait_group_gone(pgid: int, timeout: float) -> str:
    """Wait (on each process's exit, through its pidfd) until the process group ``pgid`` is
    empty or ``timeout`` s have passed; what is left, as ``pid command`` lines ('' if none)."""
    deadline = time.monotonic() + timeout
    while (left := _group(pgid)) and time.monotonic() < deadline:
        for pid in left:
            try:
                fd = os.pidfd_open(pid)
            except ProcessLookupError:
                continue
            try:
                select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            finally:
                os.close(fd)
    return '\n'.join(f'{pid} {cmd}' for pid, cmd in _group(pgid).items())


def _kill_group(pgid: int) -> None:
    """Kill what is left of the process group ``pgid``."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def shut_down(proc: subprocess.Popen, log: Path) -> None:
    """SIGINT to the launch service, as Ctrl-C to ``ros2 launch``: it must stop every process
    it started and exit 0."""
    proc.send_signal(signal.SIGINT)
    try:
        code = proc.wait(timeout=DEADLINE_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f'the launch service did not stop within {DEADLINE_S:.0f} s of SIGINT '
                    f'({_signal_state(proc.pid)}; its process group: '
                    f'{_group(proc.pid)}):\n' + _tail(log))
    assert code == 0, f'launch exited {code}:\n' + _tail(log)
    # the alignment node's refinement worker process exits within ~1 s of the node
    # (ga_ros.core.window.worker): wait for it with a deadline, then nothing may be left
    left = _wait_group_gone(proc.pid, 30.0)
    _kill_group(proc.pid)
    assert not left, f'processes of the launch outlived it by 30 s:\n{left}\n' + _tail(log)


def _signal_state(pid: int) -> str:
    """The state and the blocked, ignored and caught signal masks of process ``pid`` (from
    ``/proc``): a SIGINT that nothing handles shows as blocked or ignored there."""
    try:
        lines = Path(f'/proc/{pid}/status').read_text().splitlines()
    except OSError as exc:
        return f'no /proc status: {exc}'
    return ', '.join(t for t in lines if t.split(':')[0] in ('State', 'SigBlk', 'SigIgn',
                                                             'SigCgt', 'Threads'))


def _tail(log: Path, lines: int = 60) -> str:
    return '\n'.join(log.read_text(errors='replace').splitlines()[-lines:])


def play(ws: Workspace, bag: Path, domain: int, log: Path, *options: str) -> subprocess.Popen:
    """The installed ``ga-ros play`` (``lib/ga_ros/ga-ros``) of ``bag`` on ``domain``."""
    exe = ws.install / 'ga_ros' / 'lib' / 'ga_ros' / 'ga-ros'
    command = ' '.join(shlex.quote(a) for a in [str(exe), 'play', str(bag), *options])
    env = dict(ws.env, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    with open(log, 'ab') as out:
        return subprocess.Popen(ws.sourced(f'exec {command}'), env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)


def stand_in_tf2_ros(prefix: Path) -> Path:
    """An ament prefix with a package ``tf2_ros`` whose ``static_transform_publisher`` is
    :data:`STAND_IN`; returns the prefix."""
    lib = prefix / 'lib' / 'tf2_ros'
    lib.mkdir(parents=True)
    index = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'tf2_ros').write_text('')
    exe = lib / 'static_transform_publisher'
    exe.write_text(f'#!{sys.executable}\n' + STAND_IN.read_text())
    exe.chmod(0o755)
    return prefix


def wait_for_path(domain: int, predicate, what: str, procs: list[subprocess.Popen],
                  log: Path) -> object:
    """Subscribe to the corrected path on ``domain`` and spin until a message satisfies
    ``predicate``; return it. Fails (with the launch log) after :data:`DEADLINE_S` or when
    the launch exits."""
    from ga_ros.ros.harness import HarnessTimeout, NodeClient

    with NodeClient(domain) as client:
        found: list = []

        last: list = []

        def done() -> bool:
            last[:] = client.paths[-1:] or last
            found.extend(m for _, m in client.paths if predicate(m))
            client.paths.clear()
            return bool(found)

        try:
            client.spin_until(done, DEADLINE_S, what, proc=procs[0])
        except HarnessTimeout as e:
            seen = 'no path' if not last else (
                f'last path: {len(last[0][1].poses)} poses in {last[0][1].header.frame_id!r}, '
                'from ' + ', '.join(f'({p.pose.position.x:.2f}, {p.pose.position.y:.2f})'
                                    for p in last[0][1].poses[:3]) + ' ...')
            pytest.fail(f'{e} ({seen}):\n' + _tail(log))
        return found[0]


# --------------------------------------------------------------------------- defaults
def _config(file: str, key: str) -> object:
    value = yaml.safe_load((REPO / 'config' / file).read_text())
    for part in key.split('.'):
        value = value[part]
    return value


def _node_default(name: str) -> object:
    if name == 'odom0.type':
        from ga_ros.inputs.messages import ODOMETRY
        return ODOMETRY
    from ga_ros.inputs.absolute import POSE_COV
    return POSE_COV


VO = 'vo_node.ros__parameters.'
#: Launch argument -> where its default is defined: ('config', file, key) or ('node', parameter).
DEFAULTS = {
    ('odometry.launch.py', 'track_mode'): ('config', 'inputs.yaml', 'odom0.track.mode'),
    ('odometry.launch.py', 'datum'): ('config', 'alignment.yaml',
                                      'alignment_node.ros__parameters.datum'),
    ('odometry.launch.py', 'odom_type'): ('node', 'odom0.type'),
    ('odometry.launch.py', 'fix_type'): ('node', 'fix0.type'),
    **{('play_bag.launch.py', t): ('config', 'vo.yaml', f'{VO}{t}_topic')
       for t in ('left_image', 'right_image', 'left_info', 'right_info')},
    ('play_bag.launch.py', 'compressed'): ('config', 'vo.yaml', f'{VO}compressed'),
    ('stereo_vo.launch.py', 'compressed'): ('config', 'vo.yaml', f'{VO}compressed'),
    ('stereo_vo.launch.py', 'base_frame'): ('config', 'vo.yaml', f'{VO}base_frame'),
}
#: Launch arguments without a default in config/ (what they name is the user's).
OWN = {
    'odometry.launch.py': {'odom_topic', 'fix_topic', 'use_sim_time'},
    'play_bag.launch.py': {'bag', 'rate', 'map'},
    'stereo_vo.launch.py': {'start_camera', 'camera_package', 'camera_executable', 'left_image',
                            'right_image', 'left_info', 'right_info', 'camera_frame',
                            'camera_pose', 'use_sim_time', 'map'},
}


def test_launch_argument_defaults_are_those_of_config(colcon_workspace, monkeypatch):
    monkeypatch.syspath_prepend(str(VENDOR))
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(colcon_workspace.install / 'ga_ros'))
    from launch.launch_description_sources import get_launch_description_from_python_launch_file
    from launch.utilities import perform_substitutions

    from launch import LaunchContext

    share = colcon_workspace.install / 'ga_ros' / 'share' / 'ga_ros' / 'launch'
    checked = 0
    for name in LAUNCH_FILES:
        described = get_launch_description_from_python_launch_file(str(share / name))
        arguments = {a.name: a for a in described.get_launch_arguments()}
        assert set(arguments) == OWN[name] | {a for f, a in DEFAULTS if f == name}, name
        for arg, where in ((a, w) for (f, a), w in DEFAULTS.items() if f == name):
            want = _config(*where[1:]) if where[0] == 'config' else _node_default(where[1])
            got = perform_substitutions(LaunchContext(), arguments[arg].default_value)
            want = str(want).lower() if isinstance(want, bool) else str(want)
            assert got == want, f'{name} {arg}: {got!r}, config/ and the node: {want!r}'
            checked += 1
    assert checked == len(DEFAULTS)


# --------------------------------------------------------------------------- each launch file
def _stereo_path_ok(msg) -> bool:
    return msg.header.frame_id == 'map' and len(msg.poses) >= 5


def test_play_bag_launch_plays_the_installed_player_into_both_nodes(colcon_workspace,
                                                                    tmp_path):
    from ga_ros.ros.harness import domain_id

    domain, log = domain_id(321), tmp_path / 'launch.log'
    with launched(colcon_workspace, 'play_bag.launch.py', [
            f'bag:={STEREO_BAG}', 'rate:=2.0', 'compressed:=true',
            'left_image:=/stereo/left/image_raw/compressed',
            'right_image:=/stereo/right/image_raw/compressed',
            'left_info:=/stereo/left/camera_info', 'right_info:=/stereo/right/camera_info'],
            domain, log) as proc:
        path = wait_for_path(domain, _stereo_path_ok, 'a corrected path of 5 VO keyframes',
                             [proc], log)
        assert len(path.poses) >= 5
        shut_down(proc, log)
    text = log.read_text(errors='replace')
    assert '[play' in text and '[vo_node' in text and '[alignment_node' in text


def test_stereo_vo_launch_publishes_the_camera_pose_as_separate_arguments(colcon_workspace,
                                                                          tmp_path):
    from ga_ros.ros.harness import domain_id

    domain, log = domain_id(322), tmp_path / 'launch.log'
    prefix = stand_in_tf2_ros(tmp_path / 'tf2_ros')
    calls = tmp_path / 'static_tf_calls.txt'
    env = {'AMENT_PREFIX_PATH': os.pathsep.join(
        p for p in (str(prefix), os.environ.get('AMENT_PREFIX_PATH', '')) if p),
           'GA_ROS_STATIC_TF_LOG': str(calls)}
    # the README's example; the bag's own /tf_static is not played: the extrinsic must come
    # from the launch file's static_transform_publisher
    with launched(colcon_workspace, 'stereo_vo.launch.py', [
            'start_camera:=false', 'camera_pose:=0.2 0 0.5 -1.5708 0 -1.5708',
            'camera_frame:=stereo_left', 'compressed:=true', 'use_sim_time:=true',
            'left_image:=/stereo/left/image_raw/compressed',
            'right_image:=/stereo/right/image_raw/compressed',
            'left_info:=/stereo/left/camera_info', 'right_info:=/stereo/right/camera_info'],
            domain, log, env) as proc:
        player = play(colcon_workspace, STEREO_BAG, domain, tmp_path / 'play.log', '--rate',
                      '2.0', '--topics', '/stereo/left/image_raw/compressed',
                      '/stereo/right/image_raw/compressed', '/stereo/left/camera_info',
                      '/stereo/right/camera_info')
        try:
            wait_for_path(domain, _stereo_path_ok, 'a corrected path of 5 VO keyframes',
                          [proc], log)
        finally:
            player.send_signal(signal.SIGINT)
            player.wait(timeout=60)
        shut_down(proc, log)
    assert calls.read_text().splitlines() == [' '.join(repr(a) for a in [
        '--x', '0.2', '--y', '0', '--z', '0.5', '--roll', '-1.5708', '--pitch', '0',
        '--yaw', '-1.5708', '--frame-id', 'base_link', '--child-frame-id', 'stereo_left'])]


def test_stereo_vo_launch_refuses_a_malformed_camera_pose(colcon_workspace, tmp_path):
    from ga_ros.ros.harness import domain_id

    log = tmp_path / 'launch.log'
    with launched(colcon_workspace, 'stereo_vo.launch.py',
                  ['start_camera:=false', 'camera_pose:=0.2 0 0.5'], domain_id(323),
                  log) as proc:
        code = proc.wait(timeout=DEADLINE_S)
    assert code != 0
    assert "camera_pose needs six numbers 'x y z roll pitch yaw'" in log.read_text()


def _odometry_bag(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A 20 x 10 m rectangle: ``/odom`` (drifting, 10 Hz, in ``odom``) and ``/amcl_pose`` fixes
    (1 Hz, in ``map``, 0.1 m noise) where ``map`` is 5 m / 3 m / 0.6 rad away from ``odom``.
    Returns the stamps (ns) and the true poses ``T_map_base``."""
    from bag_fixtures import (
        ODOMETRY,
        POSE_COV_STAMPED,
        odometry_msg,
        pose_cov_stamped_msg,
        rectangle_drive,
        write_bag,
    )

    from ga_ros.geometry import se3

    rng = np.random.default_rng(32)
    drive = rectangle_drive(1.0, 10.0, 1_700_000_000_000_000_000)
    T_map_odom = se3.from_translation_rotvec(np.array([5.0, -3.0, 0.0]),
                                             np.array([0.0, 0.0, 0.6]))
    T_map = T_map_odom @ drive.T_true
    cov = np.diag([0.01, 0.01, 1e6, 1e6, 1e6, 1e6])
    rows = []
    for k, (s, T) in enumerate(zip(drive.stamps_ns, drive.T_odom)):
        s = int(s)
        rows.append((s, '/odom', ODOMETRY, odometry_msg(T, s)))
        if k % 10 == 5:
            T_fix = T_map[k].copy()
            T_fix[:2, 3] += rng.normal(0.0, 0.1, 2)
            rows.append((s, '/amcl_pose', POSE_COV_STAMPED,
                         pose_cov_stamped_msg(T_fix, s, cov, 'map')))
    write_bag(path, rows)
    return drive.stamps_ns, T_map


def test_odometry_launch_with_fixes_puts_the_path_in_their_frame(colcon_workspace, tmp_path):
    from ga_ros.ros.harness import domain_id

    stamps, T_map = _odometry_bag(tmp_path / 'bag')

    def in_fix_frame(msg) -> bool:
        """At least 20 poses in ``map``, half of them within 0.5 m of the truth (the fixes'
        frame; the odometry's own frame is 5.8 m and 0.6 rad away)."""
        if msg.header.frame_id != 'map' or len(msg.poses) < 20:
            return False
        at = np.array([p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in msg.poses])
        k = np.clip(np.searchsorted(stamps, at), 0, len(stamps) - 1)
        if np.abs(stamps[k] - at).max() > 50_000_000:   # a keyframe is an odometry sample
            return False
        xy = np.array([[p.pose.position.x, p.pose.position.y] for p in msg.poses])
        err = np.linalg.norm(xy - T_map[k, :2, 3], axis=1)
        return bool(np.median(err) < 0.5)

    domain, log = domain_id(324), tmp_path / 'launch.log'
    with launched(colcon_workspace, 'odometry.launch.py', [
            'odom_topic:=/odom', 'fix_topic:=/amcl_pose', 'datum:=fixes',
            'use_sim_time:=true'], domain, log) as proc:
        player = play(colcon_workspace, tmp_path / 'bag', domain, tmp_path / 'play.log',
                      '--rate', '2.0')
        try:
            wait_for_path(domain, in_fix_frame, "a path in the fixes' frame", [proc], log)
        finally:
            player.send_signal(signal.SIGINT)
            player.wait(timeout=60)
        shut_down(proc, log)


def test_every_launch_file_is_run_here():
    """A new launch file needs its test above."""
    assert LAUNCH_FILES == ['odometry.launch.py', 'play_bag.launch.py', 'stereo_vo.launch.py']
