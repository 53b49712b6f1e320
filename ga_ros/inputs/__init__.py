"""Standard inputs (ROS-free): odometry and pose streams, external constraints -> Measurements.

Fed by plain calls with numpy types (the ROS node and the bag replay convert messages at the
edge), so live and offline share one driver. See :mod:`ga_ros.inputs.odometry`.
"""
