"""
The BCIV solver: the estimate from the moments of Step 2 (Steps 1, 3 and 4).

Ikenoue, Kanae, Yang and Wada (2008), "Bias-compensation based method for
errors-in-variables model identification": the IV-type estimate of eq. (38),
the noise system of eq. (75) with Q~(b) of eq. (61) (colored input noise,
noise vector (64)) or eq. (66) (white, (67)), and the compensated estimate of
eq. (53), alternated; the white fixed point is in
:mod:`bcid_ros.estimators.bciv.white`. Also the structure checks (eqs. 37,
54, 72) and the data windows of eqs. (54), (68)-(70). Both the recursive
:class:`~bcid_ros.estimators.bciv.online.Bciv` and the batch
:func:`~bcid_ros.estimators.bciv.batch.bciv_batch` call this solver; they
differ only in how they sum the moments.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import numpy as np
from scipy.linalg.lapack import dgesv, dposv

from bcid_ros.estimators.bciv.white import WhiteFixedPoint

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
INPUT_NOISE = ('colored', 'white')

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
        #: The white fixed point of eqs. (65)-(67), from E'XE.
        self._white = (WhiteFixedPoint(order, p, self._basis_x @ self.q_basis)
                       if input_noise == 'white' else None)

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
            theta, gamma, done, converged, status = self._white_estimate(
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
    def _white_estimate(self, theta_iv: np.ndarray, start: float, max_steps: int,
                        tolerance: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        """
        Return the white fixed point of Steps 3-4 (eqs. 65-67) from ``start`` = N sigma_d^2.

        :class:`~bcid_ros.estimators.bciv.white.WhiteFixedPoint` finds it by
        the secant method; where its scalar equation breaks down, the plain
        alternation from theta_IV is iterated instead (at least 200 steps).
        """
        # E'X [R | -r]
        self._basis_x.dot(self.moments, self._noise_moments)
        found = self._white.solve(theta_iv, self._iv_solution[:, 1:], self._noise_moments,
                                  start, max_steps, tolerance)
        if found is None:
            return self._alternate(theta_iv, theta_iv, max(max_steps, 200), tolerance)
        theta, gamma, done, converged = found
        return theta, gamma, done, converged, OK

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
