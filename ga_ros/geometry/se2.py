"""SE(2) on planar poses stored as 4x4 ``T_world_node``: log, adjoint and Jacobians.

A planar pose is a 4x4 pose whose rotation is about ``z`` and whose ``z`` translation is zero
(a 2-D g2o vertex embedded in SE(3)). Its parameters are ``[x, y, theta]`` and a tangent vector
is ``[rho_x, rho_y, theta]`` (m, m, rad) -- the components ``[x y rz]`` of the SE(3) tangent
``[x y z rx ry rz]``: se(2) is the subalgebra of se(3) spanned by them, so the SE(3) ``exp``,
``log``, adjoint and Jacobians of a planar argument restricted to those rows and columns are
the SE(2) ones (tested). Perturbations are on the right, ``T exp(xi)``, as in :mod:`se3`.
Formulas: J. Sola, D. Atchuthan, J. Deray, *A micro Lie theory for state estimation in
robotics*, arXiv:1812.01537, eqs. 155-164.

Everything is vectorised over a leading axis and works on ``(m,)`` component arrays (no
``3x3`` matrix products): these run per connection in every iteration of a 2-D solve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray

#: Components of the SE(3) tangent ``[x y z rx ry rz]`` that form the SE(2) tangent.
AXES = np.array([0, 1, 5])
#: Below this angle (rad) the Taylor branches are used (the closed forms divide by theta).
_SMALL = 1e-4


@dataclass(frozen=True)
class Planar:
    """Planar poses as components: position ``x, y`` (m), ``cos``/``sin`` of the heading."""

    x: FloatArray
    y: FloatArray
    c: FloatArray
    s: FloatArray

    @staticmethod
    def from_matrix(T: FloatArray) -> Planar:
        """From ``(..., 4, 4)`` poses (only ``R[:2, :2]`` and ``t[:2]`` are read), as contiguous
        copies: arithmetic on strided views of the 4x4 stack is several times slower."""
        T = np.asarray(T, dtype=float)
        return Planar(*(np.array(T[..., r, c])  # a copy, C-contiguous (and 0-d for one pose)
                        for r, c in ((0, 3), (1, 3), (0, 0), (1, 0))))

    def take(self, index: IntArray) -> Planar:
        """The poses ``index`` (e.g. each connection's end) of a stack of poses."""
        return Planar(self.x[index], self.y[index], self.c[index], self.s[index])

    @staticmethod
    def from_xytheta(x: FloatArray, y: FloatArray, theta: FloatArray) -> Planar:
        return Planar(np.asarray(x, dtype=float), np.asarray(y, dtype=float), np.cos(theta),
                      np.sin(theta))

    def inverse(self) -> Planar:
        """``T^-1``: ``(R', -R' t)``."""
        return Planar(-(self.c * self.x + self.s * self.y), self.s * self.x - self.c * self.y,
                      self.c, -self.s)

    def compose(self, other: Planar) -> Planar:
        """``self @ other``."""
        return Planar(self.x + self.c * other.x - self.s * other.y,
                      self.y + self.s * other.x + self.c * other.y,
                      self.c * other.c - self.s * other.s, self.s * other.c + self.c * other.s)

    def log(self) -> FloatArray:
        """``(..., 3)`` tangent ``[rho_x, rho_y, theta]`` with ``theta`` in ``(-pi, pi]``."""
        theta = np.arctan2(self.s, self.c)
        a, b = _v_inverse_coefficients(theta)
        # V(theta)^-1 = [[a, b], [-b, a]] (Sola eq. 156 inverted)
        return np.stack([a * self.x + b * self.y, -b * self.x + a * self.y, theta], axis=-1)


def _v_inverse_coefficients(theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``V(theta)^-1 = [[a, b], [-b, a]]`` with ``a = (theta/2) cot(theta/2)``, ``b = theta/2``.

    ``V = [[sin t / t, -(1 - cos t) / t], [(1 - cos t) / t, sin t / t]]`` (Sola eq. 156);
    ``a -> 1 - theta^2 / 12`` for small angles (Taylor, to avoid 0/0).
    """
    theta = np.asarray(theta, dtype=float)
    small = np.abs(theta) < _SMALL
    h = np.where(small, 1.0, 0.5 * theta)
    a = np.where(small, 1.0 - theta * theta / 12.0, h / np.tan(h))
    return a, 0.5 * theta


def exp(xi: FloatArray) -> FloatArray:
    """``[rho_x, rho_y, theta] -> (..., 4, 4)`` planar pose (Sola eq. 156)."""
    P = _exp_planar(xi)
    out = np.zeros(np.shape(P.x) + (4, 4))
    out[..., 0, 0] = P.c
    out[..., 0, 1] = -P.s
    out[..., 1, 0] = P.s
    out[..., 1, 1] = P.c
    out[..., 2, 2] = 1.0
    out[..., 3, 3] = 1.0
    out[..., 0, 3] = P.x
    out[..., 1, 3] = P.y
    return out


def _exp_planar(xi: FloatArray) -> Planar:
    """:func:`exp` as components."""
    xi = np.asarray(xi, dtype=float)
    rx, ry, t = xi[..., 0], xi[..., 1], xi[..., 2]
    small = np.abs(t) < _SMALL
    ts = np.where(small, 1.0, t)
    sa = np.where(small, 1.0 - t * t / 6.0, np.sin(ts) / ts)      # sin t / t
    cb = np.where(small, 0.5 * t - t ** 3 / 24.0, (1.0 - np.cos(ts)) / ts)  # (1 - cos t) / t
    return Planar(sa * rx - cb * ry, cb * rx + sa * ry, np.cos(t), np.sin(t))


def adjoint(P: Planar) -> FloatArray:
    """``Ad(T)`` ``(..., 3, 3)`` with ``T exp(xi) T^-1 = exp(Ad(T) xi)``:
    ``[[R, [y, -x]'], [0, 1]]`` (Sola eq. 159)."""
    out = np.zeros(np.shape(P.x) + (3, 3))
    _fill_adjoint(out, P, -2, -1)
    return out


def adjoint_columns(P: Planar) -> FloatArray:
    """:func:`adjoint` of ``m`` poses as columns ``(3, 3, m)`` (entry ``[r, c]`` a contiguous
    ``m``-long row, for column-wise products)."""
    out = np.zeros((3, 3) + np.shape(P.x))
    _fill_adjoint(out, P, 0, 1)
    return out


def _fill_adjoint(out: FloatArray, P: Planar, row_axis: int, col_axis: int) -> None:
    """Write the non-zero entries of ``Ad(T)`` (:func:`adjoint`) into ``out``, whose axes
    ``row_axis``, ``col_axis`` index the matrix (its zeros stay as they are)."""
    view = np.moveaxis(out, (row_axis, col_axis), (0, 1))
    view[0, 0] = P.c
    view[0, 1] = -P.s
    view[1, 0] = P.s
    view[1, 1] = P.c
    view[0, 2] = P.y
    view[1, 2] = -P.x
    view[2, 2] = 1.0


def right_jacobian_inv(xi: FloatArray) -> FloatArray:
    """``J_r(xi)^-1`` ``(..., 3, 3)`` of SE(2).

    ``J_r = [[A, b], [0, 1]]`` with ``A = [[s/t, (1-c)/t], [-(1-c)/t, s/t]]`` and
    ``b = [(t rx - ry + ry c - rx s) / t^2, (rx + t ry - rx c - ry s) / t^2]`` (Sola eq. 163),
    so ``J_r^-1 = [[A^-1, -A^-1 b], [0, 1]]`` with ``A^-1 = [[a, -t/2], [t/2, a]]``,
    ``a = (t/2) cot(t/2)``. Small angles use the Taylor series of ``(t - sin t)/t^2`` and
    ``(1 - cos t)/t^2``.
    """
    xi = np.asarray(xi, dtype=float)
    out = np.zeros(xi.shape[:-1] + (3, 3))
    _fill_right_jacobian_inv(out, xi[..., 0], xi[..., 1], xi[..., 2], -2, -1)
    return out


def right_jacobian_inv_columns(xi: FloatArray) -> FloatArray:
    """:func:`right_jacobian_inv` of ``(m, 3)`` tangents as columns ``(3, 3, m)`` (entry
    ``[r, c]`` a contiguous ``m``-long row, for column-wise products)."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros((3, 3) + xi.shape[:-1])
    _fill_right_jacobian_inv(out, xi[..., 0], xi[..., 1], xi[..., 2], 0, 1)
    return out


def _fill_right_jacobian_inv(out: FloatArray, rx: FloatArray, ry: FloatArray, t: FloatArray,
                             row_axis: int, col_axis: int) -> None:
    """Write the non-zero entries of ``J_r^-1`` (:func:`right_jacobian_inv`) into ``out``,
    whose axes ``row_axis``, ``col_axis`` index the matrix (its zeros stay as they are)."""
    small = np.abs(t) < _SMALL
    ts = np.where(small, 1.0, t)
    t2 = t * t
    p = np.where(small, t / 6.0 - t * t2 / 120.0, (ts - np.sin(ts)) / (ts * ts))
    q = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / (ts * ts))
    b0 = p * rx - q * ry
    b1 = q * rx + p * ry
    a, h = _v_inverse_coefficients(t)
    view = np.moveaxis(out, (row_axis, col_axis), (0, 1))
    view[0, 0] = a
    view[0, 1] = -h
    view[1, 0] = h
    view[1, 1] = a
    view[0, 2] = -(a * b0 - h * b1)
    view[1, 2] = -(h * b0 + a * b1)
    view[2, 2] = 1.0


def local(T_a: FloatArray, T_b: FloatArray) -> FloatArray:
    """``log(T_a^-1 T_b)`` ``(..., 3)`` of planar 4x4 poses."""
    return Planar.from_matrix(T_a).inverse().compose(Planar.from_matrix(T_b)).log()


def retract(T: FloatArray, xi: FloatArray) -> FloatArray:
    """``T @ exp(xi)`` of planar 4x4 poses, the rotation rebuilt from its angle (no drift)."""
    P = Planar.from_matrix(T).compose(_exp_planar(xi))
    theta = np.arctan2(P.s, P.c)
    out = np.array(T, dtype=float, copy=True)
    c, s = np.cos(theta), np.sin(theta)
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 0, 3] = P.x
    out[..., 1, 3] = P.y
    return out
