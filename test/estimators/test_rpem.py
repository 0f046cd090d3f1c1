"""
The recursive prediction-error estimator ``rpem`` (OE and ARMAX).

Statistical tolerances come from the Monte Carlo standard error of the mean
over the seeds, or from the estimate's own standard deviation where the
noise is white (its covariance assumes white prediction errors); each says
which in a comment.
"""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy import signal, stats

from bcid_ros.analysis.pem import fit_oe, Structure
from bcid_ros.analysis.realistic import realistic_case
from bcid_ros.identifier import persistence
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.polynomials import is_stable
from bcid_ros.estimators.rpem import (BATCH_LIMIT, FIT_GROWTH, PredictorHistory, pull_inside,
                                      REGION_MARGIN, Rpem, STABILITY_RADIUS)
from bcid_ros.identifier.parameters import check_identifier_parameters, estimator_from_parameters

#: The OE plant of most tests: F = 1 - 1.5 q^-1 + 0.7 q^-2, B = q^-1 + 0.5 q^-2.
F = [1.0, -1.5, 0.7]
B = [0.0, 1.0, 0.5]
TRUTH = np.array([-1.5, 0.7, 1.0, 0.5])


def oe_data(seed, count=3000, noise_pole=0.9, noise_std=0.5):
    """Return (y, u) of the OE plant with AR(1)-coloured output noise (white for pole 0)."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(count)
    v = signal.lfilter([1.0], [1.0, -noise_pole], rng.standard_normal(count))
    return signal.lfilter(B, F, u) + noise_std * v / v.std(), u


def roots_inside(theta, order, model):
    """Whether the published F (OE) or A and C (ARMAX) have every root within the radius."""
    polynomials = [theta[:order]] + ([theta[-order:]] if model == 'armax' else [])
    return all(np.abs(np.roots(np.concatenate(([1.0], a)))).max() < STABILITY_RADIUS + 1e-12
               for a in polynomials)


def test_consistent_with_coloured_noise_where_rls_is_biased():
    seeds = range(8)
    estimates = {'rpem': [], 'rls': []}
    for seed in seeds:
        y, u = oe_data(seed)
        for name in estimates:
            estimator = make_estimator(name, order=2)
            estimator.run(y, u)
            estimates[name].append(estimator.theta)
    rpem = np.array(estimates['rpem'])
    rls = np.array(estimates['rls'])
    # bias of the mean within 4 Monte Carlo standard errors of the mean (spread / sqrt(M))
    standard_error = rpem.std(axis=0, ddof=1) / np.sqrt(len(seeds))
    assert (np.abs(rpem.mean(axis=0) - TRUTH) < 4 * standard_error).all()
    # rls on the same data: its bias is many of its own standard errors
    rls_error = rls.std(axis=0, ddof=1) / np.sqrt(len(seeds))
    assert (np.abs(rls.mean(axis=0) - TRUTH) > 10 * rls_error).any()


def armax_data(seed, count=4000):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(count)
    e = 0.5 * rng.standard_normal(count)
    return signal.lfilter(B, F, u) + signal.lfilter([1.0, -0.5, 0.3], F, e), u


def test_armax_recovers_a_b_c_and_its_std_is_calibrated():
    truth = np.concatenate((TRUTH, [-0.5, 0.3]))
    estimates, stds = [], []
    for seed in range(8):
        estimator = make_estimator('rpem', order=2, model='armax')
        estimator.run(*armax_data(seed))
        assert estimator.parameter_names == ('a1', 'a2', 'b1_1', 'b1_2', 'c1', 'c2')
        assert estimator.noise_names == ('sigma2',)
        estimates.append(estimator.theta)
        stds.append(estimator.parameter_std)
        # the innovation variance 0.25 within 4 of its standard errors (2 sigma^4 / N)
        assert abs(estimator.noise[0] - 0.25) < 4 * 0.25 * np.sqrt(2 / 4000)
    estimates = np.array(estimates)
    spread = estimates.std(axis=0, ddof=1)
    # bias within 4 Monte Carlo standard errors of the mean
    assert (np.abs(estimates.mean(axis=0) - truth) < 4 * spread / np.sqrt(8)).all()
    # the mean reported std against the spread of 8 runs: 7 s^2 / sigma^2 is chi2(7), so a
    # calibrated std lies within these bounds of the spread with probability 0.999 each
    low, high = np.sqrt(stats.chi2.ppf([0.0005, 0.9995], 7) / 7)
    ratio = np.mean(stds, axis=0) / spread
    assert ((ratio > 1 / high) & (ratio < 1 / low)).all()


def test_miso_with_per_input_delays_and_their_names():
    rng = np.random.default_rng(4)
    count = 4000
    u = rng.standard_normal((count, 2))
    shifted = np.column_stack([np.concatenate((np.zeros(1), u[:-1, 0])),
                               np.concatenate((np.zeros(3), u[:-3, 1]))])
    y = (signal.lfilter(B, F, shifted[:, 0]) + signal.lfilter([0.0, -0.4, 0.3], F, shifted[:, 1])
         + 0.3 * rng.standard_normal(count))
    estimator = make_estimator('rpem', order=2, num_inputs=2, input_delay=[1, 3])
    estimator.run(y, u)
    assert estimator.parameter_names == ('a1', 'a2', 'b1_2', 'b1_3', 'b2_4', 'b2_5')
    truth = np.array([-1.5, 0.7, 1.0, 0.5, -0.4, 0.3])
    # white noise: the own std is calibrated; 4 std per parameter (6e-5 each to fail)
    assert (np.abs(estimator.theta - truth) < 4 * estimator.parameter_std).all()
    assert estimator.valid


@pytest.mark.parametrize('model', ['oe', 'armax'])
def test_feedthrough_and_an_operating_point(model):
    rng = np.random.default_rng(12)
    u = rng.standard_normal(4000)
    y = signal.lfilter([0.4, 1.0, 0.5], F, u) + 0.1 * rng.standard_normal(4000)
    estimator = make_estimator('rpem', order=2, feedthrough=True, model=model, detrend='mean')
    estimator.run(y + 2.0, u + 1.0)
    assert estimator.parameter_names[:5] == ('a1', 'a2', 'b1_0', 'b1_1', 'b1_2')
    truth = np.array([-1.5, 0.7, 0.4, 1.0, 0.5])
    # white output noise: for OE the own std is calibrated (4 std per parameter); ARMAX
    # fits C = A for it, its a and b have the same std
    assert (np.abs(estimator.theta[:5] - truth) < 4 * estimator.parameter_std[:5]).all()
    # the model's operating point lies on the plant's: y0 - 2 = G(1) (u0 - 1), G(1) = 9.5;
    # over seeds 12-19 this gap spread by 0.004 (std), so 0.03 is 7 of its std
    y0, u0 = estimator.operating_point
    assert abs(y0 - 2.0 - 9.5 * (u0 - 1.0)) < 0.03


def test_oversampled_plant_with_held_prbs():
    # poles 0.99 and 0.95, a PRBS held for 10 samples, white noise at about 25 dB SNR
    rng = np.random.default_rng(6)
    count = 6000
    u = np.repeat(rng.choice([-1.0, 1.0], count // 10), 10)
    f = np.poly([0.99, 0.95])
    b = [0.0, 0.01, 0.008]
    x = signal.lfilter(b, f, u)
    y = x + 0.05 * x.std() * rng.standard_normal(count)
    estimator = make_estimator('rpem', order=2)
    estimator.run(y, u)
    truth = np.concatenate((f[1:], b[1:]))
    # white noise: 4 own std per parameter
    assert (np.abs(estimator.theta - truth) < 4 * estimator.parameter_std).all()
    rls = make_estimator('bcrls', order=2)
    rls.run(y, u)
    delta = np.linalg.norm(estimator.theta - truth) / np.linalg.norm(truth)
    assert delta < np.linalg.norm(rls.theta - truth) / np.linalg.norm(truth)


def hostile_cases():
    rng = np.random.default_rng(5)
    count = 3000
    u = rng.standard_normal(count)
    v = 0.1 * rng.standard_normal(count)
    y1 = signal.lfilter(B, F, u) + v
    y2 = signal.lfilter([0.0, -0.5, 0.3], [1.0, -0.6, 0.2], u) + v
    burst = y1.copy()
    burst[1500:1510] = 1e3
    burst[2500] = 1e150
    step = np.concatenate((np.zeros(500), np.ones(count - 500)))
    rest = np.concatenate((np.zeros(300), u[300:]))
    return {
        'plant change': (np.concatenate((y1[:1500], y2[1500:])), u),
        'burst': (burst, u),
        'step input': (signal.lfilter(B, F, step) + v, step),
        'at rest, then excited': (signal.lfilter(B, F, rest) + v, rest),
        'integrator': (signal.lfilter([0.0, 1.0], [1.0, -1.0], u) + v, u),
        'unstable plant': (signal.lfilter([0.0, 0.01], [1.0, -1.01], u), u),
        'noise only': (v, u),
        'all zero': (np.zeros(count), np.zeros(count)),
    }


@pytest.mark.parametrize('model', ['oe', 'armax'])
@pytest.mark.parametrize('case', list(hostile_cases()))
def test_never_publishes_an_unstable_or_diverged_model(case, model):
    y, u = hostile_cases()[case]
    for settings in ({}, {'forgetting_factor': 0.99, 'outlier_threshold': 5.0}):
        estimator = make_estimator('rpem', order=2, model=model, **settings)
        trajectory = estimator.run(y, u)
        published = trajectory.theta[trajectory.ready]
        assert published.shape[0] > 0
        assert np.isfinite(published).all()
        assert all(roots_inside(theta, 2, model) for theta in published)


def test_batch_and_recursion_keep_roots_inside():
    def inside(a):
        return is_stable(a, REGION_MARGIN)

    assert 1.0 - REGION_MARGIN == STABILITY_RADIUS
    assert inside(np.array([-1.5, 0.7])) and not inside(np.array([-2.0, 1.0]))
    assert not inside(np.array([0.0, 0.0, -0.9995]))  # a root at 0.9995^(1/3) > radius
    pulled = pull_inside(np.array([-2.5, 1.0]))  # roots 2 and 0.5
    assert np.abs(np.roots(np.concatenate(([1.0], pulled)))).max() < STABILITY_RADIUS
    assert inside(pulled)


def test_without_change_detection_a_change_is_not_restarted_from_but_not_valid():
    # the watch has no test of the size of the errors (a plant that changes is the
    # detector's): switched off, a change restarts nothing, the recursion and the fits
    # blend both plants, and the residual tests see it
    y, u = hostile_cases()['plant change']
    estimator = make_estimator('rpem', order=2, change_detection=False)
    reasons = []
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
        reasons.append(estimator.validity_reasons)
    assert 'restarted' not in estimator.flags and 'plant_change' not in estimator.flags
    after = np.array([-0.6, 0.2, -0.5, 0.3])
    wrong = np.linalg.norm(estimator.theta - after) > 0.1 * np.linalg.norm(after)
    assert wrong and not estimator.valid
    assert any(r.startswith('residual correlated with u1') for r in reasons[-1])


def test_a_plant_change_is_detected_and_the_fits_restart_after_it():
    # the defaults: the CUSUM sees the change, the estimate is not valid from that sample
    # on, and the fits take only the samples after the change point
    y, u = hostile_cases()['plant change']
    estimator = make_estimator('rpem', order=2)
    valid, reasons = [], []
    for t in range(y.shape[0]):
        valid.append(estimator.update(y[t], u[t]))
        reasons.append(estimator.validity_reasons)
    detected = [t for t, why in enumerate(reasons) if any('plant changed' in r for r in why)]
    assert estimator.flags['plant_change'] == 1 and 'restarted' not in estimator.flags
    first = detected[0]
    assert 1500 <= first <= 1530 and not valid[first]
    # the change point: sample 1501 (1-based) is the first of the new plant
    point = int(reasons[first][0].split('sample ')[1].rstrip(')'))
    assert abs(point - 1501) <= 5
    after = np.array([-0.6, 0.2, -0.5, 0.3])
    assert np.linalg.norm(estimator.theta - after) < 0.05 * np.linalg.norm(after)
    assert estimator.valid


def test_a_projection_stuck_at_the_boundary_is_not_valid():
    y, u = hostile_cases()['integrator']
    estimator = make_estimator('rpem', order=2)
    trajectory = estimator.run(y, u)
    assert estimator.flags['stability_projection'] > 1000
    assert trajectory.valid.mean() < 0.5
    assert any('stability projection active' in r for r in estimator.validity_reasons)


ROUND_TRIP_SETTINGS = [{}, {'detrend': 'mean', 'forgetting_factor': 0.995,
                            'outlier_threshold': 4.0, 'input_delay': 1}]


@pytest.mark.parametrize('model', ['oe', 'armax'])
@pytest.mark.parametrize('settings', ROUND_TRIP_SETTINGS)
def test_state_round_trip_is_bit_exact(model, settings, tmp_path):
    y, u = oe_data(9, count=3000)
    y = y + 4.0
    whole = make_estimator('rpem', order=2, model=model, **settings)
    whole.run(y, u)
    first = make_estimator('rpem', order=2, model=model, **settings)
    first.run(y[:1300], u[:1300])
    # through the state file: the scalars go through JSON, the arrays through npz
    values = check_identifier_parameters(dict(settings, estimator='rpem', model=model))
    fingerprint = persistence.configuration_fingerprint(values)
    path = Path(tmp_path) / 'state.npz'
    persistence.save_state(path, fingerprint,
                           {'estimator': persistence.estimator_section(first)})
    second = estimator_from_parameters(values)
    persistence.restore_estimator(second, persistence.load_state(path, fingerprint)['estimator'])
    for estimator in (first, second):
        estimator.run(y[1300:], u[1300:])
        np.testing.assert_array_equal(estimator.theta, whole.theta)
        np.testing.assert_array_equal(estimator.noise, whole.noise)
        np.testing.assert_array_equal(estimator.parameter_covariance,
                                      whole.parameter_covariance)
        np.testing.assert_array_equal(estimator.theta_uncompensated,
                                      whole.theta_uncompensated)
        assert estimator.flags == whole.flags and estimator.valid == whole.valid


def test_a_state_from_before_the_parameter_term_loads_and_keeps_the_estimate():
    y, u = oe_data(9, count=3000)
    whole = make_estimator('rpem', order=2)
    whole.run(y, u)
    first = make_estimator('rpem', order=2)
    first.run(y[:1300], u[:1300])
    state = first.get_state()
    old = {key: value for key, value in state.arrays.items() if 'gradient' not in key}
    assert len(old) == len(state.arrays) - 3  # the term's sums, ring and pending gradients
    second = make_estimator('rpem', order=2)
    second.set_state(dataclasses.replace(state, arrays=old))
    second.run(y[1300:], u[1300:])
    # the estimate does not read the monitor: bit for bit; the tests count the term from the
    # gradients recorded after the load, and this well-fitted plant stays valid
    np.testing.assert_array_equal(second.theta, whole.theta)
    assert second.valid and whole.valid


def run_case(case, order, delay, term=True):
    """Run rpem ('oe') sample by sample over a realistic case; return it."""
    estimator = make_estimator('rpem', order=order, num_inputs=case.num_inputs,
                               input_delay=delay, detrend=case.detrend)
    if not term:  # the plain cross test: no covariance, so no parameter term
        estimator._monitor._covariance_of = None
    for t in range(case.samples):
        estimator.update(float(case.y[t]), case.u[t])
    return estimator


def test_the_estimates_own_error_does_not_fail_an_accurate_fit_but_a_wrong_dead_time_does():
    # equation-error noise (A y = B u + e): the OE model's noise e/A is strongly coloured, and
    # at 32 dB the consistent (not efficient) OE estimate's own error correlates the residual
    # with u at lag 1 (-0.32): the plain test fails it, the parameter term explains it
    case = realistic_case((0, 45))
    assert case.noise == 'equation' and case.input_delay == (1,) and case.snr_db > 30.0
    low, high = AdequacyMonitor(num_inputs=1, model='oe').thresholds
    right = run_case(case, case.order, case.input_delay)
    error = np.linalg.norm(right.theta - case.theta) / np.linalg.norm(case.theta)
    plain = run_case(case, case.order, case.input_delay, term=False)
    np.testing.assert_array_equal(plain.theta, right.theta)  # the monitor does not steer
    assert error < 0.01 and right.valid and not plain.valid
    # margins, one deterministic run each: Q = 1.7 against the low threshold 23.2, the plain
    # Q = 205 against the high 27.1 (these figures on the reference machine)
    assert right._monitor.statistics[0] < low / 4.0
    assert plain._monitor.statistics[0] > 4.0 * high
    assert any('residual correlated with u1 at lag 1' in r for r in plain.validity_reasons)
    # a dead time one sample off either way: Q = 653 and 656, far above the high threshold
    for delay in (0, 2):
        wrong = run_case(case, case.order, (delay,))
        assert not wrong.valid and wrong._monitor.statistics[0] > 10.0 * high
        assert any(r.startswith('residual correlated with u1') for r in wrong.validity_reasons)


def test_the_std_after_the_batch_fits_is_the_batch_references():
    # held PRBS and equation-error noise at 34 dB: the prediction errors before each batch
    # fit are of the earlier, far estimates; recorded into the HAC they made the std 600
    # times the batch sandwich's (3.3 against 0.005 for a1). Both estimate one asymptotic
    # covariance; the HAC's relative error over ~4000 scores is a few tens of per cent, so a
    # factor of 2 either way holds it and catches any such swelling
    case = realistic_case((0, 13))
    estimator = run_case(case, case.order, case.input_delay)
    structure = Structure(order=case.order, num_inputs=case.num_inputs,
                          input_delay=list(case.input_delay))
    reference = fit_oe(case.y - case.y.mean(), case.u - case.u.mean(axis=0), structure,
                       offset=True)
    ratio = estimator.parameter_std / reference.std
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
    assert np.all(np.abs(estimator.theta - case.theta) < 3.0 * estimator.parameter_std)


@pytest.mark.parametrize('model', ['oe', 'armax'])
@pytest.mark.parametrize('detrend', ['none', 'mean'])
def test_units_scale_the_estimate_exactly(model, detrend):
    y, u = oe_data(2, count=2500)
    y = y + 3.0
    plain = make_estimator('rpem', order=2, model=model, detrend=detrend)
    plain.run(y, u)
    scaled = make_estimator('rpem', order=2, model=model, detrend=detrend)
    scaled.run(y * 2.0 ** 20, u * 2.0 ** -9)
    # a unchanged, b times s_y / s_u = 2^29, c unchanged: exact for powers of two
    factor = np.array([1.0, 1.0, 2.0 ** 29, 2.0 ** 29] + [1.0, 1.0] * (model == 'armax'))
    np.testing.assert_array_equal(scaled.theta, plain.theta * factor)
    np.testing.assert_array_equal(scaled.noise, plain.noise * 2.0 ** 40)


def test_bad_model_is_refused_naming_it():
    with pytest.raises(ValueError, match="model must be 'oe' or 'armax', got 'bj'"):
        Rpem(order=2, model='bj')
    with pytest.raises(ValueError, match="parameter 'model' must be one of 'oe', 'armax'"):
        check_identifier_parameters({'estimator': 'rpem', 'model': 'bj'})


def test_joint_state_mode_refuses_it_clearly():
    with pytest.raises(ValueError, match="'estimator' must be one of rls, bcrls with "
                                         "input_mode: joint_state .*got 'rpem'"):
        check_identifier_parameters({'estimator': 'rpem', 'input_mode': 'joint_state',
                                     'joints': ['a']})


def test_gate_refuses_spikes_and_keeps_the_estimate():
    y, u = oe_data(3, count=4000, noise_pole=0.0, noise_std=0.1)
    spiky = y.copy()
    spikes = [900, 1700, 2300, 3100]
    spiky[spikes] += 5.0  # 50 noise standard deviations
    clean = make_estimator('rpem', order=2, outlier_threshold=5.0)
    clean.run(y, u)
    gated = make_estimator('rpem', order=2, outlier_threshold=5.0)
    gated.run(spiky, u)
    assert gated.flags['outlier_rejected'] == len(spikes)
    # each refusal costs the n + 1 samples of a restarted regressor: a few in 4000,
    # which moves the estimate by a small fraction of its std
    assert (np.abs(gated.theta - clean.theta) < 0.5 * clean.parameter_std).all()
    ungated = make_estimator('rpem', order=2)
    ungated.run(spiky, u)
    assert np.linalg.norm(ungated.theta - clean.theta) > 3 * np.linalg.norm(
        gated.theta - clean.theta)


def fit_schedule(first, limit):
    """Return the sample counts at which the fits fall: first, then times FIT_GROWTH."""
    counts = [first]
    while int(np.ceil(FIT_GROWTH * counts[-1])) <= limit:
        counts.append(int(np.ceil(FIT_GROWTH * counts[-1])))
    return counts


def test_not_ready_before_the_first_fit_then_fits_as_samples_grow():
    y, u = oe_data(1, count=1000)
    estimator = make_estimator('rpem', order=2)
    first = max(50, 10 * 4)
    trajectory = estimator.run(y, u)
    # the first fit is due at sample `first` and taken a few samples later (spread over
    # the updates, test_rpem_spread_fit.py); ready from there on
    taken = int(np.argmax(trajectory.ready))
    assert first - 1 < taken <= first + 16 and trajectory.ready[taken:].all()
    assert estimator.fits == len(fit_schedule(first, 1000))
    assert estimator.parameter_std is not None
    fresh = make_estimator('rpem', order=2)
    assert fresh.parameter_std is None and not fresh.theta.any()


def test_held_adaptation_keeps_theta_and_the_predictor_running():
    y, u = oe_data(7, count=3000)
    estimator = make_estimator('rpem', order=2)
    estimator.run(y[:1500], u[:1500])
    theta, covariance = estimator.theta, estimator.covariance
    estimator.adapt = False
    estimator.run(y[1500:2000], u[1500:2000])
    np.testing.assert_array_equal(estimator.theta, theta)
    np.testing.assert_array_equal(estimator.covariance, covariance)
    assert estimator.held_samples == 500
    estimator.adapt = True
    estimator.run(y[2000:], u[2000:])
    assert (np.abs(estimator.theta - TRUTH) < 0.05).all()


def test_the_store_is_a_ring_of_the_last_batch_limit_samples():
    y, u = oe_data(8, count=BATCH_LIMIT + 300, noise_pole=0.0)
    estimator = make_estimator('rpem', order=1)
    estimator.run(y, u)
    state = estimator.get_state()
    assert state.scalars['stored'] == BATCH_LIMIT
    assert state.scalars['next_fit'] == 0  # no fit after the limit
    assert estimator.fits == len(fit_schedule(50, BATCH_LIMIT))


def test_predictor_history_gathers_lags_and_levels_the_outputs():
    history = PredictorHistory(2, 1, False, (1,), True, True)
    for t in range(4):
        phi = history.push(float(t), np.array([10.0 + t]))
        history.set_newest(float(t), 100.0 + t)
    # phi(3) = [-x(2), -x(1), u(1), u(0), e(2), e(1), 1] (one sample of dead time)
    np.testing.assert_array_equal(phi, [-2.0, -1.0, 11.0, 10.0, 102.0, 101.0, 1.0])
    np.testing.assert_array_equal(history.level_output_lags()[:2], [-1.5, -1.5])
    history.clear()
    assert not history.ready and history.push(0.0, np.array([0.0]))[-1] == 1.0


@pytest.mark.parametrize('model', ['oe', 'armax'])
def test_replay_of_the_parameters_builds_it(model):
    values = check_identifier_parameters({'estimator': 'rpem', 'model': model, 'order': 2})
    estimator = estimator_from_parameters(values)
    assert isinstance(estimator, Rpem) and estimator.model == model
    assert 'model' in persistence.configuration_fingerprint(values)
