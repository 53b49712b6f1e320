"""ROS 2 message type names -> rclpy message classes, through the ament resource index.

One lookup for every place that subscribes or publishes by type name: the alignment node's
inputs (``odom0.type``, ``fix0.type``) and ``ga-ros play`` (the types recorded in a bag).
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from pathlib import Path

from ga_ros.errors import InputError

_MSGTYPE = re.compile(r'^([a-z][a-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)$')


def interface_index(package: str) -> set[str] | None:
    """The interfaces a ROS package declares in the ament resource index (``msg/Type.msg``,
    ...), or None if no prefix (``AMENT_PREFIX_PATH``, then this Python's prefix) lists the
    package as providing ROS interfaces."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for prefix in prefixes + [sys.prefix]:
        entry = Path(prefix, 'share', 'ament_index', 'resource_index', 'rosidl_interfaces',
                     package)
        if entry.is_file():
            return {line.strip() for line in entry.read_text().splitlines() if line.strip()}
    return None


def message_class(msgtype: str) -> type:
    """The rclpy message class of a ROS 2 type name ``pkg/msg/Type``.

    Only names of that form whose package the ament resource index lists as providing that
    message are imported (ROS's own message lookup; a bag cannot make the player import an
    arbitrary Python module).

    Raises
    ------
    InputError
        If the name is malformed or no installed ROS interface package provides the message.
    """
    match = _MSGTYPE.match(msgtype)
    if match is None:
        raise InputError(f'malformed message type name {msgtype!r} (expected pkg/msg/Type)')
    pkg, name = match.groups()
    declared = interface_index(pkg)
    if declared is None or not {f'msg/{name}.msg', f'msg/{name}.idl'} & declared:
        raise InputError(f'unknown message type {msgtype!r}: no ROS interface package here '
                         f'provides it (source the workspace that builds {pkg!r})')
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError):
        raise InputError(f'unknown message type {msgtype!r}: the Python module of {pkg!r} is '
                         'not installed in this environment') from None
