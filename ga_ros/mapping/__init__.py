"""Maps built from the corrected poses (ROS-free): keyframe point-cloud maps that follow the
alignment's corrections (:mod:`ga_ros.mapping.cloud_map`), their voxel accumulator
(:mod:`ga_ros.mapping.voxels`), PLY files (:mod:`ga_ros.mapping.ply`) and figures of a map
(:mod:`ga_ros.mapping.figures`)."""
