"""``ga-ros replay BAG --map``: the clouds of the committed stereo sample at the GA and the F2F
poses, as PLY files read back by an independent parser, and their figures in summary.json (the
GA map more consistent between tracks than the F2F one)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.map_outputs import MapOutputConfig
from ga_ros.replay.pipeline import replay

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'mapping'))
from test_cloud_map import read_ply  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / 'bags' / 'stereo_sample'


@pytest.fixture(scope='module')
def mapped(tmp_path_factory: pytest.TempPathFactory):
    if not BAG.exists():
        pytest.skip('sample bag not generated')
    out = tmp_path_factory.mktemp('map')
    return replay(BAG, out, ReplayConfig(plot=False, map=MapOutputConfig())), out


def test_map_files_and_figures(mapped) -> None:
    r, out = mapped
    summary = json.loads((out / 'summary.json').read_text())['map']
    assert summary['keyframes_with_cloud'] == r.n_nodes == 79
    for name in ('ga', 'f2f'):
        header, rec = read_ply(out / f'map_{name}.ply')
        fig = summary[name]
        assert len(rec) == fig['points'] > 10000
        assert fig['keyframes_placed'] == 79
        xyz = np.c_[rec['x'], rec['y'], rec['z']].astype(float)
        # the terrain lies 5-65 m above the reference plane (ga_ros.sim.stereo), the map is in
        # the ground truth's frame (anchored at its first pose): heights within the relief
        # plus the stereo noise
        assert np.percentile(xyz[:, 2], 1) > 0 and np.percentile(xyz[:, 2], 99) < 75
        # covered area: the occupied cells, counted here independently
        cells = {(int(np.floor(x / fig['cell_m'])), int(np.floor(y / fig['cell_m'])))
                 for x, y in xyz[:, :2]}
        assert fig['covered_area_m2'] == pytest.approx(len(cells) * fig['cell_m'] ** 2)
        assert 0 <= rec['intensity'].min() and rec['intensity'].max() <= 255
        assert any(h.startswith('comment ga_ros map') for h in header)
    # the target of issue 35: the GA cloud more consistent than the F2F one
    ga, f2f = summary['ga'], summary['f2f']
    assert ga['track_height_spread_m']['median'] < 0.8 * f2f['track_height_spread_m']['median']
    assert ga['height_spread_m']['median'] < f2f['height_spread_m']['median']
    assert summary['track_height_spread_ga_over_f2f'] == pytest.approx(
        ga['track_height_spread_m']['median'] / f2f['track_height_spread_m']['median'])
    assert r.files['map_ga'].endswith('map_ga.ply')


def test_map_of_a_measurements_bag_is_refused_with_a_warning(tmp_path: Path) -> None:
    from ga_ros.replay.samples import make_measurements_bag

    bag = make_measurements_bag(tmp_path / 'bag', n_tracks=1)
    r = replay(bag, tmp_path / 'out', ReplayConfig(plot=False, map=MapOutputConfig()))
    assert any('--map needs a stereo bag' in w for w in r.warnings)
    assert not (tmp_path / 'out' / 'map_ga.ply').exists() and not r.map
