"""ga_ros as a ROS package: declared dependencies, launch files, ``--help``, ``colcon build``.

The launch files are checked without the ``launch`` package: parsed with ``ast``, every
``ga_ros`` executable must be a console script, every parameter file must exist, every
parameter name must be one the node declares (built from its config dataclasses) and every
remapped topic one the node uses.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from ga_ros.bench.data import SHARED_DATA

REPO = Path(__file__).resolve().parents[2]
#: rosdep's key lists (base.yaml, python.yaml) in the shared data ($GA_ROS_SHARED_DATA)
ROSDEP = SHARED_DATA / 'rosdep'

#: ROS 2 packages (released in rosdistro, not rosdep keys of base.yaml / python.yaml).
ROS_PACKAGES = {
    'rclpy', 'rmw_fastrtps_cpp', 'geometry_msgs', 'nav_msgs', 'sensor_msgs', 'std_msgs',
    'std_srvs', 'visualization_msgs', 'diagnostic_msgs', 'builtin_interfaces', 'rosgraph_msgs',
    'tf2_msgs', 'lifecycle_msgs', 'rcl_interfaces', 'tf2_ros', 'ros2launch', 'launch_ros',
    'ament_index_python', 'ament_lint_auto'}

#: pip name (setup.py) -> rosdep key (package.xml); None: no key, installed by the README's
#: pip step.
PIP_TO_ROSDEP = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'cvxopt': 'python3-cvxopt',
    'opencv-python-headless': 'python3-opencv', 'matplotlib': 'python3-matplotlib',
    'PyYAML': 'python3-yaml', 'tqdm': 'python3-tqdm', 'rosbags': 'python3-rosbags-pip',
    'mcap-ros2-support': 'mcap-ros2-support', 'mcap': 'mcap-ros2-support',
    'numba': 'python3-numba', 'threadpoolctl': None, 'pymetis': None, 'lz4': None,
    'zstandard': None}

#: import name -> pip name, where they differ.
IMPORT_TO_PIP = {'cv2': 'opencv-python-headless', 'yaml': 'PyYAML', 'llvmlite': 'numba'}

#: Third-party imports that are not dependencies: the optional reference solvers of the
#: benchmarks (``ga-ros bench --gtsam``, the CHOLMOD comparison), skipped when absent.
BENCHMARK_ONLY = {'gtsam', 'sksparse'}


def _package_xml() -> dict[str, list[str]]:
    root = ET.parse(REPO / 'package.xml').getroot()
    out: dict[str, list[str]] = {}
    for el in root:
        if el.tag.endswith('depend'):
            out.setdefault(el.tag, []).append(el.text.strip())
    return out


def _setup_call() -> ast.Call:
    tree = ast.parse((REPO / 'setup.py').read_text())
    return next(n for n in ast.walk(tree) if isinstance(n, ast.Call)
                and getattr(n.func, 'id', '') == 'setup')


def _setup_kw(name: str) -> object:
    kw = next(k for k in _setup_call().keywords if k.arg == name)
    return ast.literal_eval(kw.value)


def _requirements() -> dict[str, str]:
    pins = {}
    for line in (REPO / 'requirements.txt').read_text().splitlines():
        m = re.match(r'^([A-Za-z0-9_.\-]+)==(\S+)', line)
        if m:
            pins[m.group(1).lower()] = m.group(2)
    return pins


def _console_scripts() -> dict[str, str]:
    scripts = _setup_kw('entry_points')['console_scripts']
    return dict(s.replace(' ', '').split('=', 1) for s in scripts)


# --------------------------------------------------------------------------- dependencies
@pytest.mark.skipif(not (ROSDEP / 'python.yaml').exists(),
                    reason=f'rosdep keys not found at {ROSDEP} (set GA_ROS_SHARED_DATA)')
def test_package_xml_keys_exist_in_rosdep():
    keys: set[str] = set()
    for f in ('base.yaml', 'python.yaml'):
        keys |= set(yaml.safe_load((ROSDEP / f).read_text()))
    deps = [d for ds in _package_xml().values() for d in ds]
    unknown = [d for d in deps if d not in ROS_PACKAGES and d not in keys]
    assert not unknown, f'not rosdep keys: {unknown}'


def test_setup_py_package_xml_and_requirements_agree():
    install = [r for r in _setup_kw('install_requires') if r != 'setuptools']
    extras = [r for rs in _setup_kw('extras_require').values() for r in rs]
    pins = _requirements()
    assert [r for r in install + extras if r.lower() not in pins] == []
    xml_python = {d for ds in _package_xml().values() for d in ds if d not in ROS_PACKAGES}
    xml_python.discard('python3-pytest')  # the test runner
    wanted = {PIP_TO_ROSDEP[r] for r in install + extras if PIP_TO_ROSDEP[r] is not None}
    assert xml_python == wanted
    # the packages without a key are named in the README's pip step
    readme = (REPO / 'README.md').read_text()
    for pip_name in [r for r in install + extras if PIP_TO_ROSDEP[r] is None]:
        assert re.search(rf'pip install[^\n]*\b{pip_name}==', readme), pip_name


def _third_party_imports() -> set[str]:
    names = set()
    for path in (REPO / 'ga_ros').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split('.')[0])
    ros = {n for n in names if n.endswith(('_msgs', '_srvs', '_interfaces')) or n == 'rclpy'}
    return names - set(sys.stdlib_module_names) - {'ga_ros', '__future__'} - ros


def test_every_third_party_import_is_declared():
    declared = {r for r in _setup_kw('install_requires')}
    declared |= {r for rs in _setup_kw('extras_require').values() for r in rs}
    missing = sorted(n for n in _third_party_imports() - BENCHMARK_ONLY
                     if IMPORT_TO_PIP.get(n, n) not in declared)
    assert missing == []


# --------------------------------------------------------------------------- launch files
def _node_facts(executable: str, inputs: tuple[str, ...],
                absolutes: tuple[str, ...] = ()) -> tuple[set[str], set[str]]:
    """(declared parameter names, topics used) of a ga_ros node, without starting it."""
    pytest.importorskip('rclpy')
    if executable == 'vo_node':
        from ga_ros.ros.vo_node import VoNodeSettings, declared_parameters

        params = set(declared_parameters())
        settings = VoNodeSettings()
    elif executable == 'map_node':
        from ga_ros.ros.map_node import MapNodeSettings
        from ga_ros.ros.map_node import declared_parameters as map_parameters

        params = set(map_parameters())
        settings = MapNodeSettings()
    else:
        from ga_ros.ros.alignment_node import NodeSettings, declared_parameters

        params = set(declared_parameters(inputs, absolutes))
        settings = NodeSettings()
    topics = {getattr(settings, f.name) for f in fields(settings) if f.name.endswith('_topic')}
    return params | {'use_sim_time'}, topics


def _flat(mapping: dict, prefix: str = '') -> set[str]:
    out = set()
    for k, v in mapping.items():
        out |= _flat(v, f'{prefix}{k}.') if isinstance(v, dict) else {prefix + k}
    return out


def _kw(call: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


LAUNCH_FILES = sorted((REPO / 'launch').glob('*.launch.py'))


def test_launch_files_exist_and_are_installed():
    names = {p.name for p in LAUNCH_FILES}
    assert {'stereo_vo.launch.py', 'odometry.launch.py', 'play_bag.launch.py'} <= names
    assert "glob('launch/*.launch.py')" in (REPO / 'setup.py').read_text()


@pytest.mark.parametrize('path', LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_names_only_what_exists(path: Path):
    tree = ast.parse(path.read_text())
    scripts = _console_scripts()
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    nodes = [c for c in calls if getattr(c.func, 'id', '') == 'Node'
             and isinstance(_kw(c, 'package'), ast.Constant)
             and _kw(c, 'package').value == 'ga_ros']
    assert nodes, 'no ga_ros node'
    for call in nodes:
        exe = ast.literal_eval(_kw(call, 'executable'))
        assert exe in scripts, exe
        params = _kw(call, 'parameters')
        dicts = [e for e in getattr(params, 'elts', []) if isinstance(e, ast.Dict)]
        names = {ast.literal_eval(k) for d in dicts for k in d.keys}
        inputs: tuple[str, ...] = ()
        for d in dicts:
            for k, v in zip(d.keys, d.values):
                if ast.literal_eval(k) == 'inputs' and isinstance(v, ast.Constant):
                    inputs = tuple(n.strip() for n in v.value.split(',') if n.strip())
        # absolute inputs: named by a constant, or (chosen by a launch argument) those with a
        # topic parameter that are not standard inputs
        absolutes = tuple(sorted({n.rsplit('.', 1)[0] for n in names if n.endswith('.topic')}
                                 - set(inputs)))
        declared, topics = _node_facts(exe, inputs, absolutes)
        files = [c.value for c in ast.walk(params) if isinstance(c, ast.Constant)
                 and isinstance(c.value, str) and c.value.endswith('.yaml')] if params else []
        for name in files:
            f = REPO / 'config' / name
            assert f.exists(), name
            section = yaml.safe_load(f.read_text()).get(exe, {}).get('ros__parameters', {})
            assert section, f'{name} has no {exe} section'
            assert _flat(section) - declared == set(), name
        assert names - declared == set(), exe
        remaps = _kw(call, 'remappings')
        for pair in getattr(remaps, 'elts', []):
            src = ast.literal_eval(pair.elts[0])
            assert src in topics, f'{exe} does not use {src!r}'
    # processes: a console script of the installed ga_ros (lib/ga_ros, not on PATH)
    for call in calls:
        if getattr(call.func, 'id', '') == 'ExecuteProcess':
            exe = _kw(call, 'cmd').elts[0]
            assert getattr(exe, 'func', None) and exe.func.id == 'ExecutableInPackage', \
                'ExecuteProcess must find its executable in the package (ExecutableInPackage)'
            assert [ast.literal_eval(a) for a in exe.args] in [[s, 'ga_ros'] for s in scripts]


def test_launch_file_parameters_are_checked_against_the_node():
    """The launch-file check rejects a parameter name the node does not declare."""
    declared, topics = _node_facts('alignment_node', ('odom0',))
    assert 'odom0.topic' in declared and 'transform_publish_period_sec' in declared
    assert 'odom0.qos_reliability' in declared and 'sensor_frame' not in declared
    assert 'fix0.topic' not in declared
    assert {'fix0.topic', 'fix0.type', 'fix0.frame_id'} <= _node_facts(
        'alignment_node', ('odom0',), ('fix0',))[0]
    declared_vo, topics_vo = _node_facts('vo_node', ())
    assert {'T_base_camera', 'qos_reliability', 'base_frame'} <= declared_vo
    assert 'camera_info' not in declared_vo and 'stereo/left/image_rect' in topics_vo


# --------------------------------------------------------------------------- executables
@pytest.mark.parametrize('module', ['alignment_node', 'vo_node', 'lifecycle_alignment_node',
                                    'map_node'])
def test_node_help_exits_without_starting_ros(module: str):
    pytest.importorskip('rclpy')
    out = subprocess.run([sys.executable, '-m', f'ga_ros.ros.{module}', '--help'],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith('usage: ') and 'parameters (' in out.stdout
    assert 'ros2 run ga_ros' in out.stdout
    assert '[INFO]' not in out.stderr + out.stdout   # no node started (it logs its topics)



@pytest.mark.parametrize('module', ['alignment_node', 'vo_node'])
def test_node_with_unparsable_ros_arguments_says_how_to_write_them(module: str):
    """``-p state_file:=`` (a shell ate the quotes of ``''``) is one clear line and exit 2."""
    pytest.importorskip('rclpy')
    out = subprocess.run([sys.executable, '-m', f'ga_ros.ros.{module}', '--ros-args', '-p',
                          'state_file:='], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr
    assert 'Traceback' not in out.stderr
    assert f'{module}: error: ROS arguments not understood' in out.stderr
    assert 'state_file:=' in out.stderr


@pytest.mark.slow
def test_colcon_build_then_installed_executables_answer_help(colcon_workspace, tmp_path: Path):
    install, env = colcon_workspace.install, colcon_workspace.env
    share = install / 'ga_ros' / 'share' / 'ga_ros'
    assert {p.name for p in (share / 'launch').glob('*.launch.py')} == {
        p.name for p in LAUNCH_FILES}
    assert (share / 'config' / 'alignment.yaml').exists() and (share / 'package.xml').exists()
    for exe in ('alignment_node', 'vo_node', 'lifecycle_alignment_node', 'map_node', 'ga-ros'):
        path = install / 'ga_ros' / 'lib' / 'ga_ros' / exe
        assert path.exists(), exe
        script = f'source "{install}/setup.bash" && "{path}" --help'
        out = subprocess.run(['bash', '-c', script], env=env, cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, (exe, out.stderr)
        assert out.stdout.startswith('usage: '), exe
    # the sourced workspace's copy is the one imported, not the developer's tree
    where = subprocess.run(['bash', '-c', f'source "{install}/setup.bash" && "{sys.executable}"'
                            ' -c "import ga_ros; print(ga_ros.__file__)"'], env=env,
                           cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert str(install) in where.stdout, where.stdout + where.stderr
