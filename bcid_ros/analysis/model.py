"""
Properties of an identified discrete-time model: poles, zeros, gains, responses.

A :class:`DiscreteModel` is ``y = sum_i q^-d_i B_i(q)/A(q) u_i`` with
``a = [1, a1, ..., an]`` and rows ``b_i = [b_i0, ..., b_in]`` in ascending
powers of q^-1, and a dead time d_i (samples) per input. Its
continuous-time equivalent comes from the matrix logarithm of its
state-space form: a zero-order-hold sampled system x' = F x has the
discrete state matrix Phi = exp(F T), so F = log(Phi) / T.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy import linalg, signal

#: A pole whose imaginary part is below this (relative) is treated as real.
REAL_TOLERANCE = 1e-9


@dataclasses.dataclass(frozen=True)
class DiscreteModel:
    """
    An identified model ``q^-d_i B_i/A`` per input.

    Parameters
    ----------
    a, b : numpy.ndarray
        A = [1, a1, ..., an], shape ``(n + 1,)``, and one row [b_i0, ..., b_in]
        per input, shape ``(r, n + 1)``.
    delay : int or sequence of int
        The dead time d_i of each input in samples (one integer for all).

    """

    a: np.ndarray
    b: np.ndarray
    delay: Any = 0

    @property
    def delays(self) -> tuple[int, ...]:
        """Return the dead time d_i of each input."""
        if np.ndim(self.delay) == 0:
            return (int(self.delay),) * self.num_inputs
        return tuple(int(d) for d in self.delay)

    @property
    def order(self) -> int:
        """Return n, the degree of A."""
        return self.a.size - 1

    @property
    def num_inputs(self) -> int:
        """Return r."""
        return self.b.shape[0]

    def poles(self) -> np.ndarray:
        """Return the roots of z^n A(z), sorted by decreasing magnitude."""
        roots = np.roots(self.a)
        return roots[np.argsort(-np.abs(roots), kind='stable')]

    def zeros(self, input_index: int = 0) -> np.ndarray:
        """Return the finite zeros of B_i (the roots of z^n B_i(z) after leading zeros)."""
        coefficients = np.trim_zeros(self.b[input_index], 'f')
        if coefficients.size <= 1:
            return np.zeros(0, dtype=complex)
        return np.roots(coefficients)

    def dc_gain(self) -> np.ndarray:
        """Return B_i(1)/A(1) per input (inf when A has a pole at z = 1)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            return self.b.sum(axis=1) / self.a.sum()

    def numerator(self, input_index: int = 0) -> np.ndarray:
        """Return q^-d_i B_i as one coefficient array in ascending powers of q^-1."""
        return np.concatenate([np.zeros(self.delays[input_index]), self.b[input_index]])

    def step(self, count: int) -> np.ndarray:
        """Return the unit-step responses, shape ``(count, r)``."""
        step = np.ones(count)
        return np.column_stack([signal.lfilter(self.numerator(i), self.a, step)
                                for i in range(self.num_inputs)])

    def settling_samples(self, largest: int = 2000) -> int:
        """Return a step-response length that shows the slowest pole settle (5 time constants)."""
        radius = float(np.abs(self.poles()).max()) if self.order else 0.0
        delay = max(self.delays)
        if not radius < 1.0:
            return min(largest, 100 + delay)
        span = 5.0 / -np.log(max(radius, 1e-3))
        return int(min(largest, max(20, np.ceil(span))) + delay + self.order)

    def frequency_response(self, count: int = 512) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(w, H)``: w in rad/sample over (0, pi], H shape ``(count, r)``."""
        w = np.linspace(np.pi / count, np.pi, count)
        responses = [signal.freqz(self.numerator(i), self.a, worN=w)[1]
                     for i in range(self.num_inputs)]
        return w, np.column_stack(responses)

    def continuous(self, period: float) -> dict[str, Any]:
        """
        Return the continuous-time equivalents of the poles for sample period T.

        With A in observable canonical (companion) form Phi, the poles of
        the continuous plant are the eigenvalues of F = logm(Phi) / T. A
        real pole on the negative real axis (or at 0) is not exp(s T) of any
        real s: such a pole has no continuous-time equivalent (it comes from
        the sampling, e.g. a fast zero-order-hold effect, or from noise) and
        is listed apart; the matrix logarithm is taken of the other poles.

        Returns
        -------
        dict
            ``'poles'`` (continuous poles s as ``[re, im]``, one of each
            conjugate pair), ``'modes'`` (per real pole its time constant,
            per complex pair its natural frequency, damping and damped
            frequency; in seconds and rad/s), ``'no_equivalent'`` (the
            discrete poles that have none, as ``[re, im]``), ``'dc_gain'``
            (the same as the discrete one for a zero-order hold) and
            ``'dead_time_s'`` (d_i T: a number for one input, a list for
            several).

        """
        poles = self.poles()
        bad = np.array([p for p in poles if _is_real(p) and p.real <= 0.0])
        good = np.array([p for p in poles if not (_is_real(p) and p.real <= 0.0)])
        modes: list[dict[str, Any]] = []
        continuous = np.zeros(0, dtype=complex)
        if good.size:
            phi = companion(np.real(np.poly(good)))
            generator = linalg.logm(phi) / period
            continuous = np.linalg.eigvals(np.real_if_close(generator, tol=1e6))
            continuous = continuous[np.argsort(-continuous.real, kind='stable')]
        listed = []
        for s in continuous:
            if _is_real(s):
                s = complex(s.real, 0.0)
                # an integrator (s = 0) has no time constant: None (JSON null)
                tau = None if abs(s.real) * period <= REAL_TOLERANCE else -1.0 / s.real
                modes.append({'kind': 'real', 'pole': [s.real, 0.0], 'time_constant_s': tau})
                listed.append(s)
            elif s.imag > 0:
                wn = abs(s)
                modes.append({'kind': 'complex', 'pole': [s.real, s.imag],
                              'natural_frequency_rad_s': wn, 'damping': -s.real / wn,
                              'damped_frequency_rad_s': s.imag})
                listed.append(s)
        gains = [float(g) if np.isfinite(g) else None for g in self.dc_gain()]
        return {'sample_period_s': period,
                'poles': [[float(s.real), float(s.imag)] for s in listed],
                'modes': modes,
                'no_equivalent': [[float(p.real), float(p.imag)] for p in bad],
                'dc_gain': gains if len(gains) > 1 else gains[0],
                'dead_time_s': (self.delays[0] * period if self.num_inputs == 1
                                else [d * period for d in self.delays])}


def _is_real(value: complex) -> bool:
    return abs(value.imag) <= REAL_TOLERANCE * max(1.0, abs(value))


def companion(a: np.ndarray) -> np.ndarray:
    """Return the observable canonical state matrix of 1/A, whose eigenvalues are A's roots."""
    n = a.size - 1
    matrix = np.zeros((n, n))
    matrix[:, 0] = -a[1:]
    matrix[:-1, 1:] = np.eye(n - 1)
    return matrix


def complex_list(values: np.ndarray) -> list[list[float]]:
    """Return complex numbers as JSON-friendly ``[re, im]`` pairs."""
    return [[float(np.real(v)), float(np.imag(v))] for v in values]


__all__ = ['DiscreteModel', 'companion', 'complex_list']
