"""Parameters of the alignment node: :class:`NodeSettings` (its ROS-side settings), the
run-time changeable fields and the list of every declared parameter (no rclpy needed)."""


from dataclasses import dataclass

from ga_ros import topics
from ga_ros.core.config_ranges import check_ranges, ranged
from ga_ros.core.gaps import GapConfig
from ga_ros.core.window import AlignerConfig
from ga_ros.inputs.absolute import AbsoluteInputConfig
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.corrections import CorrectionThresholds
from ga_ros.pipeline.params import parameter_names

#: A dataclass field with a default and its parameter range ``[lo, hi]``.
field_ = ranged


@dataclass(frozen=True)
class NodeSettings:
    """ROS-side parameters of the alignment node (the aligner's are in ``AlignerConfig``).

    Attributes
    ----------
    map_frame : frame of the corrected path / poses (REP 105 ``map``).
    measurements_topic : input: nav_msgs/Odometry measurement encoding (README).
    path_topic : output: nav_msgs/Path of every node, transient local.
    pose_topic : output: PoseWithCovarianceStamped of the newest adjusted node.
    odom_topic : output: nav_msgs/Odometry of the newest node.
    markers_topic : output: MarkerArray of nodes and connections.
    diagnostics_topic : output: DiagnosticArray.
    measurement_queue_depth : depth of the (reliable) measurement subscription queue, messages.
    state_file : the state (snapshot, ``.journal``, ``.lock``, ...) for ``~/save_state`` /
        ``~/load_state`` and resume on start. ``'default'``: ``$ROS_HOME/ga_ros/<namespace>/
        <node name>/state`` (``ROS_HOME`` defaults to ``~/.ros``), logged at start; a path;
        ``''``: no persistence (a crash loses what the publishers no longer hold). Two nodes
        never share one: the second gets a clear error (``.lock``, ``fcntl.flock``) and runs
        without persistence (or refuses to start with ``state_required``).
    autosave : journal every measurement and save the state to ``state_file`` after every
        window update.
    warn_throttle_sec : minimum interval between two warnings about rejected input, s.
    publish_markers : publish the connection network as a MarkerArray.
    residual_color_scale : Mahalanobis residual drawn fully red (unitless); with the aligner's
        ``quality`` on, the ``|w|`` drawn fully red (e.g. the w-test's critical value).
    diagnostics_period_sec : period of the diagnostics timer, s (0 disables; diagnostics are
        also published after every update).
    odom_max_rate_hz : between updates, publish the newest node's pose (its frame-to-frame
        continuation from the last adjusted node, covariance unknown) on ``odom_topic`` at most
        this often, Hz (0: only after updates).
    inputs : comma-separated names of standard inputs (``odom0,pose0``); each has parameters
        ``<name>.topic``, ``<name>.type`` and the OdometryInputConfig fields ``<name>.<field>``
        (config/inputs.yaml).
    constraints_topic : input: external constraints (nav_msgs/Odometry, ``stamp/<ns>`` or
        ``node/<id>`` ends) on the first standard input's keyframes.
    absolutes : comma-separated names of absolute inputs (``fix0,amcl0``: GNSS, AMCL, USBL,
        motion capture; :mod:`ga_ros.pipeline.absolute`), tied to the first standard input's
        keyframes; each has parameters ``<name>.topic``, ``<name>.type`` and the
        AbsoluteInputConfig fields ``<name>.<field>``. With any, set ``datum: fixes`` (the map
        frame is then the fixes' frame).
    track_boundary_topic : input: std_msgs/Empty, a new track of the standard inputs.
    covariance_policy : measurement covariance that is not positive definite: ``reject`` or
        ``repair`` (eigenvalue clipping).
    input_warn_throttle_sec : minimum interval between two default-covariance warnings, s.
    odom_frame : REP 105 odometry frame of the first standard input (``map -> odom`` on TF).
    base_frame : the robot's base frame: ``child_frame_id`` of the corrected odometry (and
        child of ``map`` when ``publish_map_to_base``).
    publish_tf : publish ``map_frame -> odom_frame`` on ``tf_topic`` (odom: the first standard
        input's frame, or without standard inputs the frame-to-frame integration of the
        consecutive measurements).
    publish_map_to_base : also publish ``map_frame -> base_frame`` (only when nothing else
        publishes ``odom -> base``: a frame has one parent).
    tf_topic : TF topic (``/tf``; remap it to ``tf`` for namespaced robots); static transforms
        go on it with ``_static`` appended (``/tf_static``).
    publish_earth_transform : with a NavSatFix input and ``datum: fixes`` (the map frame is then
        the ENU frame at the inputs' origin), publish REP 105 ``earth_frame -> map_frame`` (ECEF
        to ENU at that origin) once on the static TF topic, latched, as soon as the origin is
        known (the ``datum`` parameter, or the first fix).
    earth_frame : REP 105 Earth-centred, Earth-fixed frame (``earth``).
    transform_publish_period_sec : period of the TF timer, s (0: after updates only).
    publish_tf_when_contested : keep publishing ``map_frame -> odom_frame`` when another node
        publishes a transform to ``odom_frame`` on ``tf_topic`` (a frame has one parent: TF
        consumers would jump between the two); off: ours stops until the other has been
        silent for :data:`TF_CONTEST_HOLD_SEC`.
    loss_warn_fraction : diagnostics WARN when a standard input's lost / expected messages
        exceed this.
    window_path_topic : output: nav_msgs/Path of the nodes the window can still move.
    full_path_min_period_sec : publish the full path at most this often, s (0: after every
        update; big surveys: e.g. 10, the window path carries the updates).
    corrections_topic : output: nav_msgs/Path of the keyframes that moved or were added since
        the previous message (reliable, volatile; ``docs/node.md``).
    corrections : when a keyframe counts as moved for ``corrections_topic``
        (:class:`~ga_ros.pipeline.corrections.CorrectionThresholds`; parameters
        ``corrections.translation_m``, ``corrections.rotation_rad``).
    measurement_durability : ``transient_local`` (default: the publisher's history is delivered
        again after a restart, so nothing published while the node was down or still queued
        when it was killed is lost; the publisher must be transient local too, as ``ga-ros
        play`` and the VO node are; a volatile publisher is not matched and named in an error
        line; re-delivered measurements are counted as ``rejected/duplicate``) or ``volatile``
        (any publisher; what is published while the node is down is lost).
    fsync_period_sec : journal durability: every record reaches the OS at once (``kill -9``
        loses nothing); it is also fsync-ed (power cut) after every measurement if 0, else at
        most every this many seconds.
    journal_compact_records : compact the journal at a window update once this many records
        followed its last compaction (its base: the state then, embedded), so a recovery from
        the journal alone replays only what came after (0: never; the journal's replay then grows
        with the survey).
    track_idle_timeout_sec : end the open track when no measurement has arrived for this long,
        wall-clock s (0: never; a track end then comes from the next track's first measurement,
        the end-of-input message or ``~/finish_track``). Measurements of a track that arrive
        after its end are rejected (``out_of_order``): keep it well above any pause of the VO.
    path_period_sec : publish the path, when nodes were added since the last one, at most this
        often, s; the open track's nodes are then in it at their dead-reckoned poses
        (diagnostics ``dead_reckoned_nodes``: how many at the end of the path) (0: only after
        updates).
    allow_reset : whether ``~/reset`` may clear the state (and empty the state files); off by
        default, since any peer on the ROS graph can call it.
    allow_finish_track : whether ``~/finish_track`` may end the open track; off by default:
        a call mid-track turns the rest of the track into ``out_of_order`` rejections and the
        later tracks into ``unknown_source`` ones (tracks end by the next track's first
        measurement, the end-of-input message or ``track_idle_timeout_sec``).
    allow_load_state : whether ``~/load_state`` may replace the state by the state file's;
        off by default (with ``autosave: false`` it reverts to an older save).
    state_required : refuse to start when ``state_file`` cannot be used (its directory is a
        file or read-only, ...) instead of running without persistence (one error line and
        ``persistence: off`` in the diagnostics).
    gaps : measurements whose source node is unknown (a gap in the stream): how long they are
        held for the missing measurements, and the bridges that join what is still apart
        (:class:`~ga_ros.core.gaps.GapConfig`; parameters ``gaps.<name>``).
    """

    map_frame: str = 'map'
    measurements_topic: str = topics.MEASUREMENTS
    path_topic: str = topics.CORRECTED_PATH
    pose_topic: str = topics.CORRECTED_POSE
    odom_topic: str = topics.CORRECTED_ODOM
    markers_topic: str = topics.NETWORK_MARKERS
    diagnostics_topic: str = topics.DIAGNOSTICS
    measurement_queue_depth: int = field_(100000, 1, 1000000)
    state_file: str = 'default'
    autosave: bool = True
    warn_throttle_sec: float = field_(2.0, 0.0, 3600.0)
    publish_markers: bool = True
    residual_color_scale: float = field_(3.0, 1e-6, 1e6)
    diagnostics_period_sec: float = field_(1.0, 0.0, 3600.0)
    odom_max_rate_hz: float = field_(10.0, 0.0, 1000.0)
    inputs: str = ''
    absolutes: str = ''
    constraints_topic: str = topics.CONSTRAINTS
    track_boundary_topic: str = topics.TRACK_BOUNDARY
    covariance_policy: str = 'reject'
    input_warn_throttle_sec: float = field_(10.0, 0.0, 3600.0)
    odom_frame: str = 'odom'
    base_frame: str = 'base_link'
    publish_tf: bool = True
    publish_map_to_base: bool = False
    tf_topic: str = '/tf'
    publish_earth_transform: bool = True
    earth_frame: str = 'earth'
    transform_publish_period_sec: float = field_(0.05, 0.0, 3600.0)
    publish_tf_when_contested: bool = False
    loss_warn_fraction: float = field_(0.01, 0.0, 1.0)
    window_path_topic: str = topics.WINDOW_PATH
    full_path_min_period_sec: float = field_(0.0, 0.0, 86400.0)
    corrections_topic: str = topics.CORRECTIONS
    corrections: CorrectionThresholds = CorrectionThresholds()

    measurement_durability: str = 'transient_local'
    fsync_period_sec: float = field_(1.0, 0.0, 3600.0)
    journal_compact_records: int = field_(1000, 0, 10**9)
    track_idle_timeout_sec: float = field_(0.0, 0.0, 86400.0)
    path_period_sec: float = field_(1.0, 0.0, 3600.0)
    allow_reset: bool = False
    allow_finish_track: bool = False
    allow_load_state: bool = False
    state_required: bool = False
    gaps: GapConfig = GapConfig()

    def __post_init__(self) -> None:
        check_ranges(self)


#: NodeSettings fields that may change at run time (read at use).
DYNAMIC_SETTINGS = frozenset({
    'map_frame', 'odom_frame', 'base_frame', 'publish_tf', 'publish_map_to_base',
    'publish_tf_when_contested', 'loss_warn_fraction',
    'warn_throttle_sec', 'publish_markers', 'residual_color_scale', 'odom_max_rate_hz',
    'covariance_policy', 'input_warn_throttle_sec', 'full_path_min_period_sec'})
#: AlignerConfig fields that may change at run time (the aligner reads them at each update).
DYNAMIC_ALIGNER = frozenset({'outlier_chi2_prob', 'solver.max_iterations', 'solver.tolerance',
                             'solver.robust_loss', 'solver.robust_scale'})


#: Parameters of each standard input ``<name>.``: besides the OdometryInputConfig fields.
INPUT_PARAMETERS = ('topic', 'type', 'qos_reliability', 'qos_depth')


#: Parameters of each absolute input ``<name>.``: besides the AbsoluteInputConfig fields.
ABSOLUTE_PARAMETERS = ('topic', 'type')


def declared_parameters(inputs: tuple[str, ...] = (),
                        absolutes: tuple[str, ...] = ()) -> list[str]:
    """Every parameter the alignment node declares (built from its config dataclasses, no
    rclpy), with those of the standard inputs named in ``inputs`` and of the absolute inputs
    named in ``absolutes``."""
    names = parameter_names(AlignerConfig) + parameter_names(NodeSettings)
    for name in inputs:
        names += [f'{name}.{p}' for p in INPUT_PARAMETERS]
        names += parameter_names(OdometryInputConfig, f'{name}.')
    for name in absolutes:
        names += [f'{name}.{p}' for p in ABSOLUTE_PARAMETERS]
        names += parameter_names(AbsoluteInputConfig, f'{name}.')
    return names
