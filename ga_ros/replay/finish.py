"""The end of a replay: the last updates and the final outputs.

After the last item: the held measurements, the last track's update (the online estimate, what
the live node publishes at the end) and the final batch of everything read (by default); then
the corrected poses with their covariances, the F2F path (the odometry anchored as the corrected
path), the TUM files, the errors against ground truth and the plot
(:class:`ga_ros.replay.outputs.ReplayOutputs`), and what the replay did about frames
(``summary.json``'s ``frames``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.calibration import CalibrationConfig, check_cameras
from ga_ros.core.quality.variance_components import VarianceComponentConfig
from ga_ros.errors import GaError, InputError, SolverError
from ga_ros.eval.metrics import trajectory_error
from ga_ros.geometry import se3
from ga_ros.io.trajectory import Trajectory
from ga_ros.pipeline.inputs import InputFrontEnd
from ga_ros.pipeline.map_to_odom import MapToOdom
from ga_ros.replay.result import plain_fields
from ga_ros.replay.run import ReplayRun


def finish_stationary(run: ReplayRun) -> None:
    """Outputs of a robot that did not move: its first keyframe at the datum, and a note.
    Used when keyframes were made but no motion between two of them reached the aligner."""
    node, stamp = min(run.stamps.items(), key=lambda kv: kv[1])
    T0 = np.eye(4)
    if run.gt is not None and run.config.anchor_to_ground_truth:
        hit = run.match(np.array([node]), np.array([stamp]))
        if hit.n_matched:
            T0 = hit.T_world_gt[0].copy()
    traj = Trajectory(np.array([stamp], dtype=np.int64), T0[None],
                      np.array([node], dtype=np.int64), np.zeros(1, dtype=np.int64),
                      run.config.outputs.map_frame)
    res = run.result
    res.corrected = traj
    res.n_nodes, res.n_tracks = 1, 1
    n = len(run.stamps)
    res.notes.append(f'the robot did not move: {n} keyframe{"s" if n > 1 else ""}, '
                     'stationary trajectory written')
    run.out.path(traj, run.last_ns)
    run.out.poses(traj, np.zeros((1, 6, 6)), run.last_ns)
    run.out.odometry(traj, np.zeros((1, 6, 6)), run.last_ns)
    run.out.path(traj, run.last_ns, topic=run.config.outputs.f2f_topic)
    run.out.tum('trajectory_ga.tum', traj)
    run.out.tum('trajectory_online.tum', traj)
    run.out.tum('trajectory_f2f.tum', traj)
    front = getattr(run.source, 'front', None)
    odom = MapToOdom(front if isinstance(front, InputFrontEnd) else None)
    T_map_odom = odom.update(traj.node_ids, traj.T_world_node)
    if run.config.tf and T_map_odom is not None:
        run.out.map_to_odom(T_map_odom, stamp, run.last_ns)
    if run.gt is not None and len(run.gt):
        run.out.ground_truth(run.gt, run.last_ns)
        _ground_truth_files(run, traj)


def finish(run: ReplayRun) -> None:
    """The last updates and every final output of a replay whose aligner was made (else
    nothing): the online and final-batch corrected poses, the F2F path, the TUM files, the
    errors against ground truth, the plot."""
    res = run.result
    if run.aligner is None:
        return
    online = _last_updates(run)
    traj = run.corrected()
    res.corrected = traj
    res.online = online if online is not None else traj
    assert run.session is not None
    counts = run.session.counts
    res.gaps = {'bridges': counts.bridges, 'reversed_measurements': counts.reversed,
                'unjoined_nodes': traj.node_ids[run.session.unjoined(traj.node_ids)].tolist()}
    if run.config.tf and run.odom is not None and run.odom.latest() is not None:
        run.out.map_to_odom(run.odom.T_map_odom,   # the final correction, at the end
                            run.odom.stamp(run.last_ns + run.stamp_offset_ns), run.last_ns)
    run.markers(traj, everything=True)
    res.n_nodes = len(traj)
    res.n_tracks = int(np.unique(traj.track_ids).size)
    covs = _pose_covariances(run, traj)
    run.out.poses(traj, covs, run.last_ns)
    run.out.odometry(traj, covs, run.last_ns)
    f2f = f2f_path(run, traj)
    run.out.path(f2f, run.last_ns, topic=run.config.outputs.f2f_topic)
    run.out.tum('trajectory_ga.tum', traj)
    run.out.tum('trajectory_online.tum', res.online)
    run.out.tum('trajectory_f2f.tum', f2f)
    gt_kf = None
    if run.gt is not None and len(run.gt):
        run.out.ground_truth(run.gt, run.last_ns)
        gt_kf = _ground_truth_files(run, traj)
        _errors_vs_ground_truth(run, traj, f2f, res.online)
    if run.config.plot:
        _plot(run, traj, f2f, gt_kf)
    if run.config.mosaic:
        _mosaics(run, traj, f2f)


def _mosaics(run: ReplayRun, traj: Trajectory, f2f: Trajectory) -> None:
    """``mosaic_ga.png`` / ``mosaic_f2f.png`` and their figures (a source without a camera
    or a mosaic too large is a warning: the other outputs stand)."""
    from ga_ros.mapping.replay_mosaic import replay_mosaics

    try:
        run.result.mosaic = replay_mosaics(run.source, run.out.dir, {'ga': traj, 'f2f': f2f})
    except GaError as exc:
        run.result.warnings.append(f'mosaic: {exc}')
        return
    for name, m in run.result.mosaic.items():
        run.out.files[f'mosaic_{name}'] = Path(m['png'])


def _last_updates(run: ReplayRun) -> Trajectory | None:
    """The held measurements (in, bridged if need be), the last track's update and the final
    batch of everything read (``final_batch``); returns the online estimate, the corrected path
    after the last track's update, as the live node publishes it at the end (None if that
    failed). A failure of the last update is added to the result's error, one of the final
    batch to its warnings (GA is then the online estimate); the replay goes on."""
    res = run.result
    assert run.aligner is not None
    try:
        assert run.session is not None
        flushed = run.session.flush_gaps()  # held measurements: in, bridged if need be
        run.admitted(flushed)
        for u in flushed.updates:
            run.update(u)
        run.update(run.aligner.finish_track())
    except GaError as exc:
        res.error = (res.error + '; ' if res.error else '') + f'final update failed: {exc}'
        return None
    online = run.corrected()
    book = getattr(run.aligner, 'online_variance', None)
    if book is not None:
        res.online_variance_components = book.as_dict()
        res.warnings += [f'online: {w}' for w in book.warnings()]
    cal = getattr(run.aligner, 'online_calibration', None)
    if cal is not None:
        res.online_calibration = cal.as_dict()
    if run.config.final_batch:
        mode = run.config.variance_components
        vce = mode != 'off' and hasattr(run.aligner, 'variance_components')
        cameras = tuple(run.config.calibrate_cameras)
        asked = run.config.calibrate or bool(cameras)
        calibrate = asked and hasattr(run.aligner, 'calibration')
        if asked and not calibrate:
            res.warnings.append('--calibrate / --calibrate-camera need the window aligner '
                                '(--aligner window): the final batch ran without calibration')
        if calibrate and cameras:
            try:
                check_cameras(cameras, run.groups.source_names(), '--calibrate-camera')
            except InputError as exc:
                res.error = (res.error + '; ' if res.error else '') + str(exc)
                return online
        vce = vce and not calibrate  # the calibrated batch takes their place
        try:
            if calibrate:
                u = run.aligner.refine_batch(variance_groups=run.groups,
                                             calibration=CalibrationConfig(cameras=cameras))
            elif vce:
                u = run.aligner.refine_batch(
                    variance_groups=run.groups,
                    variance_config=VarianceComponentConfig(apply=mode == 'apply'))
            else:
                u = run.aligner.refine_batch()
        except GaError as exc:
            res.warnings.append(f'final batch failed ({exc}): trajectory_ga.tum is the online '
                                'estimate')
            return online
        run.update(u, per_track=False)
        res.final_batch = True
        res.final_batch_update = plain_fields(u)
        cal = getattr(run.aligner, 'calibration', None) if calibrate else None
        if cal is not None:
            res.calibration = cal.as_dict()
        vc = getattr(run.aligner, 'variance_components', None) if vce else None
        if vc is not None:
            res.variance_components = vc.as_dict()
            res.warnings += vc.warnings()
    return online


def _pose_covariances(run: ReplayRun, traj: Trajectory) -> FloatArray:
    """(n, 6, 6) marginal covariances of the corrected poses, order ``[x y z rx ry rz]``; zero
    where unknown or with ``pose_covariance`` off (as ROS writes an unknown covariance)."""
    covs = np.zeros((len(traj), 6, 6))
    if not run.config.pose_covariance:
        return covs
    assert run.aligner is not None
    batch = getattr(run.aligner, 'covariances', None)  # all blocks at once, if offered
    try:
        if batch is None:
            raise SolverError('no batch covariances')
        covs[:] = np.asarray(batch(traj.node_ids), dtype=float).reshape(-1, 6, 6)
    except GaError:
        for k, n in enumerate(traj.node_ids):
            try:
                covs[k] = run.aligner.covariance(int(n))
            except GaError:  # unknown: zero, as ROS does for an unknown covariance
                pass
    return covs


def odometry_chain(run: ReplayRun, node_ids: IntArray) -> dict[int, FloatArray]:
    """The odometry as recorded (standard inputs: the first input's own pose ``T_odom_k`` at
    each keyframe) or, without standard inputs, as estimated (the frame-to-frame integration
    of the consecutive measurements, VO's for a stereo bag): node id -> (4, 4) pose in the
    odometry's frame, for the nodes of ``node_ids`` it has."""
    front = getattr(run.source, 'front', None)
    out: dict[int, FloatArray] = {}
    if isinstance(front, InputFrontEnd):
        for n in node_ids:
            try:
                out[int(n)] = front.keyframe_pose(int(n))
            except InputError:
                pass
        return out
    assert run.f2f is not None
    return {int(n): run.f2f.poses[int(n)] for n in node_ids if int(n) in run.f2f.poses}


def f2f_path(run: ReplayRun, traj: Trajectory) -> Trajectory:
    """The F2F path: the odometry (:func:`odometry_chain`) anchored exactly as the corrected
    path is, i.e. moved rigidly so that its first node is where the corrected path has that node
    (the datum: the ground truth's first pose, the identity, or where the fixes put it), in the
    map frame, node order of the corrected path."""
    chain = odometry_chain(run, traj.node_ids)
    rows = [k for k, n in enumerate(traj.node_ids) if int(n) in chain]
    f_ids = traj.node_ids[rows]
    T = np.array([chain[int(n)] for n in f_ids]).reshape(-1, 4, 4)
    if len(rows) and not np.array_equal(T[0], traj.T_world_node[rows[0]]):
        T = traj.T_world_node[rows[0]] @ se3.inverse(T[0]) @ T
    return Trajectory(traj.stamps_ns[rows].astype(np.int64), T,
                      np.asarray(f_ids, dtype=np.int64),
                      traj.track_ids[rows].astype(np.int64), run.config.outputs.map_frame)


def _ground_truth_files(run: ReplayRun, traj: Trajectory) -> Trajectory | None:
    """``trajectory_gt.tum``: the ground truth at the keyframe stamps, as the error figures use
    it (interpolated, one line per matched keyframe, so evo pairs every line with
    ``trajectory_ga.tum``), and ``trajectory_gt_raw.tum``: the ground-truth stream as read.
    Returns the former (None when no keyframe matched)."""
    assert run.gt is not None
    run.out.tum('trajectory_gt_raw.tum', run.gt)
    hit = run.match(traj.node_ids, traj.stamps_ns)
    if not hit.n_matched:
        return None
    i = hit.i_est
    gt = Trajectory(traj.stamps_ns[i].astype(np.int64), hit.T_world_gt,
                    traj.node_ids[i].astype(np.int64), traj.track_ids[i].astype(np.int64),
                    run.gt.frame_id)
    run.out.tum('trajectory_gt.tum', gt)
    return gt


def _errors_vs_ground_truth(run: ReplayRun, traj: Trajectory, f2f: Trajectory,
                            online: Trajectory) -> None:
    """The result's ``ground_truth`` text and ``errors`` of the corrected (``'ga'``: the final
    batch when computed), online (``'online'``) and F2F (``'f2f'``) positions at the matched
    nodes (at least three each)."""
    assert run.gt is not None
    res = run.result
    hit = run.match(traj.node_ids, traj.stamps_ns)
    res.ground_truth = hit.describe(run.gt_source, 'nodes', run.match_by == 'node')
    res.errors_compared = 'raw' if run.config.anchor_to_ground_truth else 'aligned'
    i_est = hit.i_est
    if len(i_est) < 3:
        return
    gt_xyz = hit.T_world_gt[:, :3, 3]
    res.errors['ga'] = trajectory_error(traj.T_world_node[i_est, :3, 3], gt_xyz)
    nodes = traj.node_ids[i_est]
    for key, other in (('online', online), ('f2f', f2f)):
        index = {int(n): k for k, n in enumerate(other.node_ids)}
        ok = [j for j, n in enumerate(nodes) if int(n) in index]
        if len(ok) >= 3:
            rows = [index[int(nodes[j])] for j in ok]
            res.errors[key] = trajectory_error(other.T_world_node[rows, :3, 3], gt_xyz[ok])


def _plot(run: ReplayRun, traj: Trajectory, f2f: Trajectory, gt: Trajectory | None) -> None:
    """``trajectory.png``: GA (final batch), the online estimate when it differs, F2F, the
    fixes and the ground truth at the keyframes, all in the map frame; the compared RMSEs in the
    title."""
    res = run.result
    title = f'{Path(res.bag).name}: {res.n_nodes} nodes, {res.n_tracks} tracks'
    if 'ga' in res.errors and 'f2f' in res.errors:
        how = ('position RMSE' if res.errors_compared == 'raw'
               else 'position RMSE after rigid alignment')
        title += (f'\n{how}: F2F {res.errors["f2f"].compared(res.errors_compared):.3g} m, '
                  f'GA {res.errors["ga"].compared(res.errors_compared):.3g} m')
    online = res.online
    online_xyz = None
    if online is not None and res.final_batch and len(online) == len(traj):
        online_xyz = online.T_world_node[:, :3, 3]
    fixes = np.array(run.fix_xyz).reshape(-1, 3) if run.fix_xyz else None
    run.out.plot('trajectory.png', traj.T_world_node[:, :3, 3], f2f.T_world_node[:, :3, 3],
                 None if gt is None else gt.T_world_node[:, :3, 3], title, online=online_xyz,
                 fixes=fixes, frame=run.config.outputs.map_frame)


def frames_summary(run: ReplayRun) -> dict[str, Any]:
    """What the replay did about frames (``summary.json``'s ``frames``)."""
    config, source = run.config, run.source
    out: dict[str, Any] = {
        'map_frame': config.outputs.map_frame, 'odom_frame': config.outputs.odom_frame,
        'base_frame': config.outputs.sensor_frame,
        'transform_publish_period_sec': config.transform_publish_period_sec,
        'input_tf_to_odom_not_copied': run.tf_removed}
    front = getattr(source, 'front', None)
    ext = getattr(front, 'extrinsic', None)
    if ext is not None:
        out['camera_extrinsic'] = {'source': ext.source, 'camera_frame': ext.camera_frame,
                                   'T_base_camera': np.round(ext.T_base_cam, 9).tolist()}
    warnings = list(getattr(source, 'warnings', []) or [])
    if run.tf_removed:
        warnings.append(f'{run.tf_removed} input transforms to {config.outputs.odom_frame!r} '
                        f"not copied (another localiser's; ours is the one "
                        f'{config.outputs.map_frame} -> {config.outputs.odom_frame})')
    out['warnings'] = [w for w in warnings if 'DEFAULT covariance' not in w]
    return out


def map_to_odom_summary(run: ReplayRun) -> None:
    """After the final outputs: how the map was placed (``summary.json``'s
    ``frames.map_to_odom``, :meth:`MapToOdom.diagnostic_values`) and, when ``map -> odom``
    jumped beyond the fixes' uncertainty, a warning (printed, and in ``frames.warnings``)."""
    if run.odom is None:
        return
    res = run.result
    res.frames['map_to_odom'] = {k.split('/', 1)[1]: v
                                 for k, v in run.odom.diagnostic_values().items()}
    if run.odom.jumps_warned:
        text = (f"map -> odom jumped beyond the fixes' uncertainty {run.odom.jumps_warned} "
                f'time(s); the last: {run.odom.last_warning}')
        res.frames.setdefault('warnings', []).append(text)
        res.warnings.append(text)
