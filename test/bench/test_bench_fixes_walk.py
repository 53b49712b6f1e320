"""``ga-ros bench fixes``: the final + calibration (random walk) table (no data needed)."""

from __future__ import annotations

from ga_ros.bench.fixes import FixBenchFigures, table


def _fig(walk_m: float) -> FixBenchFigures:
    return FixBenchFigures(30.0, 2.0, 4091, 14, 31.56, 22.65, 5.81, 1.61,
                           ours_final_cal_m=1.45, ours_final_cal_stated_m=1.75,
                           ours_final_cal_walk_m=walk_m, ours_final_cal_walk_cpu_s=11.4,
                           gtsam_batch_m=1.61, isam2_online_m=6.09, isam2_final_m=1.69,
                           walk_calibration=['motion scale: not estimated (x)',
                                             'motion yaw_rate = 0.0056 ...; random walk 8 knots'],
                           update_ms_quarters=[1.0] * 4, update_cpu_ms_quarters=[1.0] * 4)


def test_walk_column_beside_gtsam_batch():
    out = table([_fig(1.449)]).splitlines()
    head = next(i for i, line in enumerate(out) if 'final+cal(walk)' in line)
    row = out[head + 1].split()
    # interval, noise, ours final + cal., the walk, GTSAM LM, both ratios, CPU, the walk's line
    assert row[4:10] == ['1.45', '1.45', '1.61', '0.901', '0.900', '11.40']
    assert 'random walk 8 knots' in out[head + 1] and 'scale' not in out[head + 1]


def test_no_walk_no_table():
    assert 'final+cal(walk)' not in table([_fig(float('nan'))])
