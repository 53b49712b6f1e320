"""What the aligner and the background refinement exchange (ROS-free, picklable): the
:class:`RefinementSnapshot` a refinement solves, its :class:`RefinementResult`, and the
smoothing steps (:class:`SmoothingStep`, :class:`SparseSmoothing`) that carry a later
correction of the prior nodes back to the eliminated ones
(:func:`~ga_ros.core.window.elimination.smooth`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.solver import SolverConfig
from ga_ros.core.window.freeze import AbsorbedPrior


@dataclass(frozen=True)
class RefinementSnapshot:
    """What a refinement solves: a copy of the aligner's data after one track's update.

    Attributes
    ----------
    after_tracks : number of finished tracks when the snapshot was taken.
    node_ids, track_ids : (n,) ids of the nodes of finished tracks, in the aligner's order; node 0
        (index 0) is the datum, held fixed (unless :attr:`free_datum`).
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
    fixes : the weighted parameters of the absolute fixes of the snapshot's nodes
        (:mod:`ga_ros.core.fixes`), one single-node prior per node with a used fix, node indices
        of the snapshot, linearised at ``T_world_node``: all of them enter the batch solve; those
        of nodes frozen at the hand-off also enter the rebuilt priors (and the past prior when
        their track retires), as the aligner's freezing keeps them.
    fix_used : indices in the aligner's fix book of the fixes in ``fixes`` (the hand-off checks
        that the frozen nodes' fixes did not change since).
    n_fixes : number of fixes the aligner held at the snapshot.
    free_datum : no node is held fixed (``datum='fixes'``: the fixes and the gauge prior define
        the map frame).
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
    fixes: tuple[AbsorbedPrior, ...] = ()
    fix_used: IntArray | None = None
    n_fixes: int = 0
    free_datum: bool = False

    @property
    def datum(self) -> bool:
        """Whether node 0 of the snapshot is the survey's datum (held fixed)."""
        return self.first_node == 0 and not self.free_datum

    def frozen_fixes(self, before: int | None = None) -> tuple[AbsorbedPrior, ...]:
        """The priors of :attr:`fixes` on frozen nodes (of index below ``before``, if given)."""
        return tuple(p for p in self.fixes if self.frozen[p.nodes].all()
                     and (before is None or int(p.nodes.max()) < before))


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
    """The back substitution of a sparse elimination (:func:`sparse_eliminate`): ``d_L =
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

    @property
    def N_LR(self) -> sp.csr_matrix:  # noqa: N802 - the matrix's name
        """``N_LR``, the coupling of the eliminated nodes to the remaining ones (CSR)."""
        return self._N_LR

    @property
    def u_L(self) -> FloatArray:  # noqa: N802 - the vector's name
        """``u_L``, the eliminated nodes' half gradient."""
        return self._u_L

    def solve_eliminated(self, b: FloatArray) -> FloatArray:
        """``N_LL^-1 b`` for ``b`` of shape ``(6 l,)`` or ``(6 l, k)`` (the same factor)."""
        return self._chol.solve(b)

    def forward_eliminated(self, b: FloatArray) -> FloatArray | None:
        """``L^-1 P b`` for ``b`` of shape ``(6 l, k)``, with ``P N_LL P' = L L'`` the same
        factor (``b' N_LL^-1 b = Y' Y``); ``None`` without CHOLMOD's own factor
        (:meth:`~ga_ros.core.linalg.cholmod.SparseCholesky.forward`)."""
        return self._chol.forward(b)


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
