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
connection touching them, onto the nodes they leave behind (:func:`retire_tracks`), at its
refined estimate, and hands that prior back with the result; the aligner keeps it for the next
refinement. Retired tracks stay where the last refinement (and its smoothing) that covered them
left them. Snapshot, worker and result are then of the horizon's size whatever the survey's
length (about ``H + refine_every_tracks`` tracks); while the survey is no longer than the
horizon nothing is retired and the result is the whole-survey one, bit for bit. ``H = 0``
refines the whole survey every time.

Every absorbed connection still enters exactly one prior, so the published covariances stay
honest (Monte-Carlo NEES in ``test/test_honest_covariances.py``).

**Cost.** The rebuilt priors come from eliminating the absorbed terms track by track on dense
matrices of about two swaths (:class:`_Marginal`: interior nodes first, each gain over the
nodes it is coupled to); tracks of more than :data:`SPARSE_FROM_TRACK_NODES` nodes take one
sparse elimination instead (:func:`_sparse_eliminate`), whose cost does not grow with the cube
of a swath. The back substitution (smoothing) needs the eliminations' gains, ~0.7 M values per
200-pose track: a worker process keeps them and applies them when the aligner sends the prior
nodes' corrections (:meth:`RefinementWorker.smooth`), so the hand-off receives poses,
covariances and priors only.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from concurrent.futures import (
    BrokenExecutor,
    Executor,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
)
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.linalg.banded import CovarianceSkeleton
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior, SolverConfig, normal_matrix_at, solve
from ga_ros.core.storage import unpack_sym6
from ga_ros.errors import DegenerateGeometryError, GaError, InputError
from ga_ros.geometry import so3
from ga_ros.runtime import blas_threads

#: Where a refinement runs: a separate process ('spawn' start method: safe beside the DDS threads
#: of a live node), a thread of this process, or inline at the hand-off (same result, blocking).
REFINE_EXECUTORS = ('process', 'thread', 'inline')


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
        as the aligner stores them (upper triangles, :func:`~ga_ros.core.storage.pack_sym6`).
    status : (m,) 0 active, 1 absorbed into a prior, 2 excluded as an outlier.
    freeze_policy : ``'weighted'`` or ``'marginal'`` (which nodes the rebuilt priors keep).
    solver : settings of the batch solve.
    leaving : tracks that will have frozen by the hand-off (they leave the window before the
        update that installs the result); the priors are rebuilt for that state.
    prior_band, prior_hubs : half-bandwidth (nodes) and hub nodes of the rebuilt priors'
        sparse information (:func:`band_prior`); ``prior_band = -1``: dense (the exact Schur
        complement).
    first_node : the aligner's row of the snapshot's node 0 (the horizon's first node). 0: the
        horizon starts at the survey's datum, which is held fixed; otherwise the gauge comes
        from the ``past`` prior.
    past : the past prior (bounded refinement, see the module doc), node indices of the
        snapshot.
    retire_max : at most this many of the oldest tracks of ``track_order`` retire after this
        refinement (:func:`retirable_tracks`); 0: none (whole-survey refinement).
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
class SmoothingStep:
    """One elimination of :func:`absorbed_priors`, kept for back substitution.

    Given the tangent corrections ``d_R`` of the nodes ``R`` still present after the step (at
    the linearisation point), the eliminated nodes ``L`` move by ``d_L = offset + gain d_R``
    (their conditional mean under the absorbed terms).
    """

    eliminated: IntArray
    remaining: IntArray
    gain: FloatArray
    offset: FloatArray

    def back(self, dR: FloatArray) -> FloatArray:
        """``d_L`` (6 per eliminated node) from ``d_R`` (6 per remaining node)."""
        return self.offset + (self.gain.astype(np.float64) @ dR if dR.size else 0.0)


class SparseSmoothing:
    """The back substitution of a sparse elimination (:func:`_sparse_eliminate`): ``d_L =
    -N_LL^-1 (u_L + N_LR d_R)`` with a sparse Cholesky factor of ``N_LL`` (not picklable: it
    stays in the process that made it, :func:`_refine_in_worker`).

    Attributes
    ----------
    eliminated, remaining : node indices of ``L`` and ``R`` (the prior nodes).
    """

    def __init__(self, eliminated: IntArray, remaining: IntArray, N_LL: sp.spmatrix,
                 N_LR: sp.spmatrix, u_L: FloatArray) -> None:
        from ga_ros.core.linalg.blocks import BlockPattern
        from ga_ros.core.linalg.cholesky import SparseCholesky

        self.eliminated, self.remaining = eliminated, remaining
        self._chol = SparseCholesky(*BlockPattern.from_matrix(N_LL, 6))
        self._N_LR = sp.csr_matrix(N_LR)
        self._u_L = u_L

    def back(self, dR: FloatArray) -> FloatArray:
        """``d_L`` (6 per eliminated node) from ``d_R`` (6 per remaining node)."""
        rhs = self._u_L + (self._N_LR @ dR if dR.size else 0.0)
        return -self._chol.solve(rhs)


@dataclass(frozen=True)
class AbsorbedPrior:
    """One joint Gaussian prior of absorbed connections (the aligner's prior layout).

    Attributes
    ----------
    nodes : (k,) node indices the prior is over.
    T_world_node : (k, 4, 4) prior mean (residual: :func:`tangent_prior`).
    information : (6k, 6k) information, node-major, ``[x y z rx ry rz]`` per node: dense, or
        block-banded (``scipy.sparse`` BSR, 6x6 blocks) for a :func:`band_prior`.
    rank : rank of ``information`` when known (positive definite by construction: ``6k``).
    """

    nodes: IntArray
    T_world_node: FloatArray
    information: FloatArray | sp.spmatrix
    rank: int | None = None


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
    retired : number of the snapshot's oldest tracks retired (:func:`retire_tracks`).
    past : the past prior for the next refinement (snapshot node indices; the snapshot's own
        if nothing retired).
    smoothing_kept : the smoothing steps stayed in the worker process that computed them
        (``smoothing`` is then empty): :meth:`RefinementWorker.smooth` applies them there.
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
    retired (:func:`retire_tracks`).
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
                        priors=_gaussian(snap, snap.past))
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
            priors, steps = _eliminate_absorbed(snap, res.T_world_node)
            retired = retirable_tracks(snap)
            past = retire_tracks(snap, res.T_world_node, retired) if retired else snap.past
    except (GaError, np.linalg.LinAlgError, ValueError) as exc:
        return _failed(empty, f'{type(exc).__name__}: {exc}', t0)
    assert res.T_world_node.shape == (n, 4, 4)
    return RefinementResult(snap.after_tracks, True, res.reason, res.T_world_node, cov,
                            priors, snap.frozen, np.nonzero(snap.status == 1)[0], steps,
                            res.iterations, time.perf_counter() - t0, retired, past)


def _gaussian(snap: RefinementSnapshot, priors: tuple[AbsorbedPrior, ...]
              ) -> list[GaussianPrior]:
    """The solver's form of priors over snapshot nodes."""
    return [GaussianPrior(snap.node_ids[p.nodes], p.T_world_node, p.information)
            for p in priors]


def _track_rank(snap: RefinementSnapshot) -> IntArray:
    """(n,) position of each node's track in ``track_order`` (unfinished tracks last)."""
    order = {t: k for k, t in enumerate(snap.track_order)}
    tracks, inverse = np.unique(snap.track_ids, return_inverse=True)
    rank = np.array([order.get(int(t), len(order)) for t in tracks.tolist()], dtype=np.int64)
    return rank[inverse]


def retirable_tracks(snap: RefinementSnapshot) -> int:
    """How many of the oldest tracks of ``track_order`` (at most ``retire_max``) retire.

    A track can retire when nothing can change its terms any more: its nodes and those of every
    older track are frozen, and every connection touching them is absorbed or excluded with both
    ends frozen (a frozen node takes no new connection, and the gate re-tests only connections
    touching the window). ``snap`` is the state at the hand-off (:func:`predict_freezes`).
    """
    if snap.retire_max <= 0:
        return 0
    rank = _track_rank(snap)
    limit = snap.retire_max
    if not snap.frozen.all():
        limit = min(limit, int(rank[~snap.frozen].min()))
    open_ = (snap.status == 0) | ~snap.frozen[snap.src] | ~snap.frozen[snap.dst]
    if open_.any():
        limit = min(limit, int(np.minimum(rank[snap.src[open_]], rank[snap.dst[open_]]).min()))
    return max(0, limit)


def retire_tracks(snap: RefinementSnapshot, T_lin: FloatArray, k: int
                  ) -> tuple[AbsorbedPrior, ...]:
    """The past prior after the ``k`` oldest tracks of the snapshot retire, linearised at
    ``T_lin`` (snapshot node indices).

    The current past prior and every absorbed connection touching a retiring node are summed
    and the retiring nodes eliminated (Schur complement) onto the nodes they leave behind: the
    exact marginal of those terms in the linear limit, one prior per connected group (dense, or
    sparse as :func:`band_prior` like the window's). The retiring tracks are the snapshot's
    first nodes (its rows follow ``track_order``).
    """
    e = int((_track_rank(snap) < k).sum())
    conns = np.nonzero((snap.status == 1) & ((snap.src < e) | (snap.dst < e)))[0]
    if _long_tracks(snap):
        free, N, u = _normal_terms(snap, conns, T_lin, snap.past)
        return _sparse_priors(free, N, u, free >= e, T_lin, snap.prior_band, snap.prior_hubs)
    work = _Marginal()
    work.add(*_normal_terms(snap, conns, T_lin, snap.past))
    gone = [i for i in work.cols if i < e]
    if len(gone) == len(work.cols):
        return ()
    if gone:
        work.eliminate(gone)
    return tuple(_prior_of(work, np.sort(group), T_lin, snap.prior_band, snap.prior_hubs)
                 for group in work.groups())


#: Tracks of more nodes than this make the eliminations of :func:`_eliminate_absorbed` and
#: :func:`retire_tracks` sparse (:func:`_sparse_eliminate`): the dense ones work on about two
#: swaths at a time, cubic in the swath's length (minutes and GBs per refinement for 1,000-pose
#: tracks); for shorter tracks they are the faster of the two.
SPARSE_FROM_TRACK_NODES = 400


def _long_tracks(snap: RefinementSnapshot) -> bool:
    """Whether the snapshot has a track of more than :data:`SPARSE_FROM_TRACK_NODES` nodes."""
    _, counts = np.unique(snap.track_ids, return_counts=True)
    return bool(counts.size) and int(counts.max()) > SPARSE_FROM_TRACK_NODES


def _sparse_priors(free: IntArray, N: sp.spmatrix, u: FloatArray, target: BoolArray,
                   T_lin: FloatArray, band: int, hubs: int) -> tuple[AbsorbedPrior, ...]:
    """The priors of sparse terms ``(N, u)`` over the nodes ``free`` on their ``target`` nodes
    (the others eliminated), one per connected group (:func:`marginal_prior` of each, so
    without a dense matrix of more than the group's targets). Equal to :func:`_prior_of` of the
    dense elimination (``test/test_refinement.py``)."""
    Nc = sp.csr_matrix(N)
    coo = Nc.tocoo()
    k = free.size
    blocks = sp.csr_matrix((np.ones(coo.nnz), (coo.row // 6, coo.col // 6)), shape=(k, k))
    _, label = connected_components(blocks, directed=False)
    priors = []
    for c in np.unique(label):
        mine = np.nonzero(label == c)[0]
        nodes, keep = free[mine], target[mine]
        if not keep.any():
            continue
        at = (6 * mine[:, None] + np.arange(6)).ravel()
        priors.append(marginal_prior(nodes, Nc[at][:, at], u[at], keep, T_lin[nodes[keep]],
                                     band, hubs, coords=T_lin[nodes, :3, 3]))
    return tuple(priors)


def _sparse_eliminate(snap: RefinementSnapshot, T_lin: FloatArray, keep: BoolArray,
                      smoothing: bool = True
                      ) -> tuple[tuple[AbsorbedPrior, ...], tuple[SparseSmoothing, ...]]:
    """:func:`_eliminate_absorbed` for long tracks: every absorbed term and the past prior in
    one sparse normal matrix, the priors from it (:func:`_sparse_priors`) and (if
    ``smoothing``) one back substitution with a sparse factor of the eliminated nodes' block
    (:class:`SparseSmoothing`)."""
    absorbed = np.nonzero(snap.status == 1)[0]
    free, N, u = _normal_terms(snap, absorbed, T_lin, snap.past)
    N = sp.csr_matrix(N)  # once, for both
    kf = keep[free]
    priors = _sparse_priors(free, N, u, kf, T_lin, snap.prior_band, snap.prior_hubs)
    L, R = np.nonzero(~kf)[0], np.nonzero(kf)[0]
    if L.size == 0 or not smoothing:
        return priors, ()
    cL = (6 * L[:, None] + np.arange(6)).ravel()
    cR = (6 * R[:, None] + np.arange(6)).ravel()
    NL = N[cL]
    return priors, (SparseSmoothing(free[L], free[R], NL[:, cL], NL[:, cR], u[cL]),)


#: :func:`marginal_prior`: above this many eliminated unknowns, the exact Schur complement of a
#: sparse ``N`` comes from a partial sparse factorisation
#: (:func:`~ga_ros.core.linalg.cholesky.trailing_factor`), below it from dense blocks.
DENSE_SCHUR_MAX = 300


def marginal_prior(nodes: IntArray, N: FloatArray | sp.spmatrix, u: FloatArray,
                   keep: BoolArray, T_keep: FloatArray, band: int, hubs: int,
                   coords: FloatArray | None = None) -> AbsorbedPrior:
    """The joint Gaussian prior that absorbed terms leave on some of their nodes: the one rule
    of the aligner's freeze (:meth:`~ga_ros.core.window.TrackWindowAligner._marginalise`) and
    of the refinement's rebuilt priors (:func:`_sparse_priors`, :func:`_prior_of`).

    The terms' normal matrix ``N`` and half gradient ``u`` (linearised at the nodes' poses) are
    marginalised onto the nodes ``keep`` (Schur complement ``H``, ``g``; the others
    eliminated). The prior's mean is the terms' own optimum on them (``T_keep`` moved by the
    step ``H^-1 g``, :func:`tangent_prior`); its information is:

    * **sparse** (:func:`sparse_prior_applies`: ``band >= 0`` and more kept nodes than the
      skeleton keeps densely anyway): :func:`band_prior` of the exact covariance skeleton of
      ``Sigma = H^-1 = (N^-1)_kept`` (band of ``band`` nodes along the node order plus ``hubs``
      hub nodes), from the selected inversion of a sparse ``N``
      (:func:`~ga_ros.core.linalg.skeleton.sparse_skeleton`, linear in the number of nodes for a
      strip) or a Cholesky factor of a dense one; positive definite, rank ``6k``;
    * otherwise, or if ``N`` is not positive definite (:class:`DegenerateGeometryError` from the
      sparse path), the **exact** ``H`` (:func:`tangent_prior`): from a partial sparse
      factorisation (:func:`~ga_ros.core.linalg.cholesky.trailing_factor`, rank ``6k``) when more
      than
      :data:`DENSE_SCHUR_MAX` unknowns are eliminated from a sparse ``N``, else from dense
      blocks (rank unknown: ``None``; a singular ``H`` is allowed, its step is the least-squares
      one).

    Parameters
    ----------
    nodes : (n,) node indices of ``N``'s blocks (6 unknowns each, ``[x y z rx ry rz]``).
    N : (6n, 6n) normal matrix, ``scipy.sparse`` or dense; u : (6n,) half gradient.
    keep : (n,) the nodes the prior is over (in node order, which is the band order).
    T_keep : (k, 4, 4) their poses ``T_world_node`` (the linearisation point).
    band, hubs : ``prior_band`` (-1: the exact dense prior always) and ``prior_hubs``.
    coords : optional (n, 3) node positions (band ordering of the non-compiled selection).

    Returns
    -------
    The prior over ``nodes[keep]``.

    Raises
    ------
    DegenerateGeometryError
        The eliminated nodes are not determined by the terms (their block is singular).
    """
    from ga_ros.core.linalg import skeleton
    from ga_ros.core.linalg.blocks import BlockPattern
    from ga_ros.core.linalg.cholesky import trailing_factor

    keep = np.asarray(keep, dtype=bool)
    S, Lx = np.nonzero(keep)[0], np.nonzero(~keep)[0]
    kept = np.asarray(nodes, dtype=np.int64)[S]
    colsS = (6 * S[:, None] + np.arange(6)).ravel()
    colsL = (6 * Lx[:, None] + np.arange(6)).ravel()
    sparse_in = sp.issparse(N)
    if sparse_prior_applies(S.size, band, hubs):
        try:
            if sparse_in:
                skel, x = skeleton.sparse_skeleton(N, 6, S, band, hubs, coords=coords, rhs=u)
                step = x.reshape(-1, 6)[S].ravel()
            else:  # dense: Sigma_SS and the step from one Cholesky factor of N
                cho = _cho_factor(N)
                Sigma = sla.cho_solve(cho, np.eye(N.shape[0])[:, colsS])[colsS]
                skel = CovarianceSkeleton.of_dense(Sigma, 6, band, hubs)
                step = sla.cho_solve(cho, u)[colsS]
            mean, info = band_prior(T_keep, skel, step)
            # a completion of positive definite clique covariances: full rank
            return AbsorbedPrior(kept, mean, info, info.shape[0])
        except DegenerateGeometryError:  # N not positive definite: the exact paths below
            pass
    if sparse_in and colsL.size > DENSE_SCHUR_MAX:
        try:
            tf = trailing_factor(*BlockPattern.from_matrix(N, 6), S, u)
            step = tf.solution.reshape(-1, 6)[S].ravel()  # H^-1 g: the kept part of N^-1 u
            mean, info = tangent_prior(T_keep, tf.information(), None, step=step)
            # the trailing block of a positive definite factor: full rank
            return AbsorbedPrior(kept, mean, info, info.shape[0])
        except DegenerateGeometryError:  # N_LL or H singular: dense blocks below
            pass
    Nd = sp.csr_matrix(N) if sparse_in else np.asarray(N)

    def part(rows: IntArray, cols: IntArray) -> FloatArray:
        return Nd[rows][:, cols].toarray() if sparse_in else Nd[np.ix_(rows, cols)]

    H, g = part(colsS, colsS), u[colsS]
    if colsL.size:
        NLS = part(colsL, colsS)
        cho = _cho_factor(part(colsL, colsL))
        H = H - NLS.T @ sla.cho_solve(cho, NLS)
        g = g - NLS.T @ sla.cho_solve(cho, u[colsL])
    # The absorbed terms alone are not at their optimum (the window's estimate is), so their
    # marginal keeps a linear term g: cost = (d + H^-1 g)' H (d + H^-1 g) + const in the
    # tangent d of the kept nodes (their mean and information: tangent_prior)
    mean, info = tangent_prior(T_keep, 0.5 * (H + H.T), g)
    return AbsorbedPrior(kept, mean, info)


def _cho_factor(M: FloatArray) -> tuple[FloatArray, bool]:
    """``scipy.linalg.cho_factor`` of a block that must be positive definite."""
    try:
        return sla.cho_factor(M)
    except np.linalg.LinAlgError as exc:
        raise DegenerateGeometryError('absorbed terms leave some eliminated nodes undetermined '
                                      '(their normal block is singular): the network needs a '
                                      'datum or a prior on them') from exc


def _normal_terms(snap: RefinementSnapshot, conns: IntArray, T_lin: FloatArray,
                  priors: tuple[AbsorbedPrior, ...] = ()
                  ) -> tuple[IntArray, FloatArray, FloatArray]:
    """Normal matrix ``N`` (sparse) and half gradient ``u`` of some connections and priors at
    ``T_lin``, over their free nodes (snapshot indices, the datum excluded), in that order."""
    nodes = np.unique(np.concatenate([snap.src[conns], snap.dst[conns]]
                                     + [p.nodes for p in priors]))
    local = np.full(snap.node_ids.size, -1, dtype=np.int64)
    local[nodes] = np.arange(nodes.size)
    net = ConnectionNetwork.from_arrays(
        snap.node_ids[nodes], snap.track_ids[nodes], local[snap.src[conns]],
        local[snap.dst[conns]], snap.z[conns], unpack_sym6(snap.cov21[conns]))
    datum = snap.datum and bool((nodes == 0).any())
    fixed = [int(snap.node_ids[0])] if datum else []
    N, free_ids, u = normal_matrix_at(net, T_lin[nodes], 'se3', fixed, _gaussian(snap, priors))
    free = nodes[nodes != 0] if datum else nodes
    assert free.size == free_ids.size
    return free, N, u


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
    for t in snap.leaving:
        in_t = snap.track_ids == t
        frozen |= in_t
        mine = (status == 0) & (in_t[snap.src] | in_t[snap.dst])
        if snap.freeze_policy == 'weighted':
            mine &= frozen[snap.src] & frozen[snap.dst]
        status[mine] = 1
    return replace(snap, frozen=frozen, status=status, leaving=())


def prior_nodes(frozen: BoolArray, src: IntArray, dst: IntArray, status: IntArray,
                freeze_policy: str, touched_by: IntArray | None = None,
                datum: bool = True) -> BoolArray:
    """Which nodes the priors of the absorbed connections are over (``(n,)`` mask).

    ``'weighted'``: frozen nodes that keep an active connection to a node that is not frozen
    (the paper's weighted parameters). ``'marginal'``: nodes that are not frozen. In both cases
    only nodes touched by an absorbed connection (or listed in ``touched_by``: the past prior's
    nodes) count, and never the datum (index 0, if ``datum``).
    """
    n = frozen.size
    act = status == 0
    if freeze_policy == 'weighted':
        keep = np.zeros(n, dtype=bool)
        s_, d_ = src[act], dst[act]
        keep[s_[~frozen[d_]]] = True
        keep[d_[~frozen[s_]]] = True
        keep &= frozen
    else:
        keep = ~frozen
    touched = np.zeros(n, dtype=bool)
    touched[src[status == 1]] = True
    touched[dst[status == 1]] = True
    if touched_by is not None:
        touched[touched_by] = True
    keep &= touched
    if datum and n:
        keep[0] = False
    return keep


def absorbed_priors(snap: RefinementSnapshot, T_lin: FloatArray) -> tuple[AbsorbedPrior, ...]:
    """Joint Gaussian priors of every absorbed connection (see :func:`_eliminate_absorbed`)."""
    return _eliminate_absorbed(snap, T_lin, smoothing=False)[0]


def _eliminate_absorbed(snap: RefinementSnapshot, T_lin: FloatArray, smoothing: bool = True
                        ) -> tuple[tuple[AbsorbedPrior, ...],
                                   tuple[SmoothingStep | SparseSmoothing, ...]]:
    """Joint Gaussian priors of every absorbed connection (status 1), linearised at ``T_lin``.

    The absorbed connections are summed in the order their tracks froze and every node that no
    later absorbed connection touches, and that is not a prior node (:func:`prior_nodes`), is
    eliminated as soon as its last connection is in (Schur complement): the working matrix spans
    about two tracks whatever the survey's length, and the result is the exact marginal of the
    absorbed terms on the prior nodes in the linear limit (the order of elimination does not
    change a Schur complement; ``test/test_refinement.py`` checks it against one dense
    elimination). As in the aligner's freezing, the absorbed terms are not at their optimum, so
    their marginal keeps a linear term ``g``: the prior mean is ``T_lin`` moved by ``-H^-1 g``.
    A bounded refinement's past prior (the terms of the retired tracks) enters first.

    Returns one prior per connected group of prior nodes (at most one in a lawnmower survey),
    and the elimination steps for back substitution (:class:`SmoothingStep`).

    Tracks of more than :data:`SPARSE_FROM_TRACK_NODES` nodes: one sparse elimination
    instead (:func:`_sparse_eliminate`, the same priors, one :class:`SparseSmoothing`).

    Raises
    ------
    numpy.linalg.LinAlgError, ga_ros.errors.DegenerateGeometryError
        An eliminated group is not determined by the absorbed terms (no datum, no prior node).
    """
    absorbed = np.nonzero(snap.status == 1)[0]
    if absorbed.size == 0 and not snap.past:
        return (), ()
    n = snap.node_ids.size
    past_nodes = np.concatenate([p.nodes for p in snap.past] or [np.zeros(0, np.int64)])
    keep = prior_nodes(snap.frozen, snap.src, snap.dst, snap.status, snap.freeze_policy,
                       past_nodes, snap.datum)
    if _long_tracks(snap):
        return _sparse_eliminate(snap, T_lin, keep, smoothing)
    rank = _track_rank(snap)
    # a connection is added at the freeze of its later frozen end (the earlier end may be the
    # window's, under 'marginal'); a node is eliminated after its last absorbed connection.
    # The past prior (bounded refinement) comes first, at step -1.
    rs, rd = rank[snap.src[absorbed]], rank[snap.dst[absorbed]]
    fs, fd = snap.frozen[snap.src[absorbed]], snap.frozen[snap.dst[absorbed]]
    step = np.maximum(np.where(fs, rs, -1), np.where(fd, rd, -1))
    last = np.full(n, -1, dtype=np.int64)
    np.maximum.at(last, snap.src[absorbed], step)
    np.maximum.at(last, snap.dst[absorbed], step)
    stages = [(-1, absorbed[:0], snap.past)] if snap.past else []
    stages += [(int(s), absorbed[step == s], ()) for s in np.unique(step)]
    work = _Marginal()
    steps: list[SmoothingStep] = []
    for s, conns, priors in stages:
        work.add(*_normal_terms(snap, conns, T_lin, priors))
        gone = [i for i in work.cols if last[i] <= s and not keep[i]]
        if gone:
            steps += work.eliminate(gone)
    if not work.cols:
        return (), tuple(steps)
    priors = tuple(_prior_of(work, np.sort(group), T_lin, snap.prior_band, snap.prior_hubs)
                   for group in work.groups())
    return priors, tuple(steps)


class _Marginal:
    """Dense marginal information ``(H, g)`` of absorbed terms over a changing set of nodes,
    with its block pattern (which node blocks of ``H`` are nonzero), for the eliminations of
    :func:`_eliminate_absorbed` and :func:`retire_tracks`.

    ``cols`` maps a node index to its block position in ``H`` (positions ``0..k-1`` in the
    dict's order).
    """

    def __init__(self) -> None:
        self.H = np.zeros((0, 0))
        self.g = np.zeros(0)
        self.nz = np.zeros((0, 0), dtype=bool)
        self.cols: dict[int, int] = {}

    def add(self, free: IntArray, N: sp.spmatrix, u: FloatArray) -> None:
        """Add terms ``(N, u)`` over the nodes ``free`` (new ones appended)."""
        for i in free.tolist():
            if i not in self.cols:
                self.cols[i] = len(self.cols)
        k = len(self.cols)
        if k > self.nz.shape[0]:
            grow = k - self.nz.shape[0]
            self.H = np.pad(self.H, ((0, 6 * grow), (0, 6 * grow)))
            self.g = np.pad(self.g, (0, 6 * grow))
            self.nz = np.pad(self.nz, ((0, grow), (0, grow)))
        pos = np.array([self.cols[i] for i in free.tolist()], dtype=np.int64)
        at = (6 * pos[:, None] + np.arange(6)).ravel()
        C = sp.coo_matrix(N)
        C.sum_duplicates()  # each entry once: a plain fancy-index add is exact
        self.H[at[C.row], at[C.col]] += C.data
        self.g[at] += u
        self.nz[pos[C.row // 6], pos[C.col // 6]] = True

    def eliminate(self, gone: list[int]) -> list[SmoothingStep]:
        """Schur complement of the nodes ``gone`` out of ``(H, g)``; returns the back
        substitutions ``d_L = -H_LL^-1 (g_L + H_LC d_C)`` (``C``: remaining nodes coupled to
        ``L``).

        The block pattern is used twice (the result is the same Schur complement): the nodes of
        ``gone`` coupled to no remaining node (the interior, e.g. the older of two frozen
        swaths) go first, then the others; and each elimination touches only the remaining
        nodes coupled to it (its gain has their columns only, its update their block of
        ``H``): less dense work per track, and no zero columns in the gains the hand-off
        receives.
        """
        k = len(self.cols)
        H, g, nz = self.H, self.g, self.nz
        is_gone = np.zeros(k, dtype=bool)
        is_gone[[self.cols[i] for i in gone]] = True
        interior = np.zeros(k, dtype=bool)
        interior[is_gone] = ~nz[np.ix_(is_gone, ~is_gone)].any(axis=1)
        parts = [interior, is_gone & ~interior] if interior.any() else [is_gone]
        node = np.array(list(self.cols), dtype=np.int64)
        steps = []
        left = np.ones(k, dtype=bool)
        for part in parts:
            if not part.any():
                continue
            left &= ~part
            Lp = np.nonzero(part)[0]
            Cp = np.nonzero(left & nz[Lp].any(axis=0))[0]
            cL = (6 * Lp[:, None] + np.arange(6)).ravel()
            cC = (6 * Cp[:, None] + np.arange(6)).ravel()
            cho = sla.cho_factor(H[np.ix_(cL, cL)])
            HLC = H[np.ix_(cL, cC)]
            gain = -sla.cho_solve(cho, HLC)
            offset = -sla.cho_solve(cho, g[cL])
            if Cp.size:
                upd = HLC.T @ gain
                H[np.ix_(cC, cC)] += 0.5 * (upd + upd.T)
                g[cC] += HLC.T @ offset
                nz[np.ix_(Cp, Cp)] = True  # fill: the eliminated nodes coupled them
            # kept in single precision (half the memory and transfer; a correction of 1 m is
            # then carried to 0.1 um)
            steps.append(SmoothingStep(node[Lp], node[Cp], gain.astype(np.float32), offset))
        stay = np.nonzero(left)[0]
        cS = (6 * stay[:, None] + np.arange(6)).ravel()
        self.H, self.g, self.nz = H[np.ix_(cS, cS)], g[cS], nz[np.ix_(stay, stay)]
        self.cols = {int(node[p]): q for q, p in enumerate(stay.tolist())}
        return steps

    def groups(self) -> list[IntArray]:
        """The nodes, grouped by the connected components of the block pattern."""
        S = np.array(list(self.cols), dtype=np.int64)
        _, label = connected_components(self.nz, directed=False)
        return [S[label == c] for c in np.unique(label)]


#: In a worker process: the smoothing steps of its last refinement, by its ``after_tracks``
#: (:func:`_refine_in_worker`, :func:`_smooth_in_worker`).
_KEPT_STEPS: dict[int, tuple[SmoothingStep, ...]] = {}


def _refine_in_worker(snap: RefinementSnapshot) -> RefinementResult:
    """:func:`refine_snapshot` in the worker process, keeping the smoothing steps there.

    The steps hold a dense gain per eliminated group (~0.7 M values per 200-pose track, 60-80 MB
    for a horizon of 25-30 such tracks); shipping them to the aligner's process cost it ~30 ms
    of CPU at every hand-off (pickles through the pipe), and their transient copies let its
    heap grow. The aligner sends the prior nodes' corrections instead
    (:meth:`RefinementWorker.smooth`) and receives the corrections of the frozen nodes.
    """
    res = refine_snapshot(snap)
    _KEPT_STEPS.clear()
    if not res.ok:
        return res
    _KEPT_STEPS[res.after_tracks] = res.smoothing
    return replace(res, smoothing=(), smoothing_kept=True)


def _smooth_in_worker(after_tracks: int, nodes: IntArray, d_nodes: FloatArray
                      ) -> tuple[IntArray, FloatArray]:
    """:func:`smoothed` with the steps kept by :func:`_refine_in_worker` (in the worker)."""
    steps = _KEPT_STEPS.pop(after_tracks, None)
    if steps is None:
        raise InputError(f'the worker no longer holds the smoothing of refinement '
                         f'{after_tracks}')
    return smoothed(steps, nodes, d_nodes)


def smoothed(steps: tuple[SmoothingStep, ...], nodes: IntArray, d_nodes: FloatArray
             ) -> tuple[IntArray, FloatArray]:
    """:func:`smooth` with arrays: corrections ``d_nodes`` (k, 6) of the prior nodes ``nodes``
    in, every node's correction out (``(m,)`` node indices in increasing order, ``(m, 6)``)."""
    d = smooth(steps, dict(zip(np.asarray(nodes).tolist(), np.asarray(d_nodes))))
    idx = np.array(sorted(d), dtype=np.int64)
    return idx, (np.stack([d[int(i)] for i in idx]) if idx.size else np.zeros((0, 6)))


def smooth(steps: tuple[SmoothingStep | SparseSmoothing, ...],
           d_known: dict[int, FloatArray]
           ) -> dict[int, FloatArray]:
    """Back substitution through elimination steps, newest first (Rauch-Tung-Striebel style).

    Parameters
    ----------
    steps : from :func:`_eliminate_absorbed`, in elimination order.
    d_known : tangent corrections (6,) of the prior nodes, by node index.

    Returns
    -------
    Corrections of every node (prior nodes and eliminated ones), by node index.
    """
    d = dict(d_known)
    for st in reversed(steps):
        dR = np.concatenate([d.get(int(i), np.zeros(6)) for i in st.remaining]
                            or [np.zeros(0)])
        dL = st.back(dR)
        for k, i in enumerate(st.eliminated.tolist()):
            d[i] = dL[6 * k:6 * k + 6]
    return d


def _prior_of(work: _Marginal, group: IntArray, T_lin: FloatArray, band: int = -1,
              hubs: int = 0) -> AbsorbedPrior:
    """The prior of one group of prior nodes (in index order) from the dense marginal
    ``work`` (:func:`marginal_prior` with nothing left to eliminate)."""
    at = (6 * np.array([work.cols[int(i)] for i in group])[:, None] + np.arange(6)).ravel()
    group = np.asarray(group, dtype=np.int64)
    return marginal_prior(group, work.H[np.ix_(at, at)], work.g[at],
                          np.ones(group.size, dtype=bool), T_lin[group], band, hubs)


def sparse_prior_applies(m: int, band: int, hubs: int) -> bool:
    """Whether a prior over ``m`` nodes is built sparse (:func:`band_prior`): ``band >= 0``
    and more nodes than the skeleton keeps densely anyway (else the exact dense prior)."""
    return 0 <= band and m > band + 1 + max(hubs, 0)


def band_prior(T_lin: FloatArray, skeleton: CovarianceSkeleton, step: FloatArray
               ) -> tuple[FloatArray, sp.bsr_matrix]:
    """The sparse joint prior of absorbed terms over nodes ordered along the trajectory.

    The exact marginal of the absorbed terms on the prior nodes ``S`` (Schur complement) has a
    dense information that couples the whole swath. This prior keeps its mean (the absorbed
    terms' own optimum on ``S``, ``T_lin`` moved by the step ``H^-1 g``) and replaces its
    covariance ``Sigma_S`` by the maximum-entropy Gaussian that agrees with it on a skeleton
    (:class:`~ga_ros.core.linalg.banded.CovarianceSkeleton`): a band of ``w`` nodes along the
    trajectory plus a few hub nodes spread along it. Every node's marginal covariance, its
    correlations with the ``w`` nodes before and after it and with every hub are exact; the
    hubs keep the long-range correlations (a band alone made the boundary's common drift look
    several times better known than it is: overconfident window covariances). The information
    is block-banded plus ``h`` dense block rows (sparse window factorisations, linear in the
    swath length). The aligner's freeze and the background refinement both build their priors
    here.

    Parameters
    ----------
    T_lin : (m, 4, 4) linearisation point of the prior nodes, in band order.
    skeleton : the kept entries of ``Sigma_S`` (blocks ``[x y z rx ry rz]``).
    step : (6m,) ``H^-1 g``, the absorbed terms' optimum on ``S`` as a tangent step from
        ``T_lin`` (``-step``).

    Returns
    -------
    T_mean : (m, 4, 4); information : (6m, 6m) sparse BSR (see :func:`tangent_prior`).
    """
    return tangent_prior(T_lin, skeleton.information(), None, step=step)


def tangent_prior(T_lin: FloatArray, H: FloatArray, g: FloatArray | None,
                  iterations: int = 4, step: FloatArray | None = None
                  ) -> tuple[FloatArray, FloatArray]:
    """Mean and information of a Gaussian prior whose cost matches ``(d + H^-1 g)' H (d + H^-1
    g)`` to second order at ``T_lin`` (``d`` the right-perturbation tangent of the ``k`` poses).

    The solver's prior residual (:func:`ga_ros.core.models.prior_residual`) takes position and
    rotation apart: ``e = [R_mean' (p - p_mean), log(R_mean' R)]``, Jacobian ``B = diag(R_mean'
    R, J_r(phi)^-1)`` per node. Here ``p_mean = p_lin - R_lin s_p`` and ``R_mean = R_lin
    exp(-phi)`` with ``phi = J_r(phi)^-1 s_phi`` (a fixed point, a few iterations), ``s = H^-1
    g``, so that ``e(T_lin) = B s``; with ``H' = B^-T H B^-1`` the gradient ``B' H' e`` and the
    Gauss-Newton matrix ``B' H' B`` at ``T_lin`` are exactly ``g`` and ``H`` (the plain shift
    ``T_lin exp(-s)``, ``H' = H`` is off by ``O(|s| |g|)``).

    Why not the SE(3) tangent ``log(T_mean^-1 T)``: the prior is a change of variables away from
    the same quadratic at ``T_lin``, but it has to hold where the next tracks move the boundary,
    on a long swath ~100 m and ~3 deg along its weakly determined bending mode. The absorbed
    connections are relative motions, so their cost depends on rotations and on *differences*
    of world positions; the tangent's translation ``J_l(phi)^-1 R_mean' (p - p_mean)`` mixes the
    rotation with the absolute displacement (``phi x dp / 2``: metres there), the split residual
    only with differences of displacements. On 200-pose swaths at 20 % noise the true absorbed
    cost at the window's boundary rose 303 above the freeze estimate; the tangent prior said 232
    (the window then ends 12 batch sd^2 from the batch solution, covariances 0.67 of it), the
    split one 314 (0.08 batch sd^2, 0.92): ``test/test_nees_long_swaths.py``, docs/design.md
    "The frozen prior's residual: position and rotation apart".

    Parameters
    ----------
    T_lin : (k, 4, 4) linearisation point ``T_world_node``.
    H : (6k, 6k) information, node-major ``[x y z rx ry rz]``, dense or ``scipy.sparse`` (its
        block pattern is kept); g : (6k,) half gradient.
    step : (6k,) ``H^-1 g`` where the caller already has it (from a factorisation of its own);
        ``g`` is then not used.

    Returns
    -------
    T_mean : (k, 4, 4); information : (6k, 6k), sparse (BSR) if ``H`` is.
    """
    k = T_lin.shape[0]
    if step is not None:
        s = np.asarray(step, dtype=float)
    elif sp.issparse(H):
        from scipy.sparse.linalg import spsolve  # lazy: rarely needed

        s = spsolve(sp.csc_matrix(H), g)
    else:
        try:  # least squares only if the absorbed terms leave a direction free
            s = sla.cho_solve(sla.cho_factor(H), g)
        except np.linalg.LinAlgError:
            s = np.linalg.lstsq(H, g, rcond=None)[0]
    s = s.reshape(k, 6)
    phi = s[:, 3:]
    for _ in range(iterations):
        phi = (so3.right_jacobian_inv(phi) @ s[:, 3:, None])[:, :, 0]
    R_lin = T_lin[:, :3, :3]
    mean = T_lin.copy()
    mean[:, :3, :3] = R_lin @ so3.exp(-phi)
    mean[:, :3, 3] -= (R_lin @ s[:, :3, None])[:, :, 0]
    Binv = np.zeros((k, 6, 6))  # blocks of B^-1 at T_lin: R_lin' R_mean, J_r(phi)
    Binv[:, :3, :3] = so3.exp(-phi)
    Binv[:, 3:, 3:] = so3.right_jacobian(phi)
    if sp.issparse(H):  # block (a, b) becomes B_a^-T H_ab B_b^-1, on the same pattern
        Hb = sp.bsr_matrix(H, blocksize=(6, 6))
        Hb.sort_indices()
        rows = np.repeat(np.arange(k), np.diff(Hb.indptr))
        data = np.swapaxes(Binv[rows], 1, 2) @ Hb.data @ Binv[Hb.indices]
        return mean, sp.bsr_matrix((data, Hb.indices.copy(), Hb.indptr.copy()), shape=Hb.shape)
    info = H.reshape(k, 6, k, 6)
    info = np.einsum('aij,aibk,bkl->ajbl', Binv, info, Binv).reshape(6 * k, 6 * k)
    return mean, 0.5 * (info + info.T)


def _exit_with_parent(parent_pid: int) -> None:
    """In the worker process: exit when the aligner's process is gone (killed with SIGKILL,
    say), instead of living on as an orphan."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name='ga_refine_parent', daemon=True).start()


_SPAWN_LOCK = threading.Lock()


def _preparation_without_main(prepare):
    """``multiprocessing.spawn.get_preparation_data`` without the parent's main module."""
    def without_main(name: str) -> dict:
        data = prepare(name)
        data.pop('init_main_from_path', None)
        data.pop('init_main_from_name', None)
        return data
    return without_main


class _WorkerProcess(multiprocessing.context.SpawnProcess):
    """A spawned process that does not run the parent's main module again.

    A spawned child normally re-imports the script that started the parent (as
    ``__mp_main__``): a script without an ``if __name__ == '__main__':`` guard would run again
    in the refinement worker (its output twice, a second survey, a second worker refused in
    bootstrap). The worker needs nothing from it (its job and data come from ``ga_ros``), so
    the start-up data it receives leave the main module out (the rest -- ``sys.path``, working
    directory, authentication key -- is unchanged).
    """

    @staticmethod
    def _Popen(process_obj):  # noqa: N802 - multiprocessing's name
        from multiprocessing import spawn

        with _SPAWN_LOCK:
            prepare = spawn.get_preparation_data
            spawn.get_preparation_data = _preparation_without_main(prepare)
            try:
                return multiprocessing.context.SpawnProcess._Popen(process_obj)
            finally:
                spawn.get_preparation_data = prepare


class _WorkerContext(multiprocessing.context.SpawnContext):
    """The 'spawn' start method with :class:`_WorkerProcess`."""

    Process = _WorkerProcess


class RefinementWorker:
    """Runs :func:`refine_snapshot` off the update path and hands results back in order.

    At most one refinement is in flight. The executor (a one-worker process pool with the
    'spawn' start method that does not re-run the parent's main module, :class:`_WorkerProcess`;
    a one-worker thread pool; or none for ``'inline'``) is created on the
    first submission and shut down by :meth:`close` (also when the worker is garbage collected).

    Parameters
    ----------
    executor : one of :data:`REFINE_EXECUTORS`.
    """

    def __init__(self, executor: str = 'process') -> None:
        if executor not in REFINE_EXECUTORS:
            raise InputError(f'refine_executor must be one of {REFINE_EXECUTORS}, '
                             f'got {executor!r}')
        self.kind = executor
        self._pool: Executor | None = None
        self._pending: tuple[int, Future | RefinementSnapshot] | None = None

    @property
    def pending_due(self) -> int | None:
        """Track count at whose update the pending refinement is installed (``None``: none)."""
        return None if self._pending is None else self._pending[0]

    def submit(self, snap: RefinementSnapshot, due: int) -> None:
        """Start refining ``snap``; its result is due at the update of the ``due``-th track."""
        if self._pending is not None:
            raise InputError('a refinement is already in flight')
        if self.kind == 'inline':
            self._pending = (due, snap)
            return
        job = _refine_in_worker if self.kind == 'process' else refine_snapshot
        try:
            future = self._executor().submit(job, snap)
        except BrokenExecutor:  # the worker process died (its result said so): a new one
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
            future = self._executor().submit(job, snap)
        self._pending = (due, future)

    def _executor(self) -> Executor:
        """The executor, created on first use."""
        if self._pool is None:
            if self.kind == 'process':
                self._pool = ProcessPoolExecutor(
                    max_workers=1, mp_context=_WorkerContext(),
                    initializer=_exit_with_parent, initargs=(os.getpid(),))
            else:
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix='ga_refine')
        return self._pool

    def smooth(self, res: RefinementResult, nodes: IntArray, d_nodes: FloatArray
               ) -> tuple[IntArray, FloatArray]:
        """Back substitution of an installed result (:func:`smoothed`): in this process from
        ``res.smoothing``, or in the worker process that kept the steps
        (``res.smoothing_kept``; it is idle at this point of the hand-off, the next snapshot is
        submitted after the update). Raises :class:`InputError` if the worker is gone."""
        if not res.smoothing_kept:
            return smoothed(res.smoothing, nodes, d_nodes)
        if self._pool is None:
            raise InputError('the refinement worker that kept the smoothing is gone')
        try:
            return self._pool.submit(_smooth_in_worker, res.after_tracks, nodes,
                                     d_nodes).result()
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - a crashed worker must not end the survey
            raise InputError(f'smoothing in the worker failed: {type(exc).__name__}: '
                             f'{exc}') from exc

    def take(self, n_tracks: int) -> RefinementResult | None:
        """The pending result if it is due at the update of the ``n_tracks``-th track (waits
        for it), else ``None``. A worker that died yields a failed result."""
        if self._pending is None or self._pending[0] > n_tracks:
            return None
        _, job = self._pending
        self._pending = None
        if isinstance(job, RefinementSnapshot):
            return refine_snapshot(job)
        try:
            return job.result()
        except Exception as exc:  # noqa: BLE001 - a crashed worker must not end the survey
            return RefinementResult(-1, False, f'worker failed: {type(exc).__name__}: {exc}',
                                    np.zeros((0, 4, 4)), np.zeros((0, 6, 6)), (),
                                    np.zeros(0, bool), np.zeros(0, np.int64), (), 0, 0.0)

    def drop(self) -> None:
        """Forget the pending refinement (a reset, a restored state)."""
        if self._pending is not None and isinstance(self._pending[1], Future):
            self._pending[1].cancel()
        self._pending = None

    def close(self) -> None:
        """Drop the pending refinement and shut the executor down (without waiting)."""
        self.drop()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001, S110 - interpreter shutdown
            pass
