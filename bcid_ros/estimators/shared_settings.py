"""
The settings a single-plant estimator and a batched one check and expose alike.

:class:`SharedSettings` is a mixin of :class:`~bcid_ros.estimators.base.RecursiveEstimator`
and of the batched forms: the model structure, p0, and the settings that may change while
running (the forgetting factor, which it hands to every part whose memory is the
estimator's, the gate's threshold, and those that follow a changing plant). Each range is
the parameter spec's of :mod:`bcid_ros.estimators.settings`.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.settings import SHARED_SETTINGS, TRACKING
from bcid_ros.estimators.simulation_check import SimulationWindow


def check_forgetting_factor(value: Any) -> float:
    """Return the forgetting factor lambda as a float in (0, 1], or raise ValueError."""
    return SHARED_SETTINGS['forgetting_factor'].check_argument(value)


class SharedSettings:
    """
    The settings a single-plant estimator and a batched one check and expose alike.

    The model structure (order, inputs, feedthrough), p0, and the two
    settings that may change while running: the forgetting factor and the
    gate's threshold (whose squared limit the rulebook's gate takes); and
    those that follow a changing plant (``change_detection``, ``adaptation``,
    ``parameter_drift``).
    """

    #: Whether it follows a changing plant: the change detector runs (``change_detection``)
    #: and ``adaptation: kalman`` is available (docs/tracking.md).
    tracks: ClassVar[bool] = False

    def _check_settings(self, order: int, num_inputs: int, feedthrough: bool,
                        initial_covariance: float, forgetting_factor: float,
                        outlier_threshold: float) -> None:
        """Check and keep the shared settings; raise ValueError naming a bad one."""
        self.order = SHARED_SETTINGS['order'].check_argument(order)
        self.num_inputs = SHARED_SETTINGS['num_inputs'].check_argument(num_inputs)
        self.feedthrough = bool(feedthrough)
        self.initial_covariance = SHARED_SETTINGS['initial_covariance'].check_argument(
            initial_covariance)
        # not through the property, which subclasses may extend with checks of their state
        self._forgetting_factor = check_forgetting_factor(forgetting_factor)
        self.outlier_threshold = outlier_threshold

    @property
    def forgetting_factor(self) -> float:
        """Forgetting factor lambda in (0, 1]; may be changed while running."""
        return self._forgetting_factor

    @forgetting_factor.setter
    def forgetting_factor(self, value: float) -> None:
        self._forgetting_factor = check_forgetting_factor(value)
        self._follow_forgetting_factor()
        self._pass_on('forgetting_factor', self._forgetting_factor)

    def _pass_on(self, name: str, value: Any) -> None:
        """Give a setting changed while running to parts that keep their own (none here)."""

    def _follow_forgetting_factor(self) -> None:
        """
        Give every part whose memory is the estimator's the forgetting factor now in force.

        P's recursion reads it at every step; the residual tests' window
        (:meth:`~bcid_ros.estimators.adequacy.AdequacyMonitor.follow_forgetting_factor`)
        and the HAC covariance's weights (``_hac``) are told here, so that a
        live change reaches them as it reaches P, not at the next reset.
        """
        monitor, hac = getattr(self, '_monitor', None), getattr(self, '_hac', None)
        if monitor is not None:
            monitor.follow_forgetting_factor(self._forgetting_factor)
        if hac is not None:
            hac.forgetting_factor = self._forgetting_factor
        for window in self._simulation_windows():
            window.follow_forgetting_factor(self._forgetting_factor)

    def _simulation_windows(self) -> list[SimulationWindow]:
        """Return the simulation check's windows (one per plant; none kept: [])."""
        windows = getattr(self, '_simulations', None)
        if windows is not None:
            return windows
        window = getattr(self, '_simulation', None)
        return [] if window is None else [window]

    def _check_tracking(self, change_detection: bool, adaptation: str,
                        parameter_drift: float) -> None:
        """Check and keep the settings that follow a changing plant (docs/tracking.md)."""
        if adaptation not in TRACKING['adaptation'].choices:
            raise ValueError(f"adaptation must be 'forgetting' or 'kalman', got {adaptation!r}")
        if not self.tracks and (adaptation != 'forgetting' or parameter_drift):
            raise ValueError(f'adaptation: kalman and parameter_drift are not available for '
                             f'{type(self).__name__}, got {adaptation!r}, {parameter_drift!r}')
        if adaptation == 'kalman' and self._forgetting_factor < 1.0:
            raise ValueError(f'adaptation: kalman takes the place of forgetting: '
                             f'forgetting_factor must be 1, got {self._forgetting_factor!r}')
        self.adaptation = adaptation
        self.change_detection = change_detection
        self.parameter_drift = parameter_drift

    @property
    def change_detection(self) -> bool:
        """Whether the CUSUM test of plant changes runs (docs/tracking.md); may change live."""
        return self._change_detection

    @change_detection.setter
    def change_detection(self, value: bool) -> None:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f'change_detection must be true or false, got {value!r}')
        self._change_detection = bool(value)
        self._pass_on('change_detection', self._change_detection)

    @property
    def parameter_drift(self) -> float:
        """
        Return q, the random walk's step variance (``adaptation: kalman``; 0 otherwise).

        Per sample, each parameter of the model of unit-size signals takes a
        random step of variance q times the noise variance: P <- P + q S^-2 (S
        the signal scales of the parameters; docs/tracking.md).
        """
        return self._parameter_drift

    @parameter_drift.setter
    def parameter_drift(self, value: float) -> None:
        value = TRACKING['parameter_drift'].check_argument(value)
        if value and self.adaptation != 'kalman':
            raise ValueError(f'parameter_drift needs adaptation: kalman, got {value!r} with '
                             f'adaptation: {self.adaptation}')
        self._parameter_drift = value
        propagation = getattr(self, '_propagation', None)
        if propagation is not None and hasattr(propagation, 'drift'):
            propagation.drift = value  # the random walk's Q follows a live change
        self._pass_on('parameter_drift', value)

    @property
    def outlier_threshold(self) -> float:
        """Gate of the normalised prediction error, >= 0 (0 = off); may change while running."""
        return self._outlier_threshold

    @outlier_threshold.setter
    def outlier_threshold(self, value: float) -> None:
        self._outlier_threshold = SHARED_SETTINGS['outlier_threshold'].check_argument(value)
        self._gate_limit2 = rules.gate_limit2(self._outlier_threshold)
        self._pass_on('outlier_threshold', self._outlier_threshold)


__all__ = ['SharedSettings', 'check_forgetting_factor']
