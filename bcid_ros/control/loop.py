r"""
The indirect self-tuning regulator: trust gate, redesign, fallback, counters.

:class:`AdaptiveController` is everything the controller node does, without
ROS: the node hands it each measured output, reference and estimate message
and publishes what it returns.

**Trust gate.** A new estimate is looked at every ``redesign_period`` and
used only if, in this order,

1. its names parse as ``a1..an, b1_<lag>...`` (``bad_names``) and match the
   configured order, feedthrough and delay (``wrong_order``), with one
   finite value per name (``bad_names``, ``nonfinite_estimate``);
2. the identifier says it is valid (``not_valid``; none received yet counts
   as not valid);
3. with ``max_relative_std > 0``: a ``parameter_std`` with the same names
   exists (``no_std``, ``std_mismatch``) and the relative std of the
   polynomials A and B (:func:`relative_std`) is at most
   ``max_relative_std`` (``std_too_large``);
4. the design is well-conditioned (``ill_conditioned``) and exact
   (``design_residual``).

A trusted estimate for which the controller in the loop already places the
closed-loop poles within ``redesign_tolerance`` of the target (distance of
:func:`~bcid_ros.control.design.pole_distance`) is not designed for
(``kept``): every switch restarts the compensation window of a closed-loop
identifier, so the loop switches only when it matters.

Each refused estimate increments exactly one of these counters and keeps
the controller in the loop: the fallback until a first estimate passes,
the last good design after. Estimates that stop arriving for
``estimate_timeout`` seconds are reported once per silence
(``estimates_silent``); an estimate turning invalid (``estimate_invalidated``)
and an identifier that disappears (``identifier_lost``) are reported. A
non-finite output or reference is refused (``nonfinite_output``,
``nonfinite_reference``): the input is then held, and is never NaN.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from bcid_ros.control.design import (check_estimate, closed_loop_poles, Controller,
                                     DesignRefused, place_poles, Plant, pole_distance)
from bcid_ros.control.parameters import check_controller_parameters, structure_of
from bcid_ros.control.reference import ReferenceGenerator
from bcid_ros.control.runtime import ControllerRuntime

#: Why an estimate was not used, with the diagnostic key of each counter.
REFUSALS = {
    'bad_names': 'refused: names not a1..an,b1_<lag>',
    'wrong_order': 'refused: order/lags differ from the configuration',
    'nonfinite_estimate': 'refused: NaN or Inf in the estimate',
    'not_valid': 'refused: estimate not valid',
    'no_std': 'refused: no parameter_std',
    'std_mismatch': 'refused: parameter_std names differ',
    'std_too_large': 'refused: relative std too large',
    'ill_conditioned': 'refused: ill-conditioned design (near cancellation)',
    'design_residual': 'refused: design residual',
}

#: The other counters, with their diagnostic keys.
EVENTS = {
    'redesigns': 'redesigns (controller switched)',
    'kept': 'trusted estimates met by the controller in the loop (not switched)',
    'nonfinite_output': 'refused outputs: NaN or Inf (input held)',
    'nonfinite_reference': 'refused references: NaN or Inf (last kept)',
    'saturated': 'samples with the input saturated',
    'estimates_silent': 'estimate silences (last controller kept)',
    'estimate_invalidated': 'estimates turned invalid',
    'identifier_lost': 'identifier gone (no publisher; last controller kept)',
}


@dataclasses.dataclass
class Outcome:
    """
    What one look at the estimates did.

    Attributes
    ----------
    kind : str
        ``switched`` (a new controller is in the loop), ``kept`` (a trusted
        estimate that the controller in the loop already meets within
        ``redesign_tolerance``), ``refused`` (with ``reason``), ``silent``,
        ``invalidated``, ``lost`` or ``none``.
    message : str
        One log line for a person ('' for ``none``).
    reason : str
        The refusal counter (``refused`` only).

    """

    kind: str = 'none'
    message: str = ''
    reason: str = ''


def relative_std(values: np.ndarray, std: np.ndarray, order: int) -> float:
    r"""
    Return the relative uncertainty of the estimated polynomials A and B.

    .. math::

        \max\left(\frac{\lVert\sigma_a\rVert}{\lVert[1, a]\rVert},
                  \frac{\lVert\sigma_b\rVert}{\lVert b\rVert}\right)

    A is monic, so its size includes the 1 (a plant pole at 0 is no
    uncertainty); B has no such scale, and a b whose sign is not known
    (B near 0) is infinitely uncertain, however small its std next to the
    a coefficients.
    """
    a_part = float(np.linalg.norm(std[:order])) / math.sqrt(1.0 + np.sum(values[:order] ** 2))
    b_norm = float(np.linalg.norm(values[order:]))
    b_std = float(np.linalg.norm(std[order:]))
    b_part = b_std / b_norm if b_norm > 0.0 else (0.0 if b_std == 0.0 else math.inf)
    return max(a_part, b_part)


class AdaptiveController:
    """
    Pole placement on the latest trusted estimate, fallback before, input never NaN.

    Parameters
    ----------
    values : dict
        Controller parameters (:data:`~bcid_ros.control.parameters.CONTROLLER_PARAMETERS`);
        checked, missing ones take their defaults.

    Raises
    ------
    ValueError
        If a parameter is not allowed; the message names it.

    """

    def __init__(self, values: dict[str, Any]) -> None:
        self.settings = check_controller_parameters(values)
        settings = self.settings
        self.structure = structure_of(settings)
        self.poles = tuple(settings['closed_loop_poles'])
        self.strictly_proper = settings['computation_delay'] or self.structure.lags[0] == 0
        self.fallback = Controller.from_coefficients(settings['fallback_numerator'],
                                                     settings['fallback_denominator'])
        self.runtime = ControllerRuntime(self.fallback, input_limit=settings['input_limit'],
                                         antiwindup_pole=settings['antiwindup_pole'],
                                         delayed=settings['computation_delay'])
        self.reference = ReferenceGenerator(settings['reference_signal'],
                                            amplitude=settings['reference_amplitude'],
                                            period=settings['reference_period'],
                                            seed=settings['reference_seed'])
        self.setpoint = settings['reference_offset']
        self.counters = dict.fromkeys(list(REFUSALS) + list(EVENTS), 0)
        self.trusted = False
        self.samples = 0
        #: The plant of the last trusted estimate (None before the first).
        self.plant: Plant | None = None
        #: The plant of the latest estimate with good names (trusted or not).
        self.latest_plant: Plant | None = None
        self.last_reference = self.setpoint
        self._parameters: tuple[tuple[str, ...], np.ndarray] | None = None
        self._std: tuple[tuple[str, ...], np.ndarray] | None = None
        self._valid: bool | None = None
        self._fresh = False
        self._last_estimate_time: float | None = None
        self._silent = False

    # ------------------------------------------------------------ the loop
    @property
    def controller(self) -> Controller:
        """Return the controller in the loop."""
        return self.runtime.controller

    def set_reference(self, value: float) -> bool:
        """Take a setpoint from the reference topic; refuse (and count) a non-finite one."""
        if not math.isfinite(value):
            self.counters['nonfinite_reference'] += 1
            return False
        self.setpoint = float(value)
        return True

    def step(self, output: float) -> float:
        """
        Take the measured output y_t and return the input to publish.

        The reference r'_t is the setpoint plus the built-in excitation. A
        non-finite output is refused (counted) and the last input is
        returned again, the controller state untouched.

        """
        if not math.isfinite(output):
            self.counters['nonfinite_output'] += 1
            return self.runtime.last_input
        self.samples += 1
        self.last_reference = self.setpoint + self.reference.next()
        before = self.runtime.saturated_samples
        value = self.runtime.step(self.last_reference - output)
        self.counters['saturated'] += self.runtime.saturated_samples - before
        return value

    # ------------------------------------------------------- the estimates
    def offer_parameters(self, names: Sequence[str], values: Sequence[float],
                         now: float) -> None:
        """Store the latest ``parameters`` message (looked at by :meth:`redesign`)."""
        self._parameters = (tuple(names), np.asarray(values, dtype=float).copy())
        self._fresh = True
        self._last_estimate_time = now
        self._silent = False

    def offer_std(self, names: Sequence[str], values: Sequence[float]) -> None:
        """Store the latest ``parameter_std`` message."""
        self._std = (tuple(names), np.asarray(values, dtype=float).copy())
        self._fresh = True

    def offer_valid(self, valid: bool) -> Outcome:
        """Store the latest ``valid`` message; report a turn to invalid."""
        was = self._valid
        self._valid = bool(valid)
        self._fresh = True
        if was and not self._valid:
            self.counters['estimate_invalidated'] += 1
            return Outcome('invalidated', 'the identifier\'s estimate turned invalid (restart '
                           'or loss of trust); keeping the controller in the loop')
        return Outcome()

    def redesign(self, now: float) -> Outcome:
        """
        Look at the latest estimate: redesign if it passes the trust gate.

        Called every ``redesign_period``. An estimate is looked at once; a
        refusal is counted once per estimate.

        """
        timeout = self.settings['estimate_timeout']
        if timeout > 0.0 and self._last_estimate_time is not None and not self._silent and \
                now - self._last_estimate_time > timeout:
            self._silent = True
            self.counters['estimates_silent'] += 1
            return Outcome('silent', f'no estimate for {now - self._last_estimate_time:.1f} s '
                           f'(estimate_timeout {timeout:g} s); keeping the '
                           f'{"last designed" if self.trusted else "fallback"} controller')
        if not self._fresh or self._parameters is None:
            return Outcome()
        self._fresh = False
        try:
            plant = self._trusted_plant()
            tolerance = self.settings['redesign_tolerance']
            if self.trusted and tolerance > 0.0:
                distance = pole_distance(closed_loop_poles(plant, self.controller), self.poles)
                if distance <= tolerance:
                    self.plant = plant
                    self.counters['kept'] += 1
                    return Outcome('kept', f'the controller in the loop places the poles of '
                                   f'the new estimate within {distance:.3g} of the target '
                                   f'(redesign_tolerance {tolerance:g}); not switched')
            controller = place_poles(plant, self.poles,
                                     integral=self.settings['integral_action'],
                                     strictly_proper=self.strictly_proper,
                                     max_condition=self.settings['max_condition'])
        except DesignRefused as refusal:
            self.counters[refusal.reason] += 1
            kept = 'last designed' if self.trusted else 'fallback'
            return Outcome('refused', f'estimate not used ({refusal.reason}): {refusal}; '
                           f'keeping the {kept} controller', refusal.reason)
        self.plant = plant
        self.runtime.switch(controller)
        self.trusted = True
        self.counters['redesigns'] += 1
        return Outcome('switched', f'new controller: numerator '
                       f'{np.array2string(controller.numerator, precision=6)}, denominator '
                       f'{np.array2string(controller.denominator, precision=6)} '
                       f'(condition {controller.condition:.3g})')

    def _trusted_plant(self) -> Plant:
        """Return the plant of the latest estimate if it passes the trust gate (1-3)."""
        names, values = self._parameters
        values = check_estimate(names, values, self.structure)
        plant = Plant.from_estimate(values, self.structure)
        self.latest_plant = plant
        if not self._valid:
            why = 'no valid message yet' if self._valid is None else 'valid is false'
            raise DesignRefused('not_valid', f'the identifier says the estimate is not '
                                f'trustworthy ({why})')
        limit = self.settings['max_relative_std']
        if limit > 0.0:
            self._check_std(names, values, limit)
        return plant

    def _check_std(self, names: tuple[str, ...], values: np.ndarray, limit: float) -> None:
        if self._std is None:
            raise DesignRefused('no_std', 'no parameter_std received (max_relative_std > 0)')
        std_names, std = self._std
        if std_names != names or std.shape != values.shape or \
                not np.all(np.isfinite(std)) or np.any(std < 0.0):
            raise DesignRefused('std_mismatch', f'parameter_std names '
                                f'{",".join(std_names)!r} or values do not fit the '
                                f'estimate {",".join(names)!r}')
        relative = relative_std(values, std, self.structure.order)
        if not relative <= limit:
            raise DesignRefused('std_too_large', f'relative std {relative:.3g} > '
                                f'max_relative_std {limit:g}')

    def identifier_lost(self) -> Outcome:
        """Count that the identifier disappeared (the node sees its publishers go)."""
        self.counters['identifier_lost'] += 1
        kept = 'last designed' if self.trusted else 'fallback'
        return Outcome('lost', f'the identifier is gone (no publisher on its parameters); '
                       f'keeping the {kept} controller')

    # ------------------------------------------------------ the diagnostics
    def predicted_poles(self) -> np.ndarray | None:
        """Return the closed-loop poles of (latest estimate, controller in the loop)."""
        if self.latest_plant is None:
            return None
        return closed_loop_poles(self.latest_plant, self.controller)

    @property
    def refusals(self) -> int:
        """Return the number of refused estimates, all reasons."""
        return sum(self.counters[key] for key in REFUSALS)


__all__ = ['AdaptiveController', 'EVENTS', 'Outcome', 'REFUSALS', 'relative_std']
