"""
BCIV: bias-compensated IV-type estimation for errors-in-variables models.

Ikenoue, Kanae, Yang and Wada (2008), "Bias-compensation based method for
errors-in-variables model identification", eqs. (37)-(75) and the recursive
algorithm of section 4. What "the estimate at sample N" means differs by
noise case (the reasons, and the paper's limits, are in ``docs/bciv.md`` and
``docs/papers.md``):

* colored input noise: eq. (72) does not fix the gain of B, so the
  alternation of eqs. (75) and (53) has a unit eigenvalue; the estimate is
  K alternations started from the IV-type estimate theta_IV,N, never
  warm-started from the previous BCIV estimate;
* white input noise (eqs. 65-67): there is no such direction; the estimate
  is a fixed point of the alternation, found warm-started at every sample;
* ``bciv_update='printed'``: the paper's Steps 0-5 as printed, one
  alternation per sample warm-started from the previous estimate.

The modules, each importing only those below it:

* :mod:`~bcid_ros.estimators.bciv.online`: :class:`Bciv`, the recursive
  estimator (sample handling, units, gate, validity, state);
* :mod:`~bcid_ros.estimators.bciv.batch`: :func:`bciv_batch`, the batch
  reference;
* :mod:`~bcid_ros.estimators.bciv.uncertainty`: the covariance of the
  estimate (the delta method on the moments);
* :mod:`~bcid_ros.estimators.bciv.history`: the window of samples that
  holds the IV-type vector and the regressor (eqs. 54, 68-70);
* :mod:`~bcid_ros.estimators.bciv.solver`: :class:`BcivSolver`, the
  estimate from the moments (eqs. 38, 75, 53), shared by both forms;
* :mod:`~bcid_ros.estimators.bciv.white`: the white-noise fixed point
  (eqs. 65-67);
* :mod:`~bcid_ros.estimators.bciv.units`: the signal scales and the M_0
  term they set.
"""

from bcid_ros.estimators.bciv.batch import bciv_batch, BcivBatch
from bcid_ros.estimators.bciv.history import RING_SAMPLES, SampleHistory
from bcid_ros.estimators.bciv.online import Bciv, RUNAWAY_SHIFT, UPDATES
from bcid_ros.estimators.bciv.solver import (BcivResult, BcivSolver, CHECK_PERIOD,
                                             check_structure, COMPENSATION_MAX, CONDITION_MAX,
                                             DEFAULT_TOLERANCE, INPUT_NOISE, noise_count, OK,
                                             published_noise, RUNAWAY, SINGULAR)
from bcid_ros.estimators.bciv.units import regularisation_weights, window_scales
from bcid_ros.estimators.bciv.white import WhiteFixedPoint

__all__ = ['Bciv', 'bciv_batch', 'BcivBatch', 'BcivResult', 'BcivSolver', 'CHECK_PERIOD',
           'check_structure', 'COMPENSATION_MAX', 'CONDITION_MAX', 'DEFAULT_TOLERANCE',
           'INPUT_NOISE', 'noise_count', 'OK', 'published_noise', 'regularisation_weights',
           'RING_SAMPLES', 'RUNAWAY', 'RUNAWAY_SHIFT', 'SampleHistory', 'SINGULAR', 'UPDATES',
           'WhiteFixedPoint', 'window_scales']
