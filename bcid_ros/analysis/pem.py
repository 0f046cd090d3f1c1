"""
Batch prediction-error estimation (scipy): the efficient offline reference.

Three models, in the recursive estimators' parametrisation and parameter names
(:func:`bcid_ros.estimators.base.parameter_names`), with r inputs, a dead time
d_i per input and ``F = A = 1 + a1 q^-1 + ... + an q^-n``,
``B_i = q^-d_i (b_i1 q^-1 + ... + b_in q^-n)`` (``b_i0`` at lag d_i with
feedthrough):

* **output error** (:func:`fit_oe`): ``y = sum_i B_i(q)/F(q) u_i + v``, by
  minimising the simulation error with :func:`scipy.optimize.least_squares`
  and an analytic Jacobian; consistent in open loop whatever the colour of v;
* **ARX** (:func:`fit_arx`): ``A y = sum_i B_i u_i + e``, by least squares;
* **ARMAX** (:func:`fit_armax`): ``A y = sum_i B_i u_i + C e``,
  ``C = 1 + c1 q^-1 + ... + cn q^-n`` (names add ``c1 ... cn``), by minimising
  the one-step prediction error with C kept minimum-phase.

The methods are those of Ljung, *System Identification: Theory for the User*
(2nd ed., 1999): the model structures of ch. 4, the prediction-error criterion
of ch. 7, the asymptotic covariance of ch. 9 and the gradients and
Gauss-Newton search of ch. 10; for the start, the instrumental-variable
refinement (ch. 7) in Young's simplified refined IV form (Young, *Recursive
Estimation and Time-Series Analysis*, 2011, ch. 7).
The data must be centred by the caller (remove the operating point first).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np
from scipy import linalg, optimize, signal

from bcid_ros.analysis.least_squares import (best_run, kept_start, MAX_EVALUATIONS, runs,
                                             SOLVERS)
from bcid_ros.analysis.metrics import coloured_noise_covariance, nrmse_fit
from bcid_ros.analysis.structure import Structure
from bcid_ros.estimators.base import check_int
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients, spectral_radius
from bcid_ros.estimators.regressor import ArxRegressor

#: Largest pole (or zero of C) radius of a start: a root beyond is reflected
#: into the unit circle and pulled in to this radius.
START_RADIUS = 0.999
#: Instrumental-variable refinement: most iterations, and the relative change of
#: theta below which it stops.
REFINE_ITERATIONS = 20
REFINE_TOLERANCE = 1e-7
#: Order of the long ARX model whose residual starts ARMAX (Hannan-Rissanen).
LONG_ARX_ORDER = 20
#: Values of the ``initial`` argument of :func:`fit_oe`.
INITIALS = ('auto', 'estimate', 'zero')
#: ``initial='auto'``: a fitted time constant longer than this many records makes the
#: estimated start-up transient a persistent signal, and the fit falls back to 'zero'.
PERSISTENT_RECORDS = 2.0
#: Values of :attr:`PemResult.model`.
MODELS = ('oe', 'arx', 'armax')


@dataclasses.dataclass(frozen=True)
class PemResult:
    """
    A batch estimate: parameters, fitted output, loss, covariance, convergence.

    Attributes
    ----------
    model : str
        'oe', 'arx' or 'armax'.
    structure : Structure
        The structure fitted.
    theta : numpy.ndarray, shape ``(p,)``
        The estimate, ordered as :attr:`parameter_names`.
    parameter_names : tuple of str
        The estimators' names (ARMAX adds ``c1 ... cn``).
    output : numpy.ndarray, shape ``(N - start,)``
        OE: the simulated output sum_i B_i/F u_i (with the estimated initial
        transient); ARX and ARMAX: the one-step prediction y(t|t-1).
    residual : numpy.ndarray, shape ``(N - start,)``
        y - output over the same samples: the simulation error (OE), the
        equation error (ARX) or the innovation (ARMAX).
    start : int
        Index of the first sample of ``output`` (0 for OE; n + max(d_i) else).
    loss : float
        V = mean of residual^2.
    covariance : numpy.ndarray, shape ``(p, p)``
        Asymptotic covariance of theta (see :attr:`covariance_assumes`).
    covariance_assumes : str
        What the covariance formula assumes, in one line.
    noise_order : int
        Order of the AR model of the residual used by the OE covariance (0: white).
    converged : bool
        Whether the optimiser met a tolerance (always True for ARX).
    evaluations : int
        Residual evaluations of the winning run (0 for ARX).
    message : str
        The optimiser's message.
    start_losses : tuple of float
        Loss at each start tried, before optimisation.
    initial : str
        OE: 'estimate' when the start-up transient was fitted, 'zero' when the
        simulation started from rest; '' otherwise.
    offset : float
        OE with ``offset=True``: the fitted constant c in ``output`` (else 0).

    """

    model: str
    structure: Structure
    theta: np.ndarray
    parameter_names: tuple[str, ...]
    output: np.ndarray
    residual: np.ndarray
    start: int
    loss: float
    covariance: np.ndarray
    covariance_assumes: str
    noise_order: int = 0
    converged: bool = True
    evaluations: int = 0
    message: str = ''
    start_losses: tuple[float, ...] = ()
    initial: str = ''
    offset: float = 0.0

    @property
    def std(self) -> np.ndarray:
        """Return the standard deviation of each parameter, shape ``(p,)``."""
        return np.sqrt(np.maximum(np.diagonal(self.covariance), 0.0))

    @property
    def denominator(self) -> np.ndarray:
        """Return F (OE) or A = [1, a1, ..., an]."""
        return self.structure.split(self.theta)[0]

    @property
    def numerators(self) -> np.ndarray:
        """Return the rows b_i, shape ``(r, b_length)`` (without the dead-time zeros)."""
        return self.structure.split(self.theta)[1]

    @property
    def noise_polynomial(self) -> np.ndarray:
        """Return C = [1, c1, ..., cn] (ARMAX) or [1.0]."""
        if self.model != 'armax':
            return np.ones(1)
        return np.concatenate([[1.0], self.theta[-self.structure.order:]])

    @property
    def stable(self) -> bool:
        """Return whether every root of F (A) is strictly inside the unit circle."""
        return is_stable(monic_coefficients(self.denominator), 0.0)

    def fit(self, y: np.ndarray) -> float:
        """Return the NRMSE fit in percent of :attr:`output` to the y it was fitted to."""
        y = np.asarray(y, dtype=float).reshape(-1)[self.start:]
        return nrmse_fit(y, self.output)


# ---------------------------------------------------------------- helpers
def stabilise(polynomial: np.ndarray, radius: float = START_RADIUS) -> np.ndarray:
    """
    Return the monic polynomial with every root beyond ``radius`` reflected inside.

    A root z with |z| > ``radius`` becomes z / |z|^2 (its mirror in the unit
    circle, which keeps the magnitude of the frequency response up to a
    constant: :func:`bcid_ros.estimators.lti.stable_reflection`), pulled in
    to ``radius`` if the mirror is still beyond it.
    """
    polynomial = np.asarray(polynomial, dtype=float)
    if is_stable(monic_coefficients(polynomial), 1.0 - radius):
        return polynomial.copy()
    roots = np.roots(polynomial)
    magnitude = np.abs(roots)
    outside = magnitude > radius
    moved = roots[outside] / magnitude[outside] ** 2
    moved *= np.minimum(1.0, radius / np.abs(moved))
    roots[outside] = moved
    return np.real(np.poly(roots))


def simulate_oe(theta: Any, u: Any, structure: Structure) -> np.ndarray:
    r"""
    Return the free-run simulated output :math:`\sum_i B_i(q)/F(q)\,u_i` from rest.

    Parameters
    ----------
    theta : array_like, shape ``(p,)``
        OE (or ARX) parameters in the estimators' order.
    u : array_like, shape ``(N,)`` or ``(N, r)``
        Inputs (centred like the data the model was fitted to).
    structure : Structure
        Order, inputs, dead times and feedthrough of theta.

    Returns
    -------
    numpy.ndarray, shape ``(N,)``
        Non-finite where an unstable model overflowed.

    Raises
    ------
    ValueError
        If ``theta`` or ``u`` do not match ``structure``.

    """
    theta = _check_theta(theta, structure, 'oe')
    u = _check_inputs(u, structure, None)
    denominator, b = structure.split(theta)
    with np.errstate(over='ignore', invalid='ignore'):
        return signal.lfilter([1.0], denominator, _input_sum(b, u, structure))


def oe_jacobian(theta: Any, u: Any, structure: Structure) -> np.ndarray:
    r"""
    Return the gradient :math:`\psi = \partial\hat y/\partial\theta` of the OE simulated output.

    .. math::

        \partial\hat y/\partial a_k = -q^{-k}\hat y/F,\quad
        \partial\hat y/\partial b_{ik} = q^{-(d_i+k)}u_i/F

    (Ljung 1999, ch. 10), from rest, shape ``(N, p)``. With white v of
    variance :math:`\sigma^2`, :math:`\sigma^2(\psi^T\psi)^{-1}` is the
    asymptotic covariance of the OE estimate (Ljung 1999, ch. 9).

    Raises
    ------
    ValueError
        If ``theta`` or ``u`` do not match ``structure``.

    """
    theta = _check_theta(theta, structure, 'oe')
    u = _check_inputs(u, structure, None)
    problem = _OutputError(np.zeros(u.shape[0]), u, structure, 'zero')
    if not is_stable(monic_coefficients(structure.split(theta)[0]), 0.0):
        raise ValueError('theta must have a stable F for its gradient')
    return problem.jacobian(theta)


def _input_sum(b: np.ndarray, u: np.ndarray, structure: Structure) -> np.ndarray:
    """Return sum_i q^-d_i B_i(q) u_i(t) from rest, shape ``(N,)``."""
    total = np.zeros(u.shape[0])
    lead = structure.first_lag
    for i, delay in enumerate(structure.input_delay):
        for k, coefficient in enumerate(b[i]):
            lag = delay + lead + k
            if lag < total.size:
                total[lag:] += coefficient * u[:total.size - lag, i]
    return total


def _shift_into(columns: np.ndarray, x: np.ndarray, lags: range) -> None:
    """Write q^-k x (zeros before the start) into column j of ``columns`` for the j-th lag k."""
    count = x.size
    for j, lag in enumerate(lags):
        lag = min(lag, count)
        columns[:lag, j] = 0.0
        columns[lag:, j] = x[:count - lag]


def _shifted(x: np.ndarray, lags: range | list[int]) -> np.ndarray:
    """Return the columns q^-k x (zeros before the start) for k in ``lags``, ``(N, len)``."""
    columns = np.zeros((x.size, len(lags)))
    for j, lag in enumerate(lags):
        if lag < x.size:
            columns[lag:, j] = x[:x.size - lag]
    return columns


def _check_structure(structure: Any) -> Structure:
    if not isinstance(structure, Structure):
        raise ValueError(f'structure must be a Structure, got {type(structure).__name__}')
    return structure


def _check_theta(theta: Any, structure: Structure, model: str) -> np.ndarray:
    _check_structure(structure)
    theta = np.asarray(theta, dtype=float).reshape(-1)
    size = len(structure.parameter_names(model))
    if theta.size != size or not np.isfinite(theta).all():
        raise ValueError(f'theta must hold {size} finite values for this structure, '
                         f'got {theta.size}')
    return theta


def _check_inputs(u: Any, structure: Structure, count: int | None) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    if u.ndim == 1:
        u = u[:, None]
    if u.ndim != 2 or u.shape[1] != structure.num_inputs or (
            count is not None and u.shape[0] != count):
        expected = 'N' if count is None else str(count)
        raise ValueError(f'u must have shape ({expected}, {structure.num_inputs}), '
                         f'got {np.shape(u)}')
    if not np.isfinite(u).all():
        raise ValueError('u must be finite')
    return u


def _check_data(y: Any, u: Any, structure: Structure,
                extra: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Return (y, u) as float arrays, or raise ValueError naming the argument."""
    _check_structure(structure)
    y = np.asarray(y, dtype=float)
    if y.ndim != 1 or not np.isfinite(y).all():
        raise ValueError(f'y must be a finite 1-D array, got shape {y.shape}')
    u = _check_inputs(u, structure, y.size)
    needed = 2 * (structure.span + structure.num_parameters + extra) + 10
    if y.size < needed:
        raise ValueError(f'y must have at least {needed} samples for this structure, '
                         f'got {y.size}')
    return y, u


# ---------------------------------------------------------------- ARX
def fit_arx(y: Any, u: Any, structure: Structure) -> PemResult:
    r"""
    Fit the ARX model ``A y = sum_i B_i u_i + e`` by least squares.

    .. math::

        \hat\theta = \arg\min_\theta \sum_{t \ge n + \max d_i}
            \big(y(t) - \varphi^T(t)\theta\big)^2

    with the estimators' regressor :math:`\varphi(t)` (Ding et al. 2006,
    eqs. (53)-(55); :class:`~bcid_ros.estimators.regressor.ArxRegressor`) over
    the samples whose regressor is filled, solved by QR-based ``lstsq``. The
    covariance :math:`\hat\sigma^2(\Phi^T\Phi)^{-1}`, with
    :math:`\hat\sigma^2 = \mathrm{RSS}/(N' - p)`, assumes a white equation
    error e independent of the inputs (the ARX model true).

    Parameters
    ----------
    y : array_like, shape ``(N,)``
        Output, centred.
    u : array_like, shape ``(N,)`` or ``(N, r)``
        Inputs, centred.
    structure : Structure
        Order, inputs, dead times, feedthrough.

    Returns
    -------
    PemResult
        ``output`` is the one-step prediction from sample n + max(d_i) on.

    Raises
    ------
    ValueError
        If the data do not match ``structure`` or are too short; the message
        names the argument.

    """
    y, u = _check_data(y, u, structure)
    phi, target = _arx_rows(y, u, structure)
    theta = _least_squares(phi, target)[0]
    output = phi @ theta
    residual = target - output
    rows = phi.shape[0]
    sigma2 = float(residual @ residual) / max(rows - theta.size, 1)
    covariance = sigma2 * _gram_inverse(phi)
    return PemResult('arx', structure, theta, structure.parameter_names('arx'),
                     output, residual, structure.span,
                     float(np.mean(residual ** 2)), covariance,
                     'white equation error e independent of u (the ARX model true)')


def _arx_rows(y: np.ndarray, u: np.ndarray,
              structure: Structure) -> tuple[np.ndarray, np.ndarray]:
    """Return (Phi, y(t)) over t = n + max(d_i) ... N - 1."""
    regressor = ArxRegressor(structure.order, structure.num_inputs, structure.feedthrough,
                             structure.input_delay)
    return regressor.regressors(y, u), y[regressor.span:]


def _least_squares(phi: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (theta, residual) of min |target - phi theta| by QR (columns scaled)."""
    scale = np.linalg.norm(phi, axis=0)
    scale[scale == 0.0] = 1.0
    theta = linalg.lstsq(phi / scale, target, lapack_driver='gelsy')[0] / scale
    return theta, target - phi @ theta


def _gram_inverse(columns: np.ndarray) -> np.ndarray:
    """
    Return (J^T J)^-1 through the QR factor R of the column-scaled J.

    A direction that the data do not determine (R singular to working
    precision) gets an infinite or huge variance, never a small one.
    """
    scale = np.linalg.norm(columns, axis=0)
    scale[scale == 0.0] = 1.0
    r = linalg.qr(columns / scale, mode='r')[0][:columns.shape[1]]
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        try:
            inverse_r = linalg.solve_triangular(r, np.eye(r.shape[0]))
        except linalg.LinAlgError:
            return np.full((r.shape[0], r.shape[0]), np.inf)
        return (inverse_r @ inverse_r.T) / np.outer(scale, scale)


# ---------------------------------------------------------------- OE
class _OutputError:
    r"""
    The OE simulation error and its Jacobian, for :func:`scipy.optimize.least_squares`.

    The unknowns x are theta = [a, b] followed (``initial='estimate'``) by the
    initial transient w: M = n + max(d_i) free values w(0) ... w(M-1) added
    to sum_i B_i u_i, so that F x_s = sum_i B_i u_i + w from rest (every
    initial state of the plant and every unknown input before the record
    gives such a w, supported on those M samples), and (``offset``) by a
    constant c: yhat = x_s + c.

    .. math::

        \partial\hat y/\partial a_k = -q^{-k}x_s/F,\quad
        \partial\hat y/\partial b_{ik} = q^{-(d_i+k)}u_i/F,\quad
        \partial\hat y/\partial w_m = q^{-m}\delta/F,\quad
        \partial\hat y/\partial c = 1
    """

    def __init__(self, y: np.ndarray, u: np.ndarray, structure: Structure,
                 initial: str, offset: bool = False) -> None:
        self.y = y
        self.u = u
        self.structure = structure
        self.num_theta = structure.num_parameters
        self.num_initial = structure.span if initial == 'estimate' else 0
        self.num_offset = 1 if offset else 0
        self._impulse = np.zeros(y.size)
        self._impulse[0] = 1.0
        self._cached: tuple[bytes, np.ndarray] | None = None

    def simulate(self, x: np.ndarray) -> np.ndarray | None:
        """Return yhat of x (None when F is not stable)."""
        key = x.tobytes()
        if self._cached is not None and self._cached[0] == key:
            return self._cached[1]
        denominator, b = self.structure.split(x[:self.num_theta])
        if not is_stable(monic_coefficients(denominator), 0.0):
            return None
        drive = _input_sum(b, self.u, self.structure)
        drive[:self.num_initial] += x[self.num_theta:self.num_theta + self.num_initial]
        yhat = signal.lfilter([1.0], denominator, drive)
        if self.num_offset:
            yhat += x[-1]
        self._cached = (key, yhat)
        return yhat

    def residual(self, x: np.ndarray) -> np.ndarray:
        """Return yhat - y; NaN when F is unstable (least_squares then shrinks its step)."""
        yhat = self.simulate(x)
        if yhat is None or not np.isfinite(yhat).all():
            return np.full(self.y.size, np.nan)
        return yhat - self.y

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Return d yhat / dx, shape ``(N, p + M + offset)``."""
        n = self.structure.order
        denominator = self.structure.split(x[:self.num_theta])[0]
        dynamic = self.simulate(x) - (x[-1] if self.num_offset else 0.0)
        columns = np.empty((self.y.size, x.size), order='F')
        _shift_into(columns[:, :n], -signal.lfilter([1.0], denominator, dynamic),
                    range(1, n + 1))
        self._fill_linear(columns[:, n:], denominator)
        return columns

    def linear_columns(self, denominator: np.ndarray) -> np.ndarray:
        """Return d yhat / d[b, w, c], which depends on F only: ``(N, p - n + M + offset)``."""
        count = self.num_theta - self.structure.order + self.num_initial + self.num_offset
        columns = np.empty((self.y.size, count), order='F')
        self._fill_linear(columns, denominator)
        return columns

    def _fill_linear(self, columns: np.ndarray, denominator: np.ndarray) -> None:
        """Write d yhat / d[b, w, c] into ``columns``."""
        structure = self.structure
        first = 0
        for i, delay in enumerate(structure.input_delay):
            lags = range(delay + structure.first_lag, delay + structure.order + 1)
            _shift_into(columns[:, first:first + len(lags)],
                        signal.lfilter([1.0], denominator, self.u[:, i]), lags)
            first += len(lags)
        if self.num_initial:
            response = signal.lfilter([1.0], denominator, self._impulse)
            _shift_into(columns[:, first:first + self.num_initial], response,
                        range(self.num_initial))
        if self.num_offset:
            columns[:, -1] = 1.0

    def best_numerators(self, denominator: np.ndarray) -> np.ndarray:
        """Return x = [a, b, w, c] with the b, w and c that fit best for this F (linear LS)."""
        linear = _least_squares(self.linear_columns(denominator), self.y)[0]
        return np.concatenate([denominator[1:], linear])


def fit_oe(y: Any, u: Any, structure: Structure, *, initial: str = 'auto',
           offset: bool = False, starts: int = 2,
           max_evaluations: int = MAX_EVALUATIONS, solver: str = 'trf',
           denominators: Sequence[np.ndarray] = ()) -> PemResult:
    r"""
    Fit the MISO output-error model ``y = sum_i B_i/F u_i + v`` by prediction-error minimisation.

    Minimises the simulation error (the prediction-error criterion with the
    OE predictor, Ljung 1999, chs. 4 and 7)

    .. math::

        V_N(\theta) = \frac1N\sum_{t=0}^{N-1}\Big(y(t) - \sum_i
            \frac{B_i(q)}{F(q)}u_i(t) - \frac{w(q)}{F(q)}\delta(t)\Big)^2

    with :func:`scipy.optimize.least_squares` (trust-region reflective) and
    the analytic Jacobian of :class:`_OutputError`. w (``initial =
    'estimate'``) is the start-up transient of a record that does not begin at
    rest: n + max(d_i) free values of the drive at the first samples, which
    any initial state gives; ``'zero'`` simulates from rest (w = 0). With
    ``'auto'`` (the default) w is estimated unless the fit then has a time
    constant -1/ln|pole| longer than ``PERSISTENT_RECORDS`` records: its
    "transient" would be a persistent signal (a sinusoid on the unit circle,
    an offset) fitted to the noise, so the fit is redone from rest. F stays
    stable: a step to an unstable F is refused and the trust region shrinks.
    With ``offset`` a constant c is added to the simulated output and fitted
    with it: for a record centred by its sample means, whose output mean is
    not G(1) times the input mean (a slow plant over a finite record).

    Starts: the ARX least-squares estimate, and its refinement by the
    simplified refined instrumental-variable method (SRIV: prefilter y and u
    by 1/F, instruments from the simulated noise-free output; Young 2011), each
    with F reflected to stability (:func:`stabilise`) and its B and w refitted
    by linear least squares. Up to ``starts`` runs, from the lowest start
    losses; the lowest end wins (an over-parametrised OE model has several
    minima, and the lowest start does not always lead to the lowest).

    ``denominators`` adds starts: each F given (of degree n, reflected to
    stability) with its B, w and c refitted, every one run besides the
    ``starts`` best of the others. A fit of order n + 1 started from an
    order-n fit's F times (1 - p q^-1) can end no higher than that fit (its
    B times the same factor is one of the B refitted), so the search's
    estimation loss never rises with the order (docs/analyze.md).

    Covariance (Ljung 1999, ch. 9: an OE estimate under coloured noise):
    the sandwich :math:`B^{-1}\,(\hat\sigma_w^2\,G^TG)\,B^{-1}` with
    :math:`B = \psi^T\psi`, ψ the Jacobian of theta with the w (and offset)
    columns projected out, and :math:`G = L^T\psi`, L the Toeplitz matrix of the AR
    model 1/D(q) of the residual chosen by AIC (order <= 30). It assumes open
    loop (v independent of u), the plant in the model set and a stationary v
    that an AR model of that order describes; with D = 1 it is the white-noise
    formula :math:`\hat\sigma^2(\psi^T\psi)^{-1}`.

    Parameters
    ----------
    y : array_like, shape ``(N,)``
        Output, centred.
    u : array_like, shape ``(N,)`` or ``(N, r)``
        Inputs, centred.
    structure : Structure
        Order, inputs, dead times, feedthrough.
    initial : str
        ``'auto'`` (default), ``'estimate'`` or ``'zero'`` (the record starts at rest).
    offset : bool
        Fit a constant output offset c too (:attr:`PemResult.offset`).
    starts : int
        Most least-squares runs, >= 1, from the best starts first.
    max_evaluations : int
        Most residual evaluations of one run, >= 1.
    denominators : sequence of numpy.ndarray
        More starts: F = [1, f_1, ..., f_n] each (see above).
    solver : str
        ``'trf'`` (default): :func:`scipy.optimize.least_squares`, trust-region
        reflective, which factors the N x p Jacobian by SVD at every
        iteration. ``'lm'``: Levenberg-Marquardt on the p x p normal
        equations
        (:func:`~bcid_ros.analysis.least_squares.levenberg_marquardt`),
        several times cheaper per iteration; what ``bcid analyze`` uses for its many fits.

    Returns
    -------
    PemResult
        ``output`` is the simulated output (with the fitted start-up transient).

    Raises
    ------
    ValueError
        If an argument is out of range or the data do not match ``structure``;
        the message names the argument.

    """
    if initial not in INITIALS:
        raise ValueError(f"initial must be one of {', '.join(INITIALS)}, got {initial!r}")
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
    starts = check_int('starts', starts, 1)
    max_evaluations = check_int('max_evaluations', max_evaluations, 1)
    y, u = _check_data(y, u, _check_structure(structure),
                       0 if initial == 'zero' else structure.span)
    offset = bool(offset)
    denominators = [stabilise(_check_denominator(f, structure)) for f in denominators]
    longest = PERSISTENT_RECORDS * y.size if initial == 'auto' else math.inf
    result = _fit_oe(y, u, structure, 'zero' if initial == 'zero' else 'estimate', offset,
                     starts, max_evaluations, solver, denominators, longest)
    if _time_constant(result.denominator) > longest:
        result = _fit_oe(y, u, structure, 'zero', offset, starts, max_evaluations, solver,
                         denominators)
    return result


def _check_denominator(denominator: Any, structure: Structure) -> np.ndarray:
    denominator = np.asarray(denominator, dtype=float).reshape(-1)
    if (denominator.size != structure.order + 1 or denominator[0] != 1.0
            or not np.isfinite(denominator).all()):
        raise ValueError(f'denominators must each be [1, f_1, ..., f_{structure.order}], '
                         f'finite, got {denominator.tolist()}')
    return denominator


def _fit_oe(y: np.ndarray, u: np.ndarray, structure: Structure, initial: str, offset: bool,
            starts: int, max_evaluations: int, solver: str,
            denominators: Sequence[np.ndarray] = (), longest: float = math.inf) -> PemResult:
    """
    Run the starts; return the lowest end whose longest time constant is within ``longest``.

    The starts of ``denominators`` (an order-n fit with a pole added) count
    as ends too, so the result is never worse than they are; with no end
    within ``longest``, the lowest end.
    """
    problem = _OutputError(y, u, structure, initial, offset)
    candidates = _oe_starts(problem)
    losses = [float(np.mean(problem.residual(x) ** 2)) for x in candidates]
    ended = runs(problem.residual, problem.jacobian, candidates, losses, starts,
                 max_evaluations, solver)
    warm = [problem.best_numerators(denominator) for denominator in denominators]
    for x in warm:
        losses.append(float(np.mean(problem.residual(x) ** 2)))
        ended += runs(problem.residual, problem.jacobian, [x], [losses[-1]], 1,
                      max_evaluations, solver)
    # (the warm starts themselves too: where the runs from them end beyond the record's
    # time constant, the start is still no worse than the order-n fit it came from)
    ended += [kept_start(problem.residual, x, 'an order-n fit with a pole added, kept: the '
                         'runs ended higher or with a time constant beyond the record')
              for x in warm]
    within = [run for run in ended if _time_constant(_denominator_of(run.x, structure))
              <= longest]
    best = min(within or ended, key=lambda run: run.cost)
    return _oe_result(problem, best, tuple(losses))


def _denominator_of(x: np.ndarray, structure: Structure) -> np.ndarray:
    """Return F = [1, a_1, ..., a_n] of the unknowns x (theta first)."""
    return np.concatenate(([1.0], x[:structure.order]))


def _time_constant(denominator: np.ndarray) -> float:
    """Return the longest time constant -1/ln|pole| of 1/F in samples (inf at |pole| >= 1)."""
    radius = spectral_radius(monic_coefficients(denominator))
    if radius >= 1.0:
        return math.inf
    return -1.0 / math.log(radius) if radius > 0.0 else 0.0


def _oe_starts(problem: _OutputError) -> list[np.ndarray]:
    """Return the distinct starting points x (stable F), ARX first then SRIV."""
    y, u, structure = problem.y, problem.u, problem.structure
    phi, target = _arx_rows(y, u, structure)
    arx = _least_squares(phi, target)[0]
    denominator = stabilise(np.concatenate([[1.0], arx[:structure.order]]))
    starts = [problem.best_numerators(denominator)]
    refined = _refine_iv(y, u, structure, np.concatenate([denominator[1:],
                                                          arx[structure.order:]]))
    if refined is not None:
        starts.append(problem.best_numerators(np.concatenate([[1.0],
                                                              refined[:structure.order]])))
    return starts


def _refine_iv(y: np.ndarray, u: np.ndarray, structure: Structure,
               theta: np.ndarray) -> np.ndarray | None:
    r"""
    Return the best SRIV iterate of the OE model started at ``theta`` (stable F), or None.

    Each iteration prefilters by the current 1/F and solves
    :math:`\sum\zeta\varphi_f^T\,\theta = \sum\zeta y_f` with the regressor
    :math:`\varphi_f` of the filtered data and the instrument ζ built like
    it from the filtered simulated output :math:`\hat x_f = B/F^2 u` instead
    of :math:`y_f` (Young 2011, Sec. 7.3); F is reflected to stability after
    each solve. A poorly determined pole can make the iterates wander
    instead of converge, so the iterate with the lowest simulation error is
    returned (the start included), not the last.
    """
    regressor = ArxRegressor(structure.order, structure.num_inputs, structure.feedthrough,
                             structure.input_delay)
    start = regressor.span
    best, best_loss = None, math.inf
    for _ in range(REFINE_ITERATIONS):
        denominator = np.concatenate([[1.0], theta[:structure.order]])
        simulated = simulate_oe(theta, u, structure)
        loss = float(np.mean((y - simulated) ** 2))
        if loss < best_loss:
            best, best_loss = theta, loss
        filtered_u = signal.lfilter([1.0], denominator, u, axis=0)
        filtered_y = signal.lfilter([1.0], denominator, y)
        filtered_x = signal.lfilter([1.0], denominator, simulated)
        phi = regressor.regressors(filtered_y, filtered_u)
        # the instrument is phi with the filtered simulated output in place of y_f
        instrument = phi.copy()
        for k in range(1, structure.order + 1):
            instrument[:, k - 1] = -filtered_x[start - k:filtered_x.size - k]
        scale = np.linalg.norm(phi, axis=0)
        scale[scale == 0.0] = 1.0
        weighted = instrument / scale
        try:
            solved = np.linalg.solve(weighted.T @ (phi / scale),
                                     weighted.T @ filtered_y[start:]) / scale
        except np.linalg.LinAlgError:
            break
        if not np.isfinite(solved).all():
            break
        solved[:structure.order] = stabilise(np.concatenate(
            [[1.0], solved[:structure.order]]))[1:]
        change = np.linalg.norm(solved - theta) / max(np.linalg.norm(solved), 1e-300)
        theta = solved
        if change < REFINE_TOLERANCE:
            break
    return best


def _oe_result(problem: _OutputError, run: optimize.OptimizeResult,
               start_losses: tuple[float, ...]) -> PemResult:
    structure = problem.structure
    p = problem.num_theta
    output = problem.y + run.fun
    residual = problem.y - output
    jacobian = problem.jacobian(run.x)
    psi = jacobian[:, :p]
    if jacobian.shape[1] > p:
        nuisance = jacobian[:, p:]
        psi = psi - nuisance @ _least_squares_matrix(nuisance, psi)
    covariance, noise_order = coloured_noise_covariance(psi, residual, jacobian.shape[1])
    return PemResult(
        'oe', structure, run.x[:p].copy(), structure.parameter_names('oe'),
        output, residual, 0, float(np.mean(residual ** 2)), covariance,
        'open loop (v independent of u), the plant in the model set, stationary noise '
        f'described by the AR({noise_order}) model of the residual',
        noise_order, bool(run.status > 0), int(run.nfev), str(run.message), start_losses,
        'estimate' if problem.num_initial else 'zero',
        float(run.x[-1]) if problem.num_offset else 0.0)


def _least_squares_matrix(columns: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Return the LS coefficients of every column of ``targets`` on ``columns``."""
    scale = np.linalg.norm(columns, axis=0)
    scale[scale == 0.0] = 1.0
    return linalg.lstsq(columns / scale, targets, lapack_driver='gelsy')[0] / scale[:, None]


# ---------------------------------------------------------------- ARMAX
class _Armax:
    r"""
    The ARMAX innovation and its Jacobian, for :func:`scipy.optimize.least_squares`.

    With :math:`\varepsilon(t) = y(t) - \varphi^T(t)\theta_{ab}` (the ARX
    equation error) the innovation is :math:`e = \varepsilon/C`, from rest at
    t = n + max(d_i), and (Ljung 1999, ch. 10)

    .. math::

        \partial e/\partial\theta_{ab} = -\varphi/C,\quad
        \partial e/\partial c_k = -q^{-k}e/C
    """

    def __init__(self, y: np.ndarray, u: np.ndarray, structure: Structure) -> None:
        self.structure = structure
        self.phi, self.target = _arx_rows(y, u, structure)
        self.num_ab = structure.num_parameters
        self._cached: tuple[bytes, np.ndarray] | None = None

    def innovation(self, x: np.ndarray) -> np.ndarray | None:
        key = x.tobytes()
        if self._cached is not None and self._cached[0] == key:
            return self._cached[1]
        noise = np.concatenate([[1.0], x[self.num_ab:]])
        if not is_stable(monic_coefficients(noise), 0.0):
            return None
        error = signal.lfilter([1.0], noise, self.target - self.phi @ x[:self.num_ab])
        self._cached = (key, error)
        return error

    def residual(self, x: np.ndarray) -> np.ndarray:
        """Return e(t); NaN when C is not minimum-phase."""
        error = self.innovation(x)
        if error is None or not np.isfinite(error).all():
            return np.full(self.target.size, np.nan)
        return error

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Return de/dx, shape ``(N', p + n)``."""
        noise = np.concatenate([[1.0], x[self.num_ab:]])
        error = self.innovation(x)
        filtered = signal.lfilter([1.0], noise,
                                  np.hstack([self.phi, _shifted(error,
                                                                range(1, noise.size))]),
                                  axis=0)
        return -filtered


def fit_armax(y: Any, u: Any, structure: Structure, *,
              max_evaluations: int = MAX_EVALUATIONS) -> PemResult:
    r"""
    Fit the ARMAX model ``A y = sum_i B_i u_i + C e`` by prediction-error minimisation.

    Minimises :math:`\frac1{N'}\sum e^2(t)`, :math:`e = (A y - \sum_i B_i u_i)/C`
    (Ljung 1999, chs. 4 and 7), over t >= n + max(d_i), with
    :func:`scipy.optimize.least_squares` and the analytic Jacobian of
    :class:`_Armax`; a step to a C with a root on or outside the unit circle
    is refused. Starts: Hannan-Rissanen (the residual of a long ARX model as
    the lagged innovations in a least-squares fit, C reflected to minimum
    phase) and the ARX estimate with C = 1; the lower end wins. The
    covariance :math:`\hat\sigma^2(\psi^T\psi)^{-1}` (Ljung 1999, ch. 9), ψ
    the gradient of e, assumes a white innovation independent of past u (the
    model true).

    Parameters
    ----------
    y : array_like, shape ``(N,)``
        Output, centred.
    u : array_like, shape ``(N,)`` or ``(N, r)``
        Inputs, centred.
    structure : Structure
        Order (of A, every B_i and C), inputs, dead times, feedthrough.
    max_evaluations : int
        Most residual evaluations of one run, >= 1.

    Returns
    -------
    PemResult
        theta ends with ``c1 ... cn``; ``output`` is the one-step prediction
        from sample n + max(d_i) on.

    Raises
    ------
    ValueError
        If an argument is out of range or the data do not match ``structure``;
        the message names the argument.

    """
    max_evaluations = check_int('max_evaluations', max_evaluations, 1)
    y, u = _check_data(y, u, _check_structure(structure), structure.order + LONG_ARX_ORDER)
    problem = _Armax(y, u, structure)
    arx = _least_squares(problem.phi, problem.target)[0]
    starts = [np.concatenate([arx, np.zeros(structure.order)])]
    hannan = _hannan_rissanen(y, u, structure)
    if hannan is not None:
        starts.insert(0, hannan)
    losses = [float(np.mean(problem.residual(x) ** 2)) for x in starts]
    best = best_run(problem.residual, problem.jacobian, starts, losses, len(starts),
                    max_evaluations)
    output = problem.target - best.fun
    residual = problem.target - output
    psi = problem.jacobian(best.x)
    sigma2 = float(residual @ residual) / max(residual.size - best.x.size, 1)
    return PemResult('armax', structure, best.x.copy(), structure.parameter_names('armax'),
                     output, residual, structure.span,
                     float(np.mean(residual ** 2)), sigma2 * _gram_inverse(psi),
                     'white innovation e independent of past u (the ARMAX model true)', 0,
                     bool(best.status > 0), int(best.nfev), str(best.message), tuple(losses))


def _hannan_rissanen(y: np.ndarray, u: np.ndarray, structure: Structure) -> np.ndarray | None:
    """Return the Hannan-Rissanen start [a, b, c] with C reflected to minimum phase."""
    long = Structure(max(LONG_ARX_ORDER, 3 * structure.order), structure.num_inputs,
                     structure.input_delay, structure.feedthrough)
    if y.size < 4 * (long.span + long.num_parameters):
        return None
    phi, target = _arx_rows(y, u, long)
    innovation = np.zeros(y.size)
    innovation[long.span:] = _least_squares(phi, target)[1]
    phi, target = _arx_rows(y, u, structure)
    lagged = _shifted(innovation, range(1, structure.order + 1))[structure.span:]
    start = max(long.span + structure.order - structure.span, 0)
    theta = _least_squares(np.hstack([phi, lagged])[start:], target[start:])[0]
    if not np.isfinite(theta).all():
        return None
    n = structure.num_parameters
    theta[n:] = stabilise(np.concatenate([[1.0], theta[n:]]))[1:]
    return theta


__all__ = ['INITIALS', 'MODELS', 'PemResult', 'Structure', 'fit_armax', 'fit_arx', 'fit_oe',
           'oe_jacobian', 'simulate_oe', 'stabilise']
