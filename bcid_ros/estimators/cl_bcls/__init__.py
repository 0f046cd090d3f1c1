"""
Closed-loop bias-compensated least squares (Ikeda 2008): online and batch.

Ikeda (2008), "Bias-compensated least squares method in closed loop
environment", IFAC World Congress: least squares on prefiltered data
(eqs. 9-17), a bias compensation that uses the known controller (Theorem
1, eqs. 29-59) and an iterative redesign of the prefilter (Algorithm 1).
docs/cl_bcls.md explains the settings, the safety rules and their reasons.

The modules, each importing only those below it:

* :mod:`~bcid_ros.estimators.cl_bcls.online`: :class:`ClosedLoopBcls`, the
  online estimator that the identifier node runs;
* :mod:`~bcid_ros.estimators.cl_bcls.uncertainty`: the covariance of its
  estimate (the delta method on the moments);
* :mod:`~bcid_ros.estimators.cl_bcls.excitation`: the power of the
  reference, reconstructed without measuring it;
* :mod:`~bcid_ros.estimators.cl_bcls.window`: with ``window`` > 0, what the
  estimator remembers (:class:`WindowMemory`): the samples a redesign runs
  the batch Algorithm 1 on;
* :mod:`~bcid_ros.estimators.cl_bcls.moments`: with ``window`` 0, what it
  remembers (:class:`AllDataMemory`): the moments of all rows since the
  controller change, and Algorithm 1 on them. The two memories answer the
  same calls (a row's a-priori error and commit, the compensation's terms,
  the redesign schedule, the redesign as a :class:`Redesign`, the state);
* :mod:`~bcid_ros.estimators.cl_bcls.compensation`: the compensated
  estimate per sample (eqs. 58, 59) and when not to trust it;
* :mod:`~bcid_ros.estimators.cl_bcls.running_ls`: the prefilters, the
  units and the recursive LS per sample;
* :mod:`~bcid_ros.estimators.cl_bcls.batch`: the batch Algorithm 1
  (:func:`closed_loop_bcls`) and the compensation of eqs. (53)-(59);
* :mod:`~bcid_ros.estimators.cl_bcls.bias`: the bias terms of Theorem 1;
* :mod:`~bcid_ros.estimators.cl_bcls.regression`: the model, its prefiltered
  regression form and the LS over a record.
"""

from bcid_ros.estimators.cl_bcls.batch import (algorithm1, closed_loop_bcls, ClosedLoopResult,
                                               compensated_estimate, DEFAULT_TOLERANCE,
                                               is_contracting)
from bcid_ros.estimators.cl_bcls.bias import (augmented_system, bias_terms,
                                              closed_loop_realisation, noise_state_covariance,
                                              prefilter_realisation, solve_p12, solve_p22)
from bcid_ros.estimators.cl_bcls.compensation import (Compensation, MAX_CONDITION,
                                                      model_reasons, Redesign, scaled_condition,
                                                      validity_reasons)
from bcid_ros.estimators.cl_bcls.excitation import ExcitationMeter
from bcid_ros.estimators.cl_bcls.moments import (AllDataMemory, MomentCompensation,
                                                 PrefilteredMoments)
from bcid_ros.estimators.cl_bcls.online import ClosedLoopBcls
from bcid_ros.estimators.cl_bcls.regression import (CompensationFailure, plant_from_regression,
                                                    prefilter_polynomial, PrefilteredLs,
                                                    prefiltered_ls, prefiltered_regression,
                                                    regression_from_plant)
from bcid_ros.estimators.cl_bcls.running_ls import (PrefilterBank, RunningLs, SignalScales,
                                                    update_is_safe)
from bcid_ros.estimators.cl_bcls.window import window_lengths, WindowMemory

__all__ = ['algorithm1', 'AllDataMemory', 'augmented_system', 'bias_terms', 'closed_loop_bcls',
           'closed_loop_realisation', 'ClosedLoopBcls', 'ClosedLoopResult',
           'compensated_estimate', 'Compensation', 'CompensationFailure', 'DEFAULT_TOLERANCE',
           'ExcitationMeter', 'is_contracting', 'MAX_CONDITION', 'model_reasons',
           'MomentCompensation', 'noise_state_covariance', 'plant_from_regression',
           'prefilter_polynomial', 'prefilter_realisation', 'PrefilterBank', 'PrefilteredLs',
           'prefiltered_ls', 'prefiltered_regression', 'PrefilteredMoments', 'Redesign',
           'regression_from_plant', 'RunningLs', 'scaled_condition',
           'SignalScales', 'solve_p12', 'solve_p22', 'update_is_safe', 'validity_reasons',
           'window_lengths', 'WindowMemory']
