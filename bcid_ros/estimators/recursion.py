r"""
The recursive least-squares step of every estimator, over a leading plant axis.

One engine for the covariance recursion (Ding, Chen and Qiu 2006, eqs. (47)-(50);
the same step drives the Gauss-Newton recursion of rpem on psi):

.. math::

    e &= y - \varphi^T\hat\theta, \quad g = P\varphi, \quad s = \lambda + \varphi^T g \\
    \hat\theta &\leftarrow \hat\theta + g e / s, \quad
    P \leftarrow P - h h^T,\ h = g/\sqrt{s} \\
    P &\leftarrow \mathrm{propagate}(P) \quad \text{(what happens to P between samples)}

:func:`innovation`, :func:`ls_step` (one plant, BLAS: the hot path) and its
numpy twin :func:`ls_steps` (K plants), :func:`downdate` (P alone, for a
step whose theta moves otherwise), the propagation strategies
(:class:`Forgetting`: P / lambda with anti-windup; :class:`RandomWalk`: P + Q),
and the guarded and gated step of K plants (:func:`ls_step_rows`) that the
batched estimators run and a single plant runs as K = 1 for its rare samples.
The estimators (``rls``, ``bcrls``, the batched forms, ``rpem``, ``cl_bcls``'s
running LS, ``bciv``'s error floor) import it; it imports only the rulebook.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.blas import KERNELS, load_blas

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


def innovation(theta: np.ndarray, p: np.ndarray, phi: np.ndarray, y: float,
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


def ls_step(theta: np.ndarray, p: np.ndarray, g: np.ndarray, s: float,
            e: float) -> np.ndarray:
    r"""
    Make the RLS step (47)-(49) in place, without the division by :math:`\lambda`.

    :math:`\hat\theta \leftarrow \hat\theta + g e/s` and
    :math:`P \leftarrow P - h h^T` with :math:`h = g/\sqrt{s}`, which is
    symmetric to the last bit. ``g``, ``s`` and ``e`` come from
    :func:`innovation` and ``s`` must be finite and positive; ``g`` is
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


def downdate(p: np.ndarray, g: np.ndarray, s: float) -> np.ndarray:
    r"""
    Return :math:`P - h h^T`, :math:`h = g/\sqrt{s}`: the P part of :func:`ls_step` alone.

    For a recursion that moves theta by a rule of its own (rpem's projection
    into the stability region). In place when ``p`` is C-contiguous; ``g``
    is overwritten with h. The same arithmetic as :func:`ls_step`'s.
    """
    blas = KERNELS or load_blas()
    h = blas['dscal'](1.0 / math.sqrt(s), g)
    return blas['dger'](-1.0, h, h, 1, 1, p.T, 0, 0, 1).T


def ls_steps(theta: np.ndarray, p: np.ndarray, g: np.ndarray, s: np.ndarray,
             e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Make the RLS step (47)-(49) of K plants at once, without the division by :math:`\lambda`.

    The batched form of :func:`ls_step` (the same algebra, in numpy
    element-wise operations, which round in other places than the BLAS
    kernels: the two agree within rounding, not bit for bit). ``theta``
    ``(K, p)``, ``p`` ``(K, p, p)``, ``g`` ``(K, p)``, ``s`` and ``e``
    ``(K,)``, from :func:`innovation` per plant. Returns new arrays.
    """
    # theta(t) = theta(t-1) + g e / s
    theta = theta + g * (e / s)[:, None]
    # P(t) = P(t-1) - h h', h = g / sqrt(s): symmetric to the last bit
    h = g * (1.0 / np.sqrt(s))[:, None]
    return theta, p - h[:, :, None] * h[:, None, :]


class Forgetting:
    r"""
    Propagate P between samples by exponential forgetting, with anti-windup.

    :math:`P \leftarrow P/\lambda` (eq. (49)'s division) unless the normalised
    trace :math:`\mathrm{tr}(SPS) = \sum_k P_{kk} s_k^2` is at or past
    ``trace_limit`` (p0 p, its start): then P is held and the plant counted
    as ``windup_limited``, so that P cannot wind up while the data are not
    exciting. ``trace_limit = inf`` forgets without the limit.

    A propagation strategy: :func:`ls_step_rows` and the single-plant
    estimators call :meth:`propagate` (K plants) or :meth:`propagate_one`
    after every step; another strategy (:class:`RandomWalk`) is another
    object with the same two methods.
    """

    def __init__(self, trace_limit: float) -> None:
        self.trace_limit = trace_limit

    def propagate(self, p: np.ndarray, lam: float, weights: np.ndarray) -> np.ndarray:
        """
        Propagate ``p`` ``(K, p, p)`` in place; return where it was held (windup), ``(K,)``.

        ``weights`` ``(K, p)`` are the squared component scales :math:`s_k^2`.
        """
        if lam == 1.0:
            return np.zeros(p.shape[0], dtype=bool)
        # P(t) <- P(t) / lambda unless that would wind the normalised P up past its start
        windup = ~(rowdot(np.diagonal(p, axis1=1, axis2=2), weights) < self.trace_limit)
        p *= np.where(windup, 1.0, 1.0 / lam)[:, None, None]
        return windup

    def propagate_one(self, p: np.ndarray, lam: float, weights: np.ndarray | None = None) -> bool:
        """Propagate one plant's ``p`` ``(p, p)`` in place; return whether it was held."""
        if lam == 1.0:
            return False
        limit = self.trace_limit
        if limit < math.inf and not (
                (float(np.trace(p)) if weights is None else p.diagonal().dot(weights)) < limit):
            return True
        p *= 1.0 / lam
        return False


class RandomWalk:
    r"""
    Propagate P between samples by a random walk of the parameters: :math:`P \leftarrow P + Q`.

    The Kalman filter's time update for :math:`\theta(t) = \theta(t-1) + w(t)`,
    :math:`\mathrm{cov}\,w = Q = q S^{-2}`: ``drift`` q is the variance per
    sample of a parameter of a signal of unit size (the same normalised units
    as p0), so Q does not depend on the units of y and u. P only grows, so it
    never collapses while the data are not exciting; it is never held. Used
    with :math:`\lambda = 1` (the step's s then is :math:`1 + \varphi^T P\varphi`).
    Not wired to a setting here.
    """

    def __init__(self, drift: float) -> None:
        self.drift = drift

    def propagate(self, p: np.ndarray, lam: float, weights: np.ndarray) -> np.ndarray:
        """Add Q_k = q diag(1 / weights_k) to each ``p`` ``(K, p, p)`` in place; never held."""
        diagonal = np.einsum('kii->ki', p)
        diagonal += self.drift / weights
        return np.zeros(p.shape[0], dtype=bool)

    def propagate_one(self, p: np.ndarray, lam: float, weights: np.ndarray | None = None) -> bool:
        """Add Q = q diag(1 / weights) (q I without weights) to ``p`` in place; never held."""
        diagonal = np.einsum('ii->i', p)
        diagonal += self.drift if weights is None else self.drift / weights
        return False


#: What happens to P between samples: one of the strategies above.
Propagation = Forgetting | RandomWalk


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
    propagation: Propagation
    initial_covariance: float


@dataclasses.dataclass
class StepOutcome:
    """
    What happened to each plant of a :func:`ls_step_rows` call (masks over its rows).

    ``stepped``: the LS step was made; ``events``: flag name -> where it
    occurred; ``restart``: the regressor must restart (a step undone or a
    sample refused); ``relearn``: the plant starts afresh with new scales;
    ``errors``: the a-priori prediction errors (the equation errors);
    ``gains``: s(t) of the steps made with no safeguard and the gate quiet
    (those the single plant takes on its plain path, whose normalised error
    e / sqrt(s) goes to the change detector), 0 elsewhere.
    """

    stepped: np.ndarray
    events: dict[str, np.ndarray]
    restart: np.ndarray
    relearn: np.ndarray
    errors: np.ndarray
    gains: np.ndarray


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
    needed. ``rows`` are distinct and ascending; ``y`` ``(R,)`` and ``phi``
    ``(R, p)`` are their samples.
    """
    lam = settings.forgetting_factor
    count = rows.shape[0]
    stored = rows_view(rows, plants.tau.shape[0])
    theta, p_old = _copy_rows(plants.theta, stored), _copy_rows(plants.p, stored)
    loss, tau = _copy_rows(plants.loss, stored), _copy_rows(plants.tau, stored)
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
    plain = ~careful
    if tested.any():
        every = tested.all()  # (the common case: the arrays themselves, no subsets taken)
        at, e2_at, loss_at, tau_at, s_at = where_rows(tested, rows, e2, loss, tau, s)
        gated = stored if every else at
        # z^2 = e^2 / [(J / tau + floor)(s + 1 - lambda)]: the error over its variance
        z2 = e2_at / ((loss_at / tau_at + plants.variance_floor[gated]) * (s_at + 1.0 - lam))
        # the gate's quiet case (rules.gate_is_quiet): no score pending, within the limit
        quiet = (plants.score[gated] == 0.0) & (z2 <= settings.gate_limit2)
        used, plants.score[gated], plants.tail[gated], change = rules.gate(
            z2, settings.gate_limit2, plants.score[gated], plants.tail[gated])
        if every:
            plain &= quiet
            refused = ~used
        else:
            plain[tested] &= quiet
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
            plants, *where_rows(commit, rows, theta, p_old, g, s, e, loss, tau, careful),
            settings)
        stepped[commit] = kept
        for key, where in (('windup_limited', windup), ('covariance_repaired', repaired)):
            if where.any():
                events[key] = _mask(count, np.flatnonzero(commit)[where])
    if stepped.all():  # every plant stepped (the common case): none repaired, undone, refused
        nothing = np.zeros(count, dtype=bool)
        return StepOutcome(stepped, events, nothing, nothing.copy(), e, np.where(plain, s, 0.0))
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
    gains = np.where(plain & stepped, s, 0.0)
    return StepOutcome(stepped, events, undone | refused, relearn, e, gains)


def where_rows(mask: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Return the rows of ``arrays`` where ``mask``: the arrays themselves where it is all true."""
    if mask.all():
        return arrays
    return tuple(array[mask] for array in arrays)


def rows_view(rows: np.ndarray, count: int) -> slice | np.ndarray:
    """Return distinct ascending ``rows`` of ``count`` plants as a slice where they are all."""
    # (indexing by the slice gives views and copies no rows; by the rows, a gather)
    return slice(None) if rows.shape[0] == count else rows


def _copy_rows(array: np.ndarray, stored: slice | np.ndarray) -> np.ndarray:
    """Return a copy of the rows ``stored`` of ``array`` (a slice copied whole: no gather)."""
    return array[stored].copy() if isinstance(stored, slice) else array[stored]


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
    stored = rows_view(rows, plants.tau.shape[0])
    theta_new, p_new = ls_steps(theta, p_old, g, s, e)
    windup = settings.propagation.propagate(p_new, lam, plants.component_scale[stored] ** 2)
    plants.theta[stored], plants.p[stored] = theta_new, p_new
    # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
    plants.loss[stored] = lam * (loss + e * e / s)
    plants.tau[stored] = lam * tau + 1.0
    updates = plants.updates[stored] + 1
    plants.updates[stored] = updates
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
    plants.undone[stored if kept.all() else rows[kept]] = 0
    return kept, windup, repaired


def repair_rows(plants: LsPlants, rows: np.ndarray, initial_covariance: float) -> None:
    """Rebuild P of ``rows`` as the nearest symmetric positive definite matrices."""
    scale = plants.component_scale[rows]
    fallback = initial_covariance / scale ** 2
    plants.p[rows] = rules.repair_covariances(
        plants.p[rows], fallback[:, :, None] * np.eye(scale.shape[1]), scale)


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
