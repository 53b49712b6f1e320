"""ROS-free pipeline: what the nodes and the replay both drive."""
