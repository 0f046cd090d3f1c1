"""
Where ``valid`` is decided, for one plant and for K: the one home of the decision.

An estimate is valid when its estimator is ready and there is no reason to
distrust it. The reasons are the estimator's own (from its equations: an
unstable model, a compensation that does not converge, ...) and the ones every
estimator shares: the residual tests' and the simulation check's; a detected
plant change adds its own, which holds until the residual tests are ready on a
full window of the new plant's samples and the new estimate is known to
``PRECISION`` of its size (:func:`imprecision`; docs/trust.md, docs/tracking.md). An
estimator that states a standing precision (:meth:`Validity._standing_precision`:
rpem) is, at all times, not valid while its own std says its estimate is not known to
that looser share of its size. A
check changes nothing but the reasons: what it finds that needs action is done
by the estimator's update.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, ClassVar, Sequence

import numpy as np

from bcid_ros.estimators.residual_state import residual_reasons
from bcid_ros.estimators.simulation_check import (CHECK_PERIOD, simulation_reasons,
                                                  SimulationWindow, UNDERSTATED)

#: After a plant change, the estimate must be known to this share of its size (2-norm)
#: before the change is done: PRECISION_SIGMAS sqrt(tr C) <= PRECISION ||theta_hat||.
PRECISION = 0.1
#: The multiple of sqrt(tr C), the RMS of ||theta_hat - theta||, that bounds the error: for
#: a Gaussian error of any covariance C, P(||e|| >= k sqrt(tr C)) <= P(|z| >= k) for
#: k^2 >= 1.54 (Szekely and Bakirov 2003), 4.6 % at k = 2.
PRECISION_SIGMAS = 2.0
#: At all times, where an estimator states it (:meth:`Validity._standing_precision`): an
#: estimate that passed every check is not valid while PRECISION_SIGMAS sqrt(tr C) > this
#: share of ||theta_hat||, its error up to a third of its size (docs/trust.md, "Precision at
#: all times").
STANDING_PRECISION = 0.3
#: How the reason of an estimate not yet known to PRECISION begins (it names the std).
IMPRECISE = 'imprecise'
#: Why the estimate is not precise enough after a change, and at all times.
_AFTER_CHANGE = "the new plant's samples do not determine it yet"
_STANDING = 'its samples do not determine it'
#: The reason's text while there is no covariance.
_NO_STD = 'no std of the estimate yet'


def decided_reasons(own: Sequence[str], monitor: Any, plant: int | None = None,
                    simulation: SimulationWindow | None = None,
                    theta: np.ndarray | None = None, order: int = 0,
                    covariance: Callable[[], np.ndarray | None] | None = None,
                    count: Callable[[], float | None] | None = None,
                    precision: float | None = None) -> list[str]:
    """
    Return the reasons not to trust an estimate: ``own`` and the ones every estimator shares.

    ``own`` are the estimator's (from its own equations: an unstable model, a
    compensation that does not converge, ...); the shared ones are the residual
    tests' (:func:`~bcid_ros.estimators.residual_state.residual_reasons`) when the
    estimator keeps an :class:`~bcid_ros.estimators.adequacy.AdequacyMonitor`
    (``monitor`` None: none), of ``plant`` of a many-plant monitor, then the
    simulation check's of the model ``theta`` of order ``order`` on ``simulation``
    (:func:`~bcid_ros.estimators.simulation_check.simulation_reasons`; None: the
    estimator keeps no window), counting the estimate's own error from ``covariance``
    (a function giving theta's covariance, asked only when the check runs), and that
    covariance against the window's information where ``count`` gives the samples the
    estimate rests on. ``precision`` (None: not asked) is the share of its size the
    estimate must be known to at all times (:func:`imprecision`), judged only where no other
    reason holds and only with a std (none yet is no evidence of imprecision). The one place
    that decides which reasons count, for one plant and for K.
    """
    reasons = list(own)
    if monitor is not None:
        reasons += residual_reasons(monitor, plant)
    if simulation is not None:
        reasons += simulation_reasons(simulation, theta, order, covariance, count)
    if precision is not None and not reasons:  # the model passed: is it known well enough?
        imprecise = imprecision(theta, covariance, precision, _STANDING)
        if imprecise and not imprecise.endswith(_NO_STD):
            reasons.append(imprecise)
    return reasons


def decided_after_change(own: Sequence[str], change: str, monitor: Any,
                         plant: int | None = None, simulation: SimulationWindow | None = None,
                         theta: np.ndarray | None = None, order: int = 0,
                         covariance: Callable[[], np.ndarray | None] | None = None,
                         ready_again: bool | None = None,
                         count: Callable[[], float | None] | None = None,
                         precision: float | None = None) -> tuple[list[str], str]:
    """
    Return the reasons of :func:`decided_reasons` with a plant change's, and the change's.

    ``change`` is the reason a detected plant change gave (``''``: none); it
    comes first, and holds until the residual tests of ``monitor`` (of
    ``plant`` of a many-plant monitor) are ready again, on a full window of the
    new plant's samples, and the simulation check has judged the model on the
    samples since the change (its window at its minimum length: the window is
    cleared at the change, and an empty one has no verdict), with no other
    reason left: a short-record verdict on the samples replayed at the restart
    does not end it. ``ready_again``, where given, is the estimator's own word
    that its estimate now rests on the new plant's samples alone (rpem: a fit of
    only those) and replaces the residual tests' readiness. ``precision``: as in
    :func:`decided_reasons` (the change's ``PRECISION`` is the stricter). Returns the reasons
    and the change's reason that still holds (``''`` once the change is done).
    """
    found = (monitor, plant, simulation, theta, order, covariance, count, precision)
    reasons = decided_reasons([change, *own] if change else own, *found)
    if change and reasons == [change] and (simulation is None or simulation.judged) and (
            _ready_again(monitor, plant) if ready_again is None else ready_again):
        imprecise = imprecision(theta, covariance)
        if imprecise:  # the model explains the new samples, but they do not pin it down yet
            return [change, imprecise], change
        return decided_reasons(own, *found), ''
    return reasons, change


def imprecision(theta: np.ndarray | None,
                covariance: Callable[[], np.ndarray | None] | None,
                level: float = PRECISION, why: str = _AFTER_CHANGE) -> str:
    r"""
    Return why the estimate is not known to ``level`` of its size (``''``: it is).

    With C the estimate's covariance (``covariance()``), :math:`\sqrt{\mathrm{tr}\,C}`
    is the RMS of :math:`\lVert\hat\theta - \theta\rVert`, and for a Gaussian error
    of any C, :math:`P(\lVert e\rVert \ge k\sqrt{\mathrm{tr}\,C}) \le P(|z| \ge k)`
    for :math:`k^2 \ge 1.54` (Szekely and Bakirov 2003: the one-dimensional form is the
    extreme one), so :math:`k\sqrt{\mathrm{tr}\,C} \le` ``level``
    :math:`\lVert\hat\theta\rVert` (k = ``PRECISION_SIGMAS``) bounds the relative
    error by ``level`` with probability at least 95.4 %, whatever the shape of C
    (``PRECISION`` after a change, ``STANDING_PRECISION`` at all times; ``why`` ends the
    reason).
    No covariance yet (``covariance()`` None, or a many-plant row of NaN: the single
    estimator's None) is no precision shown; not judged (``''``) without an estimate or
    a covariance to ask.
    """
    if theta is None or covariance is None:
        return ''
    matrix = covariance()
    if matrix is None or not np.isfinite(matrix).all():
        return f'{IMPRECISE}: {_NO_STD}'
    size = float(np.linalg.norm(theta))
    spread = math.sqrt(max(float(np.trace(matrix)), 0.0))
    bound = PRECISION_SIGMAS * spread / size if size > 0.0 else math.inf
    if bound <= level:
        return ''
    return (f'{IMPRECISE}: {PRECISION_SIGMAS:g} sqrt(tr C) is {100.0 * bound:.0f} % of |theta|, '
            f'above {100.0 * level:g} % ({why})')


def doubt_the_model(reasons: Sequence[str]) -> bool:
    """
    Return whether ``reasons`` doubt the model, not only its covariance.

    A std judged too small (``UNDERSTATED``), an estimate not yet known to
    ``PRECISION`` after a change (``IMPRECISE``, with the change's reason it holds) and one
    not known to ``STANDING_PRECISION`` (``IMPRECISE`` alone) name the covariance: the model
    passed its checks.
    """
    if any(reason.startswith(IMPRECISE) for reason in reasons):
        return len(reasons) > 2  # [change, imprecise] and nothing else
    return not all(reason.startswith(UNDERSTATED) for reason in reasons)


def _plant_covariance(estimator: Any, plant: int) -> np.ndarray:
    """Return one plant's parameter covariance of K plants (NaN: none known)."""
    return estimator.parameter_covariance_of(np.array([plant]))[0]


def _ready_again(monitor: Any, plant: int | None) -> bool:
    """Whether the residual tests (of ``plant``) are ready (no tests: ready)."""
    if monitor is None:
        return True
    return bool(np.all(monitor.ready if plant is None else monitor.ready_of(plant)))


class Validity:
    """
    :attr:`valid` of one plant: readiness and no reason to distrust the estimate.

    A mixin of :class:`~bcid_ros.estimators.base.RecursiveEstimator`. The
    estimators hand their own reasons to :meth:`_decide_validity` on their
    schedule; the shared ones join them there (:func:`decided_reasons`), and
    a plant change's reason holds as :func:`decided_after_change` says.
    """

    #: Whether the estimator has reasons that change with every sample (:meth:`_live_reasons`).
    _LIVE_REASONS: ClassVar[bool] = False
    #: The residual tests whose reasons join the estimator's own (None: it keeps none).
    _monitor: Any = None
    #: The simulation check's window, whose reason joins them too (None: it keeps none;
    #: :meth:`_start_simulation_check`).
    _simulation: SimulationWindow | None = None
    #: The recorded samples from one simulation check to the next (1: at every decision).
    _SIMULATION_CHECK_PERIOD: ClassVar[int] = CHECK_PERIOD
    #: Whether the estimator takes a plant change from the check's runs of contradictions
    #: (its window then looks at a run's samples alone as well: ``looks_at_tail``).
    _SIMULATION_CHANGES: ClassVar[bool] = False

    @property
    def valid(self) -> bool:
        """
        Whether the estimate can be trusted: :attr:`ready` and no :attr:`validity_reasons`.

        A controller may act on the estimate while this is true; when it turns
        false, :attr:`validity_reasons` says why. Decided here for every
        estimator (none overrides it): the reasons of the last
        :meth:`_decide_validity` and, where they change with every sample,
        :meth:`_live_reasons`.
        """
        return self.ready and not (self._reasons or self._LIVE_REASONS and self._live_reasons())

    @property
    def validity_reasons(self) -> tuple[str, ...]:
        """Return why the estimate is not trustworthy now (empty when it is, or not ready)."""
        if self._LIVE_REASONS:
            return self._reasons + tuple(self._live_reasons())
        return self._reasons

    def _decide_validity(self, own: Sequence[str], change: str = '',
                         ready_again: bool | None = None) -> str:
        """
        Decide the reasons not to trust the estimate from the estimator's ``own`` reasons.

        The estimators call this on their schedule (every ``VALIDITY_PERIOD``
        updates), with the reasons their own equations give; the shared ones
        join them here (:func:`decided_reasons`), and a detected plant
        change's reason ``change`` holds as :func:`decided_after_change`
        says (``ready_again``: the estimator's word that the new plant's
        samples are in, where the residual tests' readiness is not it).
        Returns the change's reason that still holds (``''``: done or
        none). It changes nothing but the reasons: what a check finds that
        needs action (a diverging compensation, a restart) is done by the
        estimator's update.
        """
        with np.errstate(all='ignore'):
            reasons, change = decided_after_change(
                own, change, self._monitor, simulation=self._simulation,
                theta=None if self._simulation is None else self._theta(), order=self.order,
                # asked at most once a decision (the check and the precision after a change)
                covariance=functools.cache(lambda: self.parameter_covariance),
                ready_again=ready_again,
                count=self._covariance_count, precision=self._standing_precision())
        self._reasons = tuple(reasons)
        return change

    def _standing_precision(self) -> float | None:
        """
        Return the share of its size the estimate must be known to at all times (None: not asked).

        :func:`decided_reasons`'s ``precision``; an estimator whose std is calibrated from
        its first fit on states ``STANDING_PRECISION`` (rpem).
        """
        return None

    def _covariance_count(self) -> float | None:
        """
        Return the samples the estimate rests on, to judge its covariance by (None: not judged).

        An estimator whose reported covariance of [a, b] is that of the output-error
        criterion, the simulation check's (rpem's ``oe``), gives it: the check then names a
        covariance far smaller than the window's own information allows
        (:func:`~bcid_ros.estimators.simulation_check.understatement`).
        """
        return None

    def _start_simulation_check(self) -> None:
        """
        Start the simulation check's window afresh (a reset, a plant change, a restart).

        An estimator whose model predicts a simulated output from the measured inputs
        keeps one and records the samples it learns from in it (as the model sees them:
        deviations with ``detrend: mean``), clearing it at a gap; the base class judges
        it in :meth:`_decide_validity` and keeps it in the state (docs/trust.md).
        """
        self._simulation = SimulationWindow(self.order, self.num_inputs, self.feedthrough,
                                            self.input_delay, self._forgetting_factor,
                                            self._SIMULATION_CHECK_PERIOD,
                                            self._SIMULATION_CHANGES)

    def _live_reasons(self) -> list[str] | tuple[str, ...]:
        """Return the reasons that change with every sample (``_LIVE_REASONS``); none here."""
        return ()


class PlantsValidity:
    """
    :attr:`valid` of K plants (the batched estimators): decided as one plant's, per plant.

    Each plant is valid when :attr:`ready` with no reasons; the reasons are
    its own and the shared ones (:func:`decided_reasons`), kept in
    ``_reasons`` (a :class:`~bcid_ros.estimators.plants.PlantReasons`). A
    check that asks a plant's covariance gets that plant's alone, from the
    estimator's ``parameter_covariance_of``.
    """

    _monitor: Any = None
    #: One simulation check's window per plant (None: none kept).
    _simulations: Any = None

    @property
    def valid(self) -> np.ndarray:
        """Whether each plant is :attr:`ready` with no validity reasons, shape ``(K,)``."""
        return self.ready & ~self._reasons.any

    @property
    def validity_reasons(self) -> tuple[tuple[str, ...], ...]:
        """Return the reasons not to trust each plant's estimate, one tuple per plant."""
        return tuple(self._reasons.of(plant) for plant in range(self.num_plants))

    def plant_validity_reasons(self, plant: int) -> tuple[str, ...]:
        """Return why plant k's estimate is not trustworthy now (empty when it is)."""
        return self._reasons.of(range(self.num_plants)[plant])

    def _decide_validity(self, plants: np.ndarray, own: Sequence[Sequence[str]],
                         changes: list[str] | None = None) -> None:
        """
        Decide the reasons of ``plants`` from their ``own``, as one plant's decision.

        ``changes``: each plant's plant-change reason (``''``: none), which
        holds as :func:`decided_after_change` says; cleared in place where a
        change is done. None: no plant changes.
        """
        windows = self._simulations
        theta = None if windows is None else self._theta()
        with np.errstate(all='ignore'):
            for plant, mine in zip(plants.tolist(), own):
                reasons, change = decided_after_change(
                    mine, '' if changes is None else changes[plant], self._monitor, plant,
                    None if windows is None else windows[plant],
                    None if theta is None else theta[plant], self.order,
                    # the plant's own covariance, at most once, and only if a check asks
                    functools.cache(functools.partial(_plant_covariance, self, plant)))
                self._reasons.set(plant, tuple(reasons))
                if changes is not None:
                    changes[plant] = change


__all__ = ['decided_after_change', 'decided_reasons', 'doubt_the_model', 'imprecision',
           'IMPRECISE', 'PlantsValidity', 'PRECISION', 'PRECISION_SIGMAS', 'STANDING_PRECISION',
           'Validity']
