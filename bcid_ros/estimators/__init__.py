"""
Recursive estimators: pure numpy, free of ROS.

Use :func:`make_estimator` to build one by its registry name, the value of
the identifier node's ``estimator`` parameter.
"""

from __future__ import annotations

import importlib
from typing import Any

from bcid_ros.estimators.base import (EstimatorState, parameter_names, RecursiveEstimator,
                                      Trajectory)

#: Registry name -> 'module:class'. A module is imported when its estimator is
#: first asked for by name.
ESTIMATORS = {
    'rls': 'bcid_ros.estimators.rls:Rls',
    'bcrls': 'bcid_ros.estimators.bcrls:Bcrls',
    'bciv': 'bcid_ros.estimators.bciv:Bciv',
    'cl_bcls': 'bcid_ros.estimators.cl_bcls:ClosedLoopBcls',
    'rpem': 'bcid_ros.estimators.rpem:Rpem',
}


def estimator_class(name: str) -> type[RecursiveEstimator]:
    """
    Return the estimator class registered as ``name``.

    Raises
    ------
    ValueError
        If ``name`` is not one of :data:`ESTIMATORS`.

    """
    if name not in ESTIMATORS:
        raise ValueError(f'estimator must be one of {", ".join(ESTIMATORS)}; got {name!r}')
    module, cls = ESTIMATORS[name].split(':')
    return getattr(importlib.import_module(module), cls)


def make_estimator(name: str, **settings: Any) -> RecursiveEstimator:
    """Build the estimator ``name`` with keyword settings (see each class)."""
    return estimator_class(name)(**settings)


__all__ = ['ESTIMATORS', 'EstimatorState', 'RecursiveEstimator', 'Trajectory',
           'estimator_class', 'make_estimator', 'parameter_names']
