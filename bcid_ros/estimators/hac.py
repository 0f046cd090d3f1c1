r"""
A recursive HAC (heteroscedasticity and autocorrelation consistent) covariance.

An estimate :math:`\hat\theta` that solves the weighted estimating equations
:math:`\sum_t w_t \psi_t \varepsilon_t(\theta) = 0` (rls: :math:`\psi = \varphi`
and the equation error; a prediction-error method: the gradient and the
prediction error), :math:`w_t = \lambda^{T-t}`, has the sandwich covariance

.. math::

    \mathrm{cov}\,\hat\theta = B^{-1}\,\mathrm{var}\Big(\sum_t w_t s_t\Big)\,B^{-T},
    \qquad s_t = \psi_t\varepsilon_t, \quad B = \sum_t w_t \psi_t\psi_t^T,

and :math:`\mathrm{var}(\sum_t w_t s_t) = \tau_2\,\Omega` for stationary
scores, :math:`\tau_2 = \sum w_t^2`, :math:`\Omega = \sum_k \Gamma_s(k)` the
long-run covariance of the scores (Newey and West 1987). When the residual is
white and independent of :math:`\psi`, :math:`\Omega = \sigma^2 E\psi\psi^T`
and this is the plain :math:`\sigma^2 P\tau_2/\tau`; when it is coloured
(output-error data, oversampled plants) the plain one can be many times too
small. :class:`HacCovariance` estimates :math:`\Omega` from the weighted
lagged products of the scores, prewhitened (Andrews and Monahan 1992) with a
data-dependent bandwidth (Andrews 1991); docs/trust.md has the measured
coverage that chose it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from bcid_ros.estimators.lagged import effective_size, LaggedProducts, weights_of_counts
from bcid_ros.estimators.settings import SHARED_SETTINGS

#: Prewhitening: none (plain Newey-West), an AR(1) per component, or the larger of the two
#: in every direction (docs/trust.md).
PREWHITENINGS = ('none', 'diagonal', 'larger')
#: Lag windows: Bartlett (Newey-West) and Parzen.
KERNELS = ('bartlett', 'parzen')
#: Largest lag of the lag window (the bandwidth is capped here). Prewhitened,
#: the bandwidths measured on oversampled plants stay below 8 (docs/trust.md).
MAX_LAG = 16
#: The AR(1) coefficients of the prewhitening are capped at this magnitude
#: (Andrews and Monahan 1992 cap at 0.97): (1 - rho)^-1 stays below 33.
PREWHITENING_CAP = 0.97
#: The AR(1) coefficients of the bandwidth rule are clipped to this magnitude.
RHO_CAP = 0.99


@dataclasses.dataclass(frozen=True)
class HacState:
    """A copy of a :class:`HacCovariance`'s state (:meth:`HacCovariance.get_state`)."""

    products: dict[str, Any]


class HacCovariance:
    r"""
    The HAC sandwich covariance of an estimate from its estimating-equation scores.

    The scores are kept as weighted lagged products
    :math:`G(k) = \sum_t w_t^2 s_t s_{t-k}^T`, k = 0..L+1 (one list append per
    sample, one matrix product per block of 64,
    :mod:`bcid_ros.estimators.lagged`), so that
    :math:`\hat\Gamma(k) = \lambda^k G(k)/\tau_2` (:math:`w_t w_{t-k} = \lambda^k
    w_t^2`) and :math:`\tau_2\sum_k\hat\Gamma(k)` estimates
    :math:`\mathrm{var}\sum_t w_t s_t`. When :meth:`covariance` is read with
    the estimator's :math:`P = B^{-1}`, the moments are taken to the
    coordinates of the parameters, :math:`\Gamma_h(k) = P\hat\Gamma(k)P` of the
    influences :math:`h_t = P s_t` (:math:`\hat\theta - \theta \approx \sum_t
    w_t h_t`), normalised to unit variance, and:

    1. prewhitening (``'diagonal'``, Andrews and Monahan 1992):
       :math:`h^*_t = h_t - A h_{t-1}` with A the diagonal of the AR(1)
       coefficients :math:`\rho_a = \Gamma_h(1)_{aa}/\Gamma_h(0)_{aa}`, capped at
       ``PREWHITENING_CAP``; its moments are
       :math:`\Gamma^*(k) = \Gamma_h(k) - A\Gamma_h(k-1) - \Gamma_h(k+1)A
       + A\Gamma_h(k)A` (:math:`\Gamma_h(-1) = \Gamma_h(1)^T`). ``'none'``: A = 0.
       ``'larger'``: both, and :math:`\Omega_d + (\Omega_n - \Omega_d)_+` of
       the diagonal's :math:`\Omega_d` and the plain :math:`\Omega_n` (the
       positive part of a symmetric matrix keeps its positive eigenvalues): the
       least matrix of that form at or above each of them in every direction.
       The diagonal AR(1) misjudges a component that is a sum of unlike
       ones (a small principal axis hidden under a persistent one: rpem's std
       after a fit, docs/trust.md), and the plain one a persistent one
       (oversampled plants, below); each is right where the other fails;
    2. lag window: :math:`\Omega^* = \Gamma^*(0) + \sum_{k=1}^{L}\kappa(k/b)
       [\Gamma^*(k) + \Gamma^*(k)^T]`, Bartlett :math:`\kappa(x) = 1 - x` or
       Parzen, with the bandwidth of Andrews (1991), eq. (6.2) with the AR(1)
       plug-in (6.4) on the whitened components:
       :math:`b = 1.1447(\alpha_1 T)^{1/3}` (Bartlett),
       :math:`2.6614(\alpha_2 T)^{1/5}` (Parzen), T the effective sample size
       :math:`\tau^2/\tau_2`, capped at L;
    3. recolouring: :math:`\Omega_h = (I - A)^{-1}\Omega^*(I - A)^{-1}`;

    and :math:`\mathrm{cov}\,\hat\theta = \tau_2\,\Omega_h\,T/(T - p)`, the
    factor :math:`T/(T-p)` the small-sample correction of rls's
    :math:`\hat\sigma^2`. Prewhitening the scores themselves instead
    overstates the std up to five times on an oversampled plant, whose
    nearly collinear regressors make it over-difference the directions that
    decide the parameters (docs/trust.md).

    Parameters
    ----------
    dimension : int
        p, the length of a score.
    forgetting_factor : float
        The estimator's :math:`\lambda` in (0, 1].
    prewhitening : str
        One of :data:`PREWHITENINGS`.
    kernel : str
        One of :data:`KERNELS`.
    bandwidth : float, optional
        A fixed bandwidth b > 0; None: Andrews' rule (above).
    max_lag : int
        L >= 1.
    plants : int, optional
        K: scores ``(K, p)`` (:meth:`record`, every plant) or ``(R, p)``
        (:meth:`record_rows`, the plants that step) and results per plant,
        each plant with its own blocks, counts and weights; plant k's
        covariance is that of one HAC fed plant k's scores, within rounding
        (test/test_trust_plants.py), NaN where that one gives None.
        :meth:`plant_state` and :meth:`load_plant` move a plant to and from a
        single HAC's :meth:`get_state`. None: one plant, ``(p,)``.

    Raises
    ------
    ValueError
        If a setting is out of range.

    """

    def __init__(self, *, dimension: int, forgetting_factor: float = 1.0,
                 prewhitening: str = 'diagonal', kernel: str = 'bartlett',
                 bandwidth: float | None = None, max_lag: int = MAX_LAG,
                 plants: int | None = None) -> None:
        if not (isinstance(dimension, int) and dimension >= 1):
            raise ValueError(f'dimension must be an integer >= 1; got {dimension!r}')
        forgetting_factor = SHARED_SETTINGS['forgetting_factor'].check_argument(forgetting_factor)
        if prewhitening not in PREWHITENINGS:
            raise ValueError(f'prewhitening must be one of {", ".join(PREWHITENINGS)}; '
                             f'got {prewhitening!r}')
        if kernel not in KERNELS:
            raise ValueError(f'kernel must be one of {", ".join(KERNELS)}; got {kernel!r}')
        if bandwidth is not None and not 0.0 < bandwidth < math.inf:
            raise ValueError(f'bandwidth must be None or > 0; got {bandwidth!r}')
        if not (isinstance(max_lag, int) and max_lag >= 1):
            raise ValueError(f'max_lag must be an integer >= 1; got {max_lag!r}')
        if plants is not None and not (isinstance(plants, int) and plants >= 1):
            raise ValueError(f'plants must be None or an integer >= 1; got {plants!r}')
        self.dimension = dimension
        self.prewhitening, self.kernel, self.bandwidth = prewhitening, kernel, bandwidth
        self.max_lag, self.plants = max_lag, plants
        self._products = LaggedProducts(width=dimension, lags=max_lag + 1,
                                        decay=forgetting_factor ** 2, plants=plants)
        self.forgetting_factor = forgetting_factor
        self._lead = (1,) if plants is None else (plants,)
        self.reset()

    @property
    def forgetting_factor(self) -> float:
        """Return the estimator's forgetting factor lambda; may change while running (as P's)."""
        return self._forgetting_factor

    @forgetting_factor.setter
    def forgetting_factor(self, value: float) -> None:
        value = SHARED_SETTINGS['forgetting_factor'].check_argument(value)
        self._forgetting_factor = value
        # the scores' products are weighted by lambda^2 per step (w_t w_s of both)
        self._products.decay = value ** 2

    def __repr__(self) -> str:
        return (f'HacCovariance(dimension={self.dimension}, forgetting_factor='
                f'{self.forgetting_factor:g}, prewhitening={self.prewhitening!r}, '
                f'kernel={self.kernel!r}, bandwidth={self.bandwidth}, max_lag={self.max_lag}, '
                f'plants={self.plants})')

    def reset(self) -> None:
        """Forget every score (of every plant)."""
        self._products.reset()
        self._bandwidths: np.ndarray | None = None

    def clear(self, rows: Any) -> None:
        """Forget the scores of the plants ``rows`` (indices or a slice): a restart of those."""
        if self.plants is None:
            self.reset()
            return
        self._products.clear(rows)
        if self._bandwidths is not None:
            self._bandwidths[rows] = np.nan

    def record(self, score: Any) -> None:
        r"""
        Add one score :math:`s_t = \psi_t\varepsilon_t`, ``(p,)`` or ``(K, p)`` (every plant).

        One plant keeps it by reference until the next block of
        :data:`~bcid_ros.estimators.lagged.BLOCK`: do not change it afterwards.
        :math:`\varepsilon_t` may be the a-priori or the a-posteriori error of a recursive
        estimator: on stationary data both give the coverage of the batch residual
        (docs/trust.md).
        """
        self._products.append(score)

    def record_product(self, psi: np.ndarray, error: float) -> None:
        r"""
        Add the score :math:`\psi_t\varepsilon_t` of one plant from its two factors.

        The same as ``record(psi * error)``, the product formed for a block at
        once: a third of the cost per sample. ``psi`` is kept by reference.
        """
        self._products.append_product(psi, error)

    def record_all(self, scores: Any) -> None:
        """Add one plant's scores ``(m, p)``, oldest first: ``record`` of each row (copied)."""
        self._products.extend(scores)

    def complete(self) -> None:
        """
        Add the scores not yet in a block: the estimate is then of every score recorded.

        For a record that is whole (a batch fit's scores): the estimate is otherwise
        that of the last full block, and none before the first. Later scores start a
        new block.
        """
        self._products.flush()

    def record_rows(self, rows: Any, scores: Any) -> None:
        """
        Add one score of each plant in ``rows`` (K plants); the others do not step now.

        Parameters
        ----------
        rows : numpy.ndarray or slice
            The plants that record: distinct indices, or a slice.
        scores : numpy.ndarray, shape ``(R, p)``
            Their scores, in the order of ``rows`` (copied).

        Raises
        ------
        ValueError
            If the covariance is of one plant (``plants=None``).

        """
        if self.plants is None:
            raise ValueError('record_rows needs plants=K; one plant records with record()')
        self._products.record(rows, scores)

    # ------------------------------------------------------------ the results
    @property
    def samples(self) -> Any:
        """Count the recorded scores: an int, or ``(K,)``."""
        return self._products.samples

    def _weights_now(self) -> tuple[Any, Any]:
        """
        Return tau = sum w and tau_2 = sum w^2 over every recorded score (per plant).

        From the count at the factor now in force: after a live change, the
        new factor's weights, which the sums' own reach within a few memories.
        """
        return weights_of_counts(self.samples, self.forgetting_factor)

    def long_run(self, transform: np.ndarray | None = None) -> np.ndarray | None:
        r"""
        Return :math:`\hat\Omega`, ``(p, p)`` or ``(K, p, p)``, at the last block.

        It is per unit of :math:`\tau_2`: :math:`\tau_2\hat\Omega` estimates
        :math:`\mathrm{var}\sum_t w_t s_t`. With a ``transform`` M ``(p, p)``
        or ``(K, p, p)`` it is that of :math:`M s_t` instead, prewhitened and
        windowed in those coordinates. One plant: None before its first block;
        K plants: NaN in the plants before their first block.
        """
        products = self._products
        if self.plants is None:
            if products.count == 0 or not products.weight > 0.0:
                return None
            m = None if transform is None else np.asarray(transform, dtype=float)[None]
            long_run, self._bandwidths = self._long_run_of(
                products.sums[None], products.weight, products.squared_weight, m)
            return long_run[0]
        return self._long_run_rows(np.ones(self.plants, dtype=bool), transform)

    def _long_run_rows(self, wanted: np.ndarray, transform: np.ndarray | None) -> np.ndarray:
        """Return the long run ``(K, p, p)`` of the ``wanted`` plants with a block (NaN else)."""
        products, p, plants = self._products, self.dimension, self.plants
        long_run, self._bandwidths = np.full((plants, p, p), np.nan), np.full(plants, np.nan)
        known = wanted & (products.count > 0) & (products.weight > 0.0)
        if known.any():
            rows = _ALL if known.all() else np.flatnonzero(known)
            m = None if transform is None else np.broadcast_to(
                np.asarray(transform, dtype=float), (plants, p, p))[rows]
            long_run[rows], self._bandwidths[rows] = self._long_run_of(
                products.sums[rows], products.weight[rows], products.squared_weight[rows], m)
        return long_run

    def _long_run_of(self, sums: np.ndarray, weight: Any, squared: Any,
                     transform: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """
        Return Omega ``(R, p, p)`` and the bandwidths ``(R,)`` of R plants' sums.

        ``sums`` ``(R, p, p, L + 2)``; ``weight`` and ``squared`` the sums of the
        weights and of their squares, floats (one plant) or ``(R,)``.
        """
        lam = self.forgetting_factor
        lag_weights = lam ** np.arange(self.max_lag + 2, dtype=float)
        # (R, L + 2, p, p)
        gamma = np.moveaxis(sums * lag_weights, -1, 1) / np.reshape(weight, (-1, 1, 1, 1))
        if transform is not None:
            # Gamma_h(k) = M Gamma(k) M'
            gamma = transform[:, None] @ gamma @ np.swapaxes(transform, -1, -2)[:, None]
        # the effective sample size T = tau^2 / tau_2 at the last block (tau_2 > 0 here)
        size = effective_size(weight, squared)
        return long_run_covariance(gamma, size, self.prewhitening, self.kernel, self.bandwidth,
                                   lam)

    @property
    def bandwidths(self) -> Any:
        """Return the bandwidth b of the last :meth:`long_run` (per plant, NaN where none)."""
        if self._bandwidths is None:
            return None
        return float(self._bandwidths[0]) if self.plants is None else self._bandwidths.copy()

    def covariance(self, bread_inverse: np.ndarray,
                   wanted: np.ndarray | None = None) -> np.ndarray | None:
        r"""
        Return :math:`\tau_2 P\hat\Omega P\,T/(T - p)`, the HAC covariance of the estimate.

        Parameters
        ----------
        bread_inverse : numpy.ndarray, shape ``(p, p)`` or ``(K, p, p)``
            :math:`P = (\sum_t w_t\psi_t\psi_t^T)^{-1}` now.
        wanted : numpy.ndarray of bool, shape ``(K,)``, optional
            K plants: the plants whose covariance is asked (the others NaN, not
            computed: a validity decision of one plant among many).

        Returns
        -------
        numpy.ndarray or None
            Shape of ``bread_inverse``. One plant: None before the first block
            or while :math:`T \le p`; K plants: NaN in those plants.

        """
        tau, tau2 = self._weights_now()
        if self.plants is None:
            size = tau * tau / tau2 if tau2 > 0.0 else 0.0
            if not size > self.dimension:
                return None
            # the long-run covariance of the influences P s_t is P Omega P
            covariance = self.long_run(transform=np.asarray(bread_inverse, dtype=float))
            if covariance is None:
                return None
            covariance = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))
            return covariance * (tau2 * size / (size - self.dimension))
        size = np.where(tau2 > 0.0, tau * tau / np.where(tau2 > 0.0, tau2, 1.0), 0.0)
        enough = size > self.dimension
        if wanted is not None:
            enough &= wanted
        # the plants with too few samples are left out (their P may not be finite yet)
        covariance = self._long_run_rows(enough, bread_inverse)
        covariance = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))
        factor = np.where(enough, tau2 * size / np.where(enough, size - self.dimension, 1.0),
                          np.nan)
        return covariance * factor[:, None, None]

    # ------------------------------------------------------------ the state
    def get_state(self) -> HacState:
        """Return a copy of the state."""
        return HacState(products=self._products.state())

    def set_state(self, state: HacState) -> None:
        """Continue from a :meth:`get_state` of a covariance with the same settings."""
        self._products.load(state.products)
        self._bandwidths = None

    def plant_state(self, plant: int) -> HacState:
        """Return plant k's state in the form of a single plant's :meth:`get_state` (K plants)."""
        return HacState(products=self._products.plant_state(plant))

    def load_plant(self, plant: int, state: HacState) -> None:
        """Take over plant k from a single plant's :meth:`get_state` (K plants)."""
        self._products.load_plant(plant, state.products)
        if self._bandwidths is not None:
            self._bandwidths[plant] = np.nan


#: Every plant, as rows (a slice: views, not copies).
_ALL = slice(None)


def long_run_covariance(gamma: np.ndarray, size: float, prewhitening: str, kernel: str,
                        bandwidth: float | None, forgetting_factor: float = 1.0
                        ) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Return :math:`\hat\Omega` ``(K, p, p)`` and the bandwidths ``(K,)`` from the lagged moments.

    ``gamma`` ``(K, L + 2, p, p)`` holds :math:`\hat\Gamma(k)`, k = 0..L+1; ``size``
    is the effective sample size T; the forgetting factor :math:`\lambda` of
    the weights (see :func:`whitened_moments`). See :class:`HacCovariance` for
    the steps; the bandwidths of ``'larger'`` are those of its diagonal prewhitening.
    """
    if prewhitening == 'larger':
        diagonal, widths = long_run_covariance(gamma, size, 'diagonal', kernel, bandwidth,
                                               forgetting_factor)
        plain, _ = long_run_covariance(gamma, size, 'none', kernel, bandwidth,
                                       forgetting_factor)
        return diagonal + positive_part(plain - diagonal), widths
    count, lags = gamma.shape[0], gamma.shape[1] - 2
    # normalised units: unit variance per component (zero-power components keep scale 1)
    diagonal = np.einsum('kii->ki', gamma[:, 0])
    scale = np.sqrt(np.where(diagonal > 0.0, diagonal, 1.0))
    gamma = gamma / (scale[:, None, :, None] * scale[:, None, None, :])
    a = prewhitening_matrix(gamma, prewhitening)
    whitened = whitened_moments(gamma, a, forgetting_factor)           # (K, L+1, p, p)
    if bandwidth is None:
        widths = np.minimum(andrews_bandwidth(whitened, size, kernel), float(lags))
    else:
        widths = np.full(count, min(float(bandwidth), float(lags)))
    # a zero bandwidth (white whitened scores) keeps lag 0 only
    weights = lag_window(np.arange(1, lags + 1)[None, :] / np.maximum(widths, 1e-12)[:, None],
                         kernel)
    lagged = np.einsum('kl,klij->kij', weights, whitened[:, 1:])
    omega = whitened[:, 0] + lagged + np.swapaxes(lagged, -1, -2)
    # recolour: Omega = (I - A)^-1 Omega* (I - A)^-T
    identity = np.eye(gamma.shape[-1])
    recolour = np.linalg.inv(identity - a)
    omega = recolour @ omega @ np.swapaxes(recolour, -1, -2)
    omega = 0.5 * (omega + np.swapaxes(omega, -1, -2))
    return omega * (scale[:, :, None] * scale[:, None, :]), widths


def positive_part(matrices: np.ndarray) -> np.ndarray:
    """
    Return the positive part ``(K, p, p)`` of symmetric matrices: negative eigenvalues at 0.

    A matrix that is not finite (no data: all-zero scores) stays NaN, as the sums it came from.
    """
    symmetric = 0.5 * (matrices + np.swapaxes(matrices, -1, -2))
    finite = np.isfinite(symmetric).all(axis=(-2, -1))
    result = np.full_like(symmetric, np.nan)
    values, vectors = np.linalg.eigh(symmetric[finite])
    result[finite] = (vectors * np.maximum(values, 0.0)[..., None, :]) @ np.swapaxes(
        vectors, -1, -2)
    return result


def prewhitening_matrix(gamma: np.ndarray, prewhitening: str) -> np.ndarray:
    """Return the prewhitening matrix A ``(K, p, p)`` of normalised moments (see the class)."""
    count, p = gamma.shape[0], gamma.shape[-1]
    if prewhitening == 'none':
        return np.zeros((count, p, p))
    # AR(1) of each component: rho_a = Gamma(1)_aa / Gamma(0)_aa (unit variance here)
    rho = np.clip(np.einsum('kii->ki', gamma[:, 1]), -PREWHITENING_CAP, PREWHITENING_CAP)
    return rho[:, :, None] * np.eye(p)


def whitened_moments(gamma: np.ndarray, a: np.ndarray, forgetting_factor: float = 1.0
                     ) -> np.ndarray:
    r"""
    Return the moments :math:`\Gamma^*(k)` (k = 0..L) of :math:`s_t - A s_{t-1}` from those of s.

    ``gamma`` ``(K, L + 2, p, p)`` holds :math:`\Gamma(k) \propto \sum_t w_t w_{t-k}
    s_t s_{t-k}^T`, k = 0..L+1, and ``a`` ``(K, p, p)`` the prewhitening matrices.
    A product with :math:`s_{t-1}` in place of :math:`s_t` has its weights one
    sample older, :math:`w_{t-1} = \lambda w_t`, so that, exactly but for one
    row at the ends,

    .. math::

        \Gamma^*(k) = \Gamma(k) - \lambda^{-1}[A\Gamma(k-1) + \Gamma(k+1)A^T]
            + \lambda^{-2}A\Gamma(k)A^T, \qquad \Gamma(-1) = \Gamma(1)^T.

    The factors matter: prewhitening cancels most of :math:`\Gamma(k)`, and
    recolouring multiplies what is left by up to :math:`(1 - 0.97)^{-2}`.
    """
    lags = gamma.shape[1] - 2
    previous = np.concatenate((np.swapaxes(gamma[:, 1:2], -1, -2), gamma[:, :lags]), axis=1)
    a_row = a[:, None]
    a_t = np.swapaxes(a_row, -1, -2)
    current = gamma[:, :lags + 1]
    older = 1.0 / forgetting_factor
    return (current - older * (a_row @ previous + gamma[:, 1:lags + 2] @ a_t)
            + (older * older) * (a_row @ current @ a_t))


def andrews_bandwidth(whitened: np.ndarray, size: float, kernel: str) -> np.ndarray:
    r"""
    Return Andrews' (1991) AR(1) plug-in bandwidth of each plant, ``(K,)``.

    Each (whitened, unit-variance) component a gets an AR(1) fit
    :math:`\rho_a = \Gamma^*(1)_{aa}/\Gamma^*(0)_{aa}`, innovation variance
    :math:`\sigma_a^2 = 1 - \rho_a^2`;
    :math:`\alpha_1 = \sum 4\rho^2\sigma^4/((1-\rho)^6(1+\rho)^2) / \sum\sigma^4/(1-\rho)^4`,
    :math:`\alpha_2 = \sum 4\rho^2\sigma^4/(1-\rho)^8 / \sum\sigma^4/(1-\rho)^4`.
    """
    power = np.einsum('kii->ki', whitened[:, 0])
    first = np.einsum('kii->ki', whitened[:, 1])
    rho = np.clip(np.where(power > 0.0, first / np.where(power > 0.0, power, 1.0), 0.0),
                  -RHO_CAP, RHO_CAP)
    sigma4 = (1.0 - rho * rho) ** 2
    denominator = (sigma4 / (1.0 - rho) ** 4).sum(axis=-1)
    if kernel == 'bartlett':
        numerator = (4.0 * rho * rho * sigma4 / ((1.0 - rho) ** 6 * (1.0 + rho) ** 2)).sum(-1)
        return 1.1447 * (numerator / denominator * size) ** (1.0 / 3.0)
    numerator = (4.0 * rho * rho * sigma4 / (1.0 - rho) ** 8).sum(axis=-1)
    return 2.6614 * (numerator / denominator * size) ** 0.2


def lag_window(x: np.ndarray, kernel: str) -> np.ndarray:
    """Return the Bartlett or Parzen lag window at x = k / b >= 0."""
    if kernel == 'bartlett':
        return np.maximum(1.0 - x, 0.0)
    return np.where(x <= 0.5, 1.0 - 6.0 * x * x + 6.0 * x ** 3,
                    np.where(x <= 1.0, 2.0 * (1.0 - x) ** 3, 0.0))
