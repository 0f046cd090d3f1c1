"""
The per-sample interface that every bcid_ros estimator implements.

An estimator is fed one sample with :meth:`RecursiveEstimator.update` or a
block of samples with :meth:`RecursiveEstimator.update_block`: the only two
ways in, and a block gives the estimate of the same samples one by one. Both
go down one chain, each link named for what it does: the operating point and
the held adaptation (``_operate``), the quiet warnings after a huge value
(``_learn``), the transaction (``_guarded_update``) and the estimator's own
step (``_update``). The offline tools run ``update`` over an array with
:meth:`RecursiveEstimator.run`; the identifier's feeder (node and replay)
feeds its frames through ``update_block``.

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
import math
import time
from typing import Any, Callable, ClassVar

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.blocks import BlockStopped, checked_rows, UpdateTimes
from bcid_ros.estimators.operation import Operation
from bcid_ros.estimators.settings import MAX_DELAY
from bcid_ros.estimators.shared_settings import SharedSettings
from bcid_ros.estimators.transaction import all_finite, Transaction
from bcid_ros.estimators.validity import Validity

#: |value| * HUGE_SCREEN >= 1 (|value| >= 2^450, about 3e135) marks a sample
#: whose products in an update could overflow: see RecursiveEstimator._learn.
HUGE_SCREEN = 2.0 ** -450
#: The same limit, for the sum of the magnitudes of a sample.
HUGE_VALUE = 1.0 / HUGE_SCREEN
#: A block of fewer rows goes row by row: the work done once per block (the size screen,
#: rls's gather of the regressors) costs more than it saves on so few (measured: rls's gather
#: of one row costs about ten pushes, and breaks even near eight rows).
BLOCK_MIN_ROWS = 8


def standard_deviations(covariance: np.ndarray | None) -> np.ndarray | None:
    """Return the square roots of the diagonal of ``covariance`` (None passes through)."""
    if covariance is None:
        return None
    return np.sqrt(np.maximum(np.diagonal(covariance), 0.0))


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


class RecursiveEstimator(SharedSettings, Validity, Operation, Transaction, abc.ABC):
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
            self._operate(y, u)
        else:
            self._learn(y, u)
        return self.valid

    def update_block(self, rows: Any, times: UpdateTimes | None = None) -> int:
        """
        Process a block of samples, oldest first, and return how many were taken.

        The estimate is the one :meth:`update` gives on each row in turn; what
        that does per sample is done for the block at once where it can be
        (:meth:`_block_step`). This is how the identifier's feeder, ``bcid
        replay`` and the node feed their frames.

        Parameters
        ----------
        rows : array_like, shape ``(k, 1 + r)``
            The samples ``[y, u1, ..., ur]``.
        times : UpdateTimes, optional
            Add each row's update time to these.

        Returns
        -------
        int
            The rows taken: k.

        Raises
        ------
        ValueError
            If ``rows`` do not have 1 + r columns or a value is not finite
            (nothing is taken then).
        BlockStopped
            If a row's update raised: the block ends there, and the error says
            how many rows were taken before it.

        """
        rows = checked_rows(rows, self.num_inputs)
        if not all_finite(rows.reshape(-1)):
            raise ValueError('rows contain NaN or Inf')
        step = self._block_step(rows)
        outputs, inputs = rows[:, 0].tolist(), rows[:, 1:]
        taken = total = 0
        largest = 0 if times is None else times.largest_ns
        try:
            if times is None:
                for taken, (y, u) in enumerate(zip(outputs, inputs)):
                    step(y, u)
            else:
                clock = time.perf_counter_ns
                for taken, (y, u) in enumerate(zip(outputs, inputs)):
                    start = clock()
                    step(y, u)
                    elapsed = clock() - start
                    total += elapsed
                    if elapsed > largest:
                        largest = elapsed
        except Exception as error:
            if times is not None:
                times.add(taken, total, largest)
            raise BlockStopped(taken, error) from error
        if times is not None:
            times.add(len(outputs), total, largest)
        return len(outputs)

    def _block_step(self, rows: np.ndarray) -> Callable[[float, np.ndarray], None]:
        """
        Return the function that takes each row of the checked block ``rows``.

        The size screen of :meth:`update` is done here for the block at once
        (no value near 2^450: then no row needs the quiet path, and the rows go
        straight to the step), and so is the centring monitor's share (one
        row in ``CENTRING_STRIDE``, the same rows as sample by sample). With
        an operating point or a held adaptation, or in a block of fewer than
        ``BLOCK_MIN_ROWS`` rows, each row takes the whole per-sample path. If
        a row's update raises, the monitor has already seen the rows after it
        (it only ever gives a warning).
        """
        if self._means is not None or not self._adapting or rows.shape[0] < BLOCK_MIN_ROWS:
            return self._take_row
        if self._centring is not None:
            self._centring.take_rows(rows)
        if self._quiet_left or not float(np.abs(rows).max()) * rows.shape[1] < HUGE_VALUE:
            return self._learn_row
        return self._guarded_update

    def _screen_size(self, y: float, u: np.ndarray) -> None:
        """Quiet the next updates if a checked sample is beyond 2^450 (see :meth:`_learn`)."""
        if not abs(y) + sum(map(abs, u.tolist())) < HUGE_VALUE:
            self._quiet_left = self.order + 2

    def _take_row(self, y: float, u: np.ndarray) -> None:
        """Take a checked row of a block by the whole per-sample path (see :meth:`_block_step`)."""
        self._screen_size(y, u)
        if self._operated:
            self._operate(y, u)
        else:
            self._learn(y, u)

    def _learn_row(self, y: float, u: np.ndarray) -> None:
        """Learn from a checked row of a block with a huge value (the monitor has the block)."""
        self._screen_size(y, u)
        self._learn(y, u)

    def _learn(self, y: float, u: np.ndarray) -> None:
        """
        Learn from a sample (the operating point removed, if one is) through the transaction.

        A value beyond 2^450 (about 3e135) makes phi' P phi overflow to Inf,
        which the transaction refuses; numpy would also warn about it. The
        warnings are silenced for the order + 2 samples whose regressors can
        hold that value (errstate costs microseconds, so only for those).
        """
        if not self._quiet_left:
            self._guarded_update(y, u)
            return
        self._quiet_left -= 1
        with np.errstate(all='ignore'):
            self._guarded_update(y, u)

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
    def ready(self) -> bool:
        """Whether the regressor is filled and the estimator is past its idle phase."""
        return self.samples >= self.num_parameters

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
