"""
What rpem's :class:`~bcid_ros.estimators.rpem.online.Rpem` holds: made, saved, restored.

One idea apart from the recursion: every number the estimator keeps is made in
:meth:`RpemState._reset`, written by :meth:`RpemState._state_items` and read back by
:meth:`RpemState._load_state`; :meth:`RpemState.set_state` fills in what a snapshot of an
older version lacks (each key with the value that version behaved as if it held).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.change_detection import with_detector_arrays
from bcid_ros.estimators.recursion import Forgetting, RandomWalk
from bcid_ros.estimators.residual_state import (residual_items, residual_states,
                                                with_gradient_arrays)
from bcid_ros.estimators.rpem.feed import with_feed_items
from bcid_ros.estimators.rpem.uncertainty import excess_root

#: The snapshot keys' prefix of the test of the recursion against its fit (_left_fit).
LEFT_FIT_PREFIX = 'change_left_fit_'
#: The snapshot key of the block-mean test's numbers (all zeros when absent: afresh).
BLOCK_TEST_KEY = 'change_block_test'


class RpemState:
    """The state of :class:`~bcid_ros.estimators.rpem.online.Rpem` (a mixin: its attributes)."""

    def _reset(self) -> None:
        p, size = self.num_parameters, self._size
        self._predictor.clear()
        self._feed.reset()
        self._store.clear()
        # theta in normalised units, and the offset last with detrend: mean
        self._theta_n = np.zeros(size)
        self._p = self.initial_covariance * np.eye(size)
        self._arx = np.zeros(p)
        self._signal_scale = np.ones(1 + self.num_inputs)
        # the means the last fit centred its samples on (detrend: mean; _normalised)
        self._fit_mean = np.zeros(1 + self.num_inputs)
        self._set_scale_dependents()
        #: What happens to P between samples: recursion.Forgetting (P / lambda, anti-windup)
        #: or, with adaptation: kalman, recursion.RandomWalk (P + q I in normalised units)
        self._propagation = (RandomWalk(self._parameter_drift) if self.adaptation == 'kalman'
                             else Forgetting(self.initial_covariance * size))
        self._fitted = False
        self._fits = 0
        self._samples = 0
        self._updates = 0
        self._loss = 0.0
        self._tau = 0.0
        self._lambda_t = self._forgetting_factor
        # the root R of the last fit's E = R R^T (uncertainty.fitted_state_excess) and the
        # sample it came at
        self._excess = np.zeros((size, size))
        self._fit_sample = 0
        # the last fresh fit after a change, its weight and its window's first sample
        # (Rpem._window_moved; weight 0: none)
        self._window_theta = np.zeros(p)
        self._window_weight = 0.0
        self._window_start = 0
        # a fit handed over at the last update, to be judged at the next (Rpem._fitted_now)
        self._decide_pending = False
        self._watch.clear()
        self._gate_from = rules.GATE_WARMUP * p
        self._changes = 0
        self._reasons: tuple[str, ...] = ()
        self._period_reasons: list[str] = []
        self._change_note = ''
        # whether the estimate has been valid since the last change (the detector runs)
        self._settled = False
        self._detector.clear()
        self._left_fit.clear()
        self._paired.reset()
        self._block_test.clear()
        # (phi, psi, y, u) of the step whose sample the gate is testing
        self._gating: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None
        self._forget_residuals()

    #: The scalars of the recursion; the predictor and the store name theirs.
    _SCALARS = ('fitted', 'fits', 'samples', 'updates', 'loss', 'tau', 'lambda_t', 'changes',
                'forgetting_factor', 'fit_sample', 'decide_pending', 'window_weight',
                'window_start')
    #: The type of each scalar that is no int.
    _KINDS: dict[str, Callable[[Any], Any]] = {
        'loss': float, 'tau': float, 'lambda_t': float, 'forgetting_factor': float,
        'fitted': bool, 'decide_pending': bool, 'window_weight': float}

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        lag_arrays, lag_scalars = self._predictor.state_items()
        stored_arrays, stored_scalars = self._store.state_items()
        arrays = {'theta_n': self._theta_n, 'p': self._p,
                  'psi_history': lag_arrays['psi_history'], 'arx': self._arx,
                  'signal_scale': self._signal_scale, 'fit_mean': self._fit_mean,
                  'fitted_state_root': self._excess, 'window_theta': self._window_theta,
                  **stored_arrays,
                  'history': lag_arrays['history']}
        scalars = {**stored_scalars,
                   **{name: getattr(self, '_' + name) for name in self._SCALARS},
                   **self._watch.state_items(), **lag_scalars, 'reasons': list(self._reasons),
                   'period_reasons': list(self._period_reasons),
                   'change_note': self._change_note, 'settled': self._settled,
                   **self._paired.state_items()}
        residual_arrays, residual_scalars = residual_items(self._monitor.get_state(),
                                                           self._hac.get_state())
        feed_arrays, feed_scalars = self._feed.state_items()
        return ({**arrays, **residual_arrays, **self._detector.get_state(),
                 **self._left_fit.get_state(prefix=LEFT_FIT_PREFIX), **feed_arrays,
                 BLOCK_TEST_KEY: self._block_test.state.copy()},
                {**scalars, **residual_scalars, **feed_scalars})

    def set_state(self, state: Any) -> None:
        """
        Restore a :meth:`get_state` snapshot; one from before the parameter term loads too.

        Its residual tests then count the estimate's error from the samples
        after the load on (:func:`~bcid_ros.estimators.residual_state.with_gradient_arrays`).
        """
        own, _ = self._state_items()
        arrays = with_detector_arrays(with_gradient_arrays(state.arrays, own), own)
        if 'fit_mean' not in arrays:  # a snapshot from before: its running means
            arrays['fit_mean'] = np.array(arrays.get('operating_point', own['fit_mean']))
        if 'fitted_state_root' not in arrays:  # from before: E itself, or the held alone
            arrays['fitted_state_root'] = (excess_root(arrays['fitted_state_excess'])
                                           if 'fitted_state_excess' in arrays
                                           else np.zeros_like(own['fitted_state_root']))
        if 'window_theta' not in arrays:  # from before: no fit to compare the next with
            arrays['window_theta'] = np.zeros_like(own['window_theta'])
        arrays, scalars = self._store.with_job_items(arrays, state.scalars)
        arrays, scalars = with_feed_items(arrays, scalars)
        scalars = {'fit_sample': 0, 'decide_pending': False, 'window_weight': 0.0,
                   'window_start': 0, **scalars}
        super().set_state(dataclasses.replace(state, arrays=arrays, scalars=scalars))

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._theta_n, self._arx = arrays['theta_n'], arrays['arx']
        self._signal_scale = arrays['signal_scale']
        self._fit_mean = arrays['fit_mean']
        self._excess = arrays['fitted_state_root']
        self._window_theta = arrays['window_theta']
        self._p = np.ascontiguousarray(arrays['p'])
        self._predictor.load_state(arrays, scalars)
        self._feed.load_state(arrays, scalars)
        self._store.load_state(arrays, scalars)
        self._watch.load_state(scalars)
        for name in self._SCALARS:
            setattr(self, '_' + name, self._KINDS.get(name, int)(scalars[name]))
        self._reasons = tuple(scalars['reasons'])
        self._period_reasons = list(scalars.get('period_reasons', ()))
        self._change_note = str(scalars.get('change_note', ''))
        self._settled = bool(scalars.get('settled', False))
        self._paired.load_state(scalars)
        self._detector.set_state(arrays)
        self._left_fit.set_state(arrays, prefix=LEFT_FIT_PREFIX)
        self._block_test.load(arrays[BLOCK_TEST_KEY])
        self._set_scale_dependents()
        monitor, hac = residual_states(arrays, scalars)
        self._monitor.set_state(monitor)
        self._hac.set_state(hac)


__all__ = ['BLOCK_TEST_KEY', 'LEFT_FIT_PREFIX', 'RpemState']
