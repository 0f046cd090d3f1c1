"""
BCRLS: bias-compensated recursive least squares for MISO output-error systems.

Ding, Chen and Qiu (2006), "Bias compensation based recursive least-squares
identification algorithm for MISO systems", eqs. (46)-(55), with the matrix
Lambda that the printed eqs. (26)/(46) drop (docs/papers.md) and an exact
extension to exponential forgetting (derived in docs/estimators.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bcid_ros.estimators.rls import load_blas, ls_batch, Rls

#: Below this, the denominator 1 + theta_c' Lambda theta_LS of eq. (51) is
#: treated as broken down. At the fixed point it is 1 + sum(a_c * a_LS), which
#: is about 1 + |a|^2 > 1 because LS shrinks a towards zero without flipping it.
DENOMINATOR_MIN = 0.1
#: A compensated estimate farther than this (relative) from theta_LS is
#: treated as a diverging compensation and restarted from theta_LS.
COMPENSATION_MAX = 1e6
#: The compensation (46) iterates theta_c <- theta_LS + M theta_c with
#: M = tau sigma2 P Lambda, whose spectral radius is tau sigma2 lambda_max(P_aa).
#: Above this the fixed point amplifies the LS error by 1 / (1 - rho) > 5: an
#: over-specified order drives it to 1 (docs/estimators.md).
CONTRACTION_MAX = 0.8
#: A compensation larger than this times |theta_LS| (normalised units) has
#: run away from the LS estimate.
RUNAWAY = 1.0


class Bcrls(Rls):
    r"""
    Bias-compensated RLS for the output-error model y = sum_i B_i/alpha u_i + v.

    The LS part is :class:`~bcid_ros.estimators.rls.Rls`, eqs. (47)-(50),
    with its units, transaction and gate; the compensation adds, with
    :math:`\Lambda = \mathrm{diag}(I_n, 0)`:

    .. math::

        \hat\sigma^2(t) &= \frac{J(t)}{\tau(t)\,[1 + \hat\theta_c^T(t-1)\Lambda
            \hat\theta_{LS}(t)]} && \text{(51)} \\
        \hat\theta_c(t) &= \hat\theta_{LS}(t)
            + \tau(t)\,\hat\sigma^2(t)\,P(t)\Lambda\hat\theta_c(t-1) && \text{(46)}

    With :math:`\lambda = 1`, :math:`\tau(t) = t` and these are the paper's
    (46) and (51) (with the :math:`\Lambda` that (46) misprints away); with
    :math:`\lambda < 1`, t becomes the weighted count :math:`\tau(t)` and J the
    weighted loss (docs/estimators.md derives it from eqs. (21)-(39)).

    **Safeguards** (each counted in :attr:`flags`, never turned into NaN):

    * ``sigma2_denominator``: the denominator of (51) fell below
      ``DENOMINATOR_MIN``; the previous :math:`\hat\sigma^2` is kept;
    * ``compensation_reset``: the compensated estimate became non-finite or
      ran away (relative size above ``COMPENSATION_MAX``); it restarts from
      :math:`\hat\theta_{LS}(t)`.

    **Validity** adds to :class:`~bcid_ros.estimators.rls.Rls`'s (the
    stability is that of :math:`\hat\theta_c`): (46) is the iteration
    :math:`\theta_c \leftarrow \hat\theta_{LS} + M\theta_c`,
    :math:`M = \tau\hat\sigma^2 P\Lambda`, whose fixed point solves
    :math:`(I - M)\theta_c = \hat\theta_{LS}`. The spectral radius of M is
    :math:`\rho = \tau\hat\sigma^2\lambda_{max}(P_{aa})`
    (:math:`P_{aa}` the a-block of P). The estimate is not valid when
    :math:`\rho >` ``CONTRACTION_MAX`` (ill-conditioned compensation: an
    over-parameterised A makes :math:`R - \sigma^2\Lambda` singular and
    :math:`\rho \to 1`), when the normalised compensation
    :math:`|S(\hat\theta_c - \hat\theta_{LS})|` exceeds ``RUNAWAY``
    :math:`|S\hat\theta_{LS}|`, or when a ``compensation_reset`` happened
    since the last check.

    The noise estimate is published as ``sigma2``.

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`.
    input_delay, detrend, adapt
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`; a dead time
        delays the input lags of phi (docs/estimators.md, "Dead time").

    """

    name = 'bcrls'
    noise_names = ('sigma2',)
    options: tuple[str, ...] = ()

    def __init__(self, **settings: Any) -> None:
        # scipy's BLAS loads with the first estimator, not with the module
        self._dgemv = load_blas()['dgemv']
        super().__init__(**settings)

    def _after_ls_step(self) -> None:
        """Apply eqs. (51) and (46) after the LS step."""
        theta_ls = self._theta_ls
        # Lambda theta_c(t-1)
        previous = self._lambda_theta_c
        # denominator of (51): 1 + theta_c(t-1)' Lambda theta_LS(t)
        denominator = 1.0 + previous.dot(theta_ls)
        if denominator >= DENOMINATOR_MIN:
            # sigma2(t) = J(t) / (tau(t) * denominator)          (51)
            self._sigma2 = self._loss / (self._tau * denominator)
        else:
            self._flag('sigma2_denominator')
        # theta_c(t) = theta_LS(t) + tau sigma2 P(t) Lambda theta_c(t-1)   (46), one BLAS call
        # positional: dgemv(alpha, a, x, beta, y, offx, incx, offy, incy, trans)
        compensated = self._dgemv(self._tau * self._sigma2, self._p.T, previous, 1.0,
                                  theta_ls, 0, 1, 0, 1, 1)
        size = compensated.dot(compensated)
        if not size <= COMPENSATION_MAX ** 2 and not (
                size <= COMPENSATION_MAX ** 2 * (1.0 + theta_ls.dot(theta_ls))):
            self._flag('compensation_reset')
            compensated = theta_ls.copy()
        self._theta_c = compensated
        self._lambda_theta_c = compensated * self._lambda_diagonal

    @property
    def sigma2(self) -> float:
        """Return the noise variance estimate of eq. (51)."""
        return self._sigma2

    def _theta(self) -> np.ndarray:
        return self._theta_c

    def _noise(self) -> np.ndarray:
        return np.array([self._sigma2])

    def _find_problems(self) -> list[str]:
        """Add the conditioning and the size of the compensation to the RLS reasons."""
        reasons = super()._find_problems()
        n = self.order
        contraction = self._tau * self._sigma2 * float(np.linalg.eigvalsh(self._p[:n, :n])[-1])
        if not contraction <= CONTRACTION_MAX:
            reasons.append(f'ill-conditioned compensation (contraction {contraction:.3g} '
                           f'> {CONTRACTION_MAX})')
        scale = self._component_scale
        shift = np.linalg.norm(scale * (self._theta_c - self._theta_ls))
        size = np.linalg.norm(scale * self._theta_ls)
        if not shift <= RUNAWAY * size:
            reasons.append(f'compensation runs away from LS ({shift / size:.3g} x |theta_LS|)'
                           if size > 0 else 'compensation runs away from LS')
        resets = self.flags.get('compensation_reset', 0)
        if resets > self._resets_checked:
            reasons.append('compensation reset')
        self._resets_checked = resets
        return reasons

    def _reset(self) -> None:
        super()._reset()
        self._resets_checked = 0
        # the diagonal of Lambda = diag(I_n, 0)
        self._lambda_diagonal = np.zeros(self.num_parameters)
        self._lambda_diagonal[:self.order] = 1.0
        self._theta_c = np.zeros(self.num_parameters)
        self._lambda_theta_c = np.zeros(self.num_parameters)
        self._sigma2 = 0.0

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, scalars = super()._state_items()
        return {**arrays, 'theta_c': self._theta_c}, {
            **scalars, 'sigma2': self._sigma2, 'resets_checked': self._resets_checked}

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        super()._load_state(arrays, scalars)
        self._theta_c = arrays['theta_c']
        self._lambda_theta_c = self._theta_c * self._lambda_diagonal
        self._sigma2 = float(scalars['sigma2'])
        self._resets_checked = int(scalars['resets_checked'])


def bcls_fixed_point(y: np.ndarray, u: np.ndarray, *, order: int, num_inputs: int = 1,
                     feedthrough: bool = False, tolerance: float = 1e-12,
                     max_iterations: int = 1000,
                     input_delay: Any = None) -> tuple[np.ndarray, float, np.ndarray]:
    r"""
    Return the batch bias-compensated LS estimate: the fixed point of eqs. (24) and (39).

    .. math::

        \theta_c = \hat\theta_{LS} + \sigma^2 N P \Lambda \theta_c, \qquad
        \sigma^2 = \frac{J/N}{1 + \theta_c^T \Lambda \hat\theta_{LS}}

    with :math:`P = (\Phi^T\Phi)^{-1}` and J the LS loss over the N updates.
    BCRLS tracks this point recursively; it is the reference its estimates
    are tested against.

    Parameters
    ----------
    y, u : numpy.ndarray
        Outputs ``(N,)`` and inputs ``(N,)`` or ``(N, r)``.
    order, num_inputs, feedthrough
        The model structure.
    tolerance : float
        Stop when the estimate moves by less than this (2-norm).
    max_iterations : int
        Iteration cap.
    input_delay : sequence of int, optional
        Dead time d_i of each input (None: none); Lambda still selects the
        a-block (docs/estimators.md, "Dead time").

    Returns
    -------
    theta_c : numpy.ndarray, shape ``(p,)``
        Compensated estimate.
    sigma2 : float
        Noise variance estimate.
    theta_ls : numpy.ndarray, shape ``(p,)``
        Plain LS estimate.

    Raises
    ------
    ValueError
        If the iteration does not converge within ``max_iterations``.

    """
    theta_ls, p, loss, count = ls_batch(y, u, order=order, num_inputs=num_inputs,
                                        feedthrough=feedthrough, input_delay=input_delay)
    n = order
    theta_c = theta_ls.copy()
    for _ in range(max_iterations):
        sigma2 = loss / count / (1.0 + float(theta_c[:n] @ theta_ls[:n]))
        updated = theta_ls + sigma2 * count * (p[:, :n] @ theta_c[:n])
        if np.linalg.norm(updated - theta_c) < tolerance:
            return updated, sigma2, theta_ls
        theta_c = updated
    raise ValueError(f'the BCLS fixed point did not converge in {max_iterations} iterations')
