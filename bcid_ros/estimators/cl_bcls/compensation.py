r"""
The compensated estimate of the online closed-loop BCLS, and when not to trust it.

Ikeda (2008), eqs. (58) and (59) per sample, written for stacked statistics
(:mod:`~bcid_ros.estimators.cl_bcls.moments`): with the loss J, the bias
direction C, :math:`B` and P of the running LS,

.. math::

    \hat\sigma_\nu^2 = \frac{2J}{B + \sqrt{B^2 - 4 (C^T P C) J}}, \qquad
    \hat\theta_{BC} = \hat\theta_{LS} - \hat\sigma_\nu^2 P C

(:meth:`Compensation.apply`), which with one prefilter and no forgetting is
eqs. (53), (56)-(59) (B = N beta, C'PC = N alpha). A redesign hands over its
result as a :class:`Redesign`. The estimate is not to be trusted when the
assumptions of the paper fail on the data (a stable true loop, A4; a moving
reference, A5) or the compensation is near a breakdown: the checks are
:func:`model_reasons` (at each redesign) and :func:`validity_reasons` (at each
sample); docs/cl_bcls.md, "Validity", has their reasons.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from bcid_ros.estimators.lti import closed_loop_polynomial, Controller
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients

#: ``no_excitation`` below this ratio of the varying power of the reconstructed
#: reference b_c(q) r = a_c(q) u + b_c(q) y to that of b_c(q) y (docs/cl_bcls.md, "Validity").
MIN_EXCITATION_RATIO = 0.02
#: ``runaway_compensation`` when the compensation moves a or b by more than this times
#: the LS estimate's own size (max(1, |a_LS|) for a, |b_LS| for b).
RUNAWAY_RATIO = 1.0
#: ``ill_conditioned_compensation`` when sqrt(beta^2 - 4 alpha gamma) / beta of eq. (58)
#: falls below this: sigma2 is then near the double root and infinitely sensitive.
MIN_DISCRIMINANT_RATIO = 0.05
#: :attr:`Compensation.discriminant_ratio` after B^2 - 4 C'PC J < 0 (``model_contradicted``).
CONTRADICTED = -1.0
#: ``ill_conditioned_information`` above this condition number of the information
#: matrix scaled to unit diagonal (scale-free).
MAX_CONDITION = 1e8


class Redesign(NamedTuple):
    """
    What a redesign hands to the estimator (the running LS it has taken over already).

    Attributes
    ----------
    flags : tuple of str
        The conditions to count, in the order they arose.
    failed : bool
        The redesign is dropped (the compensated estimate is held).
    iterations : int
        LS solves or fixed-point steps made.
    direction : numpy.ndarray or None
        The compensation's direction: C of the moments (``window`` 0) or c
        of the window's last iteration.
    beta : float or None
        beta of the window's last iteration (None: unchanged).
    terms : tuple or None
        (theta_LS, P C, C, B) to compensate with (``window`` 0), or None.
    estimate : tuple or None
        (theta_BC, sigma2, discriminant ratio) taken as they are (a
        window), or None.
    prefilter : numpy.ndarray or None
        The prefilter of the following samples (None: unchanged).
    regressor : numpy.ndarray or None
        The regressor to continue from (a window), or None.
    new_epoch : bool
        Whether the prefilter opens a new epoch of the moments.

    """

    flags: tuple[str, ...]
    failed: bool
    iterations: int = 0
    direction: np.ndarray | None = None
    beta: float | None = None
    terms: tuple[Any, ...] | None = None
    estimate: tuple[np.ndarray, float, float] | None = None
    prefilter: np.ndarray | None = None
    regressor: np.ndarray | None = None
    new_epoch: bool = False


class Compensation:
    """
    The compensated estimate theta_BC, sigma2 and their health, between and at redesigns.

    :attr:`direction` is None until a redesign succeeds (the estimate is
    then not compensated). The estimator's form of theta_BC (plant form with
    ``window`` 0, regression form with a window) is the one of its running LS.

    Parameters
    ----------
    num_parameters : int
        p = 2n.

    """

    def __init__(self, num_parameters: int) -> None:
        self.direction: np.ndarray | None = None
        self.beta = 1.0
        self.theta = np.zeros(num_parameters)
        self.sigma2 = 0.0
        self.holding = False
        self.discriminant_ratio = 1.0
        self.model_reasons: tuple[str, ...] = ()

    def apply(self, theta: np.ndarray, pc: np.ndarray, direction: np.ndarray,
              total_beta: float, loss: float) -> str:
        """
        Apply the generalised eqs. (58), (59) with C, B, P C and J given.

        Returns
        -------
        str
            ``''``, or the flag of why the last good estimate is kept:
            ``negative_variance_argument`` (B^2 - 4 C'PC J < 0) or
            ``nonfinite_estimate``.

        """
        quadratic = direction.dot(pc)
        discriminant = total_beta * total_beta - 4.0 * quadratic * loss
        if not discriminant >= 0.0:
            # (negative: the data contradict the model, see validity_reasons)
            self.discriminant_ratio = CONTRADICTED
            return 'negative_variance_argument'
        root = math.sqrt(discriminant)
        # sigma2 = 2 J / (B + sqrt(B^2 - 4 C'PC J))                          (58)
        sigma2 = 2.0 * loss / (total_beta + root)
        # theta_BC = theta_LS - sigma2 P C                                   (59)
        compensated = theta - sigma2 * pc
        if not math.isfinite(compensated.dot(compensated) + sigma2):
            return 'nonfinite_estimate'
        self.discriminant_ratio = root / total_beta
        self.theta = compensated
        self.sigma2 = sigma2
        return ''

    def hold(self) -> None:
        """Keep the estimate after a failed redesign (if there is one to keep)."""
        self.holding = self.direction is not None

    def take(self, direction: np.ndarray, beta: float | None,
             estimate: tuple[np.ndarray, float, float] | None) -> None:
        """Take a successful redesign's direction, and its beta and estimate if it has them."""
        self.direction = direction
        if beta is not None:
            self.beta = beta
        self.holding = False
        if estimate is not None:
            self.theta, self.sigma2, self.discriminant_ratio = estimate

    def reasons(self, excitation_ratio: float) -> tuple[str, ...]:
        """Return :func:`validity_reasons` for this estimate."""
        return validity_reasons(self.model_reasons, self.direction is not None, self.holding,
                                self.discriminant_ratio, excitation_ratio)

    # ------------------------------------------------------------ the state
    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the state (not copied)."""
        compensated = self.direction is not None
        arrays = {'theta_bc': self.theta,
                  'direction': self.direction if compensated else np.zeros(self.theta.shape)}
        scalars = {'beta': self.beta, 'sigma2': self.sigma2, 'compensated': compensated,
                   'holding': self.holding, 'model_reasons': list(self.model_reasons),
                   'discriminant_ratio': self.discriminant_ratio}
        return arrays, scalars

    def load(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over a state made by :meth:`state_items`."""
        self.theta = arrays['theta_bc']
        self.direction = arrays['direction'] if scalars['compensated'] else None
        self.beta = float(scalars['beta'])
        self.sigma2 = float(scalars['sigma2'])
        self.holding = bool(scalars['holding'])
        self.model_reasons = tuple(scalars['model_reasons'])
        self.discriminant_ratio = float(scalars['discriminant_ratio'])

    def snapshot(self) -> tuple[Any, ...]:
        """Return what a step may change (it rebinds, never changes in place)."""
        return (self.direction, self.beta, self.theta, self.sigma2, self.holding,
                self.discriminant_ratio, self.model_reasons)

    def restore(self, saved: tuple[Any, ...]) -> None:
        """Go back to a :meth:`snapshot`."""
        (self.direction, self.beta, self.theta, self.sigma2, self.holding,
         self.discriminant_ratio, self.model_reasons) = saved


def scaled_condition(matrix: np.ndarray) -> float:
    """Return the condition number of a symmetric matrix scaled to unit diagonal."""
    diagonal = np.diag(matrix)
    if not (diagonal > 0.0).all():
        return math.inf
    scale = 1.0 / np.sqrt(diagonal)
    return float(np.linalg.cond(matrix * np.outer(scale, scale)))


def model_reasons(theta: np.ndarray, theta_ls: np.ndarray, information_inverse: np.ndarray,
                  controller: Controller) -> tuple[str, ...]:
    """
    Return the checks of a compensated model that fail (after a redesign).

    Parameters
    ----------
    theta, theta_ls : numpy.ndarray, shape ``(2n,)``
        The compensated and the LS estimate, plant form [a | b].
    information_inverse : numpy.ndarray, shape ``(2n, 2n)``
        P of the running LS.
    controller : Controller
        The controller in the loop.

    Returns
    -------
    tuple of str
        ``unstable_closed_loop``, ``runaway_compensation``,
        ``ill_conditioned_information``: see :func:`validity_reasons`.

    """
    n = theta.shape[0] // 2
    reasons = []
    a_p = np.concatenate(([1.0], theta[:n]))
    if not is_stable(monic_coefficients(closed_loop_polynomial(a_p, theta[n:], controller))):
        reasons.append('unstable_closed_loop')
    step = theta - theta_ls
    if (np.linalg.norm(step[:n]) > RUNAWAY_RATIO * max(1.0, np.linalg.norm(theta_ls[:n]))
            or np.linalg.norm(step[n:]) > RUNAWAY_RATIO * np.linalg.norm(theta_ls[n:])):
        reasons.append('runaway_compensation')
    if scaled_condition(information_inverse) > MAX_CONDITION:
        reasons.append('ill_conditioned_information')
    return tuple(reasons)


def validity_reasons(model: tuple[str, ...], compensated: bool, holding: bool,
                     discriminant_ratio: float, excitation_ratio: float) -> tuple[str, ...]:
    r"""
    Return why the estimate is not valid, in this order.

    * ``not_compensated``: no redesign has succeeded since the last reset
      or controller change (``compensated`` is False);
    * the ``model`` reasons of the last redesign (:func:`model_reasons`):
      ``unstable_closed_loop``: the compensated model in the loop with the
      known controller is unstable, while the data are bounded;
      ``runaway_compensation``: the compensation moves a or b by more than
      :data:`RUNAWAY_RATIO` times the LS estimate's size;
      ``ill_conditioned_information``: the information matrix scaled to unit
      diagonal has a condition number above :data:`MAX_CONDITION`;
    * ``redesign_failed``: the last redesign failed and the compensated
      estimate is held (``holding``);
    * ``model_contradicted``: the last compensation found
      :math:`B^2 - 4 C^T P C J < 0` (``discriminant_ratio`` is
      ``CONTRADICTED``). Under the model the loss is
      :math:`J \approx B\sigma^2 - \sigma^4 C^T P C`, at most
      :math:`B^2 / (4 C^T P C)` for any noise variance: a larger loss is more
      equation error than white output noise can give, as from process
      noise or a nonlinearity in the loop (a motor's friction);
    * ``ill_conditioned_compensation``: eq. (58) is near its double root,
      :math:`\sqrt{\beta^2 - 4\alpha\gamma}/\beta` <
      :data:`MIN_DISCRIMINANT_RATIO` (sigma2 and theta then react without
      bound to the data);
    * ``no_excitation``: the reconstructed reference
      :math:`a_c(q) u + b_c(q) y = b_c(q) r` has a varying power below
      :data:`MIN_EXCITATION_RATIO` times that of :math:`b_c(q) y`
      (``excitation_ratio``): the loop runs on noise alone and the plant is
      not identifiable.
    """
    if not compensated:
        reasons = ['not_compensated']
    else:
        reasons = list(model)
        if holding:
            reasons.append('redesign_failed')
        if discriminant_ratio == CONTRADICTED:
            reasons.append('model_contradicted')
        elif discriminant_ratio < MIN_DISCRIMINANT_RATIO:
            reasons.append('ill_conditioned_compensation')
    if excitation_ratio < MIN_EXCITATION_RATIO:
        reasons.append('no_excitation')
    return tuple(reasons)
