"""
The nodes' console scripts: each imports its node only when it runs.

A SIGINT while a node's modules are still loading (rclpy, numpy: a second on a
busy machine) would otherwise end in a traceback from the import machinery; here
it ends quietly, as a SIGINT while the node spins does.
"""


def identifier_node() -> int:
    """Run ``identifier_node``."""
    try:
        from bcid_ros.nodes.identifier_node import main
    except KeyboardInterrupt:
        return 0
    return main()


def identifier_lifecycle_node() -> int:
    """Run ``identifier_lifecycle_node``."""
    try:
        from bcid_ros.nodes.identifier_lifecycle_node import main
    except KeyboardInterrupt:
        return 0
    return main()


def simulator_node() -> int:
    """Run ``simulator_node``."""
    try:
        from bcid_ros.nodes.simulator_node import main
    except KeyboardInterrupt:
        return 0
    return main()


def adaptive_controller_node() -> int:
    """Run ``adaptive_controller_node``."""
    try:
        from bcid_ros.nodes.adaptive_controller_node import main
    except KeyboardInterrupt:
        return 0
    return main()
