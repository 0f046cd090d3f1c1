"""bcid_ros: online, bias-compensated system identification for ROS 2."""

__version__ = '0.1.0'
