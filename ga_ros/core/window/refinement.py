"""Background batch refinement of the track window's frozen estimate (ROS-free).

The track window (:mod:`ga_ros.core.window`) filters: a track that leaves the window is frozen
at the estimate of that moment and never re-estimated with later data, and its connections are
absorbed into joint Gaussian priors linearised where the tracks froze. The batch solution of the
same data smooths. A *refinement* closes the gap without blocking the per-track update:

1. after every ``refine_every_tracks``-th track the aligner takes a :class:`RefinementSnapshot`
   (node poses, connections and their status, which nodes are frozen) and hands it to a worker
   (a separate process by default, truly parallel on a multi-core machine; a thread; or inline);
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

Every absorbed connection still enters exactly one prior, so the published covariances stay
honest (Monte-Carlo NEES in ``test/test_honest_covariances.py``).

**Cost.** The rebuilt priors come from eliminating the absorbed terms track by track on dense
matrices of about two swaths (:class:`~ga_ros.core.window.elimination.Marginal`: interior nodes
first, each gain over the nodes it is coupled to); tracks of more than
:data:`~ga_ros.core.window.elimination.SPARSE_FROM_TRACK_NODES` nodes take one sparse
elimination instead (:func:`~ga_ros.core.window.elimination.sparse_eliminate`), whose cost
does not grow with the cube
of a swath. The back substitution (smoothing) needs the eliminations' gains, ~0.7 M values per
200-pose track: a worker process keeps them and applies them when the aligner sends the prior
nodes' corrections (:meth:`~ga_ros.core.window.worker.RefinementWorker.smooth`), so the
hand-off receives poses,
covariances and priors only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window.elimination import (
    SmoothingStep,
    SparseSmoothing,
    eliminate_absorbed,
    gaussian,
    retirable_tracks,
    retire_tracks,
)
from ga_ros.core.window.freeze import AbsorbedPrior, freeze_policy
from ga_ros.core.window.storage import unpack_sym6
from ga_ros.errors import GaError
from ga_ros.runtime import blas_threads


@dataclass(frozen=True)
class RefinementSnapshot:
    """What a refinement solves: a copy of the aligner's data after one track's update.

    Attributes
    ----------
    after_tracks : number of finished tracks when the snapshot was taken.
    node_ids, track_ids : (n,) ids of the nodes of finished tracks, in the aligner's order; node 0
        (index 0) is the datum, held fixed.
    T_world_node : (n, 4, 4) online estimate (warm start).
    frozen : (n,) frozen flags at the snapshot.
    track_order : finished track ids in order of appearance (the order in which they freeze).
    src, dst : (m,) connection end points as node indices.
    z : (m, 6) measured motions ``[t, rotvec]`` of ``T_src_dst``; cov21 : (m, 21) their covariances
        as the aligner stores them (upper triangles,
        :func:`~ga_ros.core.window.storage.pack_sym6`).
    status : (m,) 0 active, 1 absorbed into a prior, 2 excluded as an outlier.
    freeze_policy : ``'weighted'`` or ``'marginal'`` (which nodes the rebuilt priors keep).
    solver : settings of the batch solve.
    leaving : tracks that will have frozen by the hand-off (they leave the window before the
        update that installs the result); the priors are rebuilt for that state.
    prior_band, prior_hubs : half-bandwidth (nodes) and hub nodes of the rebuilt priors'
        sparse information (:func:`~ga_ros.core.window.freeze.band_prior`);
        ``prior_band = -1``: dense (the exact Schur
        complement).
    first_node : the aligner's row of the snapshot's node 0 (the horizon's first node). 0: the
        horizon starts at the survey's datum, which is held fixed; otherwise the gauge comes
        from the ``past`` prior.
    past : the past prior (bounded refinement, see the module doc), node indices of the
        snapshot.
    retire_max : at most this many of the oldest tracks of ``track_order`` retire after this
        refinement (:func:`~ga_ros.core.window.elimination.retirable_tracks`); 0: none
        (whole-survey refinement).
    conn_rows : (m,) the aligner's rows of the snapshot's connections (``None``: rows ``0..m-1``).
    connections_total : number of connections the aligner held at the snapshot.
    """

    after_tracks: int
    node_ids: IntArray
    track_ids: IntArray
    T_world_node: FloatArray
    frozen: BoolArray
    track_order: tuple[int, ...]
    src: IntArray
    dst: IntArray
    z: FloatArray
    cov21: FloatArray
    status: IntArray
    freeze_policy: str
    solver: SolverConfig
    leaving: tuple[int, ...] = ()
    prior_band: int = -1
    prior_hubs: int = 0
    first_node: int = 0
    past: tuple[AbsorbedPrior, ...] = ()
    retire_max: int = 0
    conn_rows: IntArray | None = None
    connections_total: int = -1

    @property
    def datum(self) -> bool:
        """Whether node 0 of the snapshot is the survey's datum (held fixed)."""
        return self.first_node == 0


@dataclass(frozen=True)
class RefinementResult:
    """Outcome of :func:`refine_snapshot`.

    Attributes
    ----------
    after_tracks : the snapshot's ``after_tracks``.
    ok : the batch solve converged and the priors could be rebuilt; otherwise nothing is
        installed and ``reason`` says why.
    reason : the solver's termination reason, or the error.
    T_world_node : (n, 4, 4) refined poses of the snapshot's nodes (snapshot order).
    frozen_cov : (f, 6, 6) marginal covariances ``[x y z rx ry rz]`` of the snapshot's frozen
        nodes (in index order; the datum's block is zero).
    priors : joint priors of the absorbed connections, relinearised at the refined frozen poses.
    frozen : (n,) frozen flags at the hand-off (the snapshot's plus the ``leaving`` tracks).
    absorbed : (a,) connections absorbed into priors at the hand-off (predicted).
    smoothing : back-substitution steps from the priors' nodes to every other frozen node.
    iterations : Gauss-Newton iterations of the batch solve.
    seconds : wall time of the whole refinement (solve, covariances, priors).
    retired : number of the snapshot's oldest tracks retired
        (:func:`~ga_ros.core.window.elimination.retire_tracks`).
    past : the past prior for the next refinement (snapshot node indices; the snapshot's own
        if nothing retired).
    smoothing_kept : the smoothing steps stayed in the worker process that computed them
        (``smoothing`` is then empty):
        :meth:`~ga_ros.core.window.worker.RefinementWorker.smooth` applies them there.
    """

    after_tracks: int
    ok: bool
    reason: str
    T_world_node: FloatArray
    frozen_cov: FloatArray
    priors: tuple[AbsorbedPrior, ...]
    frozen: BoolArray
    absorbed: IntArray
    smoothing: tuple[SmoothingStep | SparseSmoothing, ...]
    iterations: int
    seconds: float
    retired: int = 0
    past: tuple[AbsorbedPrior, ...] = ()
    smoothing_kept: bool = False


def refine_snapshot(snap: RefinementSnapshot) -> RefinementResult:
    """Batch solve of a snapshot, frozen covariances and rebuilt priors (runs in a worker).

    The batch solve uses every connection that is not excluded (status != 2) and the past
    prior, warm-started at the online estimate, the datum (if the snapshot holds it) fixed. The
    priors are rebuilt by :func:`absorbed_priors` at the refined poses, for the state after the
    ``leaving`` tracks froze (:func:`predict_freezes`); then the retirable oldest tracks are
    retired (:func:`~ga_ros.core.window.elimination.retire_tracks`).
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
            res = solve(net, snap.T_world_node, snap.solver,
                        fixed=[int(snap.node_ids[0])] if snap.datum else [],
                        priors=gaussian(snap, snap.past))
            # like the window's own updates, a solve that used up its iterations (the cost
            # still creeping down) is kept: refusing it stalled the retirement, so the horizon
            # and the refinement's cost grew with the survey
            if not res.converged and res.reason != 'max_iterations':
                return _failed(empty, f'batch solve did not converge: {res.reason}', t0)
            frozen = np.nonzero(snap.frozen)[0]
            cov = np.zeros((frozen.size, 6, 6))
            free = frozen != 0 if snap.datum else np.ones(frozen.size, dtype=bool)
            if free.any():
                cov[free] = res.covariance(snap.node_ids[frozen[free]])
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
    """Joint Gaussian priors of every absorbed connection (see
    :func:`~ga_ros.core.window.elimination.eliminate_absorbed`)."""
    return eliminate_absorbed(snap, T_lin, smoothing=False)[0]

