"""A stereo camera driver + vo_node + alignment_node.

    ros2 launch ga_ros stereo_vo.launch.py camera_pose:='0.2 0 0.5 -1.5708 0 -1.5708'

The driver (default: realsense2_camera's infrared pair; ``start_camera:=false`` when it runs
elsewhere) feeds ``vo_node``, whose measurements go to ``alignment_node``. The camera's extrinsic
comes from ``/tf_static``: your robot_state_publisher, or the static transform started here,
``camera_pose:='x y z roll pitch yaw'`` (m, rad; ``R = Rz(yaw) Ry(pitch) Rx(roll)``, fixed axes) of
``camera_frame`` in ``base_frame``, handed to tf2_ros' ``static_transform_publisher`` as
``--x --y --z --roll --pitch --yaw --frame-id --child-frame-id`` (empty: none started). The
``compressed`` and ``base_frame`` defaults are those of ``config/vo.yaml`` (read from the
installed file). ``map:=true`` also starts ``map_node`` (``config/map.yaml``): the keyframe clouds
at their corrected poses on ``ga/map``.
"""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from launch import LaunchDescription

#: static_transform_publisher's options, in the order of camera_pose's numbers.
POSE_OPTIONS = ('--x', '--y', '--z', '--roll', '--pitch', '--yaw')


def camera_transform(context, *args, **kwargs):
    """tf2_ros' static_transform_publisher of ``camera_pose`` (none if it is empty)."""
    pose = LaunchConfiguration('camera_pose').perform(context).split()
    if not pose:
        return []
    try:
        [float(v) for v in pose]
    except ValueError:
        pose = []
    if len(pose) != len(POSE_OPTIONS):
        raise RuntimeError("camera_pose needs six numbers 'x y z roll pitch yaw' (m, rad), got "
                           f"{LaunchConfiguration('camera_pose').perform(context)!r}")
    arguments = [a for option, value in zip(POSE_OPTIONS, pose) for a in (option, value)]
    arguments += ['--frame-id', LaunchConfiguration('base_frame').perform(context),
                  '--child-frame-id', LaunchConfiguration('camera_frame').perform(context)]
    return [Node(package='tf2_ros', executable='static_transform_publisher',
                 name='camera_static_transform', output='screen', arguments=arguments)]


def generate_launch_description():
    config = os.path.join(get_package_share_directory('ga_ros'), 'config')
    with open(os.path.join(config, 'vo.yaml')) as f:
        vo = yaml.safe_load(f)['vo_node']['ros__parameters']
    return LaunchDescription([
        DeclareLaunchArgument('start_camera', default_value='true'),
        DeclareLaunchArgument('camera_package', default_value='realsense2_camera'),
        DeclareLaunchArgument('camera_executable', default_value='realsense2_camera_node'),
        DeclareLaunchArgument('left_image', default_value='/camera/infra1/image_rect_raw'),
        DeclareLaunchArgument('right_image', default_value='/camera/infra2/image_rect_raw'),
        DeclareLaunchArgument('left_info', default_value='/camera/infra1/camera_info'),
        DeclareLaunchArgument('right_info', default_value='/camera/infra2/camera_info'),
        DeclareLaunchArgument('compressed', default_value=str(vo['compressed']).lower(),
                              description='images are sensor_msgs/CompressedImage'),
        DeclareLaunchArgument('base_frame', default_value=vo['base_frame']),
        DeclareLaunchArgument('camera_frame', default_value='camera_infra1_optical_frame'),
        DeclareLaunchArgument('camera_pose', default_value='',
                              description="'x y z roll pitch yaw' (m, rad) of camera_frame in "
                                          'base_frame; empty: from your /tf_static'),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
        DeclareLaunchArgument('map', default_value='false',
                              description='also start map_node (the point-cloud map ga/map)'),
        Node(package=LaunchConfiguration('camera_package'),
             executable=LaunchConfiguration('camera_executable'),
             condition=IfCondition(LaunchConfiguration('start_camera')), output='screen'),
        OpaqueFunction(function=camera_transform),
        Node(package='ga_ros', executable='vo_node', name='vo_node', output='screen',
             parameters=[os.path.join(config, 'vo.yaml'),
                         {'use_sim_time': LaunchConfiguration('use_sim_time'),
                          'compressed': ParameterValue(LaunchConfiguration('compressed'),
                                                       value_type=bool),
                          'base_frame': ParameterValue(LaunchConfiguration('base_frame'),
                                                       value_type=str),
                          'camera_frame': ParameterValue(LaunchConfiguration('camera_frame'),
                                                         value_type=str)}],
             remappings=[('stereo/left/image_rect', LaunchConfiguration('left_image')),
                         ('stereo/right/image_rect', LaunchConfiguration('right_image')),
                         ('stereo/left/camera_info', LaunchConfiguration('left_info')),
                         ('stereo/right/camera_info', LaunchConfiguration('right_info'))]),
        Node(package='ga_ros', executable='alignment_node', name='alignment_node',
             output='screen',
             parameters=[os.path.join(config, 'alignment.yaml'),
                         {'use_sim_time': LaunchConfiguration('use_sim_time')}]),
        Node(package='ga_ros', executable='map_node', name='map_node', output='screen',
             condition=IfCondition(LaunchConfiguration('map')),
             parameters=[os.path.join(config, 'map.yaml'),
                         {'use_sim_time': LaunchConfiguration('use_sim_time'),
                          'base_frame': ParameterValue(LaunchConfiguration('base_frame'),
                                                       value_type=str)}]),
    ])
