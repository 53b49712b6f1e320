"""Numeric fields at their limits give one line (``file:line: ...``) and exit code 1, never a
traceback: g2o ids, trajectory stamps, input settings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ga_ros.cli.main import main as cli_main
from ga_ros.errors import FormatError, InputError
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.io.groundtruth import read_ground_truth_file
from ga_ros.io.trajectory import read_tum, write_tum

EDGE = '1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1'
V = 'VERTEX_SE3:QUAT'
E = 'EDGE_SE3:QUAT'


@pytest.mark.parametrize('lines,match', [
    ([f'{V} {"9" * 5000} 0 0 0 0 0 0 1', f'{V} 1 0 0 0 0 0 0 1', f'{E} {"9" * 5000} 1 {EDGE}'],
     r':1: vertex id must be a non-negative integer below 2\^63, got .*\(5000 characters\)'),
    ([f'{V} 0 0 0 0 0 0 0 1', f'{V} 99999999999999999999999 0 0 0 0 0 0 1',
      f'{E} 0 99999999999999999999999 {EDGE}'], ':2: vertex id must be'),
    ([f'{V} -5 0 0 0 0 0 0 1', f'{V} 1 0 0 0 0 0 0 1', f'{E} -5 1 {EDGE}'],
     ":1: vertex id must be a non-negative integer below 2\\^63, got '-5'"),
    ([f'{V} 0 0 0 0 0 0 0 1', f'{V} 1 0 0 0 0 0 0 1', f'{E} 0 1 nan{EDGE[1:]}'],
     ':3: NaN or infinite value'),
])
def test_g2o_numeric_limits(tmp_path: Path, capsys, lines: list[str], match: str) -> None:
    path = tmp_path / 'bad.g2o'
    path.write_text('\n'.join(lines) + '\n')
    assert cli_main(['solve', str(path)]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err
    import re

    assert re.search(match, err), err
    assert len(err) < 400  # the 5,000 digits are not echoed


@pytest.mark.parametrize('stamp', ['9' * 5000, '1e400', '1e13', 'nan', '-inf'])
def test_trajectory_stamps_beyond_int64_ns(tmp_path: Path, stamp: str) -> None:
    (tmp_path / 'gt.tum').write_text(f'{stamp} 0 0 0 0 0 0 1\n')
    with pytest.raises(FormatError, match='gt.tum:1: timestamp .* not a'):
        read_tum(tmp_path / 'gt.tum')
    with pytest.raises(FormatError, match='gt.tum:1:'):
        read_ground_truth_file(tmp_path / 'gt.tum')


def test_euroc_stamp_of_too_many_digits(tmp_path: Path) -> None:
    (tmp_path / 'data.csv').write_text('1' * 25 + ',0,0,0,1,0,0,0\n')
    with pytest.raises(FormatError, match='data.csv:1: timestamp .* at most 19 digits'):
        read_ground_truth_file(tmp_path / 'data.csv', fmt='euroc')


@pytest.mark.parametrize('key,value,match', [
    ('keyframe_travel_m', float('nan'), 'must be a finite number'),
    ('keyframe_travel_m', '1e400', 'must be a number'),
    ('first_node_id', 10**26, 'must be a finite number below 2\\^63'),
    ('first_node_id', 1.5, 'must be an integer'),
    ('keyframe_travel_m', True, 'must be a number'),
    ('pose_covariance_frame', 3, 'must be a str'),
])
def test_input_settings_are_typed(key: str, value: object, match: str) -> None:
    with pytest.raises(InputError, match=f'odom0.{key} {match}'):
        OdometryInputConfig.from_mapping('odom0', {key: value})
    ok = OdometryInputConfig.from_mapping('odom0', {'keyframe_travel_m': 2})  # int for a float
    assert ok.keyframe_travel_m == 2


def test_empty_trajectory_is_written_and_read(tmp_path: Path) -> None:
    write_tum(tmp_path / 'empty.tum', np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    assert (tmp_path / 'empty.tum').read_text() == '# timestamp x y z qx qy qz qw\n'
    assert len(read_tum(tmp_path / 'empty.tum')) == 0
