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


def test_drift_run_matches_the_reference_only_when_nothing_moved_after_its_merge() -> None:
    """Every keyframe live: the final mosaic is the reference's, no correction ignored. A
    small live bound under corrections that go on for ~10 tracks: corrections of merged
    keyframes are ignored and the final mosaic differs from the reference's (it can fail)."""
    rows, _ = map_mosaic.run_drift(36, 36, 64, 150, sigma0_m=0.3, decay=0.7)
    assert [(r.moves_ignored, r.differing) for r in rows] == [(0, 0.0), (0, 0.0)]
    rows, _ = map_mosaic.run_drift(36, 8, 64, 150, sigma0_m=0.3, decay=0.7)
    for r in rows:
        assert r.merged_settled + r.merged_forced == 28
        assert r.moves_ignored > 0 and r.max_ignored_shift_m > 0.01 and r.differing > 0.01
