"""
Offline analysis of a recorded bag: order and delay, validation, model properties.

Pure numpy and scipy (matplotlib only in :mod:`bcid_ros.analysis.plot`, imported
when a figure is asked for); no ROS. :func:`analyze` fits every candidate
order and delay with the configured estimator and recommends one;
:class:`DiscreteModel` gives poles, zeros, gains, responses and continuous-time
equivalents. ``bcid analyze`` (:mod:`bcid_ros.analysis.command`) is the
command line around them; docs/analyze.md documents the rule and its check.
"""

from bcid_ros.analysis.model import DiscreteModel
from bcid_ros.analysis.search import Analysis, analyze, Candidate, recommend

__all__ = ['Analysis', 'Candidate', 'DiscreteModel', 'analyze', 'recommend']
