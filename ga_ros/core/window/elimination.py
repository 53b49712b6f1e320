"""The eliminations of the background refinement: the joint priors of absorbed connections
rebuilt at a refined estimate, the retirement of old tracks into the past prior, and the back
substitution (smoothing) through those eliminations (ROS-free).

The rebuilt priors come from one sparse elimination (:func:`sparse_eliminate`): every absorbed
term of the horizon, its frozen fixes and the past prior linearised and summed once, the back
substitution (:func:`smooth`) one solve with a sparse factor of the eliminated block, which a
worker process keeps (:mod:`ga_ros.core.window.worker`), the priors from that factor where they
are exact and over few nodes (:func:`priors_from_smoothing`), else by selected inversion or a
partial factorisation (:func:`sparse_priors`).
The track-by-track elimination on dense matrices of about two swaths (:class:`Marginal`:
interior nodes first, each gain over the nodes it is coupled to) gives the same priors and
smoothing; it runs when :data:`SPARSE_FROM_TRACK_NODES` is raised above the tracks' length (the
tests compare the two). Every prior is built by the freeze's rule,
:func:`~ga_ros.core.window.freeze.marginal_prior`.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior, normal_matrix_at
from ga_ros.core.window.freeze import (
    DENSE_SCHUR_MAX,
    AbsorbedPrior,
    marginal_prior,
    prior_nodes,
    sparse_prior_applies,
    tangent_prior,
)
from ga_ros.core.window.snapshot import RefinementSnapshot, SmoothingStep, SparseSmoothing
from ga_ros.core.window.storage import unpack_sym6
from ga_ros.errors import DegenerateGeometryError


def eliminate_absorbed(snap: RefinementSnapshot, T_lin: FloatArray, smoothing: bool = True
                        ) -> tuple[tuple[AbsorbedPrior, ...],
                                   tuple[SmoothingStep | SparseSmoothing, ...]]:
    """Joint Gaussian priors of every absorbed connection (status 1), linearised at ``T_lin``.

    The absorbed connections are summed in the order their tracks froze and every node that no
    later absorbed connection touches, and that is not a prior node (:func:`prior_nodes`), is
    eliminated as soon as its last connection is in (Schur complement): the working matrix spans
    about two tracks whatever the survey's length, and the result is the exact marginal of the
    absorbed terms on the prior nodes in the linear limit (the order of elimination does not
    change a Schur complement; ``test/core/window/test_refinement.py`` checks it against one dense
    elimination). As in the aligner's freezing, the absorbed terms are not at their optimum, so
    their marginal keeps a linear term ``g``: the prior mean is ``T_lin`` moved by ``-H^-1 g``.
    A bounded refinement's past prior (the terms of the retired tracks) enters first.

    Returns one prior per connected group of prior nodes (at most one in a lawnmower survey),
    and the elimination steps for back substitution (:class:`SmoothingStep`).

    Tracks of more than :data:`SPARSE_FROM_TRACK_NODES` nodes (by default every snapshot): one
    sparse elimination instead (:func:`sparse_eliminate`, the same priors, one
    :class:`SparseSmoothing`).

    Raises
    ------
    numpy.linalg.LinAlgError, ga_ros.errors.DegenerateGeometryError
        An eliminated group is not determined by the absorbed terms (no datum, no prior node).
    """
    absorbed = np.nonzero(snap.status == 1)[0]
    fixes = snap.frozen_fixes()
    if absorbed.size == 0 and not snap.past and not fixes:
        return (), ()
    n = snap.node_ids.size
    past_nodes = np.concatenate([p.nodes for p in snap.past + fixes]
                                or [np.zeros(0, np.int64)])
    keep = prior_nodes(snap.frozen, snap.src, snap.dst, snap.status, snap.freeze_policy,
                       past_nodes, snap.datum)
    if long_tracks(snap):
        return sparse_eliminate(snap, T_lin, keep, smoothing)
    rank = track_rank(snap)
    # a connection is added at the freeze of its later frozen end (the earlier end may be the
    # window's, under 'marginal'); a node is eliminated after its last absorbed connection.
    # The past prior (bounded refinement) comes first, at step -1.
    rs, rd = rank[snap.src[absorbed]], rank[snap.dst[absorbed]]
    fs, fd = snap.frozen[snap.src[absorbed]], snap.frozen[snap.dst[absorbed]]
    step = np.maximum(np.where(fs, rs, -1), np.where(fd, rd, -1))
    last = np.full(n, -1, dtype=np.int64)
    np.maximum.at(last, snap.src[absorbed], step)
    np.maximum.at(last, snap.dst[absorbed], step)
    # a frozen node's fixes (weighted parameters) enter at its track's freeze
    fix_node = np.array([int(p.nodes[0]) for p in fixes], dtype=np.int64)
    fix_step = rank[fix_node]
    np.maximum.at(last, fix_node, fix_step)
    stages = [(-1, absorbed[:0], snap.past)] if snap.past else []
    stages += [(int(s), absorbed[step == s], tuple(p for p, q in zip(fixes, fix_step) if q == s))
               for s in np.union1d(np.unique(step), fix_step)]
    work = Marginal()
    steps: list[SmoothingStep] = []
    for s, conns, priors in stages:
        work.add(*normal_terms(snap, conns, T_lin, priors))
        gone = [i for i in work.cols if last[i] <= s and not keep[i]]
        if gone:
            steps += work.eliminate(gone)
    if not work.cols:
        return (), tuple(steps)
    priors = tuple(prior_of(work, np.sort(group), T_lin, snap.prior_band, snap.prior_hubs)
                   for group in work.groups())
    return priors, tuple(steps)


class Marginal:
    """Dense marginal information ``(H, g)`` of absorbed terms over a changing set of nodes,
    with its block pattern (which node blocks of ``H`` are nonzero), for the eliminations of
    :func:`eliminate_absorbed` and :func:`retire_tracks`.

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


def prior_of(work: Marginal, group: IntArray, T_lin: FloatArray, band: int = -1,
              hubs: int = 0) -> AbsorbedPrior:
    """The prior of one group of prior nodes (in index order) from the dense marginal
    ``work`` (:func:`marginal_prior` with nothing left to eliminate)."""
    at = (6 * np.array([work.cols[int(i)] for i in group])[:, None] + np.arange(6)).ravel()
    group = np.asarray(group, dtype=np.int64)
    return marginal_prior(group, work.H[np.ix_(at, at)], work.g[at],
                          np.ones(group.size, dtype=bool), T_lin[group], band, hubs)


#: Tracks of more nodes than this make the eliminations of :func:`eliminate_absorbed` and
#: :func:`retire_tracks` sparse (:func:`sparse_eliminate`): every absorbed term linearised and
#: summed once per refinement, one sparse factorisation. The dense track-by-track ones (one
#: linearisation and one dense Schur complement per track, about two swaths at a time, cubic in
#: the swath's length) took twice the CPU of a whole refinement at 20 and at 204 poses per track
#: (0.16 against 0.09 s, 1.5 against 0.78 s; equal results to 1e-13), so every snapshot takes
#: the sparse one; tests raise the threshold to compare the two.
SPARSE_FROM_TRACK_NODES = 0


def long_tracks(snap: RefinementSnapshot) -> bool:
    """Whether the snapshot has a track of more than :data:`SPARSE_FROM_TRACK_NODES` nodes."""
    _, counts = np.unique(snap.track_ids, return_counts=True)
    return bool(counts.size) and int(counts.max()) > SPARSE_FROM_TRACK_NODES


def block_components(N: sp.csr_matrix, d: int) -> IntArray:
    """(k,) connected component of each ``d x d`` block of a symmetric CSR matrix of ``k``
    block rows (the graph of its nonzero blocks; the labels of
    :func:`scipy.sparse.csgraph.connected_components`). The block graph is ``N``'s own index
    arrays with every column divided by ``d`` and every ``d`` rows taken as one (duplicate,
    unsorted entries: no conversion, no sort)."""
    k = N.shape[0] // d
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    graph = sp.csr_matrix((np.ones(N.indices.size), N.indices // d,
                           np.ascontiguousarray(N.indptr[::d])),
                          shape=(k, k))
    return connected_components(graph, directed=False)[1]


def sparse_priors(free: IntArray, N: sp.spmatrix, u: FloatArray, target: BoolArray,
                   T_lin: FloatArray, band: int, hubs: int, label: IntArray | None = None
                   ) -> tuple[AbsorbedPrior, ...]:
    """The priors of sparse terms ``(N, u)`` over the nodes ``free`` on their ``target`` nodes
    (the others eliminated), one per connected group (:func:`marginal_prior` of each, so
    without a dense matrix of more than the group's targets). Equal to :func:`prior_of` of the
    dense elimination (``test/core/window/test_refinement.py``). ``label``: the blocks'
    components (:func:`block_components`) if the caller has them."""
    Nc = sp.csr_matrix(N)
    label = block_components(Nc, 6) if label is None else label
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


def sparse_eliminate(snap: RefinementSnapshot, T_lin: FloatArray, keep: BoolArray,
                      smoothing: bool = True
                      ) -> tuple[tuple[AbsorbedPrior, ...], tuple[SparseSmoothing, ...]]:
    """:func:`eliminate_absorbed` for long tracks: every absorbed term and the past prior in
    one sparse normal matrix, the priors from it (:func:`sparse_priors`) and (if
    ``smoothing``) one back substitution with a sparse factor of the eliminated nodes' block
    (:class:`SparseSmoothing`)."""
    absorbed = np.nonzero(snap.status == 1)[0]
    free, N, u = normal_terms(snap, absorbed, T_lin, snap.past + snap.frozen_fixes())
    N = sp.csr_matrix(N)  # once, for both
    kf = keep[free]
    L, R = np.nonzero(~kf)[0], np.nonzero(kf)[0]
    if L.size == 0 or not smoothing:
        return sparse_priors(free, N, u, kf, T_lin, snap.prior_band, snap.prior_hubs), ()
    cL = (6 * L[:, None] + np.arange(6)).ravel()
    cR = (6 * R[:, None] + np.arange(6)).ravel()
    NL = N[cL]
    sm = SparseSmoothing(free[L], free[R], NL[:, cL], NL[:, cR], u[cL])
    label = block_components(N, 6)
    priors = (priors_from_smoothing(sm, free, N, u, kf, T_lin, snap.prior_band,
                                    snap.prior_hubs, label)
              or sparse_priors(free, N, u, kf, T_lin, snap.prior_band, snap.prior_hubs, label))
    return priors, (sm,)


#: :func:`priors_from_smoothing` takes at most this many prior unknowns (``6 k``, ``k`` prior
#: nodes; right-hand sides of its solve), else :func:`sparse_priors` builds the priors.
FACTOR_PRIOR_MAX_UNKNOWNS = 600


def priors_from_smoothing(sm: SparseSmoothing, free: IntArray, N: sp.csr_matrix,
                          u: FloatArray, target: BoolArray, T_lin: FloatArray, band: int,
                          hubs: int, label: IntArray | None = None
                          ) -> tuple[AbsorbedPrior, ...] | None:
    """:func:`sparse_priors` from the smoothing's factor of ``N_LL`` (no second factorisation),
    where every group's prior is the exact one from a partial factorisation
    (:func:`~ga_ros.core.window.freeze.marginal_prior`: few prior nodes, more than
    :data:`~ga_ros.core.window.freeze.DENSE_SCHUR_MAX` eliminated unknowns): ``X = N_LL^-1
    [N_LR, u_L]`` (``6 k + 1`` right-hand sides, ``k`` prior nodes), the Schur complement
    ``H = N_RR - N_RL X_R`` and ``g = u_R - N_RL x_u`` of all groups at once (block diagonal
    over the groups: their eliminated nodes are not coupled), each group's prior
    (:func:`~ga_ros.core.window.freeze.tangent_prior` at the step ``H^-1 g``, as the partial
    factorisation's). The same priors as :func:`sparse_priors` up to rounding
    (``test/core/window/test_fixes_refinement.py``). ``None`` where that path does not apply (many
    prior nodes, a banded prior, a group without eliminated nodes, ``H`` not positive
    definite): the caller takes :func:`sparse_priors`. With CHOLMOD's own factor the solve is
    its forward half, ``Y = L^-1 P [N_LR, u_L]``, and ``N_RL X = Y_R' Y``.

    Parameters
    ----------
    sm : the sparse smoothing of the eliminated nodes ``free[~target]`` onto ``free[target]``.
    free, N, u, target, T_lin, band, hubs, label : as :func:`sparse_priors` (``N`` CSR).
    """
    R = np.nonzero(target)[0]
    if 6 * R.size > FACTOR_PRIOR_MAX_UNKNOWNS or R.size == 0:
        return None
    label = block_components(N, 6) if label is None else label
    groups = []
    for c in np.unique(label):
        mine = label == c
        n_keep = int((mine & target).sum())
        if n_keep == 0:
            continue
        if (sparse_prior_applies(n_keep, band, hubs)
                or 6 * int((mine & ~target).sum()) <= DENSE_SCHUR_MAX):
            return None
        groups.append(np.nonzero(label[R] == c)[0])  # positions in R
    cR = (6 * R[:, None] + np.arange(6)).ravel()
    B = np.column_stack([sm.N_LR.toarray(), sm.u_L])
    try:
        Y = sm.forward_eliminated(B)  # L^-1 P B of N_LL = P' L L' P: B' N_LL^-1 B = Y' Y
        G = Y[:, :-1].T @ Y if Y is not None else B[:, :-1].T @ sm.solve_eliminated(B)
    except DegenerateGeometryError:
        return None
    H_all = N[cR][:, cR].toarray() - G[:, :-1]
    g_all = u[cR] - G[:, -1]
    priors = []
    for pos in groups:
        at = (6 * pos[:, None] + np.arange(6)).ravel()
        H = H_all[np.ix_(at, at)]
        H = 0.5 * (H + H.T)
        try:
            cho = sla.cho_factor(H, lower=True)
        except np.linalg.LinAlgError:
            return None  # H singular: the least-squares step of the dense path
        step = sla.cho_solve(cho, g_all[at])
        nodes = free[R[pos]]
        mean, info = tangent_prior(T_lin[nodes], H, None, step=step)
        priors.append(AbsorbedPrior(nodes, mean, info, info.shape[0]))
    return tuple(priors)


def gaussian(snap: RefinementSnapshot, priors: tuple[AbsorbedPrior, ...]
              ) -> list[GaussianPrior]:
    """The solver's form of priors over snapshot nodes.

    The single-node priors (the absolute fixes' weighted parameters, one per node), if their
    nodes are distinct, become one prior with a block-diagonal information, in their order and
    where the first of them stood: the same terms of the normal equations, added in the same
    order, from one vectorised evaluation instead of one per fix.
    """
    single = [k for k, p in enumerate(priors) if p.nodes.size == 1]
    nodes = np.array([int(priors[k].nodes[0]) for k in single], dtype=np.int64)
    if len(single) < 2 or np.unique(nodes).size != nodes.size:
        return [GaussianPrior(snap.node_ids[p.nodes], p.T_world_node, p.information)
                for p in priors]
    merged = GaussianPrior(
        snap.node_ids[nodes], np.concatenate([priors[k].T_world_node for k in single]),
        sp.block_diag([_dense(priors[k].information) for k in single],
                      format='bsr').tobsr(blocksize=(6, 6)))
    out: list[GaussianPrior] = []
    for k, p in enumerate(priors):
        if p.nodes.size != 1:
            out.append(GaussianPrior(snap.node_ids[p.nodes], p.T_world_node, p.information))
        elif k == single[0]:
            out.append(merged)
    return out


def _dense(information) -> FloatArray:
    return information.toarray() if sp.issparse(information) else np.asarray(information, float)


def normal_terms(snap: RefinementSnapshot, conns: IntArray, T_lin: FloatArray,
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
    N, free_ids, u = normal_matrix_at(net, T_lin[nodes], 'se3', fixed, gaussian(snap, priors),
                                      jit=True)
    free = nodes[nodes != 0] if datum else nodes
    assert free.size == free_ids.size
    return free, N, u


def track_rank(snap: RefinementSnapshot) -> IntArray:
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
    rank = track_rank(snap)
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
    e = int((track_rank(snap) < k).sum())
    conns = np.nonzero((snap.status == 1) & ((snap.src < e) | (snap.dst < e)))[0]
    terms = snap.past + snap.frozen_fixes(before=e)  # the retiring nodes' fixes go with them
    if long_tracks(snap):
        free, N, u = normal_terms(snap, conns, T_lin, terms)
        return sparse_priors(free, N, u, free >= e, T_lin, snap.prior_band, snap.prior_hubs)
    work = Marginal()
    work.add(*normal_terms(snap, conns, T_lin, terms))
    gone = [i for i in work.cols if i < e]
    if len(gone) == len(work.cols):
        return ()
    if gone:
        work.eliminate(gone)
    return tuple(prior_of(work, np.sort(group), T_lin, snap.prior_band, snap.prior_hubs)
                 for group in work.groups())


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
    steps : from :func:`eliminate_absorbed`, in elimination order.
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
