"""The ga-ros entry point: subcommand discovery, aliases, error mapping."""

from __future__ import annotations

import json

import pytest

from ga_ros.cli.benchmarks import BENCHMARKS
from ga_ros.cli.main import build_parser, main


def test_every_documented_subcommand_is_registered():
    sub = next(a for a in build_parser()._actions if a.dest == 'command')
    for name in ('bench', 'solve', 'replay', 'play', 'demo', 'reproduce', 'simulate',
                 'make-bags'):
        assert name in sub.choices, name
    for name in ('bench-vo', 'bench-g2o', 'bench-node', 'bench-replay'):  # one spelling
        assert name not in sub.choices, name


def test_bench_window_receives_its_arguments(capsys):
    assert main(['bench', 'window', '--tracks', '2', '--window', '1', '--no-batch',
                 '--refine-every', '0', '--json']) == 0
    fig = json.loads(capsys.readouterr().out)
    assert fig['tracks'] == 2 and fig['window_tracks'] == 1 and fig['refine_every_tracks'] == 0
    assert fig['nodes'] == 2 * 204
    assert fig['gap_rigid_pct'] == 0.0  # no batch: the window is compared with itself
    stages = fig['stage_cpu_ms']  # CPU per track by stage, 'other' the rest of each thread
    assert set(stages) == {'track end', 'background'}
    for role in stages.values():
        assert set(role) == {'assembly', 'factorisation', 'solves', 'covariances', 'priors',
                             'quality tests', 'outputs', 'process hand-off', 'other'}
    end, bg = stages['track end'], stages['background']
    assert end['assembly'] > 0 and end['factorisation'] > 0 and end['outputs'] > 0
    # the next freeze, computed ahead in a background thread: its covariances (no refinement
    # replaces them) and prior
    assert bg['covariances'] > 0 and bg['priors'] > 0
    assert fig['total_cpu_ms_p50'] >= fig['per_track_cpu_ms_p50']


@pytest.mark.parametrize('target,module,argv,expected', [
    ('linalg', 'linalg', ['--repeat', '3'], ['--repeat', '3']),
    ('linalg', 'linalg', [], []),  # the benchmark's own default (5)
    ('compare', 'compare', ['--repeat', '2'], ['--repeat', '2']),
    ('compare', 'compare', [], []),  # the benchmark's own default (1)
])
def test_bench_passes_repeat_to_its_benchmark(monkeypatch, target, module, argv, expected):
    import importlib
    bench = importlib.import_module(f'ga_ros.bench.{module}')
    seen: list[list[str]] = []
    monkeypatch.setattr(bench, 'main', lambda a: seen.append(a) or 0)
    assert main(['bench', target] + argv) == 0
    got = seen[0]
    tail = got[got.index('--repeat'):got.index('--repeat') + 2] if '--repeat' in got else []
    assert tail == expected


@pytest.mark.parametrize('name', sorted(BENCHMARKS))
def test_every_benchmark_answers_help_under_its_one_spelling(capsys, name):
    with pytest.raises(SystemExit) as exc:
        main(['bench', name, '--help'])
    assert exc.value.code == 0
    assert f'usage: ga-ros bench {name}' in capsys.readouterr().out


def test_bench_lists_every_benchmark(capsys):
    with pytest.raises(SystemExit):
        main(['bench', '--help'])
    out = capsys.readouterr().out
    assert all(name in out for name in BENCHMARKS)


def test_input_errors_become_exit_code_1(tmp_path, capsys):
    bad = tmp_path / 'bad.g2o'
    bad.write_text('VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 7 1 0 0 0 0 0 1\n')
    assert main(['solve', str(bad)]) == 1
    err = capsys.readouterr().err
    assert 'bad.g2o:2' in err and err.count('\n') == 1
