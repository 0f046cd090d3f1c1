"""
The HAC covariance: its long-run variance, its coverage on coloured errors, plants and state.

Coverage runs many least-squares problems at once through the plant axis. A share within
+-2 std over R runs has the binomial standard error sqrt(0.954 * 0.046 / R); the tolerances are
four of them.
"""

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators.hac import HacCovariance, whitened_moments
from bcid_ros.estimators.lagged import BLOCK

#: An oversampled plant: poles 0.95 and 0.9.
A = np.array([1.0, -1.85, 0.855])
B = np.array([0.0, 0.05, 0.04])
THETA = np.r_[A[1:], B[1:]]
RUNS = 200


def coloured(rng, shape, kind):
    """Return unit-variance noise of ``kind`` along axis 0 (a 1000-sample burn-in)."""
    white = rng.standard_normal((shape[0] + 1000,) + shape[1:])
    if kind == 'ar0.9':
        noise = signal.lfilter([1.0], [1.0, -0.9], white, axis=0)
    elif kind == 'oversampled':  # poles 0.9 +- 0.1j
        noise = signal.lfilter([1.0], [1.0, -1.8, 0.82], white, axis=0)
    else:
        noise = white
    noise = noise[1000:]
    return noise / noise.std()


def oe_regression(rng, samples, noise):
    """
    Return psi (R, N, 4) and y (R, N) of y = psi' theta + v, psi the noise-free OE regressor.

    psi(t) = [-x(t-1), -x(t-2), u(t-1), u(t-2)], x = B/A u with a low-pass u: the regression of
    a prediction-error output-error model at the truth, where LS is consistent for any colour
    of the output noise v (std 0.5).
    """
    u = coloured(rng, (samples + 2, RUNS), 'ar0.9')
    x = signal.lfilter(B, A, u, axis=0)
    y = x + 0.5 * coloured(rng, (samples + 2, RUNS), noise)
    psi = np.stack([-x[1:-1], -x[:-2], u[1:-1], u[:-2]], axis=-1)
    return np.swapaxes(psi, 0, 1), y[2:].T


def weighted_ls(psi, y, lam):
    """Return theta, P = (sum w psi psi')^-1 and the residuals of weighted LS, per run."""
    weights = lam ** np.arange(psi.shape[1] - 1, -1, -1, dtype=float)
    p = np.linalg.inv(np.einsum('ktp,t,ktq->kpq', psi, weights, psi))
    theta = np.einsum('kpq,ktq,t,kt->kp', p, psi, weights, y)
    return theta, p, y - np.einsum('ktp,kp->kt', psi, theta)


def hac_std(psi, residual, p, lam, **settings):
    """Return the HAC std of every run, (R, 4), recorded one sample at a time."""
    hac = HacCovariance(dimension=4, forgetting_factor=lam, plants=RUNS, **settings)
    scores = psi * residual[:, :, None]
    for t in range(scores.shape[1]):
        hac.record(scores[:, t])
    return np.sqrt(np.einsum('kii->ki', hac.covariance(p)))


def plain_std(psi, residual, p, lam):
    """Return the std of sigma^2 P tau_2 / tau (rls's, white residual), (R, 4)."""
    weights = lam ** np.arange(psi.shape[1] - 1, -1, -1, dtype=float)
    tau, tau2 = weights.sum(), (weights ** 2).sum()
    sigma2 = np.einsum('t,kt->k', weights, residual ** 2) / (tau - 4 * tau2 / tau)
    return np.sqrt(np.einsum('kii->ki', p) * (sigma2 * tau2 / tau)[:, None])


def share_within(theta, std, width):
    """Return the share of runs with |theta - truth| <= width std, per parameter."""
    return (np.abs(theta - THETA) <= width * std).mean(axis=0)


@pytest.mark.parametrize('noise, samples, lam', [
    ('white', 1000, 1.0), ('ar0.9', 1000, 1.0), ('oversampled', 1000, 1.0),
    ('ar0.9', 3000, 0.995)])
def test_the_hac_std_covers_on_coloured_errors(noise, samples, lam):
    rng = np.random.default_rng({'white': 1, 'ar0.9': 2, 'oversampled': 3}[noise] + int(lam < 1))
    psi, y = oe_regression(rng, samples, noise)
    theta, p, residual = weighted_ls(psi, y, lam)
    std = hac_std(psi, residual, p, lam)
    error2 = 4.0 * math.sqrt(0.954 * 0.046 / RUNS)
    within2 = share_within(theta, std, 2.0)
    # with forgetting (about 400 effective samples) the a's cover 90-94 % (docs/trust.md)
    floor = 0.954 - error2 - (0.03 if lam < 1.0 else 0.0)
    assert within2.min() >= floor, within2
    assert within2.max() <= 1.0
    # +-3 std: 99.73 %, four standard errors of 200 runs below is 98.0 %
    assert share_within(theta, std, 3.0).min() >= 0.9973 - 4.0 * math.sqrt(
        0.9973 * 0.0027 / RUNS) - (0.01 if lam < 1.0 else 0.0)
    plain = share_within(theta, plain_std(psi, residual, p, lam), 2.0)
    if noise == 'white':
        # both estimate the same variance here: the shares differ by a few runs
        assert np.abs(plain - within2).max() <= 0.03
    else:
        # the plain std is 2.7-3 times too small for the a's (docs/trust.md)
        assert plain[:2].max() < 0.8


def test_the_long_run_variance_of_ar1_scores():
    rng = np.random.default_rng(5)
    rho, plants, samples = 0.5, 50, 4000
    scores = signal.lfilter([1.0], [1.0, -rho], rng.standard_normal((samples, plants, 1)), axis=0)
    hac = HacCovariance(dimension=1, plants=plants)
    for t in range(samples):
        hac.record(scores[t])
    ratio = hac.long_run()[:, 0, 0] / (1.0 / (1.0 - rho) ** 2)
    # ln Omega^ = ln sigma^2 - 2 ln(1 - rho^) spreads by 2 sqrt((1 - rho^2) / N) / (1 - rho)
    # = 0.11 and sqrt(2 / N) = 0.02: 0.12 per plant, 0.017 for the mean of 50; four of them
    assert abs(np.log(ratio).mean()) < 4.0 * 0.12 / math.sqrt(plants)
    assert hac.bandwidths.max() <= hac.max_lag


def test_larger_is_at_or_above_both_prewhitenings_in_every_direction():
    """
    'larger' is Omega_d + (Omega_n - Omega_d)_+, above each in the Loewner order.

    It is the diagonal's in the directions where the diagonal's is the larger. The scores: a
    persistent AR(1) 0.9 component plus a small one of alternating sign (-0.6), mixed, so
    that neither prewhitening is the larger in every direction.
    """
    rng = np.random.default_rng(11)
    persistent = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(3000))
    alternating = 0.3 * signal.lfilter([1.0], [1.0, 0.6], rng.standard_normal(3000))
    scores = np.column_stack((persistent + alternating, persistent - alternating,
                              rng.standard_normal(3000)))
    omega = {}
    for prewhitening in ('diagonal', 'none', 'larger'):
        hac = HacCovariance(dimension=3, prewhitening=prewhitening)
        hac.record_all(scores)
        omega[prewhitening] = hac.long_run()
    scale = np.abs(omega['larger']).max()
    for other in ('diagonal', 'none'):
        assert np.linalg.eigvalsh(omega['larger'] - omega[other]).min() >= -1e-12 * scale
    # neither contains the other here, and the larger is the diagonal's plus the positive
    # part of the difference, whose null space it leaves alone
    difference = np.linalg.eigvalsh(omega['none'] - omega['diagonal'])
    assert difference.min() < 0.0 < difference.max()
    values, vectors = np.linalg.eigh(omega['none'] - omega['diagonal'])
    below = vectors[:, values < 0.0]
    np.testing.assert_allclose(below.T @ omega['larger'] @ below,
                               below.T @ omega['diagonal'] @ below, rtol=1e-9,
                               atol=1e-12 * scale)


def test_whitened_moments_are_those_of_the_whitened_series():
    rng = np.random.default_rng(6)
    samples, lags = 5000, 4
    scores = signal.lfilter([1.0], [1.0, -0.7], rng.standard_normal((samples, 2)), axis=0)
    a = np.diag([0.6, -0.3])

    def moments(series, count):
        return np.stack([series[k:].T @ series[:len(series) - k] / samples
                         for k in range(count)])

    gamma = moments(scores, lags + 2)
    formula = whitened_moments(gamma[None], a[None])[0]
    direct = moments(scores[1:] - scores[:-1] @ a.T, lags + 1)
    # the two differ only by the products of the first k + 2 and the last row: at most
    # (k + 3) (1 + |A|)^2 max|s|^2 / N
    bound = (lags + 3) * 1.6 ** 2 * np.abs(scores).max() ** 2 / samples
    difference = np.abs(formula - direct).max()
    assert difference < bound
    assert np.abs(formula - gamma[:lags + 1]).max() > 10 * difference  # whitening changed them


def test_whitened_moments_carry_the_weights_of_forgetting():
    """Weights w_t = lambda^(N-t); rows at both ends zero, so the formula is exact."""
    rng = np.random.default_rng(9)
    samples, lags, lam = 400, 3, 0.9
    scores = rng.standard_normal((samples, 2))
    scores[:lags + 3] = 0.0
    scores[-2:] = 0.0
    weights = lam ** np.arange(samples - 1, -1, -1, dtype=float)
    a = np.diag([0.8, -0.5])

    def moments(series, count):
        # sum_t w_t w_{t-k} s_t s_{t-k}'
        return np.stack([(series[k:] * (weights[k:] * weights[:samples - k])[:, None]).T
                         @ series[:samples - k] for k in range(count)])

    whitened = np.zeros_like(scores)
    whitened[1:] = scores[1:] - scores[:-1] @ a.T
    direct = moments(whitened, lags + 1)
    gamma = moments(scores, lags + 2)
    formula = whitened_moments(gamma[None], a[None], lam)[0]
    # the same sums in another order: rounding of a few ulp of the largest term
    np.testing.assert_allclose(formula, direct, atol=1e-12 * np.abs(direct).max())
    # without the factors lambda^-1, lambda^-2 they are off by about 10 %
    assert np.abs(whitened_moments(gamma[None], a[None])[0] - direct).max() > 0.02 * np.abs(
        direct).max()


def test_one_plant_and_a_batch_agree():
    rng = np.random.default_rng(7)
    scores = signal.lfilter([1.0], [1.0, -0.8], rng.standard_normal((1500, 3, 4)), axis=0)
    bread = np.linalg.inv(np.einsum('tkp,tkq->kpq', scores, scores))
    batch = HacCovariance(dimension=4, plants=3)
    single = HacCovariance(dimension=4)
    changed = HacCovariance(dimension=4)
    for t in range(1500):
        batch.record(scores[t])
        single.record(scores[t, 2])
        changed.record(scores[t, 2] * (1.5 if t == 700 else 1.0))
    reference = single.covariance(bread[2])
    # two summation orders of 1500 products (rounding ~1e-13 relative), then a 4 x 4 solve and
    # scaling of condition < 1e3: 1e-9 relative
    np.testing.assert_allclose(batch.covariance(bread)[2], reference, rtol=1e-9)
    assert np.abs(changed.covariance(bread[2]) - reference).max() > 1e-4 * np.abs(
        reference).max()


def test_a_restored_covariance_continues_bit_for_bit():
    rng = np.random.default_rng(8)
    scores = rng.standard_normal((2000, 3))
    first = HacCovariance(dimension=3, forgetting_factor=0.999)
    for t in range(1000 + BLOCK // 3):
        first.record(scores[t])
    second = HacCovariance(dimension=3, forgetting_factor=0.999)
    second.set_state(first.get_state())
    for t in range(1000 + BLOCK // 3, 2000):
        first.record(scores[t])
        second.record(scores[t])
    bread = np.eye(3)
    np.testing.assert_array_equal(first.covariance(bread), second.covariance(bread))


def test_no_covariance_before_the_first_block():
    hac = HacCovariance(dimension=2)
    for _ in range(BLOCK - 1):
        hac.record(np.ones(2))
    assert hac.covariance(np.eye(2)) is None and hac.long_run() is None
    hac.record(np.ones(2))
    assert hac.covariance(np.eye(2)) is not None


@pytest.mark.parametrize('lam', [1.0, 0.995])
def test_complete_puts_every_recorded_score_in_the_estimate(lam):
    """A record shorter than a block (a short batch fit's scores) has an estimate once complete."""
    rng = np.random.default_rng(7)
    scores = rng.standard_normal((100, 2))
    hac = HacCovariance(dimension=2, forgetting_factor=lam)
    hac.record_all(scores)
    assert hac.long_run() is None
    hac.complete()
    assert hac.long_run() is not None and hac.samples == 100
    # G(0) = sum_t w_t^2 s_t s_t', w_t = lam^(T - t): 100 terms, each rounded, so within
    # about 100 eps of the sum of their sizes
    weights = lam ** (2 * np.arange(99, -1, -1, dtype=float))
    expected = np.einsum('t,ti,tj->ij', weights, scores, scores)
    sizes = np.einsum('t,ti,tj->ij', weights, np.abs(scores), np.abs(scores))
    error = np.abs(hac.get_state().products['sums'][..., 0] - expected)
    assert (error <= 100 * np.finfo(float).eps * sizes).all()
    # the scores after it start a block of their own
    before = hac.long_run()
    for score in rng.standard_normal((BLOCK - 1, 2)):
        hac.record(score)
    assert hac.long_run().tobytes() == before.tobytes()
    hac.record(np.ones(2))
    assert hac.long_run().tobytes() != before.tobytes()


@pytest.mark.parametrize('settings, message', [
    ({'dimension': 0}, 'dimension must be an integer >= 1'),
    ({'forgetting_factor': 0.0}, r'forgetting_factor must be in \(0, 1\]'),
    ({'prewhitening': 'var'}, 'prewhitening must be one of none, diagonal'),
    ({'kernel': 'qs'}, 'kernel must be one of bartlett, parzen'),
    ({'bandwidth': -1.0}, 'bandwidth must be None or > 0'),
    ({'max_lag': 0}, 'max_lag must be an integer >= 1'),
    ({'plants': 0}, 'plants must be None or an integer >= 1'),
])
def test_settings_are_validated(settings, message):
    with pytest.raises(ValueError, match=message):
        HacCovariance(**{'dimension': 2, **settings})


def test_repr_is_one_line():
    text = repr(HacCovariance(dimension=6, forgetting_factor=0.995))
    assert '\n' not in text and 'dimension=6' in text and "prewhitening='diagonal'" in text


def test_importing_the_trust_modules_does_not_import_scipy():
    code = ('import sys, bcid_ros.estimators.adequacy, bcid_ros.estimators.hac; '
            'sys.exit(int("scipy" in sys.modules))')
    assert subprocess.run([sys.executable, '-c', code]).returncode == 0


@pytest.mark.parametrize('lam', [1.0, 0.995])
@pytest.mark.parametrize('before', [0, 1, BLOCK - 1, BLOCK + 7])
def test_record_all_is_record_of_each_row_bit_for_bit(lam, before):
    """Whole blocks added at once (record_all) give the sums of row-by-row records."""
    rng = np.random.default_rng(5)
    first, scores = rng.standard_normal((before, 3)), rng.standard_normal((3 * BLOCK + 41, 3))
    scores[BLOCK + 3] = np.nan  # a non-finite row counts as zero in either path
    by_row, at_once = (HacCovariance(dimension=3, forgetting_factor=lam) for _ in range(2))
    for hac in (by_row, at_once):
        hac.record_all(first)
    for score in scores.copy():
        by_row.record(score)
    at_once.record_all(scores)
    scores[:] = 0.0  # record_all copies
    row_state, once_state = by_row.get_state().products, at_once.get_state().products
    assert row_state.keys() == once_state.keys()
    for name, value in row_state.items():
        assert np.asarray(value).tobytes() == np.asarray(once_state[name]).tobytes(), name
    assert by_row.covariance(np.eye(3)).tobytes() == at_once.covariance(np.eye(3)).tobytes()
