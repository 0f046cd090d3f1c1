"""
Recursive estimators: pure numpy, free of ROS.

Use :func:`make_estimator` to build one by its registry name, the value of
the identifier node's ``estimator`` parameter; :mod:`.registry` says what
each one is (model kind, options, input modes, batched form).
"""

from __future__ import annotations

from typing import Any

from bcid_ros.estimators.base import (EstimatorState, parameter_names, RecursiveEstimator,
                                      Trajectory)
from bcid_ros.estimators.registry import (batched_class, ESTIMATOR_NAMES, estimator_class,
                                          REGISTRY)

#: The registry, by name (see :mod:`bcid_ros.estimators.registry`).
ESTIMATORS = REGISTRY


def make_estimator(name: str, **settings: Any) -> RecursiveEstimator:
    """Build the estimator ``name`` with keyword settings (see each class)."""
    return estimator_class(name)(**settings)


def make_batched_estimator(name: str, num_plants: int, **settings: Any) -> Any:
    """
    Build the batched form of estimator ``name`` over ``num_plants`` plants.

    Raises
    ------
    ValueError
        If ``name`` has no batched form.

    """
    return batched_class(name)(num_plants, **settings)


__all__ = ['ESTIMATORS', 'ESTIMATOR_NAMES', 'EstimatorState', 'RecursiveEstimator',
           'Trajectory', 'batched_class', 'estimator_class', 'make_batched_estimator',
           'make_estimator', 'parameter_names']
