"""The damped steps: Levenberg-Marquardt, Powell's dogleg and the dogleg's chord step."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.solver.linearise import _System
from ga_ros.core.solver.problem import _Problem
from ga_ros.errors import DegenerateGeometryError


@dataclass
class _Step:
    """One accepted (or refused) correction of :func:`_iterate`."""

    T: FloatArray
    v: FloatArray
    step: float  # max |dx| (m, rad); 0 when refused
    accepted: bool
    cost: float = np.nan  # cost at T (damped strategies only)
    gauss_newton: bool = True  # the full Gauss-Newton step was taken
    predicted: float = np.nan  # the decrease its quadratic model predicted (dogleg)


@dataclass
class _Trust:
    """State carried between iterations by the damped strategies."""

    chol: SparseCholesky | None = None
    factorisations: int = 0
    lam: float = 1e-4  # Levenberg-Marquardt damping
    radius: float = 0.0  # dogleg trust radius (0: not set yet, the first step tries full GN)
    auto: bool = False  # a new factor may be simplicial (SolverConfig.factor 'auto')
    cost: float = np.inf  # cost at the current estimate
    chord: bool = False  # dogleg: try the last factorisation first (see _chord_step)
    predicted: float = np.nan  # dogleg: the decrease the last step's model predicted
    since_factor: float = np.inf  # undamped: sum of max |dx| since the last factorisation
    factored: FloatArray | None = None  # undamped: the values of N last factored (kept)

    def factor(self, pattern: BlockPattern, data: FloatArray) -> SparseCholesky:
        if self.chol is None:
            self.chol = SparseCholesky(pattern, data, auto=self.auto)
        else:
            self.chol.refactor(data)
        self.factorisations += 1
        return self.chol


def _lm_step(prob: _Problem, T: FloatArray, sysd: _System, data: FloatArray,
             state: _Trust) -> _Step:
    """One Levenberg-Marquardt step of the Gauss-Helmert system.

    The system is linearised at the adjusted observations ``l0 = l_b + v`` exactly as in the
    undamped iteration (so its fixed point is the adjustment's optimum); the damping
    ``lam * diag(N)`` only shortens steps, and a step is accepted when the cost (the value of
    ``sum w' M^-1 w`` at ``v = 0``, which for se3 is exactly ``sum e' P e``) does not increase.
    Each refused step costs one more factorisation (see :func:`_dogleg_step` for a strategy
    that needs one per iteration).
    """
    diag_pos = prob.pattern.indptr[:-1]  # first entry of each CSC column is its diagonal
    diag = data[diag_pos]
    for _ in range(12):
        damped = data.copy()
        damped[diag_pos] += state.lam * np.maximum(diag, 1e-9)
        try:
            dx = -state.factor(prob.pattern, damped).solve(sysd.u)
        except DegenerateGeometryError:
            state.lam *= 10.0
            continue
        T_new = prob.retract(T, dx)
        cost = prob.cost_at(T_new)
        if cost <= state.cost:
            state.lam = max(state.lam / 10.0, 1e-9)
            return _Step(T_new, prob.next_residuals(T_new, sysd, dx),
                         float(np.abs(dx).max()), True, cost, False)
        state.lam *= 10.0
    return _Step(T, prob.residual_update(sysd, np.zeros_like(sysd.u)), 0.0, False, state.cost)


def _dogleg_step(prob: _Problem, T: FloatArray, sysd: _System, data: FloatArray,
                 state: _Trust, chord_h: FloatArray | None = None) -> _Step:
    """One step of Powell's dogleg (Nocedal & Wright, Sec. 4.1): one factorisation at most.

    The cost ``F = sum e' P e`` (+ priors) has the quadratic model
    ``F + 2 u' h + h' N h`` around ``T``. The Gauss-Newton step ``h_gn = -N^-1 u`` (the only
    factorisation) and the Cauchy point ``h_sd = -(u'u / u'N u) u`` span the dogleg path; a step
    of length at most the trust radius on it is tried, and a refused step only shrinks the
    radius and moves along the same path (no new factorisation). The first iteration tries the
    full Gauss-Newton step, so on a good initial guess this is Gauss-Newton. ``chord_h``: the
    chord step ``-N_old^-1 u`` (:func:`_chord_step`), tried first when given.
    """
    u = sysd.u
    if chord_h is not None:
        chord = _chord_step(prob, T, sysd, data, chord_h, state)
        if chord is not None:
            return chord
    h_gn = -state.factor(prob.pattern, data).solve(u)
    n_gn = float(np.linalg.norm(h_gn))
    radius = state.radius if state.radius > 0 else n_gn
    Nu = h_sd = None  # the Cauchy point, computed only when the radius cuts the GN step
    alpha = n_sd = 0.0
    for _ in range(30):
        if n_gn > radius and h_sd is None:
            Nu = prob.pattern.matvec(data, u)
            uNu = float(u @ Nu)
            alpha = float(u @ u) / uNu if uNu > 0 else 0.0
            h_sd = -alpha * u
            n_sd = float(np.linalg.norm(h_sd))
        if n_gn <= radius:
            a, b = 0.0, 1.0
        elif n_sd >= radius:
            a, b = radius / n_sd, 0.0
        else:  # |h_sd + t (h_gn - h_sd)| = radius, t in (0, 1)
            p = h_gn - h_sd
            pp, sp_, ss = float(p @ p), float(h_sd @ p), n_sd * n_sd
            t = (-sp_ + np.sqrt(sp_ * sp_ + pp * (radius * radius - ss))) / pp
            a, b = 1.0 - t, t
        h = b * h_gn if a == 0.0 else a * h_sd + b * h_gn
        Nh = -b * u if a == 0.0 else -a * alpha * Nu - b * u  # N h_gn = -u, N h_sd = -alpha Nu
        predicted = -(2.0 * float(u @ h) + float(h @ Nh))
        T_new = prob.retract(T, h)
        cost = prob.cost_at(T_new)
        actual = state.cost - cost
        norm_h = float(np.linalg.norm(h))
        rho = actual / predicted if predicted > 0 else -1.0
        if rho > 1e-4 or (actual >= 0 and predicted <= 1e-300):
            if rho > 0.75:
                radius = max(radius, 3.0 * norm_h)
            elif rho < 0.25:
                radius = 0.5 * norm_h
            state.radius = radius
            return _Step(T_new, prob.next_residuals(T_new, sysd, h),
                         float(np.abs(h).max()) if h.size else 0.0, True, cost, b == 1.0,
                         predicted)
        radius = 0.25 * norm_h
        if radius < 1e-12:
            break
    state.radius = max(radius, 1e-12)
    return _Step(T, prob.residual_update(sysd, np.zeros_like(u)), 0.0, False, state.cost)


def _chord_step(prob: _Problem, T: FloatArray, sysd: _System, data: FloatArray,
                h: FloatArray, state: _Trust) -> _Step | None:
    """The chord step ``h = -N_old^-1 u`` from the last factorisation (``N_old``, one
    iteration old), kept instead of factoring ``N`` anew when the new linearisation confirms it.

    With the quadratic model ``q(h) = 2 u' h + h' N h`` of the current linearisation, the step
    is kept when (a) the new and the old matrix agree along it, ``h' N h / h' N_old h`` within
    ``[0.8, 1.25]`` (``h' N_old h = -u' h``; a stale factor, e.g. of ``10 N``, fails), so that
    ``h`` is close to the Gauss-Newton step, and (b) the cost falls by at least a quarter of the
    predicted ``-q(h)`` (the dogleg's acceptance). It then counts as a Gauss-Newton step for the
    convergence test on the relative cost decrease. Otherwise ``None``: the caller factors ``N``
    as usual (the chord cost one solve, one product with ``N`` and perhaps one cost evaluation).
    """
    u = sysd.u
    old = -float(u @ h)  # h' N_old h
    hNh = float(h @ prob.pattern.matvec(data, h))
    if not (old > 0 and 0.8 * old <= hNh <= 1.25 * old):
        return None
    predicted = 2.0 * old - hNh
    T_new = prob.retract(T, h)
    cost = prob.cost_at(T_new)
    actual = state.cost - cost
    if not (actual >= 0 and actual >= 0.25 * predicted):
        return None
    return _Step(T_new, prob.next_residuals(T_new, sysd, h),
                 float(np.abs(h).max()) if h.size else 0.0, True, cost, True, predicted)
