"""The core never imports ROS (STYLE habit 1): import every module outside ``ga_ros.ros`` in a
fresh interpreter where ``import rclpy`` (and the message packages) fail."""

from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

import ga_ros

BLOCKED = ['rclpy', 'rosidl_runtime_py', 'builtin_interfaces', 'std_msgs', 'geometry_msgs',
           'nav_msgs', 'sensor_msgs', 'visualization_msgs', 'diagnostic_msgs', 'std_srvs',
           'rosgraph_msgs', 'rcl_interfaces']

SCRIPT = """
import importlib, sys, traceback
for name in {blocked!r}:
    sys.modules[name] = None
failed = []
for mod in {modules!r}:
    try:
        importlib.import_module(mod)
    except Exception:
        failed.append((mod, traceback.format_exc(limit=3)))
leaked = sorted(m for m in sys.modules if m.split('.')[0] in {blocked!r} and sys.modules[m])
for mod, tb in failed:
    print('FAILED', mod, tb)
print('LEAKED', leaked)
sys.exit(1 if failed or leaked else 0)
"""


def core_modules() -> list[str]:
    root = Path(ga_ros.__file__).parent
    names = ['ga_ros']
    for info in pkgutil.walk_packages([str(root)], prefix='ga_ros.'):
        if info.name == 'ga_ros.ros' or info.name.startswith('ga_ros.ros.'):
            continue
        names.append(info.name)
    return names


def test_core_modules_found():
    mods = core_modules()
    assert 'ga_ros.core.network' in mods and 'ga_ros.geometry.se3' in mods
    assert not any(m.startswith('ga_ros.ros') for m in mods)


def test_core_imports_without_ros():
    script = SCRIPT.format(blocked=BLOCKED, modules=core_modules())
    proc = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_blocking_works():
    """The check itself can fail: importing a ROS module in the blocked interpreter errors."""
    script = SCRIPT.format(blocked=BLOCKED, modules=['ga_ros.ros.conversions'])
    proc = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 1
    assert 'FAILED ga_ros.ros.conversions' in proc.stdout
