"""The structure of a MISO model for the batch fits: order, inputs, dead times, feedthrough."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from bcid_ros.estimators.base import check_delays, check_int, parameter_names


@dataclasses.dataclass(frozen=True)
class Structure:
    """
    The structure of a MISO model: order, inputs, dead times, feedthrough.

    Parameters
    ----------
    order : int
        n >= 1, the degree of F (A) and of every B_i (and of C for ARMAX).
    num_inputs : int
        r >= 1.
    input_delay : int or sequence of int
        Dead time d_i >= 0 of each input (one integer for all).
    feedthrough : bool
        Whether ``b{i}_{d_i}`` (lag d_i) is a parameter.

    Raises
    ------
    ValueError
        Naming the argument that is out of range.

    """

    order: int
    num_inputs: int = 1
    input_delay: Any = 0
    feedthrough: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, 'order', check_int('order', self.order, 1))
        object.__setattr__(self, 'num_inputs', check_int('num_inputs', self.num_inputs, 1))
        object.__setattr__(self, 'input_delay', check_delays(self.input_delay, self.num_inputs))
        object.__setattr__(self, 'feedthrough', bool(self.feedthrough))

    @property
    def first_lag(self) -> int:
        """Return the first lag of every B_i after its dead time: 0 with feedthrough, else 1."""
        return 0 if self.feedthrough else 1

    @property
    def b_length(self) -> int:
        """Return the number of coefficients of one B_i."""
        return self.order + 1 - self.first_lag

    @property
    def num_parameters(self) -> int:
        """Return p = n + r (n or n + 1) of the OE and ARX models (ARMAX adds n)."""
        return self.order + self.num_inputs * self.b_length

    @property
    def span(self) -> int:
        """Return n + max(d_i), the oldest lag of the ARX regressor."""
        return self.order + max(self.input_delay)

    def parameter_names(self, model: str = 'oe') -> tuple[str, ...]:
        """Return the names of theta of ``model`` ('oe', 'arx' or 'armax')."""
        names = parameter_names(self.order, self.num_inputs, self.feedthrough, self.input_delay)
        if model == 'armax':
            names += tuple(f'c{k}' for k in range(1, self.order + 1))
        return names

    def split(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(F, b)``: F = [1, a1, ..., an] and the rows b_i, shape ``(r, b_length)``."""
        n = self.order
        denominator = np.concatenate([[1.0], theta[:n]])
        return denominator, theta[n:n + self.num_inputs * self.b_length].reshape(
            self.num_inputs, self.b_length)

    def numerator(self, b_row: np.ndarray, input_index: int) -> np.ndarray:
        """Return q^-d_i B_i as coefficients in ascending powers of q^-1."""
        lead = self.input_delay[input_index] + self.first_lag
        return np.concatenate([np.zeros(lead), b_row])


__all__ = ['Structure']
