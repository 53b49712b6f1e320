"""Seeded stereo-image simulator of the paper's experiment 2 (Madjidi & Negahdaripour 2005, V-B).

A textured terrain with a height field (5-65 m above the reference plane ``z = 0``) is seen by a
nadir stereo camera flying at ~110 m in a lawnmower pattern. Images are rendered by ray casting:
for each pixel the ray is intersected with the height field by fixed-point iterations on the
height map, then the orthophoto texture is sampled at the hit point (vectorised numpy plus
``cv2.remap``; a 320x240 image renders in a few ms).

Frames and conventions
----------------------
* World: ``x`` east, ``y`` north, ``z`` up (m). Terrain heights are world ``z``.
* Camera (OpenCV): ``z`` forward (nadir: down), ``x`` right, ``y`` down; ``T_world_cam`` is the
  pose of the **left** camera; the right camera is ``T_world_cam @ T_left_right`` with
  ``T_left_right`` a translation of ``+baseline_m`` along the left camera's ``x``. The pair is
  rectified and undistorted by construction (identical ``K``, parallel axes).
* Image up (``-y_cam``) points along the direction of travel; the long image side is across track.

Choice of baseline
------------------
At 45-105 m depth a small (0.3 m) baseline gives disparities below 2 px at 320x240. As in the
paper (a wide-baseline rig), the default rig uses ``baseline_m = 10`` m with a focal length of
``0.75 * width`` px (67 deg horizontal field of view): disparities of 23-53 px at 320x240
(46-107 px at 640x480), so a 0.1 px matching error gives a depth error of 0.05-0.46 m.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3

_REMAP_COLS = 1024


@dataclass(frozen=True)
class StereoRig:
    """A rectified pinhole stereo rig with square pixels.

    Attributes
    ----------
    width, height : image size (px).
    focal_px : focal length (px), the same for ``x`` and ``y``.
    baseline_m : distance between the two optical centres along the left camera's ``x`` (m).
    """

    width: int = 320
    height: int = 240
    focal_px: float = 240.0
    baseline_m: float = 10.0

    @staticmethod
    def for_size(width: int, height: int, baseline_m: float = 10.0) -> StereoRig:
        """The default rig scaled to an image size (focal length ``0.75 * width`` px)."""
        return StereoRig(int(width), int(height), 0.75 * float(width), float(baseline_m))

    @property
    def K(self) -> FloatArray:
        """(3, 3) intrinsic matrix of both (rectified) cameras; principal point at the centre."""
        return np.array([[self.focal_px, 0.0, (self.width - 1) / 2.0],
                         [0.0, self.focal_px, (self.height - 1) / 2.0],
                         [0.0, 0.0, 1.0]])

    @property
    def T_left_right(self) -> FloatArray:
        """(4, 4) pose of the right camera in the left camera frame."""
        return se3.from_rt(np.eye(3), np.array([self.baseline_m, 0.0, 0.0]))


@dataclass(frozen=True)
class TerrainConfig:
    """Extent and appearance of a procedural terrain.

    Attributes
    ----------
    x_min, x_max, y_min, y_max : world extent (m).
    texture_resolution_m : ground sample distance of the orthophoto texture (m/px).
    height_resolution_m : grid spacing of the height map (m).
    min_height_m, max_height_m : relief range above the reference plane (m); paper: 5-65 m.
    relief_wavelength_m : shortest wavelength of the height octaves (m); longer = gentler slopes.
    seed : seed of the generator (the terrain is a pure function of the config).
    """

    x_min: float = -100.0
    x_max: float = 200.0
    y_min: float = -100.0
    y_max: float = 400.0
    texture_resolution_m: float = 0.15
    height_resolution_m: float = 2.0
    min_height_m: float = 5.0
    max_height_m: float = 65.0
    relief_wavelength_m: float = 150.0
    seed: int = 0


def _fractal(rng: np.random.Generator, shape: tuple[int, int], cell_m: float,
             wavelengths_m: list[float], amplitudes: list[float]) -> FloatArray:
    """Sum of smooth noise octaves (Gaussian noise on a coarse grid, bicubic upsampling)."""
    out = np.zeros(shape, np.float32)
    for wl, amp in zip(wavelengths_m, amplitudes):
        ny = max(int(np.ceil(shape[0] * cell_m / wl)) + 3, 4)
        nx = max(int(np.ceil(shape[1] * cell_m / wl)) + 3, 4)
        coarse = rng.standard_normal((ny, nx)).astype(np.float32)
        out += amp * cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    return out


def _sample(grid: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Bilinear sample of ``grid`` at fractional grid coordinates (any matching shapes)."""
    shape = gx.shape
    if gx.ndim == 2 and max(shape) < 32000:
        return cv2.remap(grid, gx.astype(np.float32), gy.astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)
    n = gx.size
    pad = (-n) % _REMAP_COLS
    fx = np.pad(gx.ravel().astype(np.float32), (0, pad)).reshape(-1, _REMAP_COLS)
    fy = np.pad(gy.ravel().astype(np.float32), (0, pad)).reshape(-1, _REMAP_COLS)
    out = cv2.remap(grid, fx, fy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.ravel()[:n].reshape(shape)


class Terrain:
    """A seeded height field with an orthophoto texture (multi-octave noise, hill shading).

    Parameters
    ----------
    config : extent, resolution, relief and seed.
    """

    def __init__(self, config: TerrainConfig = TerrainConfig()) -> None:
        if not (config.x_max > config.x_min and config.y_max > config.y_min):
            raise InputError('terrain extent is empty')
        if config.texture_resolution_m <= 0 or config.height_resolution_m <= 0:
            raise InputError('terrain resolutions must be positive')
        self.config = config
        rng = np.random.default_rng(config.seed)
        c = config
        hr = c.height_resolution_m
        hshape = (int(np.ceil((c.y_max - c.y_min) / hr)) + 1,
                  int(np.ceil((c.x_max - c.x_min) / hr)) + 1)
        wl = c.relief_wavelength_m
        h = _fractal(rng, hshape, hr, [4 * wl, 2 * wl, wl], [1.0, 0.5, 0.25])
        h = (h - h.min()) / max(float(h.max() - h.min()), 1e-6)
        #: (ny, nx) float32 height map (m), row = y index, col = x index.
        self.heights = (c.min_height_m + h * (c.max_height_m - c.min_height_m)).astype(np.float32)
        tr = c.texture_resolution_m
        tshape = (int(np.ceil((c.y_max - c.y_min) / tr)) + 1,
                  int(np.ceil((c.x_max - c.x_min) / tr)) + 1)
        wls = [40.0, 16.0, 6.0, 2.5, 1.2, 0.6]
        tex = _fractal(rng, tshape, tr, wls, [0.6, 0.8, 1.0, 1.0, 0.8, 0.5])
        edges = _fractal(rng, tshape, tr, [3.0], [1.0])
        tex = tex / max(float(tex.std()), 1e-6) + 0.8 * np.tanh(4.0 * edges)
        # Lambertian hill shading of the height field (view independent).
        gy_h, gx_h = np.gradient(self.heights, hr)
        shade = (1.0 - 0.6 * gx_h - 0.4 * gy_h) / np.sqrt(1.0 + gx_h ** 2 + gy_h ** 2)
        shade = cv2.resize(shade.astype(np.float32), (tshape[1], tshape[0]),
                           interpolation=cv2.INTER_LINEAR)
        img = (110.0 + 38.0 * tex) * (0.75 + 0.25 * shade)
        #: (ny, nx) uint8 orthophoto texture.
        self.texture = np.clip(img, 0, 255).astype(np.uint8)
        # Mip-map levels (Gaussian pyramid): level l has texels of 2^l * texture_resolution_m.
        self._mips = [self.texture]
        while len(self._mips) < 5 and min(self._mips[-1].shape) > 64:
            self._mips.append(cv2.pyrDown(self._mips[-1]))

    def height_at(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Terrain height (m) at world ``x, y`` (m), bilinear; any matching shapes."""
        c = self.config
        gx = (np.asarray(x) - c.x_min) / c.height_resolution_m
        gy = (np.asarray(y) - c.y_min) / c.height_resolution_m
        return _sample(self.heights, gx, gy).astype(float)

    def intersect(self, origin: FloatArray, directions: FloatArray, iterations: int = 12,
                  s0: np.ndarray | None = None) -> FloatArray:
        """Ray parameter ``s`` of the first hit of rays ``origin + s * d`` with the terrain.

        Parameters
        ----------
        origin : (3,) ray origin in the world frame (m), above the terrain.
        directions : (..., 3) ray directions in the world frame with ``d_z < 0``.
        iterations : fixed-point iterations ``s <- (h(x(s), y(s)) - o_z) / d_z``; they converge
            while the terrain slope times the ray's ``|d_xy| / |d_z|`` stays below one.
        s0 : (...,) initial guess of ``s``; default: the plane at the mean terrain height.

        Returns
        -------
        (...,) float32 ``s`` (in units of ``|d|``; with ``d_cam = K^-1 [u v 1]`` it is depth).
        """
        c = self.config
        d = np.asarray(directions, np.float32)
        ox, oy, oz = (float(v) for v in origin)
        dz = np.minimum(d[..., 2], -1e-6)
        inv_r = 1.0 / c.height_resolution_m
        if s0 is None:
            s = (np.float32(self.heights.mean()) - oz) / dz
        else:
            s = np.asarray(s0, np.float32)
        for _ in range(iterations):
            gx = (ox + s * d[..., 0] - c.x_min) * inv_r
            gy = (oy + s * d[..., 1] - c.y_min) * inv_r
            s = (_sample(self.heights, gx, gy) - oz) / dz
        return s

    def texture_at(self, x: np.ndarray, y: np.ndarray,
                   footprint_m: np.ndarray | None = None) -> np.ndarray:
        """Texture grey level (float32) at world ``x, y`` (m).

        ``footprint_m`` (same shape, m) is the ground size of the pixel that samples it: the
        texture is then filtered to that size (trilinear mip-mapping), as a camera integrates
        over its pixel; None samples the full-resolution texture (bilinear, may alias).
        """
        c = self.config
        gx = (x - c.x_min) / c.texture_resolution_m
        gy = (y - c.y_min) / c.texture_resolution_m
        if footprint_m is None:
            return _sample(self.texture, gx, gy).astype(np.float32)
        lod = np.clip(np.log2(np.maximum(footprint_m, 1e-9) / c.texture_resolution_m), 0,
                      len(self._mips) - 1).astype(np.float32)
        out = np.zeros(np.shape(gx), np.float32)
        for level, mip in enumerate(self._mips):
            w = np.clip(1.0 - np.abs(lod - level), 0.0, 1.0)
            if not np.any(w > 0):
                continue
            k = np.float32(0.5 ** level)
            out += w * _sample(mip, gx * k, gy * k).astype(np.float32)
        return out


@dataclass
class Survey:
    """Ground truth of a simulated lawnmower flight.

    Attributes
    ----------
    T_world_cam : (n, 4, 4) poses of the left camera.
    stamps_ns : (n,) acquisition times (ns).
    swath : (n,) swath index of each frame (turn frames carry the swath they lead into).
    track : (n,) track index (a track is one double swath: ``swath // 2``).
    in_turn : (n,) True for frames in the turn between two swaths.
    """

    T_world_cam: FloatArray
    stamps_ns: IntArray
    swath: IntArray
    track: IntArray
    in_turn: BoolArray


@dataclass(frozen=True)
class LawnmowerConfig:
    """A lawnmower flight of a nadir camera: swaths along world ``y``, stepping along ``x``.

    Attributes
    ----------
    n_tracks : number of tracks (double swaths: up then down).
    positions_per_swath : frames per swath.
    step_m : travel between consecutive frames along a swath (m).
    swath_spacing_m : distance between adjacent swaths (m).
    turn_positions : frames in the semicircular turn between swaths (0: jump to the next swath).
    altitude_m : flying height above the reference plane (m).
    attitude_jitter_deg : standard deviation of the smooth roll/pitch/yaw wobble (deg).
    position_jitter_m : standard deviation of the smooth position wobble (m).
    frame_period_s : time between frames (s).
    seed : seed of the wobble.
    """

    n_tracks: int = 2
    positions_per_swath: int = 40
    step_m: float = 6.0
    swath_spacing_m: float = 20.0
    turn_positions: int = 16
    altitude_m: float = 110.0
    attitude_jitter_deg: float = 1.0
    position_jitter_m: float = 1.0
    frame_period_s: float = 0.5
    seed: int = 0


def nadir_rotation(heading_rad: float) -> FloatArray:
    """``R_world_cam`` of a nadir camera whose image up points along ``heading_rad``.

    ``heading_rad`` is the direction of travel, measured counter-clockwise from world ``x``.
    """
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    return np.array([[s, -c, 0.0], [-c, -s, 0.0], [0.0, 0.0, -1.0]])


def _smooth_noise(rng: np.random.Generator, n: int, dims: int, width: float) -> FloatArray:
    """Unit-variance smooth noise, ``(n, dims)``, correlation length ``width`` samples."""
    raw = rng.standard_normal((n + 8 * int(width) + 1, dims))
    k = np.exp(-0.5 * (np.arange(-3 * width, 3 * width + 1) / width) ** 2)
    out = np.stack([np.convolve(raw[:, i], k, mode='same') for i in range(dims)], axis=1)
    off = 4 * int(width)
    out = out[off:off + n]
    return out / max(float(out.std()), 1e-9)


def lawnmower(config: LawnmowerConfig = LawnmowerConfig()) -> Survey:
    """Ground-truth poses of a nadir stereo camera flying a lawnmower pattern.

    Swath ``k`` runs along ``+y`` (even ``k``) or ``-y`` (odd ``k``) at ``x = k * spacing``,
    starting at ``y = 0``; turns are semicircles of diameter ``swath_spacing_m``.
    """
    c = config
    if c.n_tracks < 1 or c.positions_per_swath < 2 or c.step_m <= 0:
        raise InputError('lawnmower needs n_tracks >= 1, positions_per_swath >= 2, step_m > 0')
    length = (c.positions_per_swath - 1) * c.step_m
    pos, head, swath, turn = [], [], [], []
    for k in range(2 * c.n_tracks):
        up = k % 2 == 0
        ys = np.arange(c.positions_per_swath) * c.step_m
        ys = ys if up else length - ys
        for y in ys:
            pos.append((k * c.swath_spacing_m, y))
            head.append(np.pi / 2 if up else -np.pi / 2)
            swath.append(k)
            turn.append(False)
        if k < 2 * c.n_tracks - 1 and c.turn_positions > 0:
            r = c.swath_spacing_m / 2.0
            cx, cy = k * c.swath_spacing_m + r, (length if up else 0.0)
            for j in range(1, c.turn_positions + 1):
                a = np.pi * j / (c.turn_positions + 1)
                th = np.pi - a if up else np.pi + a
                pos.append((cx + r * np.cos(th), cy + r * np.sin(th)))
                head.append(th - np.pi / 2 if up else th + np.pi / 2)
                swath.append(k + 1)
                turn.append(True)
    n = len(pos)
    rng = np.random.default_rng(c.seed)
    att = np.deg2rad(c.attitude_jitter_deg) * _smooth_noise(rng, n, 3, 4.0)
    dpos = c.position_jitter_m * _smooth_noise(rng, n, 3, 4.0)
    T = np.zeros((n, 4, 4))
    for i in range(n):
        R = nadir_rotation(head[i]) @ so3.exp(att[i])
        p = np.array([pos[i][0], pos[i][1], c.altitude_m]) + dpos[i]
        T[i] = se3.from_rt(R, p)
    sw = np.asarray(swath, np.int64)
    stamps = (np.arange(n) * c.frame_period_s * 1e9).astype(np.int64)
    return Survey(T, stamps, sw, sw // 2, np.asarray(turn, bool))


def terrain_config_for(survey: Survey, margin_m: float = 100.0, seed: int = 0,
                       texture_resolution_m: float = 0.15) -> TerrainConfig:
    """A :class:`TerrainConfig` covering the survey's footprint plus ``margin_m``."""
    p = survey.T_world_cam[:, :3, 3]
    return TerrainConfig(float(p[:, 0].min() - margin_m), float(p[:, 0].max() + margin_m),
                         float(p[:, 1].min() - margin_m), float(p[:, 1].max() + margin_m),
                         texture_resolution_m=texture_resolution_m, seed=seed)


@dataclass
class StereoScene:
    """A terrain seen through a stereo rig: renders rectified pairs with exact ground truth.

    Attributes
    ----------
    terrain : the textured height field.
    rig : the stereo rig.
    noise_std : standard deviation of the additive image noise (grey levels).
    """

    terrain: Terrain
    rig: StereoRig = field(default_factory=StereoRig)
    noise_std: float = 1.5

    def __post_init__(self) -> None:
        u, v = np.meshgrid(np.arange(self.rig.width, dtype=np.float32),
                           np.arange(self.rig.height, dtype=np.float32))
        K = self.rig.K
        self._rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1],
                                   np.ones_like(u)], axis=-1).astype(np.float32)
        # Coarse-to-fine ray casting: converge on every 4th pixel, then refine at full size.
        self._coarse = 4
        self._up_x = (u / self._coarse).astype(np.float32)
        self._up_y = (v / self._coarse).astype(np.float32)

    def _depth(self, T: FloatArray, d: np.ndarray) -> np.ndarray:
        c = self._coarse
        s_coarse = np.ascontiguousarray(self.terrain.intersect(T[:3, 3], d[::c, ::c], 10))
        s0 = cv2.remap(s_coarse, self._up_x, self._up_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
        return self.terrain.intersect(T[:3, 3], d, 3, s0)

    def render(self, T_world_cam: FloatArray, rng: np.random.Generator | None = None,
               with_depth: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Render one ``uint8`` (height, width) image; optionally also its z-depth (m)."""
        T = np.asarray(T_world_cam, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError('T_world_cam must be a finite 4x4 pose')
        R = T[:3, :3].astype(np.float32)
        d = self._rays_cam @ R.T
        s = self._depth(T, d)
        x = T[0, 3] + s * d[..., 0]
        y = T[1, 3] + s * d[..., 1]
        # Pixel footprint on the ground ~ depth / focal length (nadir view).
        img = self.terrain.texture_at(x, y, s / np.float32(self.rig.focal_px))
        if rng is not None and self.noise_std > 0:
            img = img + rng.normal(0.0, self.noise_std, img.shape).astype(np.float32)
        img = np.clip(img + 0.5, 0, 255).astype(np.uint8)
        return (img, s) if with_depth else img

    def render_pair(self, T_world_cam: FloatArray,
                    rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render the rectified ``(left, right)`` pair of the left-camera pose ``T_world_cam``.

        ``rng`` adds independent image noise to each image (``noise_std``); None: noise free.
        """
        T = np.asarray(T_world_cam, float)
        return self.render(T, rng), self.render(T @ self.rig.T_left_right, rng)

    def ground_points(self, T_world_cam: FloatArray, step_px: int = 20) -> FloatArray:
        """World points (m) seen by a grid of pixels (every ``step_px``), shape (k, 3)."""
        T = np.asarray(T_world_cam, float)
        rays = self._rays_cam[step_px // 2::step_px, step_px // 2::step_px]
        d = rays @ T[:3, :3].T.astype(np.float32)
        s = self.terrain.intersect(T[:3, 3], d)
        return (T[:3, 3] + s[..., None] * d).reshape(-1, 3)

    def overlap(self, T_world_a: FloatArray, T_world_b: FloatArray, step_px: int = 20) -> float:
        """True image overlap: fraction of view ``a``'s ground points that view ``b`` images."""
        p = self.ground_points(T_world_a, step_px)
        Tb = se3.inverse(np.asarray(T_world_b, float))
        pc = p @ Tb[:3, :3].T + Tb[:3, 3]
        K = self.rig.K
        z = pc[:, 2]
        ok = z > 0
        u = K[0, 0] * pc[:, 0] / np.where(ok, z, 1) + K[0, 2]
        v = K[1, 1] * pc[:, 1] / np.where(ok, z, 1) + K[1, 2]
        ok &= (u >= 0) & (u <= self.rig.width - 1) & (v >= 0) & (v <= self.rig.height - 1)
        return float(ok.mean())


def make_scene(survey: Survey, rig: StereoRig | None = None, seed: int = 0,
               noise_std: float = 1.5) -> StereoScene:
    """A :class:`StereoScene` whose terrain covers ``survey`` (texture GSD matched to the rig)."""
    rig = rig or StereoRig()
    gsd = 0.6 * 45.0 / rig.focal_px  # finest ground sample distance at the highest terrain
    return StereoScene(Terrain(terrain_config_for(survey, seed=seed,
                                                  texture_resolution_m=max(gsd, 0.1))),
                       rig, noise_std)
