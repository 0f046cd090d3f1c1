r"""
The controller in the loop: one sample at a time, saturation, anti-windup, switching.

**Anti-windup (observer form).** A controller :math:`R u = S e` with R
monic of degree :math:`n_r` runs as

.. math::

    A_o v = (A_o - R)\,u + S e, \qquad u = \mathrm{sat}(v)
    = \min(\max(v, -u_{max}), u_{max}),                              \qquad (AW)

with the observer polynomial :math:`A_o = (q - p_o)^{n_r}`, ``antiwindup_pole``
:math:`p_o \in [0, 1)` (Astrom and Wittenmark, Computer-Controlled Systems,
ch. 9). Unsaturated, u = v and (AW) is R u = S e. Saturated, the controller
state moves with the stable :math:`A_o` driven by the bounded u and e, so it
cannot wind up, whatever R (an integrator (q - 1), an unstable R). With the
default :math:`p_o = 0`, :math:`A_o = q^{n_r}` and (AW) reads
:math:`v_t = \sum_k (-r_k) u_{t-k} + \sum_k s_k e_{t-k}` from the applied
inputs: for a PI, the velocity form :math:`v_t = u_{t-1} + s_0 e_t + s_1 e_{t-1}`.

**Timing.** With ``delayed=True`` (the input computed on receipt of
:math:`y_t` is applied at t + 1), C must be strictly proper and
:meth:`ControllerRuntime.step` given :math:`e_t` returns :math:`u_{t+1}`;
otherwise it returns :math:`u_t`. Either way, in the plant's sample index,
:math:`u = C(q) e`.

**Switching.** The runtime keeps the histories of e and of the applied u.
At a switch the new controller takes them over and its past v are set to
the applied u: it continues as if it had produced the inputs actually
applied (for the PI above, exactly bumpless).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from bcid_ros.control.design import Controller


class ControllerRuntime:
    r"""
    Run a feedback C(q) = S/R sample by sample, saturated, with anti-windup (AW).

    Parameters
    ----------
    controller : Controller
        The first controller.
    input_limit : float
        :math:`u_{max} > 0`: the input stays in :math:`[-u_{max}, u_{max}]`.
    antiwindup_pole : float
        :math:`p_o \in [0, 1)` of :math:`A_o = (q - p_o)^{n_r}`.
    delayed : bool
        The input computed from :math:`e_t` is applied at t + 1 (C must be
        strictly proper).

    Raises
    ------
    ValueError
        If ``input_limit`` is not a positive finite number, ``antiwindup_pole``
        is outside [0, 1), or the controller is not strictly proper with
        ``delayed``.

    """

    def __init__(self, controller: Controller, *, input_limit: float,
                 antiwindup_pole: float = 0.0, delayed: bool = True) -> None:
        if not (math.isfinite(input_limit) and input_limit > 0.0):
            raise ValueError(f'parameter \'input_limit\' must be a number in (0, inf), got '
                             f'{input_limit!r}')
        if not 0.0 <= antiwindup_pole < 1.0:
            raise ValueError(f'parameter \'antiwindup_pole\' must be a number in [0, 1), got '
                             f'{antiwindup_pole!r}')
        self.input_limit = float(input_limit)
        self.antiwindup_pole = float(antiwindup_pole)
        self.delayed = bool(delayed)
        self.saturated_samples = 0
        self._errors: collections.deque[float] = collections.deque([0.0], maxlen=1)
        self._inputs: collections.deque[float] = collections.deque([0.0], maxlen=1)
        self._raw: collections.deque[float] = collections.deque([0.0], maxlen=1)
        self.controller = controller
        self.switch(controller)

    @property
    def last_input(self) -> float:
        """Return the last input returned (0 before the first step)."""
        return self._inputs[0]

    def switch(self, controller: Controller) -> None:
        """
        Put ``controller`` in the loop, keeping the signal histories (bumpless).

        Raises
        ------
        ValueError
            If ``delayed`` and the controller is not strictly proper.

        """
        if self.delayed and not controller.strictly_proper:
            raise ValueError('the controller must be strictly proper (numerator degree < '
                             'denominator degree) when the input is applied one sample late')
        degree = controller.denominator.size - 1
        self._r = controller.denominator[1:]
        # S padded to n_r + 1 coefficients: s_0 multiplies the newest error
        self._s = np.concatenate([np.zeros(degree + 1 - controller.numerator.size),
                                  controller.numerator])
        # A_o = (q - p_o)^{n_r}, its coefficients below the leading 1
        self._ao = np.atleast_1d(np.real(np.poly(np.full(degree, self.antiwindup_pole))))[1:]
        keep = degree + 1
        self._errors = self._resized(self._errors, keep)
        self._inputs = self._resized(self._inputs, keep)
        self._raw = collections.deque(self._inputs, maxlen=keep)
        self.controller = controller

    @staticmethod
    def _resized(history: collections.deque[float], keep: int) -> collections.deque[float]:
        # the oldest value stands for the times before the history began
        values = list(history) + [history[-1]] * max(0, keep - len(history))
        return collections.deque(values[:keep], maxlen=keep)

    def step(self, error: float) -> float:
        """
        Take the error :math:`e_t = r'_t - y_t` and return the next input.

        Returns :math:`u_{t+1}` with ``delayed``, else :math:`u_t`; always
        finite and within the limit. A non-finite error is the caller's to
        refuse (:class:`~bcid_ros.control.loop.AdaptiveController` does).

        """
        self._errors.appendleft(float(error))
        shift = 1 if self.delayed else 0
        degree = self._r.size
        errors = np.fromiter(self._errors, float, len(self._errors))
        inputs = np.fromiter(self._inputs, float, len(self._inputs))
        raw = np.fromiter(self._raw, float, len(self._raw))
        # A_o v = (A_o - R) u + S e, solved for the newest v (eq. AW)
        value = float(np.dot(self._s[shift:], errors[:degree + 1 - shift]))
        if degree:
            value += float(np.dot(self._ao - self._r, inputs[:degree])
                           - np.dot(self._ao, raw[:degree]))
        if not math.isfinite(value):
            # cannot happen with finite errors and a stable A_o; hold the input if it does
            value = self.last_input
        applied = min(max(value, -self.input_limit), self.input_limit)
        if applied != value:
            self.saturated_samples += 1
        self._raw.appendleft(value)
        self._inputs.appendleft(applied)
        return applied


__all__ = ['ControllerRuntime']
