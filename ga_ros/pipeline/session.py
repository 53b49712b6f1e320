"""The alignment session: one ROS-free object that the alignment node and the replay both drive.

It owns the :class:`~ga_ros.core.window.TrackWindowAligner`, the rejection counters (keyed by
the typed :class:`~ga_ros.errors.Reason` of each rejection), the crash insurance (measurement
journal + snapshots, :mod:`ga_ros.ros.journal`) and the diagnostic values. One call per
measurement: :meth:`AlignmentSession.step` ``(measurement) -> StepOutput``. The node turns
messages into measurements and :class:`StepOutput` into messages; nothing else.
"""

from __future__ import annotations

import os
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.core.persistence import load_state, save_state
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import GaError, InputError, Reason, SolverError
from ga_ros.ros.journal import (
    MeasurementJournal,
    journal_path,
    read_journal,
    read_snapshot_info,
    snapshot_info_path,
    write_snapshot_info,
)

#: Called with warnings the session wants shown (the node logs them, throttled).
Warn = Callable[[str], None]


@dataclass(frozen=True)
class SessionConfig:
    """Settings of the session besides the aligner's.

    Attributes
    ----------
    state_file : ``.npz`` snapshot for save/load and resume on start (``''``: none).
    autosave : journal every accepted measurement and save a snapshot after every update.
    """

    state_file: str = ''
    autosave: bool = True


@dataclass(frozen=True)
class StepOutput:
    """What one measurement did.

    Attributes
    ----------
    accepted : the aligner took the measurement.
    updates : window updates it triggered (a track end), in order.
    reason : why it was rejected (None when accepted or when the solver failed).
    error : message of the rejection (the error's text) or of the failure (``'<Type>: text'``);
        '' when accepted.
    solver_failed : a window update raised; the previous estimate stands.
    notes : warnings about the updates (failed or unconverged updates, autosave failures).
    """

    accepted: bool
    updates: tuple[Any, ...] = ()
    reason: Reason | None = None
    error: str = ''
    solver_failed: bool = False
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Restored:
    """Result of a restore: the new aligner and how it was rebuilt (``'snapshot + n journal
    records'`` or ``'replay of n journal records'``)."""

    aligner: TrackWindowAligner
    how: str


@dataclass(frozen=True)
class Health:
    """Diagnostics level: ``ok`` False means WARN, with ``message`` saying why."""

    ok: bool
    message: str


def rejection_reason(exc: BaseException) -> Reason:
    """The typed reason of a rejection (``Reason.INVALID`` when the error names none)."""
    try:
        return Reason(getattr(exc, 'reason', Reason.INVALID))
    except ValueError:
        return Reason.INVALID


@dataclass
class _Counters:
    rejected: Counter = field(default_factory=Counter)
    received: int = 0
    accepted: int = 0
    updates: int = 0
    solver_failures: int = 0
    not_converged: int = 0
    callback_seconds: float = 0.0
    callback_count: int = 0


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
        self.counts = _Counters()
        self.last_update: Any = None
        self.last_error = ''
        s = self.session
        self.journal = (MeasurementJournal(journal_path(s.state_file))
                        if s.state_file and s.autosave else None)

    # ------------------------------------------------------------------ one measurement
    def step(self, m: Measurement) -> StepOutput:
        """Add one measurement to the aligner (and the journal).

        Never raises on bad input: a rejection is counted by reason and returned; a failing
        window update is counted and returned (the aligner keeps its previous estimate).
        """
        t0 = time.perf_counter()
        self.counts.received += 1
        try:
            updates = self.aligner.add_measurement(m)
        except InputError as exc:
            return StepOutput(False, reason=self.reject(exc), error=str(exc))
        except GaError as exc:  # a failed window update: the previous estimate stands
            self.solver_failed(exc)
            return StepOutput(False, error=f'{type(exc).__name__}: {exc}', solver_failed=True)
        self.counts.accepted += 1
        if self.journal is not None:
            self.journal.append(m)
        done = tuple(u for u in updates if u is not None)
        if done:
            return StepOutput(True, done, notes=tuple(self.after_updates(done)))
        self.counts.callback_seconds += time.perf_counter() - t0
        self.counts.callback_count += 1
        return StepOutput(True)

    def undecodable(self, exc: BaseException) -> Reason:
        """Count an input that could not be decoded into a measurement; returns its reason."""
        self.counts.received += 1
        return self.reject(exc)

    def reject(self, exc: BaseException) -> Reason:
        """Count a rejected input; returns its reason."""
        reason = rejection_reason(exc)
        self.counts.rejected[reason] += 1
        self.last_error = f'{reason}: {exc}'
        return reason

    def internal_error(self, exc: BaseException) -> None:
        """Count an unexpected exception on an input (the node must never die on one)."""
        self.counts.rejected[Reason.INTERNAL] += 1
        self.last_error = f'{type(exc).__name__}: {exc}'

    def solver_failed(self, exc: BaseException) -> None:
        """Count a failed window update (the previous estimate stands)."""
        self.counts.solver_failures += 1
        self.last_error = f'solver: {exc}'

    def after_updates(self, updates: tuple[Any, ...]) -> list[str]:
        """Count window updates; returns a warning per failed or unconverged one."""
        notes = []
        self.counts.updates += len(updates)
        self.last_update = updates[-1]
        for u in updates:
            reason = str(getattr(u, 'reason', ''))
            if reason.startswith('failed'):
                self.counts.solver_failures += 1
                self.last_error = f'solver: {reason}'
                notes.append(f'window update of track {u.track_id} failed, previous estimate '
                             f'kept: {reason}')
            elif not getattr(u, 'converged', True):
                self.counts.not_converged += 1
                notes.append(f'window update of track {u.track_id} did not converge ({reason})')
        if self.session.autosave and self.session.state_file:
            try:
                self.save()
            except (OSError, GaError) as exc:
                notes.append(f'autosave to {self.session.state_file} failed: {exc}')
        return notes

    def finish_track(self) -> Any:
        """Close the open track now (window update); None if no track is open.

        Raises
        ------
        SolverError
            The update failed (counted; the previous estimate stands).
        """
        try:
            update = self.aligner.finish_track()
        except SolverError as exc:
            self.solver_failed(exc)
            raise
        if update is not None:
            self.after_updates((update,))
        return update

    def reset(self) -> None:
        """Forget everything: a fresh aligner, zero counters, and (autosave) empty state files."""
        self.aligner = TrackWindowAligner(self.config)
        if self.journal is not None:  # autosave: the files mirror the live state
            self.journal.clear()
            for f in (self.session.state_file, snapshot_info_path(self.session.state_file)):
                Path(f).unlink(missing_ok=True)
        self.counts = _Counters()
        self.last_update, self.last_error = None, ''

    def close(self) -> None:
        """Close the journal."""
        if self.journal is not None:
            self.journal.close()

    # ------------------------------------------------------------------ state files
    def save(self, path: str | None = None) -> None:
        """Write the aligner snapshot atomically (temporary file, then rename), and how many
        journal records it holds."""
        target = Path(path or self.session.state_file)
        if not str(target) or str(target) == '.':
            raise InputError('no state file (parameter state_file is empty)')
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f'.{target.stem}.tmp{os.getpid()}.npz')
        save_state(self.aligner, str(tmp))
        os.replace(tmp, target)
        write_snapshot_info(target, self.journal.count if self.journal is not None else 0)

    def restore(self, path: str, n_records: int | None = None) -> Restored:
        """A new aligner holding the snapshot ``path`` plus the journal records after it (up to
        ``n_records`` in all; default: every record). Falls back to replaying the journal into
        a fresh aligner if the snapshot cannot be loaded. Raises if neither works; the session
        is not changed."""
        records = read_journal(journal_path(path)) if self.journal is not None else []
        if n_records is not None:
            records = records[:n_records]
        aligner, start, how = None, 0, 'journal replay'
        snapshot_error: Exception | None = None
        if os.path.exists(path):
            try:
                aligner = load_state(path).aligner
                start = min(read_snapshot_info(path), len(records))
                how = 'snapshot'
            except Exception as exc:  # noqa: BLE001 - any unusable snapshot: use the journal
                snapshot_error = exc
        if aligner is None:
            if not records:
                raise snapshot_error or InputError(f'no state in {path}')
            why = f'not usable ({snapshot_error})' if snapshot_error else 'missing'
            self.warn(f'snapshot {path} {why}; replaying {len(records)} journal records')
            aligner = TrackWindowAligner(self.config)
        n = 0
        for m in records[start:]:
            try:
                aligner.add_measurement(m)
                n += 1
            except GaError:
                pass  # already in the snapshot (a crash between snapshot and sidecar)
        how = (f'snapshot + {n} journal records' if how == 'snapshot'
               else f'replay of {n} journal records')
        return Restored(aligner, how)

    def load(self) -> str:
        """Replace the state by the state file's (``~/load_state``); returns how.

        Raises
        ------
        InputError
            No state file; other errors if it cannot be read (the state is then unchanged).
        """
        path = self.session.state_file
        if not path or not os.path.exists(path):
            raise InputError(f'no state file {path!r}')
        n_records = read_snapshot_info(path) if self.journal is not None else 0
        restored = self.restore(path, n_records)
        self.aligner = restored.aligner
        if self.journal is not None:
            self.journal.truncate(n_records)  # the journal mirrors the restored state
        return restored.how

    def resume(self) -> str | None:
        """On start: restore from the state file and its journal if they exist.

        Returns how (None if there was nothing to resume). A bad file is reported through
        ``warn`` and the session starts empty (returns ``'failed: ...'``).
        """
        path = self.session.state_file
        if not path or (not os.path.exists(path) and not journal_path(path).exists()):
            return None
        try:
            restored = self.restore(path)
        except Exception as exc:  # noqa: BLE001 - a bad state file must not stop the node
            self.warn(f'could not resume from {path}: {exc}; starting empty')
            self.aligner = TrackWindowAligner(self.config)
            if self.journal is not None:
                self.journal.clear()
            return f'failed: {exc}'
        self.aligner = restored.aligner
        return restored.how

    # ------------------------------------------------------------------ outputs
    def newest_adjusted(self, cp: Any) -> int | None:
        """Path index of the newest node that a window update has adjusted (the open track's
        nodes are only frame-to-frame continuations without a covariance yet)."""
        open_track = getattr(self.aligner, 'open_track', None)
        tracks = np.asarray(cp.track_ids)
        done = (np.nonzero(tracks != open_track)[0] if open_track is not None
                else np.arange(tracks.size))
        return int(done[-1]) if done.size else None

    def covariance_or_unknown(self, node_id: int) -> FloatArray:
        """Marginal covariance of a node, or the ROS "unknown" covariance (``[0, 0] = -1``)."""
        try:
            return np.asarray(self.aligner.covariance(int(node_id)), dtype=float).reshape(6, 6)
        except GaError:
            cov = np.zeros((6, 6))
            cov[0, 0] = -1.0
            return cov

    def n_nodes(self) -> int:
        """Nodes held by the aligner."""
        return int(getattr(self.aligner.stats, 'n_nodes', 0))

    def diagnostic_values(self) -> dict[str, object]:
        """Current counters and last-update figures (the diagnostics key/values)."""
        st = self.aligner.stats
        u = self.last_update
        c = self.counts
        tiw = getattr(st, 'tracks_in_window', 0)
        values: dict[str, object] = {
            'tracks_in_window': len(tiw) if hasattr(tiw, '__len__') else int(tiw),
            'nodes': int(getattr(st, 'n_nodes', 0)),
            'connections': int(getattr(st, 'n_connections', 0)),
            'iterations': int(u.iterations) if u is not None else 0,
            'variance_factor': float(u.sigma0_sq) if u is not None else float('nan'),
            'update_ms': float(u.update_ms) if u is not None else float('nan'),
            'converged': bool(u.converged) if u is not None else True,
            'last_track': int(u.track_id) if u is not None else -1,
            'outliers_excluded': int(getattr(st, 'n_outliers', 0)),
            'last_update_outliers': int(getattr(u, 'n_outliers', 0)) if u is not None else 0,
            'updates': c.updates,
            'solver_failures': c.solver_failures,
            'not_converged': c.not_converged,
            'measurements_received': c.received,
            'measurements_accepted': c.accepted,
            'measurement_callback_us': (1e6 * c.callback_seconds / c.callback_count
                                        if c.callback_count else float('nan')),
        }
        values['rejected'] = sum(c.rejected.values())
        for key in sorted(c.rejected):
            values[f'rejected/{key}'] = c.rejected[key]
        values['last_error'] = self.last_error
        return values

    def health(self) -> Health:
        """Overall state for the diagnostics level."""
        if self.counts.solver_failures:
            return Health(False, 'solver failures (previous estimate kept)')
        if self.counts.rejected:
            return Health(False, 'rejected measurements')
        return Health(True, 'ok')
