"""The replay's corrected path after each update, kept in step with the aligner
(:class:`~ga_ros.replay.stamped_path.StampedPath`): after every update its stamps, poses,
corrections stamps and message bytes equal what the rules applied to the whole path give
(:meth:`ReplayRun.corrected_from_scratch`, the message built as rosbags objects and
serialized), on an odometry bag with fixes and on the measurement bag whose first node no message
stamps (with and without its ground truth)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_COV_STAMPED,
    odometry_msg,
    pose_cov_stamped_msg,
    rectangle_drive,
    reference_network_markers,
)

from ga_ros.io.bag_messages import PATH, trajectory_to_path_msg, typestore
from ga_ros.io.bag_writer import BagWriter
from ga_ros.replay import run as run_module
from ga_ros.replay.stamped_path import KnownStamps

REPO = Path(__file__).resolve().parents[2]


def _checking_update(checked: list):
    """ReplayRun.update, then the kept path against the one from scratch."""
    original = run_module.ReplayRun.update

    def update(self, u, per_track=True):
        original(self, u, per_track)
        if u is None:
            return
        ref = self.corrected_from_scratch()
        cp, stamps, corr, top = self.path.sync(self.aligner, self.first_id)
        assert np.array_equal(stamps, ref.stamps_ns)
        assert np.array_equal(cp.T_world_node, ref.T_world_node)
        assert np.array_equal(cp.node_ids, ref.node_ids)
        assert np.array_equal(cp.track_ids, ref.track_ids)
        assert top == int(ref.stamps_ns.max())
        aligner_stamps = self.aligner.corrected_path().stamps_ns
        assert np.array_equal(corr, np.where(aligner_stamps < 0, ref.stamps_ns, aligner_stamps))
        msg = trajectory_to_path_msg(ref, frame_id=self.config.outputs.map_frame, stamp_ns=top)
        assert self.path.message(top) == bytes(typestore().serialize_cdr(msg, PATH))
        checked.append(self.path.mirror.changed_from)

    return update


def _odometry_bag(path: Path) -> Path:
    rng = np.random.default_rng(2)
    drive = rectangle_drive(3.0, 5.0, 1_765_000_000_000_000_000, yaw_per_step=2e-4)
    cov = np.zeros((6, 6))
    cov[0, 0] = cov[1, 1] = 0.09
    cov[2, 2] = 1.0
    with BagWriter(path) as bag:
        for k, (s, T) in enumerate(zip(drive.stamps_ns, drive.T_odom)):
            bag.write('/odom', ODOMETRY, odometry_msg(T, int(s)), int(s))
            if k % 40 == 7:
                Tm = drive.T_true[k].copy()
                Tm[:2, 3] += rng.normal(0, 0.3, 2)
                bag.write('/fix', POSE_COV_STAMPED, pose_cov_stamped_msg(Tm, int(s), cov, 'map'),
                          int(s) + 1000)
    return path


@pytest.mark.parametrize('case', ['odometry_with_fixes',
                                  pytest.param('measurements', marks=pytest.mark.slow),
                                  pytest.param('measurements_gt', marks=pytest.mark.slow)])
def test_the_kept_path_equals_the_path_from_scratch_after_every_update(
        tmp_path, monkeypatch, capsys, case) -> None:
    from ga_ros.cli.main import main

    checked: list = []
    monkeypatch.setattr(run_module.ReplayRun, 'update', _checking_update(checked))
    if case == 'odometry_with_fixes':
        args = [str(_odometry_bag(tmp_path / 'bag')), '--odom-topic', '/odom',
                '--absolute-topic', '/fix']
    else:
        args = [str(REPO / 'bags' / 'aerial_measurements')]
        if case == 'measurements':
            args += ['--ground-truth-topic', '/nothing']
    rc = main(['replay', *args, '--out', str(tmp_path / 'out'), '--no-plot', '--no-progress'])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert len(checked) >= 10
    assert max(checked) > 0, 'every update copied the whole path'


def test_known_stamps_give_numpys_median_interval() -> None:
    rng = np.random.default_rng(4)
    for _ in range(100):
        k = KnownStamps()
        values = []
        for s in rng.integers(0, 10 ** 6, int(rng.integers(0, 40))).tolist():
            k.add(s)
            values.append(s)
            known = np.sort(np.array(values, np.int64))
            want = (int(known[0] - np.median(np.diff(known))) if known.size >= 2
                    else int(known[0]))
            assert k.before_first() == want
    assert KnownStamps().before_first() == 0


@pytest.mark.parametrize(('n', 'm', 'frame'), [(0, 0, 'map'), (1, 0, 'm'), (5, 3, 'map'),
                                                (40, 70, 'world_frame'), (3, 1, 'abc')])
def test_network_markers_bytes_equal_rosbags_serialization(n: int, m: int, frame: str) -> None:
    from ga_ros.io.bag_writer import residual_color
    from ga_ros.io.cdr import network_markers_cdr

    rng = np.random.default_rng(n + m)
    p = rng.normal(size=(n, 3)) * 100
    src = rng.integers(0, max(n, 1), m) if n else np.zeros(0, int)
    dst = rng.integers(0, max(n, 1), m) if n else np.zeros(0, int)
    r = np.abs(rng.normal(size=m)) * 3
    if m:
        r[0] = np.nan
    stamp = int(rng.integers(0, 2 ** 31 * 10 ** 9))
    msg = reference_network_markers(p, src, dst, r, frame, stamp)
    want = bytes(typestore().serialize_cdr(msg, 'visualization_msgs/msg/MarkerArray'))
    assert network_markers_cdr(p, src, dst, residual_color(r), frame, stamp, 2.0, 0.5,
                               'ga') == want
