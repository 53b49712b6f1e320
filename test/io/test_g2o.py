"""g2o reading/writing, the independent cost evaluator, and batch solves of small public graphs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import connection_cost
from ga_ros.errors import FormatError
from ga_ros.geometry import se3
from ga_ros.io.g2o import (
    PoseGraph,
    edge_errors,
    graph_cost,
    read_g2o,
    se2_to_se3,
    se3_to_se2,
    write_g2o,
)
from ga_ros.pipeline.pose_graph import GraphSolveConfig, solve_graph

# initial costs and GTSAM optima from shared/data/README.md
INITIAL = {'tinyGrid3D': 286.64, 'smallGrid3D': 167788.67, 'intel': 553.996}
OPTIMUM = {'tinyGrid3D': 18.6278, 'smallGrid3D': 1035.851, 'intel': 45.0042}

INFO3 = ' '.join(['100 0 0 0 0 0', '100 0 0 0 0', '100 0 0 0', '25 0 0', '25 0', '25'])
INFO2 = '100 0 0 100 0 400'


def _hat6(xi):
    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]]
    X[:3, 3] = xi[:3]
    return X


def _random_graph_3d(rng, n=12, extra=8, noise=0.05) -> tuple[PoseGraph, np.ndarray]:
    """A random 3-D graph written to g2o text and read back; returns graph and true poses."""
    T_true = np.stack([se3.exp(rng.normal(0, [2, 2, 2, 1, 1, 1])) for _ in range(n)])
    pairs = [(k, k + 1) for k in range(n - 1)]
    while len(pairs) < n - 1 + extra:
        i, j = rng.choice(n, 2, replace=False)
        if (i, j) not in pairs:
            pairs.append((int(i), int(j)))
    lines = []
    for k in range(n):
        p, q = se3.to_pos_quat(T_true[k] @ se3.exp(rng.normal(0, 0.2, 6)))
        lines.append(f'VERTEX_SE3:QUAT {k} {" ".join(map(str, p))} {" ".join(map(str, q))}')
    iu = np.triu_indices(6)
    for i, j in pairs:
        T = se3.relative(T_true[i], T_true[j]) @ se3.exp(rng.normal(0, noise, 6))
        p, q = se3.to_pos_quat(T)
        A = rng.normal(size=(6, 6))
        info = A @ A.T + 6 * np.eye(6)
        lines.append(f'EDGE_SE3:QUAT {i} {j} {" ".join(map(str, p))} {" ".join(map(str, q))} '
                     f'{" ".join(map(str, info[iu]))}')
    return lines, T_true


def _write(tmp_path, lines, name='g.g2o'):
    path = tmp_path / name
    path.write_text('\n'.join(lines) + '\n')
    return path


# ------------------------------------------------------------------------------ real files
def test_initial_costs_match_reference(pose_graph_dir):
    for name, ref in INITIAL.items():
        g = read_g2o(pose_graph_dir / f'{name}.g2o')
        assert graph_cost(g, g.T_init) == pytest.approx(ref, rel=2e-5), name


def test_tiny_grid_contents(pose_graph_dir):
    g = read_g2o(pose_graph_dir / 'tinyGrid3D.g2o')
    assert (g.dim, g.n_vertices, g.n_edges, g.fixed) == (3, 9, 11, ())
    np.testing.assert_array_equal(g.vertex_ids, np.arange(9))
    assert g.network.n_nodes == 9 and g.network.n_connections == 11
    # edge 0 -> 1 and its information from the file's first EDGE line
    np.testing.assert_allclose(g.T_meas[0, :3, 3], [1.033099, 0.093536, -0.037961])
    np.testing.assert_allclose(g.information[0], np.diag([100, 100, 100, 25, 25, 25]))
    np.testing.assert_allclose(g.network.arrays().cov[0], np.diag([.01, .01, .01, .04, .04, .04]))


@pytest.mark.parametrize('name', ['tinyGrid3D', 'smallGrid3D', 'intel'])
def test_batch_solve_reaches_reference_optimum(pose_graph_dir, name):
    g = read_g2o(pose_graph_dir / f'{name}.g2o')
    res = solve_graph(g, GraphSolveConfig())
    assert res.cost == pytest.approx(graph_cost(g, res.T_world_node))
    gap = (res.cost - OPTIMUM[name]) / OPTIMUM[name]
    assert abs(gap) < 1e-3, f'{name}: cost {res.cost} vs reference {OPTIMUM[name]}'
    # the datum (first vertex) did not move
    np.testing.assert_allclose(res.T_world_node[0], g.T_init[0], atol=1e-12)


# ---------------------------------------------------------------------------- cost checks
def test_cost_hand_computed_cases(tmp_path):
    # translation only: e = [0.1, 0, 0, 0, 0, 0], Omega_xx = 100 -> cost 1
    lines = ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1', 'VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1',
             f'EDGE_SE3:QUAT 0 1 0.9 0 0 0 0 0 1 {INFO3}']
    g = read_g2o(_write(tmp_path, lines))
    assert graph_cost(g, g.T_init) == pytest.approx(1.0, rel=1e-12)
    # rotation only about z: 0.3 rad vs measured 0.1 rad, Omega_rz = 25 -> 25 * 0.2^2 = 1
    q3 = Rotation.from_rotvec([0, 0, 0.3]).as_quat()
    q1 = Rotation.from_rotvec([0, 0, 0.1]).as_quat()
    lines = ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1',
             f'VERTEX_SE3:QUAT 1 0 0 0 {" ".join(map(str, q3))}',
             f'EDGE_SE3:QUAT 0 1 0 0 0 {" ".join(map(str, q1))} {INFO3}']
    g = read_g2o(_write(tmp_path, lines))
    assert graph_cost(g, g.T_init) == pytest.approx(1.0, rel=1e-9)
    # 2-D: vertex 1 at (1, 0, 0.5) against measured (1, 0, 0.5): zero; then theta off by 0.1
    lines = ['VERTEX_SE2 0 0 0 0', 'VERTEX_SE2 1 1 0 0.6', f'EDGE_SE2 0 1 1 0 0.5 {INFO2}']
    g = read_g2o(_write(tmp_path, lines))
    # T_meas^-1 T_j = rotation of 0.1 about z after a zero translation: e = [0, 0, 0.1]
    assert graph_cost(g, g.T_init) == pytest.approx(400 * 0.01, rel=1e-9)


def test_cost_matches_matrix_logarithm_and_solver(tmp_path, rng):
    lines, T_true = _random_graph_3d(rng)
    g = read_g2o(_write(tmp_path, lines))
    T = g.T_init
    e = edge_errors(g, T)
    for k in range(g.n_edges):
        D = np.linalg.inv(g.T_meas[k]) @ np.linalg.inv(T[g.edge_src[k]]) @ T[g.edge_dst[k]]
        X = np.real(logm(D))
        xi = np.array([X[0, 3], X[1, 3], X[2, 3], X[2, 1], X[0, 2], X[1, 0]])
        np.testing.assert_allclose(expm(_hat6(xi)), D, atol=1e-9)
        np.testing.assert_allclose(e[k], xi, atol=1e-7)
    brute = sum(e[k] @ g.information[k] @ e[k] for k in range(g.n_edges))
    assert graph_cost(g, T) == pytest.approx(brute, rel=1e-12)
    assert graph_cost(g, T) == pytest.approx(connection_cost(g.network, T), rel=1e-8)


def test_2d_cost_matches_se2_logarithm_and_embedding(tmp_path, rng):
    n = 8
    v = rng.normal(0, [3, 3, 2], size=(n, 3))
    lines = [f'VERTEX_SE2 {k} {v[k, 0]} {v[k, 1]} {v[k, 2]}' for k in range(n)]
    for i, j in [(k, k + 1) for k in range(n - 1)] + [(0, 5), (2, 7), (6, 1)]:
        m = rng.normal(0, [2, 2, 1.5])
        A = rng.normal(size=(3, 3))
        info = A @ A.T + 3 * np.eye(3)
        lines.append(f'EDGE_SE2 {i} {j} {m[0]} {m[1]} {m[2]} '
                     f'{" ".join(map(str, info[np.triu_indices(3)]))}')
    g = read_g2o(_write(tmp_path, lines))
    assert g.dim == 2
    np.testing.assert_allclose(g.T_init[:, 2, 3], 0.0)

    def mat(x):
        c, s = np.cos(x[2]), np.sin(x[2])
        return np.array([[c, -s, x[0]], [s, c, x[1]], [0, 0, 1]])

    e = edge_errors(g, g.T_init)
    vm = se3_to_se2(g.T_meas)
    for k in range(g.n_edges):
        D = np.linalg.inv(mat(vm[k])) @ np.linalg.inv(mat(v[g.edge_src[k]])) @ mat(
            v[g.edge_dst[k]])
        X = np.real(logm(D))
        np.testing.assert_allclose(e[k], [X[0, 2], X[1, 2], X[1, 0]], atol=1e-8)
    # the SE(3) embedding (unit information off the plane) has exactly the 2-D cost
    assert graph_cost(g, g.T_init) == pytest.approx(connection_cost(g.network, g.T_init),
                                                    rel=1e-9)
    np.testing.assert_allclose(se3_to_se2(se2_to_se3(v)), np.column_stack(
        [v[:, :2], (v[:, 2] + np.pi) % (2 * np.pi) - np.pi]), atol=1e-12)


# ------------------------------------------------------------------------------ round trips
def test_write_read_round_trip_3d(tmp_path, rng):
    lines, _ = _random_graph_3d(rng)
    lines.append('FIX 3 0')
    g = read_g2o(_write(tmp_path, lines))
    assert g.fixed == (3, 0)
    T = g.T_init @ se3.exp(rng.normal(0, 0.1, (g.n_vertices, 6)))
    out = tmp_path / 'out.g2o'
    write_g2o(out, g, T)
    g2 = read_g2o(out)
    assert (g2.dim, g2.fixed) == (3, (3, 0))
    np.testing.assert_array_equal(g2.vertex_ids, g.vertex_ids)
    np.testing.assert_allclose(g2.T_init, T, atol=1e-12)
    np.testing.assert_allclose(g2.T_meas, g.T_meas, atol=1e-12)
    np.testing.assert_allclose(g2.information, g.information, rtol=1e-14)
    assert graph_cost(g2, g2.T_init) == pytest.approx(graph_cost(g, T), rel=1e-10)


def test_edges_written_as_read_equal_the_ones_formatted_from_the_arrays(tmp_path, rng):
    """write_g2o writes a read graph's edge records back as read (PoseGraph.edge_lines): the
    same values bit for bit, irregular spacing normalised, offsets and their parameter ids
    kept; formatting the edges from the arrays (edge_lines None) gives the same graph."""
    import dataclasses

    lines, _ = _random_graph_3d(rng, n=6, extra=3)
    lines = ['PARAMS_SE3OFFSET 4 0.1 0 0 0 0 0.0499791692706783 0.998750260394966',
             *lines[:6], *[ln.replace(' ', '   ', 2) for ln in lines[6:8]],
             *(ln.replace(' ', ' 4 ', 3).replace(' 4 ', ' ', 2) for ln in lines[8:])]
    g = read_g2o(_write(tmp_path, lines))
    assert g.edge_param is not None and (g.edge_param == 4).sum() == len(lines) - 9
    written = {}
    for how, graph in (('read', g), ('arrays', dataclasses.replace(g, edge_lines=None))):
        write_g2o(tmp_path / f'{how}.g2o', graph)
        written[how] = read_g2o(tmp_path / f'{how}.g2o')
    text = (tmp_path / 'read.g2o').read_text().splitlines()
    assert [ln for ln in text if ln.startswith('EDGE')] == [' '.join(ln.split())
                                                         for ln in lines[7:]]
    plain = g.edge_param < 0  # the others through the offset, which is written formatted
    np.testing.assert_array_equal(written['read'].T_meas[plain], g.T_meas[plain])
    np.testing.assert_array_equal(written['read'].information[plain], g.information[plain])
    np.testing.assert_allclose(written['read'].T_meas, g.T_meas, atol=1e-14)
    np.testing.assert_allclose(written['arrays'].T_meas, g.T_meas, atol=1e-12)
    np.testing.assert_allclose(written['arrays'].information, g.information, rtol=1e-12)
    np.testing.assert_array_equal(written['arrays'].edge_param, g.edge_param)


def test_changed_edges_are_written_from_the_arrays(tmp_path, rng):
    """The edge records read are written back only for the very arrays read with them: a graph
    with another information (dataclasses.replace) or one edited in place is written from its
    arrays, and the read ids, ends and motions cannot be edited in place."""
    import dataclasses

    lines, _ = _random_graph_3d(rng, n=6, extra=3)
    g = read_g2o(_write(tmp_path, lines))
    assert g.edges_as_read() and g.with_initial_guess(g.T_init).edges_as_read()
    for a in (g.vertex_ids, g.edge_src, g.edge_dst, g.T_meas):
        with pytest.raises(ValueError):
            a[0] = a[1]
    doubled = dataclasses.replace(g, information=2 * g.information)
    edited = read_g2o(tmp_path / 'g.g2o')
    edited.information[2] *= 3.0
    for name, graph, want in (('doubled', doubled, 2 * g.information),
                              ('edited', edited, edited.information)):
        assert not graph.edges_as_read()
        write_g2o(tmp_path / f'{name}.g2o', graph)
        np.testing.assert_allclose(read_g2o(tmp_path / f'{name}.g2o').information, want,
                                   rtol=1e-12)


def test_ill_conditioned_information_is_refused_with_its_line(tmp_path):
    """An information matrix so ill-conditioned that its covariance is not positive definite
    (the network's rule) is refused naming its file and line, strict or not."""
    # ones(6, 6) + 3e-12 I: positive definite by the information's own rule (smallest
    # eigenvalue 3e-12 above 1e-12 of the largest entry), but its inverse's smallest eigenvalue
    # 1 / 6 is below 1e-12 of the inverse's largest entry (~1 / 3e-12)
    info = ' '.join(' '.join(['1.000000000003'] + ['1'] * (5 - r)) for r in range(6))
    lines = ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1', 'VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1',
             f'EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO3}',
             f'EDGE_SE3:QUAT 1 0 -1 0 0 0 0 0 1 {info}']
    for strict in (False, True):
        with pytest.raises(FormatError, match=r'g\.g2o:4.*ill-conditioned'):
            read_g2o(_write(tmp_path, lines), strict=strict)


def test_repaired_edges_are_written_from_the_arrays(tmp_path):
    """An edge whose information was repaired is written repaired (no verbatim edge lines)."""
    bad = '1 0 0 -1 0 1'  # indefinite
    lines = ['VERTEX_SE2 0 0 0 0', 'VERTEX_SE2 1 1 0 0', f'EDGE_SE2 0 1 1 0 0 {bad}']
    with pytest.warns(UserWarning):
        g = read_g2o(_write(tmp_path, lines))
    assert g.edge_lines is None
    write_g2o(tmp_path / 'out.g2o', g)
    np.testing.assert_allclose(read_g2o(tmp_path / 'out.g2o').information, g.information,
                               rtol=1e-12)


def test_write_read_round_trip_2d(tmp_path):
    lines = ['VERTEX_SE2 5 0 0 0', 'VERTEX_SE2 7 1 0.5 3.0', 'VERTEX_SE2 9 2 1 -3.1',
             f'EDGE_SE2 5 7 1 0.4 2.9 {INFO2}', f'EDGE_SE2 7 9 1 0.5 0.2 {INFO2}',
             f'EDGE_SE2 9 5 -2 0 3.1 {INFO2}']
    g = read_g2o(_write(tmp_path, lines))
    out = tmp_path / 'out.g2o'
    write_g2o(out, g)
    text = out.read_text()
    assert 'VERTEX_SE2 7 1.0 0.5 3.0' in text and 'SE3' not in text
    g2 = read_g2o(out)
    np.testing.assert_allclose(g2.T_init, g.T_init, atol=1e-12)
    np.testing.assert_allclose(g2.information, g.information)


def test_export_network(tmp_path, rng):
    net = ConnectionNetwork()
    for k in (10, 11, 12):
        net.add_node(k, 0)
    cov = np.diag([0.01, 0.02, 0.03, 0.001, 0.002, 0.003])
    net.add_connection(10, 11, [1, 0, 0, 0, 0, 0.1], cov)
    net.add_connection(11, 12, [1, 0.1, 0, 0.05, 0, 0.1], cov)
    T = se3.exp(rng.normal(0, 1, (3, 6)))
    out = tmp_path / 'net.g2o'
    write_g2o(out, PoseGraph.from_network(net, T, fixed=(10,)))
    g = read_g2o(out)
    np.testing.assert_allclose(g.network.arrays().z, net.arrays().z, atol=1e-12)
    np.testing.assert_allclose(g.network.arrays().cov, net.arrays().cov, rtol=1e-9)
    assert graph_cost(g, T) == pytest.approx(connection_cost(net, T), rel=1e-9)


# ------------------------------------------------------------------------------- bad input
GOOD3 = ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1', 'VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1',
         f'EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO3}']


@pytest.mark.parametrize('bad, line, words', [
    ('VERTEX_SE3:QUAT 2 1 0 0 0 0 1', 3, 'fields'),
    ('VERTEX_SE3:QUAT 2 1 0 zero 0 0 0 1', 3, 'non-numeric'),
    ('VERTEX_SE3:QUAT 2 1 0 nan 0 0 0 1', 3, 'NaN'),
    ('VERTEX_SE3:QUAT x 1 0 0 0 0 0 1', 3, 'vertex id'),
    ('VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1', 3, 'already defined on line 2'),
    ('VERTEX_SE3:QUAT 2 1 0 0 0 0 0 3', 3, 'quaternion'),
    ('VERTEX_XYZ 2 1 0 0', 3, 'unknown tag'),
    ('VERTEX_SE2 2 1 0 0', 3, 'mixed'),
    ('EDGE_SE3:QUAT 0 5 1 0 0 0 0 0 1 ' + INFO3, 3, 'vertex 5'),
    ('EDGE_SE3:QUAT 1 1 1 0 0 0 0 0 1 ' + INFO3, 3, 'itself'),
    ('EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 ' + INFO3.replace('25 0 0', '-25 0 0'), 3,
     'positive definite'),
    ('EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 ' + INFO3.replace('100 0 0 0 0 0', '100 200 0 0 0 0', 1),
     3, 'positive definite'),
    ('EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 ' + ' '.join(INFO3.split()[:-1]), 3, 'fields'),
    ('FIX 9', 3, 'FIX'),
])
def test_malformed_line_is_reported_with_file_and_line(tmp_path, bad, line, words):
    path = _write(tmp_path, GOOD3[:2] + [bad] + GOOD3[2:])
    with pytest.raises(FormatError) as info:
        read_g2o(path, strict=True)
    assert info.value.path == str(path) and info.value.line == line
    assert f'{path}:{line}:' in str(info.value) and words in str(info.value)


def test_bad_line_late_in_file_stops_everything(tmp_path):
    # a good prefix is never returned: the error is at the very end
    path = _write(tmp_path, GOOD3 + ['EDGE_SE3:QUAT 1 0 1 0 0 0 0 0 1 ' + INFO3 + ' 7'])
    with pytest.raises(FormatError, match=r':4: '):
        read_g2o(path)


def test_edge_before_its_vertex_is_fine_and_empty_file_is_not(tmp_path):
    g = read_g2o(_write(tmp_path, [GOOD3[2], '# comment', '', GOOD3[0], GOOD3[1]]))
    assert g.n_vertices == 2 and g.n_edges == 1
    with pytest.raises(FormatError, match='no vertices'):
        read_g2o(_write(tmp_path, ['# nothing']))
    with pytest.raises(FormatError, match='cannot read'):
        read_g2o(tmp_path / 'missing.g2o')


def test_fix_lines_set_the_datum(tmp_path, pose_graph_dir):
    lines = (pose_graph_dir / 'tinyGrid3D.g2o').read_text().splitlines() + ['FIX 4']
    g = read_g2o(_write(tmp_path, lines))
    assert g.fixed == (4,)
    res = solve_graph(g)
    np.testing.assert_allclose(res.T_world_node[4], g.T_init[4], atol=1e-12)
    assert np.abs(res.T_world_node[0] - g.T_init[0]).max() > 1e-3
    assert res.cost == pytest.approx(OPTIMUM['tinyGrid3D'], rel=1e-3)  # gauge-free optimum


def test_2d_solve_with_the_files_information_as_weights(tmp_path, rng):
    """A 2-D graph solved with its file's 3x3 information as the weights (what solve_graph
    passes) reaches the solve that inverts the covariances back; a wrong shape is refused."""
    from ga_ros.core.solver import solve
    from ga_ros.errors import InputError

    n = 30
    lines = [f'VERTEX_SE2 {k} {np.cos(k / 5) * 5 + rng.normal(0, 0.1):.6f} '
             f'{np.sin(k / 5) * 5 + rng.normal(0, 0.1):.6f} {k / 5 + 1.6:.6f}' for k in range(n)]
    lines += [f'EDGE_SE2 {k} {(k + 1) % n} {2 * 5 * np.sin(0.1):.6f} 0 0.2 100 10 0 200 0 900'
              for k in range(n)]
    g = read_g2o(_write(tmp_path, lines))
    cfg = GraphSolveConfig().solver_config(dim=2)
    given = solve(g.network, g.T_init, cfg, weights=g.information)
    inverted = solve(g.network, g.T_init, cfg)
    assert given.iterations == inverted.iterations
    np.testing.assert_allclose(given.T_world_node, inverted.T_world_node, rtol=0, atol=1e-9)
    assert given.cost == pytest.approx(inverted.cost, rel=1e-9)
    with pytest.raises(InputError, match=r'\(30, 3, 3\) for the se2 model'):
        solve(g.network, g.T_init, cfg, weights=np.broadcast_to(np.eye(6), (n, 6, 6)))
