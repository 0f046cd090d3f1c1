"""
Offline analysis of a recorded bag or CSV log: structure, validation, model properties.

Pure numpy and scipy (matplotlib only in :mod:`bcid_ros.analysis.plot`, imported
when a figure is asked for); no ROS. :func:`analyze` chooses the order and the
dead time of every input with batch output-error fits (:mod:`bcid_ros.analysis.
batch`, :mod:`bcid_ros.analysis.pem`) validated on the end of the record, then
runs the online estimators on that structure beside the batch model
(:mod:`bcid_ros.analysis.online`); :class:`DiscreteModel` gives poles, zeros,
gains, responses and continuous-time equivalents. ``bcid analyze``
(:mod:`bcid_ros.analysis.command`) is the command line around them;
docs/analyze.md documents the rule and its checks.
"""

from bcid_ros.analysis.model import DiscreteModel
from bcid_ros.analysis.search import Analysis, analyze, Candidate, recommend

__all__ = ['Analysis', 'Candidate', 'DiscreteModel', 'analyze', 'recommend']
