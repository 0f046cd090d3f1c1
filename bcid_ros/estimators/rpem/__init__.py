"""
RPEM: the recursive prediction-error method for output-error and ARMAX models.

Ljung and Söderström (1983), *Theory and Practice of Recursive
Identification* (L&S): the recursive prediction-error algorithm in its
Gauss-Newton form, with the output-error predictor and the recursive
maximum-likelihood (ARMAX) one, and the projection into the stability region
D_M; Ljung, *System Identification*, 2nd ed. (1999), ch. 11 (sec. 11.4, the
recursive prediction-error method) and ch. 10 (sec. 10.2, the batch
Gauss-Newton search, here started by instrumental-variable, Steiglitz-McBride,
iterations). What MATLAB's ``recursiveOE`` and ``recursiveARMAX`` run, with a
batch-refined start and the safeguards a real plant needs (docs/estimators.md,
"RPEM"). Equation numbers are not given: the books were not at hand to check
them.

The modules, each importing only those below it:

* :mod:`~bcid_ros.estimators.rpem.online`: :class:`Rpem`, the recursive
  estimator (the recursion, the gate, the hand-over from a fit, validity);
* :mod:`~bcid_ros.estimators.rpem.state`: what it holds, made, saved and
  restored (snapshots of older versions included);
* :mod:`~bcid_ros.estimators.rpem.feed`: the last fit's model run on, whose
  one-step errors the change detector tests;
* :mod:`~bcid_ros.estimators.rpem.watch`: :class:`RestartWatch`, the
  projection and undone-step monitors that restart it (a plant that changes
  or drifts is the change detector's), and their validity reasons;
* :mod:`~bcid_ros.estimators.rpem.uncertainty`: the HAC sandwich covariance
  of the estimate;
* :mod:`~bcid_ros.estimators.rpem.store`: :class:`SampleStore`, the stored
  samples, their segments and scales, and the schedule of the batch fits;
* :mod:`~bcid_ros.estimators.rpem.fit`: :class:`BatchFit`, the batch
  prediction-error fit (ARX and IV starts, Gauss-Newton search), and
  :class:`FitResult`;
* :mod:`~bcid_ros.estimators.rpem.segment`: :class:`SegmentPredictor`, the
  predictor of one stored segment at fixed parameters;
* :mod:`~bcid_ros.estimators.rpem.history`: :class:`PredictorHistory` and
  :class:`RecursivePredictor`, the lags of the recursion's predictor and of
  its gradient filter;
* :mod:`~bcid_ros.estimators.rpem.stability`: the stability region D_M
  (``REGION_MARGIN``, the margin of its test by
  :func:`~bcid_ros.estimators.polynomials.is_stable`; :func:`pull_inside`).
"""

from bcid_ros.estimators.rpem.fit import (BatchFit, FitResult, IV_ITERATIONS, LM_ITERATIONS,
                                          LM_TOLERANCE, OUTLIER_WEIGHT)
from bcid_ros.estimators.rpem.history import PredictorHistory, RecursivePredictor
from bcid_ros.estimators.rpem.online import LAMBDA_RATE, LAMBDA_START, MODELS, Rpem
from bcid_ros.estimators.rpem.segment import (INITIAL_PRIOR, Prediction, SegmentPredictor,
                                              solve_regularised)
from bcid_ros.estimators.rpem.stability import (HALVINGS, pull_inside, REGION_MARGIN,
                                                STABILITY_RADIUS)
from bcid_ros.estimators.rpem.store import (BATCH_LIMIT, FIRST_FIT_PER_PARAMETER,
                                            FIRST_FIT_SAMPLES, FIT_GROWTH, OUTLIER_SHARE,
                                            SampleStore, Segment, signal_size, StoredFit)
from bcid_ros.estimators.rpem.uncertainty import parameter_covariance
from bcid_ros.estimators.rpem.watch import (on_boundary, PROJECTION_RESTART, PROJECTION_SHARE,
                                            RestartWatch, UNDONE_RESTART)

__all__ = ['BATCH_LIMIT', 'BatchFit', 'FIRST_FIT_PER_PARAMETER',
           'FIRST_FIT_SAMPLES', 'FIT_GROWTH', 'FitResult', 'HALVINGS', 'INITIAL_PRIOR',
           'IV_ITERATIONS', 'LAMBDA_RATE', 'LAMBDA_START', 'LM_ITERATIONS', 'LM_TOLERANCE',
           'MODELS', 'OUTLIER_SHARE', 'OUTLIER_WEIGHT', 'parameter_covariance', 'Prediction',
           'PredictorHistory', 'PROJECTION_RESTART', 'PROJECTION_SHARE', 'pull_inside',
           'REGION_MARGIN',
           'RecursivePredictor', 'RestartWatch', 'Rpem', 'SampleStore', 'Segment',
           'SegmentPredictor', 'signal_size', 'solve_regularised', 'STABILITY_RADIUS',
           'StoredFit', 'UNDONE_RESTART', 'on_boundary']
