"""``ga-ros bench camcal`` (:mod:`ga_ros.bench.camera_calibration`) on a small survey: what
it prints is what it ran (the camera's estimates against the truth, GTSAM's LM on the same
graph equal to our plain adjustment)."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.bench.camera_calibration import bench_camcal, table
from ga_ros.bench.gtsam_runner import gtsam_installed

PHI = np.array([0.02, -0.01, 0.03])


def test_the_table_shows_what_ran() -> None:
    fig = bench_camcal(5, PHI, n_swaths=3, with_gtsam=False)
    assert fig.rmse_m['+camera cal'] < fig.rmse_m['plain']
    assert len(fig.estimates) == 3 and all('[truth ' in e for e in fig.estimates)
    text = table([fig])
    assert 'extrinsic_rz' in text and '0.02,-0.01,0.03' in text
    assert 'GTSAM' not in text.splitlines()[-1]   # no ratio without its column


@pytest.mark.skipif(not gtsam_installed(), reason='gtsam not installed')
def test_gtsam_reaches_our_plain_adjustment() -> None:
    fig = bench_camcal(5, PHI, n_swaths=3)
    assert fig.rmse_m['GTSAM LM'] == pytest.approx(fig.rmse_m['plain'], rel=1e-3)
    assert table([fig]).splitlines()[-1].startswith('ratio +camera cal / GTSAM LM')
