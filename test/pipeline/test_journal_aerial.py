"""Recovery from the journal alone on the bundled aerial bag (``bags/aerial_measurements``:
29,896 measurements, 5,100 nodes), ROS-free through the pipeline session with the default
settings: killed before and after the end of input, the snapshot lost, the recovered state is
the uninterrupted run's bit for bit."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from test_journal_events import assert_same_state

from ga_ros.core.window import AlignerConfig
from ga_ros.pipeline.journal import journal_path, recover
from ga_ros.pipeline.session import AlignmentSession, SessionConfig

BAG = Path(__file__).resolve().parents[2] / 'bags' / 'aerial_measurements'


def _bag_measurements() -> list:
    if not BAG.exists():
        pytest.skip(f'sample bag not generated ({BAG}: ga-ros make-bags)')
    from ga_ros.io.bag import BagReader
    from ga_ros.io.bag_messages import odometry_to_measurement

    with BagReader(BAG) as bag:
        return [odometry_to_measurement(m.msg) for m in bag.messages(['/ga/measurements'])]


def _alone(journal: Path, tmp: Path):
    """The state recovered from a copy of ``journal`` with no snapshot beside it."""
    tmp.mkdir()
    shutil.copyfile(journal, journal_path(tmp / 'state'))
    res = recover(tmp / 'state', AlignerConfig(), checkpoint=False)
    assert res.source == 'journal'
    return res


@pytest.mark.slow
@pytest.mark.timeout(2400)   # the whole survey twice over on a loaded 2-core machine
def test_the_aerial_bag_is_recovered_bit_for_bit_from_the_journal_alone(tmp_path):
    ms = _bag_measurements()
    assert len(ms) == 29896
    state = tmp_path / 'state'
    live = AlignmentSession(AlignerConfig(), SessionConfig(str(state)))
    assert live.resume() is None
    for m in ms:
        assert live.step(m).accepted
    before = tmp_path / 'before.journal'      # killed before the end of input
    shutil.copyfile(journal_path(state), before)
    res = _alone(before, tmp_path / 'a')
    assert 0 < res.records_replayed < 2000     # the open track's, after the base
    assert res.aligner.open_track == live.aligner.open_track is not None
    assert_same_state(res.aligner, live.aligner)
    res.aligner.close()
    live.finish_track('end_of_input')         # killed after the end of input
    live.journal.close()
    res = _alone(journal_path(state), tmp_path / 'b')
    assert res.aligner.stats.n_nodes == 5100
    assert res.aligner.open_track is None or res.aligner.open_track in res.aligner.state.finished
    assert_same_state(res.aligner, live.aligner)
    res.aligner.close()
    live.close()
