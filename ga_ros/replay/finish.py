"""The end of a replay: the last updates and the final outputs.

After the last item: the held measurements, the last track's update and the optional batch
refinement; then the corrected poses with their covariances, the F2F path, the TUM files, the
errors against ground truth and the plot (:class:`ga_ros.replay.outputs.ReplayOutputs`), and
what the replay did about frames (``summary.json``'s ``frames``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import GaError, SolverError
from ga_ros.eval.metrics import trajectory_error
from ga_ros.io.trajectory import Trajectory
from ga_ros.pipeline.inputs import InputFrontEnd
from ga_ros.pipeline.map_to_odom import MapToOdom
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
    run.out.tum('trajectory_f2f.tum', traj)
    front = getattr(run.source, 'front', None)
    odom = MapToOdom(front if isinstance(front, InputFrontEnd) else None)
    T_map_odom = odom.update(traj.node_ids, traj.T_world_node)
    if run.config.tf and T_map_odom is not None:
        run.out.map_to_odom(T_map_odom, stamp, run.last_ns)
    if run.gt is not None and len(run.gt):
        run.out.ground_truth(run.gt, run.last_ns)
        run.out.tum('trajectory_gt.tum', run.gt)


def finish(run: ReplayRun) -> None:
    """The last updates and every final output of a replay whose aligner was made (else
    nothing): corrected poses, F2F path, TUM files, errors against ground truth, plot."""
    res = run.result
    if run.aligner is None:
        return
    _last_updates(run)
    traj = run.corrected()
    res.corrected = traj
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
    f2f = _f2f_path(run, traj)
    run.out.path(f2f, run.last_ns, topic=run.config.outputs.f2f_topic)
    run.out.tum('trajectory_ga.tum', traj)
    run.out.tum('trajectory_f2f.tum', f2f)
    gt_xyz = None
    if run.gt is not None and len(run.gt):
        run.out.ground_truth(run.gt, run.last_ns)
        run.out.tum('trajectory_gt.tum', run.gt)
        _errors_vs_ground_truth(run, traj, f2f)
        gt_xyz = run.gt.T_world_node[:, :3, 3]
    if run.config.plot:
        _plot(run, traj, f2f.T_world_node[:, :3, 3], gt_xyz)


def _last_updates(run: ReplayRun) -> None:
    """The held measurements (in, bridged if need be), the last track's update and the batch
    refinement; a failure is added to the result's error and the replay goes on."""
    res = run.result
    assert run.aligner is not None
    try:
        assert run.session is not None
        flushed = run.session.flush_gaps()  # held measurements: in, bridged if need be
        run.admitted(flushed)
        for u in flushed.updates:
            run.update(u)
        run.update(run.aligner.finish_track())
        if run.config.refine_batch:
            run.update(run.aligner.refine_batch())
    except GaError as exc:
        res.error = (res.error + '; ' if res.error else '') + f'final update failed: {exc}'


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


def _f2f_path(run: ReplayRun, traj: Trajectory) -> Trajectory:
    """The F2F path over the nodes it reached, in node order of the corrected path."""
    assert run.f2f is not None
    f_ids = [int(n) for n in traj.node_ids if int(n) in run.f2f.poses]
    return Trajectory(np.array([run.stamps.get(n, traj.stamps_ns[0]) for n in f_ids],
                               dtype=np.int64),
                      np.array([run.f2f.poses[n] for n in f_ids]).reshape(-1, 4, 4),
                      np.array(f_ids, dtype=np.int64),
                      np.array([run.f2f.tracks.get(n, -1) for n in f_ids], dtype=np.int64),
                      run.config.outputs.map_frame)


def _errors_vs_ground_truth(run: ReplayRun, traj: Trajectory, f2f: Trajectory) -> None:
    """The result's ``ground_truth`` text and ``errors`` of the corrected (``'ga'``) and F2F
    (``'f2f'``) positions at the matched nodes (at least three each)."""
    assert run.gt is not None
    res = run.result
    hit = run.match(traj.node_ids, traj.stamps_ns)
    res.ground_truth = hit.describe(run.gt_source, 'nodes', run.match_by == 'node')
    i_est = hit.i_est
    if len(i_est) < 3:
        return
    gt_xyz = hit.T_world_gt[:, :3, 3]
    res.errors['ga'] = trajectory_error(traj.T_world_node[i_est, :3, 3], gt_xyz)
    f_index = {int(n): k for k, n in enumerate(f2f.node_ids)}
    ok = [j for j, i in enumerate(i_est) if int(traj.node_ids[i]) in f_index]
    if len(ok) >= 3:
        f_rows = [f_index[int(traj.node_ids[i_est[j]])] for j in ok]
        res.errors['f2f'] = trajectory_error(f2f.T_world_node[f_rows, :3, 3], gt_xyz[ok])


def _plot(run: ReplayRun, traj: Trajectory, f2f_xyz: FloatArray,
          gt_xyz: FloatArray | None) -> None:
    """``trajectory.png``: corrected, F2F and ground-truth positions, ATEs in the title."""
    res = run.result
    title = f'{Path(res.bag).name}: {res.n_nodes} nodes, {res.n_tracks} tracks'
    if 'ga' in res.errors and 'f2f' in res.errors:
        title += (f'\nATE vs ground truth: F2F {res.errors["f2f"].ate_raw:.3g} m, '
                  f'GA {res.errors["ga"].ate_raw:.3g} m')
    run.out.plot('trajectory.png', traj.T_world_node[:, :3, 3], f2f_xyz, gt_xyz, title)


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
