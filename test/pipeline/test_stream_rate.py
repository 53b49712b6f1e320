"""Rate / gap counting of a sensor stream (ga_ros.pipeline.stream_rate)."""

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.pipeline.stream_rate import StreamMonitor


def _stamps(rate_hz: float, n: int, rng: np.random.Generator, jitter_s: float) -> np.ndarray:
    t = np.arange(n) / rate_hz + rng.normal(0.0, jitter_s, n)
    return np.round(t * 1e9).astype(np.int64) + 1_700_000_000 * 10**9


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_lost_messages_are_counted_from_stamp_gaps(seed):
    rng = np.random.default_rng(seed)
    stamps = _stamps(20.0, 400, rng, jitter_s=0.002)
    keep = np.ones(len(stamps), bool)
    # drop single messages and runs of 2-4, never the first 10 (the seeding steps are judged
    # later anyway) and never adjacent runs
    for start in rng.choice(np.arange(10, 390, 8), size=25, replace=False):
        keep[start:start + int(rng.integers(1, 5))] = False
    mon = StreamMonitor()
    for s in stamps[keep]:
        mon.add(int(s))
    r = mon.report()
    assert r.received == keep.sum()
    assert r.lost == (~keep[:np.flatnonzero(keep)[-1]]).sum()
    assert r.expected == r.received + r.lost
    assert r.rate_hz == pytest.approx(20.0, rel=0.02)


def test_a_steady_stream_loses_nothing_and_repeats_are_counted_apart():
    mon = StreamMonitor()
    for k in range(100):
        mon.add(k * 50_000_000)
        if k == 40:
            mon.add(k * 50_000_000)       # a repeated stamp
    r = mon.report()
    assert (r.received, r.lost, r.gaps, r.not_advancing) == (101, 0, 0, 1)
    assert r.loss_fraction == 0.0


def test_gaps_in_the_seeding_steps_are_judged_once_the_rate_is_known():
    mon = StreamMonitor(min_steps=5)
    period = 100_000_000
    stamps = [k * period for k in (0, 1, 4, 5, 6, 7, 9, 10, 11, 12)]   # 2 lost, then 1
    for s in stamps:
        mon.add(s)
    assert mon.report().lost == 3
    assert mon.report().gaps == 2


def test_bad_settings_are_refused():
    with pytest.raises(InputError):
        StreamMonitor(gap_factor=1.0)
    with pytest.raises(InputError):
        StreamMonitor(window=0)


def test_frames_lost_on_one_side_or_both_are_counted_once():
    from ga_ros.pipeline.stream_rate import FrameMonitor

    rng = np.random.default_rng(4)
    period, n = 50_000_000, 300
    mon = FrameMonitor(tolerance_ns=5_000_000)
    truth_complete = 0
    for k in range(n):
        s = 10**18 + k * period
        left, right = rng.random() > 0.2, rng.random() > 0.1
        if 100 <= k < 104:
            left = right = False                     # a run of frames of which nothing came
        if k in (0, n - 1):
            left = right = True                      # the ends are seen
        if left:
            mon.announce(s + 1000)                   # the right camera 1 us later
        if right:
            mon.announce(s + 2000)
        if left and right:
            mon.completed(s + 1000)
            truth_complete += 1
    mon.flush()
    r = mon.report()
    assert r.received == truth_complete
    assert r.received + r.lost == n
    assert r.rate_hz == pytest.approx(20.0)


def test_a_frame_completed_after_it_was_settled_is_received_not_lost():
    from ga_ros.pipeline.stream_rate import FrameMonitor

    mon = FrameMonitor(tolerance_ns=10, settle_ns=100)
    mon.announce(0)
    for k in range(1, 6):
        mon.announce(k * 50)
        mon.completed(k * 50)
    assert mon.report().lost == 1 and mon.report().received == 2
    mon.completed(0)                                  # the late partner of frame 0
    mon.flush()
    r = mon.report()
    assert (r.received, r.lost) == (6, 0)
