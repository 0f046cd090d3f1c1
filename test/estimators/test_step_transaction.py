"""
The exact transactions of bciv and cl_bcls: an undone sample leaves the state it found.

Each test refuses one sample after the fact (its step made, then found unsound) in one
estimator, and compares it, bit for bit, with a twin that skipped that sample and restarted
its regressor instead: both then run on over the same samples. Bit equality is between two
computations of the same test run.
"""

import contextlib

import numpy as np
import pytest

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.transaction import all_finite
from bcid_ros.estimators.bciv import Bciv
from bcid_ros.estimators.cl_bcls import running_ls, update_is_safe
from bcid_ros.simulation import make_scenario
from bcid_ros.simulation.ikeda import IkedaClosedLoop

SAMPLES = 900


def assert_same_state(first, second, skip=()):
    """Assert that two estimators hold the same state (all but the flags and ``skip``)."""
    one, other = first.get_state(), second.get_state()
    assert one.arrays.keys() == other.arrays.keys()
    for key in one.arrays:
        assert np.array_equal(one.arrays[key], other.arrays[key]), key
    for key in set(one.scalars) | set(other.scalars):
        if key not in ('flags',) + tuple(skip):
            assert one.scalars[key] == other.scalars[key], key
    assert np.array_equal(first.theta, second.theta)
    assert np.array_equal(first.noise, second.noise)
    assert first.covariance_trace == second.covariance_trace


def undo_against_restart(make, y, u, at, refuse, skip=(), settle=0):
    """Refuse sample ``at`` inside ``refuse(est)``; compare with a twin restarted instead."""
    undone, twin = make(), make()
    for t in range(at):
        assert undone.update(y[t], u[t]) == twin.update(y[t], u[t])
    with refuse(undone):
        undone.update(y[at], u[at])
    twin.restart_regressor()
    assert undone.flags.get('update_undone', 0) == 1
    for t in range(at + 1, at + 1 + settle):
        undone.update(y[t], u[t])
        twin.update(y[t], u[t])
    assert_same_state(undone, twin, skip)
    for t in range(at + 1 + settle, len(y)):
        assert undone.update(y[t], u[t]) == twin.update(y[t], u[t])
    assert_same_state(undone, twin, skip)
    assert undone.flags.get('update_undone', 0) == 1


@contextlib.contextmanager
def unsound_once(est):
    """Make the next step of ``est`` come out unsound (its _is_sound says no, once)."""
    est._is_sound = lambda: False
    try:
        yield
    finally:
        del est._is_sound


# --------------------------------------------------------------------------- bciv
@pytest.mark.parametrize('scenario, settings', [
    ('ikenoue_colored', {'iv_lag': 5}),
    ('ikenoue_white_input', {'iv_lag': 4, 'input_noise': 'white'}),
    ('ikenoue_colored', {'iv_lag': 5, 'input_delay': 2, 'outlier_threshold': 5.0}),
])
@pytest.mark.parametrize('at', ['fill', 150, 700])  # the scales are chosen; idle; running
def test_an_undone_bciv_step_leaves_the_state_it_found(scenario, settings, at):
    z, w = make_scenario(scenario).simulate(SAMPLES, 3)

    def make():
        return Bciv(order=2, idle_samples=100, **settings)
    if at == 'fill':  # the first update: the window is full and the scales are chosen
        at = make()._solver.m - 1 + settings.get('input_delay', 0)
    undo_against_restart(make, np.asarray(z, dtype=float), np.asarray(w, dtype=float),
                         at, unsound_once)


# ------------------------------------------------------------------------ cl_bcls
PAPER = IkedaClosedLoop()


def paper_loop():
    y, u = PAPER.simulate(SAMPLES, 5)
    return y, u.reshape(-1, 1)


def make_cl_bcls(**settings):
    return lambda: make_estimator('cl_bcls', **{**PAPER.estimator_settings(),
                                                'redesign_period': 200, **settings})


def first_redesign_after(make, y, u, start):
    """Return the sample at which ``make()`` redesigns first after sample ``start``."""
    est = make()
    for t in range(len(y)):
        before = est.redesigns
        est.update(y[t], u[t])
        if t > start and est.redesigns > before:
            return t
    raise AssertionError('no redesign')


WINDOWS = [{'window': 400}, {'window': 0}, {'window': 0, 'forgetting_factor': 0.999}]


@pytest.mark.parametrize('settings', WINDOWS)
def test_an_undone_cl_bcls_redesign_step_leaves_the_state_it_found(settings):
    # a step that redesigns runs as the saving transaction: the redesign is undone too
    y, u = paper_loop()
    make = make_cl_bcls(**settings)
    at = first_redesign_after(make, y, u, 300)
    # (the window's row and the meter's pending sample are rewritten by the next sample)
    undo_against_restart(make, y, u, at, unsound_once, settle=1)


@pytest.mark.parametrize('settings', WINDOWS)
@pytest.mark.parametrize('at', [0, 1])  # the scales unset; set (and the first LS step)
def test_an_undone_cl_bcls_step_leaves_the_state_it_found(settings, at):
    y, u = paper_loop()
    undo_against_restart(make_cl_bcls(**settings), y, u, at, unsound_once, settle=1)


@contextlib.contextmanager
def non_finite_update_once(est):
    """Make the next RLS update of a cl_bcls step look non-finite to its check."""
    saved = running_ls.update_is_safe, running_ls.all_finite
    running_ls.update_is_safe = lambda *args: False
    running_ls.all_finite = lambda *vectors: False
    try:
        yield
    finally:
        running_ls.update_is_safe, running_ls.all_finite = saved


@pytest.mark.parametrize('settings', WINDOWS)
def test_a_plain_cl_bcls_step_checks_its_update_before_committing_it(settings):
    # Between redesigns the step checks the RLS update itself and refuses the sample before
    # anything is committed, as it does a non-finite error: the sample still counts in
    # ``samples`` (it was processed), nothing else differs from skipping it.
    y, u = paper_loop()
    make = make_cl_bcls(**settings)
    at = first_redesign_after(make, y, u, 300) + 50
    undo_against_restart(make, y, u, at, non_finite_update_once, skip=('samples',), settle=1)


# ------------------------------------------------------------------- the checks
def test_all_finite_tells_nan_and_inf_from_an_overflowing_sum():
    assert all_finite(np.array([1.0, -2.0]), np.zeros(0), np.array([3.0]))
    # finite values whose sum overflows are finite: the exact test decides
    assert all_finite(np.array([1.7e308, 1.7e308]), np.array([-1.7e308]))
    for bad in (np.nan, np.inf, -np.inf):
        assert not all_finite(np.array([1.0, bad]), np.array([2.0]))
        assert not all_finite(np.array([1.0]), np.array([bad, -bad]))


def test_update_is_safe_is_conservative():
    theta, step = np.array([1.0, -2.0]), np.array([3.0, 4.0])
    assert update_is_safe(theta, step, 1e100)
    assert not update_is_safe(theta, step, 1e160)  # |step| 5e160: it might overflow
    with np.errstate(over='ignore'):  # (theta' theta overflows: that is why it says no)
        assert not update_is_safe(np.array([1e160, 0.0]), step, 1.0)
    assert not update_is_safe(theta, np.array([np.nan, 0.0]), 1.0)
    assert not update_is_safe(theta, step, np.inf)
