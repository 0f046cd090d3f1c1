"""
The plant axis of the residual monitor and the HAC covariance: K plants that step apart.

In a batched estimator a plant does not record when its sample is missing, refused, or its
regressor refills, and it starts after its own warm-up. Each plant of a K-plant monitor (HAC)
fed through ``record_rows`` must take the decisions of one single-plant monitor (HAC) fed that
plant's samples, exactly, and give its statistics (covariances) within the rounding bound of
``test/equivalence.py``; one changed sample must break that bound.
"""

import dataclasses

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators.adequacy import AdequacyMonitor, BLOCK
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.lagged import BLOCK as HAC_BLOCK
from equivalence import assert_paths_agree, rounding_spread

PLANTS = 4
SAMPLES = 3000
WINDOW = 250
#: plant 3 restarts here (a reset of that plant alone)
RESTART = 2000


def recording_masks(rng, samples, plants):
    """
    Return which plants record at each time, ``(samples, plants)`` bools.

    Plant 0 records every sample; plant 1 misses 10 % at random (missing, refused); plant 2
    starts after a warm-up of 300 and refills its regressor over 1500-1700; plant 3 misses
    every 7th sample. All record over the first 200 samples but plant 2 (its warm-up), and all
    over 2200-2400, so that the counts of the blocks part and meet again.
    """
    mask = np.ones((samples, plants), dtype=bool)
    mask[:, 1] = rng.random(samples) > 0.1
    mask[:300, 2] = False
    mask[1500:1700, 2] = False
    mask[::7, 3] = False
    mask[2200:2400] = True
    return mask


def rows_at(mask, t):
    """Return the plants that record at t: a slice when all do (the fast path), else indices."""
    if mask[t].all() and t % 5:
        return slice(None)
    return np.flatnonzero(mask[t])  # every fifth time all plants as indices: the general path


def monitor_data(rng, samples):
    """
    Return residuals ``(N, K)`` and inputs ``(N, K, 2)`` of four plants.

    Plants 0 and 2 are white, plant 1 coloured, plant 3 correlated with u2 at lag 2, so that
    some plants are in alarm with reasons.
    """
    inputs = signal.lfilter([1.0], [1.0, -0.8], rng.standard_normal((samples, PLANTS, 2)), axis=0)
    residual = rng.standard_normal((samples, PLANTS))
    residual[:, 1] = signal.lfilter([1.0], [1.0, -0.3], residual[:, 1])
    residual[2:, 3] += 0.3 * inputs[:-2, 3, 1]
    return residual, inputs


#: The length p of the gradients of the parameter term ('oe_term').
TERM = 3


def term_data(inputs):
    """
    Return gradients ``(N, K, p)`` and a covariance C ``(K, p, p)`` per plant (the term).

    The gradients are filtered and lagged inputs plus noise, as an OE model's psi; plant 2's
    C is NaN (unknown: tested without the term), the others differ in size.
    """
    rng = np.random.default_rng(56)
    gradients = np.stack([signal.lfilter([0.0, 1.0], [1.0, -0.5], inputs[:, :, 0], axis=0),
                          np.roll(inputs[:, :, 1], 2, axis=0),
                          rng.standard_normal(inputs.shape[:2])], axis=2)
    covariance = np.array([(k + 1) * 1e-3 * np.eye(TERM) + 2e-4 for k in range(PLANTS)])
    covariance[2] = np.nan
    return gradients, covariance


def monitor_settings(model, covariance, plant=None):
    """
    Return the monitor's settings: 'oe_term' is 'oe' with the parameter term.

    'oe_white_term' is 'oe_white' with its settling term (C read at every block).
    """
    if not model.endswith('_term'):
        return {'model': model}
    base = model[:-len('_term')]
    if plant is None:  # K plants: the rows asked for
        return {'model': base, 'num_parameters': TERM,
                'parameter_covariance': lambda rows: covariance[rows]}
    return {'model': base, 'num_parameters': TERM,
            'parameter_covariance': lambda rows: covariance[plant]}


def run_singles(residual, inputs, mask, model='arx', gradients=None, covariance=None):
    """
    Feed one single-plant monitor per plant its own samples; return its record over time.

    The statistics ``(N, K, T)`` after each sample and the decisions: alarms, reasons,
    readiness and check counts after each sample.
    """
    def single(k):
        return AdequacyMonitor(num_inputs=2, window=WINDOW,
                               **monitor_settings(model, covariance, k))

    monitors = [single(k) for k in range(PLANTS)]
    statistics = np.full((residual.shape[0], PLANTS, monitors[0].num_tests), np.nan)
    decisions = []
    for t in range(residual.shape[0]):
        if t == RESTART:
            monitors[3] = single(3)
        for k in np.flatnonzero(mask[t]):
            monitors[k].record(float(residual[t, k]), inputs[t, k],
                               None if gradients is None else gradients[t, k])
        statistics[t] = [monitor.statistics for monitor in monitors]
        decisions.append(([m.alarm for m in monitors], [m.reasons for m in monitors],
                          [m.ready for m in monitors], [m.checks for m in monitors]))
    return statistics, decisions, monitors


def run_batch(residual, inputs, mask, model='arx', gradients=None, covariance=None):
    """Feed a K-plant monitor through record_rows; return the record of :func:`run_singles`."""
    monitor = AdequacyMonitor(num_inputs=2, window=WINDOW, plants=PLANTS,
                              **monitor_settings(model, covariance))
    statistics = np.full((residual.shape[0], PLANTS, monitor.num_tests), np.nan)
    decisions = []
    for t in range(residual.shape[0]):
        if t == RESTART:
            monitor.clear(np.array([3]))
        rows = rows_at(mask, t)
        monitor.record_rows(rows, residual[t, rows], inputs[t, rows],
                            None if gradients is None else gradients[t, rows])
        statistics[t] = monitor.statistics
        decisions.append((monitor.alarm.tolist(), monitor.reasons, monitor.ready.tolist(),
                          monitor.checks.tolist()))
    return statistics, decisions, monitor


@pytest.mark.parametrize('model', ['arx', 'oe', 'oe_term'])
def test_each_plant_of_a_batch_decides_as_a_single_monitor_fed_its_samples(model):
    rng = np.random.default_rng(51)
    residual, inputs = monitor_data(rng, SAMPLES)
    mask = recording_masks(rng, SAMPLES, PLANTS)
    gradients, covariance = term_data(inputs) if model == 'oe_term' else (None, None)
    term = {'model': model, 'gradients': gradients, 'covariance': covariance}
    expected, decisions, singles = run_singles(residual, inputs, mask, **term)
    actual, batch_decisions, batch = run_batch(residual, inputs, mask, **term)
    # the decisions after every sample, exactly: alarms, reasons, ready, checks
    for t, (mine, theirs) in enumerate(zip(batch_decisions, decisions)):
        assert mine == theirs, t
    # the plants check at their own times: the counts differ between plants
    assert len(set(batch.checks.tolist())) > 2 and batch.checks.min() >= 5
    # plant 1's coloured residual fails the whiteness test ('oe' has none), plant 3 names u2
    assert batch.alarm[1] == (model == 'arx')
    assert 'residual correlated with u2 at lag 2' in ' '.join(batch.reasons_of(3))
    if model == 'oe_term':  # the term lowers Q of the plants with a C, not of plant 2
        plain = run_batch(residual, inputs, mask, model='oe')[0][-1]
        assert (actual[-1][[0, 1, 3]] < plain[[0, 1, 3]]).all()
        np.testing.assert_array_equal(actual[-1][2], plain[2])
    # the statistics after every sample, within the bound of two arithmetic paths

    def compute(residual, inputs):
        return {'statistics': run_singles(residual, inputs, mask, **term)[0]}

    spread = rounding_spread(compute, residual, inputs)
    assert_paths_agree({'statistics': actual}, {'statistics': expected}, spread, SAMPLES,
                       f'monitor {model}')
    # one changed sample of plant 1 (recorded at 2500) breaks the bound
    assert mask[2500, 1]
    changed = residual.copy()
    changed[2500, 1] += 0.5
    with pytest.raises(AssertionError, match='times the bound'):
        assert_paths_agree({'statistics': run_batch(changed, inputs, mask, **term)[0]},
                           {'statistics': expected}, spread, SAMPLES, 'changed')


@pytest.mark.parametrize('model', ['arx', 'oe_term', 'oe_white_term'])
def test_a_plant_moves_out_to_a_single_monitor_and_back(model):
    rng = np.random.default_rng(52)
    residual, inputs = monitor_data(rng, SAMPLES)
    mask = recording_masks(rng, SAMPLES, PLANTS)
    gradients, covariance = term_data(inputs)
    covariance[2] = 1e-3  # plant 2 moves: with a term
    if not model.endswith('_term'):
        gradients = None
    moved, back = 1100, 1900  # plant 2 is in its warm-up gap part of the way
    single_samples = np.flatnonzero(mask[:, 2])

    def single_monitor():
        return AdequacyMonitor(num_inputs=2, window=WINDOW,
                               **monitor_settings(model, covariance, 2))

    def gradient(t, rows):
        return None if gradients is None else gradients[t, rows]

    def compute(residual, inputs):
        single = single_monitor()
        for t in single_samples:
            single.record(float(residual[t, 2]), inputs[t, 2], gradient(t, 2))
        return {'statistics': single.statistics, 'single': single}

    reference = compute(residual, inputs)
    batch = AdequacyMonitor(num_inputs=2, window=WINDOW, plants=PLANTS,
                            **monitor_settings(model, covariance))
    single = single_monitor()
    for t in range(SAMPLES):
        if t == moved:
            state = batch.plant_state(2)
            assert state.pending is None and state.pending_residuals.shape[1] == 1
            single.set_state(state)
        if t == back:
            batch.load_plant(2, single.get_state())
        recording = mask[t].copy()
        if moved <= t < back:  # plant 2 lives in the single monitor meanwhile
            if recording[2]:
                single.record(float(residual[t, 2]), inputs[t, 2], gradient(t, 2))
            recording[2] = False
        rows = np.flatnonzero(recording)
        batch.record_rows(rows, residual[t, rows], inputs[t, rows], gradient(t, rows))
    expected = reference['single']
    assert batch.reasons_of(2) == expected.reasons and batch.alarm[2] == expected.alarm
    assert batch.checks[2] == expected.checks
    spread = rounding_spread(lambda *data: {'statistics': compute(*data)['statistics']},
                             residual, inputs)
    assert_paths_agree({'statistics': batch.statistics[2]},
                       {'statistics': expected.statistics}, spread, SAMPLES, 'moved')


@pytest.mark.parametrize('model', ['arx', 'oe_term', 'oe_white_term'])
def test_a_plant_state_has_the_form_of_a_single_monitors(model):
    rng = np.random.default_rng(53)
    residual, inputs = monitor_data(rng, 1000)
    mask = recording_masks(rng, 1000, PLANTS)
    gradients, covariance = term_data(inputs)
    batch = AdequacyMonitor(num_inputs=2, window=WINDOW, plants=PLANTS,
                            **monitor_settings(model, covariance))
    single = AdequacyMonitor(num_inputs=2, window=WINDOW,
                             **monitor_settings(model, covariance, 1))
    for t in range(1000):
        rows = np.flatnonzero(mask[t])
        batch.record_rows(rows, residual[t, rows], inputs[t, rows], gradients[t, rows])
        if mask[t, 1]:
            single.record(float(residual[t, 1]), inputs[t, 1], gradients[t, 1])
    mine, theirs = batch.plant_state(1), single.get_state()
    for field in dataclasses.fields(theirs):
        value, expected = getattr(mine, field.name), getattr(theirs, field.name)
        assert np.shape(value) == np.shape(expected), field.name
    # the pending samples, weights, alarms and counts are copies, not sums: equal exactly
    np.testing.assert_array_equal(mine.pending_residuals, theirs.pending_residuals)
    np.testing.assert_array_equal(mine.pending_inputs, theirs.pending_inputs)
    assert mine.weights == theirs.weights and mine.checks == theirs.checks
    np.testing.assert_array_equal(mine.alarms, theirs.alarms)
    history = batch._history
    np.testing.assert_array_equal(mine.ring[:, :history], theirs.ring[:, :history])
    if model.endswith('_term'):
        np.testing.assert_array_equal(mine.pending_gradients, theirs.pending_gradients)
        q = batch._gradient_history
        np.testing.assert_array_equal(mine.gradient_ring[:, :q], theirs.gradient_ring[:, :q])


@pytest.mark.parametrize('model', ['oe', 'oe_term', 'oe_white_term'])
def test_a_batch_restored_with_uneven_cursors_continues_bit_for_bit(model):
    rng = np.random.default_rng(54)
    residual, inputs = monitor_data(rng, SAMPLES)
    mask = recording_masks(rng, SAMPLES, PLANTS)
    gradients, covariance = term_data(inputs)
    first, second = (AdequacyMonitor(num_inputs=2, window=WINDOW, plants=PLANTS,
                                     **monitor_settings(model, covariance)) for _ in range(2))
    for t in range(SAMPLES):
        if t == 1234:
            assert len(set(first._cursors.counts().tolist())) > 1
            second.set_state(first.get_state())
        rows = rows_at(mask, t)
        first.record_rows(rows, residual[t, rows], inputs[t, rows], gradients[t, rows])
        if t >= 1234:
            second.record_rows(rows, residual[t, rows], inputs[t, rows], gradients[t, rows])
    np.testing.assert_array_equal(first.statistics, second.statistics)
    np.testing.assert_array_equal(first.checks, second.checks)
    assert first.reasons == second.reasons


def test_a_batch_state_with_shared_pending_samples_still_loads():
    """A K-plant state of the shared block timing (no per-plant counts) continues the same."""
    rng = np.random.default_rng(55)
    residual, inputs = monitor_data(rng, 1000)
    first = AdequacyMonitor(num_inputs=2, window=WINDOW, plants=PLANTS)
    for t in range(3 * BLOCK + 40):
        first.record(residual[t], inputs[t])
    state = first.get_state()
    history, count = first._history, 40
    pending = state.ring[:, history:history + count]
    shared = dataclasses.replace(
        state, pending=None, weights=(float(state.weights[0][0]), float(state.weights[1][0])),
        checks=int(state.checks[0]), pending_residuals=pending[:, :, 0].T.copy(),
        pending_inputs=np.swapaxes(pending[:, :, 1:], 0, 1).copy())
    second = AdequacyMonitor(num_inputs=2, window=WINDOW, plants=PLANTS)
    second.set_state(shared)
    for t in range(3 * BLOCK + 40, 1000):
        first.record(residual[t], inputs[t])
        second.record(residual[t], inputs[t])
    np.testing.assert_array_equal(first.statistics, second.statistics)
    np.testing.assert_array_equal(first.checks, second.checks)


# ------------------------------------------------------------------ the HAC
HAC_READS = range(0, SAMPLES, 50)


def hac_data(rng):
    """Return coloured scores ``(N, K, p)`` and a bread P ``(K, p, p)`` per plant."""
    scores = signal.lfilter([1.0], [1.0, -0.7], rng.standard_normal((SAMPLES, PLANTS, 4)),
                            axis=0)
    bread = np.linalg.inv(np.einsum('tkp,tkq->kpq', scores[:400], scores[:400]))
    return scores, bread


def run_single_hacs(scores, bread, mask, lam):
    """Feed one single-plant HAC per plant its own scores; read them every 50 samples."""
    hacs = [HacCovariance(dimension=4, forgetting_factor=lam) for _ in range(PLANTS)]
    covariances, bandwidths, known = [], [], []
    for t in range(SAMPLES):
        if t == RESTART:
            hacs[3] = HacCovariance(dimension=4, forgetting_factor=lam)
        for k in np.flatnonzero(mask[t]):
            hacs[k].record(scores[t, k])
        if t in HAC_READS:
            found = [hac.covariance(bread[k]) for k, hac in enumerate(hacs)]
            known.append([value is not None for value in found])
            covariances.append([np.full((4, 4), np.nan) if value is None else value
                                for value in found])
            bandwidths.append([np.nan if value is None else hac.bandwidths
                               for value, hac in zip(found, hacs)])
    return np.array(covariances), np.array(bandwidths), np.array(known), hacs


def run_batch_hac(scores, bread, mask, lam):
    """Feed a K-plant HAC through record_rows; return the record of :func:`run_single_hacs`."""
    hac = HacCovariance(dimension=4, forgetting_factor=lam, plants=PLANTS)
    covariances, bandwidths, known = [], [], []
    for t in range(SAMPLES):
        if t == RESTART:
            hac.clear(np.array([3]))
        rows = rows_at(mask, t)
        hac.record_rows(rows, scores[t, rows])
        if t in HAC_READS:
            covariance = hac.covariance(bread)
            covariances.append(covariance)
            bandwidths.append(hac.bandwidths)
            known.append(np.isfinite(covariance).all(axis=(1, 2)))
    return np.array(covariances), np.array(bandwidths), np.array(known), hac


@pytest.mark.parametrize('lam', [1.0, 0.998])
def test_each_plant_of_a_batch_hac_is_a_single_hac_fed_its_scores(lam):
    rng = np.random.default_rng(61)
    scores, bread = hac_data(rng)
    mask = recording_masks(rng, SAMPLES, PLANTS)
    expected, widths, known, singles = run_single_hacs(scores, bread, mask, lam)
    actual, batch_widths, batch_known, batch = run_batch_hac(scores, bread, mask, lam)
    # which plant has a covariance at each read (None: NaN in the batch), exactly
    np.testing.assert_array_equal(batch_known, known)
    assert not known[:3].all() and known[-1].all()
    np.testing.assert_array_equal(batch.samples, [hac.samples for hac in singles])

    def compute(scores):
        covariances, bandwidths = run_single_hacs(scores, bread, mask, lam)[:2]
        return {'covariance': covariances, 'bandwidth': bandwidths[..., None]}

    spread = rounding_spread(compute, scores)
    assert_paths_agree({'covariance': actual, 'bandwidth': batch_widths[..., None]},
                       {'covariance': expected, 'bandwidth': widths[..., None]}, spread,
                       SAMPLES, f'hac {lam}')
    changed = scores.copy()
    changed[2500, 0] *= 1.5  # plant 0 records every sample
    with pytest.raises(AssertionError, match='times the bound'):
        assert_paths_agree({'covariance': run_batch_hac(changed, bread, mask, lam)[0]},
                           {'covariance': expected}, spread, SAMPLES, 'changed')


def test_a_hac_plant_moves_out_to_a_single_hac_and_back():
    rng = np.random.default_rng(62)
    scores, bread = hac_data(rng)
    mask = recording_masks(rng, SAMPLES, PLANTS)
    moved, back = 1000 + HAC_BLOCK // 3, 2100

    def compute(scores):
        single = HacCovariance(dimension=4, forgetting_factor=0.999)
        for t in np.flatnonzero(mask[:, 1]):
            single.record(scores[t, 1])
        return {'covariance': single.covariance(bread[1])}

    batch = HacCovariance(dimension=4, forgetting_factor=0.999, plants=PLANTS)
    single = HacCovariance(dimension=4, forgetting_factor=0.999)
    for t in range(SAMPLES):
        if t == moved:
            single.set_state(batch.plant_state(1))
        if t == back:
            batch.load_plant(1, single.get_state())
        recording = mask[t].copy()
        if moved <= t < back:
            if recording[1]:
                single.record(scores[t, 1])
            recording[1] = False
        rows = np.flatnonzero(recording)
        batch.record_rows(rows, scores[t, rows])
    assert batch.samples[1] == mask[:, 1].sum()
    assert_paths_agree({'covariance': batch.covariance(bread)[1]}, compute(scores),
                       rounding_spread(compute, scores), SAMPLES, 'moved')


def test_a_batch_hac_restored_with_uneven_cursors_continues_bit_for_bit():
    rng = np.random.default_rng(63)
    scores, bread = hac_data(rng)
    mask = recording_masks(rng, SAMPLES, PLANTS)
    first = HacCovariance(dimension=4, plants=PLANTS)
    second = HacCovariance(dimension=4, plants=PLANTS)
    for t in range(SAMPLES):
        if t == 1234:
            second.set_state(first.get_state())
        rows = rows_at(mask, t)
        first.record_rows(rows, scores[t, rows])
        if t >= 1234:
            second.record_rows(rows, scores[t, rows])
    np.testing.assert_array_equal(first.covariance(bread), second.covariance(bread))
