"""ROS-free stereo visual odometry and cross-track matching.

:mod:`.calibration` (rectification), :mod:`.motion` (triangulation, motion refinement and its
covariance), :mod:`.odometry` (:class:`StereoOdometry`), :mod:`.crosstrack` (keyframe store and
overlap connections), :mod:`.dense` (dense stereo points of a keyframe by semi-global matching),
:mod:`.evaluate` (benchmarks against the simulator's ground truth).
"""
