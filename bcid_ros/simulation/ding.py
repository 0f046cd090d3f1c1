"""
The MISO output-error example of Ding, Chen and Qiu (2006), section III.

y(t) = [B_1(z) u_1(t) + B_2(z) u_2(t)] / alpha(z) + v(t), with
alpha(z) = 1 - 0.84 z^-1 + 0.16 z^-2, B_1(z) = 0.12 z^-1 + 0.324 z^-2 and
B_2(z) = 0.25 z^-1 + 0.186 z^-2. u_1, u_2 are white with unit variance and
v is white with variance 0.1^2. The non-stationary variant multiplies u_1,
u_2 and v by (1 + t^0.4), t = 1, 2, ...
"""

from __future__ import annotations

import numpy as np

from bcid_ros.estimators.base import parameter_names
from bcid_ros.simulation.base import SampleStream, Scenario, StreamingFilter, Truth

ALPHA = (1.0, -0.84, 0.16)
B1 = (0.0, 0.12, 0.324)
B2 = (0.0, 0.25, 0.186)
NOISE_STD = 0.1


class DingMiso(Scenario):
    """
    Ding et al. (2006) section III, stationary (Table I) or not (Table II).

    Parameters
    ----------
    nonstationary : bool
        Scale inputs and noise by (1 + t^0.4) as in Table II.

    """

    name = 'ding_miso'
    order = 2
    num_inputs = 2

    def __init__(self, *, nonstationary: bool = False) -> None:
        self.nonstationary = nonstationary
        if nonstationary:
            self.name = 'ding_miso_nonstationary'

    def truth(self) -> Truth:
        """Return theta = [a1 a2 b1_1 b1_2 b2_1 b2_2] and sigma2 = 0.01."""
        theta = np.array([ALPHA[1], ALPHA[2], B1[1], B1[2], B2[1], B2[2]])
        return Truth(parameter_names(2, 2, False), theta, ('sigma2',),
                     np.array([NOISE_STD ** 2]))

    def stream(self, rng: np.random.Generator) -> SampleStream:
        """Return a stream of (y, [u1, u2]) samples drawing from ``rng``."""
        return _DingStream(rng, self.nonstationary)


class _DingStream(SampleStream):
    def __init__(self, rng: np.random.Generator, nonstationary: bool) -> None:
        self.rng = rng
        self.nonstationary = nonstationary
        self.t = 0
        self.plant1 = StreamingFilter(B1, ALPHA)
        self.plant2 = StreamingFilter(B2, ALPHA)

    def take(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        # One (k, 3) draw per block keeps the samples independent of blocking.
        draws = self.rng.standard_normal((count, 3))
        u = draws[:, :2]
        v = NOISE_STD * draws[:, 2]
        if self.nonstationary:
            scale = 1.0 + np.arange(self.t + 1, self.t + count + 1) ** 0.4
            u = u * scale[:, None]
            v = v * scale
        self.t += count
        y = self.plant1(u[:, 0]) + self.plant2(u[:, 1]) + v
        return y, np.ascontiguousarray(u)
