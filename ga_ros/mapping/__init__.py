"""Maps built from corrected poses (ROS-free): the photomosaic of a downward camera
(:mod:`ga_ros.mapping.mosaic`), its ground surface (:mod:`ga_ros.mapping.surface`), its seam
misregistration (:mod:`ga_ros.mapping.seams`) and the replay's mosaic step
(:mod:`ga_ros.mapping.replay_mosaic`)."""
