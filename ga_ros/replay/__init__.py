"""Offline replay of rosbag2 bags: bag -> [stereo VO] -> track-window alignment -> outputs.

ROS-free (rosbags for the bag files): :func:`ga_ros.replay.pipeline.replay` is what
``ga-ros replay`` and ``ga-ros demo`` run.
"""
