"""
A seeded family of realistic open-loop plants, for accuracy benchmarks.

The papers' examples are second-order plants under white excitation. Plants
beside a real machine are not: they are often oversampled (poles near 1),
driven by a held binary signal, a sum of sines or a slow input, with
coloured output noise and a dead time, at an operating point. Each case of
this family draws, from its seed alone:

* order n in 1-3, one or two inputs, a dead time of 0-3 samples per input;
* poles from oversampled (radius 0.9-0.995) to moderate (0.1-0.9), with a
  lightly to well damped complex pair in some cases; random numerators with
  no near pole-zero cancellation, each input's share of the output scaled to
  a random size;
* per input an excitation: white noise, a held PRBS (a maximum-length
  sequence held 2-10 samples), a multisine (10-40 random frequencies below a
  random band edge, random phases) or low-pass filtered noise (2nd-order
  Butterworth);
* output noise, white or coloured (ARMA(1, 1)), or equation error
  (A y = B u + e, so v = e/A), at a signal-to-noise ratio of 5-40 dB;
* 2,000-10,000 samples, and in half the cases an operating point
  (y = y0 + ..., u = u0 + ...) at which the plant rests before the record.

A draw whose truth its record does not determine (the predicted relative
error of an efficient estimate above 20 %: a fast pole hidden under the
noise beside slow ones, a resonance the input does not excite) is drawn
again, since no estimator's error would then mean anything.

The true parameters are in the estimators' order and names
(:func:`bcid_ros.estimators.base.parameter_names`), without feedthrough.
Generation uses :class:`numpy.random.Generator` only and costs a few
milliseconds per case.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np
from scipy import signal

from bcid_ros.analysis.pem import oe_jacobian, Structure
from bcid_ros.estimators.base import parameter_names

#: Range of the output signal-to-noise ratio, dB (noise-free output variance over noise variance).
SNR_RANGE_DB = (5.0, 40.0)
#: Range of the record length, samples (drawn log-uniform, rounded to 100).
LENGTH_RANGE = (2000, 10000)
#: Largest dead time per input, samples.
MAX_DELAY = 3
#: Radius ranges of oversampled and moderate real poles, and of complex pairs.
SLOW_RADIUS = (0.9, 0.995)
MODERATE_RADIUS = (0.1, 0.9)
COMPLEX_RADIUS = (0.6, 0.97)
#: A zero of the numerator(s) closer than this to a pole counts as a cancellation.
CANCELLATION_DISTANCE = 0.1
#: Largest relative error (see RealisticCase.predicted_error) of a case; a draw
#: above it is not determined by its record and is drawn again.
MAX_PREDICTED_ERROR = 0.2
#: Draws per case before giving up.
MAX_ATTEMPTS = 100
#: Excitations and noises of the family.
EXCITATIONS = ('white', 'prbs', 'multisine', 'lowpass')
NOISES = ('white', 'coloured', 'equation')


@dataclasses.dataclass(frozen=True)
class RealisticCase:
    """
    One plant of the family with its record and truth.

    Attributes
    ----------
    seed : tuple of int
        The entropy the case was drawn from (``realistic_case(seed)`` redraws it).
    y : numpy.ndarray, shape ``(N,)``
        Measured output, with the operating point.
    u : numpy.ndarray, shape ``(N, r)``
        Measured inputs, with the operating point.
    order : int
        n, the degree of F and of every B_i.
    input_delay : tuple of int
        Dead time d_i of each input.
    theta : numpy.ndarray, shape ``(p,)``
        True parameters ``a1 ... an, b1_{d1+1} ... br_{dr+n}``.
    parameter_names : tuple of str
        Their names.
    operating_point : numpy.ndarray, shape ``(1 + r,)``
        ``[y0, u0_1, ..., u0_r]`` (zeros when the plant works around zero).
    poles : numpy.ndarray
        Roots of F.
    excitation : tuple of str
        Kind of each input (one of :data:`EXCITATIONS`, PRBS with its hold).
    noise : str
        One of :data:`NOISES`.
    snr_db : float
        Output signal-to-noise ratio.
    noise_free : numpy.ndarray, shape ``(N,)``
        The noise-free output around the operating point.
    predicted_error : float
        sqrt(trace of sigma_v^2 (psi^T psi)^-1) / ||theta||, psi the OE gradient
        at the truth: the relative error an efficient estimate would have
        with white noise of the same variance. Cases above
        ``MAX_PREDICTED_ERROR`` are not drawn.
    description : str
        One line that says all of the above.

    """

    seed: tuple[int, ...]
    y: np.ndarray
    u: np.ndarray
    order: int
    input_delay: tuple[int, ...]
    theta: np.ndarray
    parameter_names: tuple[str, ...]
    operating_point: np.ndarray
    poles: np.ndarray
    excitation: tuple[str, ...]
    noise: str
    snr_db: float
    noise_free: np.ndarray
    predicted_error: float
    description: str

    @property
    def num_inputs(self) -> int:
        """Return r."""
        return self.u.shape[1]

    @property
    def samples(self) -> int:
        """Return N."""
        return self.y.size

    @property
    def detrend(self) -> str:
        """Return the estimators' ``detrend`` setting this record needs: 'mean' or 'none'."""
        return 'mean' if np.any(self.operating_point != 0.0) else 'none'


def realistic_case(seed: int | Sequence[int]) -> RealisticCase:
    """
    Return the case drawn from ``seed`` (an integer or a sequence of integers).

    A draw whose truth the record does not determine, with a predicted
    relative error :attr:`RealisticCase.predicted_error` above
    ``MAX_PREDICTED_ERROR``, is drawn again from the same generator.

    Raises
    ------
    ValueError
        If ``seed`` is not a non-negative integer or a sequence of them.

    """
    entropy = _entropy(seed)
    rng = np.random.default_rng(entropy)
    for _ in range(MAX_ATTEMPTS):
        case = _draw_case(rng, entropy)
        if case.predicted_error <= MAX_PREDICTED_ERROR:
            return case
    raise RuntimeError(f'no identifiable case from seed {entropy} in {MAX_ATTEMPTS} draws')


def _draw_case(rng: np.random.Generator, entropy: tuple[int, ...]) -> RealisticCase:
    """Draw one case (see the module docstring) from ``rng``."""
    order = int(rng.integers(1, 4))
    num_inputs = int(rng.choice([1, 2], p=[0.6, 0.4]))
    delays = tuple(int(d) for d in rng.integers(0, MAX_DELAY + 1, size=num_inputs))
    count = int(round(math.exp(rng.uniform(*np.log(LENGTH_RANGE))), -2))
    poles = _draw_poles(rng, order)
    denominator = np.real(np.poly(poles))
    numerators = _draw_numerators(rng, poles, num_inputs)
    kinds, inputs = zip(*(_excitation(rng, count) for _ in range(num_inputs)))
    u = np.column_stack(inputs)
    shares = []
    for i in range(num_inputs):
        delayed = np.concatenate([np.zeros(delays[i] + 1), numerators[i]])
        share = signal.lfilter(delayed, denominator, u[:, i])
        # each input's share of the output gets a random size (log-uniform 0.5-2)
        gain = math.exp(rng.uniform(math.log(0.5), math.log(2.0))) / share.std()
        numerators[i] *= gain
        shares.append(share * gain)
    noise_free = np.sum(shares, axis=0)
    noise_kind = str(rng.choice(NOISES))
    snr_db = float(rng.uniform(*SNR_RANGE_DB))
    v = _noise(rng, noise_kind, denominator, count)
    v *= noise_free.std() / v.std() * 10.0 ** (-snr_db / 20.0)
    point = np.zeros(1 + num_inputs)
    if rng.random() < 0.5:
        point[1:] = rng.uniform(-5.0, 5.0, size=num_inputs)
        gains = np.array([b.sum() for b in numerators]) / denominator.sum()
        point[0] = float(gains @ point[1:]) + rng.uniform(-5.0, 5.0)
    theta = np.concatenate([denominator[1:], *numerators])
    predicted = _predicted_error(theta, u, Structure(order, num_inputs, delays),
                                 float(v @ v) / count)
    names = parameter_names(order, num_inputs, False, delays)
    description = _describe(entropy, order, delays, poles, kinds, noise_kind, snr_db, count,
                            point)
    return RealisticCase(entropy, point[0] + noise_free + v, point[1:] + u, order, delays, theta,
                         names, point, poles, tuple(kinds), noise_kind, snr_db, noise_free,
                         predicted, description)


def _predicted_error(theta: np.ndarray, u: np.ndarray, structure: Structure,
                     noise_variance: float) -> float:
    r"""
    Return :math:`\sqrt{\mathrm{tr}\,\sigma_v^2(\psi^T\psi)^{-1}}/\|\theta\|` at the truth.

    The relative error an efficient OE estimate would have with white noise
    of the same variance (Ljung 1999, ch. 9); inf when the gradient is
    singular.
    """
    psi = oe_jacobian(theta, u, structure)
    try:
        covariance = noise_variance * np.linalg.inv(psi.T @ psi)
    except np.linalg.LinAlgError:
        return math.inf
    trace = float(np.trace(covariance))
    return math.sqrt(trace) / float(np.linalg.norm(theta)) if trace >= 0.0 else math.inf


def realistic_family(count: int, seed: int = 0) -> list[RealisticCase]:
    """
    Return ``count`` cases of the family ``seed``: ``realistic_case((seed, k))``, k < count.

    Families of different seeds share no case.

    Raises
    ------
    ValueError
        If ``count`` is negative or ``seed`` is not a non-negative integer.

    """
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
        raise ValueError(f'count must be an integer >= 0, got {count!r}')
    _entropy(seed)
    return [realistic_case((int(seed), k)) for k in range(int(count))]


def _entropy(seed: Any) -> tuple[int, ...]:
    values = [seed] if isinstance(seed, (int, np.integer)) else seed
    try:
        items = tuple(values)
    except TypeError:
        items = ()
    if not items or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0
                        for v in items):
        raise ValueError(f'seed must be an integer >= 0 or a sequence of them, got {seed!r}')
    return tuple(int(v) for v in items)


def _draw_poles(rng: np.random.Generator, order: int) -> np.ndarray:
    """Return n poles: maybe one complex pair, the rest real, slow or moderate."""
    poles: list[complex] = []
    if order >= 2 and rng.random() < 0.4:
        radius = rng.uniform(*COMPLEX_RADIUS)
        angle = rng.uniform(0.05, 0.45) * math.pi
        poles += [radius * complex(math.cos(angle), math.sin(angle)),
                  radius * complex(math.cos(angle), -math.sin(angle))]
    while len(poles) < order:
        if rng.random() < 0.5:
            # oversampled: 1 - radius log-uniform in [0.005, 0.1]
            radius = 1.0 - math.exp(rng.uniform(math.log(1.0 - SLOW_RADIUS[1]),
                                                math.log(1.0 - SLOW_RADIUS[0])))
        else:
            radius = rng.uniform(*MODERATE_RADIUS)
        poles.append(complex(radius, 0.0))
    return np.array(poles)


def _draw_numerators(rng: np.random.Generator, poles: np.ndarray,
                     num_inputs: int) -> list[np.ndarray]:
    """Return one numerator [b_1, ..., b_n] per input without a zero cancelling a pole."""
    order = poles.size
    for _ in range(1000):
        numerators = [rng.standard_normal(order) for _ in range(num_inputs)]
        # a pole is cancelled when every input's numerator has a zero near it
        near = np.ones(order, dtype=bool)
        for b in numerators:
            zeros = np.roots(b) if order > 1 else np.zeros(0)
            distance = (np.abs(poles[:, None] - zeros[None, :]).min(axis=1) if zeros.size
                        else np.full(order, np.inf))
            near &= distance < CANCELLATION_DISTANCE
        if not near.any() and all(abs(b[0]) > 0.05 for b in numerators):
            return numerators
    raise RuntimeError('no numerator without a cancellation in 1000 draws')


def _excitation(rng: np.random.Generator, count: int) -> tuple[str, np.ndarray]:
    """Return (kind, one input of unit standard deviation and zero mean)."""
    kind = str(rng.choice(EXCITATIONS))
    if kind == 'white':
        x = rng.standard_normal(count)
    elif kind == 'prbs':
        hold = int(rng.integers(2, 11))
        bits = max(4, math.ceil(math.log2(count / hold + 1)))
        state = rng.integers(0, 2, size=bits)
        state[rng.integers(bits)] = 1
        sequence = signal.max_len_seq(bits, state=state, length=-(-count // hold))[0]
        x = np.repeat(2.0 * sequence - 1.0, hold)[:count]
        kind = f'prbs/{hold}'
    elif kind == 'multisine':
        lines = int(rng.integers(10, 41))
        edge = rng.uniform(0.05, 0.5) * math.pi
        frequencies = rng.uniform(0.002 * math.pi, edge, size=lines)
        phases = rng.uniform(0.0, 2.0 * math.pi, size=lines)
        x = np.cos(np.outer(np.arange(count), frequencies) + phases).sum(axis=1)
    else:
        cutoff = rng.uniform(0.05, 0.4)
        b, a = signal.butter(2, cutoff)
        x = signal.lfilter(b, a, rng.standard_normal(count))
        kind = f'lowpass/{cutoff:.2f}'
    x = x - x.mean()
    return kind, x / x.std()


def _noise(rng: np.random.Generator, kind: str, denominator: np.ndarray,
           count: int) -> np.ndarray:
    """Return unscaled output noise v: white, ARMA(1, 1) or e / A (equation error)."""
    e = rng.standard_normal(count)
    if kind == 'white':
        return e
    if kind == 'coloured':
        pole = rng.uniform(0.5, 0.95)
        zero = rng.uniform(-0.5, 0.5)
        return signal.lfilter([1.0, zero], [1.0, -pole], e)
    return signal.lfilter([1.0], denominator, e)


def _describe(entropy: tuple[int, ...], order: int, delays: tuple[int, ...], poles: np.ndarray,
              kinds: Sequence[str], noise: str, snr_db: float, count: int,
              point: np.ndarray) -> str:
    def pole_text(p: complex) -> str:
        if abs(p.imag) < 1e-12:
            return f'{p.real:.3f}'
        return f'{abs(p):.3f}@{math.degrees(abs(np.angle(p))):.0f}deg'
    shown = [pole_text(p) for p in poles if p.imag >= 0.0]
    seed = ','.join(map(str, entropy))
    where = 'at an operating point' if np.any(point != 0.0) else 'around zero'
    return (f'case {seed}: n={order} r={len(delays)} d={list(delays)} '
            f'poles [{" ".join(shown)}] u {"+".join(kinds)}, {noise} noise, '
            f'SNR {snr_db:.0f} dB, N={count}, {where}')


__all__ = ['EXCITATIONS', 'NOISES', 'RealisticCase', 'realistic_case', 'realistic_family']
