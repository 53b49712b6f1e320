"""Fig. 2/3 (Sec. IV, Appendix): how much each new track moves the track-1 positions."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.geometry import se3
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.seeds import EXP_FUTURE, noise_key, run_rng
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel


@dataclass
class FutureTracksResult:
    """Fig. 2/3: mean change of the track-1 positions when track ``k`` is added."""

    tracks: list[int]
    absolute_m: dict[str, list[float]]
    normalised: dict[str, list[float]]
    n_nodes: int
    n_connections: int
    model: str = 'se3'


def future_tracks(cfg: ReproduceConfig, model: str = 'se3') -> FutureTracksResult:
    """Fig. 2/3 (Sec. IV and the Appendix, eq. Avii): how much adding track ``k`` moves the
    estimated track-1 positions.

    As in the paper's Appendix, the adjustment is linearised at the true poses, where the GA
    correction is a linear function of the observation noise: ``d = N^-1 A' P xi`` (se3 model,
    ``A`` the Jacobian of ``log(T_ij^-1 T_i^-1 T_j)`` w.r.t. the nodes, ``P`` the inverse noise
    covariance, first node fixed). For ``fig3_runs`` noise draws ``xi`` per level, the same draw
    is used for tracks ``1..k-1`` and ``1..k`` and the value at ``k`` is the mean over draws and
    track-1 nodes of ``|p_i(1..k) - p_i(1..k-1)|``; normalised by the largest (track 2).

    ``model='linear'`` does the same with positions only (``p_j - p_i = t``, translation noise
    only): no heading unknowns, hence no lever arm through which a new track's rotation noise
    moves distant nodes.
    """
    from scipy.sparse import coo_matrix

    sc_all = aerial_scenario(cfg.fig3_tracks, cfg.aerial_positions_per_swath)
    z_true = sc_all.true_motions()
    T_rel = se3.from_translation_rotvec(z_true[:, :3], z_true[:, 3:])
    if model == 'se3':
        dof = 6
        A_src = -se3.adjoint(se3.inverse(T_rel))
    elif model == 'linear':
        dof = 3
        A_src = -np.broadcast_to(np.eye(3), (len(z_true), 3, 3))
    else:
        raise ValueError(f'model must be se3 or linear, got {model!r}')
    sub = [sc_all.first_tracks(k) for k in range(1, cfg.fig3_tracks + 1)]
    track1 = sub[0].n_nodes
    levels = cfg.fig3_noise_levels
    runs = cfg.fig3_runs
    # d = N^-1 A' P xi does not change when P is scaled, so one factorisation per k serves every
    # noise level: P from the 1 % sigmas, xi drawn with each level's sigmas.
    sig1 = NoiseModel(1.0, sc_all.depth_m).sigmas(z_true)[:, :dof]
    xi = np.concatenate([run_rng(cfg.seed, EXP_FUTURE, i).standard_normal((runs,) + sig1.shape)
                         * sig1 * pct for i, pct in enumerate(levels)])  # (L runs, m, 6)
    prev = None
    changes = []
    for sc in sub:
        m, n = sc.n_connections, sc.n_nodes
        rows = np.arange(dof * m).reshape(m, dof)
        keep_s, keep_d = sc.src > 0, sc.dst > 0  # node 0 is fixed: it has no columns
        cols_s = dof * (sc.src - 1)[:, None] + np.arange(dof)
        cols_d = dof * (sc.dst - 1)[:, None] + np.arange(dof)
        r_idx = np.concatenate([np.repeat(rows[keep_s], dof, axis=1).ravel(),
                                rows[keep_d].ravel()])
        c_idx = np.concatenate([np.tile(cols_s[keep_s], (1, dof)).ravel(),
                                cols_d[keep_d].ravel()])
        vals = np.concatenate([A_src[:m][keep_s].ravel(), np.ones(dof * int(keep_d.sum()))])
        A = coo_matrix((vals, (r_idx, c_idx)), shape=(dof * m, dof * (n - 1))).tocsr()
        PA = A.multiply((1.0 / sig1[:m] ** 2).reshape(-1, 1)).tocsr()
        N = (A.T @ PA).tocsc()
        rhs = np.asarray(PA.T @ xi[:, :m].reshape(xi.shape[0], -1).T)  # (dof (n-1), L runs)
        d = _spd_solve(N, rhs)
        # track-1 positions (node 0 fixed): p_i moves by R_i rho_i, and |R_i rho_i| = |rho_i|
        rho = d.reshape(n - 1, dof, -1)[:track1 - 1, :3, :]
        if prev is not None:
            changes.append(np.linalg.norm(rho - prev, axis=1).sum(axis=0) / track1)
        prev = rho
    ch = np.array(changes).reshape(len(sub) - 1, len(levels), runs).mean(axis=2)
    absolute: dict[str, list[float]] = {}
    normalised: dict[str, list[float]] = {}
    for i, pct in enumerate(levels):
        absolute[noise_key(pct)] = ch[:, i].tolist()
        normalised[noise_key(pct)] = (ch[:, i] / ch[:, i].max()).tolist()
    return FutureTracksResult(list(range(2, cfg.fig3_tracks + 1)), absolute, normalised,
                              sc_all.n_nodes, sc_all.n_connections, model)


def _spd_solve(N, rhs: FloatArray) -> FloatArray:
    """Solve ``N X = rhs`` for a sparse SPD ``N`` (CHOLMOD via cvxopt, else SuperLU)."""
    try:
        import cvxopt
        from cvxopt import cholmod
    except ImportError:  # pragma: no cover
        from scipy.sparse.linalg import splu

        return splu(N.tocsc(), permc_spec='MMD_AT_PLUS_A').solve(rhs)
    from scipy.sparse import tril

    L = tril(N, format='coo')
    M = cvxopt.spmatrix(L.data, L.row.astype(int).tolist(), L.col.astype(int).tolist(), N.shape)
    F = cholmod.symbolic(M, uplo='L')
    cholmod.numeric(M, F)
    B = cvxopt.matrix(np.asfortranarray(rhs, dtype=float))
    cholmod.solve(F, B)
    return np.array(B)
