"""Tests of the trajectory error metrics against ground truth and brute force."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from ga_ros.errors import InputError
from ga_ros.eval.metrics import (
    align_rigid,
    anchor_first,
    ate,
    improvement_pct,
    per_track_mean,
    position_errors,
)
from ga_ros.geometry import se3, so3


def _random_poses(rng, n=40):
    R = so3.exp(rng.normal(scale=0.5, size=(n, 3)))
    return se3.from_rt(R, rng.normal(scale=10, size=(n, 3)))


def test_rigid_alignment_recovers_a_known_motion(rng):
    p = rng.normal(scale=20, size=(50, 3))
    R = so3.exp(rng.normal(size=3))
    t = rng.normal(scale=5, size=3)
    q = p @ R.T + t
    a = align_rigid(p, q)
    np.testing.assert_allclose(a.R, R, atol=1e-10)
    np.testing.assert_allclose(a.t, t, atol=1e-9)
    assert np.linalg.det(a.R) == pytest.approx(1.0)


def test_rigid_alignment_is_a_least_squares_minimum(rng):
    p = rng.normal(scale=20, size=(30, 3))
    q = p @ so3.exp(np.array([0.1, -0.2, 0.3])).T + 1.0 + rng.normal(scale=2.0, size=p.shape)
    a = align_rigid(p, q)

    def cost(x):
        return np.sum((p @ so3.exp(x[:3]).T + x[3:] - q) ** 2)

    best = cost(np.concatenate([so3.log(a.R), a.t]))
    brute = minimize(cost, np.zeros(6), method='BFGS')
    assert best <= brute.fun + 1e-6
    # a reflection never comes out, even for a mirrored point set
    a2 = align_rigid(p, p * np.array([1, 1, -1]))
    assert np.linalg.det(a2.R) == pytest.approx(1.0)


def test_ate_variants(rng):
    T_true = _random_poses(rng)
    G = se3.exp(rng.normal(size=6))
    T_moved = G @ T_true
    assert ate(T_moved, T_true, 'first').rmse == pytest.approx(0.0, abs=1e-9)
    assert ate(T_moved, T_true, 'rigid').rmse == pytest.approx(0.0, abs=1e-9)
    assert ate(T_moved, T_true, 'none').rmse > 0.1
    np.testing.assert_allclose(anchor_first(T_moved, T_true), T_true, atol=1e-9)
    noisy = T_true.copy()
    noisy[:, :3, 3] += rng.normal(scale=0.5, size=(len(T_true), 3))
    e = np.linalg.norm(noisy[:, :3, 3] - T_true[:, :3, 3], axis=1)
    r = ate(noisy, T_true, 'none')
    assert r.rmse == pytest.approx(np.sqrt(np.mean(e**2)))
    assert r.mean == pytest.approx(e.mean()) and r.max == pytest.approx(e.max())
    assert ate(noisy, T_true, 'rigid').rmse <= r.rmse + 1e-12
    np.testing.assert_allclose(position_errors(noisy, T_true), e)
    with pytest.raises(InputError):
        ate(noisy, T_true, 'scale')
    with pytest.raises(InputError):
        position_errors(noisy[:3], T_true)


def test_per_track_mean_and_improvement():
    errors = np.array([1.0, 2.0, 3.0, 10.0, 20.0])
    tracks = np.array([0, 0, 0, 4, 4])
    assert per_track_mean(errors, tracks) == {0: 2.0, 4: 15.0}
    assert improvement_pct(10.0, 2.5) == pytest.approx(75.0)
    with pytest.raises(InputError):
        improvement_pct(0.0, 1.0)
