"""Freezing a track that leaves the window: the freeze policies and all their maths.

A track that leaves the window stops being an unknown of the window adjustments. Its
connections are absorbed into joint Gaussian priors (Schur complements of their normal
equations, eq. 17 and Sec. III-E of the paper), each connection entering either the window
problem or one prior, never both, so the published covariances are not overconfident. A policy
(:data:`FREEZE_POLICIES`, keyed by ``AlignerConfig.freeze_policy``) decides which connections a
freeze absorbs and which nodes the priors are over:

* :class:`WeightedFreeze` (``'weighted'``, the paper): only connections whose two ends are
  frozen are absorbed; frozen nodes that keep an active connection to the window stay in the
  prior as weighted parameters (with their joint covariance);
* :class:`MarginalFreeze` (``'marginal'``): every active connection of the leaving track is
  absorbed and the track eliminated onto the window nodes it touched (as fixed-lag smoothers
  do).

Both the aligner's freeze (:meth:`FreezePolicy.plan`) and the background refinement's rebuilt
priors (:mod:`ga_ros.core.window.elimination`) build a prior with :func:`marginal_prior`: exact
mean, information exact (dense) or sparse on a skeleton (:func:`band_prior`: a band along the
trajectory plus hub nodes, maximum entropy beyond it), residual with position and rotation
apart (:func:`tangent_prior`). Adding a policy is one subclass of :class:`FreezePolicy` and one
entry in :data:`FREEZE_POLICIES`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.linalg import selinv
from ga_ros.core.linalg.cholesky import trailing_factor
from ga_ros.core.linalg.completion import CovarianceSkeleton
from ga_ros.core.solver import GaussianPrior, SolveResult, normal_matrix_at
from ga_ros.core.window.state import WindowState
from ga_ros.errors import DegenerateGeometryError, InputError
from ga_ros.geometry import so3


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


class JointPrior(tuple):
    """One joint prior as the aligner keeps it: ``(node rows (k,), T_mean (k, 4, 4),
    information (6k, 6k))``, unpacked as that 3-tuple (state files, the refinement's snapshot),
    with the rank of the information in ``rank`` when known (a prior positive definite by
    construction: ``6k``), so that no window solve factors the information again only to count
    its equations (``None``: determined once, on first use,
    :meth:`~ga_ros.core.window.update.WindowUpdate.ranked`).
    """

    def __new__(cls, idx: IntArray, mean: FloatArray, info, rank: int | None = None
                ) -> JointPrior:
        out = super().__new__(cls, (idx, mean, info))
        out.rank = rank
        return out

    def __reduce__(self):
        return (JointPrior, (*self, self.rank))

    @classmethod
    def absorbed(cls, p: AbsorbedPrior, first_node: int = 0) -> JointPrior:
        """The aligner's prior of a refinement's :class:`AbsorbedPrior`
        (node rows relative to the snapshot's ``first_node``), with its rank."""
        return cls(p.nodes + first_node, p.T_world_node, p.information, p.rank)


@dataclass(frozen=True)
class FreezePlan:
    """Everything freezing one leaving track changes, computed without changing the aligner
    (:meth:`FreezePolicy.plan`) and installed by :func:`install_freeze`.

    Attributes
    ----------
    track : the leaving track.
    nodes : (k,) its node rows.
    cov_rows : (c,) rows whose marginal covariance is stored, ``cov`` (c, 6, 6) those blocks
        (``None``: not computed, left to the installer, see ``covariances``).
    absorbed : connection rows absorbed into the new prior (status 1 from now on).
    dropped : indices (into the aligner's list of priors) of the priors merged into it.
    prior : the new joint prior (``None``: no node kept, the absorbed terms vanish, or not
        computed yet: see ``later_prior``).
    covariances : when ``cov`` is ``None``, computes those blocks (from the last adjustment's
        factor, which must not have changed since).
    later_prior : when not ``None``, computes ``prior`` (left to the installer, like ``cov``:
        a refinement installed by the same update replaces every prior); it reads the tables
        rows of the plan and the priors it merges, which must not have changed since.
    """

    track: int
    nodes: IntArray
    cov_rows: IntArray
    cov: FloatArray | None
    absorbed: IntArray
    dropped: tuple[int, ...]
    prior: JointPrior | None
    covariances: Callable[[], FloatArray] | None = None
    later_prior: Callable[[], JointPrior | None] | None = None


#: ``terms(rows)``: the covariances, weights and measured motions of connection rows, as
#: attributes ``cov``, ``weights`` (``cov^-1``), ``T_meas`` and ``T_meas_inv`` ((m, 6, 6) and
#: (m, 4, 4) arrays in the rows' order; :func:`ga_ros.core.window.update.connection_terms`).
ConnectionTermsOf = Callable[[IntArray], object]


#: Freezing: above this many leaving nodes, their marginal covariances come from one partial
#: factorisation of the window with them ordered last, below it from sparse solves.
TRAILING_MIN_NODES = 24


#: Freezing with block-banded priors: from this many leaving nodes on, their covariances come
#: from the banded selected inversion of the window (linear in the swath length) instead of the
#: trailing dense block (cubic in it); the two cross over at a few hundred nodes (figures:
#: docs/benchmarks.md, "Figures behind constants in the code").
BANDED_MIN_NODES = 300


class FreezePolicy:
    """How a leaving track is frozen: which of its connections are absorbed
    (:meth:`absorbs`) and which nodes the priors are over (:meth:`prior_nodes`); the freeze
    itself (:meth:`plan`, :meth:`marginalise`) is the same maths for every policy."""

    #: The ``AlignerConfig.freeze_policy`` string of the policy.
    name = ''

    def absorbs(self, frozen_src: BoolArray, frozen_dst: BoolArray) -> BoolArray:
        """Which active connections of a leaving track are absorbed, given whether each one's
        source and destination node is frozen once the track has frozen."""
        raise NotImplementedError

    def prior_nodes(self, frozen: BoolArray, src: IntArray, dst: IntArray, status: IntArray
                    ) -> BoolArray:
        """``(n,)`` mask of the nodes the priors of the absorbed connections may be over, of
        node flags ``frozen``, connection ends ``src``, ``dst`` (node rows) and ``status``."""
        raise NotImplementedError

    def plan(self, state: WindowState, track: int, res: SolveResult | None,
             last_window: IntArray, priors: list, n: int, nc: int, band: int, hubs: int,
             factor_lock: threading.Lock, covariances: bool = True,
             terms: ConnectionTermsOf | None = None) -> FreezePlan:
        """The freeze of ``track`` (:class:`FreezePlan`) from the last adjustment ``res`` (of
        the nodes ``last_window``), the joint priors ``priors``, the first ``n`` nodes and
        ``nc`` connections; reads the tables of ``state`` and changes nothing in them (it may run
        in a background thread while measurements are added: those rows come after ``n``,
        ``nc``). ``band``, ``hubs``: ``prior_band``, ``prior_hubs``; ``factor_lock`` guards
        ``res``'s factor (shared with the covariance queries). ``covariances=False``: the leaving
        nodes' marginal covariances are not computed (``plan.cov`` is ``None``) but left to
        ``plan.covariances`` (for a freeze whose covariances a refinement installed with it
        replaces); the new prior is then not computed either (``plan.prior`` is ``None``, left
        to ``plan.later_prior``: that refinement replaces every prior). ``terms``: the
        absorbed connections' covariances, weights and measured motions
        (:data:`ConnectionTermsOf`: the last window's, which held them), else computed
        here."""
        nodes = np.array(state.track_nodes[track], dtype=np.int64)
        # the new prior first: a covariance asked for right after an update (the node's newest
        # pose) factors the last adjustment's system meanwhile, and the selected inversion
        # below then reuses that factorisation
        later_prior = prior = None
        if covariances:
            absorbed, dropped, prior = self.marginalise(state, nodes, priors, n, nc, band, hubs,
                                                        terms)
        else:  # the refinement installed with this freeze replaces every prior
            absorbed, dropped, later_prior = self.absorption(state, nodes, priors, n, nc, band,
                                                             hubs, terms)
        cov_rows, cov = np.zeros(0, np.int64), np.zeros((0, 6, 6))
        if res is not None:
            inside = nodes[np.isin(nodes, last_window)]
            if inside.size:
                ids = state.idarr.a[inside]
                sel = np.isin(ids, res.free_node_ids)
                if sel.any():
                    banded = band >= 0 and sel.sum() >= BANDED_MIN_NODES
                    later = partial(_locked_marginals, factor_lock, res, ids[sel], banded)
                    cov = later() if covariances else None
                    cov_rows = inside[sel]
                    if cov is None:
                        return FreezePlan(int(track), nodes, cov_rows, None, absorbed, dropped,
                                          prior, later, later_prior)
        return FreezePlan(int(track), nodes, cov_rows, cov, absorbed, dropped, prior,
                          later_prior=later_prior)

    def marginalise(self, state: WindowState, L: IntArray, priors: list, n: int, nc: int,
                    band: int, hubs: int, terms: ConnectionTermsOf | None = None
                    ) -> tuple[IntArray, tuple[int, ...], JointPrior | None]:
        """:meth:`absorption` with the new prior computed."""
        conns, dropped, prior = self.absorption(state, L, priors, n, nc, band, hubs, terms)
        return conns, dropped, None if prior is None else prior()

    def absorption(self, state: WindowState, L: IntArray, priors: list, n: int, nc: int,
                   band: int, hubs: int, terms: ConnectionTermsOf | None = None
                   ) -> tuple[IntArray, tuple[int, ...], Callable[[], JointPrior] | None]:
        """Absorb the terms of the leaving nodes ``L`` (rows of ``state``) into one joint Gaussian
        prior.

        ``'marginal'``: every active connection of ``L`` is absorbed and ``L`` is eliminated
        (Schur complement) onto the window nodes it touched. ``'weighted'``: only connections
        whose two ends are frozen (after this freeze) are absorbed; frozen nodes that keep an
        active connection to the window stay in the prior (the paper's weighted parameters, with
        their joint covariance), every other frozen node of the absorbed terms is eliminated.
        In both cases each connection enters either the window problem or one prior, never
        both, so the prior is the exact marginal in the linear limit and covariances are not
        overconfident. Priors (of ``priors``) that share nodes with the absorbed terms are
        merged in. Returns the absorbed connection rows, the indices of the merged priors and
        a function that computes the new prior (``None`` if no node is kept: there is none);
        changes nothing. The function reads the rows below ``n`` of ``state`` and the merged
        priors' values, which it holds. ``terms``: as in :meth:`plan`.
        """
        src, dst, status0 = state.src.a[:nc], state.dst.a[:nc], state.status.a[:nc]
        in_L = np.zeros(n, dtype=bool)
        in_L[L] = True
        frozen_after = state.frozen[:n] | in_L
        conns = state.track_connections(np.unique(state.trackarr.a[L]).tolist())
        conns = conns[conns < nc]
        conns = conns[(status0[conns] == 0) & (in_L[src[conns]] | in_L[dst[conns]])]
        conns = conns[self.absorbs(frozen_after[src[conns]], frozen_after[dst[conns]])]
        involved = in_L.copy()
        involved[src[conns]] = True
        involved[dst[conns]] = True
        touching = [p for p, (idx, _, _) in enumerate(priors) if involved[idx].any()]
        for p in touching:
            involved[priors[p][0]] = True
        free_datum = state.fixes.has_gauge  # datum 'fixes': the first node is not held fixed
        if not free_datum:
            involved[0] = False  # the datum is fixed, never a prior node
        allnodes = np.nonzero(involved)[0]
        # nodes that keep an active connection (other than the absorbed ones) to a node that is
        # not frozen stay in the prior; the others are eliminated
        status = status0.copy()
        status[conns] = 1
        act = np.nonzero(status == 0)[0]
        s_, d_ = src[act], dst[act]
        keep = ~frozen_after.copy()
        keep[s_[~frozen_after[d_]]] = True
        keep[d_[~frozen_after[s_]]] = True
        ids = state.idarr.a[:n]
        merged = [GaussianPrior(ids[priors[p][0]], priors[p][1], priors[p][2]) for p in touching]
        merged += state.fixes.priors(L, state.T, ids)  # the leaving nodes' fixes stay in it
        dropped = tuple(touching)
        datum = bool(((src[conns] == 0) | (dst[conns] == 0)).any()) and not free_datum
        net_nodes = np.concatenate([[0], allnodes]) if datum else allnodes
        fixed = [ids[0]] if datum else []
        # the free nodes of the absorbed terms are ``allnodes`` (the datum, if among them,
        # is fixed and was left out): no node kept, no prior
        if not keep[allnodes].any():
            return conns, dropped, None

        return conns, dropped, partial(new_prior, state, net_nodes, conns, fixed, merged, terms,
                                       keep, int(band), int(hubs))


def new_prior(state: WindowState, net_nodes: IntArray, conns: IntArray, fixed: list,
              merged: list[GaussianPrior], terms: ConnectionTermsOf | None, keep: BoolArray,
              band: int, hubs: int) -> JointPrior:
    """The joint prior of the absorbed connections ``conns`` and the priors ``merged`` over the
    nodes ``net_nodes`` (rows of ``state``, ``fixed`` the datum's id if held), on the nodes
    flagged in ``keep`` (the others eliminated), linearised at ``state.T``
    (:meth:`FreezePolicy.absorption`) with the compiled kernels that the window's solves use
    (``normal_matrix_at(jit=True)``: ~2 ms less per freeze on the aerial survey than the NumPy
    linearisation, the same values to rounding)."""
    ids = state.idarr.a
    T = state.T  # the rows of the plan: not changed by adding measurements
    if terms is None:
        net = state.subnetwork(net_nodes, conns)
        N, free_ids, u = normal_matrix_at(net, T[net_nodes], 'se3', fixed, merged, jit=True)
    else:  # the same values as computing them (each depends on its measurement only)
        kept_terms = terms(conns)
        net = state.subnetwork(net_nodes, conns, kept_terms.cov)
        N, free_ids, u = normal_matrix_at(net, T[net_nodes], 'se3', fixed, merged,
                                          kept_terms.weights,
                                          (kept_terms.T_meas, kept_terms.T_meas_inv), jit=True)
    row_of = dict(zip(ids[net_nodes].tolist(), net_nodes.tolist()))
    free_idx = np.array([row_of[int(i)] for i in free_ids], dtype=np.int64)
    kept = keep[free_idx]
    p = marginal_prior(free_idx, N, u, kept, T[free_idx[kept]], band, hubs,
                       coords=T[free_idx, :3, 3])
    return JointPrior.absorbed(p)


class WeightedFreeze(FreezePolicy):
    """The paper's weighted parameters (Sec. III-E): a connection is absorbed once both its
    ends are frozen; frozen nodes that keep an active connection to a node that is not frozen
    stay in the prior."""

    name = 'weighted'

    def absorbs(self, frozen_src: BoolArray, frozen_dst: BoolArray) -> BoolArray:
        return frozen_src & frozen_dst

    def prior_nodes(self, frozen: BoolArray, src: IntArray, dst: IntArray, status: IntArray
                    ) -> BoolArray:
        act = status == 0
        keep = np.zeros(frozen.size, dtype=bool)
        s_, d_ = src[act], dst[act]
        keep[s_[~frozen[d_]]] = True
        keep[d_[~frozen[s_]]] = True
        return keep & frozen


class MarginalFreeze(FreezePolicy):
    """Exact marginalisation: every active connection of the leaving track is absorbed; the
    priors are over nodes that are not frozen."""

    name = 'marginal'

    def absorbs(self, frozen_src: BoolArray, frozen_dst: BoolArray) -> BoolArray:
        return np.ones(frozen_src.shape, dtype=bool)

    def prior_nodes(self, frozen: BoolArray, src: IntArray, dst: IntArray, status: IntArray
                    ) -> BoolArray:
        return ~frozen


#: The freeze policies by their ``AlignerConfig.freeze_policy`` name.
FREEZE_POLICIES: dict[str, FreezePolicy] = {p.name: p for p in (WeightedFreeze(),
                                                                MarginalFreeze())}


def freeze_policy(name: str) -> FreezePolicy:
    """The policy of a ``freeze_policy`` name (:class:`InputError` for an unknown one)."""
    try:
        return FREEZE_POLICIES[name]
    except KeyError:
        raise InputError(f'freeze_policy must be one of {tuple(FREEZE_POLICIES)}, got '
                         f'{name!r}') from None


def prior_nodes(frozen: BoolArray, src: IntArray, dst: IntArray, status: IntArray,
                freeze_policy_name: str, touched_by: IntArray | None = None,
                datum: bool = True) -> BoolArray:
    """Which nodes the priors of the absorbed connections are over (``(n,)`` mask).

    The policy's nodes (:meth:`~ga_ros.core.window.freeze.FreezePolicy.prior_nodes`:
    ``'weighted'``, frozen nodes that keep an active connection to a node that is not frozen;
    ``'marginal'``, nodes that are not frozen); of them only nodes touched by an absorbed
    connection (or listed in ``touched_by``: the past prior's
    nodes) count, and never the datum (index 0, if ``datum``).
    """
    n = frozen.size
    keep = freeze_policy(freeze_policy_name).prior_nodes(frozen, src, dst, status)
    touched = np.zeros(n, dtype=bool)
    touched[src[status == 1]] = True
    touched[dst[status == 1]] = True
    if touched_by is not None:
        touched[touched_by] = True
    keep &= touched
    if datum and n:
        keep[0] = False
    return keep


def install_freeze(state: WindowState, plan: FreezePlan) -> None:
    """Apply a freeze (:class:`FreezePlan`) to ``state``: covariances, absorbed connections,
    priors,
    frozen flags."""
    if plan.cov_rows.size and plan.cov is not None:
        state.cov[plan.cov_rows] = plan.cov
    state.status.a[plan.absorbed] = 1
    dropped = set(plan.dropped)
    state.priors = [p for q, p in enumerate(state.priors) if q not in dropped]
    if plan.prior is not None:
        state.priors.append(plan.prior)
    state.frozen[plan.nodes] = True


def _locked_marginals(lock: threading.Lock, res: SolveResult, node_ids: IntArray,
                      banded: bool) -> FloatArray:
    """:func:`marginal_covariances` under ``lock`` (``res``'s factor, shared with the covariance
    queries)."""
    with lock:
        return marginal_covariances(res, node_ids, banded)


def marginal_covariances(res: SolveResult, node_ids: IntArray, banded: bool = False
                          ) -> FloatArray:
    """``(k, 6, 6)`` marginal covariances of free nodes of an adjustment (eq. 17).

    Many nodes (a track leaving the window), with the compiled kernels: selected inversion
    (:class:`~ga_ros.core.linalg.selinv.SelectedInverse`, Takahashi's equations in place) on the
    adjustment's own sparse factor, refactored at the solution with its symbolic analysis (the
    analysis is handed back, so the next window solve does not repeat it): every node block of
    ``N^-1`` in about the time of one factorisation. Without the kernels: ``banded`` (the
    window's priors are block-banded, ``prior_band >= 0``) the block-tridiagonal selected
    inversion of :meth:`SolveResult.covariance`, otherwise the window's normal matrix factored
    once more with those nodes ordered last (the trailing dense block of the factor is the
    Cholesky factor of their joint marginal information ``S = L L'``; the diagonal blocks of
    ``S^-1 = L^-T L^-1`` are read from ``L^-1``). All exact. Few nodes: sparse solves.
    """
    ids = np.asarray(node_ids, dtype=np.int64)
    sysm = res._system
    if ids.size > TRAILING_MIN_NODES and sysm is not None:
        cols = sysm.col[sysm.index_of(ids)]
        if (cols >= 0).all():
            if selinv.COMPILED:
                try:
                    return _selected_marginals(sysm, cols)
                except DegenerateGeometryError:  # not positive definite: the general path
                    pass
            elif not banded:
                try:
                    return trailing_factor(sysm.pattern, sysm.data, cols).marginal_blocks()
                except DegenerateGeometryError:  # not positive definite there: the general path
                    pass
    return res.covariance(ids)


def _selected_marginals(sysm, cols: IntArray) -> FloatArray:
    """Diagonal blocks of ``N^-1`` for the block columns ``cols`` of a solve's normal system by
    selected inversion on its factor (numeric factorisation at the solution, symbolic analysis
    reused and kept: after the in-place inversion the factor object is a valid symbolic one
    again, factored anew by the next solve that is handed it)."""
    chol = sysm.chol  # factored at the solution (the solve's analysis reused)
    sysm.take_factor()
    analysis = chol.analysis
    inv = selinv.SelectedInverse(chol, columns=cols)  # their supernodes and ancestors
    blocks = inv.diagonal_blocks(cols)
    if inv.in_place:  # CHOLMOD refactors a supernodal factor of the same pattern in place
        chol.keep_analysis(analysis)
        sysm.give_factor(chol)
    return blocks


#: :func:`marginal_prior`: above this many eliminated unknowns, the exact Schur complement of a
#: sparse ``N`` comes from a partial sparse factorisation
#: (:func:`~ga_ros.core.linalg.cholesky.trailing_factor`), below it from dense blocks.
DENSE_SCHUR_MAX = 300


def marginal_prior(nodes: IntArray, N: FloatArray | sp.spmatrix, u: FloatArray,
                   keep: BoolArray, T_keep: FloatArray, band: int, hubs: int,
                   coords: FloatArray | None = None) -> AbsorbedPrior:
    """The joint Gaussian prior that absorbed terms leave on some of their nodes: the one rule
    of the aligner's freeze (:meth:`FreezePolicy.marginalise`) and
    of the refinement's rebuilt priors (:mod:`ga_ros.core.window.elimination`).

    The terms' normal matrix ``N`` and half gradient ``u`` (linearised at the nodes' poses) are
    marginalised onto the nodes ``keep`` (Schur complement ``H``, ``g``; the others
    eliminated). The prior's mean is the terms' own optimum on them (``T_keep`` moved by the
    step ``H^-1 g``, :func:`tangent_prior`); its information is:

    * **sparse** (:func:`sparse_prior_applies`: ``band >= 0`` and more kept nodes than the
      skeleton keeps densely anyway): :func:`band_prior` of the exact covariance skeleton of
      ``Sigma = H^-1 = (N^-1)_kept`` (band of ``band`` nodes along the node order plus ``hubs``
      hub nodes), from the selected inversion of a sparse ``N``
      (:func:`~ga_ros.core.linalg.skeleton.sparse_skeleton`, linear in the number of nodes
      for a strip) or a Cholesky factor of a dense one; positive definite, rank ``6k``;
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
    return _dense_marginal(kept, N, u, colsS, colsL, T_keep)


def _dense_marginal(kept: IntArray, N: FloatArray | sp.spmatrix, u: FloatArray,
                    colsS: IntArray, colsL: IntArray, T_keep: FloatArray) -> AbsorbedPrior:
    """:func:`marginal_prior`'s exact prior from dense blocks: the Schur complement ``H, g`` of
    the unknowns ``colsL`` out of ``(N, u)`` onto ``colsS`` (rank unknown)."""
    sparse_in = sp.issparse(N)
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
    (:class:`~ga_ros.core.linalg.completion.CovarianceSkeleton`): a band of ``w`` nodes along the
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
    split one 314 (0.08 batch sd^2, 0.92): ``test/core/window/test_nees_long_swaths.py``,
    docs/window-design.md "The frozen prior's residual: position and rotation apart".

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
