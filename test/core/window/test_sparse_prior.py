"""The block-banded joint prior of frozen boundary nodes (``AlignerConfig.prior_band``).

Checked against dense computations: the band of ``N^-1`` by selected inversion against a dense
inverse, the maximum-entropy completion against the dense covariance it completes, the aligner's
sparse priors against the dense (exact Schur complement) ones, a persistence round trip, and
``freeze.marginal_prior`` (the one rule of the freeze and the refinement) on every path
against the dense Schur complement.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from ga_ros.core.linalg.banded import banded_selection
from ga_ros.core.linalg.completion import (
    CovarianceSkeleton,
    band_information,
    dense_band,
    skeleton_layout,
)
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner
from ga_ros.core.window import freeze as refinement
from ga_ros.core.window.freeze import band_prior, marginal_prior, tangent_prior
from ga_ros.core.window.persistence import load_state, save_state
from ga_ros.core.window.refinement import absorbed_priors
from ga_ros.errors import DegenerateGeometryError, InputError
from ga_ros.geometry import se3
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

D = 6


def _strip_matrix(rng, u: int, reach: int) -> np.ndarray:
    """A random SPD matrix of ``u`` 6x6 node blocks coupled up to ``reach`` nodes apart (a
    strip), with its nodes shuffled (so the selection has to find the band ordering)."""
    M = np.zeros((u * D, u * D))
    for i in range(u):
        for j in range(i, min(u, i + reach + 1)):
            B = rng.normal(size=(D, D)) * 0.3
            if i == j:
                B = B @ B.T + 5.0 * np.eye(D)
            M[i * D:(i + 1) * D, j * D:(j + 1) * D] = B
            M[j * D:(j + 1) * D, i * D:(i + 1) * D] = B.T
    M += max(0.0, 1.0 - np.linalg.eigvalsh(M).min()) * np.eye(u * D)  # positive definite
    perm = rng.permutation(u)
    P = (perm[:, None] * D + np.arange(D)).ravel()
    return M[np.ix_(P, P)]


def _scalar(nodes: np.ndarray) -> np.ndarray:
    return (np.asarray(nodes)[:, None] * D + np.arange(D)).ravel()


@pytest.mark.parametrize('w', [0, 1, 3])
def test_banded_selection_equals_the_dense_inverse_on_the_band(w):
    rng = np.random.default_rng(11)
    M = _strip_matrix(rng, 50, reach=2)
    targets = np.sort(rng.permutation(50)[:30])
    rhs = rng.normal(size=(50 * D, 2))
    sel = banded_selection(sp.csr_matrix(M), D, targets, w, rhs=rhs)
    Sigma = np.linalg.inv(M)
    ref = dense_band(Sigma[np.ix_(_scalar(targets), _scalar(targets))], D, w)
    np.testing.assert_allclose(sel.band, ref, rtol=0, atol=1e-12 * np.abs(Sigma).max())
    np.testing.assert_allclose(sel.solution, np.linalg.solve(M, rhs), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize('compiled', [True, False])
@pytest.mark.parametrize(('w', 'hubs'), [(0, 0), (2, 3), (5, 4)])
def test_sparse_skeleton_equals_the_dense_inverse_on_the_skeleton(w, hubs, compiled,
                                                                  monkeypatch):
    """Both ways to the skeleton (selected inversion on the sparse factor with the skeleton's
    pairs added to its pattern; the banded selection with hub columns by solves) against the
    dense inverse, the step ``N^-1 rhs`` against a dense solve."""
    from ga_ros.core.linalg import selinv, skeleton

    if compiled and not selinv.COMPILED:
        pytest.skip('numba is not installed')
    monkeypatch.setattr(selinv, 'COMPILED', compiled)
    rng = np.random.default_rng(12)
    M = _strip_matrix(rng, 40, reach=2)
    targets = rng.permutation(40)[:25]
    rhs = rng.normal(size=40 * D)
    skel, x = skeleton.sparse_skeleton(sp.csr_matrix(M), D, targets, w, hubs, rhs=rhs)
    Sigma = np.linalg.inv(M)
    ref = CovarianceSkeleton.of_dense(Sigma[np.ix_(_scalar(targets), _scalar(targets))], D, w,
                                      hubs)
    atol = 1e-12 * np.abs(Sigma).max()
    np.testing.assert_array_equal(skel.rest, ref.rest)
    np.testing.assert_array_equal(skel.hubs, ref.hubs)
    for name in ('band', 'cross', 'hub_cov'):
        np.testing.assert_allclose(getattr(skel, name), getattr(ref, name), rtol=0, atol=atol)
    np.testing.assert_allclose(x, np.linalg.solve(M, rhs), rtol=1e-10, atol=1e-12)


def test_sparse_skeleton_of_a_repeated_pattern_reuses_its_plan(monkeypatch):
    """A freeze's absorbed terms repeat their pattern every track: the second skeleton of the
    same pattern (other values) reuses the kept pattern, symbolic analysis and entry positions
    (:class:`skeleton._SkeletonPlan`) and still equals the dense inverse, bit for bit the skeleton
    computed without the kept plan, from CSR and from CSC input."""
    from ga_ros.core.linalg import selinv, skeleton

    if not selinv.COMPILED:
        pytest.skip('numba is not installed')
    rng = np.random.default_rng(13)
    M1 = sp.csr_matrix(_strip_matrix(rng, 40, reach=2))
    scale = sp.diags(rng.uniform(0.5, 2.0, size=40 * D))
    M2 = sp.csr_matrix(scale @ M1 @ scale)  # other values (positive definite), same pattern
    targets = np.sort(rng.permutation(40)[:25])
    rhs = rng.normal(size=40 * D)
    assert np.array_equal(M1.indptr, M2.indptr) and np.array_equal(M1.indices, M2.indices)
    monkeypatch.setattr(skeleton, '_PLANS', type(skeleton._PLANS)())
    for fmt in ('csr', 'csc'):
        for M in (M1, M2, M2):
            N = M.asformat(fmt)
            kept = skeleton.sparse_skeleton(N, D, targets, 3, 4, rhs=rhs)
            skeleton._PLANS.clear()  # a fresh plan: pattern, analysis, positions built anew
            fresh = skeleton.sparse_skeleton(N, D, targets, 3, 4, rhs=rhs)
            for name in ('band', 'cross', 'hub_cov'):
                np.testing.assert_array_equal(getattr(kept[0], name), getattr(fresh[0], name))
            np.testing.assert_array_equal(kept[1], fresh[1])
            Sigma = np.linalg.inv(M.toarray())
            ref = CovarianceSkeleton.of_dense(Sigma[np.ix_(_scalar(targets), _scalar(targets))],
                                              D, 3, 4)
            for name in ('band', 'cross', 'hub_cov'):
                np.testing.assert_allclose(getattr(kept[0], name), getattr(ref, name), rtol=0,
                                           atol=1e-12 * np.abs(Sigma).max())
        plan, = skeleton._PLANS.values()
        assert plan.kept is not None  # the analysis and positions were kept for the next


def test_banded_selection_refuses_a_singular_matrix():
    from ga_ros.errors import DegenerateGeometryError

    M = np.zeros((3 * D, 3 * D))
    M[:D, :D] = np.eye(D)
    with pytest.raises(DegenerateGeometryError):
        banded_selection(sp.csr_matrix(M), D, np.arange(3), 1)


@pytest.fixture(params=[True, False], ids=['compiled', 'python'])
def separators(request, monkeypatch):
    """The band completion's separator solves compiled (LAPACK called from the kernel) and
    without the kernels (SciPy's LAPACK in a loop)."""
    from ga_ros.core.linalg import lapack

    if request.param and not lapack.COMPILED:
        pytest.skip('numba is not installed')
    monkeypatch.setattr(lapack, 'COMPILED', request.param)
    return request.param


@pytest.mark.parametrize(('w', 'hubs'), [(0, 0), (1, 0), (2, 0), (4, 0), (1, 3), (0, 4)])
def test_completion_keeps_the_skeleton_of_the_covariance(w, hubs, separators):
    """Dempster's maximum-entropy completion: ``K`` is zero off the skeleton (band + hub rows),
    positive definite, and ``K^-1`` equals ``Sigma`` on the skeleton (not off it)."""
    rng = np.random.default_rng(3)
    m = 16
    Sigma = np.linalg.inv(_strip_matrix(rng, m, reach=m))  # a dense covariance
    skel = CovarianceSkeleton.of_dense(Sigma, D, w, hubs)
    K = skel.information() if hubs else band_information(dense_band(Sigma, D, w))
    assert sp.issparse(K)
    Kd = K.toarray()
    rest, hub = skeleton_layout(m, w, hubs)
    assert hub.size == hubs
    pos = np.full(m, -10 * m)
    pos[rest] = np.arange(rest.size)
    on = np.abs(np.subtract.outer(pos, pos)) <= w
    on[hub, :] = on[:, hub] = True
    far = np.kron(~on, np.ones((D, D)))
    assert np.abs(Kd[far > 0]).max(initial=0.0) == 0.0
    assert np.linalg.eigvalsh(Kd).min() > 0
    Ki = np.linalg.inv(Kd)
    scale = np.abs(Sigma).max()
    np.testing.assert_allclose(Ki[far == 0], Sigma[far == 0], rtol=0, atol=1e-10 * scale)
    assert np.abs(Ki - Sigma)[far > 0].max() > 1e-6 * scale  # an approximation off it
    # among all completions it has the largest entropy: the dense Sigma has a smaller det
    assert np.linalg.slogdet(Ki)[1] > np.linalg.slogdet(Sigma)[1]


def test_band_completion_with_the_full_width_is_the_exact_information(separators):
    rng = np.random.default_rng(4)
    m = 9
    Sigma = np.linalg.inv(_strip_matrix(rng, m, reach=m))
    K = band_information(dense_band(Sigma, D, m - 1)).toarray()
    Kref = np.linalg.inv(Sigma)
    np.testing.assert_allclose(K, Kref, rtol=0, atol=1e-9 * np.abs(Kref).max())


def test_band_prior_is_the_tangent_prior_of_the_completed_information():
    """The sparse prior keeps ``tangent_prior``'s mean handling: with the full width it equals
    the dense prior of the exact information and gradient."""
    rng = np.random.default_rng(5)
    m = 6
    H = _strip_matrix(rng, m, reach=m)
    g = rng.normal(size=m * D) * 0.5
    T = np.stack([np.eye(4)] * m)
    T[:, :3, 3] = rng.normal(size=(m, 3))
    mean_d, info_d = tangent_prior(T, H, g)
    Sigma = np.linalg.inv(H)
    mean_s, info_s = band_prior(T, CovarianceSkeleton.of_dense(Sigma, D, m - 3, 2), Sigma @ g)
    np.testing.assert_allclose(mean_s, mean_d, atol=1e-10)
    np.testing.assert_allclose(info_s.toarray(), info_d, rtol=0, atol=1e-8 * np.abs(info_d).max())


def _survey(n_tracks=5, per_swath=12, pct=3.0, seed=1):
    sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=per_swath)
    nm = perturb(sc.true_motions(), NoiseModel(pct, sc.depth_m), np.random.default_rng(seed))
    return sc, nm, sc.measurements(nm.z, nm.cov)


def _run(cfg, sc, ms):
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    al.add_measurements(ms)
    al.finish_track()
    return al


@pytest.mark.parametrize('policy', ['weighted', 'marginal'])
def test_sparse_prior_freeze_keeps_the_exact_marginals_of_the_boundary(policy, monkeypatch):
    """At the first freeze the sparse prior's covariance equals the exact (dense) one on the
    band, in particular every boundary node's marginal covariance, and its mean equals the
    dense prior's mean."""
    from ga_ros.core.window.freeze import FreezePolicy

    sc, _, ms = _survey()
    seen = {}
    orig = FreezePolicy.marginalise

    def once(self, state, L, priors, n, nc, band, hubs, terms=None):
        out = orig(self, state, L, priors, n, nc, band, hubs, terms)  # changes nothing
        if 'dense' not in seen:
            seen['dense'] = orig(self, state, L, priors, n, nc, -1, hubs, terms)[2]
            seen['sparse'] = out[2]
        return out

    monkeypatch.setattr(FreezePolicy, 'marginalise', once)
    w = 2
    _run(AlignerConfig(window_tracks=2, freeze_policy=policy, prior_band=w, prior_hubs=2,
                       refine_every_tracks=0), sc, ms)
    (i_d, m_d, H_d), (i_s, m_s, K_s) = seen['dense'], seen['sparse']
    assert np.array_equal(i_d, i_s) and i_s.size > w + 4
    assert sp.issparse(K_s) and not sp.issparse(H_d)
    np.testing.assert_allclose(m_s, m_d, atol=1e-9)
    _assert_same_skeleton(np.linalg.inv(K_s.toarray()), np.linalg.inv(H_d), w, 2)


def _assert_same_skeleton(Sigma_s, Sigma, w, hubs):
    a = CovarianceSkeleton.of_dense(Sigma_s, D, w, hubs)
    b = CovarianceSkeleton.of_dense(Sigma, D, w, hubs)
    tol = 1e-8 * np.abs(Sigma).max()
    for x, y in ((a.band, b.band), (a.cross, b.cross), (a.hub_cov, b.hub_cov)):
        np.testing.assert_allclose(x, y, rtol=0, atol=tol)


def test_sparse_prior_window_is_close_to_the_dense_one():
    """Same survey, sparse (w = 2, 3 hubs) and dense priors: the paths differ by a small fraction
    (< 0.1) of the batch standard deviation and the published variances by < 5 % (measured 0.02
    sd and 2 %): the sparse prior only drops the correlations between boundary nodes more than
    w apart beyond what the hubs carry. (Without hubs, w = 4 on the aerial survey gave window
    variances 22 % too small: the swath's common drift looked better known than it is.)"""
    sc, nm, ms = _survey(n_tracks=6, per_swath=16, pct=3.0, seed=2)
    cfg = AlignerConfig(window_tracks=2, refine_every_tracks=0)
    dense = _run(replace(cfg, prior_band=-1), sc, ms)
    sparse = _run(replace(cfg, prior_band=2, prior_hubs=3), sc, ms)
    assert any(sp.issparse(info) for _, _, info in sparse.state.priors)
    batch = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z), SolverConfig(tolerance=1e-10))
    ids = sc.node_ids[1:]
    sd = np.sqrt(np.diagonal(batch.covariance(ids), axis1=1, axis2=2))[:, :3]
    Td, Ts = dense.corrected_path().T_world_node[1:], sparse.corrected_path().T_world_node[1:]
    gap = np.abs(Ts[:, :3, 3] - Td[:, :3, 3]) / sd
    assert gap.max() < 0.1, gap.max()
    cd, cs = dense.covariances(ids), sparse.covariances(ids)
    ratio = np.diagonal(cs, axis1=1, axis2=2) / np.diagonal(cd, axis1=1, axis2=2)
    assert np.abs(ratio - 1.0).max() < 0.05, np.abs(ratio - 1.0).max()


def test_refinement_builds_its_priors_like_the_freeze():
    """One definition: the refinement's banded priors are the band completion of the exact
    (dense) marginal of the absorbed terms, with the dense prior's mean."""
    sc, _, ms = _survey(n_tracks=5, per_swath=12)
    al = _run(AlignerConfig(window_tracks=2, refine_every_tracks=0, prior_band=2, prior_hubs=2),
              sc, ms)
    snap = al.handoff.snapshot()
    assert (snap.prior_band, snap.prior_hubs) == (2, 2)
    n = len(al.state.ids)
    banded = absorbed_priors(snap, al.state.T[:n])
    dense = absorbed_priors(replace(snap, prior_band=-1), al.state.T[:n])
    assert len(banded) == len(dense) > 0
    for b, d in zip(banded, dense):
        assert np.array_equal(b.nodes, d.nodes) and sp.issparse(b.information)
        np.testing.assert_allclose(b.T_world_node, d.T_world_node, atol=1e-9)
        _assert_same_skeleton(np.linalg.inv(b.information.toarray()),
                              np.linalg.inv(d.information), 2, 2)


def test_sparse_priors_survive_a_save_and_restore(tmp_path):
    sc, _, ms = _survey(n_tracks=5, per_swath=12)
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 4) + 3
    cfg = AlignerConfig(window_tracks=2, refine_every_tracks=0, prior_band=2, prior_hubs=2,
                        solver=replace(ALIGNER_SOLVER, tolerance=1e-10))
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    al.add_measurements(ms[:cut])
    assert any(sp.issparse(info) for _, _, info in al.state.priors)
    save_state(al, tmp_path / 'state.bin')
    back = load_state(tmp_path / 'state.bin').aligner
    assert len(back.state.priors) == len(al.state.priors)
    for (i1, m1, h1), (i2, m2, h2) in zip(al.state.priors, back.state.priors):
        assert np.array_equal(i1, i2) and sp.issparse(h1) == sp.issparse(h2)
        np.testing.assert_array_equal(m1, m2)
        a1 = h1.toarray() if sp.issparse(h1) else h1
        a2 = h2.toarray() if sp.issparse(h2) else h2
        np.testing.assert_array_equal(a1, a2)
    for a in (al, back):
        a.add_measurements(ms[cut:])
        a.finish_track()
    np.testing.assert_allclose(back.corrected_path().T_world_node,
                               al.corrected_path().T_world_node, atol=1e-9)


def test_prior_band_must_be_minus_one_or_more():
    with pytest.raises(InputError, match='prior_band'):
        AlignerConfig(prior_band=-2)


def test_a_version_3_state_with_dense_priors_still_loads(tmp_path, monkeypatch):
    """Format 3 stored each prior's information as one dense matrix (``prior_info``)."""
    import ga_ros.core.window.persistence as persistence

    sc, _, ms = _survey(n_tracks=5, per_swath=12)
    al = _run(AlignerConfig(window_tracks=2, refine_every_tracks=0, prior_band=-1), sc, ms)
    assert al.state.priors and not any(sp.issparse(info) for _, _, info in al.state.priors)
    new_state = persistence._state_of

    def version_3(aligner):
        meta, arrays = new_state(aligner)
        for name in ('prior_nblocks', 'prior_brow', 'prior_bcol', 'prior_blocks'):
            del arrays[name]
        arrays['prior_info'] = np.concatenate([info.ravel()
                                               for _, _, info in aligner.state.priors])
        return meta, arrays

    monkeypatch.setattr(persistence, '_state_of', version_3)
    monkeypatch.setattr(persistence, 'FORMAT_VERSION', 3)
    save_state(al, tmp_path / 'v3.bin')
    monkeypatch.undo()
    saved = load_state(tmp_path / 'v3.bin')
    assert saved.version == 3
    for (i1, m1, h1), (i2, m2, h2) in zip(al.state.priors, saved.aligner.state.priors,
                                          strict=True):
        assert np.array_equal(i1, i2)
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(h1, h2)


def test_band_completion_refuses_a_skeleton_with_a_clique_not_positive_definite(rng,
                                                                                separators):
    """The completion is positive definite by construction (the freeze gives its prior full
    rank): a band whose cliques are all positive definite gives a positive definite ``K``; one
    node's block made indefinite, in the middle (the separators holding it indefinite too, but
    not singular) or at the end, and the completion refuses it, as a dense check of the
    cliques does."""
    from ga_ros.errors import DegenerateGeometryError

    m, d, w = 9, 3, 2
    A = rng.normal(size=(m * d, m * d))
    Sigma = A @ A.T + m * d * np.eye(m * d)
    band = dense_band(Sigma, d, w)
    K = band_information(band).toarray()
    assert np.linalg.eigvalsh(0.5 * (K + K.T)).min() > 0
    for node in (4, m - 1):
        bad = band.copy()
        bad[node, 0] = -np.eye(d)  # C_{node - w .. node} indefinite
        cliques = [_dense_clique(bad, k, w, d) for k in range(m - w)]
        assert min(np.linalg.eigvalsh(C).min() for C in cliques) < 0
        with pytest.raises(DegenerateGeometryError, match='clique'):
            band_information(bad)


def _dense_clique(band, k, w, d):
    """The dense covariance of the clique ``{k .. k + w}`` from a band."""
    C = np.zeros(((w + 1) * d, (w + 1) * d))
    for a in range(w + 1):
        for b in range(a, w + 1):
            C[a * d:(a + 1) * d, b * d:(b + 1) * d] = band[k + a, b - a]
            C[b * d:(b + 1) * d, a * d:(a + 1) * d] = band[k + a, b - a].T
    return C


# ------------------------------------------------ marginal_prior: the one rule, every path
def _schur(N: np.ndarray, u: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The dense Schur complement ``(H, g)`` of ``(N, u)`` onto the kept nodes."""
    cS = (np.nonzero(keep)[0][:, None] * D + np.arange(D)).ravel()
    cL = (np.nonzero(~keep)[0][:, None] * D + np.arange(D)).ravel()
    X = np.linalg.solve(N[np.ix_(cL, cL)], np.column_stack([N[np.ix_(cL, cS)], u[cL]]))
    H = N[np.ix_(cS, cS)] - N[np.ix_(cS, cL)] @ X[:, :-1]
    return 0.5 * (H + H.T), u[cS] - N[np.ix_(cS, cL)] @ X[:, -1]


@pytest.fixture
def problem():
    rng = np.random.default_rng(5)
    n = 60
    N = _strip_matrix(rng, n, reach=2)
    u = rng.normal(size=n * D)
    keep = np.zeros(n, dtype=bool)
    keep[rng.permutation(n)[:30]] = True
    T = se3.exp(rng.normal(size=(n, 6)) * [5, 5, 5, 0.3, 0.3, 0.3])
    return N, u, keep, T, np.arange(100, 100 + n)


@pytest.mark.parametrize('dense_max', [10**9, 0])  # eliminated by dense blocks / trailing_factor
def test_the_exact_prior_is_the_tangent_prior_of_the_dense_schur_complement(
        problem, dense_max, monkeypatch):
    N, u, keep, T, nodes = problem
    monkeypatch.setattr(refinement, 'DENSE_SCHUR_MAX', dense_max)
    H, g = _schur(N, u, keep)
    mean, info = tangent_prior(T[keep], H, g)
    p = marginal_prior(nodes, sp.csc_matrix(N), u, keep, T[keep], -1, 0)
    np.testing.assert_array_equal(p.nodes, nodes[keep])
    np.testing.assert_allclose(p.information, info, rtol=1e-8, atol=1e-10 * np.abs(info).max())
    np.testing.assert_allclose(p.T_world_node, mean, atol=1e-10)
    assert p.rank == (H.shape[0] if dense_max == 0 else None)


@pytest.mark.parametrize('dense_input', [False, True])
def test_the_sparse_prior_is_the_band_prior_of_the_dense_covariance_skeleton(problem,
                                                                             dense_input):
    """Sparse ``N`` (selected inversion) and dense ``N`` (Cholesky) give the band prior of the
    skeleton of ``H^-1`` and the step ``H^-1 g``; without a gradient its covariance agrees with
    ``H^-1`` on the skeleton."""
    N, u, keep, T, nodes = problem
    H, g = _schur(N, u, keep)
    Sigma = np.linalg.inv(H)
    w, hubs = 3, 2
    mean, info = band_prior(T[keep], CovarianceSkeleton.of_dense(Sigma, D, w, hubs), Sigma @ g)
    p = marginal_prior(nodes, N if dense_input else sp.csr_matrix(N), u, keep, T[keep], w, hubs,
                       coords=T[:, :3, 3])
    K = p.information.toarray()
    np.testing.assert_allclose(K, info.toarray(), rtol=1e-8, atol=1e-10 * np.abs(K).max())
    np.testing.assert_allclose(p.T_world_node, mean, atol=1e-10)
    assert p.rank == K.shape[0]
    # at the terms' optimum (no gradient, mean = T) the covariance of the prior is H^-1 on the
    # skeleton
    p0 = marginal_prior(nodes, N if dense_input else sp.csr_matrix(N), np.zeros_like(u), keep,
                        T[keep], w, hubs)
    np.testing.assert_allclose(p0.T_world_node, T[keep], atol=1e-12)
    m = keep.sum()
    Kinv = np.linalg.inv(p0.information.toarray()).reshape(m, D, m, D)
    S4 = Sigma.reshape(m, D, m, D)
    for i in range(m):  # each node's marginal and its band neighbours' correlations are exact
        for j in range(i, min(m, i + w + 1)):
            np.testing.assert_allclose(Kinv[i, :, j], S4[i, :, j], rtol=1e-7,
                                       atol=1e-9 * np.abs(S4).max())


def test_a_kept_part_left_free_falls_back_to_the_exact_singular_prior(problem):
    """Kept nodes the terms leave free in some direction (``N`` singular there): the sparse
    skeleton cannot be formed (``DegenerateGeometryError`` inside), the prior is the exact
    Schur complement, singular, rank unknown."""
    N, u, keep, T, nodes = problem
    k = np.nonzero(keep)[0][0]
    c = np.arange(k * D, (k + 1) * D)
    N = N.copy()
    N[c, :] = 0.0
    N[:, c] = 0.0  # node k: no information at all
    u = u.copy()
    u[c] = 0.0
    H, g = _schur(N, u, keep)
    mean, info = tangent_prior(T[keep], H, g)
    p = marginal_prior(nodes, sp.csr_matrix(N), u, keep, T[keep], 3, 2)
    assert not sp.issparse(p.information) and p.rank is None
    np.testing.assert_allclose(p.information, info, rtol=1e-8, atol=1e-10 * np.abs(info).max())


def test_undetermined_eliminated_nodes_are_a_degenerate_geometry_error(problem):
    N, u, keep, T, nodes = problem
    k = np.nonzero(~keep)[0][0]
    c = np.arange(k * D, (k + 1) * D)
    N = N.copy()
    N[c, :] = 0.0
    N[:, c] = 0.0
    with pytest.raises(DegenerateGeometryError, match='undetermined'):
        marginal_prior(nodes, sp.csr_matrix(N), u, keep, T[keep], -1, 0)
