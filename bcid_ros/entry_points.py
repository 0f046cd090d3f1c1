"""
The nodes' console scripts: each imports its node only when it runs.

A SIGINT while a node's modules are still loading (rclpy, numpy: a second on a
busy machine) would otherwise end in a traceback from the import machinery; here
it ends quietly, as a SIGINT while the node spins does.
"""

from types import TracebackType

from bcid_ros.interrupts import handle_interrupts_in_finalizers, interrupted


class _Loading:
    """
    A ``with`` block around a node's import that ends quietly on a SIGINT.

    :attr:`done` says whether the import finished. A SIGINT inside a C
    extension's initialisation (rclpy's pybind11 module) comes out as
    ``ImportError: initialization failed`` with the interrupt as its cause:
    that is taken as the interrupt too; any other error goes on.
    """

    done = False

    def __enter__(self) -> '_Loading':
        handle_interrupts_in_finalizers(deliver_again=True)   # no rclpy handler yet
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> bool:
        self.done = error is None
        return interrupted(error)


def identifier_node() -> int:
    """Run ``identifier_node``."""
    with _Loading() as loading:
        from bcid_ros.nodes.identifier_node import main
    return main() if loading.done else 0


def identifier_lifecycle_node() -> int:
    """Run ``identifier_lifecycle_node``."""
    with _Loading() as loading:
        from bcid_ros.nodes.identifier_lifecycle_node import main
    return main() if loading.done else 0


def simulator_node() -> int:
    """Run ``simulator_node``."""
    with _Loading() as loading:
        from bcid_ros.nodes.simulator_node import main
    return main() if loading.done else 0


def adaptive_controller_node() -> int:
    """Run ``adaptive_controller_node``."""
    with _Loading() as loading:
        from bcid_ros.nodes.adaptive_controller_node import main
    return main() if loading.done else 0
