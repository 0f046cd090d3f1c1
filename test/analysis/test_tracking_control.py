"""benchmarks/tracking_control.py's held plants: the tracking case without its change."""

import numpy as np
import pytest

from benchmarks.tracking import family_run_options, TrackingCase
from benchmarks.tracking_control import held

SEED = (0, 5)  # an abrupt gain change, order 3, coloured noise


def test_a_held_case_is_the_case_without_its_change():
    case = TrackingCase(SEED, 'family')
    theta, y = case.theta.copy(), case.y.copy()
    control = held(case)
    # the case itself is untouched
    assert np.array_equal(case.theta, theta) and np.array_equal(case.y, y)
    assert case.kind == 'abrupt' and control.kind == 'none'
    # the plant of before the change throughout
    assert np.array_equal(control.theta, np.repeat(theta[case.change_at - 1][None], len(y), 0))
    assert not np.allclose(theta[-1], theta[case.change_at - 1])
    # the same samples before the change, bit for bit; the same inputs and change sample
    before = slice(None, case.change_at)
    assert np.array_equal(control.y[before], y[before])
    assert np.array_equal(control.u, case.u) and control.change_at == case.change_at
    # after it, the same output noise (a difference of two simulations: rounding only) on
    # the held plant's output, which is not the changed plant's
    noise, held_noise = y - case.simulate(case.u), control.y - control.simulate(control.u)
    scale = np.abs(noise).max()
    assert np.abs(held_noise - noise).max() <= 1e-12 * max(scale, np.abs(y).max())
    after = slice(case.change_at, None)
    assert np.abs(control.y[after] - y[after]).max() > 10 * scale


def test_the_family_runs_take_known_configurations_only():
    args, configs = family_run_options(['--seed', '3', '--count', '4'], 'run')
    assert (args.seed, args.count, configs) == (3, 4, ['rpem', 'rpem_0.999'])
    assert family_run_options(['--estimators', 'rls'], 'run')[1] == ['rls']
    with pytest.raises(SystemExit) as stopped:  # the usage and status 2, not a traceback
        family_run_options(['--estimators', 'rpem,bogus'], 'run')
    assert stopped.value.code == 2
