"""The live mosaic benchmark (ga_ros.bench.map_mosaic) on a small survey: the bound holds, each
correction warps at least the keyframes it moved, and the bytes per live keyframe are those of
its image, patch and points."""

from __future__ import annotations

from ga_ros.bench import map_mosaic


def test_small_run_keeps_the_bound_and_warps_what_moved() -> None:
    r = map_mosaic.run(40, [1, 3], live_limit=10, width=64, points=200, repeats=2)
    assert (r.keyframes, r.live, r.merged) == (40, 10, 30)
    assert r.warps[0] >= 1 and r.warps[1] >= 3
    assert all(s > 0 for s in r.update_s) and r.build_s > 0
    image = 64 * 48
    points = 200 * (12 + 16)  # float32 xyz, then cells and heights
    # the patch: grey and mask over the 20 m x 15 m footprint at 0.1 m/px, with a margin
    patch = 2 * (20 / 0.1) * (15 / 0.1)
    assert image + points + patch < r.bytes_per_live < 1.5 * (image + points + patch)
    assert r.bytes_per_merged > 128  # its pose, and its share of the static layers
