"""Unit tests of the closed-loop BCLS estimator (Ikeda 2008) and its scenario."""

import inspect
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from scipy import signal

from bcid_ros.estimators import cl_bcls as cl
from bcid_ros.estimators import ESTIMATORS, estimator_class, lti, make_estimator
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from bcid_ros.identifier.parameters import (check_identifier_parameters, estimator_from_parameters,
                                            load_yaml_parameters)
from bcid_ros.simulation import make_scenario
from bcid_ros.simulation.ikeda import IkedaClosedLoop
from equivalence import assert_paths_agree, two_path_spread
from test_lti import random_stable_polynomial

PAPER = IkedaClosedLoop()
CONTROLLER = {key: PAPER.estimator_settings()[key]
              for key in ('controller_numerator', 'controller_denominator', 'controller_sign')}


def make(**settings):
    return make_estimator('cl_bcls', **{**PAPER.estimator_settings(), **settings})


# ------------------------------------------------------------- validation
@pytest.mark.parametrize('setting, value, message', [
    ('num_inputs', 2, r'num_inputs must be 1 for cl_bcls \(a SISO loop\), got 2'),
    ('feedthrough', True, r'feedthrough must be False for cl_bcls .*got True'),
    ('forgetting_factor', 1.5, r'forgetting_factor must be in \(0, 1\], got 1.5'),
    ('forgetting_factor', 1.5, r'forgetting_factor must be in \(0, 1\], got 1.5'),
    ('order', 0, r'order must be an integer in \[1, 64\], got 0'),
    ('controller_sign', 'neg',
     r"controller_sign must be one of negative, positive, got 'neg'"),
    ('controller_denominator', [0.0, 1.0],
     r'controller_denominator must have a non-zero first .*got \[0.0, 1.0\]'),
    ('controller_denominator', [1.0, float('nan')],
     r'controller_denominator must be a non-empty list of finite floats'),
    ('controller_numerator', [], r'controller_numerator must be a non-empty list'),
    ('controller_numerator', [1.0, 2.0, 3.0],
     r'controller_numerator must have at most len\(controller_denominator\) = 2 '
     r'coefficients \(a proper controller\), got 3'),
    ('prefilter_initial', 1.2,
     r'prefilter_initial must have all roots of f\(q\) strictly inside the unit circle'),
    ('prefilter_initial', [1.0, 0.1, 0.2],
     r'prefilter_initial must be a pole \(one float\) or the n \+ 1 = 2 coefficients'),
    ('window', 5, r'window must be 0 \(all data since the controller change\) or an integer '
     r'>= 21, got 5'),
    ('window', -1, r'window must be an integer in \[0, 1e\+09\], got -1'),
    ('redesign_period', 0, r'redesign_period must be an integer in \[1, 1e\+09\], got 0'),
    ('max_iterations', 0, r'max_iterations must be an integer in \[1, 10000\], got 0'),
    ('tolerance', 0.0, r'tolerance must be in \(0, 1e\+06\], got 0.0'),
])
def test_constructor_validation_names_the_setting(setting, value, message):
    with pytest.raises(ValueError, match=message):
        make(**{setting: value})


def test_forgetting_factor_must_be_1_with_a_window():
    with pytest.raises(ValueError, match=r'forgetting_factor must be 1 for cl_bcls with a '
                                         r'window .*got 0.99'):
        make(window=4096, forgetting_factor=0.99)
    est = make(window=4096)
    with pytest.raises(ValueError, match='forgetting_factor must be 1 for cl_bcls'):
        est.forgetting_factor = 0.95
    est.forgetting_factor = 1.0
    assert est.forgetting_factor == 1.0
    # all data since the change: the moments are weighted by the forgetting factor
    est = make(forgetting_factor=0.999)
    est.forgetting_factor = 0.99
    assert est.forgetting_factor == 0.99


def test_registry_options_and_names():
    cls = estimator_class('cl_bcls')
    assert cls is cl.ClosedLoopBcls
    # the registry is the one list of the ROS options; each is a constructor keyword
    options = ESTIMATORS['cl_bcls'].option_names
    assert options == ('controller_numerator', 'controller_denominator', 'controller_sign',
                       'prefilter_initial', 'window', 'redesign_period', 'max_iterations',
                       'tolerance')
    assert set(options) <= set(inspect.signature(cls).parameters)
    est = make(order=2)
    assert est.parameter_names == ('a1', 'a2', 'b1_1', 'b1_2')
    assert est.noise_names == ('sigma2',)
    assert 'negative feedback' in repr(est) and '\n' not in repr(est)


def test_prefilter_from_a_pole_or_coefficients():
    np.testing.assert_allclose(cl.prefilter_polynomial(0.5, 1), [1.0, -0.5])
    np.testing.assert_allclose(cl.prefilter_polynomial([0.5], 2), [1.0, -1.0, 0.25])
    np.testing.assert_allclose(cl.prefilter_polynomial([2.0, -1.0, 0.18], 2), [1.0, -0.5, 0.09])
    np.testing.assert_allclose(cl.prefilter_polynomial(0.0, 3), [1.0, 0.0, 0.0, 0.0])


# ------------------------------------------------- the linear-algebra pieces
@pytest.mark.parametrize('seed', range(6))
def test_sylvester_and_lyapunov_pieces_match_the_full_lyapunov_eq36(seed):
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 4), rng.integers(0, 3)
    h = rng.standard_normal(n)
    k = n + m
    # the monic polynomials' other coefficients and h are the data (companion forms from them)
    data = (random_stable_polynomial(rng, n + m)[1:], random_stable_polynomial(rng, n)[1:], h)

    def pieces(closed_loop, prefilter, h):
        a_cl, b_cl = lti.controller_canonical(np.r_[1.0, closed_loop])
        f_matrix, g = lti.controller_canonical(np.r_[1.0, prefilter])
        p22 = cl.solve_p22(f_matrix, g)
        return {'p22': p22, 'lyapunov p22': p22,
                'p12': cl.solve_p12(a_cl, b_cl, f_matrix, g, h, p22)}

    def scipy_solutions(closed_loop, prefilter, h):
        a_cl, b_cl = lti.controller_canonical(np.r_[1.0, closed_loop])
        f_matrix, g = lti.controller_canonical(np.r_[1.0, prefilter])
        full = cl.noise_state_covariance(a_cl, b_cl, f_matrix, g, h)  # scipy, eq. (36)
        return {'p22': full[k:, k:], 'p12': full[:k, k:],
                'lyapunov p22': scipy.linalg.solve_discrete_lyapunov(f_matrix, np.outer(g, g))}

    # our Kronecker solves against scipy's: two paths, within the rounding spreads of both
    spread = two_path_spread(pieces, scipy_solutions, *data)
    assert_paths_agree(pieces(*data), scipy_solutions(*data), spread, 1, f'seed {seed}')
    # h moved by a millionth: the bound sees it
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(pieces(*data[:2], h * (1.0 + 1e-6)), scipy_solutions(*data),
                           spread, 1)


def impulse_moments(a_p, b_p, controller, prefilter, length=3000):
    """Return E{phi eps} and E{eps^2} for unit white noise from the impulse responses."""
    n = a_p.size - 1
    b_c, a_c = controller.feedback_numerator, controller.denominator
    d_cl = np.convolve(a_p, a_c) + np.convolve(np.concatenate(([0.0], b_p)), b_c)
    impulse = np.zeros(length)
    impulse[0] = 1.0

    def tf(num):
        num = np.trim_zeros(num, 'f')
        return signal.lfilter(np.concatenate((np.zeros(d_cl.size - num.size), num)), d_cl,
                              impulse)

    y = tf(np.convolve(a_p, a_c))          # eq. (22), r = 0
    u = -tf(np.convolve(a_p, b_c))         # eq. (23), r = 0
    y_f = signal.lfilter([1.0], prefilter, y)
    u_f = signal.lfilter([1.0], prefilter, u)
    eps = signal.lfilter(a_p, prefilter, impulse)   # eq. (15)
    lagged = [np.concatenate((np.zeros(k), x[:length - k])) for x in (y_f, u_f)
              for k in range(1, n + 1)]
    return np.array([z @ eps for z in lagged]), eps @ eps


@pytest.mark.parametrize('sign', ['negative', 'positive'])
@pytest.mark.parametrize('seed', range(3))
def test_bias_terms_are_the_noise_moments_of_theorem1(seed, sign):
    # E{phi eps} = C_cl P12 h' sigma^2 (eq. 37) and E{eps^2} = (1 + h P22 h') sigma^2 (eq. 48),
    # checked against the exact sums of impulse-response products of the loop of eqs. (22)-(25).
    rng = np.random.default_rng(seed)
    n, m = 1 + seed % 2, seed % 3
    while True:
        a_p = random_stable_polynomial(rng, n, radius=0.95)
        b_p = rng.uniform(-1, 1, n)
        controller = lti.make_controller(rng.uniform(-0.5, 0.5, m + 1),
                                         random_stable_polynomial(rng, m), sign)
        d_cl, *_ = cl.closed_loop_realisation(a_p, b_p, controller)
        if is_stable(monic_coefficients(d_cl), 0.1):
            break
    prefilter = random_stable_polynomial(rng, n)
    numerator, denominator = controller.numerator, controller.denominator

    def theorem(a_p, b_p, numerator, denominator, prefilter):
        controller = lti.make_controller(numerator, np.r_[1.0, denominator], sign)
        direction, beta = cl.bias_terms(np.concatenate((a_p, b_p)), np.r_[1.0, prefilter],
                                        controller)
        return {'direction': direction, 'beta': beta}

    def sums(a_p, b_p, numerator, denominator, prefilter):
        controller = lti.make_controller(numerator, np.r_[1.0, denominator], sign)
        moments, power = impulse_moments(np.r_[1.0, a_p], b_p, controller,
                                         np.r_[1.0, prefilter])
        return {'direction': moments, 'beta': power}

    # Lyapunov solves against 3000-term sums of products (the tail beyond 3000 is below
    # 0.95^3000): two paths, within the rounding spreads of both plus the sums' N eps
    data = (a_p[1:], b_p, numerator, denominator[1:], prefilter[1:])
    spread = two_path_spread(theorem, sums, *data)
    assert_paths_agree(theorem(*data), sums(*data), spread, 3000, f'seed {seed}')
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(theorem(data[0] * (1.0 + 1e-6), *data[1:]), sums(*data), spread,
                           3000)


def test_bias_terms_refuse_an_unstable_estimated_loop():
    controller = lti.make_controller([5.0], [1.0, -0.09])
    with pytest.raises(cl.CompensationFailure, match='estimated closed loop') as info:
        cl.bias_terms(np.array([-0.8, 5.0]), np.array([1.0, -0.5]), controller)
    assert info.value.flag == 'unstable_closed_loop'


def test_negative_argument_of_eq58_is_refused():
    y, u = PAPER.simulate(500, 1)
    ls = cl.prefiltered_ls(y, u[:, 0], np.array([1.0, -0.5]))
    with pytest.raises(cl.CompensationFailure) as info:
        cl.compensated_estimate(ls, np.array([1e3, 1e3]), 1.0)
    assert info.value.flag == 'negative_variance_argument'


# --------------------------------------------------------- batch Algorithm 1
def test_prefiltered_ls_solves_the_normal_equations():
    y, u = PAPER.simulate(300, 2)
    prefilter = np.array([1.0, -0.5])
    ls = cl.prefiltered_ls(y, u[:, 0], prefilter)
    assert ls.count == 299

    def normal_equations(y, u):
        ls = cl.prefiltered_ls(y, u, prefilter)
        return {'theta': ls.theta, 'loss': ls.loss}

    def lstsq(y, u):
        phi = np.column_stack((signal.lfilter([1.0], prefilter, y)[:-1],
                               signal.lfilter([1.0], prefilter, u)[:-1]))
        theta = np.linalg.lstsq(phi, y[1:], rcond=None)[0]
        return {'theta': theta, 'loss': np.sum((y[1:] - phi @ theta) ** 2)}

    # a Cholesky-checked solve against LAPACK's least squares: two paths, within the
    # rounding spreads of both (test/equivalence.py)
    spread = two_path_spread(normal_equations, lstsq, y, u[:, 0])
    assert_paths_agree(normal_equations(y, u[:, 0]), lstsq(y, u[:, 0]), spread, 299, 'LS')
    changed = y.copy()
    changed[150] *= 1.0 + 1e-6
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(normal_equations(changed, u[:, 0]), lstsq(y, u[:, 0]), spread, 299)
    # the same filter on the same samples: the same bits
    np.testing.assert_array_equal(ls.next_regressor, [signal.lfilter([1.0], prefilter, y)[-1],
                                                      signal.lfilter([1.0], prefilter,
                                                                     u[:, 0])[-1]])


def test_algorithm1_converges_and_bias_compensation_saves_iterations():
    y, u = PAPER.simulate(4096, 11)
    bc = cl.closed_loop_bcls(y, u, order=1, prefilter_initial=0.7, **CONTROLLER)
    plain = cl.closed_loop_bcls(y, u, order=1, prefilter_initial=0.7,
                                bias_compensation=False, **CONTROLLER)
    assert bc.converged and plain.converged and bc.failure is None
    assert bc.iterations < plain.iterations
    assert bc.iterations == len(bc.history)
    np.testing.assert_allclose(bc.prefilter[1], bc.history[-2][0])
    # one realisation: the sections 7.3 spread is ~0.05 (pole) and ~0.07 (b)
    assert abs(bc.theta[0] + 0.8) < 0.2 and abs(bc.theta[1] - 0.5) < 0.25
    assert 0.8 < bc.sigma2 < 1.2
    assert plain.sigma2 is None


def test_algorithm1_first_iteration_failure_is_raised():
    y, u = PAPER.simulate(1000, 3)
    with pytest.raises(cl.CompensationFailure) as info:
        cl.closed_loop_bcls(y, u, order=1, controller_numerator=[50.0],
                            controller_denominator=[1.0, -0.09])
    assert info.value.flag == 'unstable_closed_loop'


def test_algorithm1_follows_remark3_for_an_unstable_plant():
    # plant 0.5/(q - 1.2) in a stable loop: the prefilter converges to q - 1/1.2
    loop = IkedaClosedLoop(plant_denominator=[1.0, -1.2], controller_numerator=[1.2],
                           controller_denominator=[1.0, -0.09], noise_variance=0.25)
    settings = loop.estimator_settings()
    y, u = loop.simulate(4096, 0)
    result = cl.closed_loop_bcls(y, u, order=1, prefilter_initial=0.5, tolerance=1e-6,
                                 controller_numerator=settings['controller_numerator'],
                                 controller_denominator=settings['controller_denominator'])
    assert result.converged
    # 40 runs gave std 0.003 (pole) and 0.005 (b); 5 std as bounds for one run
    assert abs(result.theta[0] + 1.2) < 0.02 and abs(result.theta[1] - 0.5) < 0.03
    # the root of q + a_1 mirrored (np.roots, 1 / r, np.poly) against 1 / a_1: a few
    # roundings of numbers near 1, 1e-9 is far above them
    assert result.next_prefilter[1] == pytest.approx(1.0 / result.theta[0], abs=1e-9)


# --------------------------------------------------------------- the online form
def online_checkpoints(y, u, make_est):
    """
    Feed samples; return the estimator and its figures at every redesign and some samples between.

    Each entry is {sample: (kind, figures)}; at a redesign ``kind`` holds the
    window start, the prefilter before it and the iterations.
    """
    est = make_est()
    checkpoints, window_start = {}, None
    for k in range(y.size):
        before = est.prefilter
        redesigns = est.redesigns
        est.update(y[k], u[k])
        figures = {'theta': est.theta, 'ls': est.theta_uncompensated, 'sigma2': est.noise[0]}
        if est.redesigns != redesigns:
            window_start = k + 1 - min(k + 1, est.window)
            checkpoints[k] = (('redesign', window_start, before, est.last_iterations), figures)
        elif window_start is not None and k % 97 == 0:
            checkpoints[k] = (('between', window_start), figures)
    return est, checkpoints


def batch_checkpoints(y, u, est, controller, kinds):
    """
    Return the figures of :func:`online_checkpoints` from the batch, at the same samples.

    At a redesign, Algorithm 1 on the window from the prefilter in use; between
    redesigns, eqs. (56)-(59) on the LS over the window start..k with the
    frozen c, beta of the last redesign. The prefilters come from the batch's own
    redesigns, as the online form's come from its own.
    """
    figures, prefilter, last = {}, None, None
    for k, kind in sorted(kinds.items()):
        start = kind[1]
        if kind[0] == 'redesign':
            last = cl.closed_loop_bcls(
                y[start:k + 1], u[start:k + 1], order=est.order,
                prefilter_initial=kind[2] if prefilter is None else prefilter,
                max_iterations=est.max_iterations, tolerance=est.tolerance, **controller)
            prefilter = last.prefilter
            figures[k] = {'theta': last.theta, 'ls': last.theta_ls, 'sigma2': last.sigma2,
                          'iterations': last.iterations}
        else:
            ls = cl.prefiltered_ls(y[start:k + 1], u[start:k + 1], prefilter)
            theta, sigma2 = cl.compensated_estimate(ls, last.direction, last.beta)
            figures[k] = {'theta': cl.plant_from_regression(theta, prefilter),
                          'ls': cl.plant_from_regression(ls.theta, prefilter),
                          'sigma2': sigma2}
    return figures


def run_and_check_against_batch(y, u, make_est, controller, online_y=None):
    """
    Compare the online form with the batch at every redesign and some samples between.

    ``online_y`` feeds the online form other outputs (the test that the bound sees
    a change); the batch and the rounding spreads take ``y``.
    """
    est, online = online_checkpoints(y if online_y is None else online_y, u, make_est)
    kinds = {k: kind for k, (kind, _) in online.items()}

    def flat(checkpoints):
        return {(k, name): value for k, figures in checkpoints.items()
                for name, value in figures.items() if name != 'iterations'}

    # Two arithmetic paths, also at a redesign: the online form hands Algorithm 1 the
    # columns of its sample buffer, so the LS's Phi' y runs BLAS gemv on a strided y
    # (incx 2) where the batch has a contiguous record; between redesigns RLS steps
    # continue the redesign's LS. Within the rounding spreads of both (test/equivalence.py).
    spread = two_path_spread(
        lambda y, u: flat({k: f for k, (_, f) in online_checkpoints(y, u, make_est)[1].items()}),
        lambda y, u: flat(batch_checkpoints(y, u, est, controller, kinds)), y, u)
    expected = batch_checkpoints(y, u, est, controller, kinds)
    for k, (kind, figures) in online.items():
        if kind[0] == 'redesign':  # a discrete outcome: exactly the batch's
            assert kind[3] == expected[k]['iterations'], k
        assert_paths_agree(figures, {name: expected[k][name] for name in figures},
                           {name: spread[k, name] for name in figures}, k + 1 - kind[1],
                           f'sample {k}')
    return est, len(online)


def test_online_form_equals_the_batch_algorithm_on_the_same_window():
    y, u = PAPER.simulate(2600, 7)
    est, checks = run_and_check_against_batch(
        y, u[:, 0], lambda: make(window=700, redesign_period=250), CONTROLLER)
    assert est.redesigns == 10 and checks > 25
    assert not est.flags
    # one sample changed by a ten-thousandth of its value online only: the bound sees it
    changed = y.copy()
    changed[2450] *= 1.0 + 1e-4
    with pytest.raises(AssertionError, match='the paths differ by'):
        run_and_check_against_batch(
            y, u[:, 0], lambda: make(window=700, redesign_period=250), CONTROLLER,
            online_y=changed)


def test_online_form_equals_batch_for_a_second_order_loop():
    loop = IkedaClosedLoop(plant_numerator=[0.3, 0.2], plant_denominator=[1.0, -1.1, 0.3],
                           controller_numerator=[0.4, -0.1],
                           controller_denominator=[1.0, -0.2], noise_variance=0.1,
                           reference_amplitude=1.0)
    settings = loop.estimator_settings()
    y, u = loop.simulate(1500, 5)
    controller = {key: settings[key] for key in CONTROLLER}
    est, checks = run_and_check_against_batch(y, u[:, 0], lambda: make_estimator(
        'cl_bcls', window=900, redesign_period=300, **settings), controller)
    # this loop is poorly excited: Algorithm 1 contracts slowly and some redesigns stop at
    # max_iterations, which the batch run must reproduce as well
    assert est.redesigns == 4 and checks > 10 and est.flags == {'not_converged': 2}


def test_before_the_first_redesign_the_estimate_is_the_ls_and_not_valid():
    y, u = PAPER.simulate(400, 1)
    # window 400: the first redesign may come at first_window = 200
    est = make(window=400, redesign_period=200)
    trajectory = est.run(y[:199], u[:199])
    assert not trajectory.valid.any()
    np.testing.assert_array_equal(trajectory.theta, trajectory.theta_uncompensated)
    assert np.all(trajectory.noise == 0.0)
    trajectory = est.run(y[199:], u[199:])
    assert trajectory.valid.all() and est.redesigns == 2
    assert est.samples == 400 and est.window_length == 400


def test_the_window_grows_up_to_its_cap_and_restart_empties_it():
    y, u = PAPER.simulate(700, 2)
    est = make(window=300, redesign_period=100)
    est.run(y[:500], u[:500])
    assert est.window_length == 300
    theta = est.theta
    est.restart_regressor()
    assert est.window_length == 0 and est.valid
    np.testing.assert_array_equal(est.theta, theta)
    est.run(y[500:], u[500:])
    assert est.window_length == 200


def test_window_settings_reach_the_truth_on_the_paper_loop():
    y, u = PAPER.simulate(6000, 21)
    est = make(window=4096)
    trajectory = est.run(y, u)
    # the first redesign waits for first_window = 2048 samples, then one every 1000; the
    # first one (from f = q) may use all 20 iterations
    assert est.first_window == 2048
    assert est.redesigns == 4 and set(est.flags) <= {'not_converged'}
    assert np.isfinite(trajectory.theta).all()
    # one run of N = 4096 (the window): section 7.3 spread is 0.05 / 0.07
    np.testing.assert_allclose(est.theta, PAPER.truth().parameters, atol=0.2)
    assert est.noise[0] == pytest.approx(1.0, abs=0.15)


# -------------------------------------------------------------------- safety
def assert_no_nan(trajectory):
    assert np.isfinite(trajectory.theta).all()
    assert np.isfinite(trajectory.theta_uncompensated).all()
    assert np.isfinite(trajectory.noise).all()


def test_unstable_estimated_loop_keeps_the_last_good_estimate():
    # Good data first, then data of a plant that the configured controller cannot
    # stabilise: every later redesign fails and the compensated estimate is held.
    y, u = PAPER.simulate(600, 4)
    est = make(window=300, redesign_period=200, prefilter_initial=0.7)
    est.run(y, u)
    assert est.valid and not est.flags
    rng = np.random.default_rng(5)
    u2 = rng.standard_normal(800)
    y2 = signal.lfilter([0.0, 8.0], [1.0, -0.8], u2) + 0.1 * rng.standard_normal(800)
    trajectory = est.run(y2, u2)
    assert_no_nan(trajectory)
    # redesigns at samples 800, 1000, 1200, 1400 all fail: from the first one (row 199,
    # after that sample's own compensation) the estimate is held
    assert est.flags == {'unstable_closed_loop': 4} and est.holding
    assert (trajectory.theta[199:] == trajectory.theta[199]).all()
    assert (trajectory.noise[199:] == trajectory.noise[199]).all()
    assert not (trajectory.theta[198] == trajectory.theta[199]).all()
    assert est.theta_uncompensated[1] > 5.0  # the LS runs on, towards b = 8


def test_unstable_estimated_loop_before_any_good_estimate_stays_invalid():
    y, u = PAPER.simulate(500, 4)
    est = make(controller_numerator=[50.0], window=200, redesign_period=100)
    trajectory = est.run(y, u)
    assert_no_nan(trajectory)
    assert not trajectory.valid.any() and not est.holding
    assert est.flags == {'unstable_closed_loop': 5}


def test_lyapunov_failure_is_flagged_and_held(monkeypatch):
    y, u = PAPER.simulate(500, 4)
    est = make(window=400, redesign_period=200, prefilter_initial=0.7)
    est.run(y[:300], u[:300])
    assert est.valid and not est.flags

    def broken(*_):
        raise np.linalg.LinAlgError('singular Kronecker system')

    monkeypatch.setattr('bcid_ros.estimators.cl_bcls.bias.solve_stein', broken)
    trajectory = est.run(y[300:], u[300:])
    assert_no_nan(trajectory)
    assert est.flags == {'lyapunov_failed': 1} and est.holding
    # the redesign at sample 400 (row 99) fails; the estimate is held from there
    assert (trajectory.theta[99:] == trajectory.theta[99]).all()


def test_unstable_redesigned_prefilter_stops_the_iteration(monkeypatch):
    y, u = PAPER.simulate(400, 8)
    monkeypatch.setattr('bcid_ros.estimators.cl_bcls.batch.stable_reflection',
                        lambda a_p: np.array([1.0, -1.0]))
    result = cl.closed_loop_bcls(y, u, order=1, prefilter_initial=0.5, **CONTROLLER)
    assert result.failure == 'unstable_prefilter' and result.iterations == 1
    np.testing.assert_array_equal(result.next_prefilter, [1.0, -0.5])
    est = make(window=400, redesign_period=200, prefilter_initial=0.5)
    trajectory = est.run(y, u)
    assert_no_nan(trajectory)
    assert est.flags == {'unstable_prefilter': 2} and est.valid
    np.testing.assert_array_equal(est.prefilter, [1.0, -0.5])


def test_negative_eq58_argument_at_a_sample_keeps_the_last_estimate():
    y, u = PAPER.simulate(300, 9)
    est = make(window=400, redesign_period=200)
    est.run(y[:250], u[:250])
    state = est.get_state()
    arrays = dict(state.arrays, direction=state.arrays['direction'] * 1e4)
    est.set_state(type(state)(state.estimator, arrays, state.scalars))
    theta, noise = est.theta, est.noise
    trajectory = est.run(y[250:], u[250:])
    assert_no_nan(trajectory)
    assert est.flags['negative_variance_argument'] == 50
    np.testing.assert_array_equal(est.theta, theta)
    np.testing.assert_array_equal(est.noise, noise)


def test_no_excitation_gives_no_nan():
    est = make(window=100, redesign_period=50)
    trajectory = est.run(np.zeros(300), np.zeros(300))
    assert_no_nan(trajectory)
    assert not est.valid and est.flags == {'singular_information': 6}


# ------------------------------------------------------------ state handling
def test_snapshot_restore_and_reset():
    y, u = PAPER.simulate(900, 12)
    est = make(window=300, redesign_period=150)
    est.run(y[:420], u[:420])
    snapshot = est.get_state()
    first = est.run(y[420:], u[420:])
    other = make(window=300, redesign_period=150)
    other.set_state(snapshot)
    second = other.run(y[420:], u[420:])
    np.testing.assert_array_equal(first.theta, second.theta)
    np.testing.assert_array_equal(first.noise, second.noise)
    assert other.redesigns == est.redesigns and other.flags == est.flags
    with pytest.raises(ValueError, match="does not match this configuration"):
        make(window=301).set_state(snapshot)
    est.reset()
    assert est.samples == 0 and not est.valid and est.redesigns == 0
    np.testing.assert_array_equal(est.prefilter, [1.0, 0.0])
    again = est.run(y, u)
    fresh = make(window=300, redesign_period=150).run(y, u)
    np.testing.assert_array_equal(again.theta, fresh.theta)


# ------------------------------------------------------------------ scenario
def test_scenario_is_the_paper_loop():
    assert isinstance(make_scenario('ikeda_closed_loop'), IkedaClosedLoop)
    truth = PAPER.truth()
    assert truth.parameter_names == ('a1', 'b1_1')
    np.testing.assert_array_equal(truth.parameters, [-0.8, 0.5])
    assert truth.noise_names == ('sigma2',) and truth.noise.tolist() == [1.0]
    assert PAPER.controller_numerator == [0.0, 0.2289]
    assert PAPER.controller_denominator == [1.0, -0.09004]
    assert PAPER.controller_sign == 'negative'
    # closed-loop poles: the roots of d_cl (eq. 8) of the example (60), 0.553 and 0.337
    np.testing.assert_allclose(sorted(np.roots(PAPER.characteristic).real), [0.337, 0.553],
                               atol=1e-3)


def test_scenario_equals_the_loop_simulated_sample_by_sample():
    count = 300
    y, u = PAPER.simulate(count, 13)
    draws = np.random.default_rng(13).standard_normal((count, 2))
    plant = controller = 0.0
    level = 0.0
    for k in range(count):
        if k % 16 == 0:
            level = 0.5 if draws[k, 1] >= 0 else -0.5
        # u[k] from the controller state, y[k] = plant state + nu[k]. The scenario filters
        # the same loop with lfilter: each step rounds by a few eps of signals below 3,
        # carried by the loop's decaying response (poles 0.55, 0.34), ~1e-15 (measured
        # 4e-16); 1e-12 is far above it and far below any wrong coefficient
        measured = plant + draws[k, 0]
        assert u[k, 0] == pytest.approx(controller, abs=1e-12)
        assert y[k] == pytest.approx(measured, abs=1e-12)
        plant = 0.8 * plant + 0.5 * controller
        controller = 0.09004 * controller + 0.2289 * (level - measured)


def test_scenario_samples_do_not_depend_on_the_block_sizes():
    whole = PAPER.stream(np.random.default_rng(5)).take(1000)
    stream = PAPER.stream(np.random.default_rng(5))
    parts = [stream.take(k) for k in (1, 15, 16, 17, 0, 200, 751)]
    np.testing.assert_array_equal(np.concatenate([p[0] for p in parts]), whole[0])
    np.testing.assert_array_equal(np.concatenate([p[1] for p in parts]), whole[1])


def test_scenario_positive_sign_and_zero_reference():
    flipped = IkedaClosedLoop(controller_numerator=[-0.2289], controller_sign='positive')
    np.testing.assert_array_equal(flipped.simulate(200, 1)[0], PAPER.simulate(200, 1)[0])
    quiet = IkedaClosedLoop(reference_amplitude=0.0, noise_variance=0.0)
    assert not quiet.simulate(100, 1)[0].any()
    with pytest.raises(ValueError, match='the closed loop must be stable'):
        IkedaClosedLoop(controller_numerator=[20.0])


# ------------------------------------------- regression: drifting first redesign
def test_is_contracting_compares_the_last_step_with_the_first():
    steps = [np.array([0.0, 0.0]), np.array([0.1, 0.0]), np.array([0.15, 0.0])]
    assert cl.is_contracting(steps)
    drifting = [np.array([0.0, 0.0]), np.array([0.05, 0.0]), np.array([0.2, 0.0])]
    assert not cl.is_contracting(drifting)
    assert cl.is_contracting(drifting[:2]) and cl.is_contracting(drifting[:1])


def config_estimator(**overrides):
    """Build the estimator the node builds from config/ikeda_closed_loop.yaml."""
    path = Path(__file__).resolve().parents[2] / 'config' / 'ikeda_closed_loop.yaml'
    values = check_identifier_parameters(load_yaml_parameters(str(path)))
    return estimator_from_parameters({**values, **overrides})


def relative_error(theta):
    truth = PAPER.truth().parameters
    return np.linalg.norm(theta - truth) / np.linalg.norm(truth)


# Seed 1082 of the bag Monte Carlo (bags/convergence_mc.py): with the first redesign at
# 1000 samples, Algorithm 1 drifted for 20 iterations from pole 0.7 to -0.91 (each step
# longer than the last), the online form adopted that end point, and later redesigns
# converged to a spurious fixed point at pole -1.01 (Remark 3 mirroring the prefilter):
# delta = 196 %. Bound: batch Algorithm 1 on the full 4096-sample records of the same 100
# Monte Carlo seeds, from f = q - 0.7, never exceeded delta = 27.1 %; 0.3 is above that and
# far below the failure.
def test_seed_1082_default_config_stays_near_the_plant():
    y, u = make_scenario('ikeda_closed_loop').simulate(4096, 1082)
    est = config_estimator()
    trajectory = est.run(y, u)
    assert_no_nan(trajectory)
    assert est.first_window == 2048 and trajectory.valid.argmax() == 2047
    assert np.abs(trajectory.theta[trajectory.valid, 0]).max() < 1.0
    assert relative_error(est.theta) < 0.3


def test_seed_1082_drifting_first_redesign_is_dropped_and_flagged():
    # window 2000 puts the first redesign at sample 1000, as before the first_window rule
    y, u = make_scenario('ikeda_closed_loop').simulate(4096, 1082)
    u = u[:, 0]
    est = config_estimator(window=2000)
    assert est.first_window == 1000
    first = est.run(y[:1000], u[:1000])
    assert est.flags == {'not_converged': 1, 'not_contracting': 1}
    assert not est.valid and est.redesigns == 0 and not first.valid.any()
    # the prefilter and the running LS stay as they were: the LS with f = q - 0.7
    np.testing.assert_array_equal(est.prefilter, [1.0, -0.7])
    at_1000 = est.theta
    # the next redesign starts again from f = q - 0.7, on 2000 samples
    rest = est.run(y[1000:2000], u[1000:2000])
    offline = cl.closed_loop_bcls(y[:2000], u[:2000], order=1, prefilter_initial=0.7,
                                  max_iterations=est.max_iterations, **CONTROLLER)
    assert est.valid and offline.converged

    def online_form(y, u):
        est = config_estimator(window=2000)
        est.run(y[:1000], u[:1000])
        theta = est.theta
        est.run(y[1000:2000], u[1000:2000])
        return {'LS at 1000': theta, 'theta at 2000': est.theta}

    # the running LS started from P(0) = p0 S^-2 (the scales the run chose): its batch
    # form is the LS regularised by P(0)^-1
    regularisation = np.diag(1.0 / est._units.initial_p().diagonal())

    def batch_form(y, u):
        prefilter = np.array([1.0, -0.7])
        phi, target, _ = cl.prefiltered_regression(y[:1000], u[:1000], prefilter)
        ls = np.linalg.solve(phi.T @ phi + regularisation, phi.T @ target)
        offline = cl.closed_loop_bcls(y[:2000], u[:2000], order=1, prefilter_initial=0.7,
                                      max_iterations=est.max_iterations, **CONTROLLER)
        return {'LS at 1000': cl.plant_from_regression(ls, prefilter),
                'theta at 2000': offline.theta}

    # RLS steps against the batch LS, and Algorithm 1 on a strided against a contiguous
    # record: two arithmetic paths, within the rounding spreads of both (test/equivalence.py)
    assert_paths_agree({'LS at 1000': at_1000, 'theta at 2000': est.theta}, batch_form(y, u),
                       two_path_spread(online_form, batch_form, y[:2000], u[:2000]), 2000,
                       'seed 1082')
    rest = est.run(y[2000:], u[2000:])
    assert_no_nan(first)
    assert_no_nan(rest)
    assert est.flags == {'not_converged': 1, 'not_contracting': 1}
    assert np.abs(rest.theta[:, 0]).max() < 1.0
    # a 2000-sample window has about twice the variance of 4096: a looser 0.5 than the
    # 0.3 above, still far below the 196 % of the failure
    assert relative_error(est.theta) < 0.5
