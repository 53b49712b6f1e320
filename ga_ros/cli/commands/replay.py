"""``ga-ros replay BAG``: offline replay of a recording through the alignment pipeline.

Runs in-process, as fast as the CPU allows, exactly what the live nodes would do, and writes an
mcap bag (corrected path, poses, measurements, markers, /tf), TUM trajectories, a PNG plot and
summary.json. ``--info`` lists the recording's topics and what would be used.

recordings (BAG):
  rosbag2 bag         a directory with metadata.yaml, or one .mcap / .db3 file (mcap, sqlite3)
  ROS 1 bag           a .bag file (read as is, no conversion)
  EuRoC ASL folder    MH_01_easy/ or its mav0/: cam0, cam1 (data.csv, data/*.png,
                      sensor.yaml: intrinsics and T_BS), state_groundtruth_estimate0/data.csv
                      (ground truth, when present); a stereo input
  KITTI odometry      sequences/NN/: image_0, image_1, calib.txt, times.txt; ground truth from
                      poses/NN.txt (two levels up) or poses.txt; a stereo input

inputs (one kind per replay; the first three are found without options):
  measurements        nav_msgs/Odometry in the ga_ros encoding (--measurements-topic,
                      default /ga/measurements): motions with covariances, no VO
  stereo pair         left/right sensor_msgs/Image or CompressedImage with CameraInfo (found by
                      name: left/right, cam0/cam1), or --calibration files; VO runs in-process
  EuRoC / KITTI       the folders above (their stereo pair and calibration)
  odometry sources    --odom-topic TOPIC (repeatable): nav_msgs/Odometry, PoseStamped or
                      PoseWithCovarianceStamped of any robot (wheel odometry, EKF, VIO, SLAM);
                      the first defines the keyframes, the others measure between them;
                      --input-config for per-input settings
  absolute fixes      --absolute-topic TOPIC (repeatable, with --odom-topic):
                      PoseWithCovarianceStamped (AMCL, USBL, motion capture), Odometry or
                      NavSatFix; the map frame is then the fixes' frame
  camera beside odom  --odom-topic with --left-image/--right-image and --camera-extrinsic: the
                      images give cross-track connections between odometry keyframes
  ground truth        --ground-truth-topic (pose topic or tf:PARENT:CHILD) or --ground-truth
                      FILE (TUM, EuRoC data.csv, KITTI poses): error figures

A recording without measurements or a stereo pair gets the command for the topics it has
(e.g. ga-ros replay BAG --odom-topic /odom --absolute-topic /amcl_pose) and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ga_ros import topics
from ga_ros.cli.commands import SUMMARIES
from ga_ros.core.solver.losses import ROBUST_LOSSES
from ga_ros.core.window.freeze import FREEZE_POLICIES
from ga_ros.errors import InputError, NoUsableInputError
from ga_ros.io.groundtruth import DEFAULT_TOLERANCE_S, FILE_FORMATS
from ga_ros.io.topic_plan import TopicConfig
from ga_ros.replay.config import VARIANCE_MODES

if TYPE_CHECKING:
    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.inputs import InputTopics

# The parser needs only the names above; the replay stack (the input front ends with OpenCV,
# the pipeline, SciPy's statistics) is imported by the functions that run it, so that
# ``ga-ros replay --help`` and ``ga-ros demo --help`` start without it.

#: Aligner options of the command line -> AlignerConfig parameter names (as the node's).
ALIGNER_OPTIONS = {'window': 'window_tracks', 'freeze_policy': 'freeze_policy',
                   'robust_loss': 'solver.robust_loss', 'robust_scale': 'solver.robust_scale',
                   'max_iterations': 'solver.max_iterations',
                   'outlier_chi2_prob': 'outlier_chi2_prob', 'gate': 'gate',
                   'quality': 'quality',
                   'online_variance_components': 'variance_components'}


def add_replay_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by ``replay`` and ``demo``: topics, frames, aligner, outputs."""
    _add_input_topic_arguments(p.add_argument_group('input topics'))
    _add_standard_input_arguments(
        p.add_argument_group('standard inputs (odometry / pose streams of any robot)'))
    _add_output_arguments(p.add_argument_group('outputs'))
    _add_alignment_arguments(p.add_argument_group('alignment'))
    _add_vo_arguments(p.add_argument_group('visual odometry (stereo bags)'))


def _add_input_topic_arguments(g: argparse._ArgumentGroup) -> None:
    """The source, its topics and calibration, the ground truth (topic or file)."""
    g.add_argument('--source', choices=('auto', 'measurements', 'stereo'), default='auto',
                   help='what to replay (auto: measurements if the topic exists, else images)')
    g.add_argument('--measurements-topic', default=topics.resolve(topics.MEASUREMENTS))
    g.add_argument('--left-image', default='', help="left images ('' = detect)")
    g.add_argument('--right-image', default='', help="right images ('' = detect)")
    g.add_argument('--left-info', default='', help="left CameraInfo ('' = detect)")
    g.add_argument('--right-info', default='', help="right CameraInfo ('' = detect)")
    g.add_argument('--calibration', nargs='+', default=[], metavar='FILE',
                   help='stereo calibration for bags without CameraInfo: two EuRoC sensor.yaml '
                        '(left, right) or a YAML of the left and right CameraInfo fields')
    g.add_argument('--ground-truth-topic', default=topics.resolve(topics.GROUND_TRUTH),
                   metavar='TOPIC',
                   help='ground truth in the bag: a PoseStamped, PoseWithCovarianceStamped, '
                        "Odometry or Path topic, or a TF pair tf:PARENT:CHILD ('' = ignore)")
    g.add_argument('--ground-truth', type=Path, metavar='FILE',
                   help='ground truth file (TUM, EuRoC data.csv or KITTI poses), matched to '
                        'the keyframes by stamp with interpolation; replaces the topic')
    g.add_argument('--ground-truth-format', choices=FILE_FORMATS, default='auto',
                   help='format of --ground-truth (auto: from its first line)')
    g.add_argument('--ground-truth-times', type=Path, metavar='FILE',
                   help='stamps of a KITTI file: its times.txt (seconds, one a line)')
    g.add_argument('--ground-truth-rate', type=float, default=0.0, metavar='HZ',
                   help='stamps of a KITTI file without times.txt: pose k at k / HZ s')
    g.add_argument('--ground-truth-start', type=float, default=0.0, metavar='SEC',
                   help="added to a KITTI file's stamps (KITTI's time 0 in the bag's clock)")
    g.add_argument('--ground-truth-tolerance', type=float, default=DEFAULT_TOLERANCE_S,
                   metavar='SEC',
                   help='largest gap between ground-truth samples to interpolate across, and '
                        'largest distance to hold the first / last one (default %(default)s)')


def _add_standard_input_arguments(s: argparse._ArgumentGroup) -> None:
    """Odometry / pose inputs, absolute fixes, constraints, track boundaries, a camera beside
    the odometry, the covariance policy."""
    s.add_argument('--odom-topic', '--input-topic', dest='input_topics', action='append',
                   default=[], metavar='TOPIC',
                   help='odometry / pose input: nav_msgs/Odometry, geometry_msgs/'
                        'PoseWithCovarianceStamped or PoseStamped (type from the bag); '
                        'repeatable: inputs odom0, odom1, ...; the first defines the keyframes, '
                        'the others measure the motion between them')
    s.add_argument('--absolute-topic', dest='absolute_topics', action='append', default=[],
                   metavar='TOPIC',
                   help='absolute fixes (weighted parameters): geometry_msgs/'
                        'PoseWithCovarianceStamped (AMCL, USBL, motion capture), nav_msgs/'
                        'Odometry or sensor_msgs/NavSatFix (type from the bag); repeatable: '
                        "inputs fix0, fix1, ...; the map frame is then the fixes' frame")
    s.add_argument('--input-config', type=Path, metavar='YAML',
                   help='input settings by name (config/inputs.yaml: keyframes, covariance '
                        'policy, track rule; a section with a topic adds that input)')
    s.add_argument('--constraints-topic', default='',
                   help='external constraints (nav_msgs/Odometry, stamp/<ns> or node/<id> ends)')
    s.add_argument('--track-boundary-topic', default='', help='std_msgs/Empty: new track')
    s.add_argument('--camera-extrinsic', nargs='+', metavar='VALUE',
                   help='with --odom-topic and --left-image/--right-image: a stereo camera '
                        'beside the odometry, T_base_camera of its left optical frame: '
                        'X Y Z QX QY QZ QW (m, quaternion x y z w), or identity (the camera '
                        'frame is the base frame); required; its images give cross-track '
                        'connections on the odometry keyframes')
    s.add_argument('--image-offset', type=float, default=0.25, metavar='S',
                   help='largest time between an odometry keyframe and its image pair (s)')
    s.add_argument('--covariance-policy', choices=('reject', 'repair'), default='reject',
                   help='measurement covariances that are not positive definite: reject them '
                        '(as the live node) or repair them by eigenvalue clipping')


def _add_output_arguments(o: argparse._ArgumentGroup) -> None:
    """Frames, topics and files of the outputs."""
    o.add_argument('--map-frame', default='map', help='frame of the corrected path')
    o.add_argument('--odom-frame', default='odom', help='REP 105 odom frame (map -> odom on /tf)')
    o.add_argument('--base-frame', default='base_link',
                   help='child frame of the corrected odometry stream')
    o.add_argument('--no-tf', action='store_true', help='no /tf in the output bag')
    o.add_argument('--path-topic', default=topics.resolve(topics.CORRECTED_PATH))
    o.add_argument('--pose-topic', default=topics.resolve(topics.CORRECTED_POSE))
    o.add_argument('--markers-topic', default=topics.resolve(topics.NETWORK_MARKERS))
    o.add_argument('--no-plot', action='store_true', help='do not write the PNG plot')
    o.add_argument('--mosaic', action='store_true',
                   help='stereo image bags: write mosaic_ga.png / mosaic_f2f.png (keyframe '
                        "images on the ground with GA's and the odometry's poses) and their "
                        'seam misregistration in summary.json')
    o.add_argument('--no-covariance', action='store_true',
                   help='write zero covariances on the pose topic (faster on big surveys)')
    o.add_argument('--no-progress', action='store_true', help='no progress bar')
    o.add_argument('--map', action='store_true',
                   help='stereo bags: write map_ga.ply (the keyframe clouds at the GA poses) and '
                        'map_f2f.ply (at the frame-to-frame poses), and the mosaics of '
                        '--mosaic; figures in summary.json')
    o.add_argument('--map-voxel', type=float, default=None, metavar='M',
                   help='edge of the map voxels with --map (m; default '
                        "map_node's voxel_m)")


def _add_alignment_arguments(a: argparse._ArgumentGroup) -> None:
    """The aligner and its settings (:data:`ALIGNER_OPTIONS`)."""
    a.add_argument('--aligner', choices=('window', 'batch'), default='window',
                   help='window: the live track-window aligner (default); batch: re-solve the '
                        'whole survey at every track end (reference; small surveys only)')
    a.add_argument('--window', type=int, help='tracks in the sliding window (default 5)')
    a.add_argument('--freeze-policy', choices=tuple(FREEZE_POLICIES))
    a.add_argument('--robust-loss', choices=ROBUST_LOSSES)
    a.add_argument('--robust-scale', type=float)
    a.add_argument('--max-iterations', type=int)
    a.add_argument('--outlier-chi2-prob', type=float,
                   help='misclosure test quantile for cross connections (0 disables)')
    a.add_argument('--gate', choices=('chi2', 'w-test'),
                   help='gross-error gate on cross connections: chi-square misclosure test '
                        "(default) or Baarda's w-test data snooping")
    a.add_argument('--quality', action='store_true', default=None,
                   help='quality control of every update (summary.json "quality" block, '
                        'markers coloured by |w|)')
    a.add_argument('--no-final-batch', action='store_true',
                   help='skip the final batch of the whole survey after the last track: '
                        'trajectory_ga.tum is then the online estimate (as trajectory_online.tum)')
    a.add_argument('--variance-components', choices=VARIANCE_MODES, default='report',
                   help='variance factor per source (each odometry input, the cross-track '
                        'connections, the fixes) in the final batch: report (default: '
                        'estimated, printed, in summary.json, the trajectory unchanged), apply '
                        '(also weighted and published with) or off')
    a.add_argument('--no-variance-components', action='store_true',
                   help='same as --variance-components off')
    a.add_argument('--calibrate', action='store_true',
                   help="the final batch also estimates each odometry source's scale and "
                        'yaw-rate corrections where the network determines them and they are '
                        'significant (docs/calibration.md); printed and in summary.json')
    a.add_argument('--calibrate-camera', dest='calibrate_cameras', action='append',
                   default=[], metavar='NAME',
                   help="the final batch also estimates this camera's extrinsic rotation error "
                        '(NAME: the source of its measurements, cam0 unless --vo source=... '
                        'names it) where the network determines it (another orientation '
                        'source: odometry, fixes); repeatable; printed and in summary.json')
    a.add_argument('--online-variance-components', choices=('off', 'apply'),
                   help='variance factor per source estimated online after each track and '
                        'used by the window adjustments and published covariances: apply, or '
                        'off (default; node parameter variance_components)')
    a.add_argument('--no-anchor', action='store_true',
                   help='start at the identity instead of the ground-truth first pose (the '
                        'errors are then compared after rigid alignment)')


def _add_vo_arguments(v: argparse._ArgumentGroup) -> None:
    """The stereo VO's parameters (image bags)."""
    v.add_argument('--vo-params', type=Path, metavar='FILE',
                   help="vo_node's parameter file (config/vo.yaml); its topic and queue "
                        'settings are ignored')
    v.add_argument('--vo', action='append', default=[], metavar='KEY=VALUE',
                   help='one VO parameter of config/vo.yaml (repeatable; after --vo-params), '
                        'e.g. --vo keyframe_max_travel_ratio=0.1')


def topic_config(args: argparse.Namespace) -> TopicConfig:
    return TopicConfig(measurements=args.measurements_topic, left_image=args.left_image,
                       right_image=args.right_image, left_info=args.left_info,
                       right_info=args.right_info, ground_truth=args.ground_truth_topic,
                       source=args.source, calibration=tuple(map(str, args.calibration)))


def vo_config(args: argparse.Namespace) -> Any:
    """The stereo front end settings of ``--vo-params`` and ``--vo`` (None: defaults)."""
    if not args.vo_params and not args.vo:
        return None
    from ga_ros.pipeline.params import parse_override, read_params_file
    from ga_ros.pipeline.stereo import front_end_config_from_params

    params = read_params_file(args.vo_params, 'vo_node') if args.vo_params else {}
    params.update(parse_override(text) for text in args.vo)
    return front_end_config_from_params(params)


def input_topics(args: argparse.Namespace) -> InputTopics:
    """The standard inputs of the command line (``--odom-topic``, ``--input-config``, ...)."""
    import yaml

    from ga_ros.inputs.names import FIX, ODOMETRY, numbered
    from ga_ros.pipeline.absolute import absolute_specs_from_mapping
    from ga_ros.pipeline.inputs import specs_from_mapping
    from ga_ros.replay.inputs import InputTopics

    sections: dict[str, Any] = {}
    if args.input_config is not None:
        try:
            sections = yaml.safe_load(args.input_config.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise InputError(f'cannot read --input-config {args.input_config}: {exc}') from exc
        if not isinstance(sections, dict):
            raise InputError(f'{args.input_config}: expected sections named like odom0, pose0')
    absolutes = sections.pop('absolutes', None) or {}
    if not isinstance(absolutes, dict):
        raise InputError(f'{args.input_config}: absolutes must map names (fix0, ...) to settings')
    abs_specs = absolute_specs_from_mapping(
        absolutes, numbered(FIX, getattr(args, 'absolute_topics', [])))
    named = numbered(ODOMETRY, args.input_topics)
    specs = specs_from_mapping(sections, named)
    return InputTopics(specs, args.constraints_topic, args.track_boundary_topic,
                       camera=camera_topics(args) if specs else None, absolutes=abs_specs)


def camera_topics(args: argparse.Namespace) -> Any:
    """A stereo camera beside the odometry (``--left-image`` and ``--right-image`` with
    ``--odom-topic``), else None."""
    if not (args.left_image or args.right_image):
        return None
    if not (args.left_image and args.right_image):
        raise InputError('a camera beside the odometry needs both --left-image and '
                         '--right-image')
    from ga_ros.pipeline.keyframe_camera import KeyframeCameraConfig
    from ga_ros.pipeline.stereo import FrontEndConfig
    from ga_ros.replay.inputs import CameraTopics
    from ga_ros.replay.stereo import front_end_config

    front = front_end_config(vo_config(args))
    extrinsic = camera_extrinsic(args.camera_extrinsic)
    assert isinstance(front, FrontEndConfig)
    config = KeyframeCameraConfig(front, extrinsic, args.image_offset)
    return CameraTopics(args.left_image, args.right_image, args.left_info, args.right_info,
                        tuple(map(str, args.calibration)), config)


def camera_extrinsic(values: list[str] | None) -> tuple[float, ...]:
    """``--camera-extrinsic``: ``x y z qx qy qz qw`` (m, quaternion x y z w) or ``identity``.

    Raises
    ------
    InputError
        Not given (identity only when said so), or neither seven numbers nor ``identity``.
    """
    from ga_ros.core.extrinsic import unknown_extrinsic_error

    if not values:
        raise unknown_extrinsic_error('camera', '--camera-extrinsic',
                                      '--camera-extrinsic identity', tf_static=False)
    if values == ['identity']:
        return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    try:
        numbers = tuple(float(v) for v in values)
    except ValueError:
        numbers = ()
    if len(numbers) != 7:
        raise InputError(f"--camera-extrinsic takes 'X Y Z QX QY QZ QW' or 'identity', got "
                         f"{' '.join(values)!r}")
    return numbers


def replay_config(args: argparse.Namespace, progress: bool) -> ReplayConfig:
    """ReplayConfig from parsed arguments (the aligner module is imported only if needed)."""
    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.outputs import OutputConfig

    if not args.ground_truth_tolerance >= 0:
        raise InputError('--ground-truth-tolerance must be >= 0 s')
    overrides = {field: getattr(args, opt) for opt, field in ALIGNER_OPTIONS.items()
                 if getattr(args, opt, None) is not None}
    aligner: Any = None
    inputs = input_topics(args)
    if inputs.absolutes:
        overrides.setdefault('datum', 'fixes')  # the map frame is the fixes' frame
    if overrides and args.aligner == 'window':
        from ga_ros.core.window import AlignerConfig
        from ga_ros.pipeline.params import config_from_params

        aligner, _ = config_from_params(AlignerConfig, overrides)
    maps = None
    if args.map:
        from dataclasses import replace

        from ga_ros.replay.map_outputs import MapOutputConfig

        maps = MapOutputConfig()
        if args.map_voxel is not None:
            maps = replace(maps, cloud=replace(maps.cloud, voxel_m=args.map_voxel))
    outputs = OutputConfig(map_frame=args.map_frame, path_topic=args.path_topic,
                           pose_topic=args.pose_topic, markers_topic=args.markers_topic,
                           odom_frame=args.odom_frame, sensor_frame=args.base_frame)
    return ReplayConfig(topics=topic_config(args), outputs=outputs, aligner=aligner,
                        aligner_kind=args.aligner, vo=vo_config(args),
                        final_batch=not args.no_final_batch,
                        variance_components=('off' if args.no_variance_components
                                             else args.variance_components),
                        calibrate=args.calibrate,
                        calibrate_cameras=tuple(args.calibrate_cameras),
                        pose_covariance=not args.no_covariance,
                        anchor_to_ground_truth=not args.no_anchor, plot=not args.no_plot,
                        progress=progress and not args.no_progress, inputs=inputs,
                        ground_truth_file=str(args.ground_truth or ''),
                        ground_truth_format=args.ground_truth_format,
                        ground_truth_times=str(args.ground_truth_times or ''),
                        ground_truth_rate_hz=args.ground_truth_rate,
                        ground_truth_start_s=args.ground_truth_start,
                        ground_truth_tolerance_s=args.ground_truth_tolerance, tf=not args.no_tf,
                        covariance_policy=args.covariance_policy,
                        mosaic=args.mosaic or args.map, map=maps)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'replay', help=SUMMARIES['replay'],
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False)
    p.add_argument('bag', type=Path, help='rosbag2 directory or .mcap / .db3 file, ROS 1 .bag '
                                          'file, EuRoC ASL folder or KITTI sequence folder')
    p.add_argument('--out', type=Path,
                   help='output directory (default out/replay/<bag name>)')
    p.add_argument('--info', action='store_true',
                   help="list the bag's topics and what the replay would use, then exit")
    p.add_argument('--json', action='store_true', help='print the summary as JSON')
    add_replay_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ga_ros.io.folder_bag import recording_info
    from ga_ros.replay.pipeline import replay
    from ga_ros.replay.text import info_text, plan_lines, result_text

    topics = topic_config(args)
    if args.info:
        text, status = info_text(recording_info(args.bag), topics, input_topics(args))
        print(text)
        return status
    out = args.out or Path('out') / 'replay' / (args.bag.stem or args.bag.name)
    config = replay_config(args, progress=sys.stderr.isatty() and not args.json)

    def show_plan(plan: Any) -> None:
        if not args.json:
            for line in plan_lines(plan):
                print(line)

    try:
        result = replay(args.bag, out, config, on_plan=show_plan)
    except NoUsableInputError as exc:  # a usage error: the command for the bag's topics
        print(f'ga-ros replay: error: {exc}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result.as_dict(), default=str))
    else:
        print(result_text(result))
    for w in result.warnings:
        print(f'ga-ros replay: warning: {w}', file=sys.stderr)
    return 0
