"""What the replay tells its user: default-covariance counts that agree, the reason given only
when true, and the progress bar (on a terminal only, ``--no-progress`` turns it off)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import ODOMETRY, odometry_msg, rectangle

from ga_ros.cli.main import main as cli_main
from ga_ros.io.bag_writer import BagWriter

T0_NS = 1_700_000_000_000_000_000


def _odom_bag(path: Path, pose_cov: np.ndarray) -> Path:
    """``/odom`` at 10 Hz along a 20 x 10 m rectangle with the given pose covariance (36) and
    no twist covariance."""
    with BagWriter(path) as bag:
        for k, T in enumerate(rectangle(np.arange(600) * 0.1)):
            stamp = T0_NS + k * 100_000_000
            bag.write('/odom', ODOMETRY, odometry_msg(T, stamp, pose_cov=pose_cov), stamp)
    return path


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp('odom')
    constant = np.diag([0.01] * 3 + [0.001] * 3).reshape(36)
    return {'none': _odom_bag(d / 'none', np.zeros(36)),
            'constant': _odom_bag(d / 'constant', constant)}


def _run(bag: Path, out: Path, capsys, *extra: str) -> tuple[dict, str]:
    assert cli_main(['replay', str(bag), '--out', str(out), '--odom-topic', '/odom',
                     '--no-plot', '--aligner', 'batch', *extra]) == 0
    text = capsys.readouterr().out
    return json.loads((out / 'summary.json').read_text()), text


def test_default_covariance_counts_agree_with_the_summary(bags, tmp_path: Path, capsys) -> None:
    summary, text = _run(bags['none'], tmp_path / 'a', capsys)
    st = summary['source_stats']['odom0']
    n = st['measurements']
    assert n == summary['n_measurements'] > 10
    assert st['default_covariances'] == st['missing_covariances'] == n
    warnings = [ln for ln in text.splitlines() if 'DEFAULT covariance' in ln]
    assert len(warnings) == 1, text
    assert f'odom0: {n} of {n} measurements used the DEFAULT covariance (the stream has none' \
        in warnings[0]


def test_the_stream_has_none_only_when_it_has_none(bags, tmp_path: Path, capsys) -> None:
    """A constant pose covariance (a stream that has covariances, which do not grow between
    keyframes) is replaced too, but the reason says so."""
    summary, text = _run(bags['constant'], tmp_path / 'b', capsys)
    st = summary['source_stats']['odom0']
    assert st['default_covariances'] == st['measurements'] > 10 and st['missing_covariances'] == 0
    (line,) = [ln for ln in text.splitlines() if 'DEFAULT covariance' in ln]
    assert 'the stream has none' not in line and 'not usable' in line


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize('tty,option,shown', [(True, '', True), (True, '--no-progress', False),
                                              (False, '', False)])
def test_progress_bar_on_a_terminal_only(bags, tmp_path: Path, monkeypatch, capsys,
                                         tty: bool, option: str, shown: bool) -> None:
    err = _Terminal() if tty else io.StringIO()
    monkeypatch.setattr('sys.stderr', err)
    _run(bags['none'], tmp_path / 'c', capsys, *([option] if option else []))
    text = err.getvalue()
    assert ('replay none' in text and '600/600' in text) == shown, text
