"""
Recursive least squares on the ARX regressor: the baseline estimator.

The recursion is eqs. (47)-(50) of Ding, Chen and Qiu (2006) with an
exponential forgetting factor, written so that the covariance P stays
symmetric positive definite and cannot wind up when the data stop being
exciting.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.base import RecursiveEstimator
from bcid_ros.estimators.blas import KERNELS, load_blas
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.regressor import ArxRegressor, phi_channels
from bcid_ros.estimators.residual_state import residual_items, residual_reasons, residual_states
from bcid_ros.estimators.simulation_check import SimulationWindow

#: How often (in updates) the covariance is checked by a Cholesky factorisation.
HEALTH_CHECK_PERIOD = 1000
#: A step with s(t) / lambda above this (the sample carries 1e8 times the
#: information of the memory) is checked before it is kept: its downdate
#: cancels about 8 digits of P. Normalised data start near p0 |phi|^2 ~ 1e6.
CAREFUL_GAIN = 1e8
#: Floor of the prediction error standard deviation, relative to the y scale,
#: so that noise-free data do not divide by zero in the gate.
VARIANCE_FLOOR = 2.0 ** -40
#: A plant whose steps are undone this many times in a row starts afresh with new scales.
UNDONE_LIMIT = 3


def rls_innovation(theta: np.ndarray, p: np.ndarray, phi: np.ndarray, y: float,
                   lam: float) -> tuple[float, np.ndarray, float]:
    r"""
    Return the a-priori quantities of one RLS step, eqs. (47)-(48).

    Parameters
    ----------
    theta : numpy.ndarray, shape ``(p,)``
        :math:`\hat\theta(t-1)`.
    p : numpy.ndarray, shape ``(p, p)``
        :math:`P(t-1)`, symmetric positive definite.
    phi : numpy.ndarray, shape ``(p,)``
        :math:`\varphi(t)`.
    y : float
        :math:`y(t)`.
    lam : float
        Forgetting factor :math:`\lambda`.

    Returns
    -------
    e : float
        :math:`e(t) = y(t) - \varphi^T(t)\hat\theta(t-1)`.
    g : numpy.ndarray, shape ``(p,)``
        :math:`g = P(t-1)\varphi(t)`.
    s : float
        :math:`s(t) = \lambda + \varphi^T(t) P(t-1)\varphi(t)`; not finite or
        :math:`\le 0` means the step must not be made.

    """
    # ndarray.dot: half the call overhead of @ at this size
    g = p.dot(phi)
    return y - phi.dot(theta), g, lam + phi.dot(g)


def rls_step(theta: np.ndarray, p: np.ndarray, g: np.ndarray, s: float,
             e: float) -> np.ndarray:
    r"""
    Make the RLS step (47)-(49) in place, without the division by :math:`\lambda`.

    :math:`\hat\theta \leftarrow \hat\theta + g e/s` and
    :math:`P \leftarrow P - h h^T` with :math:`h = g/\sqrt{s}`, which is
    symmetric to the last bit. ``g``, ``s`` and ``e`` come from
    :func:`rls_innovation` and ``s`` must be finite and positive; ``g`` is
    overwritten with h.

    Returns
    -------
    numpy.ndarray, shape ``(p, p)``
        The downdated P (the memory of ``p``, updated in place when ``p``
        is C-contiguous).

    """
    blas = KERNELS or load_blas()
    # theta(t) = theta(t-1) + g e / s   (BLAS axpy in place: daxpy(x, y, n, a))
    blas['daxpy'](g, theta, g.shape[0], e / s)
    # h = g / sqrt(s), in place (a scaling into a new array costs twice as much)
    h = blas['dscal'](1.0 / math.sqrt(s), g)
    # BLAS rank-1 update in place (P is C-ordered, so P.T is the Fortran view):
    # dger(alpha, x, y, incx, incy, a, overwrite_x, overwrite_y, overwrite_a)
    return blas['dger'](-1.0, h, h, 1, 1, p.T, 0, 0, 1).T


def rls_steps(theta: np.ndarray, p: np.ndarray, g: np.ndarray, s: np.ndarray,
              e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Make the RLS step (47)-(49) of K plants at once, without the division by :math:`\lambda`.

    The batched form of :func:`rls_step` (the same algebra, in numpy
    element-wise operations, which round in other places than the BLAS
    kernels: the two agree within rounding, not bit for bit). ``theta``
    ``(K, p)``, ``p`` ``(K, p, p)``, ``g`` ``(K, p)``, ``s`` and ``e``
    ``(K,)``, from :func:`rls_innovation` per plant. Returns new arrays.
    """
    # theta(t) = theta(t-1) + g e / s
    theta = theta + g * (e / s)[:, None]
    # P(t) = P(t-1) - h h', h = g / sqrt(s): symmetric to the last bit
    h = g * (1.0 / np.sqrt(s))[:, None]
    return theta, p - h[:, :, None] * h[:, None, :]


def matvec(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Return ``matrices[k] @ vectors[k]`` for every k, shape ``(K, p)``."""
    return np.matmul(matrices, vectors[:, :, None])[:, :, 0]


def rowdot(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Return ``left[k] . right[k]`` for every k, shape ``(K,)``."""
    return np.vecdot(left, right)


def repair_covariance(p: np.ndarray, fallback: np.ndarray,
                      weights: np.ndarray | None = None) -> np.ndarray:
    """Return the nearest symmetric positive definite matrix to one ``p`` (see rules)."""
    return rules.repair_covariances(p[None], fallback[None],
                                    None if weights is None else weights[None])[0]


@dataclasses.dataclass
class LsPlants:
    """
    The least-squares state of K plants, arrays with a leading plant axis.

    The batched estimators hold one over all their plants; a single-plant
    :class:`Rls` makes one over itself (K = 1, views of its arrays) for the
    rare samples that need more than the plain step (:func:`ls_step_rows`).

    Attributes
    ----------
    theta : numpy.ndarray, shape ``(K, p)``
        The LS estimates.
    p : numpy.ndarray, shape ``(K, p, p)``
        Their P.
    loss, tau : numpy.ndarray, shape ``(K,)``
        J and the weighted count of eq. (50).
    updates, undone : numpy.ndarray of int, shape ``(K,)``
        Updates made, and steps undone in a row.
    score, tail : numpy.ndarray, shape ``(K,)``
        The gate's change score and tail (:func:`~bcid_ros.estimators.rules.gate`).
    variance_floor : numpy.ndarray, shape ``(K,)``
        Floor of the prediction-error variance (VARIANCE_FLOOR times the y scale, squared).
    component_scale : numpy.ndarray, shape ``(K, p)``
        The signal scale of each component of phi.

    """

    theta: np.ndarray
    p: np.ndarray
    loss: np.ndarray
    tau: np.ndarray
    updates: np.ndarray
    undone: np.ndarray
    score: np.ndarray
    tail: np.ndarray
    variance_floor: np.ndarray
    component_scale: np.ndarray


@dataclasses.dataclass(frozen=True)
class LsSettings:
    """What :func:`ls_step_rows` needs of the estimator's settings (shared by its plants)."""

    forgetting_factor: float
    gate_limit2: float
    gate_from: float
    trace_limit: float
    initial_covariance: float


@dataclasses.dataclass
class StepOutcome:
    """
    What happened to each plant of a :func:`ls_step_rows` call (masks over its rows).

    ``stepped``: the LS step was made; ``events``: flag name -> where it
    occurred; ``restart``: the regressor must restart (a step undone or a
    sample refused); ``relearn``: the plant starts afresh with new scales;
    ``errors``: the a-priori prediction errors (the equation errors).
    """

    stepped: np.ndarray
    events: dict[str, np.ndarray]
    restart: np.ndarray
    relearn: np.ndarray
    errors: np.ndarray


def ls_step_rows(plants: LsPlants, rows: np.ndarray, y: np.ndarray, phi: np.ndarray,
                 settings: LsSettings) -> StepOutcome:
    """
    Do the guarded and gated RLS step (47)-(50) of plants ``rows`` (indices), in place.

    Per plant, as :class:`Rls` describes: a step with s <= 0 repairs P
    instead (``covariance_repaired``); one with a non-finite s or e^2 is
    undone (``update_undone``); once tau >= GATE_WARMUP p the gate decides
    (:func:`~bcid_ros.estimators.rules.gate`: ``outlier_rejected``, or
    ``plant_change`` with the memory cut); a risky step (s / lambda above
    CAREFUL_GAIN) is kept only if S P S stays sound and theta finite, and
    UNDONE_LIMIT such failures in a row start the plant afresh; forgetting
    stops while the normalised trace exceeds p0 p (``windup_limited``); every
    HEALTH_CHECK_PERIOD updates P is checked by Cholesky and repaired if
    needed. ``y`` ``(R,)`` and ``phi`` ``(R, p)`` are the rows' samples.
    """
    lam = settings.forgetting_factor
    count = rows.shape[0]
    theta, p_old = plants.theta[rows], plants.p[rows]
    loss, tau = plants.loss[rows], plants.tau[rows]
    # g = P(t-1) phi(t); s = lambda + phi' g; e = y(t) - phi' theta(t-1)
    g = matvec(p_old, phi)
    s = lam + rowdot(phi, g)
    e = y - rowdot(phi, theta)
    e2 = e * e
    events: dict[str, np.ndarray] = {}
    with np.errstate(invalid='ignore'):
        careful = ~((s < CAREFUL_GAIN * lam) & (e2 < math.inf))
        repair = s <= 0.0
        broken = careful & ~repair & ~((s < math.inf) & (e2 < math.inf))
    refused = np.zeros(count, dtype=bool)
    tested = ~(repair | broken) & (tau >= settings.gate_from)
    if tested.any():
        # z^2 = e^2 / [(J / tau + floor)(s + 1 - lambda)]: the error over its variance
        z2 = e2[tested] / ((loss[tested] / tau[tested] + plants.variance_floor[rows[tested]])
                           * (s[tested] + 1.0 - lam))
        at = rows[tested]
        used, plants.score[at], plants.tail[at], change = rules.gate(
            z2, settings.gate_limit2, plants.score[at], plants.tail[at])
        refused[tested] = ~used
        if change.any():
            changed = np.flatnonzero(tested)[change]
            events['plant_change'] = _mask(count, changed)
            cut = rows[changed]
            p_cut, loss_cut, tau_cut = plants.p[cut], plants.loss[cut], plants.tau[cut]
            rules.cut_memory(p_cut, loss_cut, tau_cut, theta.shape[1])
            plants.p[cut], plants.loss[cut], plants.tau[cut] = p_cut, loss_cut, tau_cut
            # the memory was cut (P grew): redo the a-priori part
            p_old[changed], loss[changed], tau[changed] = p_cut, loss_cut, tau_cut
            g[changed] = matvec(p_cut, phi[changed])
            s[changed] = lam + rowdot(phi[changed], g[changed])
    commit = ~(repair | broken | refused)
    stepped = commit.copy()
    if commit.any():
        kept, windup, repaired = _commit_rows(
            plants, rows[commit], theta[commit], p_old[commit], g[commit], s[commit], e[commit],
            loss[commit], tau[commit], careful[commit], settings)
        stepped[commit] = kept
        for key, where in (('windup_limited', windup), ('covariance_repaired', repaired)):
            if where.any():
                events[key] = _mask(count, np.flatnonzero(commit)[where])
    if repair.any():
        repair_rows(plants, rows[repair], settings.initial_covariance)
        events['covariance_repaired'] = events.get('covariance_repaired',
                                                   np.zeros(count, dtype=bool)) | repair
    relearn = np.zeros(count, dtype=bool)
    unsound = commit & ~stepped
    if unsound.any():
        # three undone in a row: the signal level is far from the scales of the first
        # samples, and what was learnt at that level is numerically worthless
        relearn[unsound] = plants.undone[rows[unsound]] >= UNDONE_LIMIT
    undone = broken | (unsound & ~relearn)
    if undone.any():
        events['update_undone'] = undone
    if refused.any():
        events['outlier_rejected'] = refused
    return StepOutcome(stepped, events, undone | refused, relearn, e)


def _mask(count: int, where: np.ndarray) -> np.ndarray:
    mask = np.zeros(count, dtype=bool)
    mask[where] = True
    return mask


def _commit_rows(plants: LsPlants, rows: np.ndarray, theta: np.ndarray, p_old: np.ndarray,
                 g: np.ndarray, s: np.ndarray, e: np.ndarray, loss: np.ndarray,
                 tau: np.ndarray, careful: np.ndarray,
                 settings: LsSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Commit the step of ``rows``; undo the careful ones that broke P.

    Return masks over ``rows``: the steps kept, where forgetting was limited
    (windup) and where the health check repaired P.
    """
    lam = settings.forgetting_factor
    theta_new, p_new = rls_steps(theta, p_old, g, s, e)
    windup = np.zeros(rows.shape[0], dtype=bool)
    if lam < 1.0:
        # P(t) <- P(t) / lambda unless that would wind the normalised P up past its start
        weighted = rowdot(np.diagonal(p_new, axis1=1, axis2=2), plants.component_scale[rows] ** 2)
        windup = ~(weighted < settings.trace_limit)
        p_new *= np.where(windup, 1.0, 1.0 / lam)[:, None, None]
    plants.theta[rows], plants.p[rows] = theta_new, p_new
    # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
    plants.loss[rows] = lam * (loss + e * e / s)
    plants.tau[rows] = lam * tau + 1.0
    updates = plants.updates[rows] + 1
    plants.updates[rows] = updates
    repaired = np.zeros(rows.shape[0], dtype=bool)
    due = updates % HEALTH_CHECK_PERIOD == 0
    if due.any():
        repaired[due] = ~rules.definite(p_new[due])
        if repaired.any():
            repair_rows(plants, rows[repaired], settings.initial_covariance)
    kept = np.ones(rows.shape[0], dtype=bool)
    if careful.any():
        risky = rows[careful]
        kept[careful] = rules.sound_covariances(plants.p[risky], plants.component_scale[risky]) \
            & np.isfinite(plants.theta[risky]).all(axis=1)
        back = ~kept
        if back.any():
            lost = rows[back]
            plants.theta[lost], plants.p[lost] = theta[back], p_old[back]
            plants.loss[lost], plants.tau[lost] = loss[back], tau[back]
            plants.updates[lost] -= 1
            plants.undone[lost] += 1
    plants.undone[rows[kept]] = 0
    return kept, windup, repaired


def repair_rows(plants: LsPlants, rows: np.ndarray, initial_covariance: float) -> None:
    """Rebuild P of ``rows`` as the nearest symmetric positive definite matrices."""
    scale = plants.component_scale[rows]
    fallback = initial_covariance / scale ** 2
    plants.p[rows] = rules.repair_covariances(
        plants.p[rows], fallback[:, :, None] * np.eye(scale.shape[1]), scale)


#: No event (a mask of one False).
_NO = np.zeros(1, dtype=bool)


def scale_dependents(scales: np.ndarray,
                     channel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return each plant's component scales ``(K, p)`` and variance floor ``(K,)``.

    ``scales`` ``(K, 1 + r)`` are the signal scales (0: not chosen yet, taken
    as 1), ``channel`` the channel of each component of phi
    (:func:`~bcid_ros.estimators.regressor.phi_channels`).
    """
    component = scales[:, channel]
    y_scale = np.where(scales[:, 0] > 0.0, scales[:, 0], 1.0)
    return np.where(component > 0.0, component, 1.0), (VARIANCE_FLOOR * y_scale) ** 2


class LsAccessors:
    """The accessors of a least-squares state, for one plant and for K (a leading axis)."""

    @property
    def signal_scale(self) -> np.ndarray:
        """Return the scales of y, u_1 ... u_r (0 while a channel has only seen zeros)."""
        return self._signal_scale.copy()

    @property
    def initial_covariance_diagonal(self) -> np.ndarray:
        """Return the diagonal of P(0) = p0 S^-2 in the user's units."""
        return self.initial_covariance / self._component_scale ** 2

    @property
    def covariance(self) -> np.ndarray:
        """Return the covariance matrix P(t) (a copy)."""
        return self._p.copy()


class Rls(LsAccessors, RecursiveEstimator):
    r"""
    Recursive least squares with forgetting, guarded, gated and unit-free.

    For the ARX regressor :math:`\varphi(t)` of Ding et al. (2006), eqs. (53)-(55):

    .. math::

        e(t) &= y(t) - \varphi^T(t)\hat\theta(t-1) \\
        s(t) &= \lambda + \varphi^T(t) P(t-1) \varphi(t) \\
        \hat\theta(t) &= \hat\theta(t-1) + P(t-1)\varphi(t)\, e(t) / s(t)
            && \text{(47), (48)} \\
        P(t) &= \frac{1}{\lambda}\Big[P(t-1) - \frac{P(t-1)\varphi(t)\varphi^T(t)P(t-1)}{s(t)}\Big]
            && \text{(49)} \\
        J(t) &= \lambda J(t-1) + \lambda e^2(t) / s(t) && \text{(50)} \\
        \tau(t) &= \lambda \tau(t-1) + 1

    With :math:`\lambda = 1` this is exactly the paper's recursion and
    :math:`\tau(t) = t`. :math:`\tau` is the weighted sample count and
    :math:`J/\tau` the published residual variance.

    **Units.** :math:`P(0) = p_0 S^{-2}`, where :math:`S = \mathrm{diag}(s_k)`
    holds the scale of the signal in :math:`\varphi_k`: per channel (y and
    each :math:`u_i`) the smallest power of two at or above the largest
    magnitude of the first samples (those in the regressor at the first
    update; a channel that is still all zero gets its scale when it first
    is not). This is RLS on the normalised signals :math:`\varphi_k/s_k` with
    :math:`P(0) = p_0 I`, mapped back, and bit-for-bit so because the scales
    are powers of two: the estimates do not depend on the units of y and u,
    and ``initial_covariance`` is the prior variance of the parameters of
    signals of unit size.

    **Safeguards** (docs/estimators.md), each counted in :attr:`flags`:

    * the downdate is written as :math:`P - h h^T` with
      :math:`h = P\varphi/\sqrt{s}`, symmetric to the last bit;
    * anti-windup: the division by :math:`\lambda` is skipped while the
      normalised trace :math:`\mathrm{tr}(SPS)` exceeds :math:`p_0 p`
      (``windup_limited``);
    * transaction: a step with a non-finite :math:`s(t)` or :math:`e^2(t)`,
      or with :math:`s(t)/\lambda >` ``CAREFUL_GAIN`` that leaves
      :math:`SPS` numerically indefinite or conditioned beyond 1e13, is
      undone (``update_undone``) and the regressor restarts; three in a row
      mean the signal level is far from that of the first samples: the
      estimator starts afresh with new scales (``rescaled``);
    * gate: :math:`z^2 = e^2 / [(J/\tau)(1 + \varphi^T P \varphi)]`, the
      squared prediction error over its variance, goes to the rulebook's
      gate (:func:`~bcid_ros.estimators.rules.gate`: ``outlier_rejected``,
      ``plant_change``) once
      :math:`\tau \ge` ``GATE_WARMUP`` p. A detected plant change cuts the
      memory to ``CHANGE_MEMORY`` p samples: :math:`P \leftarrow P/\kappa`,
      :math:`J \leftarrow \kappa J`, :math:`\tau \leftarrow \kappa\tau`, one
      extra forgetting step that keeps :math:`J/\tau` and :math:`\tau P`;
    * every ``HEALTH_CHECK_PERIOD`` updates, and whenever :math:`s \le 0`,
      P is checked by a Cholesky factorisation and, if it has lost
      definiteness, rebuilt (``covariance_repaired``).

    **Validity**, re-evaluated every ``VALIDITY_PERIOD`` updates: the model
    :math:`A(q)` of the published estimate is unstable (a pole beyond
    ``UNSTABLE_RADIUS``) while the output power over the memory did not
    grow by ``GROWTH`` since the last check (bounded data).

    The plain step is the hot path, written here on floats and BLAS; a
    sample that needs any safeguard (a risky gain, a non-finite error, the
    gate refusing or scoring, s <= 0) goes through :func:`ls_step_rows`, the
    rules of every plant of the batched estimators, with this one plant as
    K = 1: the two take the same decisions by construction.

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`.
    input_delay, detrend, adapt
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`; a dead time
        delays the input lags of phi (docs/estimators.md, "Dead time").

    """

    name = 'rls'
    noise_names = ('residual_variance',)
    #: The residual the model says is white, for the residual tests
    #: (:data:`~bcid_ros.estimators.adequacy.MODEL_TESTS`): the equation error.
    adequacy_model = 'arx'
    #: Whether the published std is the HAC sandwich of the equation error's scores.
    hac_std = True

    def __init__(self, **settings: Any) -> None:
        super().__init__(**settings)
        self._regressor = ArxRegressor(self.order, self.num_inputs, self.feedthrough,
                                       self.input_delay)
        self._trace_limit = self.initial_covariance * self.num_parameters
        self._channel = phi_channels(self.order, self.num_inputs, self.feedthrough)
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        phi = self._regressor.push(y, u)
        if self._scales_pending and self._regressor.ready:
            self._choose_scales()
        if self._regressor.ready and self._ls_step(y, phi):
            self._after_ls_step(y, phi)
            if self._tau >= self._gate_from and not self._quiet_left:
                self._record_residual(y, phi, u)
            if self._updates >= self._next_check:
                self._check_validity()

    #: _ls_step checks before it commits: the cheap form of the transaction.
    _guarded_update = _update

    def trusted_block_update(self, rows: np.ndarray) -> Callable[[float, np.ndarray], None]:
        """
        Return the update for each row of a checked block (see the base class).

        When the rows would go straight to the step with a filled regressor
        and chosen scales, their regressors are formed for the block at once
        (:meth:`ArxRegressor.push_rows`) and each row takes only the step: the
        same phi(t), so the same estimate, without a push and its checks per row. The
        regressor is then ahead of the rows until the block is done, which no
        step reads: a refused step only clears it (:meth:`_undo`), and the rows
        after that go sample by sample into the empty regressor, as they would
        have; the rescaling that reads it needs two undone steps in a row
        before it, so a block that starts after one goes sample by sample. A
        row that raises ends the block, and its caller restarts the regressor.
        """
        update = super().trusted_block_update(rows)
        regressor = self._regressor
        if (update != self._guarded_update or self._scales_pending or not regressor.ready
                or self._undone_in_row):
            return update
        regressors = iter(regressor.push_rows(rows))
        refused_before = self._refused

        def step(y: float, u: np.ndarray) -> None:
            phi = next(regressors)
            if self._refused != refused_before:  # a refusal restarted the regressor
                self._update(y, u)
            elif self._ls_step(y, phi):
                self._after_ls_step(y, phi)
                if self._tau >= self._gate_from and not self._quiet_left:
                    self._record_residual(y, phi, u)
                if self._updates >= self._next_check:
                    self._check_validity()

        return step

    def _hold(self, y: float, u: np.ndarray) -> None:
        """Move the regressor on without a step: theta, P, J and tau stay as they are."""
        self._regressor.push(y, u)

    def _after_ls_step(self, y: float, phi: np.ndarray) -> None:
        """Extend the LS step on (y, phi) (the bias compensation of subclasses); nothing here."""

    def _record_residual(self, y: float, phi: np.ndarray, u: np.ndarray) -> None:
        """
        Give the residual tests and the HAC covariance this step's equation error.

        From the gate's warm-up on (tau >= GATE_WARMUP p), as the gate: the
        a-priori errors of the first, converging steps are correlated with the
        inputs by design (docs/trust.md). Not while a huge value (beyond
        2^450) is in the regressor: its products would overflow the tests' sums.
        """
        error = self._error
        self._monitor.record(error, u)
        self._simulation.record(y, u)  # (the simulation check, issue 34)
        # the score phi e of the estimating equations sum_t w_t phi (y - phi' theta) = 0
        self._hac.record_product(phi, error)

    def _ls_step(self, y: float, phi: np.ndarray) -> bool:
        """Do the RLS step (47)-(50) on a ready regressor ``phi``; return whether it did."""
        lam = self._forgetting_factor
        g = self._p.dot(phi)
        s = lam + float(phi.dot(g))
        e = y - float(phi.dot(self._theta_ls))
        if not (s < CAREFUL_GAIN * lam and e * e < math.inf and s > 0.0):
            return self._rare_step(y, phi)
        tau = self._tau
        if tau >= self._gate_from:
            # the gate's quiet case (rules.gate_is_quiet) written out on floats: used, and
            # only a lifted tail moves; any other tested sample goes to the rules
            if self._change_score or not e * e / ((self._loss / tau + self._variance_floor)
                                                  * (s + 1.0 - lam)) <= self._gate_limit2:
                return self._rare_step(y, phi)
            if self._gate_tail != 1.0:
                self._gate_tail = rules.lowered_tail(self._gate_tail)
        self._error = e
        self._p = rls_step(self._theta_ls, self._p, g, s, e)
        # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
        self._loss = lam * (self._loss + e * e / s)
        self._tau = lam * tau + 1.0
        if lam < 1.0:
            self._forget()
        self._updates += 1
        if self._updates % HEALTH_CHECK_PERIOD == 0:
            self._check_covariance()
        self._undone_in_row = 0
        return True

    def _rare_step(self, y: float, phi: np.ndarray) -> bool:
        """Do the step by :func:`ls_step_rows` (this plant as K = 1); return whether it did."""
        plants = self._as_plants()
        outcome = ls_step_rows(plants, np.zeros(1, dtype=np.intp), np.array([y]), phi[None],
                               self._ls_settings())
        self._take_scalars(plants)
        self._error = float(outcome.errors[0])
        for key, where in outcome.events.items():
            if where[0]:
                self._flag(key)
        if outcome.events.get('plant_change', _NO)[0]:
            self._forget_residuals()
        if outcome.restart[0]:
            self._refused += 1
            self._restart_regressor()
        if outcome.relearn[0]:
            self._restart_learning()
        return bool(outcome.stepped[0])

    def _as_plants(self) -> LsPlants:
        """Return this estimator's LS state as one plant (views of theta and P)."""
        return LsPlants(self._theta_ls[None], self._p[None], np.array([self._loss]),
                        np.array([self._tau]), np.array([self._updates]),
                        np.array([self._undone_in_row]), np.array([self._change_score]),
                        np.array([self._gate_tail]), np.array([self._variance_floor]),
                        self._component_scale[None])

    def _take_scalars(self, plants: LsPlants) -> None:
        """Take back the scalars of :meth:`_as_plants` (theta and P were views)."""
        self._loss, self._tau = float(plants.loss[0]), float(plants.tau[0])
        self._updates, self._undone_in_row = int(plants.updates[0]), int(plants.undone[0])
        self._change_score, self._gate_tail = float(plants.score[0]), float(plants.tail[0])

    def _ls_settings(self) -> LsSettings:
        return LsSettings(self._forgetting_factor, self._gate_limit2, self._gate_from,
                          self._trace_limit, self.initial_covariance)

    def _restart_learning(self) -> None:
        """Start afresh with scales chosen from the samples now in the regressor."""
        self._flag('rescaled')
        regressor = self._regressor
        history, filled, position = regressor.history.copy(), regressor.filled, \
            regressor.position
        self._reset()
        regressor.history[:] = history
        regressor.filled, regressor.position = filled, position
        self._choose_scales()

    def _forget(self) -> None:
        """Apply P(t) <- P(t) / lambda unless that would wind P up past its start."""
        if self._p.diagonal().dot(self._trace_weights) < self._trace_limit:
            self._p *= 1.0 / self._forgetting_factor
        else:
            self._flag('windup_limited')

    def _check_covariance(self) -> None:
        """Repair P if it lost definiteness (the health check of the plain step)."""
        if not rules.definite(self._p[None])[0]:
            self._repair_covariance()

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix."""
        self._flag('covariance_repaired')
        repair_rows(self._as_plants(), np.zeros(1, dtype=np.intp), self.initial_covariance)

    # ------------------------------------------------------------ the units
    def _initial_p(self) -> np.ndarray:
        """Return P(0) = p0 S^-2 for the current scales."""
        return np.diag(self.initial_covariance / self._component_scale ** 2)

    def _choose_scales(self) -> None:
        """Give each channel still without a scale the one of the data in the regressor."""
        new = rules.choose_scales(self._signal_scale[None], self._regressor.peaks()[None])
        rules.rescale_new_channels(self._p[None], new, self._signal_scale[None], self._channel)
        self._set_scale_dependents()

    def _set_scale_dependents(self) -> None:
        self._scales_pending = bool((self._signal_scale == 0.0).any())
        component, floor = scale_dependents(self._signal_scale[None], self._channel)
        self._component_scale, self._variance_floor = component[0], float(floor[0])
        self._trace_weights = self._component_scale ** 2

    # --------------------------------------------------------- the validity
    def _check_validity(self) -> None:
        self._next_check = self._updates + rules.VALIDITY_PERIOD
        with np.errstate(all='ignore'):
            self._reasons = tuple(self._find_problems())

    def _find_problems(self) -> list[str]:
        """Return the reasons not to trust the estimate now (see the class docstring)."""
        power = rules.output_powers(self._p[None], np.array([self._tau]), self.order)
        reasons = rules.unstable_models(self._theta()[None, :self.order], power,
                                        np.array([self._last_power]))[0]
        self._last_power = float(power[0])
        return reasons + residual_reasons(self._monitor) + self._simulation_reasons()

    def _simulation_reasons(self) -> list[str]:
        """
        Return the simulation check's reason (:mod:`~bcid_ros.estimators.simulation_check`).

        Apart from the other reasons so that it can move with them: the model's simulated
        output over the last samples against a refit (a one-step error that is small and
        white does not make a simulation that is right).
        """
        theta = self._theta()
        n = self.order
        return self._simulation.reasons(theta[:n], theta[n:])

    def _validity_reasons(self) -> tuple[str, ...]:
        return self._reasons

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether phi(t) is filled and at least p updates have been made."""
        return self._updates >= self.num_parameters

    @property
    def valid(self) -> bool:
        """Whether :attr:`ready` and no :attr:`validity_reasons` (see the class docstring)."""
        return self._updates >= self.num_parameters and not self._reasons

    @property
    def samples(self) -> int:
        """Count the estimator updates (samples with a filled regressor)."""
        return self._updates

    @property
    def covariance_trace(self) -> float:
        """Return tr P(t)."""
        return float(np.trace(self._p))

    @property
    def loss(self) -> float:
        """Return the weighted loss J(t) of eq. (50)."""
        return self._loss

    @property
    def weighted_count(self) -> float:
        """Return tau(t) = sum of lambda^(t-i); equals t when lambda = 1."""
        return self._tau

    # ------------------------------------------------------- the uncertainty
    def _parameter_covariance(self) -> np.ndarray | None:
        r"""
        Return the HAC sandwich covariance of the LS estimate (None before its first block).

        The LS estimate solves :math:`\sum_t w_t\varphi_t(y_t - \varphi_t^T\theta) = 0`,
        so :math:`\hat\theta - \theta \approx P\sum_t w_t\varphi_t e_t` and its
        covariance is :math:`P\,\mathrm{var}(\sum_t w_t s_t)\,P` with the scores
        :math:`s_t = \varphi_t e_t`. :class:`~bcid_ros.estimators.hac.HacCovariance`
        estimates the middle from the scores' lagged products, prewhitened and
        windowed (Andrews 1991; Andrews and Monahan 1992): calibrated whether
        the equation error is white (an ARX plant) or coloured (docs/trust.md).
        The scores count from the gate's warm-up on; the first block of 64
        gives the first covariance.
        """
        if self._updates < self.num_parameters:
            return None
        return self._hac.covariance(self._p)

    def _theta(self) -> np.ndarray:
        return self._theta_ls

    def _theta_uncompensated(self) -> np.ndarray:
        return self._theta_ls

    def _noise(self) -> np.ndarray:
        return np.array([self._loss / self._tau if self._tau > 0 else 0.0])

    # -------------------------------------------------------------- the state
    def _reset(self) -> None:
        p = self.num_parameters
        self._regressor.clear()
        self._theta_ls = np.zeros(p)
        self._p = self.initial_covariance * np.eye(p)
        self._loss = 0.0
        self._tau = 0.0
        self._updates = 0
        self._signal_scale = np.zeros(1 + self.num_inputs)
        self._set_scale_dependents()
        self._gate_from = rules.GATE_WARMUP * p
        self._undone_in_row = 0
        self._next_check = p
        self._last_power = math.inf
        self._reasons: tuple[str, ...] = ()
        self._error = 0.0
        self._forget_residuals()

    def _forget_residuals(self) -> None:
        """Start the residual tests, the HAC and the simulation check afresh (reset, change)."""
        self._simulation = SimulationWindow(self.order, self.num_inputs, self.feedthrough,
                                            self.input_delay)
        self._monitor = AdequacyMonitor(num_inputs=self.num_inputs, model=self.adequacy_model,
                                        forgetting_factor=self._forgetting_factor)
        self._hac = (HacCovariance(dimension=self.num_parameters,
                                   forgetting_factor=self._forgetting_factor)
                     if self.hac_std else None)

    def _restart_regressor(self) -> None:
        self._regressor.clear()
        self._simulation.clear()  # (a gap in its window)

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays = {'theta_ls': self._theta_ls, 'p': self._p,
                  'history': self._regressor.history, 'signal_scale': self._signal_scale}
        scalars = {'loss': self._loss, 'tau': self._tau, 'updates': self._updates,
                   'filled': self._regressor.filled,
                   'position': self._regressor.position,
                   'forgetting_factor': self._forgetting_factor,
                   'undone_in_row': self._undone_in_row, 'next_check': self._next_check,
                   'last_power': self._last_power, 'reasons': self._reasons}
        residual_arrays, residual_scalars = residual_items(
            self._monitor.get_state(), None if self._hac is None else self._hac.get_state())
        # (the simulation check's window is not in the state: the batched forms, whose
        # plant states must equal this one's, have no check yet; it refills after a restore)
        return {**arrays, **residual_arrays}, {**scalars, **residual_scalars}

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._theta_ls = arrays['theta_ls']
        self._p = arrays['p']
        self._regressor.history[:] = arrays['history']
        self._signal_scale = arrays['signal_scale']
        self._set_scale_dependents()
        self._regressor.filled = int(scalars['filled'])
        self._regressor.position = int(scalars['position'])
        self._loss = float(scalars['loss'])
        self._tau = float(scalars['tau'])
        self._updates = int(scalars['updates'])
        self._forgetting_factor = float(scalars['forgetting_factor'])
        self._undone_in_row = int(scalars['undone_in_row'])
        self._next_check = int(scalars['next_check'])
        self._last_power = float(scalars['last_power'])
        self._reasons = tuple(scalars['reasons'])
        monitor, hac = residual_states(arrays, scalars)
        self._monitor.set_state(monitor)
        self._simulation.clear()
        if self._hac is not None:
            self._hac.set_state(hac)


def ls_batch(y: np.ndarray, u: np.ndarray, *, order: int, num_inputs: int = 1,
             feedthrough: bool = False, initial_covariance: Any = None,
             forgetting_factor: float = 1.0,
             input_delay: Any = None) -> tuple[np.ndarray, np.ndarray, float, float]:
    r"""
    Solve the (weighted, regularised) least-squares problem that :class:`Rls` solves recursively.

    .. math::

        \hat\theta_{LS}(N) = \Big[\lambda^{N'} P_0^{-1} + \sum_i \lambda^{N'-i}\varphi(i)
            \varphi^T(i)\Big]^{-1} \sum_i \lambda^{N'-i}\varphi(i) y(i)

    over the N' = N - n - max(d_i) updates that have a filled regressor, with
    :math:`P_0 = \mathrm{diag}(` ``initial_covariance`` :math:`)` (a scalar
    or the p diagonal entries, e.g. :attr:`Rls.initial_covariance_diagonal`).
    With ``initial_covariance=None`` the :math:`P_0^{-1}` term is dropped
    (plain LS).

    Parameters
    ----------
    y : numpy.ndarray, shape ``(N,)``
        Outputs.
    u : numpy.ndarray, shape ``(N,)`` or ``(N, r)``
        Inputs.
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        As for :class:`Rls`.
    input_delay : sequence of int, optional
        Dead time d_i of each input (None: none).

    Returns
    -------
    theta : numpy.ndarray, shape ``(p,)``
        The LS estimate.
    p : numpy.ndarray, shape ``(p, p)``
        The inverse of the (regularised) weighted information matrix.
    loss : float
        J = weighted sum of squared residuals at theta.
    tau : float
        Weighted sample count sum(lambda^(N'-i)).

    """
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(y.shape[0], -1)
    regressor = ArxRegressor(order, num_inputs, feedthrough, input_delay)
    phi = regressor.regressors(y, u)
    target = y[regressor.span:]
    weights = forgetting_factor ** np.arange(phi.shape[0] - 1, -1, -1, dtype=float)
    information = (phi * weights[:, None]).T @ phi
    if initial_covariance is not None:
        prior = np.broadcast_to(np.asarray(initial_covariance, dtype=float), (phi.shape[1],))
        information += np.diag(forgetting_factor ** phi.shape[0] / prior)
    theta = np.linalg.solve(information, (phi * weights[:, None]).T @ target)
    residual = target - phi @ theta
    return theta, np.linalg.inv(information), float(weights @ residual ** 2), float(
        weights.sum())
