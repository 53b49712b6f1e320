"""``ga-ros solve``: batch mode, JSON output, bad input, robust losses, track mode."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ga_ros.cli.main import main
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import connection_cost
from ga_ros.errors import FormatError, NetworkError
from ga_ros.geometry import se3
from ga_ros.io.g2o import graph_cost, read_g2o
from ga_ros.io.trajectory import read_kitti, read_tum
from ga_ros.pipeline.pose_graph import (
    GraphSolveConfig,
    read_tracks,
    replay_measurements,
    solve_graph,
)

TINY_OPTIMUM = 18.6278  # shared/data/README.md (GTSAM LM)
INFO3 = ' '.join(['1 0 0 0 0 0', '1 0 0 0 0', '1 0 0 0', '1 0 0', '1 0', '1'])


def _run(capsys, argv):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def _loop_graph(rng, n=40, n_tracks=4, outliers=0, sigma=(0.01, 0.003)):
    """A noisy 3-D loop: consecutive edges plus closures between neighbouring laps.

    Returns g2o lines, the true poses and the node -> track map. Vertex 0 is placed at its true
    pose (the datum); the others at the odometry integration of the noisy consecutive edges.
    """
    ang = np.linspace(0, 2 * np.pi * n_tracks * 0.98, n)
    T_true = np.stack([se3.from_translation_rotvec(
        np.array([10 * np.cos(a), 10 * np.sin(a), 0.5 * a]), np.array([0.05 * a, 0, a + 1.5]))
        for a in ang])
    per = n // n_tracks
    tracks = np.arange(n) // per
    noise = np.array([sigma[0]] * 3 + [sigma[1]] * 3)
    info = np.diag(1 / noise**2)
    edges = [(k, k + 1) for k in range(n - 1)]
    edges += [(k, k + per) for k in range(0, n - per, 2)]
    meas = []
    for i, j in edges:
        meas.append(se3.relative(T_true[i], T_true[j]) @ se3.exp(rng.normal(0, noise)))
    for _ in range(outliers):  # wrong connections: between unrelated nodes, far off
        i, j = sorted(int(x) for x in rng.choice(n, 2, replace=False))
        edges.append((i, j))
        meas.append(se3.exp(rng.normal(0, [3, 3, 3, 1, 1, 1])))
    T0 = [T_true[0]]
    for k in range(n - 1):
        T0.append(T0[-1] @ meas[k])
    lines = []
    for k in range(n):
        p, q = se3.to_pos_quat(T0[k])
        lines.append(f'VERTEX_SE3:QUAT {k} {" ".join(map(_r, p))} {" ".join(map(_r, q))}')
    iu = np.triu_indices(6)
    for (i, j), M in zip(edges, meas):
        p, q = se3.to_pos_quat(M)
        lines.append(f'EDGE_SE3:QUAT {i} {j} {" ".join(map(_r, p))} {" ".join(map(_r, q))} '
                     f'{" ".join(map(_r, info[iu]))}')
    return lines, T_true, tracks


def _r(x) -> str:
    return repr(float(x))


def _write(path, lines):
    path.write_text('\n'.join(lines) + '\n')
    return path


def _pos_rmse(T, T_true):
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


# ----------------------------------------------------------------------------------- batch
def test_solve_tiny_grid_json_and_output_file(tmp_path, capsys, pose_graph_dir):
    out = tmp_path / 'opt.g2o'
    code, stdout, _ = _run(capsys, ['solve', str(pose_graph_dir / 'tinyGrid3D.g2o'),
                                    '--out', str(out), '--json'])
    assert code == 0
    summary = json.loads(stdout)
    assert {'cost', 'iterations', 'seconds'} <= set(summary)
    assert summary['iterations'] >= 1 and summary['seconds'] >= 0
    assert summary['cost'] == pytest.approx(TINY_OPTIMUM, rel=1e-3)
    written = read_g2o(out)
    assert written.n_vertices == 9 and written.n_edges == 11
    # the printed cost is that of the written vertices under the independent evaluator
    assert graph_cost(written, written.T_init) == pytest.approx(summary['cost'], rel=1e-9)
    # re-solving the optimum changes nothing beyond the stop on the relative cost decrease
    # (GraphSolveConfig.cost_tolerance = 1e-6: the next Gauss-Newton step gains far less)
    code, stdout, _ = _run(capsys, ['solve', str(out), '--json'])
    assert json.loads(stdout)['cost'] == pytest.approx(summary['cost'], rel=1e-7)


def test_solve_text_output(capsys, pose_graph_dir):
    code, stdout, _ = _run(capsys, ['solve', str(pose_graph_dir / 'tinyGrid3D.g2o')])
    assert code == 0
    assert 'final cost' in stdout and 'iterations' in stdout and 'time' in stdout
    cost = float(next(ln for ln in stdout.splitlines() if ln.startswith('final cost')).split()[2])
    assert cost == pytest.approx(TINY_OPTIMUM, rel=1e-3)


def test_bad_file_reports_line_and_writes_nothing(tmp_path, capsys):
    src = _write(tmp_path / 'bad.g2o', ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1',
                                       'VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1',
                                       f'EDGE_SE3:QUAT 0 2 1 0 0 0 0 0 1 {INFO3}'])
    out = tmp_path / 'out.g2o'
    code, stdout, stderr = _run(capsys, ['solve', str(src), '--out', str(out)])
    assert code == 1
    assert f'{src}:3:' in stderr and 'vertex 2' in stderr
    assert not out.exists() and stdout == ''


def test_disconnected_graph_is_an_error(tmp_path, capsys):
    src = _write(tmp_path / 'g.g2o', [f'VERTEX_SE3:QUAT {k} {k} 0 0 0 0 0 1' for k in range(4)]
                 + [f'EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO3}',
                    f'EDGE_SE3:QUAT 2 3 1 0 0 0 0 0 1 {INFO3}'])
    code, _, stderr = _run(capsys, ['solve', str(src)])
    assert code == 1 and 'not connected' in stderr


def test_non_finite_cost_is_an_error(tmp_path, capsys):
    """A vertex at 1e308 (cost inf) exits 1 with a message and writes nothing."""
    src = _write(tmp_path / 'inf.g2o', ['VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1',
                                       'VERTEX_SE3:QUAT 1 1e308 0 0 0 0 0 1',
                                       'VERTEX_SE3:QUAT 2 2 0 0 0 0 0 1',
                                       f'EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO3}',
                                       f'EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 {INFO3}'])
    out = tmp_path / 'out.g2o'
    code, _, stderr = _run(capsys, ['solve', str(src), '--out', str(out), '--init', 'file'])
    assert code == 1 and 'final cost' in stderr and '1e308' in stderr
    assert not out.exists()


# ---------------------------------------------------------------------------------- robust
@pytest.mark.parametrize('loss', ['huber', 'cauchy'])
def test_robust_loss_resists_wrong_connections(tmp_path, rng, loss):
    lines, T_true, _ = _loop_graph(rng, outliers=4)
    clean = read_g2o(_write(tmp_path / 'clean.g2o', lines[:-4]))
    g = read_g2o(_write(tmp_path / 'dirty.g2o', lines))
    ref = _pos_rmse(solve_graph(clean).T_world_node, T_true)  # no outliers: noise level
    plain = _pos_rmse(solve_graph(g).T_world_node, T_true)
    robust_cfg = GraphSolveConfig.with_solver(robust_loss=loss)
    robust = _pos_rmse(solve_graph(g, robust_cfg).T_world_node, T_true)
    assert ref < 0.2
    assert plain > 5 * ref          # the wrong connections bend the plain solution
    assert robust < plain / 3       # the robust loss mostly ignores them
    if loss == 'cauchy':            # redescending: close to the outlier-free solution
        assert robust < 2 * ref


def test_robust_option_on_command_line(tmp_path, rng, capsys):
    lines, _, _ = _loop_graph(rng, outliers=3)
    src = _write(tmp_path / 'dirty.g2o', lines)
    code, stdout, _ = _run(capsys, ['solve', str(src), '--json', '--robust', 'cauchy',
                                    '--robust-scale', '2'])
    s = json.loads(stdout)
    assert code == 0 and s['robust'] == 'cauchy'
    code, stdout, _ = _run(capsys, ['solve', str(src), '--json'])
    plain = json.loads(stdout)
    # least squares has the lower sum of squares; the robust solve pays for ignoring outliers
    assert plain['cost'] < s['cost']
    assert s['objective'] < s['cost']


# ------------------------------------------------------------------------------ track mode
def test_read_tracks(tmp_path):
    ids = np.array([4, 5, 6])
    path = _write(tmp_path / 't.csv', ['node_id,track_id', '4,0', '5,0', '', '6,1'])
    np.testing.assert_array_equal(read_tracks(path, ids), [0, 0, 1])
    for body, words, line in [(['4,0', '5,x'], 'integers', 3), (['4,0', '9,1'], 'vertex', 3),
                              (['4,0', '4,1'], 'already', 3), (['4,0,1'], 'fields', 2),
                              (['4,0', '5,-1'], 'non-negative', 3)]:
        path = _write(tmp_path / 't.csv', ['node_id,track_id'] + body)
        with pytest.raises(FormatError) as info:
            read_tracks(path, ids)
        assert info.value.line == line and words in str(info.value)
    path = _write(tmp_path / 't.csv', ['node_id,track_id', '4,0'])
    with pytest.raises(FormatError, match='no track'):
        read_tracks(path, ids)


def test_replay_measurements_reveal_edges_in_track_order(tmp_path, rng):
    lines, _, tracks = _loop_graph(rng, outliers=2)
    g = read_g2o(_write(tmp_path / 'g.g2o', lines))
    # shuffle the track numbering order against the file order: track 3 runs first
    tracks = np.array([3, 0, 1, 2])[tracks]
    ms = replay_measurements(g, tracks)
    assert len(ms) == g.n_edges
    order = [int(i) for i in np.lexsort((np.arange(g.n_vertices), tracks))]
    rank = {int(g.vertex_ids[k]): r for r, k in enumerate(order)}
    dst_rank = [rank[m.dst_id] for m in ms]
    assert dst_rank == sorted(dst_rank)                        # revealed as the vertices appear
    assert all(rank[m.src_id] < rank[m.dst_id] for m in ms)    # dst is always the new vertex
    assert sorted(set(dst_rank)) == list(range(1, g.n_vertices))
    assert [m.dst_track for m in ms] == sorted(m.dst_track for m in ms)
    assert all(m.src_track == tracks[m.src_id] and m.dst_track == tracks[m.dst_id] for m in ms)
    cons = [m for m in ms if m.kind == 'consecutive']
    assert all(rank[m.dst_id] == rank[m.src_id] + 1 and m.src_track == m.dst_track for m in cons)
    # inverted edges carry the same information: the cost of any poses is unchanged
    net = ConnectionNetwork()
    for k in order:
        net.add_node(int(g.vertex_ids[k]), int(tracks[k]))
    for m in ms:
        net.add_connection(m.src_id, m.dst_id, m.z, m.cov)
    T = g.T_init @ se3.exp(rng.normal(0, 0.3, (g.n_vertices, 6)))
    assert connection_cost(net, T[order]) == pytest.approx(graph_cost(g, T), rel=1e-9)


def test_replay_rejects_a_vertex_a_live_run_cannot_place(tmp_path, rng):
    lines, _, tracks = _loop_graph(rng, n=8, n_tracks=2)
    g = read_g2o(_write(tmp_path / 'g.g2o', lines))
    tracks = tracks.copy()
    tracks[2] = 1  # order 0 1 3 | 2 4 5 6 7: vertex 3 links only to 2 and 4, both later
    with pytest.raises(NetworkError, match='vertex 3'):
        replay_measurements(g, tracks)


def _tracks_csv(path, tracks):
    path.write_text('node_id,track_id\n' + ''.join(f'{k},{t}\n' for k, t in enumerate(tracks)))
    return path


def test_track_mode_matches_batch_optimum(tmp_path, rng, capsys):
    lines, T_true, tracks = _loop_graph(rng, n=48, n_tracks=6)
    src = _write(tmp_path / 'g.g2o', lines)
    csv_path = _tracks_csv(tmp_path / 'tracks.csv', tracks)
    batch = solve_graph(read_g2o(src))
    out = tmp_path / 'out.g2o'
    code, stdout, _ = _run(capsys, ['solve', str(src), '--tracks', str(csv_path), '--window',
                                    '3', '--json', '--out', str(out)])
    assert code == 0
    s = json.loads(stdout)
    assert s['mode'] == 'tracks' and {'cost', 'iterations', 'seconds'} <= set(s)
    assert len(s['per_track_ms']) == 6 and all(ms > 0 for ms in s['per_track_ms'])
    # the final batch refinement lands on the batch optimum
    assert s['cost'] == pytest.approx(batch.cost, rel=1e-6)
    written = read_g2o(out)
    assert graph_cost(written, written.T_init) == pytest.approx(s['cost'], rel=1e-9)
    # without it, the windowed estimate is near the optimum and as accurate as the batch one
    code, stdout, _ = _run(capsys, ['solve', str(src), '--tracks', str(csv_path), '--window',
                                    '3', '--json', '--no-refine', '--out', str(out)])
    windowed = json.loads(stdout)
    assert batch.cost * (1 - 1e-9) <= windowed['cost'] < 1.3 * batch.cost
    err_batch = _pos_rmse(batch.T_world_node, T_true)
    assert _pos_rmse(read_g2o(out).T_init, T_true) < 1.5 * err_batch + 0.01


def test_track_mode_drops_connections_to_frozen_tracks(tmp_path, rng, capsys):
    lines, T_true, tracks = _loop_graph(rng, n=32, n_tracks=4)
    p, q = se3.to_pos_quat(se3.relative(T_true[0], T_true[-1]))  # a valid first-to-last edge
    info = ' '.join(['1 0 0 0 0 0', '1 0 0 0 0', '1 0 0 0', '1 0 0', '1 0', '1'])
    late = f'EDGE_SE3:QUAT 0 31 {" ".join(map(_r, p))} {" ".join(map(_r, q))} {info}'
    src = _write(tmp_path / 'g.g2o', lines + [late])
    csv_path = _tracks_csv(tmp_path / 't.csv', tracks)
    code, stdout, _ = _run(capsys, ['solve', str(src), '--tracks', str(csv_path), '--window',
                                    '2', '--json'])
    s = json.loads(stdout)
    assert code == 0 and s['rejected'] == {'frozen': 1}   # track 0 left the window long ago
    # the refined result is the optimum of the graph without that edge, judged on all edges
    without = read_g2o(_write(tmp_path / 'w.g2o', lines))
    opt = solve_graph(without)
    g = read_g2o(src)
    assert s['cost'] == pytest.approx(graph_cost(g, opt.T_world_node), rel=1e-6)
    assert s['cost'] > solve_graph(g).cost


def test_track_mode_text_output_and_bad_tracks_file(tmp_path, rng, capsys):
    lines, _, tracks = _loop_graph(rng, n=24, n_tracks=3)
    src = _write(tmp_path / 'g.g2o', lines)
    code, stdout, _ = _run(capsys, ['solve', str(src), '--tracks',
                                    str(_tracks_csv(tmp_path / 't.csv', tracks))])
    assert code == 0 and 'tracks       3' in stdout and 'final cost' in stdout
    bad = _tracks_csv(tmp_path / 'bad.csv', tracks[:-1])  # last vertex has no track
    code, stdout, stderr = _run(capsys, ['solve', str(src), '--tracks', str(bad)])
    assert code == 1 and 'no track' in stderr and stdout == ''


# ------------------------------------------------------------------------------- benchmark
def test_bench_g2o_table_on_tiny_grid(capsys, pose_graph_dir):
    code, stdout, _ = _run(capsys, ['bench', 'g2o', '--data', str(pose_graph_dir),
                                    '--only', 'tinyGrid3D'])
    assert code == 0
    rows = [r for r in stdout.splitlines() if r.startswith('| tinyGrid3D')]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip('|').split('|')]
    assert cells[2:4] == ['9', '11']
    assert float(cells[6]) == pytest.approx(TINY_OPTIMUM)  # reference read from the data README
    assert abs(float(cells[7])) < 0.1                      # gap in percent


def test_trajectory_export(tmp_path, capsys, pose_graph_dir):
    out, tum, kitti = tmp_path / 'o.g2o', tmp_path / 'o.tum', tmp_path / 'o.kitti'
    code, _, _ = _run(capsys, ['solve', str(pose_graph_dir / 'tinyGrid3D.g2o'), '-o', str(out),
                               '--tum', str(tum), '--kitti', str(kitti)])
    assert code == 0
    T = read_g2o(out).T_init
    traj = read_tum(tum)
    np.testing.assert_array_equal(traj.stamps_ns, np.arange(9) * 1_000_000_000)
    np.testing.assert_allclose(traj.T_world_cam, T, atol=1e-12)
    np.testing.assert_allclose(read_kitti(kitti), T, atol=1e-12)


def test_unwritable_output_is_a_clear_error(tmp_path, capsys, pose_graph_dir):
    code, _, stderr = _run(capsys, ['solve', str(pose_graph_dir / 'tinyGrid3D.g2o'), '--out',
                                    str(tmp_path / 'missing-dir' / 'o.g2o')])
    assert code == 1 and 'cannot write' in stderr
