"""Background batch refinement of the track window's frozen estimate (ROS-free).

The track window (:mod:`ga_ros.core.window`) filters: a track that leaves the window is frozen
at the estimate of that moment and never re-estimated with later data, and its connections are
absorbed into joint Gaussian priors linearised where the tracks froze. The batch solution of the
same data smooths. A *refinement* closes the gap without blocking the per-track update:

1. after every ``refine_every_tracks``-th track, if the linearisation demands it (the frozen
   nodes adjusted as weighted parameters drifted by ``refine_relinearize_sigma`` standard
   deviations from their priors' linearisation points, or the horizon is full twice over:
   :meth:`~ga_ros.core.window.handoff.RefinementHandoff.relinearize_due`), the aligner takes a
   :class:`RefinementSnapshot`
   (node poses, connections and their status, which nodes are frozen) and hands it to a worker
   (by default a separate process, truly parallel on a multi-core machine, for a large snapshot
   and inline for a small one; a thread; or inline);
2. the worker solves the snapshot in full (:func:`refine_snapshot`: batch Gauss-Newton,
   warm-started at the online estimate), computes the marginal covariances of the frozen nodes
   (selected inversion) and rebuilds the joint priors of the absorbed connections at the refined
   estimate (:func:`absorbed_priors`);
3. at the start of the update of track ``k + refine_lag_tracks`` (``k`` the snapshot's track),
   the aligner installs the result, waiting for it if it is not ready: the frozen poses and their
   published covariances are replaced, and the priors are the rebuilt ones (plus the tracks frozen
   since the snapshot, absorbed again at the refined estimate). The hand-off point depends on the
   track count only, so a replay and a live node give the same path whatever the timing.

**Bounded refinement** (``refine_horizon_tracks`` ``H > 0``, a fixed-lag smoother behind the
window). A refinement covers only the *horizon*: the finished tracks that have not been retired,
at least the newest ``H``. Its snapshot holds the horizon's nodes (a contiguous range of the
aligner's rows, from ``first_node``), the connections between them, and the *past prior*
(:attr:`RefinementSnapshot.past`): one joint Gaussian prior over the horizon's oldest nodes that
carries every connection touching a retired track, each exactly once. The batch solve uses it
as a prior (it also fixes the datum once the first track has retired), the rebuilt window priors
start from it, and the smoothing reaches the horizon's frozen nodes only. Each refinement then
retires the oldest horizon tracks beyond ``H`` (``retire_max``) that nothing can change any more
(frozen at the hand-off, every connection absorbed or excluded with both ends frozen:
:func:`retirable_tracks`): it eliminates them, with the past prior and every absorbed
connection touching them, onto the nodes they leave behind
(:func:`~ga_ros.core.window.elimination.retire_tracks`), at its
refined estimate, and hands that prior back with the result; the aligner keeps it for the next
refinement. Retired tracks stay where the last refinement (and its smoothing) that covered them
left them. Snapshot, worker and result are then of the horizon's size whatever the survey's
length (about ``H + refine_every_tracks`` tracks); while the survey is no longer than the
horizon nothing is retired and the result is the whole-survey one, bit for bit. ``H = 0``
refines the whole survey every time.

**Absolute fixes** (:mod:`ga_ros.core.fixes`) travel in the snapshot as single-node priors
(:attr:`RefinementSnapshot.fixes`): all of them enter the batch solve, those of frozen nodes the
rebuilt priors (at their track's freeze, as the aligner's freezing keeps them) and, when their
track retires, the past prior. The hand-off installs nothing if the frozen nodes' fixes changed
since the snapshot.

Every absorbed connection and every fix still enters exactly one prior, so the published
covariances stay honest (Monte-Carlo NEES in ``test/core/window/test_honest_covariances.py``).

**Cost.** The rebuilt priors come from one sparse elimination of the horizon's absorbed terms
(:func:`~ga_ros.core.window.elimination.sparse_eliminate`: each term linearised and summed once
per refinement), of the horizon's size whatever the survey's length. The back substitution
(smoothing) needs a sparse factor of the eliminated nodes' block (exact priors over few nodes
come from the same factor: :func:`~ga_ros.core.window.elimination.priors_from_smoothing`); a
worker process keeps it and applies it when the aligner sends the prior nodes' corrections
(:meth:`~ga_ros.core.window.worker.RefinementWorker.smooth`), so the hand-off receives poses,
covariances and priors only.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import solve
from ga_ros.core.window.elimination import (
    eliminate_absorbed,
    gaussian,
    retirable_tracks,
    retire_tracks,
)
from ga_ros.core.window.freeze import AbsorbedPrior, freeze_policy, marginal_covariances
from ga_ros.core.window.snapshot import RefinementResult, RefinementSnapshot
from ga_ros.core.window.storage import unpack_sym6
from ga_ros.errors import GaError
from ga_ros.runtime import blas_threads


def refine_snapshot(snap: RefinementSnapshot) -> RefinementResult:
    """Batch solve of a snapshot, frozen covariances and rebuilt priors (runs in a worker).

    The batch solve uses every connection that is not excluded (status != 2), the past
    prior and the absolute fixes of the snapshot's nodes (weighted parameters), warm-started at
    the online estimate, the datum (if the snapshot holds it) fixed. The priors are rebuilt by
    :func:`absorbed_priors` at the refined poses, for the state after the ``leaving`` tracks
    froze (:func:`predict_freezes`), with the frozen nodes' fixes in them; then the retirable
    oldest tracks are retired (:func:`~ga_ros.core.window.elimination.retire_tracks`).
    A solve stopped at ``max_iterations`` is installed (``reason`` says so), as the window's
    updates are. Never raises for a numerical failure: ``ok`` is then ``False``.
    """
    t0 = time.perf_counter()
    n = snap.node_ids.size
    empty = RefinementResult(snap.after_tracks, False, '', snap.T_world_node,
                             np.zeros((0, 6, 6)), (), snap.frozen, np.zeros(0, np.int64), (),
                             0, 0.0)
    try:
        with blas_threads():
            snap = predict_freezes(snap)
            keep = np.nonzero(snap.status != 2)[0]
            net = ConnectionNetwork.from_arrays(snap.node_ids, snap.track_ids, snap.src[keep],
                                                snap.dst[keep], snap.z[keep],
                                                unpack_sym6(snap.cov21[keep]))
            # the compiled kernels from the first linearisation: the rebuilt priors' selected
            # inversion loads them anyway (the window's updates have, in the aligner's process)
            res = solve(net, snap.T_world_node, snap.solver,
                        fixed=[int(snap.node_ids[0])] if snap.datum else [],
                        priors=gaussian(snap, snap.past + snap.fixes), jit=True)
            # like the window's own updates, a solve that used up its iterations (the cost
            # still creeping down) is kept: refusing it stalled the retirement, so the horizon
            # and the refinement's cost grew with the survey
            if not res.converged and res.reason != 'max_iterations':
                return _failed(empty, f'batch solve did not converge: {res.reason}', t0)
            frozen = np.nonzero(snap.frozen)[0]
            cov = np.zeros((frozen.size, 6, 6))
            free = frozen != 0 if snap.datum else np.ones(frozen.size, dtype=bool)
            if free.any():
                # by selected inversion on the batch factor whatever the horizon's size (the
                # rebuilt priors load the compiled kernels anyway); without them, as
                # SolveResult.covariance (banded=True: not a dense trailing block)
                cov[free] = marginal_covariances(res, snap.node_ids[frozen[free]], banded=True)
            priors, steps = eliminate_absorbed(snap, res.T_world_node)
            retired = retirable_tracks(snap)
            past = retire_tracks(snap, res.T_world_node, retired) if retired else snap.past
    except (GaError, np.linalg.LinAlgError, ValueError) as exc:
        return _failed(empty, f'{type(exc).__name__}: {exc}', t0)
    assert res.T_world_node.shape == (n, 4, 4)
    return RefinementResult(snap.after_tracks, True, res.reason, res.T_world_node, cov,
                            priors, snap.frozen, np.nonzero(snap.status == 1)[0], steps,
                            res.iterations, time.perf_counter() - t0, retired, past)


def _failed(empty: RefinementResult, reason: str, t0: float) -> RefinementResult:
    return replace(empty, reason=reason, seconds=time.perf_counter() - t0)


def predict_freezes(snap: RefinementSnapshot) -> RefinementSnapshot:
    """The snapshot as it will be once its ``leaving`` tracks have frozen.

    Each leaving track, in order, absorbs what the aligner's freezing absorbs: under
    ``'weighted'`` its active connections whose two ends are then frozen, under ``'marginal'``
    all its active connections. Connections that arrive later always touch a newer track, which
    is still in the window, so they are never absorbed by these freezes; the aligner checks the
    prediction at the hand-off anyway and installs nothing if it does not hold.
    """
    if not snap.leaving:
        return snap
    frozen = snap.frozen.copy()
    status = snap.status.copy()
    policy = freeze_policy(snap.freeze_policy)
    for t in snap.leaving:
        in_t = snap.track_ids == t
        frozen |= in_t
        mine = (status == 0) & (in_t[snap.src] | in_t[snap.dst])
        mine &= policy.absorbs(frozen[snap.src], frozen[snap.dst])
        status[mine] = 1
    return replace(snap, frozen=frozen, status=status, leaving=())


def absorbed_priors(snap: RefinementSnapshot, T_lin: FloatArray) -> tuple[AbsorbedPrior, ...]:
    """Joint Gaussian priors of every absorbed connection and of the frozen nodes' fixes (see
    :func:`~ga_ros.core.window.elimination.eliminate_absorbed`)."""
    return eliminate_absorbed(snap, T_lin, smoothing=False)[0]

