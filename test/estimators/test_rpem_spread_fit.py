"""
rpem's fits are spread over the updates (rpem/store.py, FitJob).

Each update does at most a slice of a fit's work (store.SLICE sample-columns of its passes,
counted, not timed), or one pass larger than it; the fit is taken at the update where its
last pass ends, its predictor run on over the samples stored since. So the hand-off comes
a few to tens of samples after the fit was due, the same in every run, and a snapshot taken
while a fit is on its way continues bit for bit.
"""

from __future__ import annotations

import numpy as np

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.rpem import BATCH_LIMIT, store
from test_rpem import fit_schedule, oe_data


def fit_samples(estimator, y, u):
    """Return the sample counts at which the estimator's fit count grew."""
    counts, fits = [], estimator.fits
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
        if estimator.fits != fits:
            counts.append(t + 1)
            fits = estimator.fits
    return counts


def run_to_a_fit_due(estimator, y, u, start):
    """Feed ``start`` samples, then on to the first whose update starts a fit; return the next."""
    estimator.run(y[:start], u[:start])
    t = start
    while estimator._store.job is None or estimator._store.job.done:
        estimator.update(y[t], u[t])
        t += 1
    return t


def logged_passes(monkeypatch):
    """Return a list that gets, per update with a fit on its way, the costs of its passes."""
    updates = []
    steps, advance = store.FitJob.steps, store.FitJob.advance

    def announced(job, batch):
        job.announced = []  # every pass's cost, as steps announced it
        inner = steps(job, batch)
        while True:
            try:
                cost = next(inner)
            except StopIteration as end:
                return end.value
            job.announced.append(cost)
            yield cost

    def counted(job, batch, amount):
        before = job.done
        ended = advance(job, batch, amount)
        # the passes run: those whose costs took the work done from `before` to job.done
        ran = np.searchsorted(np.cumsum(job.announced), [before, job.done], side='right')
        updates.append(job.announced[ran[0]:ran[1]])
        return ended

    monkeypatch.setattr(store.FitJob, 'steps', announced)
    monkeypatch.setattr(store.FitJob, 'advance', counted)
    return updates


def test_each_fit_is_taken_tens_of_samples_after_it_is_due(monkeypatch):
    y, u = oe_data(8, count=BATCH_LIMIT)
    updates = logged_passes(monkeypatch)
    taken = fit_samples(make_estimator('rpem', order=2), y, u)
    due = fit_schedule(50, BATCH_LIMIT)
    assert len(taken) == len(due)
    delays = np.array(taken) - np.array(due)
    # a fit of k samples is some 60-160 passes: over k / 400 updates at SLICE work each
    assert (delays >= 1).all() and (delays <= 64).all() and delays[-1] >= 5
    # no update did more counted work than a slice, or than its one pass
    assert all(passes for passes in updates)
    assert all(sum(passes) <= store.SLICE or len(passes) == 1 for passes in updates)
    assert max(len(passes) for passes in updates) > 1


def test_a_snapshot_while_a_fit_is_on_its_way_continues_bit_for_bit():
    y, u = oe_data(3, count=4500)
    estimator = make_estimator('rpem', order=2, forgetting_factor=0.999)
    estimator.run(y[:4375], u[:4375])  # the fit due at 4373 is on its way
    snapshot = estimator.get_state()
    assert snapshot.scalars['job_count'] > 0 and snapshot.scalars['job_done'] > 0
    first = estimator.run(y[4375:], u[4375:]).theta
    restored = make_estimator('rpem', order=2, forgetting_factor=0.999)
    restored.set_state(snapshot)
    np.testing.assert_array_equal(restored.run(y[4375:], u[4375:]).theta, first)
    assert restored.fits == estimator.fits


def test_a_snapshot_at_any_pass_of_a_fit_continues_bit_for_bit():
    # the fit's own passes, then those of the HACs of its scores (store.FitJob._uncertainty)
    # and the hand-off: a restored job runs them again to the same point
    y, u = oe_data(5, count=3000)
    estimator = make_estimator('rpem', order=2, forgetting_factor=0.999)
    t = run_to_a_fit_due(estimator, y, u, 2000)
    job = estimator._store.job
    snapshots = []
    while estimator._store.job is job:
        snapshots.append((t, estimator.get_state()))
        estimator.update(y[t], u[t])
        t += 1
    assert len(snapshots) >= 4
    first = estimator.run(y[t:], u[t:])
    for at, snapshot in snapshots[1::max(len(snapshots) // 4, 1)] + snapshots[-2:]:
        restored = make_estimator('rpem', order=2, forgetting_factor=0.999)
        restored.set_state(snapshot)
        continued = restored.run(y[at:], u[at:])
        np.testing.assert_array_equal(continued.theta[t - at:], first.theta)
        np.testing.assert_array_equal(restored.parameter_covariance,
                                      estimator.parameter_covariance)
        assert restored.fits == estimator.fits


def test_a_live_forgetting_factor_reaches_the_hac_a_fit_hands_over():
    # the job records the fit's scores in a HAC of its own, with the factor in force when it
    # was due; a live change while it is on its way must reach the HAC the recursion goes on
    # with, as it reaches the one it replaces
    y, u = oe_data(6, count=3000)
    estimator = make_estimator('rpem', order=2, forgetting_factor=0.999)
    t = run_to_a_fit_due(estimator, y, u, 2000)
    fits = estimator.fits
    estimator.forgetting_factor = 0.995
    while estimator.fits == fits:
        estimator.update(y[t], u[t])
        t += 1
    assert estimator._hac.forgetting_factor == 0.995
