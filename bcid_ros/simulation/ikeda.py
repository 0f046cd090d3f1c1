"""
The closed-loop example of Ikeda (2008), section 7.

Plant y[k] = 0.5/(q - 0.8) u[k] + nu[k] with white Gaussian observation noise
nu of variance sigma_nu^2 = 1 (assumption A3, eq. 7; there is no process
noise), under the controller of eq. (60) with negative feedback,
u[k] = 0.2289/(q - 0.09004) (r[k] - y[k]). The reference r is a random
binary sequence of magnitude 0.5 held for 16 samples ("bandwidth 1/16",
sections 7.2 and 7.3); section 7.1 uses r = 0 (``reference_amplitude=0``).

The published y and u are the measured loop signals: y includes nu and u is
the controller output. The loop is simulated through its closed-loop transfer
functions (eqs. 22, 23),

    y = (b_p b_c / d_cl) r + (a_p a_c / d_cl) nu,
    u = (a_p b_c / d_cl) (r - nu),      d_cl = a_p a_c + b_p b_c,

with filters that keep their state between blocks, which is the loop started
at rest.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bcid_ros.estimators.base import parameter_names
from bcid_ros.estimators.lti import closed_loop_polynomial, make_controller
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from bcid_ros.simulation.base import SampleStream, Scenario, StreamingFilter, Truth

#: b_p(q), a_p(q) of the example, descending powers of q.
PLANT_NUMERATOR = (0.5,)
PLANT_DENOMINATOR = (1.0, -0.8)
#: Eq. (60): b_c(q), a_c(q), descending powers of q, negative feedback.
CONTROLLER_NUMERATOR = (0.2289,)
CONTROLLER_DENOMINATOR = (1.0, -0.09004)
CONTROLLER_SIGN = 'negative'
NOISE_VARIANCE = 1.0
REFERENCE_AMPLITUDE = 0.5
REFERENCE_HOLD = 16


def _z_form(numerator: np.ndarray, denominator: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (b, a) in ascending powers of z^-1 for N(q)/D(q) with deg N <= deg D."""
    numerator = np.trim_zeros(np.asarray(numerator, dtype=float), 'f')
    if numerator.size == 0:
        numerator = np.zeros(1)
    pad = denominator.size - numerator.size
    return np.concatenate((np.zeros(pad), numerator)), np.asarray(denominator, dtype=float)


class IkedaClosedLoop(Scenario):
    """
    Ikeda (2008) section 7: a plant in a stable loop with a known controller.

    Every setting defaults to the paper's example; the others let tests and
    users build other loops of the same kind.

    Parameters
    ----------
    plant_numerator : sequence of float
        b_p(q) in descending powers of q, degree < n.
    plant_denominator : sequence of float
        a_p(q), monic, degree n (may be unstable if the loop is stable).
    controller_numerator, controller_denominator : sequence of float
        b_c(q), a_c(q) in descending powers of q (proper).
    controller_sign : str
        ``'negative'``: u = (b_c/a_c)(r - y); ``'positive'``: u = (b_c/a_c)(y - r).
    noise_variance : float
        sigma_nu^2 of the white observation noise.
    reference_amplitude : float
        r = +-amplitude (0 gives r = 0, as in section 7.1).
    reference_hold : int
        Samples each level of r is held.

    Raises
    ------
    ValueError
        If a setting is out of range or the closed loop is not stable.

    """

    name = 'ikeda_closed_loop'

    def __init__(self, *, plant_numerator: Any = PLANT_NUMERATOR,
                 plant_denominator: Any = PLANT_DENOMINATOR,
                 controller_numerator: Any = CONTROLLER_NUMERATOR,
                 controller_denominator: Any = CONTROLLER_DENOMINATOR,
                 controller_sign: str = CONTROLLER_SIGN, noise_variance: float = NOISE_VARIANCE,
                 reference_amplitude: float = REFERENCE_AMPLITUDE,
                 reference_hold: int = REFERENCE_HOLD) -> None:
        a_p = np.asarray(plant_denominator, dtype=float)
        b_p = np.trim_zeros(np.asarray(plant_numerator, dtype=float), 'f')
        if a_p.ndim != 1 or a_p.size < 2 or a_p[0] != 1.0 or not np.isfinite(a_p).all():
            raise ValueError('plant_denominator must be monic of degree >= 1, got '
                             f'{a_p.tolist()}')
        if b_p.size >= a_p.size or not np.isfinite(b_p).all():
            raise ValueError(f'plant_numerator must have degree < {a_p.size - 1} (a strictly '
                             f'proper plant), got {b_p.tolist()}')
        if not np.isfinite(noise_variance) or noise_variance < 0:
            raise ValueError(f'noise_variance must be >= 0, got {noise_variance!r}')
        if int(reference_hold) != reference_hold or reference_hold < 1:
            raise ValueError(f'reference_hold must be an integer >= 1, got {reference_hold!r}')
        self.order = a_p.size - 1
        self.plant_denominator = a_p
        self.plant_numerator = np.concatenate((np.zeros(self.order - b_p.size), b_p))
        self.controller = make_controller(controller_numerator, controller_denominator,
                                          controller_sign)
        self.noise_variance = float(noise_variance)
        self.reference_amplitude = float(reference_amplitude)
        self.reference_hold = int(reference_hold)
        b_c = self.controller.feedback_numerator
        a_c = self.controller.denominator
        b_full = np.concatenate(([0.0], self.plant_numerator))
        # d_cl = a_p a_c + b_p b_c                                           (8)
        self.characteristic = closed_loop_polynomial(a_p, self.plant_numerator, self.controller)
        if not is_stable(monic_coefficients(self.characteristic)):
            raise ValueError('the closed loop must be stable (assumption A4); its poles are '
                             f'{np.roots(self.characteristic).round(4).tolist()}')
        # y = b_p b_c/d_cl r + a_p a_c/d_cl nu ; u = a_p b_c/d_cl (r - nu)   (22), (23)
        self.transfer = {
            'r_to_y': _z_form(np.polymul(b_full, b_c), self.characteristic),
            'nu_to_y': _z_form(np.polymul(a_p, a_c), self.characteristic),
            'r_minus_nu_to_u': _z_form(np.polymul(a_p, b_c), self.characteristic),
        }

    @property
    def controller_numerator(self) -> list[float]:
        """Return b_c(q), descending powers of q, as for the ``controller_numerator`` parameter."""
        return self.controller.numerator.tolist()

    @property
    def controller_denominator(self) -> list[float]:
        """Return a_c(q), descending powers of q, as for ``controller_denominator``."""
        return self.controller.denominator.tolist()

    @property
    def controller_sign(self) -> str:
        """Return the ``controller_sign`` of the loop."""
        return self.controller.sign

    def estimator_settings(self) -> dict[str, Any]:
        """Return the cl_bcls settings (ROS parameter names) that describe this loop."""
        return {'order': self.order, 'num_inputs': 1, 'feedthrough': False,
                'controller_numerator': self.controller_numerator,
                'controller_denominator': self.controller_denominator,
                'controller_sign': self.controller_sign}

    def truth(self) -> Truth:
        """
        Return a_1..a_n, b1_1..b1_n of the plant and sigma2 = sigma_nu^2.

        sigma2 is the variance of the white observation noise nu in
        y = (b_p/a_p) u + nu (eq. 7), the quantity eq. (58) estimates.
        """
        theta = np.concatenate((self.plant_denominator[1:], self.plant_numerator))
        return Truth(parameter_names(self.order, 1, False), theta, ('sigma2',),
                     np.array([self.noise_variance]))

    def stream(self, rng: np.random.Generator) -> SampleStream:
        """Return a stream of (y, u) loop samples drawing from ``rng``."""
        return _IkedaStream(self, rng)


class _IkedaStream(SampleStream):
    def __init__(self, scenario: IkedaClosedLoop, rng: np.random.Generator) -> None:
        self.rng = rng
        self.noise_std = np.sqrt(scenario.noise_variance)
        self.amplitude = scenario.reference_amplitude
        self.hold = scenario.reference_hold
        self.t = 0
        self.level = 0.0
        self.filters = {key: StreamingFilter(*ba) for key, ba in scenario.transfer.items()}

    def take(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        if count == 0:
            # (lfilter with an empty block would return a zeroed filter state)
            return np.zeros(0), np.zeros((0, 1))
        # One (count, 2) normal draw per block: column 0 is nu, column 1 decides the sign
        # of r where a new level starts. Samples are then independent of the blocking.
        draws = self.rng.standard_normal((count, 2))
        nu = self.noise_std * draws[:, 0]
        index = np.arange(count)
        starts = (self.t + index) % self.hold == 0
        levels = np.where(draws[:, 1] >= 0.0, self.amplitude, -self.amplitude)
        # r[k] = the level drawn at the last start at or before k
        last_start = np.maximum.accumulate(np.where(starts, index, -1))
        r = np.where(last_start >= 0, levels[np.maximum(last_start, 0)], self.level)
        self.level = float(r[-1])
        self.t += count
        y = self.filters['r_to_y'](r) + self.filters['nu_to_y'](nu)
        u = self.filters['r_minus_nu_to_u'](r - nu)
        return y, u.reshape(-1, 1)
