"""
The identifier's ``state_file`` on rclpy (docs/nodes.md, "Keeping state: state_file").

:class:`StateKeeper` is what the node does with a state file: restore the
estimator and the feeder from it at start, publish the restored estimate at
once (latched), save every ``state_save_period`` seconds when the state has
changed, and save once more when the node goes. The file format, the
atomic write, the fingerprint check, the value checks, restoring all sections
or none, the lock and setting a refused file aside are
:mod:`bcid_ros.identifier.persistence`'s; here they are applied in order: lock
(or refuse to start), remove leftover temporary files, restore or set the
refused file aside (or, if it cannot be moved, never save over it).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import rclpy.logging
from rclpy.node import Node

from bcid_ros.estimators import RecursiveEstimator
from bcid_ros.identifier import persistence
from bcid_ros.identifier.feeder import SampleFeeder


class StateKeeper:
    """
    Restore an identifier's estimator and feeder from ``state_file``; save them there.

    The constructor restores (or logs why it starts fresh); :meth:`start`
    publishes a restored estimate and starts the save timer.

    Parameters
    ----------
    node : rclpy.node.Node
        The identifier node: its logger, its timer.
    settings : dict
        The identifier's checked parameters, ``state_file`` set.
    estimator : RecursiveEstimator
        The node's estimator, restored in place.
    feeder : SampleFeeder
        The node's feeder, restored in place.
    signature : callable
        Returns what changes whenever the state does (messages taken, samples
        since reset); a periodic save is skipped while it is unchanged.

    Raises
    ------
    ValueError
        If another process holds the state file (its lock), or the lock
        file cannot be created: the node refuses to start.

    Attributes
    ----------
    path : str
        The state file.
    restored : bool
        Whether the state was restored from ``path`` at start.
    timer : rclpy.timer.Timer
        The save timer, once :meth:`start` has run.

    """

    def __init__(self, node: Node, settings: dict[str, Any], estimator: RecursiveEstimator,
                 feeder: SampleFeeder, signature: Callable[[], Any]) -> None:
        self._node = node
        self._settings = settings
        self._estimator = estimator
        self._feeder = feeder
        self._signature = signature
        self.path = settings['state_file']
        self._fingerprint = persistence.configuration_fingerprint(settings)
        self._failing = False
        self._saved = None
        #: Why nothing may be saved (a refused file that could not be moved aside), or ''.
        self._blocked = ''
        self._lock: persistence.StateLock | None = None
        try:
            self._lock = persistence.StateLock(self.path)
        except persistence.StateInUse as error:
            raise ValueError(str(error)) from None
        except OSError:
            pass  # no directory or no permission: the saves fail too, and say so once
        for leftover in persistence.remove_leftovers(self.path):
            node.get_logger().info(f'removed {leftover}, left by an interrupted save')
        self.restored = self._restore()

    def _restore(self) -> bool:
        """Restore the estimator and feeder from the file if it fits; log one line."""
        logger = self._node.get_logger()
        try:
            sections = persistence.load_state(self.path, self._fingerprint)
            if sections is None:
                logger.info(f'state file {self.path} does not exist yet; starting fresh')
                return False
            persistence.restore_identifier(self._estimator, self._feeder, sections,
                                           self._settings['forgetting_factor'], self.path)
        except persistence.StateRefused as error:
            try:
                kept = persistence.set_aside(self.path)
            except OSError as move_error:
                self._blocked = (f'state file {self.path} was refused and cannot be moved '
                                 f'aside ({move_error}); it is not saved over')
                logger.error(f'{error}; {self._blocked}; starting fresh')
                return False
            logger.warning(f'{error}; kept as {kept}; starting fresh')
            return False
        logger.info(f'state restored from {self.path}: {self._feeder.used} samples used, '
                    f'{self._estimator.samples} since reset, valid {self._estimator.valid}')
        return True

    def start(self, publish_estimates: Callable[[np.ndarray, np.ndarray, np.ndarray], None]
              ) -> None:
        """Publish a restored estimate at once (latched); save every period from now on."""
        estimator = self._estimator
        if self.restored:
            self._saved = self._signature()  # the file holds it already
        if self.restored and estimator.ready:
            theta, uncompensated = estimator.theta, estimator.theta_uncompensated
            if np.isfinite(theta).all() and np.isfinite(uncompensated).all():
                publish_estimates(theta, uncompensated, estimator.noise)
        self.timer = self._node.create_timer(self._settings['state_save_period'],
                                             self._on_timer)

    def _on_timer(self) -> None:
        if self._signature() != self._saved:
            self.save()

    def save(self) -> bool:
        """
        Write the state file now (atomically); return whether it was written.

        A failure is logged once (and the recovery once); the node keeps
        running and tries again at the next period.
        """
        error = self._write()
        if error is None and self._failing:
            self._node.get_logger().info(f'state file {self.path} written again')
        elif error is not None and not self._failing:
            self._node.get_logger().error(error)
        self._failing = error is not None
        return error is None

    def _write(self) -> str | None:
        """Write the state file; return None, or the line that says why it failed."""
        if self._blocked:
            return self._blocked
        signature = self._signature()
        sections = persistence.identifier_sections(self._estimator, self._feeder)
        try:
            persistence.save_state(self.path, self._fingerprint, sections)
        except (OSError, TypeError, ValueError) as error:
            return (f'cannot write state file {self.path}: {error}; the node keeps '
                    f'running and tries again every {self._settings["state_save_period"]:g} s')
        self._saved = signature
        return None

    def release(self) -> None:
        """Release the state file's lock (a managed node's cleanup), so another may take it."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def save_and_destroy(self, destroy: Callable[[], None]) -> None:
        """Save the state, run ``destroy`` (the node's own destroy_node), then log the save."""
        error = self._write()
        self.release()
        # logged after the node is gone, to the console and the log file only: a /rosout
        # publisher, whose context a signal has already shut down, would refuse the line
        # with an error of rcl's. The node's own logger is not used: its publisher outlived
        # destroy() once in a test run (likely a destruction deferred while a handle was in
        # use; not reproduced), and a logger of another name has no publisher at all
        logger = rclpy.logging.get_logger(f'{self._node.get_logger().name}.state_file')
        destroy()
        if error is None:
            logger.info(f'state saved to {self.path} at shutdown '
                        f'({self._feeder.used} samples used)')
        elif not self._failing:
            logger.error(error)


__all__ = ['StateKeeper']
