"""
One run case per registered estimator, for the tests that loop over the registry.

The case follows from the registry entry's model kind, not from its name: the
scenario whose data the kind assumes, with that scenario's shipped parameter
file (config/) and the estimator swapped in. A new estimator of a known kind
runs every contract test with no edit here; one of a new kind fails
:func:`case` until its kind has a scenario.
"""

import functools

import numpy as np

from bcid_ros.estimators.registry import ESTIMATOR_NAMES, entry
from bcid_ros.identifier.parameters import (check_identifier_parameters, estimator_from_parameters,
                                            load_yaml_parameters)
from bcid_ros.resources import config_file
from bcid_ros.simulation import make_scenario

#: The scenario (and its parameter file) whose data suit each model kind.
SCENARIO_OF_KIND = {'arx': 'ding_miso', 'output_error': 'ding_miso',
                    'errors_in_variables': 'ikenoue_white_input',
                    'closed_loop': 'ikeda_closed_loop'}
#: Samples of a case: past cl_bcls's first compensation (about 2050) and rpem's first fit.
SAMPLES = 2500

NAMES = ESTIMATOR_NAMES
BATCHED_NAMES = tuple(name for name in ESTIMATOR_NAMES if entry(name).batched)


def parameters(name):
    """Return the identifier parameters of ``name``'s case (checked, defaults filled)."""
    scenario = SCENARIO_OF_KIND[entry(name).model]
    values = load_yaml_parameters(config_file(scenario))
    values['estimator'] = name
    for option in ('forgetting_factor',):
        values.pop(option, None)
    # the other estimators' options of the file are not this one's
    own = set(entry(name).option_names)
    for other in ESTIMATOR_NAMES:
        for option in entry(other).option_names:
            if option not in own:
                values.pop(option, None)
    return check_identifier_parameters(values)


def make(name, **changes):
    """Return a fresh estimator of ``name``'s case (``changes``: parameters changed)."""
    return estimator_from_parameters({**parameters(name), **changes})


@functools.lru_cache(maxsize=None)
def _data(scenario, samples, seed):
    y, u = make_scenario(scenario).simulate(samples, seed)
    return np.asarray(y, dtype=float), np.asarray(u, dtype=float).reshape(len(y), -1)


def data(name, samples=SAMPLES, seed=7):
    """Return (y, u ``(N, r)``) of ``name``'s scenario (copies; the same on every call)."""
    y, u = _data(SCENARIO_OF_KIND[entry(name).model], samples, seed)
    return y.copy(), u.copy()
