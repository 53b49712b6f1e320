"""File formats: g2o, TUM, KITTI, rosbag2 (mcap / sqlite3)."""
