"""
The nodes' console scripts: each imports its node only when it runs.

A SIGINT while a node's modules are still loading (rclpy, numpy: a second on a
busy machine) would otherwise end in a traceback from the import machinery, in
another error a C extension made of it, or nowhere (a library swallowed it, and
the node spun on). Here it is only noted while they load, and the script then
ends quietly, as a SIGINT while the node spins does.
"""

from collections.abc import Callable

from bcid_ros.interrupts import (defer_sigints, handle_interrupts_in_finalizers,
                                 interrupt_on_sigints, interrupted, sigint_noted)


def _load_and_run(load: Callable[[], Callable[[], int]]) -> int:
    """
    Import a node's ``main`` with SIGINT deferred, then run it; 0 if interrupted.

    An error while loading, with a SIGINT noted, is taken as the interrupt; so is
    a KeyboardInterrupt with any error on top of it (rclpy's pybind11 module makes
    ``ImportError: initialization failed`` of one). Any other error goes on.
    """
    try:
        defer_sigints()
        main = load()
        if sigint_noted():
            return 0
        # raised again from here: run_node catches it, and, from rclpy.init on,
        # rclpy's handler shuts the context down first; a SIGINT noted but not raised
        # (it came just before this line) stops run_node right after rclpy.init
        interrupt_on_sigints()
        handle_interrupts_in_finalizers(deliver_again=False)
        return main()
    except BaseException as error:
        if interrupted(error) or sigint_noted():
            return 0
        raise


def _identifier_main() -> Callable[[], int]:
    from bcid_ros.nodes.identifier_node import main
    return main


def _identifier_lifecycle_main() -> Callable[[], int]:
    from bcid_ros.nodes.identifier_lifecycle_node import main
    return main


def _simulator_main() -> Callable[[], int]:
    from bcid_ros.nodes.simulator_node import main
    return main


def _adaptive_controller_main() -> Callable[[], int]:
    from bcid_ros.nodes.adaptive_controller_node import main
    return main


def identifier_node() -> int:
    """Run ``identifier_node``."""
    return _load_and_run(_identifier_main)


def identifier_lifecycle_node() -> int:
    """Run ``identifier_lifecycle_node``."""
    return _load_and_run(_identifier_lifecycle_main)


def simulator_node() -> int:
    """Run ``simulator_node``."""
    return _load_and_run(_simulator_main)


def adaptive_controller_node() -> int:
    """Run ``adaptive_controller_node``."""
    return _load_and_run(_adaptive_controller_main)
