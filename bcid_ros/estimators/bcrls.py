"""
BCRLS: bias-compensated recursive least squares for MISO output-error systems.

Ding, Chen and Qiu (2006), "Bias compensation based recursive least-squares
identification algorithm for MISO systems", eqs. (46)-(55), with the matrix
Lambda that the printed eqs. (26)/(46) drop (docs/papers.md) and an exact
extension to exponential forgetting (derived in docs/estimators.md).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.base import weighted_square_ratio
from bcid_ros.estimators.bcrls_covariance import LaggedMoments, MOMENT_BLOCK
from bcid_ros.estimators.blas import load_blas
from bcid_ros.estimators.held_model import hold_due, precise, with_held_items
from bcid_ros.estimators.polynomials import spectral_radii
from bcid_ros.estimators.recursion import matvec, rowdot
from bcid_ros.estimators.rls import ls_batch, Rls

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
#: A compensation larger than this times |theta_LS| (normalised units) is
#: checked against its fixed point (see compensation_problems).
RUNAWAY = 1.0
#: An estimate whose normalised std exceeds this share of its size is not
#: determined by the data: it is not three std away from zero.
DETERMINED = 1.0 / 3.0
#: A compensated estimate more than this many std from the fixed point of the
#: current statistics has not converged (about 3 in 1000 under normal errors).
CONVERGED = 3.0
#: An output error beyond this times the output scale means an unstable A: the
#: filter that makes it from the equation error restarts.
OUTPUT_ERROR_LIMIT = 1e6


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
    (:math:`P_{aa}` the a-block of P). The checks take their thresholds from
    the estimate's own uncertainty (:func:`compensation_problems`):
    :math:`\rho \ge 1` diverges and restarts the compensation from
    :math:`\hat\theta_{LS}`; where :math:`\rho >` ``CONTRACTION_MAX`` or the
    normalised compensation exceeds ``RUNAWAY`` :math:`|S\hat\theta_{LS}|`,
    the estimate is not valid if its covariance is singular or its normalised
    std above ``DETERMINED`` of its size (ill-conditioned), or if it lies more
    than ``CONVERGED`` std from the fixed point of the current statistics (not
    converged). A ``compensation_reset`` since the last check is a reason
    too, and the output error of the compensated model goes to the residual
    tests (``adequacy_model`` 'oe_white') with its gradient, so that they
    count the settling estimate's error (docs/trust.md). The change detector
    takes the LS step's normalised error, as rls's, until the estimate can be
    held (500 samples, a stable A, no reason against the compensation, known
    to 10 % of its size); from
    then on the output error of that estimate held fixed, refreshed as the
    estimate grows (:mod:`~bcid_ros.estimators.held_model`): under the model
    it is white, and a moved pole shows there where it does not in the
    equation error (docs/tracking.md). Not the output error of the current
    estimate: the compensation's wandering breaks the detector's reference
    (docs/tracking.md, "False detections").

    The noise estimate is published as ``sigma2``.

    The settings (parameters) are those of :class:`~bcid_ros.estimators.rls.Rls`.
    """

    name = 'bcrls'
    noise_names = ('sigma2',)
    #: The residual tests take the output error, which Ding et al.'s model says is white.
    adequacy_model = 'oe_white'
    #: The std is bcrls's own sandwich (white output noise, which the residual tests check).
    hac_std = False

    def __init__(self, **settings: Any) -> None:
        # scipy's BLAS loads with the first estimator, not with the module
        self._dgemv = load_blas()['dgemv']
        super().__init__(**settings)

    def _after_ls_step(self, y: float, phi: np.ndarray) -> None:
        """Apply eqs. (51) and (46) after the LS step; keep z = [phi; y] for the moments."""
        # list appends: the cheapest record (phi is a fresh array from the regressor)
        self._moment_phi.append(phi)
        self._moment_y.append(y)
        if len(self._moment_y) == MOMENT_BLOCK:
            self._flush_moments()
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

    def _record_residual(self, y: float, phi: np.ndarray, u: np.ndarray) -> None:
        """
        Give the residual tests this step's output error y - B/A u of the compensated model.

        The output error is the equation error of theta_c filtered by 1 / A:
        e_oe(t) = e(t) - a_1 e_oe(t-1) - ... - a_n e_oe(t-n), with the current
        a. An unstable A makes it grow without bound: a value beyond
        ``OUTPUT_ERROR_LIMIT`` times the output scale (or not finite) restarts
        the filter and is not recorded. The covariance is bcrls's own
        sandwich, not the HAC. With it go the output error's gradient psi
        (:func:`output_gradient`), for the estimate's own error in the tests.
        The change detector takes the held model's output error once one is
        held (:mod:`~bcid_ros.estimators.held_model`), the LS step's
        normalised error e / sqrt(s) before, as rls's.
        """
        theta = self._theta_c
        past = self._output_errors
        error = output_error(theta[:self.order].tolist(), theta, past, y, phi)
        limit = OUTPUT_ERROR_LIMIT * self._signal_scale[0]
        if abs(error) < limit:
            psi = output_gradient(theta, phi, past, self._output_gradients)
            past.pop()
            past.insert(0, error)
            self._monitor.record(error, u, psi)
        else:
            self._forget_output_errors()
        if not self._held_tau:  # the detector's input: the LS step's normalised error
            if self._gain:
                self._detect(self._error / math.sqrt(self._gain))
            return
        # the held model's output error (held_model.py)
        held = self._held_errors
        error = output_error(self._held_a, self._held_theta, held, y, phi)
        if not abs(error) < limit:  # an unstable held A: its filter restarts
            self._held_errors = [0.0] * self.order
            return
        held.pop()
        held.insert(0, error)
        if self._gain:
            self._detect(error)

    @property
    def sigma2(self) -> float:
        """Return the noise variance estimate of eq. (51)."""
        return self._sigma2

    def _theta(self) -> np.ndarray:
        # (while catching up after a change: the estimate shown, Rls._plant_changed)
        return self._theta_c if self._shown is None else self._shown[0]

    def _noise(self) -> np.ndarray:
        return np.array([self._sigma2]) if self._shown is None else self._shown[2]

    def _check_validity(self, more: Sequence[str] = ()) -> None:
        """
        Add the conditioning and the convergence of the compensation to the RLS reasons.

        A compensation found diverging restarts from theta_LS here, in the
        update, after the reasons are decided (the check itself changes nothing).
        """
        resets = self.flags.get('compensation_reset', 0)
        with np.errstate(all='ignore'):
            found, diverging = compensation_problems(
                np.array([self._tau]), np.array([self._sigma2]), self._p[None],
                self._theta_c[None], self._theta_ls[None], self._component_scale[None],
                np.array([resets > self._resets_checked]), self.order, self._covariances)
        self._resets_checked = resets
        super()._check_validity(found[0] + list(more))
        if diverging[0]:
            # (46) does not contract: restart it from theta_LS rather than follow it away
            self._flag('compensation_reset')
            self._resets_checked += 1
            self._theta_c = self._theta_ls.copy()
            self._lambda_theta_c = self._theta_c * self._lambda_diagonal
        if self._change_detection and hold_due(
                not found[0] and not diverging[0] and spectral_radii(
                    self._theta_c[None, :self.order])[0] < 1.0, self._tau, self._held_tau
        ) and precise(self._theta_c[None], self._covariances(None))[0]:
            self._hold_model()

    def _hold_model(self) -> None:
        """Hold the estimate for the detector's errors (held_model.py); the first: afresh."""
        if not self._held_tau:  # the detector's reference was of the LS step's errors
            self._detector.clear()
            self._held_errors = [0.0] * self.order
        self._held_theta = self._theta_c.copy()
        self._held_a = self._held_theta[:self.order].tolist()  # (its A's, for output_error)
        self._held_tau = self._tau

    def _covariances(self, rows: np.ndarray) -> np.ndarray:
        """Return the covariance of this plant as ``(1, p, p)`` (NaN where there is none)."""
        covariance = self.parameter_covariance
        if covariance is None:
            return np.full((1, self.num_parameters, self.num_parameters), np.nan)
        return covariance[None]

    def _gradient_covariances(self, rows: np.ndarray) -> np.ndarray:
        """Return this plant's covariance for the tests' term (:func:`gradient_covariances`)."""
        return gradient_covariances(self._covariances(rows), self._theta_c[None], self.order)

    def _forget_residuals(self) -> None:
        super()._forget_residuals()
        # the output error's tests with the estimate's own error (docs/trust.md)
        self._monitor = AdequacyMonitor(
            num_inputs=self.num_inputs, model=self.adequacy_model,
            forgetting_factor=self._forgetting_factor, num_parameters=self.num_parameters,
            parameter_covariance=self._gradient_covariances)
        self._forget_output_errors()
        self._drop_held_model()

    def _forget_output_errors(self) -> None:
        """Restart the filters 1 / A of the output error and of its gradient."""
        # e_oe(t-1) ... e_oe(t-n) and psi(t-1) ... psi(t-n), newest first
        self._output_errors = [0.0] * self.order
        self._output_gradients = np.zeros((self.order, self.num_parameters))

    def _drop_held_model(self) -> None:
        """Hold no model (a reset, a change): the LS step's errors feed the detector again."""
        if getattr(self, '_held_tau', 0.0):  # its reference was of the held model's errors
            self._detector.clear()
        # the held model of the detector (held_model.py): theta_h, e_h(t-1) ... e_h(t-n),
        # and the tau it rests on (0: none held)
        self._held_theta = np.zeros(self.num_parameters)
        self._held_a = [0.0] * self.order
        self._held_errors = [0.0] * self.order
        self._held_tau = 0.0

    def _reset(self) -> None:
        super()._reset()
        self._resets_checked = 0
        # the diagonal of Lambda = diag(I_n, 0)
        self._lambda_diagonal = np.zeros(self.num_parameters)
        self._lambda_diagonal[:self.order] = 1.0
        self._theta_c = np.zeros(self.num_parameters)
        self._lambda_theta_c = np.zeros(self.num_parameters)
        self._sigma2 = 0.0
        self._reset_moments()

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, scalars = super()._state_items()
        moment_arrays, moment_scalars = self._moment_state()
        return {**arrays, 'theta_c': self._theta_c, 'output_errors': np.array(
            self._output_errors), 'output_gradients': self._output_gradients.copy(),
            'held_theta': self._held_theta, 'held_errors': np.array(self._held_errors),
            **moment_arrays}, {
            **scalars, 'sigma2': self._sigma2, 'resets_checked': self._resets_checked,
            'held_tau': self._held_tau, **moment_scalars}

    def set_state(self, state: Any) -> None:
        """Restore a :meth:`get_state` snapshot; one from before the held model loads too."""
        super().set_state(with_held_items(state, self.num_parameters, self.order))

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        super()._load_state(arrays, scalars)
        self._output_errors = arrays['output_errors'].tolist()
        # a snapshot from before the gradient: its filter starts from zero
        self._output_gradients = np.array(arrays.get(
            'output_gradients', np.zeros((self.order, self.num_parameters))), dtype=float)
        self._theta_c = arrays['theta_c']
        self._lambda_theta_c = self._theta_c * self._lambda_diagonal
        self._sigma2 = float(scalars['sigma2'])
        self._resets_checked = int(scalars['resets_checked'])
        # a snapshot from before the held model: none held (its arrays: set_state)
        self._held_tau = float(scalars.get('held_tau', 0.0))
        self._held_theta = np.array(arrays['held_theta'], dtype=float)
        self._held_a = self._held_theta[:self.order].tolist()
        self._held_errors = np.asarray(arrays['held_errors'], dtype=float).tolist()
        self._load_moments(arrays, scalars)

    # ------------------------------------------------------- the uncertainty
    def _reset_moments(self) -> None:
        self._moments = LaggedMoments(1, self.order, self.num_parameters)
        # z of the steps not yet handed to the moments, as [phi] and [y] lists
        self._moment_phi: list[np.ndarray] = []
        self._moment_y: list[float] = []

    def _flush_moments(self) -> None:
        """Hand a full block of rows z to the moments and sum it."""
        moments, n = self._moments, self.order
        moments.ring[0, n:, :-1] = np.array(self._moment_phi)  # a list of rows converts slowly
        moments.ring[0, n:, -1] = self._moment_y
        self._moment_phi, self._moment_y = [], []
        moments.flush(_ONE, self._forgetting_factor, self._theta_c, self._sigma2,
                      self._component_scale, self._signal_scale[:1])

    def _moment_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        moments, n, m = self._moments, self.order, len(self._moment_y)
        if m:  # the rows not yet handed over go into the snapshot's ring
            moments.ring[0, n:n + m, :-1] = np.array(self._moment_phi)
            moments.ring[0, n:n + m, -1] = self._moment_y
        moments.pending[0] = m
        return moments.plant_items(0)

    def _load_moments(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._moments.load_plant(0, arrays, scalars)
        n, end = self.order, self.order + int(scalars['moment_pending'])
        self._moment_phi = list(self._moments.ring[0, n:end, :-1].copy())
        self._moment_y = self._moments.ring[0, n:end, -1].tolist()

    def _parameter_covariance(self) -> np.ndarray | None:
        r"""
        Return the asymptotic covariance of :math:`\hat\theta_c` (docs/estimators.md).

        :math:`\beta = (\theta_c, \sigma^2)` solves the estimating equations
        :math:`\sum_t w_t g_t(\beta) = 0` with :math:`z = [\varphi; y]`,

        .. math::

            g_t = \begin{bmatrix} \varphi(t)(y(t) - \varphi^T(t)\theta)
                + \sigma^2\Lambda\theta \\ y(t)(y(t) - \varphi^T(t)\theta)
                - \sigma^2 \end{bmatrix},

        the fixed point of (46) and, equivalently, (51). The sandwich is
        :math:`\mathrm{cov}\,\hat\beta = (\tau_2/\tau^2) H^{-1} S H^{-T}` with
        :math:`H = \begin{bmatrix} -(R - \sigma^2\Lambda) & \Lambda\theta \\
        -r^T & -1\end{bmatrix}` and, the equation error
        :math:`w = \alpha(q) v` being MA(n),

        .. math::

            S = \sum_{k=-n}^{n} S_k, \quad
            S_k = \Gamma_z(k)\gamma_w(k) + c_k d_k^T, \quad S_{-k} = S_k^T,

        where :math:`\Gamma_z(k)` is the weighted mean of
        :math:`z_t z_{t-k}^T`, :math:`\gamma_w(k) = \sigma^2\sum_i a_i a_{i+k}`
        (:math:`a_0 = 1`), :math:`c_k = E[\zeta_t w_{t-k}]`,
        :math:`d_k = E[w_t \zeta_{t-k}]` with :math:`\zeta` the noise part of
        z (Gaussian v). :math:`H^{-1} S H^{-T}`, a per-sample quantity, is
        evaluated in normalised units at the moments and the
        :math:`(\hat\theta_c, \hat\sigma^2)` of the last block of
        ``MOMENT_BLOCK`` steps, once per block and only when read; the factor
        :math:`\tau_2/\tau^2` is the current one. None before ready and before
        the first block.
        """
        known = np.array([self._updates >= self.num_parameters and self._moments.weight[0] > 0.0])
        if not known[0]:
            return None
        ratio = weighted_square_ratio(self._tau, self._forgetting_factor)
        return self._moments.sandwiches(known)[0] * (ratio / self._tau)


#: The one plant of a single-plant estimator, as rows (a slice: views, not copies).
_ONE = slice(0, 1)


def compensate_rows(theta_ls: np.ndarray, p: np.ndarray, loss: np.ndarray, tau: np.ndarray,
                    previous: np.ndarray, sigma2: np.ndarray,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r"""
    Apply eqs. (51) and (46) to K plants at once: the batched form of :meth:`Bcrls._after_ls_step`.

    ``theta_ls`` ``(K, p)``, ``p`` ``(K, p, p)``, ``loss`` and ``tau``
    ``(K,)`` after the LS step; ``previous`` ``(K, p)`` is
    :math:`\Lambda\hat\theta_c(t-1)` and ``sigma2`` ``(K,)`` the previous
    noise variances. numpy element-wise and matmul where the single plant
    calls BLAS dgemv: the two agree within rounding. Returns the new sigma2,
    the compensated estimates, where the denominator of (51) broke down
    (sigma2 kept) and where the compensation was reset to theta_LS.
    """
    # denominator of (51): 1 + theta_c(t-1)' Lambda theta_LS(t)
    denominator = 1.0 + rowdot(previous, theta_ls)
    low = ~(denominator >= DENOMINATOR_MIN)
    # sigma2(t) = J(t) / (tau(t) * denominator)          (51)
    if low.any():
        sigma2 = sigma2.copy()
        sigma2[~low] = loss[~low] / (tau[~low] * denominator[~low])
    else:  # every plant's (the common case): the same quotients, no subsets taken
        sigma2 = loss / (tau * denominator)
    # theta_c(t) = theta_LS(t) + tau sigma2 P(t) Lambda theta_c(t-1)   (46)
    compensated = theta_ls + (tau * sigma2)[:, None] * matvec(p, previous)
    size = rowdot(compensated, compensated)
    limit = COMPENSATION_MAX ** 2
    reset = np.zeros(size.shape[0], dtype=bool)
    # all below the absolute limit (the common case, one comparison) or each checked
    if not size.max() <= limit:
        reset = ~((size <= limit) | (size <= limit * (1.0 + rowdot(theta_ls, theta_ls))))
        compensated[reset] = theta_ls[reset]
    return sigma2, compensated, low, reset


def compensation_problems(tau: np.ndarray, sigma2: np.ndarray, p: np.ndarray,
                          theta_c: np.ndarray, theta_ls: np.ndarray,
                          component_scale: np.ndarray, reset: np.ndarray, order: int,
                          covariance_of: Callable[[np.ndarray], np.ndarray],
                          ) -> tuple[list[list[str]], np.ndarray]:
    r"""
    Return, per plant, the reasons not to trust a compensated estimate, and which diverge.

    (46) is the iteration :math:`\theta_c \leftarrow \hat\theta_{LS} + M\theta_c`
    with :math:`M = \tau\hat\sigma^2 P\Lambda`, of spectral radius (contraction)
    :math:`\rho = \tau\hat\sigma^2\lambda_{max}(P_{aa})`:

    * :math:`\rho \ge 1`: the recursion diverges; the plant is returned in the
      mask (its caller restarts the compensation from theta_LS);
    * an ill-conditioned compensation, judged by the estimate's own
      uncertainty where it could be one (:math:`\rho >` ``CONTRACTION_MAX`` or
      the compensation larger than theta_LS): no covariance (the sandwich's
      bread is singular, as an over-specified order makes it) or, in
      normalised units, a standard deviation above ``DETERMINED`` of the
      estimate's size (the data do not determine it);
    * a compensation that has not converged: it is larger than theta_LS
      (normalised) and more than ``CONVERGED`` std away from the fixed point
      :math:`(I - M)^{-1}\hat\theta_{LS}` of the current statistics;
    * a ``compensation_reset`` since the last check (``reset``).

    ``covariance_of(plants)`` returns the covariances ``(k, p, p)`` of those
    plants (NaN where none); it is called only for plants that need it.
    Arrays have a leading plant axis ``(K, ...)``.
    """
    count = tau.shape[0]
    block = p[:, :order, :order]
    largest = np.full(count, np.nan)
    finite = np.isfinite(block).all(axis=(1, 2))
    if finite.any():
        largest[finite] = np.linalg.eigvalsh(block[finite])[:, -1]
    contraction = tau * sigma2 * largest
    shift = np.sqrt(rowdot(*(component_scale * (theta_c - theta_ls),) * 2))
    size = np.sqrt(rowdot(*(component_scale * theta_ls,) * 2))
    diverging = contraction >= 1.0
    large = ~(shift <= RUNAWAY * size)
    doubtful = np.flatnonzero(~diverging & ((contraction > CONTRACTION_MAX) | large))
    reasons: list[list[str]] = [[] for _ in range(count)]
    for k in np.flatnonzero(diverging | ~np.isfinite(contraction)):
        reasons[k].append(f'compensation diverges (contraction {contraction[k]:.3g})')
    if doubtful.size:
        covariance = covariance_of(doubtful)
        a_columns = _a_columns(p.shape[1], order)
        for k, matrix in zip(doubtful.tolist(), covariance):
            # I - M, M = tau sigma2 P Lambda: its solve is the fixed point
            iteration = np.eye(p.shape[1]) - tau[k] * sigma2[k] * p[k] * a_columns
            reasons[k] += _uncertain_compensation(matrix, theta_c[k], component_scale[k],
                                                  large[k], iteration, theta_ls[k])
    for k in np.flatnonzero(reset):
        reasons[k].append('compensation reset')
    return reasons, diverging


def _a_columns(width: int, order: int) -> np.ndarray:
    """Return the diagonal of Lambda = diag(I_n, 0) as a row, for P Lambda."""
    row = np.zeros(width)
    row[:order] = 1.0
    return row


def _uncertain_compensation(covariance: np.ndarray, theta_c: np.ndarray,
                            scale: np.ndarray, large: bool, contraction: np.ndarray,
                            theta_ls: np.ndarray) -> list[str]:
    """Return the reasons of :func:`compensation_problems` that need the covariance."""
    std = np.sqrt(np.maximum(np.diagonal(covariance), 0.0))
    if not np.isfinite(covariance).all():
        return ['ill-conditioned compensation (no covariance: the data do not determine it)']
    relative = float(np.linalg.norm(scale * std) / np.linalg.norm(scale * theta_c))
    if not relative <= DETERMINED:
        return [f'ill-conditioned compensation (std {relative:.3g} of the estimate)']
    if large:
        try:
            fixed_point = np.linalg.solve(contraction, theta_ls)
        except np.linalg.LinAlgError:
            return ['ill-conditioned compensation (no fixed point)']
        away = float(np.max(np.abs(theta_c - fixed_point) / np.maximum(std, 1e-300)))
        if not away <= CONVERGED:
            return [f'compensation has not converged ({away:.3g} std from its fixed point)']
    return []


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


def gradient_covariances(covariance: np.ndarray, theta_c: np.ndarray, order: int
                         ) -> np.ndarray:
    """
    Return the covariances ``(K, p, p)`` for the residual tests' term: NaN where A is not stable.

    The gradient psi = phi_hat / A (:func:`output_gradient`) is that of a
    stationary predictor only while A is stable; through an unstable A it
    grows without bound and its products would let the term explain any
    colour away, so those samples get no term.
    """
    stable = spectral_radii(theta_c[:, :order]) < 1.0
    return np.where(stable[:, None, None], covariance, np.nan)


def output_gradient(theta: np.ndarray, phi: np.ndarray, past_errors: np.ndarray,
                    past: np.ndarray) -> np.ndarray:
    r"""
    Return psi(t) = d y_hat / d theta of the output-error model, updating ``past`` in place.

    :math:`\hat y = (B/A) u`, so :math:`\psi = \hat\varphi / A(q)` with
    :math:`\hat\varphi(t) = [-\hat y(t-1) \ldots -\hat y(t-n), u \text{ lags}]`
    (Ljung, sec. 10.3), the regressor phi with y replaced by the simulated
    output :math:`\hat y = y - e_{oe}`: its first n entries plus the past output
    errors ``past_errors`` (newest first). ``past`` ``(..., n, p)`` holds
    psi(t-1) ... psi(t-n), newest first. Leading dimensions are plants.
    """
    order = past.shape[-2]
    # psi(t) = phi_hat(t) - a_1 psi(t-1) - ... - a_n psi(t-n)
    if theta.ndim == 1:  # one plant, each sample: a vector-matrix product, plain indexing
        psi = phi - theta[:order] @ past
        for i, error in enumerate(past_errors):  # a list of n floats: no array made of it
            psi[i] += error
        if order > 1:
            past[1:] = past[:-1]  # overlapping: numpy copies first
        past[0] = psi
        return psi
    psi = phi - np.einsum('ki,kij->kj', theta[:, :order], past)
    psi[..., :order] += past_errors
    if order > 1:
        past[..., 1:, :] = past[..., :-1, :]  # overlapping: numpy copies first
    past[..., 0, :] = psi
    return psi


def output_error(a: list[float], theta: np.ndarray, past: list[float], y: float,
                 phi: np.ndarray) -> float:
    """
    Return one plant's output error e(t) = y - phi^T theta - sum_i a_i e(t-i) on floats.

    ``a`` is theta's a_1 ... a_n as a list and ``past`` holds e(t-1) ... e(t-n),
    newest first (lists of n floats: no array made of them each sample);
    :func:`output_error_rows` is the rows form.
    """
    error = y - float(phi.dot(theta))
    for coefficient, previous in zip(a, past):
        error -= coefficient * previous
    return error


def output_error_rows(theta: np.ndarray, past: np.ndarray, y: np.ndarray, phi: np.ndarray,
                      y_scale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return each plant's output error, whether it is bounded, and the new past output errors.

    The rows form of ``Bcrls._record_residual`` (plants ``(K,)``, ``past``
    ``(K, n)`` newest first): e_oe(t) = y - phi^T theta - sum_i a_i e_oe(t-i);
    a plant whose error is beyond ``OUTPUT_ERROR_LIMIT`` times its output
    scale (or not finite) restarts its filter. ``theta`` ``(F, K, p)`` and
    ``past`` ``(F, K, n)`` run F filters of each plant on the same samples in
    one call (the errors ``(F, K)``), each row's products the same as alone.
    """
    error = y - rowdot(phi, theta) - rowdot(theta[..., :past.shape[-1]], past)
    bounded = np.abs(error) < OUTPUT_ERROR_LIMIT * y_scale
    past = np.concatenate([error[..., None], past[..., :-1]], axis=-1)
    if not bounded.all():
        past[~bounded] = 0.0
    return error, bounded, past
