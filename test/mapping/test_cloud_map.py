"""The keyframe cloud map (ga_ros.mapping): re-anchoring by corrections against a map built from
scratch by an independent computation, the static layer, the PLY file read back by an
independent parser, the map's figures on a scene whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.mapping.cloud_map import CloudMapConfig, KeyframeCloudMap
from ga_ros.mapping.figures import map_figures
from ga_ros.mapping.ply import write_ply
from ga_ros.pipeline.corrections import CorrectionThresholds, CorrectionTracker, HeldPoses, decoded

VOXEL = 0.25
#: no decimation: the points kept are the points given (the reference uses them as given)
EXACT = CloudMapConfig(voxel_m=VOXEL, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                       max_live_keyframes=0)


def reference_map(poses: dict[int, np.ndarray], clouds: dict[int, tuple]) -> dict:
    """The voxel map written out point by point: voxel (floor(p / VOXEL)) -> (centroid,
    mean intensity), from the final poses, with Python dicts and math.floor."""
    import math

    acc: dict[tuple[int, int, int], list[float]] = {}
    for key, T in poses.items():
        if key not in clouds:
            continue
        P, inten = clouds[key]
        for p, i in zip(np.asarray(P, float), np.asarray(inten, float)):
            q = T[:3, :3] @ p + T[:3, 3]
            v = tuple(math.floor(c / VOXEL) for c in q)
            a = acc.setdefault(v, [0.0, 0.0, 0.0, 0.0, 0])
            a[0] += q[0]
            a[1] += q[1]
            a[2] += q[2]
            a[3] += i
            a[4] += 1
    return {v: (np.array(a[:3]) / a[4], a[3] / a[4]) for v, a in acc.items()}


def as_dict(cloud) -> dict:
    out = {}
    for p, i in zip(cloud.points.astype(float), cloud.intensity.astype(float)):
        v = tuple(int(np.floor(c / VOXEL)) for c in p)
        assert v not in out, 'two points in one voxel'
        out[v] = (p, i)
    return out


def assert_same_map(got, want: dict) -> None:
    got = as_dict(got)
    # a centroid lies inside its voxel, but float32 may round it onto the next voxel's
    # boundary: match every voxel, allowing a neighbour for centroids within 1e-5 m of a face
    assert len(got) == len(want)
    for v, (p, i) in want.items():
        hit = got.get(v)
        if hit is None:  # rounded across a face
            cands = [got[u] for u in got if np.abs(np.subtract(u, v)).max() <= 1
                     and np.allclose(got[u][0], p, atol=1e-5)]
            assert cands, f'voxel {v} missing'
            hit = cands[0]
        np.testing.assert_allclose(hit[0], p, atol=2e-5)
        np.testing.assert_allclose(hit[1], i, rtol=1e-6, atol=1e-4)


def random_pose(rng, scale=1.0) -> np.ndarray:
    return se3.from_translation_rotvec(rng.normal(0, 3 * scale, 3), rng.normal(0, 0.3 * scale, 3))


def random_cloud(rng, n) -> tuple[np.ndarray, np.ndarray]:
    P = rng.uniform(-2, 2, (n, 3)).astype(np.float32)
    return P, rng.uniform(0, 255, n).astype(np.float32)


class Path:
    """What CorrectionTracker.compare reads from a corrected path."""

    def __init__(self, keys, T):
        self.node_ids = np.asarray(keys, np.int64)
        self.track_ids = np.zeros(len(keys), np.int64)
        self.stamps_ns = np.asarray(keys, np.int64)
        self.T_world_node = np.asarray(T, float)


def test_reanchored_by_corrections_equals_a_map_from_scratch(rng) -> None:
    """A survey that grows by keyframes while earlier poses move, sent as corrections (both
    thresholds 0: every change); the map re-anchored from them equals the map built point by
    point from the final path. Clouds come before and after their poses."""
    n = 40
    keys = 1_000 + 7 * np.arange(n)
    clouds = {int(k): random_cloud(rng, int(rng.integers(50, 300))) for k in keys}
    T_true = np.array([random_pose(rng) for _ in keys])
    m = KeyframeCloudMap(EXACT)
    tracker = CorrectionTracker(CorrectionThresholds(0.0, 0.0))
    held = HeldPoses()   # the consumer's side of the messages (decoded poses)
    T = T_true.copy()
    moved_total = 0
    for step in range(1, n + 1, 4):
        upto = min(step + 3, n)
        # the window moves: the last 10 keyframes get new poses at each update
        lo = max(0, upto - 10)
        T[lo:upto] = [se3.from_translation_rotvec(rng.normal(0, 0.2, 3),
                                                  rng.normal(0, 0.05, 3)) @ t
                      for t in T_true[lo:upto]]
        for k in keys[step - 1:upto:2]:   # half of the clouds before their pose
            m.add_cloud(int(k), *clouds[int(k)])
        c = tracker.compare(Path(keys[:upto], T[:upto]))
        assert c is not None
        up = m.set_poses(*held.apply(c.message()))
        moved_total += up.moved
        assert up.moved + up.placed + up.pending + up.unchanged == len(c)
        for k in keys[step:upto:2]:        # the other half after
            m.add_cloud(int(k), *clouds[int(k)])
    assert moved_total > 0 and m.n_unplaced == 0 and m.n_pending_poses == 0
    np.testing.assert_array_equal(held.T_map_base, decoded(T))
    want = reference_map({int(k): T[i] for i, k in enumerate(keys)}, clouds)
    assert_same_map(m.cloud(), want)


def test_update_touches_only_the_moved_keyframes(rng) -> None:
    """A correction naming two keyframes moves their contribution only: the work counted is
    their points, and the voxels of the others are unchanged bit for bit."""
    m = KeyframeCloudMap(EXACT)
    keys = list(range(30))
    clouds = {k: random_cloud(rng, 100) for k in keys}
    T = np.array([se3.from_translation_rotvec(np.array([10.0 * k, 0, 0]), np.zeros(3))
                  for k in keys])
    for k in keys:
        m.add_cloud(k, *clouds[k])
    m.set_poses(keys, T)
    before = as_dict(m.cloud())
    T2 = T[[3, 17]].copy()
    T2[:, 2, 3] += 1.0
    up = m.set_poses([3, 17], T2)
    assert (up.moved, up.points) == (2, 2 * 2 * 100)
    assert m.set_poses([3], T2[:1]).unchanged == 1
    after = as_dict(m.cloud())
    far = {v for v in before if not (25 <= v[0] * VOXEL <= 35 or 165 <= v[0] * VOXEL <= 175)}
    assert all(before[v][0].tobytes() == after[v][0].tobytes() for v in far)
    T_all = T.copy()
    T_all[[3, 17]] = T2
    assert_same_map(m.cloud(), reference_map(dict(enumerate(T_all)), clouds))


def test_static_layer_bounds_memory_and_keeps_the_points(rng) -> None:
    """Beyond max_live_keyframes the keyframe moved longest ago joins the static layer: its
    points stay in the map, its memory goes, its later corrections are counted, not applied."""
    cfg = CloudMapConfig(voxel_m=VOXEL, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                         max_live_keyframes=5)
    m = KeyframeCloudMap(cfg)
    clouds = {k: random_cloud(rng, 200) for k in range(12)}
    T = {k: random_pose(rng) for k in range(12)}
    sizes = []
    for k in range(12):
        m.add_cloud(k, *clouds[k])
        m.set_poses([k], T[k][None])
        sizes.append(m.nbytes() - m.voxels.nbytes)
    assert m.n_live == 5 and m.n_static == 7
    assert max(sizes[5:]) <= 1.2 * sizes[4]   # bounded: does not grow with the keyframes
    assert_same_map(m.cloud(), reference_map(T, clouds))
    up = m.set_poses([0], random_pose(rng)[None])    # static: ignored, the map unchanged
    assert up.static_ignored == 1 and m.static_moves_ignored == 1
    assert_same_map(m.cloud(), reference_map(T, clouds))
    T[11] = random_pose(rng)                          # live: moved
    m.set_poses([11], T[11][None])
    assert_same_map(m.cloud(), reference_map(T, clouds))


def test_full_message_and_bounded_waits(rng) -> None:
    """unplace_all (a full corrections message) removes the live keyframes until their new
    poses come; waiting clouds and poses are bounded, the oldest dropped."""
    cfg = CloudMapConfig(voxel_m=VOXEL, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                         max_unplaced_clouds=3, max_pending_poses=2)
    m = KeyframeCloudMap(cfg)
    clouds = {k: random_cloud(rng, 50) for k in range(6)}
    T = {k: random_pose(rng) for k in range(6)}
    for k in range(6):
        m.add_cloud(k, *clouds[k])
    assert m.n_unplaced == 3 and m.clouds_dropped == 3 and len(m.cloud()) == 0
    m.set_poses([3, 4, 5, 10, 11, 12], np.array([T[3], T[4], T[5]] + [np.eye(4)] * 3))
    assert m.n_pending_poses == 2 and m.n_live == 3
    m.unplace_all()
    assert len(m.cloud()) == 0 and m.n_unplaced == 3 and m.n_pending_poses == 0
    m.set_poses([3, 4, 5], np.array([T[3], T[4], T[5]]))
    assert_same_map(m.cloud(), reference_map({k: T[k] for k in (3, 4, 5)}, clouds))
    with pytest.raises(InputError):
        m.set_poses([1, 2], np.eye(4)[None])
    with pytest.raises(InputError):
        m.add_cloud(1, np.zeros((3, 2)), np.zeros(3))


def test_decimation_keeps_a_bounded_cloud_in_its_voxels(rng) -> None:
    """Per-keyframe decimation: one centroid per keyframe voxel, at most the cap, in range."""
    cfg = CloudMapConfig(keyframe_voxel_m=0.5, max_points_per_keyframe=20, max_range_m=3.0)
    m = KeyframeCloudMap(cfg)
    P = rng.uniform(-4, 4, (5000, 3)).astype(np.float32)
    P[0] = np.nan
    kept, inten = m.decimate(P, np.ones(5000))
    assert len(kept) == 20 and np.all(np.isfinite(kept)) and np.all(inten == 1)
    assert np.all(np.linalg.norm(kept, axis=1) <= 3.0 + 0.5 * np.sqrt(3))
    kept, _ = KeyframeCloudMap(CloudMapConfig(keyframe_voxel_m=0.5, max_points_per_keyframe=0)
                               ).decimate(P, np.ones(5000))
    vox = np.floor(kept / 0.5)
    assert len(np.unique(vox, axis=0)) == len(kept)


def read_ply(path) -> tuple[list[str], np.ndarray]:
    """A PLY reader from the format's definition: ASCII header lines to end_header, then the
    vertex records in the declared property order and types (little-endian)."""
    data = path.read_bytes()
    end = data.index(b'end_header\n') + len(b'end_header\n')
    header = data[:end].decode('ascii').splitlines()
    assert header[0] == 'ply' and header[1] == 'format binary_little_endian 1.0'
    n = next(int(h.split()[2]) for h in header if h.startswith('element vertex'))
    types = {'float': '<f4', 'double': '<f8', 'uchar': 'u1', 'int': '<i4'}
    props = [(h.split()[2], types[h.split()[1]]) for h in header if h.startswith('property')]
    rec = np.frombuffer(data[end:], dtype=np.dtype(props), count=n)
    assert len(data) == end + n * rec.dtype.itemsize
    return header, rec


def test_ply_read_back_by_an_independent_parser(tmp_path, rng) -> None:
    P, inten = random_cloud(rng, 123)
    path = write_ply(tmp_path / 'map.ply', P, inten, comments=('frame map',))
    header, rec = read_ply(path)
    assert [h for h in header if h.startswith('property')] == [
        'property float x', 'property float y', 'property float z', 'property float intensity']
    assert 'comment frame map' in header
    np.testing.assert_array_equal(np.c_[rec['x'], rec['y'], rec['z']], P)
    np.testing.assert_array_equal(rec['intensity'], inten)
    empty = write_ply(tmp_path / 'empty.ply', np.zeros((0, 3)), np.zeros(0))
    assert len(read_ply(empty)[1]) == 0
    with pytest.raises(InputError):
        write_ply(tmp_path / 'bad.ply', P, inten[:-1])


def test_figures_of_a_known_scene() -> None:
    """Two horizontal layers 0.2 m apart over a 4 m x 2 m patch, one layer over a further
    2 m x 2 m: covered area 12 m^2; spread 0.1 m (std of two equal layers) where both lie,
    0 where one lies."""
    g = np.arange(0.05, 4.0, 0.1)
    x, y = np.meshgrid(g, g[:20])
    a = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    b = a + [0, 0, 0.2]
    c = a[a[:, 0] < 2.0] + [0, 2.0, 0]
    f = map_figures(np.r_[a, b, c], cell_m=1.0)
    assert f.points == len(a) + len(b) + len(c)
    assert f.covered_area_m2 == pytest.approx(12.0)
    assert f.spread_cells == 12
    stds = np.r_[np.full(8, 0.1), np.zeros(4)]
    assert f.height_spread_median_m == pytest.approx(np.median(stds), abs=1e-9)
    assert f.height_spread_mean_m == pytest.approx(stds.mean(), abs=1e-9)


def test_spread_between_groups_of_a_known_scene(rng) -> None:
    """Two tracks see a 4 m x 4 m patch 0.2 m apart in height, with noise of 0.05 m: the
    spread between their mean heights is 0.1 m per cell (the std of two values 0.2 apart),
    whatever the noise; a third track over half the patch at the first's height gives
    std(0, 0, 0.2) there."""
    from ga_ros.mapping.figures import group_height_spread

    xy = rng.uniform(0, 4, (40000, 2))
    z = rng.normal(0, 0.05, 40000)
    a = np.c_[xy, z]
    b = np.c_[xy, z + 0.2]
    s = group_height_spread(np.r_[a, b], np.r_[np.zeros(40000), np.ones(40000)], cell_m=2.0)
    assert s.cells == 4 and s.median == pytest.approx(0.1, abs=2e-3)
    c = a[a[:, 0] < 2.0]
    s3 = group_height_spread(np.r_[a, b, c], np.r_[np.zeros(40000), np.ones(40000),
                                                    np.full(len(c), 2)], cell_m=2.0)
    assert s3.cells == 4 and s3.median == pytest.approx(
        np.median([0.1, 0.1, np.std([0, 0, 0.2]), np.std([0, 0, 0.2])]), abs=2e-3)


def test_map_from_poses_keeps_every_keyframe(rng) -> None:
    """More keyframes than clouds may wait: all are in the map built at once."""
    from ga_ros.mapping.cloud_map import map_from_poses

    cfg = CloudMapConfig(voxel_m=VOXEL, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                         max_live_keyframes=0, max_unplaced_clouds=2)
    clouds = {k: random_cloud(rng, 20) for k in range(7)}
    T = {k: random_pose(rng) for k in range(7)}
    m = map_from_poses(cfg, list(T), np.array(list(T.values())), clouds)
    assert m.n_live == 7
    assert_same_map(m.cloud(), reference_map(T, clouds))


def late_loop_closure(m: KeyframeCloudMap, clouds: dict, T: dict, wobble: list[int],
                      n_updates: int, step: float = 0.3) -> None:
    """Update u places keyframe u at its pose in ``T`` and moves the keyframes of ``wobble``
    (placed at the first update) by +-``step`` m around theirs (a refinement still at work);
    a last update puts them at their poses in ``T`` (a loop closure)."""
    for u in range(n_updates):
        m.add_cloud(u, *clouds[u])
        keys = [u] + [k for k in wobble if k != u and k < max(u, 1)]
        poses = [T[k] @ se3.from_translation_rotvec(np.r_[step * (-1) ** u, 0.0, 0.0],
                                                    np.zeros(3)) if k in wobble else T[k]
                 for k in keys]
        m.set_poses(keys, np.array(poses))
        assert m.n_live <= m.config.max_live_keyframes
    m.set_poses(wobble, np.array([T[k] for k in wobble]))


def test_keyframes_that_keep_moving_stay_live(rng) -> None:
    """A refinement keeps correcting the first keyframes, then a loop closure moves them: they
    stay live while the later ones, settled, are merged, and the map equals the one built from
    the final poses. Counting every small move as a move (settle_voxels huge: the map merges
    by placement order) merges them instead and their last corrections are ignored."""
    clouds = {k: random_cloud(rng, 200) for k in range(12)}
    T = {k: random_pose(rng) for k in range(12)}
    results = {}
    for settle_voxels in (0.25, 1e6):
        cfg = CloudMapConfig(voxel_m=VOXEL, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                             max_live_keyframes=5, settle_updates=2, settle_voxels=settle_voxels)
        m = results[settle_voxels] = KeyframeCloudMap(cfg)
        late_loop_closure(m, clouds, T, [0, 1], 12)
    m = results[0.25]
    assert {0, 1} <= set(m.keys()) and m.n_static == 7
    assert m.static_settled == 7 and m.static_forced == 0 and m.static_moves_ignored == 0
    assert_same_map(m.cloud(), reference_map(T, clouds))
    by_age = results[1e6]
    assert not {0, 1} & set(by_age.keys()) and by_age.static_moves_ignored >= 2
    with pytest.raises(AssertionError):
        assert_same_map(by_age.cloud(), reference_map(T, clouds))


def test_small_moves_do_not_keep_a_keyframe_live_and_the_bound_holds(rng) -> None:
    """Moves below settle_voxels do not unsettle a keyframe (it is merged first); when every
    keyframe keeps moving the bound holds all the same and the merges are counted forced."""
    clouds = {k: random_cloud(rng, 100) for k in range(12)}
    T = {k: random_pose(rng) for k in range(12)}
    cfg = CloudMapConfig(voxel_m=VOXEL, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                         max_live_keyframes=5, settle_updates=2, settle_voxels=0.25)
    # keyframe 0 moves by 1 mm every update (far below 0.0625 m), keyframe 1 by 0.3 m
    m = KeyframeCloudMap(cfg)
    for u in range(6):
        m.add_cloud(u, *clouds[u])
        keys = list(range(u + 1))
        poses = [T[k] for k in keys]
        if u >= 1:
            poses[0] = T[0] @ se3.from_translation_rotvec(np.r_[1e-3 * u, 0, 0], np.zeros(3))
            poses[1] = T[1] @ se3.from_translation_rotvec(np.r_[0.3 * (-1) ** u, 0, 0],
                                                          np.zeros(3))
        up = m.set_poses(keys, np.array(poses))
        assert up.moved == min(u, 2)
    assert m.n_static == 1 and 0 not in m.keys() and 1 in m.keys()   # the small mover went first
    assert m.static_settled == 1 and m.static_forced == 0
    # every keyframe moving at every update: merged all the same, counted forced
    m = KeyframeCloudMap(cfg)
    for u in range(12):
        m.add_cloud(u, *clouds[u])
        keys = list(range(u + 1))
        m.set_poses(keys, np.array([T[k] @ se3.from_translation_rotvec(
            np.r_[0.3 * (-1) ** u, 0, 0], np.zeros(3)) for k in keys]))
        assert m.n_live <= 5
    assert m.n_static == 7 and m.static_forced == 7 and m.static_settled == 0
