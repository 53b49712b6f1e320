"""One adjustment's fixed parts, built once (:class:`_Problem`), and the costs evaluated on it."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import columns, kernels, models
from ga_ros.core.linalg.blocks import BlockPattern, kept_block_pattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.network import ConnectionArrays
from ga_ros.core.solver.config import SolverConfig
from ga_ros.core.solver.linearise import (
    _consistent_residuals,
    _inv_spd,
    _Kept,
    _linear_system,
    _misclosure,
    _motion_system,
    _residual_update,
    _System,
    _Terms,
)
from ga_ros.core.solver.priors import _add_priors, _prior_cost, _PriorData
from ga_ros.errors import InputError
from ga_ros.geometry import se3

#: Problems with more connections (motion models) are linearised and assembled in parts
#: (:func:`_motion_system_in_parts`) ...
_PARTS_ABOVE = 65_536


#: ... of this many connections (the temporaries of a part: ~60 MB).
_CONNECTIONS_PER_PART = 16_384


@dataclass
class WarmStart:
    """What a caller that solves one problem after another hands the next :func:`solve` (the
    window aligner: the same pattern every track, the weights and measured motions kept from
    the previous update). ``WarmStart()`` is a cold start.

    Attributes
    ----------
    jit : use the compiled se3 kernels (:mod:`ga_ros.core.kernels`) from the first
        linearisation on, for a caller that solves many problems in one process (the window
        aligner): the one-off cost of loading them is paid once. Default: only once a solve
        has run :data:`~ga_ros.core.kernels.AFTER_ITERATIONS` linearisations.
    weights : (m, 6, 6) the inverses of the connections' covariances, if the caller has them
        (se3; e.g. kept from the previous window update), or (m, 3, 3) those of their
        ``[x y rz]`` blocks (se2; a 2-D g2o file's information): not inverted again.
    factor : a factor handed over by :meth:`SolveResult.release_factor` of an earlier solve;
        if its pattern is this problem's, its symbolic analysis is reused (a window update
        solves the same pattern every track).
    factor_at_solution : ``True`` (default): the result's covariances ``Q_x = N^-1`` (eq. 17)
        come from ``N`` factored at the solution (on first use). ``False`` (undamped
        iterations only): from the iteration's last numeric factorisation, at the start of its
        last full Gauss-Newton step (the chord steps after it reuse that factor), so a solve
        that converges with one factorisation needs no second one for its covariances.
        ``N = J' P J`` depends on the estimate only through the connections' relative poses
        ``T_i^-1 T_j`` (the Jacobians ``[-Ad(T_ij^-1), I]``) and the priors' residuals, so the
        two differ by the change of those over the last correction (first order in it; a
        rigid motion of the whole network changes nothing). ``Q_x`` is itself the first-order
        covariance of an estimate that lies about one standard deviation from the truth, so a
        linearisation point a fraction of a correction away is within its own approximation.
        Measured: a small survey at 10 % noise, variances within 1.1 % of the dense inverse
        at the solution (``test_window_fast.py`` bounds them at 5 %); the aerial survey's
        window (6,732 unknowns, 10 % noise) 0.4-2.3 % for the track that leaves it next and up
        to 10 % for the newest two tracks, whose weak modes the last correction moved by metres.
        :attr:`SolveResult.factor_offset` bounds the distance. The normal matrix of the result
        (:attr:`SolveResult.normal_matrix`, a sequential prior) is then the factored one too.
    measured : se3 only: ``(T_meas, T_meas^-1)``, the (m, 4, 4) measured motions of the
        connections (``T_src_dst`` of each ``z``,
        :func:`ga_ros.geometry.se3.from_translation_rotvec`) and their inverses, if the caller
        has them (e.g. kept from the previous window update, as ``weights``): not computed
        again.
    """

    jit: bool = False
    weights: FloatArray | None = None
    factor: SparseCholesky | None = None
    factor_at_solution: bool = True
    measured: tuple[FloatArray, FloatArray] | None = None

    @staticmethod
    def of(warm: WarmStart | None, hooks: dict) -> WarmStart:
        """``warm``, or one built from :func:`solve`'s keywords (its fields by name).

        Raises
        ------
        InputError
            Both given, or a keyword that is not a field.
        """
        unknown = set(hooks) - {f.name for f in fields(WarmStart)}
        if unknown:
            raise InputError(f'solve() got unknown keywords {sorted(unknown)}; the warm-start '
                             f'fields are {[f.name for f in fields(WarmStart)]}')
        if warm is not None and hooks:
            raise InputError('give either warm=WarmStart(...) or its fields as keywords')
        return warm if warm is not None else WarmStart(**hooks)


@dataclass
class _Problem:
    """One adjustment's fixed parts (connections, priors, datum, pattern of ``N``), built once.

    Its methods are the pieces of an iteration: the linear system at ``(T, v)``, the cost at
    ``T``, the residual update (eq. 16) and the retraction of a correction.
    """

    model: str
    conn: ConnectionArrays
    P: FloatArray | _PartWeights  # (m, o, o) weights S^-1 of the connections
    prior_data: list[_PriorData]
    cfg: SolverConfig
    free: np.ndarray  # (n,) bool
    col: IntArray  # (n,) block column of each node in N, -1 if fixed
    d: int
    pattern: BlockPattern
    S: FloatArray  # (m, o, o) covariance of the connections' observations
    T_meas: FloatArray | None  # (m, 4, 4) measured motions (motion models, not in parts)
    Tm_inv: FloatArray | None  # (m, 4, 4) their inverses (se3, not in parts)
    _last: tuple = (None, None)  # (T, e): the last misclosure computed, reused once
    linearisations: int = 0  # calls of linear_system so far
    jit: bool = False  # compiled kernels from the first linearisation (solve's ``jit``)
    factor: SparseCholesky | None = None  # a factor of this pattern to refactor (solve's)
    in_columns: bool = False  # se3 not in parts: linearised in columns unless compiled
    _meas: columns.MeasuredInverse | None = None  # meas, once computed
    _sqrt_w: columns.SqrtWeights | None = None  # sqrt_w, once computed
    _mis: tuple = (None, None)  # (T, columns.Misclosure) of the last cost_at, reused once
    _ahead: tuple = (None, None)  # (T, _System) of gradient_ahead, for the next gradient

    @staticmethod
    def build(model: str, conn: ConnectionArrays, prior_data: list[_PriorData],
              cfg: SolverConfig, free: np.ndarray, P: FloatArray | None = None,
              measured: tuple[FloatArray, FloatArray] | None = None) -> _Problem:
        kind = models.model_of(model)
        d = kind.dof
        col = np.full(free.size, -1, dtype=np.int64)
        col[free] = np.arange(int(free.sum()))
        # block pattern: connection blocks (ii, ij, ji, jj) then prior blocks
        br = [col[conn.src], col[conn.src], col[conn.dst], col[conn.dst]]
        bc = [col[conn.src], col[conn.dst], col[conn.src], col[conn.dst]]
        for pd in prior_data:
            br.append(col[pd.idx[pd.blk_r]])
            bc.append(col[pd.idx[pd.blk_c]])
        pattern = kept_block_pattern(np.concatenate(br), np.concatenate(bc), d, int(free.sum()))
        S = models.observation_covariance(model, conn.cov)
        # the measured motions and their inverses are kept, except by problems linearised in
        # parts, which compute them a part at a time (the same values: ~150 MB less at 100,000
        # poses for a few tenths of a second per linearisation)
        in_parts = _linearised_in_parts(model, len(conn))
        if measured is not None and not in_parts:  # solve's measured (se3): the caller's
            T_meas, Tm_inv = measured[0], np.ascontiguousarray(measured[1])
        else:
            T_meas = (se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
                      if kind.motion and not in_parts else None)
            # their inverses: se3 only (se2 composes the planar motions themselves)
            Tm_inv = (np.ascontiguousarray(se3.inverse(T_meas))
                      if T_meas is not None and kind.compiled else None)
        if P is None:  # the weights; a part at a time for problems linearised in parts
            P = _PartWeights(S) if in_parts else _inv_spd(S)
        return _Problem(model, conn, P, prior_data, cfg, free, col, d, pattern, S, T_meas,
                        Tm_inv, in_columns=kind.compiled and not in_parts)

    @property
    def kind(self) -> models.ConstraintModel:
        """The constraint model (:data:`ga_ros.core.models.MODELS`) of :attr:`model`."""
        return models.MODELS[self.model]

    @property
    def meas(self) -> columns.MeasuredInverse | None:
        """``Tm_inv`` as columns (se3 in columns; computed on first use: a problem
        linearised by the compiled kernel never needs it)."""
        if self._meas is None and self.in_columns:
            self._meas = columns.MeasuredInverse.of(self.Tm_inv)
        return self._meas

    @property
    def sqrt_w(self) -> columns.SqrtWeights | None:
        """``P = U'U`` as columns (se3 in columns; computed on first use)."""
        if self._sqrt_w is None and self.in_columns:
            self._sqrt_w = columns.SqrtWeights.of(self.P)
        return self._sqrt_w

    @property
    def Pf(self) -> FloatArray | None:
        """The weights when the shortcut of :func:`_linear_system` applies (se3, se2)."""
        return self.P if self.kind.motion else None

    def zero_residuals(self) -> FloatArray:
        """``v = 0``: (m, o) with ``o`` the observations per connection."""
        return np.zeros((len(self.conn), models.observations_per_connection(self.model)))

    def linear_system(self, T: FloatArray, v: FloatArray) -> _System:
        self.linearisations += 1
        if _linearised_in_parts(self.model, len(self.conn)):
            return _motion_system_in_parts(self, T)
        last_T, mis = self._mis
        self._mis = (None, None)
        compiled = self.compiled
        kept = (_Kept(True) if compiled
                else _Kept(False, self.meas, self.sqrt_w, mis if last_T is T else None))
        return _linear_system(self.terms(self.Pf), T, v, kept)

    def terms(self, P: FloatArray | None = None) -> _Terms:
        """What its linearisations sum over, with the weights ``P`` (the motion models'
        shortcut) or without (``None``: the general form)."""
        return _Terms(self.model, self.conn, self.S, self.prior_data, self.cfg, self.col,
                      self.d, P, self.T_meas, self.Tm_inv)

    def gradient(self, T: FloatArray, v: FloatArray) -> _System:
        """:meth:`linear_system` without ``N``: ``u``, the misclosure, the robust weights and
        the cost at ``T`` (``blocks`` ``None``), what a chord step needs (it reuses the last
        factorisation of ``N``). The compiled se3 kernel skips the blocks' products (~3x
        faster); the NumPy paths leave them pending (:meth:`_System.all_blocks`) and drop
        them."""
        ahead_T, ahead = self._ahead
        self._ahead = (None, None)
        if ahead_T is T:  # computed by gradient_ahead after the step that led to T
            return ahead
        if not self.fused_gradient:
            sysd = self.linear_system(T, v)  # the NumPy paths leave the blocks pending
            sysd.drop_blocks()
            return sysd
        self.linearisations += 1
        self._mis = (None, None)
        return _motion_system(self.terms(self.P), T, _Kept(True), gradient_only=True)

    @property
    def fused_gradient(self) -> bool:
        """The gradient comes from the compiled se3 kernel without the blocks of ``N``
        (:meth:`gradient`), whose misclosure is :meth:`misclosure`'s (the same compiled
        function) and, without a robust loss, whose ``cost0`` is the cost at ``T``."""
        return self.compiled and self.T_meas is not None

    def gradient_ahead(self, T: FloatArray, step: float) -> _System | None:
        """After an undamped step of size ``step`` (max ``|dx|``) to ``T``: the gradient system
        at ``T``, when the next iteration will be a chord step (``step`` below
        ``reuse_factor_below``) and the fused kernel gives the residuals and the cost at ``T``
        with it (:attr:`fused_gradient`, no robust loss). Its misclosure ``w`` and ``cost0``
        then stand for :meth:`next_residuals` and the cost of the step, and the next
        :meth:`gradient` at this very ``T`` returns it: one kernel pass instead of a misclosure,
        a cost and, in the next iteration, the gradient's own pass. ``None`` otherwise."""
        cfg = self.cfg
        if not (cfg.damping == 'none' and cfg.robust_loss == 'none' and self.fused_gradient
                and step < cfg.reuse_factor_below):
            return None
        sysd = self.gradient(T, None)
        self._ahead = (T, sysd)
        return sysd

    @property
    def compiled(self) -> bool:
        """Use the compiled se3 kernels: from the first linearisation with ``jit`` (the caller
        has loaded them: whatever the size, e.g. the window aligner's pre-alignment of ~1,200
        connections), else only once a solve has run more than
        :data:`ga_ros.core.kernels.AFTER_ITERATIONS` linearisations, on a large enough problem
        (loading numba costs ~1 s and ~100 MiB, which a short solve never earns back)."""
        if not self.kind.compiled:
            return False
        if self.jit:
            return kernels.AVAILABLE
        return (self.linearisations > kernels.AFTER_ITERATIONS
                and kernels.use_for(len(self.conn)))

    def cost_at(self, T: FloatArray) -> float:
        if not self.kind.motion:
            return _cost_at(self.terms(), T)
        if not self.compiled and self.meas is not None:  # in columns, kept for linear_system
            mis = columns.misclosure(T, self.conn.src, self.conn.dst, self.meas)
            self._last, self._mis = (T, mis.e), (T, mis)
            return (float(np.sum(self.cfg.loss.rho(columns.maha2(mis, self.sqrt_w))))
                    + _prior_cost(self.model, T, self.prior_data))
        e = self.misclosure(T)
        self._last = (T, e)
        return _cost_of_misclosure(self.model, T, e, self.P, self.prior_data, self.cfg)

    def residual_update(self, sysd: _System, dx: FloatArray) -> FloatArray:
        """Residuals after the correction ``dx`` (eq. 16). For the motion models only
        ``dx = 0`` is asked (their residuals after a step come from :meth:`next_residuals`):
        ``v = S B' k = weights * w``."""
        if self.kind.motion:
            return sysd.w * sysd.weights[:, None]
        return _residual_update(sysd, dx, self.conn, self.col, self.d, self.S)

    def consistent(self, T: FloatArray, v_linear: FloatArray) -> FloatArray:
        if self.kind.motion:
            last_T, e = self._last
            self._last = (None, None)
            return e if last_T is T else self.misclosure(T)
        return _consistent_residuals(self.model, T, self.conn, v_linear)

    def misclosure(self, T: FloatArray) -> FloatArray:
        """``e = log(T_meas^-1 T_i^-1 T_j)`` of the motion models at ``T`` (in parts if the
        problem does not keep the measured motions)."""
        if self.T_meas is not None:
            compiled = self.compiled
            return _misclosure(self.model, T, self.conn, self.T_meas, self.Tm_inv, compiled,
                               None if compiled else self.meas)
        return np.concatenate([_misclosure(self.model, T, part, None, None, self.compiled)
                               for _, part in self.parts()])

    def parts(self):
        """``(a, connections a..b-1)`` for consecutive parts of :data:`_CONNECTIONS_PER_PART`
        connections."""
        conn = self.conn
        for s in _part_slices(len(conn)):
            yield s.start, ConnectionArrays(conn.src[s], conn.dst[s], conn.z[s], conn.cov[s])

    def next_residuals(self, T: FloatArray, sysd: _System, dx: FloatArray) -> FloatArray:
        """Residuals to relinearise at after the step ``dx`` took the estimate to ``T``."""
        if self.kind.motion:
            return self.consistent(T, sysd.w)
        return self.consistent(T, self.residual_update(sysd, dx))

    def retract(self, T: FloatArray, dx: FloatArray) -> FloatArray:
        idx = np.nonzero(self.free)[0]
        if self.model == 'se3' and self.compiled:  # one compiled loop (the same to rounding)
            moved = kernels.se3_retract(T[idx], dx.reshape(-1, self.d))
            if moved is not None:
                out = T.copy()
                out[idx] = moved
                return out
        return models.retract(self.model, T, idx, dx.reshape(-1, self.d))


class _PartWeights:
    """The weights ``P = S^-1`` of a problem linearised in parts, computed a part at a time
    from the covariances ``S`` (the same values as one inversion of all: ~160 MB not kept at
    100,000 poses, for ~20 ms per 16,384 connections each time they are read). Slicing
    ``P[a:b]`` gives an array; :func:`_maha2` and :func:`_adjustment_cost` take it whole."""

    def __init__(self, S: FloatArray) -> None:
        self.S = S
        self.shape = S.shape

    def __getitem__(self, part: slice) -> FloatArray:
        return _inv_spd(self.S[part])

    def parts(self) -> list[slice]:
        """The parts' slices (:func:`_part_slices`)."""
        return _part_slices(self.shape[0])


def _linearised_in_parts(model: str, m: int) -> bool:
    """Whether a problem of ``m`` connections is linearised and assembled in parts (motion
    models above :data:`_PARTS_ABOVE` connections; :func:`_motion_system_in_parts`)."""
    return models.model_of(model).motion and m > _PARTS_ABOVE


def _part_slices(m: int) -> list[slice]:
    """Consecutive slices of :data:`_CONNECTIONS_PER_PART` of ``m`` connections."""
    return [slice(a, min(a + _CONNECTIONS_PER_PART, m))
            for a in range(0, m, _CONNECTIONS_PER_PART)]


def _maha2(e: FloatArray, P: FloatArray | _PartWeights) -> FloatArray:
    """Squared Mahalanobis norms ``e_k' P_k e_k`` ``(m,)``."""
    if isinstance(P, _PartWeights):
        return np.concatenate([_maha2(e[s], P[s]) for s in P.parts()])
    return np.einsum('mi,mij,mj->m', e, P, e)


def _cost_of_misclosure(model, T, e, P, prior_data, cfg) -> float:
    maha2 = _maha2(e, P)
    return float(np.sum(cfg.loss.rho(maha2))) + _prior_cost(model, T, prior_data)


def _cost_at(terms: _Terms, T: FloatArray) -> float:
    """Cost of the adjustment at ``x = T``: ``sum rho(e' P e)`` for se3/se2 (``e`` the
    misclosure ``log(T_meas^-1 T_i^-1 T_j)``), else the value of ``sum w' M^-1 w`` linearised at
    ``v = 0``; plus the prior terms."""
    if not models.model_of(terms.model).motion:
        return _linear_system(replace(terms, P=None), T, np.zeros_like(terms.conn.z)).cost0
    e = _misclosure(terms.model, T, terms.conn, terms.T_meas)
    P = _inv_spd(terms.S) if terms.P is None else terms.P
    return _cost_of_misclosure(terms.model, T, e, P, terms.prior_data, terms.cfg)


def _adjustment_cost(v: FloatArray, P: FloatArray | _PartWeights, weights: FloatArray) -> float:
    if isinstance(P, _PartWeights):
        return float(sum(_adjustment_cost(v[s], P[s], weights[s]) for s in P.parts()))
    return float(_maha2(v, P) @ weights)  # ~2x faster than one four-operand einsum


def _motion_system_in_parts(prob: _Problem, T: FloatArray) -> _System:
    """:func:`_motion_system` over :data:`_CONNECTIONS_PER_PART` connections at a time, each
    part's blocks added into ``N`` at once (:meth:`BlockPattern.assemble_at`): the ``4 m``
    blocks of a large problem never exist together (~700 MB for 100,000 poses). The system has
    ``data`` set and no blocks."""
    m, d = len(prob.conn), prob.d
    data = np.zeros(prob.pattern.nnz)
    u = np.zeros((int(prob.free.sum()), d))
    w, weights, cost0 = [], [], 0.0
    for a, part in prob.parts():
        b = a + len(part)
        # the part's own measured motions and their inverses (not kept), no priors
        terms = _Terms(prob.model, part, prob.S[a:b], [], prob.cfg, prob.col, d, prob.P[a:b])
        sysp = _motion_system(terms, T, _Kept(prob.compiled))
        k = np.arange(a, b)
        prob.pattern.assemble_at(sysp.all_blocks(),
                                 np.concatenate([k, k + m, k + 2 * m, k + 3 * m]), data)
        u += sysp.u.reshape(-1, d)
        w.append(sysp.w)
        weights.append(sysp.weights)
        cost0 += sysp.cost0
    prior_blocks: list[FloatArray] = []
    cost0 += _add_priors(prob.model, T, prob.prior_data, prob.col, u, prior_blocks)
    if prior_blocks:
        extra = np.concatenate(prior_blocks)
        prob.pattern.assemble_at(extra, 4 * m + np.arange(len(extra)), data)
    return _System(None, u.reshape(-1), np.concatenate(w), None, None, None, None,
                   np.concatenate(weights), cost0, data)
