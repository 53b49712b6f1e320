"""The batch solve: validation, the iteration loop (paper Sec. III-C, steps 1-6) and the final
linearisation at the solution."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import models
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver.config import SolverConfig
from ga_ros.core.solver.linearise import _System
from ga_ros.core.solver.priors import GaussianPrior, _prior_cost, _PriorData
from ga_ros.core.solver.problem import WarmStart, _adjustment_cost, _maha2, _Problem
from ga_ros.core.solver.result import SolveResult, _NormalSystem
from ga_ros.core.solver.steps import _dogleg_step, _lm_step, _Step, _Trust
from ga_ros.core.solver.termination import _chord_kept, _left_to_gain, _stop_reason
from ga_ros.errors import DegenerateGeometryError, InputError, SolverError
from ga_ros.geometry import se2
from ga_ros.runtime import blas_threads


# ----------------------------------------------------------------------------------- solve
def solve(network: ConnectionNetwork, T_init: FloatArray, config: SolverConfig | None = None,
          fixed: Sequence[int] | None = None,
          priors: Sequence[GaussianPrior] = (), warm: WarmStart | None = None,
          **hooks: object) -> SolveResult:
    """Batch mixed-adjustment solution with relinearisation (paper Sec. III-C, steps 1-6).

    Parameters
    ----------
    network : the connections (validated on insertion).
    T_init : (n, 4, 4) initial poses ``T_world_node`` in network index order (e.g.
        :func:`initial_guess_f2f`).
    config : solver settings.
    fixed : node ids held fixed (the datum). Default: the first node when there are no priors,
        none otherwise (then the priors must define the datum).
    priors : weighted parameters / sequential priors (see :class:`GaussianPrior`).
    warm : what a caller solving one problem after another hands over (weights, measured
        motions, a factor to reuse, compiled kernels, where the covariances come from): see
        :class:`~ga_ros.core.solver.problem.WarmStart`. Default: nothing.
    **hooks : the fields of :class:`~ga_ros.core.solver.problem.WarmStart` as keywords
        (``jit``, ``weights``, ``factor``, ``factor_at_solution``, ``measured``), instead of
        ``warm``.

    Returns
    -------
    SolveResult with the estimate, residuals, adjusted observations, variance factor,
    redundancy and access to marginal covariances.

    Raises
    ------
    InputError, NetworkError
        Bad shapes, unknown nodes, nodes not connected to the datum (named), ``warm`` and
        keywords together, an unknown keyword.
    DegenerateGeometryError
        Singular normal matrix.
    """
    t0 = time.perf_counter()
    warm = WarmStart.of(warm, hooks)
    weights, measured, factor = warm.weights, warm.measured, warm.factor
    cfg = config or SolverConfig()
    model = cfg.model
    d = models.dof(model)
    n = network.n_nodes
    if n == 0:
        raise InputError('the network has no nodes')
    T0 = np.asarray(T_init, dtype=float)
    if T0.shape != (n, 4, 4):
        raise InputError(f'T_init must have shape ({n}, 4, 4), got {T0.shape}')
    if not np.isfinite(T0).all():
        raise InputError('T_init has NaN or inf entries')
    conn = network.arrays()
    node_ids = network.node_ids

    if fixed is None:
        fixed = [int(node_ids[0])] if not priors else []
    fixed_idx = network.indices_of(list(fixed)) if len(fixed) else np.zeros(0, dtype=np.int64)
    prior_data = [_PriorData.build(network, p, d) for p in priors]
    anchors = list(fixed) + [int(i) for p in priors for i in p.node_ids]
    if not anchors:
        raise DegenerateGeometryError('no datum: fix a node or give priors (weighted parameters)')
    network.check_connected(anchors)
    free = np.ones(n, dtype=bool)
    free[fixed_idx] = False
    if not free.any():
        raise InputError('every node is fixed: nothing to estimate')
    kind = models.model_of(model)
    o = kind.observations
    want = (len(conn), o, o) if kind.motion else None
    if weights is not None and np.shape(weights) != want:
        raise InputError(f'weights must be {want} for the {model} model, got '
                         f'{np.shape(weights)}' if want else 'weights only for se3 and se2')
    if measured is not None and (not kind.compiled or any(
            np.shape(a) != (len(conn), 4, 4) for a in measured)):
        raise InputError(f'measured must be two ({len(conn)}, 4, 4) arrays, for the se3 model')
    prob = _Problem.build(model, conn, prior_data, cfg, free, weights, measured)
    prob.jit = bool(warm.jit)
    if factor is not None and factor.pattern.key == prob.pattern.key:
        prob.factor = factor
    with blas_threads():
        out = _iterate(prob, T0.copy(), keep_values=not warm.factor_at_solution)
    return _finish(prob, node_ids, out, t0)


@dataclass
class _Iterations:
    """Outcome of the iteration loop of :func:`solve` (before the final linearisation)."""

    T: FloatArray
    v: FloatArray
    converged: bool
    iterations: int
    reason: str
    history: list[float]
    chol: SparseCholesky | None
    factorisations: int
    since_factor: float = np.inf  # sum of max |dx| since the last factorisation of N (undamped)
    factored: FloatArray | None = None  # the values of N last factored (keep_values)


def _iterate(prob: _Problem, T: FloatArray, keep_values: bool = False) -> _Iterations:
    """Relinearise and correct until the largest correction is below the tolerance (or a
    Gauss-Newton step lowers the cost by less than ``cost_tolerance``).

    Undamped chord steps (the last factorisation reused once a correction is below
    ``reuse_factor_below``) need the gradient only (:meth:`_Problem.gradient`); their rules
    are :func:`_undamped_step`'s. Only while chord steps converge fast: one whose decrease is
    more than a quarter of the previous step's (a contraction slower than 1/2 per step, e.g. a
    factor from far away on a weak mode of the network) makes the next iteration factor ``N``
    anew.
    The dogleg's chord step (:attr:`SolverConfig.chord_decrease`) is solved before ``N`` is
    assembled: when it shows less than ``cost_tolerance`` left to gain (:func:`_left_to_gain`)
    it is the last step, taken if it lowers the cost as predicted (:func:`_chord_kept`).
    ``keep_values``: the values of ``N`` last factored are kept in the result (for
    :func:`solve`'s ``factor_at_solution=False``).
    """
    cfg = prob.cfg
    # the fused kernel's first system gives the motion model's residuals (the misclosure at T)
    v = None if prob.fused_gradient else prob.consistent(T, prob.zero_residuals())
    state = _Trust(chol=prob.factor, auto=cfg.factor == 'auto')
    last_step = np.inf
    slow = False  # the last chord step contracted too slowly: factor anew
    history: list[float] = []
    converged, reason, it = False, 'max_iterations', 0
    # without a robust loss a damped step's cost (the motion models': at T) is this sum
    plain = cfg.damping == 'none' or (prob.Pf is not None and cfg.robust_loss == 'none')
    for it in range(1, cfg.max_iterations + 1):
        # the last values of N go before the next are assembled (~190 MB at 100,000 poses)
        if state.chol is not None:
            state.chol.release_values()
        chord = (cfg.damping == 'none' and state.chol is not None
                 and last_step < cfg.reuse_factor_below and not slow)
        # a chord step needs the gradient only (it reuses the last factor of N)
        sysd = prob.gradient(T, v) if chord else prob.linear_system(T, v)
        if v is None:
            v = sysd.w
        if it == 1:  # the se3 shortcut's cost0 is the exact cost
            state.cost = sysd.cost0 if prob.Pf is not None else prob.cost_at(T)
            history.append(state.cost)
        chord_h = None  # dogleg: the chord step from the last factor, tried first
        if cfg.damping == 'dogleg' and state.chord and state.chol is not None:
            chord_h = -state.chol.solve(sysd.u)
            last = _last_chord_step(prob, T, v, sysd, chord_h, state, history, plain)
            if last is not None:  # N never assembled
                T, v = last
                converged, reason = True, 'cost_converged'
                break
        # a chord step reuses the last factor: N's values are not needed
        # the (4 m, d, d) blocks are freed before factoring
        data = None if chord else sysd.normal_values(prob.pattern, prob.compiled)
        sysd.drop_blocks()
        if cfg.damping == 'none':
            step = _undamped_step(prob, T, sysd, data, state, chord, keep_values, history)
            if step is None:  # a chord step undone: this point again, with a factorisation
                last_step = np.inf
                continue
            if step == 'cost_converged':  # less than cost_tolerance left to gain
                converged, reason = True, step
                break
        else:
            step = (_dogleg_step(prob, T, sysd, data, state, chord_h)
                    if cfg.damping == 'dogleg' else _lm_step(prob, T, sysd, data, state))
            if not step.accepted:
                reason = 'no_decrease'
                converged = step.step < cfg.tolerance * 10
                break
        T, v = step.T, step.v
        last_step = step.step
        _book_step(prob, state, step, sysd, history, plain, it)
        stop = _stop_reason(step, history, cfg)
        if stop is not None:
            converged, reason = True, stop
            break
        slow = chord and _slow_contraction(history)
    return _Iterations(T, v, converged, it, reason, history, state.chol, state.factorisations,
                       state.since_factor if cfg.damping == 'none' else np.inf, state.factored)


def _book_step(prob: _Problem, state: _Trust, step: _Step, sysd: _System,
               history: list[float], plain: bool, it: int) -> None:
    """Record the step taken at iteration ``it``: its objective in ``history``
    (:func:`_objective`), the cost and predicted decrease in ``state``, and whether the dogleg
    tries a chord step next (a Gauss-Newton step that lowered the cost by less than
    :attr:`SolverConfig.chord_decrease` of it).

    Raises
    ------
    SolverError
        The estimate after the step is not finite.
    """
    cfg = prob.cfg
    history.append(_objective(prob, plain, step.cost, step.v, step.T, sysd))
    state.chord = (step.gauss_newton and cfg.chord_decrease > 0 and cfg.cost_tolerance > 0
                   and state.cost > 0
                   and state.cost - step.cost < cfg.chord_decrease * state.cost)
    state.cost, state.predicted = step.cost, step.predicted
    if not np.isfinite(step.T).all():
        raise SolverError(f'the estimate became non-finite at iteration {it}; the previous '
                          'estimate stands')


def _slow_contraction(history: list[float]) -> bool:
    """The last step's decrease is more than a quarter of the previous step's (a contraction
    slower than 1/2 per step: a chord step's factor should be renewed)."""
    return len(history) > 2 and history[-2] - history[-1] > 0.25 * (history[-3] - history[-2])


def _objective(prob: _Problem, plain: bool, cost: float, v: FloatArray, T: FloatArray,
               sysd: _System) -> float:
    """The cost history's entry at ``T`` after a step whose cost was ``cost`` (``plain``: that
    cost is the objective, no robust reweighting to evaluate again)."""
    return cost if plain else (_adjustment_cost(v, prob.P, sysd.weights)
                               + _prior_cost(prob.model, T, prob.prior_data))


def _last_chord_step(prob: _Problem, T: FloatArray, v: FloatArray, sysd: _System,
                     chord_h: FloatArray, state: _Trust, history: list[float],
                     plain: bool) -> tuple[FloatArray, FloatArray] | None:
    """The dogleg's chord step ``chord_h`` from the last factor as the last step, when the
    decrease it predicts shows less than ``cost_tolerance`` of the cost left to gain
    (:func:`_left_to_gain`): ``(T, v)`` after it, or unchanged if it does not lower the cost
    as predicted (:func:`_chord_kept`); ``None`` when more is left to gain."""
    predicted = -float(sysd.u @ chord_h)
    if not (_left_to_gain(predicted, state.predicted, history)
            < prob.cfg.cost_tolerance * history[-1]):
        return None
    T_new = prob.retract(T, chord_h)
    cost = prob.cost_at(T_new)
    if state.cost - cost >= 0 and _chord_kept(predicted, state.cost, cost):
        T, v = T_new, prob.next_residuals(T_new, sysd, chord_h)
        history.append(_objective(prob, plain, cost, v, T, sysd))
    return T, v


def _undamped_step(prob: _Problem, T: FloatArray, sysd: _System, data: FloatArray | None,
                   state: _Trust, chord: bool, keep_values: bool,
                   history: list[float]) -> _Step | str | None:
    """One Gauss-Helmert correction ``dx = -N^-1 u`` (eq. 15): ``N`` factored from ``data``,
    or, for a chord step, the last factor reused. Returns the step, ``'cost_converged'`` when
    a chord step would gain less than ``cost_tolerance`` of the cost (not taken), or ``None``
    when a chord step taken did not lower the cost as predicted (:func:`_chord_kept`: undone).

    With a ``cost_tolerance`` the iteration stops before a chord step whose predicted
    decrease ``-u' h = h' N_old h`` is below that fraction of the cost (the Newton decrement in
    the metric of the last factor: the cost left to gain, up to the factor's error). Measured
    on the aerial window (10 % noise, after the pre-alignment): the chord step after the first
    Gauss-Newton step predicted 0.005-0.02 (cost ~30,000), so the update stops at the
    Gauss-Newton step's estimate, 0.01-0.17 m RMS from the window's optimum; taking that
    chord step and stopping on its realised decrease moved the estimate 0.1-0.35 m away from
    the optimum along the weak modes for a decrease of 0.01.
    """
    cfg = prob.cfg
    if not chord:
        state.factor(prob.pattern, data)
        state.since_factor = 0.0
        state.factored = data if keep_values else None
    dx = -state.chol.solve(sysd.u)
    if not np.isfinite(dx).all():
        raise SolverError('the correction is not finite')
    if chord and cfg.cost_tolerance > 0 and -float(sysd.u @ dx) < cfg.cost_tolerance * history[-1]:
        return 'cost_converged'
    T_new = prob.retract(T, dx)
    size = float(np.abs(dx).max()) if dx.size else 0.0
    ahead = prob.gradient_ahead(T_new, size)
    if ahead is not None:  # the next chord step's gradient, residuals and cost at once
        v_new, cost = ahead.w, ahead.cost0
    else:
        v_new = prob.next_residuals(T_new, sysd, dx)
        cost = (_adjustment_cost(v_new, prob.P, sysd.weights)
                + _prior_cost(prob.model, T_new, prob.prior_data))
    if chord and not _chord_kept(-float(sysd.u @ dx), history[-1], cost):
        return None
    state.since_factor += size
    return _Step(T_new, v_new, size, True, cost, not chord)


def _weak_equations(system: _NormalSystem, node_ids: IntArray, prior) -> float:
    """``tr(Q H)`` of a datum prior (block-diagonal information ``H``, ``Q`` the marginal
    covariance blocks of its nodes at the solution, zero for a fixed node): the equations it
    contributes to the redundancy (:attr:`GaussianPrior.weak
    <ga_ros.core.solver.priors.GaussianPrior.weak>`)."""
    diag = prior.blk_r == prior.blk_c
    Q = system.marginal_blocks(np.asarray(node_ids)[prior.idx[prior.blk_r[diag]]])
    return float(np.einsum('kij,kji->', Q, prior.H_blocks[diag]))


def _finish(prob: _Problem, node_ids: IntArray, out: _Iterations, t0: float) -> SolveResult:
    """Final linearisation at the solution: residuals, variance factor, ``N`` (eq. 17); the
    covariances from the iteration's last factor when it kept that factor's values
    (:func:`solve`'s ``factor_at_solution=False``)."""
    T = out.T
    d, conn = prob.d, prob.conn
    n_free = int(prob.free.sum())
    if prob.Pf is not None:
        # motion models: out.v is the misclosure at T, so the residuals (v = weights * w) need
        # no linearisation; N is assembled only if a covariance or prior asks for it
        if prob.cfg.robust_loss == 'none':
            weights, v = np.ones(len(conn)), out.v.copy()
        else:
            weights = prob.cfg.loss.weight(np.sqrt(np.maximum(_maha2(out.v, prob.P), 0.0)))
            v = out.v * weights[:, None]

        def data() -> FloatArray:
            return prob.linear_system(T, out.v).normal_values(prob.pattern)
    else:
        final = prob.linear_system(T, out.v)
        v = prob.residual_update(final, np.zeros(n_free * d))
        weights = final.weights
        data = final.normal_values(prob.pattern)
    if (prob.Pf is not None and prob.cfg.robust_loss == 'none' and prob.cfg.damping == 'none'
            and len(out.history) > 1):
        cost = out.history[-1]  # this very sum, evaluated at T after the last step (_iterate)
    else:
        cost = (_adjustment_cost(v, prob.P, weights)
                + _prior_cost(prob.model, T, prob.prior_data))
    r_eq = len(conn) * models.equations_per_connection(prob.model) + sum(
        p.rank for p in prob.prior_data)
    redundancy = r_eq - n_free * d
    sigma0_sq = cost / redundancy if redundancy > 0 else float('nan')
    o = models.observations_per_connection(prob.model)
    if o != conn.z.shape[1]:  # se2: the planar components of the 6-vector
        v6 = np.zeros_like(conn.z)
        v6[:, se2.AXES] = v
        v = v6
    # kept only by undamped iterations asked to (keep_values), at their last factorisation
    last = out.factored is not None
    if last:  # N as factored: covariances, normal matrix and priors of one matrix
        data = out.factored
    system = _NormalSystem(node_ids, prob.free, prob.col, d, prob.pattern, data, out.chol,
                           factored=last, auto=prob.cfg.factor == 'auto')
    system.coords = T[prob.free, :3, 3]
    weak = [p for p in prob.prior_data if p.weak]
    if weak and redundancy > 0:
        # a datum prior's redundancy number rank - tr(Q H) is not the observations'
        # (GaussianPrior.weak): the redundancy counts its equations by tr(Q H) only
        redundancy = float(redundancy) - sum(p.rank - _weak_equations(system, node_ids, p)
                                             for p in weak)
        sigma0_sq = cost / redundancy if redundancy > 0 else float('nan')
    return SolveResult(
        node_ids=node_ids, T_world_node=T, converged=out.converged, iterations=out.iterations,
        reason=out.reason, cost=float(cost), cost_history=out.history,
        sigma0_sq=float(sigma0_sq), redundancy=redundancy if weak else int(redundancy),
        n_equations=int(r_eq),
        n_observations=int(o * len(conn) + sum(p.idx.size * d for p in prob.prior_data)),
        n_unknowns=int(n_free * d), residuals=v, adjusted=conn.z + v,
        seconds=time.perf_counter() - t0, model=prob.model, weights=weights,
        factorisations=out.factorisations, factor_offset=out.since_factor if last else 0.0,
        _system=system)
