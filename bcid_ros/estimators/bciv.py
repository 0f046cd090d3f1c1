"""
BCIV: bias-compensated IV-type estimation for errors-in-variables models.

Ikenoue, Kanae, Yang and Wada (2008), "Bias-compensation based method for
errors-in-variables model identification", eqs. (37)-(75) and the recursive
algorithm of section 4. What "the estimate at sample N" means differs by
noise case (the reasons, and the paper's limits, are in ``docs/bciv.md`` and
``docs/papers.md``):

* colored input noise: eq. (72) does not fix the gain of B, so the
  alternation of eqs. (75) and (53) has a unit eigenvalue; the estimate is
  K alternations started from the IV-type estimate theta_IV,N, never
  warm-started from the previous BCIV estimate;
* white input noise (eqs. 65-67): there is no such direction; the estimate
  is a fixed point of the alternation, found warm-started at every sample;
* ``bciv_update='printed'``: the paper's Steps 0-5 as printed, one
  alternation per sample warm-started from the previous estimate.

The recursive estimator :class:`Bciv` and the batch reference
:func:`bciv_batch` share one solver, :class:`BcivSolver`, which takes the
moments of Step 2 and returns the estimate; they differ only in how the
moments are accumulated.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from scipy.linalg.blas import dger
from scipy.linalg.lapack import dgesv, dposv

from bcid_ros.estimators.base import (check_int, check_range, power_of_two_at_least,
                                      RecursiveEstimator)
from bcid_ros.estimators.moment_covariance import MomentBlocks
from bcid_ros.estimators.rls import (GROWTH, spectral_radius, UNSTABLE_RADIUS, VALIDITY_PERIOD,
                                     VARIANCE_FLOOR)

#: Above this (estimated) condition number of Q~'XQ~ the noise system of
#: eq. (75) counts as ill-conditioned and the estimate falls back to theta_IV.
CONDITION_MAX = 1e10
#: A compensated estimate farther than this (relative) from theta_IV counts as a
#: runaway of the alternation and falls back to theta_IV.
COMPENSATION_MAX = 1e6
#: Default tolerance on the 2-norm of one alternation step.
DEFAULT_TOLERANCE = 1e-10
#: The alternation checks its step against the tolerance every this many steps
#: (and after the last), which saves a fifth of its cost.
CHECK_PERIOD = 4
#: Samples the history ring of :class:`Bciv` takes before it moves its window back.
RING_SAMPLES = 512
INPUT_NOISE = ('colored', 'white')
UPDATES = ('converged', 'printed')
#: The gate tests samples once this many times p equation errors were measured
#: after the estimator became ready (their mean square is then a variance).
GATE_WARMUP = 10
#: A detected plant change cuts the weighted memory tau to this many times m samples.
CHANGE_MEMORY = 4
#: A compensation farther than this from theta_IV (relative, normalised units) is a runaway.
RUNAWAY_SHIFT = 1.0

#: Solver outcomes (the flag counted when the estimate falls back to theta_IV).
OK = ''
SINGULAR = 'noise_system_singular'
RUNAWAY = 'compensation_runaway'


class BcivResult(NamedTuple):
    """
    One BCIV estimate from given moments.

    Attributes
    ----------
    theta : numpy.ndarray, shape ``(p,)``
        theta_BCIV (theta_IV if ``status`` is not empty).
    gamma : numpy.ndarray, shape ``(q,)``
        N gamma~ of eq. (75), unnormalised: divide by the (weighted) sample count.
    theta_iv : numpy.ndarray, shape ``(p,)``
        The IV-type estimate of eq. (38).
    iterations : int
        Alternations (or, white fixed point, secant steps) made.
    converged : bool
        Whether the last step was below the tolerance.
    status : str
        ``''``, or why the estimate fell back to theta_IV.

    """

    theta: np.ndarray
    gamma: np.ndarray
    theta_iv: np.ndarray
    iterations: int
    converged: bool
    status: str


def check_structure(order: int, iv_lag: int, feedthrough: bool, input_noise: str,
                    allow_underdetermined: bool) -> None:
    """
    Refuse an IV lag that leaves eq. (37) or eq. (72) under-determined.

    The IV-type vector (54) has m = n + 2l elements. Eq. (38) needs m >= p (the
    number of parameters, 2n without feedthrough); eq. (72) has m equations in
    the p parameters and the q noise covariances (q = n + l colored, 1 white),
    so it needs m >= p + q: l >= 2n colored, 2l >= n + 1 white (without
    feedthrough; with it, b_0 adds one parameter and, colored, one covariance).

    Raises
    ------
    ValueError
        If m < p, or m < p + q and ``allow_underdetermined`` is False.

    """
    n, lag = order, iv_lag
    nb = n + 1 if feedthrough else n
    p = n + nb
    m = n + 2 * lag
    q = noise_count(order, iv_lag, feedthrough, input_noise)
    if m < p:
        lowest = -(-(p - n) // 2)
        raise ValueError(
            f'iv_lag must be >= {lowest} for order {n}, got {lag}: the IV-type vector of eq. '
            f'(54) has m = n + 2l = {m} elements, fewer than the {p} parameters of eq. (38)')
    if m < p + q and not allow_underdetermined:
        lowest = next(k for k in range(1, 10 * p + 10)
                      if n + 2 * k >= p + noise_count(n, k, feedthrough, input_noise))
        raise ValueError(
            f'iv_lag must be >= {lowest} for order {n} with {input_noise} input noise, got '
            f'{lag}: eq. (72) then has m = n + 2l = {m} equations for {p + q} unknowns ({p} '
            f'parameters and {q} noise covariance{"s" if q > 1 else ""}), so it is '
            'under-determined; set allow_underdetermined to true to run anyway')


def noise_count(order: int, iv_lag: int, feedthrough: bool, input_noise: str) -> int:
    """Return q, the length of the noise vector gamma~ (eq. 64 colored, eq. 67 white)."""
    if input_noise == 'white':
        return 1
    return order + iv_lag + (1 if feedthrough else 0)


class BcivSolver:
    r"""
    Steps 1, 3 and 4 of the recursive BCIV algorithm, computed from the moments of Step 2.

    The moments are kept unnormalised, as sums over the samples (weighted by
    :math:`\lambda^{N-t}` with a forgetting factor):

    .. math::

        \bar R = N\hat R_{\eta p} = \sum_t \eta_t p_t^T, \qquad
        \bar r = N\hat r_{\eta z} = \sum_t \eta_t z_t, \qquad
        \text{moments} = [\bar R,\ -\bar r] \quad (m \times (p + 1)),

    so that :math:`\text{moments}\,[\theta; 1] = N(\hat R_{\eta p}\theta - \hat r_{\eta z})`.
    From them, per sample:

    .. math::

        M_N^{-1} &= \bar R^T W \bar R + \rho^{-1}\lambda^{2N} I, \quad
        G = M_N \bar R^T W, \quad
        \hat\theta_{IV} = G\,\bar r && \text{Step 1, eq. (38)} \\
        \tilde\gamma_{k+1} &= (\tilde Q_k^T X \tilde Q_k)^{-1} \tilde Q_k^T X
            (\bar R\theta_k - \bar r) && \text{Step 3, eq. (75)} \\
        \theta_{k+1} &= \hat\theta_{IV} + G\,\tilde Q_k\,\tilde\gamma_{k+1}
            && \text{Step 4, eq. (53)}

    with :math:`\tilde Q_k = \tilde Q(b_k)` of eq. (61) (colored input noise,
    :math:`\tilde\gamma = [r_{dd}(0) \ldots r_{dd}(n+l-1)]`, eq. 64) or eq. (66)
    (white, :math:`\tilde\gamma = \sigma_d^2`, eq. 67). The factor N cancels
    in eq. (53); :math:`\tilde\gamma` comes out as :math:`N\tilde\gamma`.
    :math:`M_N` is that of Step 1 with :math:`M_0 = \rho I` (it sums the
    rank-2 updates of Step 1 exactly), and :math:`N^2 M_N\hat R^T_{\eta p}W`
    of Step 4 is :math:`G`.

    :math:`\tilde Q(b) = \sum_j b_j E_j` is linear in b, with constant 0/1
    matrices :math:`E_j` (:math:`m \times q`, see :attr:`q_basis`). So the
    three quantities one alternation needs, :math:`\tilde Q^TX\tilde Q`,
    :math:`\tilde Q^TX(\bar R\theta - \bar r)` and :math:`G\tilde Q`, are all
    bilinear in :math:`[b; 1]` and :math:`[\theta; 1]`; :meth:`estimate`
    evaluates them as one bilinear form (see :meth:`_alternate`).

    Parameters
    ----------
    order : int
        n.
    iv_lag : int
        l of eq. (54); m = n + 2l.
    feedthrough : bool
        Whether b_0 (lag 0) is estimated.
    input_noise : str
        ``'colored'`` or ``'white'``.
    iv_weight, noise_weight : numpy.ndarray or None
        W of eq. (38) and X of eq. (75), ``(m, m)`` symmetric positive
        definite; None means the identity.

    """

    def __init__(self, *, order: int, iv_lag: int, feedthrough: bool, input_noise: str,
                 iv_weight: np.ndarray | None = None,
                 noise_weight: np.ndarray | None = None) -> None:
        self.order, self.iv_lag, self.input_noise = order, iv_lag, input_noise
        #: The lags k of b_k: 1..n, or 0..n with feedthrough.
        self.lags = tuple(range(0 if feedthrough else 1, order + 1))
        self.num_parameters = p = order + len(self.lags)
        self.m = m = order + 2 * iv_lag
        self.q = noise_count(order, iv_lag, feedthrough, input_noise)
        self.iv_weight = None if iv_weight is None else _weight('iv_weight', iv_weight, m)
        self.noise_weight = (None if noise_weight is None
                             else _weight('noise_weight', noise_weight, m))
        #: The E_j of Q~(b) = sum_j b_j E_j side by side, (m, nb q):
        #: ``q_basis[:, j q + c]`` is column c of E_j.
        self.q_basis = self._q_basis()
        #: E_j' X stacked, (nb q, m).
        self._basis_x = self.q_basis.T if self.noise_weight is None else \
            self.q_basis.T @ self.noise_weight

        # Step 1 in fixed buffers. W [R | -r | E] is Fortran-ordered so that its
        # first p + 1 columns (the moments themselves when W = I) are contiguous
        # and Bciv updates them in place with BLAS dger.
        nbq = self.q_basis.shape[1]
        self._weighted = np.zeros((p + 1 + nbq, m)).T
        self._weighted[:, p + 1:] = self.q_basis if self.iv_weight is None else \
            self.iv_weight @ self.q_basis
        #: [R | -r], shape (m, p + 1), Fortran order.
        self.moments = (self._weighted[:, :p + 1] if self.iv_weight is None
                        else np.zeros((p + 1, m)).T)
        # One buffer holds what each sample computes, in this order:
        # * the rows of R'W [R | -r | E] ((p + 1 + nb q, p)), whose transpose is
        #   [M_N^-1 | -R'W r | R'W E]; the solve of Step 1 turns the columns after
        #   M_N^-1 into [-theta_IV | G E];
        # * E_j' X [R | -r] stacked ((nb q, p + 1)).
        # Everything after M_N^-1 goes into the tensor of the alternation by one scatter.
        rows = p + 1 + nbq
        self._sample_numbers = np.zeros(rows * p + nbq * (p + 1))
        self._normal = self._sample_numbers[:rows * p].reshape(rows, p)
        #: M_N^-1 = R'WR + rho^-1 lambda^2N I of Step 1 (Fortran-ordered view).
        self.m_inverse = self._normal[:p].T
        self._m_inverse_diagonal = self._sample_numbers[:p * p:p + 1]
        self._iv_solution = self._normal[p:].T
        self._noise_moments = self._sample_numbers[rows * p:].reshape(nbq, p + 1)
        self._forms, self._form_slots = self._bilinear_form()
        # The alternation's work buffers: x = [theta; 1], the sum over [b; 1] of
        # C, and the value of the form with its views Hbar, hbar, Dbar.
        self._x = np.ones(p + 1)
        self._over_b = np.zeros(self._forms.shape[1])
        self._form_value = np.zeros(self._forms.shape[1] // (p + 1))
        self._noise_matrix, self._noise_rhs, self._bias_map = self._form_views(self._form_value)
        if input_noise == 'white':
            self._white_forms, self._white_system = self._white_buffers()

    def _q_basis(self) -> np.ndarray:
        """Return the E_j of eq. (61) (colored) or eq. (66) (white) side by side."""
        m, q, lag = self.m, self.q, self.iv_lag
        basis = np.zeros((m, len(self.lags) * q))
        for j, k in enumerate(self.lags):
            for i in range(m):  # row i of eta (0-based) meets b_k through r_dd(|l - 1 - i + k|)
                if self.input_noise == 'colored':
                    basis[i, j * q + abs(lag - 1 - i + k)] = 1.0
                elif i == lag - 1 + k:  # white: Q~ = b~ = [0_l; b; 0_l], eq. (66)
                    basis[i, j * q] = 1.0
        return basis

    def q_tilde(self, b: np.ndarray) -> np.ndarray:
        """Return Q~(b) of eq. (61) or eq. (66), shape ``(m, q)``."""
        basis = self.q_basis.reshape(self.m, len(self.lags), self.q)
        return np.einsum('ijc,j->ic', basis, b)

    # ------------------------------------------------------------ the estimate
    def estimate(self, moments: np.ndarray, regularisation: float, *, mode: str,
                 iterations: int, tolerance: float, start: np.ndarray | None = None,
                 start_noise: float = 0.0) -> BcivResult:
        r"""
        Return the BCIV estimate for the given moments: Step 1, then Steps 3-4 by ``mode``.

        Parameters
        ----------
        moments : numpy.ndarray, shape ``(m, p + 1)``
            :math:`[\bar R, -\bar r]`; :attr:`moments` itself (no copy) or
            any array (copied into it).
        regularisation : float
            :math:`\rho^{-1}\lambda^{2N}`, the :math:`M_0 = \rho I` term of Step 1.
        mode : str
            ``'idle'``: theta_IV only; ``'steps'``: ``iterations``
            alternations from theta_IV (colored); ``'fixed_point'``: the
            white fixed point by at most ``iterations`` secant steps from
            ``start_noise``; ``'printed'``: ``iterations`` alternations from
            ``start`` (theta_IV if None).
        iterations : int
            K, or the cap on secant steps.
        tolerance : float
            Stop once a step changes theta by less than this (2-norm).
        start : numpy.ndarray or None
            theta to start ``'printed'`` from.
        start_noise : float
            N sigma_d^2 to start ``'fixed_point'`` from; 0 makes its first
            step one alternation from theta_IV.

        Returns
        -------
        BcivResult
            theta_IV instead of theta, and a zero gamma, if ``status`` is not
            empty (Q~'XQ~ singular or ill-conditioned, or a runaway: theta
            farther than :data:`COMPENSATION_MAX` relative from theta_IV).

        """
        theta_iv = self._iv_estimate(moments, regularisation)
        iv_norm2 = float(theta_iv.dot(theta_iv))
        if mode == 'idle' or not math.isfinite(iv_norm2):
            # (a non-finite theta_IV: the caller resets the moments)
            return BcivResult(theta_iv, np.zeros(self.q), theta_iv, 0, True, OK)
        if mode == 'fixed_point':
            theta, gamma, done, converged, status = self._white_fixed_point(
                theta_iv, start_noise, iterations, tolerance)
        else:
            first = theta_iv if start is None or mode == 'steps' else start
            theta, gamma, done, converged, status = self._alternate(
                theta_iv, first, iterations, tolerance)
        if status == OK:
            gap = math.dist(theta.tolist(), theta_iv.tolist())
            if not gap * gap <= COMPENSATION_MAX ** 2 * (1.0 + iv_norm2):
                status = RUNAWAY
        if status != OK:
            return BcivResult(theta_iv, np.zeros(self.q), theta_iv, done, False, status)
        return BcivResult(theta, gamma, theta_iv, done, converged, OK)

    def _iv_estimate(self, moments: np.ndarray, regularisation: float) -> np.ndarray:
        r"""
        Step 1, eq. (38): return theta_IV, and keep G E for Steps 3-4.

        One product gives :math:`[M_N^{-1} \mid -\bar R^TW\bar r \mid \bar R^TWE]`
        (before the :math:`\rho^{-1}\lambda^{2N}I` term), one Cholesky solve
        :math:`[-\hat\theta_{IV} \mid GE]`, in place.
        """
        p = self.num_parameters
        if moments is not self.moments:
            self.moments[...] = moments
        if self.iv_weight is not None:
            self._weighted[:, :p + 1] = self.iv_weight.dot(self.moments)
        # rows of R'W [R | -r | E]  (positional out: keywords cost a third of the work)
        self._weighted.T.dot(self.moments[:, :p], self._normal)
        # M_N^-1 = R'WR + rho^-1 lambda^2N I
        self._m_inverse_diagonal += regularisation
        # [-theta_IV | G E] = M_N [-R'W r | R'W E]      (38)
        if dposv(self.m_inverse, self._iv_solution, 0, 0, 1)[2] != 0:
            self._iv_solve_by_lu(regularisation)
        return -self._iv_solution[:, 0]

    def _iv_solve_by_lu(self, regularisation: float) -> None:
        """Redo the solve of Step 1 with LU after the Cholesky factorisation failed (rounding)."""
        p = self.num_parameters
        normal = self._weighted.T.dot(self.moments[:, :p]).T
        normal[:, :p] += regularisation * np.eye(p)
        _, _, solution, info = dgesv(normal[:, :p], normal[:, p:])
        if info != 0 or not np.isfinite(solution).all():
            solution = 0.0
        self._iv_solution[...] = solution

    # ------------------------------------------------- Steps 3-4, the alternation
    def _bilinear_form(self) -> tuple[np.ndarray, np.ndarray]:
        r"""
        Return the tensor C of :meth:`_alternate` (constant entries set) and its per-sample slots.

        C has shape ``(nb + 1, p + 1, width)``, returned as ``(nb + 1, (p + 1) width)``:
        the first axis runs over :math:`[b; 1]`, the second over
        :math:`[\theta; 1]`, the last over :math:`[\bar H, \bar h, \bar D]` of
        :meth:`_form_views`:

        .. math::

            C[j, n+k, \bar H_{:q,:q}] = E_j^TXE_k, \quad
            C[j, t, \bar h_{:q}] = (E_j^TX[\bar R, -\bar r])_{:, t}, \quad
            C[j, p, \bar D_{:, :q}] = GE_j, \quad
            C[nb, p, \bar D_{:, q}] = -\hat\theta_{IV},

        and the border :math:`C[nb, p, \bar H_{q,q}] = 1`,
        :math:`C[nb, p, \bar h_q] = -1`. The slots are the flat indices in C
        of the per-sample numbers, in the order they lie in the sample buffer
        (after :math:`M_N^{-1}`): :math:`-\hat\theta_{IV}`, the rows
        :math:`(GE_j)^T`, then :math:`E_j^TX[\bar R, -\bar r]`.
        """
        n, p, q, nb = self.order, self.num_parameters, self.q, len(self.lags)
        forms = np.zeros((nb + 1, p + 1, (q + 1) * (q + 2 + p)))
        noise_matrix, noise_rhs, _ = self._form_views(forms)
        gram = (self._basis_x @ self.q_basis).reshape(nb, q, nb, q)  # E_j' X E_k
        for j in range(nb):
            for k in range(nb):
                noise_matrix[j, n + k, :q, :q] = gram[j, :, k, :]
        noise_matrix[nb, p, q, q] = 1.0
        noise_rhs[nb, p, q] = -1.0
        # the same views of an array of flat indices tell where each number goes
        _, rhs_slots, bias_slots = self._form_views(np.arange(forms.size).reshape(forms.shape))
        slots = (bias_slots[nb, p, :, q],                      # -theta_IV[i]
                 bias_slots[:nb, p, :, :q].transpose(0, 2, 1),  # (G E_j)[i, c] at [j, c, i]
                 rhs_slots[:nb, :, :q].transpose(0, 2, 1))      # (E_j' X [R | -r])[c, t]
        return (forms.reshape(nb + 1, -1),
                np.concatenate([slot.reshape(-1) for slot in slots]))

    def _form_views(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r"""
        Split the last axis of C (or of its value) into :math:`\bar H, \bar h, \bar D` (views).

        .. math::

            \bar H = \begin{bmatrix} \tilde Q^TX\tilde Q & 0 \\ 0 & 1 \end{bmatrix},
            \quad \bar h = \begin{bmatrix} \tilde Q^TX(\bar R\theta - \bar r) \\ -1
            \end{bmatrix}, \quad
            \bar D = [\,G\tilde Q \mid -\hat\theta_{IV}\,],

        so that :math:`\bar H^{-1}\bar h = [\tilde\gamma; -1]` (eq. 75) and
        :math:`\bar D\,[\tilde\gamma; -1] = \hat\theta_{IV} + G\tilde Q\tilde\gamma`
        (eq. 53). :math:`\bar H` is viewed Fortran-ordered (it is symmetric)
        for an in-place Cholesky solve; :math:`\bar D` is ``(p, q + 1)``.
        """
        size = self.q + 1
        lead = values.shape[:-1]
        matrix_end = size * size
        rhs_end = matrix_end + size
        return (values[..., :matrix_end].reshape(*lead, size, size).swapaxes(-1, -2),
                values[..., matrix_end:rhs_end],
                values[..., rhs_end:].reshape(*lead, self.num_parameters, size))

    def _alternate(self, theta_iv: np.ndarray, start: np.ndarray, iterations: int,
                   tolerance: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        r"""
        Make up to ``iterations`` alternations of Steps 3 and 4 from theta = ``start``.

        One alternation evaluates the bilinear form
        :math:`\sum_{s,t} [b; 1]_s\,[\theta; 1]_t\,C[s, t, :] = [\bar H, \bar h, \bar D]`
        (:meth:`_bilinear_form`) by two products, solves eq. (75) in place by
        Cholesky and takes eq. (53) as one product: four numpy/LAPACK calls,
        which at these sizes cost more than the arithmetic. The step is
        checked every :data:`CHECK_PERIOD` alternations and after the last;
        the loop stops once it is below ``tolerance``.

        Returns
        -------
        theta, gamma, iterations, converged, status
            ``gamma`` is :math:`N\tilde\gamma` of the last step; ``status`` is
            ``''`` or :data:`SINGULAR`/:data:`RUNAWAY`.

        """
        n, p, q = self.order, self.num_parameters, self.q
        forms = self._forms
        # this sample's -theta_IV, G E_j and E_j' X [R | -r] into C
        self._basis_x.dot(self.moments, self._noise_moments)
        forms.reshape(-1)[self._form_slots] = self._sample_numbers[p * p:]
        over_b, values = self._over_b, self._form_value
        noise_matrix, noise_rhs = self._noise_matrix, self._noise_rhs
        x = self._x
        theta, b_one = x[:p], x[n:]
        theta[...] = start
        # bound methods, positional arguments: at these sizes call overhead is the cost
        sum_over_b, sum_over_theta = b_one.dot, x.dot
        over_b_2d, step_4 = over_b.reshape(p + 1, -1), self._bias_map.dot
        converged, done = False, 0
        for check in _check_schedule(iterations):
            done += 1
            # [Hbar, hbar, Dbar] at b = theta[n:]
            sum_over_b(forms, over_b)
            sum_over_theta(over_b_2d, values)
            # Step 3, eq. (75): hbar <- Hbar^-1 hbar = [gamma; -1]
            if dposv(noise_matrix, noise_rhs, 0, 1, 1)[2] != 0:
                return theta.copy(), noise_rhs[:q].copy(), done, False, SINGULAR
            if not check:
                # Step 4, eq. (53): theta = theta_IV + G Q~ gamma = Dbar [gamma; -1]
                step_4(noise_rhs, theta)
                continue
            previous = theta.tolist()
            step_4(noise_rhs, theta)
            change = math.dist(theta.tolist(), previous)
            if not math.isfinite(change):
                return theta.copy(), noise_rhs[:q].copy(), done, False, RUNAWAY
            if change <= tolerance:
                converged = True
                break
        if done == 0:
            return theta.copy(), np.zeros(q), 0, False, OK
        # noise_matrix holds the Cholesky factor of Q~'XQ~: cond >= (max/min diagonal)^2
        diagonal = noise_matrix.diagonal()[:q].tolist()
        if not min(diagonal) * math.sqrt(CONDITION_MAX) > max(diagonal):
            return theta.copy(), noise_rhs[:q].copy(), done, converged, SINGULAR
        return theta.copy(), noise_rhs[:q].copy(), done, converged, OK

    # ------------------------------------------------ white input noise
    def _white_buffers(self) -> tuple[np.ndarray, np.ndarray]:
        r"""
        Return the buffers of f(sigma) of :meth:`_white_fixed_point`, bordered for u = [b; 1].

        The forms, ``(3, nb + 1, nb + 1)``: :math:`E^TXE` (constant),
        :math:`K_1`, and :math:`c_0` in the last row (both set per sample), so
        that :math:`u^T F_0 u = b^TE^TXEb`, :math:`u^T F_1 u = b^TK_1b` and
        :math:`u^T F_2 u = c_0^Tb`. The system, ``(2, nb + 1, nb + 1)``: the
        identity and :math:`[GE]_b` (set per sample) with a zero border, so that
        :math:`(I - \sigma [GE]_b)\,b = \hat b_{IV}` bordered by :math:`1 = 1`
        has the solution u.
        """
        nb = len(self.lags)
        forms = np.zeros((3, nb + 1, nb + 1))
        forms[0, :nb, :nb] = self._basis_x @ self.q_basis
        system = np.zeros((2, nb + 1, nb + 1))
        system[0] = np.eye(nb + 1)
        return forms, system

    def _white_fixed_point(self, theta_iv: np.ndarray, start: float, max_steps: int,
                           tolerance: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        r"""
        Return the fixed point of Steps 3-4 with white input noise (eqs. 65-67).

        With :math:`\tilde Q = \tilde b` (eq. 66) and :math:`\sigma = N\sigma_d^2`,
        a fixed point satisfies :math:`\theta = \hat\theta_{IV} + \sigma\,GEb`
        (eq. 53), so for a given :math:`\sigma` its b-part solves an n x n
        system, and eq. (75) becomes a scalar equation :math:`\sigma = f(\sigma)`:

        .. math::

            (I - \sigma [GE]_b)\, b(\sigma) = \hat b_{IV}, \qquad
            f(\sigma) = \frac{c_0^Tb + \sigma\, b^TK_1b}{b^TE^TXE\,b}, \quad
            c_0 = E^TX(\bar R\hat\theta_{IV} - \bar r), \ K_1 = E^TX\bar R\,GE.

        The plain alternation converges slowly, if at all (``docs/bciv.md``),
        so the root is found by the secant method from ``start``
        (the previous :math:`N\hat\sigma_d^2`, or 0, whose first step is one
        alternation from theta_IV). The estimate is
        :math:`\hat\theta_{IV} + f(\sigma_k)\,GE\,b(\sigma_k)`. If the scalar
        equation breaks down, the plain alternation is iterated instead.
        """
        n, p = self.order, self.num_parameters
        nb = p - n
        gain = self._iv_solution[:, 1:]  # G E, (p, nb)
        self._basis_x.dot(self.moments, self._noise_moments)  # E'X [R | -r]
        forms = self._white_forms
        forms[1, :nb, :nb] = self._noise_moments[:, :p].dot(gain)  # K_1
        x = self._x  # [theta_IV; 1]
        x[:p] = theta_iv
        forms[2, nb, :nb] = self._noise_moments.dot(x)  # c_0
        # bordered by a unit row, one solve gives u = [b(sigma); 1]:
        # [[I - sigma [GE]_b, 0], [0, 1]] u = [b_IV; 1]
        identity, gain_b = self._white_system
        gain_b[:nb, :nb] = gain[n:]
        b_iv = x[n:].copy()
        # a change of sigma moves theta by |G E b| times it, and b starts at b_IV
        direction = gain.dot(theta_iv[n:])
        scale = math.sqrt(direction.dot(direction))
        tolerance_sigma = tolerance / scale if scale > 0.0 else math.inf

        def by_lapack(sigma: float) -> tuple[float | None, Any]:
            """Return the value of f and [b; 1] at sigma, or None if either is undefined."""
            _, _, u, info = dgesv(identity - sigma * gain_b, b_iv)
            if info != 0:
                return None, None
            denominator, curvature, linear = forms.dot(u).dot(u).tolist()
            if not denominator > 0.0:
                return None, None
            return (linear + sigma * curvature) / denominator, u

        # for n <= 2 the same f on Python floats: there the calls cost more than the sums
        f = by_lapack if nb > 2 else _small_white_function(
            gain_b[:nb, :nb].tolist(), b_iv[:nb].tolist(), forms[0, :nb, :nb].tolist(),
            forms[1, :nb, :nb].tolist(), forms[2, nb, :nb].tolist())
        # secant steps on phi(sigma) = sigma - f(sigma)
        s_0 = float(start)
        f_1, u = f(s_0)
        done = 1
        if f_1 is None:
            return self._plain_white(theta_iv, max_steps, tolerance)
        s_1, phi_0 = f_1, s_0 - f_1
        converged = abs(phi_0) <= tolerance_sigma
        while not converged and done < max_steps:
            f_1, u = f(s_1)
            done += 1
            if f_1 is None or not math.isfinite(f_1):
                return self._plain_white(theta_iv, max_steps, tolerance)
            phi_1 = s_1 - f_1
            if abs(phi_1) <= tolerance_sigma:
                converged = True
                break
            slope = phi_1 - phi_0
            s_next = f_1 if slope == 0.0 else s_1 - phi_1 * (s_1 - s_0) / slope
            s_0, phi_0, s_1 = s_1, phi_1, s_next
        # Step 4, eq. (53): theta = theta_IV + sigma G E b
        theta = theta_iv + gain.dot(u[:nb]) * f_1
        return theta, np.array([f_1]), done, converged, OK

    def _plain_white(self, theta_iv: np.ndarray, max_steps: int,
                     tolerance: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        """Iterate the plain alternation from theta_IV (the fallback of the secant method)."""
        return self._alternate(theta_iv, theta_iv, max(max_steps, 200), tolerance)

    # ------------------------------------------------------------- windows
    def window_indices(self) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the gathers of eta and [p; -z] from the flattened history window.

        The window has rows k = 0..m-1 holding ``[-z(t-k), w(t-k)]``. With the
        causal delay of eqs. (68)-(70) (t' = t - l + 1), eq. (54) is
        eta_t' = [w(t), ..., w(t-m+1)] and p_t' = [-z(t'-1..t'-n), w(t'-k0..t'-n)].
        """
        n, lag = self.order, self.iv_lag
        eta = np.array([2 * i + 1 for i in range(self.m)], dtype=np.intp)
        pz = [2 * (lag - 1 + j) for j in range(1, n + 1)]
        pz += [2 * (lag - 1 + j) + 1 for j in self.lags]
        pz.append(2 * (lag - 1))
        return eta, np.array(pz, dtype=np.intp)

    def data_windows(self, z: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return eta_t' ``(N', m)`` and [p_t'; -z_t'] ``(N', p + 1)`` for whole arrays.

        Row j belongs to the (j+1)-th update of the recursive form, at sample
        t = m - 1 + j.
        """
        m, n, lag = self.m, self.order, self.iv_lag
        t = np.arange(m - 1, z.shape[0])
        eta = np.stack([w[t - i] for i in range(m)], axis=1)
        columns = [-z[t - (lag - 1 + j)] for j in range(1, n + 1)]
        columns += [w[t - (lag - 1 + j)] for j in self.lags]
        columns.append(-z[t - (lag - 1)])
        return eta, np.stack(columns, axis=1)


def _small_white_function(gain: list[list[float]], b_iv: list[float], gram: list[list[float]],
                          curvature_form: list[list[float]], linear_form: list[float]
                          ) -> Callable[[float], tuple[float | None, list[float] | None]]:
    r"""
    Return f(sigma) of :meth:`BcivSolver._white_fixed_point` for nb <= 2, on Python floats.

    The same function as there: b solves :math:`(I - \sigma [GE]_b)\,b = \hat b_{IV}`,
    here by Cramer's rule (an n x n system with n <= 2), and the three forms are
    written out; LAPACK and numpy calls cost more than this arithmetic. Returns
    (None, None) where the system is singular or the denominator not positive.
    """
    size = len(b_iv)

    def f(sigma: float) -> tuple[float | None, list[float] | None]:
        if size == 1:
            determinant = 1.0 - sigma * gain[0][0]
            if determinant == 0.0:
                return None, None
            b = [b_iv[0] / determinant]
        else:
            (g00, g01), (g10, g11) = gain
            a00, a01, a10, a11 = 1.0 - sigma * g00, -sigma * g01, -sigma * g10, 1.0 - sigma * g11
            determinant = a00 * a11 - a01 * a10
            if determinant == 0.0:
                return None, None
            b = [(a11 * b_iv[0] - a01 * b_iv[1]) / determinant,
                 (a00 * b_iv[1] - a10 * b_iv[0]) / determinant]
        denominator = curvature = linear = 0.0
        for i in range(size):
            linear += linear_form[i] * b[i]
            for j in range(size):
                product = b[i] * b[j]
                denominator += gram[i][j] * product
                curvature += curvature_form[i][j] * product
        if not denominator > 0.0:
            return None, None
        return (linear + sigma * curvature) / denominator, b
    return f


@functools.lru_cache(maxsize=None)
def _check_schedule(iterations: int) -> tuple[bool, ...]:
    """Return, per alternation, whether to check its step (every CHECK_PERIOD-th and the last)."""
    return tuple((k + 1) % CHECK_PERIOD == 0 or k + 1 == iterations for k in range(iterations))


def _weight(name: str, value: Any, m: int) -> np.ndarray:
    """Return a checked (m, m) symmetric positive definite weighting matrix."""
    matrix = np.array(value, dtype=float)
    if matrix.shape != (m, m):
        raise ValueError(f'{name} must have shape ({m}, {m}), got {matrix.shape}')
    if not np.isfinite(matrix).all() or not np.allclose(matrix, matrix.T) or \
            np.linalg.eigvalsh(matrix).min() <= 0.0:
        raise ValueError(f'{name} must be symmetric positive definite')
    return matrix


class Bciv(RecursiveEstimator):
    r"""
    Recursive BCIV-type estimator for errors-in-variables models (Ikenoue et al. 2008).

    The data are the noisy output z_t (the published ``y``) and the noisy
    input w_t (``u``), SISO. With the IV-type vector (54), delayed by l - 1
    samples as in eqs. (68)-(70), every sample updates the moments (Step 2,
    unnormalised: :math:`\bar R = N\hat R_{\eta p}`, :math:`\bar r = N\hat r_{\eta z}`)
    and then computes the estimate from them with :class:`BcivSolver`:

    .. math::

        [\bar R_N,\ -\bar r_N] &= \lambda [\bar R_{N-1},\ -\bar r_{N-1}]
            + \eta_N [p_N^T,\ -z_N] && \text{Step 2} \\
        \hat\theta_{IV,N} &= (\bar R^T W \bar R + \rho^{-1}\lambda^{2N} I)^{-1}
            \bar R^T W \bar r && \text{Step 1, eq. (38), } M_0 = \rho I \\
        \tilde\gamma_{k+1} &= (\tilde Q_k^T X \tilde Q_k)^{-1} \tilde Q_k^T X
            (\bar R\theta_k - \bar r) && \text{Step 3, eq. (75)} \\
        \theta_{k+1} &= \hat\theta_{IV,N} + (\bar R^T W \bar R
            + \rho^{-1}\lambda^{2N} I)^{-1} \bar R^T W \tilde Q_k \tilde\gamma_{k+1}
            && \text{Step 4, eq. (53)}

    with :math:`\tilde Q_k = \tilde Q(b_k)` of eq. (61) (colored, noise vector
    (64): r_dd(0..n+l-1)) or eq. (66) (white, (67): sigma_d^2). The estimate at
    sample N is, by ``input_noise`` and ``bciv_update``:

    * colored, ``converged``: K = ``bciv_iterations`` alternations from
      :math:`\theta_0 = \hat\theta_{IV,N}`, stopping early below ``tolerance``;
    * white, ``converged``: a fixed point of the alternation, warm-started from
      the previous estimate (the secant method on the equivalent scalar
      equation in sigma_d^2, at most K steps; see :class:`BcivSolver`);
    * ``printed``: one alternation from the previous estimate (Steps 3-4 as
      printed).

    :math:`\hat\theta_{IV,N}` is that of the rank-2 recursion of Step 1 (it
    sums to the matrix above; ``docs/bciv.md``). For T < L = ``idle_samples``
    the estimate is :math:`\hat\theta_{IV,T}` (initial value selection of
    section 4).

    **Forgetting factor** (an extension): with exponential weights
    :math:`\lambda^{N-t}` the weighted moments normalised by
    :math:`\tau_N = \sum\lambda^{N-t}` have the same limits (71)-(72) on
    stationary data, so the same equations hold with
    :math:`\hat R_{\eta p} = \bar R/\tau_N`; the noise estimates are
    :math:`N\tilde\gamma/\tau_N`.

    **Safeguards** (counted in :attr:`flags`; the estimate stays finite):

    * ``fallback_iv``: :math:`\tilde Q^TX\tilde Q` is singular or its condition
      number exceeds ``CONDITION_MAX`` (b ~ 0, no excitation), or the
      alternation ran away; the estimate is :math:`\hat\theta_{IV,N}` for this
      sample, and the next sample tries again from it. The reason is counted
      too, as ``noise_system_singular`` or ``compensation_runaway``;
    * ``not_converged``: the white fixed point was not reached within K steps
      (the last iterate is used, and the next sample continues from it);
    * ``moments_reset``: the moments overflowed; they restart from zero.

    **Units.** :math:`M_0 = \rho S^{-2}` with
    :math:`S = s_w\,\mathrm{diag}(s_z I_n, s_w I)`, where :math:`s_z`,
    :math:`s_w` are the smallest powers of two at or above the peaks of z and
    w in the first full window (:func:`regularisation_weights`): Step 1 on
    the normalised signals with :math:`M_0 = \rho I`, mapped back exactly.
    The estimates do not depend on the units of z and w, and
    ``initial_covariance`` is rho for signals of unit size.

    **Outlier gate** (``outlier_threshold``, the base class's
    :meth:`~bcid_ros.estimators.base.RecursiveEstimator._gate`): before a
    sample enters the window its squared normalised one-step error is the
    larger of

    * :math:`\varepsilon^2/\bar\varepsilon^2`, the equation error
      :math:`\varepsilon(t) = z(t) - p(t)^T\hat\theta_{BCIV}` of the undelayed
      ARX equation (p(t) from the previous n samples) over its weighted mean
      square since the estimator became ready (z(t)^2 over its mean square
      while the window refills after a restart, when p(t) is not known);
    * :math:`w(t)^2/\bar w^2`: w(t) enters the IV-type vector (54) at once,
      l - 1 samples before it enters a regressor, so the input's size is
      tested as it arrives.

    The gate tests once ``GATE_WARMUP`` p equation errors were measured. A
    detected plant change cuts the memory to ``CHANGE_MEMORY`` m samples
    (moments and tau times kappa, lambda^2N times kappa^2) and the gate
    relearns its scales.

    **Validity**, re-evaluated every ``VALIDITY_PERIOD`` updates: the
    compensated model is unstable (a pole beyond ``UNSTABLE_RADIUS``) while
    the output's mean square did not grow ``GROWTH`` times since the last
    check; the estimate fell back to theta_IV (ill-conditioned
    :math:`\tilde Q^TX\tilde Q` or runaway) since the last check, or at this
    sample; the compensation moved farther than ``RUNAWAY_SHIFT`` times
    :math:`|\hat\theta_{IV}|` from theta_IV (normalised units).

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`; only
        ``num_inputs=1``. ``initial_covariance`` is rho of M_0 = rho I in
        normalised units (see Units).
    input_delay, detrend, adapt, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`. A dead
        time d shifts the input history by d (see :meth:`_push`).
    iv_lag : int
        l >= 1 of eq. (54); m = n + 2l.
    input_noise : str
        ``'colored'`` (eqs. 59-64) or ``'white'`` (eqs. 65-67).
    idle_samples : int
        L: the estimate is theta_IV for the first L updates.
    bciv_iterations : int
        K, alternations per sample (colored), or the cap of the white solver.
    bciv_update : str
        ``'converged'`` (the definitions above) or ``'printed'``.
    allow_underdetermined : bool
        Run even if eq. (72) has fewer equations than unknowns (l < 2n
        colored); see :func:`check_structure`.
    tolerance : float
        Stop the iterations once a step's 2-norm is below this.
    iv_weight, noise_weight : array_like or None
        W and X of eqs. (38) and (74), ``(m, m)``; None (the default, as in
        the paper's examples) is the identity. Not ROS parameters.

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    name = 'bciv'
    #: Extra constructor keywords that are ROS parameters (docs/nodes.md).
    options: tuple[str, ...] = ('iv_lag', 'input_noise', 'idle_samples', 'bciv_iterations',
                                'bciv_update', 'allow_underdetermined')
    _guarded_update = RecursiveEstimator._step_transaction

    def __init__(self, *, iv_lag: int = 5, input_noise: str = 'colored',
                 idle_samples: int = 100, bciv_iterations: int = 20,
                 bciv_update: str = 'converged', allow_underdetermined: bool = False,
                 tolerance: float = DEFAULT_TOLERANCE, iv_weight: Any = None,
                 noise_weight: Any = None, **settings: Any) -> None:
        super().__init__(**settings)
        if self.num_inputs != 1:
            raise ValueError(f'num_inputs must be 1 for bciv (the IV-type vector of eq. (54) '
                             f'is built for a single input), got {self.num_inputs}')
        self.iv_lag = check_int('iv_lag', iv_lag, 1)
        if input_noise not in INPUT_NOISE:
            raise ValueError(f"input_noise must be 'colored' or 'white', got {input_noise!r}")
        if bciv_update not in UPDATES:
            raise ValueError(f"bciv_update must be 'converged' or 'printed', got "
                             f'{bciv_update!r}')
        if not isinstance(allow_underdetermined, (bool, np.bool_)):
            raise ValueError(f'allow_underdetermined must be true or false, got '
                             f'{allow_underdetermined!r}')
        self.input_noise = input_noise
        self.bciv_update = bciv_update
        self.allow_underdetermined = bool(allow_underdetermined)
        self.idle_samples = check_int('idle_samples', idle_samples, 0)
        self.bciv_iterations = check_int('bciv_iterations', bciv_iterations, 1)
        self.tolerance = check_range('tolerance', tolerance, 0.0, 1.0)
        check_structure(self.order, self.iv_lag, self.feedthrough, input_noise,
                        self.allow_underdetermined)
        self._solver = BcivSolver(order=self.order, iv_lag=self.iv_lag,
                                  feedthrough=self.feedthrough, input_noise=input_noise,
                                  iv_weight=iv_weight, noise_weight=noise_weight)
        solver = self._solver
        self.noise_names = (('sigma2_d',) if input_noise == 'white'
                            else tuple(f'r_dd{k}' for k in range(solver.q)))
        self._mode = ('printed' if bciv_update == 'printed'
                      else 'fixed_point' if input_noise == 'white' else 'steps')
        self._iterations = 1 if bciv_update == 'printed' else self.bciv_iterations
        # The sample history is a ring of [-z, w] pairs written backwards, so
        # that the newest m samples are the contiguous window
        # ring[start:start + 2m] (row k of its (m, 2) view: sample t - k).
        self._ring = np.zeros(2 * (RING_SAMPLES + solver.m))
        self._start = 2 * RING_SAMPLES
        # the delay line of the last d inputs (input_delay, see _push)
        self._delay = self.input_delay[0]
        self._line = np.zeros(self._delay)
        self._gather = np.concatenate(solver.window_indices())
        # p(t) of the undelayed ARX equation from the newest n rows of the window
        # (before the push): -z(t-j) at 2(j-1), w(t-j) at 2(j-1) + 1
        lags = [k for k in solver.lags if k > 0]
        self._error_gather = np.array([2 * (j - 1) for j in range(1, self.order + 1)]
                                      + [2 * (k - 1) + 1 for k in lags], dtype=np.intp)
        self._error_theta = np.array(list(range(self.order)) + [
            self.order + i for i, k in enumerate(solver.lags) if k > 0], dtype=np.intp)
        # what a step may change, for the transaction; not the history window, which the
        # undo's restart empties
        self._name_step_state(
            ('_theta_iv', '_theta_bciv', '_gamma', '_filled', '_tau', '_decay', '_line_position',
             '_line_filled', '_updates', '_iterations_used', '_signal_count', '_error_count',
             '_input_power', '_output_power', '_error_power', '_next_check', '_last_power',
             '_fallbacks_checked', '_reasons', '_last_status', '_signal_scale'),
            ('_moments', '_line') if self._delay else ('_moments',))
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        w = float(u[0])
        # the gate tests the raw input's size, and the equation error of z(t) with the
        # input that enters the history now, w(t - d) (None while the delay line fills)
        delayed = self._delayed_input(w)
        error = (self._equation_error(y, delayed) if delayed is not None
                 and self._filled >= self.order and self._updates >= self._ready_count
                 else None)
        if self._error_count >= self._gate_from:
            z2 = self._gate_score(y, w, error)
            # (while the regressor refills only the sizes are tested: the change score waits)
            if not z2 <= self._gate_limit2 or (self._change_score and error is not None):
                if not self._gate(z2):
                    return
        self._track_signals(y, w, error)
        if not self._push(y, w):
            return
        if self._scales_pending:
            self._choose_scales()
        m = self._solver.m
        start = self._start
        # [eta; p; -z] of eqs. (54), (68)-(70)
        sample = self._ring[start:start + 2 * m][self._gather]
        lam = self._forgetting_factor
        if lam != 1.0:
            self._moments *= lam
        # [R | -r] = lambda [R | -r] + eta [p', -z]      (Step 2, unnormalised, in place)
        dger(1.0, sample[:m], sample[m:], 1, 1, self._moments, 1, 1, 1)
        # tau = lambda tau + 1 ; decay = lambda^2N
        self._tau = lam * self._tau + 1.0
        self._decay *= lam * lam
        self._updates += 1
        self._estimate()
        if self._updates >= self._next_check:
            self._check_validity()
        if self._updates >= self._blocks.next_boundary:
            self._close_block()

    def _delayed_input(self, w: float) -> float | None:
        """Return the input w(t - d) that the next push adds, or None while the line fills."""
        delay = self._delay
        if not delay:
            return w
        if self._line_filled < delay:
            return None
        return float(self._line[self._line_position])

    def _push(self, z: float, w: float) -> bool:
        """
        Add sample (z(t), w(t - d)) to the history; return whether the window is full.

        With a dead time d the history pairs z(t) with w(t - d), read from a
        delay line of the last d inputs: the IV-type vector and p_t then
        shift together by d, so that eqs. (54)-(75) hold unchanged for the
        shifted input (docs/bciv.md, "Dead time"). The first d samples only
        fill the delay line.
        """
        delay = self._delay
        if delay:
            position = self._line_position
            delayed = self._line[position]
            self._line[position] = w
            self._line_position = position + 1 if position + 1 < delay else 0
            if self._line_filled < delay:
                self._line_filled += 1
                return False
            w = delayed
        m = self._solver.m
        ring = self._ring
        start = self._start - 2
        if start < 0:
            # move the newest m - 1 samples to the end of the ring
            start = 2 * RING_SAMPLES
            ring[start + 2:] = ring[:2 * m - 2]
        ring[start] = -z
        ring[start + 1] = w
        self._start = start
        if self._filled < m:
            self._filled += 1
            return self._filled == m
        return True

    def _hold(self, y: float, u: np.ndarray) -> None:
        """Move the history on without touching the moments or the estimate."""
        self._push(y, u[0])

    def _estimate(self) -> None:
        """Compute theta_IV,N and theta_BCIV,N from the moments."""
        regularisation = self._regularisation()
        mode = 'idle' if self._updates < self.idle_samples else self._mode
        theta, gamma, theta_iv, done, converged, status = self._solver.estimate(
            self._moments, regularisation, mode=mode, iterations=self._iterations,
            tolerance=self.tolerance, start=self._theta_bciv,
            start_noise=self._gamma[0] * self._tau)
        if not math.isfinite(theta_iv.dot(theta_iv)):
            self._flag('moments_reset')
            self._moments[...] = 0.0
            self._tau, self._decay, self._updates = 0.0, 1.0, 0
            return
        self._theta_iv = theta_iv
        self._theta_bciv = theta
        self._iterations_used = done
        self._last_status = status
        if status:
            self._flag('fallback_iv')
            self._flag(status)
        elif mode != 'idle':
            self._gamma = gamma * (1.0 / self._tau)
            if mode == 'fixed_point' and not converged:
                self._flag('not_converged')
            if self._gamma[0] < 0.0:
                # a finite-sample estimate of a variance below zero (see _noise)
                self._flag('negative_variance')

    # ----------------------------------------------------------- the gate
    def _equation_error(self, y: float, w: float) -> float:
        """Return the one-step equation error z(t) - p(t)' theta_BCIV of the new sample."""
        window = self._ring[self._start:self._start + 2 * self.order]
        theta = self._theta_bciv
        error = y - float(window[self._error_gather].dot(theta[self._error_theta]))
        if self.feedthrough:
            error -= float(theta[self.order]) * w
        return error

    def _gate_score(self, y: float, w: float, error: float | None) -> float:
        """Return the squared normalised one-step error of a new sample (class docstring)."""
        score = w * w / self._input_power if self._input_power > 0.0 else 0.0
        if error is not None:
            part = error * error / (self._error_power + self._error_floor)
        else:  # the regressor refills after a restart: the output's own size
            part = y * y / self._output_power if self._output_power > 0.0 else 0.0
        return part if part > score else score

    def _track_signals(self, y: float, w: float, error: float | None) -> None:
        """Add an accepted sample to the weighted mean squares of w, z and the equation error."""
        lam = self._forgetting_factor
        self._signal_count = lam * self._signal_count + 1.0
        weight = 1.0 / self._signal_count
        self._input_power += (w * w - self._input_power) * weight
        self._output_power += (y * y - self._output_power) * weight
        if error is not None:
            self._error_count = lam * self._error_count + 1.0
            self._error_power += (error * error - self._error_power) / self._error_count

    def _accept_change(self) -> None:
        """Cut the memory to CHANGE_MEMORY m samples and let the gate relearn its scales."""
        keep = CHANGE_MEMORY * self._solver.m / self._tau if self._tau > 0.0 else 1.0
        if keep < 1.0:
            self._moments *= keep
            self._tau *= keep
            self._decay *= keep * keep  # the prior keeps its weight against R'WR
        self._signal_count = min(self._signal_count, 1.0)
        self._error_count = 0.0

    # ---------------------------------------------------------- the units
    def _choose_scales(self) -> None:
        """Give z and w, if still without a scale, the power of two of the window's peak."""
        peaks = np.abs(self._history).max(axis=0)
        scales = self._signal_scale.copy()
        for channel in (0, 1):
            if scales[channel] == 0.0 and peaks[channel] > 0.0:
                scales[channel] = power_of_two_at_least(float(peaks[channel]))
        self._signal_scale = scales
        self._set_scale_dependents()

    def _set_scale_dependents(self) -> None:
        scales = self._signal_scale
        self._scales_pending = bool((scales == 0.0).any())
        z_scale, w_scale = (float(s) if s > 0.0 else 1.0 for s in scales)
        self._regularisation_weights = regularisation_weights(
            z_scale, w_scale, self.order, self.num_parameters)
        self._error_floor = (VARIANCE_FLOOR * z_scale) ** 2
        self._regularised_decay = math.nan  # recompute the M_0 term
        self._normalised_units = np.ones(self.num_parameters)
        self._normalised_units[self.order:] = w_scale / z_scale

    def _regularisation(self) -> np.ndarray:
        """Return the M_0 term rho^-1 lambda^2N S^2 of Step 1 in the user's units."""
        if self._decay != self._regularised_decay:  # (cached: constant without forgetting)
            self._regularised_decay = self._decay
            self._regularisation_term = (self._decay / self.initial_covariance) * \
                self._regularisation_weights
        return self._regularisation_term

    @property
    def signal_scale(self) -> np.ndarray:
        """Return the scales of z and w (0 while a channel has only seen zeros)."""
        return self._signal_scale.copy()

    @property
    def initial_covariance_diagonal(self) -> np.ndarray:
        """Return the diagonal of M_0 = rho S^-2 in the user's units (see the class docstring)."""
        return self.initial_covariance / self._regularisation_weights

    # ------------------------------------------------------- the validity
    def _check_validity(self) -> None:
        self._next_check = self._updates + VALIDITY_PERIOD
        with np.errstate(all='ignore'):
            self._reasons = tuple(self._find_problems())

    def _find_problems(self) -> list[str]:
        """Return the reasons not to trust the estimate now (see the class docstring)."""
        reasons = []
        power = self._output_power
        bounded = not power > GROWTH * self._last_power
        self._last_power = power
        radius = spectral_radius(self._theta_bciv[:self.order])
        if not radius <= UNSTABLE_RADIUS and bounded:
            reasons.append(f'unstable model (pole radius {radius:.3g}) on bounded data')
        fallbacks = self.flags.get('fallback_iv', 0)
        if fallbacks > self._fallbacks_checked:
            reasons.append(f'ill-conditioned or runaway compensation (fell back to theta_IV '
                           f'{fallbacks - self._fallbacks_checked} times)')
        self._fallbacks_checked = fallbacks
        units = self._normalised_units
        shift = float(np.linalg.norm(units * (self._theta_bciv - self._theta_iv)))
        size = float(np.linalg.norm(units * self._theta_iv))
        if not shift <= RUNAWAY_SHIFT * size:
            reasons.append(f'compensation runs away from IV ({shift / size:.3g} x |theta_IV|)'
                           if size > 0 else 'compensation runs away from IV')
        return reasons

    def _validity_reasons(self) -> tuple[str, ...]:
        if self._last_status:
            return self._reasons + (f'compensation fell back to theta_IV ({self._last_status})',)
        return self._reasons

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether eta is filled, L updates are done and at least p updates were made."""
        return self._updates >= self._ready_count

    @property
    def samples(self) -> int:
        """Count the estimator updates (samples with a filled IV-type vector)."""
        return self._updates

    @property
    def covariance_trace(self) -> float:
        """Return tr M_N of Step 1, M_N = (R'WR + rho^-1 lambda^2N S^2)^-1 (a health indicator)."""
        if self._updates == 0:
            return float((self.initial_covariance / self._regularisation_weights).sum())
        try:
            return float(np.trace(np.linalg.inv(self._solver.m_inverse)))
        except np.linalg.LinAlgError:
            return float('inf')

    @property
    def last_iterations(self) -> int:
        """Return the number of alternations (or secant steps) of the last sample."""
        return self._iterations_used

    def _theta(self) -> np.ndarray:
        return self._theta_bciv

    def _theta_uncompensated(self) -> np.ndarray:
        return self._theta_iv

    def _noise(self) -> np.ndarray:
        # The raw gamma stays in the state: the next white fixed point starts from it.
        return published_noise(self._gamma)

    # ------------------------------------------------------- the uncertainty
    def _parameter_covariance(self) -> np.ndarray | None:
        r"""
        Return the delta-method covariance of theta_BCIV from block means of the moments.

        The estimate is a smooth function of the weighted means of Step 2,
        :math:`\hat\theta = F(\bar S/\tau)`, :math:`\bar S = [\bar R, -\bar r]`
        (K alternations of eqs. (75)/(53) from eq. (38) colored, the fixed
        point of eqs. (65)-(67) white). So

        .. math::

            \mathrm{cov}\,\hat\theta = \frac{\tau_2}{\tau^2} J\Omega J^T, \qquad
            J = \partial F/\partial(\bar S/\tau),

        with :math:`\Omega` the long-run covariance of the per-sample terms
        :math:`\eta_t[p_t^T, -z_t]` (coloured through u, d and e), from the
        spread of the sums over blocks of updates, and J by central
        differences of F (a separate :class:`BcivSolver`) at a block boundary
        (:mod:`bcid_ros.estimators.moment_covariance`). None before
        :attr:`ready`, before 16 blocks (512 updates), with
        ``bciv_update='printed'`` (its estimate is not a function of the
        moments) and after a restored state until 16 new blocks.

        Not exact: the share of true parameters within +-2 std, measured over
        200 runs (docs/estimators.md, "Uncertainty"), is 90-94 % per parameter
        on Ikenoue's colored example at N = 1000 and 10000 (b1_1: 89.5 % at
        10000), 94-97 % white at N = 10000, but 85.5 % for b1_2 white at
        N = 1000, where the alternation can end at a spurious fixed point (b
        near 0) and the std is far too small; 96 % on the runs still valid.
        """
        if not self.ready or self.bciv_update == 'printed':
            return None
        return self._blocks.covariance(self._tau, self._forgetting_factor)

    def _close_block(self) -> None:
        """Hand the moment sums of a block boundary to the block means."""
        self._blocks.close(self._updates, self._moments, self._tau, self._forgetting_factor, 0,
                           self._moment_function)

    def _moment_function(self) -> Any:
        """Return F: the estimate from the weighted means of [R | -r], as :meth:`_estimate`."""
        settings = dict(order=self.order, iv_lag=self.iv_lag, feedthrough=self.feedthrough,
                        input_noise=self.input_noise, iv_weight=self._solver.iv_weight,
                        noise_weight=self._solver.noise_weight)
        solvers: list[BcivSolver] = []  # built at the first read, not at the boundary
        shape = self._moments.shape
        # M_N^-1 of the means: R'WR / tau^2 + rho^-1 lambda^2N S^2 / tau^2
        regularisation = self._regularisation() / (self._tau * self._tau)
        mode, iterations, tolerance = self._mode, self._iterations, self.tolerance
        noise = float(self._gamma[0])

        def estimate(means: np.ndarray) -> np.ndarray:
            if not solvers:
                solvers.append(BcivSolver(**settings))
            return solvers[0].estimate(means.reshape(shape), regularisation, mode=mode,
                                       iterations=iterations, tolerance=tolerance,
                                       start_noise=noise).theta.copy()
        return estimate

    # -------------------------------------------------------------- the state
    @property
    def _history(self) -> np.ndarray:
        """Return the (m, 2) window of [-z, w] (row k: sample t - k), a view into the ring."""
        return self._ring[self._start:self._start + 2 * self._solver.m].reshape(-1, 2)

    def _reset(self) -> None:
        p = self.num_parameters
        self._ring[:] = 0.0
        self._start = 2 * RING_SAMPLES
        self._filled = 0
        self._line[:] = 0.0
        self._line_position = 0
        self._line_filled = 0
        #: The moments [R | -r] of Step 2 live in the solver's buffer, updated in place.
        self._moments = self._solver.moments
        self._moments[...] = 0.0
        self._tau = 0.0
        self._decay = 1.0
        self._updates = 0
        self._theta_iv = np.zeros(p)
        self._theta_bciv = np.zeros(p)
        self._gamma = np.zeros(self._solver.q)
        self._iterations_used = 0
        self._ready_count = max(self.idle_samples, p)
        self._gate_from = GATE_WARMUP * p
        self._signal_scale = np.zeros(2)
        self._set_scale_dependents()
        self._signal_count = self._error_count = 0.0
        self._input_power = self._output_power = self._error_power = 0.0
        self._next_check = VALIDITY_PERIOD
        self._last_power = math.inf
        self._fallbacks_checked = 0
        self._reasons: tuple[str, ...] = ()
        self._last_status = OK
        self._blocks = MomentBlocks()

    def _restart_regressor(self) -> None:
        self._history[:] = 0.0
        self._filled = 0
        self._line_filled = 0

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays = {'moments': self._moments, 'history': self._history,
                  'theta_iv': self._theta_iv, 'theta_bciv': self._theta_bciv,
                  'gamma': self._gamma, 'delay_line': self._line,
                  'signal_scale': self._signal_scale}
        scalars = {'filled': self._filled, 'tau': self._tau, 'decay': self._decay,
                   'line_position': self._line_position, 'line_filled': self._line_filled,
                   'updates': self._updates, 'iterations_used': self._iterations_used,
                   'forgetting_factor': self._forgetting_factor,
                   'signal_count': self._signal_count, 'error_count': self._error_count,
                   'input_power': self._input_power, 'output_power': self._output_power,
                   'error_power': self._error_power, 'next_check': self._next_check,
                   'last_power': self._last_power, 'fallbacks_checked': self._fallbacks_checked,
                   'reasons': self._reasons, 'last_status': self._last_status}
        return arrays, scalars

    def _is_sound(self) -> bool:
        # the base class's test, without its calls in the usual case: a finite sum means
        # that every raw value is finite, the published noise then too
        if math.isfinite(sum(self._theta_bciv.tolist()) + sum(self._theta_iv.tolist())
                         + sum(self._gamma.tolist())):
            return True
        return super()._is_sound()

    def _step_restored(self) -> None:
        self._set_scale_dependents()
        if self._updates > 0:  # M_N^-1 for covariance_trace
            self._solver.estimate(self._moments, self._regularisation(),
                                  mode='idle', iterations=0, tolerance=self.tolerance)

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._moments[...] = arrays['moments']
        self._history[...] = arrays['history']
        self._theta_iv = arrays['theta_iv']
        self._theta_bciv = arrays['theta_bciv']
        self._gamma = arrays['gamma']
        self._line[...] = arrays['delay_line']
        self._line_position = int(scalars['line_position'])
        self._line_filled = int(scalars['line_filled'])
        self._filled = int(scalars['filled'])
        self._tau = float(scalars['tau'])
        self._decay = float(scalars['decay'])
        self._updates = int(scalars['updates'])
        self._iterations_used = int(scalars['iterations_used'])
        self._forgetting_factor = float(scalars['forgetting_factor'])
        self._signal_scale = np.array(arrays['signal_scale'], dtype=float)
        self._set_scale_dependents()
        self._signal_count = float(scalars['signal_count'])
        self._error_count = float(scalars['error_count'])
        self._input_power = float(scalars['input_power'])
        self._output_power = float(scalars['output_power'])
        self._error_power = float(scalars['error_power'])
        self._next_check = int(scalars['next_check'])
        self._last_power = float(scalars['last_power'])
        self._fallbacks_checked = int(scalars['fallbacks_checked'])
        self._reasons = tuple(scalars['reasons'])
        self._last_status = str(scalars['last_status'])
        if self._updates > 0:  # M_N^-1 for covariance_trace
            self._solver.estimate(self._moments, self._regularisation(),
                                  mode='idle', iterations=0, tolerance=self.tolerance)

    def __repr__(self) -> str:
        return (f'Bciv(order={self.order}, iv_lag={self.iv_lag}, '
                f'input_noise={self.input_noise!r}, bciv_update={self.bciv_update!r}, '
                f'bciv_iterations={self.bciv_iterations}, idle_samples={self.idle_samples}, '
                f'forgetting_factor={self._forgetting_factor})')


@dataclasses.dataclass(frozen=True)
class BcivBatch:
    """
    Batch BCIV estimates at one or more sample counts.

    Attributes
    ----------
    samples : numpy.ndarray, shape ``(k,)``
        The sample counts t (data length) of each row.
    theta, theta_iv : numpy.ndarray, shape ``(k, p)``
        theta_BCIV and theta_IV (eq. 38) from the data up to t.
    noise : numpy.ndarray, shape ``(k, q)``
        gamma~ normalised by the weighted count.
    iterations : numpy.ndarray, shape ``(k,)``
    status : tuple of str
        ``''`` or the fallback reason, per row.

    """

    samples: np.ndarray
    theta: np.ndarray
    theta_iv: np.ndarray
    noise: np.ndarray
    iterations: np.ndarray
    status: tuple[str, ...]


def regularisation_weights(z_scale: float, w_scale: float, order: int,
                           num_parameters: int) -> np.ndarray:
    r"""
    Return the diagonal :math:`S^2` that puts :math:`M_0 = \rho I` in normalised units.

    Column k of :math:`\bar R` sums :math:`w\,z` (a-part) or :math:`w\,w` (b-part).
    Step 1 on the normalised signals :math:`z/s_z`, :math:`w/s_w` with
    :math:`M_0 = \rho I`, mapped back, is Step 1 on the signals as given with
    :math:`M_0^{-1} = \rho^{-1} S^2`, :math:`S = s_w\,\mathrm{diag}(s_z I_n, s_w I)`.
    """
    weights = np.full(num_parameters, w_scale * w_scale)
    weights[:order] = w_scale * z_scale
    return weights * weights


def window_scales(z: np.ndarray, w: np.ndarray, m: int) -> tuple[float, float]:
    """
    Return the scales that :class:`Bciv` gives z and w when it runs over these arrays.

    Each is the power of two at or above the peak of the first m-sample window
    (ending at sample m - 1 or later) in which the channel is not all zero; 1
    for a channel that is zero throughout.
    """
    scales = []
    for x in (z, w):
        nonzero = np.flatnonzero(x)
        if nonzero.size == 0:
            scales.append(1.0)
            continue
        end = max(int(nonzero[0]), m - 1)
        scales.append(power_of_two_at_least(float(np.abs(x[end - m + 1:end + 1]).max())))
    return scales[0], scales[1]


def published_noise(gamma: np.ndarray) -> np.ndarray:
    """
    Return the noise estimates as published: gamma with its variance entry no lower than 0.

    gamma[0] is a variance (r_dd(0), or sigma_d^2 with white input noise). Its
    finite-sample estimate can come out negative (flag ``negative_variance``);
    a consumer gets 0 instead. The covariances at other lags keep their sign.
    """
    if gamma[0] >= 0.0:
        return gamma
    noise = np.array(gamma, dtype=float)
    noise[0] = 0.0
    return noise


def bciv_batch(y: Any, u: Any, *, order: int, iv_lag: int = 5, input_noise: str = 'colored',
               feedthrough: bool = False, bciv_iterations: int = 20,
               tolerance: float = DEFAULT_TOLERANCE, initial_covariance: float = 1e6,
               forgetting_factor: float = 1.0, idle_samples: int = 0,
               checkpoints: Sequence[int] | None = None, allow_underdetermined: bool = False,
               iv_weight: Any = None, noise_weight: Any = None) -> BcivBatch:
    r"""
    Return the batch BCIV reference: moments over the data, then the same solver.

    For each checkpoint t the moments of the first t samples are summed at
    once, :math:`\bar S = \sum \lambda^{N-i}\eta_i[p_i^T, -z_i]`, and
    :meth:`BcivSolver.estimate` gives the estimate: K alternations from
    theta_IV (colored) or the fixed point from theta_IV (white). This is what
    :class:`Bciv` with ``bciv_update='converged'`` computes recursively.

    Parameters
    ----------
    y, u : array_like, shape ``(N,)``
        Noisy output z and noisy input w.
    order, iv_lag, input_noise, feedthrough, bciv_iterations, tolerance
        As for :class:`Bciv`.
    initial_covariance, forgetting_factor
        rho and lambda, as for :class:`Bciv` (M_0 = rho S^-2 with the scales of
        :func:`window_scales`).
    idle_samples : int
        Below this many updates the estimate is theta_IV.
    checkpoints : sequence of int or None
        Data lengths t at which to estimate; None means only t = N.
    allow_underdetermined : bool
        As for :class:`Bciv`.
    iv_weight, noise_weight : array_like or None
        W and X (identity if None).

    Returns
    -------
    BcivBatch
        One row per checkpoint.

    """
    if input_noise not in INPUT_NOISE:
        raise ValueError(f"input_noise must be 'colored' or 'white', got {input_noise!r}")
    check_structure(order, iv_lag, feedthrough, input_noise, allow_underdetermined)
    solver = BcivSolver(order=order, iv_lag=iv_lag, feedthrough=feedthrough,
                        input_noise=input_noise, iv_weight=iv_weight,
                        noise_weight=noise_weight)
    z = np.asarray(y, dtype=float).reshape(-1)
    w = np.asarray(u, dtype=float).reshape(-1)
    count = z.shape[0]
    checkpoints = [count] if checkpoints is None else [int(t) for t in checkpoints]
    eta, pz = solver.data_windows(z, w)
    weights_s = regularisation_weights(*window_scales(z, w, solver.m), order,
                                       solver.num_parameters)
    mode = 'fixed_point' if input_noise == 'white' else 'steps'
    rows = []
    lam = forgetting_factor
    for t in checkpoints:
        updates = max(t - solver.m + 1, 0)
        weights = lam ** np.arange(updates - 1, -1, -1, dtype=float)
        moments = eta[:updates].T @ (pz[:updates] * weights[:, None])
        tau = float(weights.sum())
        row_mode = mode if updates >= max(idle_samples, 1) else 'idle'
        result = solver.estimate(moments, lam ** (2 * updates) / initial_covariance * weights_s,
                                 mode=row_mode, iterations=bciv_iterations, tolerance=tolerance)
        gamma = result.gamma / tau if tau > 0 else result.gamma
        rows.append((result.theta, result.theta_iv, gamma, result.iterations, result.status))
    return BcivBatch(np.array(checkpoints), np.array([r[0] for r in rows]),
                     np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                     np.array([r[3] for r in rows]), tuple(r[4] for r in rows))
