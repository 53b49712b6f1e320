"""Whether the first measurement after a restart belongs to the resumed survey, and moving a
previous survey's state aside (ROS-free).

With persistence on by default, a node started again under the same name resumes the saved
state. That is right after a crash (the publishers re-deliver their history, or the survey goes
on), and wrong when another survey is played into it (``play_bag.launch.py`` run again on
another bag). The session decides on the first measurement it receives after resuming a
non-empty state (:func:`continues`), from the nodes the state holds (id, track, stamp), the
connections it holds (id pair, motion) and the measurements it holds waiting for their source
node:

* it is one of the held measurements (ids and stamp): the same survey;
* the state holds its connection (``src -> dst``): the same survey if the motion ``z`` is the
  same as one held (the survey re-delivered from its start, or a publisher's bounded history
  re-delivering its tail), or if it connects to the newest node with that node's track and
  stamp (another source's measurement of the newest motion, e.g. a second odometry), else
  another one;
* else its ``dst`` node is held: the same survey if the node's track is the measurement's and
  its stamp is too, or the measurement continues from its ``src`` as below (a new connection
  to a held node);
* else its ``src`` node is held: the same survey if the node's track is the measurement's
  ``src_track`` and its stamp is not later than the measurement's (the survey goes on);
* else (neither node held): the same survey only if the measurement is later than every held
  node (the survey goes on after a gap); an earlier one is another survey.

Another survey: the saved state's files move to a dated folder beside them
(:func:`move_survey_aside`, nothing deleted) and a fresh survey starts with that measurement.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.core.measurement import Measurement
from ga_ros.pipeline.journal import datum_path, journal_path
from ga_ros.pipeline.journal.state_files import snapshot_info_path
from ga_ros.safe_write import check_regular, sync_directory

#: Largest difference of a held connection's motion ``z`` (m, rad) from a re-delivered one.
Z_TOLERANCE = 1e-9


def continues(aligner: Any, m: Measurement,
              held: Iterable[Measurement] = ()) -> tuple[bool, str]:
    """Whether ``m`` (the first measurement after a restart) belongs to the survey whose state
    ``aligner`` holds, with the measurements ``held`` waiting for their source node (rules in
    the module doc), and why, in a few words."""
    for h in held:
        if (h.src_id, h.dst_id, h.stamp_ns) == (m.src_id, m.dst_id, m.stamp_ns):
            return True, f'the measurement {m.src_id}->{m.dst_id} is held (re-delivered)'
    path = aligner.corrected_path()
    ids = np.asarray(path.node_ids)
    if ids.size == 0:
        return True, 'the state is empty'

    def index_of(node_id: int) -> int | None:
        k = np.flatnonzero(ids == node_id)
        return int(k[0]) if k.size else None

    tracks, stamps = np.asarray(path.track_ids), np.asarray(path.stamps_ns)
    k_dst, k_src = index_of(m.dst_id), index_of(m.src_id)
    z = _held_motions(aligner, m.src_id, m.dst_id)
    if z.size:
        off = np.abs(z - np.asarray(m.z, dtype=float)).max(axis=1)
        if off.min() <= Z_TOLERANCE:
            return True, f'the connection {m.src_id}->{m.dst_id} is held (re-delivered)'
        if (k_dst == ids.size - 1 and tracks[k_dst] == m.dst_track
                and stamps[k_dst] == m.stamp_ns and tracks[k_src] == m.src_track):
            return True, (f'another measurement of the newest connection {m.src_id}->'
                          f'{m.dst_id} (another source)')
        return False, (f'the connection {m.src_id}->{m.dst_id} is held with another motion '
                       f'(differs by {off.min():.3g})')
    src_continues = (k_src is not None and tracks[k_src] == m.src_track
                     and stamps[k_src] <= m.stamp_ns)
    if k_dst is not None:
        if tracks[k_dst] != m.dst_track or not (stamps[k_dst] == m.stamp_ns or src_continues):
            return False, (f'node {m.dst_id} is held with track {tracks[k_dst]}, stamp '
                           f'{stamps[k_dst]} ns; the measurement says track {m.dst_track}, '
                           f'stamp {m.stamp_ns} ns')
        return True, f'node {m.dst_id} is held'
    if k_src is not None:
        if not src_continues:
            return False, (f'node {m.src_id} is held with track {tracks[k_src]}, stamp '
                           f'{stamps[k_src]} ns; the measurement starts from track '
                           f'{m.src_track} and is stamped {m.stamp_ns} ns')
        return True, f'it continues from node {m.src_id}'
    newest = int(stamps.max())
    if m.stamp_ns > newest:
        return True, 'it is later than every held node (the survey goes on after a gap)'
    return False, (f'neither node {m.src_id} nor {m.dst_id} is held and its stamp {m.stamp_ns} '
                   f'ns is not later than the newest held node ({newest} ns)')


def _held_motions(aligner: Any, src: int, dst: int) -> np.ndarray:
    """``(k, 6)`` the motions ``z`` of the held connections ``src -> dst`` (one per source that
    measured it; none if not held, or if the aligner does not list its connections)."""
    arrays = getattr(aligner, 'connection_arrays', None)
    if arrays is None:
        return np.zeros((0, 6))
    s, d, z = arrays()[:3]
    return np.asarray(z[(s == src) & (d == dst)], dtype=float).reshape(-1, 6)


def move_survey_aside(state_file: str | os.PathLike) -> Path:
    """Move a survey's state files (the snapshot, its journal, sidecar and datum; never its lock
    file, never a link or a foreign kind of file) into a new folder
    ``<state_file>.survey-<UTC time>`` beside them and return the folder. Nothing is deleted or
    overwritten."""
    state = Path(state_file)
    stamp = time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())
    for k in range(1000):
        folder = state.with_name(f'{state.name}.survey-{stamp}' + (f'.{k}' if k else ''))
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        break
    else:
        raise FileExistsError(f'cannot find a free name to move {state} aside')
    for p in (state, journal_path(state), snapshot_info_path(state), datum_path(state)):
        if check_regular(p):
            os.rename(p, folder / p.name)
    sync_directory(folder)
    sync_directory(state.parent)
    return folder
