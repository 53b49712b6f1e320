"""ga_ros: online, track-by-track global alignment of sensor trajectories.

The package root and everything outside :mod:`ga_ros.ros` is ROS-free: importing it never imports
rclpy (a test checks this).
"""

__version__ = '0.1.0'
