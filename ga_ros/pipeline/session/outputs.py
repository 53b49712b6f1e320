"""What a session step returns, what the session counts, and the health it reports."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ga_ros.core.measurement import Measurement
from ga_ros.errors import Reason

#: Called with warnings the session wants shown (the node logs them, throttled).
Warn = Callable[[str], None]
#: Longest error text kept in ``last_error`` (and so in every ``/diagnostics`` message), chars.
MAX_ERROR_CHARS = 200
#: Longest traceback of a failed window update warned about (its end kept), chars: within
#: the nodes' 2,000-character log lines.
MAX_TRACEBACK_CHARS = 1800
#: Distinct failed-update texts whose traceback is warned about (later ones: counted only).
MAX_FAILURES_LOGGED = 20


def bounded(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    """``text`` cut to at most ``limit`` characters (the cut marked with ``'...'``): an input
    may carry a megabyte-long frame id, and its error text is republished at 1 Hz."""
    return text if len(text) <= limit else text[:max(limit - 3, 0)] + '...'


@dataclass(frozen=True)
class StepOutput:
    """What one measurement did.

    Attributes
    ----------
    accepted : the aligner took the measurement, or it is held until its source node is known
        (``held``); False: rejected.
    updates : window updates it triggered (a track end), in order.
    reason : why it was rejected (None when accepted or when the solver failed).
    error : message of the rejection (the error's text) or of the failure (``'<Type>: text'``);
        '' when accepted.
    solver_failed : a window update raised; the previous estimate stands.
    notes : warnings about the updates (failed or unconverged updates, autosave failures) and
        about held measurements rejected when they were finally tried.
    held : the measurement waits in the held queue (its source node is not known yet).
    admitted : every measurement the aligner took during this step, in order: this one (read
        backwards if its source was unknown and its destination known), held ones whose gap was
        filled, and bridges (kind ``'bridge'``).
    """

    accepted: bool
    updates: tuple[Any, ...] = ()
    reason: Reason | None = None
    error: str = ''
    solver_failed: bool = False
    notes: tuple[str, ...] = ()
    held: bool = False
    admitted: tuple[Measurement, ...] = ()


@dataclass(frozen=True)
class Health:
    """Diagnostics level: ``ok`` False means WARN (ERROR if ``error``: data is not being
    saved), with ``message`` saying why."""

    ok: bool
    message: str
    error: bool = False


@dataclass
class Counters:
    rejected: Counter = field(default_factory=Counter)
    received: int = 0
    accepted: int = 0
    updates: int = 0
    solver_failures: int = 0
    failed_updates: int = 0
    not_converged: int = 0
    persistence_errors: int = 0
    callback_seconds: float = 0.0
    callback_count: int = 0
    bridges: int = 0
    reversed: int = 0


@dataclass
class Taken:
    """What the aligner did during one step (several measurements with held ones)."""

    updates: list = field(default_factory=list)
    admitted: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    #: exceptions of window updates re-raised by a strict aligner (:class:`UpdateBug`)
    bugs: list = field(default_factory=list)


class UpdateBug(Exception):  # noqa: N818 - named for what it reports
    """A window update failed with an exception that is not a numerical failure (a bug) and
    the aligner is strict (``GA_ROS_STRICT_UPDATES``, set for the test suite;
    :attr:`TrackWindowAligner.strict <ga_ros.core.window.aligner.TrackWindowAligner.strict>`).

    Raised by the session at the end of the call, once everything is as without ``strict``:
    the aligner's state put back and the failure counted (``failed_updates``), the measurement
    that triggered the update taken and journaled (nothing lost), the traceback warned about.
    ``result`` is what the call would have returned (a :class:`StepOutput`, or the failed
    update of ``finish_track``); the exception is chained as ``__cause__``. Not a
    :class:`~ga_ros.errors.GaError`: a caller that handles those does not swallow it; the node
    logs it as an ERROR and goes on."""

    def __init__(self, message: str, result: Any) -> None:
        super().__init__(message)
        self.result = result
