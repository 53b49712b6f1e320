"""Maps built from the corrected poses (ROS-free): keyframe point-cloud maps that follow the
alignment's corrections (:mod:`ga_ros.mapping.cloud_map`), their voxel accumulator
(:mod:`ga_ros.mapping.voxels`), PLY files (:mod:`ga_ros.mapping.ply`), figures of a map
(:mod:`ga_ros.mapping.figures`); the photomosaic of a downward camera
(:mod:`ga_ros.mapping.mosaic`), its ground surface (:mod:`ga_ros.mapping.surface`), its seam
misregistration (:mod:`ga_ros.mapping.seams`) and the replay's mosaic step
(:mod:`ga_ros.mapping.replay_mosaic`)."""
