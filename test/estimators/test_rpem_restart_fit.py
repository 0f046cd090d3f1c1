"""
rpem's fits after a plant change: a segment that starts mid-response (rpem/fit.py).

The samples after a change point begin where the old plant left its output, not at rest.
The searches of a fit shrink each segment's initial state towards 0 (INITIAL_PRIOR, which
keeps a level out of the offset), and that charges such a segment for its true state: the
ends of the searches are compared with the state free (docs/tracking_log.md, session 8), and
where those losses do not tell them apart the current estimate's end stays (session 9).
After a change the searches themselves run with the state free (session 11); the fit
the recursion continues with, and its std, keep the prior.
"""

import numpy as np
from scipy import signal

from benchmarks.tracking import reference, run_estimator, TrackingCase, within_reference
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.residual_statistics import chi2_quantile
from bcid_ros.estimators.rpem.fit import BatchFit
from bcid_ros.estimators.rpem.segment import SegmentPredictor
from bcid_ros.estimators.rpem.uncertainty import UNRESOLVED_LEVEL

BEFORE, AFTER = 3000, 135
OLD_POLES, NEW_POLES = (0.989, 0.97, 0.25), (0.989, 0.97, 0.10)


def changed_plant(seed):
    """
    Return (y, u, old theta, new theta, noise) of AFTER samples after a pole's change.

    Tracking plant (2, 0)'s form: third order, two slow poles, a multisine of 20 lines,
    35 dB; the plant runs on from the old one's state. Unit output before the change.
    """
    rng = np.random.default_rng(seed)
    count = BEFORE + AFTER
    frequencies = rng.uniform(0.002 * np.pi, 0.2 * np.pi, 20)
    u = np.sin(np.outer(np.arange(count), frequencies) + rng.uniform(0, 2 * np.pi, 20)).sum(1)
    u /= u.std()
    b = np.array([-0.074, 0.131, -0.042])
    old, new = np.real(np.poly(OLD_POLES)), np.real(np.poly(NEW_POLES))
    drive = signal.lfilter(np.r_[0.0, b], [1.0], u)
    w = np.zeros(count)
    for t in range(count):  # F(q) w = B(q) u with F switching at the change
        f = old if t < BEFORE else new
        w[t] = drive[t] - sum(f[k] * w[t - k] for k in range(1, 4) if t >= k)
    size = w[:BEFORE].std()
    noise = 10.0 ** (-35.0 / 20.0) * rng.standard_normal(count)
    y = w / size + noise
    after = slice(BEFORE, count)
    return (y[after], u[after, None], np.concatenate((old[1:], b / size)),
            np.concatenate((new[1:], b / size)), noise[after])


def test_the_truth_of_a_segment_cut_mid_response_costs_less_with_its_state_free():
    """
    At the new plant, the loss with the state free is at most the noise's (an exact bound).

    The free state x minimises sum eps^2, so the loss is no higher than at the true state:
    the sum of the noise's squares. The searches' prior charges the true state (|w| ~ 1
    against a noise of 0.018): more than twice that.
    """
    y, u, _, theta, noise = changed_plant(0)
    predictor = SegmentPredictor(3, 1, False, (0,), armax=False, offset=False)
    weights = np.ones(y.shape[0])
    free = predictor.predict(theta, y, u, weights, gradient=False, prior=0.0).eps
    shrunk = predictor.predict(theta, y, u, weights, gradient=False).eps
    bound = float(noise[predictor.span:] @ noise[predictor.span:])
    assert float(free @ free) <= bound * (1.0 + 1e-9)
    assert float(shrunk @ shrunk) > 2.0 * bound


def test_a_fit_after_a_change_lands_near_the_new_plant():
    """
    The fit of 135 samples after the change, started from the old plant: median error.

    Over ten seeds, the ends in the truth's basin are 2-24 % off, the other minima of the
    third-order loss 60-110 %; the median separates the two at 30 %. With the ends compared
    by the searches' loss the median was 63 % (the other minima won on 6 of 10), with the
    state free 20 %.
    """
    batch = BatchFit(3, 1, False, (0,), armax=False, offset=False)
    errors = []
    for seed in range(10):
        y, u, old, new, _ = changed_plant(seed)
        result = batch.fit([(y, u, np.ones(y.shape[0]))], [old], 1e-6, after_change=True)
        errors.append(np.linalg.norm(result.theta - new) / np.linalg.norm(new))
    assert np.median(errors) < 0.3, np.round(errors, 3)


def free_state_decrement(theta, y, u):
    """
    Return the loss a Gauss-Newton step of the loss with the state free would still remove.

    Over the loss itself: psi projected off the initial state's free responses (the loss
    concentrated on theta, Kaufman's variable projection), d = g^T H^-1 g with g = psi^T eps
    and H = psi^T psi; 0 at a minimum.
    """
    predictor = SegmentPredictor(3, 1, False, (0,), armax=False, offset=False)
    prediction = predictor.predict(theta, y, u, np.ones(y.shape[0]), prior=0.0)
    nuisance = prediction.nuisance
    psi = prediction.psi - nuisance @ np.linalg.lstsq(nuisance, prediction.psi, rcond=None)[0]
    gradient = psi.T @ prediction.eps
    decrement = float(gradient @ np.linalg.solve(psi.T @ psi, gradient))
    return decrement / float(prediction.eps @ prediction.eps)


def test_the_searches_after_a_change_minimise_the_loss_with_the_state_free():
    """
    The fit after a change ends where the loss with each segment's state free is least.

    The searches once shrank the state towards 0 after a change too (INITIAL_PRIOR): their
    end was the minimum of that criterion, not of the one the ends are compared by, and a
    step of the free loss from it still removed 1e-5 to 0.9 of the loss on seeds 0-5
    (tracking drift (2, 19), 2250 samples after its change: the end 40 % off, where the
    search with the state free from it ends 1.7 % off and the batch OE fit of the same
    window 0.4 %). Free, the searches stop within 5e-8 of it on these seeds (LM_TOLERANCE:
    1e-10 of the loss a step).
    """
    batch = BatchFit(3, 1, False, (0,), armax=False, offset=False)
    for seed in range(6):
        y, u, old, _, _ = changed_plant(seed)
        result = batch.fit([(y, u, np.ones(y.shape[0]))], [old], 1e-6, after_change=True)
        assert free_state_decrement(result.theta, y, u) < 1e-6, seed


def test_a_snapshot_while_a_fit_after_a_change_is_on_its_way_continues_bit_for_bit():
    """The job keeps that its samples follow a change: restored, the same passes and ends."""
    case = TrackingCase((2, 0), 'family')
    y, u = case.y[:case.change_at + 400], case.u[:case.change_at + 400]
    estimator = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    first = estimator.run(y, u).theta
    estimator = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    for t in range(y.shape[0]):
        estimator.update(float(y[t]), u[t])
        snapshot = estimator.get_state()
        if estimator.flags.get('plant_change', 0) and snapshot.scalars['job_done'] > 0:
            break
    assert snapshot.scalars['job_after_change']
    restored = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    restored.set_state(snapshot)
    np.testing.assert_array_equal(restored.run(y[t + 1:], u[t + 1:]).theta, first[t + 1:])
    estimator.run(y[t + 1:], u[t + 1:])
    assert restored.fits == estimator.fits


def test_ends_the_data_do_not_tell_apart_keep_the_current_estimates_first():
    """
    The ends ranked by loss only where the likelihood ratio exceeds its 95 % quantile.

    N = 200 unit weights, p = 6: the limit is chi2_6(0.95) = 12.6, a loss ratio of 1.063.
    The first end (the current estimate's search) stays first at a ratio of 1.05; at 1.08
    the lower one goes first; with forgetting N is the weight and the limit shrinks by
    tau_2 / tau.
    """
    batch = BatchFit(3, 1, False, (0,), armax=False, offset=False)
    count = 200 + batch.span
    usable = [(np.zeros(count), np.zeros((count, 1)), np.ones(count), None)]
    limit = chi2_quantile(UNRESOLVED_LEVEL, batch.num_parameters) / 200
    current, other = np.full(6, 0.1), np.full(6, 0.2)
    tied = [(current, 1.05), (other, 1.0)]
    assert [loss for _, loss in batch._ranked(tied, usable)] == [1.05, 1.0]
    apart = [(current, 1.0 + limit + 0.02), (other, 1.0)]
    assert batch._ranked(apart, usable)[0][0] is other
    # weights 0.99^k: N = tau = 86.6, tau_2 / tau = 0.50; a loss ratio of 1.10 gives 8.7,
    # beyond 12.6 tau_2 / tau = 6.3 (not beyond 12.6 alone)
    weights = 0.99 ** np.arange(count)[::-1]
    forgetting = [(usable[0][0], usable[0][1], weights, None)]
    tau, tau_2 = weights[batch.span:].sum(), weights[batch.span:] @ weights[batch.span:]
    chi2 = limit * 200
    assert chi2 * tau_2 / tau < tau * 0.10 < chi2
    tied = [(current, 1.10), (other, 1.0)]
    assert batch._ranked(tied, forgetting)[0][0] is other


def test_a_fit_after_a_change_keeps_its_basin_where_the_data_do_not_tell():
    """
    Tracking plant (0, 5) (gain x1.98, third order, coloured noise): recovered within 5x.

    311 samples after its change the fit's two ends were 0.35 % apart in loss (statistic
    1.1 against 12.6): the lower took the end 35 % off over the current estimate's 12 %, at
    the edge of the band (twice the delta before the change, 37 %), and the recursion from
    it left the band until 420 samples after, where the windowed batch reference is in it
    after 40. Keeping the current estimate's end: 95.
    """
    case = TrackingCase((0, 5), 'family')
    ours, ref = run_estimator(case, 'rpem')['recovery'], reference(case)['recovery']
    assert within_reference(ours, ref), (ours, ref)
