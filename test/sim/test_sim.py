"""Tests of the paper's simulators: geometry, connection rule, noise model, files written."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ga_ros.cli.main import main
from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb
from ga_ros.sim.scenario import footprint_overlap, overlap_pairs
from ga_ros.sim.trajectories import SYNTHETIC_TRAJECTORIES, synthetic_scenario


def _brute_force_pairs(xy, L, thr):
    """All pairs by explicit interval intersection of the two squares, O(n^2)."""
    out = set()
    n = len(xy)
    for i in range(n):
        for j in range(i + 1, n):
            ix = max(0.0, min(xy[i, 0], xy[j, 0]) + L / 2 - (max(xy[i, 0], xy[j, 0]) - L / 2))
            iy = max(0.0, min(xy[i, 1], xy[j, 1]) + L / 2 - (max(xy[i, 1], xy[j, 1]) - L / 2))
            if ix * iy / (L * L) >= thr - 1e-9 or j == i + 1:
                out.add((i, j))
    return out


def test_overlap_formula_matches_interval_intersection(rng):
    d = rng.uniform(-120, 120, size=(200, 2))
    L = 100.0
    ix = np.clip(L - np.abs(d[:, 0]), 0, None)
    iy = np.clip(L - np.abs(d[:, 1]), 0, None)
    np.testing.assert_allclose(footprint_overlap(d, L), ix * iy / L**2, atol=1e-12)


def test_connections_equal_brute_force_on_small_aerial_and_random_points(rng):
    sc = aerial_scenario(n_tracks=2, positions_per_swath=15)
    got = set(map(tuple, np.stack([sc.src, sc.dst], 1).tolist()))
    assert got == _brute_force_pairs(sc.positions[:, :2], 100.0, 0.7)
    xy = rng.uniform(0, 300, size=(120, 2))
    got = set(map(tuple, overlap_pairs(xy, 100.0, 0.7).tolist()))
    assert got == _brute_force_pairs(xy, 100.0, 0.7)


def test_aerial_geometry_matches_the_paper():
    sc = aerial_scenario()
    assert sc.n_nodes == 25 * 204 and sc.n_tracks == 25
    assert np.all(np.bincount(sc.track_ids) == 204)
    assert np.all(np.diff(sc.track_ids) >= 0)
    steps = np.linalg.norm(np.diff(sc.positions, axis=0), axis=1)
    turns = np.arange(101, sc.n_nodes - 1, 102)  # last node of each swath
    np.testing.assert_allclose(np.delete(steps, turns), 10.0)
    np.testing.assert_allclose(steps[turns], 20.0)
    np.testing.assert_allclose(sc.positions[:, 2], 110.0)
    assert np.ptp(sc.positions[:, 0]) == pytest.approx(1010.0)
    assert np.ptp(sc.positions[:, 1]) == pytest.approx(49 * 20.0)
    assert 15_000 <= sc.n_connections <= 31_000
    assert np.all(sc.src < sc.dst)
    ov = footprint_overlap(sc.positions[sc.dst, :2] - sc.positions[sc.src, :2], 100.0)
    assert np.all(ov >= 0.7 - 1e-9)
    # acquisition order: sorted by dst, then src
    assert np.all(np.diff(sc.dst) >= 0)
    assert sc.chain.shape == (sc.n_nodes - 1,)


@pytest.mark.parametrize('model', ['se3', 'paper', 'linear'])
def test_true_motions_reproduce_the_poses(model, rng):
    sc = synthetic_scenario('looping_closed')
    # random true rotations so the se3/paper conventions are exercised
    R = so3.exp(rng.normal(scale=0.3, size=(sc.n_nodes, 3)))
    T = se3.from_rt(R, sc.positions)
    sc = type(sc)(sc.name, T, sc.track_ids, sc.src, sc.dst, sc.footprint_m, sc.depth_m)
    z = sc.true_motions(model)
    Ti, Tj = T[sc.src], T[sc.dst]
    if model == 'se3':
        T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
        np.testing.assert_allclose(Ti @ T_meas, Tj, atol=1e-9)
        np.testing.assert_allclose(sc.f2f(z), T, atol=1e-8)
    else:
        Rw = so3.exp(z[:, 3:])
        pj = (Rw @ Ti[:, :3, 3, None])[:, :, 0] + z[:, :3]
        np.testing.assert_allclose(pj, Tj[:, :3, 3], atol=1e-8)
        if model == 'paper':
            np.testing.assert_allclose(Rw, Tj[:, :3, :3] @ np.swapaxes(Ti[:, :3, :3], 1, 2),
                                       atol=1e-9)
            np.testing.assert_allclose(sc.f2f_positions(z, 'paper'), sc.positions, atol=1e-7)


def test_noise_sigmas_and_empirical_covariance(rng):
    z = np.array([[10.0, 0, 0, 0, 0, 0], [0, 20.0, 0, 0.5, 0, 0]])
    nm = NoiseModel(10.0, depth_m=100.0)
    s = nm.sigmas(z)
    np.testing.assert_allclose(s[0], [1, 1, 1, 0.01, 0.01, 0.01])
    np.testing.assert_allclose(s[1], [2, 2, 2, 0.05, 0.05, 0.05])
    zt = np.repeat(z[:1], 20000, axis=0)
    out = perturb(zt, nm, rng)
    xi = se3.log(se3.inverse(se3.from_translation_rotvec(zt[:, :3], zt[:, 3:]))
                 @ se3.from_translation_rotvec(out.z[:, :3], out.z[:, 3:]))
    # standardised draws have identity covariance (sampling sd ~ 1/sqrt(20000) = 0.007)
    emp = np.cov((xi / s[0]).T)
    np.testing.assert_allclose(emp, np.eye(6), atol=0.04)
    np.testing.assert_allclose(out.cov[0], np.diag(s[0] ** 2))
    # seeded: same seed -> same draws
    a = perturb(z, nm, np.random.default_rng(5)).z
    b = perturb(z, nm, np.random.default_rng(5)).z
    np.testing.assert_array_equal(a, b)
    with pytest.raises(InputError):
        NoiseModel(-1.0)


def test_synthetic_trajectories_closed_vs_open():
    for name in SYNTHETIC_TRAJECTORIES:
        sc = synthetic_scenario(name)
        last = sc.n_nodes - 1
        to_first = set(sc.src[sc.dst == last].tolist())
        assert (0 in to_first) == name.endswith('closed'), name
        assert sc.n_tracks == (1 if name.startswith('lawnmower') else 2)
        # cross connections exist (the redundancy GA exploits)
        assert (~sc.consecutive).sum() > sc.n_nodes // 2
    lo = synthetic_scenario('looping_open')
    lm = synthetic_scenario('lawnmower_open')
    assert lo.n_connections / lo.n_nodes < lm.n_connections / lm.n_nodes


def test_first_tracks_and_measurements_order():
    sc = aerial_scenario(n_tracks=3, positions_per_swath=12)
    sub = sc.first_tracks(2)
    assert sub.n_nodes == 48 and sub.n_tracks == 2
    m = sub.n_connections
    np.testing.assert_array_equal(sc.src[:m], sub.src)  # a prefix of the connections
    z = sc.true_motions()
    meas = sc.measurements(z, NoiseModel(5).covariances(z))
    assert [(x.src_id, x.dst_id) for x in meas] == list(zip(sc.src.tolist(), sc.dst.tolist()))
    assert {x.kind for x in meas} == {'consecutive', 'cross'}
    with pytest.raises(InputError):
        sc.first_tracks(4)


def test_simulate_command_writes_readable_files(tmp_path, capsys):
    out = tmp_path / 'sim'
    assert main(['simulate', 'lawnmower_open', '--seed', '4', '--noise', '5',
                 '--out', str(out)]) == 0
    meta = json.loads((out / 'scenario.json').read_text())
    sc = synthetic_scenario('lawnmower_open')
    assert meta['nodes'] == sc.n_nodes and meta['connections'] == sc.n_connections
    tracks = np.loadtxt(out / 'tracks.csv', delimiter=',', skiprows=1, dtype=int)
    np.testing.assert_array_equal(tracks[:, 1], sc.track_ids)
    gt = np.loadtxt(out / 'ground_truth.tum')
    np.testing.assert_allclose(gt[:, 1:4], sc.positions, atol=1e-9)
    if meta['measurements'] == 'measurements.g2o':
        from ga_ros.io.g2o import read_g2o

        g = read_g2o(out / 'measurements.g2o')
        assert g.n_edges == sc.n_connections and g.fixed == (0,)
        # measured motions are the true ones plus noise of the stated size
        T_true = se3.relative(sc.T_world_node[g.edge_src], sc.T_world_node[g.edge_dst])
        xi = se3.log(se3.inverse(T_true) @ g.T_meas)
        sig = NoiseModel(5.0).sigmas(sc.true_motions())
        assert np.abs(xi / sig).max() < 6.0
        assert 0.8 < np.std(xi / sig) < 1.2
    assert main(['simulate', 'aerial', '--noise', '-3', '--out', str(tmp_path / 'x')]) == 1
    assert 'noise percent' in capsys.readouterr().err


def test_simulate_aerial_subset(tmp_path):
    out = tmp_path / 'aerial'
    assert main(['simulate', 'aerial', '--tracks', '2', '--seed', '1', '--out', str(out)]) == 0
    meta = json.loads((out / 'scenario.json').read_text())
    sc = aerial_scenario(n_tracks=2)
    assert (meta['nodes'], meta['connections'], meta['tracks']) == (408, sc.n_connections, 2)
    tracks = np.loadtxt(out / 'tracks.csv', delimiter=',', skiprows=1, dtype=int)
    np.testing.assert_array_equal(np.bincount(tracks[:, 1]), [204, 204])
