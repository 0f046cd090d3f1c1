"""Tests of cl_bcls with all data since the controller change, controller changes, validity."""

import numpy as np
import pytest

from bcid_ros.estimators import cl_bcls as cl
from bcid_ros.estimators import cl_bcls_batch as batch
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.lti import make_controller
from bcid_ros.simulation.ikeda import IkedaClosedLoop
from equivalence import assert_paths_agree, two_path_spread

PAPER = IkedaClosedLoop()
KEYS = ('controller_numerator', 'controller_denominator', 'controller_sign')
CONTROLLER = {key: PAPER.estimator_settings()[key] for key in KEYS}
#: A second stabilising controller for the same plant (closed-loop poles 0.55 +- 0.34j).
RETUNED = {'controller_numerator': [0.35], 'controller_denominator': [1.0, -0.3],
           'controller_sign': 'negative'}


def make(**settings):
    return make_estimator('cl_bcls', **{**PAPER.estimator_settings(), **settings})


def relative_error(theta):
    truth = PAPER.truth().parameters
    return np.linalg.norm(theta - truth) / np.linalg.norm(truth)


def dense_rows(y, u, prefilters):
    """
    Return (Psi, target) of the plant-form regression with prefilter ``prefilters[k]``.

    ``prefilters[k]`` is the f(q) in use when sample k enters the filters (first order).
    """
    rows, target = [], []
    y_f = u_f = 0.0
    for k in range(y.size):
        f_1 = prefilters[k][1]
        if k >= 1:
            # y_f[k] = y[k] - f_1 y_f[k-1]; psi = [-y_f[k-1], u_f[k-1]]
            rows.append([-y_f, u_f])
            target.append(y[k] - f_1 * y_f)
        y_f, u_f = y[k] - f_1 * y_f, u[k] - f_1 * u_f
    return np.array(rows), np.array(target)


# ------------------------------------------------------ the moments are exact
#: The redesigns of a single-prefilter run: each time the rows double from 10 * 2n + n = 21.
REDESIGNS = [21 * 2 ** j for j in range(8)]


def single_prefilter_online(y, u):
    """Return the estimates at the first redesign and at every 211th sample after it."""
    # redesign_period 5000: the prefilter stays f = q - 0.7 for the whole run
    est = make(prefilter_initial=0.7, redesign_period=5000, max_iterations=1)
    figures = {}
    for k in range(y.size):
        est.update(y[k], u[k])
        if est.redesigns and (k % 211 == 0 or not figures):
            figures[k] = {'theta': est.theta, 'ls': est.theta_uncompensated,
                          'sigma2': est.sigma2}
    return est, figures


def single_prefilter_batch(y, u, checkpoints):
    """Return at ``checkpoints`` what :func:`single_prefilter_online` returns, from the batch."""
    prefilter = np.array([1.0, -0.7])
    controller = make_controller(*CONTROLLER.values())
    figures, direction, beta, theta = {}, None, None, None
    for k in sorted(set(checkpoints) | set(REDESIGNS)):
        # the LS over all samples so far (sample k completes row k)
        ls = batch.prefiltered_ls(y[:k + 1], u[:k + 1], prefilter)
        ls_plant = batch.plant_from_regression(ls.theta, prefilter)
        if k in REDESIGNS:
            # one iteration of Algorithm 1 on the moments: the bias terms of eq. (37), (57)
            # at the compensated estimate of this row (the LS at the first redesign)
            if direction is not None:
                theta, _ = batch.compensated_estimate(ls, direction, beta)
            start = ls_plant if direction is None else batch.plant_from_regression(
                theta, prefilter)
            direction, beta = batch.bias_terms(start, prefilter, controller)
        # eqs. (53), (56)-(59) with the c, beta of the last redesign
        theta, sigma2 = batch.compensated_estimate(ls, direction, beta)
        if k in checkpoints:
            figures[k] = {'theta': batch.plant_from_regression(theta, prefilter),
                          'ls': ls_plant, 'sigma2': sigma2}
    return figures


def flat(figures):
    """Return {(sample, name): value} of {sample: {name: value}}."""
    return {(k, name): value for k, named in figures.items() for name, value in named.items()}


def test_single_prefilter_moments_equal_the_batch_ls_and_compensation():
    y, u = PAPER.simulate(3000, 3)
    u = u[:, 0]
    est, online = single_prefilter_online(y, u)
    checkpoints = sorted(online)
    # first redesign after 10 * 2n + n = 21 rows (22 samples), then every 211th sample
    assert checkpoints[0] + 1 == 22 and checkpoints[1:] == list(range(211, 3000, 211))
    assert est.epochs == 1 and est.redesigns == len(REDESIGNS)
    # The moments summed per sample against the batch LS of the prefiltered record: two
    # arithmetic paths, within the rounding spreads of both (test/equivalence.py)
    spread = two_path_spread(lambda y, u: flat(single_prefilter_online(y, u)[1]),
                             lambda y, u: flat(single_prefilter_batch(y, u, checkpoints)),
                             y, u)
    expected = single_prefilter_batch(y, u, checkpoints)
    for k in checkpoints:
        assert_paths_agree(online[k], expected[k], {name: spread[k, name] for name in online[k]},
                           k + 1, f'sample {k}')
    # one sample changed by a ten-thousandth of its value in the recursion only: the bound
    # of the last checkpoint sees it
    changed = y.copy()
    changed[1500] *= 1.0 + 1e-4
    last = checkpoints[-1]
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(single_prefilter_online(changed, u)[1][last], expected[last],
                           {name: spread[last, name] for name in online[last]}, last + 1)


def every_prefilter_run(y, u):
    """Return the cl_bcls run with redesign_period 500 and the prefilter of every sample."""
    est = make(redesign_period=500)
    prefilters = []
    for k in range(y.size):
        prefilters.append(est.prefilter)
        est.update(y[k], u[k])
    return est, prefilters


def test_rows_of_every_prefilter_stack_in_one_exact_ls():
    y, u = PAPER.simulate(4000, 5)
    u = u[:, 0]
    est, prefilters = every_prefilter_run(y, u)
    assert est.epochs >= 2

    def online(y, u):
        est = every_prefilter_run(y, u)[0]
        return {'theta': est.theta_uncompensated, 'covariance': est.covariance}

    def dense(y, u):
        psi, target = dense_rows(y, u, prefilters)
        return {'theta': np.linalg.lstsq(psi, target, rcond=None)[0],
                'covariance': np.linalg.inv(psi.T @ psi)}

    # moments per sample against one least-squares solve of the stacked rows: two paths
    assert_paths_agree(online(y, u), dense(y, u), two_path_spread(online, dense, y, u),
                       y.size, 'all prefilters')


# ---------------------------------------------------------- the measurement
# One 50,000-sample run would take too long here; 20,000 samples, 2 seeds. docs/cl_bcls.md
# has the full-length figures (all data: delta 2.0 % mean over 10 seeds, batch 2.0 %,
# window 4096: 5.5 %).
@pytest.mark.parametrize('seed', range(2))
def test_all_data_since_the_change_is_as_good_as_the_batch_algorithm(seed):
    y, u = PAPER.simulate(20000, seed)
    est = make(prefilter_initial=0.7)
    est.run(y, u)
    offline = batch.closed_loop_bcls(y, u[:, 0], order=1, prefilter_initial=0.7,
                                     max_iterations=50, **CONTROLLER)
    assert est.valid
    # both estimate the same quantity from the same data: they differ by much less than the
    # spread over seeds (about 2 % delta at this length)
    assert abs(relative_error(est.theta) - relative_error(offline.theta)) < 0.02


# ------------------------------------------------------- controller changes
def switched_data(seed):
    before = PAPER.simulate(3000, seed)
    after = IkedaClosedLoop(**RETUNED).simulate(3000, seed + 100)
    return before, after


@pytest.mark.parametrize('window', [0, 700])
def test_a_controller_change_restarts_everything_but_the_prefilter(window):
    (y1, u1), (y2, u2) = switched_data(1)
    est = make(window=window, redesign_period=250, prefilter_initial=0.7)
    est.run(y1, u1)
    assert est.valid
    prefilter = est.prefilter
    assert est.set_controller(*RETUNED.values())
    assert not est.valid and est.validity_reasons[0] == 'not_compensated'
    assert est.controller_changes == 1
    switched = est.run(y2, u2)
    fresh = make(window=window, redesign_period=250, prefilter_initial=prefilter, **RETUNED)
    fresh_run = fresh.run(y2, u2)
    # one code path from the same restarted state on the same samples: the same bits
    for name in ('theta', 'theta_uncompensated', 'noise', 'valid'):
        np.testing.assert_array_equal(getattr(switched, name), getattr(fresh_run, name))
    np.testing.assert_array_equal(est.prefilter, fresh.prefilter)


def test_no_sample_from_before_the_change_enters_the_statistics():
    (y1, u1), (y2, u2) = switched_data(2)
    runs = []
    for garbage in (0.0, 1.0):
        est = make(redesign_period=250, prefilter_initial=0.7)
        # the data before the change differ completely; the prefilter is set equal after it
        est.run(y1 + garbage * 100.0, u1 - garbage * 50.0)
        est.set_controller(*RETUNED.values())
        state = est.get_state()
        arrays = dict(state.arrays, prefilter=np.array([1.0, -0.7]))
        est.set_state(type(state)(state.estimator, arrays, dict(
            state.scalars, epoch_prefilters=[[1.0, -0.7]])))
        runs.append(est.run(y2, u2))
    np.testing.assert_array_equal(runs[0].theta, runs[1].theta)
    np.testing.assert_array_equal(runs[0].valid, runs[1].valid)


def test_the_first_estimate_after_a_change_comes_after_21_rows():
    (y1, u1), (y2, u2) = switched_data(3)
    est = make(prefilter_initial=0.7)
    est.run(y1, u1)
    est.set_controller(*RETUNED.values())

    def attempts():
        return est.redesigns + sum(est.flags.values())

    before = attempts()
    # n = 1 lag to fill, then 10 * 2n + n = 21 regression rows: the 22nd sample
    est.run(y2[:21], u2[:21])
    assert attempts() == before and est.window_length == 20
    est.run(y2[21:22], u2[21:22])
    assert attempts() == before + 1 and est.window_length == 21
    # then each time the rows double, up to redesign_period (1000) apart
    est.run(y2[22:], u2[22:])
    assert est.valid and relative_error(est.theta) < 0.2


def test_the_same_controller_again_restarts_nothing():
    y, u = PAPER.simulate(500, 4)
    est = make()
    est.run(y, u)
    theta = est.theta
    assert not est.set_controller([0.4578], [2.0, -0.18008], 'negative')
    assert est.controller_changes == 0 and est.valid
    np.testing.assert_array_equal(est.theta, theta)
    with pytest.raises(ValueError, match='controller_sign must be one of'):
        est.set_controller([0.1], [1.0, 0.0], 'sideways')
    assert est.controller_changes == 0


def test_snapshot_keeps_the_controller_and_the_moments():
    (y1, u1), (y2, u2) = switched_data(5)
    est = make(redesign_period=300)
    est.run(y1, u1)
    est.set_controller(*RETUNED.values())
    est.run(y2[:700], u2[:700])
    snapshot = est.get_state()
    first = est.run(y2[700:], u2[700:])
    other = make(redesign_period=300)
    other.set_state(snapshot)
    assert repr(other) == repr(est)
    second = other.run(y2[700:], u2[700:])
    np.testing.assert_array_equal(first.theta, second.theta)
    np.testing.assert_array_equal(first.valid, second.valid)


# --------------------------------------------------------------- validity
@pytest.mark.parametrize('window', [0, 2000])
def test_no_reference_is_never_valid(window):
    quiet = IkedaClosedLoop(reference_amplitude=0.0)
    for seed in range(5):
        y, u = quiet.simulate(6000, seed)
        est = make(window=window, redesign_period=500)
        trajectory = est.run(y, u)
        assert not trajectory.valid.any()
        assert 'no_excitation' in est.validity_reasons
        # a_c u + b_c y = b_c r = 0 up to rounding
        assert est.excitation_ratio < 1e-20


def excitation(est, y, u):
    """Return the excitation ratio of ``est`` after the samples."""
    est.run(y, u)
    return est.excitation_ratio


def test_the_excitation_ratio_does_not_depend_on_the_sign_convention_or_units():
    y, u = PAPER.simulate(3000, 6)
    est = make()
    est.run(y, u)
    flipped = make(controller_numerator=[-0.2289], controller_sign='positive')
    flipped.run(y, u)
    # the paper's loop: var(b_c r) / var(b_c y) about 0.24
    assert 0.1 < est.excitation_ratio < 0.5
    # the sign folds into the same feedback numerator: the same arithmetic, the same bits
    assert flipped.excitation_ratio == est.excitation_ratio

    # u = C (r - y) in new units: u * 1e4 = (C * 1e7) (r * 1e-3 - y * 1e-3)
    def ratio(y, u):
        return {'ratio': excitation(make(), y, u)}

    def scaled(y, u):
        return {'ratio': excitation(make(controller_numerator=[0.2289 * 1e7]), y * 1e-3,
                                    u * 1e4)}

    # the scaled run rounds its data and sums (a_c u + b_c y cancels the noise) its own
    # way: within the rounding spreads of both runs (test/equivalence.py)
    spread = two_path_spread(scaled, ratio, y, u)
    assert_paths_agree(scaled(y, u), ratio(y, u), spread, y.shape[0], 'excitation ratio')
    # one output moved by a ten-thousandth of its value in the scaled run: the bound sees it
    changed = y.copy()
    changed[1500] *= 1.0 + 1e-4
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(scaled(changed, u), ratio(y, u), spread, y.shape[0])


# False-alarm check: 10 seeds of the paper's loop at 6000 samples. Over 10 seeds at 20,000
# samples the last invalid sample was at most 558 (docs/cl_bcls.md); 2000 leaves room.
@pytest.mark.parametrize('seed', range(10))
def test_the_paper_loop_is_valid_once_converged(seed):
    y, u = PAPER.simulate(6000, seed)
    est = make()
    trajectory = est.run(y, u)
    assert trajectory.valid[2000:].all(), est.validity_reasons


def test_a_plant_the_controller_cannot_stabilise_is_not_valid():
    y, u = PAPER.simulate(2000, 4)
    est = make(redesign_period=500)
    est.run(y, u)
    assert est.valid
    est.set_controller([5.0], [1.0, 0.0])
    rng = np.random.default_rng(5)
    reference = np.repeat(rng.choice([-1.0, 1.0], 100), 10)
    # the data of an unstable loop made by the new controller: the LS estimate of the
    # loop is unstable, the redesigns fail
    plant = 0.0
    ys, us = [], []
    for k in range(reference.size):
        measured = plant + 0.1 * rng.standard_normal()
        control = 5.0 * (reference[k] - measured)
        ys.append(measured)
        us.append(control)
        plant = 0.8 * plant + 0.5 * control
        if abs(plant) > 1e6:
            break
    trajectory = est.run(np.array(ys), np.array(us))
    assert not trajectory.valid.any()
    assert np.isfinite(trajectory.theta).all()


def test_validity_reasons_name_each_check():
    y, u = PAPER.simulate(3000, 7)
    est = make()
    assert est.validity_reasons == ('not_compensated', 'no_excitation')
    est.run(y, u)
    assert est.validity_reasons == () and est.valid
    # an unstable compensated model in the loop, a runaway and a bad conditioning
    state = est.get_state()
    est.set_state(type(state)(state.estimator, dict(
        state.arrays, theta_bc=np.array([-3.0, 5.0])), state.scalars))
    est._check_model()
    assert est.validity_reasons == ('unstable_closed_loop', 'runaway_compensation')
    assert not est.valid
    assert cl.scaled_condition(np.diag([1e-9, 1e9])) == pytest.approx(1.0)
    assert cl.scaled_condition(np.array([[1.0, 1.0], [1.0, 1.0 + 1e-10]])) > cl.MAX_CONDITION
