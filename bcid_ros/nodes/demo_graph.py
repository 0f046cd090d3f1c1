"""
What both demos share: the child node processes and the demo's own node (rclpy).

``bcid demo`` (:mod:`bcid_ros.nodes.demo`) and ``bcid demo --scenario
adaptive_loop`` (:mod:`bcid_ros.nodes.demo_loop`) start the nodes as a user
would, as child processes with the scenario's config file, and watch them
from a node of their own: :func:`demo_graph` yields that node, its executor
and the list of children, and stops them all on every way out.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
import shutil
import signal
import subprocess
import sys
from typing import Any, Callable, Iterator

#: Per scenario: (samples, rate in Hz, frame size) that converge in well under a minute.
DEMO_DEFAULTS = {
    'ding_miso': (4000, 1000.0, 1),
    'ding_miso_nonstationary': (4000, 1000.0, 1),
    'ikenoue_colored': (10000, 2000.0, 20),
    'ikenoue_white_input': (10000, 2000.0, 20),
    'ikeda_closed_loop': (8192, 2000.0, 8),
    'adaptive_loop': (12000, 500.0, 1),
    'payload_change': (8000, 1000.0, 1),
}
#: Seconds to wait for a node to exit after SIGINT before it is killed.
STOP_TIMEOUT = 5.0
#: Seconds the simulator may take before its first sample (discovery included).
START_TIMEOUT = 30.0


def executable(name: str) -> list[str]:
    """Return the command that runs the console script ``name`` of this installation."""
    beside = Path(sys.executable).with_name(name)
    if beside.is_file():
        return [str(beside)]
    found = shutil.which(name)
    if found:
        return [found]
    module = {'identifier_node': 'bcid_ros.nodes.identifier_node',
              'simulator_node': 'bcid_ros.nodes.simulator_node',
              'adaptive_controller_node': 'bcid_ros.nodes.adaptive_controller_node'}[name]
    return [sys.executable, '-m', module]


class AfterDiscovery:
    """
    A subscription created once this node has discovered a publisher on another topic.

    Each demo's simulator starts once its samples have two subscribers, the identifier and
    the demo's monitor. The monitor takes the samples only once it knows the identifier's
    ``~/valid`` publisher: else the simulator can start while the monitor has not yet
    discovered the identifier, whose latched topics then reach it with their last value
    only (a CI run of the payload-change demo: the identifier discovered 1-2 s late,
    after the plant change, and ``~/valid``'s turn to false at the change never seen).
    """

    def __init__(self, node: Any, topic: str, create: Callable[[], Any]) -> None:
        self._node, self._topic, self._create = node, topic, create
        #: The subscription, None until the publisher is discovered
        self.subscription: Any = None

    def poll(self) -> bool:
        """Create the subscription if the publisher is now known; return whether it exists."""
        if self.subscription is None and self._node.count_publishers(self._topic) > 0:
            self.subscription = self._create()
        return self.subscription is not None

    def note(self) -> str:
        """Return why nothing came yet if the publisher is still unknown, else ''."""
        if self.subscription is not None:
            return ''
        return f' (no publisher of {self._topic} discovered: the demo waits to subscribe)'


class Child:
    """A node process whose output goes to a log file; stopped with SIGINT, then SIGKILL."""

    def __init__(self, name: str, command: list[str], log: Path) -> None:
        self.name = name
        self.log = log
        self._file = open(log, 'w')
        self.process = subprocess.Popen(command, stdout=self._file, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL)

    def poll(self) -> int | None:
        """Return the exit code, or None while running."""
        return self.process.poll()

    def tail(self, lines: int = 15) -> str:
        """Return the last lines of the log."""
        self._file.flush()
        try:
            text = self.log.read_text(errors='replace').splitlines()
        except OSError:
            return ''
        return '\n'.join(text[-lines:])

    def stop(self) -> int | None:
        """Stop the process (SIGINT, then SIGKILL) and return its exit code."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._file.close()
        return self.process.returncode


@contextlib.contextmanager
def demo_graph() -> Iterator[tuple[Any, Any, list[Child]]]:
    """
    Yield the demo's own node, its executor and the list of its child processes.

    The children a demo appends are stopped on the way out, SIGTERM is an
    interrupt meanwhile (as Ctrl-C), and the node and its context go down.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bcid_demo', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    children: list[Child] = []
    previous_handler = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield node, executor, children
    finally:
        for child in reversed(children):
            child.stop()
        signal.signal(signal.SIGTERM, previous_handler)
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


__all__ = ['AfterDiscovery', 'Child', 'DEMO_DEFAULTS', 'START_TIMEOUT', 'STOP_TIMEOUT',
           'demo_graph', 'executable']
