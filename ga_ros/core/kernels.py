"""Compiled per-connection kernels of the ``se3`` solver (numba, cached on disk).

The Gauss-Newton system of ``sum e' P e`` with ``e = log(T_meas^-1 T_i^-1 T_j)`` needs, per
connection, an SE(3) logarithm, ``J = J_r(e)^-1``, ``Ad(T_ij^-1)`` and a few 6x6 products
(:func:`ga_ros.core.solver.linearise._linear_system` documents the algebra). Here one loop does it
all in
registers (~1 us per connection) and writes only the results; the NumPy implementation in
columns (:mod:`ga_ros.core.columns`, ~2 us per connection) is used instead when numba is not
installed, when ``GA_ROS_JIT=0`` is set, for problems below
:data:`MIN_CONNECTIONS` connections and for the first :data:`AFTER_ITERATIONS` linearisations of
a solve: importing numba and loading the cached machine code costs ~0.5-1.5 s and ~100 MiB of
resident memory per process, more than the kernel saves on a small graph or a short solve
(aerial survey, 25,000 connections: ~0.1 s saved per iteration, 5 iterations). Both are
checked against the stacked reference :func:`ga_ros.core.models.between` (random, near-identity
and near-pi rotations).

Formulas: Barfoot, *State Estimation for Robotics* (2017), eqs. 7.78 (``J_l^-1`` of SO(3)),
7.86 (``Q``), 7.95 (``J_l^-1`` of SE(3)); the SO(3) log as :func:`ga_ros.geometry.so3.log`.
"""

from __future__ import annotations

import importlib.util
import os

import numpy as np

from ga_ros.arrays import FloatArray, IntArray

#: The compiled kernels can be used: numba is installed and ``GA_ROS_JIT`` is not ``0``.
AVAILABLE = (importlib.util.find_spec('numba') is not None
             and os.environ.get('GA_ROS_JIT', '1') != '0')
#: Smallest number of connections for which the solver uses the kernels (see above).
MIN_CONNECTIONS = 2000
#: The solver switches to the kernels after this many linearisations of one solve.
AFTER_ITERATIONS = 8

_SMALL = 1e-4  # so3.SMALL_ANGLE
_SMALL_Q = 1e-3  # se3.Q_matrix's Taylor threshold
_NEAR_PI = np.pi - 1e-2


# callees first: a compiled function calls compiled globals
_JITTED = ('_so3_log', '_so3_jl_inv', '_hat', '_mm3', '_q_matrix', '_scratch',
           '_misclosure_one', '_se3_system', '_se3_misclosure', '_se3_prior',
           '_scatter_rows', '_se3_retract')


_UNCACHED: list[str] = []  # the functions compiled without an on-disk cache (warned once)


def jit(fn):
    """``fn`` compiled by numba (``nogil``), its machine code cached on disk so that the next
    process loads it instead of compiling (numba's cache: ``$NUMBA_CACHE_DIR``, else the
    ``__pycache__`` beside the source, else ``~/.cache/numba`` for a read-only install). When
    none of them is writable, ``fn`` is compiled without a cache (once per process, warned)
    rather than failing. Every compiled kernel of ga_ros is made here."""
    from ga_ros.runtime import import_numba

    numba = import_numba()

    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
        if not _UNCACHED:
            import warnings

            warnings.warn(f'numba cannot cache the compiled kernels ({exc}); they are compiled '
                          f'in every process (seconds of start-up): set NUMBA_CACHE_DIR to a '
                          f'writable directory', RuntimeWarning, stacklevel=2)
        _UNCACHED.append(fn.__qualname__)
        return numba.njit(nogil=True)(fn)


def _compile() -> None:
    """Replace the kernels of this module by their numba versions (once; cached on disk)."""
    if hasattr(_se3_system, 'py_func'):
        return
    g = globals()
    for name in _JITTED:
        g[name] = jit(g[name])


def use_for(n_connections: int) -> bool:
    """Whether the solver should use the kernels for a problem of this size."""
    return AVAILABLE and n_connections >= MIN_CONNECTIONS


def _so3_log(R, w):  # pragma: no cover - compiled
    cos_t = (R[0, 0] + R[1, 1] + R[2, 2] - 1.0) * 0.5
    v0 = 0.5 * (R[2, 1] - R[1, 2])
    v1 = 0.5 * (R[0, 2] - R[2, 0])
    v2 = 0.5 * (R[1, 0] - R[0, 1])
    sin_t = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    theta = np.arctan2(sin_t, cos_t)
    if theta < _SMALL:
        scale = 1.0 + theta * theta / 6.0
    else:
        scale = theta / sin_t
    w[0] = v0 * scale
    w[1] = v1 * scale
    w[2] = v2 * scale
    if theta > _NEAR_PI:
        # symmetric part: (R + R')/2 - cos(t) I = (1 - cos t) u u'; the largest diagonal column
        b00 = R[0, 0] - cos_t
        b11 = R[1, 1] - cos_t
        b22 = R[2, 2] - cos_t
        col = 0
        if b11 > b00 and b11 >= b22:
            col = 1
        elif b22 > b00 and b22 > b11:
            col = 2
        u0 = 0.5 * (R[0, col] + R[col, 0]) - (cos_t if col == 0 else 0.0)
        u1 = 0.5 * (R[1, col] + R[col, 1]) - (cos_t if col == 1 else 0.0)
        u2 = 0.5 * (R[2, col] + R[col, 2]) - (cos_t if col == 2 else 0.0)
        nu = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        s = u0 * v0 + u1 * v1 + u2 * v2
        sgn = -1.0 if s < 0 else 1.0
        f = sgn * theta / nu
        w[0] = u0 * f
        w[1] = u1 * f
        w[2] = u2 * f


def _so3_jl_inv(w, out):  # pragma: no cover - compiled
    """``J_l(w)^-1 = I - [w]x / 2 + e [w]x^2`` into ``out`` (3x3)."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    theta = np.sqrt(t2)
    if theta < _SMALL:
        e = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        a = np.sin(theta) / theta
        b = (1.0 - np.cos(theta)) / t2
        e = (1.0 - a / (2.0 * b)) / t2
    # [w]x^2 = w w' - |w|^2 I
    for r in range(3):
        for c in range(3):
            out[r, c] = e * w[r] * w[c]
        out[r, r] += 1.0 - e * t2
    out[0, 1] += 0.5 * w[2]
    out[0, 2] -= 0.5 * w[1]
    out[1, 0] -= 0.5 * w[2]
    out[1, 2] += 0.5 * w[0]
    out[2, 0] += 0.5 * w[1]
    out[2, 1] -= 0.5 * w[0]


def _hat(w, out):  # pragma: no cover - compiled
    out[0, 0] = 0.0
    out[0, 1] = -w[2]
    out[0, 2] = w[1]
    out[1, 0] = w[2]
    out[1, 1] = 0.0
    out[1, 2] = -w[0]
    out[2, 0] = -w[1]
    out[2, 1] = w[0]
    out[2, 2] = 0.0


def _mm3(A, B, out):  # pragma: no cover - compiled
    for r in range(3):
        for c in range(3):
            out[r, c] = A[r, 0] * B[0, c] + A[r, 1] * B[1, c] + A[r, 2] * B[2, c]


def _q_matrix(rho, phi, Q, P, Rh, PR, RP, PRP, PP, T1, T2):  # pragma: no cover - compiled
    """Barfoot's ``Q(rho, phi)`` (eq. 7.86) into ``Q``; the rest are 3x3 scratch arrays."""
    t2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    t = np.sqrt(t2)
    if t < _SMALL_Q:
        c1 = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
        c2 = 1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0
        c3 = 1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120960.0
    else:
        s, c = np.sin(t), np.cos(t)
        c1 = (t - s) / (t2 * t)
        c2 = (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2)
        c3 = (2.0 * t - 3.0 * s + t * c) / (2.0 * t2 * t2 * t)
    _hat(phi, P)
    _hat(rho, Rh)
    _mm3(P, Rh, PR)
    _mm3(Rh, P, RP)
    _mm3(PR, P, PRP)
    _mm3(P, P, PP)
    _mm3(PP, Rh, T1)   # P P R
    _mm3(RP, P, T2)    # R P P
    for r in range(3):
        for c in range(3):
            Q[r, c] = (0.5 * Rh[r, c] + c1 * (PR[r, c] + RP[r, c] + PRP[r, c])
                       + c2 * (T1[r, c] + T2[r, c] - 3.0 * PRP[r, c]))
    _mm3(PRP, P, T1)   # P R P P
    _mm3(P, PRP, T2)   # P P R P
    for r in range(3):
        for c in range(3):
            Q[r, c] += c3 * (T1[r, c] + T2[r, c])


def _scratch():  # pragma: no cover - compiled
    """Work arrays of :func:`_misclosure_one`: Rij, tij, RE, tE, phi, Ji, e."""
    return (np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(3), np.empty(3),
            np.empty((3, 3)), np.empty(6))


def _misclosure_one(T, i, j, Tm_k, Rij, tij, RE, tE, phi, Ji, e):  # pragma: no cover
    """``e = log(T_meas^-1 T_i^-1 T_j)`` of one connection; leaves ``T_ij`` in ``Rij, tij``
    and ``J_l(phi)^-1`` in ``Ji`` (the rest are 3-vector / 3x3 scratch)."""
    for r in range(3):
        for c in range(3):
            Rij[r, c] = T[i, 0, r] * T[j, 0, c] + T[i, 1, r] * T[j, 1, c] \
                + T[i, 2, r] * T[j, 2, c]
        tij[r] = T[i, 0, r] * (T[j, 0, 3] - T[i, 0, 3]) + T[i, 1, r] * (T[j, 1, 3]
                                                                       - T[i, 1, 3]) \
            + T[i, 2, r] * (T[j, 2, 3] - T[i, 2, 3])
    for r in range(3):
        for c in range(3):
            RE[r, c] = Tm_k[r, 0] * Rij[0, c] + Tm_k[r, 1] * Rij[1, c] + Tm_k[r, 2] * Rij[2, c]
        tE[r] = Tm_k[r, 0] * tij[0] + Tm_k[r, 1] * tij[1] + Tm_k[r, 2] * tij[2] + Tm_k[r, 3]
    _so3_log(RE, phi)
    _so3_jl_inv(phi, Ji)
    for r in range(3):
        e[r] = Ji[r, 0] * tE[0] + Ji[r, 1] * tE[1] + Ji[r, 2] * tE[2]
        e[3 + r] = phi[r]


def _se3_system(T, src, dst, Tm_inv, P, e_out, blocks, gi, gj, maha):  # pragma: no cover
    """Per connection: the misclosure, ``J = J_r(e)^-1``, ``Ad(T_ij^-1)``, then the weighted
    terms of :func:`se3_system`. One loop body, its scratch arrays allocated here, on purpose:
    the same steps as compiled helpers called per connection, or the scratch arrays from a
    helper (LLVM then cannot assume they do not alias), made the kernel 5-15 % slower."""
    m = src.shape[0]
    want = blocks.shape[0] > 0  # an empty blocks array: the gradient only (blocks=False)
    Rij, tij, RE, tE, phi, Ji, e = _scratch()
    rho = np.empty(3)
    Q = np.empty((3, 3))
    S = np.empty((8, 3, 3))
    J = np.zeros((6, 6))
    Ad = np.zeros((6, 6))
    PJ = np.empty((6, 6))
    H = np.empty((6, 6))
    HA = np.empty((6, 6))
    Pe = np.empty(6)
    JiQJi = np.empty((3, 3))
    for k in range(m):
        i = src[k]
        j = dst[k]
        _misclosure_one(T, i, j, Tm_inv[k], Rij, tij, RE, tE, phi, Ji, e)
        for r in range(6):
            e_out[k, r] = e[r]
        for r in range(3):
            rho[r] = e[r]
        # J = J_r(e)^-1 = J_l(-e)^-1 = [[Ji, -Ji Q Ji], [0, Ji]] at -e (Barfoot eq. 7.95)
        for r in range(3):
            rho[r] = -rho[r]
            phi[r] = -phi[r]
        _so3_jl_inv(phi, Ji)
        _q_matrix(rho, phi, Q, S[0], S[1], S[2], S[3], S[4], S[5], S[6], S[7])
        _mm3(Ji, Q, S[0])
        _mm3(S[0], Ji, JiQJi)
        for r in range(3):
            for c in range(3):
                J[r, c] = Ji[r, c]
                J[3 + r, 3 + c] = Ji[r, c]
                J[r, 3 + c] = -JiQJi[r, c]
                J[3 + r, c] = 0.0
        # Ad(T_ij^-1) = [[R', [t']x R'], [0, R']] with R' = Rij', t' = -Rij' tij
        for r in range(3):
            tE[r] = -(Rij[0, r] * tij[0] + Rij[1, r] * tij[1] + Rij[2, r] * tij[2])
        _hat(tE, S[0])
        for r in range(3):
            for c in range(3):
                Ad[r, c] = Rij[c, r]
                Ad[3 + r, 3 + c] = Rij[c, r]
                Ad[3 + r, c] = 0.0
                Ad[r, 3 + c] = S[0, r, 0] * Rij[c, 0] + S[0, r, 1] * Rij[c, 1] \
                    + S[0, r, 2] * Rij[c, 2]
        # H = J' P J, g = J' P e, maha = e' P e
        for r in range(6):
            s = 0.0
            for c in range(6):
                s += P[k, r, c] * e[c]
                if want:
                    acc = 0.0
                    for q in range(6):
                        acc += P[k, r, q] * J[q, c]
                    PJ[r, c] = acc
            Pe[r] = s
        mh = 0.0
        for r in range(6):
            mh += e[r] * Pe[r]
            g = 0.0
            for q in range(6):
                g += J[q, r] * Pe[q]
            gj[k, r] = g
            for c in range(r, 6 if want else 0):
                acc = 0.0
                for q in range(6):
                    acc += J[q, r] * PJ[q, c]
                H[r, c] = acc
                H[c, r] = acc
        maha[k] = mh
        # g_i = -Ad' g_j; HA = H Ad; blocks (ii, ij, ji, jj) = (Ad' H Ad, -(H Ad)', -H Ad, H)
        for r in range(6):
            g = 0.0
            for q in range(6):
                g += Ad[q, r] * gj[k, q]
            gi[k, r] = -g
            for c in range(6 if want else 0):
                acc = 0.0
                for q in range(6):
                    acc += H[r, q] * Ad[q, c]
                HA[r, c] = acc
        for r in range(6 if want else 0):
            for c in range(6):
                acc = 0.0
                for q in range(6):
                    acc += Ad[q, r] * HA[q, c]
                blocks[k, r, c] = acc
                blocks[m + k, c, r] = -HA[r, c]
                blocks[2 * m + k, r, c] = -HA[r, c]
                blocks[3 * m + k, r, c] = H[r, c]


def _se3_misclosure(T, src, dst, Tm_inv, e_out):  # pragma: no cover - compiled
    m = src.shape[0]
    Rij, tij, RE, tE, phi, Ji, e = _scratch()
    for k in range(m):
        _misclosure_one(T, src[k], dst[k], Tm_inv[k], Rij, tij, RE, tE, phi, Ji, e)
        for r in range(6):
            e_out[k, r] = e[r]


def _se3_prior(T, idx, Tm, H, blk_r, blk_c, col, u, blocks, with_blocks
               ):  # pragma: no cover - compiled
    k = idx.shape[0]
    e = np.empty((k, 6))
    J = np.zeros((k, 6, 6))
    R_rel = np.empty((3, 3))
    phi = np.empty(3)
    w = np.empty(3)
    Jr = np.empty((3, 3))
    for a in range(k):
        i = idx[a]
        for r in range(3):  # R_rel = R_mean' R
            for c in range(3):
                R_rel[r, c] = (Tm[a, 0, r] * T[i, 0, c] + Tm[a, 1, r] * T[i, 1, c]
                               + Tm[a, 2, r] * T[i, 2, c])
        _so3_log(R_rel, phi)
        for r in range(3):
            w[r] = -phi[r]
        _so3_jl_inv(w, Jr)  # J_r(phi)^-1 = J_l(-phi)^-1
        d0 = T[i, 0, 3] - Tm[a, 0, 3]
        d1 = T[i, 1, 3] - Tm[a, 1, 3]
        d2 = T[i, 2, 3] - Tm[a, 2, 3]
        for r in range(3):
            e[a, r] = Tm[a, 0, r] * d0 + Tm[a, 1, r] * d1 + Tm[a, 2, r] * d2
            e[a, 3 + r] = phi[r]
            for c in range(3):
                J[a, r, c] = R_rel[r, c]
                J[a, 3 + r, 3 + c] = Jr[r, c]
    He = np.zeros((k, 6))
    for q in range(blk_r.shape[0]):  # H e, block by block in the information's order
        a, b = blk_r[q], blk_c[q]
        for r in range(6):
            acc = 0.0
            for c in range(6):
                acc += H[q, r, c] * e[b, c]
            He[a, r] += acc
    cost = 0.0
    for a in range(k):
        for r in range(6):
            cost += e[a, r] * He[a, r]
        ca = col[idx[a]]
        if ca >= 0:  # u += J' H e
            for r in range(6):
                acc = 0.0
                for c in range(6):
                    acc += J[a, c, r] * He[a, c]
                u[ca, r] += acc
    if with_blocks:  # block (a, b) of J' H J = J_a' H_ab J_b
        HJ = np.empty((6, 6))
        for q in range(blk_r.shape[0]):
            a, b = blk_r[q], blk_c[q]
            for r in range(6):
                for c in range(6):
                    acc = 0.0
                    for t in range(6):
                        acc += H[q, r, t] * J[b, t, c]
                    HJ[r, c] = acc
            for r in range(6):
                for c in range(6):
                    acc = 0.0
                    for t in range(6):
                        acc += J[a, t, r] * HJ[t, c]
                    blocks[q, r, c] = acc
    return cost


def se3_prior(T: FloatArray, idx: IntArray, T_mean: FloatArray, H_blocks: FloatArray,
              blk_r: IntArray, blk_c: IntArray, col: IntArray, u: FloatArray,
              blocks: bool = True) -> tuple[float, FloatArray | None]:
    """The terms of one se3 weighted parameter (a joint Gaussian prior) in the Gauss-Newton
    system, as :func:`ga_ros.core.solver.priors._add_priors` computes them with NumPy (to
    rounding): residual ``e = [R_mean' (p - p_mean), log(R_mean' R)]`` per node, Jacobian
    ``J = diag(R_mean' R, J_r(phi)^-1)``, ``u[col] += J' H e`` added in place (``u`` (u, 6),
    fixed nodes ``col < 0`` skipped), the cost ``e' H e``, and (``blocks``) the normal-matrix
    blocks ``J_a' H_ab J_b`` (b, 6, 6) in the information's block order (``H_blocks`` (b, 6,
    6) at block rows / columns ``blk_r``, ``blk_c``, positions into ``idx``).

    Parameters
    ----------
    T : (n, 4, 4) poses ``T_world_node``; ``idx`` (k,) the prior's nodes in ``T``;
    T_mean : (k, 4, 4) the prior's mean poses.

    Returns
    -------
    ``(cost, blocks)`` (``blocks`` ``None`` when not asked).
    """
    _compile()
    out = np.empty((blk_r.shape[0] if blocks else 0, 6, 6))
    cost = _se3_prior(np.ascontiguousarray(T), idx, np.ascontiguousarray(T_mean),
                      np.ascontiguousarray(H_blocks), blk_r, blk_c, col, u, out, blocks)
    return cost, (out if blocks else None)


def _scatter_rows(u, c, g, acc):  # pragma: no cover - compiled
    # as np.bincount: each row's sum from zero in the order of c, then added to u
    n, d = u.shape
    for j in range(n):
        for k in range(d):
            acc[j, k] = 0.0
    for i in range(c.shape[0]):
        j = c[i]
        if j >= 0:
            for k in range(d):
                acc[j, k] += g[i, k]
    for j in range(n):
        for k in range(d):
            u[j, k] += acc[j, k]


def scatter_rows(u: FloatArray, c: IntArray, g: FloatArray) -> None:
    """``u[c] += g`` (rows; ``c < 0`` skipped, repeated rows summed), bit for bit as
    ``u[:, k] += np.bincount(c, weights=g[:, k])`` per column (each row's contributions summed
    from zero in the order of ``c``, then added)."""
    _compile()
    _scatter_rows(u, c, np.ascontiguousarray(g), np.empty_like(u))


def _se3_retract(T, xi, out):  # pragma: no cover - compiled
    # columns.retract's operations per pose; returns the largest deviation |R'R - I| before the
    # Bjorck step (the caller projects by SVD where it exceeds 1e-6, as columns.retract)
    worst = 0.0
    Rd = np.empty((3, 3))
    R = np.empty((3, 3))
    RtR = np.empty((3, 3))
    for k in range(T.shape[0]):
        w0, w1, w2 = xi[k, 3], xi[k, 4], xi[k, 5]
        r0, r1, r2 = xi[k, 0], xi[k, 1], xi[k, 2]
        t2 = w0 * w0 + w1 * w1 + w2 * w2
        theta = np.sqrt(t2)
        th2 = theta * theta  # so3._coeffs' t2
        if theta < _SMALL:
            a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
            b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
            c = 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0
        else:
            a = np.sin(theta) / theta
            b = (1.0 - np.cos(theta)) / (theta * theta)
            c = (theta - np.sin(theta)) / (theta * theta * theta)
        # R_d = I + a W + b (w w' - |w|^2 I)
        Rd[0, 0] = b * (w0 * w0) + (1.0 - b * t2)
        Rd[0, 1] = a * -w2 + b * (w0 * w1)
        Rd[0, 2] = a * w1 + b * (w0 * w2)
        Rd[1, 0] = a * w2 + b * (w1 * w0)
        Rd[1, 1] = b * (w1 * w1) + (1.0 - b * t2)
        Rd[1, 2] = a * -w0 + b * (w1 * w2)
        Rd[2, 0] = a * -w1 + b * (w2 * w0)
        Rd[2, 1] = a * w0 + b * (w2 * w1)
        Rd[2, 2] = b * (w2 * w2) + (1.0 - b * t2)
        # t_d = r + b (w x r) + c (w (w.r) - |w|^2 r)
        wr = w0 * r0 + w1 * r1 + w2 * r2
        td0 = r0 + b * (w1 * r2 - w2 * r1) + c * (w0 * wr - t2 * r0)
        td1 = r1 + b * (w2 * r0 - w0 * r2) + c * (w1 * wr - t2 * r1)
        td2 = r2 + b * (w0 * r1 - w1 * r0) + c * (w2 * wr - t2 * r2)
        for i in range(3):
            for j in range(3):
                R[i, j] = T[k, i, 0] * Rd[0, j] + T[k, i, 1] * Rd[1, j] + T[k, i, 2] * Rd[2, j]
            out[k, i, 3] = (T[k, i, 0] * td0 + T[k, i, 1] * td1 + T[k, i, 2] * td2) + T[k, i, 3]
        for i in range(3):
            for j in range(3):
                RtR[i, j] = R[0, i] * R[0, j] + R[1, i] * R[1, j] + R[2, i] * R[2, j]
            RtR[i, i] -= 1.0
        for i in range(3):
            for j in range(3):
                dev = abs(RtR[i, j])
                if dev > worst:
                    worst = dev
        for i in range(3):  # R (3 I - R'R) / 2 = R - R (R'R - I) / 2
            for j in range(3):
                out[k, i, j] = R[i, j] - 0.5 * (R[i, 0] * RtR[0, j] + R[i, 1] * RtR[1, j]
                                                + R[i, 2] * RtR[2, j])
        out[k, 3, 0] = 0.0
        out[k, 3, 1] = 0.0
        out[k, 3, 2] = 0.0
        out[k, 3, 3] = 1.0
    return worst


def se3_retract(T: FloatArray, xi: FloatArray) -> FloatArray | None:
    """``T @ exp(xi)`` of ``(k, 4, 4)`` poses and ``(k, 6)`` increments ``[rho, phi]``, as
    :func:`ga_ros.core.columns.retract` computes it (to rounding), one compiled loop instead of
    ~40 NumPy calls; ``None`` where a rotation was off by more than 1e-6 before its Bjorck step
    (the caller then runs :func:`~ga_ros.core.columns.retract`, which checks and projects)."""
    _compile()
    out = np.empty((T.shape[0], 4, 4))
    worst = _se3_retract(np.ascontiguousarray(T), np.ascontiguousarray(xi), out)
    return out if worst <= 1e-6 else None


def se3_misclosure(T: FloatArray, src: IntArray, dst: IntArray, Tm_inv: FloatArray) -> FloatArray:
    """``e = log(T_meas^-1 T_i^-1 T_j)`` ``(m, 6)`` (``[rho, phi]``, m and rad).

    Parameters
    ----------
    T : (n, 4, 4) poses ``T_world_node``.
    src, dst : (m,) node indices.
    Tm_inv : (m, 4, 4) inverses of the measured motions ``T_meas``.
    """
    _compile()
    e = np.empty((src.shape[0], 6))
    _se3_misclosure(np.ascontiguousarray(T), src, dst, Tm_inv, e)
    return e


def se3_system(T: FloatArray, src: IntArray, dst: IntArray, Tm_inv: FloatArray,
               P: FloatArray, extra_blocks: int = 0, blocks: bool = True
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per-connection Gauss-Newton blocks of ``sum e' P e`` (unweighted by robust weights).

    ``extra_blocks`` rows are left uninitialised at the end of ``blocks`` for the caller.

    Returns
    -------
    e : (m, 6) misclosures.
    blocks : (4 m + extra_blocks, 6, 6) normal-matrix blocks ``(ii, ij, ji, jj)`` stacked
        block-type major, ``J_a' P J_b`` with ``J_i = -J_r(e)^-1 Ad(T_ij^-1)``,
        ``J_j = J_r(e)^-1``; empty with ``blocks=False`` (the gradient only: ~3x faster).
    gi, gj : (m, 6) gradient halves ``J_i' P e``, ``J_j' P e``.
    maha : (m,) ``e' P e``.
    """
    _compile()
    m = src.shape[0]
    e = np.empty((m, 6))
    out = np.empty((4 * m + extra_blocks if blocks else 0, 6, 6))
    gi = np.empty((m, 6))
    gj = np.empty((m, 6))
    maha = np.empty(m)
    _se3_system(np.ascontiguousarray(T), src, dst, Tm_inv, P, e, out, gi, gj, maha)
    return e, out, gi, gj, maha
