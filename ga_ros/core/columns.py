"""The ``se3`` between factor in structure-of-arrays form: misclosure and Gauss-Newton blocks.

The same algebra as :func:`ga_ros.core.models.between` (the reference, which a test compares
with this module and with finite differences), written for speed in plain NumPy: every
per-connection quantity is a *column* over the ``m`` connections (a rotation is ``(3, 3, m)``,
a vector ``(3, m)``), so each formula is a handful of elementwise operations on contiguous
``m``-long rows instead of passes over stacked ``(m, 3, 3)`` / ``(m, 6, 6)`` temporaries, and
the SO(3) logarithm and the Jacobian inverses are closed forms in the components
(``[w]x^2 x = w (w.x) - |w|^2 x``). The normal blocks are 3x3 column products, written once
into the solver's stacked ``(m, 6, 6)`` layout: ``H_jj = V' V`` of the whitened Jacobian
``V = U J`` (``P = U' U``, :class:`SqrtWeights`, once per problem; block upper triangular like
``J``), and, since ``J_i = -J Ad(T_ij^-1)``, ``H_ji = -H_jj Ad(T_ij^-1)`` and
``H_ii = -Ad(T_ij^-1)' H_ji`` (``Ad`` block upper triangular too: fewer products than
whitening ``J_i`` as well).

For ``e = log(T_meas^-1 T_i^-1 T_j)`` with right perturbations ``T_i exp(d_i)``,
``T_j exp(d_j)`` (Barfoot, *State Estimation for Robotics*, 2017, eqs. 7.78, 7.86, 7.95)::

    de/dd_j = J = J_r(e)^-1 = [[A, B], [0, A]],  A = J_r(phi)^-1,  B = -A Q(-rho, -phi) A
    de/dd_i = -J Ad(T_ij^-1) = -[[X, Y], [0, X]],  X = A R_ij',  Y = B R_ij' - X [t_ij]x

using ``Ad(T_ij^-1) = [[R_ij', -R_ij' [t_ij]x], [0, R_ij']]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg.runs import by_runs
from ga_ros.geometry import so3

_SMALL = so3.SMALL_ANGLE  # Taylor branch of the SO(3) coefficients below this angle (rad)
_SMALL_Q = 1e-3  # Taylor branch of Q's coefficients (as ga_ros.geometry.se3.Q_matrix)
_NEAR_PI = np.pi - 1e-2  # the log takes the axis from the symmetric part above this angle


@dataclass(frozen=True)
class MeasuredInverse:
    """The inverses ``T_meas^-1`` of the measured motions, as columns.

    Attributes
    ----------
    R : (3, 3, m) their rotations.
    t : (3, m) their translations (m).
    """

    R: FloatArray
    t: FloatArray

    @staticmethod
    def of(Tm_inv: FloatArray) -> MeasuredInverse:
        """From ``(m, 4, 4)`` inverses of the measured motions."""
        return MeasuredInverse(np.ascontiguousarray(Tm_inv[:, :3, :3].transpose(1, 2, 0)),
                               np.ascontiguousarray(Tm_inv[:, :3, 3].T))


@dataclass(frozen=True)
class Misclosure:
    """``e = log(T_meas^-1 T_i^-1 T_j)`` of every connection, with what its Jacobians reuse.

    Attributes
    ----------
    e : (m, 6) the misclosures ``[rho, phi]`` (m, rad).
    rho, phi : (3, m) the same as columns.
    R_ij : (3, 3, m) rotations of ``T_ij = T_i^-1 T_j``.
    t_ij : (3, m) translations of ``T_ij`` (m).
    """

    e: FloatArray
    rho: FloatArray
    phi: FloatArray
    R_ij: FloatArray
    t_ij: FloatArray


@dataclass(frozen=True)
class NormalBlocks:
    """Gauss-Newton blocks of ``sum_k w_k e_k' P_k e_k`` (robust weights ``w_k`` applied).

    Attributes
    ----------
    e : (m, 6) misclosures.
    blocks : (4 m + extra, 6, 6) ``J_a' W J_b`` for ``(a, b)`` = ``(i, i)``, ``(i, j)``,
        ``(j, i)``, ``(j, j)``, stacked block-type major; ``extra`` rows left for the caller.
    g_src, g_dst : (m, 6) gradient halves ``J_i' W e``, ``J_j' W e``.
    maha2 : (m,) ``e' P e`` (unweighted).
    """

    e: FloatArray
    blocks: FloatArray
    g_src: FloatArray
    g_dst: FloatArray
    maha2: FloatArray


def _mm3(A: FloatArray, B: FloatArray) -> FloatArray:
    """Column-wise ``A @ B`` of ``(3, 3, m)`` stacks. The operands are made C-contiguous first:
    NumPy lays a broadcast result out like its operands, and a transposed view would put the
    ``m`` axis outermost (every later operation then ~10x slower)."""
    A, B = np.ascontiguousarray(A), np.ascontiguousarray(B)
    return A[:, 0, None] * B[None, 0] + A[:, 1, None] * B[None, 1] + A[:, 2, None] * B[None, 2]


def _mv3(A: FloatArray, x: FloatArray) -> FloatArray:
    """Column-wise ``A @ x``: ``(3, 3, m) x (3, m) -> (3, m)``."""
    A, x = np.ascontiguousarray(A), np.ascontiguousarray(x)
    return A[:, 0] * x[0] + A[:, 1] * x[1] + A[:, 2] * x[2]


def _hat(w: FloatArray) -> FloatArray:
    """``[w]x`` of columns ``(3, m) -> (3, 3, m)``."""
    z = np.zeros_like(w[0])
    return np.stack([np.stack([z, -w[2], w[1]]), np.stack([w[2], z, -w[0]]),
                     np.stack([-w[1], w[0], z])])


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a x b`` of columns ``(3, m)``."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def _outer(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a b'`` of columns ``(3, m)``: ``(3, 3, m)``."""
    return a[:, None, :] * b[None, :, :]


def _so3_log(R: FloatArray) -> FloatArray:
    """Rotation vectors ``(3, m)`` of rotations ``(3, 3, m)`` (:func:`ga_ros.geometry.so3.log`'s
    formulas; the few angles near pi are handed to it)."""
    cos_t = (R[0, 0] + R[1, 1] + R[2, 2] - 1.0) * 0.5
    v = 0.5 * np.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin_t = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    theta = np.arctan2(sin_t, cos_t)
    small = theta < _SMALL
    scale = np.where(small, 1.0 + theta * theta / 6.0, theta / np.where(small, 1.0, sin_t))
    w = v * scale
    near_pi = theta > _NEAR_PI
    if near_pi.any():  # the skew part vanishes there: so3.log takes the symmetric part
        w[:, near_pi] = so3.log(R[:, :, near_pi].transpose(2, 0, 1)).T
    return w


def _jl_inv_coeff(t2: FloatArray) -> FloatArray:
    """``c`` of ``J_l(w)^-1 = I - [w]x / 2 + c [w]x^2`` (Barfoot eq. 7.78): ``(1 - a / 2b) / t^2``
    with ``a = sin t / t``, ``b = (1 - cos t) / t^2``, i.e. ``1/t^2 - sin t / (2 t (1 - cos t))``;
    Taylor below :data:`_SMALL` (``t^2 = |w|^2``)."""
    small = t2 < _SMALL * _SMALL
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    half = np.sin(0.5 * t)
    # 1 - cos t = 2 sin^2(t/2): no cancellation for small angles
    big = 1.0 / t2s - np.sin(t) / (4.0 * t * half * half)
    return np.where(small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0, big)


def misclosure(T: FloatArray, src: IntArray, dst: IntArray,
               meas: MeasuredInverse) -> Misclosure:
    """``e = log(T_meas^-1 T_i^-1 T_j)`` of every connection (the g2o/GTSAM between error).

    Parameters
    ----------
    T : (n, 4, 4) node poses ``T_world_node``.
    src, dst : (m,) node indices.
    meas : the inverses of the measured motions ``T_i_j``.
    """
    Tc = np.ascontiguousarray(T[:, :3, :].transpose(1, 2, 0))  # (3, 4, n)
    Ti, Tj = Tc[:, :, src], Tc[:, :, dst]
    Ri_t = Ti[:, :3].transpose(1, 0, 2)
    R_ij = _mm3(Ri_t, Tj[:, :3])
    t_ij = _mv3(Ri_t, Tj[:, 3] - Ti[:, 3])
    R_E = _mm3(meas.R, R_ij)
    t_E = _mv3(meas.R, t_ij) + meas.t
    phi = _so3_log(R_E)
    # rho = J_l(phi)^-1 t_E = t_E - phi x t_E / 2 + c (phi (phi.t_E) - |phi|^2 t_E)
    t2 = (phi * phi).sum(axis=0)
    c = _jl_inv_coeff(t2)
    rho = t_E - 0.5 * _cross(phi, t_E) + c * (phi * (phi * t_E).sum(axis=0) - t2 * t_E)
    e = np.empty((src.shape[0], 6))
    e[:, :3] = rho.T
    e[:, 3:] = phi.T
    return Misclosure(e, rho, phi, R_ij, t_ij)


def _q_matrix(r: FloatArray, p: FloatArray) -> FloatArray:
    """Barfoot's ``Q(rho, phi)`` (eq. 7.86) of columns ``r = rho``, ``p = phi`` ``(3, m)``:
    the closed form of :func:`ga_ros.geometry.se3.Q_matrix` (products of skew matrices as
    outer products), ``(3, 3, m)``."""
    t2 = (p * p).sum(axis=0)
    small = t2 < _SMALL_Q * _SMALL_Q
    t = np.sqrt(np.where(small, 1.0, t2))
    s, co = np.sin(t), np.cos(t)
    c1 = np.where(small, 1 / 6 - t2 / 120 + t2 * t2 / 5040, (t - s) / t**3)
    c2 = np.where(small, 1 / 24 - t2 / 720 + t2 * t2 / 40320, (t * t + 2 * co - 2) / (2 * t**4))
    c3 = np.where(small, 1 / 120 - t2 / 2520 + t2 * t2 / 120960,
                  (2 * t - 3 * s + t * co) / (2 * t**5))
    pr = (p * r).sum(axis=0)
    pxr = _cross(p, r)
    P = _hat(p)
    rp = _outer(r, p)
    out = (0.5 - 2.0 * c2 * t2) * _hat(r)
    out += c1 * (rp + rp.transpose(1, 0, 2) - pr * P)
    out += c2 * (_outer(p, pxr) - _outer(pxr, p) + 3.0 * pr * P)
    out -= (2.0 * c3 * pr) * _outer(p, p)
    diag = -2.0 * c1 * pr + 2.0 * c3 * pr * t2  # the multiples of I
    for k in range(3):
        out[k, k] += diag
    return out


def _mtm3(A: FloatArray, B: FloatArray) -> FloatArray:
    """Column-wise ``A' @ B`` of C-contiguous ``(3, 3, m)`` stacks (rows of ``A`` and ``B`` are
    contiguous ``(3, m)`` slices: no transposed copy)."""
    return (A[0][:, None] * B[0][None] + A[1][:, None] * B[1][None]
            + A[2][:, None] * B[2][None])


def _mtv3(A: FloatArray, x: FloatArray) -> FloatArray:
    """Column-wise ``A' @ x``: ``(3, 3, m) x (3, m) -> (3, m)``."""
    return A[0] * x[0] + A[1] * x[1] + A[2] * x[2]


@dataclass(frozen=True)
class SqrtWeights:
    """Upper-triangular square roots ``U`` of the weights, ``P = U' U``, as ``3 x 3`` blocks
    ``U = [[U11, U12], [0, U22]]`` of columns ``(3, 3, m)`` (computed once per problem)."""

    U11: FloatArray
    U12: FloatArray
    U22: FloatArray

    @staticmethod
    def of(P: FloatArray) -> SqrtWeights:
        """From ``(m, 6, 6)`` symmetric positive-definite weights (Cholesky ``P = L L'``,
        ``U = L'``)."""
        U = by_runs(np.linalg.cholesky, P).transpose(2, 1, 0)  # (6, 6, m): U[r, c] = L[c, r]
        return SqrtWeights(*(np.ascontiguousarray(U[r:r + 3, c:c + 3])
                             for r, c in ((0, 0), (0, 3), (3, 3))))


class _Whitened:
    """``V = U J`` of a Jacobian ``J = s [[X, Y], [0, X]]`` (``s = +-1``), whose lower-left
    block stays zero: ``V = s [[U11 X, U11 Y + U12 X], [0, U22 X]]``."""

    def __init__(self, W: SqrtWeights, X: FloatArray, Y: FloatArray, sign: float) -> None:
        self.V11 = _mm3(W.U11, X)
        self.V12 = _mm3(W.U11, Y) + _mm3(W.U12, X)
        self.V22 = _mm3(W.U22, X)
        if sign < 0:
            for V in (self.V11, self.V12, self.V22):
                np.negative(V, out=V)

    def scale(self, s: FloatArray) -> None:
        for V in (self.V11, self.V12, self.V22):
            V *= s

    def gradient(self, r1: FloatArray, r2: FloatArray) -> FloatArray:
        """``V' r`` ``(m, 6)`` for the whitened residual ``r = [r1; r2]`` (columns)."""
        g = np.empty((r1.shape[1], 6))
        g[:, :3] = _mtv3(self.V11, r1).T
        g[:, 3:] = (_mtv3(self.V12, r1) + _mtv3(self.V22, r2)).T
        return g

    def normal(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``V' V = [[h11, h12], [h12', h22]]``: ``(h11, h12, h22)`` as columns."""
        return (_mtm3(self.V11, self.V11), _mtm3(self.V11, self.V12),
                _mtm3(self.V12, self.V12) + _mtm3(self.V22, self.V22))


def _put(out: FloatArray, b11: FloatArray, b12: FloatArray, b21: FloatArray,
         b22: FloatArray) -> None:
    """The ``3 x 3`` column blocks of ``[[b11, b12], [b21, b22]]`` into ``out`` ``(m, 6, 6)``."""
    out[:, :3, :3] = b11.transpose(2, 0, 1)
    out[:, :3, 3:] = b12.transpose(2, 0, 1)
    out[:, 3:, :3] = b21.transpose(2, 0, 1)
    out[:, 3:, 3:] = b22.transpose(2, 0, 1)


def maha2(mis: Misclosure, W: SqrtWeights) -> FloatArray:
    """``e' P e`` ``(m,)`` of misclosures, as ``|U e|^2``."""
    r1 = _mv3(W.U11, mis.rho) + _mv3(W.U12, mis.phi)
    r2 = _mv3(W.U22, mis.phi)
    return (r1 * r1).sum(axis=0) + (r2 * r2).sum(axis=0)


class Linearised:
    """One linearisation of ``sum_k rho(e_k' P_k e_k)`` in two stages: the misclosures, robust
    weights and gradient at once, the normal blocks on demand (:meth:`normal_blocks`).

    A caller that needs the gradient only (a chord step, which reuses the last factorisation
    of ``N``, or a stop on the decrease it predicts) never pays for the blocks' products.

    Attributes
    ----------
    e : (m, r) misclosures (``r`` = 6 se3, 3 se2).
    g_src, g_dst : (m, r) gradient halves ``J_i' W e``, ``J_j' W e``.
    maha2 : (m,) ``e' P e`` (unweighted by the robust loss).
    """

    def __init__(self, e: FloatArray, g_src: FloatArray, g_dst: FloatArray, maha2: FloatArray,
                 products) -> None:
        self.e, self.g_src, self.g_dst, self.maha2 = e, g_src, g_dst, maha2
        self._products = products  # (extra) -> (4 m + extra, r, r) blocks

    def normal_blocks(self, extra_blocks: int = 0) -> NormalBlocks:
        """The blocks ``J_a' W J_b`` (``(4 m + extra_blocks, r, r)``, see :class:`NormalBlocks`),
        with ``extra_blocks`` rows left uninitialised for the caller."""
        return NormalBlocks(self.e, self._products(extra_blocks), self.g_src, self.g_dst,
                            self.maha2)


def linearise(T: FloatArray, src: IntArray, dst: IntArray, meas: MeasuredInverse,
              W: SqrtWeights, robust=None, mis: Misclosure | None = None) -> Linearised:
    """Gauss-Newton system of ``sum_k rho(e_k' P_k e_k)`` at ``T`` (see the module docstring):
    misclosures and gradient now, blocks on demand (:meth:`Linearised.normal_blocks`).

    With ``P = U' U`` and ``V = U J`` (block upper triangular like ``J``), ``H_jj = V' V``,
    and with ``Ad(T_ij^-1) = [[S, -K], [0, S]]`` (``S = R_ij'``, ``K = S [t_ij]x``) and
    ``J_i = -J Ad(T_ij^-1)``: ``H_ji = -H_jj Ad(T_ij^-1)``, ``H_ii = -Ad(T_ij^-1)' H_ji``
    and ``g_i = -Ad(T_ij^-1)' g_j``, all in columns.

    Parameters
    ----------
    T : (n, 4, 4) node poses ``T_world_node``.
    src, dst : (m,) node indices.
    meas : inverses of the measured motions.
    W : square roots of the weights (inverse covariances, ``[x y z rx ry rz]`` order).
    robust : ``maha2 -> (m,) weights`` (IRLS weights of a robust loss), or None.
    mis : :func:`misclosure` at ``T``, if the caller has it.
    """
    if mis is None:
        mis = misclosure(T, src, dst, meas)
    e = mis.e
    rho, phi = -mis.rho, -mis.phi  # J_r(e)^-1 = J_l(-e)^-1
    t2 = (phi * phi).sum(axis=0)
    # A = J_l(phi)^-1 = (1 - c t^2) I - [phi]x / 2 + c phi phi' at phi = -phi(e)
    c = _jl_inv_coeff(t2)
    A = c * _outer(phi, phi) - 0.5 * _hat(phi)
    for k in range(3):
        A[k, k] += 1.0 - c * t2
    B = -_mm3(_mm3(A, _q_matrix(rho, phi)), A)
    S = np.ascontiguousarray(mis.R_ij.transpose(1, 0, 2))  # R_ij'
    K = _mm3(S, _hat(mis.t_ij))  # Ad(T_ij^-1) = [[S, -K], [0, S]]
    Vj = _Whitened(W, A, B, 1.0)
    r1 = _mv3(W.U11, mis.rho) + _mv3(W.U12, mis.phi)  # r = U e
    r2 = _mv3(W.U22, mis.phi)
    maha2 = (r1 * r1).sum(axis=0) + (r2 * r2).sum(axis=0)
    if robust is not None:
        sw = np.sqrt(robust(maha2))
        Vj.scale(sw)
        r1, r2 = r1 * sw, r2 * sw
    g_dst = Vj.gradient(r1, r2)
    g1, g2 = np.ascontiguousarray(g_dst[:, :3].T), np.ascontiguousarray(g_dst[:, 3:].T)
    g_src = np.empty_like(g_dst)  # -Ad(T_ij^-1)' g_j = [-S' g1; K' g1 - S' g2]
    g_src[:, :3] = -_mtv3(S, g1).T
    g_src[:, 3:] = (_mtv3(K, g1) - _mtv3(S, g2)).T

    def products(extra: int) -> FloatArray:
        m = e.shape[0]
        h11, h12, h22 = Vj.normal()
        h21 = np.ascontiguousarray(h12.transpose(1, 0, 2))
        # H_ji = -H_jj Ad(T_ij^-1)
        x11, x21 = -_mm3(h11, S), -_mm3(h21, S)
        x12 = _mm3(h11, K) - _mm3(h12, S)
        x22 = _mm3(h21, K) - _mm3(h22, S)
        # H_ii = -Ad(T_ij^-1)' H_ji (symmetric: y12 = y21')
        y11 = -_mtm3(S, x11)
        y21 = _mtm3(K, x11) - _mtm3(S, x21)
        y22 = _mtm3(K, x12) - _mtm3(S, x22)
        blocks = np.empty((4 * m + extra, 6, 6))
        _put(blocks[:m], y11, y21.transpose(1, 0, 2), y21, y22)
        _put(blocks[2 * m:3 * m], x11, x12, x21, x22)
        blocks[m:2 * m] = blocks[2 * m:3 * m].transpose(0, 2, 1)
        _put(blocks[3 * m:4 * m], h11, h12, h21, h22)
        return blocks

    return Linearised(e, g_src, g_dst, maha2, products)


# ------------------------------------------------------------------------------------- se2
def _planar_sqrt_weights(P: FloatArray) -> FloatArray:
    """Upper-triangular ``U`` with ``P = U' U`` of ``(m, 3, 3)`` symmetric positive-definite
    weights, as columns ``(3, 3, m)`` (the closed-form 3x3 Cholesky: a few ``m``-long rows)."""
    p = np.ascontiguousarray(P.reshape(-1, 9).T)  # row k: entry (k // 3, k % 3) of every P
    U = np.zeros((3, 3, P.shape[0]))
    U[0, 0] = np.sqrt(p[0])
    U[0, 1] = p[1] / U[0, 0]
    U[0, 2] = p[2] / U[0, 0]
    U[1, 1] = np.sqrt(p[4] - U[0, 1] * U[0, 1])
    U[1, 2] = (p[5] - U[0, 1] * U[0, 2]) / U[1, 1]
    U[2, 2] = np.sqrt(p[8] - U[0, 2] * U[0, 2] - U[1, 2] * U[1, 2])
    return U


def planar_linearise(T: FloatArray, src: IntArray, dst: IntArray, T_meas: FloatArray,
                     P: FloatArray, robust=None) -> Linearised:
    """The ``se2`` counterpart of :func:`linearise`: Gauss-Newton system of
    ``sum_k rho(e_k' P_k e_k)``, ``e = log(T_meas^-1 T_i^-1 T_j)`` ``[rho_x, rho_y, theta]``,
    blocks on demand.

    The same algebra as :func:`ga_ros.core.models.between` for ``se2`` (a test compares the
    two): ``de/dd_j = J = J_r(e)^-1``, ``de/dd_i = -J Ad(T_ij^-1)``, every ``3 x 3`` matrix a
    column stack ``(3, 3, m)`` and the blocks products of the whitened Jacobians ``V = U J``
    (``P = U' U``).

    Parameters
    ----------
    T : (n, 4, 4) planar node poses ``T_world_node``.
    src, dst : (m,) node indices.
    T_meas : (m, 4, 4) planar measured motions ``T_i_j``.
    P : (m, 3, 3) weights (inverse covariances, ``[x y rz]`` order).
    robust : as :func:`linearise`.

    Returns
    -------
    :class:`Linearised` with ``(m, 3)`` gradients and ``(4 m + extra, 3, 3)`` blocks.
    """
    from ga_ros.geometry import se2  # lazy: se3 problems never need it

    nodes = se2.Planar.from_matrix(T)
    T_ij = nodes.take(src).inverse().compose(nodes.take(dst))
    e = se2.Planar.from_matrix(T_meas).inverse().compose(T_ij).log()
    ec = np.ascontiguousarray(e.T)  # (3, m)
    J = se2.right_jacobian_inv_columns(e)  # (3, 3, m)
    Ad = se2.adjoint_columns(T_ij.inverse())  # Ad(T_ij^-1)
    U = _planar_sqrt_weights(P)
    Vj = _mm3(U, J)
    Vi = _mm3(Vj, Ad)
    np.negative(Vi, out=Vi)
    r = _mv3(U, ec)  # U e
    maha2 = (r * r).sum(axis=0)
    if robust is not None:
        sw = np.sqrt(robust(maha2))
        Vi *= sw
        Vj *= sw
        r = r * sw

    def products(extra: int) -> FloatArray:
        m = e.shape[0]
        blocks = np.empty((4 * m + extra, 3, 3))
        blocks[:m] = _mtm3(Vi, Vi).transpose(2, 0, 1)
        blocks[2 * m:3 * m] = _mtm3(Vj, Vi).transpose(2, 0, 1)
        blocks[m:2 * m] = blocks[2 * m:3 * m].transpose(0, 2, 1)
        blocks[3 * m:4 * m] = _mtm3(Vj, Vj).transpose(2, 0, 1)
        return blocks

    return Linearised(e, np.ascontiguousarray(_mtv3(Vi, r).T),
                      np.ascontiguousarray(_mtv3(Vj, r).T), maha2, products)


# ------------------------------------------------------------------------------ retraction
def retract(T: FloatArray, xi: FloatArray) -> FloatArray:
    """``T @ exp(xi)`` of ``(k, 4, 4)`` poses and ``(k, 6)`` increments ``[rho, phi]``: the
    same result as :func:`ga_ros.geometry.se3.retract` (a test compares them), in columns.

    ``exp(xi) = (R_d, t_d)`` with ``R_d = I + a W + b W^2``, ``t_d = (I + b W + c W^2) rho``
    (``W = [phi]x``, ``W^2 v = phi (phi.v) - |phi|^2 v``; :func:`ga_ros.geometry.so3._coeffs`),
    then ``R = R_T R_d``, ``t = R_T t_d + t_T`` and one Bjorck step ``R (3 I - R'R) / 2`` (with
    the SVD projection of :func:`~ga_ros.geometry.se3.retract` where it is needed).
    """
    T = np.asarray(T, dtype=float)
    xi = np.asarray(xi, dtype=float)
    k = T.shape[0]
    _, a, b, c = so3._coeffs(xi[:, 3:])
    w = np.ascontiguousarray(xi[:, 3:].T)
    r = np.ascontiguousarray(xi[:, :3].T)
    t2 = (w * w).sum(axis=0)
    Rd = a * _hat(w) + b * _outer(w, w)
    for i in range(3):
        Rd[i, i] += 1.0 - b * t2
    td = r + b * _cross(w, r) + c * (w * (w * r).sum(axis=0) - t2 * r)
    RT = np.ascontiguousarray(T[:, :3, :3].transpose(1, 2, 0))
    R = _mm3(RT, Rd)
    out = np.empty_like(T)
    out[:, 3] = (0.0, 0.0, 0.0, 1.0)
    out[:, :3, 3] = (_mv3(RT, td) + T[:, :3, 3].T).T
    RtR = _mtm3(R, R)
    for i in range(3):
        RtR[i, i] -= 1.0
    before = np.abs(RtR).reshape(9, k).max(axis=0)
    R -= 0.5 * _mm3(R, RtR)  # R (3 I - R'R) / 2 = R - R (R'R - I) / 2
    Rk = R.transpose(2, 0, 1)
    if np.any(before > 1e-6):
        dev = np.abs(np.swapaxes(Rk, -1, -2) @ Rk - np.eye(3)).max(axis=(-2, -1))
        if np.any(dev > 1e-10):
            Rk = so3.project(Rk)
    out[:, :3, :3] = Rk
    return out
