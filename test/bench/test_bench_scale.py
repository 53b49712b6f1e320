"""``ga-ros bench scale`` (:mod:`ga_ros.bench.scale`) on a tiny survey: what it prints is what it
ran."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np


def _module():
    from ga_ros.bench import scale

    return scale


def test_lazy_measurements_equal_the_scenario_list() -> None:
    from ga_ros.sim.aerial import aerial_scenario

    sc = aerial_scenario(n_tracks=2, positions_per_swath=6)
    rng = np.random.default_rng(3)
    z = rng.normal(size=(sc.n_connections, 6))
    cov = np.broadcast_to(np.eye(6), (sc.n_connections, 6, 6)).copy()
    lazy = list(_module().lazy_measurements(sc, z, cov))
    ref = sc.measurements(z, cov)
    assert len(lazy) == len(ref)
    for a, b in zip(lazy, ref):
        assert (a.src_id, a.dst_id, a.src_track, a.dst_track, a.stamp_ns, a.kind) == \
            (b.src_id, b.dst_id, b.src_track, b.dst_track, b.stamp_ns, b.kind)
        np.testing.assert_array_equal(a.z, b.z)


def test_rss_slope_follows_the_minima_of_each_block() -> None:
    """A growth of 2 KiB/pose with a 27 MiB transient present at random tracks: the slope of
    the block minima is the growth; a plain fit through every sample is not."""
    rng = np.random.default_rng(0)
    poses = 200 * np.arange(1, 101)
    rss = 300 + poses * 2 / 1024 + 27 * (rng.random(100) < np.linspace(0.0, 0.9, 100))
    assert abs(_module().rss_slope(poses, rss, 5) - 2.0) < 0.05
    assert abs(np.polyfit(poses, rss, 1)[0] * 1024 - 2.0) > 0.5
    assert np.isnan(_module().rss_slope(poses[:3], rss[:3], 5))


def test_tiny_run_reports_every_figure() -> None:
    res = subprocess.run([sys.executable, '-m', 'ga_ros.cli.main', 'bench', 'scale',
                          '--tracks', '3', '--positions-per-swath', '8', '--checkpoints', '1,3,9',
                          '--span', '2',
                          '--json', '--restore-timeout', '120'],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    fig = json.loads(res.stdout)
    assert fig['tracks_done'] == 3 and fig['poses_done'] == 3 * 16
    assert len(fig['update_ms']) == 3
    assert [c['tracks'] for c in fig['checkpoints']] == [1, 3]
    assert fig['update_poses'] == [17, 33, 48]  # the next track's first node is in
    assert len(fig['update_rss_before_mib']) == 3 and min(fig['update_rss_before_mib']) > 50
    # blocks of span // 2 = 1 track: the line through every sample
    slope = np.polyfit(fig['update_poses'], fig['update_rss_before_mib'], 1)[0] * 1024
    assert abs(fig['checkpoints'][1]['kib_per_pose_fit'] - slope) < 1e-9 * max(1, abs(slope))
    assert fig['missing_checkpoints'] == [9]
    cp = fig['checkpoints'][1]
    assert cp['update_ms_max'] == max(fig['update_ms'][1:])  # the span of 2 tracks
    assert len(fig['update_cpu_ms']) == 3 and min(fig['update_cpu_ms']) > 0
    # the update's own thread: part of the process's CPU in the same call
    own = fig['update_thread_cpu_ms']
    assert len(own) == 3 and all(0 < t <= c + 1.0 for t, c in zip(own, fig['update_cpu_ms']))
    assert 0 < cp['thread_cpu_ms_p50'] <= cp['thread_cpu_ms_p95']
    assert fig['load_note'] == 'ok' and fig['load_seconds'] > 0 and fig['state_mib'] > 0
    assert fig['batch_converged'] is True
    # the kernel's peak (ru_maxrss) and current (statm) counters are synced in batches of
    # pages: they may disagree by a fraction of a MiB
    assert fig['peak_rss_after_batch_mib'] >= fig['rss_before_batch_mib'] - 1.0
    assert fig['rss_before_batch_mib'] > 50
