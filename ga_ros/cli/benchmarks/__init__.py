"""The benchmarks of ``ga-ros bench NAME``: one module (or function) each, with its own parser.

:data:`BENCHMARKS` is the one list of them. Each entry names ``module:function``, a
``main(argv) -> int`` that parses the benchmark's options (``prog='ga-ros bench NAME'``) and
prints its figures. ROS-free benchmarks live in :mod:`ga_ros.bench`; those that start ROS nodes
or build rclpy messages live here, above the ROS adapters.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Benchmark:
    """One ``ga-ros bench`` target: ``entry`` is ``'package.module:function'``."""

    entry: str
    summary: str


BENCHMARKS: dict[str, Benchmark] = {
    'solve': Benchmark('ga_ros.cli.benchmarks.estimator:main_solve',
                       'batch solve of the aerial survey'),
    'window': Benchmark('ga_ros.cli.benchmarks.estimator:main_window',
                        'track-by-track alignment of the aerial survey (GTSAM IFLS beside)'),
    'compare': Benchmark('ga_ros.bench.compare:main',
                         'ga-ros against GTSAM in one run: aerial survey and public pose graphs'),
    'g2o': Benchmark('ga_ros.cli.benchmarks.g2o:main',
                     'the public g2o pose graphs against their reference optima'),
    'linalg': Benchmark('ga_ros.bench.linalg:main',
                        'sparse Cholesky back ends and orderings on the same normal matrices'),
    'scale': Benchmark('ga_ros.bench.scale:main',
                       'the aerial survey scaled towards 100,000 poses: update time, RSS'),
    'nees': Benchmark('ga_ros.bench.nees:main',
                      'published covariances against actual errors (position NEES)'),
    'online-gap': Benchmark('ga_ros.bench.online_gap:main',
                            'online estimate against batch, per track and policy'),
    'outliers': Benchmark('ga_ros.bench.outliers:main',
                          'wrong cross-track connections: how well each defence rejects them'),
    'freeze': Benchmark('ga_ros.bench.freeze:main', 'CPU of each stage of a track freeze'),
    'prior': Benchmark('ga_ros.bench.prior:main',
                       'sparse joint priors against dense ones (covariances, CPU)'),
    'persistence': Benchmark('ga_ros.bench.persistence:main',
                             'snapshot save / load and crash recovery at survey scale'),
    'journal': Benchmark('ga_ros.bench.journal:main',
                         'journal append / fsync cost; recovery from the journal alone'),
    'gaps': Benchmark('ga_ros.bench.gaps:main',
                      'measurements lost from the stream: nodes kept with and without healing'),
    'vo': Benchmark('ga_ros.cli.benchmarks.vo:main',
                    'stereo visual odometry and cross-track matching on simulated images'),
    'stereo-throughput': Benchmark('ga_ros.bench.stereo_throughput:main',
                                   'stereo front end at 752x480 (pairs per second)'),
    'keyframe-cloud': Benchmark('ga_ros.cli.benchmarks.keyframe_cloud:main',
                                'CPU of the keyframe clouds (dense stereo) on the sample bag'),
    'node': Benchmark('ga_ros.cli.benchmarks.node:main',
                      'the alignment node as a process: latency, sustained measurement rate'),
    'faults': Benchmark('ga_ros.cli.benchmarks.faults:main',
                        'fault catalogue against live alignment nodes: nodes kept, recovery'),
    'replay': Benchmark('ga_ros.cli.benchmarks.replay:main',
                        'replay throughput on the sample bags'),
    'fixes': Benchmark('ga_ros.bench.fixes:main',
                       'real odometry + absolute fixes (Plaza): ga-ros against GTSAM LM / iSAM2'),
    'fusion': Benchmark('ga_ros.bench.fusion:main',
                        'simulated sources stated alike: each alone, fused, fused with '
                        'variance components'),
    'fixcal': Benchmark('ga_ros.bench.fix_calibration:main',
                        'Plaza odometry + fixes with a latency (and an offset source): the '
                        "batch with and without the fix sources' offset and time offset"),
    'fixwalk': Benchmark('ga_ros.bench.fix_bias_walk:main',
                         'Plaza odometry + fixes whose offset wanders: the batch without '
                         'calibration, with a constant offset, with the offset a random walk'),
    'camcal': Benchmark('ga_ros.bench.camera_calibration:main',
                        "a camera's extrinsic rotation error on a simulated swath survey: the "
                        'batch with and without the camera parameters, against GTSAM LM'),
    'long': Benchmark('ga_ros.bench.long_survey:main',
                      'a long survey with a fix every track: late against early update time, '
                      'CPU, RSS per pose'),
    'corrections': Benchmark('ga_ros.bench.corrections:main',
                             'ga/corrections bytes per update against the whole path (aerial)'),
    'outputs': Benchmark('ga_ros.cli.benchmarks.replay_outputs:main',
                         "the replay's outputs per update, early against late in a long run "
                         'with fixes'),
    'path-msg': Benchmark('ga_ros.cli.benchmarks.path_msg:main',
                          'the corrected path message at survey scale (CDR against rclpy)'),
    'map': Benchmark('ga_ros.bench.map:main',
                     "map_node's cloud map and live mosaic: update cost against the keyframes "
                     'moved and bytes held, up to 5,000 keyframes'),
}
