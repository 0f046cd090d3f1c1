r"""
The excitation of a closed loop, measured without the reference (Ikeda 2008, eqs. 5, 6).

The plant is identifiable in the loop only if the reference r moves (A5):
on noise alone the loop's signals are filtered noise, and the compensation
has nothing to separate. r is not measured, but with the known controller
u = (b_c/a_c)(r - y) it is reconstructed exactly, up to the filter b_c(q):
a_c(q) u + b_c(q) y = b_c(q) r. :class:`ExcitationMeter` keeps the power of
that signal against the power of b_c(q) y; ``no_excitation`` in the
estimator's validity is their ratio below a threshold (docs/cl_bcls.md,
"Validity").
"""

from __future__ import annotations

import math
import operator

import numpy as np

from bcid_ros.estimators.lti import Controller


class ExcitationMeter:
    r"""
    Power of the reference reconstructed from y, u and the known controller.

    With :math:`u = (b_c/a_c)(r - y)` (negative-feedback form),
    :math:`w = a_c(q) u + b_c(q) y = b_c(q) r` exactly: the noise cancels.
    The meter keeps the weighted sums of w, w^2, v = b_c(q) y and v^2 over
    the samples since the last restart whose m lags are all present. It takes
    each sample one sample late (``pending``): an outlier in u shows only in
    the next prediction error, and a refused sample restarts the meter before
    the outlier has entered it.
    """

    def __init__(self, controller: Controller) -> None:
        # coefficients on [x[k], x[k-1], ..., x[k-m]] (q^-m times the polynomials); the
        # meter works on Python floats: at these sizes numpy calls cost more than the sums
        self.a_c = controller.denominator.tolist()
        self.b_c = controller.feedback_numerator.tolist()
        size = len(self.a_c)
        self.y = [0.0] * size
        self.u = [0.0] * size
        self.lags = 0
        self.sums = [0.0] * 5  # weight, sum w, sum w^2, sum v, sum v^2 (changed in place)
        self.pending = [0.0] * 3  # y, u, 1 if held

    def restart(self) -> None:
        """Forget the lags and the pending sample (after a gap), keep the sums."""
        size = len(self.a_c)
        self.y = [0.0] * size
        self.u = [0.0] * size
        self.lags = 0
        self.pending[2] = 0.0

    def update(self, y: float, u: float, forgetting: float) -> None:
        """Hold this sample and take the one held before it."""
        pending = self.pending
        if not pending[2]:
            self.pending = [y, u, 1.0]
            return
        ys, us = self.y, self.u
        ys.pop()
        ys.insert(0, pending[0])
        us.pop()
        us.insert(0, pending[1])
        self.pending = [y, u, 1.0]
        if self.lags < len(ys) - 1:
            self.lags += 1
            return
        v = sum(map(operator.mul, self.b_c, ys))
        # w = a_c(q) u + b_c(q) y = b_c(q) r
        w = sum(map(operator.mul, self.a_c, us)) + v
        sums = self.sums
        if forgetting != 1.0:
            sums[:] = [value * forgetting for value in sums]
        sums[0] += 1.0
        sums[1] += w
        sums[2] += w * w
        sums[3] += v
        sums[4] += v * v

    def ratio(self) -> float:
        """Return var(w) / var(v) over the samples so far (0 if none, inf if v is constant)."""
        weight, w1, w2, v1, v2 = self.sums
        if weight <= 0.0:
            return 0.0
        var_w = max(w2 / weight - (w1 / weight) ** 2, 0.0)
        var_v = max(v2 / weight - (v1 / weight) ** 2, 0.0)
        if var_v <= 0.0:
            return math.inf if var_w > 0.0 else 0.0
        return var_w / var_v

    def state(self) -> np.ndarray:
        """Return the state as one flat array."""
        return np.array(self.y + self.u + self.sums + self.pending + [self.lags], dtype=float)

    def load(self, flat: np.ndarray) -> None:
        """Load a state made by :meth:`state` (same controller order)."""
        size = len(self.a_c)
        values = np.asarray(flat, dtype=float).tolist()
        self.y = values[:size]
        self.u = values[size:2 * size]
        self.sums = values[2 * size:2 * size + 5]
        # a state saved before the pending sample existed has none
        self.pending = (values[2 * size + 5:2 * size + 8]
                        if len(values) == 2 * size + 9 else [0.0] * 3)
        self.lags = int(values[-1])
