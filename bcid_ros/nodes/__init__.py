"""
The ROS 2 nodes: thin rclpy adapters over the identifier core, the estimators and the scenarios.

Every module here imports rclpy; what the nodes share with the offline
tools (names, layouts, the sample feeder, pairing, parameter tables, the
state file) is :mod:`bcid_ros.identifier`'s. ``identifier_node``
(:mod:`bcid_ros.nodes.identifier_node`), ``simulator_node``
(:mod:`bcid_ros.nodes.simulator_node`) and ``adaptive_controller_node``
(:mod:`bcid_ros.nodes.adaptive_controller_node`); ``bcid demo``
(:mod:`bcid_ros.nodes.demo`, :mod:`bcid_ros.nodes.demo_loop`) runs them.
See docs/nodes.md.
"""
