"""Odometry, and optionally absolute fixes, into alignment_node.

    ros2 launch ga_ros odometry.launch.py odom_topic:=/odom
    ros2 launch ga_ros odometry.launch.py odom_topic:=/odom fix_topic:=/amcl_pose datum:=fixes

The odometry is the first standard input ``odom0`` (it defines the keyframes; the REP 105
``odom`` frame); the node publishes ``map -> odom`` and the corrected path. ``fix_topic`` (empty:
no fixes) is the absolute input ``fix0``: AMCL or a motion-capture pose
(``geometry_msgs/msg/PoseWithCovarianceStamped``), ``nav_msgs/msg/Odometry`` or GNSS
(``sensor_msgs/msg/NavSatFix``), set with ``fix_type``; with ``datum:=fixes`` the map frame is the
fixes' (README "Absolute fixes"). Other per-input settings: ``config/inputs.yaml``. Every
default is the one of ``config/`` (read from the installed files).
"""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from launch import LaunchDescription


def _text(name: str) -> ParameterValue:
    """The launch argument ``name`` as a string parameter (never re-typed by YAML)."""
    return ParameterValue(LaunchConfiguration(name), value_type=str)


def generate_launch_description():
    config = os.path.join(get_package_share_directory('ga_ros'), 'config')
    with open(os.path.join(config, 'alignment.yaml')) as f:
        node = yaml.safe_load(f)['alignment_node']['ros__parameters']
    with open(os.path.join(config, 'inputs.yaml')) as f:
        inputs = yaml.safe_load(f)
    fix_topic = LaunchConfiguration('fix_topic')
    return LaunchDescription([
        DeclareLaunchArgument('odom_topic', default_value='/odom',
                              description='odometry topic (input odom0)'),
        DeclareLaunchArgument('odom_type', default_value='nav_msgs/msg/Odometry',
                              description='its type: nav_msgs/msg/Odometry, '
                                          'geometry_msgs/msg/PoseStamped, ...'),
        DeclareLaunchArgument('track_mode', default_value=inputs['odom0']['track']['mode'],
                              description="track boundaries: 'none', 'frames', 'heading', "
                                          "'distance', 'time', 'external'"),
        DeclareLaunchArgument('fix_topic', default_value='',
                              description='absolute fixes (input fix0); empty: none'),
        DeclareLaunchArgument('fix_type', default_value='geometry_msgs/msg/'
                                                       'PoseWithCovarianceStamped',
                              description='their type: geometry_msgs/msg/'
                                          'PoseWithCovarianceStamped, nav_msgs/msg/Odometry, '
                                          'sensor_msgs/msg/NavSatFix'),
        DeclareLaunchArgument('datum', default_value=node['datum'],
                              description="'first_node' (held fixed) or 'fixes' (the map "
                                          "frame is the fixes')"),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
        Node(package='ga_ros', executable='alignment_node', name='alignment_node',
             output='screen',
             parameters=[os.path.join(config, 'alignment.yaml'),
                         {'use_sim_time': LaunchConfiguration('use_sim_time'),
                          'inputs': 'odom0',
                          'odom0.topic': _text('odom_topic'),
                          'odom0.type': _text('odom_type'),
                          'odom0.track.mode': _text('track_mode'),
                          'odom0.qos_reliability': 'auto',
                          'datum': _text('datum'),
                          'absolutes': ParameterValue(PythonExpression(
                              ["'fix0' if '", fix_topic, "' else ''"]), value_type=str),
                          'fix0.topic': ParameterValue(fix_topic, value_type=str),
                          'fix0.type': _text('fix_type')}]),
    ])
