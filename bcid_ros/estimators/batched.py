"""
RLS over many plants of one structure, with one vectorised update per sample.

A robot's joints, or a fleet's actuators, are K plants with the same model
structure (order n, r inputs, feedthrough) and the same settings. Running K
:class:`~bcid_ros.estimators.rls.Rls` objects costs K Python calls per
sample, most of it call overhead at these sizes. Here the K states are
stacked (theta as ``(K, p)``, P as ``(K, p, p)``, one regressor history per
plant) and each sample of all plants is one numpy pass.

Each plant follows the recursion of its single-plant estimator with the same
rules: the step and every safeguard around it are
:func:`~bcid_ros.estimators.recursion.ls_step_rows` (which the single plant runs as
K = 1 for its rare samples) and the rulebook
(:mod:`~bcid_ros.estimators.rules`); the compensation of BCRLS is
:func:`~bcid_ros.estimators.bcrls.compensate_rows`, the batched twin of the
single plant's. The single plant's plain step calls BLAS, the batched one
numpy: the estimates agree within rounding (the tests bound the difference by
the problem's own rounding spread), and the decisions (flags, validity) are the
same. The identifier's sample policy (``SampleFeeder``) applies per plant: a
plant whose sample is missing or not finite restarts its own regressor and is
counted, and the other plants are not touched. BCRLS over many plants,
:class:`~bcid_ros.estimators.batched_bcrls.BatchedBcrls`, adds the compensation
to this LS part.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.base import check_int, EstimatorState, HUGE_VALUE, parameter_names
from bcid_ros.estimators.change_detection import ChangeDetector, with_detector_arrays
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.plants import (held_nbytes, PlantReasons, StackedRegressors,
                                        usable_samples)
from bcid_ros.estimators.recursion import (Forgetting, ls_step_rows, LsPlants, LsSettings,
                                           RandomWalk, rows_view, scale_dependents,
                                           where_rows)
from bcid_ros.estimators.regressor import phi_channels
from bcid_ros.estimators.residual_state import residual_items, residual_states
from bcid_ros.estimators.rls import (caught_up_items, LsAccessors, REPLAY_SLICE, RESTART_SPAN,
                                     Rls)
from bcid_ros.estimators.shared_settings import SharedSettings
from bcid_ros.estimators.simulation_windows import SimulationWindows
from bcid_ros.estimators.validity import PlantsValidity

Rows = slice | np.ndarray

#: What a validity decision costs of the REPLAY_SLICE the plants catching up share in an
#: update, in replayed rows (Rls._replay: some 60 rows' worth, 2-3 ms for bcrls).
DECISION_ROWS = 60
#: What a plant's restart costs of that slice in the update that detects it (the snapshot
#: into a new single-plant estimator and its restart, about 1.2 ms: some 50-60 rows).
RESTART_ROWS = 60
#: The rows each plant catching up replays in every update, whatever is left of the slice
#: (up to a row that would decide): its own sample's and one more, so that its queue
#: shrinks and stays within a snapshot's room (rls.QUEUE_ROWS) however many plants catch up.
LEAST_ROWS = 2


class BatchedRls(LsAccessors, PlantsValidity, SharedSettings):
    r"""
    K independent RLS estimators of one structure, updated together.

    Each plant k follows :class:`~bcid_ros.estimators.rls.Rls` (eqs.
    (47)-(50) of Ding et al. (2006) with forgetting) with everything around
    it (units, transaction, gate and plant change, anti-windup, covariance
    repair, validity), by the same functions
    (:func:`~bcid_ros.estimators.recursion.ls_step_rows` and the rulebook), counted
    per plant in :attr:`flags`; P_k(0) = p0 S_k^-2 with plant k's own
    power-of-two signal scales (:attr:`signal_scale`).

    **Samples.** :meth:`update` takes one sample of every plant. Plant k's
    sample is not used when it is marked absent (counted in :attr:`missing`)
    or holds NaN or Inf (counted in :attr:`nonfinite`); its regressor then
    restarts, so no later update regresses across the gap, exactly as the
    identifier does for one plant. The other plants go on undisturbed.

    **Plant changes** (``change_detection``, docs/tracking.md): each plant's
    normalised one-step error goes to one
    :class:`~bcid_ros.estimators.change_detection.ChangeDetector` over the
    plant axis (one vectorised record per update); a detection on plant k
    restarts plant k alone, as its single-plant estimator does
    (:meth:`~bcid_ros.estimators.rls.Rls._plant_changed`, run on plant k's
    snapshot: one implementation of the restart), from plant k's kept samples
    after the change point. Until the replay of those samples has caught up
    (spread over the next updates, as the single plant's), that single-plant
    estimator holds plant k and takes its samples: the plants catching up
    share one ``REPLAY_SLICE`` an update, in turns, so that a change seen on
    every joint at once does not stall one update. ``adaptation: kalman``
    propagates P by the same random walk as the single plant
    (:class:`~bcid_ros.estimators.recursion.RandomWalk`).

    Parameters
    ----------
    num_plants : int
        K >= 1.
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
        As for :class:`~bcid_ros.estimators.base.RecursiveEstimator`, shared
        by all plants.
    change_detection, adaptation, parameter_drift
        As for :class:`~bcid_ros.estimators.base.RecursiveEstimator`, shared
        by all plants.

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    #: The single-plant estimator whose recursion each plant follows.
    name: ClassVar[str] = 'rls'
    noise_names: ClassVar[tuple[str, ...]] = ('residual_variance',)
    #: The single-plant snapshot's arrays and scalars (with their types), each
    #: held here as the per-plant array ``_<key>``.
    _SNAPSHOT_ARRAYS: ClassVar[tuple[str, ...]] = ('theta_ls', 'p', 'signal_scale')
    _SNAPSHOT_SCALARS: ClassVar[dict[str, type]] = {
        'loss': float, 'tau': float, 'updates': int, 'undone_in_row': int, 'next_check': int,
        'last_power': float}
    adequacy_model: ClassVar[str] = Rls.adequacy_model
    hac_std: ClassVar[bool] = Rls.hac_std
    tracks: ClassVar[bool] = Rls.tracks
    #: The single-plant estimator, whose restart after a detected change each plant takes.
    _single: ClassVar[type] = Rls

    def __init__(self, num_plants: int, *, order: int, num_inputs: int = 1,
                 feedthrough: bool = False, initial_covariance: float = 1e6,
                 forgetting_factor: float = 1.0, outlier_threshold: float = 0.0,
                 change_detection: bool = True, adaptation: str = 'forgetting',
                 parameter_drift: float = 0.0) -> None:
        self.num_plants = check_int('num_plants', num_plants, 1)
        self._check_settings(order, num_inputs, feedthrough, initial_covariance,
                             forgetting_factor, outlier_threshold)
        self._check_tracking(change_detection, adaptation, parameter_drift)
        self.parameter_names = parameter_names(self.order, self.num_inputs, self.feedthrough)
        self.num_parameters = len(self.parameter_names)
        # what happens to P between samples, as Rls's: P / lambda or P + q S^-2
        self._propagation = (RandomWalk(self._parameter_drift) if self.adaptation == 'kalman'
                             else Forgetting(self.initial_covariance * self.num_parameters))
        self._gate_from = rules.GATE_WARMUP * self.num_parameters
        self._regressors = StackedRegressors(self.num_plants, self.order, self.num_inputs,
                                             self.feedthrough)
        self._channel = phi_channels(self.order, self.num_inputs, self.feedthrough)
        # a value at or above this may overflow in a step: see RecursiveEstimator.update
        self._huge = HUGE_VALUE / (1 + self.num_inputs)
        #: Samples of each plant that were missing / not finite (not used).
        self.missing = np.zeros(self.num_plants, dtype=np.int64)
        self.nonfinite = np.zeros(self.num_plants, dtype=np.int64)
        self._all_plants = np.arange(self.num_plants)
        self.reset()

    # ----------------------------------------------------------------- API
    def update(self, y: Any, u: Any, present: Any = None) -> np.ndarray:
        """
        Process one sample of every plant and return which estimates are now valid.

        Parameters
        ----------
        y : array_like, shape ``(K,)``
            Output sample y_k(t) of each plant.
        u : array_like, shape ``(K, r)`` (or ``(K,)`` when r = 1)
            Input sample u_k(t) of each plant.
        present : array_like of bool, shape ``(K,)``, optional
            False where plant k has no sample at t (its values are ignored).
            Default: all present.

        Returns
        -------
        numpy.ndarray of bool, shape ``(K,)``
            :attr:`valid` after this sample.

        Raises
        ------
        ValueError
            If an array does not have the shape above. Nothing is changed then.

        """
        y, u, present = self._checked(y, u, present)
        huge = self._huge
        catching = sorted(self._catching)  # (a plant detecting a change here joins next time)
        # one comparison each screens for NaN, Inf and values that could overflow
        if (not catching and present is None and np.abs(y).max() < huge
                and np.abs(u).max() < huge):
            skipped = usable = None
        else:
            skipped, usable = self._screen(y, u, present)
        if self._change_detection:
            self._remember(y, u, skipped)
        regressors = self._regressors
        regressors.push(y, u)
        if skipped is not None:
            regressors.clear(skipped)
            self._clear_simulations(skipped)
        rows = regressors.ready_rows()
        if rows is not None:
            phi = regressors.phi(rows)
            if self._quiet_left:
                # a huge value is in some regressor: its overflow is refused, not warned about
                self._quiet_left -= 1
                np.maximum(self._quiet - 1, 0, out=self._quiet)
                with np.errstate(all='ignore'):
                    self._step(rows, y[rows], phi, u[rows])
            else:
                self._step(rows, y[rows], phi, u[rows])
        elif self._quiet_left:
            self._quiet_left -= 1
            np.maximum(self._quiet - 1, 0, out=self._quiet)
        if catching:
            self._catch_up(catching, y, u, usable)
        if self._catching:
            self._show_catching()
        return self.valid

    def reset(self, plants: Any = None) -> None:
        """
        Return plants (default: all) to the state right after construction.

        The sample counters :attr:`missing` and :attr:`nonfinite` are kept.
        """
        rows = self._plant_rows(plants)
        if isinstance(rows, slice):
            self.flags: dict[str, np.ndarray] = {}
            self._allocate()
            self._quiet_left = 0
            self._quiet = np.zeros(self.num_plants, dtype=np.int64)
            #: The plants catching up after a restart, each held by its single-plant estimator.
            self._catching: dict[int, Rls] = {}
            self._catch_turn = 0
        for plant in self._indices(rows).tolist():
            self._catching.pop(plant, None)
        for counts in self.flags.values():
            counts[rows] = 0
        self._change_score[rows] = 0.0
        self._gate_tail[rows] = 1.0
        self._reset_learning(rows)
        if isinstance(rows, slice):
            # plants that start together would decide together every VALIDITY_PERIOD updates,
            # each decision's simulation check a refit of its window: their decisions after
            # the first are spread over the period, and again after each restart (plants
            # changing at once restart in one frame: Rls._check_offset)
            self._check_offset[:] = self._all_plants * rules.VALIDITY_PERIOD // self.num_plants
            self._check_phase[:] = self._check_offset
        self._regressors.clear(rows)
        self._clear_simulations(rows)

    def restart_regressor(self, plants: Any = None) -> None:
        """Forget plants' (default: all) sample history, keep what they learnt; n + 1 refill it."""
        rows = self._plant_rows(plants)
        self._regressors.clear(rows)
        self._clear_simulations(rows)
        for plant in self._indices(rows).tolist():
            if plant in self._catching:  # (after its queued rows, as the single plant's)
                self._catching[plant].restart_regressor()

    def _clear_simulations(self, rows: Any) -> None:
        """Empty the simulation check's window of ``rows`` (a gap, a restart, a reset)."""
        self._simulations.clear(self._indices(rows))

    @property
    def theta(self) -> np.ndarray:
        """Compensated estimates, shape ``(K, p)`` (a copy)."""
        return self._shown(self._theta().copy(), 'theta')

    @property
    def theta_uncompensated(self) -> np.ndarray:
        """LS estimates before compensation, shape ``(K, p)`` (a copy)."""
        return self._shown(self._theta_ls.copy(), 'theta_uncompensated')

    @property
    def noise(self) -> np.ndarray:
        """Noise estimates named by :attr:`noise_names`, shape ``(K, len(noise_names))``."""
        variance = np.zeros(self.num_plants)
        np.divide(self._loss, self._tau, out=variance, where=self._tau > 0)
        return self._shown(variance[:, None], 'noise')

    @property
    def ready(self) -> np.ndarray:
        """Whether each plant has made at least p updates, shape ``(K,)``."""
        return self._shown(self._updates >= self.num_parameters, 'ready')

    @property
    def samples(self) -> np.ndarray:
        """Count each plant's estimator updates (samples with a filled regressor)."""
        return self._shown(self._updates.copy(), 'samples')

    @property
    def used(self) -> np.ndarray:
        """Count each plant's samples that went into its regressor, shape ``(K,)``."""
        return self._regressors.pushes - self.missing - self.nonfinite

    @property
    def covariance_trace(self) -> np.ndarray:
        """Return tr P_k(t) of each plant, shape ``(K,)``."""
        return self._shown(np.trace(self._p, axis1=1, axis2=2), 'covariance_trace')

    @property
    def loss(self) -> np.ndarray:
        """Return the weighted losses J_k(t) of eq. (50), shape ``(K,)`` (a copy)."""
        return self._shown(self._loss.copy(), 'loss')

    @property
    def weighted_count(self) -> np.ndarray:
        """Return tau_k(t), shape ``(K,)`` (a copy)."""
        return self._shown(self._tau.copy(), 'weighted_count')

    @property
    def signal_scale(self) -> np.ndarray:
        """Return each plant's scales of y, u_1 ... u_r, shape ``(K, 1 + r)``."""
        return self._shown(super().signal_scale, 'signal_scale')

    @property
    def initial_covariance_diagonal(self) -> np.ndarray:
        """Return each plant's diagonal of P(0) = p0 S^-2 in the user's units, ``(K, p)``."""
        return self._shown(super().initial_covariance_diagonal, 'initial_covariance_diagonal')

    @property
    def covariance(self) -> np.ndarray:
        """Return each plant's covariance matrix P_k(t), shape ``(K, p, p)`` (a copy)."""
        return self._shown(super().covariance, 'covariance')

    @property
    def parameter_covariance(self) -> np.ndarray:
        """
        Return each plant's covariance of :attr:`theta`, shape ``(K, p, p)``.

        Plant k's is that of its single-plant estimator
        (``parameter_covariance``, docs/estimators.md "Uncertainty"); all NaN
        where that one is None (not ready, no data for one yet, not finite
        or a negative variance).
        """
        return self.parameter_covariance_of(self._all_plants)

    def parameter_covariance_of(self, plants: np.ndarray) -> np.ndarray:
        """
        Return the rows ``plants`` (indices) of :attr:`parameter_covariance`, the same bits.

        Without the other plants' (the validity decisions of a few plants in an update
        of many: K plants' covariances, and those of the plants catching up, cost
        milliseconds).
        """
        plants = np.asarray(plants, dtype=np.int64).reshape(-1)
        wanted = np.zeros(self.num_plants, dtype=bool)
        wanted[plants] = True
        wanted[list(self._catching)] = False  # (their rows are their single plants')
        covariance = self._shown(self._parameter_covariance(wanted), 'parameter_covariance',
                                 wanted=set(plants.tolist()))[plants]
        diagonal = np.diagonal(covariance, axis1=1, axis2=2)
        unknown = ~(np.isfinite(covariance).all(axis=(1, 2)) & (diagonal >= 0.0).all(axis=1))
        covariance[unknown] = np.nan
        return covariance

    @property
    def parameter_std(self) -> np.ndarray:
        """Return each plant's standard deviations of :attr:`theta`, ``(K, p)``; NaN where none."""
        return np.sqrt(np.diagonal(self.parameter_covariance, axis1=1, axis2=2))

    def _parameter_covariance(self, wanted: np.ndarray | None = None) -> np.ndarray:
        """
        Return the HAC covariance per plant (``Rls._parameter_covariance``), NaN where none.

        ``wanted`` ``(K,)``: only those plants' (the others NaN).
        """
        covariance = self._hac.covariance(self._p, wanted)
        covariance[self._updates < self.num_parameters] = np.nan
        return covariance

    @property
    def nbytes(self) -> int:
        """Bytes of every array this estimator holds, its helpers' included, for sizing."""
        return held_nbytes(self)

    def plant_flags(self, plant: int) -> dict[str, int]:
        """Return the flags counted for one plant (only those that occurred)."""
        return {key: int(counts[plant]) for key, counts in self.flags.items()
                if counts[plant]}

    def plant_state(self, plant: int) -> EstimatorState:
        """
        Return plant k's state as the snapshot its single-plant estimator would make.

        :meth:`~bcid_ros.estimators.base.RecursiveEstimator.set_state` of a
        single-plant estimator of the same configuration accepts it.
        """
        plant = range(self.num_plants)[plant]
        if plant in self._catching:
            return self._catching[plant].get_state()
        arrays, scalars = self._plant_items(plant)
        arrays['history'], filled, position = self._regressors.plant_ring(plant)
        scalars.update(filled=filled, position=position,
                       forgetting_factor=self._forgetting_factor,
                       flags=self.plant_flags(plant),
                       change_score=float(self._change_score[plant]),
                       gate_tail=float(self._gate_tail[plant]))
        replay_arrays, replay_scalars = caught_up_items(self.num_inputs, self.num_parameters,
                                                        len(self.noise_names))
        arrays.update(replay_arrays)
        scalars.update(replay_scalars)
        return EstimatorState(self.name, {k: np.array(v, copy=True) for k, v in arrays.items()},
                              scalars)

    def set_plant_state(self, plant: int, state: EstimatorState) -> None:
        """
        Load a single-plant snapshot (or one of :meth:`plant_state`) into plant k.

        The forgetting factor in the snapshot is ignored: it is shared by all
        plants. A snapshot taken while catching up after a restart goes on
        catching up here. A snapshot of another estimator or of other
        dimensions raises ValueError.
        """
        if state.estimator != self.name:
            raise ValueError(f'state is from estimator {state.estimator!r}, not {self.name!r}')
        plant = range(self.num_plants)[plant]
        single = None
        if state.scalars.get('replay_queued', 0):
            single = self._single_estimator()
            single.set_state(state)
        self._load_single(plant, state)  # (raises before anything changed, as set_state)
        self._catching.pop(plant, None)
        if single is not None:
            self._catching[plant] = single

    def _load_single(self, plant: int, state: EstimatorState) -> None:
        """Load a single-plant snapshot (its shown values aside) into plant k's arrays."""
        arrays, _ = self._plant_items(plant)
        arrays['history'] = self._regressors.history[plant]
        # a snapshot from before the detector loads too, its detector started afresh (Rls's)
        state_arrays = with_detector_arrays(state.arrays, arrays)
        state_arrays.setdefault('recent', np.zeros_like(arrays['recent']))
        # (the simulation check's window may be absent or of another lambda: it loads what fits)
        arrays.pop('simulation_rows')
        for key, value in arrays.items():
            if key not in state_arrays or np.shape(state_arrays[key]) != np.shape(value):
                raise ValueError(f'state array {key!r} does not match this configuration')
        self._load_plant(plant, state_arrays, state.scalars)
        self._load_flags(plant, dict(state.scalars.get('flags', {})))
        self._change_score[plant] = float(state.scalars.get('change_score', 0.0))
        self._gate_tail[plant] = float(state.scalars.get('gate_tail', 1.0))
        self._regressors.load_plant_ring(plant, np.asarray(state.arrays['history'], dtype=float),
                                         int(state.scalars['filled']),
                                         int(state.scalars['position']))

    def _load_flags(self, plant: int, flags: dict[str, int]) -> None:
        """Make plant k's flag counts those of ``flags``."""
        for counts in self.flags.values():
            counts[plant] = 0
        for key, count in flags.items():
            self._flag_counts(key)[plant] = count

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(num_plants={self.num_plants}, order={self.order}, '
                f'num_inputs={self.num_inputs}, feedthrough={self.feedthrough}, '
                f'forgetting_factor={self._forgetting_factor})')

    # ------------------------------------------------------------ the samples
    def _checked(self, y: Any, u: Any,
                 present: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Return the sample arrays as float arrays of the documented shapes, or raise."""
        plants, inputs = self.num_plants, self.num_inputs
        y = np.asarray(y, dtype=float)
        u = np.asarray(u, dtype=float)
        if inputs == 1 and u.shape == (plants,):
            u = u[:, None]
        if y.shape != (plants,):
            raise ValueError(f'y must have shape ({plants},), got {y.shape}')
        if u.shape != (plants, inputs):
            raise ValueError(f'u must have shape ({plants}, {inputs}), got {u.shape}')
        if present is not None:
            present = np.asarray(present, dtype=bool)
            if present.shape != (plants,):
                raise ValueError(f'present must have shape ({plants},), got {present.shape}')
            if present.all():
                present = None
        return y, u, present

    def _screen(self, y: np.ndarray, u: np.ndarray, present: np.ndarray | None
                ) -> tuple[np.ndarray | None, np.ndarray]:
        """
        Count the samples not used; return the plants not stepped here (None: all are).

        Also return which samples are usable. The plants catching up take
        theirs through their single-plant estimators (:meth:`_catch_up`) and
        are not stepped here either.
        """
        usable = usable_samples(y, u, present)
        if present is not None:
            self.missing += ~present
            self.nonfinite += present & ~usable
        else:
            self.nonfinite += ~usable
        stepped = usable
        if self._catching:  # their single-plant estimators take them, after the step
            stepped = usable.copy()
            stepped[list(self._catching)] = False
        with np.errstate(invalid='ignore', over='ignore'):
            # the single plant's screen: the sum of the magnitudes (RecursiveEstimator.update)
            huge = stepped & ~(np.abs(y) + np.abs(u).sum(axis=1) < HUGE_VALUE)
        if huge.any():
            # the order + 2 steps whose regressors can hold it run with warnings off, and
            # those plants' residual tests skip them (as Rls._record_residual's)
            self._quiet_left = self.order + 2
            self._quiet[huge] = self.order + 2
        return (None if stepped.all() else np.flatnonzero(~stepped)), usable

    def _remember(self, y: np.ndarray, u: np.ndarray, skipped: np.ndarray | None) -> None:
        """Keep each used sample among its plant's last RESTART_SPAN (Rls._remember)."""
        rows = self._all_plants
        if skipped is not None:
            used = np.ones(self.num_plants, dtype=bool)
            used[skipped] = False
            rows = np.flatnonzero(used)
            y, u = y[rows], u[rows]
        seen = self._seen if skipped is None else self._seen[rows]
        slots = seen % RESTART_SPAN
        self._recent[rows, slots, 0] = y
        self._recent[rows, slots, 1:] = u
        if skipped is None:
            seen += 1
        else:
            self._seen[rows] += 1

    # ------------------------------------------------------------- the step
    def _step(self, rows: Rows, y: np.ndarray, phi: np.ndarray, u: np.ndarray) -> None:
        """Do one step of the plants ``rows``, whose regressors ``phi`` are filled."""
        rows = self._indices(rows)
        if self._pending_any:
            self._choose_scales(rows)
        settings = LsSettings(self._forgetting_factor, self._gate_limit2, self._gate_from,
                              self._propagation, self.initial_covariance)
        outcome = ls_step_rows(self._plants, rows, y, phi, settings)
        events = outcome.events  # (each mask present only where it holds somewhere)
        checked = self._step_events(rows, events) if events else None
        if outcome.restart.any():
            self._regressors.clear(rows[outcome.restart])
            self._clear_simulations(rows[outcome.restart])
        if outcome.relearn.any():
            self._restart_learning(rows[outcome.relearn])
        if checked is not None:
            # valid is decided at every such event (Rls._rare_step)
            self._check_validity(checked)
        stepped = outcome.stepped
        if stepped.any():
            rows, y, phi, u, errors, gains = where_rows(stepped, rows, y, phi, u,
                                                        outcome.errors, outcome.gains)
            self._after_ls_step(rows, y, phi)
            # the residual tests and the HAC from the gate's warm-up on (Rls._record_residual)
            every = self._view_rows(rows)
            tested = (self._tau[every] >= self._gate_from) & (self._quiet[every] == 0)
            at = rows
            if not tested.all():  # a sample a window does not take: a gap
                self._simulations.gap(rows[~tested])
                at, y, phi, u, errors, gains = where_rows(tested, rows, y, phi, u, errors, gains)
            if at.size:
                self._simulations.record(at, y, u)
                self._record_residuals(at, y, phi, u, errors)
                if self._change_detection:
                    self._detect(at, errors, gains)
            due = self._updates[every] >= self._next_check[every]
            if due.any():
                self._check_validity(rows[due])

    def _step_events(self, rows: np.ndarray, events: dict[str, np.ndarray]) -> np.ndarray | None:
        """Count the ``events`` of a step of ``rows``; return the plants to check (None: none)."""
        for key, where in events.items():
            self._flag(key, rows, where)
        changed = events.get('plant_change', np.zeros(rows.shape[0], dtype=bool))
        if changed.any():
            self._forget_residuals(rows[changed])
            # as Rls._rare_step: the samples given are counted while detection runs
            count = self._seen if self._change_detection else self._updates
            for plant in rows[changed].tolist():
                self._change_notes[plant] = f'plant changed (sample {count[plant]})'
        checked = changed | events.get('outlier_rejected', changed & False)
        return rows[checked] if checked.any() else None

    def _detect(self, rows: np.ndarray, errors: np.ndarray, gains: np.ndarray) -> None:
        """
        Give the detector the normalised errors e / sqrt(s) of ``rows``; restart changed plants.

        As Rls._record_residual: only the steps of the plain path (``gains`` > 0)
        are recorded, all plants' in one vectorised record.
        """
        plain = gains > 0.0
        if not plain.any():
            return
        rows, errors, gains = where_rows(plain, rows, errors, gains)
        rows, inputs = self._detector_errors(rows, errors, gains)
        ages = self._detector.record_rows(rows, inputs)
        changed = ages > 0
        if changed.any():
            for plant, age in zip(rows[changed].tolist(), ages[changed].tolist()):
                self._plant_changed(plant, age)

    def _detector_errors(self, rows: np.ndarray, errors: np.ndarray, gains: np.ndarray,
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Return the plants of ``rows`` that give the detector an input, and their inputs."""
        return rows, errors / np.sqrt(gains)

    def _plant_changed(self, plant: int, age: int) -> None:
        """
        Restart plant k from its ``age`` samples after the change point, as its single plant.

        Plant k's snapshot goes into a single-plant estimator of the same
        settings, which takes the restart (:meth:`Rls._plant_changed`: the
        memory cut, the queue of plant k's kept samples to replay, the change's
        reason) and holds plant k until caught up (:meth:`_catch_up`): the
        other plants are not touched.
        """
        single = self._single_estimator()
        single.set_state(self.plant_state(plant))
        single._plant_changed(age)
        self._catching[plant] = single
        # plant k's rows are its single's only once caught up (_show_catching); until then
        # no decision of this update's step may take them
        self._next_check[plant] = np.iinfo(np.int64).max

    def _catch_up(self, plants: list[int], y: np.ndarray, u: np.ndarray,
                  usable: np.ndarray) -> None:
        """
        Give each plant catching up (``plants``) its sample, through its single plant.

        They share one REPLAY_SLICE of rows (a validity decision counts
        DECISION_ROWS), in turns from update to update, after the restarts
        of this update's detections (RESTART_ROWS each); a plant whose turn
        finds none left replays LEAST_ROWS up to a row that would decide, so
        that its queue still shrinks while it can (with more plants catching
        up than the slice has rows, an update costs more than the slice rather
        than leave queues growing for good) and no update makes more than two
        decisions. Each plant's rows are replayed in the same order whatever
        its slice, so once caught up it is its single plant's estimate bit for
        bit.
        """
        turn = self._catch_turn % len(plants)
        self._catch_turn += 1
        # (the plants catching up only grow in an update: those more are its detections)
        left = REPLAY_SLICE - RESTART_ROWS * (len(self._catching) - len(plants))
        for plant in plants[turn:] + plants[:turn]:
            single = self._catching[plant]
            single._replay_slice = max(left, LEAST_ROWS)
            single._replay_decides = left > 0
            queued, checks = single.catching_up, single._checks
            if usable[plant]:
                single.update(y[plant], u[plant])
            else:  # (missing or not finite: the identifier's policy, as for every plant)
                single.restart_regressor()
            left -= queued + 1 - single.catching_up + DECISION_ROWS * (single._checks - checks)

    def _show_catching(self) -> None:
        """
        Show the plants catching up as their single plants; take back those caught up.

        Until caught up, plant k's rows of the arrays are not its state: its
        flags and reasons are copied here and the accessors read the rest from
        its single plant (:meth:`_shown`). A full load each update would cost
        about 0.5 ms a plant catching up (many joints changing at once).
        """
        for plant, single in list(self._catching.items()):
            if single.catching_up:
                self._load_flags(plant, single.flags)
            else:
                del self._catching[plant]
                self._load_single(plant, single.get_state())
            self._reasons.set(plant, single.validity_reasons)

    def _shown(self, values: np.ndarray, name: str, wanted: Any = None) -> np.ndarray:
        """
        Return ``values`` with the row of each plant catching up its single plant's ``name``.

        ``wanted``: only those plants' rows (None: all); the others are not asked.
        """
        for plant, single in self._catching.items():
            if wanted is not None and plant not in wanted:
                continue
            value = getattr(single, name)
            values[plant] = np.nan if value is None else value  # (None: unknown, as NaN)
        return values

    def _pass_on(self, name: str, value: Any) -> None:
        """Give a setting changed while running to the single plants catching up, as to all."""
        for single in getattr(self, '_catching', {}).values():  # (none while being built)
            setattr(single, name, value)

    def _single_estimator(self) -> Rls:
        """Return a single-plant estimator of these settings (for one plant's restart)."""
        return self._single(
            order=self.order, num_inputs=self.num_inputs, feedthrough=self.feedthrough,
            initial_covariance=self.initial_covariance,
            forgetting_factor=self._forgetting_factor,
            outlier_threshold=self.outlier_threshold, change_detection=True,
            adaptation=self.adaptation, parameter_drift=self._parameter_drift)

    def _after_ls_step(self, rows: np.ndarray, y: np.ndarray, phi: np.ndarray) -> None:
        """Extend the LS step of ``rows`` on (y, phi) (the compensation of subclasses)."""

    def _record_residuals(self, rows: np.ndarray, y: np.ndarray, phi: np.ndarray,
                          u: np.ndarray, errors: np.ndarray) -> None:
        """Give the residual tests and the HAC the steps of ``rows``."""
        self._monitor.record_rows(rows, errors, u)
        self._hac.record_rows(rows, phi * errors[:, None])

    def _forget_residuals(self, rows: np.ndarray) -> None:
        """Start the residual tests (and the HAC) of ``rows`` afresh (Rls._forget_residuals)."""
        self._monitor.clear(rows)
        self._clear_simulations(rows)
        if self._hac is not None:
            self._hac.clear(rows)
        if hasattr(self, '_output_errors'):
            self._output_errors[rows] = 0.0
            self._output_gradients[rows] = 0.0

    def _restart_learning(self, plants: np.ndarray) -> None:
        """Start ``plants`` afresh with scales chosen from the samples now in their regressors."""
        self._flag('rescaled', plants)
        self._reset_learning(plants)
        self._choose_scales(plants)

    # ------------------------------------------------------------ the units
    def _choose_scales(self, plants: np.ndarray) -> None:
        """Give each channel of ``plants`` still without a scale the one of its regressor."""
        plants = plants[self._scales_pending[plants]]
        if not plants.size:
            return
        scales = self._signal_scale[plants]
        new = rules.choose_scales(scales, self._regressors.peaks(plants))
        if new.any():
            p = self._p[plants]
            rules.rescale_new_channels(p, new, scales, self._channel)
            self._p[plants], self._signal_scale[plants] = p, scales
        self._set_scale_dependents(plants)

    def _set_scale_dependents(self, rows: Rows) -> None:
        scales = self._signal_scale[rows]
        self._scales_pending[rows] = (scales == 0.0).any(axis=1)
        self._pending_any = bool(self._scales_pending.any())
        self._component_scale[rows], self._variance_floor[rows] = scale_dependents(
            scales, self._channel)

    # --------------------------------------------------------- the validity
    def _check_validity(self, plants: np.ndarray, more: Any = None) -> None:
        """Decide the reasons of ``plants`` (Rls._check_validity; ``more``: a subclass's)."""
        self._next_check[plants] = (self._updates[plants] + rules.VALIDITY_PERIOD
                                    - self._check_phase[plants])
        self._check_phase[plants] = 0
        with np.errstate(all='ignore'):
            power = rules.output_powers(self._p[plants], self._tau[plants], self.order)
            own = rules.unstable_models(self._theta()[plants, :self.order], power,
                                        self._last_power[plants])
        if more is not None:
            own = [mine + list(theirs) for mine, theirs in zip(own, more)]
        self._decide_validity(plants, own, self._change_notes)
        self._last_power[plants] = power

    # ----------------------------------------------------------- the helpers
    def _plant_rows(self, plants: Any) -> Rows:
        """Return ``plants`` (None = all, an index, indices or a mask) as rows."""
        if plants is None:
            return slice(None)
        rows = np.arange(self.num_plants)[plants]
        return np.atleast_1d(rows)

    def _indices(self, rows: Any) -> np.ndarray:
        """Return rows as an index array."""
        return np.arange(self.num_plants)[rows]

    def _view_rows(self, rows: np.ndarray) -> Rows:
        """Return distinct ascending ``rows`` as a slice where they are every plant (a view)."""
        return rows_view(rows, self.num_plants)

    def _flag_counts(self, key: str) -> np.ndarray:
        """Return the per-plant counts of flag ``key``, made on first use."""
        if key not in self.flags:
            self.flags[key] = np.zeros(self.num_plants, dtype=np.int64)
        return self.flags[key]

    def _flag(self, key: str, rows: Rows, where: np.ndarray | None = None) -> None:
        """Count one occurrence of ``key`` for the plants ``rows`` (where ``where``)."""
        plants = self._indices(rows)
        if where is not None:
            plants = plants[where]
        self._flag_counts(key)[plants] += 1

    def _theta(self) -> np.ndarray:
        return self._theta_ls

    # -------------------------------------------------------------- the state
    def _allocate(self) -> None:
        """Make the per-plant state arrays (their values are set by the resets)."""
        plants, p = self.num_plants, self.num_parameters
        # the simulation check's window of each plant (RecursiveEstimator._start_simulation_check)
        self._simulations = SimulationWindows(plants, self.order, self.num_inputs,
                                              self.feedthrough, (0,) * self.num_inputs,
                                              self._forgetting_factor)
        self._theta_ls = np.zeros((plants, p))
        self._p = np.zeros((plants, p, p))
        self._loss = np.zeros(plants)
        self._tau = np.zeros(plants)
        self._updates = np.zeros(plants, dtype=np.int64)
        self._signal_scale = np.zeros((plants, 1 + self.num_inputs))
        self._scales_pending = np.ones(plants, dtype=bool)
        self._component_scale = np.ones((plants, p))
        self._variance_floor = np.zeros(plants)
        self._undone_in_row = np.zeros(plants, dtype=np.int64)
        self._change_score = np.zeros(plants)
        self._gate_tail = np.ones(plants)
        self._next_check = np.zeros(plants, dtype=np.int64)
        self._check_phase = np.zeros(plants, dtype=np.int64)
        self._check_offset = np.zeros(plants, dtype=np.int64)
        self._last_power = np.zeros(plants)
        self._reasons = PlantReasons(plants)
        # the change detector and each plant's last RESTART_SPAN samples (Rls._remember)
        self._detector = ChangeDetector(plants)
        self._recent = np.zeros((plants, RESTART_SPAN, 1 + self.num_inputs))
        self._seen = np.zeros(plants, dtype=np.int64)
        # the reason of a change the gate found, until the new estimate passes its checks
        self._change_notes = [''] * plants
        # the LS state as the step function sees it (the same arrays)
        self._plants = LsPlants(self._theta_ls, self._p, self._loss, self._tau, self._updates,
                                self._undone_in_row, self._change_score, self._gate_tail,
                                self._variance_floor, self._component_scale)
        # each plant's residual tests and HAC
        self._monitor = AdequacyMonitor(num_inputs=self.num_inputs, model=self.adequacy_model,
                                        forgetting_factor=self._forgetting_factor, plants=plants)
        self._hac = (HacCovariance(dimension=p, forgetting_factor=self._forgetting_factor,
                                   plants=plants) if self.hac_std else None)

    def _reset_learning(self, rows: Rows) -> None:
        """Return what ``rows`` learnt to the start (``Rls._reset`` but the regressor)."""
        self._theta_ls[rows] = 0.0
        self._p[rows] = self.initial_covariance * np.eye(self.num_parameters)
        self._loss[rows] = 0.0
        self._tau[rows] = 0.0
        self._updates[rows] = 0
        self._signal_scale[rows] = 0.0
        self._set_scale_dependents(rows)
        self._undone_in_row[rows] = 0
        self._next_check[rows] = self.num_parameters
        self._check_phase[rows] = self._check_offset[rows]
        self._last_power[rows] = math.inf
        self._reasons.clear(self._indices(rows))
        for plant in self._indices(rows).tolist():
            self._change_notes[plant] = ''
        # (Rls._reset: the kept samples and the detector start afresh too)
        self._recent[rows] = 0.0
        self._seen[rows] = 0
        self._detector.clear(rows)
        self._forget_residuals(self._indices(rows))

    def _plant_items(self, plant: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of plant k as in the single-plant snapshot (not copied)."""
        arrays = {key: getattr(self, '_' + key)[plant] for key in self._SNAPSHOT_ARRAYS}
        scalars = {key: kind(getattr(self, '_' + key)[plant])
                   for key, kind in self._SNAPSHOT_SCALARS.items()}
        scalars['reasons'] = self._reasons.of(plant)
        residual_arrays, residual_scalars = residual_items(
            self._monitor.plant_state(plant),
            None if self._hac is None else self._hac.plant_state(plant))
        detector = self._detector.get_state([plant])
        window_arrays, window_scalars = self._simulations[plant].state_items()
        return ({**arrays, **residual_arrays, **detector, 'recent': self._recent[plant],
                 **window_arrays},
                {**scalars, **residual_scalars, 'seen': int(self._seen[plant]),
                 'check_phase': int(self._check_phase[plant]),
                 'check_offset': int(self._check_offset[plant]),
                 'change_note': self._change_notes[plant], **window_scalars})

    def _load_plant(self, plant: int, arrays: dict[str, np.ndarray],
                    scalars: dict[str, Any]) -> None:
        """Take over plant k's (arrays, scalars) of a single-plant snapshot."""
        for key in self._SNAPSHOT_ARRAYS:
            getattr(self, '_' + key)[plant] = arrays[key]
        for key, kind in self._SNAPSHOT_SCALARS.items():
            getattr(self, '_' + key)[plant] = kind(scalars[key])
        self._set_scale_dependents(np.array([plant]))
        monitor, hac = residual_states(arrays, scalars)
        self._monitor.load_plant(plant, monitor)
        self._simulations[plant].load(arrays, scalars)
        if self._hac is not None:
            self._hac.load_plant(plant, hac)
        self._reasons.set(plant, scalars['reasons'])
        self._change_notes[plant] = str(scalars.get('change_note', ''))
        self._recent[plant] = arrays['recent']
        self._seen[plant] = int(scalars.get('seen', 0))
        self._check_phase[plant] = int(scalars.get('check_phase', 0))
        self._check_offset[plant] = int(scalars.get('check_offset', 0))
        self._detector.set_state(arrays, [plant])


__all__ = ['BatchedRls']
