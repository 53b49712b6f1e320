"""Node frame ids of the ROS measurement encoding: ``'ga/<track>/<node>'``.

The measurement encoding (``nav_msgs/Odometry`` on ``/ga/measurements``, see the README) carries
the node and track ids of a connection's two ends in ``header.frame_id`` and ``child_frame_id``.
Both the rclpy conversions (:mod:`ga_ros.ros.conversions`) and the ROS-free bag reader
(:mod:`ga_ros.io.bag_messages`) parse them here, so the two cannot drift apart.
"""

from __future__ import annotations

import re

from ga_ros.errors import InputError

#: Prefix of every node frame id.
NODE_FRAME_PREFIX = 'ga'

#: Largest accepted node or track id (ids are non-negative and fit in an int64 with margin).
MAX_ID = 2**53

# Same language as ga_ros.ros.conversions: an optional leading '/', decimal ids of 1-19 digits.
_NODE_FRAME = re.compile(r'^/?ga/(\d{1,19})/(\d{1,19})$')


def node_frame(track: int, node: int) -> str:
    """Frame id ``'ga/<track>/<node>'`` of a node.

    Parameters
    ----------
    track : track id (non-negative integer).
    node : node id (non-negative integer).

    Returns
    -------
    str
        The frame id, e.g. ``'ga/3/412'``.

    Raises
    ------
    InputError
        If an id is negative, not an integer, or larger than :data:`MAX_ID`.
    """
    for name, value in (('track', track), ('node', node)):
        if isinstance(value, bool) or not hasattr(value, '__index__'):
            raise InputError(f'{name} id must be an integer, got {value!r}')
        if not 0 <= int(value) <= MAX_ID:
            raise InputError(f'{name} id out of range [0, {MAX_ID}]: {int(value)}')
    return f'{NODE_FRAME_PREFIX}/{int(track)}/{int(node)}'


def parse_node_frame(frame_id: str) -> tuple[int, int]:
    """Parse a node frame id ``'ga/<track>/<node>'``.

    Parameters
    ----------
    frame_id : the frame id; a leading ``'/'`` is tolerated, ids are decimal (1-19 digits).

    Returns
    -------
    tuple[int, int]
        ``(track, node)``.

    Raises
    ------
    InputError
        If the string does not have exactly that form or an id exceeds :data:`MAX_ID`.
    """
    if not isinstance(frame_id, str):
        raise InputError(f'node frame id must be a string, got {type(frame_id).__name__}')
    match = _NODE_FRAME.match(frame_id)
    if match is None:
        raise InputError(f"malformed node frame id {frame_id!r}: expected 'ga/<track>/<node>'")
    track, node = int(match.group(1)), int(match.group(2))
    if track > MAX_ID or node > MAX_ID:
        raise InputError(f'node frame id {frame_id!r}: id out of range [0, {MAX_ID}]')
    return track, node
