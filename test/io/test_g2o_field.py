"""Pose graphs as exporters write them (issue 13): sensor-offset parameters, TORO, edge-only
files and initialisation, imperfect information matrices, optimum evidence, lossless round trip.

Every file is written by the test (or stripped from a shared dataset into ``tmp_path``)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from scipy.linalg import logm

from ga_ros.cli.main import main
from ga_ros.core.covariance import nearest_positive_definite, not_positive_definite
from ga_ros.core.initialization import PoseGraphEdges, chordal_initialization, initialize
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.g2o import (
    InformationRepairWarning,
    graph_cost,
    read_g2o,
    se2_to_se3,
    se3_to_se2,
    write_g2o,
)
from ga_ros.pipeline.pose_graph import (
    initial_guess,
    optimum_evidence,
    solve_graph,
)

IU6, IU3 = np.triu_indices(6), np.triu_indices(3)


def _write(tmp_path, lines, name='g.g2o'):
    path = tmp_path / name
    path.write_text('\n'.join(lines) + '\n')
    return path


def _f(values) -> str:
    return ' '.join(repr(float(v)) for v in np.ravel(values))


def _pq(T) -> str:
    p, q = se3.to_pos_quat(T)
    return f'{_f(p)} {_f(q)}'


def _info6(rng):
    A = rng.normal(size=(6, 6))
    return A @ A.T + 6 * np.eye(6)


def _log_twist(D) -> np.ndarray:
    """``[rho, phi]`` of a 4x4 motion by the matrix logarithm (independent of ga_ros)."""
    X = np.real(logm(D))
    return np.array([X[0, 3], X[1, 3], X[2, 3], X[2, 1], X[0, 2], X[1, 0]])


def _cli_json(capsys, *argv) -> dict:
    capsys.readouterr()
    assert main(['solve', *map(str, argv), '--json']) == 0
    return json.loads(capsys.readouterr().out)


# ------------------------------------------------------------------------- sensor offsets
def test_identity_offset_and_parameter_ids_read_as_a_plain_file(tmp_path, rng):
    T = se3.exp(rng.normal(0, 1, (3, 6)))
    info = _info6(rng)
    verts = [f'VERTEX_SE3:QUAT {k} {_pq(T[k])}' for k in range(3)]
    e01 = f'{_pq(se3.relative(T[0], T[1]))} {_f(info[IU6])}'
    e12 = f'{_pq(se3.relative(T[1], T[2]))} {_f(info[IU6])}'
    plain = read_g2o(_write(tmp_path, verts + [f'EDGE_SE3:QUAT 0 1 {e01}',
                                               f'EDGE_SE3:QUAT 1 2 {e12}'], 'a.g2o'))
    rtab = read_g2o(_write(tmp_path, ['PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1', *verts,
                                      f'EDGE_SE3:QUAT 0 1 0 {e01}', f'EDGE_SE3:QUAT 1 2 {e12}'],
                           'b.g2o'))
    np.testing.assert_array_equal(rtab.T_meas, plain.T_meas)
    np.testing.assert_array_equal(rtab.information, plain.information)
    assert rtab.edge_param.tolist() == [0, -1] and plain.edge_param is None
    out = tmp_path / 'c.g2o'
    write_g2o(out, rtab)
    text = out.read_text().splitlines()
    assert text[0].startswith('PARAMS_SE3OFFSET 0 ') and text[4].startswith('EDGE_SE3:QUAT 0 1 0 ')


@pytest.mark.parametrize('dim', [3, 2])
def test_non_identity_offset_gives_the_sensor_frame_cost(tmp_path, rng, dim):
    """An edge naming offset S measures Z = S^-1 Ti^-1 Tj S: the graph's cost at any poses must
    be sum e' Omega e with e = Log(Z^-1 S^-1 Xi^-1 Xj S), computed here by a matrix log."""
    n = 4
    if dim == 3:
        T = se3.exp(rng.normal(0, 1, (n, 6)))
        S = se3.exp(np.array([0.3, -0.2, 0.5, 0.2, -0.4, 0.7]))
        head = f'PARAMS_SE3OFFSET 7 {_pq(S)}'
        vert = [f'VERTEX_SE3:QUAT {k} {_pq(T[k])}' for k in range(n)]
    else:
        xyt = rng.normal(0, 1, (n, 3))
        T = se2_to_se3(xyt)
        s = np.array([0.3, -0.2, 0.7])
        S = se2_to_se3(s)
        head = f'PARAMS_SE2OFFSET 7 {_f(s)}'
        vert = [f'VERTEX_SE2 {k} {_f(xyt[k])}' for k in range(n)]
    pairs = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2)]
    Z, infos, edges = [], [], []
    for i, j in pairs:
        Zk = se3.inverse(S) @ se3.relative(T[i], T[j]) @ S @ se3.exp(rng.normal(0, 0.05, 6)
                                                                    * ([1] * 6 if dim == 3 else
                                                                       [1, 1, 0, 0, 0, 1]))
        if dim == 3:
            info = _info6(rng)
            edges.append(f'EDGE_SE3:QUAT {i} {j} 7 {_pq(Zk)} {_f(info[IU6])}')
        else:
            A = rng.normal(size=(3, 3))
            info = A @ A.T + 3 * np.eye(3)
            Zk = se2_to_se3(se3_to_se2(Zk))
            edges.append(f'EDGE_SE2 {i} {j} 7 {_f(se3_to_se2(Zk))} {_f(info[IU3])}')
        Z.append(Zk)
        infos.append(info)
    g = read_g2o(_write(tmp_path, [head, *vert, *edges]))
    X = T @ se3.exp(rng.normal(0, 0.1, (n, 6)) * ([1] * 6 if dim == 3 else [1, 1, 0, 0, 0, 1]))
    expected = 0.0
    ax = [0, 1, 5]
    for (i, j), Zk, info in zip(pairs, Z, infos):
        e = _log_twist(se3.inverse(Zk) @ se3.inverse(S) @ se3.relative(X[i], X[j]) @ S)
        e = e if dim == 3 else e[ax]
        expected += e @ info @ e
    assert graph_cost(g, X) == pytest.approx(expected, rel=1e-9)
    # written back in the sensor frame with the parameter: identical graph on reading again
    write_g2o(tmp_path / 'back.g2o', g)
    assert 'EDGE_SE' in (tmp_path / 'back.g2o').read_text()
    g2 = read_g2o(tmp_path / 'back.g2o')
    np.testing.assert_allclose(g2.T_meas, g.T_meas, atol=1e-12)
    np.testing.assert_allclose(g2.information, g.information, rtol=1e-10, atol=1e-9)
    assert g2.edge_param.tolist() == [7] * len(pairs)


def test_offset_problems_are_refused_with_their_line(tmp_path):
    base = ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1', 'VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1']
    info = _f(np.eye(6)[IU6])
    unused = ['PARAMS_SE3OFFSET 0 0.1 0 0 0 0 0 1', *base,
              f'EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {info}']
    with pytest.raises(FormatError, match=r':1: sensor offset 0 is not the identity'):
        read_g2o(_write(tmp_path, unused))
    undefined = [*base, f'EDGE_SE3:QUAT 0 1 3 1 0 0 0 0 0 1 {info}']
    with pytest.raises(FormatError, match=r':3: edge names parameter 3'):
        read_g2o(_write(tmp_path, undefined))
    duplicate = ['PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1', 'PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1', *base]
    with pytest.raises(FormatError, match=r':2: parameter 0 is already defined on line 1'):
        read_g2o(_write(tmp_path, duplicate))


# ------------------------------------------------------------------------------------ TORO
def test_toro_file_reads_as_the_same_g2o_graph_and_writes_back_as_toro(tmp_path, rng):
    n = 5
    xyt = rng.normal(0, 1, (n, 3))
    g2o_lines, toro_lines = [], []
    for k in range(n):
        g2o_lines.append(f'VERTEX_SE2 {k} {_f(xyt[k])}')
        toro_lines.append(f'VERTEX2 {k} {_f(xyt[k])}')
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0)]:
        meas = rng.normal(0, 1, 3)
        A = rng.normal(size=(3, 3))
        I = A @ A.T + np.eye(3)
        g2o_lines.append(f'EDGE_SE2 {i} {j} {_f(meas)} '
                         f'{_f([I[0, 0], I[0, 1], I[0, 2], I[1, 1], I[1, 2], I[2, 2]])}')
        # TORO: inf_ff inf_fs inf_ss inf_rr inf_fr inf_sr
        toro_lines.append(f'EDGE2 {i} {j} {_f(meas)} '
                          f'{_f([I[0, 0], I[0, 1], I[1, 1], I[2, 2], I[0, 2], I[1, 2]])}')
    a = read_g2o(_write(tmp_path, g2o_lines, 'a.g2o'))
    b = read_g2o(_write(tmp_path, toro_lines, 'b.graph'))
    np.testing.assert_array_equal(a.information, b.information)
    np.testing.assert_array_equal(a.T_meas, b.T_meas)
    assert (a.flavour, b.flavour) == ('g2o', 'toro')
    write_g2o(tmp_path / 'c.graph', b)
    text = (tmp_path / 'c.graph').read_text()
    assert 'EDGE2 ' in text and 'VERTEX2 ' in text and 'EDGE_SE2' not in text
    np.testing.assert_array_equal(read_g2o(tmp_path / 'c.graph').information, a.information)


# ------------------------------------------------------------------------ lossless round trip
def test_round_trip_is_lossless(tmp_path, rng):
    """g2o -> network -> g2o: ids, order, FIX, offsets and information come back bit for bit;
    motions through the rotation matrix to within rounding (1e-15)."""
    T = se3.exp(rng.normal(0, 1, (4, 6)))
    lines = ['# exported by a test', 'PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1']
    lines += [f'VERTEX_SE3:QUAT {k} {_pq(T[k])}' for k in (3, 1, 0, 2)]
    for i, j in [(3, 1), (1, 0), (0, 2), (2, 3)]:
        lines.append(f'EDGE_SE3:QUAT {i} {j} {_pq(se3.relative(T[i], T[j]))} '
                     f'{_f(_info6(rng)[IU6])}')
    lines += ['', 'FIX 1']
    g = read_g2o(_write(tmp_path, lines))
    write_g2o(tmp_path / 'one.g2o', g)
    g1 = read_g2o(tmp_path / 'one.g2o')
    write_g2o(tmp_path / 'two.g2o', g1)
    g2 = read_g2o(tmp_path / 'two.g2o')
    np.testing.assert_array_equal(g2.information, g.information)
    np.testing.assert_allclose(g2.T_init, g.T_init, atol=1e-15)
    X = se3.exp(rng.normal(0, 1, (4, 6)))
    assert graph_cost(g2, X) == pytest.approx(graph_cost(g, X), rel=1e-12)
    np.testing.assert_array_equal(g1.information, g.information)
    np.testing.assert_array_equal(g1.vertex_ids, [3, 1, 0, 2])
    assert g1.fixed == (1,) and g1.offsets.keys() == {0}
    np.testing.assert_allclose(g1.T_meas, g.T_meas, atol=1e-15)
    np.testing.assert_allclose(g1.network.arrays().cov, g.network.arrays().cov, rtol=1e-12)


# ---------------------------------------------------------------- edge-only files and init
def _strip_vertices(src, dst):
    dst.write_text(''.join(ln for ln in src.read_text().splitlines(keepends=True)
                           if not ln.startswith('VERTEX')))
    return dst


#: GTSAM optima from the file's guess (shared/data/README.md); test_g2o checks we reach them too
OPTIMUM = {'tinyGrid3D': 18.6278, 'smallGrid3D': 1035.851, 'intel': 45.0042}


@pytest.mark.parametrize('name', ['tinyGrid3D', 'smallGrid3D', 'intel'])
def test_edge_only_file_reaches_the_optimum_of_the_file_guess(tmp_path, pose_graph_dir, capsys,
                                                              name):
    full = pose_graph_dir / f'{name}.g2o'
    stripped = _strip_vertices(full, tmp_path / f'{name}-edges.g2o')
    got = _cli_json(capsys, stripped, '--out', tmp_path / 'out.g2o')
    assert got['init'] == 'chordal'
    assert got['cost'] == pytest.approx(OPTIMUM[name], rel=2e-5)
    if name != 'intel':  # the small ones: also against our own solve from the file's guess
        ref = _cli_json(capsys, full, '--init', 'file')
        assert ref['init'] == 'file' and got['cost'] == pytest.approx(ref['cost'], rel=1e-7)
    # same vertices (in increasing id order, as in these files) and a written guess
    assert read_g2o(tmp_path / 'out.g2o').has_guess
    assert read_g2o(stripped).vertex_ids.tolist() == read_g2o(full).vertex_ids.tolist()
    capsys.readouterr()
    assert main(['solve', str(stripped), '--init', 'file']) == 1
    assert 'no vertices' in capsys.readouterr().err


@pytest.mark.parametrize('method', ['odometry', 'spanning-tree', 'chordal'])
def test_every_init_reaches_the_optimum_on_small_grid(pose_graph_dir, method):
    g = read_g2o(pose_graph_dir / 'smallGrid3D.g2o')
    ref = solve_graph(g).cost
    guess = initial_guess(g, method)
    assert guess.method == method
    np.testing.assert_allclose(guess.T_world_node[0], g.T_init[0], atol=1e-12)  # datum kept
    assert solve_graph(g.with_initial_guess(guess.T_world_node)).cost == pytest.approx(ref,
                                                                                      rel=1e-6)


@pytest.mark.parametrize('dim', [3, 2])
def test_chordal_recovers_noise_free_poses_exactly(rng, dim):
    n = 30
    if dim == 3:
        T = se3.exp(rng.normal(0, [3, 3, 3, 2, 2, 2], (n, 6)))
        d = 6
    else:
        T = se2_to_se3(rng.normal(0, [3, 3, 3], (n, 3)))
        d = 3
    T = se3.inverse(T[0]) @ T          # vertex 0 at the identity (the datum)
    pairs = np.array([(k, k + 1) for k in range(n - 1)] + [tuple(rng.choice(n, 2, False))
                                                           for _ in range(20)])
    A = rng.normal(size=(len(pairs), d, d))
    info = A @ np.swapaxes(A, 1, 2) + np.eye(d)
    edges = PoseGraphEdges(n=n, src=pairs[:, 0], dst=pairs[:, 1],
                           T_meas=se3.relative(T[pairs[:, 0]], T[pairs[:, 1]]),
                           information=info, dim=dim)
    np.testing.assert_allclose(chordal_initialization(edges, 0), T, atol=1e-9)
    for method in ('odometry', 'spanning-tree'):
        np.testing.assert_allclose(initialize(edges, method, 0), T, atol=1e-9)


def test_spanning_tree_takes_the_most_certain_edge(rng):
    """Triangle 0-1-2 where the direct edge 0-2 is wrong but uncertain: the spanning tree
    composes 0-1-2; odometry also uses the chain; brute force: the only other tree is wrong."""
    T = se3.exp(rng.normal(0, 1, (3, 6)))
    T = se3.inverse(T[0]) @ T
    meas = np.stack([se3.relative(T[0], T[1]), se3.relative(T[1], T[2]),
                     se3.relative(T[0], T[2]) @ se3.exp(np.full(6, 0.3))])
    info = np.stack([np.eye(6) * 100, np.eye(6) * 100, np.eye(6) * 0.01])
    edges = PoseGraphEdges(n=3, src=np.array([0, 1, 0]), dst=np.array([1, 2, 2]),
                           T_meas=meas, information=info, dim=3)
    np.testing.assert_allclose(initialize(edges, 'spanning-tree'), T, atol=1e-12)
    info2 = info[[2, 0, 1]]   # now edge 0-1 is the uncertain one: the tree avoids it
    edges2 = PoseGraphEdges(n=3, src=np.array([0, 1, 0]), dst=np.array([1, 2, 2]),
                            T_meas=meas, information=info2, dim=3)
    got = initialize(edges2, 'spanning-tree')
    np.testing.assert_allclose(got[2], meas[2], atol=1e-12)
    np.testing.assert_allclose(got[1], meas[2] @ se3.inverse(meas[1]), atol=1e-12)


def test_disconnected_vertex_is_refused(tmp_path):
    info = _f(np.eye(6)[IU6])
    path = _write(tmp_path, [f'EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {info}',
                             f'EDGE_SE3:QUAT 2 3 1 0 0 0 0 0 1 {info}'])
    g = read_g2o(path)
    assert not g.has_guess and g.vertex_ids.tolist() == [0, 1, 2, 3]
    for method in ('chordal', 'spanning-tree'):
        with pytest.raises(InputError, match='not connected to the datum'):
            initial_guess(g, method)


# ------------------------------------------------------------ imperfect information matrices
def test_nearest_positive_definite_is_eigenvalue_clipping(rng):
    A = rng.normal(size=(50, 6, 6))
    A = A + np.swapaxes(A, 1, 2)                      # symmetric, mostly indefinite
    X = nearest_positive_definite(A, rel_floor=1e-6)
    w_in = np.linalg.eigvalsh(A)
    w_out = np.linalg.eigvalsh(X)
    floor = 1e-6 * np.abs(w_in).max(axis=1)
    np.testing.assert_allclose(w_out, np.maximum(w_in, floor[:, None]), rtol=1e-9, atol=1e-12)
    assert not not_positive_definite(X).any()
    # Frobenius distance as Higham's theorem says, and no random PD matrix is closer
    dist = np.linalg.norm(A - X, axis=(1, 2))
    np.testing.assert_allclose(dist, np.sqrt(((w_in - np.maximum(w_in, floor[:, None])) ** 2)
                                             .sum(axis=1)), rtol=1e-9)
    for _ in range(200):
        B = rng.normal(size=(6, 6))
        Y = X[0] + 0.1 * (B @ B.T) * rng.uniform() - 0.05 * np.eye(6) * rng.uniform()
        if np.linalg.eigvalsh(Y)[0] > 0:
            assert np.linalg.norm(A[0] - Y) >= dist[0] - 1e-12
    # a positive-definite matrix comes back unchanged
    P = A[0] @ A[0].T + np.eye(6)
    np.testing.assert_allclose(nearest_positive_definite(P[None])[0], P, rtol=1e-12, atol=1e-12)


def test_indefinite_information_is_repaired_with_one_warning_or_refused(tmp_path, capsys):
    good = _f(np.eye(6)[IU6] * 100)
    bad_info = np.eye(6) * 100
    bad_info[3, 4] = bad_info[4, 3] = 200                     # indefinite
    lines = ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1', 'VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1',
             'VERTEX_SE3:QUAT 2 2 0 0 0 0 0 1',
             f'EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {_f(bad_info[IU6])}',
             f'EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 {good}',
             f'EDGE_SE3:QUAT 0 2 2 0 0 0 0 0 1 {_f(bad_info[IU6])}']
    path = _write(tmp_path, lines)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        g = read_g2o(path)
    msgs = [str(w.message) for w in caught if issubclass(w.category, InformationRepairWarning)]
    assert len(msgs) == 1 and 'lines 4, 6' in msgs[0]
    assert g.repaired_lines == (4, 6) and not not_positive_definite(g.information).any()
    np.testing.assert_array_equal(g.information[1], np.eye(6) * 100)
    capsys.readouterr()
    assert main(['solve', str(path), '--json']) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out['repaired_edges'] == 2 and out['repaired_lines'] == [4, 6]
    assert captured.err.count('warning:') == 1 and 'lines 4, 6' in captured.err
    capsys.readouterr()
    assert main(['solve', str(path), '--strict']) == 1
    err = capsys.readouterr().err
    assert f'{path}:4:' in err and 'positive definite' in err


# ------------------------------------------------------------------- optimum evidence
def _simulated_graph(tmp_path, rng, info_scale=1.0):
    """A 3-D chain with loop closures whose noise matches its information (times scale)."""
    n = 60
    steps = se3.exp(np.column_stack([np.ones(n - 1), np.zeros((n - 1, 2)),
                                     np.zeros((n - 1, 2)), np.full(n - 1, 0.2)]))
    T = [np.eye(4)]
    for S in steps:
        T.append(T[-1] @ S)
    T = np.stack(T)
    pairs = [(k, k + 1) for k in range(n - 1)] + [(k, k + 31) for k in range(0, n - 31, 2)]
    cov = np.diag([0.01, 0.01, 0.01, 0.001, 0.001, 0.001]) ** 2 * 100
    info = np.linalg.inv(cov)
    L = np.linalg.cholesky(cov)
    lines = [f'VERTEX_SE3:QUAT {k} {_pq(T[k])}' for k in range(n)]
    for i, j in pairs:
        Z = se3.relative(T[i], T[j]) @ se3.exp(L @ rng.normal(size=6))
        lines.append(f'EDGE_SE3:QUAT {i} {j} {_pq(Z)} {_f((info * info_scale)[IU6])}')
    return _write(tmp_path, lines)


def test_variance_factor_and_chi_square_test(tmp_path, rng, capsys):
    good = _cli_json(capsys, _simulated_graph(tmp_path, rng))
    m, n = 59 + 15, 60
    assert good['dof'] == 6 * m - 6 * (n - 1)
    assert good['variance_factor'] == pytest.approx(good['cost'] / good['dof'])
    assert good['chi2_test'] == 'pass' and 0.5 < good['variance_factor'] < 2
    from scipy.stats import chi2
    np.testing.assert_allclose(good['chi2_95'], chi2.ppf([0.025, 0.975], good['dof']))
    over = _cli_json(capsys, _simulated_graph(tmp_path, rng, info_scale=25.0))
    assert over['chi2_test'] == 'cost too large' and over['variance_factor'] > 10
    g = read_g2o(_simulated_graph(tmp_path, rng, info_scale=0.01))
    assert optimum_evidence(g, solve_graph(g).T_world_node).chi2_test == 'cost too small'


def test_check_init_reports_the_other_initialisation(pose_graph_dir, capsys):
    out = _cli_json(capsys, pose_graph_dir / 'tinyGrid3D.g2o', '--check-init',
                    '--init', 'file')
    chk = out['check_init']
    assert chk['method'] == 'chordal' and not chk['lower']
    assert chk['cost'] == pytest.approx(out['cost'], rel=1e-6)
    capsys.readouterr()
    assert main(['solve', str(pose_graph_dir / 'tinyGrid3D.g2o'), '--check-init',
                 '--init', 'chordal']) == 0
    text = capsys.readouterr().out
    assert 'init: chordal' in text and 'check-init   spanning-tree' in text
    assert 'variance factor' in text


def test_check_init_finds_the_lower_minimum_of_a_wound_ring(tmp_path, capsys):
    """A 2-D ring of 8 poses measured exactly; the file's guess winds the headings once more
    around the loop. From it the solver stops in the local minimum where every edge keeps a
    45 degree rotation error (cost 8 * 100 * (pi/4)^2, written here); chordal reaches 0."""
    n = 8
    ang = 2 * np.pi * np.arange(n) / n
    xyt = np.column_stack([np.cos(ang), np.sin(ang), ang + np.pi / 2])
    guess = xyt + np.column_stack([np.zeros((n, 2)), ang])
    lines = [f'VERTEX_SE2 {k} {_f(guess[k])}' for k in range(n)]
    for k in range(n):
        j = (k + 1) % n
        z = se3_to_se2(se3.relative(se2_to_se3(xyt[k]), se2_to_se3(xyt[j])))
        lines.append(f'EDGE_SE2 {k} {j} {_f(z)} 100 0 0 100 0 100')
    out = _cli_json(capsys, _write(tmp_path, lines), '--check-init', '--init', 'file')
    assert out['cost'] == pytest.approx(n * 100 * (np.pi / 4) ** 2, rel=1e-6)
    assert out['chi2_test'] == 'cost too large'
    assert out['check_init']['lower'] and out['check_init']['cost'] < 1e-12
