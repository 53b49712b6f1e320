"""Tools that run the nodes as separate processes (multi-host demo); ROS-free modules."""
