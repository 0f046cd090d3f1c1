"""The restart after a detected plant change, its replay spread over the updates (rls, bcrls)."""

import dataclasses
import types

import numpy as np
import pytest
from test_tracking import changing_plant, run as feed

from bcid_ros.estimators import make_estimator
from bcid_ros.identifier import persistence
from bcid_ros.estimators.rls import REPLAY_SLICE, RESTART_SPAN

#: (estimator, equation-error noise, the plant after): changes small enough to be found
#: hundreds of samples after (seed 1: rls queues all 400 kept samples, bcrls 187), so that
#: the replay takes several slices
CASES = [('rls', True, ([1.0, -1.5, 0.7], [0.0, 1.2, 0.6])),
         ('bcrls', False, ([1.0, -1.45, 0.65], [0.0, 1.1, 0.55]))]


def to_detection(name, equation, after, seed=1):
    """Run to the first detection of the changing plant; return the estimator, data and t."""
    y, u, _ = changing_plant(seed, samples=5000, equation=equation, after=after)
    estimator = make_estimator(name, order=2)
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
        if estimator.flags.get('plant_change', 0):
            return estimator, y, u, t
    raise AssertionError('no detection')


def same_state(first, second):
    """Assert two snapshots are the same bits (a NaN scalar equals a NaN read from a file)."""
    assert first.arrays.keys() == second.arrays.keys()
    for key, value in first.arrays.items():
        np.testing.assert_array_equal(value, second.arrays[key], err_msg=key)
    np.testing.assert_equal(first.scalars, second.scalars)


def copy_of(estimator, name, path=None):
    """Return a twin of the estimator from its snapshot (through a state file at ``path``)."""
    twin = make_estimator(name, order=2)
    if path is None:
        twin.set_state(estimator.get_state())
        return twin
    fingerprint = persistence.configuration_fingerprint({'estimator': name})
    persistence.save_state(path, fingerprint,
                           {'estimator': persistence.estimator_section(estimator)})
    section = persistence.load_state(path, fingerprint)['estimator']
    persistence.check_values(section, persistence.estimator_section(twin), 'estimator')
    persistence.restore_estimator(twin, section)
    return twin


def one_shot_restart(self, age):
    """Restart as before the spread: the kept rows after the change point replayed at once."""
    self._flag('plant_change')
    first = self._seen - age + 1
    count = min(age + self._regressor.span, RESTART_SPAN, self._seen)
    rows = self._recent[np.arange(self._seen - count, self._seen) % RESTART_SPAN].copy()
    theta, scale = self._theta_ls.copy(), self._signal_scale.copy()
    flags, quiet, recent, updates, seen = (dict(self.flags), self._quiet_left, self._recent,
                                           self._updates, self._seen)
    self._reset()
    self._signal_scale = scale
    self._set_scale_dependents()
    self._p = self._initial_p()
    self._theta_ls[:] = theta
    self._relearned += 1
    self._quiet_left = 0
    with np.errstate(all='ignore'):
        for row in rows:
            self._step_sample(float(row[0]), row[1:])
    self.flags, self._quiet_left, self._recent = flags, quiet, recent
    self._updates, self._seen = updates, seen
    self._change_note = f'plant changed (sample {first})'
    self._check_validity()


@pytest.mark.parametrize('name, equation, plant', CASES)
def test_the_caught_up_estimate_is_the_one_shot_replay_bit_for_bit(name, equation, plant):
    # the same samples into an estimator whose restart replays the rows at once, as before
    # the spread: once caught up, the spread one is the same bits, and the flags the same
    spread, y, u, t = to_detection(name, equation, plant)
    assert spread.catching_up > 2 * REPLAY_SLICE  # the change point, the regressor's span
    one_shot = make_estimator(name, order=2)
    one_shot._plant_changed = types.MethodType(one_shot_restart, one_shot)
    feed(one_shot, y[:t + 1], u[:t + 1])
    assert one_shot.flags['plant_change'] == 1
    later = slice(t + 1, t + 200)
    feed(one_shot, y[later], u[later])
    feed(spread, y[later], u[later])
    assert not spread.catching_up
    same_state(one_shot.get_state(), spread.get_state())
    assert one_shot.flags == spread.flags  # the replay's own flags are not the updates'
    # replayed at once by the estimator itself (the batched plants' restart): the same
    at_once, _, _, _ = to_detection(name, equation, plant)
    at_once._finish_catch_up()
    feed(at_once, y[later], u[later])
    same_state(one_shot.get_state(), at_once.get_state())


@pytest.mark.parametrize('name, equation, plant', CASES)
def test_no_update_replays_more_than_a_slice_and_valid_is_false_while_catching_up(
        name, equation, plant):
    estimator, y, u, t = to_detection(name, equation, plant)
    note = estimator.validity_reasons[0]
    assert note.startswith('plant changed (sample ') and not estimator.valid
    # published until caught up: the detection's estimate, not one of a few replayed rows
    shown = estimator.theta, estimator.theta_uncompensated, estimator.noise
    steps = []
    step = estimator._step_sample

    def counted(*sample):
        steps[-1] += 1
        step(*sample)

    estimator._step_sample = counted
    updates = 0
    while estimator.catching_up:
        steps.append(0)
        updates += 1
        t += 1
        valid = estimator.update(y[t], u[t])
        if estimator.catching_up:  # (once caught up, valid is the one-shot replay's)
            assert not valid and estimator.validity_reasons[0] == note
            for before, now in zip(shown, (estimator.theta, estimator.theta_uncompensated,
                                           estimator.noise)):
                np.testing.assert_array_equal(before, now)
        assert estimator.flags['plant_change'] == 1  # on the detection's sample only
    # each update: its slice, then its own sample once the queue is empty
    assert max(steps) <= REPLAY_SLICE + 1
    assert 400 // REPLAY_SLICE <= updates <= 20


@pytest.mark.parametrize('name, equation, plant', CASES)
@pytest.mark.parametrize('after, through_file', [(1, False), (4, False), (4, True)])
def test_a_snapshot_mid_catch_up_goes_on_bit_for_bit(
        name, equation, plant, after, through_file, tmp_path):
    estimator, y, u, t = to_detection(name, equation, plant)
    feed(estimator, y[t + 1:t + 1 + after], u[t + 1:t + 1 + after])
    assert estimator.catching_up
    restored = copy_of(estimator, name, tmp_path / 'state.npz' if through_file else None)
    same_state(estimator.get_state(), restored.get_state())
    later = slice(t + 1 + after, t + 300)
    valid, reasons = feed(estimator, y[later], u[later])
    valid_restored, reasons_restored = feed(restored, y[later], u[later])
    np.testing.assert_array_equal(valid, valid_restored)
    assert reasons == reasons_restored
    same_state(estimator.get_state(), restored.get_state())


@pytest.mark.parametrize('name, equation, plant', CASES)
def test_a_gap_held_samples_and_blocks_during_the_catch_up_keep_their_place_among_the_rows(
        name, equation, plant):
    # a gap (restart_regressor) and samples taken while the adaptation is held, queued
    # behind the rows, are those after the one-shot replay; a block is its samples one by one
    spread, y, u, t = to_detection(name, equation, plant)
    one_shot = copy_of(spread, name)
    one_shot._finish_catch_up()
    for estimator in (one_shot, spread):
        estimator.update(y[t + 1], u[t + 1])
        estimator.restart_regressor()
        estimator.adapt = False
        for s in range(t + 2, t + 5):
            estimator.update(y[s], u[s])
        estimator.adapt = True
        estimator.update_block(np.column_stack([y[t + 5:t + 100], u[t + 5:t + 100]]))
    assert not spread.catching_up
    same_state(one_shot.get_state(), spread.get_state())


def test_an_inconsistent_replay_snapshot_is_refused():
    """A snapshot whose queue cannot hold the restart's rows and their end is refused, not run."""
    estimator, _, _, _ = to_detection(*CASES[0])
    state = estimator.get_state()
    queued = state.scalars['replay_queued']
    assert queued > state.scalars['restart_left'] > 0  # mid-catch-up, as written
    for bad in ({'restart_left': queued}, {'replay_queued': 10 ** 6}):
        twin = make_estimator('rls', order=2)
        with pytest.raises(ValueError, match='restart replay state'):
            twin.set_state(dataclasses.replace(state, scalars={**state.scalars, **bad}))
