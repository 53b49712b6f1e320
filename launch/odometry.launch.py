"""Odometry (and absolute fixes) into alignment_node (``ros2 launch ga_ros odometry.launch.py
odom_topic:=/odom``): the first standard input ``odom0`` is the REP 105 ``odom`` frame; the node
publishes ``map -> odom``. Per-input settings: ``odom0.<setting>`` (config/inputs.yaml lists
them); absolute fixes are inputs too (``absolute0.topic`` etc., README "Absolute fixes")."""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description():
    config = os.path.join(get_package_share_directory('ga_ros'), 'config')
    return LaunchDescription([
        DeclareLaunchArgument('odom_topic', default_value='/odom'),
        DeclareLaunchArgument('odom_type', default_value='nav_msgs/msg/Odometry'),
        DeclareLaunchArgument('track_mode', default_value='heading'),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
        Node(package='ga_ros', executable='alignment_node', name='alignment_node',
             output='screen',
             parameters=[os.path.join(config, 'alignment.yaml'),
                         {'use_sim_time': LaunchConfiguration('use_sim_time'),
                          'inputs': 'odom0',
                          'odom0.topic': LaunchConfiguration('odom_topic'),
                          'odom0.type': LaunchConfiguration('odom_type'),
                          'odom0.track.mode': LaunchConfiguration('track_mode'),
                          'odom0.qos_reliability': 'auto'}]),
    ])
