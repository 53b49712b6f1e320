"""Thin ROS 2 adapters around the ROS-free core (the only place that imports rclpy).

All message <-> core conversions live in :mod:`ga_ros.ros.conversions`.
"""
