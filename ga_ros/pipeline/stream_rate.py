"""Rate and loss of a sensor stream, estimated from its header stamps (ROS-free).

A camera or an odometry driver publishes at a steady rate; a message lost in transport (a
best-effort subscription, a full queue) leaves a gap in the stamps the receiver sees. One
:class:`StreamMonitor` per input estimates the period as the median of the recent stamp steps
and counts, for every step longer than ``gap_factor`` times that period, the messages that
should have been there::

    lost += round(step / period) - 1

so that ``expected = received + lost`` and the loss fraction is ``lost / expected``. The first
``min_steps`` steps only seed the median (they are checked once it is known). Stamps that do
not advance (repeats, steps back) are counted apart and not used for the rate.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ga_ros.errors import InputError


@dataclass(frozen=True)
class StreamReport:
    """What a stream monitor saw.

    Attributes
    ----------
    received : messages handed to the monitor.
    lost : messages missing from the stamp sequence (gaps), estimated.
    expected : ``received + lost``.
    rate_hz : estimated publication rate (1 / median stamp step), Hz; NaN before two stamps.
    gaps : stamp steps counted as gaps.
    not_advancing : stamps equal to or older than the previous one.
    """

    received: int
    lost: int
    expected: int
    rate_hz: float
    gaps: int
    not_advancing: int

    @property
    def loss_fraction(self) -> float:
        """``lost / expected`` (0 when nothing was expected)."""
        return self.lost / self.expected if self.expected else 0.0

    def values(self, prefix: str = '') -> dict[str, object]:
        """Diagnostics key/values (``<prefix>received``, ``expected``, ``lost``, ``rate_hz``)."""
        return {f'{prefix}received': self.received, f'{prefix}expected': self.expected,
                f'{prefix}lost': self.lost, f'{prefix}rate_hz': round(self.rate_hz, 3)
                if np.isfinite(self.rate_hz) else 'unknown'}


class StreamMonitor:
    """Rate estimate and gap count of one stream (module docstring).

    Parameters
    ----------
    gap_factor : a stamp step longer than this many median periods is a gap (> 1).
    window : number of recent stamp steps whose median is the period.
    min_steps : steps needed before gaps are judged (earlier ones are judged then).
    """

    def __init__(self, gap_factor: float = 1.5, window: int = 50, min_steps: int = 5) -> None:
        if not gap_factor > 1.0:
            raise InputError(f'gap_factor must be > 1, got {gap_factor}')
        if window < 1 or min_steps < 1:
            raise InputError('window and min_steps must be at least 1')
        self.gap_factor = float(gap_factor)
        self.min_steps = int(min_steps)
        self._steps: deque[int] = deque(maxlen=int(window))
        self._unjudged: list[int] = []
        self._last_ns: int | None = None
        self.received = 0
        self.lost = 0
        self.gaps = 0
        self.not_advancing = 0

    def add(self, stamp_ns: int) -> int:
        """Record one message stamped ``stamp_ns`` (ns); returns the messages found lost."""
        self.received += 1
        stamp_ns = int(stamp_ns)
        last, self._last_ns = self._last_ns, stamp_ns
        if last is None:
            return 0
        step = stamp_ns - last
        if step <= 0:
            self.not_advancing += 1
            self._last_ns = max(last, stamp_ns)
            return 0
        self._steps.append(step)
        if len(self._steps) < self.min_steps:
            self._unjudged.append(step)
            return 0
        todo, self._unjudged = self._unjudged + [step], []
        return sum(self._judge(s) for s in todo)

    def period_ns(self) -> float:
        """Median of the recent stamp steps, ns (NaN before the first step)."""
        return float(np.median(self._steps)) if self._steps else float('nan')

    def _judge(self, step: int) -> int:
        period = self.period_ns()
        if not step > self.gap_factor * period:
            return 0
        missing = max(int(round(step / period)) - 1, 1)
        self.gaps += 1
        self.lost += missing
        return missing

    def report(self) -> StreamReport:
        """The counts so far."""
        period = self.period_ns()
        rate = 1e9 / period if np.isfinite(period) and period > 0 else float('nan')
        return StreamReport(self.received, self.lost, self.received + self.lost, rate,
                            self.gaps, self.not_advancing)


class FrameMonitor:
    """Frames of a multi-stream sensor (a stereo camera: left and right images at the same
    stamps) announced by any stream, against the frames that arrived complete (a pair).

    A frame is *announced* when any of its messages arrives (stamps within ``tolerance_ns`` are
    one frame) and *complete* when the caller pairs it. Frames are settled in stamp order once
    the newest announced stamp is ``settle_ns`` past them (or on :meth:`flush`): an incomplete
    one is lost (one of its messages was), and frames of which no message arrived at all are
    counted from the gaps of the settled stamps (:class:`StreamMonitor`). A frame completed
    after it was settled as lost (a very late message) is moved back to the received ones.

    Parameters
    ----------
    tolerance_ns : largest stamp difference of two messages of one frame (the pairing
        tolerance), ns.
    settle_ns : stamp time after which an incomplete frame is lost, ns.
    gap_factor : as :class:`StreamMonitor`.
    """

    def __init__(self, tolerance_ns: int, settle_ns: int = 1_000_000_000,
                 gap_factor: float = 1.5) -> None:
        self.tolerance_ns = int(tolerance_ns)
        self.settle_ns = int(settle_ns)
        self._open: dict[int, bool] = {}            # frame stamp -> complete
        self._lost_recent: deque[int] = deque(maxlen=1000)
        self._gaps = StreamMonitor(gap_factor)
        self._newest: int | None = None
        self.complete = 0
        self.incomplete = 0

    def _frame(self, stamp_ns: int) -> int | None:
        return next((s for s in self._open if abs(s - stamp_ns) <= self.tolerance_ns), None)

    def announce(self, stamp_ns: int) -> None:
        """A message of the frame stamped ``stamp_ns`` arrived."""
        stamp_ns = int(stamp_ns)
        if self._frame(stamp_ns) is None:
            if any(abs(s - stamp_ns) <= self.tolerance_ns for s in self._lost_recent):
                return                              # of a frame already settled as lost
            self._open[stamp_ns] = False
        self._newest = stamp_ns if self._newest is None else max(self._newest, stamp_ns)
        self._settle(self._newest - self.settle_ns)

    def completed(self, stamp_ns: int) -> None:
        """The frame stamped ``stamp_ns`` arrived complete."""
        stamp_ns = int(stamp_ns)
        late = next((s for s in self._lost_recent if abs(s - stamp_ns) <= self.tolerance_ns),
                    None)
        if late is not None:                         # settled as lost, then completed
            self._lost_recent.remove(late)
            self.incomplete -= 1
            self.complete += 1
            return
        frame = self._frame(stamp_ns)
        if frame is None:
            self.announce(stamp_ns)
            frame = self._frame(stamp_ns)
        if frame is not None and not self._open[frame]:
            self._open[frame] = True

    def flush(self) -> None:
        """Settle every open frame (e.g. when the input has been idle)."""
        if self._open:
            self._settle(max(self._open) + 1)

    def _settle(self, before_ns: int) -> None:
        for stamp in sorted(s for s in self._open if s < before_ns):
            if self._open.pop(stamp):
                self.complete += 1
            else:
                self.incomplete += 1
                self._lost_recent.append(stamp)
            self._gaps.add(stamp)

    def report(self) -> StreamReport:
        """Settled frames: ``received`` complete, ``lost`` incomplete or never announced."""
        g = self._gaps.report()
        lost = self.incomplete + g.lost
        return StreamReport(self.complete, lost, self.complete + lost, g.rate_hz, g.gaps,
                            g.not_advancing)
