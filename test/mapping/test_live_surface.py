"""The live height model's static layer (ga_ros.mapping.live_surface.LiveHeightGrid.merge): a
merge changes no height and drops the merged keyframes' points; afterwards the heights equal
those of ga_ros.mapping.surface.height_grid_from_points of every point (merged ones included)
while the live points of a cell are where they were, and differ only near a live keyframe that
moved. The weighted medians are checked against repeated points."""

from __future__ import annotations

import numpy as np

from ga_ros.geometry import se3
from ga_ros.mapping.live_surface import LiveHeightGrid, weighted_cell_medians
from ga_ros.mapping.surface import (
    SurfaceConfig,
    cell_medians,
    height_grid_from_points,
    place_points,
)

CONFIG = SurfaceConfig(cell_m=2.0)


def keyframes(n: int = 16, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """Points (k, 3) in each keyframe's frame over a wavy ground (heights to +-3 m, noise
    0.3 m) and poses ``T_map_kf`` 6 m apart along x: neighbours overlap."""
    rng = np.random.default_rng(seed)
    pts, T = [], []
    for k in range(n):
        t = np.array([6.0 * k, 3.0 * (k % 3), 0.0])
        T.append(se3.from_translation_rotvec(t, rng.normal(0, 0.02, 3)))
        xy = rng.uniform(-10, 10, (900, 2)) + t[:2]
        z = 3.0 * np.sin(0.2 * xy[:, 0]) * np.cos(0.15 * xy[:, 1]) + rng.normal(0, 0.3, 900)
        p_map = np.c_[xy, z]
        pts.append(((p_map - T[-1][:3, 3]) @ T[-1][:3, :3]).astype(np.float32))
    return pts, np.asarray(T)


def offline(points: list[np.ndarray], T: np.ndarray) -> dict[tuple[int, int], float]:
    """Heights of height_grid_from_points of all the points, by global cell."""
    grid = height_grid_from_points(np.concatenate(
        [place_points(p.astype(float), Tk) for p, Tk in zip(points, T)]), CONFIG)
    i0 = int(round(-grid.y_max / CONFIG.cell_m))
    j0 = int(round(grid.x_min / CONFIG.cell_m))
    i, j = np.nonzero(np.isfinite(grid.z))
    return {(a + i0, b + j0): grid.z[a, b] for a, b in zip(i.tolist(), j.tolist())}


def live_heights(g: LiveHeightGrid) -> dict[tuple[int, int], float]:
    i, j = np.nonzero(np.isfinite(g.heights))
    return {(a + g.i0, b + g.j0): g.heights[a, b] for a, b in zip(i.tolist(), j.tolist())}


def test_weighted_cell_medians_are_those_of_the_repeated_points() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(1, 80))
        i, j = rng.integers(-2, 2, n), rng.integers(0, 3, n)
        z = rng.integers(0, 6, n).astype(float)  # ties on purpose
        w = rng.integers(1, 5, n)
        got = weighted_cell_medians(i, j, z, w, 3)
        want = cell_medians(np.repeat(i, w), np.repeat(j, w), np.repeat(z, w), 3)
        for a, b in zip(got, want):
            assert np.array_equal(a, b)


def test_merge_changes_no_height_and_drops_the_points() -> None:
    points, T = keyframes()
    g = LiveHeightGrid(CONFIG)
    for k, (p, Tk) in enumerate(zip(points, T)):
        g.add_points(k, p)
        g.set_pose(k, Tk)
        g.commit()
    ref = offline(points, T)
    before = live_heights(g)
    assert before == ref  # the live model is the offline one before any merge
    held = g.points_nbytes()
    assert g.merge(list(range(8))) == 8
    assert sorted(g.keyframes) == list(range(8, 16)) and g.merged == 8
    assert g.points_nbytes() < 0.55 * held
    assert int(g.static_w.sum()) == 8 * 900
    # every cell recomputed from the live points and the static layer: nothing changes,
    # including the cells the merged and the live keyframes share
    for k in range(8, 16):
        g.set_pose(k, T[k] @ se3.from_translation_rotvec(np.array([40.0, 0, 0]), np.zeros(3)))
        g.commit()
    for k in range(8, 16):
        g.set_pose(k, T[k])
        g.commit()
    assert live_heights(g) == ref
    # a live keyframe moved: heights far from it are still exactly the offline ones; near it,
    # cells shared with merged points are approximate (the merged points' spread forgotten)
    T2 = T.copy()
    T2[9] = T[9] @ se3.from_translation_rotvec(np.array([0.7, -0.5, 0.3]), np.zeros(3))
    g.set_pose(9, T2[9])
    g.commit()
    now, want = live_heights(g), offline(points, T2)
    assert now.keys() == want.keys()
    reach = (CONFIG.radius_cells() + 1) * CONFIG.cell_m
    x9 = (T[9][0, 3], T2[9][0, 3])
    far = [c for c in want if (c[1] + 1) * CONFIG.cell_m < min(x9) - 10 - reach
           or c[1] * CONFIG.cell_m > max(x9) + 10 + reach]
    assert len(far) > 50 and all(now[c] == want[c] for c in far)
    diff = np.array([abs(now[c] - want[c]) for c in want])
    print(f'after a move next to merged points: heights off by up to {diff.max():.3f} m '
          f'(median {np.median(diff):.4f} m) against the model of every point')
    assert diff.max() < 0.05  # a tenth of the noise of one point (0.3 m)


def test_clear_static_forgets_the_merged_points() -> None:
    points, T = keyframes(6)
    g = LiveHeightGrid(CONFIG)
    for k, (p, Tk) in enumerate(zip(points, T)):
        g.add_points(k, p)
        g.set_pose(k, Tk)
    g.commit()
    g.merge([0, 1, 2])
    g.clear_static()
    g.commit()
    assert live_heights(g) == offline(points[3:], T[3:])
    assert not g.static_w.any()
