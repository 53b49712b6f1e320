"""The shared ``main`` of ga_ros's nodes: init, spin, shut down cleanly, map errors to exit 1."""

from __future__ import annotations

import sys
from collections.abc import Callable

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from ga_ros.errors import GaError
from ga_ros.runtime import limit_blas_threads


def wants_help(args: list[str] | None) -> bool:
    """True when the command line (``sys.argv[1:]`` if ``args`` is None) asks for ``-h`` /
    ``--help`` before any ``--ros-args``."""
    argv = list(sys.argv[1:] if args is None else args)
    if '--ros-args' in argv:
        argv = argv[:argv.index('--ros-args')]
    return '-h' in argv or '--help' in argv


def node_usage(name: str, doc: str, parameters: list[str]) -> str:
    """The ``--help`` text of a node: how to run it, its summary and its parameter names.

    Parameters
    ----------
    name : the executable (``alignment_node``).
    doc : the node module's docstring (its first paragraph is shown).
    parameters : the parameter names the node declares.
    """
    summary = (doc or '').strip().split('\n\n')[0]
    lines = [f'usage: {name} [-h] [--ros-args [--params-file FILE] [-p NAME:=VALUE] '
             '[-r FROM:=TO] ...]', '', summary, '',
             f'ros2 run ga_ros {name} --ros-args --params-file '
             '$(ros2 pkg prefix ga_ros)/share/ga_ros/config/<file>.yaml', '',
             f'parameters ({len(parameters)}):']
    lines += [f'  {p}' for p in parameters]
    return '\n'.join(lines)


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's message, without rcl's file and line suffix."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text.split(', at /')[0]


def run_node(factory: Callable[[], Node], name: str, args: list[str] | None = None,
             usage: Callable[[], str] | None = None) -> int:
    """Create the node with ``factory()`` and spin it until shutdown.

    Returns the process exit code: 0 on a normal or Ctrl-C shutdown, 1 when the node cannot
    start (a bad parameter value, reported as one line on stderr). BLAS is pinned to one thread
    (see :func:`ga_ros.runtime.limit_blas_threads`). With ``-h`` / ``--help`` (before any
    ``--ros-args``) ``usage()`` is printed and 0 returned without starting rclpy.
    """
    if usage is not None and wants_help(args):
        print(usage())
        return 0
    _blas = limit_blas_threads()  # noqa: F841 (kept alive while the node runs)
    try:
        rclpy.init(args=args)
    except RCLError as exc:
        print(f'{name}: error: ROS arguments not understood ({_first_line(exc)}). Write them as '
              f'`--ros-args -p name:=value`; an empty string is `-p "name:=\'\'"` '
              f'(the quotes reach the node).', file=sys.stderr)
        return 2
    node = None
    code = 0
    try:
        node = factory()
        _spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (GaError, ParameterException) as exc:
        print(f'{name}: error: {type(exc).__name__}: {exc}', file=sys.stderr)
        code = 1
    except Exception:
        if rclpy.ok():
            raise
        # SIGTERM / SIGINT during start-up: rclpy shut the context down under the constructor
        print(f'{name}: stopped during start-up', file=sys.stderr)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _spin(node: Node) -> None:
    """Spin until shutdown; an exception escaping a callback is logged, not fatal (a node must
    not die on one bad message or timer tick)."""
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while rclpy.ok():
            try:
                executor.spin_once()
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception as exc:  # noqa: BLE001 - logged, the node goes on
                if not rclpy.ok():
                    raise
                node.get_logger().error(f'callback failed (the node goes on): '
                                        f'{type(exc).__name__}: {exc}',
                                        throttle_duration_sec=5.0)
    finally:
        executor.remove_node(node)
