"""
The interface contract, run by every registered estimator and its batched form.

The names come from the registry (registry_cases.py picks the data by model
kind), so a new estimator runs all of this with no edit here. Each check is
one code path run twice, so it asserts bit equality.
"""

import numpy as np
import pytest
from registry_cases import BATCHED_NAMES, data, make, NAMES

from bcid_ros.estimators import make_batched_estimator
from bcid_ros.identifier.feeder import SampleFeeder


def same_state(first, second, leave=()):
    assert first.estimator == second.estimator
    assert first.arrays.keys() == second.arrays.keys()
    for key, value in first.arrays.items():
        if key not in leave:
            np.testing.assert_array_equal(value, second.arrays[key], err_msg=key)
    assert ({key: value for key, value in first.scalars.items() if key not in leave}
            == {key: value for key, value in second.scalars.items() if key not in leave})


def same_run(first, second):
    np.testing.assert_array_equal(first.theta, second.theta)
    np.testing.assert_array_equal(first.theta_uncompensated, second.theta_uncompensated)
    np.testing.assert_array_equal(first.noise, second.noise)
    np.testing.assert_array_equal(first.valid, second.valid)
    np.testing.assert_array_equal(first.ready, second.ready)


def feed_blocks(est, y, u, size):
    """Feed (y, u) in checked blocks of ``size`` rows, the estimator's block path."""
    rows = np.column_stack([y, u])
    for first in range(0, len(y), size):
        assert est.update_block(rows[first:first + size]) == len(rows[first:first + size])


@pytest.mark.parametrize('name', NAMES)
def test_state_round_trip(name):
    y, u = data(name)
    half = len(y) // 2
    est = make(name)
    est.run(y[:half], u[:half])
    state = est.get_state()
    restored = make(name)
    restored.set_state(state)
    same_state(state, restored.get_state())
    same_run(est.run(y[half:], u[half:]), restored.run(y[half:], u[half:]))
    assert est.flags == restored.flags
    assert est.validity_reasons == restored.validity_reasons


@pytest.mark.parametrize('name', NAMES)
def test_reset_returns_to_the_constructed_state(name):
    y, u = data(name)
    est = make(name)
    first = est.run(y, u)
    est.reset()
    same_state(make(name).get_state(), est.get_state())
    same_run(first, est.run(y, u))


@pytest.mark.parametrize('name', NAMES)
def test_bad_input_is_refused_and_changes_nothing(name):
    y, u = data(name)
    est = make(name)
    est.run(y[:300], u[:300])
    before = est.get_state()
    bad_u = u[300].copy()
    bad_u[0] = np.inf
    for sample in ((np.nan, u[300]), (y[300], bad_u), (y[300], np.append(u[300], 0.0)),
                   (y[300], u[300][:0])):
        with pytest.raises(ValueError):
            est.update(*sample)
    same_state(before, est.get_state())


@pytest.mark.parametrize('name', NAMES)
def test_blocks_equal_sample_by_sample(name):
    y, u = data(name)
    looped, blocked = make(name), make(name)
    end = len(y) - 200
    looped.run(y[:end], u[:end])
    feed_blocks(blocked, y[:end], u[:end], 64)
    same_state(looped.get_state(), blocked.get_state())
    # the same samples in the ring, whatever its rotation: the same estimates after
    same_run(looped.run(y[end:], u[end:]), blocked.run(y[end:], u[end:]))


@pytest.mark.parametrize('name', NAMES)
def test_replay_equals_the_update_loop(name):
    y, u = data(name)
    count = 20
    size = len(y) // count * count
    looped, replayed = make(name), make(name)
    trajectory = looped.run(y[:size], u[:size])
    feeder = SampleFeeder(replayed, publish_period=count)
    result = feeder.take_messages(np.column_stack([y[:size], u[:size]]), count)
    assert result.used == size and not result.failures
    same_state(looped.get_state(), replayed.get_state())
    # what it publishes is the estimate after each message once ready
    for index, (theta, _, _) in zip(result.published, result.estimates):
        np.testing.assert_array_equal(theta, trajectory.theta[(index + 1) * count - 1])
    assert len(result.published) == int(trajectory.ready[count - 1::count].sum())


@pytest.mark.parametrize('name', NAMES)
def test_live_settings_equal_settings_given_at_construction(name):
    y, u = data(name)
    for setting, value in (('outlier_threshold', 4.0), ('forgetting_factor', 0.995)):
        try:
            built = make(name, **{setting: value})
        except ValueError:  # a setting the estimator's configuration refuses
            continue
        changed = make(name)
        setattr(changed, setting, value)
        same_run(built.run(y, u), changed.run(y, u))
        same_state(built.get_state(), changed.get_state())


@pytest.mark.parametrize('name', NAMES)
def test_held_adaptation_keeps_what_was_learnt(name):
    y, u = data(name)
    est = make(name)
    est.run(y[:1200], u[:1200])
    theta, samples = est.theta, est.samples
    est.adapt = False
    held = est.run(y[1200:1500], u[1200:1500])
    np.testing.assert_array_equal(held.theta, np.broadcast_to(theta, held.theta.shape))
    assert est.samples == samples and est.held_samples == 300
    est.adapt = True
    est.run(y[1500:], u[1500:])
    assert est.samples > samples


def plants_data(name, plants=3):
    """Return (y ``(N, K)``, u ``(N, K, r)``): the case's data scaled differently per plant."""
    y, u = data(name)
    scale = 2.0 ** np.arange(plants)
    return y[:, None] * scale, u[:, None, :] * scale[:, None]


def make_plants(name, plants=3, **changes):
    y, u = data(name)
    return make_batched_estimator(name, plants, order=2, num_inputs=u.shape[1], **changes)


def run_plants(batched, y, u):
    valid = np.array([batched.update(y[t], u[t]) for t in range(len(y))])
    return batched.theta, valid


@pytest.mark.parametrize('name', BATCHED_NAMES)
def test_batched_state_round_trip_per_plant(name):
    y, u = plants_data(name)
    half = len(y) // 2
    batched = make_plants(name)
    run_plants(batched, y[:half], u[:half])
    moved = make_plants(name)
    for k in range(batched.num_plants):
        moved.set_plant_state(k, batched.plant_state(k))
        same_state(batched.plant_state(k), moved.plant_state(k))
    first, second = run_plants(batched, y[half:], u[half:]), run_plants(moved, y[half:], u[half:])
    np.testing.assert_array_equal(first[0], second[0])
    np.testing.assert_array_equal(first[1], second[1])


@pytest.mark.parametrize('name', BATCHED_NAMES)
def test_batched_reset_and_live_settings(name):
    y, u = plants_data(name)
    batched = make_plants(name)
    first = run_plants(batched, y, u)
    batched.reset()
    again = run_plants(batched, y, u)
    np.testing.assert_array_equal(first[0], again[0])
    built = make_plants(name, forgetting_factor=0.995)
    changed = make_plants(name)
    changed.forgetting_factor = 0.995
    np.testing.assert_array_equal(run_plants(built, y, u)[0], run_plants(changed, y, u)[0])


@pytest.mark.parametrize('name', BATCHED_NAMES)
def test_batched_bad_sample_stays_with_its_plant(name):
    y, u = plants_data(name)
    batched = make_plants(name)
    run_plants(batched, y[:300], u[:300])
    bad = y[300].copy()
    bad[1] = np.nan
    batched.update(bad, u[300])
    assert batched.nonfinite.tolist() == [0, 1, 0]
    with pytest.raises(ValueError):
        batched.update(y[301][:2], u[301])
    run_plants(batched, y[301:], u[301:])
    assert np.isfinite(batched.theta).all()
