"""
Unit tests of the BCIV estimator (Ikenoue et al. 2008) and its batch reference.

The solver against the paper's equations written out: test_bciv_speed_equivalence.py.
"""

import inspect

import numpy as np
import pytest

from bcid_ros.estimators import ESTIMATORS, make_estimator
from bcid_ros.estimators.bciv import (Bciv, bciv_batch, BcivSolver, DEFAULT_TOLERANCE,
                                      published_noise)
from bcid_ros.simulation import make_scenario
from equivalence import assert_paths_agree, two_path_spread

COLORED = {'input_noise': 'colored', 'iv_lag': 5}
WHITE = {'input_noise': 'white', 'iv_lag': 4}


def section(name, samples, seed=11, **settings):
    """Return (z, w, truth) of an Ikenoue scenario."""
    plant = make_scenario(name, **settings)
    z, w = plant.simulate(samples, seed)
    return z, w[:, 0], plant.truth()


# ---------------------------------------------------------------- validation
@pytest.mark.parametrize('settings, message', [
    ({'num_inputs': 2}, r'num_inputs must be 1 for bciv .*got 2'),
    ({'iv_lag': 0}, r'iv_lag must be an integer in \[1, 1000\], got 0'),
    ({'input_noise': 'pink'}, r"input_noise must be 'colored' or 'white', got 'pink'"),
    ({'bciv_update': 'fast'}, r"bciv_update must be 'converged' or 'printed', got 'fast'"),
    ({'idle_samples': -1}, r'idle_samples must be an integer in \[0, 1e\+09\], got -1'),
    ({'bciv_iterations': 0}, r'bciv_iterations must be an integer in \[1, 10000\], got 0'),
    ({'tolerance': -1.0}, r'tolerance must be in \[0, 1\], got -1.0'),
    ({'allow_underdetermined': 'yes'}, r"allow_underdetermined must be true or false, got 'yes'"),
    ({'forgetting_factor': 0.0}, r'forgetting_factor must be in \(0, 1\], got 0.0'),
    ({'iv_weight': np.eye(3)}, r'iv_weight must have shape \(12, 12\), got \(3, 3\)'),
    ({'noise_weight': -np.eye(12)}, r'noise_weight must be symmetric positive definite'),
])
def test_constructor_validation_names_the_setting(settings, message):
    with pytest.raises(ValueError, match=message):
        make_estimator('bciv', order=2, **settings)


def test_underdetermined_colored_lag_is_refused_with_the_count():
    # n = 2, l = 3: m = 8 equations against 2n + (n + l) = 9 unknowns.
    message = (r'iv_lag must be >= 4 for order 2 with colored input noise, got 3: eq\. \(72\) '
               r'then has m = n \+ 2l = 8 equations for 9 unknowns \(4 parameters and 5 noise '
               r'covariances\), so it is under-determined; set allow_underdetermined')
    with pytest.raises(ValueError, match=message):
        Bciv(order=2, iv_lag=3)
    assert Bciv(order=2, iv_lag=3, allow_underdetermined=True).noise_names == tuple(
        f'r_dd{k}' for k in range(5))
    Bciv(order=2, iv_lag=4)  # l = 2n is enough


def test_white_input_noise_needs_one_more_equation_than_parameters():
    # n = 2, l = 1: m = 4 = 2n, so sigma_d^2 is left free (every value is a fixed point).
    with pytest.raises(ValueError, match=r'iv_lag must be >= 2 .*white input noise, got 1'):
        Bciv(order=2, iv_lag=1, input_noise='white')
    Bciv(order=2, iv_lag=2, input_noise='white')
    # Too short for eq. (38) itself: refused even when under-determination is allowed.
    with pytest.raises(ValueError, match=r'fewer than the 8 parameters of eq\. \(38\)'):
        Bciv(order=4, iv_lag=1, allow_underdetermined=True)


def test_names_and_repr():
    colored = Bciv(order=2, iv_lag=5)
    assert colored.parameter_names == ('a1', 'a2', 'b1_1', 'b1_2')
    assert colored.noise_names == tuple(f'r_dd{k}' for k in range(7))
    assert Bciv(order=2, **WHITE).noise_names == ('sigma2_d',)
    # the registry is the one list of the ROS options; each is a constructor keyword
    options = ESTIMATORS['bciv'].option_names
    assert options == ('iv_lag', 'input_noise', 'idle_samples', 'bciv_iterations',
                       'bciv_update', 'allow_underdetermined')
    assert set(options) <= set(inspect.signature(Bciv).parameters)
    assert repr(colored) == ("Bciv(order=2, iv_lag=5, input_noise='colored', "
                             "bciv_update='converged', bciv_iterations=20, idle_samples=100, "
                             'forgetting_factor=1.0)')


# -------------------------------------------------- recursive == batch
def assert_recursion_equals_batch(z, w, checkpoints, settings, recursion_z=None):
    """
    Assert that the recursive estimates after ``checkpoints`` samples are bciv_batch's.

    Moments summed sample by sample against summed at once, then the same
    solver: two arithmetic paths, within the rounding spreads of both
    (test/equivalence.py). With white input noise both also stop the secant
    method once a step moves theta by less than ``tolerance``, from other
    starts (the recursion from its last fixed point): with the contraction
    rate below 0.8 on these data (0.75, test_bciv_speed_equivalence.py) each
    end is within tolerance / (1 - 0.8) of the root, so theta may differ by
    10 tolerance, and since theta - theta_IV = N sigma_d^2 G E b (eq. 53),
    sigma_d^2 by that over |G E b|. ``recursion_z`` feeds the recursion other
    outputs (the test that the bound sees a change).
    """
    rows = [t - 1 for t in checkpoints]

    def recursion(z, w):
        trajectory = Bciv(order=2, **settings).run(z, w)
        return {'theta': trajectory.theta[rows], 'theta_iv': trajectory.theta_uncompensated[rows],
                'noise': trajectory.noise[rows]}

    def batch(z, w):
        result = bciv_batch(z, w, order=2, checkpoints=checkpoints, **settings)
        return {'theta': result.theta, 'theta_iv': result.theta_iv,
                'noise': np.array([published_noise(noise) for noise in result.noise])}

    expected = batch(z, w)
    allowance = {}
    if settings.get('input_noise') == 'white':
        stop = 10 * settings.get('tolerance', DEFAULT_TOLERANCE)
        allowance['theta'] = stop
        shift = np.linalg.norm(expected['theta'] - expected['theta_iv'], axis=1)
        noise = np.abs(expected['noise']).max(axis=1)
        # (no compensation, theta = theta_IV: no secant ran, nothing to allow)
        allowance['noise'] = np.divide(stop * noise, shift, out=np.zeros_like(noise),
                                       where=shift > 0.0)
    assert_paths_agree(recursion(z if recursion_z is None else recursion_z, w), expected,
                       two_path_spread(recursion, batch, z, w), checkpoints[-1], 'bciv',
                       allowance)


@pytest.mark.slow
@pytest.mark.parametrize('name, settings', [('ikenoue_colored', COLORED),
                                            ('ikenoue_white_input', WHITE)])
def test_recursive_equals_batch(name, settings):
    z, w, _ = section(name, 10000, seed=5)
    checkpoints = (2000, 5000, 10000)
    trajectory = Bciv(order=2, **settings).run(z, w)
    assert_recursion_equals_batch(z, w, checkpoints, settings)
    # Updates start when the window of m samples is full (sample m - 1, 0-based);
    # ready after L = 100 updates, valid once converged (a fifth of the run).
    first_ready = 100 + (2 + 2 * settings['iv_lag']) - 2
    assert trajectory.ready[first_ready:].all() and not trajectory.ready[:first_ready].any()
    assert not trajectory.valid[:first_ready].any() and trajectory.valid[2000:].all()


@pytest.mark.parametrize('name, settings', [('ikenoue_colored', COLORED),
                                            ('ikenoue_white_input', WHITE)])
def test_recursive_equals_batch_with_forgetting_and_idle(name, settings):
    z, w, _ = section(name, 1500, seed=6)
    settings = dict(settings, forgetting_factor=0.995, idle_samples=300)
    trajectory = Bciv(order=2, **settings).run(z, w)
    batch = bciv_batch(z, w, order=2, checkpoints=(200, 1500), **settings)
    # During the idle period the estimate is theta_IV.
    np.testing.assert_array_equal(trajectory.theta[199], trajectory.theta_uncompensated[199])
    np.testing.assert_array_equal(batch.theta[0], batch.theta_iv[0])
    assert_recursion_equals_batch(z, w, (200, 1500), settings)


def test_the_batch_bound_catches_one_changed_sample():
    # one output changed by a ten-thousandth of its value in the recursion only
    z, w, _ = section('ikenoue_colored', 1500, seed=6)
    changed = z.copy()
    changed[700] *= 1.0 + 1e-4
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_recursion_equals_batch(z, w, (1500,), COLORED, recursion_z=changed)


def test_colored_estimate_is_k_steps_from_iv_not_warm_started():
    z, w, _ = section('ikenoue_colored', 3000)
    est = Bciv(order=2, **COLORED)
    est.run(z, w)
    assert est.last_iterations == 20
    fresh = bciv_batch(z, w, order=2, **COLORED)
    assert_recursion_equals_batch(z, w, (3000,), COLORED)
    # Twice K steps from theta_IV moves only along the neutral direction, a little.
    longer = bciv_batch(z, w, order=2, bciv_iterations=40, **COLORED)
    assert 0 < np.abs(longer.theta[0] - fresh.theta[0]).max() < 5e-3


def test_printed_recursion_makes_one_alternation_per_sample():
    z, w, _ = section('ikenoue_colored', 2000)
    est = Bciv(order=2, bciv_update='printed', **COLORED)
    trajectory = est.run(z, w)
    assert est.last_iterations == 1
    assert np.isfinite(trajectory.theta).all()
    assert np.abs(trajectory.theta[-1] - bciv_batch(z, w, order=2, **COLORED).theta[0]).max() > 0


# -------------------------------------------------------- failure modes
@pytest.mark.parametrize('settings', [COLORED, WHITE, dict(COLORED, bciv_update='printed')])
def test_fallback_on_zero_b_and_recovery(settings):
    # No input for the first 400 samples: every moment is zero, so b_IV = 0 and
    # Q~'XQ~ = 0. The estimate must fall back to theta_IV, flag it, and recover.
    z, w, truth = section('ikenoue_colored' if settings is not WHITE else
                          'ikenoue_white_input', 6000, seed=3)
    w = w.copy()
    w[:400] = 0.0
    est = Bciv(order=2, idle_samples=20, **settings)
    trajectory = est.run(z[:400], w[:400])
    # 400 - m + 1 updates, compensated from update L = 20 on
    assert est.flags['fallback_iv'] == (400 - est._solver.m + 1) - 20 + 1
    assert est.flags['noise_system_singular'] == est.flags['fallback_iv']
    np.testing.assert_array_equal(trajectory.theta, trajectory.theta_uncompensated)
    trajectory = est.run(z[400:3000], w[400:3000])
    after = est.flags['fallback_iv']
    assert np.isfinite(trajectory.theta).all() and np.isfinite(trajectory.noise).all()
    est.run(z[3000:], w[3000:])
    assert est.flags['fallback_iv'] == after  # recovered: no new fallbacks
    if settings.get('bciv_update') != 'printed':
        # ... and back on the regular estimate of all the data.
        assert_recursion_equals_batch(z, w, (6000,), dict(settings, idle_samples=20))
    # a is identified whatever the path; the printed recursion's b can drift along the
    # neutral direction (the gain of B, docs/bciv.md), so only a is checked against the truth.
    assert np.abs(est.theta[:2] - truth.parameters[:2]).max() < 0.25


def test_ill_conditioned_noise_system_falls_back(monkeypatch):
    z, w, _ = section('ikenoue_colored', 600)
    monkeypatch.setattr('bcid_ros.estimators.bciv.solver.CONDITION_MAX', 1.0)
    est = Bciv(order=2, idle_samples=0, **COLORED)
    trajectory = est.run(z, w)
    assert est.flags['fallback_iv'] == est.samples
    np.testing.assert_array_equal(trajectory.theta, trajectory.theta_uncompensated)


@pytest.mark.parametrize('seed', range(4))
def test_random_data_never_give_nan(seed):
    rng = np.random.default_rng(seed)
    count = 800
    scale = 10.0 ** rng.uniform(-6, 6)
    z = scale * rng.standard_normal(count) * rng.uniform(0, 3)
    w = scale * rng.standard_normal(count)
    w[rng.integers(0, count, 200)] = 0.0
    z[:100] = 0.0
    for settings in (COLORED, WHITE, dict(COLORED, bciv_update='printed'),
                     dict(COLORED, iv_lag=2, allow_underdetermined=True)):
        est = Bciv(order=int(rng.integers(1, 3)), idle_samples=int(rng.integers(0, 50)),
                   forgetting_factor=float(rng.choice([1.0, 0.98])), **settings)
        trajectory = est.run(z, w)
        assert np.isfinite(trajectory.theta).all()
        assert np.isfinite(trajectory.theta_uncompensated).all()
        assert np.isfinite(trajectory.noise).all()
        assert np.isfinite(est.covariance_trace)


def test_huge_samples_reset_the_moments_instead_of_nan():
    est = Bciv(order=2, idle_samples=0, **COLORED)
    z, w, _ = section('ikenoue_colored', 300)
    est.run(z, w)
    with np.errstate(over='ignore', invalid='ignore'):
        est.run(np.full(30, 1e200), np.full(30, 1e200))
    assert est.flags.get('moments_reset', 0) > 0
    assert np.isfinite(est.theta).all() and np.isfinite(est.noise).all()


# ------------------------------------------------------------- the state
@pytest.mark.parametrize('settings', [COLORED, WHITE, dict(WHITE, bciv_update='printed')])
def test_snapshot_restore_and_reset_replay_exactly(settings):
    z, w, _ = section('ikenoue_colored', 1200)
    est = Bciv(order=2, **settings)
    est.run(z[:600], w[:600])
    snapshot = est.get_state()
    first = est.run(z[600:], w[600:])
    est.set_state(snapshot)
    again = est.run(z[600:], w[600:])
    np.testing.assert_array_equal(again.theta, first.theta)
    np.testing.assert_array_equal(again.noise, first.noise)
    est.reset()
    fresh = Bciv(order=2, **settings)
    np.testing.assert_array_equal(est.run(z, w).theta, fresh.run(z, w).theta)
    assert snapshot.scalars['updates'] == 600 - (2 + 2 * settings['iv_lag']) + 1


def test_restart_regressor_skips_the_gap():
    z, w, _ = section('ikenoue_colored', 200)
    est = Bciv(order=2, **COLORED)
    est.run(z[:100], w[:100])
    assert est.samples == 100 - 11
    est.restart_regressor()
    est.run(z[100:111], w[100:111])
    assert est.samples == 89  # the window of m = 12 samples is not full yet
    est.update(z[111], w[111])
    assert est.samples == 90


@pytest.mark.parametrize('rho', [1e-2, 1.0, 1e6])
def test_theta_iv_is_step_1_with_m0_rho(rho):
    # theta_IV,N of Step 1 with M_0 = rho I and theta_IV,0 = 0 sums to
    # (rho^-1 D^2 + S'S)^-1 S's (D: the units' power-of-two scales); early on (N < p) only
    # the rho term makes it unique.
    z, w, _ = section('ikenoue_colored', 40)
    est = Bciv(order=2, initial_covariance=rho, idle_samples=1000, **COLORED)
    trajectory = est.run(z, w)
    solver = BcivSolver(order=2, iv_lag=5, feedthrough=False, input_noise='colored')
    eta, pz = solver.data_windows(z, w)
    for updates in (1, 3, 29):
        s_p, s = eta[:updates].T @ pz[:updates, :4], eta[:updates].T @ -pz[:updates, 4]
        # M_0 = rho I in the units of z and w divided by their power-of-two scales
        phi = np.diag(1.0 / est.initial_covariance_diagonal) + s_p.T @ s_p
        expected = np.linalg.solve(phi, s_p.T @ s)
        # Both solves lose about cond(Phi) * eps (cond ~ 1e10 at rho = 1e6, N = 1).
        tolerance = max(1e-9, 1e-14 * np.linalg.cond(phi))
        np.testing.assert_allclose(trajectory.theta_uncompensated[updates + 10], expected,
                                   rtol=tolerance, atol=1e-12)


def test_a_negative_variance_estimate_is_flagged_and_published_as_zero():
    # Seed 5, white input noise, l = 4: sigma_d^2 comes out at -1.11 at sample 2000
    # (the white-case variance estimate is that noisy at 2000 samples).
    z, w, _ = section('ikenoue_white_input', 2000, seed=5)
    est = Bciv(order=2, input_noise='white', iv_lag=4)
    est.run(z, w)
    raw = bciv_batch(z, w, order=2, input_noise='white', iv_lag=4).noise[0]
    assert raw[0] < 0
    assert est.flags['negative_variance'] > 0
    np.testing.assert_array_equal(est.noise, [0.0])
    np.testing.assert_array_equal(published_noise(np.array([-0.5, -0.2])), [0.0, -0.2])
