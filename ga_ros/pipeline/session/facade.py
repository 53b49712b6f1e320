"""The session facade: :class:`AlignmentSession`, one call per measurement (the module doc of
:mod:`ga_ros.pipeline.session`)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.fixes import FixTerm
from ga_ros.core.gaps import GapHealer, Route, fingerprint, reversed_measurement
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import save_state, state_chunks
from ga_ros.errors import GaError, InputError, PersistenceError, Reason, SolverError
from ga_ros.pipeline.journal import (
    DROPPED,
    HELD,
    REVERSED,
    Datum,
    MeasurementJournal,
    RecoveryResult,
    TrackEnd,
    clear_state,
    journal_path,
    recover,
)
from ga_ros.pipeline.journal.lock import StateLock
from ga_ros.pipeline.journal.records import DATUM_KIND, KIND_MASK, MAP_ODOM_KIND, MapOdom, is_event
from ga_ros.pipeline.journal.recovery import check_state_path
from ga_ros.pipeline.path_mirror import newest_not_in_track
from ga_ros.pipeline.session.config import SessionConfig
from ga_ros.pipeline.session.diagnostics import diagnostic_values, health
from ga_ros.pipeline.session.outputs import (
    MAX_ERROR_CHARS,
    MAX_FAILURES_LOGGED,
    MAX_TRACEBACK_CHARS,
    Counters,
    Health,
    StepOutput,
    Taken,
    UpdateBug,
    Warn,
    bounded,
)
from ga_ros.pipeline.session.rejections import refused, rejection_reason, unknown_source
from ga_ros.pipeline.session.restore import how, rebuild_gaps
from ga_ros.pipeline.session.survey_identity import continues, move_survey_aside


class AlignmentSession:
    """Aligner + rejection counters + journal/snapshot recovery + diagnostics.

    Parameters
    ----------
    config : the aligner's configuration.
    session : state file and autosave (:class:`SessionConfig`).
    warn : called with warnings (e.g. a snapshot that could not be used); default: ignored.
    aligner : the aligner to drive (default: a new :class:`TrackWindowAligner` of ``config``);
        the replay passes its own (e.g. anchored at the ground truth, or the batch aligner).
    """

    def __init__(self, config: AlignerConfig | None = None,
                 session: SessionConfig | None = None, warn: Warn | None = None,
                 aligner: Any = None) -> None:
        self.config = config or AlignerConfig()
        self.session = session or SessionConfig()
        self.warn: Warn = warn or (lambda text: None)
        self.aligner = aligner if aligner is not None else TrackWindowAligner(self.config)
        self.gaps = GapHealer(self.session.gaps)
        self.counts = Counters()
        self.last_update: Any = None
        self.last_error = ''
        self.last_persistence_error = ''
        #: The last write error while writes fail ('' once a write succeeds again).
        self.persistence_failing = ''
        #: Inputs applied but not saved (their journal write failed) since the last snapshot.
        self.unsaved = 0
        #: Why persistence was switched off at start ('' if it was not).
        self.persistence_off = ''
        #: Why no snapshot is written (the state path holds a file that is not ga_ros's; the
        #: journal goes on, recovery replays it all) ('' if snapshots are written).
        self.snapshots_off = ''
        self._next_sync = 0.0
        #: The failure texts whose traceback was warned about (:meth:`_log_failure`).
        self._failures_logged: set[str] = set()
        #: The map frame's datum ``(lat_deg, lon_deg, alt_m)`` the journal held at the last
        #: resume or load (``None`` without one).
        self.datum: tuple[float, float, float] | None = None
        #: The journal's last ``map -> odom`` record (:meth:`journal_map_odom`) at the last
        #: resume or load, with its node and that node's pose then (what the measured bridge
        #: across a restart checks, :mod:`~ga_ros.pipeline.session.restore`), or the one the
        #: running inputs' own keyframe of the loaded newest node gives (set by
        #: :func:`~ga_ros.pipeline.session.restore.continue_inputs`); ``None``: none, or not
        #: restored. Its ``T_map_odom``: :attr:`map_odom`.
        self.map_odom_entry: MapOdom | None = None
        #: How the first new node after a restart (or a load) was bridged: ``''`` (no
        #: restart), ``'pending'`` (not yet), ``'measured'`` (the odometry went on) or
        #: ``'guessed: <why>'``. A fact of this start, not kept in the state (the journal keeps
        #: the bridges themselves: :meth:`~ga_ros.core.gaps.GapHealer.unjoined`).
        self.restart_bridge = ''
        #: Opened by :meth:`resume` (after recovery has checked and repaired the files).
        self.journal: MeasurementJournal | None = None
        #: The state file's lock, taken by :meth:`resume` (``SessionConfig.lock_owner``).
        self.lock: StateLock | None = None
        #: A non-empty state was resumed and no measurement has come since: the first one
        #: decides whether it is the same survey (:mod:`.survey_identity`).
        self.survey_check_pending = False
        #: The folder the previous survey's state was moved to when another survey's first
        #: measurement came (``None`` otherwise; the node takes it and resets its outputs).
        self.previous_survey: Path | None = None
        #: A node new to the survey that nothing else will introduce (:meth:`bridge_at_once`;
        #: ``None``: none).
        self._bridge_now: int | None = None
        self._bridge_node = -1
        #: The measurement of the bridge across a restart (:meth:`bridge_at_once`).
        self._measure_bridge: Callable[[int, int, int, int], Measurement | str] | None = None
        self._map_odom_journaled: FloatArray | None = None

    # ------------------------------------------------------------------ one measurement
    def step(self, m: Measurement) -> StepOutput:
        """Add one measurement to the aligner (and the journal), or hold it until its source
        node is known (:mod:`ga_ros.core.gaps`).

        Never raises on bad input: a rejection is counted by reason and returned; a failing
        window update is counted and returned (the aligner keeps its previous estimate).
        """
        t0 = time.perf_counter()
        if self.survey_check_pending:
            self._check_survey(m)
        self.counts.received += 1
        gaps = self.gaps
        route = gaps.route(m)
        if route in (Route.HOPELESS, Route.DUPLICATE):
            exc = refused(m, route)
            return StepOutput(False, reason=self.reject(exc), error=str(exc))
        taken = Taken()
        if route is Route.HOLD:
            gaps.hold(m)
            self._journal(m, HELD)
            now = m.src_id == self._bridge_now
            if now:
                self._bridge_now = None
            if now or gaps.overdue():
                self._drain(taken, flush=now)
            return self._output(taken, True, held=True)
        try:
            self._take(m, taken, route is Route.REVERSE)
        except InputError as exc:
            return StepOutput(False, reason=self.reject(exc), error=str(exc))
        except GaError as exc:  # a failed window update: the previous estimate stands
            self.solver_failed(exc)
            return StepOutput(False, error=f'{type(exc).__name__}: {exc}', solver_failed=True)
        gaps.arrived(m)
        if gaps.held:
            self._drain(taken)
        if not taken.updates:
            self.counts.callback_seconds += time.perf_counter() - t0
            self.counts.callback_count += 1
        return self._output(taken, True)

    def _check_survey(self, m: Measurement) -> None:
        """The first measurement after resuming a non-empty state: if it does not belong to
        that survey (:func:`~ga_ros.pipeline.session.survey_identity.continues`), move the saved
        state aside to a dated folder (:attr:`previous_survey`), say so (``warn``) and start a
        fresh survey. A state that cannot be moved is kept and resumed (an error line)."""
        self.survey_check_pending = False
        same, why = continues(self.aligner, m, (h.m for h in self.gaps.held))
        if same or not self.session.state_file:
            return
        path = self.session.state_file
        old_nodes = self.n_nodes()
        if self.journal is not None:
            self.journal.close()
        try:
            folder = move_survey_aside(path)
        except (OSError, GaError) as exc:
            if self.journal is not None:
                self.journal.open()
            self.persistence_failed(f'state file {path}: a different survey came but it could '
                                    f'not be moved aside ({exc}): the new survey is added to '
                                    'the old one')
            return
        self.previous_survey = folder
        if self.journal is not None:
            self.journal = MeasurementJournal(journal_path(path))
            self.journal.open()
        self._fresh_estimator()
        self.warn(f'a different survey: its first measurement {m.src_id}->{m.dst_id} (track '
                  f'{m.dst_track}, stamp {m.stamp_ns} ns) does not belong to the saved one '
                  f'({why}); the saved survey ({old_nodes} nodes) was moved to {folder}/ and a '
                  'new survey starts')

    def next_ids(self) -> tuple[int, int]:
        """``(node id, track id)`` after every node and track the state holds (the aligner's
        and the held measurements'); ``(0, 0)`` for an empty state: where an input restarted on
        this state numbers its keyframes on
        (:meth:`InputFrontEnd.continue_from <ga_ros.pipeline.inputs.InputFrontEnd.continue_from>`).
        """
        path = self.aligner.corrected_path()
        nodes = [int(np.max(path.node_ids))] if len(path.node_ids) else []
        tracks = [int(np.max(path.track_ids))] if len(path.track_ids) else []
        for h in self.gaps.held:
            nodes += [int(h.m.src_id), int(h.m.dst_id)]
            tracks += [int(h.m.src_track), int(h.m.dst_track)]
        return (max(nodes) + 1 if nodes else 0), (max(tracks) + 1 if tracks else 0)

    def bridge_at_once(self, node_id: int,
                       measure: Callable[[int, int, int, int], Measurement | str] | None = None
                       ) -> None:
        """Node ``node_id`` is new to the survey and no measurement will ever join it to the
        nodes before (an input restarted on a restored state numbers on from :meth:`next_ids`):
        the first measurement from it is bridged as soon as it is held, instead of after the
        healer's waits. ``measure(from node, from track, node_id, its track)`` gives the
        bridge's measurement (the odometry's motion across the restart,
        :func:`~ga_ros.pipeline.session.restore.measured_bridge`), or why there is none: the
        healer's guess (:meth:`~ga_ros.core.gaps.GapHealer.bridge_to`) then, with a warning.
        A fresh survey forgets it."""
        self._bridge_now = self._bridge_node = int(node_id)
        self._measure_bridge = measure

    def add_fix(self, term: FixTerm, C_offset: FloatArray | None = None) -> None:
        """Add an absolute fix to the aligner (``add_fix``) and, once accepted, to the gap healer
        (the fix joins the piece of its node, :meth:`~ga_ros.core.gaps.GapHealer.anchor`) and to
        the journal (with the information it entered with, so a recovery replays the same term
        between the same measurements).

        Raises
        ------
        InputError
            The aligner refused it (unknown or frozen node; counted there by reason).
        """
        info = self.aligner.add_fix(term, C_offset)
        self.gaps.anchor(term.node_id)  # the fix joins the piece of its node
        if self.journal is None:
            return
        try:
            self.journal.append_fix(term, info, C_offset)
            self.sync()
            self.persistence_failing = ''
        except OSError as exc:  # as for a measurement (_journal): counted, warned, applied
            self.persistence_failed(f'journal {self.journal.path}: fix applied but NOT '
                                    f'journaled ({exc})')

    @property
    def newest_node_id(self) -> int | None:
        """The aligner's newest node (``None`` before the first measurement)."""
        return self.aligner.newest_node_id

    def flush_gaps(self) -> StepOutput:
        """Admit every held measurement now, bridging the gaps that are still open (the track
        or the stream ends; :meth:`finish_track` calls it first)."""
        taken = Taken()
        self._drain(taken, flush=True)
        return self._output(taken, True)

    def _output(self, taken: Taken, accepted: bool, held: bool = False) -> StepOutput:
        """The step's output (its updates counted); raises :class:`UpdateBug` (carrying it)
        if a strict aligner re-raised a bug of one of them."""
        done = tuple(u for u in taken.updates if u is not None)
        notes = tuple(taken.notes) + (tuple(self.after_updates(done)) if done else ())
        out = StepOutput(accepted, done, notes=notes, held=held, admitted=tuple(taken.admitted))
        if taken.bugs:
            raise _bug(taken.bugs[0], out)
        return out

    def _journal(self, m: Measurement, flags: int = 0) -> None:
        """Append a measurement to the journal (``flags``: :data:`HELD`, :data:`REVERSED`). A
        write failure (full disk, read-only file system, I/O error) is counted and warned about;
        the measurement stays accepted and applied (the estimate is complete, only the crash
        insurance misses it)."""
        if self.journal is None:
            return
        try:
            self.journal.append(m, flags)
            self.sync()
            self.persistence_failing = ''
        except OSError as exc:
            self.persistence_failed(f'journal {self.journal.path}: measurement applied but NOT '
                                    f'journaled ({exc})')

    def _journal_event(self, event: TrackEnd | Datum | MapOdom | None,
                       happened: bool = True) -> None:
        """Append a track end, a datum or a ``map -> odom`` correction to the journal (if
        ``happened``); a write failure is counted and warned about, as for a measurement."""
        if self.journal is None or event is None or not happened:
            return
        try:
            if isinstance(event, TrackEnd):
                self.journal.append_track_end(event)
            elif isinstance(event, MapOdom):
                self.journal.append_map_odom(event)
            else:
                self.journal.append_datum(event)
            self.sync()
            self.persistence_failing = ''
        except OSError as exc:
            self.persistence_failed(f'journal {self.journal.path}: {type(event).__name__} '
                                    f'applied but NOT journaled ({exc})')

    def journal_datum(self, lla: tuple[float, float, float]) -> None:
        """Journal the map frame's geodetic origin ``(lat_deg, lon_deg, alt_m)`` once it is
        known (a recovery gives it back: :attr:`RecoveryResult.datum`)."""
        self._journal_event(Datum(tuple(float(v) for v in lla)))

    def journal_map_odom(self, T_map_odom: FloatArray) -> None:
        """Journal the REP 105 correction a window update gave (``T_map_odom``, (4, 4)) if it
        differs from the last one journaled and the state has nodes: a recovery gives the last back
        (:attr:`map_odom`), so a restarted node sends it, not the identity, until its first
        update. It holds while the odometry's ``odom`` frame went on across the restart (the
        alignment node alone restarted); an odometry restarted too starts a new ``odom``, which
        the first update places again. The record holds the newest node and its pose (the
        measured bridge across a restart, :mod:`~ga_ros.pipeline.session.restore`)."""
        T = np.asarray(T_map_odom, dtype=float)
        if self.n_nodes() == 0 or (self._map_odom_journaled is not None
                                   and np.array_equal(T, self._map_odom_journaled)):
            return   # no state to restore it with, or journaled already
        self._map_odom_journaled = T.copy()
        node = self.newest_node_id
        pose = getattr(self.aligner, 'pose', None)
        if node is None or pose is None:
            self._journal_event(MapOdom(T))
        else:   # the newest node and its pose now: a restart checks the state did not move
            self._journal_event(MapOdom(T, int(node), pose(int(node))))

    @property
    def map_odom(self) -> FloatArray | None:
        """(4, 4) ``T_map_odom`` the restored state's journal last held (of
        :attr:`map_odom_entry`; ``None``: none, or not restored): the node sends it until its
        first update."""
        return None if self.map_odom_entry is None else self.map_odom_entry.T_map_odom

    def _take(self, m: Measurement, taken: Taken, reverse: bool = False) -> None:
        """The aligner takes ``m`` (``reverse``: read backwards; journaled as it came, counted,
        noted by the healer); raises what the aligner raises."""
        m_in = reversed_measurement(m) if reverse else m
        try:
            taken.updates += self.aligner.add_measurement(m_in)
        except GaError:
            raise
        except Exception as exc:
            if not getattr(self.aligner, 'strict', False):
                raise
            # a strict aligner re-raised a bug of the window update that ``m`` triggered, its
            # state put back and the track finished: ``m`` is taken now (no update left to
            # run), as without strict; raised at the end of the call (UpdateBug)
            taken.bugs.append(exc)
            taken.updates.append(self.aligner.stats.last_update)
            taken.updates += self.aligner.add_measurement(m_in)
        if m.kind == 'bridge':
            self.counts.bridges += 1
        else:
            self.counts.accepted += 1
        if reverse:
            self.counts.reversed += 1
            self.gaps.reversed.add(fingerprint(m))
        self.gaps.admitted(m_in)
        self._journal(m, REVERSED if reverse else 0)
        taken.admitted.append(m_in)

    def _drain(self, taken: Taken, flush: bool = False) -> None:
        """Admit the held measurements that became admissible, in their order, pass after pass
        while one does; then, while the first one still stuck has waited too long
        (:meth:`~ga_ros.core.gaps.GapHealer.overdue`; ``flush``: whatever its wait), bridge it
        and go on."""
        gaps = self.gaps
        while gaps.held:
            if self._pass(taken):
                continue
            if not (flush or gaps.overdue()):
                return
            h = gaps.held[0].m
            stuck = gaps.route(h, front=True) is Route.HOLD
            if stuck and self._measured_bridge(h, taken):
                continue
            bridge = gaps.bridge_to(h) if stuck else None
            if bridge is not None:
                try:
                    self._take(bridge, taken)
                except GaError as exc:
                    taken.notes.append(f'bridge to node {h.src_id} refused: {exc}')
                else:
                    continue
            gaps.held.popleft()
            exc = unknown_source(h)
            self.reject(exc)
            self._journal(h, DROPPED)
            taken.notes.append(f'held measurement rejected: {exc}')

    def _measured_bridge(self, h: Measurement, taken: Taken) -> bool:
        """The bridge across a restart to ``h``'s source, measured (:meth:`bridge_at_once`):
        returns whether it was taken; if not, says why (``warn``, :attr:`restart_bridge`)."""
        measure = self._measure_bridge
        if measure is None or int(h.src_id) != self._bridge_node:
            return False
        self._measure_bridge = None
        origin = self.gaps.bridge_origin(h)
        try:
            m = (measure(origin[0], origin[1], int(h.src_id), int(h.src_track))
                 if origin is not None else 'no node to bridge from')
            if not isinstance(m, str):
                self._take(m, taken)
        except GaError as exc:
            m = f'its measurement was refused ({exc})'
        if isinstance(m, str):
            self.restart_bridge = bounded(f'guessed: {m}')
            self.warn(f'restart: node {h.src_id} bridged to the restored survey by a guess '
                      f'(constant velocity; not joined until a real connection): {m}')
            return False
        self.restart_bridge = 'measured'
        return True

    def _pass(self, taken: Taken) -> bool:
        """One pass over the held queue: admits (or rejects) every measurement whose route is no
        longer ``HOLD``, in order; returns whether any left the queue."""
        gaps = self.gaps
        kept = []
        progress = False
        while gaps.held:
            item = gaps.held.popleft()
            h = item.m
            route = gaps.route(h, front=not kept)
            if route is Route.HOLD:
                kept.append(item)
                continue
            progress = True
            if route in (Route.HOPELESS, Route.DUPLICATE):
                exc = refused(h, route)
                self.reject(exc)
                self._journal(h, DROPPED)
                taken.notes.append(f'held measurement rejected: {exc}')
                continue
            try:
                self._take(h, taken, route is Route.REVERSE)
            except InputError as exc:
                self.reject(exc)
                self._journal(h, DROPPED)
                taken.notes.append(f'held measurement rejected: {exc}')
            except GaError as exc:
                self.solver_failed(exc)
                taken.notes.append(f'held measurement: {type(exc).__name__}: {exc}')
        gaps.held.extend(kept)
        return progress

    def persistence_failed(self, text: str) -> None:
        """Count a failed journal write (an input applied but not saved) and warn; the node
        goes on. Writes count as failing until one succeeds again."""
        self.counts.persistence_errors += 1
        self.unsaved += 1
        self.last_persistence_error = self.persistence_failing = bounded(text)
        self.last_error = self.last_persistence_error
        self.warn(self.last_persistence_error)

    def undecodable(self, exc: BaseException) -> Reason:
        """Count an input that could not be decoded into a measurement; returns its reason."""
        self.counts.received += 1
        return self.reject(exc)

    def reject(self, exc: BaseException) -> Reason:
        """Count a rejected input; returns its reason."""
        reason = rejection_reason(exc)
        self.counts.rejected[reason] += 1
        self.last_error = bounded(f'{reason}: {exc}')
        return reason

    def internal_error(self, exc: BaseException) -> None:
        """Count an unexpected exception on an input (the node must never die on one)."""
        self.counts.rejected[Reason.INTERNAL] += 1
        self.last_error = bounded(f'{type(exc).__name__}: {exc}')

    def solver_failed(self, exc: BaseException) -> None:
        """Count a failed window update (the previous estimate stands)."""
        self.counts.solver_failures += 1
        self.last_error = bounded(f'solver: {exc}')

    def after_updates(self, updates: tuple[Any, ...]) -> list[str]:
        """Count window updates; returns a warning per failed or unconverged one."""
        notes = []
        self.counts.updates += len(updates)
        self.last_update = updates[-1]
        for u in updates:
            reason = str(getattr(u, 'reason', ''))
            if reason.startswith('failed'):
                self.counts.solver_failures += 1
                self.counts.failed_updates += 1
                self.last_error = bounded(f'solver: {reason}')
                notes.append(f'window update of track {u.track_id} failed, previous estimate '
                             f'kept: {reason}')
                self._log_failure(reason)
            elif not getattr(u, 'converged', True):
                self.counts.not_converged += 1
                notes.append(f'window update of track {u.track_id} did not converge ({reason})')
            refine = str(getattr(u, 'refine_reason', ''))
            if refine.startswith(('failed', 'not installed')):
                notes.append(f'background refinement after track {u.refined_after_tracks} '
                             f'{refine}; the online estimate stands')
        if self.session.autosave and self.session.state_file and not self.snapshots_off:
            try:
                self.save()
            except (OSError, GaError) as exc:
                text = f'autosave to {self.session.state_file} failed: {exc}'
                self.counts.persistence_errors += 1
                self.last_persistence_error = self.last_error = bounded(text)
                self.persistence_failing = self.last_persistence_error
                notes.append(text)
        if self.session.autosave and self.journal is not None:
            try:
                self.compact()
            except (OSError, GaError) as exc:  # the journal is as it was: nothing lost
                text = f'journal {self.journal.path} not compacted: {exc}'
                self.counts.persistence_errors += 1
                self.last_persistence_error = self.last_error = bounded(text)
                self.persistence_failing = self.last_persistence_error
                notes.append(text)
        return notes

    def _log_failure(self, reason: str) -> None:
        """Warn once per distinct failure (its text) with the aligner's traceback of it
        (:attr:`TrackWindowAligner.last_failure
        <ga_ros.core.window.aligner.TrackWindowAligner.last_failure>`, its last
        :data:`MAX_TRACEBACK_CHARS`); a repeat is in the per-update note only."""
        if reason in self._failures_logged or len(self._failures_logged) >= MAX_FAILURES_LOGGED:
            return
        self._failures_logged.add(reason)
        trace = str(getattr(self.aligner, 'last_failure', '') or reason)
        if len(trace) > MAX_TRACEBACK_CHARS:
            trace = '...' + trace[-MAX_TRACEBACK_CHARS + 3:]
        self.warn(f'a window update failed (counted in failed_updates, its measurements kept '
                  f'for the next update):\n{trace}')

    def compact(self, force: bool = False) -> bool:
        """Compact the journal (:meth:`MeasurementJournal.compact`) if
        ``SessionConfig.compact_records`` records follow its base (``force``: if any do) and
        no measurement is held: its base is then the current state, followed by the records a
        restart needs (bridges, measurements taken reversed, the datum, the last ``map -> odom``).
        Returns whether it was compacted; raises ``OSError`` (the journal is then unchanged)."""
        j, every = self.journal, self.session.compact_records
        if j is None or self.gaps.held or j.since_base == 0 or not (
                force or 0 < every <= j.since_base):
            return False
        recs = j.file_records()
        kinds = recs['kind']
        keep = (((kinds & KIND_MASK) == KINDS.index('bridge')) & ~is_event(kinds)
                | ((kinds & DROPPED) == REVERSED) & ~is_event(kinds))
        for kind in (DATUM_KIND, MAP_ODOM_KIND):   # the last of each
            last = np.flatnonzero(kinds == kind)
            if last.size:
                keep[last[-1]] = True
        j.sync()
        j.compact(state_chunks(self.aligner, j.count), recs[keep], *self.gaps.waits())
        return True

    def finish_track(self, cause: str = 'finish_track') -> Any:
        """Close the open track now (window update); None if no track is open. The track end is
        journaled (``cause``: one of :data:`~ga_ros.pipeline.journal.TRACK_END_CAUSES`), so a
        recovery from the journal ends it too.

        Raises
        ------
        SolverError
            The update failed (counted; the previous estimate stands).
        """
        try:
            flushed = self.flush_gaps()
        except UpdateBug as exc:   # (a bridged gap's update; the track end still comes)
            flushed, bug = exc.result, exc
        else:
            bug = None
        track = getattr(self.aligner, 'open_track', None)
        try:
            update = self.aligner.finish_track()
        except SolverError as exc:
            self.solver_failed(exc)
            self._journal_event(TrackEnd(int(track), cause), track is not None)
            raise
        except GaError:
            raise
        except Exception as exc:
            if not getattr(self.aligner, 'strict', False):
                raise
            update, bug = self.aligner.stats.last_update, exc   # as without strict, then raised
        self._journal_event(TrackEnd(int(track), cause) if track is not None else None,
                            update is not None)
        if update is not None:
            self.after_updates((update,))
        result = update if update is not None or not flushed.updates else flushed.updates[-1]
        if bug is not None:
            raise _bug(bug.__cause__ if isinstance(bug, UpdateBug) else bug, result)
        return result

    def reset(self) -> None:
        """Forget everything: a fresh aligner, zero counters, and (autosave) emptied state files.

        Raises
        ------
        ForeignFileError, UnsafePathError
            A state path is not ga_ros's own file or is a link: nothing was changed.
        """
        if self.journal is not None:  # autosave: the files mirror the live state
            self.journal.close()
            clear_state(self.session.state_file)
            self.journal = MeasurementJournal(journal_path(self.session.state_file))
        self._fresh_estimator()

    def _fresh_estimator(self) -> None:
        """A fresh aligner (the old one's background work stopped), gap healer and counters;
        no datum, no last update."""
        self._close_aligner()
        self.aligner = TrackWindowAligner(self.config)
        self.gaps = GapHealer(self.session.gaps)
        self.counts = Counters()
        self.last_update, self.last_error = None, ''
        self.datum = None
        self._map_odom_journaled = self.map_odom_entry = None
        self._bridge_now, self._bridge_node, self._measure_bridge = None, -1, None
        self.restart_bridge = ''

    def _close_aligner(self) -> None:
        """Stop the aligner's background refinement (worker process or thread), if any."""
        close = getattr(self.aligner, 'close', None)
        if close is not None:
            close()

    def close(self) -> None:
        """Close the journal (after an ``fsync``), stop the background refinement and release
        the state file's lock."""
        self._close_aligner()
        if self.journal is not None:
            try:
                self.journal.sync()
            except OSError:
                pass
            self.journal.close()
        self._release_lock()

    def _release_lock(self) -> None:
        if self.lock is not None:
            self.lock.release()
            self.lock = None

    def sync(self, now: float | None = None) -> None:
        """``fsync`` the journal if ``SessionConfig.fsync_period_sec`` has passed since the
        last one (0: every call). Called after each accepted measurement."""
        if self.journal is None:
            return
        now = time.monotonic() if now is None else now
        if now >= self._next_sync:
            self.journal.sync()
            self._next_sync = now + self.session.fsync_period_sec

    # ------------------------------------------------------------------ state files
    def save(self, path: str | None = None) -> None:
        """Write the aligner snapshot atomically, with how many journal records it holds.

        Raises
        ------
        InputError
            No state file; :class:`~ga_ros.errors.ForeignFileError` if ``path`` exists and is
            not a ga_ros state (left untouched), :class:`~ga_ros.errors.UnsafePathError` for a
            link.
        """
        target = path or self.session.state_file
        if not target:
            raise InputError('no state file (parameter state_file is empty)')
        if self.journal is not None:
            self.journal.sync()
        records = self.journal.count if self.journal is not None else None
        save_state(self.aligner, target, journal_records=records)
        if target == self.session.state_file:   # the snapshot holds every applied input
            self.persistence_failing = ''
            self.unsaved = 0

    def _recover(self) -> RecoveryResult:
        """:func:`recover` the state file, with the journal closed meanwhile and reopened
        after (recovery may repair it)."""
        path = self.session.state_file
        if self.journal is not None:
            self.journal.close()
        result = recover(path, self.config)
        for text in result.messages:
            self.warn(text)
        self.snapshots_off = (f'{path} is not a ga_ros state (left untouched)'
                              if result.snapshot_refused else '')
        if self.session.autosave:
            self.journal = MeasurementJournal(journal_path(path))
        return result

    def load(self) -> str:
        """Replace the state by the state file's and its journal's (``~/load_state``); returns
        how. What the session knew of the state it replaces goes with it: a pending bridge
        across a restart, :attr:`restart_bridge`, the last ``map -> odom`` journaled; the
        survey check of a start is not made (the loaded state is the one chosen). Standard
        inputs running under it continue after the loaded nodes by
        :func:`~ga_ros.pipeline.session.restore.continue_inputs`, as after a start.

        Raises
        ------
        InputError
            No state file, a foreign file or a link (the state is then unchanged).
        """
        path = self.session.state_file
        if not path or not (os.path.lexists(path) or os.path.lexists(journal_path(path))):
            raise InputError(f'no state file {path!r}')
        result = self._recover()
        if result.source == 'empty':
            raise InputError(f'no state in {path!r}')
        self._close_aligner()
        self.aligner = result.aligner
        self.gaps = rebuild_gaps(self.session.gaps, self.aligner, result)
        self.datum = result.datum
        self.map_odom_entry = result.map_odom_entry
        self._map_odom_journaled = None
        self._bridge_now, self._bridge_node, self._measure_bridge = None, -1, None
        self.restart_bridge = ''
        self.survey_check_pending = False
        return how(result)

    def resume(self) -> str | None:
        """On start: restore from the state file and its journal if they exist.

        Returns how (None if there was nothing to resume). Damaged files are moved aside and
        reported through ``warn`` (never deleted). A state path that is a foreign file or a link
        is never written: persistence is switched off (``'failed: ...'``) and the session
        starts empty.
        """
        path = self.session.state_file
        if not path:
            return None
        try:
            if self.session.lock_owner and self.lock is None:
                check_state_path(path)  # a link, a foreign file: no lock file beside it
                self.lock = StateLock(path, self.session.lock_owner)
            result = self._recover()
        except (GaError, OSError) as exc:  # a foreign file, a link: never touch that path
            return self._without_persistence(exc)
        self.aligner = result.aligner
        self.gaps = rebuild_gaps(self.session.gaps, self.aligner, result)
        self.datum = result.datum
        self.map_odom_entry = result.map_odom_entry
        try:
            if self.journal is not None:
                self.journal.open()  # the journal can be written (not at the first measurement)
        except (GaError, OSError) as exc:
            return self._without_persistence(exc)
        self.survey_check_pending = result.source != 'empty' and self.n_nodes() > 0
        return None if result.source == 'empty' else how(result)

    def _without_persistence(self, exc: BaseException) -> str:
        """Switch persistence off after a state path failed at start, with one warning line
        (or raise :class:`PersistenceError` if ``state_required``); returns ``'failed: ...'``."""
        text = bounded(f'state file {self.session.state_file} cannot be used '
                       f'({type(exc).__name__}: {exc})', 2 * MAX_ERROR_CHARS)
        if self.session.state_required:
            raise PersistenceError(f'{text}; parameter state_required is true: not starting '
                                   '(fix the path, or set state_file to another one)') from None
        if self.journal is not None:
            self.journal.close()
        self.journal = None
        self._release_lock()
        self.session = replace(self.session, state_file='', autosave=False)
        self.persistence_off = bounded(text)
        self.warn(f'{text}; running WITHOUT persistence (a crash loses the state)')
        return f'failed: {exc}'

    # ------------------------------------------------------------------ outputs
    def newest_adjusted(self, cp: Any) -> int | None:
        """Path index of the newest node that a window update has adjusted (the open track's
        nodes are only frame-to-frame continuations without a covariance yet). Reads back from
        the end of the path only as far as the open track's rows reach."""
        return newest_not_in_track(cp.track_ids, getattr(self.aligner, 'open_track', None))

    def covariance_or_unknown(self, node_id: int) -> FloatArray:
        """Marginal covariance of a node, or the ROS "unknown" covariance (``[0, 0] = -1``)."""
        try:
            return np.asarray(self.aligner.covariance(int(node_id)), dtype=float).reshape(6, 6)
        except GaError:
            cov = np.zeros((6, 6))
            cov[0, 0] = -1.0
            return cov

    def dead_reckoned_nodes(self) -> int:
        """Nodes of the open track (at the end of the path, at their dead-reckoned poses: no
        window update has adjusted them yet), counted among the rows an update can change (not
        the whole path)."""
        open_track = getattr(self.aligner, 'open_track', None)
        if open_track is None:
            return 0
        rows = getattr(self.aligner, 'mutable_rows', None)   # the open track is not frozen:
        path = (self.aligner.corrected_path() if rows is None   # its rows come after them
                else self.aligner.corrected_path(rows()[0]))
        return int(np.count_nonzero(path.track_ids == open_track))

    def unjoined(self, node_ids: Any) -> Any:
        """Per node id: True if the node hangs off a bridge, not yet joined to the datum or to
        an absolute fix by a real connection (:meth:`~ga_ros.core.gaps.GapHealer.unjoined`)."""
        return self.gaps.unjoined(np.asarray(node_ids, dtype=np.int64))

    def n_nodes(self) -> int:
        """Nodes held by the aligner."""
        return int(getattr(self.aligner.stats, 'n_nodes', 0))

    def diagnostic_values(self) -> dict[str, object]:
        """Current counters and last-update figures (the diagnostics key/values,
        :func:`~ga_ros.pipeline.session.diagnostics.diagnostic_values`)."""
        return diagnostic_values(self)

    def health(self) -> Health:
        """Overall state for the diagnostics level
        (:func:`~ga_ros.pipeline.session.diagnostics.health`)."""
        return health(self)


def _bug(exc: BaseException, result: Any) -> UpdateBug:
    """The :class:`UpdateBug` of ``exc`` (a strict aligner's re-raised bug), chained to it."""
    bug = UpdateBug(f'a window update failed with a bug (strict updates, '
                    f'GA_ROS_STRICT_UPDATES): {type(exc).__name__}: {exc}; the state was put '
                    'back and nothing was lost', result)
    bug.__cause__ = exc
    return bug
