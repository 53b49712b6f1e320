"""The linear system of one iteration: the general Gauss-Helmert form (eqs. 15-16) and the
Gauss-Newton shortcut of the motion models (se3, se2), whole or in parts."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import columns, kernels, models
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.completion import spd_inverse
from ga_ros.core.network import ConnectionArrays
from ga_ros.core.solver.config import SolverConfig
from ga_ros.core.solver.priors import _add_priors
from ga_ros.geometry import se3


@dataclass
class _System:
    blocks: FloatArray  # (4 m + b, d, d) in pattern order
    u: FloatArray  # (n_free d,)
    w: FloatArray  # (m, r)
    A_src: FloatArray | None  # None: the compiled se3 kernel (motion models need no A, B, M)
    A_dst: FloatArray | None
    B: FloatArray | None
    Minv: FloatArray | None  # weighted M^-1
    weights: FloatArray  # (m,) robust weights
    cost0: float  # sum w' M^-1 w (robust-weighted) + prior cost at the linearisation point
    data: FloatArray | None = None  # N's lower-triangle values, when assembled in parts
    pending: Callable[[], FloatArray] | None = None  # computes the blocks (NumPy se3, se2)

    def all_blocks(self) -> FloatArray | None:
        """The ``(4 m + b, d, d)`` blocks, computed now if they were left pending (the NumPy
        motion systems compute them only when ``N`` is needed: a chord step, or a stop on the
        decrease it predicts, needs the gradient alone)."""
        if self.blocks is None and self.pending is not None:
            self.blocks, self.pending = self.pending(), None
        return self.blocks

    def drop_blocks(self) -> None:
        """Let go of the blocks (and of what would compute them)."""
        self.blocks = self.pending = None

    def normal_values(self, pattern: BlockPattern, compiled: bool = False) -> FloatArray:
        """``N``'s lower-triangle values on ``pattern``, handed over once: the system keeps
        neither them nor its blocks (the next iteration's are assembled without them).
        ``compiled``: assembled by the compiled loop (:meth:`BlockPattern.assemble`)."""
        data = (self.data if self.data is not None
                else pattern.assemble(self.all_blocks(), compiled))
        self.data = None
        self.drop_blocks()
        return data


@dataclass(frozen=True)
class _Terms:
    """What a linearisation sums over: the connections, their observations' covariance and
    weights, the priors and the block columns of the unknowns.

    Attributes
    ----------
    model : the constraint model's name (:data:`ga_ros.core.models.MODELS`).
    conn : the connections.
    S : (m, o, o) covariance of the connections' observations.
    prior_data : the priors (:class:`~ga_ros.core.solver.priors._PriorData`).
    cfg : the solver settings (robust loss).
    col : (n,) block column of each node in ``N``, -1 if fixed.
    d : unknowns per node.
    P : (m, o, o) the weights ``S^-1`` (motion models: the Gauss-Newton shortcut), or ``None``
        (the general Gauss-Helmert form).
    T_meas, Tm_inv : (m, 4, 4) the measured motions and their inverses (se3), when kept.
    """

    model: str
    conn: ConnectionArrays
    S: FloatArray
    prior_data: list
    cfg: SolverConfig
    col: IntArray
    d: int
    P: FloatArray | None = None
    T_meas: FloatArray | None = None
    Tm_inv: FloatArray | None = None


@dataclass(frozen=True)
class _Kept:
    """How an se3 linearisation runs and what it reuses: ``compiled`` (the numba kernel), else
    the column forms of the measured inverses (``meas``) and weights (``sqrt_w``) and the
    misclosure ``mis`` already computed at this estimate (:mod:`ga_ros.core.columns`)."""

    compiled: bool = False
    meas: columns.MeasuredInverse | None = None
    sqrt_w: columns.SqrtWeights | None = None
    mis: columns.Misclosure | None = None


def _linear_system(terms: _Terms, T: FloatArray, v: FloatArray,
                   kept: _Kept = _Kept()) -> _System:
    """``N`` blocks and ``u`` of the linearised adjustment at ``(l0 = l_b + v, x0 = T)``.

    se3 with the weights ``P = S^-1`` given takes a shortcut: with ``v`` consistent with ``x0``
    (see :func:`_consistent_residuals`) the misclosure ``f(l0, x0)`` is zero, ``B = -J_r(v)``,
    ``w = v`` and ``A = [-Ad(T_ij^-1), I]``, so ``A' M^-1 A = J' P J`` and ``A' M^-1 w = J' P e``
    with ``J = J_r(e)^-1 A`` and ``e = v = log(T_meas^-1 T_i^-1 T_j)``: the Gauss-Newton system
    of ``sum e' P e``, which needs neither ``B`` nor a 6x6 inverse per connection (a test checks
    it against the general form). se2 takes the same shortcut in its 3 planar components; se3
    runs it in the compiled kernel :func:`ga_ros.core.kernels.se3_system` when ``compiled``.
    """
    if models.model_of(terms.model).motion and terms.P is not None:  # the shortcut
        return _motion_system(terms, T, kept)
    model, conn, S, cfg, col, d = terms.model, terms.conn, terms.S, terms.cfg, terms.col, terms.d
    lin = models.linearise(model, T, conn.src, conn.dst, conn.z, v)
    B = lin.B
    w = lin.f - (B @ v[:, :, None])[:, :, 0]  # w = f(l0, x0) + B (l_b - l0)
    M = B @ S @ np.swapaxes(B, 1, 2)
    Minv = _inv_spd(M)
    maha2 = np.einsum('mi,mij,mj->m', w, Minv, w)
    weights = cfg.loss.weight(np.sqrt(np.maximum(maha2, 0.0)))
    Wm = Minv * weights[:, None, None]
    AiT = np.swapaxes(lin.A_src, 1, 2) @ Wm
    AjT = np.swapaxes(lin.A_dst, 1, 2) @ Wm
    blocks = [AiT @ lin.A_src, AiT @ lin.A_dst, AjT @ lin.A_src, AjT @ lin.A_dst]
    gi = (AiT @ w[:, :, None])[:, :, 0]
    gj = (AjT @ w[:, :, None])[:, :, 0]
    n_free = int((col >= 0).sum())
    u = np.zeros((n_free, d))
    _scatter_gradient(u, col[conn.src], gi)
    _scatter_gradient(u, col[conn.dst], gj)
    cost0 = float(np.sum(cfg.loss.rho(maha2)))
    cost0 += _add_priors(model, T, terms.prior_data, col, u, blocks)
    return _System(np.concatenate(blocks), u.reshape(-1), w, lin.A_src, lin.A_dst, B, Wm,
                   weights, cost0)


def _motion_system(terms: _Terms, T: FloatArray, kept: _Kept,
                   gradient_only: bool = False) -> _System:
    """The shortcut of :func:`_linear_system` (se3, se2): ``H = J' W J``, ``g = J' W e`` with
    ``J = J_r(e)^-1`` shared by both ends (``A_dst = J``, ``A_src = -J Ad(T_ij^-1)``).

    The blocks are written into one preallocated ``(4 m + b, d, d)`` array (connection blocks
    ``ii, ij, ji, jj``, then the ``b`` prior blocks), without a concatenated copy; the NumPy
    paths compute them only when asked (:meth:`_System.all_blocks`).
    ``gradient_only`` (compiled se3 only: :meth:`_Problem.gradient`): no blocks are computed
    (``blocks`` ``None``), the rest is the same.
    """
    model, conn, P, cfg, col, d = terms.model, terms.conn, terms.P, terms.cfg, terms.col, terms.d
    T_meas, Tm_inv = terms.T_meas, terms.Tm_inv
    compiled, meas, sqrt_w, mis = kept.compiled, kept.meas, kept.sqrt_w, kept.mis
    m = len(conn)
    u = np.zeros((int((col >= 0).sum()), d))
    prior_blocks: list[FloatArray] = []
    prior_cost = _add_priors(model, T, terms.prior_data, col, u,
                             None if gradient_only else prior_blocks,
                             compiled=kept.compiled)
    extra = sum(len(b) for b in prior_blocks)
    kind = models.model_of(model)  # se3: compiled kernels and columns, se2: NumPy
    if T_meas is None and (not kind.compiled or (Tm_inv is None and meas is None)):
        T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    if kind.compiled and Tm_inv is None and (compiled or meas is None):
        Tm_inv = np.ascontiguousarray(se3.inverse(T_meas))
    if kind.compiled and compiled:
        w, blocks, gi, gj, maha2 = kernels.se3_system(T, conn.src, conn.dst, Tm_inv, P, extra,
                                                       blocks=not gradient_only)
        weights = cfg.loss.weight(np.sqrt(np.maximum(maha2, 0.0)))
        if cfg.robust_loss != 'none':
            if not gradient_only:
                blocks[:4 * m] *= np.tile(weights, 4)[:, None, None]
            gi *= weights[:, None]
            gj *= weights[:, None]
    else:  # structure of arrays (NumPy), the blocks' products left pending
        robust = None if cfg.robust_loss == 'none' else (
            lambda r2: cfg.loss.weight(np.sqrt(np.maximum(r2, 0.0))))
        if kind.compiled:  # columns.linearise
            lin = columns.linearise(
                T, conn.src, conn.dst,
                meas if meas is not None else columns.MeasuredInverse.of(Tm_inv),
                sqrt_w if sqrt_w is not None else columns.SqrtWeights.of(P), robust, mis)
        else:  # se2: columns.planar_linearise
            lin = columns.planar_linearise(T, conn.src, conn.dst, T_meas, P, robust)
        w, gi, gj, maha2 = lin.e, lin.g_src, lin.g_dst, lin.maha2
        weights = cfg.loss.weight(np.sqrt(np.maximum(maha2, 0.0)))
        blocks = None
    _scatter_gradient(u, col[conn.src], gi, compiled)
    _scatter_gradient(u, col[conn.dst], gj, compiled)

    def with_priors(blocks: FloatArray) -> FloatArray:
        k = 4 * m
        for b in prior_blocks:
            blocks[k:k + len(b)] = b
            k += len(b)
        return blocks

    pending = None
    if blocks is not None:
        blocks = with_priors(blocks)
    elif not gradient_only:
        pending = lambda: with_priors(lin.normal_blocks(extra).blocks)  # noqa: E731
    cost0 = float(np.sum(cfg.loss.rho(maha2))) + prior_cost
    # the motion models' residual update needs only w and the weights (no A, B, M)
    return _System(None if gradient_only else blocks, u.reshape(-1), w, None, None, None, None,
                   weights, cost0, pending=pending)


def _scatter_gradient(u: FloatArray, c: IntArray, g: FloatArray, compiled: bool = False
                      ) -> None:
    """``u[c] += g`` over the free nodes (``c >= 0``), repeated indices summed; ``compiled``:
    by :func:`ga_ros.core.kernels.scatter_rows` (bit for bit the same sums)."""
    if compiled:
        from ga_ros.core import kernels

        kernels.scatter_rows(u, c, g)
        return
    keep = c >= 0
    for k in range(u.shape[1]):
        u[:, k] += np.bincount(c[keep], weights=g[keep, k], minlength=u.shape[0])


def _misclosure(model: str, T: FloatArray, conn: ConnectionArrays, T_meas: FloatArray | None,
                Tm_inv: FloatArray | None = None, compiled: bool = False,
                meas: columns.MeasuredInverse | None = None) -> FloatArray:
    """``e = log(T_meas^-1 T_i^-1 T_j)`` of the motion models (se3: compiled if asked, else
    in columns, :func:`ga_ros.core.columns.misclosure`)."""
    kind = models.model_of(model)
    if kind.compiled and meas is not None and not compiled:
        return columns.misclosure(T, conn.src, conn.dst, meas).e
    if T_meas is None:
        T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    if not kind.compiled:
        return kind.motion_misclosure(T, conn.src, conn.dst, T_meas)
    if Tm_inv is None:
        Tm_inv = np.ascontiguousarray(se3.inverse(T_meas))
    if compiled:
        return kernels.se3_misclosure(T, conn.src, conn.dst, Tm_inv)
    return columns.misclosure(T, conn.src, conn.dst, columns.MeasuredInverse.of(Tm_inv)).e


def _residual_update(sysd: _System, dx: FloatArray, conn, col, d, S) -> FloatArray:
    """``k = -M^-1 (A d + w)``, ``v = S B' k`` (eq. 16), with the robust weights in ``M^-1``."""
    D = np.zeros((col.size, d))
    free = col >= 0
    D[free] = dx.reshape(-1, d)[col[free]]
    Ad = (sysd.A_src @ D[conn.src][:, :, None] + sysd.A_dst @ D[conn.dst][:, :, None])[:, :, 0]
    k = -(sysd.Minv @ (Ad + sysd.w)[:, :, None])
    return (S @ np.swapaxes(sysd.B, 1, 2) @ k)[:, :, 0]


def _consistent_residuals(model: str, T: FloatArray, conn: ConnectionArrays,
                          v_linear: FloatArray, T_meas: FloatArray | None = None) -> FloatArray:
    """Residuals to relinearise at next (paper Sec. III-C step 5: ``l0 = l_b + v``).

    For se3 the constraint ``f = 0`` has the closed-form solution
    ``v = log(T_meas^-1 T_i^-1 T_j)`` at the new ``x``; using it (instead of the linear
    prediction ``v = S B' k``) keeps ``v`` on the principal branch of the rotation log, and the
    Gauss-Helmert step becomes exactly Gauss-Newton on ``sum e' P e``. The position models keep
    the linear prediction (their constraints are not solvable for ``v`` in closed form). se2 as
    se3, in its planar components.
    """
    if not models.model_of(model).motion:
        return v_linear
    return _misclosure(model, T, conn, T_meas)


def _inv_spd(M: FloatArray) -> FloatArray:
    """Inverse of a stack of SPD matrices, via Cholesky (raises on a non-PD block)."""
    return spd_inverse(M, "a connection has a singular B S B' block")
