"""SO(3): rotation vectors, Rodrigues' formula, log, and their Jacobians.

All functions are vectorised over any number of leading axes: a rotation vector has shape
``(..., 3)`` (radians, axis times angle) and a rotation matrix ``(..., 3, 3)``.

Jacobian conventions (Barfoot, *State Estimation for Robotics*, 2017, eqs. 7.77-7.87; Sola et al.,
"A micro Lie theory", 2018)::

    exp(w + dw) ~= exp(w) @ exp(right_jacobian(w) @ dw)
    exp(w + dw) ~= exp(left_jacobian(w) @ dw) @ exp(w)

with ``left_jacobian(w) == right_jacobian(-w)``. Small angles use Taylor series (the closed forms
divide by powers of the angle and lose all precision below ~1e-4 rad).
"""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray

#: Below this angle (rad) the Taylor branches are used.
SMALL_ANGLE = 1e-4


def hat(w: FloatArray) -> FloatArray:
    """Skew matrix ``[w]x``, ``hat(w) @ v == cross(w, v)``; ``(..., 3) -> (..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee(W: FloatArray) -> FloatArray:
    """Inverse of :func:`hat`: ``(..., 3, 3) -> (..., 3)`` (uses the skew part)."""
    W = np.asarray(W, dtype=float)
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def _coeffs(w: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Angle ``theta`` and ``a = sin(t)/t``, ``b = (1-cos t)/t^2``, ``c = (t - sin t)/t^3``."""
    theta = np.linalg.norm(w, axis=-1)
    small = theta < SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(t)) / (t * t))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / (t * t * t))
    return theta, a, b, c


def _exp_one(w: FloatArray) -> FloatArray:
    """:func:`exp` of one rotation vector ``(3,)``, bit for bit (the same operations in the
    same order, on scalars: a tenth of the array path's NumPy overhead; tested)."""
    w0, w1, w2 = float(w[0]), float(w[1]), float(w[2])
    theta = np.sqrt(np.float64(w0 * w0 + w1 * w1 + w2 * w2))  # np.linalg.norm's sum
    t2 = theta * theta  # as _coeffs (not the sum: they may differ in the last bit)
    if theta < SMALL_ANGLE:
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    else:
        a = np.sin(theta) / theta
        b = (1.0 - np.cos(theta)) / (theta * theta)
    W = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    return np.eye(3) + a * W + b * (W @ W)


def exp(w: FloatArray) -> FloatArray:
    """Rodrigues' formula ``R = I + a [w]x + b [w]x^2``; ``(..., 3) -> (..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    if w.shape == (3,):
        return _exp_one(w)
    _, a, b, _ = _coeffs(w)
    W = hat(w)
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def log(R: FloatArray) -> FloatArray:
    """Rotation vector of a rotation matrix, angle in ``[0, pi]``; ``(..., 3, 3) -> (..., 3)``.

    Near ``pi`` the axis is taken from the symmetric part ``(R + I) / 2 = u u'`` because the
    skew part vanishes there.
    """
    R = np.asarray(R, dtype=float)
    if R.shape == (3, 3):
        w = _log_one(R)
        if w is not None:
            return w
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    cos_t = (np.trace(R, axis1=-2, axis2=-1) - 1.0) * 0.5
    v = vee(R)  # = sin(theta) * axis
    sin_t = np.linalg.norm(v, axis=-1)
    theta = np.arctan2(sin_t, cos_t)  # well conditioned at 0 and pi, unlike arccos
    small = theta < SMALL_ANGLE
    scale = np.where(small, 1.0 + theta * theta / 6.0, theta / np.where(small, 1.0, sin_t))
    w = v * scale[..., None]
    near_pi = theta > np.pi - 1e-2
    if np.any(near_pi):
        Rp = R[near_pi]
        # symmetric part: (R + R')/2 - cos(t) I = (1 - cos t) u u'
        B = 0.5 * (Rp + np.swapaxes(Rp, -1, -2)) - cos_t[near_pi, None, None] * np.eye(3)
        col = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        u = np.take_along_axis(B, col[:, None, None], axis=-1)[..., 0]
        u = u / np.linalg.norm(u, axis=-1, keepdims=True)
        sgn = np.sign(np.sum(u * v[near_pi], axis=-1))  # so that exp(log(R)) == R
        sgn = np.where(sgn == 0, 1.0, sgn)
        w[near_pi] = u * (sgn * theta[near_pi])[..., None]
    return w.reshape(shape + (3,))


def _log_one(R: FloatArray) -> FloatArray | None:
    """:func:`log` of one rotation matrix ``(3, 3)``, bit for bit (the same operations in the
    same order, on scalars; tested), or ``None`` near ``pi`` (the array path's branch)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    cos_t = np.float64(((r00 + r11) + r22 - 1.0) * 0.5)
    v0, v1, v2 = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    sin_t = np.sqrt(np.float64(v0 * v0 + v1 * v1 + v2 * v2))
    theta = np.arctan2(sin_t, cos_t)
    if theta > np.pi - 1e-2:
        return None
    scale = 1.0 + theta * theta / 6.0 if theta < SMALL_ANGLE else theta / sin_t
    return np.array([v0, v1, v2]) * scale


def left_jacobian(w: FloatArray) -> FloatArray:
    """``J_l(w) = I + b [w]x + c [w]x^2`` (Barfoot eq. 7.77); ``(..., 3) -> (..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    _, _, b, c = _coeffs(w)
    W = hat(w)
    return np.eye(3) + b[..., None, None] * W + c[..., None, None] * (W @ W)


def right_jacobian(w: FloatArray) -> FloatArray:
    """``J_r(w) = J_l(-w)``; ``(..., 3) -> (..., 3, 3)``."""
    return left_jacobian(-np.asarray(w, dtype=float))


def left_jacobian_inv(w: FloatArray) -> FloatArray:
    """``J_l(w)^-1 = I - [w]x / 2 + e [w]x^2``, ``e = (1 - a / (2 b)) / t^2`` (Barfoot 7.78)."""
    w = np.asarray(w, dtype=float)
    theta, a, b, _ = _coeffs(w)
    small = theta < SMALL_ANGLE
    t2 = np.where(small, 1.0, theta * theta)
    th2 = theta * theta
    e = np.where(small, 1.0 / 12.0 + th2 / 720.0 + th2 * th2 / 30240.0,
                 (1.0 - a / (2.0 * np.where(small, 1.0, b))) / t2)
    W = hat(w)
    return np.eye(3) - 0.5 * W + e[..., None, None] * (W @ W)


def right_jacobian_inv(w: FloatArray) -> FloatArray:
    """``J_r(w)^-1 = J_l(-w)^-1``; ``(..., 3) -> (..., 3, 3)``."""
    return left_jacobian_inv(-np.asarray(w, dtype=float))


def project(R: FloatArray) -> FloatArray:
    """Nearest rotation matrix (SVD), for re-orthonormalising accumulated products."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=float))
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    return U @ Vt
