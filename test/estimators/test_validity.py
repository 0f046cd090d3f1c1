"""`valid` has one home (validity.py): every registered estimator, one plant and K, decides it."""

import inspect

import numpy as np
import pytest
from registry_cases import BATCHED_NAMES, data, make, NAMES

from bcid_ros.estimators import make_batched_estimator, validity
from bcid_ros.estimators.registry import batched_class, estimator_class


def registered_classes():
    for name in NAMES:
        yield estimator_class(name)
        if name in BATCHED_NAMES:
            yield batched_class(name)


def test_no_estimator_decides_valid_itself():
    for cls in registered_classes():
        for owner in inspect.getmro(cls):
            if owner.__module__ == validity.__name__ or owner is object:
                continue
            # the decision and its reasons live in validity.py; an estimator gives its own reasons
            assert not {'valid', 'validity_reasons', '_validity_reasons'} & set(vars(owner)), (
                f'{owner.__module__}.{owner.__name__} decides valid itself')


def same_state(first, second):
    assert first.estimator == second.estimator
    assert first.arrays.keys() == second.arrays.keys()
    for key, value in first.arrays.items():
        np.testing.assert_array_equal(value, second.arrays[key], err_msg=key)
    assert first.scalars == second.scalars


@pytest.mark.parametrize('name', NAMES)
def test_asking_for_validity_changes_nothing(name):
    est = make(name)
    y, u = data(name)
    est.run(y, u)
    before = est.get_state()
    for _ in range(3):
        assert est.valid == (est.ready and not est.validity_reasons)
    same_state(before, est.get_state())


@pytest.mark.parametrize('name', NAMES)
def test_the_decision_joins_the_estimators_reasons_to_the_shared_ones(name):
    est = make(name)
    y, u = data(name)
    est.run(y, u)
    assert est.ready
    before = est.get_state()
    est._decide_validity(['an own reason'])
    # its reasons first, then the residual tests' (for an estimator that keeps them)
    expected = tuple(validity.decided_reasons(['an own reason'], est._monitor))
    assert est.validity_reasons[:len(expected)] == expected
    assert not est.valid
    after = est.get_state()
    # nothing but the reasons changed, and the simulation check's verdict where the decision
    # ran it (rpem judges its window at every decision)
    decided = {'reasons', 'simulation_since', 'simulation_statistic', 'simulation_reason',
               'simulation_coverage_reason', 'simulation_judged'}
    assert {key: value for key, value in after.scalars.items() if key not in decided} == {
        key: value for key, value in before.scalars.items() if key not in decided}
    for key, value in before.arrays.items():
        np.testing.assert_array_equal(value, after.arrays[key], err_msg=key)


@pytest.mark.parametrize('name', BATCHED_NAMES)
def test_many_plants_decide_as_one(name):
    y, u = data(name)
    settings = {'order': 2, 'num_inputs': u.shape[1]}
    batched = make_batched_estimator(name, 2, **settings)
    stacked_y, stacked_u = np.stack([y, 0.5 * y], axis=1), np.stack([u, 0.5 * u], axis=1)
    for t in range(400):
        batched.update(stacked_y[t], stacked_u[t])
    batched._decide_validity(np.array([1]), [['an own reason']])
    assert batched.plant_validity_reasons(1)[0] == 'an own reason'
    np.testing.assert_array_equal(batched.valid, batched.ready & [
        not batched.plant_validity_reasons(k) for k in range(2)])
    assert not batched.valid[1]


class ShortRecordMonitor:
    """The residual tests of one plant or K, ready or judging a short record with no reason."""

    def __init__(self, ready):
        self.ready = ready
        self.reasons = []

    def short_reasons(self, plant=None):
        return ()

    def reasons_of(self, plant):
        return []

    def ready_of(self, plant):
        return self.ready[plant]


@pytest.mark.parametrize('plant', [None, 1])
def test_a_plant_change_holds_until_the_tests_are_ready_on_new_samples_with_nothing_else(plant):
    change = 'plant changed (sample 4001)'
    ready = [True, True] if plant is not None else True
    waiting = [True, False] if plant is not None else False
    # a short-record verdict with no reason does not end the change: the tests are not ready
    assert validity.decided_after_change([], change, ShortRecordMonitor(waiting), plant) == (
        [change], change)
    # another reason keeps it too, first among them
    assert validity.decided_after_change(['unstable model'], change, ShortRecordMonitor(ready),
                                         plant) == ([change, 'unstable model'], change)
    # ready again and nothing else wrong: the change is done, and so is its reason
    assert validity.decided_after_change([], change, ShortRecordMonitor(ready), plant) == (
        [], '')
    assert validity.decided_after_change(['unstable model'], '', ShortRecordMonitor(ready),
                                         plant) == (['unstable model'], '')
