"""
The estimate's own error in the output-error tests (``oe_white``, bcrls), while it settles.

A recursive estimate's output error is v(t) + psi'(t) theta~(t): early in a run theta~(t) is
large and colours the residual of a right model. The monitor reads the estimate's covariance
at every block and profiles its error out of the whiteness test (docs/trust.md, "While the
estimate settles"). The Monte Carlo tests run many plants at once; a share over K plants has
the binomial standard error sqrt(p (1 - p) / K), and the tolerances are four of them.
"""

import math

import numpy as np
from scipy import signal

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.adequacy import AdequacyMonitor, chi2_quantile
from bcid_ros.estimators.residual_statistics import covariance_factors, profiled_whiteness

PLANTS = 1000
SAMPLES = 1000
LAGS = 10
P = 3


def settling_residuals(seed, share, colour=0.0):
    """
    Return residuals, inputs, gradients and C(t) of PLANTS estimates that settle.

    psi: a white input through three low-pass filters (an output-error gradient); the
    estimate's error theta~(t) = L(t) xi with one xi ~ N(0, I) per plant and
    C(t) = share (100 / t) I / p: its output error has ``share`` times the noise's power at
    t = 100, falling as 1 / t. v is white, or AR(1) ``colour``.
    """
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((SAMPLES, PLANTS))
    psi = np.stack([signal.lfilter([1.0], [1.0, -0.9], u, axis=0),
                    signal.lfilter([0.0, 1.0], [1.0, -0.9], u, axis=0),
                    signal.lfilter([0.0, 0.0, 1.0], [1.0, -0.8], u, axis=0)], axis=-1)
    psi /= psi.std(axis=(0, 1))
    v = signal.lfilter([1.0], [1.0, -colour], rng.standard_normal((SAMPLES, PLANTS)), axis=0)
    v /= v.std()
    xi = rng.standard_normal((PLANTS, P))
    scale = np.sqrt(share * 100.0 / np.maximum(np.arange(1, SAMPLES + 1), 100) / P)
    residual = v + np.einsum('tkj,kj->tk', psi, xi) * scale[:, None]
    return residual, u[:, :, None], psi, scale


def run(residual, inputs, psi, scale, term):
    """Feed a K-plant ``oe_white`` monitor; C(t) is read at every block (with the term)."""
    now = {'t': 0}
    monitor = AdequacyMonitor(
        num_inputs=1, model='oe_white', plants=PLANTS, num_parameters=P * term,
        parameter_covariance=lambda rows: np.broadcast_to(
            scale[now['t']] ** 2 * np.eye(P), (len(rows), P, P)))
    for t in range(SAMPLES):
        now['t'] = t
        monitor.record(residual[t], inputs[t], psi[t])
    return monitor


def tolerance(tail):
    """Return four binomial standard errors of a share ``tail`` over PLANTS."""
    return 4.0 * math.sqrt(tail * (1.0 - tail) / PLANTS)


def test_the_profiled_statistic_of_plants_searched_together_is_each_ones_alone():
    # the batched forms search all their plants at once: each plant's numbers must be
    # those of the plant searched alone, bit for bit (one code path, the same draws)
    rng = np.random.default_rng(3)
    rho = rng.normal(0.0, 0.05, (6, LAGS))
    halves = rng.normal(0.0, 0.05, (6, LAGS, P, P))
    forms = 0.5 * (halves + np.swapaxes(halves, -1, -2))
    size = rng.uniform(200.0, 5000.0, 6)
    together, deviations = profiled_whiteness(rho, forms, size)
    for k in range(6):
        alone, deviation = profiled_whiteness(rho[k:k + 1], forms[k:k + 1], size[k:k + 1])
        assert together[k] == alone[0]
        np.testing.assert_array_equal(deviations[k], deviation[0])
    # the profile never does worse than xi = 0 (the plain statistic), and with A = 0 is it
    assert (together <= size * np.einsum('km,km->k', rho, rho)).all()
    plain, _ = profiled_whiteness(rho, np.zeros_like(forms), size)
    np.testing.assert_array_equal(plain, size * np.einsum('km,km->k', rho, rho))


def test_the_factor_of_the_covariance_moves_with_it_continuously():
    # the sums add the blocks of C(t) and of C(t') a last bit apart: their factors must be as
    # close, whatever eigenvectors eigh picks for two close eigenvalues (a factor of them was
    # 0.3 apart here, a rotation within their plane)
    rng = np.random.default_rng(3)
    basis, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    covariance = basis @ np.diag([1.0, 1.0 + 1e-12, 2.0]) @ basis.T
    nudge = 1e-13 * rng.standard_normal((3, 3))
    first, second = covariance_factors(np.stack([covariance, covariance + nudge + nudge.T]))
    assert np.abs(first - second).max() < 1e-11
    np.testing.assert_allclose(first @ first.T, covariance, rtol=0.0, atol=1e-14)
    # the PSD part of an indefinite matrix, zeros for one not finite
    indefinite, unknown = covariance_factors(
        np.stack([np.diag([4.0, -1.0, 0.0]), np.full((3, 3), np.nan)]))
    np.testing.assert_allclose(indefinite, np.diag([2.0, 0.0, 0.0]), rtol=0.0, atol=1e-15)
    np.testing.assert_array_equal(unknown, np.zeros((3, 3)))


def test_the_settling_term_keeps_the_output_error_tests_within_their_rate():
    # the error's power is the noise's at t = 100 (a tenth at 1000): the plain tests fail
    residual, inputs, psi, scale = settling_residuals(3, share=1.0)
    plain = run(residual, inputs, psi, scale, term=False).statistics
    statistics = run(residual, inputs, psi, scale, term=True).statistics
    # each test's own rate (2 tests at 1 %) and the 10 % point: at most nominal (the common xi
    # over the window bounds the error's variance from above, so it may be lower)
    per_test = 1.0 - 0.99 ** 0.5
    for tail in (per_test, 0.1):
        threshold = chi2_quantile(tail, LAGS)
        above = (statistics > threshold).mean(axis=0)
        assert (above <= tail + tolerance(tail)).all(), (tail, above)
        # measured 0.56-0.86 without the term
        assert ((plain > threshold).mean(axis=0) > 0.3).all()


def test_the_settling_term_does_not_hide_a_coloured_noise():
    # AR(1) 0.3 noise under a settling error of 0.3 times the noise's power at t = 100: the
    # term explains part of the colour (a third of the window's residual is the estimate's
    # error early on) but not most of it. Measured: 74 % of the plants in alarm (100 % without
    # the error and the term); half is 17 binomial standard errors below.
    residual, inputs, psi, scale = settling_residuals(4, share=0.3, colour=0.3)
    monitor = run(residual, inputs, psi, scale, term=True)
    assert monitor.alarm.mean() > 0.5


def test_bcrls_on_output_error_plants_is_not_refused_by_its_residual_tests_early():
    # first- and second-order OE plants with white noise at 20-30 dB (bcrls's model): the
    # residual tests are in alarm at 500, 1000 and 3000 samples no more often than their
    # stated rate, 1 % a moment (before the term: 18 of these 60 plants at some moment; with it, 1)
    refused = 0
    for seed in range(60):
        rng = np.random.default_rng((7, seed))
        order = int(rng.integers(1, 3))
        a = np.real(np.poly(rng.uniform(0.3, 0.95, size=order)))
        b = rng.standard_normal(order)
        u = rng.standard_normal(3000)
        x = signal.lfilter(np.concatenate(([0.0], b / np.abs(b).sum())), a, u)
        v = rng.standard_normal(3000)
        y = x + v * x.std() * 10.0 ** (-rng.uniform(20.0, 30.0) / 20.0)
        estimator = make_estimator('bcrls', order=order)
        alarm = False
        for t in range(3000):
            estimator.update(y[t], u[t])
            if t + 1 in (500, 1000, 3000):
                alarm |= any(reason.startswith('residual')
                             for reason in estimator.validity_reasons)
        refused += alarm
    # a plant in alarm at any of the three moments: at most 3 % under the null (the union
    # bound), within four binomial standard errors over the 60 plants (at most 7)
    assert refused <= 60 * (0.03 + 4.0 * math.sqrt(0.03 * 0.97 / 60)), refused
