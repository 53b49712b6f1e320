"""Every topic name of ga_ros, defined once.

The defaults are RELATIVE names (no leading ``/``): without a namespace they resolve to
``/ga/...`` as before, and with ``--ros-args -r __ns:=/robot1`` they move with the node
(``/robot1/ga/...``). Bags store absolute names: :func:`resolve` gives the name a node in
``namespace`` would use, which is what the replay reads and writes.
"""

from __future__ import annotations

#: Measurements (``nav_msgs/Odometry`` encoding), from ``vo_node`` to ``alignment_node``.
MEASUREMENTS = 'ga/measurements'
#: ``child_frame_id`` of the end-of-input / track-end message on the measurements topic: a
#: ``nav_msgs/Odometry`` with this child frame (other fields ignored) ends the open track after
#: every measurement published before it (``ga-ros play`` sends one at the end of a bag).
TRACK_END_FRAME = 'ga/track_end'
#: Suffix of the input-done topic of a measurements topic (``std_msgs/Empty``, volatile): the
#: alignment node publishes one after it has processed an end-of-input message, so that a
#: publisher (``ga-ros play``) keeps its history until the input was processed, not only
#: received (a node killed with measurements still queued gets them again after a restart).
INPUT_DONE_SUFFIX = '_done'


def input_done_topic(measurements_topic: str) -> str:
    """The input-done topic of a measurements topic (``ga/measurements_done``): after each
    end-of-input message an alignment node publishes a ``diagnostic_msgs/KeyValue`` there,
    ``key`` its fully qualified node name, ``value`` how many measurements it has received on
    that topic (decimal), so a player can tell that every node got everything it sent."""
    return measurements_topic + INPUT_DONE_SUFFIX


#: Corrected path (``nav_msgs/Path``, transient local), every node in the map frame.
CORRECTED_PATH = 'ga/corrected_path'
#: Newest adjusted node (``geometry_msgs/PoseWithCovarianceStamped``).
CORRECTED_POSE = 'ga/corrected_pose'
#: Newest node as ``nav_msgs/Odometry``.
CORRECTED_ODOM = 'ga/corrected_odom'
#: Poses of the nodes the window can still move (``nav_msgs/Path``), after every update: the
#: light output for big surveys (the full path may then be sent at a low rate).
WINDOW_PATH = 'ga/window_path'
#: Per-update corrections (``nav_msgs/Path``, reliable, volatile): anchor keyframes of what moved
#: beyond a threshold and the keyframes added since the previous message, each pose named by its
#: stamp, its ``header.frame_id`` the map frame (:mod:`ga_ros.pipeline.corrections`,
#: ``docs/node.md``).
CORRECTIONS = 'ga/corrections'
#: ``header.frame_id`` of the marker that opens a full corrections message (``poses[0]``, not a
#: keyframe): the consumer drops every keyframe it held and takes the ones that follow.
CORRECTIONS_FULL_FRAME = 'ga/full_path'
#: Ending of a corrections entry's ``header.frame_id`` (``map/span``): the entry
#: closes a span from the previous entry, and the keyframes held between the two get the
#: interpolated correction (:func:`ga_ros.pipeline.corrections.interpolate_correction`).
CORRECTIONS_SPAN_SUFFIX = '/span'
#: External constraints (``nav_msgs/Odometry``, ``stamp/<ns>`` or ``node/<id>`` ends).
CONSTRAINTS = 'ga/constraints'
#: ``std_msgs/Empty``: start a new track of the standard inputs.
TRACK_BOUNDARY = 'ga/track_boundary'
#: Connection network (``visualization_msgs/MarkerArray``, transient local).
NETWORK_MARKERS = 'ga/network_markers'
#: Frame-to-frame (dead-reckoning) path written by the replay.
F2F_PATH = 'ga/f2f_path'
#: Ground truth (``nav_msgs/Path``) in sample and simulated bags.
GROUND_TRUTH = 'ga/ground_truth'
#: Raw integrated VO pose of every frame (``nav_msgs/Odometry``).
VO_ODOMETRY = 'ga/vo/odometry'
#: ``std_msgs/Empty``: start a new track.
VO_TRACK_BOUNDARY = 'ga/vo/track_boundary'
#: Debug image of the VO.
VO_DEBUG_IMAGE = 'ga/vo/debug_image'
#: Dense stereo points of each new keyframe (``sensor_msgs/PointCloud2``, the camera's optical
#: frame, stamped with the keyframe's stamp), from ``vo_node``.
KEYFRAME_CLOUD = 'ga/keyframe_cloud'
#: Rectified left image of each new keyframe (``sensor_msgs/Image``, stamp and frame of its
#: cloud) and the rectified camera's ``sensor_msgs/CameraInfo``, from ``vo_node``.
KEYFRAME_IMAGE = 'ga/keyframe_image'
KEYFRAME_CAMERA_INFO = 'ga/keyframe_camera_info'
#: The photomosaic of ``map_node`` (``sensor_msgs/Image`` in the map frame, transient local)
#: and its georeference (``nav_msgs/MapMetaData``, same stamp).
MOSAIC = 'ga/mosaic'
MOSAIC_INFO = 'ga/mosaic_info'
#: The point-cloud map of ``map_node`` (``sensor_msgs/PointCloud2`` in the map frame, transient
#: local): the keyframe clouds at their corrected poses, voxel-downsampled.
MAP_CLOUD = 'ga/map'
#: Stereo input of ``vo_node``.
LEFT_IMAGE = 'stereo/left/image_rect'
RIGHT_IMAGE = 'stereo/right/image_rect'
LEFT_INFO = 'stereo/left/camera_info'
RIGHT_INFO = 'stereo/right/camera_info'
#: Diagnostics: absolute, where ``diagnostic_aggregator`` listens.
DIAGNOSTICS = '/diagnostics'


def resolve(name: str, namespace: str = '/') -> str:
    """Absolute name of topic ``name`` for a node in ``namespace`` (ROS name resolution).

    Parameters
    ----------
    name : absolute (``/a/b``, returned unchanged) or relative (``a/b``) topic name; ``''`` is
        returned unchanged (it means "no topic" in the replay's options).
    namespace : the node's namespace (``/`` or ``/robot1``).

    Returns
    -------
    str
        ``/a/b`` or ``/robot1/a/b``.
    """
    if not name or name.startswith('/'):
        return name
    return namespace.rstrip('/') + '/' + name
