"""Settings of one replay: :class:`ReplayConfig`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ga_ros.errors import InputError
from ga_ros.io.groundtruth import DEFAULT_TOLERANCE_S
from ga_ros.io.topic_plan import TopicConfig
from ga_ros.pipeline.map_to_odom import TRANSFORM_PERIOD_S
from ga_ros.replay.inputs import InputTopics
from ga_ros.replay.map_outputs import MapOutputConfig
from ga_ros.replay.outputs import OutputConfig

#: What the final batch does with the variance factors per source (``ReplayConfig``).
VARIANCE_MODES = ('off', 'report', 'apply')


@dataclass(frozen=True)
class ReplayConfig:
    """Settings of one replay.

    Attributes
    ----------
    topics : input topic names (and the source: measurements or stereo images).
    outputs : output topic names, map frame, bag name.
    aligner : :class:`ga_ros.core.window.AlignerConfig` (None = its defaults), or a
        :class:`ga_ros.core.solver.SolverConfig` with ``aligner_kind='batch'``.
    aligner_kind : ``'window'`` (the live node's track-window aligner) or ``'batch'``.
    vo : configuration object of the stereo VO (None = its defaults); used for image bags.
    final_batch : after the last track, solve the whole survey once more in one batch
        (:meth:`~ga_ros.core.window.TrackWindowAligner.refine_batch`, fixes included): GA's
        trajectory (``trajectory_ga.tum``); the online estimate (the live node's at the end)
        goes to ``trajectory_online.tum``.
    variance_components : the final batch's variance factor per source (each odometry input's
        motions, the cross-track connections, the fixes;
        :mod:`ga_ros.core.quality.variance_components`), one of :data:`VARIANCE_MODES`:
        ``'off'``; ``'report'``: estimated, printed, warned about and in ``summary.json``'s
        ``variance_components``, the trajectory and covariances unchanged; ``'apply'``: also
        weighted and published with (the significant ones).
    calibrate : each odometry source's additional parameters (scale and yaw-rate
        corrections, :mod:`ga_ros.core.calibration`) are estimated where the network
        determines them and they are significant: online (the window aligner's ``calibrate``,
        :mod:`ga_ros.core.window.calibration`: the online trajectory uses them; the text and
        ``summary.json``'s ``online_calibration`` show the last estimate) and in the final
        batch (GA's trajectory uses them, the text and ``summary.json``'s ``calibration`` show
        them, in place of the variance components).
    calibrate_cameras : sources (``cam0``, ...) whose motions and cross-track connections a
        camera's extrinsic rotation error conjugates: the final batch estimates it
        (:attr:`CalibrationConfig.cameras <ga_ros.core.calibration.CalibrationConfig>`, with
        the odometry's parameters, in place of the variance components; the text and
        ``summary.json``'s ``calibration`` show it). A name that is not a source of the
        replay is an :class:`~ga_ros.errors.InputError` (before reading where the inputs name
        their sources: a stereo bag, odometry topics; else at the final batch).
    pose_covariance : write each corrected pose's marginal covariance (else zeros).
    anchor_to_ground_truth : start the F2F and corrected paths at the ground-truth pose of the
        first node (the datum) when the bag has ground truth; else at the identity.
    plot : write the PNG plot.
    progress : show a progress bar on stderr.
    inputs : standard inputs (odometry / pose topics, constraints, track boundaries); when it
        has inputs they are the source (:mod:`ga_ros.replay.inputs`).
    ground_truth_file : TUM, EuRoC or KITTI ground truth (:mod:`ga_ros.io.groundtruth`),
        matched by stamp; replaces the bag's ground truth.
    ground_truth_format : ``'auto'``, ``'tum'``, ``'euroc'`` or ``'kitti'``.
    ground_truth_times, ground_truth_rate_hz, ground_truth_start_s : stamps of a KITTI file
        (its ``times.txt``, or a rate in Hz; plus a start time in s).
    ground_truth_tolerance_s : largest gap between ground-truth samples to interpolate across,
        and largest distance to hold the first / last sample (s).
    tf : write ``map -> odom`` on ``/tf`` every ``transform_publish_period_sec`` of the bag's
        log time, from the first measurement to the end, with the latest correction (and copy
        the input bag's ``/tf``, ``/tf_static`` without the transforms that would give ``odom``
        a second parent, counted in the summary's ``frames``).
    transform_publish_period_sec : period of ``map -> odom`` in the output bag, s (as the
        node's parameter of the same name).
    covariance_policy : a measurement covariance that is not positive definite: ``'reject'``
        (as the live node by default) or ``'repair'`` (eigenvalue clipping).
    mosaic : for a stereo image bag, write ``mosaic_ga.png`` / ``mosaic_f2f.png`` of the
        keyframes' left images with GA's and the odometry's poses and their seam
        misregistration (:mod:`ga_ros.mapping.replay_mosaic`).
    map : write the maps of a stereo bag (``map_ga.ply``, ``map_f2f.ply``;
        :mod:`ga_ros.replay.map_outputs`) with these settings; None: no maps. The replay's
        ``--map`` sets both ``map`` and ``mosaic``.
    """

    topics: TopicConfig = TopicConfig()
    outputs: OutputConfig = OutputConfig()
    aligner: Any = None
    aligner_kind: str = 'window'
    vo: Any = None
    final_batch: bool = True
    variance_components: str = 'report'
    calibrate: bool = False
    calibrate_cameras: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.variance_components not in VARIANCE_MODES:
            raise InputError(f'variance_components must be one of {VARIANCE_MODES}, got '
                             f'{self.variance_components!r}')
    pose_covariance: bool = True
    anchor_to_ground_truth: bool = True
    plot: bool = True
    progress: bool = False
    inputs: InputTopics = InputTopics()
    ground_truth_file: str = ''
    ground_truth_format: str = 'auto'
    ground_truth_times: str = ''
    ground_truth_rate_hz: float = 0.0
    ground_truth_start_s: float = 0.0
    ground_truth_tolerance_s: float = DEFAULT_TOLERANCE_S
    tf: bool = True
    covariance_policy: str = 'reject'
    transform_publish_period_sec: float = TRANSFORM_PERIOD_S
    mosaic: bool = False
    map: MapOutputConfig | None = None
