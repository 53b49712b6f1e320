"""SE(3): 4x4 homogeneous poses, exp/log, adjoint and Jacobians, quaternion conversions.

Conventions used throughout ga_ros
----------------------------------
* A pose ``T_a_b`` (shape ``(..., 4, 4)``) maps points from frame ``b`` into frame ``a``:
  ``p_a = T_a_b @ p_b``. Node poses are ``T_world_node``.
* A tangent vector is ``xi = [rho, phi]`` (shape ``(..., 6)``): translation part first, then the
  rotation vector (rad), the same order as a ROS pose covariance ``[x y z rx ry rz]``.
* Perturbations are on the right: ``T (+) xi = T @ exp(xi)``; a pose covariance is the covariance
  of that ``xi`` (the convention of GTSAM, g2o and of ROS ``PoseWithCovariance``).
* ``exp(x + d) ~= exp(x) @ exp(right_jacobian(x) @ d) ~= exp(left_jacobian(x) @ d) @ exp(x)``
  (Barfoot, *State Estimation for Robotics*, eqs. 7.85-7.95, with his ``[rho; phi]`` order).
"""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.geometry import so3


def identity(n: int | None = None) -> FloatArray:
    """Identity pose, ``(4, 4)`` or ``(n, 4, 4)``."""
    return np.eye(4) if n is None else np.broadcast_to(np.eye(4), (n, 4, 4)).copy()


def from_rt(R: FloatArray, t: FloatArray) -> FloatArray:
    """Pose from rotation ``(..., 3, 3)`` and translation ``(..., 3)``."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    one = R.shape == (3, 3) and t.shape == (3,)  # one pose: no broadcast
    out = np.zeros((4, 4) if one else np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def from_translation_rotvec(t: FloatArray, w: FloatArray) -> FloatArray:
    """Pose ``(R(w), t)`` from translation ``t`` (m) and rotation vector ``w`` (rad)."""
    return from_rt(so3.exp(w), t)


def to_translation_rotvec(T: FloatArray) -> FloatArray:
    """``[t, w]`` (shape ``(..., 6)``, m and rad) of a pose; inverse of
    :func:`from_translation_rotvec`."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], so3.log(T[..., :3, :3])], axis=-1)


def from_pos_quat(p: FloatArray, quat_xyzw: FloatArray) -> FloatArray:
    """Pose from position ``(..., 3)`` and unit quaternion ``(..., 4)`` in ``x y z w`` order
    (ROS and g2o order). The quaternion is normalised; a zero quaternion raises ValueError.

    NumPy only (the rotation matrix of a unit quaternion, e.g. Sola, *Quaternion kinematics for
    the error-state Kalman filter*, 2017, eq. 115): importing SciPy's ``Rotation`` costs
    ~0.1-0.3 s of a command's start-up.
    """
    q = np.asarray(quat_xyzw, dtype=float)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError('found a zero quaternion (norm 0): cannot make a rotation of it')
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[..., 0, 1] = 2.0 * (x * y - z * w)
    R[..., 0, 2] = 2.0 * (x * z + y * w)
    R[..., 1, 0] = 2.0 * (x * y + z * w)
    R[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[..., 1, 2] = 2.0 * (y * z - x * w)
    R[..., 2, 0] = 2.0 * (x * z - y * w)
    R[..., 2, 1] = 2.0 * (y * z + x * w)
    R[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return from_rt(R, p)


def quat_from_matrix(R: FloatArray) -> FloatArray:
    """Unit quaternion ``(..., 4)`` (``x y z w``, ``w >= 0``) of rotation matrices ``(..., 3, 3)``.

    Shepperd's method (J. Guidance and Control 1(3), 1978): of the four ways to recover the
    quaternion from the trace and the diagonal, the one with the largest square root is used,
    so no division by a small number occurs (every rotation, including angles near pi).
    """
    R = np.asarray(R, dtype=float)
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    s21, s02, s10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], \
        R[..., 1, 0] - R[..., 0, 1]
    a01, a02, a12 = R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], \
        R[..., 1, 2] + R[..., 2, 1]
    # candidates (x y z w) * 4 q_k, q_k = w, x, y, z the pivot; k by the largest 4 q_k^2
    diag = np.stack([r00 + r11 + r22, r00 - r11 - r22, r11 - r00 - r22, r22 - r00 - r11],
                    axis=-1)
    k = np.argmax(diag, axis=-1)[..., None]
    piv = 1.0 + np.take_along_axis(diag, k, axis=-1)[..., 0]  # 4 q_k^2
    cand = np.stack([np.stack([s21, s02, s10, piv], axis=-1),
                     np.stack([piv, a01, a02, s21], axis=-1),
                     np.stack([a01, piv, a12, s02], axis=-1),
                     np.stack([a02, a12, piv, s10], axis=-1)], axis=-2)
    q = np.take_along_axis(cand, k[..., None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def to_pos_quat(T: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Position ``(..., 3)`` and quaternion ``(..., 4)`` (``x y z w``, ``w >= 0``) of a pose."""
    T = np.asarray(T, dtype=float)
    return T[..., :3, 3].copy(), quat_from_matrix(T[..., :3, :3])


def inverse(T: FloatArray) -> FloatArray:
    """``T^-1`` using the rotation's transpose."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return from_rt(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def relative(T_w_a: FloatArray, T_w_b: FloatArray) -> FloatArray:
    """``T_a_b = T_w_a^-1 @ T_w_b``: the motion of ``b`` expressed in the frame of ``a``."""
    return inverse(T_w_a) @ np.asarray(T_w_b, dtype=float)


def Q_matrix(xi: FloatArray) -> FloatArray:
    """Barfoot's ``Q(rho, phi)`` (eq. 7.86), the off-diagonal block of the SE(3) left Jacobian.

    ``Q = rho^/2 + c1 (p^r^ + r^p^ + p^r^p^) + c2 (p^p^r^ + r^p^p^ - 3 p^r^p^)
    + c3 (p^r^p^p^ + p^p^r^p^)`` with the products of skew matrices in closed form
    (``a^b^ = b a' - (a.b) I``, hence ``p^r^p^ = -(p.r) p^``, ``p^p^r^ = p (p x r)' - t^2 r^``,
    ``r^p^p^ = (r x p) p' - t^2 r^``, and both quartic terms ``-(p.r) (p p' - t^2 I)``):
    outer products of 3-vectors instead of stacked 3x3 matrix products.
    """
    xi = np.asarray(xi, dtype=float)
    rho, phi = xi[..., :3], xi[..., 3:]
    t2 = np.sum(phi * phi, axis=-1)
    theta = np.sqrt(t2)
    small = theta < 1e-3
    t = np.where(small, 1.0, theta)
    c1 = np.where(small, 1 / 6 - t2 / 120 + t2 * t2 / 5040, (t - np.sin(t)) / t**3)
    c2 = np.where(small, 1 / 24 - t2 / 720 + t2 * t2 / 40320,
                  (t * t + 2 * np.cos(t) - 2) / (2 * t**4))
    c3 = np.where(small, 1 / 120 - t2 / 2520 + t2 * t2 / 120960,
                  (2 * t - 3 * np.sin(t) + t * np.cos(t)) / (2 * t**5))
    e = (..., None, None)
    pr = np.sum(phi * rho, axis=-1)[e]
    pxr = _cross(phi, rho)
    P = so3.hat(phi)
    Rh = so3.hat(rho)
    eye = np.eye(3)
    outer = rho[..., :, None] * phi[..., None, :]      # r p' (broadcast: einsum is ~5x slower)
    out = (0.5 - 2.0 * c2[e] * t2[e]) * Rh
    out += c1[e] * (outer + np.swapaxes(outer, -1, -2) - 2.0 * pr * eye - pr * P)
    out += c2[e] * (phi[..., :, None] * pxr[..., None, :] - pxr[..., :, None] * phi[..., None, :]
                    + 3.0 * pr * P)
    out -= (2.0 * c3[e] * pr) * (phi[..., :, None] * phi[..., None, :] - t2[e] * eye)
    return out


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a x b`` over the last axis (``np.cross`` costs several times more on stacks)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def exp(xi: FloatArray) -> FloatArray:
    """Exponential map ``[rho, phi] -> T``; ``(..., 6) -> (..., 4, 4)`` (Barfoot eq. 7.83)."""
    xi = np.asarray(xi, dtype=float)
    phi = xi[..., 3:]
    # so3.exp and so3.left_jacobian share [phi]x and its square: R = I + a W + b W^2,
    # J_l = I + b W + c W^2 (the same arithmetic as those functions)
    _, a, b, c = so3._coeffs(phi)
    W = so3.hat(phi)
    W2 = W @ W
    e = (..., None, None)
    t = ((np.eye(3) + b[e] * W + c[e] * W2) @ xi[..., :3, None])[..., 0]
    return from_rt(np.eye(3) + a[e] * W + b[e] * W2, t)


def log(T: FloatArray) -> FloatArray:
    """Logarithm ``T -> [rho, phi]``; ``(..., 4, 4) -> (..., 6)``."""
    T = np.asarray(T, dtype=float)
    phi = so3.log(T[..., :3, :3])
    rho = (so3.left_jacobian_inv(phi) @ T[..., :3, 3:4])[..., 0]
    return np.concatenate([rho, phi], axis=-1)


def adjoint(T: FloatArray) -> FloatArray:
    """``Ad(T)`` with ``T exp(xi) T^-1 = exp(Ad(T) xi)``: ``[[R, [t]x R], [0, R]]``, 6x6."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = so3.hat(T[..., :3, 3]) @ R
    return out


def change_frame(T_ca_cb: FloatArray, cov: FloatArray, T_base_cam: FloatArray
                 ) -> tuple[FloatArray, FloatArray]:
    """The motion of a rigid body's base from the motion of a sensor mounted on it.

    ``T_ba_bb = T_base_cam T_ca_cb T_base_cam^-1`` with covariance
    ``Ad(T_base_cam) C Ad(T_base_cam)^T`` (right perturbation: ``T_ca_cb exp(d)`` moves the
    base motion to ``T_ba_bb exp(Ad(T_base_cam) d)``).

    Parameters
    ----------
    T_ca_cb : (4, 4) the sensor's motion between two times.
    cov : (6, 6) its covariance ``[x y z rx ry rz]``.
    T_base_cam : (4, 4) the extrinsic: the sensor frame in the base frame.

    Returns
    -------
    tuple
        ``T_ba_bb`` (4, 4) and its (6, 6) covariance.
    """
    A = adjoint(T_base_cam)
    C = A @ np.asarray(cov, dtype=float) @ A.T
    return T_base_cam @ np.asarray(T_ca_cb, dtype=float) @ inverse(T_base_cam), 0.5 * (C + C.T)


def left_jacobian(xi: FloatArray) -> FloatArray:
    """SE(3) left Jacobian ``[[J, Q], [0, J]]`` with ``J = so3.left_jacobian(phi)``."""
    xi = np.asarray(xi, dtype=float)
    J = so3.left_jacobian(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = J
    out[..., 3:, 3:] = J
    out[..., :3, 3:] = Q_matrix(xi)
    return out


def left_jacobian_inv(xi: FloatArray) -> FloatArray:
    """``[[J^-1, -J^-1 Q J^-1], [0, J^-1]]`` (Barfoot eq. 7.95)."""
    xi = np.asarray(xi, dtype=float)
    Ji = so3.left_jacobian_inv(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Ji
    out[..., 3:, 3:] = Ji
    out[..., :3, 3:] = -Ji @ Q_matrix(xi) @ Ji
    return out


def right_jacobian(xi: FloatArray) -> FloatArray:
    """``J_r(xi) = J_l(-xi)``."""
    return left_jacobian(-np.asarray(xi, dtype=float))


def right_jacobian_inv(xi: FloatArray) -> FloatArray:
    """``J_r(xi)^-1 = J_l(-xi)^-1``."""
    return left_jacobian_inv(-np.asarray(xi, dtype=float))


def retract(T: FloatArray, xi: FloatArray) -> FloatArray:
    """``T @ exp(xi)``, re-orthonormalised so that repeated updates do not drift.

    A product of rotations is orthonormal to rounding, so one Bjorck (Newton-Schulz polar) step
    ``R (3 I - R'R) / 2``, which squares the deviation, suffices; a rotation that is still off by
    more than 1e-10 afterwards (a non-orthonormal input) is projected by SVD. That check runs
    only where the deviation before the step exceeds 1e-6 (the step leaves ``3/4`` of its square
    and less: below 1e-11 otherwise).
    """
    out = np.asarray(T, dtype=float) @ exp(xi)
    R = out[..., :3, :3]
    RtR = np.swapaxes(R, -1, -2) @ R
    before = np.abs(RtR - np.eye(3)).max(axis=(-2, -1))
    R = 1.5 * R - 0.5 * (R @ RtR)
    if np.any(before > 1e-6):
        dev = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
        if np.any(dev > 1e-10):
            R = so3.project(R)
    out[..., :3, :3] = R
    return out


def local(T_a: FloatArray, T_b: FloatArray) -> FloatArray:
    """``log(T_a^-1 T_b)``: the right-tangent vector taking ``T_a`` to ``T_b``."""
    return log(relative(T_a, T_b))


def integrate(T_first: FloatArray, motions: FloatArray) -> FloatArray:
    """Chain relative motions: ``T[0] = T_first``, ``T[k+1] = T[k] @ motions[k]``.

    Parameters
    ----------
    T_first : (4, 4) pose of the first node in the world frame.
    motions : (n, 4, 4) consecutive motions ``T_k_k+1``.

    Returns
    -------
    (n + 1, 4, 4) poses ``T_world_k`` (the frame-to-frame, F2F, integration).
    """
    motions = np.asarray(motions, dtype=float)
    out = np.empty((motions.shape[0] + 1, 4, 4))
    out[0] = T_first
    for k in range(motions.shape[0]):  # a sequential scan: each pose depends on the last
        out[k + 1] = out[k] @ motions[k]
    return out


def misclosure(T_meas: FloatArray, T_world_i: FloatArray, T_world_j: FloatArray) -> FloatArray:
    """Misclosure ``e = log(T_meas^-1 T_i^-1 T_j)`` of measured motions at given poses.

    The between-factor error of g2o / GTSAM and the ``se3`` model's ``f`` (docs/method.md Sec. 1):
    zero when the poses agree with the measurement, in the right-perturbation tangent of the
    measurement, ROS order ``[x y z rx ry rz]`` (m, rad).

    Parameters
    ----------
    T_meas : (..., 4, 4) measured motions ``T_i_j``.
    T_world_i, T_world_j : (..., 4, 4) poses of the source and destination nodes.

    Returns
    -------
    (..., 6) misclosures.
    """
    return log(inverse(T_meas) @ relative(T_world_i, T_world_j))
