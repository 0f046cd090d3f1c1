"""The shared recursive step (estimators/recursion.py): the step and the propagation of P."""

import numpy as np

from bcid_ros.estimators.recursion import downdate, Forgetting, innovation, ls_step, RandomWalk


def spd(rng, count, size):
    a = rng.standard_normal((count, size, size))
    return a @ np.swapaxes(a, 1, 2) + np.eye(size)


def test_downdate_is_the_covariance_part_of_the_step():
    rng = np.random.default_rng(3)
    p = spd(rng, 1, 5)[0]
    theta, phi = rng.standard_normal(5), rng.standard_normal(5)
    e, g, s = innovation(theta, p, phi, 0.3, 0.99)
    # one arithmetic path (the same BLAS dscal and dger): bit equal
    stepped = ls_step(theta.copy(), p.copy(), g.copy(), s, e)
    np.testing.assert_array_equal(downdate(p.copy(), g.copy(), s), stepped)


def test_forgetting_divides_by_lambda_and_holds_at_the_trace_limit():
    rng = np.random.default_rng(4)
    p = spd(rng, 4, 3)
    weights = rng.uniform(0.5, 2.0, (4, 3))
    traces = np.einsum('kii,ki->k', p, weights)
    # the limit between the plants' weighted traces: the two largest are held
    forgetting = Forgetting(float(np.sort(traces)[1]) * 1.0000001)
    held_expected = traces >= forgetting.trace_limit
    assert held_expected.sum() == 2
    batched = p.copy()
    held = forgetting.propagate(batched, 0.9, weights)
    np.testing.assert_array_equal(held, held_expected)
    for k in range(4):
        one = p[k].copy()
        assert forgetting.propagate_one(one, 0.9, weights[k]) == held_expected[k]
        # one multiplication by 1 / lambda (or none) per entry either way: bit equal
        np.testing.assert_array_equal(one, batched[k])
        np.testing.assert_array_equal(one, p[k] if held_expected[k] else p[k] * (1.0 / 0.9))
    # lambda = 1: nothing happens and nothing is held
    same = p.copy()
    assert not Forgetting(0.0).propagate(same, 1.0, weights).any()
    np.testing.assert_array_equal(same, p)
    # without a limit: always forgets, whatever the trace (unweighted form of rpem/cl_bcls)
    unlimited = p[0].copy()
    assert not Forgetting(np.inf).propagate_one(unlimited, 0.5)
    np.testing.assert_array_equal(unlimited, p[0] * 2.0)


def test_random_walk_adds_q_in_normalised_units_and_never_holds():
    rng = np.random.default_rng(5)
    p = spd(rng, 3, 4)
    scales2 = 4.0 ** rng.integers(-2, 3, (3, 4)).astype(float)
    walk = RandomWalk(1e-4)
    batched = p.copy()
    assert not walk.propagate(batched, 1.0, scales2).any()
    for k in range(3):
        # Q = q S^-2 on the diagonal, the off-diagonal untouched: P grows, never collapses
        np.testing.assert_array_equal(batched[k], p[k] + np.diag(1e-4 / scales2[k]))
        one = p[k].copy()
        assert not walk.propagate_one(one, 1.0, scales2[k])
        np.testing.assert_array_equal(one, batched[k])
    plain = p[0].copy()
    walk.propagate_one(plain, 1.0)
    np.testing.assert_array_equal(plain, p[0] + 1e-4 * np.eye(4))
