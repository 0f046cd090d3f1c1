"""
rpem's fits are spread over the updates (rpem/store.py, FitJob).

Each update does at most a slice of a fit's work (store.SLICE sample-columns of its passes,
counted, not timed); the fit is taken at the update where its last pass ends, its
predictor run on over the samples stored since. So the hand-off comes a few to tens of
samples after the fit was due, the same in every run, and a snapshot taken while a fit is
on its way continues bit for bit.
"""

from __future__ import annotations

import numpy as np

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.rpem import BATCH_LIMIT, store
from bcid_ros.estimators.rpem.fit import PASS_COST
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


def test_each_fit_is_taken_tens_of_samples_after_it_is_due(monkeypatch):
    y, u = oe_data(8, count=BATCH_LIMIT)
    work = []
    advance = store.FitJob.advance

    def counted(job, batch, amount):
        before = job.done
        ended = advance(job, batch, amount)
        work.append(job.done - before)
        return ended

    monkeypatch.setattr(store.FitJob, 'advance', counted)
    taken = fit_samples(make_estimator('rpem', order=2), y, u)
    due = fit_schedule(50, BATCH_LIMIT)
    assert len(taken) == len(due)
    delays = np.array(taken) - np.array(due)
    # a fit of k samples is some 60-160 passes: over k / 400 updates at SLICE work each
    assert (delays >= 1).all() and (delays <= 64).all() and delays[-1] >= 5
    # no update did more than a slice and the pass that ran over it (the largest: a
    # gradient over every stored sample, 2 (p + 1) columns)
    assert max(work) <= store.SLICE + 2 * (4 + 1) * BATCH_LIMIT + PASS_COST


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
