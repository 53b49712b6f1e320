"""The catalogue of fault cases by name, the run of one case, and the table of the rows."""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

from ga_ros.ros.fault_catalogue.crash_cases import (
    case_damaged_snapshot,
    case_disk_full,
    case_ended_snapshot_lost,
    case_foreign,
    case_kill_defaults,
    case_kill_recovery,
    case_kill_state,
    case_sigterm,
    case_state_path,
)
from ga_ros.ros.fault_catalogue.input_cases import (
    case_bad_input,
    case_flood_frame_ids,
    case_flood_queue,
)
from ga_ros.ros.fault_catalogue.peer_cases import (
    case_finish_race,
    case_hostile_services,
    case_idle_timeout,
    case_play_clock_late_node,
    case_play_early,
    case_reset_by_peer,
    case_sigterm_startup,
)
from ga_ros.ros.fault_catalogue.session_cases import case_journal_only_fixes
from ga_ros.ros.fault_catalogue.state_cases import (
    case_another_survey,
    case_bounded_history,
    case_disk_full_then_space,
    case_two_nodes_one_state,
)
from ga_ros.ros.fault_catalogue.survey import Case, Ctx, Row, Survey, small_survey


def catalogue() -> dict[str, Case]:
    """Every case by its short name, in the order of the table."""
    cases: dict[str, Case] = {}
    names = ['nan', 'negative-cov', 'tiny-cov', 'huge-cov', 'self-loop', 'foreign-frame',
             'duplicate', 'out-of-order', 'track-jump', 'node-id-2^53']
    labels = ['NaN pose', 'negative covariance', 'tiny covariance 1e-20 I',
              'huge covariance 1e308', 'self-loop', 'foreign frame id', 'duplicate',
              'out of order', 'track id jump 1e6', 'node id 2^53']
    for k, (name, label) in enumerate(zip(names, labels)):
        cases[name] = case_bad_input(label, k)
    cases.update({
        'kill-defaults': case_kill_defaults,
        'kill-state': case_kill_state,
        'kill-recovery': case_kill_recovery,
        'sigterm-update': case_sigterm,
        'snapshot-empty': case_damaged_snapshot('empty'),
        'snapshot-random': case_damaged_snapshot('random'),
        'snapshot-truncated': case_damaged_snapshot('truncated'),
        'journal-header': case_damaged_snapshot('header'),
        'end-snapshot-lost': case_ended_snapshot_lost,
        'disk-full': case_disk_full,
        'read-only-dir': case_state_path('read-only directory'),
        'bogus-path': case_state_path('path under a regular file'),
        'foreign-state': case_foreign('foreign text file'),
        'symlink-state': case_foreign('symlink'),
        'hostile-services': case_hostile_services,
        'reset-by-peer': case_reset_by_peer,
        'finish-race': case_finish_race,
        'idle-timeout': case_idle_timeout,
        'flood-frame-ids': case_flood_frame_ids,
        'flood-queue': case_flood_queue,
        'play-early': case_play_early,
        'sigterm-startup': case_sigterm_startup,
        'kill-bounded-history': case_bounded_history,
        'two-nodes-one-state': case_two_nodes_one_state,
        'disk-full-then-space': case_disk_full_then_space,
        'play-clock-late-node': case_play_clock_late_node,
        'journal-only-fixes': case_journal_only_fixes,
        'another-survey': case_another_survey,
    })
    return cases


def run_case(name: str, case: Case, survey: Survey | None, dom: int,
             bag: Path | None = None, budget_s: float | None = None) -> Row:
    """Run one case in a fresh temporary directory (a failing case is a row, not a crash);
    ``survey`` None: the small simulated one, written in that directory. ``budget_s``: the
    seconds the case may take; a wait still open then fails at once (an ``ERROR`` row naming
    what it waited for), so a case that hangs ends in bounded time."""
    with tempfile.TemporaryDirectory(prefix='ga_fault_') as tmp:
        work = Path(tmp)
        home = os.environ.get('ROS_HOME')
        os.environ['ROS_HOME'] = str(work / 'ros_home')  # the nodes' default state: the case's
        try:
            deadline = math.inf if budget_s is None else time.monotonic() + budget_s
            return case(Ctx(work, dom, survey or small_survey(work), deadline))
        except Exception as exc:  # noqa: BLE001 - a failed case is a row
            return Row(name, 'ERROR', '-', 0, 0, note=f'{type(exc).__name__}: {exc}'[:160])
        finally:
            if home is None:
                os.environ.pop('ROS_HOME', None)
            else:
                os.environ['ROS_HOME'] = home


def table(rows: list[Row]) -> str:
    """The Markdown table of the rows."""
    lines = ['| case | survived | counted | nodes expected | nodes kept | lost | '
             'recover (s) | note |', '|---|---|---|---:|---:|---:|---:|---|']
    for r in rows:
        rec = f'{r.recover_s:.1f}' if r.recover_s is not None else '-'
        lines.append(f'| {r.name} | {r.survived} | {r.counted} | {r.expected} | {r.kept} | '
                     f'{r.lost} | {rec} | {r.note} |')
    return '\n'.join(lines)
