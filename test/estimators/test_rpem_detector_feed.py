"""
What rpem feeds its change detector at an operating point (``detrend: mean``).

Each fit centres its samples on the running means of the moment it starts; the recursion
goes on in that frame, so the errors fed to the detector are those of the fitted model,
mean 0 like the fit's residuals (its reference). Centred on the running means of each
sample's own time instead, a slow plant at a high SNR fed errors whose mean moved by tens
of standard errors over 150 samples early in the record, and the detector flagged plants
that never changed (docs/tracking_log.md, "Limits and what is left").
"""

import dataclasses

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators import make_estimator

#: Window of fed errors whose mean is tested, and the stretch of the record tested (after
#: the fit of about 700 samples, where the running means still move).
WINDOW = 150
STRETCH = (700, 2200)


def slow_plant_at_an_operating_point(seed, count=3000):
    """Return (y, u): poles 0.95 and 0.9, white input, white noise 40 dB, point (20, 3)."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(count)
    x = signal.lfilter([0.0, 0.05, 0.04], np.poly([0.95, 0.9]), u)
    y = x + 0.01 * x.std() * rng.standard_normal(count)
    return y + 20.0, u + 3.0


def fed_errors(estimator, y, u):
    """Run ``estimator`` over the record; return (sample count, error) of each fed error."""
    fed = []
    record = estimator._detector.record

    def recorded(error):
        fed.append((estimator.samples, error))
        return record(error)

    estimator._detector.record = recorded
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
    return np.array(fed)


@pytest.mark.parametrize('seed', [0, 1])
def test_the_errors_fed_at_an_operating_point_are_centred_like_the_fits_residuals(seed):
    y, u = slow_plant_at_an_operating_point(seed)
    estimator = make_estimator('rpem', order=2, detrend='mean')
    fed = fed_errors(estimator, y, u)
    inside = (fed[:, 0] > STRETCH[0]) & (fed[:, 0] <= STRETCH[1])
    errors = fed[inside, 1]
    windows = errors[:errors.shape[0] // WINDOW * WINDOW].reshape(-1, WINDOW)
    assert windows.shape[0] >= 9
    # each window's mean in standard errors: N(0, 1) for white errors of mean 0 (the
    # model is right, the noise white); the mean square of 9-10 of them is chi2 over its
    # degrees of freedom, above 4 with probability < 1e-4 (the running frame: 397 and 325)
    z = windows.mean(axis=1) / windows.std(axis=1) * np.sqrt(WINDOW)
    assert np.mean(z * z) < 4.0
    # the running frame flagged a change on both seeds (1 and 3 times); the detector's
    # false-alarm bound is 1e-5 per sample, 0.03 over the 2900 samples fed
    assert estimator.flags.get('plant_change', 0) == 0
    assert estimator.valid


def test_the_operating_point_lies_on_the_plants_static_line():
    y, u = slow_plant_at_an_operating_point(2)
    estimator = make_estimator('rpem', order=2, detrend='mean')
    estimator.run(y, u)
    y0, u0 = estimator.operating_point
    # G(1) = 0.09 / (0.05 * 0.1) = 18: the model's point lies on y0 - 20 = 18 (u0 - 3); an
    # error of 1 % in G(1) at |u0 - 3| < 0.1 moves it by less than 0.02
    assert abs(y0 - 20.0 - 18.0 * (u0 - 3.0)) < 0.05


def test_the_fits_frame_is_kept_in_the_state():
    y, u = slow_plant_at_an_operating_point(3)
    half = 1200  # after the fit of about 700 samples, before the next
    estimator = make_estimator('rpem', order=2, detrend='mean')
    estimator.run(y[:half], u[:half])
    state = estimator.get_state()
    restored = make_estimator('rpem', order=2, detrend='mean')
    restored.set_state(state)
    # a snapshot from before the frame was kept loads with the running means as its frame
    old = make_estimator('rpem', order=2, detrend='mean')
    old.set_state(dataclasses.replace(state, arrays={
        key: value for key, value in state.arrays.items() if key != 'fit_mean'}))
    np.testing.assert_array_equal(old.get_state().arrays['fit_mean'],
                                  state.arrays['operating_point'])
    for each in (estimator, restored):
        each.run(y[half:], u[half:])
    # save and restore: one code path, the same bits
    np.testing.assert_array_equal(restored.theta, estimator.theta)
    np.testing.assert_array_equal(restored.operating_point, estimator.operating_point)


def slow_stationary_plant(seed, count=6000):
    """Return (y, u): poles 0.994, 0.993, 0.972, white input, white noise at 17 dB."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(count)
    a = np.poly([0.99401641, 0.99289754, 0.97230473])
    x = signal.lfilter([0.0, 1.41e-5, -3.75e-6, 1.20e-5], a, u)
    x /= x.std()
    return x + 10.0 ** (-17.0 / 20.0) * rng.standard_normal(count), u


def fed_after_fits(estimator, y, u):
    """Run ``estimator``; per fit: residuals' size, mean square, errors fed, detections after."""
    detector = estimator._detector
    prime, record = detector.prime, detector.record
    fits, fed = [], []

    def primed(residuals, row=0):
        residuals = np.asarray(residuals)
        fits.append((estimator.samples, residuals.size, float(np.mean(residuals[-1024:] ** 2)),
                     estimator.flags.get('plant_change', 0)))
        return prime(residuals, row)

    def recorded(error):
        fed.append((estimator.samples, error))
        return record(error)

    detector.prime, detector.record = primed, recorded
    estimator.run(y, u)
    fed = np.array(fed)
    out = []
    changes = [fit[3] for fit in fits[1:]] + [estimator.flags.get('plant_change', 0)]
    for k, (at, size, mean_square, detected) in enumerate(fits):
        end = fits[k + 1][0] if k + 1 < len(fits) else y.shape[0]
        inside = (fed[:, 0] > at) & (fed[:, 0] <= end)
        out.append((size, mean_square, fed[inside, 1], changes[k] - detected))
    return out


@pytest.mark.parametrize('seed', range(4))
def test_the_errors_fed_under_forgetting_are_those_the_fits_residuals_describe(seed):
    # lambda 0.999 on a slow third-order plant: the recursion's estimate leaves the fit
    # between fits (its errors' mean square up to 2.3 times the fit's residuals' on these
    # seeds, 6 false plant_change on seed 1); the errors of the fit's model, fed instead,
    # are the process its residuals describe
    y, u = slow_stationary_plant(seed)
    estimator = make_estimator('rpem', order=3, forgetting_factor=0.999)
    fits = fed_after_fits(estimator, y, u)
    ratios = [float(np.mean(errors ** 2)) / mean_square
              for size, mean_square, errors, _ in fits
              if size >= 1000 and errors.shape[0] >= 200]
    assert len(ratios) >= 3
    # the mean square of >= 200 white errors over their variance: standard deviation
    # sqrt(2 / 200) = 0.1 (the reference's own error is smaller): 1.5 is 5 of them
    assert max(ratios) < 1.5
    # the bound is 1e-5 per sample: no detection after a fit of 1000 samples or more; fits
    # of a few hundred samples, whose own error their residuals do not count, may still
    # raise one, and its memory cut brings such fits again (docs/tracking_log.md; on seeds 0-15
    # 4 and 7 detections, before and after rpem's OE lags under forgetting followed the
    # step, every one after a fit of 463-569 samples)
    assert all(detections == 0 for size, _, _, detections in fits if size >= 1000)


def test_a_recursion_that_leaves_its_fit_restarts_from_a_refit_not_a_plant_change():
    y, u = slow_plant_at_an_operating_point(4, count=4000)
    estimator = make_estimator('rpem', order=2, detrend='mean')
    estimator.run(y[:2500], u[:2500])
    assert estimator._settled and estimator.fits >= 1
    assert estimator.flags.get('restarted', 0) == 0
    # the recursion's estimate moved off its fit by hand (the plant did not change): its
    # errors grow, those of the fit's model do not
    estimator._theta_n[:2] = np.poly([0.9, 0.85])[1:]
    estimator.run(y[2500:2700], u[2500:2700])
    assert estimator.flags.get('restarted', 0) == 1
    assert estimator.flags.get('plant_change', 0) == 0
    estimator.run(y[2700:], u[2700:])
    assert estimator.flags.get('plant_change', 0) == 0
    assert np.linalg.norm(estimator.theta[:2] - np.poly([0.95, 0.9])[1:]) < 0.05


def test_a_snapshot_from_before_the_fit_models_feed_loads():
    y, u = slow_stationary_plant(5, count=3000)
    estimator = make_estimator('rpem', order=3, forgetting_factor=0.999)
    estimator.run(y[:2000], u[:2000])
    state = estimator.get_state()
    assert {'feed_theta', 'feed_history', 'change_left_fit_weight'} <= set(state.arrays)
    old = make_estimator('rpem', order=3, forgetting_factor=0.999)
    # from before: the estimate stands for the fit's model, the recursion's lags for its
    old.set_state(dataclasses.replace(
        state, arrays={key: value for key, value in state.arrays.items()
                       if not key.startswith(('feed_', 'change_left_fit_'))},
        scalars={key: value for key, value in state.scalars.items()
                 if not key.startswith('feed_')}))
    np.testing.assert_array_equal(old.get_state().arrays['feed_theta'], state.arrays['theta_n'])
    old.run(y[2000:], u[2000:])
    assert np.isfinite(old.theta).all()
