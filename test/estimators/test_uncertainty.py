"""
The parameter covariance of the estimators: its formulas and its bookkeeping.

Single runs against the formulas (rls: the HAC of its scores; bcrls: the sandwich of the
BCLS fixed point; bciv and cl_bcls: block means of their moments). Whether the
std is calibrated over Monte Carlo runs is
test/statistical/test_uncertainty_calibration.py.
"""

import math

import numpy as np
import pytest
from uncertainty_cases import (arx_data, ding_data, IKEDA, ikeda, IKENOUE_COLORED, ikenoue,
                               run, run_single)

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.base import standard_deviations, weighted_square_ratio
from bcid_ros.estimators.bcrls_covariance import add_lagged_moments
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.moment_covariance import MAX_BLOCKS, MomentBlocks
from equivalence import assert_paths_agree, assert_within, EPS, rounding_spread


# ------------------------------------------------------------------ formulas
def offline_hac(y, u, theta, lam, covariance):
    """
    Return rls's covariance built offline: the HAC of its scores phi_t e_t.

    The scores of the updates from the gate's warm-up on (tau >= 10 p = 60), e_t the
    a-priori error with the estimate before the sample (``theta`` after each sample).
    """
    hac = HacCovariance(dimension=6, forgetting_factor=lam)
    for t in range(2, y.shape[0]):
        phi = np.array([-y[t - 1], -y[t - 2], u[t - 1, 0], u[t - 2, 0], u[t - 1, 1], u[t - 2, 1]])
        tau = (1.0 - lam ** (t - 1)) / (1.0 - lam) if lam < 1.0 else t - 1.0  # after update t
        if tau >= 60.0:
            hac.record(phi * (y[t] - phi @ theta[t - 1]))
    return hac.covariance(covariance)


@pytest.mark.parametrize('lam', [1.0, 0.99])
def test_rls_covariance_is_the_hac_of_its_scores(lam):
    y, u = arx_data(np.random.default_rng(1), 1500)

    def estimate(y, u):
        estimator = make_estimator('rls', order=2, num_inputs=2, forgetting_factor=lam)
        theta = estimator.run(y, u).theta
        return estimator, theta

    def online(y, u):
        return {'covariance': estimate(y, u)[0].parameter_covariance}

    def offline(y, u):
        estimator, theta = estimate(y, u)
        return {'covariance': offline_hac(y, u, theta, lam, estimator.covariance)}

    # two paths (the products formed per block there and per sample here, the a-priori
    # error from BLAS there and numpy here): within the rounding spread of the offline one
    spread = rounding_spread(offline, y, u)
    assert_paths_agree(online(y, u), offline(y, u), spread, y.shape[0], 'rls HAC')
    estimator = estimate(y, u)[0]
    np.testing.assert_array_equal(estimator.parameter_std,
                                  np.sqrt(np.diag(estimator.parameter_covariance)))
    # one output changed by a millionth of its value: the bound sees it
    changed = y.copy()
    changed[700] *= 1.0 + 1e-6
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(online(changed, u), offline(y, u), spread, y.shape[0], 'rls HAC')


def test_the_effective_sample_size_ratio():
    lam = 0.99
    updates = 1498
    weights = lam ** np.arange(updates)
    tau = weights.sum()
    # the closed form equals sum(w^2) / sum(w) over the weights of the updates
    assert weighted_square_ratio(tau, lam) == pytest.approx(
        (weights ** 2).sum() / weights.sum(), rel=1e-9)
    assert weighted_square_ratio(10.0, 1.0) == 1.0
    assert weighted_square_ratio(1e9, 0.5) == pytest.approx(1.0 / 1.5)


def test_not_ready_estimators_have_no_covariance():
    for name in ('rls', 'bcrls'):
        estimator = make_estimator(name, order=2, num_inputs=2)
        assert estimator.parameter_covariance is None and estimator.parameter_std is None
    assert standard_deviations(None) is None


def test_bcrls_lagged_moments_equal_the_batch_sums_and_survive_a_state_round_trip():
    y, u = ding_data(np.random.default_rng(3), 1000)
    estimator = run('bcrls', y, u)
    # the snapshot's moments: the sums so far, and the ring of the lag context and pending rows
    state = estimator.get_state()
    ring = state.arrays['moment_ring'][:estimator.order + state.scalars['moment_pending']]
    sums, weight = add_lagged_moments(state.arrays['moment_sums'], state.scalars['moment_weight'],
                                      ring, estimator.order, estimator.forgetting_factor)
    phi = np.column_stack([-y[1:-1], -y[:-2], u[1:-1, 0], u[:-2, 0], u[1:-1, 1], u[:-2, 1]])
    z = np.column_stack([phi, y[2:]])
    assert weight == z.shape[0]

    def bound(z, k):
        # blocks of 64 rows added up against one product over all N rows: two summation
        # orders of N terms, each within N eps sum |term| of the exact sum (Higham)
        return 2 * z.shape[0] * EPS * (np.abs(z[k:]).T @ np.abs(z[:z.shape[0] - k]))

    for k in range(3):
        assert_within(sums[k], z[k:].T @ z[:z.shape[0] - k], bound(z, k), f'lag {k}')
    # one sample changed by a millionth of its value: far above that bound
    changed = z.copy()
    changed[500, 1] *= 1.0 + 1e-6
    with pytest.raises(AssertionError, match='times the bound'):
        assert_within(sums[0], changed.T @ changed, bound(changed, 0))
    # a snapshot in the middle of a block continues to the same covariance, bit for bit
    first = run('bcrls', y[:537], u[:537])
    second = make_estimator('bcrls', order=2, num_inputs=2)
    second.set_state(first.get_state())
    for k in range(537, 1000):
        first.update(y[k], u[k])
        second.update(y[k], u[k])
    np.testing.assert_array_equal(first.parameter_covariance, second.parameter_covariance)
    np.testing.assert_array_equal(first.parameter_covariance, estimator.parameter_covariance)


def test_bcrls_covariance_is_unit_free():
    y, u = ding_data(np.random.default_rng(4), 1500)
    base = run('bcrls', y, u)
    scaled = run('bcrls', y * 1e-3, u * 1e4)
    # theta: a -> a, b -> b s_y / s_u; so std of b scales by 1e-7. The scaled data are the
    # same up to half an ulp per sample and a prior p0 S^-2 up to 4x apart (~1 / (p0 N)):
    # measured 1.4e-8 relative, 1e-6 leaves room
    factor = np.array([1.0, 1.0, 1e-7, 1e-7, 1e-7, 1e-7])
    np.testing.assert_allclose(scaled.parameter_std, base.parameter_std * factor, rtol=1e-6)
    covariance = base.parameter_covariance
    np.testing.assert_allclose(covariance, covariance.T, rtol=0, atol=0)
    assert np.linalg.eigvalsh(covariance).min() > 0


def check_covariance_matrix(covariance):
    """Assert a finite, exactly symmetric, positive definite matrix."""
    assert np.isfinite(covariance).all()
    np.testing.assert_array_equal(covariance, covariance.T)
    assert np.linalg.eigvalsh(covariance).min() > 0


@pytest.mark.parametrize('name, data, settings', [
    ('bciv', ikenoue, IKENOUE_COLORED), ('cl_bcls', ikeda, IKEDA)], ids=['bciv', 'cl_bcls'])
def test_block_covariance_none_before_ready_and_16_blocks_then_psd(name, data, settings):
    y, u = data(3000, 5)
    estimator = make_estimator(name, **settings)
    assert estimator.parameter_covariance is None
    # 16 blocks of 32 updates (samples for cl_bcls) after the first boundary
    for k in range(400):
        estimator.update(y[k], u[k])
    assert estimator.ready and estimator.parameter_std is None
    for k in range(400, 3000):
        estimator.update(y[k], u[k])
    covariance = estimator.parameter_covariance
    check_covariance_matrix(covariance)
    np.testing.assert_array_equal(estimator.parameter_std, np.sqrt(np.diag(covariance)))
    # a reset forgets the blocks
    estimator.reset()
    assert estimator.parameter_covariance is None


def test_bciv_printed_update_publishes_no_covariance():
    y, u = ikenoue(1500, 6)
    estimator = run_single('bciv', y, u, bciv_update='printed', **IKENOUE_COLORED)
    assert estimator.ready and estimator.parameter_covariance is None


@pytest.mark.parametrize('name, data, settings', [
    ('bciv', ikenoue, IKENOUE_COLORED), ('cl_bcls', ikeda, IKEDA)], ids=['bciv', 'cl_bcls'])
def test_block_covariance_scales_with_the_units(name, data, settings):
    y, u = data(2000, 7)
    base = run_single(name, y, u, **settings)
    if name == 'cl_bcls':
        # the controller maps the scaled y to the scaled u: its gain times 1e4 / 1e-3
        settings = dict(settings, controller_numerator=[0.2289e7])
    scaled = run_single(name, y * 1e-3, u * 1e4, **settings)
    # theta: a -> a, b -> b s_y / s_u = 1e-7 b, so the std of b scales by 1e-7. Only the
    # prior (up to 16x apart in normalised units) and half an ulp per sample differ:
    # measured theta 1.4e-8 (bciv) and 4e-15 (cl_bcls) relative, std 4e-8 and 1e-6
    factor = np.repeat([1.0, 1e-7], settings['order'])
    np.testing.assert_allclose(scaled.theta, base.theta * factor, rtol=1e-7)
    np.testing.assert_allclose(scaled.parameter_std, base.parameter_std * factor, rtol=1e-4)
    check_covariance_matrix(scaled.parameter_covariance)


def test_moment_blocks_sum_each_block_exactly_with_forgetting():
    lam = 0.999
    rng = np.random.default_rng(8)
    terms = rng.standard_normal((5000, 3))
    blocks = MomentBlocks()
    sums, tau = np.zeros(3), 0.0
    boundaries = []
    for t in range(terms.shape[0]):
        sums = lam * sums + terms[t]
        tau = lam * tau + 1.0
        if t + 1 >= blocks.next_boundary:
            boundaries.append(t + 1)
            blocks.close(t + 1, sums, tau, lam, 0, lambda: lambda v: v)
    # 1 / (16 (1 - lambda)) = 62.5: the blocks stop doubling at 32 rows, the oldest go
    assert blocks.block_length == 32 and blocks.blocks == MAX_BLOCKS - 1
    for index, block in enumerate(blocks._sums):
        end = boundaries[len(boundaries) - blocks.blocks + index]
        rows = terms[end - 32:end]
        weights = lam ** np.arange(31, -1, -1)
        # a block is the difference of two running sums of ~1 / (1 - lambda) = 1000 terms
        # (rounding ~1e3 eps of their size, ~1e-12); 1e-9 is far above it
        np.testing.assert_allclose(block, weights @ rows, rtol=1e-9, atol=1e-9)
        # the closed form (1 - lambda^32) / (1 - lambda) against a sum of 32 powers: the
        # cancellation in 1 - lambda^32 costs eps / 0.03 ~ 1e-14 relative, 1e-12 is above it
        assert blocks._weights[index][1] == pytest.approx(weights.sum(), rel=1e-12)
        assert blocks._weights[index][2] == pytest.approx((weights ** 2).sum(), rel=1e-12)


def test_moment_blocks_long_run_covariance_of_a_mean():
    # white terms with covariance diag(1, 4): the mean of N has covariance diag(1, 4) / N
    rng = np.random.default_rng(9)
    count = 4096
    terms = rng.standard_normal((count, 2)) * [1.0, 2.0]
    blocks = MomentBlocks()
    sums = np.zeros(2)
    for t in range(count):
        sums += terms[t]
        if t + 1 >= blocks.next_boundary:
            blocks.close(t + 1, sums, float(t + 1), 1.0, 0, lambda: lambda v: v)
    covariance = blocks.covariance(float(count), 1.0) * count
    # about 64 blocks: a variance from them has a relative standard error sqrt(2 / 63) = 18 %
    np.testing.assert_allclose(np.diag(covariance), [1.0, 4.0], rtol=4 * math.sqrt(2 / 63))
    # a second group with another mean (from the boundary at 2049 = 1 + 64 * 32 on) does
    # not inflate the spread
    shifted = MomentBlocks()
    sums = np.zeros(2)
    for t in range(count):
        sums += terms[t] + (10.0 if t >= 2049 else 0.0)
        if t + 1 >= shifted.next_boundary:
            shifted.close(t + 1, sums, float(t + 1), 1.0, t >= 2049, lambda: lambda v: v)
    assert shifted.covariance(float(count), 1.0)[0, 0] * count < 1.0 + 4 * math.sqrt(2 / 60)


def test_block_covariance_skips_a_block_whose_sums_are_not_its_own():
    y, u = ikenoue(2500, 10)
    starts = []
    for cut in (False, True):
        estimator = run_single('bciv', y[:2000], u[:2000], **IKENOUE_COLORED)
        blocks = estimator._blocks
        add, calls = blocks._add, []
        # record where each added block starts (the previous boundary)
        blocks._add = lambda *args, add=add, calls=calls, blocks=blocks: (
            calls.append(blocks._base_count), add(*args))
        if cut:
            # a memory cut (a detected plant change) scales the moments
            estimator._accept_change()
        for k in range(2000, 2500):
            estimator.update(y[k], u[k])
        starts.append(calls)
        check_covariance_matrix(estimator.parameter_covariance)
    # without the cut the block over it is added; with it, that block is skipped
    assert starts[0][0] < 1989 < starts[0][1]
    assert starts[1][0] == starts[0][1]


def test_block_covariance_restarts_after_a_restored_state():
    y, u = ikenoue(1800, 11)
    first = run_single('bciv', y[:1000], u[:1000], **IKENOUE_COLORED)
    assert first.parameter_covariance is not None
    second = make_estimator('bciv', **IKENOUE_COLORED)
    second.set_state(first.get_state())
    # the blocks are not saved: none until 16 new blocks of 32 updates
    assert second.parameter_covariance is None
    second.run(y[1000:1800], u[1000:1800])
    np.testing.assert_array_equal(second.theta, run_single(
        'bciv', y, u, **IKENOUE_COLORED).theta)
    check_covariance_matrix(second.parameter_covariance)


def test_moment_blocks_give_none_when_the_function_fails_and_do_not_retry_at_every_read():
    blocks, sums, calls = MomentBlocks(), np.zeros(2), []

    def failing(means):
        calls.append(1)
        raise ArithmeticError('no fixed point')
    terms = np.random.default_rng(12).standard_normal((1000, 2))
    for t in range(terms.shape[0]):
        sums += terms[t]
        if t + 1 >= blocks.next_boundary:
            blocks.close(t + 1, sums, float(t + 1), 1.0, 0, lambda: failing)
    assert blocks.blocks >= 16
    assert blocks.covariance(1000.0, 1.0) is None and blocks.covariance(1000.0, 1.0) is None
    assert len(calls) == 1
