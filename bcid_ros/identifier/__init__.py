"""
The identifier's core without ROS: what the identifier node and ``bcid replay`` share.

The names of the nodes' interface (:mod:`~bcid_ros.identifier.interface`),
the message layouts (:mod:`~bcid_ros.identifier.layouts`), the sample feeder
(:mod:`~bcid_ros.identifier.feeder`) and its many-joint form
(:mod:`~bcid_ros.identifier.joint_feeder`, :mod:`~bcid_ros.identifier.joint_demux`),
the pairing of separate input and output topics
(:mod:`~bcid_ros.identifier.pairing`), the parameter tables
(:mod:`~bcid_ros.identifier.parameters`), the state file
(:mod:`~bcid_ros.identifier.persistence`) and the CDR codec
(:mod:`~bcid_ros.identifier.cdr`). Nothing here imports rclpy: the nodes
(:mod:`bcid_ros.nodes`) are thin rclpy adapters over it, and the offline
commands use it without a ROS graph. docs/architecture.md shows where it
stands among the layers.
"""
