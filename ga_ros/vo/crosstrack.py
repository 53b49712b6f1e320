"""Cross-track connections: a bounded keyframe store and verified overlap measurements.

For each new keyframe (:class:`ga_ros.vo.odometry.Keyframe`), :meth:`CrossTrackMatcher.add`
predicts which stored keyframes of other segments (swaths / tracks) overlap it, from the
current corrected path when one was given (:meth:`CrossTrackMatcher.set_corrected_poses`) or
else from the odometry's own integration. For each candidate, ORB descriptors are matched
(ratio test and mutual check), the motion is found by PnP RANSAC on the stored 3-D points and
refined with its covariance (:func:`ga_ros.vo.motion.refine_motion`), and the connection is
emitted only when it passes every gate: inlier count and ratio, image spread of the inliers,
stereo-depth agreement at both ends, variance factor, and agreement with the predicted motion.
A wrong connection is worse than a missing one, so the gates are strict; every attempt is
reported with its statistics (:class:`CrossAttempt`).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.errors import DegenerateGeometryError, InputError
from ga_ros.geometry import se3, so3
from ga_ros.runtime import lazy_import
from ga_ros.vo.motion import refine_motion
from ga_ros.vo.odometry import Keyframe

cv2 = lazy_import('cv2')  # imported on first use (start-up of the command line)


@dataclass(frozen=True)
class CrossTrackConfig:
    """Parameters of :class:`CrossTrackMatcher` (mirrored by ``config/vo.yaml``, prefix
    ``cross_``).

    Attributes
    ----------
    window_tracks : keyframes of the latest this-many tracks are kept (the alignment window).
    max_keyframes : hard bound on the store size (oldest evicted first).
    min_predicted_overlap : candidates need at least this predicted image overlap (0-1).
    max_candidates : verified candidates per new keyframe (highest predicted overlap first).
    ratio_test : Lowe ratio of the best to second-best descriptor distance.
    max_descriptor_distance : largest accepted Hamming distance (bits).
    pnp_reprojection_px : RANSAC inlier threshold (px).
    pnp_iterations : RANSAC iterations.
    sigma_keypoint_px : image noise of an ORB keypoint at pyramid level 0 (px).
    min_inliers : fewer refined inliers reject the connection.
    min_inlier_ratio : inliers / descriptor matches below this reject.
    min_spread : inlier bounding-box area / image area below this rejects.
    min_depth_agreement : fraction of inliers whose depth in the new keyframe agrees with the
        transferred stored point (within 3 sigma + 2 %) below this rejects.
    max_sigma0_sq : variance factor above this rejects.
    max_prediction_error_m : translation disagreement with the predicted motion that rejects
        (m); <= 0 disables.
    max_prediction_error_deg : rotation disagreement with the predicted motion that rejects
        (deg); <= 0 disables.
    refine_lk : refine the correspondences by Lucas-Kanade on the stored keyframe image
        warped by the similarity of the descriptor matches (needs keyframe images), then
        re-estimate the motion from every stored point that falls in the new image.
    lk_window_px : Lucas-Kanade window (px).
    sigma_lk_px : image noise of a refined correspondence (px).
    covariance_scale : factor applied to the estimated covariance; the default 1.8 is an
        empirical calibration (raw mean NEES 11.1 at 320x240 and 10.2 at 640x480 on simulator
        seeds 1-2; geometric mean of the two corrections; see docs/design.md, "Covariance
        honesty").
    """

    window_tracks: int = 5
    max_keyframes: int = 3000
    min_predicted_overlap: float = 0.4
    max_candidates: int = 4
    ratio_test: float = 0.8
    max_descriptor_distance: int = 64
    pnp_reprojection_px: float = 2.5
    pnp_iterations: int = 200
    sigma_keypoint_px: float = 0.7
    min_inliers: int = 30
    min_inlier_ratio: float = 0.3
    min_spread: float = 0.15
    min_depth_agreement: float = 0.8
    max_sigma0_sq: float = 4.0
    max_prediction_error_m: float = 30.0
    max_prediction_error_deg: float = 20.0
    refine_lk: bool = True
    lk_window_px: int = 15
    sigma_lk_px: float = 0.3
    covariance_scale: float = 1.8


@dataclass
class CrossAttempt:
    """Statistics of one verified (or rejected) candidate pair.

    Attributes
    ----------
    src_id, dst_id : stored keyframe and new keyframe.
    predicted_overlap : predicted image overlap (0-1).
    accepted : True when the connection was emitted.
    reason : why it was rejected ('' when accepted).
    gate : short key of the failed gate (``'matches'``, ``'pnp'``, ``'refinement'``,
        ``'inliers'``, ``'inlier_ratio'``, ``'spread'``, ``'depth'``, ``'variance'``,
        ``'prediction'``; '' when accepted).
    n_matches, n_inliers : descriptor matches, refined motion inliers.
    inlier_ratio, spread, depth_agreement, sigma0_sq : the gated statistics.
    measurement : the connection (``kind='cross'``) when accepted.
    """

    src_id: int
    dst_id: int
    predicted_overlap: float
    accepted: bool = False
    reason: str = ''
    gate: str = ''
    n_matches: int = 0
    n_inliers: int = 0
    inlier_ratio: float = 0.0
    spread: float = 0.0
    depth_agreement: float = 0.0
    sigma0_sq: float = float('nan')
    measurement: Measurement | None = None


def predicted_overlap(T_world_a: FloatArray, depth_a: float, T_world_b: FloatArray,
                      K: FloatArray, width: int, height: int) -> float:
    """Fraction of image ``b`` covered by view ``a``'s footprint (at ``a``'s median depth).

    The four image corners of ``a`` are back-projected to ``depth_a`` (m), projected into
    camera ``b``, and the polygon is intersected with ``b``'s image rectangle.
    """
    Kinv = np.linalg.inv(K)
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [width - 1, height - 1, 1],
                        [0, height - 1, 1]], float)
    X_a = (corners @ Kinv.T) * depth_a
    T_b_a = se3.inverse(T_world_b) @ T_world_a
    X_b = X_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    if np.any(X_b[:, 2] <= 1e-3):
        return 0.0
    uv = (X_b[:, :2] / X_b[:, 2:3]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    poly = uv.astype(np.float32)
    if cv2.contourArea(poly) < 0:  # orientation does not matter; area sign does
        poly = poly[::-1].copy()
    rect = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]],
                    np.float32)
    try:
        area, _ = cv2.intersectConvexConvex(poly, rect)
    except cv2.error:
        return 0.0
    return float(max(area, 0.0) / ((width - 1) * (height - 1)))


class CrossTrackMatcher:
    """Bounded keyframe store that emits verified cross-track connections (see module doc).

    Parameters
    ----------
    K : (3, 3) rectified intrinsics; ``width``, ``height``: image size (px).
    config : parameters.
    """

    def __init__(self, K: FloatArray, width: int, height: int,
                 config: CrossTrackConfig = CrossTrackConfig()) -> None:
        self.K = np.asarray(K, float).reshape(3, 3)
        self.width = int(width)
        self.height = int(height)
        self.config = config
        self._store: OrderedDict[int, Keyframe] = OrderedDict()
        self._corrected: dict[int, FloatArray] = {}
        self._corrected_ids = np.zeros(0, np.int64)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def __len__(self) -> int:
        return len(self._store)

    @property
    def node_ids(self) -> list[int]:
        """Ids of the stored keyframes, oldest first."""
        return list(self._store)

    def set_corrected_poses(self, node_ids: np.ndarray, T_world_node: FloatArray) -> None:
        """Use a corrected path (e.g. the aligner's ``/ga/path``) to predict overlaps.

        Keyframes not on the path are placed by chaining the odometry's own motion from the
        latest earlier keyframe that is on it.
        """
        T = np.asarray(T_world_node, float).reshape(-1, 4, 4)
        ids = np.asarray(node_ids).ravel()
        if len(ids) != len(T) or not np.all(np.isfinite(T)):
            raise InputError('corrected path: node ids and poses disagree or are not finite')
        self._corrected = {int(i): T[k] for k, i in enumerate(ids)}
        self._corrected_ids = np.unique(ids.astype(np.int64))

    def predicted_pose(self, node_id: int, T_world_vo: FloatArray | None = None) -> FloatArray:
        """Best available ``T_world_kf`` of a keyframe (corrected path, else VO chained)."""
        if node_id in self._corrected:
            return self._corrected[node_id]
        kf = self._store.get(node_id)
        T_vo = kf.T_world_kf if kf is not None else np.asarray(T_world_vo, float)
        # Latest corrected keyframe before this one that is still stored (usually the first).
        k = int(np.searchsorted(self._corrected_ids, node_id)) - 1
        while k >= 0 and int(self._corrected_ids[k]) not in self._store:
            k -= 1
        if k < 0:
            return T_vo
        b = int(self._corrected_ids[k])
        return self._corrected[b] @ se3.inverse(self._store[b].T_world_kf) @ T_vo

    def add(self, kf: Keyframe) -> list[CrossAttempt]:
        """Verify candidates for a new keyframe, then store it (evicting old tracks).

        Returns one :class:`CrossAttempt` per verified candidate; accepted ones carry their
        measurement ``T_src_dst`` with ``src`` the stored keyframe and ``dst`` the new one.
        """
        cfg = self.config
        attempts: list[CrossAttempt] = []
        if len(kf.descriptors) >= cfg.min_inliers:
            T_w_new = self.predicted_pose(kf.node_id, kf.T_world_kf)
            cands = []
            for old in self._store.values():
                if old.segment == kf.segment or old.node_id == kf.node_id:
                    continue
                T_w_old = self.predicted_pose(old.node_id)
                dist = np.linalg.norm(T_w_old[:3, 3] - T_w_new[:3, 3])
                if dist > 2.0 * max(old.median_depth_m, kf.median_depth_m):
                    continue
                ov = predicted_overlap(T_w_old, old.median_depth_m, T_w_new, self.K,
                                       self.width, self.height)
                if ov >= cfg.min_predicted_overlap:
                    cands.append((ov, old, se3.inverse(T_w_old) @ T_w_new))
            cands.sort(key=lambda c: -c[0])
            for ov, old, T_pred in cands[:cfg.max_candidates]:
                attempts.append(self._verify(old, kf, ov, T_pred))
        self._store[kf.node_id] = kf
        self._evict(kf.track_id)
        return attempts

    def _evict(self, current_track: int) -> None:
        cfg = self.config
        while self._store:
            oldest = next(iter(self._store.values()))
            if (oldest.track_id <= current_track - cfg.window_tracks
                    or len(self._store) > cfg.max_keyframes):
                self._store.popitem(last=False)
                self._corrected.pop(oldest.node_id, None)
            else:
                break

    def _refine_lk(self, old: Keyframe, new: Keyframe, io: np.ndarray, inew: np.ndarray,
                   T_old_new: FloatArray) -> tuple | None:
        """Sub-pixel correspondences by LK on the warped old image; re-estimated motion."""
        cfg = self.config
        A, _ = cv2.estimateAffinePartial2D(old.uv[io].astype(np.float32),
                                           new.uv[inew].astype(np.float32))
        if A is None:
            return None
        warped = cv2.warpAffine(old.image, A, (self.width, self.height), flags=cv2.INTER_LINEAR)
        # Every stored point predicted inside the new image (margin of half a window).
        T_no = se3.inverse(T_old_new)
        Xn = old.points @ T_no[:3, :3].T + T_no[:3, 3]
        front = Xn[:, 2] > 1e-3
        pred = np.full((len(Xn), 2), -1e6)
        pred[front] = (Xn[front, :2] / Xn[front, 2:3]) * [self.K[0, 0], self.K[1, 1]] + \
            [self.K[0, 2], self.K[1, 2]]
        m = cfg.lk_window_px / 2
        sel = np.flatnonzero(front & (pred[:, 0] > m) & (pred[:, 0] < self.width - 1 - m)
                             & (pred[:, 1] > m) & (pred[:, 1] < self.height - 1 - m))
        if len(sel) < cfg.min_inliers:
            return None
        p_w = (old.uv[sel] @ A[:, :2].T + A[:, 2]).astype(np.float32)
        init = pred[sel].astype(np.float32)
        win = (cfg.lk_window_px, cfg.lk_window_px)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        p_n, st, _ = cv2.calcOpticalFlowPyrLK(warped, new.image, p_w, init, winSize=win,
                                              maxLevel=1, criteria=crit,
                                              flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(new.image, warped, p_n, p_w.copy(), winSize=win,
                                                maxLevel=1, criteria=crit,
                                                flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        ok = ((st.ravel() == 1) & (st2.ravel() == 1)
              & (np.linalg.norm(back - p_w, axis=1) < 0.5)
              & (np.linalg.norm(p_n - init, axis=1) < 3.0 * cfg.pnp_reprojection_px))
        if ok.sum() < cfg.min_inliers:
            return None
        idx = sel[ok]
        try:
            est = refine_motion(old.points[idx], p_n[ok].astype(float), self.K, T_old_new,
                                old.points_cov[idx], cfg.sigma_lk_px, min_points=cfg.min_inliers)
        except DegenerateGeometryError:
            return None
        return est, p_n[ok][est.inliers].astype(float)

    def _verify(self, old: Keyframe, new: Keyframe, overlap: float,
                T_pred: FloatArray) -> CrossAttempt:
        """Match, estimate and gate one candidate pair (the stored ``old``, the ``new``
        keyframe; ``T_pred``: the predicted ``T_old_new``)."""
        cfg = self.config
        att = CrossAttempt(old.node_id, new.node_id, overlap)
        pairs = self._mutual_matches(old, new)
        att.n_matches = len(pairs)
        if len(pairs) < cfg.min_inliers:
            att.reason, att.gate = f'{len(pairs)} descriptor matches', 'matches'
            return att
        io, inew = np.array(pairs).T
        X = old.points[io]
        uv = new.uv[inew]
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X, uv, self.K, None, iterationsCount=cfg.pnp_iterations,
            reprojectionError=cfg.pnp_reprojection_px, confidence=0.9999,
            flags=cv2.SOLVEPNP_AP3P)
        if not ok or inl is None or len(inl) < cfg.min_inliers:
            att.reason = f'PnP RANSAC: {0 if inl is None else len(inl)} inliers'
            att.gate = 'pnp'
            return att
        inl = inl.ravel()
        T_new_old = se3.from_translation_rotvec(np.asarray(tvec, float).ravel(),
                                                np.asarray(rvec, float).ravel())
        sigma = cfg.sigma_keypoint_px * (1.2 ** new.octave[inew[inl]].astype(float))
        try:
            est = refine_motion(X[inl], uv[inl], self.K, se3.inverse(T_new_old),
                                old.points_cov[io[inl]], sigma, min_points=cfg.min_inliers)
        except DegenerateGeometryError as exc:
            att.reason, att.gate = f'refinement: {exc}', 'refinement'
            return att
        keep = inl[est.inliers]
        att.inlier_ratio = est.n_inliers / len(pairs)
        att.depth_agreement = _depth_agreement(old, new, io[keep], inew[keep], est.T_src_dst)
        pts = uv[keep]
        if cfg.refine_lk and old.image is not None and new.image is not None:
            lk = self._refine_lk(old, new, io[keep], inew[keep], est.T_src_dst)
            if lk is not None:
                est, pts = lk
        att.n_inliers = est.n_inliers
        att.sigma0_sq = est.sigma0_sq
        span = np.ptp(pts, axis=0)
        att.spread = float(span[0] * span[1] / ((self.width - 1) * (self.height - 1)))
        att.reason, att.gate = self._failed_gate(att, se3.inverse(T_pred) @ est.T_src_dst)
        if not att.gate:
            att.accepted = True
            att.measurement = Measurement.from_pose(
                old.node_id, new.node_id, old.track_id, new.track_id, est.T_src_dst,
                est.cov * cfg.covariance_scale, new.stamp_ns, 'cross')
        return att

    def _mutual_matches(self, old: Keyframe, new: Keyframe) -> list[tuple[int, int]]:
        """Descriptor matches ``(old index, new index)`` that pass the ratio test, the distance
        bound and the mutual (best both ways) check."""
        cfg = self.config
        knn = self._matcher.knnMatch(new.descriptors, old.descriptors, k=2)
        back = self._matcher.match(old.descriptors, new.descriptors)
        best_back = {m.queryIdx: m.trainIdx for m in back}
        pairs = []
        for m in knn:
            if len(m) < 2:
                continue
            a, b = m
            if (a.distance < cfg.ratio_test * b.distance
                    and a.distance <= cfg.max_descriptor_distance
                    and best_back.get(a.trainIdx) == a.queryIdx):
                pairs.append((a.trainIdx, a.queryIdx))
        return pairs

    def _failed_gate(self, att: CrossAttempt, dT: FloatArray) -> tuple[str, str]:
        """``(reason, gate)`` of the first gate the statistics of ``att`` fail, ``('', '')``
        when they pass all; ``dT``: the estimated motion relative to the predicted one."""
        cfg = self.config
        dt = float(np.linalg.norm(dT[:3, 3]))
        da = float(np.rad2deg(np.linalg.norm(so3.log(dT[:3, :3]))))
        if att.n_inliers < cfg.min_inliers:
            return f'{att.n_inliers} inliers', 'inliers'
        if att.inlier_ratio < cfg.min_inlier_ratio:
            return f'inlier ratio {att.inlier_ratio:.2f}', 'inlier_ratio'
        if att.spread < cfg.min_spread:
            return f'inlier spread {att.spread:.2f}', 'spread'
        if att.depth_agreement < cfg.min_depth_agreement:
            return f'depth agreement {att.depth_agreement:.2f}', 'depth'
        if att.sigma0_sq > cfg.max_sigma0_sq:
            return f'variance factor {att.sigma0_sq:.2f}', 'variance'
        if cfg.max_prediction_error_m > 0 and dt > cfg.max_prediction_error_m:
            return f'{dt:.1f} m from the predicted motion', 'prediction'
        if cfg.max_prediction_error_deg > 0 and da > cfg.max_prediction_error_deg:
            return f'{da:.1f} deg from the predicted motion', 'prediction'
        return '', ''


def _depth_agreement(old: Keyframe, new: Keyframe, io: np.ndarray, inew: np.ndarray,
                     T_old_new: FloatArray) -> float:
    """Fraction of the matched points ``(io, inew)`` whose stored point, moved into the new
    frame by ``T_old_new``, agrees in depth with the new stereo point (within 3 sigma of the
    two depths plus 2 % of the depth)."""
    T_no = se3.inverse(T_old_new)
    X_new_pred = old.points[io] @ T_no[:3, :3].T + T_no[:3, 3]
    X_new = new.points[inew]
    sz = np.sqrt(old.points_cov[io, 2, 2] + new.points_cov[inew, 2, 2])
    agree = np.abs(X_new_pred[:, 2] - X_new[:, 2]) < 3.0 * sz + 0.02 * X_new[:, 2]
    return float(agree.mean())
