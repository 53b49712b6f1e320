"""The names of the input sources: one definition for the odometry, the fixes and the cameras.

A source's name is what its measurements carry (``Measurement.source``, ``AbsoluteFix.source``):
the group of its variance factor and the name of its additional parameters
(``docs/calibration.md``). Unnamed inputs are numbered by kind in the order they are given:
``odom0``, ``odom1``, ... (``ga-ros replay --odom-topic``), ``fix0``, ... (``--absolute-topic``)
and ``cam0`` for the stereo camera (the visual odometry of a stereo bag or ``vo_node``, a
camera beside the odometry); the nodes' parameters name them otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from ga_ros.core.encoding import SOURCE_BYTES
from ga_ros.errors import InputError

#: The prefixes of the numbered names: odometry / pose inputs, absolute fixes, stereo cameras.
ODOMETRY = 'odom'
FIX = 'fix'
CAMERA = 'cam'


def source_name(kind: str, index: int) -> str:
    """The name of the ``index``-th (0-based) input of a kind (:data:`ODOMETRY`,
    :data:`FIX`, :data:`CAMERA`): ``odom0``, ``fix1``, ``cam0``."""
    return f'{kind}{int(index)}'


def numbered(kind: str, topics: Sequence[str]) -> dict[str, str]:
    """``{name: topic}`` of inputs of one kind given in order (``--odom-topic A --odom-topic
    B``: ``{'odom0': A, 'odom1': B}``)."""
    return {source_name(kind, k): t for k, t in enumerate(topics)}


#: The default source of a stereo camera's measurements (its consecutive motions and its
#: cross-track connections).
CAMERA_SOURCE = source_name(CAMERA, 0)


def check_source_name(name: str, what: str) -> str:
    """``name`` if it can name a source: not empty, at most
    :data:`~ga_ros.core.encoding.SOURCE_BYTES` bytes in UTF-8 (what the measurement encoding
    carries).

    Raises
    ------
    InputError
        Empty or too long (``what`` names the setting).
    """
    name = str(name)
    if not name or len(name.encode('utf-8')) > SOURCE_BYTES:
        raise InputError(f'{what} must be a name of 1 to {SOURCE_BYTES} bytes, got {name!r}')
    return name
