"""A recorded stereo bag played into vo_node and alignment_node in simulation time.

    ros2 launch ga_ros play_bag.launch.py bag:=/path/to/stereo.mcap
    ros2 launch ga_ros play_bag.launch.py bag:=src/ga_ros/bags/stereo_sample compressed:=true \\
        left_image:=/stereo/left/image_raw/compressed \\
        right_image:=/stereo/right/image_raw/compressed \\
        left_info:=/stereo/left/camera_info right_info:=/stereo/right/camera_info

``ga-ros play`` (the installed package's executable, ``lib/ga_ros/ga-ros``) publishes the bag's
messages and ``/clock``; the nodes run with ``use_sim_time``. ``map:=true`` also starts
``map_node`` (``config/map.yaml``): the keyframe clouds at their corrected poses on ``ga/map``
and the keyframe images' mosaic on ``ga/mosaic``.
The camera's extrinsic comes from the bag's ``/tf_static``. The topic and ``compressed``
defaults are those of ``config/vo.yaml`` (read from the installed file).
"""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import ExecutableInPackage

from launch import LaunchDescription


def generate_launch_description():
    config = os.path.join(get_package_share_directory('ga_ros'), 'config')
    with open(os.path.join(config, 'vo.yaml')) as f:
        vo = yaml.safe_load(f)['vo_node']['ros__parameters']
    sim_time = {'use_sim_time': True}
    topics = ('left_image', 'right_image', 'left_info', 'right_info')
    return LaunchDescription([
        DeclareLaunchArgument('bag', description='rosbag2 directory, or a .mcap / .db3 file'),
        DeclareLaunchArgument('rate', default_value='1.0',
                              description='speed factor (1 = real time)'),
        *[DeclareLaunchArgument(t, default_value=vo[f'{t}_topic'], description=f'{t} topic')
          for t in topics],
        DeclareLaunchArgument('compressed', default_value=str(vo['compressed']).lower(),
                              description='images are sensor_msgs/CompressedImage'),
        DeclareLaunchArgument('map', default_value='false',
                              description='also start map_node (the point-cloud map ga/map)'),
        Node(package='ga_ros', executable='vo_node', name='vo_node', output='screen',
             parameters=[os.path.join(config, 'vo.yaml'), sim_time,
                         {'compressed': ParameterValue(LaunchConfiguration('compressed'),
                                                       value_type=bool)},
                         {f'{t}_topic': ParameterValue(LaunchConfiguration(t), value_type=str)
                          for t in topics}]),
        Node(package='ga_ros', executable='alignment_node', name='alignment_node',
             output='screen', parameters=[os.path.join(config, 'alignment.yaml'), sim_time]),
        Node(package='ga_ros', executable='map_node', name='map_node', output='screen',
             condition=IfCondition(LaunchConfiguration('map')),
             parameters=[os.path.join(config, 'map.yaml'), sim_time]),
        ExecuteProcess(cmd=[ExecutableInPackage('ga-ros', 'ga_ros'), 'play',
                            LaunchConfiguration('bag'), '--rate', LaunchConfiguration('rate')],
                       name='play', output='screen'),
    ])
