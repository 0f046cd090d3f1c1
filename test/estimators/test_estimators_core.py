"""Unit and property tests of the estimator core: interface, regressor, RLS and BCRLS."""

import subprocess
import sys

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators import estimator_class, make_estimator, parameter_names, rules
from bcid_ros.estimators.adequacy import SHORT_MINIMUM
from bcid_ros.estimators.bcrls import bcls_fixed_point
from bcid_ros.estimators.blocks import BlockStopped
from bcid_ros.estimators.recursion import innovation, ls_step, repair_covariance
from bcid_ros.estimators.regressor import ArxRegressor
from bcid_ros.estimators.rls import ls_batch
from bcid_ros.simulation import make_scenario
from equivalence import assert_paths_agree, two_path_spread


def ding_data(samples, seed=1):
    """Return Ding's stationary MISO example: y, u and the true theta."""
    plant = make_scenario('ding_miso')
    y, u = plant.simulate(samples, seed)
    return y, u, plant.truth().parameters


def test_parameter_names_follow_the_spec():
    assert parameter_names(2, 2, False) == ('a1', 'a2', 'b1_1', 'b1_2', 'b2_1', 'b2_2')
    assert parameter_names(1, 1, True) == ('a1', 'b1_0', 'b1_1')


def test_regressor_by_hand():
    reg = ArxRegressor(order=2, num_inputs=1, feedthrough=True)
    samples = [(1.0, 10.0), (2.0, 20.0), (3.0, 30.0), (4.0, 40.0)]
    phis = [reg.push(y, np.array([u])) for y, u in samples]
    assert not ArxRegressor(2, 1, True).ready
    # phi(t) = [-y(t-1), -y(t-2), u(t), u(t-1), u(t-2)]
    np.testing.assert_array_equal(phis[2], [-2.0, -1.0, 30.0, 20.0, 10.0])
    np.testing.assert_array_equal(phis[3], [-3.0, -2.0, 40.0, 30.0, 20.0])
    assert reg.ready


def test_regressor_batch_form_equals_push():
    rng = np.random.default_rng(0)
    y, u = rng.standard_normal(50), rng.standard_normal((50, 3))
    for feedthrough in (False, True):
        reg = ArxRegressor(3, 3, feedthrough)
        pushed = [reg.push(y[t], u[t]) for t in range(50)][3:]
        np.testing.assert_array_equal(np.array(pushed), reg.regressors(y, u))


@pytest.mark.parametrize('feedthrough,delay',
                         [(False, None), (True, None), (False, (2, 0)), (True, (1, 3))])
def test_regressor_push_rows_equals_push(feedthrough, delay):
    rng = np.random.default_rng(1)
    rows = rng.standard_normal((300, 3))
    one, block = (ArxRegressor(2, 2, feedthrough, delay) for _ in range(2))
    expected = np.array([one.push(row[0], row[1:]) for row in rows])
    start, phis = 0, []
    for size in [1, 2, 3, 7, 1, 50, 4, 5, 9] * 10:
        phis.extend(block.push_rows(rows[start:start + size]))
        start = min(start + size, len(rows))
    np.testing.assert_array_equal(np.array(phis), expected[:len(phis)])
    assert len(phis) == start == len(rows)
    # the same state after: the next push gives the same phi
    np.testing.assert_array_equal(block.push(0.5, np.array([1.0, 2.0])),
                                  one.push(0.5, np.array([1.0, 2.0])))


def test_registry_refuses_unknown_estimator():
    with pytest.raises(ValueError, match="estimator must be one of rls, bcrls.*got 'lms'"):
        estimator_class('lms')


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
@pytest.mark.parametrize('setting, value, message', [
    ('order', 0, r'order must be an integer in \[1, 64\], got 0'),
    ('num_inputs', 1.5, r'num_inputs must be an integer in \[1, 64\], got 1.5'),
    ('forgetting_factor', 1.5, r'forgetting_factor must be in \(0, 1\], got 1.5'),
    ('forgetting_factor', 0.0, r'forgetting_factor must be in \(0, 1\], got 0.0'),
    ('initial_covariance', -1.0, r'initial_covariance must be in \(0, 1e\+15\], got -1.0'),
])
def test_constructor_validation_names_the_setting(name, setting, value, message):
    settings = {'order': 2, 'num_inputs': 1, setting: value}
    with pytest.raises(ValueError, match=message):
        make_estimator(name, **settings)


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
def test_bad_samples_are_refused_and_leave_the_state_alone(name):
    est = make_estimator(name, order=2, num_inputs=2)
    y, u, _ = ding_data(20)
    est.run(y, u)
    before = est.get_state()
    with pytest.raises(ValueError, match='u must have 2 elements, got 3'):
        est.update(0.0, [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match='NaN or Inf'):
        est.update(float('nan'), [1.0, 2.0])
    with pytest.raises(ValueError, match='NaN or Inf'):
        est.update(0.0, [float('inf'), 2.0])
    after = est.get_state()
    for key, value in before.arrays.items():
        np.testing.assert_array_equal(value, after.arrays[key])
    assert before.scalars == after.scalars


BLAS_CHECK = """
import sys
import numpy as np
from bcid_ros.estimators.blas import load_blas
kernels = load_blas()
assert 'scipy.linalg' not in sys.modules, 'the kernels imported all of scipy.linalg'
from scipy.linalg import blas
rng = np.random.default_rng(0)
a, x, y = rng.standard_normal((3, 3)), rng.standard_normal(3), rng.standard_normal(3)
calls = {'daxpy': (x, y.copy(), 3, 0.5), 'dscal': (0.5, x.copy()),
         'dger': (-1.0, x, y, 1, 1, a.T.copy(order='F'), 0, 0, 1),
         'dgemv': (0.5, a, x, 1.0, y, 0, 1, 0, 1, 1)}
for name, arguments in calls.items():
    mine = kernels[name](*[v.copy() if isinstance(v, np.ndarray) else v for v in arguments])
    theirs = getattr(blas, name)(*[v.copy() if isinstance(v, np.ndarray) else v
                                   for v in arguments])
    assert np.array_equal(mine, theirs), name
print('ok')
"""


def test_blas_kernels_load_without_scipy_linalg_and_equal_its_own():
    # A fresh process: this one imported scipy.linalg long ago (then the normal import is used).
    done = subprocess.run([sys.executable, '-c', BLAS_CHECK], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == 'ok', done.stderr


def test_blas_kernels_fall_back_to_scipy_linalg(monkeypatch):
    from scipy.linalg import blas

    from bcid_ros.estimators import blas as kernels

    def missing():
        raise ImportError('no extension file')

    assert kernels.fblas_module() is sys.modules['scipy.linalg._fblas']
    monkeypatch.setattr(kernels, '_fblas_from_file', missing)
    assert kernels.fblas_module() is blas


def test_rls_recovers_a_noise_free_arx_plant_with_feedthrough():
    # y(t) = 0.7 y(t-1) + 0.5 u(t) + 0.2 u(t-1): a1 = -0.7, b1_0 = 0.5, b1_1 = 0.2
    rng = np.random.default_rng(3)
    u = rng.standard_normal(40)
    y = signal.lfilter([0.5, 0.2], [1.0, -0.7], u)
    est = make_estimator('rls', order=1, num_inputs=1, feedthrough=True)
    est.run(y, u)
    # The prior P(0) = p0 S^-2 (S: power-of-two signal scales, here 2 and 4) pulls theta
    # towards 0 by about |theta| s^2 / (p0 N) = 0.7 * 16 / (1e6 * 40) ~ 3e-7.
    np.testing.assert_allclose(est.theta, [-0.7, 0.5, 0.2], atol=1e-6)
    assert_recursion_equals_batch(y, u, keys=('theta',), order=1, feedthrough=True)
    assert est.parameter_names == ('a1', 'b1_0', 'b1_1')


def recursion_figures(y, u, name='rls', **settings):
    """Return theta_LS, P, J and tau of the estimator ``name`` after the samples."""
    est = make_estimator(name, **settings)
    est.run(y, u)
    return {'theta': est.theta_uncompensated, 'covariance': est.covariance,
            'loss': est.loss, 'tau': est.weighted_count}


def batch_figures(y, u, prior, **settings):
    """Return what :func:`recursion_figures` returns, from the batch solution (ls_batch)."""
    theta, p, loss, tau = ls_batch(y, u, initial_covariance=prior, **settings)
    updates = y.shape[0] - settings['order']
    # J of eq. (50) is the minimum of the regularised cost, which adds
    # lambda^N' theta' P0^-1 theta to the residual sum of squares.
    regularisation = settings.get('forgetting_factor', 1.0) ** updates * float(
        theta @ (theta / prior))
    return {'theta': theta, 'covariance': p, 'loss': loss + regularisation, 'tau': tau}


def assert_recursion_equals_batch(y, u, keys=('theta', 'covariance', 'loss', 'tau'),
                                  name='rls', recursion_y=None, **settings):
    """
    Assert that the recursion (47)-(50) on y, u ends at the batch LS solution of the same data.

    A rank-1 update per sample and one solve of the normal equations are two
    arithmetic paths: they agree within the rounding spreads of both
    (test/equivalence.py), which hold the ill-conditioned start of the
    recursion, plus the summation term of the N' updates. ``recursion_y``
    feeds the recursion other outputs (the test that the bound sees a change).
    """
    prior = make_estimator(name, **settings)
    prior.run(y, u)
    prior = prior.initial_covariance_diagonal

    def recursion(y, u):
        figures = recursion_figures(y, u, name, **settings)
        return {key: figures[key] for key in keys}

    def batch(y, u):
        figures = batch_figures(y, u, prior, **settings)
        return {key: figures[key] for key in keys}

    spread = two_path_spread(recursion, batch, y, u)
    assert_paths_agree(recursion(y if recursion_y is None else recursion_y, u), batch(y, u),
                       spread, y.shape[0] - settings['order'], name)


@pytest.mark.parametrize('samples', [50, 1000, 5000])
@pytest.mark.parametrize('lam', [1.0, 0.99])
def test_rls_equals_batch_least_squares(samples, lam):
    y, u, _ = ding_data(samples)
    assert_recursion_equals_batch(y, u, order=2, num_inputs=2, forgetting_factor=lam)


def test_the_batch_bound_catches_one_changed_sample():
    # one output changed by a ten-thousandth of its value in the recursion only: far
    # below the noise, far above rounding; the comparison with the batch must fail
    y, u, _ = ding_data(1000)
    changed = y.copy()
    changed[500] *= 1.0 + 1e-4
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_recursion_equals_batch(y, u, recursion_y=changed, order=2, num_inputs=2)


@pytest.mark.parametrize('samples', [1000, 3000, 10000])
def test_bcrls_tracks_the_batch_bcls_fixed_point(samples):
    y, u, truth = ding_data(samples, seed=2)
    est = make_estimator('bcrls', order=2, num_inputs=2)
    est.run(y, u)
    theta_c, sigma2, theta_ls = bcls_fixed_point(y, u, order=2, num_inputs=2)
    # The recursion uses theta_c(t-1) where the fixed point uses theta_c itself; the
    # gap (measured 1e-6..3e-5) must be far below the estimation error (~1e-2).
    assert np.abs(est.theta - theta_c).max() < 1e-4
    assert np.abs(est.theta - theta_c).max() < 0.01 * np.linalg.norm(theta_c - truth)
    # theta_LS without the prior p0 S^-2: the prior's pull, ~ |theta| s^2 / (p0 N) < 1e-8,
    # is the only difference beyond rounding (the rounding: the test just below)
    np.testing.assert_allclose(est.theta_uncompensated, theta_ls, atol=1e-7)
    assert est.sigma2 == pytest.approx(sigma2, rel=1e-3)
    # bcrls's LS part is the RLS recursion: it ends at the regularised batch solution
    assert_recursion_equals_batch(y, u, keys=('theta',), name='bcrls', order=2, num_inputs=2)


def test_bcrls_without_forgetting_is_the_paper_recursion():
    """Check eqs. (46)-(51) against a literal transcription on a short record."""
    y, u, _ = ding_data(200, seed=4)
    est = make_estimator('bcrls', order=2, num_inputs=2)
    est.run(y, u)
    prior = est.initial_covariance_diagonal

    def estimator(y, u):
        est = make_estimator('bcrls', order=2, num_inputs=2)
        est.run(y, u)
        return {'theta': est.theta, 'sigma2': est.sigma2}

    def transcription(y, u):
        phi = ArxRegressor(2, 2, False).regressors(y, u)
        lam = np.diag([1.0, 1.0, 0, 0, 0, 0])
        p = np.diag(prior)
        theta_ls, theta_c, loss = np.zeros(6), np.zeros(6), 0.0
        for t, (row, target) in enumerate(zip(phi, y[2:]), start=1):
            gain = p @ row / (1 + row @ p @ row)
            loss += (target - row @ theta_ls) ** 2 / (1 + row @ p @ row)
            theta_ls = theta_ls + gain * (target - row @ theta_ls)
            p = (np.eye(6) - np.outer(gain, row)) @ p
            sigma2 = loss / (t * (1 + theta_c @ lam @ theta_ls))
            theta_c = theta_ls + t * sigma2 * p @ lam @ theta_c
        return {'theta': theta_c, 'sigma2': sigma2}

    # two arithmetic paths (the transcription's P update is not even symmetric): within
    # the rounding spreads of both (test/equivalence.py)
    assert_paths_agree(estimator(y, u), transcription(y, u),
                       two_path_spread(estimator, transcription, y, u), 198, 'bcrls')


def test_bcrls_with_forgetting_stays_consistent_on_stationary_data():
    # With lambda = 0.999 the effective window is ~1000 samples: the compensated
    # estimate must still be far less biased than LS over the same window.
    y, u, truth = ding_data(20000, seed=5)
    est = make_estimator('bcrls', order=2, num_inputs=2, forgetting_factor=0.999)
    trajectory = est.run(y, u)
    late = slice(5000, None, 500)
    err_bc = np.linalg.norm(trajectory.theta[late] - truth, axis=1).mean()
    err_ls = np.linalg.norm(trajectory.theta_uncompensated[late] - truth, axis=1).mean()
    assert err_bc < 0.5 * err_ls
    assert est.sigma2 == pytest.approx(0.01, rel=0.15)


def test_rls_with_forgetting_keeps_p_symmetric_positive_definite_for_long():
    y, u, truth = ding_data(60000, seed=6)
    est = make_estimator('rls', order=2, num_inputs=2, forgetting_factor=0.95)
    est.run(y, u)
    p = est.covariance
    assert np.array_equal(p, p.T)
    assert np.linalg.eigvalsh(p).min() > 0
    assert np.isfinite(est.theta).all()
    assert np.linalg.norm(est.theta - truth) < 0.2


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
def test_no_excitation_does_not_wind_up(name):
    est = make_estimator(name, order=2, num_inputs=2, forgetting_factor=0.9)
    y, u, _ = ding_data(500)
    est.run(y, u)
    est.run(np.zeros(20000), np.zeros((20000, 2)))
    assert np.isfinite(est.theta).all() and np.isfinite(est.noise).all()
    # The bound on the normalised trace tr(S P S) is p0 * p (plus one step of 1/lambda);
    # S^2 = p0 / diag P(0).
    normalised = np.diag(est.covariance) * (1e6 / est.initial_covariance_diagonal)
    assert normalised.sum() <= 1e6 * 6 / 0.9
    assert est.flags.get('windup_limited', 0) > 0


def test_bcrls_denominator_breakdown_is_flagged_and_finite():
    y, u, _ = ding_data(300)
    est = make_estimator('bcrls', order=2, num_inputs=2)
    est.run(y, u)
    state = est.get_state()
    sigma2 = est.sigma2
    arrays = dict(state.arrays)
    # theta_c(t-1) with a = (+50, 0) makes 1 + theta_c' Lambda theta_LS < 0.
    arrays['theta_c'] = np.array([50.0, 0.0, 0.1, 0.3, 0.2, 0.2])
    est.set_state(type(state)(state.estimator, arrays, state.scalars))
    est.update(y[0], u[0])
    assert est.flags['sigma2_denominator'] == 1
    assert est.sigma2 == sigma2
    assert np.isfinite(est.theta).all()


def test_bcrls_runaway_compensation_restarts_from_ls():
    y, u, _ = ding_data(300)
    est = make_estimator('bcrls', order=2, num_inputs=2)
    est.run(y, u)
    state = est.get_state()
    # 1 + theta_c' Lambda theta_LS < 0 keeps sigma2, and P Lambda theta_c ~ 1e297 runs away.
    arrays = dict(state.arrays, theta_c=np.array([1e300, 1e300, 0, 0, 0, 0]))
    est.set_state(type(state)(state.estimator, arrays, state.scalars))
    with np.errstate(over='ignore', invalid='ignore'):
        est.update(y[1], u[1])
    assert est.flags == {'sigma2_denominator': 1, 'compensation_reset': 1}
    np.testing.assert_array_equal(est.theta, est.theta_uncompensated)


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
def test_snapshot_restore_and_reset_replay_exactly(name):
    y, u, _ = ding_data(1000)
    est = make_estimator(name, order=2, num_inputs=2)
    est.run(y[:500], u[:500])
    snapshot = est.get_state()
    first = est.run(y[500:], u[500:]).theta
    est.set_state(snapshot)
    np.testing.assert_array_equal(est.run(y[500:], u[500:]).theta, first)
    est.reset()
    fresh = make_estimator(name, order=2, num_inputs=2)
    np.testing.assert_array_equal(est.run(y, u).theta, fresh.run(y, u).theta)
    # The snapshot holds copies: running on did not change it.
    assert snapshot.scalars['updates'] == 498


def test_set_state_refuses_a_foreign_snapshot():
    rls = make_estimator('rls', order=2, num_inputs=2)
    bcrls = make_estimator('bcrls', order=2, num_inputs=2)
    with pytest.raises(ValueError, match="state is from estimator 'rls', not 'bcrls'"):
        bcrls.set_state(rls.get_state())
    other = make_estimator('rls', order=3, num_inputs=2)
    with pytest.raises(ValueError, match="state array 'theta_ls' does not match"):
        other.set_state(rls.get_state())


def test_validity_waits_for_the_regressor_p_updates_and_the_residual_tests():
    est = make_estimator('bcrls', order=2, num_inputs=2)
    y, u, _ = ding_data(1000)
    valid, ready, reasons = [], [], []
    for t in range(1000):
        valid.append(est.update(y[t], u[t]))
        ready.append(est.ready)
        reasons.append(est.validity_reasons)
    # 2 samples fill the lags, then p = 6 updates: ready from sample 8 on; the residual
    # tests start at the gate's warm-up (60 updates) and judge once they have SHORT_MINIMUM
    # samples (with fewer lags until the window is full), at the next validity check:
    # until then that is the reason
    assert ready == [False] * 7 + [True] * 993
    first = valid.index(True)
    assert (7 + 60 + SHORT_MINIMUM <= first < 7 + 60 + SHORT_MINIMUM + rules.VALIDITY_PERIOD
            and all(valid[first:]))
    assert reasons[7][0].startswith('residual tests not ready')
    assert all(r and r[0].startswith('residual tests not ready') for r in reasons[7:first])
    est.restart_regressor()
    assert est.samples == 998
    est.update(y[0], u[0])
    est.update(y[1], u[1])
    assert est.samples == 998  # no regression over the gap
    est.update(y[2], u[2])
    assert est.samples == 999


@pytest.mark.parametrize('seed', range(12))
def test_random_stable_plants_stay_finite_and_p_positive_definite(seed):
    """Property test: random stable MISO plants, noise levels, settings."""
    rng = np.random.default_rng(1000 + seed)
    order, inputs = int(rng.integers(1, 4)), int(rng.integers(1, 4))
    feedthrough = bool(rng.integers(0, 2))
    poles = rng.uniform(0.1, 0.95, order) * rng.choice([-1, 1], order)
    alpha = np.poly(poles)
    u = rng.standard_normal((3000, inputs)) * rng.uniform(0.01, 100)
    y = np.zeros(3000)
    for i in range(inputs):
        b = rng.standard_normal(order + 1)
        if not feedthrough:
            b[0] = 0.0
        y += signal.lfilter(b, alpha, u[:, i])
    y += rng.uniform(0, 2) * y.std() * rng.standard_normal(3000)
    lam = float(rng.choice([1.0, 0.99, 0.9]))
    for name in ('rls', 'bcrls'):
        est = make_estimator(name, order=order, num_inputs=inputs, feedthrough=feedthrough,
                             forgetting_factor=lam)
        trajectory = est.run(y, u)
        assert np.isfinite(trajectory.theta).all()
        assert np.isfinite(trajectory.noise).all()
        assert (trajectory.noise >= 0).all()
        p = est.covariance
        assert np.array_equal(p, p.T)
        assert np.linalg.eigvalsh(p).min() > 0


def test_repr_is_one_line():
    text = repr(make_estimator('bcrls', order=2, num_inputs=2))
    assert text == 'Bcrls(order=2, num_inputs=2, feedthrough=False, forgetting_factor=1.0)'


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
def test_update_block_equals_update(name):
    y, u, _ = ding_data(500)
    rows = np.column_stack([y, u])
    checked = make_estimator(name, order=2, num_inputs=2)
    blocks = make_estimator(name, order=2, num_inputs=2)
    for t in range(500):
        checked.update(y[t], u[t])
    taken = [blocks.update_block(rows[first:first + 37]) for first in range(0, 500, 37)]
    assert sum(taken) == 500
    np.testing.assert_array_equal(checked.theta, blocks.theta)
    np.testing.assert_array_equal(checked.noise, blocks.noise)


@pytest.mark.parametrize('bad', [np.nan, np.inf])
def test_update_block_refuses_a_block_with_nan_or_inf_and_takes_nothing(bad):
    y, u, _ = ding_data(50)
    rows = np.column_stack([y, u])
    est = make_estimator('rls', order=2, num_inputs=2)
    est.update_block(rows[:20])
    before = est.get_state()
    spoiled = rows[20:].copy()
    spoiled[7, 1] = bad
    with pytest.raises(ValueError, match='NaN or Inf'):
        est.update_block(spoiled)
    with pytest.raises(ValueError, match='1 \\+ num_inputs = 3'):
        est.update_block(rows[20:, :2])
    after = est.get_state()
    for key, value in before.arrays.items():
        np.testing.assert_array_equal(value, after.arrays[key])


def test_a_row_that_raises_ends_the_block_and_says_how_many_were_taken():
    y, u, _ = ding_data(50)
    est = make_estimator('rls', order=2, num_inputs=2)
    calls = []

    def failing(y, u):
        calls.append(y)
        if len(calls) == 8:
            raise RuntimeError('broken')

    est._block_step = lambda rows: failing
    with pytest.raises(BlockStopped) as stopped:
        est.update_block(np.column_stack([y, u]))
    assert stopped.value.taken == 7
    assert isinstance(stopped.value.error, RuntimeError)
    assert stopped.value.__cause__ is stopped.value.error


def test_the_rls_step_functions_are_the_textbook_step():
    rng = np.random.default_rng(8)
    a = rng.standard_normal((6, 6))
    p = a @ a.T + np.eye(6)
    theta, phi, y, lam = rng.standard_normal(6), rng.standard_normal(6), 0.7, 0.98

    def functions(theta, p, phi, y):
        e, g, s = innovation(theta, p, phi, float(y), lam)
        theta = theta.copy()
        new_p = ls_step(theta, p.copy(), g, s, e)
        return {'e': e, 's': s, 'theta': theta, 'p': new_p}

    def textbook(theta, p, phi, y):
        s = lam + phi @ p @ phi
        gain = p @ phi / s
        e = y - phi @ theta
        return {'e': e, 's': s, 'theta': theta + gain * e, 'p': p - np.outer(gain, phi @ p)}

    # BLAS axpy/ger against numpy's products: two paths, within the rounding spread of both
    data = (theta, p, phi, np.array(y))
    spread = two_path_spread(functions, textbook, *data)
    assert_paths_agree(functions(*data), textbook(*data), spread, 1, 'one step')
    # one entry of phi moved by 1e-9 of its size: far above rounding, the bound sees it
    moved = phi.copy()
    moved[3] *= 1.0 + 1e-9
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(functions(theta, p, moved, y), textbook(*data), spread, 1)
    new_p = functions(*data)['p']
    assert np.array_equal(new_p, new_p.T)  # one path: p_ij - h_i h_j is p_ji - h_j h_i


def test_repair_covariance_returns_a_positive_definite_matrix():
    broken = np.diag([1e6, 1.0, -1e-3])
    repaired = repair_covariance(broken, np.eye(3))
    assert np.linalg.eigvalsh(repaired).min() > 0
    np.testing.assert_allclose(np.diag(repaired)[:2], [1e6, 1.0])
    fallback = 5.0 * np.eye(3)
    np.testing.assert_array_equal(repair_covariance(np.full((3, 3), np.nan), fallback), fallback)
