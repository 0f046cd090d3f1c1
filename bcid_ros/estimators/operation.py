"""
The operating point (``detrend: mean``) and the held adaptation of one estimator.

:class:`Operation` is a mixin of :class:`~bcid_ros.estimators.base.RecursiveEstimator`:
the link of its update chain between the way in and the learning step
(``_operate``), with the settings and monitors it reads: ``detrend``, ``adapt``,
the feeder's ``excitation_hold`` and the centring monitor (docs/estimators.md).
"""

from __future__ import annotations

import numpy as np

from bcid_ros.estimators.operating_point import (CentringMonitor, operating_point_names,
                                                 RunningMean)
from bcid_ros.estimators.settings import DETRENDS


class Operation:
    """
    The operating point and the held adaptation of one estimator (a mixin).

    The host provides ``_learn`` (learn from a sample), ``_restart_regressor``,
    ``num_inputs``, ``_forgetting_factor`` and ``_refused`` (the count of
    refused samples).
    """

    def _init_operation(self, detrend: str, adapt: bool) -> None:
        if detrend not in DETRENDS:
            raise ValueError(f"detrend must be 'none' or 'mean', got {detrend!r}")
        self.detrend = detrend
        self._means = RunningMean(self.num_inputs) if detrend == 'mean' else None
        self._centring: CentringMonitor | None = None
        self._excitation_hold = False
        self._held = 0
        self.adapt = adapt

    def _set_operated(self) -> None:
        # the plain per-sample path unless a mean, a hold or a monitor is involved
        self._operated = bool(self._means is not None or self._centring is not None
                              or not self._adapting)

    def _operate(self, y: float, u: np.ndarray) -> None:
        """
        Learn with the operating point removed, or hold the learnt state.

        With ``detrend: mean`` the sample minus the recursive means goes to
        the estimator (the means themselves are held with the adaptation); a
        sample the estimator refuses (:meth:`_undo`) is taken back out of the
        means.
        While adaptation is held, :meth:`_hold` only moves the sample
        history on: nothing learnt changes, so nothing can wind up.
        """
        if self._centring is not None:
            self._centring.take(y, u)
        if not self._adapting:
            self._held += 1
            if self._means is not None:
                y, u = self._means.apply(y, u)
            self._hold(y, u)
            return
        if self._means is None:
            self._learn(y, u)
            return
        refused = self._refused
        self._learn(*self._means.centre(y, u, self._forgetting_factor))
        if self._refused != refused:
            # a sample the estimator refused (an outlier) must not move the
            # operating point either: the means would carry it for 1 / (1 - lambda)
            self._means.undo()

    def _hold(self, y: float, u: np.ndarray) -> None:
        """
        Take a sample without learning from it (adaptation held).

        This generic form restarts the regressor, so that no update regresses
        across the held stretch; estimators whose sample history is separate
        from what they learn override it to keep the history running.
        """
        self._restart_regressor()

    @property
    def adapt(self) -> bool:
        """
        Whether samples update the estimate; may change while running.

        False holds theta, P, the noise statistics and the operating point
        while the regressor and the counters keep running (:attr:`held_samples`).
        """
        return self._adapt

    @adapt.setter
    def adapt(self, value: bool) -> None:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f'adapt must be true or false, got {value!r}')
        self._adapt = bool(value)
        self._adapting = self._adapt and not self._excitation_hold
        self._set_operated()

    @property
    def excitation_hold(self) -> bool:
        """Whether adaptation is held because the input is not exciting (set by the feeder)."""
        return self._excitation_hold

    @excitation_hold.setter
    def excitation_hold(self, value: bool) -> None:
        self._excitation_hold = bool(value)
        self.adapt = self._adapt

    @property
    def held_samples(self) -> int:
        """Count the samples taken while adaptation was held (since construction)."""
        return self._held

    @property
    def operating_point(self) -> np.ndarray | None:
        """Return the recursive means ``[y0, u1, ..., ur]`` (``detrend: mean``), else None."""
        return None if self._means is None else self._means.mean.copy()

    @property
    def operating_point_names(self) -> tuple[str, ...]:
        """Return ``('y', 'u1', ..., 'ur')``, the names of :attr:`operating_point`."""
        return operating_point_names(self.num_inputs)

    def monitor_centring(self, on: bool = True) -> None:
        """Watch whether the data are centred (see :attr:`centring_problem`)."""
        self._centring = CentringMonitor(self.num_inputs) if on else None
        self._set_operated()

    @property
    def centring_problem(self) -> str:
        """
        Return why the raw data look far from centred, or '' (see :meth:`monitor_centring`).

        Only with ``detrend: none``: with ``mean`` the regression sees centred data.
        """
        if self._centring is None or self._means is not None:
            return ''
        return self._centring.problem()


__all__ = ['Operation']
