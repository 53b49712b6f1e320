"""Log lines of bounded length (ga_ros.ros.bounded_log), the rejection summary with a
megabyte-long frame id, and measurements lost in the queue counted once
(ga_ros.ros.alignment_diagnostics.QueueLoss)."""

from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from rclpy.node import Node  # noqa: E402

from ga_ros.ros.alignment_diagnostics import QueueLoss  # noqa: E402
from ga_ros.ros.bounded_log import (  # noqa: E402
    MAX_LOG_LINE_CHARS,
    BoundedLogger,
    BoundedLogging,
    bounded_line,
    shown_id,
)
from ga_ros.ros.harness import domain_id, ros_context  # noqa: E402


class _Sink:
    """A logger that records what it is given."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str, dict]] = []

    def __getattr__(self, level: str):
        return lambda message, **kw: self.lines.append((level, message, kw)) or True


def test_a_long_line_is_cut_with_its_length_and_a_short_one_kept() -> None:
    sink = _Sink()
    log = BoundedLogger(sink)
    huge = 'x' * 1_000_000
    log.warning(f'rejected {huge}', throttle_duration_sec=2.0)
    log.info('short')
    (lvl, text, kw), (lvl2, text2, _) = sink.lines
    assert lvl == 'warning' and kw == {'throttle_duration_sec': 2.0}
    assert len(text) == MAX_LOG_LINE_CHARS and text.endswith(f'[cut: {1_000_009} chars]')
    assert text.startswith('rejected xxx')
    assert (lvl2, text2) == ('info', 'short')
    assert bounded_line('abc', 3) == 'abc' and len(bounded_line('abcd' * 100, 50)) == 50


def test_a_long_id_is_shown_cut_with_its_length() -> None:
    assert shown_id('base_link') == "'base_link'"
    s = shown_id('f' * 1_048_576)
    assert len(s) < 100 and s.endswith('... (1048576 chars)')


def test_a_node_logs_bounded_lines_keyed_by_its_own_call_site() -> None:
    """rclpy throttles per calling line: through the bounded logger the caller it records
    is this test, not the wrapper."""

    class _Node(BoundedLogging, Node):
        pass

    with ros_context(domain_id(7)) as ctx:
        node = _Node('bounded_log_test', context=ctx)
        try:
            logger = node.get_logger()
            assert isinstance(logger, BoundedLogger) and node.get_logger() is logger
            logger.warning('x' * 10_000, throttle_duration_sec=60.0)
            inner = logger._logger
            files = {c.file_path for c in inner.contexts}
            assert files == {__file__}, files
        finally:
            node.destroy_node()


def test_a_loss_seen_by_both_witnesses_is_counted_once() -> None:
    q = QueueLoss()
    for seq in (1, 2, 3, 8, 9, 20):        # 4 + 10 missing
        q.seen({'publication_sequence_number': seq})
    assert q.gaps == 14
    q.lost_events += 14                     # DDS reports the same samples lost
    assert q.total == 14
    q.lost_events += 3                      # more than the gaps show (e.g. a second publisher)
    assert q.total == 17
