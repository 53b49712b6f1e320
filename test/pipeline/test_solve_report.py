"""``pipeline.solve_report``: one ``ga-ros solve`` as a library call (start, solve, evidence,
report), checked against the independent cost evaluator and a re-read of the written file."""

from __future__ import annotations

import numpy as np
import pytest
from test_solve_start import _ring

from ga_ros.errors import InputError
from ga_ros.io.g2o import graph_cost, read_g2o
from ga_ros.pipeline.pose_graph import initial_guess
from ga_ros.pipeline.solve_report import (
    SolveRequest,
    iteration_cap_hint,
    solve_report,
    write_solution,
)


def test_batch_report_starts_from_the_cheaper_start_and_reports_the_cost(tmp_path, rng):
    graph = read_g2o(_ring(rng, tmp_path / 'ring.g2o', start_noise=0.5))
    report = solve_report(graph, SolveRequest(check_init=True, quality=True), name='ring')
    file_cost = graph_cost(graph, graph.T_init)
    chordal_cost = graph_cost(graph, initial_guess(graph, 'chordal').T_world_node)
    assert report.guess.method == ('file' if file_cost <= chordal_cost else 'chordal')
    np.testing.assert_allclose(report.graph.T_init, report.guess.T_world_node, atol=0)
    s = report.summary('ring.g2o', None, 0.0)
    assert s['cost'] == pytest.approx(graph_cost(graph, report.result.T_world_node), rel=1e-9)
    assert s['cost'] <= min(file_cost, chordal_cost)
    assert s['mode'] == 'batch' and s['init'] == report.guess.method
    assert s['check_init']['method'] != report.guess.method
    assert 'w_max' in s['quality'] and 'sigma0_sq' not in s['quality']
    assert (s['hint'] is None) == (s['termination'] != 'max_iterations')


def test_track_mode_has_update_times_and_neither_hint_nor_batch_extras(tmp_path, rng):
    graph = read_g2o(_ring(rng, tmp_path / 'ring.g2o', n=60))
    tracks = tmp_path / 'tracks.csv'
    tracks.write_text('node_id,track_id\n' + ''.join(f'{k},{k // 20}\n' for k in range(60)))
    report = solve_report(graph, SolveRequest(tracks=str(tracks), window=2, max_iterations=1,
                                              check_init=True, quality=True))
    s = report.summary('ring.g2o', None, 0.0)
    assert s['mode'] == 'tracks' and len(s['per_track_ms']) == 3
    assert s['hint'] is None and s['check_init'] is None and 'quality' not in s
    assert s['cost'] == pytest.approx(graph_cost(graph, report.result.T_world_node), rel=1e-9)


def test_written_solution_reads_back_as_the_solved_poses(tmp_path, rng):
    graph = read_g2o(_ring(rng, tmp_path / 'ring.g2o'))
    report = solve_report(graph)
    write_solution(report, tmp_path / 'out.g2o', tmp_path / 'out.tum')
    back = read_g2o(tmp_path / 'out.g2o')
    np.testing.assert_allclose(back.T_init, report.result.T_world_node, atol=1e-9)
    rows = np.array([ln.split() for ln in (tmp_path / 'out.tum').read_text().splitlines()
                     if not ln.startswith('#')], dtype=float)
    np.testing.assert_allclose(rows[:, 0], graph.vertex_ids, atol=1e-9)  # stamp = id in s
    np.testing.assert_allclose(rows[:, 1:4], report.result.T_world_node[:, :3, 3], atol=1e-9)
    assert not (tmp_path / 'out.kitti').exists()


def test_absurd_vertex_is_refused_with_the_file_name(tmp_path, rng):
    path = _ring(rng, tmp_path / 'ring.g2o', n=12)
    lines = path.read_text().splitlines()
    lines[3] = 'VERTEX_SE3:QUAT 3 1e308 0 0 0 0 0 1'
    path.write_text('\n'.join(lines) + '\n')
    with pytest.raises(InputError, match=r'^ring\.g2o: .*absurd.*Nothing was written'):
        solve_report(read_g2o(path), SolveRequest(init='file'), name='ring.g2o')


def test_iteration_cap_hint_suggests_another_start_unless_chordal():
    assert iteration_cap_hint('cost_converged', 'file') is None
    assert '--init chordal' in iteration_cap_hint('max_iterations', 'file')
    hint = iteration_cap_hint('max_iterations', 'chordal')
    assert '--max-iterations' in hint and '--init' not in hint
