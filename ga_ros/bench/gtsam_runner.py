"""The GTSAM side of ``ga-ros bench compare``, run in its own process (``python -m``).

``batch IN.g2o OUT.g2o``: read with ``gtsam.readG2o``, a strong prior on the first pose,
``LevenbergMarquardtOptimizer`` with default parameters, ``gtsam.writeG2o``; prints one JSON
object (solver seconds, iterations, poses written to OUT for the cost comparison).

``tracks PROBLEM.npz K``: the track-by-track survey in ``PROBLEM.npz`` (written by
:func:`ga_ros.bench.compare.dump_tracks`) through ``IncrementalFixedLagSmoother`` with a lag
of ``K`` tracks (keys are stamped with their track index); one ``update()`` per track with
that track's factors and new poses (iSAM2 relinearises once per update; an optional third
argument adds empty updates); prints the per-update milliseconds and the final poses.

GTSAM is an optional benchmark extra (``pip install -r requirements-bench.txt``), never a
dependency of ga_ros.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import time

import numpy as np

#: What to do when the optional extra is missing.
INSTALL_HINT = 'GTSAM not installed: pip install -r requirements-bench.txt (gtsam==4.3.0)'


def gtsam_installed() -> bool:
    """Whether the optional benchmark extra ``gtsam`` can be imported (without importing it)."""
    return importlib.util.find_spec('gtsam') is not None


#: ga_ros orders tangent vectors [x y z rx ry rz]; GTSAM's Pose3 uses [rx ry rz x y z]
_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])


def _pose3(T):
    import gtsam

    return gtsam.Pose3(np.asarray(T, dtype=float))


def batch(path_in: str, path_out: str) -> dict:
    import gtsam

    t0 = time.perf_counter()
    with open(path_in, encoding='ascii') as f:
        is3d = any(line.startswith('VERTEX_SE3') for line in f)
    graph, initial = gtsam.readG2o(path_in, is3d)
    key0 = min(initial.keys())
    if is3d:
        graph.add(gtsam.PriorFactorPose3(key0, initial.atPose3(key0),
                                         gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))))
    else:
        graph.add(gtsam.PriorFactorPose2(key0, initial.atPose2(key0),
                                         gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))))
    t_read = time.perf_counter() - t0
    params = gtsam.LevenbergMarquardtParams()
    t = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = opt.optimize()
    solve_s = time.perf_counter() - t
    gtsam.writeG2o(graph, result, path_out)
    return {'solver_seconds': solve_s, 'read_seconds': t_read, 'iterations': opt.iterations(),
            'error': 2.0 * graph.error(result)}


def tracks(path: str, lag_tracks: int, extra_updates: int = 0) -> dict:
    import gtsam

    d = np.load(path)
    src, dst, z, cov = d['src'], d['dst'], d['z'], d['cov']
    node_track, T_first = d['node_track'], d['T_first']
    from ga_ros.geometry import se3

    T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
    group = np.maximum(node_track[src], node_track[dst])  # a track ends when the next begins
    params = gtsam.ISAM2Params()
    smoother = gtsam.IncrementalFixedLagSmoother(float(lag_tracks) - 0.5, params)
    est: dict[int, np.ndarray] = {int(src[0]): np.asarray(T_first, dtype=float)}
    ms, cpu_ms = [], []  # wall clock and CPU time of this process per update
    first = True
    for g in np.unique(group):
        factors = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps = {}
        if first:
            key = int(src[0])
            factors.add(gtsam.PriorFactorPose3(key, _pose3(est[key]),
                                               gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))))
            values.insert(key, _pose3(est[key]))
            stamps[key] = float(node_track[key])
            first = False
        for k in np.nonzero(group == g)[0]:
            i, j = int(src[k]), int(dst[k])
            if j not in est:
                est[j] = est[i] @ T_meas[k]
                values.insert(j, _pose3(est[j]))
                stamps[j] = float(node_track[j])
            C = cov[k][np.ix_(_TO_GTSAM, _TO_GTSAM)]
            factors.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_meas[k]),
                                                 gtsam.noiseModel.Gaussian.Covariance(C)))
        ts = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, stamp in stamps.items():
            ts.insert((key, stamp))
        t, c = time.perf_counter(), time.process_time()
        smoother.update(factors, values, ts)
        for _ in range(extra_updates):  # more iSAM2 relinearisation/solve rounds, no new data
            smoother.update()
        ms.append(1e3 * (time.perf_counter() - t))
        cpu_ms.append(1e3 * (time.process_time() - c))
        result = smoother.calculateEstimate()
        for key in result.keys():
            est[int(key)] = result.atPose3(key).matrix()
    n = node_track.size
    return {'update_ms': ms, 'update_cpu_ms': cpu_ms,
            'T_world_node': np.stack([est[i] for i in range(n)]).tolist()}


def main(argv: list[str]) -> int:
    if argv[0] == 'batch':
        print(json.dumps(batch(argv[1], argv[2])))
    else:
        print(json.dumps(tracks(argv[1], int(argv[2]), int(argv[3]) if len(argv) > 3 else 0)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main(sys.argv[1:]))
