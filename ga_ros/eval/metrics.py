"""Error metrics against ground truth.

* Position error of each node: ``|p_est - p_true|`` (m).
* ATE (absolute trajectory error, Sturm et al. 2012): RMSE of the position errors, either *raw*
  (the estimate's first pose is moved onto the true first pose, i.e. "first pose anchored") or
  *aligned* (after the least-squares rigid motion that best maps the estimated positions onto the
  true ones: Horn 1987 / Umeyama 1991, without scale).
* Per-track mean errors and the relative improvement of one estimate over another (as a number,
  and in words: "lower" / "higher").
* :func:`trajectory_error`: the replay's summary (raw and aligned RMSE, max) of matched
  positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import InputError
from ga_ros.geometry import se3


@dataclass(frozen=True)
class RigidAlignment:
    """``p_true ~= R @ p_est + t`` (rotation ``R`` (3, 3), translation ``t`` (3,) in m)."""

    R: FloatArray
    t: FloatArray

    def apply(self, p: FloatArray) -> FloatArray:
        """Transform positions ``(n, 3)``."""
        return np.asarray(p, dtype=float) @ self.R.T + self.t


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error (m): RMSE, mean, median and max of the per-node errors."""

    rmse: float
    mean: float
    median: float
    max: float
    errors: FloatArray


def _positions(x: FloatArray) -> FloatArray:
    x = np.asarray(x, dtype=float)
    if x.ndim == 3 and x.shape[1:] == (4, 4):
        return x[:, :3, 3]
    if x.ndim == 2 and x.shape[1] == 3:
        return x
    raise InputError(f'expected poses (n, 4, 4) or positions (n, 3), got shape {x.shape}')


def position_errors(est: FloatArray, true: FloatArray) -> FloatArray:
    """Per-node position errors ``(n,)`` (m) of poses ``(n, 4, 4)`` or positions ``(n, 3)``."""
    p, q = _positions(est), _positions(true)
    if p.shape != q.shape:
        raise InputError(f'estimate and ground truth differ in shape: {p.shape} vs {q.shape}')
    return np.linalg.norm(p - q, axis=1)


def align_rigid(p_est: FloatArray, p_true: FloatArray) -> RigidAlignment:
    """Least-squares rigid alignment (Umeyama 1991, eqs. 34-42, scale fixed to 1).

    Minimises ``sum |R p_est_k + t - p_true_k|^2`` over rotations ``R`` and translations ``t``.

    Parameters
    ----------
    p_est, p_true : (n, 3) corresponding positions (m), ``n >= 3`` not collinear for a unique
        rotation (a collinear set still gives a minimiser).
    """
    p, q = _positions(p_est), _positions(p_true)
    if p.shape != q.shape or p.shape[0] < 2:
        raise InputError(f'need two (n >= 2, 3) position sets of equal shape, got {p.shape}, '
                         f'{q.shape}')
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    C = (q - mq).T @ (p - mp) / p.shape[0]
    U, _, Vt = np.linalg.svd(C)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    return RigidAlignment(R=R, t=mq - R @ mp)


def anchor_first(T_est: FloatArray, T_true: FloatArray) -> FloatArray:
    """Move the estimated trajectory rigidly so its first pose equals the true first pose:
    ``T_true[0] @ T_est[0]^-1 @ T_est`` (``(n, 4, 4)``)."""
    T_est = np.asarray(T_est, dtype=float)
    T_true = np.asarray(T_true, dtype=float)
    if T_est.shape != T_true.shape or T_est.ndim != 3 or T_est.shape[1:] != (4, 4):
        raise InputError('anchor_first needs two pose stacks (n, 4, 4) of equal shape')
    return T_true[0] @ se3.inverse(T_est[0]) @ T_est


def ate(T_est: FloatArray, T_true: FloatArray, align: str = 'rigid') -> AteResult:
    """Absolute trajectory error.

    Parameters
    ----------
    T_est, T_true : (n, 4, 4) poses ``T_world_node`` (``align='none'`` also accepts positions).
    align : ``'none'`` (compare as given), ``'first'`` (raw: first pose anchored, see
        :func:`anchor_first`) or ``'rigid'`` (after :func:`align_rigid`).
    """
    if align == 'none':
        e = position_errors(T_est, T_true)
    elif align == 'first':
        e = position_errors(anchor_first(T_est, T_true), T_true)
    elif align == 'rigid':
        p, q = _positions(T_est), _positions(T_true)
        e = np.linalg.norm(align_rigid(p, q).apply(p) - q, axis=1)
    else:
        raise InputError(f"align must be 'none', 'first' or 'rigid', got {align!r}")
    return AteResult(rmse=float(np.sqrt(np.mean(e * e))), mean=float(e.mean()),
                     median=float(np.median(e)), max=float(e.max()), errors=e)


def per_track_mean(errors: FloatArray, track_ids: IntArray) -> dict[int, float]:
    """Mean of ``errors`` (n,) over the nodes of each track: ``{track_id: mean}``."""
    errors = np.asarray(errors, dtype=float)
    track_ids = np.asarray(track_ids)
    if errors.shape != track_ids.shape:
        raise InputError('errors and track_ids must have the same shape')
    tracks, inv = np.unique(track_ids, return_inverse=True)
    sums = np.bincount(inv, weights=errors)
    counts = np.bincount(inv)
    return {int(t): float(s / c) for t, s, c in zip(tracks, sums, counts)}


def improvement_pct(error_before: float, error_after: float) -> float:
    """Relative error reduction in percent: ``100 (before - after) / before``."""
    if not error_before > 0:
        raise InputError(f'reference error must be > 0, got {error_before}')
    return float(100.0 * (error_before - error_after) / error_before)


def relative_change_text(error: float, reference: float, name: str) -> str:
    """``error`` against ``reference`` in words: ``'76.5 % lower than F2F'``, ``'7.0 % higher
    than F2F'`` or ``'equal to F2F'`` (to the printed precision); ``''`` without a positive
    reference.

    Parameters
    ----------
    error, reference : the two errors (same unit).
    name : what the reference is (``'F2F'``).
    """
    if not reference > 0 or not np.isfinite(error):
        return ''
    pct = 100.0 * (error - reference) / reference
    if round(abs(pct), 1) == 0.0:
        return f'equal to {name}'
    return f'{abs(pct):.1f} % {"lower" if pct < 0 else "higher"} than {name}'



@dataclass(frozen=True)
class TrajectoryError:
    """Position errors of an estimate against ground truth (m), as the replay reports them.

    Attributes
    ----------
    ate_raw : RMSE of position errors as estimated (the first pose is the datum).
    ate_aligned : RMSE after the best rigid alignment (:func:`align_rigid`).
    max_raw : largest raw position error.
    n : number of matched poses.
    """

    ate_raw: float
    ate_aligned: float
    max_raw: float
    n: int

    def compared(self, how: str) -> float:
        """The RMSE compared between estimates: ``'raw'`` (:attr:`ate_raw`, estimates anchored
        at the ground truth) or ``'aligned'`` (:attr:`ate_aligned`, estimates in another
        frame)."""
        if how not in ('raw', 'aligned'):
            raise InputError(f"how must be 'raw' or 'aligned', got {how!r}")
        return self.ate_raw if how == 'raw' else self.ate_aligned

    def as_dict(self) -> dict[str, float]:
        return {'ate_raw_m': self.ate_raw, 'ate_aligned_m': self.ate_aligned,
                'max_raw_m': self.max_raw, 'n': self.n}


def trajectory_error(p_est: FloatArray, p_ref: FloatArray) -> TrajectoryError:
    """Raw and rigidly aligned position RMSE of ``p_est`` (n, 3) against ``p_ref`` (n, 3), m."""
    p_est = np.asarray(p_est, dtype=float).reshape(-1, 3)
    p_ref = np.asarray(p_ref, dtype=float).reshape(-1, 3)
    err = np.linalg.norm(p_est - p_ref, axis=1)
    err_al = np.linalg.norm(align_rigid(p_est, p_ref).apply(p_est) - p_ref, axis=1)
    return TrajectoryError(float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(err_al**2))),
                           float(err.max()), int(err.size))


def position_nees(T_est: FloatArray, cov: FloatArray, T_ref: FloatArray) -> FloatArray:
    """Position NEES ``e' C_pp^-1 e`` of each node ``(n,)`` (mean 3 when ``cov`` is honest).

    ``e`` is the translation part of the right-perturbation error ``log(T_est^-1 T_ref)`` (the
    solver's convention ``T = T_est exp(d)``, ``d = [x y z rx ry rz]`` in the node's frame), so
    ``cov`` is the published ``(n, 6, 6)`` covariance of ``d`` and ``C_pp`` its position block.
    The datum is the first node (held fixed by the solver): no alignment is applied.

    Parameters
    ----------
    T_est, T_ref : (n, 4, 4) estimated and true poses ``T_world_node``.
    cov : (n, 6, 6) covariances in the order ``[x y z rx ry rz]`` (m^2, rad^2).
    """
    T_est = np.asarray(T_est, dtype=float)
    T_ref = np.asarray(T_ref, dtype=float)
    cov = np.asarray(cov, dtype=float)
    n = T_est.shape[0]
    if T_est.shape != (n, 4, 4) or T_ref.shape != (n, 4, 4) or cov.shape != (n, 6, 6):
        raise InputError(f'expected (n, 4, 4) poses and (n, 6, 6) covariances, got '
                         f'{T_est.shape}, {T_ref.shape} and {cov.shape}')
    e = se3.log(se3.inverse(T_est) @ T_ref)[:, :3]
    return np.einsum('ni,ni->n', e, np.linalg.solve(cov[:, :3, :3], e[:, :, None])[:, :, 0])
