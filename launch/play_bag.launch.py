"""A recorded stereo bag played into vo_node and alignment_node in simulation time
(``ros2 launch ga_ros play_bag.launch.py bag:=/path/to/bag``): ``ga-ros play`` publishes the
bag's messages and ``/clock``; both nodes run with ``use_sim_time``."""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description():
    config = os.path.join(get_package_share_directory('ga_ros'), 'config')
    sim_time = {'use_sim_time': True}
    return LaunchDescription([
        DeclareLaunchArgument('bag'),
        DeclareLaunchArgument('rate', default_value='1.0'),
        Node(package='ga_ros', executable='vo_node', name='vo_node', output='screen',
             parameters=[os.path.join(config, 'vo.yaml'), sim_time]),
        Node(package='ga_ros', executable='alignment_node', name='alignment_node',
             output='screen', parameters=[os.path.join(config, 'alignment.yaml'), sim_time]),
        ExecuteProcess(cmd=['ga-ros', 'play', LaunchConfiguration('bag'),
                            '--rate', LaunchConfiguration('rate')], output='screen'),
    ])
