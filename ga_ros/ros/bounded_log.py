"""Log lines of bounded length: an input may carry a megabyte-long frame id, and a node that
logs it (throttled or not) would write megabytes to its log. :class:`BoundedLogging` is a mixin
of the package's nodes whose ``get_logger()`` cuts every line to :data:`MAX_LOG_LINE_CHARS`,
showing where it was cut and how long it was."""

from __future__ import annotations

import os
from typing import Any

#: Longest log line a ga_ros node writes, in characters (the cut is marked, with the length).
MAX_LOG_LINE_CHARS = 2000


def bounded_line(text: object, limit: int = MAX_LOG_LINE_CHARS) -> str:
    """``str(text)`` cut to at most ``limit`` characters; a cut line ends with
    ``'... [cut: N chars]'`` (N: the whole line's length)."""
    s = str(text)
    if len(s) <= limit:
        return s
    tail = f'... [cut: {len(s)} chars]'
    return s[:max(limit - len(tail), 0)] + tail


def shown_id(text: object, limit: int = 64) -> str:
    """``repr(str(text))`` of a frame id or name for a log line: ids longer than ``limit``
    characters are cut, with their length (``'abc...' (1048576 chars)``)."""
    s = str(text)
    return repr(s) if len(s) <= limit else f'{s[:limit]!r}... ({len(s)} chars)'


class BoundedLogger:
    """An rclpy logger whose lines are cut by :func:`bounded_line`; everything else (levels,
    ``throttle_duration_sec``, ``once``, ``skip_first``) is rclpy's. rclpy keys throttling by
    the calling line: this module registers itself among rclpy's internal callers, so the
    key stays the node's own call site."""

    def __init__(self, logger: Any, limit: int = MAX_LOG_LINE_CHARS) -> None:
        self._logger = logger
        self._limit = limit

    def debug(self, message: object, **kwargs: Any) -> bool:
        return self._logger.debug(bounded_line(message, self._limit), **kwargs)

    def info(self, message: object, **kwargs: Any) -> bool:
        return self._logger.info(bounded_line(message, self._limit), **kwargs)

    def warning(self, message: object, **kwargs: Any) -> bool:
        return self._logger.warning(bounded_line(message, self._limit), **kwargs)

    warn = warning

    def error(self, message: object, **kwargs: Any) -> bool:
        return self._logger.error(bounded_line(message, self._limit), **kwargs)

    def fatal(self, message: object, **kwargs: Any) -> bool:
        return self._logger.fatal(bounded_line(message, self._limit), **kwargs)

    def __getattr__(self, name: str) -> Any:   # name, get_child, set_level, ...
        return getattr(self._logger, name)


def _register_as_internal_caller() -> None:
    """Add this file to rclpy's list of logging helpers skipped when finding the caller (the
    list is meant to be extended: rclpy keeps entries added before it fills its own)."""
    from rclpy.impl import rcutils_logger
    path = os.path.realpath(__file__)
    if path not in rcutils_logger._internal_callers:
        rcutils_logger._internal_callers.append(path)


class BoundedLogging:
    """Node mixin (before :class:`rclpy.node.Node` in the bases): ``get_logger()`` returns a
    :class:`BoundedLogger`."""

    def get_logger(self) -> BoundedLogger:
        logger = getattr(self, '_bounded_logger', None)
        if logger is None:
            _register_as_internal_caller()
            logger = BoundedLogger(super().get_logger())
            self._bounded_logger = logger
        return logger
