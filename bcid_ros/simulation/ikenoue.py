"""
The errors-in-variables examples of Ikenoue, Kanae, Yang and Wada (2008), section 5.

Both sections simulate A(q^-1) y_t = B(q^-1) u_t (eq. 1) and publish the
noisy measurements z_t = y_t + e_t and w_t = u_t + d_t (eq. 4) as the
sample ``(y, u) = (z_t, w_t)``.

* **Section 5.1** (eq. 76): B/A = (1.0 q^-1 + 0.5 q^-2)/(1 - 1.5 q^-1 + 0.7 q^-2),
  u_t = 0.9 u_{t-1} + eps_t (var 1), colored output noise
  e_t = -0.8 e_{t-1} + w_e,t + 0.3 w_e,t-1 (var 1.8898) and colored input
  noise d_t = 0.6 d_{t-1} + w_d,t + 0.2 w_d,t-1 (var 0.0263): 20 dB on both.
* **Section 5.2** (eq. 78): B/A = (0.169901 q^-1 + 0.143831 q^-2)/
  (1 - 1.575157 q^-1 + 0.606531 q^-2), u_t = eps_t - 0.3 eps_{t-1} +
  0.5 eps_{t-2} - 0.7 eps_{t-3} + 0.9 eps_{t-4} (var(eps) = 0.3788), white
  input noise with sigma_d^2 = 0.1 and colored output noise
  e_t = e_{t-1} - 0.4 e_{t-2} + w_e,t - 0.87 w_e,t-1 + 0.57 w_e,t-2 (var
  0.2264), the reading of the garbled printed formula that gives the stated
  10 dB (docs/papers.md).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

from bcid_ros.estimators.base import check_int, parameter_names
from bcid_ros.simulation.base import SampleStream, Scenario, StreamingFilter, Truth

#: Per section: plant (B, A), input shaping filter (num, den, var(eps)),
#: output noise (num, den, var) and input noise (num, den, var), all in
#: ascending powers of q^-1.
SECTIONS = {
    '5.1': {
        'name': 'ikenoue_colored',
        'plant': ((0.0, 1.0, 0.5), (1.0, -1.5, 0.7)),
        'input': ((1.0,), (1.0, -0.9), 1.0),
        'output_noise': ((1.0, 0.3), (1.0, 0.8), 1.8898),
        'input_noise': ((1.0, 0.2), (1.0, -0.6), 0.0263),
    },
    '5.2': {
        'name': 'ikenoue_white_input',
        'plant': ((0.0, 0.169901, 0.143831), (1.0, -1.575157, 0.606531)),
        'input': ((1.0, -0.3, 0.5, -0.7, 0.9), (1.0,),
                  1.0 / (1 + 0.3 ** 2 + 0.5 ** 2 + 0.7 ** 2 + 0.9 ** 2)),
        'output_noise': ((1.0, -0.87, 0.57), (1.0, -1.0, 0.4), 0.2264),
        'input_noise': ((1.0,), (1.0,), 0.1),
    },
}
#: Number of published input-noise covariances r_dd0..r_dd{k-1} in section 5.1
#: by default: enough for an IV lag l <= 8 with n = 2 (the estimator publishes n + l).
DEFAULT_COVARIANCE_LAGS = 10


def autocovariance(numerator, denominator, variance: float, lags: int) -> np.ndarray:
    """
    Return r(0..lags-1) of x = (numerator/denominator)(q^-1) w, w white with ``variance``.

    The filter must be stable; the impulse response is summed until it has
    decayed below 1e-300 of its peak (exact to rounding).

    Parameters
    ----------
    numerator, denominator : sequence of float
        Ascending powers of q^-1.
    variance : float
        Variance of the white driving noise.
    lags : int
        Number of lags returned.

    Returns
    -------
    numpy.ndarray, shape ``(lags,)``

    """
    poles = np.roots(np.asarray(denominator, dtype=float)) if len(denominator) > 1 else []
    radius = max((abs(p) for p in poles), default=0.0)
    if radius >= 1.0:
        raise ValueError(f'denominator {tuple(denominator)} is not stable')
    length = lags + len(numerator) + (int(math.ceil(-700.0 / math.log(radius)))
                                      if radius > 0 else 0)
    impulse = np.zeros(length)
    impulse[0] = 1.0
    h = signal.lfilter(numerator, denominator, impulse)
    return variance * np.array([h[:length - k].dot(h[k:]) for k in range(lags)])


def _variance(*filters) -> float:
    """Return the variance of a cascade of (num, den) filters driven by unit white noise."""
    num, den = np.array([1.0]), np.array([1.0])
    for b, a in filters:
        num, den = np.convolve(num, b), np.convolve(den, a)
    return float(autocovariance(num, den, 1.0, 1)[0])


class IkenoueEiv(Scenario):
    """
    Ikenoue et al. (2008) section 5.1 (colored input noise) or 5.2 (white input noise).

    Parameters
    ----------
    section : str
        ``'5.1'`` or ``'5.2'``.
    input_snr_db, output_snr_db : float or None
        Override the input (u/d) or output (y/e) signal-to-noise ratio in dB
        by scaling the variance of the driving white noise; None keeps the
        paper's values (20/20 dB in 5.1, 10/10 dB in 5.2).
    covariance_lags : int
        How many input-noise covariances r_dd(0), r_dd(1), ... :meth:`truth`
        publishes in section 5.1 (the estimator publishes n + l of them).

    Raises
    ------
    ValueError
        If ``section`` is unknown or a setting is out of range.

    """

    name = 'ikenoue_colored'
    order = 2
    num_inputs = 1

    def __init__(self, *, section: str = '5.1', input_snr_db: float | None = None,
                 output_snr_db: float | None = None,
                 covariance_lags: int = DEFAULT_COVARIANCE_LAGS) -> None:
        section = str(section)
        if section not in SECTIONS:
            raise ValueError(f"section must be '5.1' or '5.2', got {section!r}")
        self.section = section
        spec = SECTIONS[section]
        self.name = spec['name']
        self.covariance_lags = check_int('covariance_lags', covariance_lags, 1)
        self.plant = spec['plant']
        self.input = spec['input']
        self.output_noise = spec['output_noise']
        self.input_noise = spec['input_noise']
        input_power = self.input[2] * _variance(self.input[:2])
        output_power = self.input[2] * _variance(self.input[:2], self.plant)
        noise_in, noise_out = self.input_noise[2], self.output_noise[2]
        gain_in = _variance(self.input_noise[:2])
        gain_out = _variance(self.output_noise[:2])
        for label, value in (('input_snr_db', input_snr_db), ('output_snr_db', output_snr_db)):
            if value is not None and not (np.isfinite(value) and -60 <= value <= 200):
                raise ValueError(f'{label} must be in [-60, 200] dB or None, got {value!r}')
        if input_snr_db is not None:
            noise_in = input_power / gain_in / 10 ** (input_snr_db / 10)
        if output_snr_db is not None:
            noise_out = output_power / gain_out / 10 ** (output_snr_db / 10)
        #: Variances of the white noises driving d and e.
        self.input_noise_variance = float(noise_in)
        self.output_noise_variance = float(noise_out)
        #: The resulting SNRs, 10 log10(E[u^2]/E[d^2]) and 10 log10(E[y^2]/E[e^2]).
        self.input_snr_db = 10 * math.log10(input_power / (noise_in * gain_in))
        self.output_snr_db = 10 * math.log10(output_power / (noise_out * gain_out))

    def truth(self) -> Truth:
        """
        Return theta = [a1 a2 b1_1 b1_2] and the input-noise figures.

        Section 5.1 publishes r_dd0 ... r_dd{k-1} (k = ``covariance_lags``),
        computed exactly from the input-noise model; section 5.2 publishes
        ``sigma2_d``, the variance of the white input noise.
        """
        b, a = self.plant
        theta = np.array([a[1], a[2], b[1], b[2]])
        names = parameter_names(self.order, 1, False)
        if self.section == '5.2':
            return Truth(names, theta, ('sigma2_d',), np.array([self.input_noise_variance]))
        r_dd = autocovariance(*self.input_noise[:2], self.input_noise_variance,
                              self.covariance_lags)
        return Truth(names, theta, tuple(f'r_dd{k}' for k in range(self.covariance_lags)),
                     r_dd)

    def stream(self, rng: np.random.Generator) -> SampleStream:
        """Return a stream of (z_t, [w_t]) samples drawing from ``rng``."""
        return _IkenoueStream(self, rng)


class _IkenoueStream(SampleStream):
    def __init__(self, scenario: IkenoueEiv, rng: np.random.Generator) -> None:
        self.rng = rng
        self.input_std = math.sqrt(scenario.input[2])
        self.output_noise_std = math.sqrt(scenario.output_noise_variance)
        self.input_noise_std = math.sqrt(scenario.input_noise_variance)
        self.shaping = StreamingFilter(*scenario.input[:2])
        self.plant = StreamingFilter(*scenario.plant)
        self.output_noise = StreamingFilter(*scenario.output_noise[:2])
        self.input_noise = StreamingFilter(*scenario.input_noise[:2])

    def take(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        # One (k, 3) draw per block keeps the samples independent of blocking:
        # columns eps (input), omega_e (output noise), omega_d (input noise).
        draws = self.rng.standard_normal((count, 3))
        u = self.shaping(self.input_std * draws[:, 0])
        y = self.plant(u)
        z = y + self.output_noise(self.output_noise_std * draws[:, 1])
        w = u + self.input_noise(self.input_noise_std * draws[:, 2])
        return z, w.reshape(-1, 1)
