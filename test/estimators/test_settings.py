"""One range per setting: the node's parameter table and the constructors check the same spec."""

import re

import numpy as np
import pytest

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.registry import entry
from bcid_ros.estimators.settings import (BCIV_OPTIONS, CL_BCLS_OPTIONS, RPEM_OPTIONS,
                                          SHARED_SETTINGS)
from bcid_ros.identifier.parameters import BASE_SETTINGS, IDENTIFIER_PARAMETERS


def test_the_tables_hold_the_settings_specs_themselves():
    for spec in SHARED_SETTINGS.values():
        assert any(item is spec for item in IDENTIFIER_PARAMETERS), spec.name
    assert entry('bciv').options is BCIV_OPTIONS
    assert entry('cl_bcls').options is CL_BCLS_OPTIONS
    assert entry('rpem').options is RPEM_OPTIONS


def beyond(spec):
    """Return the values just outside ``spec``'s range (one integer, or one ulp)."""
    if spec.type == 'integer':
        return [spec.low - 1, spec.high + 1]
    low = spec.low if spec.low_open else np.nextafter(spec.low, -np.inf)
    return [low, np.nextafter(spec.high, np.inf)]


RANGED = sorted(name for name, spec in SHARED_SETTINGS.items()
                if spec.type in ('integer', 'double'))


def test_the_constructor_takes_every_setting_of_the_table():
    assert BASE_SETTINGS == tuple(SHARED_SETTINGS)
    assert set(RANGED) == {'order', 'num_inputs', 'initial_covariance', 'forgetting_factor',
                           'outlier_threshold'}


@pytest.mark.parametrize('name', RANGED)
def test_a_constructor_refuses_what_the_node_refuses(name):
    spec = SHARED_SETTINGS[name]
    for value in beyond(spec):
        with pytest.raises(ValueError) as constructor:
            make_estimator('rls', **{'order': 2, name: value})
        with pytest.raises(ValueError):
            spec.check(value)
        # the message names the setting, its range and the value
        message = str(constructor.value)
        assert message.startswith(f'{name} must be ') and re.search(r'[\[(].*, .*\]', message)
        assert repr(float(value) if spec.type == 'double' else value) in message


@pytest.mark.parametrize('name, options, value', [
    ('window', CL_BCLS_OPTIONS, 10 ** 9 + 1), ('tolerance', CL_BCLS_OPTIONS, 2e6),
    ('max_iterations', CL_BCLS_OPTIONS, 10001), ('iv_lag', BCIV_OPTIONS, 1001),
    ('bciv_iterations', BCIV_OPTIONS, 0),
])
def test_an_option_beyond_its_table_range_is_refused_by_the_estimator(name, options, value):
    estimator = 'cl_bcls' if options is CL_BCLS_OPTIONS else 'bciv'
    settings = {'order': 1}
    if estimator == 'cl_bcls':
        settings.update(controller_numerator=[0.2], controller_denominator=[1.0, -0.1])
    with pytest.raises(ValueError, match=f'^{name} must be'):
        make_estimator(estimator, **settings, **{name: value})


def test_numpy_scalars_and_the_range_ends_are_taken():
    assert SHARED_SETTINGS['order'].check_argument(np.int64(3)) == 3
    assert SHARED_SETTINGS['forgetting_factor'].check_argument(np.float32(1.0)) == 1.0
    assert SHARED_SETTINGS['outlier_threshold'].check_argument(0) == 0.0
    estimator = make_estimator('rls', order=1, forgetting_factor=1.0, outlier_threshold=1e6,
                               initial_covariance=1e15)
    assert estimator.forgetting_factor == 1.0
    with pytest.raises(ValueError, match=r'forgetting_factor must be in \(0, 1\], got nan'):
        estimator.forgetting_factor = float('nan')
