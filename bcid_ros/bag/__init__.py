"""
rosbag2 MCAP bags: read, write, replay, record and play.

The offline half (:mod:`~bcid_ros.bag.reader`, :mod:`~bcid_ros.bag.writer`,
:mod:`~bcid_ros.bag.replay`, :mod:`~bcid_ros.bag.simulate`,
:mod:`~bcid_ros.bag.info`) needs only ``mcap``, ``mcap_ros2`` and ``rosbags``;
:mod:`~bcid_ros.bag.record` and :mod:`~bcid_ros.bag.play` use rclpy.
Nothing is imported here, so that importing one half never loads the other.
"""
