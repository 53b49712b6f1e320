"""The ROS-free estimator core: connection network, constraint models, mixed-adjustment solver."""
