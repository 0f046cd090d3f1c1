r"""
The adaptive loop simulated in one process, without ROS: plant, estimator, controller.

This is the loop the three nodes will run (simulator in plant mode,
identifier, controller), with the same :class:`AdaptiveController` and the
same estimators, sample by sample:

1. the plant gives :math:`y_t = y_0 + \frac{B}{A}(u - u_0)_t + v_t` (output
   error, white :math:`v_t` of standard deviation ``noise_std``), with the
   input :math:`u_t` held since the previous sample;
2. the estimator takes :math:`(y_t, u_t)`;
3. the controller takes :math:`y_t` and returns the input applied at t + 1
   (``computation_delay``; the controller is strictly proper);
4. every ``redesign_every`` samples the estimate is offered (names, values,
   valid) and the controller looks at it. When the controller switches,
   ``estimator_factory`` may be called again with the new controller (a
   closed-loop estimator that must know the controller restarts), or the
   estimator's ``set_controller`` is called with it, as the identifier's
   ``controller_topic`` makes ``cl_bcls`` do.

It measures what the loop achieves: at each look, the estimate and the
closed-loop poles of (true plant, controller in the loop).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import numpy as np

from bcid_ros.control.design import closed_loop_poles, Controller, Plant
from bcid_ros.control.loop import AdaptiveController


@dataclasses.dataclass
class LoopRun:
    """
    The record of one simulated adaptive loop.

    Attributes
    ----------
    y, u, r : numpy.ndarray
        Output, applied input and reference r', shape ``(samples,)``.
    look_samples : numpy.ndarray
        The samples at which the estimate was looked at, shape ``(k,)``.
    estimates : numpy.ndarray
        The estimate offered at each look (NaN when the estimator had none
        valid), shape ``(k, p)``.
    poles : numpy.ndarray
        Closed-loop poles of (true plant at that sample, controller in the
        loop after the look), sorted by decreasing modulus, shape ``(k, m)``.
    outcomes : list of str
        The kind of each look's outcome (``switched``, ``refused``, ...).
    loop : AdaptiveController
        The controller at the end (counters, controller in the loop).

    """

    y: np.ndarray
    u: np.ndarray
    r: np.ndarray
    look_samples: np.ndarray
    estimates: np.ndarray
    poles: np.ndarray
    outcomes: list[str]
    loop: AdaptiveController


class _Plant:
    """Output-error ARX plant at an operating point, strictly proper."""

    def __init__(self, plant: Plant, y0: float, u0: float) -> None:
        self.y0, self.u0 = y0, u0
        self.set(plant)
        self._inputs = np.zeros(self._b.size)
        self._states = np.zeros(self._a.size)

    def set(self, plant: Plant) -> None:
        # x_t = -a_1 x_(t-1) - ... + b_1 u_(t-1) + ...; B padded to lags 1..N
        degree = plant.denominator.size - 1
        self._a = plant.denominator[1:].copy()
        b = np.zeros(degree)
        b[degree - plant.numerator.size:] = plant.numerator
        self._b = b

    def output(self, noise: float) -> float:
        x = float(np.dot(self._b, self._inputs) - np.dot(self._a, self._states))
        self._states = np.concatenate([[x], self._states[:-1]])
        return self.y0 + x + noise

    def apply(self, u: float) -> None:
        self._inputs = np.concatenate([[u - self.u0], self._inputs[:-1]])


def simulate_adaptive_loop(estimator_factory: Callable[[Controller], Any],
                           settings: dict[str, Any], theta: Sequence[float], *,
                           samples: int, noise_std: float, rng: np.random.Generator,
                           redesign_every: int = 1000, restart_on_switch: bool = False,
                           set_controller_on_switch: bool = False,
                           y0: float = 0.0, u0: float = 0.0, change_at: int | None = None,
                           theta_after: Sequence[float] | None = None,
                           std_of: Callable[[Any], Sequence[float]] | None = None) -> LoopRun:
    """
    Run plant, estimator and adaptive controller together for ``samples`` samples.

    Parameters
    ----------
    estimator_factory : callable
        ``factory(controller)`` returns a fresh estimator (``update(y, u)``,
        ``theta``, ``valid``) for the controller in the loop.
    settings : dict
        Controller parameters; ``computation_delay`` must be true and the
        plant strictly proper (lags from 1).
    theta : sequence of float
        The true plant ``[a1..an, b1_<lags>]`` in the configured structure.
    samples : int
        Loop length.
    noise_std : float
        Standard deviation of the white output noise.
    rng : numpy.random.Generator
        Source of the noise.
    redesign_every : int
        Samples between two looks at the estimate.
    restart_on_switch : bool
        Build a new estimator at every controller switch.
    set_controller_on_switch : bool
        Call ``estimator.set_controller(numerator, denominator)`` with the
        new controller at every switch, as the identifier does with
        ``controller_topic``.
    y0, u0 : float
        Operating point of the plant.
    change_at : int, optional
        Sample at which the plant becomes ``theta_after``.
    theta_after : sequence of float, optional
        The plant after the change.
    std_of : callable, optional
        ``std_of(estimator)`` returns the standard deviations offered as
        ``parameter_std`` (none offered without it: set ``max_relative_std``
        to 0 then).

    Returns
    -------
    LoopRun

    Raises
    ------
    ValueError
        If the settings are not allowed, or do not describe a strictly
        proper plant with ``computation_delay``.

    """
    loop = AdaptiveController(settings)
    structure = loop.structure
    if not loop.settings['computation_delay'] or structure.lags[0] == 0:
        raise ValueError('simulate_adaptive_loop needs computation_delay: true and a strictly '
                         'proper plant (no lag-0 feedthrough)')
    truth = Plant.from_estimate(theta, structure)
    after = None if theta_after is None else Plant.from_estimate(theta_after, structure)
    plant = _Plant(truth, y0, u0)
    estimator = estimator_factory(loop.controller)
    noise = rng.standard_normal(samples) * noise_std
    y, u, r = np.empty(samples), np.empty(samples), np.empty(samples)
    looks, estimates, poles, outcomes = [], [], [], []
    pending = 0.0
    for t in range(samples):
        if change_at is not None and t == change_at and after is not None:
            truth = after
            plant.set(truth)
        y[t] = plant.output(noise[t])
        u[t] = pending
        plant.apply(u[t])
        estimator.update(y[t], u[t])
        pending = loop.step(y[t])
        r[t] = loop.last_reference
        if (t + 1) % redesign_every:
            continue
        valid = bool(estimator.valid)
        values = np.asarray(estimator.theta, dtype=float)
        loop.offer_parameters(structure.names, values, float(t))
        if std_of is not None:
            loop.offer_std(structure.names, std_of(estimator))
        loop.offer_valid(valid)
        outcome = loop.redesign(float(t))
        if outcome.kind == 'switched' and restart_on_switch:
            estimator = estimator_factory(loop.controller)
        elif outcome.kind == 'switched' and set_controller_on_switch:
            estimator.set_controller(*loop.controller.message_data())
        looks.append(t + 1)
        estimates.append(values if valid else np.full(values.size, np.nan))
        poles.append(closed_loop_poles(truth, loop.controller))
        outcomes.append(outcome.kind)
    width = max((p.size for p in poles), default=0)
    padded = np.full((len(poles), width), np.nan, dtype=complex)
    for row, value in zip(padded, poles):
        row[:value.size] = value
    return LoopRun(y, u, r, np.array(looks), np.array(estimates).reshape(len(looks), -1),
                   padded, outcomes, loop)


__all__ = ['LoopRun', 'simulate_adaptive_loop']
