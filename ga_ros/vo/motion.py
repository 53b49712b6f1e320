"""Stereo triangulation and 3-D-to-2-D motion refinement with an honest 6x6 covariance.

The motion ``T_src_dst`` (pose of the ``dst`` camera in the ``src`` camera frame) is estimated
from points ``X_src`` triangulated by the rectified stereo pair at ``src`` and their image
positions ``uv_dst`` in the left image at ``dst``. The residual of point ``i`` is
``r_i = pi(T_src_dst^-1 X_i) - uv_i`` (px). Its covariance combines the image noise at ``dst``
and the stereo error of ``X_i`` pushed through the projection:

``C_i = sigma_i^2 I_2 + A_i Sigma_X_i A_i^T``, with ``A_i = d pi / d X_dst * R_dst_src``.

The refinement is weighted Gauss-Newton on the right perturbation ``T_src_dst @ exp(xi)``,
``xi = [rho, phi]`` (m, rad; ROS order). With ``X_dst = T^-1 X_src``, the perturbed point is
``exp(-xi) X_dst ~= X_dst - rho + [X_dst]_x phi``, so ``d X_dst / d xi = [-I, [X_dst]_x]``.
The covariance is ``max(s^2, 1) (J^T C^-1 J)^-1`` with the variance factor
``s^2 = sum_i r_i^T C_i^-1 r_i / (2 n - 6)`` estimated from the residuals. ``s^2`` is floored at
1: residuals smaller than the prior image noise (a still camera tracks its own image to 0.01 px)
say nothing about the errors the prior model stands for (calibration, correlated KLT errors), so
they never shrink the covariance below the prior's ``(J^T C^-1 J)^-1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray
from ga_ros.errors import DegenerateGeometryError
from ga_ros.geometry import se3, so3


def triangulate(uv: FloatArray, disparity: FloatArray, K: FloatArray,
                baseline_m: float) -> FloatArray:
    """3-D points (m) in the left camera frame from left pixels and disparities.

    Parameters
    ----------
    uv : (n, 2) left-image pixel coordinates (px), rectified.
    disparity : (n,) ``u_left - u_right`` (px), positive.
    K : (3, 3) rectified intrinsics.
    baseline_m : stereo baseline (m).
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = fx * baseline_m / disparity
    return np.stack([(uv[:, 0] - cx) * z / fx, (uv[:, 1] - cy) * z / fy, z], axis=1)


def point_covariance(uv: FloatArray, disparity: FloatArray, K: FloatArray, baseline_m: float,
                     sigma_uv_px: float, sigma_disparity_px: float) -> FloatArray:
    """(n, 3, 3) covariance (m^2) of :func:`triangulate` for independent pixel errors.

    ``sigma_uv_px`` is the error of the left position, ``sigma_disparity_px`` of the disparity.
    """
    fx, fy = K[0, 0], K[1, 1]
    d = disparity
    b = baseline_m
    n = len(d)
    J = np.zeros((n, 3, 3))
    J[:, 0, 0] = b / d
    J[:, 1, 1] = fx * b / (fy * d)
    X = triangulate(uv, d, K, b)
    J[:, :, 2] = -X / d[:, None]
    S = np.diag([sigma_uv_px ** 2, sigma_uv_px ** 2, sigma_disparity_px ** 2])
    return J @ S @ J.transpose(0, 2, 1)


def project(X: FloatArray, K: FloatArray) -> FloatArray:
    """(n, 2) pixel coordinates of camera-frame points ``X`` (n, 3)."""
    z = X[:, 2]
    return np.stack([K[0, 0] * X[:, 0] / z + K[0, 2], K[1, 1] * X[:, 1] / z + K[1, 2]], axis=1)


@dataclass
class MotionEstimate:
    """Result of :func:`refine_motion`.

    Attributes
    ----------
    T_src_dst : (4, 4) motion.
    cov : (6, 6) covariance of the right perturbation of ``T_src_dst``, ``[x y z rx ry rz]``:
        ``max(s^2, 1) (J^T C^-1 J)^-1``.
    inliers : (n,) mask of the points kept by the chi-square gate.
    n_inliers : number of kept points.
    sigma0_sq : a-posteriori variance factor ``s^2`` (1 when the noise model is right).
    chi2 : (n,) whitened squared residual of every point (2 degrees of freedom).
    iterations : Gauss-Newton iterations run.
    """

    T_src_dst: FloatArray
    cov: FloatArray
    inliers: BoolArray
    n_inliers: int
    sigma0_sq: float
    chi2: FloatArray
    iterations: int


def _residuals(T_src_dst: FloatArray, X_src: FloatArray, uv: FloatArray, K: FloatArray,
               cov_X: FloatArray, sigma_px: FloatArray
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Residuals (n, 2), Jacobians (n, 2, 6), inverse residual covariances (n, 2, 2), depths."""
    T_dst_src = se3.inverse(T_src_dst)
    R = T_dst_src[:3, :3]
    Xd = X_src @ R.T + T_dst_src[:3, 3]
    z = Xd[:, 2]
    zs = np.where(z > 1e-9, z, 1e-9)
    fx, fy = K[0, 0], K[1, 1]
    r = project(np.column_stack([Xd[:, :2], zs]), K) - uv
    n = len(Xd)
    P = np.zeros((n, 2, 3))
    P[:, 0, 0] = fx / zs
    P[:, 0, 2] = -fx * Xd[:, 0] / zs ** 2
    P[:, 1, 1] = fy / zs
    P[:, 1, 2] = -fy * Xd[:, 1] / zs ** 2
    D = np.zeros((n, 3, 6))
    D[:, :, :3] = -np.eye(3)
    D[:, :, 3:] = so3.hat(Xd)
    J = P @ D
    A = P @ R
    C = A @ cov_X @ A.transpose(0, 2, 1)
    C[:, 0, 0] += sigma_px ** 2
    C[:, 1, 1] += sigma_px ** 2
    det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    W = np.empty_like(C)
    W[:, 0, 0] = C[:, 1, 1] / det
    W[:, 1, 1] = C[:, 0, 0] / det
    W[:, 0, 1] = -C[:, 0, 1] / det
    W[:, 1, 0] = -C[:, 1, 0] / det
    return r, J, W, z


def _chi2(r: FloatArray, W: FloatArray) -> FloatArray:
    """(n,) ``r_i^T W_i r_i`` for 2x2 ``W_i``."""
    return (r[:, 0] * (W[:, 0, 0] * r[:, 0] + W[:, 0, 1] * r[:, 1])
            + r[:, 1] * (W[:, 1, 0] * r[:, 0] + W[:, 1, 1] * r[:, 1]))


def _normal(J: FloatArray, W: FloatArray, r: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Normal matrix ``sum J_i^T W_i J_i`` (6, 6) and gradient ``sum J_i^T W_i r_i`` (6,)."""
    WJ = W @ J  # (n, 2, 6)
    Jf = J.reshape(-1, 6)
    WJf = WJ.reshape(-1, 6)
    return Jf.T @ WJf, WJf.T @ r.reshape(-1)


def refine_motion(X_src: FloatArray, uv_dst: FloatArray, K: FloatArray, T_src_dst: FloatArray,
                  cov_X: FloatArray, sigma_px: float | FloatArray, iterations: int = 6,
                  chi2_gate: float = 13.8, min_points: int = 6) -> MotionEstimate:
    """Weighted Gauss-Newton refinement of ``T_src_dst`` and its covariance (see module doc).

    Parameters
    ----------
    X_src : (n, 3) points in the ``src`` camera frame (m).
    uv_dst : (n, 2) their pixel positions in the ``dst`` left image (px).
    K : (3, 3) rectified intrinsics.
    T_src_dst : (4, 4) initial motion (e.g. from PnP RANSAC).
    cov_X : (n, 3, 3) covariances of ``X_src`` (m^2).
    sigma_px : scalar or (n,) image noise at ``dst`` (px).
    iterations : maximum Gauss-Newton iterations.
    chi2_gate : points whose whitened squared residual exceeds ``chi2_gate * max(s^2, 1)`` are
        dropped (13.8 = 99.9 % of chi-square with 2 dof).
    min_points : fewer inliers than this raises.

    Raises
    ------
    DegenerateGeometryError
        Too few points, points behind the camera, or a singular normal matrix.
    """
    X_src = np.asarray(X_src, float)
    uv_dst = np.asarray(uv_dst, float)
    n = len(X_src)
    sig = np.broadcast_to(np.asarray(sigma_px, float), (n,))
    T = np.asarray(T_src_dst, float).copy()
    keep = np.ones(n, bool)
    it = 0
    N = np.eye(6)
    chi2 = np.zeros(n)
    s2 = 1.0
    for it in range(1, iterations + 1):
        if keep.sum() < min_points:
            raise DegenerateGeometryError(f'only {int(keep.sum())} points for the motion')
        r, J, W, z = _residuals(T, X_src, uv_dst, K, cov_X, sig)
        chi2 = _chi2(r, W)
        k = keep & (z > 1e-6)
        N, g = _normal(J[k], W[k], r[k])
        try:
            dx = -np.linalg.solve(N, g)
        except np.linalg.LinAlgError as exc:
            raise DegenerateGeometryError('singular normal matrix in the motion') from exc
        T = T @ se3.exp(dx)
        if it >= 2:
            dof = max(2 * int(k.sum()) - 6, 1)
            s2 = float(chi2[k].sum() / dof)
            keep = (chi2 <= chi2_gate * max(s2, 1.0)) & (z > 1e-6)
        if np.max(np.abs(dx)) < 1e-7 and it >= 3:
            break
    r, J, W, z = _residuals(T, X_src, uv_dst, K, cov_X, sig)
    chi2 = _chi2(r, W)
    keep &= z > 1e-6
    m = int(keep.sum())
    if m < min_points:
        raise DegenerateGeometryError(f'only {m} points for the motion')
    N, _ = _normal(J[keep], W[keep], r[keep])
    s2 = float(chi2[keep].sum() / max(2 * m - 6, 1))
    try:
        cov = max(s2, 1.0) * np.linalg.inv(N)
    except np.linalg.LinAlgError as exc:
        raise DegenerateGeometryError('singular normal matrix in the motion') from exc
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)) or np.min(np.linalg.eigvalsh(cov)) <= 0:
        raise DegenerateGeometryError('motion covariance is not positive definite')
    return MotionEstimate(T, cov, keep, m, s2, chi2, it)
