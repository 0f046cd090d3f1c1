"""A bare rclpy echo node: subscribe to samples, republish each message on echo."""

import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import Float64MultiArray

from bcid_ros.nodes.common import SAMPLES_QOS


def main() -> None:
    """Echo samples to echo until interrupted."""
    rclpy.init()
    node = rclpy.create_node('bcid_bench_echo')
    echo = node.create_publisher(Float64MultiArray, 'echo', SAMPLES_QOS)
    node.create_subscription(Float64MultiArray, 'samples', echo.publish, SAMPLES_QOS)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
