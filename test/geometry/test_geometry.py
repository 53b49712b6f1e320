"""SO(3)/SE(3) helpers against numerical differentiation and identities."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.geometry import se3, so3


def _rotvecs(rng: np.random.Generator) -> np.ndarray:
    """Random, near-identity and near-pi rotation vectors."""
    axes = rng.normal(size=(30, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, 3.0, 10), 10.0 ** rng.uniform(-9, -3, 10),
                             np.pi - 10.0 ** rng.uniform(-7, -2, 10)])
    return axes * angles[:, None]


def test_so3_exp_log_roundtrip(rng):
    w = _rotvecs(rng)
    R = so3.exp(w)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(so3.exp(so3.log(R)), R, atol=1e-9)
    ok = np.linalg.norm(w, axis=1) < np.pi - 1e-6
    assert np.allclose(so3.log(R)[ok], w[ok], atol=1e-8)


def test_so3_exp_matches_scipy(rng):
    from scipy.spatial.transform import Rotation
    w = _rotvecs(rng)
    assert np.allclose(so3.exp(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-12)


@pytest.mark.parametrize('side', ['left', 'right'])
def test_so3_jacobians_numerical(rng, side):
    eps = 1e-6
    for w in _rotvecs(rng)[:20]:
        J = so3.left_jacobian(w) if side == 'left' else so3.right_jacobian(w)
        num = np.zeros((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            if side == 'right':
                f = lambda s: so3.log(so3.exp(w).T @ so3.exp(w + s * d))  # noqa: E731
            else:
                f = lambda s: so3.log(so3.exp(w + s * d) @ so3.exp(w).T)  # noqa: E731
            num[:, k] = (f(1) - f(-1)) / (2 * eps)
        assert np.allclose(J, num, atol=1e-7)
        Jinv = so3.left_jacobian_inv(w) if side == 'left' else so3.right_jacobian_inv(w)
        assert np.allclose(Jinv @ J, np.eye(3), atol=1e-9)


def _twists(rng):
    w = _rotvecs(rng)
    rho = rng.normal(scale=3.0, size=w.shape)
    return np.concatenate([rho, w], axis=1)


def test_se3_exp_log_roundtrip(rng):
    xi = _twists(rng)
    T = se3.exp(xi)
    assert np.allclose(se3.exp(se3.log(T)), T, atol=1e-8)
    ok = np.linalg.norm(xi[:, 3:], axis=1) < np.pi - 1e-6
    assert np.allclose(se3.log(T)[ok], xi[ok], atol=1e-7)


def test_se3_exp_matches_matrix_exponential(rng):
    from scipy.linalg import expm
    for xi in _twists(rng)[:10]:
        X = np.zeros((4, 4))
        X[:3, :3] = so3.hat(xi[3:])
        X[:3, 3] = xi[:3]
        assert np.allclose(se3.exp(xi), expm(X), atol=1e-10)


def test_se3_adjoint(rng):
    xi = _twists(rng)[:10]
    T = se3.exp(_twists(rng)[10:20])
    lhs = T @ se3.exp(xi) @ se3.inverse(T)
    rhs = se3.exp((se3.adjoint(T) @ xi[..., None])[..., 0])
    assert np.allclose(lhs, rhs, atol=1e-9)


@pytest.mark.parametrize('side', ['left', 'right'])
def test_se3_jacobians_numerical(rng, side):
    eps = 1e-6
    for xi in _twists(rng)[:20]:
        J = se3.left_jacobian(xi) if side == 'left' else se3.right_jacobian(xi)
        num = np.zeros((6, 6))
        T0 = se3.exp(xi)
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            if side == 'right':
                f = lambda s: se3.log(se3.inverse(T0) @ se3.exp(xi + s * d))  # noqa: E731
            else:
                f = lambda s: se3.log(se3.exp(xi + s * d) @ se3.inverse(T0))  # noqa: E731
            num[:, k] = (f(1) - f(-1)) / (2 * eps)
        assert np.allclose(J, num, atol=2e-6 * max(1.0, np.abs(xi).max()))
        Jinv = se3.left_jacobian_inv(xi) if side == 'left' else se3.right_jacobian_inv(xi)
        assert np.allclose(Jinv @ J, np.eye(6), atol=1e-8)


def test_quaternion_roundtrip(rng):
    T = se3.exp(_twists(rng))
    p, q = se3.to_pos_quat(T)
    assert np.all(q[:, 3] >= 0)
    assert np.allclose(se3.from_pos_quat(p, q), T, atol=1e-10)


def test_integrate_chains_motions(rng):
    motions = se3.exp(_twists(rng)[:5] * 0.1)
    T = se3.integrate(np.eye(4), motions)
    assert np.allclose(se3.relative(T[:-1], T[1:]), motions, atol=1e-10)


def test_quaternions_equal_scipy_near_identity_near_pi_and_at_random(rng):
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=(300, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.concatenate([rng.uniform(0, 1e-9, 100), np.pi - rng.uniform(0, 1e-7, 100),
                            rng.uniform(0, np.pi, 100)])
    R = Rotation.from_rotvec(axis * angle[:, None])
    q_ref = R.as_quat()
    q_ref = np.where(q_ref[:, 3:] < 0, -q_ref, q_ref)
    q = se3.quat_from_matrix(R.as_matrix())
    sign = np.where(np.sum(q * q_ref, axis=1) < 0, -1.0, 1.0)  # w = 0 exactly: either sign
    np.testing.assert_allclose(q * sign[:, None], q_ref, atol=1e-12)
    T = se3.from_pos_quat(np.zeros((300, 3)), rng.normal(size=(300, 4)) * 3.0)
    np.testing.assert_allclose(T[:, :3, :3], Rotation.from_quat(
        se3.quat_from_matrix(T[:, :3, :3])).as_matrix(), atol=1e-12)
    with pytest.raises(ValueError):
        se3.from_pos_quat(np.zeros(3), np.zeros(4))


def test_one_rotation_is_bit_for_bit_the_array_path(rng):
    # exp / log / from_rt of a single (3,) / (3, 3) take a scalar path; it must equal the
    # array path (the same input as a batch of one) to the last bit, at every angle scale,
    # at zero, near pi (log's branch) and on matrices off SO(3) by rounding
    n = 20_000
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.concatenate([10 ** rng.uniform(-12, 0.5, n // 2), rng.uniform(0, np.pi, n // 2)])
    w = axis * angle[:, None]
    w[:10] = 0.0
    w[10:20] *= 1e-300
    w[20:40] = axis[20:40] * (np.pi - rng.uniform(0, 2e-2, 20))[:, None]
    R = so3.exp(w[:, None, :])[:, 0]  # the array path
    R_off = R + rng.normal(scale=1e-9, size=R.shape)
    t = rng.normal(size=(n, 3))
    for k in range(n):
        assert np.array_equal(so3.exp(w[k]), R[k]), w[k]
        assert np.array_equal(so3.log(R[k]), so3.log(R[k][None])[0]), w[k]
        assert np.array_equal(so3.log(R_off[k]), so3.log(R_off[k][None])[0]), w[k]
        if k % 100 == 0:
            assert np.array_equal(se3.from_rt(R[k], t[k]), se3.from_rt(R[k][None], t[k])[0])
