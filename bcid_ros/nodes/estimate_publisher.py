"""
The identifier's latched estimate topics (docs/nodes.md, "identifier_node").

:class:`EstimatePublisher` turns one estimator's results into messages:
``~/parameters``, ``~/parameters_uncompensated``, ``~/noise_variance``,
``~/parameter_std`` and ``~/parameter_covariance`` (when the estimator has
them and someone subscribes to them), ``~/operating_point`` (with
``detrend: mean``), ``~/parameters_stamped`` (the estimate with the stamp of
the last sample used) and ``~/valid`` (when it changes; false while the
estimate is stale, see ``stale_after``).
"""

from __future__ import annotations

from typing import Any, Callable

from builtin_interfaces.msg import Time
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray

from bcid_ros.estimators import RecursiveEstimator
from bcid_ros.estimators.base import standard_deviations
from bcid_ros.identifier import interface
from bcid_ros.nodes.common import LATCHED_QOS
from bcid_ros.nodes.messages import (as_doubles, covariance_message, estimate_message,
                                     SerializedArray, valid_message)


class EstimatePublisher:
    """
    Publish one estimator's estimates and validity on the identifier's latched topics.

    Parameters
    ----------
    node : rclpy.node.Node
        The identifier node that owns the publishers.
    estimator : RecursiveEstimator
        The estimator whose uncertainty, operating point and validity are read.
    detrend : str
        The ``detrend`` parameter: ``'mean'`` adds ``~/operating_point``.
    stale : callable, optional
        Returns why the estimate is stale (``''`` while it is not): ``~/valid``
        is false while it says something.

    Attributes
    ----------
    published : int
        Estimates published (one per call of :meth:`publish`).

    """

    def __init__(self, node: Node, estimator: RecursiveEstimator, detrend: str,
                 stale: Callable[[], str] = str) -> None:
        self._estimator = estimator
        self._stale = stale
        names = estimator.parameter_names
        self._topics = {  # publisher and serialised layout of each estimate topic
            topic: (node.create_publisher(Float64MultiArray, topic, LATCHED_QOS),
                    SerializedArray(message))
            for topic, message in (
                (interface.PARAMETERS, estimate_message(names)),
                (interface.PARAMETERS_UNCOMPENSATED, estimate_message(names)),
                (interface.NOISE_VARIANCE, estimate_message(tuple(estimator.noise_names))),
                (interface.PARAMETER_STD, estimate_message(names)),
                (interface.PARAMETER_COVARIANCE, covariance_message(names)))}
        if detrend == 'mean':
            self._topics[interface.OPERATING_POINT] = (
                node.create_publisher(Float64MultiArray, interface.OPERATING_POINT,
                                      LATCHED_QOS),
                SerializedArray(estimate_message(estimator.operating_point_names)))
        self.stamped_publisher = node.create_publisher(JointState, interface.PARAMETERS_STAMPED,
                                                       LATCHED_QOS)
        self._stamped = JointState(name=list(names))
        self.published = 0
        self.valid_publisher = node.create_publisher(Bool, interface.VALID, LATCHED_QOS)
        self._valid = self.valid
        self.valid_publisher.publish(valid_message(self._valid))

    @property
    def valid(self) -> bool:
        """Return whether the estimate is trustworthy: the estimator's validity, and not stale."""
        return bool(self._estimator.valid) and not self._stale()

    def publish(self, theta: np.ndarray, uncompensated: np.ndarray, noise: np.ndarray,
                stamp: Time | None = None) -> None:
        """
        Publish the estimates (the caller has checked that they are due and finite).

        ``stamp`` is the stamp of the last sample used; None (an estimate
        restored from the state file, whose samples' times are not kept)
        publishes time zero on ``~/parameters_stamped``.
        """
        self._publish(interface.PARAMETERS, theta)
        stamped = self._stamped
        stamped.header.stamp = stamp if stamp is not None else Time()
        stamped.position = as_doubles(theta)
        self.stamped_publisher.publish(stamped)
        self._publish(interface.PARAMETERS_UNCOMPENSATED, uncompensated)
        if noise.size and np.isfinite(noise).all():
            self._publish(interface.NOISE_VARIANCE, noise)
        self._publish_uncertainty()
        operating_point = self._estimator.operating_point
        if operating_point is not None:
            self._publish(interface.OPERATING_POINT, operating_point)
        self.published += 1

    def _publish_uncertainty(self) -> None:
        """
        Publish the std and covariance to whichever of the two has subscribers.

        Computing them (bcrls's sandwich, bciv's delta method) costs more than
        the rest of a frame's publishing, so it is done only when read; a
        subscriber that joins gets the next estimate's.
        """
        std, covariance = (self._topics[interface.PARAMETER_STD][0],
                           self._topics[interface.PARAMETER_COVARIANCE][0])
        wanted_std, wanted_covariance = (std.get_subscription_count() > 0,
                                         covariance.get_subscription_count() > 0)
        if not (wanted_std or wanted_covariance):
            return
        values = self._estimator.parameter_covariance
        if values is None:  # the estimator has none (yet)
            return
        if wanted_std:
            self._publish(interface.PARAMETER_STD, standard_deviations(values))
        if wanted_covariance:
            self._publish(interface.PARAMETER_COVARIANCE, values)

    def _publish(self, topic: str, values: Any) -> None:
        publisher, serialized = self._topics[topic]
        publisher.publish(serialized.serialize(values))

    def update_valid(self) -> None:
        """Publish ``~/valid`` if the estimator's validity changed since the last one."""
        valid = self.valid
        if valid != self._valid:
            self._valid = valid
            self.valid_publisher.publish(valid_message(valid))


__all__ = ['EstimatePublisher']
