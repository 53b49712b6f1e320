"""Quality control (ga_ros.core.quality) against an independent dense computation.

The dense reference builds the full ``A``, ``B``, ``S`` of the mixed model for a small network,
inverts ``N`` with numpy and forms ``Q_vv = S B' M^-1 (M - A N^-1 A') M^-1 B S`` (docs/method.md
eq. 17); every figure of the report is compared with it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2, ncx2, norm
from solver_problems import make_problem

from ga_ros.core import models
from ga_ros.core.network import ConnectionArrays, ConnectionNetwork
from ga_ros.core.quality import (
    QualityConfig,
    b_method_alpha,
    data_snooping,
    noncentrality,
    quality_control,
)
from ga_ros.core.solver import GaussianPrior, SolverConfig, initial_guess_f2f, solve
from ga_ros.errors import InputError


def random_spd(rng: np.random.Generator, m: int, sigma: np.ndarray) -> np.ndarray:
    """(m, 6, 6) correlated covariances with standard deviations about ``sigma``."""
    out = np.empty((m, 6, 6))
    for k in range(m):
        C = rng.uniform(-0.4, 0.4, size=(6, 6))
        corr = np.eye(6) + 0.5 * (C + C.T) * (1 - np.eye(6))
        corr = corr @ corr.T
        dd = 1 / np.sqrt(np.diag(corr))
        corr = corr * dd[:, None] * dd[None, :]
        s = sigma * rng.uniform(0.5, 2.0, size=6)
        out[k] = corr * s[:, None] * s[None, :]
    return out


def correlated_problem(rng, model: str, n: int = 9, gaps=(1, 2, 3)):
    prob = make_problem(rng, model, n=n, gaps=gaps)
    c = prob.network.arrays()
    cov = random_spd(rng, len(c), np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01]))
    z = c.z.copy()
    if model == 'se3':
        from ga_ros.geometry import se3
        L = np.linalg.cholesky(cov)
        eps = (L @ rng.normal(size=(len(c), 6, 1)))[:, :, 0]
        T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:]) @ se3.exp(-eps)
        z = se3.to_translation_rotvec(T_meas)
    else:
        z = z + (np.linalg.cholesky(cov) @ rng.normal(size=(len(c), 6, 1)))[:, :, 0]
    net = ConnectionNetwork.from_arrays(prob.network.node_ids, prob.network.track_ids, c.src,
                                        c.dst, z, cov)
    return net, prob.T_true


def dense_reference(net: ConnectionNetwork, res, free_ids, lam0: float) -> dict:
    """Dense Q_vv P, w, connection statistics and MDB of the solution ``res``."""
    conn = net.arrays()
    m = len(conn)
    d = models.dof(res.model)
    lin = models.linearise(res.model, res.T_world_node, conn.src, conn.dst, conn.z,
                           res.residuals)
    rc = lin.f.shape[1]
    col = {int(i): k for k, i in enumerate(free_ids)}
    A = np.zeros((m * rc, len(free_ids) * d))
    Bm = np.zeros((m * rc, 6 * m))
    S = np.zeros((6 * m, 6 * m))
    for k in range(m):
        r = slice(k * rc, (k + 1) * rc)
        for node, blk in ((conn.src[k], lin.A_src[k]), (conn.dst[k], lin.A_dst[k])):
            nid = int(net.node_ids[node])
            if nid in col:
                A[r, col[nid] * d:(col[nid] + 1) * d] += blk
        Bm[r, 6 * k:6 * k + 6] = lin.B[k]
        S[6 * k:6 * k + 6, 6 * k:6 * k + 6] = conn.cov[k]
    P = np.linalg.inv(S)
    M = Bm @ S @ Bm.T
    Mi = np.linalg.inv(M)
    Qx = np.linalg.inv(A.T @ Mi @ A)
    Qvv = S @ Bm.T @ Mi @ (M - A @ Qx @ A.T) @ Mi @ Bm @ S
    R = Qvv @ P
    v = res.residuals.reshape(-1)
    Pv = P @ v
    PQP = P @ Qvv @ P
    var = np.diag(PQP)
    ok = var > 1e-6 * np.abs(P).max()
    w = np.where(ok, Pv / np.sqrt(np.where(ok, var, 1)), 0.0).reshape(m, 6)
    mdb = np.where(ok, np.sqrt(lam0 / np.where(ok, var, 1)), np.inf).reshape(m, 6)
    stat = np.empty(m)
    dof = np.empty(m, dtype=int)
    for k in range(m):
        s = slice(6 * k, 6 * k + 6)
        blk = PQP[s, s]
        dof[k] = np.linalg.matrix_rank(blk, tol=1e-6 * np.abs(blk).max())
        stat[k] = Pv[s] @ np.linalg.pinv(blk, rcond=1e-8) @ Pv[s]
    blocks = np.stack([R[6 * k:6 * k + 6, 6 * k:6 * k + 6] for k in range(m)])
    return {'R_blocks': blocks, 'trace_R': float(np.trace(R)), 'w': w, 'mdb': mdb,
            'stat': stat, 'dof': dof, 'cost': float(v @ P @ v),
            'redundancy': m * rc - len(free_ids) * d}


@pytest.mark.parametrize('model', ['linear', 'se3', 'paper'])
def test_report_matches_dense_computation(rng, model):
    net, T_true = correlated_problem(rng, model)
    res = solve(net, initial_guess_f2f(net), SolverConfig(model=model))
    rep = quality_control(net, res)
    ref = dense_reference(net, res, res.free_node_ids, rep.lambda0)
    R = ref['R_blocks']
    np.testing.assert_allclose(rep.redundancy_components, np.einsum('mjj->mj', R), atol=1e-8)
    np.testing.assert_allclose(rep.redundancy_numbers, np.trace(R, axis1=1, axis2=2), atol=1e-8)
    # redundancy numbers sum to r - u (the trace of the idempotent Q_vv P)
    assert rep.redundancy == ref['redundancy'] == res.redundancy
    np.testing.assert_allclose(rep.redundancy_numbers.sum(), rep.redundancy, atol=1e-7)
    np.testing.assert_allclose(ref['trace_R'], rep.redundancy, atol=1e-7)
    assert np.all(rep.redundancy_numbers > -1e-9)
    assert np.all(rep.redundancy_numbers < models.equations_per_connection(model) + 1e-9)
    np.testing.assert_allclose(rep.w, ref['w'], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(rep.mdb, ref['mdb'], rtol=1e-6)
    np.testing.assert_array_equal(rep.connection_dof, ref['dof'])
    np.testing.assert_allclose(rep.connection_statistic, ref['stat'], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rep.cost, ref['cost'], rtol=1e-9)
    np.testing.assert_allclose(rep.sigma0_sq, res.sigma0_sq, rtol=1e-6)
    s = rep.summary()
    assert s['connections'] == len(net.arrays())
    assert s['global_passed'] == (rep.cost <= chi2.isf(0.05, rep.redundancy))


def test_priors_share_the_redundancy(rng):
    """With a weighted first node instead of a fixed one, connection and prior redundancies
    sum to r - u; the prior group's share equals the dense ``tr(I - S_p^-1 Q_x)``."""
    net, T_true = correlated_problem(rng, 'se3')
    cov0 = np.diag([0.02, 0.02, 0.02, 0.005, 0.005, 0.005]) ** 2
    ids = net.node_ids[[0, 4]]
    prior = GaussianPrior.from_covariances(ids, T_true[[0, 4]], np.stack([cov0, 4 * cov0]))
    res = solve(net, initial_guess_f2f(net), SolverConfig(model='se3'), priors=[prior])
    rep = quality_control(net, res, priors=[prior])
    assert rep.redundancy == res.redundancy
    np.testing.assert_allclose(rep.redundancy_numbers.sum() + rep.prior_redundancy,
                               rep.redundancy, atol=1e-7)
    Q = np.linalg.inv(res.normal_matrix.toarray())
    cols = [int(np.nonzero(res.free_node_ids == i)[0][0]) for i in ids]
    Hp = prior.information.toarray()
    from ga_ros.geometry import so3
    # the prior residual [R_mean' (p - p_mean), log(R_mean' R)]: Jacobian diag(R_mean' R, J_r^-1)
    R_rel = np.swapaxes(T_true[[0, 4], :3, :3], 1, 2) @ res.T_world_node[[0, 4], :3, :3]
    J = np.zeros((2, 6, 6))
    J[:, :3, :3] = R_rel
    J[:, 3:, 3:] = so3.right_jacobian_inv(so3.log(R_rel))
    trace = 0.0
    for a in range(2):
        for b in range(2):
            Qba = Q[6 * cols[b]:6 * cols[b] + 6, 6 * cols[a]:6 * cols[a] + 6]
            Nab = J[a].T @ Hp[6 * a:6 * a + 6, 6 * b:6 * b + 6] @ J[b]
            trace += np.sum(Nab * Qba.T)
    np.testing.assert_allclose(rep.prior_redundancy, 12 - trace, atol=1e-7)
    assert 0 < rep.prior_redundancy < 12


def test_b_method_constants():
    cfg = QualityConfig()
    # Baarda's classic values: alpha0 = 0.001, beta0 = 0.80 -> lambda0 = 17.07, |w| > 3.29
    assert cfg.lambda0 == pytest.approx(17.075, abs=0.01)
    assert cfg.w_critical == pytest.approx(3.2905, abs=1e-3)
    assert cfg.lambda0 == pytest.approx((norm.isf(0.0005) + norm.isf(0.2)) ** 2, rel=1e-3)
    lam = noncentrality(0.01, 0.8, 3)
    assert ncx2.sf(chi2.isf(0.01, 3), 3, lam) == pytest.approx(0.8, abs=1e-9)
    a3 = b_method_alpha(cfg.lambda0, 0.8, 3)
    assert a3 > cfg.alpha0  # a 3-D test at the same lambda0 needs a larger level
    assert noncentrality(a3, 0.8, 3) == pytest.approx(cfg.lambda0, rel=1e-6)
    assert b_method_alpha(cfg.lambda0, 0.8, 1) == pytest.approx(0.001, rel=1e-6)
    with pytest.raises(InputError):
        QualityConfig(alpha0=0.9, power=0.5)
    with pytest.raises(InputError):
        QualityConfig(snoop_test='max')


def test_monte_carlo_linear_model(rng):
    """Under H0 the w-statistics are standard normal, the connection statistics chi2(q) and
    the global test rejects at its level."""
    base, _ = correlated_problem(rng, 'linear', n=8)
    c = base.arrays()
    T_true = initial_guess_f2f(base)
    # exact observations from the chain, then fresh noise each run
    p = T_true[:, :3, 3]
    z_true = c.z.copy()
    z_true[:, :3] = p[c.dst] - p[c.src]
    Lc = np.linalg.cholesky(c.cov)
    cfg = QualityConfig(alpha=0.1)
    ws, stats, dofs, rejects = [], [], [], []
    runs = 200
    for _ in range(runs):
        z = z_true + (Lc @ rng.normal(size=(len(c), 6, 1)))[:, :, 0]
        net = ConnectionNetwork.from_arrays(base.node_ids, base.track_ids, c.src, c.dst, z,
                                            c.cov)
        res = solve(net, T_true, SolverConfig(model='linear'))
        rep = quality_control(net, res, config=cfg)
        ws.append(rep.w[:, :3].ravel())
        stats.append(rep.connection_statistic)
        dofs.append(rep.connection_dof)
        rejects.append(not rep.global_passed)
    w = np.concatenate(ws)
    assert abs(w.mean()) < 0.05
    assert abs(w.var() - 1.0) < 0.08
    stat, dof = np.concatenate(stats), np.concatenate(dofs)
    assert np.all(dof == 3)
    assert abs(stat.mean() / 3.0 - 1.0) < 0.05
    rate = np.mean(rejects)
    assert abs(rate - 0.1) < 3.5 * np.sqrt(0.1 * 0.9 / runs)


@pytest.mark.parametrize('test, until', [('connection', 'global'), ('w', 'local')])
def test_data_snooping_finds_a_gross_error(rng, test, until):
    prob = make_problem(rng, 'se3', n=14, noise=1.0, gaps=(1, 2, 3))
    c = prob.network.arrays()
    bad = 17
    z = c.z.copy()
    z[bad, :3] += np.array([0.6, -0.4, 0.3])  # ~ 12 sigma of translation
    net = ConnectionNetwork.from_arrays(prob.network.node_ids, prob.network.track_ids, c.src,
                                        c.dst, z, c.cov)
    res = solve(net, initial_guess_f2f(net))
    rep = quality_control(net, res)
    assert not rep.global_passed
    assert int(np.nanargmax(rep.test_ratio(test))) == bad
    cfg = QualityConfig(snoop_test=test, alpha0=1e-4)
    out = data_snooping(net, initial_guess_f2f(net), config=cfg, until=until)
    assert out.removed.tolist() == [bad]
    assert not out.kept[bad] and out.kept.sum() == len(c) - 1
    if until == 'global':
        assert out.report.global_passed
    else:
        assert out.report.rejected(test).sum() == 0
    assert out.iterations == 2
    err = np.linalg.norm(out.result.T_world_node[:, :3, 3] - prob.T_true[:, :3, 3], axis=1)
    assert err.max() < 0.2


def test_bridge_is_untestable(rng):
    """A connection whose removal splits the network has r_i = 0: no test, infinite MDB."""
    prob = make_problem(rng, 'linear', n=6, gaps=(1, 2))
    c = prob.network.arrays()
    node_ids = np.append(prob.network.node_ids, 99)
    tracks = np.append(prob.network.track_ids, 0)
    src = np.append(c.src, 5)
    dst = np.append(c.dst, 6)
    net = ConnectionNetwork.from_arrays(node_ids, tracks, src, dst,
                                        np.vstack([c.z, c.z[:1]]), np.vstack([c.cov, c.cov[:1]]))
    res = solve(net, initial_guess_f2f(net), SolverConfig(model='linear'))
    rep = quality_control(net, res)
    assert rep.redundancy_numbers[-1] == pytest.approx(0.0, abs=1e-9)
    assert rep.connection_dof[-1] == 0 and np.isnan(rep.connection_statistic[-1])
    assert np.all(np.isinf(rep.mdb[-1]))
    assert not rep.rejected()[-1]


def test_wrong_network_is_rejected(rng):
    net, _ = correlated_problem(rng, 'se3')
    other, _ = correlated_problem(rng, 'se3', n=10)
    res = solve(other, initial_guess_f2f(other))
    with pytest.raises(InputError):
        quality_control(net, res)


def test_selected_and_solved_inverse_blocks_agree(rng):
    """Selected inversion on the factor and the sparse-solve path give the dense inverse's blocks
    for every connected pair, a fixed end giving zero blocks; a pair off the pattern of ``N``
    (unconnected nodes) is solved for."""
    import scipy.sparse as sp

    from ga_ros.core.quality.cofactors import inverse_blocks

    net, _ = correlated_problem(rng, 'se3', n=12, gaps=(1, 3, 5))
    res = solve(net, initial_guess_f2f(net))
    N = sp.csr_matrix(res.normal_matrix)
    c = net.arrays()
    col = {int(i): k for k, i in enumerate(res.free_node_ids)}
    cs = np.array([col.get(int(net.node_ids[s]), -1) for s in c.src])
    cd = np.array([col.get(int(net.node_ids[s]), -1) for s in c.dst])
    far = len(col) - 1
    rows, cols = np.concatenate([cs, cd, cd, [0]]), np.concatenate([cd, cs, cd, [far]])
    assert N[6 * 0:6, 6 * far:6 * far + 6].nnz == 0  # off the pattern
    dense = np.linalg.inv(N.toarray())
    selected = inverse_blocks(N, 6, rows, cols)
    solved = inverse_blocks(N, 6, rows, cols, selected=False)  # sparse solves
    for k, (r, cc) in enumerate(zip(rows, cols)):
        ref = np.zeros((6, 6)) if r < 0 or cc < 0 else dense[6 * r:6 * r + 6, 6 * cc:6 * cc + 6]
        np.testing.assert_allclose(selected[k], ref, atol=1e-12 * np.abs(dense).max())
        np.testing.assert_allclose(solved[k], ref, atol=1e-12 * np.abs(dense).max())


def test_outlier_benchmark_injection_and_snooping():
    """The benchmark's injected errors have the requested count and size, and data snooping
    rejects them on a small aerial survey without touching good connections."""
    from ga_ros.bench.outliers import inject, run_method
    from ga_ros.geometry import se3
    from ga_ros.sim.aerial import aerial_scenario
    from ga_ros.sim.noise import NoiseModel, perturb

    sc = aerial_scenario(n_tracks=2, positions_per_swath=12)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(3))
    z, bad = inject(sc, nm.z, 0.1, (5.0, 15.0), (5.0, 15.0), np.random.default_rng(4))
    n_cross = int((~sc.consecutive).sum())
    assert bad.sum() == round(0.1 * n_cross) and not (bad & sc.consecutive).any()
    np.testing.assert_array_equal(z[~bad], nm.z[~bad])
    xi = se3.log(se3.inverse(se3.from_translation_rotvec(nm.z[bad, :3], nm.z[bad, 3:]))
                 @ se3.from_translation_rotvec(z[bad, :3], z[bad, 3:]))
    size_m = np.linalg.norm(xi[:, :3], axis=1)
    size_deg = np.degrees(np.linalg.norm(xi[:, 3:], axis=1))
    assert np.all(((size_m >= 5 - 1e-9) & (size_m <= 15 + 1e-9) & (size_deg < 1e-9)) |
                  ((size_deg >= 5 - 1e-9) & (size_deg <= 15 + 1e-9) & (size_m < 1e-9)))
    out = run_method('snoop-w', sc, z, nm.cov, bad, 1e-4, 5)
    np.testing.assert_array_equal(out.rejected, bad)


def test_outside_connection_test_equals_the_increase_of_the_cost(rng):
    """Linear model: testing a left-out connection against the adjustment gives exactly the
    increase of v'Pv when it is added (the sequential-adjustment identity)."""
    net, _ = correlated_problem(rng, 'linear', n=9)
    c = net.arrays()
    out = np.array([2, 11, 20])
    keep = np.ones(len(c), dtype=bool)
    keep[out] = False
    sub = ConnectionNetwork.from_arrays(net.node_ids, net.track_ids, c.src[keep], c.dst[keep],
                                        c.z[keep], c.cov[keep])
    cfg = SolverConfig(model='linear')
    res_sub = solve(sub, initial_guess_f2f(net), cfg)
    rep = quality_control(sub, res_sub, outside=ConnectionArrays(c.src[out], c.dst[out],
                                                                 c.z[out], c.cov[out]))
    for j, k in enumerate(out):
        keep_k = keep.copy()
        keep_k[k] = True
        with_k = ConnectionNetwork.from_arrays(net.node_ids, net.track_ids, c.src[keep_k],
                                               c.dst[keep_k], c.z[keep_k], c.cov[keep_k])
        res_k = solve(with_k, initial_guess_f2f(net), cfg)
        np.testing.assert_allclose(rep.outside_statistic[j], res_k.cost - res_sub.cost,
                                   rtol=1e-6)
    assert np.all(rep.outside_critical == chi2.isf(b_method_alpha(rep.lambda0, 0.8, 3), 3))


def test_snooping_does_not_readmit_a_gross_error(rng):
    """With re-admission on, the removed gross error fails the outside test and stays out."""
    prob = make_problem(rng, 'se3', n=14, noise=1.0, gaps=(1, 2, 3))
    c = prob.network.arrays()
    z = c.z.copy()
    z[17, :3] += np.array([0.6, -0.4, 0.3])
    net = ConnectionNetwork.from_arrays(prob.network.node_ids, prob.network.track_ids, c.src,
                                        c.dst, z, c.cov)
    strict = QualityConfig(snoop_test='w', alpha0=1e-4)
    out = data_snooping(net, initial_guess_f2f(net), config=strict, readmit=True)
    assert out.removed.tolist() == [17]
    chk = quality_control(out.network, out.result, config=strict, outside=ConnectionArrays(
        c.src[[17]], c.dst[[17]], z[[17]], c.cov[[17]]))
    assert chk.outside_statistic[0] > 5 * chk.outside_critical[0]


def test_a_datum_prior_counts_by_the_equations_left_to_it(rng):
    """A weak datum prior (``GaussianPrior(weak=True)``, the gauge of ``datum='fixes'``) beside
    a prior that determines the datum: the solver's and the quality control's redundancy is
    ``r - u`` less the datum prior's redundancy number ``6 - tr(Q_00 H)``, ``Q`` from the dense
    inverse of the normal matrix."""
    net, T_true = correlated_problem(rng, 'se3')
    cov0 = np.diag([0.02, 0.02, 0.02, 0.005, 0.005, 0.005]) ** 2
    strong = GaussianPrior.from_covariances(net.node_ids[[4]], T_true[[4]], cov0[None])
    H_w = np.diag([1 / 30.0 ** 2] * 3 + [1 / 0.3 ** 2] * 3)
    weak = GaussianPrior(net.node_ids[[0]], T_true[[0]], H_w, weak=True)
    res = solve(net, initial_guess_f2f(net), SolverConfig(model='se3'), priors=[strong, weak])
    plain = solve(net, initial_guess_f2f(net), SolverConfig(model='se3'),
                  priors=[strong, GaussianPrior(weak.node_ids, weak.T_world_node, H_w)])
    Q = np.linalg.inv(res.normal_matrix.toarray())
    c = 6 * int(np.nonzero(res.free_node_ids == net.node_ids[0])[0][0])
    r_weak = 6 - np.trace(Q[c:c + 6, c:c + 6] @ H_w)
    assert 5.0 < r_weak < 6.0  # the strong prior holds the datum: the weak one is all residual
    np.testing.assert_allclose(res.redundancy, plain.redundancy - r_weak, atol=1e-8)
    np.testing.assert_allclose(res.sigma0_sq, res.cost / res.redundancy, rtol=1e-12)
    rep = quality_control(net, res, priors=[strong, weak])
    np.testing.assert_allclose(rep.redundancy, res.redundancy, atol=1e-12)
