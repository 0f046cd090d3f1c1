"""
The ROS 2 nodes: thin rclpy adapters over the estimators and the scenarios.

``identifier_node`` (:mod:`bcid_ros.nodes.identifier_node`) and
``simulator_node`` (:mod:`bcid_ros.nodes.simulator_node`); ``bcid demo``
(:mod:`bcid_ros.nodes.demo`) runs both. See docs/nodes.md.
"""
