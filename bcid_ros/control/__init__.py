"""
Adaptive control on the identifier's estimates (pure numpy, no ROS).

* :mod:`~bcid_ros.control.design`: pole placement by the Diophantine equation
  (Sylvester matrix), the estimate's names and structure;
* :mod:`~bcid_ros.control.runtime`: the controller in the loop, saturated,
  with anti-windup and bumpless switching;
* :mod:`~bcid_ros.control.reference`: built-in excitation signals;
* :mod:`~bcid_ros.control.loop`: the self-tuning regulator (trust gate,
  fallback, counters) that the controller node runs;
* :mod:`~bcid_ros.control.parameters`: the node's parameter table.

See docs/adaptive_loop.md.
"""

from bcid_ros.control.design import (closed_loop_poles, Controller, DesignRefused,
                                     ModelStructure, place_poles, Plant)
from bcid_ros.control.loop import AdaptiveController
from bcid_ros.control.runtime import ControllerRuntime

__all__ = ['AdaptiveController', 'Controller', 'ControllerRuntime', 'DesignRefused',
           'ModelStructure', 'Plant', 'closed_loop_poles', 'place_poles']
