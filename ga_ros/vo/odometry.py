"""Keyframe-based stereo visual odometry (ROS-free): :class:`StereoOdometry`.

Pipeline of :meth:`StereoOdometry.process` (one call per rectified stereo pair):

1. At a keyframe: corners in the left image (``cv2.goodFeaturesToTrack``), their disparity by
   pyramidal Lucas-Kanade along the rectified rows with a left-right consistency check, and
   3-D points with covariances (:mod:`ga_ros.vo.motion`). ORB features are stereo-matched the
   same way and kept for the cross-track store (:mod:`ga_ros.vo.crosstrack`).
2. Every frame: the keyframe's features are tracked from the previous frame by KLT, started at
   their positions predicted by a constant-velocity model.
3. ``cv2.solvePnPRansac`` (keyframe 3-D points to current pixels) then weighted Gauss-Newton
   refinement with the covariance ``s^2 (J^T C^-1 J)^-1`` (:func:`ga_ros.vo.motion.refine_motion`).
4. A frame becomes the next keyframe when the tracked fraction, the travel relative to the scene
   depth, or the rotation passes a threshold; the motion keyframe-to-keyframe is then emitted
   as a :class:`ga_ros.core.measurement.Measurement` (node ids = keyframe ids).

Bad frames (wrong size or type) raise :class:`ga_ros.errors.InputError` and change nothing. A
textureless frame or a lost track returns a result without a measurement and the odometry
re-initialises (a new keyframe with a new node id, no motion to the previous one).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.core.tracks import TrackRules, TrackSegmenter
from ga_ros.errors import DegenerateGeometryError, InputError
from ga_ros.geometry import se3, so3
from ga_ros.runtime import lazy_import
from ga_ros.vo.calibration import StereoCalibration
from ga_ros.vo.motion import point_covariance, project, refine_motion, triangulate

cv2 = lazy_import('cv2')  # imported on first use (start-up of the command line)


@dataclass(frozen=True)
class VoConfig:
    """Parameters of :class:`StereoOdometry` (mirrored one to one by ``config/vo.yaml``).

    Attributes
    ----------
    max_features : corners detected per keyframe.
    feature_quality : ``qualityLevel`` of ``cv2.goodFeaturesToTrack`` (fraction of the best).
    min_feature_distance_px : minimum distance between corners (px).
    klt_window_px : Lucas-Kanade window size (px, odd).
    klt_levels : pyramid levels for temporal tracking.
    klt_derotate_deg : when the predicted in-plane image rotation exceeds this (deg), the
        previous image is warped by the predicted similarity before KLT (0: never).
    stereo_levels : pyramid levels for stereo matching (disparities can be large).
    expected_depth_m : scene depth used to seed the first stereo search (m); 0: no seed.
    min_disparity_px : smallest accepted disparity (px).
    max_row_error_px : largest accepted vertical offset of a stereo match (px).
    max_lr_error_px : largest accepted left-right-left round-trip error (px).
    pnp_reprojection_px : RANSAC inlier threshold (px).
    pnp_iterations : RANSAC iterations.
    min_inliers : fewer PnP inliers than this = track lost.
    sigma_track_px : prior image noise of tracked features at the current frame (px): a
        lower bound of the KLT error on good texture. The motion covariance is
        ``max(s^2, 1)`` times the prior's (:mod:`ga_ros.vo.motion`): residuals above the prior
        scale it up, a still camera (residuals of 0.01 px) never shrinks it.
    sigma_disparity_px : prior disparity noise (px), the same kind of lower bound.
    covariance_scale : factor applied to the estimated covariance. 1.0 with the default priors
        (0.07 / 0.05 px) and ``s^2`` floored at 1: the consecutive motions' NEES on the
        simulator is then near or below its expected 6 (``ga-ros bench vo``). Larger priors
        would make the floor dominate and the covariance several times too large.
    keyframe_min_tracked_fraction : new keyframe when fewer inliers than this fraction remain.
    keyframe_max_travel_ratio : new keyframe when travel / median depth exceeds this.
    keyframe_max_rotation_deg : new keyframe when the rotation exceeds this (deg).
    keyframe_min_inliers : new keyframe when fewer inliers remain (and at least ``min_inliers``).
    min_texture_std : grey-level standard deviation below which a frame is textureless.
    orb_features : ORB features per keyframe for cross-track matching (0: none).
    orb_levels : ORB pyramid levels (the altitude barely changes: few levels suffice).
    orb_subpixel : refine ORB keypoints with ``cv2.cornerSubPix``.
    keyframe_images : keep each keyframe's left image in its store record (cross-track LK
        refinement; 77 kB per keyframe at 320x240).
    max_sigma0_sq : a motion whose variance factor exceeds this is treated as a lost track
        (450: residuals of 1.5 px rms at ``sigma_track_px`` 0.07).
    track : track boundaries (parameters ``track.<field>``,
        :class:`ga_ros.core.tracks.TrackRules`); default ``mode`` ``'heading'`` (a reversal of
        the travel direction ends a swath, two swaths a track: the survey's double swath).
    heading_min_step_depth_ratio : ``track.heading_min_step_m`` as a fraction of the median
        scene depth at the keyframe (0.02: 1.6 m at 80 m, 6 cm at 3 m), so that every keyframe
        and track rule scales with the scene and works from 1 m to 150 m without tuning; 0: use
        ``track.heading_min_step_m``.
    first_node_id : id of the first keyframe.
    """

    max_features: int = 300
    feature_quality: float = 0.01
    min_feature_distance_px: float = 10.0
    klt_window_px: int = 15
    klt_levels: int = 3
    klt_derotate_deg: float = 2.0
    stereo_levels: int = 4
    expected_depth_m: float = 0.0
    min_disparity_px: float = 1.0
    max_row_error_px: float = 1.0
    max_lr_error_px: float = 0.5
    pnp_reprojection_px: float = 2.0
    pnp_iterations: int = 100
    min_inliers: int = 25
    sigma_track_px: float = 0.07
    sigma_disparity_px: float = 0.05
    covariance_scale: float = 1.0
    keyframe_min_tracked_fraction: float = 0.5
    keyframe_max_travel_ratio: float = 0.2
    keyframe_max_rotation_deg: float = 15.0
    keyframe_min_inliers: int = 60
    min_texture_std: float = 3.0
    orb_features: int = 500
    orb_levels: int = 1
    orb_subpixel: bool = False
    keyframe_images: bool = True
    max_sigma0_sq: float = 450.0
    track: TrackRules = TrackRules(mode='heading')
    heading_min_step_depth_ratio: float = 0.02
    first_node_id: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.track, TrackRules):
            raise InputError(f'track must be a TrackRules, got {type(self.track).__name__}')
        if self.max_features < 8 or self.min_inliers < 6 or self.klt_window_px < 5:
            raise InputError('max_features >= 8, min_inliers >= 6, klt_window_px >= 5 required')


@dataclass
class StereoFrame:
    """A stereo pair (rectified or raw, see :class:`StereoCalibration`) and its time.

    Attributes
    ----------
    left, right : (height, width) uint8 grey, or (height, width, 3) uint8 BGR images.
    stamp_ns : acquisition time (ns).
    """

    left: np.ndarray
    right: np.ndarray
    stamp_ns: int = 0


class VoState(enum.Enum):
    """State of :class:`StereoOdometry`."""

    UNINITIALISED = 'uninitialised'
    TRACKING = 'tracking'
    LOST = 'lost'


@dataclass
class Keyframe:
    """What the cross-track store keeps of a keyframe.

    Attributes
    ----------
    node_id, track_id : ids of the keyframe node.
    segment : swath counter (``'heading'`` mode) or track id; cross-track candidates must come
        from another segment.
    stamp_ns : acquisition time (ns).
    T_world_kf : (4, 4) pose from the odometry's own integration (its world = first camera).
    uv : (n, 2) ORB keypoint positions (px); ``octave`` (n,) their pyramid level.
    descriptors : (n, 32) uint8 ORB descriptors.
    points : (n, 3) stereo points in the keyframe's camera frame (m); ``points_cov`` (n, 3, 3).
    median_depth_m : median depth of the points (m).
    image : the rectified left image (uint8), for the sub-pixel refinement of cross-track
        correspondences; None when not kept.
    """

    node_id: int
    track_id: int
    segment: int
    stamp_ns: int
    T_world_kf: FloatArray
    uv: FloatArray
    octave: np.ndarray
    descriptors: np.ndarray
    points: FloatArray
    points_cov: FloatArray
    median_depth_m: float
    image: np.ndarray | None = None


@dataclass
class VoResult:
    """Outcome of one :meth:`StereoOdometry.process` call.

    Attributes
    ----------
    state : state after the call.
    status : ``'initialised'``, ``'tracked'``, ``'keyframe'``, ``'lost'`` or ``'rejected'``.
    reason : why a frame was lost or rejected ('' otherwise).
    stamp_ns : time of the frame.
    keyframe_id : node id of the current reference keyframe (-1 when none).
    track_id : track of the frame.
    measurement : keyframe-to-keyframe motion emitted at a new keyframe, else None.
    keyframe : the new keyframe's store record (at ``'initialised'`` / ``'keyframe'``).
    T_kf_cur : (4, 4) motion of this frame from the reference keyframe (None when lost).
    cov : (6, 6) covariance of ``T_kf_cur``.
    T_world_cam : (4, 4) integrated pose (world = first camera frame).
    n_features, n_tracked, n_inliers : keyframe features, KLT survivors, motion inliers.
    sigma0_sq : variance factor of the motion refinement.
    median_depth_m : median scene depth at the keyframe (m).
    new_track : True when this frame started a new track.
    """

    state: VoState
    status: str
    reason: str = ''
    stamp_ns: int = 0
    keyframe_id: int = -1
    track_id: int = 0
    measurement: Measurement | None = None
    keyframe: Keyframe | None = None
    T_kf_cur: FloatArray | None = None
    cov: FloatArray | None = None
    T_world_cam: FloatArray = field(default_factory=lambda: np.eye(4))
    n_features: int = 0
    n_tracked: int = 0
    n_inliers: int = 0
    sigma0_sq: float = float('nan')
    median_depth_m: float = float('nan')
    new_track: bool = False


class StereoOdometry:
    """Stereo visual odometry with one step method, :meth:`process` (see module doc).

    Parameters
    ----------
    calibration : rectified geometry and optional rectification maps.
    config : parameters.
    """

    def __init__(self, calibration: StereoCalibration, config: VoConfig = VoConfig()) -> None:
        self.calibration = calibration
        self.config = config
        self.state = VoState.UNINITIALISED
        self.segmenter = TrackSegmenter(config.track)
        self._next_id = int(config.first_node_id)
        self._kf_id = -1
        self._kf_track = 0
        self._kf_stamp = 0
        self._kf_points = np.zeros((0, 3))
        self._kf_cov = np.zeros((0, 3, 3))
        self._track_pts = np.zeros((0, 2), np.float32)
        self._track_idx = np.zeros(0, np.int64)
        self._prev_img: np.ndarray | None = None
        self._T_world_kf = np.eye(4)
        self._T_kf_prev = np.eye(4)
        self._delta = np.eye(4)
        self._median_depth = float('nan')
        self._median_disp = 0.0
        self._orb = cv2.ORB_create(nfeatures=max(config.orb_features, 1),
                                   nlevels=config.orb_levels, fastThreshold=10)
        self._lk_flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        self._criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)

    # ------------------------------------------------------------------ public
    def request_track_boundary(self) -> None:
        """Start a new track at the next keyframe (e.g. from a topic)."""
        self.segmenter.request_boundary()

    @property
    def next_node_id(self) -> int:
        """Id the next keyframe will get."""
        return self._next_id

    def recalibrated(self, calibration: StereoCalibration) -> StereoOdometry:
        """A new odometry for a changed calibration that continues this one's node ids, track
        ids and integrated pose (it re-initialises on its first frame, with no motion to the
        last keyframe)."""
        out = StereoOdometry(calibration, self.config)
        out.segmenter = self.segmenter
        out._next_id = self._next_id
        out._kf_track = self._kf_track
        out._T_world_kf = self._T_world_kf @ self._T_kf_prev
        return out

    def reset(self) -> None:
        """Forget the reference keyframe; the next frame re-initialises (keeps ids and pose)."""
        self.state = VoState.UNINITIALISED
        self._prev_img = None

    def process(self, frame: StereoFrame) -> VoResult:
        """Process one stereo pair.

        Raises
        ------
        InputError
            Images of the wrong size, type or shape for the calibration (nothing changed).
        """
        left, right = self._validate(frame)
        # The right image is rectified only where it is used (keyframes: _initialise).
        left = self.calibration.rectify_one(left, 'left')
        stamp = int(frame.stamp_ns)
        std = float(cv2.meanStdDev(left)[1][0, 0])
        if (std < self.config.min_texture_std
                or float(cv2.meanStdDev(right)[1][0, 0]) < self.config.min_texture_std):
            self._lose()
            return self._result('rejected', f'textureless frame (grey-level std {std:.1f})',
                                stamp)
        if self.state != VoState.TRACKING:
            return self._initialise(left, right, stamp, 'initialised')
        return self._track(left, right, stamp)

    # ----------------------------------------------------------------- helpers
    def _validate(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        cal = self.calibration
        out = []
        for name, img in (('left', frame.left), ('right', frame.right)):
            img = np.asarray(img)
            if img.dtype != np.uint8:
                raise InputError(f'{name} image has dtype {img.dtype}; expected uint8')
            if img.ndim == 3 and img.shape[2] in (3, 4):
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3
                                   else cv2.COLOR_BGRA2GRAY)
            elif img.ndim == 3 and img.shape[2] == 1:
                img = img[:, :, 0]
            if img.ndim != 2:
                raise InputError(f'{name} image has shape {img.shape}; expected (h, w) or '
                                 '(h, w, 3)')
            if img.shape != (cal.height, cal.width):
                raise InputError(f'{name} image is {img.shape[1]}x{img.shape[0]}; calibration '
                                 f'is {cal.width}x{cal.height}')
            out.append(np.ascontiguousarray(img))
        return out[0], out[1]

    def _lose(self) -> None:
        self.state = VoState.LOST
        self._prev_img = None
        self._T_world_kf = self._T_world_kf @ self._T_kf_prev
        self._T_kf_prev = np.eye(4)

    def _result(self, status: str, reason: str, stamp: int, **kw: object) -> VoResult:
        return VoResult(self.state, status, reason, stamp, self._kf_id, self._kf_track,
                        T_world_cam=self._T_world_kf @ self._T_kf_prev,
                        median_depth_m=self._median_depth, **kw)

    def _stereo(self, left: np.ndarray, right: np.ndarray, pts: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """Disparities (n,) and validity mask of left points ``pts`` (n, 2) float32."""
        cfg = self.config
        if len(pts) == 0:
            return np.zeros(0), np.zeros(0, bool)
        guess = self._median_disp
        if guess <= 0 and cfg.expected_depth_m > 0:
            guess = self.calibration.K[0, 0] * self.calibration.baseline_m / cfg.expected_depth_m
        init = pts.copy()
        init[:, 0] -= guess
        win = (cfg.klt_window_px, cfg.klt_window_px)
        pr, st, _ = cv2.calcOpticalFlowPyrLK(left, right, pts, init, winSize=win,
                                             maxLevel=cfg.stereo_levels, criteria=self._criteria,
                                             flags=self._lk_flags)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(right, left, pr, pts.copy(), winSize=win,
                                                maxLevel=1, criteria=self._criteria,
                                                flags=self._lk_flags)
        disp = (pts[:, 0] - pr[:, 0]).astype(float)
        w = self.calibration.width
        ok = ((st.ravel() == 1) & (st2.ravel() == 1)
              & (np.linalg.norm(back - pts, axis=1) < cfg.max_lr_error_px)
              & (np.abs(pr[:, 1] - pts[:, 1]) < cfg.max_row_error_px)
              & (disp > cfg.min_disparity_px)
              & (pr[:, 0] >= 0) & (pr[:, 0] <= w - 1))
        return disp, ok

    def _initialise(self, left: np.ndarray, right: np.ndarray, stamp: int,
                    status: str, measurement_from: tuple | None = None) -> VoResult:
        """Make this frame the reference keyframe (``left`` rectified, ``right`` raw)."""
        cfg = self.config
        cal = self.calibration
        right = cal.rectify_one(right, 'right')
        corners = cv2.goodFeaturesToTrack(left, cfg.max_features, cfg.feature_quality,
                                          cfg.min_feature_distance_px, blockSize=7)
        corners = (np.zeros((0, 2), np.float32) if corners is None
                   else corners.reshape(-1, 2).astype(np.float32))
        orb_kps: list = []
        desc = None
        if cfg.orb_features > 0:
            orb_kps, desc = self._orb.detectAndCompute(left, None)
            if desc is None:
                orb_kps = []
        orb_uv = np.array([k.pt for k in orb_kps], np.float32).reshape(-1, 2)
        if len(orb_uv):
            # ORB reports level-L pixels as x_L * scale; the pixel centre is at
            # (x_L + 0.5) * scale - 0.5 in level-0 pixels. Then sub-pixel corner refinement,
            # which is rotation-equivariant (the same ground point from opposite headings).
            scale = self._orb.getScaleFactor() ** np.array([k.octave for k in orb_kps])
            orb_uv += (0.5 * (scale - 1.0))[:, None].astype(np.float32)
            if cfg.orb_subpixel:
                ref = cv2.cornerSubPix(left, orb_uv.reshape(-1, 1, 2).copy(), (3, 3), (-1, -1),
                                       self._criteria).reshape(-1, 2)
                moved = np.linalg.norm(ref - orb_uv, axis=1) < 1.5
                orb_uv[moved] = ref[moved]
        allpts = np.vstack([corners, orb_uv]).astype(np.float32)
        disp, ok = self._stereo(left, right, allpts)
        nc = len(corners)
        c_ok = ok[:nc]
        if c_ok.sum() < cfg.min_inliers:
            self._lose()
            return self._result('lost' if status == 'keyframe' else 'rejected',
                                f'only {int(c_ok.sum())} stereo points at the keyframe', stamp)
        pts = corners[c_ok]
        d = disp[:nc][c_ok]
        self._kf_points = triangulate(pts.astype(float), d, cal.K, cal.baseline_m)
        self._kf_cov = point_covariance(pts.astype(float), d, cal.K, cal.baseline_m, 0.0,
                                        cfg.sigma_disparity_px)
        self._median_disp = float(np.median(d))
        self._median_depth = float(np.median(self._kf_points[:, 2]))
        self._track_pts = pts.copy()
        self._track_idx = np.arange(len(pts))
        self._prev_img = left
        step_m = (cfg.heading_min_step_depth_ratio * self._median_depth
                  if cfg.heading_min_step_depth_ratio > 0 else cfg.track.heading_min_step_m)
        new_track = self.segmenter.update(self._T_world_kf @ self._T_kf_prev, stamp, step_m)
        T_world_kf = self._T_world_kf @ self._T_kf_prev
        kf_id = self._next_id
        self._next_id += 1
        meas = None
        if measurement_from is not None:
            src_id, src_track, T, cov = measurement_from
            meas = Measurement.from_pose(src_id, kf_id, src_track, self.segmenter.track_id, T,
                                         cov, stamp, 'consecutive')
        self._kf_id = kf_id
        self._kf_track = self.segmenter.track_id
        self._kf_stamp = stamp
        self._T_world_kf = T_world_kf
        self._T_kf_prev = np.eye(4)
        self.state = VoState.TRACKING
        keyframe = None
        o_ok = ok[nc:]
        if cfg.orb_features > 0 and o_ok.sum() > 0:
            ouv = orb_uv[o_ok].astype(float)
            od = disp[nc:][o_ok]
            X = triangulate(ouv, od, cal.K, cal.baseline_m)
            keyframe = Keyframe(kf_id, self._kf_track, self.segmenter.segment, stamp, T_world_kf,
                                ouv, np.array([k.octave for k in orb_kps])[o_ok],
                                desc[o_ok], X,
                                point_covariance(ouv, od, cal.K, cal.baseline_m, 0.0,
                                                 cfg.sigma_disparity_px),
                                float(np.median(X[:, 2])),
                                left.copy() if cfg.keyframe_images else None)
        return self._result(status, '', stamp, measurement=meas, keyframe=keyframe,
                            n_features=len(pts), new_track=new_track)

    def _track(self, left: np.ndarray, right: np.ndarray, stamp: int) -> VoResult:
        cfg = self.config
        cal = self.calibration
        # Constant-velocity prediction of the keyframe points in the current image.
        T_kf_pred = self._T_kf_prev @ self._delta
        Xp = self._kf_points[self._track_idx]
        T_pred_kf = se3.inverse(T_kf_pred)
        Xc = Xp @ T_pred_kf[:3, :3].T + T_pred_kf[:3, 3]
        init = self._track_pts.copy()
        front = Xc[:, 2] > 1e-3
        init[front] = project(Xc[front], cal.K).astype(np.float32)
        win = (cfg.klt_window_px, cfg.klt_window_px)
        prev_img, prev_pts = self._prev_img, self._track_pts
        if cfg.klt_derotate_deg > 0 and front.sum() >= 3:
            # Rotating platform (turns): warp the previous image by the predicted similarity so
            # that the KLT patches are compared without in-plane rotation.
            A, _ = cv2.estimateAffinePartial2D(self._track_pts[front], init[front])
            if A is not None and abs(np.arctan2(A[1, 0], A[0, 0])) > np.deg2rad(
                    cfg.klt_derotate_deg):
                prev_img = cv2.warpAffine(self._prev_img, A, (cal.width, cal.height),
                                          flags=cv2.INTER_LINEAR)
                prev_pts = (self._track_pts @ A[:, :2].T + A[:, 2]).astype(np.float32)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev_img, left, prev_pts, init,
                                              winSize=win, maxLevel=cfg.klt_levels,
                                              criteria=self._criteria, flags=self._lk_flags)
        w, h = cal.width, cal.height
        ok = ((st.ravel() == 1) & (nxt[:, 0] >= 0) & (nxt[:, 0] <= w - 1)
              & (nxt[:, 1] >= 0) & (nxt[:, 1] <= h - 1))
        n_tracked = int(ok.sum())
        idx = self._track_idx[ok]
        uv = nxt[ok]
        try:
            if n_tracked < cfg.min_inliers:
                raise DegenerateGeometryError(f'only {n_tracked} features tracked')
            T_init, inl = self._pnp(self._kf_points[idx], uv)
            idx, uv = idx[inl], uv[inl]
            est = refine_motion(self._kf_points[idx], uv.astype(float), cal.K, T_init,
                                self._kf_cov[idx], cfg.sigma_track_px,
                                min_points=cfg.min_inliers)
            if est.sigma0_sq > cfg.max_sigma0_sq:
                raise DegenerateGeometryError(f'variance factor {est.sigma0_sq:.1f}')
        except DegenerateGeometryError as exc:
            kf_id = self._kf_id
            self._lose()
            res = self._initialise(left, right, stamp, 'lost')
            res.status = 'lost'
            res.reason = f'track lost after keyframe {kf_id}: {exc}'
            return res
        T = est.T_src_dst
        cov = est.cov * cfg.covariance_scale
        n_in = est.n_inliers
        self._delta = se3.inverse(self._T_kf_prev) @ T
        self._T_kf_prev = T
        self._track_pts = uv[est.inliers].astype(np.float32)
        self._track_idx = idx[est.inliers]
        self._prev_img = left
        travel = float(np.linalg.norm(T[:3, 3])) / max(self._median_depth, 1e-6)
        angle = float(np.linalg.norm(so3.log(T[:3, :3])))
        new_kf = (n_in < cfg.keyframe_min_tracked_fraction * len(self._kf_points)
                  or n_in < cfg.keyframe_min_inliers
                  or travel > cfg.keyframe_max_travel_ratio
                  or angle > np.deg2rad(cfg.keyframe_max_rotation_deg))
        if new_kf:
            src = (self._kf_id, self._kf_track, T, cov)
            n_feat = len(self._kf_points)
            res = self._initialise(left, right, stamp, 'keyframe', measurement_from=src)
            if res.status == 'keyframe':
                res.T_kf_cur, res.cov = T, cov
                res.n_tracked, res.n_inliers, res.sigma0_sq = n_tracked, n_in, est.sigma0_sq
                res.n_features = n_feat
            return res
        return self._result('tracked', '', stamp, T_kf_cur=T, cov=cov,
                            n_features=len(self._kf_points), n_tracked=n_tracked,
                            n_inliers=n_in, sigma0_sq=est.sigma0_sq)

    def _pnp(self, X: FloatArray, uv: np.ndarray) -> tuple[FloatArray, np.ndarray]:
        """RANSAC PnP: initial ``T_kf_cur`` and inlier indices from keyframe points and
        current pixels."""
        cfg = self.config
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X.astype(np.float64), uv.astype(np.float64), self.calibration.K, None,
            iterationsCount=cfg.pnp_iterations, reprojectionError=cfg.pnp_reprojection_px,
            confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        if not ok or inl is None or len(inl) < cfg.min_inliers:
            n = 0 if inl is None else len(inl)
            raise DegenerateGeometryError(f'PnP RANSAC found {n} inliers')
        T_cur_kf = se3.from_translation_rotvec(np.asarray(tvec, float).ravel(),
                                               np.asarray(rvec, float).ravel())
        return se3.inverse(T_cur_kf), inl.ravel()
