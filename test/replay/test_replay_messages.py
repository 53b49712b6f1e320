"""What the replay tells its user: default-covariance counts that agree, the reason given only
when true, and the progress bar (on a terminal only, ``--no-progress`` turns it off)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from ga_ros.cli.main import main as cli_main
from ga_ros.geometry import se3
from ga_ros.io.bag_messages import header, matrix_to_pose_msg, typestore
from ga_ros.io.bag_writer import BagWriter

T0_NS = 1_700_000_000_000_000_000


def _odom_bag(path: Path, pose_cov: np.ndarray) -> Path:
    """``/odom`` at 10 Hz along a 20 x 10 m rectangle with the given pose covariance (36) and
    no twist covariance."""
    types = typestore().types
    vec = types['geometry_msgs/msg/Vector3']
    with BagWriter(path) as bag:
        for k in range(600):
            s = k * 0.1
            d = np.mod(s, 60.0)
            if d < 20:
                x, y, yaw = d, 0.0, 0.0
            elif d < 30:
                x, y, yaw = 20.0, d - 20, np.pi / 2
            elif d < 50:
                x, y, yaw = 20 - (d - 30), 10.0, np.pi
            else:
                x, y, yaw = 0.0, 10 - (d - 50), -np.pi / 2
            T = se3.from_translation_rotvec(np.array([x, y, 0.0]), np.array([0, 0, yaw]))
            stamp = T0_NS + k * 100_000_000
            msg = types['nav_msgs/msg/Odometry'](
                header=header('odom', stamp), child_frame_id='base_link',
                pose=types['geometry_msgs/msg/PoseWithCovariance'](
                    pose=matrix_to_pose_msg(T), covariance=pose_cov.copy()),
                twist=types['geometry_msgs/msg/TwistWithCovariance'](
                    twist=types['geometry_msgs/msg/Twist'](linear=vec(x=0.0, y=0.0, z=0.0),
                                                           angular=vec(x=0.0, y=0.0, z=0.0)),
                    covariance=np.zeros(36)))
            bag.write('/odom', 'nav_msgs/msg/Odometry', msg, stamp)
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
