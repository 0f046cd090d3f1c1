r"""
The prefiltered LS per sample: the prefilters, the regressor and the recursive LS.

Ikeda (2008), eqs. (10) and (14) per sample, with the prefilter f in use:

.. math::

    y_f[k] = \frac{q^n}{f(q)} y[k], \quad u_f[k] = \frac{q^n}{f(q)} u[k], \qquad
    \varphi[k] = [y_f[k-1] \dots y_f[k-n], u_f[k-1] \dots u_f[k-n]]^T,

(:class:`PrefilterBank`), and the LS of eqs. (16), (17) with the residual
sum of squares of eq. (45) kept recursively between redesigns
(:class:`RunningLs`): in the regression form :math:`y = \varphi^T\theta`
of eq. (13) with a window, in the form :math:`y_f = \psi^T[a \mid b]`,
:math:`\psi = D\varphi`, with all data since the controller change
(docs/cl_bcls.md). Both check an update before they commit it
(:func:`update_is_safe`). The LS starts from :math:`P(0) = p_0 S^{-2}` in
the units of :class:`SignalScales`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.lti import controller_canonical
from bcid_ros.estimators.recursion import (Forgetting, ls_step, repair_covariance,
                                           VARIANCE_FLOOR)
from bcid_ros.estimators.transaction import all_finite

#: The all-data memory forgets without anti-windup: its P is bounded by the redesigns.
FORGETTING = Forgetting(math.inf)
#: Squared 2-norm below which an update cannot overflow (see update_is_safe).
SAFE_SQUARE = 2.0 ** 1022
#: What a memory's row step did: the row is in; the gate refused it; its update may not be
#: finite (nothing changed); s was not positive (P lost definiteness and needs a repair).
STEPPED, REFUSED, UNSAFE, REPAIR = 'stepped', 'refused', 'unsafe', 'repair'


def update_is_safe(theta: np.ndarray, direction: np.ndarray, ratio: float) -> bool:
    """
    Return True if theta + ratio * direction is surely finite (False: it may not be).

    Entries below 2^511 in size sum to less than 2^512: one test of two dot
    products for the usual case, conservative (NaN and overflow give False).
    """
    return (ratio * ratio * direction.dot(direction) < SAFE_SQUARE
            and theta.dot(theta) < SAFE_SQUARE)


class SignalScales:
    r"""
    The units: :math:`S = \mathrm{diag}(s_y I_n, s_u I_n)`, fixed at the first LS step.

    Per signal the smallest power of two at or above its largest magnitude
    before the first LS step (fixed then, until a reset or controller
    change): ``p0`` of :math:`P(0) = p_0 S^{-2}` is the prior variance for
    signals of unit size, the gate's variance floor scales with :math:`s_y`,
    and a redesign measures its steps on :math:`[a \mid b\,s_u/s_y]`.

    Parameters
    ----------
    order : int
        n.
    initial_covariance : float
        p0.

    """

    def __init__(self, order: int, initial_covariance: float) -> None:
        self.order, self.initial_covariance = order, initial_covariance
        #: [s_y, s_u], 0 until fixed
        self.scales = np.zeros(2)
        self.peaks = np.zeros(2)
        self.variance_floor = VARIANCE_FLOOR ** 2

    def watch(self, y: float, u0: float, fix: bool) -> bool:
        """Keep the peaks of |y|, |u|; fix the scales if ``fix`` (return whether they are)."""
        peaks = self.peaks = np.array((max(self.peaks[0], abs(y)),
                                       max(self.peaks[1], abs(u0))))
        if not fix:
            return False
        self.scales = rules.powers_of_two_at_least(peaks)
        self.variance_floor = (VARIANCE_FLOOR * self.scales[0]) ** 2
        return True

    def initial_p(self) -> np.ndarray:
        """Return P(0) = p0 S^-2, S = diag(s_y I_n, s_u I_n) (p0 I before the scales)."""
        scales = self.scales if self.scales[0] > 0.0 else np.ones(2)
        return np.diag(self.initial_covariance / np.repeat(scales, self.order) ** 2)

    def unit_weights(self) -> np.ndarray:
        """Return the factors that make [a | b] unit-free: 1 for a, s_u / s_y for b."""
        scales = self.scales if self.scales[0] > 0.0 else np.ones(2)
        return np.repeat([1.0, scales[1] / scales[0]], self.order)

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the state (not copied)."""
        return {'scales': self.scales, 'peaks': self.peaks}, {}

    def load(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over a state made by :meth:`state_items` (or one from before the scales)."""
        self.scales = arrays.get('scales', np.zeros(2))
        self.peaks = arrays.get('peaks', np.zeros(2))
        self.variance_floor = (VARIANCE_FLOOR * (self.scales[0] or 1.0)) ** 2

    def snapshot(self) -> tuple:
        """Return what a step may change (it rebinds, never changes in place)."""
        return self.scales, self.peaks, self.variance_floor

    def restore(self, saved: tuple) -> None:
        """Go back to a :meth:`snapshot`."""
        self.scales, self.peaks, self.variance_floor = saved


class PrefilterBank:
    """
    The prefilters q^n/f(q) of y and u in state-space form and the regressor phi (eqs. 10, 14).

    The filters keep their state across a change of f. :attr:`lags` counts
    the samples since the last restart up to n: phi holds n lags from then on.

    Parameters
    ----------
    prefilter : numpy.ndarray, shape ``(n + 1,)``
        f(q) = [1, f_1, ..., f_n].

    """

    def __init__(self, prefilter: np.ndarray) -> None:
        self.order = prefilter.shape[0] - 1
        self.set_prefilter(prefilter)
        self.restart()

    def set_prefilter(self, prefilter: np.ndarray) -> None:
        """Filter the following samples with f(q) = ``prefilter``."""
        n = self.order
        self.prefilter = np.array(prefilter, dtype=float)
        f_matrix, _ = controller_canonical(self.prefilter)
        shift = np.zeros((2 * n, 2 * n))
        shift[:n, :n] = f_matrix
        shift[n:, n:] = f_matrix
        self.shift = shift

    def restart(self) -> None:
        """Empty the filters (after a gap or a controller change)."""
        self.phi = np.zeros(2 * self.order)
        self.lags = 0

    def take_regressor(self, phi: np.ndarray) -> None:
        """Continue from a full regressor (the next one of a batch LS)."""
        self.phi = phi.copy()
        self.lags = self.order

    def advance(self, y: float, u0: float) -> None:
        """Filter one sample into phi."""
        # phi[k+1] = blockdiag(F, F) phi[k] + [g y[k]; g u[k]]        (10), (14)
        phi = self.shift.dot(self.phi)
        phi[0] += y
        phi[self.order] += u0
        self.phi = phi

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the state (not copied)."""
        return {'prefilter': self.prefilter, 'phi': self.phi}, {'lags': self.lags}

    def load(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over a state made by :meth:`state_items`."""
        self.set_prefilter(arrays['prefilter'])
        self.phi = arrays['phi']
        self.lags = int(scalars['lags'])

    def snapshot(self) -> tuple:
        """Return what a step may change (it rebinds, never changes in place)."""
        return self.prefilter, self.shift, self.phi, self.lags

    def restore(self, saved: tuple) -> None:
        """Go back to a :meth:`snapshot`."""
        self.prefilter, self.shift, self.phi, self.lags = saved


class RunningLs:
    r"""
    The running LS: theta_LS, P = M^-1, the loss J and the row count N (eqs. 16, 17, 45).

    With all data since the change the rows are weighted by the forgetting
    factor and J is the weighted residual sum of squares
    (:meth:`forgetting_step`); with a window, the plain RLS of the shared
    step (:meth:`step`). Each memory computes the
    a-priori part in its own form. A redesign replaces the four
    (:meth:`restart_from`).

    Parameters
    ----------
    initial_p : numpy.ndarray, shape ``(2n, 2n)``
        P(0); theta_LS(0) = 0.

    """

    def __init__(self, initial_p: np.ndarray) -> None:
        self.theta = np.zeros(initial_p.shape[0])
        self.p = initial_p
        self.loss = 0.0
        self.count = 0.0

    def restart_from(self, theta: np.ndarray, p: np.ndarray, loss: float, count: float) -> None:
        """Continue from a solved LS (a redesign's)."""
        self.theta, self.p, self.loss, self.count = theta, p, loss, count

    # --------------------------------------------- all data: psi rows, forgetting
    def forgetting_step(self, g: np.ndarray, s: float, e: float, lam: float) -> bool:
        """Do the step of theta, P and J; False (and nothing changed) if it may not be finite."""
        if not self._ls_step(g, s, e):
            return False
        FORGETTING.propagate_one(self.p, lam)
        # J = lam J + lam e^2 / s (weighted LS loss)
        self.loss = lam * (self.loss + e * e / s)
        return True

    # --------------------------------------------------- a window: phi rows, lambda 1
    def step(self, g: np.ndarray, s: float, e: float) -> bool:
        """Do the RLS step and count the row; False (and nothing changed) if not finite."""
        if not self._ls_step(g, s, e):
            return False
        # J += e^2 / s ; N += 1
        self.loss += e * e / s
        self.count += 1.0
        return True

    def _ls_step(self, g: np.ndarray, s: float, e: float) -> bool:
        """Do the shared RLS step of theta and P (``g`` is overwritten); False if not finite."""
        theta = self.theta
        safe = update_is_safe(theta, g, e / s)
        if not safe:  # (rare) keep what the step changes, to check it after
            saved = theta.copy(), self.p.copy()
        # theta_LS += g e / s ; P -= g g' / s
        self.p = ls_step(theta, self.p, g, s, e)
        if not safe and not all_finite(theta):
            theta[:], self.p = saved
            return False
        return True

    # ----------------------------------------------------------------- both
    def cut(self, keep: float) -> None:
        """Keep the share ``keep`` of the memory (one extra forgetting step)."""
        self.p *= 1.0 / keep
        self.loss *= keep
        self.count *= keep

    def repair(self, fallback: np.ndarray) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix."""
        self.p = repair_covariance(self.p, fallback)

    def snapshot(self) -> tuple:
        """Return what a step may change: theta and P (changed in place too), J and N."""
        return self.theta, self.theta.copy(), self.p, self.p.copy(), self.loss, self.count

    def restore(self, saved: tuple) -> None:
        """Go back to a :meth:`snapshot`."""
        self.theta, theta, self.p, p, self.loss, self.count = saved
        self.theta[:] = theta
        self.p[:] = p
