"""CPU time of this process and of every process it started (benchmarks count all the work:
the background refinement runs in a worker process by default).

Linux only (``/proc``); elsewhere the children still alive are not counted.
"""

from __future__ import annotations

import os
import resource
from pathlib import Path

_TICK = os.sysconf('SC_CLK_TCK')


def _descendants(pid: int | str = 'self') -> list[int]:
    """Pids of the live descendants of a process (from ``/proc/PID/task/*/children``)."""
    out: list[int] = []
    try:
        tasks = list(Path(f'/proc/{pid}/task').iterdir())
    except OSError:
        return out
    for task in tasks:
        try:
            kids = [int(p) for p in (task / 'children').read_text().split()]
        except OSError:
            continue
        for k in kids:
            out.append(k)
            out.extend(_descendants(k))
    return out


def _proc_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a live process (its threads included), 0 if it is gone."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _TICK  # utime, stime (fields 14, 15)


def all_cpu_seconds() -> float:
    """User + system CPU seconds of this process (every thread), of its children that ended
    and were waited for, and of its live descendants (e.g. the refinement worker)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    ended = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (own.ru_utime + own.ru_stime + ended.ru_utime + ended.ru_stime
            + sum(_proc_cpu_seconds(p) for p in _descendants()))


def rmse_cpu_cells(rmse_m: dict[str, float], cpu_s: dict[str, float],
                   columns: list[str] | tuple[str, ...]) -> str:
    """One table row's cells: per column ``RMSE (m) / CPU (s)`` (the CPU left blank where
    ``cpu_s`` has none; ``nan`` where the column did not run), each right-aligned in 14."""
    cells = []
    for c in columns:
        r, cpu = rmse_m.get(c, float('nan')), cpu_s.get(c)
        cells.append(f'{r:7.3f}' + (f' /{cpu:5.2f}' if cpu is not None else '       '))
    return '  '.join(f'{c:>14s}' for c in cells)
