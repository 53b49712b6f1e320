"""Diagnostics of the alignment node: the key/values, their level and message, and the
count of measurements lost before the node took them (mixin of
:class:`~ga_ros.ros.alignment_node.AlignmentNode`)."""


from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus

from ga_ros.pipeline.session import bounded
from ga_ros.ros import conversions as conv


class AlignmentDiagnostics:
    """Diagnostics of :class:`~ga_ros.ros.alignment_node.AlignmentNode`."""

    def diagnostic_values(self) -> dict[str, object]:
        """The session's diagnostics key/values, with the last update's quality figures."""
        values = self.session.diagnostic_values()
        values['measurements_lost_in_queue'] = self.queue_loss.total
        values.update(self.odom.diagnostic_values())
        values.update(conv.quality_values(getattr(self.session.last_update, 'quality', None)))
        book = getattr(self.session.aligner, 'online_variance', None)
        if book is not None:  # the variance factor per source (variance_components 'apply')
            values.update(book.diagnostic_values())
        cal = getattr(self.session.aligner, 'online_calibration', None)
        if cal is not None:  # the odometry's corrections estimated online (calibrate)
            values.update(cal.diagnostic_values())
        for name, sub in getattr(self, 'sensor_subscriptions', {}).items():
            values[f'qos/{name}'] = (sub.reliability if sub.decided
                                     else 'best_effort (auto: no publisher yet)')
        return values

    def _publish_diagnostics(self) -> None:
        try:
            self.queue_loss.publishers = self.sub.get_publisher_count()
            values = self.diagnostic_values()
            health = self.session.health()
        except Exception as exc:  # noqa: BLE001 - diagnostics must not stop the node
            values = {'error': bounded(str(exc))}
            health = None
        problems = [health.message] if health is not None and not health.ok else []
        if self.odom.warning:
            problems.append(self.odom.warning)
        book = getattr(self.session.aligner, 'online_variance', None)
        if book is not None:
            problems += book.warnings()  # "odom1's stated covariance is 4x too small ..."
        if self.tf_contested_by:
            s = self.settings
            values['tf_contested_by'] = self.tf_contested_by
            problems.append(f'another node publishes {self.tf_contested_by} -> {s.odom_frame}'
                            + ('' if s.publish_tf_when_contested else '; ours not published'))
        for name, mon in self.input_streams.items():
            r = mon.report()
            values.update(r.values(f'input/{name}/'))
            if r.loss_fraction > self.settings.loss_warn_fraction:
                problems.append(f'{name}: {r.lost} of {r.expected} messages lost')
        level, message = DiagnosticStatus.OK, 'ok'
        error = health is not None and health.error
        if self.queue_loss.total:
            problems.append(f'{self.queue_loss.total} measurements lost by a full subscription '
                            'queue')
        if self.incompatible_publishers:
            error = True
            problems.append('a publisher with an incompatible QoS is not received')
        if problems:
            level = DiagnosticStatus.ERROR if error else DiagnosticStatus.WARN
            message = '; '.join(problems)
        level_int = level[0] if isinstance(level, bytes) else int(level)
        self.pub_diag.publish(conv.diagnostics_msg(
            f'{self.get_fully_qualified_name()}: global alignment', 'ga_ros', values,
            self.get_clock().now().nanoseconds, level=level_int, message=message))


@dataclass
class QueueLoss:
    """Measurements lost before the node took them, each counted once. Two witnesses see the
    losses: DDS's message-lost events and gaps in the publisher's sequence numbers (a full
    ``KEEP_LAST`` subscription queue drops the oldest message; the numbers are per publisher,
    so gaps are counted only while exactly one publisher is matched). Both report the same
    samples when both see them, so the total is the larger of the two, not their sum.

    Attributes
    ----------
    lost_events : messages DDS reported lost.
    gaps : messages missing between two consecutive sequence numbers taken.
    publishers : matched publishers (refreshed by the diagnostics timer).
    """

    lost_events: int = 0
    gaps: int = 0
    publishers: int = 1
    _last: int | None = None

    @property
    def total(self) -> int:
        """Messages known to be lost (each once: the larger of the two witnesses' counts)."""
        return max(self.lost_events, self.gaps)

    def seen(self, info: Any) -> None:
        """Note the message info (``publication_sequence_number``) of a message taken."""
        try:
            seq = int(info['publication_sequence_number'])
        except (KeyError, TypeError, ValueError):
            return
        if seq <= 0 or seq >= 2**63 or self.publishers != 1:  # unsupported, or several
            self._last = None
            return
        if self._last is not None and seq > self._last + 1:
            self.gaps += seq - self._last - 1
        self._last = seq


@dataclass
class RejectionLog:
    """Rejections not logged yet: how many, and the last one (source and target frame, reason,
    error)."""

    pending: int = 0
    last: tuple[Any, ...] = ()


