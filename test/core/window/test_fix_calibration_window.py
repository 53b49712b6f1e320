"""A fix source's time offset estimated by the window aligner's final batch
(``refine_batch(calibration=...)``, :mod:`ga_ros.core.calibration.fix_parameters`): the
fixes of a live survey, stamped late, as a GNSS receiver with latency delivers them."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.calibration import CalibrationConfig
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.sim.biased import FixSource, biased_fixes, biased_survey

TRACK = 25   # keyframes per track


def _run(seed: int, latency_s: float):
    """The survey's motions (no odometry bias) and fixes of one source every 4 keyframes with
    ``latency_s``, fed to a window aligner; returns the aligner and the true poses."""
    rng = np.random.default_rng(seed)
    s = biased_survey(rng, n_nodes=300, scale=0.0, yaw_rate=0.0)
    stamps = np.concatenate([[0.0], np.cumsum(s.dt_s)])
    obs = biased_fixes(rng, s.T_true, stamps,
                       [FixSource('gnss', every=4, sigma_m=0.3, latency_s=latency_s)])
    fixes = {int(t.node_id): t for t in obs.terms}
    arr = s.network.arrays()
    al = TrackWindowAligner(AlignerConfig(datum='fixes', refine_executor='inline'),
                            T_world_first=s.T_true[0])
    track = prev = 0
    for c in range(len(arr)):
        i = c + 1
        al.add_measurement(Measurement(c, i, prev, track, arr.z[c], arr.cov[c],
                                       int(round(stamps[i] * 1e9)), 'consecutive', 'odom0'))
        prev = track
        for node in (c, i) if c == 0 else (i,):
            if node in fixes:
                al.add_fix(fixes[node])
        if i % TRACK == 0:
            al.finish_track()
            track += 1
    al.finish_track()
    return al, s.T_true


def _rmse(al, T_true) -> float:
    T = al.corrected_path().T_world_node
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


@pytest.mark.parametrize('seed', [1, 2])
def test_the_final_batch_estimates_a_fix_sources_latency(seed) -> None:
    """0.5 s of latency: recovered within 3 sigma, and the path closer to the truth than the
    calibration without fix parameters."""
    al, T_true = _run(seed, 0.5)
    al.refine_batch(calibration=CalibrationConfig(fix_parameters=()))
    plain = _rmse(al, T_true)
    al.refine_batch(calibration=CalibrationConfig())   # the default: the time offset
    est = {p.name: p for p in al.calibration.parameters if p.source == 'gnss'}
    tau = est['time_offset']
    assert tau.estimated, al.calibration.lines()
    assert abs(tau.value - 0.5) < 3 * tau.sigma, al.calibration.lines()
    assert _rmse(al, T_true) < 0.8 * plain, (_rmse(al, T_true), plain)
    al.close()


def test_without_latency_nothing_changes() -> None:
    """No latency: the time offset is not significant and the final batch is the one without
    fix parameters bit for bit (the fixes' priors are the book's)."""
    al, _ = _run(3, 0.0)
    for _ in range(2):   # a second batch from the first one's poses, as below
        al.refine_batch(calibration=CalibrationConfig(fix_parameters=()))
    again = al.corrected_path().T_world_node.copy()
    al.close()
    al, _ = _run(3, 0.0)
    al.refine_batch(calibration=CalibrationConfig(fix_parameters=()))
    al.refine_batch(calibration=CalibrationConfig())
    est = {p.name: p for p in al.calibration.parameters if p.source == 'gnss'}
    assert not est['time_offset'].estimated
    np.testing.assert_array_equal(al.corrected_path().T_world_node, again)
    al.close()
