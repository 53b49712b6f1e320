"""The paper's experiment 2 (Sec. V-B) from rendered stereo: motions measured by our VO.

:func:`render_vo_survey` renders the aerial survey as stereo video with
:mod:`ga_ros.sim.stereo` (320x240, 110 m altitude, 5-65 m relief, lawnmower of 20 m swath
spacing and 10 m steps) and drives :class:`ga_ros.pipeline.stereo.StereoFrontEnd` (the front end
of ``vo_node`` and of the replay) with it: stereo VO, then cross-track matching with the
corrected path of an online :class:`~ga_ros.core.window.TrackWindowAligner` fed back, as
``vo_node`` gets the alignment node's path. Every keyframe is a node (``keyframe_max_travel_ratio``
below the step over the scene depth, so that each position of the paper's survey is one node).
The motions, their covariances (the VO's own) and the truth of every node are returned as a
:class:`VoSurvey`, which :meth:`VoSurvey.scenario` turns into the :class:`~ga_ros.sim.scenario.
Scenario` the synthetic experiments use, so the same window / batch code runs on both.

:func:`register_pair` is the paper's Fig. 12: an image of the neighbouring swath is warped into
a first view by the homography of the ground plane induced by a relative motion
(``H = K (R + t n' / d) K^-1``), and the registration error is measured in the overlap.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError, InputError
from ga_ros.geometry import se3
from ga_ros.pipeline.stereo import FrontEndConfig, ImagePair, StereoFrontEnd
from ga_ros.safe_write import write_npz
from ga_ros.sim.scenario import Scenario
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import CameraModel
from ga_ros.vo.evaluate import motion_errors
from ga_ros.vo.odometry import VoConfig

#: Cache file of :func:`render_vo_survey` in the report directory.
CACHE_NAME = 'exp2_vo_survey.npz'
#: Bump when the cached content or the pipeline that produced it changes meaning.
CACHE_VERSION = 2


@dataclass(frozen=True)
class StereoSurveyConfig:
    """What :func:`render_vo_survey` renders and how the VO runs.

    Attributes
    ----------
    n_tracks : double tracks (the paper: 25).
    positions_per_swath : frames per swath (the paper: 102, i.e. 204 per track, 1 km swaths).
    step_m : travel between frames along a swath (m); the paper: ~10 m (90 % overlap). 8 m
        here: at 10 m the VO's first frame-to-frame step (no velocity prior yet, ~30-50 px of
        image motion at 320x240) loses the track.
    turn_positions : frames in the semicircular turn between swaths (2 m apart).
    width, height : image size (px); the rig is :meth:`StereoRig.for_size` (10 m baseline).
    noise_std : image noise (grey levels).
    seed : seed of terrain, flight wobble and image noise.
    keyframe_max_travel_ratio : VO keyframe threshold (travel / median depth); below
        ``step_m / depth`` every frame of a swath is a keyframe, hence a node.
    fig12_pairs : number of overlapping image pairs of neighbouring swaths kept for Fig. 12.
    """

    n_tracks: int = 25
    positions_per_swath: int = 102
    step_m: float = 8.0
    turn_positions: int = 16
    width: int = 320
    height: int = 240
    noise_std: float = 1.5
    seed: int = 0
    keyframe_max_travel_ratio: float = 0.05
    fig12_pairs: int = 3

    def __post_init__(self) -> None:
        if self.n_tracks < 1 or self.positions_per_swath < 4 or self.step_m <= 0:
            raise InputError('stereo survey needs n_tracks >= 1, positions_per_swath >= 4 and '
                             'step_m > 0')


@dataclass
class VoSurvey:
    """Motions measured by the VO on a rendered survey, with the truth of every node.

    Attributes
    ----------
    T_true : (n, 4, 4) true ``T_world_node`` of each keyframe node (left camera), node ``k`` at
        index ``k`` (ids renumbered to ``0..n-1`` in keyframe order).
    track_ids : (n,) track of each node as the VO segmented it (a double swath).
    swath : (n,) true swath of each node's frame; ``frame`` : (n,) frame index in the survey.
    src, dst : (m,) node indices of each motion (``src < dst``).
    z : (m, 6) measured ``[t, w]`` of ``T_src_dst`` (m, rad); cov : (m, 6, 6) the VO's own
        covariance, order ``[x y z rx ry rz]``.
    cross : (m,) True for cross-track connections (the matcher), False for consecutive ones.
    depth_m : median scene depth (m) of the survey (altitude minus median terrain height).
    stats : front-end counts and timings (JSON-ready).
    fig12 : image pairs for Fig. 12: ``{'a': (k,), 'b': (k,), 'img_a': (k, h, w) uint8,
        'img_b': ..., 'plane_height_m': (k,), 'plane': (k, 4)}`` (node indices, left
        images, median ground height under ``a``, and the ground plane ``n . X = c`` fitted to
        the terrain ``a`` sees, as ``[n_x, n_y, n_z, c]`` with ``n`` the upward unit normal).
    K : (3, 3) intrinsics of the left camera.
    """

    T_true: FloatArray
    track_ids: IntArray
    swath: IntArray
    frame: IntArray
    src: IntArray
    dst: IntArray
    z: FloatArray
    cov: FloatArray
    cross: np.ndarray
    depth_m: float
    K: FloatArray
    stats: dict = field(default_factory=dict)
    fig12: dict = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return int(self.T_true.shape[0])

    def scenario(self) -> Scenario:
        """The survey as a :class:`Scenario` (truth, tracks, connections; footprint unused)."""
        return Scenario('stereo', self.T_true, self.track_ids, self.src, self.dst, 0.0,
                        self.depth_m)

    def nees(self) -> dict[str, dict[str, float]]:
        """NEES ``e' C^-1 e`` of the measured motions against the truth (``e = log(T_true^-1
        T_meas)``, 6 dof: mean 6 when the covariances are honest), consecutive and cross."""
        T_rel = se3.relative(self.T_true[self.src], self.T_true[self.dst])
        out: dict[str, dict[str, float]] = {}
        for name, sel in (('consecutive', ~self.cross), ('cross', self.cross)):
            idx = np.nonzero(sel)[0]
            vals = np.array([motion_errors(T_rel[k], Measurement(0, 1, 0, 0, self.z[k],
                                                                  self.cov[k]))
                             for k in idx]).reshape(-1, 3)
            out[name] = {'n': int(idx.size)}
            if idx.size:
                out[name].update({
                    'nees_mean': float(vals[:, 2].mean()), 'nees_median': float(
                        np.median(vals[:, 2])), 'nees_p90': float(np.percentile(vals[:, 2], 90)),
                    'expected_mean': 6.0, 'translation_error_median_m': float(
                        np.median(vals[:, 0])), 'rotation_error_median_deg': float(
                        np.median(vals[:, 1]))})
        return out


def _mono8(img: np.ndarray) -> SimpleNamespace:
    """A ``sensor_msgs/Image``-like mono8 message (fields read by ``image_to_grey``)."""
    h, w = img.shape
    return SimpleNamespace(height=h, width=w, encoding='mono8', is_bigendian=0, step=w,
                           data=np.ascontiguousarray(img))


def _camera_models(rig: StereoRig) -> tuple[CameraModel, CameraModel]:
    """Left and right CameraInfo-like models of a rectified rig."""
    K = rig.K
    P_l = np.hstack([K, np.zeros((3, 1))])
    P_r = P_l.copy()
    P_r[0, 3] = -K[0, 0] * rig.baseline_m
    return (CameraModel(rig.width, rig.height, K, P=P_l),
            CameraModel(rig.width, rig.height, K, P=P_r))


def _cache_key(cfg: StereoSurveyConfig) -> str:
    return json.dumps({'version': CACHE_VERSION, **asdict(cfg)}, sort_keys=True)


def save_survey(vs: VoSurvey, cfg: StereoSurveyConfig, path: Path) -> None:
    """Write ``vs`` to ``path`` (npz) with the key of ``cfg``."""
    f = vs.fig12
    write_npz(
        path, compressed=True, key=_cache_key(cfg), T_true=vs.T_true, track_ids=vs.track_ids,
        swath=vs.swath,
        frame=vs.frame, src=vs.src, dst=vs.dst, z=vs.z, cov=vs.cov, cross=vs.cross,
        depth_m=vs.depth_m, K=vs.K, stats=json.dumps(vs.stats),
        fig12_a=f.get('a', np.zeros(0, int)), fig12_b=f.get('b', np.zeros(0, int)),
        fig12_img_a=f.get('img_a', np.zeros((0, 1, 1), np.uint8)),
        fig12_img_b=f.get('img_b', np.zeros((0, 1, 1), np.uint8)),
        fig12_h=f.get('plane_height_m', np.zeros(0)), fig12_plane=f.get('plane',
                                                                        np.zeros((0, 4))))


def load_survey(cfg: StereoSurveyConfig, path: Path) -> VoSurvey | None:
    """The cached survey at ``path`` if it was made with ``cfg`` (else None)."""
    if not path.is_file():
        return None
    try:
        d = np.load(path, allow_pickle=False)
        if str(d['key']) != _cache_key(cfg):
            return None
        h = d['fig12_h']
        plane = d['fig12_plane'] if 'fig12_plane' in d else np.column_stack(
            [np.zeros((h.size, 2)), np.ones(h.size), h])  # files without the fitted plane
        fig12 = {'a': d['fig12_a'], 'b': d['fig12_b'], 'img_a': d['fig12_img_a'],
                 'img_b': d['fig12_img_b'], 'plane_height_m': h, 'plane': plane}
        return VoSurvey(d['T_true'], d['track_ids'], d['swath'], d['frame'], d['src'],
                        d['dst'], d['z'], d['cov'], d['cross'], float(d['depth_m']), d['K'],
                        json.loads(str(d['stats'])), fig12)
    except (OSError, KeyError, ValueError):
        return None


def render_vo_survey(cfg: StereoSurveyConfig, cache: Path | None = None,
                     log: Callable[[str], None] | None = None) -> VoSurvey:
    """Render the survey, run the stereo front end on it (VO + cross-track matching with the
    online aligner's corrected path fed back) and collect motions and truth.

    Parameters
    ----------
    cfg : survey and VO settings.
    cache : npz file; when it holds a survey made with ``cfg`` it is returned without
        rendering, else the new survey is written there.
    log : optional ``callable(str)`` for progress lines.

    Raises
    ------
    InputError
        When the VO lost its track (the keyframe chain is broken: no F2F, no single network).
    """
    if cache is not None:
        cached = load_survey(cfg, cache)
        if cached is not None:
            return cached
    say = log or (lambda s: None)
    t_all = time.perf_counter()
    survey = lawnmower(LawnmowerConfig(n_tracks=cfg.n_tracks,
                                       positions_per_swath=cfg.positions_per_swath,
                                       step_m=cfg.step_m, turn_positions=cfg.turn_positions,
                                       seed=cfg.seed))
    rig = StereoRig.for_size(cfg.width, cfg.height)
    t0 = time.perf_counter()
    scene = make_scene(survey, rig, seed=cfg.seed, noise_std=cfg.noise_std)
    terrain_s = time.perf_counter() - t0
    front = StereoFrontEnd(FrontEndConfig(
        vo=VoConfig(keyframe_max_travel_ratio=cfg.keyframe_max_travel_ratio)))
    front.set_camera_models(*_camera_models(rig))
    run = _drive_front_end(front, survey, scene, cfg.seed, say)
    vs = _collect_survey(run, front, survey, scene, rig)
    vs.fig12 = _fig12_pairs(vs, scene, cfg.fig12_pairs)
    stats = front.stats
    vs.stats = {
        'frames': len(survey.T_world_cam), 'keyframes': vs.n_nodes, 'motions': len(run.meas),
        'consecutive': int((~vs.cross).sum()), 'cross': int(vs.cross.sum()),
        'cross_attempts': stats.cross_attempts, 'cross_duplicates_dropped': run.duplicates,
        'front_end': stats.summary(),
        'image_size': f'{cfg.width}x{cfg.height}', 'baseline_m': rig.baseline_m,
        'seconds': {'terrain': terrain_s, **run.seconds,
                    'total': time.perf_counter() - t_all}}
    if cache is not None:
        save_survey(vs, cfg, cache)
    return vs


@dataclass
class _FrontEndRun:
    """What :func:`_drive_front_end` collected.

    Attributes
    ----------
    meas : the motions the online aligner accepted, in arrival order.
    node_frame : survey frame index of each keyframe id.
    duplicates : cross-track motions dropped because they repeat a consecutive one.
    seconds : wall-clock seconds of ``render``, ``vo``, ``cross_track`` and ``online_window``.
    """

    meas: list[Measurement] = field(default_factory=list)
    node_frame: dict[int, int] = field(default_factory=dict)
    duplicates: int = 0
    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(
        ('render', 'vo', 'cross_track', 'online_window'), 0.0))


def _drive_front_end(front: StereoFrontEnd, survey, scene, seed: int,
                     say: Callable[[str], None]) -> _FrontEndRun:
    """Render every frame of ``survey``, feed it to ``front`` and its motions to an online
    :class:`~ga_ros.core.window.TrackWindowAligner`, whose corrected path goes back to the
    front end (as ``vo_node`` gets the alignment node's path)."""
    from ga_ros.core.window import AlignerConfig, TrackWindowAligner

    frame_of_stamp = {int(s): i for i, s in enumerate(survey.stamps_ns)}
    rng = np.random.default_rng(seed + 1)
    run = _FrontEndRun()
    sec = run.seconds
    aligner = None
    n = len(survey.T_world_cam)
    for i in range(n):
        t0 = time.perf_counter()
        left, right = scene.render_pair(survey.T_world_cam[i], rng)
        t1 = time.perf_counter()
        front.stats.pairs += 1  # the pairing step is skipped: the images come paired
        frame = front.process_pair(ImagePair(_mono8(left), _mono8(right),
                                             int(survey.stamps_ns[i])))
        t2 = time.perf_counter()
        sec['render'] += t1 - t0
        sec['vo'] += t2 - t1
        for node, stamp in frame.node_stamps.items():
            run.node_frame[node] = frame_of_stamp[stamp]
        new = [frame.measurement] if frame.measurement is not None else []
        t3 = time.perf_counter()
        if frame.measurement is not None:
            new += _cross_measurements(front, frame, run)
        t4 = time.perf_counter()
        sec['cross_track'] += t4 - t3
        for m in new:
            if aligner is None:
                aligner = TrackWindowAligner(AlignerConfig(), T_world_first=survey.T_world_cam[
                    run.node_frame[m.src_id]])
            try:
                updates = aligner.add_measurement(m)
            except GaError:
                continue  # counted by the aligner; the measurement stays out, as in the node
            run.meas.append(m)
            if updates:
                path = aligner.corrected_path()
                front.set_corrected(path.node_ids, path.T_world_node)
        sec['online_window'] += time.perf_counter() - t4
        if (i + 1) % 500 == 0:
            say(f'  stereo survey: {i + 1}/{n} pairs, {len(run.meas)} motions')
    return run


def _cross_measurements(front: StereoFrontEnd, frame, run: _FrontEndRun) -> list[Measurement]:
    """The accepted cross-track motions of ``frame``'s keyframe; those that repeat the
    consecutive keyframe pair are counted in ``run.duplicates`` and dropped."""
    out = []
    for a in front.match(frame):
        if not a.accepted or a.measurement is None:
            continue
        if a.measurement.dst_id == a.measurement.src_id + 1:
            # the same keyframe pair as the consecutive motion (around a turn): the network
            # keeps one connection per pair
            run.duplicates += 1
            continue
        out.append(a.measurement)
    return out


def _collect_survey(run: _FrontEndRun, front: StereoFrontEnd, survey, scene,
                    rig: StereoRig) -> VoSurvey:
    """The motions and the truth of every keyframe node as a :class:`VoSurvey` (without
    ``fig12`` and ``stats``); refused when the keyframe chain is broken."""
    stats = front.stats
    if stats.lost:
        raise InputError(f'the VO lost its track {stats.lost} time(s) ({stats.lost_reasons}); '
                         'experiment 2 needs one unbroken keyframe chain: change the seed or '
                         'the survey')
    node_frame, meas = run.node_frame, run.meas
    ids = np.array(sorted(node_frame), dtype=np.int64)
    if not np.array_equal(ids, np.arange(ids.size)):
        raise InputError('keyframe ids are not 0..n-1; experiment 2 expects a fresh front end')
    frames = np.array([node_frame[k] for k in ids.tolist()], dtype=np.int64)
    track = np.zeros(ids.size, dtype=np.int64)
    for m in meas:
        track[m.src_id], track[m.dst_id] = m.src_track, m.dst_track
    src = np.array([m.src_id for m in meas], dtype=np.int64)
    dst = np.array([m.dst_id for m in meas], dtype=np.int64)
    cross = np.array([m.kind == 'cross' for m in meas], dtype=bool)
    T_true = survey.T_world_cam[frames]
    heights = scene.terrain.height_at(T_true[:, 0, 3], T_true[:, 1, 3])
    return VoSurvey(T_true, track, survey.swath[frames], frames, src, dst,
                    np.array([m.z for m in meas]), np.array([m.cov for m in meas]), cross,
                    float(np.median(T_true[:, 2, 3] - heights)), rig.K)


def _fig12_pairs(vs: VoSurvey, scene, k: int) -> dict:
    """``k`` cross-track connections of neighbouring swaths, one in each ``k``-th of the
    survey: the one whose keyframe chain between the two views is the longest there (the F2F
    motion between them then has the most drift to remove), with their noise-free left images
    and the ground plane fitted (least squares) to the terrain ``a`` sees."""
    idx = np.nonzero(vs.cross & (np.abs(vs.swath[vs.src] - vs.swath[vs.dst]) == 1))[0]
    empty = {'a': np.zeros(0, int), 'b': np.zeros(0, int)}
    if idx.size == 0 or k < 1:
        return empty
    picks = []
    edges = np.linspace(0, vs.n_nodes, k + 1)
    for j in range(k):
        sel = idx[(vs.dst[idx] >= edges[j]) & (vs.dst[idx] < edges[j + 1])]
        if sel.size:
            picks.append(int(sel[np.argmax(vs.dst[sel] - vs.src[sel])]))
    a, b = vs.src[picks], vs.dst[picks]
    T = vs.T_true
    img_a = np.stack([scene.render(T[i]) for i in a])
    img_b = np.stack([scene.render(T[i]) for i in b])
    heights, planes = [], []
    for i in a:
        g = scene.ground_points(T[i], step_px=10)
        heights.append(float(np.median(g[:, 2])))
        # z = p x + q y + r  ->  n = (-p, -q, 1) / |.|, c = r / |.|
        (p, q, r), *_ = np.linalg.lstsq(np.column_stack([g[:, :2], np.ones(len(g))]), g[:, 2],
                                        rcond=None)
        norm = float(np.sqrt(p * p + q * q + 1.0))
        planes.append([-p / norm, -q / norm, 1.0 / norm, r / norm])
    return {'a': a, 'b': b, 'img_a': img_a, 'img_b': img_b,
            'plane_height_m': np.array(heights), 'plane': np.array(planes)}


@dataclass(frozen=True)
class Registration:
    """Image ``b`` warped into view ``a`` and how well it registers.

    Attributes
    ----------
    warped : (h, w) uint8, ``b`` seen from ``a`` through the ground-plane homography.
    mask : (h, w) bool, pixels of ``a`` that ``b`` covers.
    overlap : fraction of ``a`` covered.
    mean_abs_diff : mean ``|a - warped|`` over the overlap (grey levels); NaN below 5 % overlap.
    ncc : normalised cross-correlation over the overlap (1: perfect); NaN below 5 % overlap.
    """

    warped: np.ndarray
    mask: np.ndarray
    overlap: float
    mean_abs_diff: float
    ncc: float


def ground_homography(K: FloatArray, T_world_a: FloatArray, T_world_b: FloatArray,
                      plane: float | FloatArray) -> FloatArray:
    """Homography of a ground plane from pixels of ``a`` to pixels of ``b``:
    ``H = K (R_ba + t_ba n_a' / d_a) K^-1``.

    Parameters
    ----------
    K : (3, 3) intrinsics of both views.
    T_world_a, T_world_b : (4, 4) camera poses (OpenCV camera axes).
    plane : a height ``h`` (m) for the horizontal plane ``z_world = h``, or ``[n_x, n_y, n_z,
        c]``: the plane ``n . X = c`` in the world frame, ``n`` the upward unit normal.

    ``n_a`` is the plane's normal pointing away from camera ``a``, in ``a``'s frame, and
    ``d_a`` the distance of ``a`` from the plane, both from ``T_world_a``; ``(R_ba, t_ba)`` is
    ``T_world_b^-1 T_world_a``. Only the relative motion and the pose of ``a`` relative to the
    plane matter, so an estimate of the poses gives the registration that estimate implies.
    """
    pl = np.atleast_1d(np.asarray(plane, float))
    n_w, c = (np.array([0.0, 0.0, 1.0]), float(pl[0])) if pl.size == 1 else (pl[:3], pl[3])
    T_ba = se3.inverse(np.asarray(T_world_b, float)) @ np.asarray(T_world_a, float)
    n_a = np.asarray(T_world_a)[:3, :3].T @ -n_w
    d_a = float(n_w @ np.asarray(T_world_a)[:3, 3] - c)
    if d_a <= 0:
        raise InputError(f'camera a is {d_a:.1f} m above the ground plane; it must be above it')
    H = K @ (T_ba[:3, :3] + np.outer(T_ba[:3, 3], n_a) / d_a) @ np.linalg.inv(K)
    return H / H[2, 2]


def register_pair(img_a: np.ndarray, img_b: np.ndarray, H_ab: FloatArray) -> Registration:
    """Warp ``img_b`` into view ``a`` (``cv2.warpPerspective`` with ``H_ab``: pixel of ``a`` to
    pixel of ``b``) and measure the registration error over the overlap."""
    h, w = img_a.shape
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped = cv2.warpPerspective(img_b, H_ab, (w, h), flags=flags)
    mask = cv2.warpPerspective(np.full(img_b.shape, 255, np.uint8), H_ab, (w, h),
                               flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    overlap = float(mask.mean())
    if overlap < 0.05:
        return Registration(warped, mask, overlap, float('nan'), float('nan'))
    a = img_a[mask].astype(float)
    b = warped[mask].astype(float)
    mad = float(np.abs(a - b).mean())
    a0, b0 = a - a.mean(), b - b.mean()
    ncc = float((a0 @ b0) / max(np.sqrt((a0 @ a0) * (b0 @ b0)), 1e-12))
    return Registration(warped, mask, overlap, mad, ncc)
