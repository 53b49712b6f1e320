"""The diagnostics of a session: its key/values and its overall health."""

from __future__ import annotations

from typing import Any

from ga_ros.pipeline.session.outputs import Health, bounded


def diagnostic_values(session: Any) -> dict[str, object]:
    """Current counters and last-update figures of a session (the diagnostics key/values;
    ``session``: an :class:`~ga_ros.pipeline.session.AlignmentSession`)."""
    st = session.aligner.stats
    u = session.last_update
    c = session.counts
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
        'dead_reckoned_nodes': session.dead_reckoned_nodes(),
        'outliers_excluded': int(getattr(st, 'n_outliers', 0)),
        'last_update_outliers': int(getattr(u, 'n_outliers', 0)) if u is not None else 0,
        'updates': c.updates,
        'solver_failures': c.solver_failures,
        # the aligner's, kept in its state: restarts included (a session count otherwise)
        'failed_updates': int(getattr(st, 'n_failed_updates', c.failed_updates)),
        'not_converged': c.not_converged,
        'measurements_received': c.received,
        'measurements_accepted': c.accepted,
        'measurement_callback_us': (1e6 * c.callback_seconds / c.callback_count
                                    if c.callback_count else float('nan')),
        'held_measurements': len(session.gaps.held),
        'bridges': c.bridges,
        'reversed_measurements': c.reversed,
        'unjoined_nodes': session.gaps.n_unjoined,
        'persistence': ('off: ' + session.persistence_off if session.persistence_off
                        else 'failing: ' + session.persistence_failing
                        if session.persistence_failing
                        else 'journal only: ' + session.snapshots_off if session.snapshots_off
                        else 'on' if session.journal is not None else 'none'),
        'persistence_errors': c.persistence_errors,
        'persistence_unsaved': session.unsaved,
    }
    values['rejected'] = sum(c.rejected.values())
    for key in sorted(c.rejected):
        values[f'rejected/{key}'] = c.rejected[key]
    values['last_error'] = bounded(session.last_error)
    if session.last_persistence_error:
        values['last_persistence_error'] = session.last_persistence_error
    if getattr(session, 'restart_bridge', ''):
        values['restart_bridge'] = session.restart_bridge
    return values


def health(session: Any) -> Health:
    """Overall state of a session for the diagnostics level (``session``: an
    :class:`~ga_ros.pipeline.session.AlignmentSession`)."""
    if session.persistence_failing:
        return Health(False, f'state/journal writes are failing '
                             f'({session.counts.persistence_errors} so far): measurements are '
                             'not saved', error=True)
    if session.persistence_off:
        return Health(False, 'running without persistence: the state file cannot be used',
                      error=True)
    if session.unsaved:
        return Health(False, f'{session.unsaved} input(s) applied but not saved (a write '
                             'failed); writes succeed again and the next snapshot saves them')
    if session.snapshots_off:
        return Health(False, 'no snapshots (the state path holds a foreign file): a restart '
                             'replays the whole journal')
    if session.counts.solver_failures:
        return Health(False, 'solver failures (previous estimate kept)')
    if session.counts.rejected:
        return Health(False, 'rejected measurements')
    if session.gaps.n_unjoined:
        return Health(False, f'{session.gaps.n_unjoined} nodes hang off a bridge over a gap '
                             '(not yet joined by a real connection)')
    return Health(True, 'ok')
