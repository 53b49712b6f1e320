"""The fault catalogue (ga_ros/ros/fault_catalogue/, ``ga-ros bench faults``) in CI: the cases
that fit the time budget, on the small simulated survey, against live node processes started
with their default settings. Every case must keep every node of the reference path (the aligner
fed the clean measurements); the full-size runs are the benchmark's (docs/benchmarks.md,
"Faults against live nodes")."""

from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from ga_ros.domains import claimed  # noqa: E402
from ga_ros.ros import fault_catalogue as fc  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
#: Seconds a case may take (under the 600 s pytest timeout of setup.cfg): a wait still open
#: then fails at once, and the row names it, so a hang is a failure that says what it waited for.
BUDGET_S = 420.0

#: The cases CI runs. ``flood-queue`` (20,000 duplicates into a 1,000-deep queue) is left to
#: ``ga-ros bench faults --only flood-queue``: on a starved machine Fast DDS's shared-memory
#: delivery can stall for good mid-flood (about 1 run in 20 at load ~10; the case then fails
#: with "DDS delivery stalled"), a transport matter outside ga_ros that CI would report as ours.
CASES = ['kill-defaults', 'kill-recovery', 'sigterm-update', 'snapshot-random',
         'snapshot-empty', 'disk-full', 'bogus-path', 'hostile-services', 'flood-frame-ids',
         'kill-bounded-history', 'another-survey']


@pytest.mark.parametrize('name', CASES)
def test_no_node_lost(name: str) -> None:
    with claimed() as dom:       # machine-wide: no concurrent run hears this case's nodes
        row = fc.run_case(name, fc.catalogue()[name], None, dom, budget_s=BUDGET_S)
    if row.survived == 'skipped':
        pytest.skip(row.counted)
    assert row.survived.startswith('yes'), row
    assert row.expected > 0 and row.lost == 0, row
    if name.startswith(('kill', 'sigterm')) and name != 'kill-bounded-history':
        assert row.counted == 'play exit 0', row                 # everything delivered
    if name == 'disk-full':
        assert 'write errors ERROR' in row.counted and not row.counted.startswith('0 '), row
    if name == 'bogus-path':
        assert row.counted.startswith('1 log line; persistence off'), row
    if name == 'hostile-services':
        assert row.counted == '2/2 refused', row
    if name == 'flood-frame-ids':
        assert row.counted == '50/50 rejected, last_error 200 chars', row
    if name == 'kill-bounded-history':   # the older half lived only in the default state
        assert row.counted.endswith('duplicates; persistence on'), row
        assert int(row.counted.split()[0]) > 0, row              # history overlapped the state
    if name == 'another-survey':         # the first survey moved aside, the second afresh
        assert row.counted == '1 moved aside, 1 WARN line; play exit 0, 0', row
        assert row.note == f'first survey: {row.expected}/{row.expected} kept', row
