r"""
A plant stepped one sample at a time with a held input, for ``simulator_node`` ``mode: plant``.

The plant of a :class:`~bcid_ros.simulation.custom.CustomScenario`, run in
closed loop: the input is not drawn from the scenario's input model but
given from outside (the controller's commands) and held between commands
(zero-order hold; 0 until the first command). At sample t

.. math::

    y_t = y_0 + \sum_i q^{-d_i} \frac{B_i}{A} (u_i - u_{0,i})_t + v_t,
    \qquad v = \frac{C}{D} e \quad \left(\frac{C}{D A} e \text{ with equation error}\right)

where :math:`u_t` is the command held at t. A command given after sample t
is applied from sample t + 1: the timing an adaptive controller with
``computation_delay`` assumes (the input computed from y_t is applied at
t + 1). After ``change_after`` samples A and B become those of the plant
after the change; the signal histories carry over, so the change is a
change of coefficients, not a restart.

:class:`ChangingStream` runs the same plant in open loop (``simulator_node``
``mode: open_loop`` with ``change_after_samples``): the input is the custom
scenario's own input model, applied sample by sample.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from bcid_ros.simulation.base import SampleStream, Truth
from bcid_ros.simulation.custom import CustomScenario


class _Polynomials:
    """The difference equations of one plant, on histories long enough for both plants."""

    def __init__(self, scenario: CustomScenario) -> None:
        self.scenario = scenario
        self.a = scenario.a[1:]  # a1..an
        # input i at lag k = d_i + j has coefficient b_ij (j = 0..n)
        lags = scenario.b.shape[1] + int(scenario.input_delay.max())
        self.b = np.zeros((scenario.num_inputs, lags))
        for i, (row, delay) in enumerate(zip(scenario.b, scenario.input_delay)):
            self.b[i, delay:delay + row.size] = row
        denominator = (np.convolve(scenario.d, scenario.a) if scenario.equation_error
                       else scenario.d)
        self.noise_numerator = scenario.c
        self.noise_denominator = denominator[1:]


def _dot_history(coefficients: np.ndarray, history: np.ndarray) -> float:
    """Return sum_k c_k h_k over the first len(c) entries of the history (newest first)."""
    size = coefficients.shape[-1]
    return float(np.sum(coefficients * history[..., :size]))


class HeldInputPlant:
    """
    A custom plant stepped one sample at a time, its input held between commands.

    Parameters
    ----------
    scenario : CustomScenario
        The plant, its noise model, dead times and operating point (its
        input model is not used: the input comes from :meth:`hold`).
    rng : numpy.random.Generator
        Source of the white noise e, one draw per sample.
    after : CustomScenario, optional
        The plant after the change (same number of inputs); its noise
        model, dead times and operating point replace the first plant's.
    change_after : int
        Samples after which the plant becomes ``after`` (0: never).

    Raises
    ------
    ValueError
        If ``after`` has another number of inputs, or ``change_after`` is
        negative.

    """

    def __init__(self, scenario: CustomScenario, rng: np.random.Generator, *,
                 after: CustomScenario | None = None, change_after: int = 0) -> None:
        if after is not None and after.num_inputs != scenario.num_inputs:
            raise ValueError(f'plant_numerator_after must describe r = {scenario.num_inputs} '
                             f'inputs like plant_numerator, got {after.num_inputs}')
        if int(change_after) != change_after or change_after < 0:
            raise ValueError(f'change_after_samples must be an integer >= 0, got '
                             f'{change_after!r}')
        self.rng = rng
        self.num_inputs = scenario.num_inputs
        self._plants = [_Polynomials(scenario)]
        if after is not None and change_after:
            self._plants.append(_Polynomials(after))
        self.change_after = int(change_after) if len(self._plants) > 1 else 0
        depth = max(max(p.b.shape[1], p.a.size, p.noise_numerator.size,
                        p.noise_denominator.size) for p in self._plants) + 1
        self._inputs = np.zeros((self.num_inputs, depth))  # u - u0, newest first (lag 0)
        self._states = np.zeros(depth)  # noiseless deviation x, newest first (lag 1 at [0])
        self._draws = np.zeros(depth)  # e, newest first (lag 0)
        self._noise = np.zeros(depth)  # v, newest first (lag 1 at [0])
        self._held = np.zeros(self.num_inputs)
        self.commands = 0
        self.samples = 0
        self.changed = False

    # -------------------------------------------------------------- state
    @property
    def scenario(self) -> CustomScenario:
        """Return the plant in effect (the one after the change once it happened)."""
        return self._plants[-1 if self.changed else 0].scenario

    def truth(self) -> Truth:
        """Return the truth of the plant in effect."""
        return self.scenario.truth()

    @property
    def held(self) -> np.ndarray:
        """Return the command that the next sample applies (a copy)."""
        return self._held.copy()

    # -------------------------------------------------------------- input
    def hold(self, command: Sequence[float]) -> None:
        """
        Hold ``command`` (r values, finite) from the next sample on.

        Raises
        ------
        ValueError
            If the command does not have r finite values; the held input
            is then unchanged.

        """
        values = np.asarray(command, dtype=float).reshape(-1)
        if values.size != self.num_inputs:
            raise ValueError(f'the input command must have r = {self.num_inputs} values, got '
                             f'{values.size}')
        if not np.isfinite(values).all():
            raise ValueError(f'the input command must be finite, got {values.tolist()}')
        self._held = values
        self.commands += 1

    # --------------------------------------------------------------- step
    def step(self) -> tuple[float, np.ndarray]:
        """
        Advance one sample with the held input; return ``(y_t, u_t)``.

        u_t is the input applied at t (the held command), as published in
        the ``samples`` message. The plant changes before sample
        ``change_after`` is computed, so y at that index is the first output
        of the new plant.
        """
        if self.change_after and self.samples == self.change_after:
            self.changed = True
        plant = self._plants[-1 if self.changed else 0]
        scenario = plant.scenario
        u = self._held.copy()
        self._inputs = np.roll(self._inputs, 1, axis=1)
        self._inputs[:, 0] = u - scenario.input_offset
        x = _dot_history(plant.b, self._inputs) - _dot_history(plant.a, self._states)
        self._states = np.roll(self._states, 1)
        self._states[0] = x
        self._draws = np.roll(self._draws, 1)
        self._draws[0] = self.rng.standard_normal() * np.sqrt(scenario.noise_variance)
        v = (_dot_history(plant.noise_numerator, self._draws)
             - _dot_history(plant.noise_denominator, self._noise))
        self._noise = np.roll(self._noise, 1)
        self._noise[0] = v
        self.samples += 1
        return scenario.output_offset + x + v, u


class ChangingStream(SampleStream):
    """
    The custom scenario's input, open loop, through a plant that changes after a sample count.

    The input is drawn by the scenario's own stream (its input model,
    offsets and measurement noise; that stream's output is not used), and
    each sample is held and stepped by a :class:`HeldInputPlant`, whose
    noise has a generator of its own seeded once from ``rng``: the samples
    do not depend on the block sizes, as every :class:`SampleStream`'s.
    The plant sees the measured input (``input_noise_variance`` > 0 then
    adds its noise to the plant's input too).

    Parameters
    ----------
    scenario, after, change_after
        As :class:`HeldInputPlant`.
    rng : numpy.random.Generator
        Source of the input and of the plant noise's seed.

    """

    def __init__(self, scenario: CustomScenario, rng: np.random.Generator, *,
                 after: CustomScenario | None, change_after: int) -> None:
        plant_seed = int(rng.integers(2 ** 63))
        self._inputs = scenario.stream(rng)
        self.plant = HeldInputPlant(scenario, np.random.default_rng(plant_seed), after=after,
                                    change_after=change_after)

    def take(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Return the next ``count`` samples ``(y, u)``, u held through each sample."""
        _, u = self._inputs.take(count)
        y = np.empty(count)
        for row in range(count):
            self.plant.hold(u[row])
            y[row] = self.plant.step()[0]
        return y, u


def plant_pair(settings: dict[str, Any],
               names: Sequence[str]) -> tuple[CustomScenario, CustomScenario | None]:
    """
    Return the custom plant and the plant after the change from simulator parameters.

    The plant after the change takes every setting of the first but
    ``plant_denominator_after`` and ``plant_numerator_after`` (empty: the
    same polynomial as before); it is None without ``change_after_samples``.

    Raises
    ------
    ValueError
        If a setting is not allowed; the message names it.

    """
    values = {name: settings[name] for name in names}
    before = CustomScenario(**values)
    if not settings.get('change_after_samples'):
        return before, None
    changed = dict(values)
    for name in ('plant_denominator', 'plant_numerator'):
        new = settings.get(f'{name}_after') or []
        if len(new):
            changed[name] = new
    try:
        after = CustomScenario(**changed)
    except ValueError as error:
        raise ValueError(f'the plant after the change (plant_denominator_after, '
                         f'plant_numerator_after): {error}') from None
    return before, after


__all__ = ['ChangingStream', 'HeldInputPlant', 'plant_pair']
