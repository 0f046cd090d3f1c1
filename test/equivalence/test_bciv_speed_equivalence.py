"""
The fast BCIV solver computes the paper's equations: compared with them written out densely.

:func:`dense_bciv` is the reference: Steps 1, 3 and 4 of the recursive algorithm
(eqs. 38, 75, 53), with Q~ built entry by entry from eqs. (59)/(61) and (66)
and every product and solve written as in the paper. The fast path
(:class:`~bcid_ros.estimators.bciv.BcivSolver` and the per-sample
:class:`~bcid_ros.estimators.bciv.Bciv`) is compared with it in the same test
run, never with numbers saved elsewhere: numpy and BLAS pick SIMD kernels at run
time, so last bits differ between CPUs. Tolerances follow from rounding: a
backward-stable solve loses at most (condition number) x (m eps) relative, with
m eps covering the m-term inner products that form the matrices (Higham's gamma_m).
"""

from typing import NamedTuple

import numpy as np
import pytest

from bcid_ros.estimators.bciv import (Bciv, BcivSolver, CHECK_PERIOD, DEFAULT_TOLERANCE,
                                      RING_SAMPLES)
from bcid_ros.simulation import make_scenario

EPS = np.finfo(float).eps


# ------------------------------------------------------- the reference
def q_tilde_entrywise(b, order, lag, white, feedthrough=False):
    """Build Q~ of eq. (61) (colored) or eq. (66) (white) entry by entry."""
    m = order + 2 * lag
    lags = range(0 if feedthrough else 1, order + 1)
    if white:
        # Q~ = b~ = [0_l; b; 0_l]; with b_0 (feedthrough) the b block starts one row higher
        q = np.zeros((m, 1))
        for k, value in zip(lags, b):
            q[lag - 1 + k, 0] = value
        return q
    # (Q~ gamma~)_i = sum_k b_k r_dd(|l - 1 - i + k|), 0-based row i, lag k (eqs. 59-61)
    q = np.zeros((m, order + lag + (1 if feedthrough else 0)))
    for i in range(m):
        for k, value in zip(lags, b):
            q[i, abs(lag - 1 - i + k)] += value
    return q


class Dense(NamedTuple):
    """What :func:`dense_bciv` returns: the estimate and the numbers its tolerances need."""

    theta: np.ndarray
    gamma: np.ndarray
    theta_iv: np.ndarray
    cond_m: float  # cond(M_N^-1), the matrix of eqs. (38) and (53)
    cond_h: float  # cond(Q~'XQ~) of the last eq. (75)
    residual_gain: float  # (|R||theta| + |r|) / |R theta - r|: cancellation in eq. (75)
    rate: float  # the largest |step k + 1| / |step k| of the first 20: how fast it contracts


def dense_bciv(moments, order, lag, white, iterations, *, regularisation=1e-6,
               feedthrough=False, iv_weight=None, noise_weight=None, start=None):
    """Return ``iterations`` alternations of eqs. (75) and (53) after eq. (38), densely."""
    p = moments.shape[1] - 1
    r_eta_p, r_eta_z = moments[:, :p], -moments[:, p]  # N R_eta_p, N r_eta_z
    m = r_eta_p.shape[0]
    w = np.eye(m) if iv_weight is None else iv_weight
    x = np.eye(m) if noise_weight is None else noise_weight
    # Step 1, eq. (38), with M_0 = rho I: M_N^-1 = R'WR + rho^-1 I
    m_inverse = r_eta_p.T @ w @ r_eta_p + regularisation * np.eye(p)
    theta_iv = np.linalg.solve(m_inverse, r_eta_p.T @ w @ r_eta_z)
    theta = theta_iv if start is None else start
    steps = []
    for _ in range(iterations):
        q_tilde = q_tilde_entrywise(theta[order:], order, lag, white, feedthrough)
        residual = r_eta_p @ theta - r_eta_z
        # Step 3, eq. (75)
        noise_matrix = q_tilde.T @ x @ q_tilde
        gamma = np.linalg.solve(noise_matrix, q_tilde.T @ x @ residual)
        # Step 4, eq. (53)
        previous = theta
        theta = theta_iv + np.linalg.solve(m_inverse, r_eta_p.T @ w @ q_tilde @ gamma)
        steps.append(np.linalg.norm(theta - previous))
    if not iterations:
        return Dense(theta, None, theta_iv, np.linalg.cond(m_inverse), np.nan, np.nan, np.nan)
    size = np.abs(r_eta_p) @ np.abs(theta) + np.abs(r_eta_z)
    ratios = [after / before for before, after in zip(steps[1:20], steps[2:21])]
    return Dense(theta, gamma, theta_iv, np.linalg.cond(m_inverse),
                 np.linalg.cond(noise_matrix),
                 np.linalg.norm(size) / np.linalg.norm(r_eta_p @ theta - r_eta_z),
                 max(ratios, default=np.nan))


def tolerances(dense, m, iterations):
    """Return the relative rounding bounds on theta_IV, theta and gamma (module docstring)."""
    # Step 1: two solvers (Cholesky, LU), each within cond(M) m eps.
    iv = 2 * m * dense.cond_m * EPS
    # Each alternation adds both solves' rounding; the unit eigenvalue (colored) keeps it.
    theta = iterations * 2 * m * (dense.cond_m + dense.cond_h) * EPS
    # Eq. (75) amplifies a relative error of R theta - r by cond(Q~'XQ~), and forming
    # R theta - r amplifies the error of theta by its cancellation.
    gamma = dense.cond_h * dense.residual_gain * (theta + 2 * m * EPS)
    return iv, theta, gamma


def assert_close(actual, expected, relative, what):
    """Assert |actual - expected|_max <= relative * |expected|_max."""
    bound = relative * np.abs(expected).max()
    error = np.abs(np.asarray(actual) - expected).max()
    assert error <= bound, f'{what}: error {error:.3g} above the rounding bound {bound:.3g}'


def section(name, samples, seed):
    """Return (z, w) of an Ikenoue scenario, w as a 1-D array."""
    z, w = make_scenario(name).simulate(samples, seed)
    return z, w[:, 0]


# ------------------------------------------------------- the solver alone
@pytest.mark.parametrize('white, lag, feedthrough', [
    (False, 5, False), (False, 3, False), (True, 4, False), (False, 6, True), (True, 3, True)])
def test_q_tilde_is_eqs_61_and_66(white, lag, feedthrough):
    solver = BcivSolver(order=2, iv_lag=lag, feedthrough=feedthrough,
                        input_noise='white' if white else 'colored')
    b = np.random.default_rng(1).standard_normal(len(solver.lags))
    # at most two b_k meet in one entry, and a + b == b + a exactly: bit equality
    np.testing.assert_array_equal(solver.q_tilde(b),
                                  q_tilde_entrywise(b, 2, lag, white, feedthrough))


WEIGHTS = {'iv_weight': np.diag(np.linspace(1.0, 3.0, 12)),
           'noise_weight': np.diag(np.linspace(2.0, 0.5, 12))}


@pytest.mark.parametrize('white, lag, feedthrough, weights, samples', [
    (False, 5, False, {}, 150), (False, 5, False, {}, 4000), (False, 3, False, {}, 3000),
    (True, 4, False, {}, 3000), (False, 6, True, {}, 3000), (True, 3, True, {}, 3000),
    (False, 5, False, WEIGHTS, 3000)])
def test_alternations_equal_the_equations_written_out(white, lag, feedthrough, weights,
                                                      samples):
    z, w = section('ikenoue_white_input' if white else 'ikenoue_colored', samples, 11)
    solver = BcivSolver(order=2, iv_lag=lag, feedthrough=feedthrough,
                        input_noise='white' if white else 'colored', **weights)
    eta, pz = solver.data_windows(z, w)
    moments = eta.T @ pz
    for iterations in (1, 7, 20):
        fast = solver.estimate(moments, 1e-6, mode='steps', iterations=iterations,
                               tolerance=0.0)
        dense = dense_bciv(moments, 2, lag, white, iterations, feedthrough=feedthrough,
                           **weights)
        assert fast.status == '' and fast.iterations == iterations
        iv, theta, gamma = tolerances(dense, solver.m, iterations)
        assert_close(fast.theta_iv, dense.theta_iv, iv, 'theta_IV')
        assert_close(fast.theta, dense.theta, theta, 'theta')
        assert_close(fast.gamma, dense.gamma, gamma, 'gamma')


def test_the_rounding_bounds_catch_a_moved_moment():
    # one moment moved by 1e-7 of its value (what one sample moved by ~3e-4 does to a sum
    # of 3000 of them): far above rounding, the bounds above must see it
    z, w = section('ikenoue_colored', 3000, 11)
    solver = BcivSolver(order=2, iv_lag=5, feedthrough=False, input_noise='colored')
    eta, pz = solver.data_windows(z, w)
    moments = eta.T @ pz
    dense = dense_bciv(moments, 2, 5, False, 7)
    iv, theta, _ = tolerances(dense, solver.m, 7)
    moved = moments.copy()
    moved[3, 1] *= 1.0 + 1e-7
    fast = solver.estimate(moved, 1e-6, mode='steps', iterations=7, tolerance=0.0)
    with pytest.raises(AssertionError, match='above the rounding bound'):
        assert_close(fast.theta_iv, dense.theta_iv, iv, 'theta_IV')
    with pytest.raises(AssertionError, match='above the rounding bound'):
        assert_close(fast.theta, dense.theta, theta, 'theta')


def test_white_fixed_point_is_the_limit_of_the_alternation():
    z, w = section('ikenoue_white_input', 4000, 11)
    solver = BcivSolver(order=2, iv_lag=4, feedthrough=False, input_noise='white')
    eta, pz = solver.data_windows(z, w)
    moments = eta.T @ pz
    fast = solver.estimate(moments, 1e-6, mode='fixed_point', iterations=20,
                           tolerance=DEFAULT_TOLERANCE)
    assert fast.status == '' and fast.converged
    # Here the alternation contracts (rate ~0.75): 300 plain alternations reach its
    # unique fixed point to rounding.
    dense = dense_bciv(moments, 2, 4, True, 300)
    assert dense.rate < 0.8
    # The secant stops with a last step below the tolerance; a contraction at this rate
    # is then within step / (1 - rate) of its fixed point; rounding adds as above.
    _, theta, _ = tolerances(dense, solver.m, 1)
    size = np.abs(dense.theta).max()
    assert_close(fast.theta, dense.theta, (DEFAULT_TOLERANCE / size + theta) / (1 - dense.rate),
                 'the fixed point')
    one_step = dense_bciv(moments, 2, 4, True, 1)
    assert np.abs(one_step.theta - fast.theta).max() > 1e-4  # it did have to iterate


def test_early_stop_checks_every_period_and_stops_below_the_tolerance():
    z, w = section('ikenoue_colored', 3000, 4)
    solver = BcivSolver(order=2, iv_lag=5, feedthrough=False, input_noise='colored')
    eta, pz = solver.data_windows(z, w)
    moments = eta.T @ pz

    def steps(iterations, tolerance):
        return solver.estimate(moments, 1e-6, mode='steps', iterations=iterations,
                               tolerance=tolerance)
    full = [steps(k, 0.0).theta for k in range(1, 21)]
    sizes = [np.linalg.norm(full[k] - full[k - 1]) for k in range(1, 20)]  # step k + 1
    tolerance = sizes[10]  # the 12th step: first checked at 12 (period 4)
    stopped = steps(20, tolerance)
    first = next(k + 2 for k, size in enumerate(sizes) if size <= tolerance and
                 (k + 2) % CHECK_PERIOD == 0)
    assert stopped.status == '' and stopped.converged and stopped.iterations == first
    # the same computation in the same run: bit equality
    np.testing.assert_array_equal(stopped.theta, full[first - 1])
    # Never stops below the cap when the tolerance is not reached; the last step is checked.
    capped = steps(7, 0.0)
    assert capped.iterations == 7 and not capped.converged


# ------------------------------------------------- the recursive estimator
SAMPLES, SEED, STRIDE = 3000, 21, 50
CASES = {
    'colored': ('ikenoue_colored', {'order': 2, 'iv_lag': 5}),
    'white': ('ikenoue_white_input', {'order': 2, 'iv_lag': 4, 'input_noise': 'white'}),
    'printed': ('ikenoue_colored', {'order': 2, 'iv_lag': 5, 'bciv_update': 'printed'}),
    'colored_forgetting': ('ikenoue_colored', {'order': 2, 'iv_lag': 5, 'idle_samples': 40,
                                               'forgetting_factor': 0.999}),
}


@pytest.mark.parametrize('case', sorted(CASES))
def test_recursive_estimate_equals_the_equations_on_its_own_moments(case):
    scenario, settings = CASES[case]
    z, w = section(scenario, SAMPLES, SEED)
    est = Bciv(**settings)
    white = est.input_noise == 'white'
    m, lag = est._solver.m, est.iv_lag
    negative, not_converged, compared = 0, 0, 0
    for t in range(SAMPLES):
        before = est.get_state()
        est.update(z[t], w[t])
        state = est.get_state()
        flags = state.scalars['flags']
        missed = flags.get('not_converged', 0) > before.scalars['flags'].get('not_converged', 0)
        not_converged += missed
        if state.scalars['updates'] > before.scalars['updates']:
            negative += state.arrays['gamma'][0] < 0.0
        if (t + 1) % STRIDE or missed:
            continue
        compared += 1
        scalars, arrays = state.scalars, state.arrays
        idle = scalars['updates'] < est.idle_samples
        if est.bciv_update == 'printed':
            start, iterations = before.arrays['theta_bciv'], 1
        elif white:  # a fixed point: one more alternation from it
            start, iterations = arrays['theta_bciv'], 1
        else:  # K alternations from theta_IV
            start, iterations = None, est.last_iterations
        dense = dense_bciv(arrays['moments'], est.order, lag, white, 0 if idle else iterations,
                           regularisation=scalars['decay'] / est.initial_covariance_diagonal,
                           start=start)
        iv, theta, gamma = tolerances(dense, m, iterations)
        assert_close(arrays['theta_iv'], dense.theta_iv, iv, f'theta_IV at {t}')
        if idle:
            np.testing.assert_array_equal(arrays['theta_bciv'], arrays['theta_iv'])
            continue
        if white:
            # The secant stops once its step moves theta by < tolerance; one alternation
            # then moves it by that times the alternation's local gain (10 allowed).
            theta += 10 * est.tolerance / np.abs(dense.theta).max()
            gamma = dense.cond_h * dense.residual_gain * (theta + 2 * m * EPS)
        assert_close(arrays['theta_bciv'], dense.theta, theta, f'theta at {t}')
        # the estimator holds gamma normalised by the weighted count tau
        assert_close(arrays['gamma'] * scalars['tau'], dense.gamma, gamma, f'gamma at {t}')
    assert compared >= SAMPLES // STRIDE - 2
    # Flags: no fallback on these data; each negative variance estimate counted once.
    assert set(est.flags) <= {'negative_variance', 'not_converged'}
    assert est.flags.get('negative_variance', 0) == negative
    # The secant method reaches the tolerance within K = 20 steps on >= 98 % of samples
    # (about 1 % miss it on this run, at samples where the fixed point is ill-determined).
    assert not_converged == est.flags.get('not_converged', 0) <= 0.02 * est.samples
    assert white or not_converged == 0


@pytest.mark.parametrize('forgetting_factor', [1.0, 0.995])
def test_moments_recursion_equals_the_sum(forgetting_factor):
    z, w = section('ikenoue_colored', 4000, 8)
    est = Bciv(order=2, iv_lag=5, forgetting_factor=forgetting_factor)
    est.run(z, w)
    eta, pz = est._solver.data_windows(z, w)
    weights = forgetting_factor ** np.arange(len(eta) - 1, -1, -1.0)
    terms = eta[:, :, None] * (pz * weights[:, None])[:, None, :]
    # Summing N terms (and scaling by lambda each step) rounds by at most 2 N eps sum |term|.
    bound = 2 * len(eta) * EPS * np.abs(terms).sum(axis=0)
    assert (np.abs(est.get_state().arrays['moments'] - terms.sum(axis=0)) <= bound).all()
    assert est.get_state().scalars['tau'] == pytest.approx(weights.sum(), rel=len(eta) * EPS)


def test_history_ring_wraps_without_losing_samples():
    rng = np.random.default_rng(2)
    count = 3 * RING_SAMPLES + 17
    y, u = rng.standard_normal(count), rng.standard_normal(count)
    est = Bciv(order=2, iv_lag=5)
    m = est._solver.m
    for t in range(count):
        est.update(y[t], u[t])
        if t in (RING_SAMPLES - 1, RING_SAMPLES, RING_SAMPLES + m, count - 1):
            history = est.get_state().arrays['history']
            expected = np.stack([-y[t - m + 1:t + 1][::-1], u[t - m + 1:t + 1][::-1]], axis=1)
            np.testing.assert_array_equal(history, expected)


def test_covariance_trace_is_the_trace_of_m_n():
    z, w = section('ikenoue_colored', 800, 6)
    est = Bciv(order=2, iv_lag=5, initial_covariance=10.0)
    est.run(z, w)
    eta, pz = est._solver.data_windows(z, w)
    s_p = eta.T @ pz[:, :4]
    m_inverse = s_p.T @ s_p + np.diag(1.0 / est.initial_covariance_diagonal)
    # two inversions of M_N^-1 from differently summed moments: cond(M_N^-1) N eps apart
    rel = 2 * len(eta) * np.linalg.cond(m_inverse) * EPS
    assert est.covariance_trace == pytest.approx(np.trace(np.linalg.inv(m_inverse)), rel=rel)
    # a restored state gives the same M_N (the same computation: bit equality)
    again = Bciv(order=2, iv_lag=5, initial_covariance=10.0)
    again.set_state(est.get_state())
    assert again.covariance_trace == est.covariance_trace
