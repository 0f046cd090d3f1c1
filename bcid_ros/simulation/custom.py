"""
A user-defined plant for the simulator node's ``scenario: custom``.

y(t) = y0 + sum_i z^-d_i B_i(z)/A(z) (u_i(t) - u0_i) + v(t), with
v = C(z)/D(z) e and e white Gaussian (output error), or
A(z) (y(t) - y0) = sum_i z^-d_i B_i(z) (u_i(t) - u0_i) + v(t) with
``equation_error=True``. d_i is the dead time of input i in samples and
(u0, y0) the operating point (both zero by default). Polynomials are in ascending powers of z^-1:
A = [1, a1, ..., an], B_i = [b_i0, b_i1, ..., b_in] (all r of them
concatenated in one list, as a ROS double array can carry), C = [1, c1, ...],
D = [1, d1, ...]. Each input is a white Gaussian or random binary signal,
coloured by a filter, and may be measured with white noise (errors in
variables).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import signal

from bcid_ros.estimators.base import parameter_names
from bcid_ros.estimators.lti import finite_vector
from bcid_ros.simulation.base import SampleStream, Scenario, StreamingFilter, Truth

#: Impulse-response length used for the stationary variance of C/D e.
VARIANCE_HORIZON = 20000


def _polynomial(name: str, value: Any, monic: bool = False) -> np.ndarray:
    array = finite_vector(name, value)
    if monic and array[0] != 1.0:
        raise ValueError(f'{name} must start with 1 (monic, ascending powers of z^-1), '
                         f'got {array.tolist()}')
    return array


def _check_stable(name: str, denominator: np.ndarray) -> None:
    if denominator.size > 1 and np.abs(np.roots(denominator)).max() >= 1.0:
        raise ValueError(f'{name} must be stable (all roots inside the unit circle), got '
                         f'{denominator.tolist()}')


def _nonnegative(name: str, value: Any) -> float:
    value = float(value)
    if not np.isfinite(value) or value < 0:
        raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
    return value


def _finite(name: str, value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a finite number, got {value!r}') from None
    if not np.isfinite(number):
        raise ValueError(f'{name} must be a finite number, got {value!r}')
    return number


def _per_input(name: str, value: Any, num_inputs: int) -> np.ndarray:
    """Return one finite number per input from one number or a list of r numbers."""
    array = _polynomial(name, value)
    if array.size == 1:
        return np.full(num_inputs, array[0])
    if array.size != num_inputs:
        raise ValueError(f'{name} must be one number or r = {num_inputs} numbers (one per '
                         f'input), got {array.size}')
    return array


def _per_input_delays(value: Any, num_inputs: int) -> np.ndarray:
    """Return one dead time d_i >= 0 (an integer number of samples) per input."""
    delays = _per_input('input_delay', value, num_inputs)
    if np.any(delays < 0) or np.any(delays != np.round(delays)):
        raise ValueError('input_delay must hold integers >= 0 (samples), one or one per '
                         f'input, got {delays.tolist()}')
    return delays.astype(int)


class CustomScenario(Scenario):
    """
    A plant, noise model and input model given by parameters.

    Parameters
    ----------
    plant_denominator : sequence of float
        A(z) = [1, a1, ..., an], stable.
    plant_numerator : sequence of float
        B_1(z), ..., B_r(z) concatenated, each [b_i0, ..., b_in]: r (n + 1)
        numbers. The model has direct feedthrough if any b_i0 is non-zero.
    noise_numerator, noise_denominator : sequence of float
        C(z) and D(z) of the noise v = C/D e, monic; D stable.
    noise_variance : float
        Variance of the white e.
    equation_error : bool
        A y = B u + v instead of y = B/A u + v.
    input_signal : str
        ``'white'`` (Gaussian) or ``'binary'`` (random +-1 held for
        ``input_hold`` samples), scaled by sqrt(input_variance).
    input_variance : float
        Variance of the input driving signal.
    input_hold : int
        Samples each binary level is held.
    input_numerator, input_denominator : sequence of float
        Colouring filter of each input; the denominator monic and stable.
    input_noise_variance : float
        Variance of white noise added to the measured inputs.
    input_delay : int or sequence of int
        Dead time d_i >= 0 of each input in samples (one number for all).
    input_offset : float or sequence of float
        Operating point u0_i of each input (one number for all): the
        measured input is u0_i plus the coloured driving signal.
    output_offset : float
        Operating point y0 of the output.

    Raises
    ------
    ValueError
        If a setting is not allowed; the message names it.

    """

    name = 'custom'

    def __init__(self, *, plant_denominator: Any = (1.0, -0.8), plant_numerator: Any = (0.0, 0.5),
                 noise_numerator: Any = (1.0,), noise_denominator: Any = (1.0,),
                 noise_variance: float = 0.01, equation_error: bool = False,
                 input_signal: str = 'white', input_variance: float = 1.0, input_hold: int = 1,
                 input_numerator: Any = (1.0,), input_denominator: Any = (1.0,),
                 input_noise_variance: float = 0.0, input_delay: Any = 0,
                 input_offset: Any = 0.0, output_offset: float = 0.0) -> None:
        self.a = _polynomial('plant_denominator', plant_denominator, monic=True)
        if self.a.size < 2:
            raise ValueError('plant_denominator must have order n >= 1: [1, a1, ..., an], got '
                             f'{self.a.tolist()}')
        _check_stable('plant_denominator', self.a)
        self.order = self.a.size - 1
        numerator = _polynomial('plant_numerator', plant_numerator)
        if numerator.size % (self.order + 1):
            raise ValueError(f'plant_numerator must hold r (n + 1) = r x {self.order + 1} '
                             f'numbers (b_i0 ... b_in for each input), got {numerator.size}')
        self.b = numerator.reshape(-1, self.order + 1)
        self.num_inputs = self.b.shape[0]
        self.feedthrough = bool(np.any(self.b[:, 0] != 0.0))
        self.c = _polynomial('noise_numerator', noise_numerator, monic=True)
        self.d = _polynomial('noise_denominator', noise_denominator, monic=True)
        _check_stable('noise_denominator', self.d)
        self.noise_variance = _nonnegative('noise_variance', noise_variance)
        self.equation_error = bool(equation_error)
        if input_signal not in ('white', 'binary'):
            raise ValueError(f"input_signal must be 'white' or 'binary', got {input_signal!r}")
        self.input_signal = input_signal
        self.input_variance = _nonnegative('input_variance', input_variance)
        if isinstance(input_hold, bool) or int(input_hold) != input_hold or input_hold < 1:
            raise ValueError(f'input_hold must be an integer >= 1, got {input_hold!r}')
        self.input_hold = int(input_hold)
        self.input_numerator = _polynomial('input_numerator', input_numerator)
        self.input_denominator = _polynomial('input_denominator', input_denominator, monic=True)
        _check_stable('input_denominator', self.input_denominator)
        self.input_noise_variance = _nonnegative('input_noise_variance', input_noise_variance)
        self.input_delay = _per_input_delays(input_delay, self.num_inputs)
        self.input_offset = _per_input('input_offset', input_offset, self.num_inputs)
        self.output_offset = _finite('output_offset', output_offset)

    def truth(self) -> Truth:
        """
        Return [a1..an, b1_(0|1)..br_n] and sigma2, the variance of v.

        sigma2 is the stationary variance of v = C/D e (equal to
        ``noise_variance`` for white noise). With an input delay d_i the
        names of input i carry the true lags, ``b{i}_{d_i + 1}`` ... (or
        from ``b{i}_{d_i}`` with feedthrough).
        """
        first = 0 if self.feedthrough else 1
        theta = np.concatenate([self.a[1:]] + [row[first:] for row in self.b])
        impulse = np.zeros(VARIANCE_HORIZON)
        impulse[0] = 1.0
        gain = float(np.sum(signal.lfilter(self.c, self.d, impulse) ** 2))
        return Truth(self._parameter_names(), theta, ('sigma2',),
                     np.array([self.noise_variance * gain]))

    def _parameter_names(self) -> tuple[str, ...]:
        names = list(parameter_names(self.order, self.num_inputs, self.feedthrough))
        first = 0 if self.feedthrough else 1
        for i, delay in enumerate(self.input_delay):
            for k in range(first, self.order + 1):
                index = names.index(f'b{i + 1}_{k}')
                names[index] = f'b{i + 1}_{k + int(delay)}'
        return tuple(names)

    def stream(self, rng: np.random.Generator) -> SampleStream:
        """Return a stream of (y, u) samples drawing from ``rng``."""
        return _CustomStream(self, rng)


class _CustomStream(SampleStream):
    def __init__(self, scenario: CustomScenario, rng: np.random.Generator) -> None:
        self.s = scenario
        self.rng = rng
        self.t = 0
        r = scenario.num_inputs
        self.levels = np.zeros(r)
        self.colour = [StreamingFilter(scenario.input_numerator, scenario.input_denominator)
                       for _ in range(r)]
        # the dead time is d_i leading zeros of B_i: exact and kept across blocks
        self.plant = [StreamingFilter(np.concatenate([np.zeros(d), b]), scenario.a)
                      for b, d in zip(scenario.b, scenario.input_delay)]
        noise_denominator = (np.convolve(scenario.d, scenario.a) if scenario.equation_error
                             else scenario.d)
        self.noise = StreamingFilter(scenario.c, noise_denominator)

    def take(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        s = self.s
        r = s.num_inputs
        # One (k, 2r + 1) draw per block keeps the samples independent of blocking.
        draws = self.rng.standard_normal((count, 2 * r + 1))
        drive = draws[:, :r]
        if s.input_signal == 'binary':
            drive = np.empty((count, r))
            for row in range(count):
                if (self.t + row) % s.input_hold == 0:
                    self.levels = np.where(draws[row, :r] >= 0.0, 1.0, -1.0)
                drive[row] = self.levels
        self.t += count
        drive = drive * np.sqrt(s.input_variance)
        u = np.column_stack([self.colour[i](drive[:, i]) for i in range(r)])
        y = s.output_offset + self.noise(np.sqrt(s.noise_variance) * draws[:, r])
        for i in range(r):
            y = y + self.plant[i](u[:, i])
        # u is the deviation u - u0; the plant sees it, the measurement adds u0 back
        measured = u + s.input_offset + np.sqrt(s.input_noise_variance) * draws[:, r + 1:]
        return y, np.ascontiguousarray(measured)
