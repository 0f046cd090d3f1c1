"""Tests of the batch prediction-error reference bcid_ros.analysis.pem (OE, ARX, ARMAX)."""

import numpy as np
import pytest
from scipy import signal

from bcid_ros.analysis import pem
from bcid_ros.analysis.metrics import nrmse_fit
from bcid_ros.estimators.base import parameter_names
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from bcid_ros.estimators.rls import ls_batch


def delayed(u, delays):
    """Return u_i(t - d_i) per column, zeros before the start."""
    out = np.zeros_like(u)
    for i, d in enumerate(delays):
        out[d:, i] = u[:u.shape[0] - d, i]
    return out


def oe_data(rng, f, b, count, delays=(0,), noise=None, hold=1):
    """Return (y, u, x): y = sum_i B_i/F u_i(t - d_i) + v, u held PRBS-like, x noise-free."""
    r = len(b)
    levels = rng.choice([-1.0, 1.0], size=(count // hold + 1, r))
    u = np.repeat(levels, hold, axis=0)[:count] if hold > 1 else rng.standard_normal((count, r))
    shifted = delayed(u, delays)
    x = sum(signal.lfilter(np.concatenate([[0.0], b[i]]), f, shifted[:, i]) for i in range(r))
    v = np.zeros(count) if noise is None else noise(rng, count)
    return x + v, u, x


def coloured(scale):
    """Return a noise maker: scale * (1 + 0.5 q^-1)/(1 - 0.8 q^-1) e, e white."""
    return lambda rng, count: scale * signal.lfilter([1.0, 0.5], [1.0, -0.8],
                                                     rng.standard_normal(count))


F2 = np.array([1.0, -1.5, 0.7])
B2 = [np.array([1.0, 0.5])]


def test_oe_with_coloured_noise_is_unbiased_and_its_covariance_calibrated():
    # 40 seeded runs: the mean error per parameter is within 3 Monte Carlo standard errors
    # of 0, and the mean of z^2 = (error / reported std)^2 is 1 within 3 of its standard
    # errors, sqrt(2 / R) for chi-square(1) draws.
    runs, count = 40, 1500
    truth = np.concatenate([F2[1:], B2[0]])
    errors, z = [], []
    for seed in range(runs):
        y, u, _ = oe_data(np.random.default_rng(1000 + seed), F2, B2, count,
                          noise=coloured(0.7))
        result = pem.fit_oe(y, u, pem.Structure(2))
        errors.append(result.theta - truth)
        z.append((result.theta - truth) / result.std)
    errors, z = np.array(errors), np.array(z)
    stderr = errors.std(axis=0, ddof=1) / np.sqrt(runs)
    assert np.all(np.abs(errors.mean(axis=0)) <= 3.0 * stderr)
    assert np.all(np.abs((z ** 2).mean(axis=0) - 1.0) <= 3.0 * np.sqrt(2.0 / runs))


def test_oe_coloured_covariance_is_wider_than_the_white_formula_claims():
    # The residual is coloured (AR model of order > 0) and the sandwich differs from
    # sigma^2 (psi' psi)^-1; for this low-pass noise on a low-pass plant it is larger.
    y, u, _ = oe_data(np.random.default_rng(7), F2, B2, 4000, noise=coloured(0.7))
    result = pem.fit_oe(y, u, pem.Structure(2))
    psi = pem.oe_jacobian(result.theta, u, pem.Structure(2))
    white = result.loss * np.linalg.inv(psi.T @ psi)
    assert result.noise_order > 0
    assert np.all(np.diagonal(result.covariance) > np.diagonal(white))


def test_miso_with_per_input_delays_recovers_the_truth_with_its_names():
    f = np.array([1.0, -1.2, 0.5])
    b = [np.array([0.8, 0.3]), np.array([-0.5, 0.9])]
    delays = (1, 3)
    y, u, _ = oe_data(np.random.default_rng(11), f, b, 3000, delays=delays,
                      noise=lambda rng, n: 0.3 * rng.standard_normal(n))
    structure = pem.Structure(2, 2, delays)
    result = pem.fit_oe(y, u, structure)
    truth = np.concatenate([f[1:], *b])
    assert result.parameter_names == parameter_names(2, 2, False, delays)
    assert result.parameter_names[2:] == ('b1_2', 'b1_3', 'b2_4', 'b2_5')
    # one seeded run: every parameter within 4 of its reported std (two-sided 6e-5 each)
    assert np.all(np.abs(result.theta - truth) <= 4.0 * result.std)


def test_oversampled_plant_with_held_prbs():
    # poles 0.99 and 0.95, input held 10 samples, 20 dB SNR, coloured noise
    f = np.real(np.poly([0.99, 0.95]))
    b = [np.array([0.02, 0.015])]
    rng = np.random.default_rng(5)
    y, u, x = oe_data(rng, f, b, 6000, hold=10)
    y = x + coloured(0.1 * x.std() / 2.4)(rng, x.size)
    result = pem.fit_oe(y, u, pem.Structure(2))
    truth = np.concatenate([f[1:], b[0]])
    assert result.stable and result.converged
    assert np.all(np.abs(result.theta - truth) <= 4.0 * result.std)
    # ARX on the same data is far off (the bias the batch OE avoids)
    arx = pem.fit_arx(y, u, pem.Structure(2))
    assert np.linalg.norm(arx.theta - truth) > 10.0 * np.linalg.norm(result.theta - truth)


def test_estimated_initial_transient_of_a_record_that_does_not_start_at_rest():
    # the record is cut 300 samples into a run: the plant is not at rest at its start
    f = np.real(np.poly([0.97, 0.9]))
    b = [np.array([0.3, -0.1])]
    y, u, x = oe_data(np.random.default_rng(3), f, b, 3300,
                      noise=lambda rng, n: 0.05 * rng.standard_normal(n))
    y, u = y[300:], u[300:]
    truth = np.concatenate([f[1:], b[0]])
    estimated = pem.fit_oe(y, u, pem.Structure(2), initial='estimate')
    from_rest = pem.fit_oe(y, u, pem.Structure(2), initial='zero')
    assert estimated.initial == 'estimate' and from_rest.initial == 'zero'
    assert np.all(np.abs(estimated.theta - truth) <= 4.0 * estimated.std)
    assert np.linalg.norm(from_rest.theta - truth) > 3.0 * np.linalg.norm(
        estimated.theta - truth)


def test_offset_of_a_slow_plant_centred_by_its_sample_means():
    # at rest, then driven by an input whose mean is 0.3: after centring both signals by
    # their sample means the output of a slow plant (poles 0.99, 0.95) keeps a constant
    # offset from G(q) times the input, which the offset fits (the transient toward the
    # new mean is a free response, which the estimated start-up transient fits)
    f = np.real(np.poly([0.99, 0.95]))
    b = np.array([0.02, -0.015])
    rng = np.random.default_rng(8)
    u = rng.standard_normal(2000) + 0.3
    x = signal.lfilter(np.concatenate([[0.0], b]), f, u)
    y = x + 0.001 * x.std() * rng.standard_normal(x.size)
    y, u = y - y.mean(), u - u.mean()
    truth = np.concatenate([f[1:], b])
    with_offset = pem.fit_oe(y, u, pem.Structure(2), offset=True)
    without = pem.fit_oe(y, u, pem.Structure(2))
    assert np.all(np.abs(with_offset.theta - truth) <= 4.0 * with_offset.std)
    # measured: 3e-6 against 8e-3
    assert np.linalg.norm(without.theta - truth) > 100.0 * np.linalg.norm(
        with_offset.theta - truth)
    assert with_offset.offset != 0.0 and without.offset == 0.0
    assert np.array_equal(with_offset.residual, y - with_offset.output)


def test_simulate_oe_equals_the_filter_of_each_delayed_input():
    rng = np.random.default_rng(2)
    structure = pem.Structure(2, 2, (2, 0), feedthrough=True)
    theta = np.array([-1.1, 0.3, 0.5, 0.2, -0.1, 1.0, 0.0, 0.4])
    u = rng.standard_normal((500, 2))
    expected = (signal.lfilter([0.0, 0.0, 0.5, 0.2, -0.1], [1.0, -1.1, 0.3], u[:, 0])
                + signal.lfilter([1.0, 0.0, 0.4], [1.0, -1.1, 0.3], u[:, 1]))
    simulated = pem.simulate_oe(theta, u, structure)
    # two summation orders of the same filter: rounding of order eps times the sum of
    # |impulse response| (< 10 here) times max |u| (< 5)
    assert np.abs(simulated - expected).max() <= 100 * 10 * 5 * np.finfo(float).eps


def test_arx_equals_ls_batch_within_the_solvers_rounding():
    # ARX data: A y = B_1 u_1(t) + B_2 u_2(t - 2) + e
    rng = np.random.default_rng(9)
    u = rng.standard_normal((2000, 2))
    delays = (0, 2)
    shifted = delayed(u, delays)
    drive = (signal.lfilter([0.0, 1.0, 0.5], [1.0], shifted[:, 0])
             + signal.lfilter([0.0, -0.3, 0.8], [1.0], shifted[:, 1])
             + 0.5 * rng.standard_normal(2000))
    y = signal.lfilter([1.0], [1.0, -1.5, 0.7], drive)
    structure = pem.Structure(2, 2, delays)
    result = pem.fit_arx(y, u, structure)
    theta, _, loss, _ = ls_batch(y, u, order=2, num_inputs=2, input_delay=delays)
    condition = np.linalg.cond(pem._arx_rows(y, u, structure)[0])
    # QR (lstsq) against the normal equations (ls_batch): the normal equations lose
    # cond^2 * eps relative; 10 * p of slack for the accumulation
    bound = 10 * theta.size * condition ** 2 * np.finfo(float).eps * np.linalg.norm(theta)
    assert np.linalg.norm(result.theta - theta) <= bound
    # the same loss from the two residuals, to the same relative bound
    assert abs(result.loss * result.residual.size - loss) <= 10 * bound * loss
    # the bound still catches one changed sample
    changed = y.copy()
    changed[1000] += 1.0
    assert np.linalg.norm(pem.fit_arx(changed, u, structure).theta - theta) > bound


def test_armax_recovers_c():
    a = np.array([1.0, -1.5, 0.7])
    c = np.array([1.0, 0.6, 0.2])
    rng = np.random.default_rng(4)
    u = rng.standard_normal((4000, 1))
    e = rng.standard_normal(4000)
    y = signal.lfilter([0.0, 1.0, 0.5], a, u[:, 0]) + signal.lfilter(c, a, e)
    result = pem.fit_armax(y, u, pem.Structure(2))
    truth = np.array([-1.5, 0.7, 1.0, 0.5, 0.6, 0.2])
    assert result.parameter_names == ('a1', 'a2', 'b1_1', 'b1_2', 'c1', 'c2')
    assert is_stable(monic_coefficients(result.noise_polynomial), 0.0)
    assert np.all(np.abs(result.theta - truth) <= 4.0 * result.std)
    assert result.loss == pytest.approx(1.0, abs=4.0 * np.sqrt(2.0 / 4000))


def test_returned_f_is_stable_when_the_arx_start_is_not():
    # data from a plant with a pole at 1.01 (400 samples): the ARX estimate is unstable,
    # the OE start is reflected inside, and no step may leave the unit circle
    f = np.real(np.poly([1.01, 0.5]))
    y, u, _ = oe_data(np.random.default_rng(1), f, [np.array([0.5, 0.2])], 400,
                      noise=lambda rng, n: 0.1 * rng.standard_normal(n))
    structure = pem.Structure(2)
    assert not pem.fit_arx(y, u, structure).stable
    result = pem.fit_oe(y, u, structure, initial='estimate')
    assert result.stable and is_stable(monic_coefficients(result.denominator), 0.0)
    assert np.isfinite(result.std).all()


def test_stabilise_reflects_and_pulls_in():
    polynomial = np.real(np.poly([1.25, 0.5]))
    roots = np.sort(np.abs(np.roots(pem.stabilise(polynomial))))
    assert roots == pytest.approx([0.5, 0.8])
    on_circle = np.real(np.poly([1.0, -0.2]))
    assert np.abs(np.roots(pem.stabilise(on_circle, 0.99))).max() == pytest.approx(0.99)
    stable = np.real(np.poly([0.9, 0.3]))
    assert np.array_equal(pem.stabilise(stable), stable)


def test_fit_is_the_nrmse_of_the_output():
    y, u, _ = oe_data(np.random.default_rng(6), F2, B2, 1500,
                      noise=lambda rng, n: 0.5 * rng.standard_normal(n))
    result = pem.fit_oe(y, u, pem.Structure(2))
    assert result.fit(y) == nrmse_fit(y, result.output)
    assert np.array_equal(result.residual, y - result.output)


@pytest.mark.parametrize('call, match', [
    (lambda y, u: pem.Structure(0), 'order'),
    (lambda y, u: pem.Structure(2, 0), 'num_inputs'),
    (lambda y, u: pem.Structure(2, 1, -1), 'input_delay'),
    (lambda y, u: pem.Structure(2, 2, (0, 1, 2)), 'input_delay'),
    (lambda y, u: pem.fit_oe(y, np.ones((y.size, 2)), pem.Structure(2)), 'u must have shape'),
    (lambda y, u: pem.fit_oe(np.r_[np.nan, y[1:]], u, pem.Structure(2)), 'y must be'),
    (lambda y, u: pem.fit_oe(y[:20], u[:20], pem.Structure(2)), 'y must have at least'),
    (lambda y, u: pem.fit_oe(y, u, pem.Structure(2), initial='rest'), 'initial'),
    (lambda y, u: pem.fit_oe(y, u, pem.Structure(2), starts=0), 'starts'),
    (lambda y, u: pem.fit_oe(y, u, pem.Structure(2), max_evaluations=0), 'max_evaluations'),
    (lambda y, u: pem.fit_oe(y, u, 2), 'structure'),
    (lambda y, u: pem.fit_arx(y, u[:-1], pem.Structure(2)), 'u must have shape'),
    (lambda y, u: pem.fit_armax(y, u, pem.Structure(2), max_evaluations=-1),
     'max_evaluations'),
    (lambda y, u: pem.simulate_oe([1.0, 2.0], u, pem.Structure(2)), 'theta'),
    (lambda y, u: pem.oe_jacobian([-2.5, 1.0, 1.0, 1.0], u, pem.Structure(2)), 'theta'),
])
def test_bad_arguments_raise_value_errors_naming_them(call, match):
    y, u, _ = oe_data(np.random.default_rng(0), F2, B2, 300)
    with pytest.raises(ValueError, match=match):
        call(y, u)
