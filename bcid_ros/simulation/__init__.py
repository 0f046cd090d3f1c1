"""
Plants, noise models and the papers' scenarios (pure numpy and scipy).

Use :func:`make_scenario` to build a scenario by the name the simulator
node's ``scenario`` parameter takes.
"""

from __future__ import annotations

import importlib
from typing import Any

from bcid_ros.simulation.base import SampleStream, Scenario, StreamingFilter, Truth

#: Scenario name -> ('module:class', keyword settings).
SCENARIOS: dict[str, tuple[str, dict[str, Any]]] = {
    'ding_miso': ('bcid_ros.simulation.ding:DingMiso', {}),
    'ding_miso_nonstationary': ('bcid_ros.simulation.ding:DingMiso', {'nonstationary': True}),
    'ikenoue_colored': ('bcid_ros.simulation.ikenoue:IkenoueEiv', {'section': '5.1'}),
    'ikenoue_white_input': ('bcid_ros.simulation.ikenoue:IkenoueEiv', {'section': '5.2'}),
    'ikeda_closed_loop': ('bcid_ros.simulation.ikeda:IkedaClosedLoop', {}),
    'custom': ('bcid_ros.simulation.custom:CustomScenario', {}),
    'joints': ('bcid_ros.simulation.joints:JointsScenario', {}),
}


def make_scenario(name: str, **settings: Any) -> Scenario:
    """
    Build the scenario ``name``; ``settings`` go to its constructor.

    Raises
    ------
    ValueError
        If ``name`` is not one of :data:`SCENARIOS`.

    """
    if name not in SCENARIOS:
        raise ValueError(f'scenario must be one of {", ".join(SCENARIOS)}; got {name!r}')
    target, defaults = SCENARIOS[name]
    module, cls = target.split(':')
    return getattr(importlib.import_module(module), cls)(**{**defaults, **settings})


__all__ = ['SCENARIOS', 'SampleStream', 'Scenario', 'StreamingFilter', 'Truth',
           'make_scenario']
