"""Reading bags without ROS: rosbag2 (mcap or sqlite3), an mcap file cut short, ROS 1 ``.bag``.

Everything here uses :mod:`rosbags` (pure Python CDR and storage plugins) and never imports
``rclpy``. Messages come out as rosbags message objects (dataclasses with the ROS field names),
converted to core types once, at the edge (:mod:`ga_ros.io.bag_messages`). Which topics the
replay reads: :mod:`ga_ros.io.topic_plan`; writing bags: :mod:`ga_ros.io.bag_writer`.

Modules: :mod:`~ga_ros.io.bag.reader` (:class:`BagReader`, :func:`bag_info`),
:mod:`~ga_ros.io.bag.summary` (:class:`BagInfo`, :class:`BagTopic`, :class:`BagMessage`),
:mod:`~ga_ros.io.bag.mcap_recovery` (an mcap file cut short), :mod:`~ga_ros.io.bag.rosbag1`.
"""

from ga_ros.io.bag.reader import BagReader, bag_info
from ga_ros.io.bag.summary import BagInfo, BagMessage, BagTopic

__all__ = ['BagInfo', 'BagMessage', 'BagReader', 'BagTopic', 'bag_info']
