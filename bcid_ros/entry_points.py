"""
The console scripts: the nodes' and ``bcid``; each imports its modules only when it runs.

A SIGINT while a node's modules are still loading (rclpy, numpy: a second on a
busy machine) would otherwise end in a traceback from the import machinery, in
another error a C extension made of it, or nowhere (a library swallowed it, and
the node spun on). Here it is only noted while they load, and the script then
ends quietly, as a SIGINT while the node spins does (``bcid``: exit code 130, as
a SIGINT while a command runs).
"""

from collections.abc import Callable
import importlib

from bcid_ros.interrupts import (defer_sigints, handle_interrupts_in_finalizers,
                                 interrupt_on_sigints, interrupted, sigint_noted)


def _load_and_run(load: Callable[[], Callable[[], int]], interrupted_code: int = 0) -> int:
    """
    Import a ``main`` with SIGINT deferred, then run it; ``interrupted_code`` if interrupted.

    Any error with a SIGINT noted since the start is taken as the interrupt; so is
    a KeyboardInterrupt with any error on top of it (rclpy's pybind11 module made
    ``ImportError: initialization failed`` of one raised inside its import). Any
    other error goes on.
    """
    try:
        defer_sigints()
        main = load()
        # the interrupt noted while loading, if any, raised here; from here a SIGINT
        # raises it: run_node catches it, and from rclpy.init on rclpy's handler shuts the
        # context down first (and run_node looks for one noted but swallowed meanwhile)
        interrupt_on_sigints()
        handle_interrupts_in_finalizers(deliver_again=False)
        return main()
    except BaseException as error:
        if interrupted(error) or sigint_noted():
            return interrupted_code
        raise


def _main_of(module: str) -> Callable[[], Callable[[], int]]:
    """Return what imports ``module`` and gives its ``main`` (as ``cli`` its commands)."""
    return lambda: importlib.import_module(module).main


def identifier_node() -> int:
    """Run ``identifier_node``."""
    return _load_and_run(_main_of('bcid_ros.nodes.identifier_node'))


def identifier_lifecycle_node() -> int:
    """Run ``identifier_lifecycle_node``."""
    return _load_and_run(_main_of('bcid_ros.nodes.identifier_lifecycle_node'))


def simulator_node() -> int:
    """Run ``simulator_node``."""
    return _load_and_run(_main_of('bcid_ros.nodes.simulator_node'))


def adaptive_controller_node() -> int:
    """Run ``adaptive_controller_node``."""
    return _load_and_run(_main_of('bcid_ros.nodes.adaptive_controller_node'))


def bcid() -> int:
    """Run ``bcid`` (130 if interrupted, as a command is)."""
    return _load_and_run(_main_of('bcid_ros.cli'), interrupted_code=130)
