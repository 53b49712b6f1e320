"""Small synthetic networks with exact ground truth, for the estimator tests."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.core.network import ConnectionNetwork
from ga_ros.geometry import se3, so3
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

SIGMA = np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])


@dataclass
class Problem:
    network: ConnectionNetwork
    T_true: np.ndarray
    pairs: list


def true_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    steps = rng.normal(scale=[1.0, 0.3, 0.2, 0.05, 0.05, 0.3], size=(n - 1, 6))
    steps[:, 0] += 1.0
    return se3.integrate(np.eye(4), se3.exp(steps))


def make_problem(rng: np.random.Generator, model: str = 'se3', n: int = 12, noise: float = 0.0,
                 gaps=(1, 2, 4), sigma: np.ndarray = SIGMA, tracks: int = 1) -> Problem:
    """Nodes on a random walk, connections ``(i, i + g)``; observations in the model's
    convention, with Gaussian noise ``noise * sigma`` (covariance ``diag((noise*sigma)^2)``, or
    ``diag(sigma^2)`` when noise is 0)."""
    T = true_poses(rng, n)
    pairs = [(i, i + g) for g in gaps for i in range(n - g)]
    std = sigma * (noise if noise > 0 else 1.0)
    cov = np.diag(std ** 2)
    net = ConnectionNetwork()
    for i in range(n):
        net.add_node(i, i * tracks // n)
    for i, j in pairs:
        eps = rng.normal(size=6) * std if noise > 0 else np.zeros(6)
        if model == 'se3':
            T_meas = se3.relative(T[i], T[j]) @ se3.exp(-eps)
            z = se3.to_translation_rotvec(T_meas)
        else:
            w = so3.log(T[i, :3, :3].T @ T[j, :3, :3])
            if model == 'paper':
                t = T[j, :3, 3] - so3.exp(w) @ T[i, :3, 3]
            else:
                t = T[j, :3, 3] - T[i, :3, 3]
            z = np.concatenate([t, w]) + eps
        net.add_connection(i, j, z, cov)
    return Problem(net, T, pairs)


def perturbed(rng: np.random.Generator, T: np.ndarray, scale: float = 0.05) -> np.ndarray:
    out = T @ se3.exp(rng.normal(scale=scale, size=(T.shape[0], 6)))
    out[0] = T[0]
    return out


def noisy_aerial_survey(n_tracks: int, per_swath: int, pct: float, seed: int):
    """A small simulated aerial survey with ``pct`` % motion noise: ``(scenario, noisy motions,
    measurements in acquisition order)``."""
    sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=per_swath)
    nm = perturb(sc.true_motions(), NoiseModel(pct, sc.depth_m), np.random.default_rng(seed))
    return sc, nm, sc.measurements(nm.z, nm.cov)


def whitener(info: np.ndarray) -> np.ndarray:
    """``L`` with ``L' L = info`` over its non-null space (eigenvalues above 1e-12 of the
    largest): the square-root weight of an information matrix, for the joint least-squares
    checks of the calibration tests."""
    w, V = np.linalg.eigh(0.5 * (info + info.T))
    keep = w > 1e-12 * w.max()
    return np.sqrt(w[keep])[:, None] * V[:, keep].T
