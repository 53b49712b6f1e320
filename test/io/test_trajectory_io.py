"""TUM and KITTI trajectory files: round trips, exact timestamps, malformed lines."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.trajectory import read_kitti, read_tum, write_kitti, write_tum


def _poses(rng, n=20):
    return se3.exp(rng.normal(0, [5, 5, 5, 2, 2, 2], size=(n, 6)))


def test_tum_round_trip(tmp_path, rng):
    T = _poses(rng)
    stamps = 1_700_000_000_000_000_000 + np.cumsum(rng.integers(1, 10**8, size=len(T)))
    path = tmp_path / 'traj.tum'
    write_tum(path, stamps, T)
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.stamps_ns, stamps)  # exact, no float rounding
    np.testing.assert_allclose(traj.T_world_cam, T, atol=1e-12)
    assert len(traj) == len(T)


def test_tum_line_layout_and_quaternion_order(tmp_path):
    q = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_quat()  # x y z w
    T = se3.from_pos_quat(np.array([1.0, 2.0, 3.0]), q)
    path = tmp_path / 't.txt'
    write_tum(path, np.array([1_234_567_890_123_456_789]), T[None])
    row = [r for r in path.read_text().splitlines() if not r.startswith('#')][0].split()
    assert row[0] == '1234567890.123456789'
    np.testing.assert_allclose([float(x) for x in row[1:4]], [1, 2, 3])
    np.testing.assert_allclose([float(x) for x in row[4:]], q * np.sign(q[3]), atol=1e-15)


def test_tum_reader_accepts_comments_and_short_fractions(tmp_path):
    path = tmp_path / 't.txt'
    path.write_text('# header\n\n1.5 0 0 0 0 0 0 1\n2 1 0 0 0 0 0 1\n3.25e0 2 0 0 0 0 0 1\n')
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.stamps_ns, [1_500_000_000, 2_000_000_000, 3_250_000_000])
    np.testing.assert_allclose(traj.T_world_cam[:, 0, 3], [0, 1, 2])


@pytest.mark.parametrize('line, words', [
    ('1.0 0 0 0 0 0 1', '8 fields'),
    ('1.0 0 0 x 0 0 0 1', 'non-numeric'),
    ('abc 0 0 0 0 0 0 1', 'timestamp'),
    ('1.0 0 0 0 0 0 0 2', 'norm'),
    ('1.0 0 0 inf 0 0 0 1', 'NaN'),
])
def test_tum_malformed_lines(tmp_path, line, words):
    path = tmp_path / 'bad.txt'
    path.write_text(f'0 0 0 0 0 0 0 1\n{line}\n')
    with pytest.raises(FormatError) as info:
        read_tum(path)
    assert info.value.line == 2 and f'{path}:2:' in str(info.value) and words in str(info.value)


def test_kitti_round_trip_and_layout(tmp_path, rng):
    T = _poses(rng)
    path = tmp_path / 'poses.txt'
    write_kitti(path, T)
    rows = path.read_text().splitlines()
    assert len(rows) == len(T)
    np.testing.assert_allclose(np.array(rows[3].split(), dtype=float), T[3, :3, :].ravel())
    np.testing.assert_allclose(read_kitti(path), T, atol=1e-12)


@pytest.mark.parametrize('line, words', [
    ('1 0 0 0 0 1 0 0 0 0 1', '12 values'),
    ('1 0 0 0 0 1 0 0 0 0 1 zz', 'non-numeric'),
    ('2 0 0 0 0 1 0 0 0 0 1 0', 'rotation'),
    ('-1 0 0 0 0 1 0 0 0 0 1 0', 'rotation'),
])
def test_kitti_malformed_lines(tmp_path, line, words):
    path = tmp_path / 'bad.txt'
    path.write_text(f'1 0 0 0 0 1 0 0 0 0 1 0\n{line}\n')
    with pytest.raises(FormatError) as info:
        read_kitti(path)
    assert info.value.line == 2 and words in str(info.value)


def test_writers_reject_bad_input_and_leave_no_file(tmp_path, rng):
    T = _poses(rng, 3)
    T[1, 0, 3] = np.nan
    with pytest.raises(InputError):
        write_kitti(tmp_path / 'k.txt', T)
    with pytest.raises(InputError):
        write_tum(tmp_path / 't.txt', np.arange(2), _poses(rng, 3))
    assert not list(tmp_path.iterdir())
