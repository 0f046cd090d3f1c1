"""
The per-sample interface that every bcid_ros estimator implements.

An estimator is fed one sample at a time with :meth:`RecursiveEstimator.update`
and exposes its current estimate through properties. The offline tools run
the very same ``update`` over an array with :meth:`RecursiveEstimator.run`,
so there is one code path for the node, the replay, the reproductions and
the benchmarks.

Parameter names follow the node's topics (docs/nodes.md): ``a1,...,an`` then,
for each input ``i`` and lag ``k``, ``b{i}_{k}`` (lag 0 only with direct
feedthrough).

The base class also owns three generic safeguards that every estimator
inherits (docs/estimators.md, "Estimates you can trust"):

* the update is a transaction: a step that would leave the state non-finite
  is undone, counted (flag ``update_undone``) and the regressor restarts;
* the outlier gate of :meth:`RecursiveEstimator._gate`, with its detection
  of a real plant change;
* :attr:`RecursiveEstimator.valid` is readiness *and* no reason to distrust
  the estimate (:attr:`RecursiveEstimator.validity_reasons`).
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import math
import operator
from typing import Any, Callable, ClassVar, Sequence

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.operating_point import (CentringMonitor, operating_point_names,
                                                 RunningMean)
from bcid_ros.estimators.residual_state import residual_reasons
from bcid_ros.estimators.settings import DETRENDS, MAX_DELAY, SHARED_SETTINGS, TRACKING
from bcid_ros.estimators.simulation_check import simulation_reasons, SimulationWindow

#: |value| * HUGE_SCREEN >= 1 (|value| >= 2^450, about 3e135) marks a sample
#: whose products in an update could overflow: see _quiet_update.
HUGE_SCREEN = 2.0 ** -450
#: The same limit, for the sum of the magnitudes of a sample.
HUGE_VALUE = 1.0 / HUGE_SCREEN
#: The generic transaction copies a state of at most this many numbers before
#: every sample, and a larger one every CHECKPOINT_PERIOD samples.
EXACT_CHECKPOINT_SIZE = 4096
#: See EXACT_CHECKPOINT_SIZE.
CHECKPOINT_PERIOD = 64


def standard_deviations(covariance: np.ndarray | None) -> np.ndarray | None:
    """Return the square roots of the diagonal of ``covariance`` (None passes through)."""
    if covariance is None:
        return None
    return np.sqrt(np.maximum(np.diagonal(covariance), 0.0))


def all_finite(*vectors: np.ndarray) -> bool:
    """
    Return whether every value of the 1-D float arrays ``vectors`` is finite.

    The sum of all the values is finite when they are, which one cheap sum of
    Python floats tells in the usual case; a non-finite sum is a NaN, an Inf
    or an overflow of finite values, which the exact test then tells apart.
    """
    total = 0.0
    for vector in vectors:
        total += sum(vector.tolist())
    return math.isfinite(total) or all(bool(np.isfinite(vector).all()) for vector in vectors)


def weighted_square_ratio(tau: Any, forgetting_factor: float) -> Any:
    r"""
    Return :math:`\tau_2/\tau`, the sum of the squared weights over the sum of the weights.

    With weights :math:`\lambda^{t-i}` over t samples,
    :math:`\tau = (1 - \lambda^t)/(1 - \lambda)` and
    :math:`\tau_2 = \sum\lambda^{2(t-i)} = \tau(2 - (1-\lambda)\tau)/(1 + \lambda)`,
    so the ratio follows from :math:`\tau` and :math:`\lambda` alone: 1 without
    forgetting, :math:`1/(1 + \lambda)` in the steady state. A weighted
    estimate from :math:`\tau` samples has the variance of one from
    :math:`\tau^2/\tau_2` (its effective sample size). :math:`(1-\lambda)\tau`
    is clipped to 1 (its steady state), which also covers a factor lowered
    while running. ``tau`` may be an array (one per plant).
    """
    lam = forgetting_factor
    return (2.0 - np.minimum((1.0 - lam) * tau, 1.0)) / (1.0 + lam)


def parameter_names(order: int, num_inputs: int, feedthrough: bool,
                    input_delay: Any = None) -> tuple[str, ...]:
    """
    Return the names of the ARX parameter vector (those of the node's topics).

    Parameters
    ----------
    order : int
        Plant order n (number of ``a`` coefficients).
    num_inputs : int
        Number of inputs r.
    feedthrough : bool
        Whether the lag-0 coefficients ``b{i}_0`` are estimated.
    input_delay : sequence of int, optional
        Dead time d_i of each input; the names of input i carry the true
        lags d_i + 1 ... d_i + n (from d_i with feedthrough). None: no delay.

    Returns
    -------
    tuple of str
        ``('a1', ..., 'an', 'b1_0' or 'b1_1', ..., 'br_n')`` without delays.

    """
    first_lag = 0 if feedthrough else 1
    delays = [0] * num_inputs if input_delay is None else list(input_delay)
    names = [f'a{k}' for k in range(1, order + 1)]
    for i in range(1, num_inputs + 1):
        delay = delays[i - 1]
        names.extend(f'b{i}_{k + delay}' for k in range(first_lag, order + 1))
    return tuple(names)


def check_delays(value: Any, num_inputs: int) -> tuple[int, ...]:
    """
    Return one dead time d_i >= 0 per input from one integer or r integers.

    Raises
    ------
    ValueError
        Naming ``input_delay``, the allowed values and the value given.

    """
    items = list(np.atleast_1d(np.asarray(value, dtype=object)).reshape(-1))
    if len(items) == 1:
        items = items * num_inputs
    if len(items) != num_inputs or any(
            isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number))
            or v != int(v) or not 0 <= v <= MAX_DELAY for v in items):
        raise ValueError(f'input_delay must be one integer or r = {num_inputs} integers, '
                         f'each in [0, {MAX_DELAY}] (samples), got {value!r}')
    return tuple(int(v) for v in items)


def decided_reasons(own: Sequence[str], monitor: Any, plant: int | None = None,
                    simulation: SimulationWindow | None = None,
                    theta: np.ndarray | None = None, order: int = 0,
                    covariance: Callable[[], np.ndarray | None] | None = None) -> list[str]:
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
    (a function giving theta's covariance, asked only when the check runs). The one
    place that decides which reasons count, for one plant and for K.
    """
    reasons = list(own)
    if monitor is not None:
        reasons += residual_reasons(monitor, plant)
    if simulation is not None:
        reasons += simulation_reasons(simulation, theta, order, covariance)
    return reasons


def check_int(name: str, value: Any, minimum: int) -> int:
    """Return ``value`` as an int, or raise ValueError naming ``name``."""
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise ValueError(f'{name} must be an integer >= {minimum}, got {value!r}')
    return int(value)


def check_range(name: str, value: Any, low: float, high: float,
                low_open: bool = False) -> float:
    """Return ``value`` as a float in [low, high] (or (low, high]), or raise ValueError."""
    value = float(value)
    too_low = value <= low if low_open else value < low
    if not np.isfinite(value) or too_low or value > high:
        bracket = '(' if low_open else '['
        raise ValueError(f'{name} must be in {bracket}{low:g}, {high:g}], got {value!r}')
    return value


def check_forgetting_factor(value: Any) -> float:
    """Return the forgetting factor lambda as a float in (0, 1], or raise ValueError."""
    return SHARED_SETTINGS['forgetting_factor'].check_argument(value)


class SharedSettings:
    """
    The settings a single-plant estimator and a batched one check and expose alike.

    The model structure (order, inputs, feedthrough), p0, and the two
    settings that may change while running: the forgetting factor and the
    gate's threshold (whose squared limit the rulebook's gate takes); and
    those that follow a changing plant (``change_detection``, ``adaptation``,
    ``parameter_drift``).
    """

    #: Whether it follows a changing plant: the change detector runs (``change_detection``)
    #: and ``adaptation: kalman`` is available (docs/tracking.md).
    tracks: ClassVar[bool] = False

    def _check_settings(self, order: int, num_inputs: int, feedthrough: bool,
                        initial_covariance: float, forgetting_factor: float,
                        outlier_threshold: float) -> None:
        """Check and keep the shared settings; raise ValueError naming a bad one."""
        self.order = SHARED_SETTINGS['order'].check_argument(order)
        self.num_inputs = SHARED_SETTINGS['num_inputs'].check_argument(num_inputs)
        self.feedthrough = bool(feedthrough)
        self.initial_covariance = SHARED_SETTINGS['initial_covariance'].check_argument(
            initial_covariance)
        # not through the property, which subclasses may extend with checks of their state
        self._forgetting_factor = check_forgetting_factor(forgetting_factor)
        self.outlier_threshold = outlier_threshold

    @property
    def forgetting_factor(self) -> float:
        """Forgetting factor lambda in (0, 1]; may be changed while running."""
        return self._forgetting_factor

    @forgetting_factor.setter
    def forgetting_factor(self, value: float) -> None:
        self._forgetting_factor = check_forgetting_factor(value)
        self._follow_forgetting_factor()

    def _follow_forgetting_factor(self) -> None:
        """
        Give every part whose memory is the estimator's the forgetting factor now in force.

        P's recursion reads it at every step; the residual tests' window
        (:meth:`~bcid_ros.estimators.adequacy.AdequacyMonitor.follow_forgetting_factor`)
        and the HAC covariance's weights (``_hac``) are told here, so that a
        live change reaches them as it reaches P, not at the next reset.
        """
        monitor, hac = getattr(self, '_monitor', None), getattr(self, '_hac', None)
        if monitor is not None:
            monitor.follow_forgetting_factor(self._forgetting_factor)
        if hac is not None:
            hac.forgetting_factor = self._forgetting_factor
        for window in self._simulation_windows():
            window.follow_forgetting_factor(self._forgetting_factor)

    def _simulation_windows(self) -> list[SimulationWindow]:
        """Return the simulation check's windows (one per plant; none kept: [])."""
        windows = getattr(self, '_simulations', None)
        if windows is not None:
            return windows
        window = getattr(self, '_simulation', None)
        return [] if window is None else [window]

    def _check_tracking(self, change_detection: bool, adaptation: str,
                        parameter_drift: float) -> None:
        """Check and keep the settings that follow a changing plant (docs/tracking.md)."""
        if adaptation not in TRACKING['adaptation'].choices:
            raise ValueError(f"adaptation must be 'forgetting' or 'kalman', got {adaptation!r}")
        if not self.tracks and (adaptation != 'forgetting' or parameter_drift):
            raise ValueError(f'adaptation: kalman and parameter_drift are not available for '
                             f'{type(self).__name__}, got {adaptation!r}, {parameter_drift!r}')
        if adaptation == 'kalman' and self._forgetting_factor < 1.0:
            raise ValueError(f'adaptation: kalman takes the place of forgetting: '
                             f'forgetting_factor must be 1, got {self._forgetting_factor!r}')
        self.adaptation = adaptation
        self.change_detection = change_detection
        self.parameter_drift = parameter_drift

    @property
    def change_detection(self) -> bool:
        """Whether the CUSUM test of plant changes runs (docs/tracking.md); may change live."""
        return self._change_detection

    @change_detection.setter
    def change_detection(self, value: bool) -> None:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f'change_detection must be true or false, got {value!r}')
        self._change_detection = bool(value)

    @property
    def parameter_drift(self) -> float:
        """
        Return q, the random walk's step variance (``adaptation: kalman``; 0 otherwise).

        Per sample, each parameter of the model of unit-size signals takes a
        random step of variance q times the noise variance: P <- P + q S^-2 (S
        the signal scales of the parameters; docs/tracking.md).
        """
        return self._parameter_drift

    @parameter_drift.setter
    def parameter_drift(self, value: float) -> None:
        value = TRACKING['parameter_drift'].check_argument(value)
        if value and self.adaptation != 'kalman':
            raise ValueError(f'parameter_drift needs adaptation: kalman, got {value!r} with '
                             f'adaptation: {self.adaptation}')
        self._parameter_drift = value
        propagation = getattr(self, '_propagation', None)
        if propagation is not None and hasattr(propagation, 'drift'):
            propagation.drift = value  # the random walk's Q follows a live change

    @property
    def outlier_threshold(self) -> float:
        """Gate of the normalised prediction error, >= 0 (0 = off); may change while running."""
        return self._outlier_threshold

    @outlier_threshold.setter
    def outlier_threshold(self, value: float) -> None:
        self._outlier_threshold = SHARED_SETTINGS['outlier_threshold'].check_argument(value)
        self._gate_limit2 = rules.gate_limit2(self._outlier_threshold)


class PlantsValidity:
    """
    :attr:`valid` of K plants (the batched estimators): decided as one plant's, per plant.

    Each plant is valid when :attr:`ready` with no reasons; the reasons are
    its own and the shared ones (:func:`decided_reasons`), kept in
    ``_reasons`` (a :class:`~bcid_ros.estimators.plants.PlantReasons`).
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

    def _decide_validity(self, plants: np.ndarray, own: Sequence[Sequence[str]]) -> None:
        """Decide the reasons of ``plants`` from their ``own`` (as one plant's decision)."""
        windows = self._simulations
        theta = None if windows is None else self._theta()
        with np.errstate(all='ignore'):
            for plant, mine in zip(plants.tolist(), own):
                self._reasons.set(plant, tuple(decided_reasons(
                    mine, self._monitor, plant, None if windows is None else windows[plant],
                    None if theta is None else theta[plant], self.order,
                    functools.partial(self._plant_covariance, plant))))

    def _plant_covariance(self, plant: int) -> np.ndarray:
        """Return plant k's parameter covariance (NaN where none: see ``check``)."""
        return self.parameter_covariance[plant]


@dataclasses.dataclass(frozen=True)
class EstimatorState:
    """
    A frozen snapshot of an estimator's full internal state.

    Attributes
    ----------
    estimator : str
        The registry name of the estimator that made the snapshot.
    arrays : dict of str to numpy.ndarray
        Copies of every array of the state.
    scalars : dict of str to float or int or bool
        Every scalar of the state, counters included.

    """

    estimator: str
    arrays: dict[str, np.ndarray]
    scalars: dict[str, Any]


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """
    Estimates after every sample of a batch run, shape ``(N, ...)``.

    Rows where ``ready`` is False hold whatever the estimator held then (its
    initial values before it first updates); use ``ready`` to mask them, as the
    node does before it publishes. ``valid`` is the node's ``~/valid``: ready
    and no reason to distrust the estimate.
    """

    theta: np.ndarray
    theta_uncompensated: np.ndarray
    noise: np.ndarray
    valid: np.ndarray
    parameter_names: tuple[str, ...]
    noise_names: tuple[str, ...]
    ready: np.ndarray

    @property
    def final(self) -> np.ndarray:
        """Return the compensated estimate after the last sample, shape ``(p,)``."""
        return self.theta[-1]


class RecursiveEstimator(SharedSettings, abc.ABC):
    """
    Base class of the per-sample estimators.

    Subclasses implement :meth:`_update` (one step given ``y`` and a float
    array ``u`` of shape ``(r,)``), :meth:`_reset`, the state hooks and the
    ``_theta``/``_theta_uncompensated``/``_noise`` accessors; they may
    override :meth:`_guarded_update` (the transaction), call :meth:`_gate`
    with their normalised prediction error, hand their own reasons not to
    trust the estimate to :meth:`_decide_validity` (and, if some change with
    every sample, report them in :meth:`_live_reasons`), and may override
    :meth:`_hold` (a sample taken while the adaptation is held). The base
    class owns the input checks, the generic transaction, the gate's change
    detection, :attr:`valid`, the snapshot plumbing and the operating point
    (``detrend``) and ``adapt`` settings.

    Parameters
    ----------
    order : int
        Plant order n >= 1.
    num_inputs : int
        Number of inputs r >= 1.
    feedthrough : bool
        Estimate the lag-0 input coefficients ``b{i}_0``.
    initial_covariance : float
        p0 of P(0) = p0 I, > 0 (estimators that normalise their signals read
        it in normalised units: see their docstrings).
    forgetting_factor : float
        lambda in (0, 1]; 1 means no forgetting.
    outlier_threshold : float
        Gate of the normalised one-step prediction error, >= 0; 0 turns the
        gate off (estimators that implement it: see :meth:`_gate`).
    input_delay : int or sequence of int
        Dead time d_i >= 0 of each input (one integer for all):
        B_i(q) = q^-d_i (b_i1 q^-1 + ... + b_in q^-n); the names carry the
        true lags. Estimators that do not support it refuse a non-zero one.
    detrend : str
        ``'none'`` or ``'mean'``: regress the deviations from the recursive
        means of y and u (:attr:`operating_point`, docs/estimators.md).
    adapt : bool
        False holds the learnt state (see :attr:`adapt`); may change while running.

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    #: Registry name, as in the ``estimator`` ROS parameter.
    name: ClassVar[str] = ''
    #: Names of the published noise estimates.
    noise_names: tuple[str, ...] = ()
    #: Whether the estimator has reasons that change with every sample (:meth:`_live_reasons`).
    _LIVE_REASONS: ClassVar[bool] = False
    #: The residual tests whose reasons join the estimator's own (None: it keeps none).
    _monitor: Any = None
    #: The simulation check's window, whose reason joins them too (None: it keeps none;
    #: :meth:`_start_simulation_check`).
    _simulation: SimulationWindow | None = None

    def __init__(self, *, order: int, num_inputs: int = 1, feedthrough: bool = False,
                 initial_covariance: float = 1e6, forgetting_factor: float = 1.0,
                 outlier_threshold: float = 0.0, input_delay: Any = 0,
                 detrend: str = 'none', adapt: bool = True, change_detection: bool = True,
                 adaptation: str = 'forgetting', parameter_drift: float = 0.0) -> None:
        self._check_settings(order, num_inputs, feedthrough, initial_covariance,
                             forgetting_factor, outlier_threshold)
        self._check_tracking(change_detection, adaptation, parameter_drift)
        self.input_delay = check_delays(input_delay, self.num_inputs)
        self.parameter_names = parameter_names(self.order, self.num_inputs, self.feedthrough,
                                               self.input_delay)
        self.num_parameters = len(self.parameter_names)
        self._init_operation(detrend, adapt)
        self._change_score = 0.0
        self._gate_tail = 1.0
        self._quiet_left = 0
        # samples refused by _undo, so that they can be kept out of the operating point
        self._refused = 0
        self._checkpoint: tuple[dict[str, np.ndarray], dict[str, Any]] | None = None
        self._since_checkpoint = 0
        self._checkpoint_period = 1
        self.flags: dict[str, int] = {}
        #: The reasons of the last :meth:`_decide_validity` (kept in the estimators' state).
        self._reasons: tuple[str, ...] = ()

    # ----------------------------------------------------------------- API
    def update(self, y: float, u: Any) -> bool:
        """
        Process one sample and return whether the estimate is now valid.

        Parameters
        ----------
        y : float
            Output sample y(t).
        u : float or array_like, shape ``(r,)``
            Input sample u(t).

        Returns
        -------
        bool
            :attr:`valid` after this sample.

        Raises
        ------
        ValueError
            If ``u`` does not have r elements or a value is not finite. The
            state is left untouched in that case.

        """
        u = np.asarray(u, dtype=float)
        if u.ndim != 1:
            u = u.reshape(-1)
        if u.shape[0] != self.num_inputs:
            raise ValueError(f'u must have {self.num_inputs} elements, got {u.shape[0]}')
        y = float(y)
        # One sum screens for NaN, Inf and sizes whose products could overflow
        # (NaN fails every comparison); in Python floats, which never warn and
        # cost a third of numpy's abs and dot at this size.
        if not abs(y) + sum(map(abs, u.tolist())) < HUGE_VALUE:
            if not (math.isfinite(y) and np.isfinite(u).all()):
                raise ValueError('sample contains NaN or Inf')
            self._quiet_left = self.order + 2
        if self._operated:
            self._operated_update(y, u)
        elif self._quiet_left:
            self._quiet_update(y, u)
        else:
            self._guarded_update(y, u)
        return self.valid

    def update_trusted(self, y: float, u: np.ndarray) -> None:
        """
        Process one sample that the caller has already checked, without checking it again.

        For callers that check whole blocks of samples at once (the node's
        frames): ``y`` must be a finite float and ``u`` a finite float64 array
        of shape ``(r,)``. The result is the same as :meth:`update`'s: the
        size screen for values beyond 2^450 still runs (see
        :meth:`_quiet_update`), the NaN/Inf check does not.
        """
        if not abs(y) + sum(map(abs, u.tolist())) < HUGE_VALUE:
            self._quiet_left = self.order + 2
        if self._operated:
            self._operated_update(y, u)
        elif self._quiet_left:
            self._quiet_update(y, u)
        else:
            self._guarded_update(y, u)

    def trusted_block_update(self, rows: np.ndarray) -> Callable[[float, np.ndarray], None]:
        """
        Return the update to call instead of :meth:`update_trusted` on each of these rows.

        For a caller that feeds a checked block ``rows`` (shape ``(k, 1 + r)``,
        finite) row by row, in order; the estimate is the same as
        :meth:`update_trusted`'s on each row. What that does per sample is
        done here for the block at once where it can be: the size screen
        (no value near 2^450: then no sample needs the quiet path, and the
        rows go straight to the step), and the centring monitor's share (one
        row in ``CENTRING_STRIDE``, the same rows as sample by sample). If a
        row's update raises, the monitor has already seen the rows after it
        (it only ever gives a warning).
        """
        if self._means is not None or not self._adapting or not rows.size:
            return self.update_trusted
        if self._centring is not None:
            self._centring.take_rows(rows)
        if self._quiet_left or not float(np.abs(rows).max()) * rows.shape[1] < HUGE_VALUE:
            return self._update_trusted_plain
        return self._guarded_update

    def _update_trusted_plain(self, y: float, u: np.ndarray) -> None:
        # update_trusted without the operating-point step (see trusted_block_update)
        if not abs(y) + sum(map(abs, u.tolist())) < HUGE_VALUE:
            self._quiet_left = self.order + 2
        self._learn(y, u)

    def _quiet_update(self, y: float, u: np.ndarray) -> None:
        """
        Update with floating-point warnings off, while a huge sample is in the regressor.

        A value beyond 2^450 (about 3e135) makes phi' P phi overflow to Inf,
        which the transaction refuses; numpy would also warn about it. The
        warnings are silenced for the order + 2 samples whose regressors can
        hold that value (errstate costs microseconds, so only for those).
        """
        self._quiet_left -= 1
        with np.errstate(all='ignore'):
            self._guarded_update(y, u)

    # --------------------------------------- operating point and adaptation
    def _init_operation(self, detrend: str, adapt: bool) -> None:
        if detrend not in DETRENDS:
            raise ValueError(f"detrend must be 'none' or 'mean', got {detrend!r}")
        self.detrend = detrend
        self._means = RunningMean(self.num_inputs) if detrend == 'mean' else None
        self._centring: CentringMonitor | None = None
        self._excitation_hold = False
        self._held = 0
        self.adapt = adapt

    def _set_operated(self) -> None:
        # the plain per-sample path unless a mean, a hold or a monitor is involved
        self._operated = bool(self._means is not None or self._centring is not None
                              or not self._adapting)

    def _operated_update(self, y: float, u: np.ndarray) -> None:
        """
        Update with the operating point removed, or hold the learnt state.

        With ``detrend: mean`` the sample minus the recursive means goes to
        the estimator (the means themselves are held with the adaptation); a
        sample the estimator refuses (:meth:`_undo`) is taken back out of the
        means.
        While adaptation is held, :meth:`_hold` only moves the sample
        history on: nothing learnt changes, so nothing can wind up.
        """
        if self._centring is not None:
            self._centring.take(y, u)
        if not self._adapting:
            self._held += 1
            if self._means is not None:
                y, u = self._means.apply(y, u)
            self._hold(y, u)
            return
        if self._means is None:
            self._learn(y, u)
            return
        refused = self._refused
        self._learn(*self._means.centre(y, u, self._forgetting_factor))
        if self._refused != refused:
            # a sample the estimator refused (an outlier) must not move the
            # operating point either: the means would carry it for 1 / (1 - lambda)
            self._means.undo()

    def _learn(self, y: float, u: np.ndarray) -> None:
        """Update on a sample from which the operating point is removed, if one is."""
        if self._quiet_left:
            self._quiet_update(y, u)
        else:
            self._guarded_update(y, u)

    def _hold(self, y: float, u: np.ndarray) -> None:
        """
        Take a sample without learning from it (adaptation held).

        This generic form restarts the regressor, so that no update regresses
        across the held stretch; estimators whose sample history is separate
        from what they learn override it to keep the history running.
        """
        self._restart_regressor()

    @property
    def adapt(self) -> bool:
        """
        Whether samples update the estimate; may change while running.

        False holds theta, P, the noise statistics and the operating point
        while the regressor and the counters keep running (:attr:`held_samples`).
        """
        return self._adapt

    @adapt.setter
    def adapt(self, value: bool) -> None:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f'adapt must be true or false, got {value!r}')
        self._adapt = bool(value)
        self._adapting = self._adapt and not self._excitation_hold
        self._set_operated()

    @property
    def excitation_hold(self) -> bool:
        """Whether adaptation is held because the input is not exciting (set by the feeder)."""
        return self._excitation_hold

    @excitation_hold.setter
    def excitation_hold(self, value: bool) -> None:
        self._excitation_hold = bool(value)
        self.adapt = self._adapt

    @property
    def held_samples(self) -> int:
        """Count the samples taken while adaptation was held (since construction)."""
        return self._held

    @property
    def operating_point(self) -> np.ndarray | None:
        """Return the recursive means ``[y0, u1, ..., ur]`` (``detrend: mean``), else None."""
        return None if self._means is None else self._means.mean.copy()

    @property
    def operating_point_names(self) -> tuple[str, ...]:
        """Return ``('y', 'u1', ..., 'ur')``, the names of :attr:`operating_point`."""
        return operating_point_names(self.num_inputs)

    def monitor_centring(self, on: bool = True) -> None:
        """Watch whether the data are centred (see :attr:`centring_problem`)."""
        self._centring = CentringMonitor(self.num_inputs) if on else None
        self._set_operated()

    @property
    def centring_problem(self) -> str:
        """
        Return why the raw data look far from centred, or '' (see :meth:`monitor_centring`).

        Only with ``detrend: none``: with ``mean`` the regression sees centred data.
        """
        if self._centring is None or self._means is not None:
            return ''
        return self._centring.problem()

    def run(self, y: Any, u: Any) -> Trajectory:
        """
        Run :meth:`update` over arrays and return the trajectory.

        Parameters
        ----------
        y : array_like, shape ``(N,)``
            Outputs.
        u : array_like, shape ``(N,)`` or ``(N, r)``
            Inputs.

        Returns
        -------
        Trajectory
            The estimates after each sample.

        """
        y = np.asarray(y, dtype=float).reshape(-1)
        u = np.asarray(u, dtype=float).reshape(y.shape[0], -1)
        count = y.shape[0]
        theta = np.empty((count, self.num_parameters))
        theta_unc = np.empty((count, self.num_parameters))
        noise = np.empty((count, len(self.noise_names)))
        valid = np.empty(count, dtype=bool)
        ready = np.empty(count, dtype=bool)
        for t in range(count):
            valid[t] = self.update(y[t], u[t])
            ready[t] = self.ready
            theta[t] = self._theta()
            theta_unc[t] = self._theta_uncompensated()
            noise[t] = self._noise()
        return Trajectory(theta, theta_unc, noise, valid, self.parameter_names,
                          self.noise_names, ready)

    def reset(self) -> None:
        """Return to the state right after construction."""
        self.flags = {}
        self._change_score = 0.0
        self._gate_tail = 1.0
        self._quiet_left = 0
        self._checkpoint = None
        if self._means is not None:
            self._means.clear()
        self._reset()

    def restart_regressor(self) -> None:
        """
        Forget the sample history (after a gap) but keep what was learnt.

        The next samples refill the regressor before any update is made, so
        a missing sample is never regressed over.
        """
        self._restart_regressor()

    def get_state(self) -> EstimatorState:
        """Return a frozen snapshot of the full state (copies)."""
        arrays, scalars = self._state_items()
        scalars = dict(scalars, flags=dict(self.flags), change_score=self._change_score,
                       gate_tail=self._gate_tail)
        if self._simulation is not None:
            # (not in _state_items: the step's checkpoint need not copy the window, which a
            # refused step clears with the regressor)
            window_arrays, window_scalars = self._simulation.state_items()
            arrays, scalars = {**arrays, **window_arrays}, {**scalars, **window_scalars}
        if self._means is not None:
            arrays = dict(arrays, operating_point=self._means.mean)
            scalars['operating_weight'] = self._means.weight
        return EstimatorState(self.name, {k: np.array(v, copy=True) for k, v in arrays.items()},
                              scalars)

    def set_state(self, state: EstimatorState) -> None:
        """
        Restore a snapshot made by :meth:`get_state` of the same configuration.

        Raises
        ------
        ValueError
            If the snapshot comes from another estimator or other dimensions.

        """
        if state.estimator != self.name:
            raise ValueError(f'state is from estimator {state.estimator!r}, not {self.name!r}')
        own_arrays, _ = self._state_items()
        for key, value in own_arrays.items():
            if key not in state.arrays or np.shape(state.arrays[key]) != np.shape(value):
                raise ValueError(f'state array {key!r} does not match this configuration')
        scalars = dict(state.scalars)
        self.flags = dict(scalars.pop('flags', {}))
        self._change_score = float(scalars.pop('change_score', 0.0))
        self._gate_tail = float(scalars.pop('gate_tail', 1.0))
        weight = scalars.pop('operating_weight', None)
        if self._means is not None and weight is not None:
            self._means.mean[:] = state.arrays['operating_point']
            self._means.weight = float(weight)
        self._checkpoint = None
        self._load_state({k: np.array(v, copy=True) for k, v in state.arrays.items()}, scalars)
        if self._simulation is not None:
            self._simulation.load(state.arrays, scalars)
        self._follow_forgetting_factor()

    @property
    def theta(self) -> np.ndarray:
        """Compensated estimate, shape ``(p,)`` (a copy)."""
        return self._theta().copy()

    @property
    def theta_uncompensated(self) -> np.ndarray:
        """LS or IV-type estimate before compensation, shape ``(p,)`` (a copy)."""
        return self._theta_uncompensated().copy()

    @property
    def noise(self) -> np.ndarray:
        """Noise estimates named by :attr:`noise_names` (a copy)."""
        return np.array(self._noise(), dtype=float)

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
    def ready(self) -> bool:
        """Whether the regressor is filled and the estimator is past its idle phase."""
        return self.samples >= self.num_parameters

    @property
    def validity_reasons(self) -> tuple[str, ...]:
        """Return why the estimate is not trustworthy now (empty when it is, or not ready)."""
        if self._LIVE_REASONS:
            return self._reasons + tuple(self._live_reasons())
        return self._reasons

    @property
    @abc.abstractmethod
    def samples(self) -> int:
        """Count the samples used in estimator updates since the last reset."""

    @property
    def covariance_trace(self) -> float:
        """Trace of the parameter covariance P (a health indicator), or NaN if none."""
        return float('nan')

    @property
    def parameter_covariance(self) -> np.ndarray | None:
        """
        Return the covariance of :attr:`theta` in the units of theta, ``(p, p)``, or None.

        None when the estimator has no calibrated covariance (the default),
        not yet enough data for one, or one that is not finite or has a
        negative variance (a sandwich evaluated at an ill-conditioned
        compensation: a standard deviation of zero would claim certainty).
        Each estimator documents its formula (docs/estimators.md, "Uncertainty").
        """
        covariance = self._parameter_covariance()
        if (covariance is None or not np.isfinite(covariance).all()
                or not (np.diagonal(covariance) >= 0.0).all()):
            return None
        return np.array(covariance, dtype=float)

    @property
    def parameter_std(self) -> np.ndarray | None:
        """Return the standard deviation of each parameter of :attr:`theta`, or None."""
        return standard_deviations(self.parameter_covariance)

    def _parameter_covariance(self) -> np.ndarray | None:
        """Return the covariance of the estimate (see :attr:`parameter_covariance`); none here."""
        return None

    def _flag(self, key: str) -> None:
        """Count one occurrence of a reported condition (see :attr:`flags`)."""
        self.flags[key] = self.flags.get(key, 0) + 1

    # ------------------------------------------------ the generic safeguards
    def _guarded_update(self, y: float, u: np.ndarray) -> None:
        """
        Do one step as a transaction: step, check, and go back if the state is unsound.

        This generic form keeps a checkpoint of the state, renewed before
        every sample when the state holds at most ``EXACT_CHECKPOINT_SIZE``
        numbers and every ``CHECKPOINT_PERIOD`` samples otherwise (a copy of
        a long data window per sample would cost more than the step), and
        checks after every step that the estimates and noise statistics are
        finite. An unsound step takes the state back to the checkpoint
        (before the sample, or at most that many samples before it), is
        counted as ``update_undone`` and restarts the regressor, so the suspect
        sample does not enter the next regressors either. Estimators that can
        tell before committing whether a step is sound override this with an
        exact and cheaper form (:class:`~bcid_ros.estimators.rls.Rls`);
        those that name what a step changes take :meth:`_step_transaction`.
        """
        if self._checkpoint is None or self._since_checkpoint >= self._checkpoint_period:
            arrays, scalars = self._state_items()
            self._checkpoint = ({key: np.array(value, copy=True)
                                 for key, value in arrays.items()}, dict(scalars))
            self._since_checkpoint = 0
            size = sum(value.size for value in self._checkpoint[0].values())
            self._checkpoint_period = 1 if size <= EXACT_CHECKPOINT_SIZE else CHECKPOINT_PERIOD
        self._since_checkpoint += 1
        self._update(y, u)
        if not self._is_sound():
            arrays, scalars = self._checkpoint
            self._load_state({key: value.copy() for key, value in arrays.items()},
                             dict(scalars))
            self._undo('update_undone')

    def _name_step_state(self, attributes: tuple[str, ...], arrays: tuple[str, ...]) -> None:
        """
        Name what one step may change, for :meth:`_step_transaction`.

        ``attributes`` are those a step may rebind (kept by reference: the
        objects they refer to must not be changed in place), ``arrays`` the
        arrays or lists it may change in place (copied; dotted paths
        allowed). An array that a step may also rebind is named in both.
        """
        self._step_attributes = attributes
        self._step_split = len(attributes)
        # one C-level call reads them all (it returns a tuple from two names on)
        read = operator.attrgetter(*attributes, *arrays)
        self._read_step_state = read if len(attributes + arrays) > 1 else (
            lambda obj: (read(obj),))

    def _step_transaction(self, y: float, u: np.ndarray) -> None:
        """
        Do one step as an exact transaction that saves only what the step may change.

        The light form of :meth:`_guarded_update`, for estimators that name
        what one step may change (:meth:`_name_step_state`): before every
        sample it keeps references to those attributes and copies of those
        arrays (a few dozen numbers, where the generic checkpoint copies the
        whole state), steps, and checks with :meth:`_is_sound`. An unsound
        step puts them back, calls :meth:`_step_restored`, is counted as
        ``update_undone`` and restarts the regressor: the state is exactly the
        one before the sample with the regressor restarted (what the restart
        clears need not be saved; the flags and the gate's change score count
        on, as with the generic form).
        """
        saved = self._read_step_state(self)
        arrays = saved[self._step_split:]
        copies = [array.copy() for array in arrays]
        self._update(y, u)
        if self._is_sound():
            return
        for name, value in zip(self._step_attributes, saved):
            setattr(self, name, value)
        for array, copy in zip(arrays, copies):
            array[:] = copy
        self._step_restored()
        self._undo('update_undone')

    def _step_restored(self) -> None:
        """Recompute what derives from the state put back by :meth:`_step_transaction`."""

    def _is_sound(self) -> bool:
        """Whether the estimates and noise statistics are all finite."""
        return all_finite(self._theta(), self._theta_uncompensated(), self._noise())

    def _undo(self, flag: str) -> None:
        """Count a refused step and restart the regressor."""
        self._flag(flag)
        self._refused += 1
        self._restart_regressor()

    def _gate(self, z2: float, error_z2: float | None = None) -> bool:
        r"""
        Return whether a sample with squared normalised prediction error ``z2`` is used.

        With the one-step prediction error :math:`e(t)` and its variance
        :math:`\hat\sigma_e^2(1 + \varphi^T P\varphi)` the estimator computes
        :math:`z^2 = e^2 / [\hat\sigma_e^2(1 + \varphi^T P\varphi)]` and the
        rulebook's gate decides (:func:`~bcid_ros.estimators.rules.gate`). A
        refused sample is counted (flag ``outlier_rejected``) and the regressor
        restarts; a detected plant change is counted (``plant_change``) and
        :meth:`_accept_change` cuts the memory before the sample is used.
        ``error_z2``: the error's part of ``z2`` where it holds another size
        too, which the change score then judges by (:func:`rules.gate`).
        """
        # the quiet case on floats first: rules.gate on scalars costs ~10 us
        tail = rules.gate_is_quiet(z2, self._gate_limit2, self._change_score, self._gate_tail)
        if tail:
            self._gate_tail = tail
            return True
        used, self._change_score, self._gate_tail, change = rules.gate(
            z2, self._gate_limit2, self._change_score, self._gate_tail, error_z2)
        if change:
            self._flag('plant_change')
            self._accept_change()
        elif not used:
            self._undo('outlier_rejected')
        return used

    def _accept_change(self) -> None:
        """Prepare for a real plant change detected by :meth:`_gate`; nothing here."""

    def _decide_validity(self, own: Sequence[str]) -> None:
        """
        Decide the reasons not to trust the estimate from the estimator's ``own`` reasons.

        The estimators call this on their schedule (every ``VALIDITY_PERIOD``
        updates), with the reasons their own equations give; the shared ones
        join them here (:func:`decided_reasons`). It changes nothing but the
        reasons: what a check finds that needs action (a diverging
        compensation, a restart) is done by the estimator's update.
        """
        with np.errstate(all='ignore'):
            self._reasons = tuple(decided_reasons(
                own, self._monitor, simulation=self._simulation,
                theta=None if self._simulation is None else self._theta(), order=self.order,
                covariance=lambda: self.parameter_covariance))

    def _start_simulation_check(self) -> None:
        """
        Start the simulation check's window afresh (a reset, a plant change, a restart).

        An estimator whose model predicts a simulated output from the measured inputs
        keeps one and records the samples it learns from in it (as the model sees them:
        deviations with ``detrend: mean``), clearing it at a gap; the base class judges
        it in :meth:`_decide_validity` and keeps it in the state (docs/trust.md).
        """
        self._simulation = SimulationWindow(self.order, self.num_inputs, self.feedthrough,
                                            self.input_delay, self._forgetting_factor)

    def _live_reasons(self) -> list[str] | tuple[str, ...]:
        """Return the reasons that change with every sample (``_LIVE_REASONS``); none here."""
        return ()

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(order={self.order}, num_inputs={self.num_inputs}, '
                f'feedthrough={self.feedthrough}, '
                f'forgetting_factor={self._forgetting_factor})')

    # ---------------------------------------------------- subclass hooks
    @abc.abstractmethod
    def _update(self, y: float, u: np.ndarray) -> None:
        """Do one step on a checked sample."""

    @abc.abstractmethod
    def _reset(self) -> None:
        """Restore the initial state."""

    @abc.abstractmethod
    def _restart_regressor(self) -> None:
        """Clear the sample history, keep the learnt statistics."""

    @abc.abstractmethod
    def _theta(self) -> np.ndarray:
        """Return the compensated estimate (no copy needed)."""

    @abc.abstractmethod
    def _theta_uncompensated(self) -> np.ndarray:
        """Return the uncompensated estimate (no copy needed)."""

    @abc.abstractmethod
    def _noise(self) -> np.ndarray:
        """Return the noise estimates."""

    @abc.abstractmethod
    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the full state, not copied."""

    @abc.abstractmethod
    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over (arrays, scalars) made by :meth:`_state_items`."""
