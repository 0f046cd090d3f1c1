"""
BCIV: bias-compensated IV-type estimation for errors-in-variables models.

Ikenoue, Kanae, Yang and Wada (2008), "Bias-compensation based method for
errors-in-variables model identification", eqs. (37)-(75) and the recursive
algorithm of section 4, read with the corrections of PAPER_NOTES.md:

* colored input noise: the alternation of eqs. (75) and (53) has a unit
  eigenvalue (the gain of B is not fixed by eq. (72)), so the estimate at
  sample N is defined as K alternations started from the IV-type estimate
  theta_IV,N, never warm-started from the previous BCIV estimate;
* white input noise (eqs. 65-67): the alternation contracts to a unique
  fixed point, which is found warm-started at every sample;
* ``bciv_update='printed'``: the paper's Steps 0-5 as printed, one
  alternation per sample warm-started from the previous estimate.

The recursive estimator :class:`Bciv` and the batch reference
:func:`bciv_batch` share one solver, :class:`BcivSolver`, which takes the
IV moments and returns the estimate; they differ only in how the moments
are accumulated.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np
from scipy.linalg.blas import dger
from scipy.linalg.lapack import dgesv, dposv

from bcid_ros.estimators.base import check_int, check_range, RecursiveEstimator

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

#: Solver outcomes (the flag counted when the estimate falls back to theta_IV).
OK = ''
SINGULAR = 'noise_system_singular'
RUNAWAY = 'compensation_runaway'


@dataclasses.dataclass(frozen=True)
class BcivResult:
    """
    One BCIV estimate from given moments.

    Attributes
    ----------
    theta : numpy.ndarray, shape ``(p,)``
        theta_BCIV (theta_IV if ``status`` is not empty).
    gamma : numpy.ndarray, shape ``(q,)``
        The noise covariances of eq. (75), normalised by the sample count.
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
    The BCIV estimate of eqs. (38), (53), (75) from the IV moments: shared by both forms.

    The moments are kept unnormalised as one array
    :math:`\bar S = \sum_t \lambda^{N-t}\,\eta_t\,[p_t^T,\ -z_t]`, shape
    ``(m, p + 1)``, so that :math:`\bar S [\theta; 1] = N(\hat R_{\eta p}\theta -
    \hat r_{\eta z})`. The noise vector then comes out as :math:`N\tilde\gamma`;
    the factor N cancels in eq. (53).

    **The structure of Q~.** Eq. (61) is linear in b:
    :math:`\tilde Q(b) = \sum_j b_j E_j` with constant 0/1 matrices
    :math:`E_j` (``(m, q)``), :math:`(E_j)_{i,c} = 1` iff
    :math:`|l - 1 - i + k_j| = c` (colored; :math:`k_j` the lag of
    :math:`b_j`) or :math:`i = l - 1 + k_j` (white, eq. 66). Hence
    :math:`\tilde Q^TX\tilde Q = \sum_{jk} b_j b_k E_j^TXE_k` with the constant
    :math:`E_j^TXE_k`, and one alternation is a quadratic form in
    :math:`x = [\theta; 1]`: with the per-sample tensor built by :meth:`prepare`,
    two small matrix products give :math:`\tilde Q^TX\tilde Q`,
    :math:`\tilde Q^TX\bar S x` and :math:`G\tilde Q` at once,
    :math:`G = (\bar S_p^TW\bar S_p + \rho^{-1}\lambda^{2N} I)^{-1}\bar S_p^TW`.

    **Cost.** At n = 2, l = 5 every array is tiny, so the cost is the number
    of numpy/LAPACK calls, not arithmetic: one alternation is four calls
    (two products, an in-place Cholesky solve, one product) with positional
    arguments, and :meth:`prepare` is two products, one Cholesky solve and one
    scatter. The moments :attr:`moments` live in a Fortran-ordered buffer
    that :class:`Bciv` updates in place with BLAS ``dger``.

    Parameters
    ----------
    order : int
        n.
    iv_lag : int
        l of eq. (54).
    feedthrough : bool
        Whether b_0 (lag 0) is estimated.
    input_noise : str
        ``'colored'`` or ``'white'``.
    iv_weight, noise_weight : numpy.ndarray or None
        W and X, ``(m, m)`` symmetric positive definite; None means identity.

    """

    def __init__(self, *, order: int, iv_lag: int, feedthrough: bool, input_noise: str,
                 iv_weight: np.ndarray | None = None,
                 noise_weight: np.ndarray | None = None) -> None:
        n, lag = order, iv_lag
        self.order, self.iv_lag, self.input_noise = n, lag, input_noise
        first = 0 if feedthrough else 1
        self.lags = tuple(range(first, n + 1))
        nb = len(self.lags)
        self.num_parameters = p = n + nb
        self.m = m = n + 2 * lag
        self.q = q = noise_count(n, lag, feedthrough, input_noise)
        self.b_index = np.arange(n, p)
        self.w = None if iv_weight is None else _weight('iv_weight', iv_weight, m)
        self.x = None if noise_weight is None else _weight('noise_weight', noise_weight, m)
        # E_j, stacked as columns: e_all[:, j q + c] = (E_j)[:, c]
        e_all = np.zeros((m, nb * q))
        for j, k in enumerate(self.lags):
            for i in range(m):
                if input_noise == 'white':
                    if i == lag - 1 + k:
                        e_all[i, j * q] = 1.0
                else:
                    e_all[i, j * q + abs(lag - 1 - i + k)] = 1.0
        self.e_all = e_all
        x_weight = np.eye(m) if self.x is None else self.x
        #: E_all' X, shape (nb q, m)
        self.etx = e_all.T @ x_weight
        # T_jk = E_j' X E_k, shape (nb, nb, q, q)
        etxe = (self.etx @ e_all).reshape(nb, q, nb, q).transpose(0, 2, 1, 3)
        self.t = np.ascontiguousarray(etxe)
        self._t_white = self.t[:, :, 0, 0].tolist()

        # ---- The moments and the products of eq. (38), in fixed buffers.
        # big = [S_p | -s | W E_all] in Fortran order, so that the moments block
        # is contiguous and BLAS dger updates it in place (W = I: the moments
        # themselves live in big).
        big = np.zeros((p + 1 + nb * q, m)).T
        big[:, p + 1:] = e_all if self.w is None else self.w @ e_all
        self._big = big
        self.moments = big[:, :p + 1] if self.w is None else np.zeros((p + 1, m)).T
        # One buffer holds [Phi' ; Phi^-1 [-S'W s | S'W E_all]]' (rows of the
        # transposed products) and E_all' X S, so that one scatter moves every
        # per-sample number into the tensor below.
        rows = p + 1 + nb * q
        self._buffer = np.zeros(rows * p + nb * q * (p + 1))
        self._products = self._buffer[:rows * p].reshape(rows, p)  # [S_p'W big]'
        self.phi = self._products[:p].T  # Phi, Fortran order (kept: dposv copies it)
        self._phi_diagonal = self._buffer[:p * p:p + 1]
        self._solved = self._products[p:].T  # (p, 1 + nb q), Fortran order
        self._ge = self._solved[:, 1:]  # G E_all
        self._etxs = self._buffer[rows * p:].reshape(nb * q, p + 1)  # E_all' X S
        self.theta_iv = np.zeros(p)
        self._scattered = True

        # ---- The quadratic-form tensor of one alternation.
        # C[s, t, :] over x = [theta; 1]; only b and the trailing 1 can be the
        # first factor, so s runs over xb = x[n:] = [b; 1]. The last axis holds
        # Ha ((q+1)^2: Q~'XQ~ bordered by a unit corner), ra (q+1: Q~'X S x,
        # then -1) and Da (p (q+1): G Q~, then -theta_IV), so that
        # Ha^-1 ra = [gamma; -1] and Da [gamma; -1] = theta_IV + G Q~ gamma.
        qa = q + 1
        ha_end, ra_end = qa * qa, qa * qa + qa
        width = ra_end + p * qa
        c = np.zeros((nb + 1, p + 1, width))
        for j in range(nb):
            for k in range(nb):
                c[j, n + k, :ha_end].reshape(qa, qa)[:q, :q] = self.t[j, k]
        c[nb, p, ha_end - 1] = 1.0
        c[nb, p, ra_end - 1] = -1.0
        self._c = c.reshape(nb + 1, (p + 1) * width)
        # Where the per-sample numbers of the buffer go in C (one scatter):
        # solved[i, 0] = -theta_IV[i] -> C[nb, p, Da(i, q)];
        # solved[i, 1 + j q + c] = (G E_j)[i, c] -> C[j, p, Da(i, c)];
        # (E_all' X S)[j q + c, t] -> C[j, t, ra(c)].
        index = np.zeros((nb + 1, p + 1, width), dtype=np.intp)
        index.reshape(-1)[:] = np.arange(index.size)
        target = [index[nb, p, ra_end + i * qa + q] for i in range(p)]
        target += [index[j, p, ra_end + i * qa + col]
                   for j in range(nb) for col in range(q) for i in range(p)]
        target += [index[j, t, ha_end + col]
                   for j in range(nb) for col in range(q) for t in range(p + 1)]
        self._scatter = np.array(target, dtype=np.intp)
        self._c_flat = c.reshape(-1)
        # Work buffers of the alternation; x = [theta; 1], whose head is rewritten.
        self._w1 = np.empty((p + 1) * width)
        self._w1_2d = self._w1.reshape(p + 1, width)
        self._out = np.empty(width)
        self._ha = self._out[:ha_end].reshape(qa, qa).T  # symmetric: the F-order view
        self._ra = self._out[ha_end:ra_end]
        self._ha_diagonal = self._out[:ha_end - 1:qa + 1]  # the first q
        self._check_cache: dict[int, tuple[bool, ...]] = {}
        self._da = self._out[ra_end:].reshape(p, qa)
        x = np.ones(p + 1)
        self._loop = (self._c, self._w1, self._w1_2d, self._out, self._ha, self._ra,
                      self._da, x, x[n:], x[:p])

    # ----------------------------------------------------------- per sample
    def prepare(self, saug: np.ndarray, regularisation: float) -> np.ndarray:
        r"""
        Compute theta_IV of eq. (38) and the tensors of the alternation from the moments.

        .. math::

            \Phi = \bar S_p^T W \bar S_p + \rho^{-1}\lambda^{2N} I, \quad
            G = \Phi^{-1}\bar S_p^T W, \quad \hat\theta_{IV} = -G\,\bar S_{:,p}

        One product gives :math:`[\Phi \mid -\bar S_p^TW\bar s \mid \bar S_p^TWE]`,
        one Cholesky solve :math:`[-\hat\theta_{IV} \mid GE]`, one product
        :math:`E^TX\bar S`, and one scatter puts them into the tensor of
        :meth:`alternate`.

        Parameters
        ----------
        saug : numpy.ndarray, shape ``(m, p + 1)``
            The unnormalised moments :math:`[\sum\eta p^T,\ -\sum\eta z]`;
            :attr:`moments` itself (no copy) or any array (copied into it).
        regularisation : float
            :math:`\rho^{-1}\lambda^{2N}`, the M_0 = rho I term of Step 0.

        Returns
        -------
        numpy.ndarray, shape ``(p,)``
            theta_IV (a new array).

        """
        p = self.num_parameters
        moments = self.moments
        if saug is not moments:
            moments[...] = saug
        big = self._big
        if self.w is not None:
            big[:, :p + 1] = self.w.dot(moments)
        # [Phi | -S'W s | S'W E_all]' = [W S_p | -W s | W E_all]' S_p
        big.T.dot(moments[:, :p], self._products)
        # Phi = S'WS + rho^-1 lambda^2N I   (M_N^-1 of Step 1)
        self._phi_diagonal += regularisation
        # [-theta_IV | G E_all] = Phi^-1 [-S'W s | S'W E_all], G = Phi^-1 S'W      (38)
        info = dposv(self.phi, self._solved, 0, 0, 1)[2]
        if info != 0:
            self._fallback_solve(regularisation)
        # E_all' X [S_p | -s]
        self.etx.dot(moments, self._etxs)
        self._scattered = False  # the tensor of :meth:`alternate` is filled on demand
        self.theta_iv = theta_iv = -self._solved[:, 0]
        return theta_iv

    def _fallback_solve(self, regularisation: float) -> None:
        """Redo the solve of :meth:`prepare` with LU after the Cholesky factorisation failed."""
        p = self.num_parameters
        products = self._big.T.dot(self.moments[:, :p]).T
        products[:, :p] += regularisation * np.eye(p)
        solved, _ = _general_solve(products[:, :p], products[:, p:])
        self._solved[...] = solved

    def alternate(self, start: np.ndarray, iterations: int,
                  tolerance: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        r"""
        Make up to ``iterations`` alternations of eqs. (75) and (53) from ``start``.

        .. math::

            \tilde\gamma_{k+1} &= (\tilde Q_k^TX\tilde Q_k)^{-1}\tilde Q_k^TX
                (\hat R_{\eta p}\theta_k - \hat r_{\eta z}) && \text{(75)} \\
            \theta_{k+1} &= \hat\theta_{IV} + (\hat R^T_{\eta p} W \hat R_{\eta p})^{-1}
                \hat R^T_{\eta p} W \tilde Q_k \tilde\gamma_{k+1} && \text{(53)}

        with :math:`\tilde Q_k = \tilde Q(b_k)`. One alternation is four calls:
        two products for the quadratic form, one in-place Cholesky solve and one
        product. Checks the step every :data:`CHECK_PERIOD` steps and after the
        last, and stops once it is below ``tolerance`` (2-norm). Call
        :meth:`prepare` first.

        Returns
        -------
        theta, gamma, iterations, converged, status
            ``gamma`` is the unnormalised :math:`N\tilde\gamma` of the last
            step; ``status`` is ``''`` or :data:`SINGULAR`/:data:`RUNAWAY`.

        """
        q = self.q
        c, w1, w1_2d, out, ha, ra, da, x, xb, head = self._loop
        if not self._scattered:
            # the per-sample numbers of prepare() into the tensor
            self._c_flat[self._scatter] = self._buffer[self.num_parameters ** 2:]
            self._scattered = True
        # bound methods, positional arguments: at these sizes the call overhead
        # is the cost, and keywords add a third to it
        quadratic, contract, update = xb.dot, x.dot, da.dot
        head[...] = start
        converged = False
        done = 0
        checks = self._check_cache.get(iterations) or self._checks(iterations)
        for check in checks:
            done += 1
            # [vec Ha, ra, vec Da] = sum_st x_s x_t C[s, t, :]
            quadratic(c, w1)
            contract(w1_2d, out)
            # [gamma; -1] = Ha^-1 ra, in place      (75)
            if dposv(ha, ra, 0, 1, 1)[2] != 0:
                return head.copy(), ra[:q].copy(), done, False, SINGULAR
            if not check:
                # theta = theta_IV + G Q~ gamma = Da [gamma; -1]      (53)
                update(ra, head)
                continue
            previous = head.tolist()
            update(ra, head)
            change = math.dist(head.tolist(), previous)
            if not math.isfinite(change):
                return head.copy(), ra[:q].copy(), done, False, RUNAWAY
            if change <= tolerance:
                converged = True
                break
        if done == 0:
            return head.copy(), np.zeros(q), 0, False, OK
        # Cholesky factor diagonal of Q~'XQ~: cond ~ (max/min)^2
        diagonal = self._ha_diagonal.tolist()
        if not min(diagonal) * math.sqrt(CONDITION_MAX) > max(diagonal):
            return head.copy(), ra[:q].copy(), done, converged, SINGULAR
        return head.copy(), ra[:q].copy(), done, converged, OK

    def _checks(self, iterations: int) -> tuple[bool, ...]:
        """Return, per alternation, whether to check the step (every CHECK_PERIOD and the last)."""
        checks = self._check_cache.get(iterations)
        if checks is None:
            checks = tuple((k + 1) % CHECK_PERIOD == 0 or k + 1 == iterations
                           for k in range(iterations))
            self._check_cache[iterations] = checks
        return checks

    def fixed_point(self, start: float, max_iterations: int,
                    tolerance: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        r"""
        Solve the fixed point of eqs. (75)/(53) with white input noise (eqs. 65-67).

        With :math:`\tilde Q = \tilde b` (eq. 66) one alternation is the map
        :math:`T(\theta) = \hat\theta_{IV} + \sigma(\theta)\, G E b`, with
        :math:`\sigma(\theta) = b^T E^TX(\bar S x)/(b^T E^TXE b)` the
        unnormalised :math:`N\sigma_d^2` of eq. (75) and :math:`b` the b-part of
        :math:`\theta`. It contracts to a unique fixed point (PAPER_NOTES.md),
        but slowly (0.75 per step in section 5.2). At a fixed point
        :math:`\theta = \hat\theta_{IV} + \sigma\, G E b`, so for a given
        :math:`\sigma` the b-part solves the n x n system

        .. math::

            (I - \sigma [GE]_b)\, b(\sigma) = \hat b_{IV}, \qquad
            f(\sigma) = \frac{b^T(c_0 + \sigma K_1 b)}{b^T E^TXE\, b}, \quad
            c_0 = E^TX(\bar S_p\hat\theta_{IV} - \bar s), \ K_1 = E^TX\bar S_p G E

        and the fixed point is the root of the scalar equation
        :math:`\sigma = f(\sigma)`. It is found by the secant method from
        ``start`` (the previous :math:`N\hat\sigma_d^2`, or 0, which makes the
        first step exactly one alternation from :math:`\hat\theta_{IV}`).
        The estimate returned is :math:`T(\theta(\sigma_k))`. If the scalar
        system breaks down, the plain alternation is iterated instead.
        Call :meth:`prepare` first.

        Parameters
        ----------
        start : float
            Initial :math:`\sigma` (unnormalised).
        max_iterations : int
            Cap on secant steps.
        tolerance : float
            Stop when the implied change of theta is below this (2-norm).

        Returns
        -------
        theta, gamma, iterations, converged, status
            As :meth:`alternate`.

        """
        p, bi = self.num_parameters, self.b_index
        ge, etxs, theta_iv = self._ge, self._etxs, self.theta_iv
        etx_sp = etxs[:, :p]
        # c0 = E'X (S_p theta_IV - s); K1 = E'X S_p G E     (per sample, n x n)
        c0 = (etx_sp.dot(theta_iv) + etxs[:, p]).tolist()
        k1 = etx_sp.dot(ge).tolist()
        ge_b = ge[bi].tolist()
        beta = theta_iv[bi].tolist()
        t_mat = self._t_white
        scale = math.sqrt(ge.dot(theta_iv[bi]).dot(ge.dot(theta_iv[bi])))
        tol = tolerance / scale if scale > 0.0 else math.inf
        f = _white_map(ge_b, beta, k1, c0, t_mat)
        s0 = float(start)
        f0, b = f(s0)
        done = 1
        if f0 is None:
            return self._plain_white(max_iterations, tolerance)
        s1, phi0 = f0, s0 - f0
        f1, b1 = f0, b
        converged = abs(phi0) <= tol
        while not converged and done < max_iterations:
            f1, b1 = f(s1)
            done += 1
            if f1 is None or not math.isfinite(f1):
                return self._plain_white(max_iterations, tolerance)
            phi1 = s1 - f1
            if abs(phi1) <= tol:
                converged = True
                break
            slope = phi1 - phi0
            # secant step on phi(sigma) = sigma - f(sigma)
            s_next = f1 if slope == 0.0 else s1 - phi1 * (s1 - s0) / slope
            s0, phi0, s1 = s1, phi1, s_next
        # theta = T(theta(sigma)) = theta_IV + f(sigma) G E b(sigma)      (53)
        theta = theta_iv + ge.dot(b1) * f1
        return theta, np.array([f1]), done, converged, OK

    def _plain_white(self, max_iterations: int,
                     tolerance: float) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        """Iterate the plain alternation from theta_IV (the fallback of :meth:`fixed_point`)."""
        return self.alternate(self.theta_iv, max(max_iterations, 200), tolerance)

    def solve(self, saug: np.ndarray, regularisation: float, *, mode: str,
              iterations: int, tolerance: float, start: np.ndarray | None = None,
              start_noise: float = 0.0) -> BcivResult:
        """
        Return the BCIV estimate for the moments ``saug`` (the whole per-sample step).

        Parameters
        ----------
        saug : numpy.ndarray, shape ``(m, p + 1)``
            Moments, see :meth:`prepare`.
        regularisation : float
            rho^-1 lambda^2N.
        mode : str
            ``'steps'``: ``iterations`` alternations from theta_IV (the
            colored definition); ``'fixed_point'``: the white fixed point,
            warm-started from ``start_noise``, at most ``iterations`` secant
            steps; ``'printed'``: ``iterations`` alternations from ``start``
            (theta_IV if None); ``'idle'``: theta_IV only.
        iterations : int
            K, or the iteration cap.
        tolerance : float
            Stop when a step is below this (2-norm).
        start : numpy.ndarray or None
            theta to start ``'printed'`` from.
        start_noise : float
            Unnormalised N sigma_d^2 to start ``'fixed_point'`` from; 0 makes
            its first step one alternation from theta_IV.

        Returns
        -------
        BcivResult
            ``gamma`` is unnormalised (N gamma~); divide by the weighted count.

        """
        return BcivResult(*self.step(saug, regularisation, mode, iterations, tolerance, start,
                                     start_noise))

    def step(self, saug: np.ndarray, regularisation: float, mode: str, iterations: int,
             tolerance: float, start: np.ndarray | None,
             start_noise: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, bool, str]:
        """Do :meth:`solve` and return the fields of :class:`BcivResult` as a tuple."""
        theta_iv = self.prepare(saug, regularisation)
        iv_list = theta_iv.tolist()
        iv_norm2 = float(theta_iv.dot(theta_iv))
        if mode == 'idle' or not math.isfinite(iv_norm2):
            # (non-finite theta_IV: the caller resets the moments)
            return theta_iv, np.zeros(self.q), theta_iv, 0, True, OK
        if mode == 'fixed_point':
            theta, gamma, done, converged, status = self.fixed_point(start_noise, iterations,
                                                                     tolerance)
        else:
            first = theta_iv if start is None or mode == 'steps' else start
            theta, gamma, done, converged, status = self.alternate(first, iterations,
                                                                   tolerance)
        if status == OK:
            gap = math.dist(theta.tolist(), iv_list)
            if not gap * gap <= COMPENSATION_MAX ** 2 * (1.0 + iv_norm2):
                status = RUNAWAY
        if status != OK:
            return theta_iv, np.zeros(self.q), theta_iv, done, False, status
        return theta, gamma, theta_iv, done, converged, OK

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


def _weight(name: str, value: Any, m: int) -> np.ndarray:
    """Return a checked (m, m) symmetric positive definite weighting matrix."""
    matrix = np.array(value, dtype=float)
    if matrix.shape != (m, m):
        raise ValueError(f'{name} must have shape ({m}, {m}), got {matrix.shape}')
    if not np.isfinite(matrix).all() or not np.allclose(matrix, matrix.T) or \
            np.linalg.eigvalsh(matrix).min() <= 0.0:
        raise ValueError(f'{name} must be symmetric positive definite')
    return matrix


def _general_solve(matrix: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
    """Solve with LU when the Cholesky factorisation failed (rounding near singular)."""
    _, _, solved, info = dgesv(matrix, rhs)
    if info != 0 or not np.isfinite(solved).all():
        return np.zeros_like(rhs), info
    return solved, info


class Bciv(RecursiveEstimator):
    r"""
    Recursive BCIV-type estimator for errors-in-variables models (Ikenoue et al. 2008).

    The data are the noisy output z_t (the published ``y``) and the noisy
    input w_t (``u``), SISO. With the IV-type vector (54), delayed by l - 1
    samples as in eqs. (68)-(70), every sample updates the moments and then
    computes the estimate from them:

    .. math::

        \bar S_N &= \lambda \bar S_{N-1} + \eta_N [p_N^T,\ -z_N]
            && \text{(Step 2, eqs. 39-40, unnormalised)} \\
        \hat\theta_{IV,N} &= (\bar S_p^T W \bar S_p + \rho^{-1}\lambda^{2N} I)^{-1}
            \bar S_p^T W \bar s && \text{(38), = Step 1 with } M_0 = \rho I \\
        \hat{\tilde\gamma}_{k+1} &= (\tilde Q_k^T X \tilde Q_k)^{-1} \tilde Q_k^T X
            (\hat R_{\eta p}\theta_k - \hat r_{\eta z}) && \text{(75)} \\
        \theta_{k+1} &= \hat\theta_{IV,N} + (\hat R_{\eta p}^T W \hat R_{\eta p})^{-1}
            \hat R_{\eta p}^T W \tilde Q_k \hat{\tilde\gamma}_{k+1} && \text{(53)}

    with :math:`\tilde Q_k = \tilde Q(b_k)` of eq. (61) (colored, noise vector
    (64): r_dd(0..n+l-1)) or eq. (66) (white, (67): sigma_d^2). The estimate at
    sample N is, by ``input_noise`` and ``bciv_update``:

    * colored, ``converged``: K = ``bciv_iterations`` alternations from
      :math:`\theta_0 = \hat\theta_{IV,N}`, stopping early below ``tolerance``;
    * white, ``converged``: the unique fixed point, warm-started from the
      previous estimate (the secant method on the equivalent scalar equation
      in sigma_d^2, at most K steps; see :meth:`BcivSolver.fixed_point`);
    * ``printed``: one alternation from the previous estimate (Steps 3-4 as
      printed).

    :math:`\hat\theta_{IV,N}` equals the rank-2 recursion of Step 1 in exact
    arithmetic (:math:`M_N^{-1} = \lambda^2 M_{N-1}^{-1} + \Psi_N\Lambda_N^{-1}\Psi_N^T`
    sums to :math:`\bar S_p^TW\bar S_p + \rho^{-1}\lambda^{2N}I`); solving the
    4x4 system is as cheap and does not accumulate the rounding of an
    indefinite rank-2 update. For T < L = ``idle_samples`` the estimate is
    :math:`\hat\theta_{IV,T}` (initial value selection of section 4).

    **Forgetting factor** (an extension): with exponential weights
    :math:`\lambda^{N-t}` the weighted moments normalised by
    :math:`\tau_N = \sum\lambda^{N-t}` have the same limits (71)-(72) on
    stationary data, so the same equations hold with
    :math:`\hat R = \bar S/\tau`; the noise estimates are :math:`N\tilde\gamma/\tau`.

    **Safeguards** (counted in :attr:`flags`; the estimate stays finite):

    * ``fallback_iv``: :math:`\tilde Q^TX\tilde Q` is singular or its condition
      number exceeds ``CONDITION_MAX`` (b ~ 0, no excitation), or the
      alternation ran away; the estimate is :math:`\hat\theta_{IV,N}` for this
      sample, and the next sample tries again from it. The reason is counted
      too, as ``noise_system_singular`` or ``compensation_runaway``;
    * ``not_converged``: the white fixed point was not reached within K steps
      (the last iterate is used, and the next sample continues from it);
    * ``moments_reset``: the moments overflowed; they restart from zero.

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`; only
        ``num_inputs=1``. ``initial_covariance`` is rho of M_0 = rho I.
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
    #: Extra constructor keywords that are ROS parameters (SPEC section 5).
    options: tuple[str, ...] = ('iv_lag', 'input_noise', 'idle_samples', 'bciv_iterations',
                                'bciv_update', 'allow_underdetermined')

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
        self._gather = np.concatenate(solver.window_indices())
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        m = self._solver.m
        ring = self._ring
        start = self._start - 2
        if start < 0:
            # move the newest m - 1 samples to the end of the ring
            start = 2 * RING_SAMPLES
            ring[start + 2:] = ring[:2 * m - 2]
        ring[start] = -y
        ring[start + 1] = u[0]
        self._start = start
        if self._filled < m:
            self._filled += 1
            if self._filled < m:
                return
        # [eta; p; -z] of eqs. (54), (68)-(70)
        sample = ring[start:start + 2 * m][self._gather]
        lam = self._forgetting_factor
        if lam != 1.0:
            self._saug *= lam
        # S = lambda S + eta [p', -z]      (Step 2, unnormalised, in place)
        dger(1.0, sample[:m], sample[m:], 1, 1, self._saug, 1, 1, 1)
        # tau = lambda tau + 1 ; decay = lambda^2N
        self._tau = lam * self._tau + 1.0
        self._decay *= lam * lam
        self._updates += 1
        self._estimate()

    def _estimate(self) -> None:
        """Compute theta_IV,N and theta_BCIV,N from the moments."""
        regularisation = self._decay / self.initial_covariance
        mode = 'idle' if self._updates < self.idle_samples else self._mode
        theta, gamma, theta_iv, done, converged, status = self._solver.step(
            self._saug, regularisation, mode, self._iterations, self.tolerance,
            self._theta_bciv, self._gamma[0] * self._tau)
        if not math.isfinite(theta_iv.dot(theta_iv)):
            self._flag('moments_reset')
            self._saug[...] = 0.0
            self._tau, self._decay, self._updates = 0.0, 1.0, 0
            return
        self._theta_iv = theta_iv
        self._theta_bciv = theta
        self._iterations_used = done
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

    # --------------------------------------------------------- the accessors
    @property
    def valid(self) -> bool:
        """Whether eta is filled, L updates are done and at least p updates were made."""
        return self._updates >= max(self.idle_samples, self.num_parameters)

    @property
    def samples(self) -> int:
        """Count the estimator updates (samples with a filled IV-type vector)."""
        return self._updates

    @property
    def covariance_trace(self) -> float:
        """Return tr M_N of Step 1, M_N = (S'WS + rho^-1 lambda^2N I)^-1 (a health indicator)."""
        if self._updates == 0:
            return self.initial_covariance * self.num_parameters
        phi = self._solver.phi
        try:
            return float(np.trace(np.linalg.inv(phi)))
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
        #: The moments S live in the solver's buffer, updated in place.
        self._saug = self._solver.moments
        self._saug[...] = 0.0
        self._tau = 0.0
        self._decay = 1.0
        self._updates = 0
        self._theta_iv = np.zeros(p)
        self._theta_bciv = np.zeros(p)
        self._gamma = np.zeros(self._solver.q)
        self._iterations_used = 0

    def _restart_regressor(self) -> None:
        self._history[:] = 0.0
        self._filled = 0

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays = {'moments': self._saug, 'history': self._history,
                  'theta_iv': self._theta_iv, 'theta_bciv': self._theta_bciv,
                  'gamma': self._gamma}
        scalars = {'filled': self._filled, 'tau': self._tau, 'decay': self._decay,
                   'updates': self._updates, 'iterations_used': self._iterations_used,
                   'forgetting_factor': self._forgetting_factor}
        return arrays, scalars

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._saug[...] = arrays['moments']
        self._history[...] = arrays['history']
        self._theta_iv = arrays['theta_iv']
        self._theta_bciv = arrays['theta_bciv']
        self._gamma = arrays['gamma']
        self._filled = int(scalars['filled'])
        self._tau = float(scalars['tau'])
        self._decay = float(scalars['decay'])
        self._updates = int(scalars['updates'])
        self._iterations_used = int(scalars['iterations_used'])
        self._forgetting_factor = float(scalars['forgetting_factor'])
        if self._updates > 0:
            self._solver.prepare(self._saug, self._decay / self.initial_covariance)

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
    :meth:`BcivSolver.solve` gives the estimate: K alternations from
    theta_IV (colored) or the fixed point from theta_IV (white). This is what
    :class:`Bciv` with ``bciv_update='converged'`` computes recursively.

    Parameters
    ----------
    y, u : array_like, shape ``(N,)``
        Noisy output z and noisy input w.
    order, iv_lag, input_noise, feedthrough, bciv_iterations, tolerance
        As for :class:`Bciv`.
    initial_covariance, forgetting_factor
        rho and lambda, as for :class:`Bciv`.
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
    mode = 'fixed_point' if input_noise == 'white' else 'steps'
    rows = []
    lam = forgetting_factor
    for t in checkpoints:
        updates = max(t - solver.m + 1, 0)
        weights = lam ** np.arange(updates - 1, -1, -1, dtype=float)
        saug = eta[:updates].T @ (pz[:updates] * weights[:, None])
        tau = float(weights.sum())
        row_mode = mode if updates >= max(idle_samples, 1) else 'idle'
        result = solver.solve(saug, lam ** (2 * updates) / initial_covariance, mode=row_mode,
                              iterations=bciv_iterations, tolerance=tolerance)
        gamma = result.gamma / tau if tau > 0 else result.gamma
        rows.append((result.theta, result.theta_iv, gamma, result.iterations, result.status))
    return BcivBatch(np.array(checkpoints), np.array([r[0] for r in rows]),
                     np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                     np.array([r[3] for r in rows]), tuple(r[4] for r in rows))


def _small_solve(matrix: list[list[float]], rhs: list[float]) -> list[float] | None:
    """Solve a small dense system in pure Python (Gauss, partial pivoting); None if singular."""
    size = len(rhs)
    a = [row[:] + [rhs[i]] for i, row in enumerate(matrix)]
    for col in range(size):
        pivot = max(range(col, size), key=lambda r: abs(a[r][col]))
        if not abs(a[pivot][col]) > 1e-300:
            return None
        a[col], a[pivot] = a[pivot], a[col]
        head = a[col]
        for r in range(col + 1, size):
            factor = a[r][col] / head[col]
            if factor != 0.0:
                row = a[r]
                for k in range(col, size + 1):
                    row[k] -= factor * head[k]
    out = [0.0] * size
    for r in range(size - 1, -1, -1):
        row = a[r]
        out[r] = (row[size] - sum(row[k] * out[k] for k in range(r + 1, size))) / row[r]
    return out


def _white_map(ge_b: list, beta: list, k1: list, c0: list, t_mat: list):
    """
    Return f(sigma) -> (f, b) of :meth:`BcivSolver.fixed_point`, in plain floats.

    For n = 2 (and 1) the n x n algebra is written out: a few dozen float
    operations cost less than one numpy call.
    """
    if len(beta) == 2:
        (g00, g01), (g10, g11) = ge_b
        beta0, beta1 = beta
        (k00, k01), (k10, k11) = k1
        c00, c01 = c0
        (t00, t01), (t10, t11) = t_mat

        def f2(sigma):
            # (I - sigma [GE]_b) b = b_IV, by Cramer's rule
            a00, a01, a10, a11 = 1.0 - sigma * g00, -sigma * g01, -sigma * g10, 1.0 - sigma * g11
            det = a00 * a11 - a01 * a10
            if det == 0.0:
                return None, None
            b0 = (a11 * beta0 - a01 * beta1) / det
            b1 = (a00 * beta1 - a10 * beta0) / det
            # den = b' E'XE b ; num = b' (c0 + sigma K1 b)
            den = b0 * (t00 * b0 + t01 * b1) + b1 * (t10 * b0 + t11 * b1)
            if not den > 0.0:
                return None, None
            num = (b0 * (c00 + sigma * (k00 * b0 + k01 * b1))
                   + b1 * (c01 + sigma * (k10 * b0 + k11 * b1)))
            return num / den, [b0, b1]
        return f2
    span = range(len(beta))

    def f(sigma):
        # (I - sigma [GE]_b) b = b_IV
        b = _small_solve([[(1.0 if i == j else 0.0) - sigma * ge_b[i][j] for j in span]
                          for i in span], beta)
        if b is None:
            return None, None
        # den = b' E'XE b ; num = b' (c0 + sigma K1 b)
        den = sum(b[i] * sum(t_mat[i][j] * b[j] for j in span) for i in span)
        if not den > 0.0:
            return None, None
        num = sum(b[i] * (c0[i] + sigma * sum(k1[i][j] * b[j] for j in span)) for i in span)
        return num / den, b
    return f
