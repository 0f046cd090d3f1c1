"""
The identification node in its managed (lifecycle) form (docs/nodes.md, "Managed node").

The same identifier as ``identifier_node`` (:class:`~bcid_ros.nodes.identifier_node.Identifier`),
run by the transitions of a ROS 2 managed node instead of at construction:

- configure: check the parameters, build the estimator, load the state file;
- activate: make the topics (at the first activation), subscribe, publish;
- deactivate: stop taking samples (the subscriptions go); the state is kept;
- cleanup: save the state file, drop the topics and the estimator;
- shutdown (from any state): save the state file.

A refused parameter fails the transition (the node stays unconfigured) with
one error line. Drive it with ``ros2 lifecycle set /bcid_identifier configure``
or the ``~/change_state`` service.

Run it as ``identifier_lifecycle_node --ros-args --params-file config/ding_miso.yaml``.
"""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from bcid_ros.identifier import interface
from bcid_ros.identifier.parameters import IDENTIFIER_PARAMETERS
from bcid_ros.nodes.common import run_node, usage
from bcid_ros.nodes.identifier_node import Identifier

#: The entity kinds a node owns, each with the method that destroys one.
_ENTITIES = (('publishers', 'destroy_publisher'), ('subscriptions', 'destroy_subscription'),
             ('timers', 'destroy_timer'), ('services', 'destroy_service'),
             ('clients', 'destroy_client'))


class IdentifierLifecycleNode(Identifier, LifecycleNode):
    """
    The identifier as a managed node: configure, activate, deactivate, cleanup, shutdown.

    Parameters
    ----------
    node_name : str
        Default ``bcid_identifier``.
    **kwargs
        Passed to :class:`rclpy.lifecycle.LifecycleNode`.

    """

    def __init__(self, node_name: str = interface.IDENTIFIER_NODE, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_identifier()
        self._unconfigured: dict[str, set[int]] = {}

    def _entities(self) -> dict[str, set[int]]:
        return {kind: {id(entity) for entity in getattr(self, kind)} for kind, _ in _ENTITIES}

    def _destroy_entities_since(self, before: dict[str, set[int]]) -> None:
        """Destroy what was made since ``before`` (the node's own services stay)."""
        for kind, destroy in _ENTITIES:
            for entity in [e for e in getattr(self, kind) if id(e) not in before[kind]]:
                getattr(self, destroy)(entity)

    def _forget(self) -> None:
        """Drop the estimator and everything built on it (back to unconfigured)."""
        if getattr(self, 'state_keeper', None) is not None:
            self.state_keeper.release()  # a configure after cleanup takes the file again
        self.estimator = self.state_keeper = self.joint_state = None
        self.estimates = None

    def _save(self, transition: str) -> None:
        if self.state_keeper is not None and self.state_keeper.save():
            self.get_logger().info(f'state saved to {self.state_keeper.path} at {transition} '
                                   f'({self.feeder.used} samples used)')

    # ------------------------------------------------------------ transitions
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Check the parameters, build the estimator and load the state file."""
        self._unconfigured = self._entities()
        try:
            self.configure_identifier()
        except ValueError as error:
            self.get_logger().error(f'configure refused: {error}')
            self._destroy_entities_since(self._unconfigured)
            self._forget()
            return TransitionCallbackReturn.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Make the topics at the first activation; subscribe and publish."""
        try:
            self.activate_identifier()
        except ValueError as error:  # controller_topic, checked when it is subscribed
            self.get_logger().error(f'activate refused: {error}')
            return TransitionCallbackReturn.FAILURE
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop taking samples; keep the state and the latched estimates."""
        self.deactivate_identifier()
        self.get_logger().info('deactivated: samples are not taken; the state is kept')
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Save the state file; drop the topics and the estimator."""
        self._save('cleanup')
        self._destroy_entities_since(self._unconfigured)
        self._forget()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Save the state file (from any state)."""
        self._save('shutdown')
        return super().on_shutdown(state)


def main(argv: list[str] | None = None) -> int:
    """Run ``identifier_lifecycle_node`` (unconfigured at start) until SIGINT or SIGTERM."""
    return run_node(IdentifierLifecycleNode, argv, 'identifier_lifecycle_node',
                    help_text=usage('identifier_lifecycle_node', __doc__.strip().splitlines()[0],
                                    IDENTIFIER_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
