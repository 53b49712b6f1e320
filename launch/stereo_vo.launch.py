"""A stereo camera driver + vo_node + alignment_node (``ros2 launch ga_ros stereo_vo.launch.py``).

The driver (default: realsense2_camera's infrared pair; ``start_camera:=false`` when it runs
elsewhere) feeds ``vo_node``, whose measurements go to ``alignment_node``. The camera's extrinsic
comes from ``/tf_static``: your robot_state_publisher, or the static transform started here
(``camera_pose:='x y z roll pitch yaw'`` of ``camera_frame`` in ``base_link``; empty: none).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description():
    config = os.path.join(get_package_share_directory('ga_ros'), 'config')
    camera_pose = LaunchConfiguration('camera_pose')
    return LaunchDescription([
        DeclareLaunchArgument('start_camera', default_value='true'),
        DeclareLaunchArgument('camera_package', default_value='realsense2_camera'),
        DeclareLaunchArgument('camera_executable', default_value='realsense2_camera_node'),
        DeclareLaunchArgument('left_image', default_value='/camera/infra1/image_rect_raw'),
        DeclareLaunchArgument('right_image', default_value='/camera/infra2/image_rect_raw'),
        DeclareLaunchArgument('left_info', default_value='/camera/infra1/camera_info'),
        DeclareLaunchArgument('right_info', default_value='/camera/infra2/camera_info'),
        DeclareLaunchArgument('camera_frame', default_value='camera_infra1_optical_frame'),
        DeclareLaunchArgument('camera_pose', default_value=''),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
        Node(package=LaunchConfiguration('camera_package'),
             executable=LaunchConfiguration('camera_executable'),
             condition=IfCondition(LaunchConfiguration('start_camera')), output='screen'),
        Node(package='tf2_ros', executable='static_transform_publisher',
             condition=IfCondition(PythonExpression(["'", camera_pose, "' != ''"])),
             arguments=[camera_pose, 'base_link', LaunchConfiguration('camera_frame')]),
        Node(package='ga_ros', executable='vo_node', name='vo_node', output='screen',
             parameters=[os.path.join(config, 'vo.yaml'),
                         {'use_sim_time': LaunchConfiguration('use_sim_time'),
                          'camera_frame': LaunchConfiguration('camera_frame')}],
             remappings=[('stereo/left/image_rect', LaunchConfiguration('left_image')),
                         ('stereo/right/image_rect', LaunchConfiguration('right_image')),
                         ('stereo/left/camera_info', LaunchConfiguration('left_info')),
                         ('stereo/right/camera_info', LaunchConfiguration('right_info'))]),
        Node(package='ga_ros', executable='alignment_node', name='alignment_node',
             output='screen',
             parameters=[os.path.join(config, 'alignment.yaml'),
                         {'use_sim_time': LaunchConfiguration('use_sim_time')}]),
    ])
