"""rpem/window.py: the move of a fit against the last one of a nested window (Hausman)."""

import numpy as np
import pytest

from bcid_ros.estimators.rpem.window import moved

#: A correlated covariance of three parameters per sample.
SIGMA = np.array([[1.0, 0.6, 0.2], [0.6, 2.0, -0.3], [0.2, -0.3, 0.5]])
#: Two parameters correlated 0.99 (a slow plant's numerator and pole), and a third: the
#: correlation matrix's eigenvalues 0.01, 1 and 1.99, the smallest 0.005 of the largest.
TIGHT = np.array([[1.0, 1.98, 0.0], [1.98, 4.0, 0.0], [0.0, 0.0, 0.5]])
#: A covariance of ten decades (eigenvalues 1, 1e-2 and 1e-10 in a random frame).
ROTATION = np.linalg.qr(np.random.default_rng(9).standard_normal((3, 3)))[0]
DECADES = (ROTATION * np.array([1.0, 1e-2, 1e-10])) @ ROTATION.T


def nested_means(rng, first, second, shift=0.0, sigma=SIGMA):
    """Return the means of the first ``first`` and of all ``second`` samples (a later shift)."""
    samples = rng.multivariate_normal(np.zeros(3), sigma, size=second)
    samples[first:] += shift
    return samples[:first].mean(axis=0), samples.mean(axis=0)


@pytest.mark.parametrize('sigma', [SIGMA, TIGHT, DECADES])
def test_nested_means_of_one_distribution_move_at_the_stated_rate(sigma):
    # 4000 pairs at level 1 %: W over the directions kept is chi-square with as many degrees
    # of freedom (the projections on the correlation matrix's eigenvectors are independent),
    # 40 expected, sd 6.3; the bound is 5 sd either side of 40
    rng = np.random.default_rng(7)
    count = 0
    for _ in range(4000):
        older, newer = nested_means(rng, 200, 300, sigma=sigma)
        count += moved(newer - older, sigma / 300, 300.0, 200.0, level=0.01)
    assert 8 <= count <= 72


def test_a_step_along_a_tight_combination_of_correlated_parameters_is_a_move():
    """
    A drift moves correlated parameters together: 6 std of their tight combination is a move.

    Tracking plants (0, 17) and (2, 21) during their drifts: every parameter within 1.3-3.3
    of its std, W 18-93 against 16.3. Judged parameter by parameter (Bonferroni: 3.59 at
    1e-3), this step of 0.42 std per parameter was no move (rpem/window.py).
    """
    values, vectors = np.linalg.eigh(TIGHT / np.sqrt(np.outer(np.diag(TIGHT),
                                                              np.diag(TIGHT))))
    z = 6.0 * np.sqrt(values[0]) * vectors[:, 0]  # 6 std along the tight direction
    assert np.max(np.abs(z)) < 0.5
    step = z * np.sqrt(np.diag(TIGHT) * 0.5)  # in units: z times sqrt(C_kk (N2/N1 - 1))
    assert moved(step, TIGHT, 300.0, 200.0)
    assert not moved(step / 3.0, TIGHT, 300.0, 200.0)  # W = 4 against 16.3


def test_a_shift_of_the_newer_samples_is_a_move():
    # the 100 newer samples shifted by 0.5 sd: the means differ by 1/6 sd, about 6 sd of the
    # difference's spread (sqrt(1/200 - 1/300) = 0.041 sd)
    rng = np.random.default_rng(8)
    moves = [moved(newer - older, SIGMA / 300, 300.0, 200.0)
             for older, newer in (nested_means(rng, 200, 300, shift=0.5 * np.sqrt(
                 np.diag(SIGMA))) for _ in range(50))]
    assert np.mean(moves) > 0.9


def test_no_spread_or_no_newer_samples_is_no_move():
    step = np.array([1.0, 0.0, 0.0])
    assert not moved(step, SIGMA, 300.0, 300.0)  # the same window: nothing to compare
    assert not moved(step, np.zeros((3, 3)), 300.0, 200.0)  # no spread to judge against
    assert not moved(step, -SIGMA, 300.0, 200.0)  # not a covariance
    assert not moved(np.full(3, np.nan), SIGMA, 300.0, 200.0)


def test_a_step_along_the_weakest_direction_alone_is_no_move():
    """
    A covariance of ten decades: a step of 6 std along its weakest direction, none per parameter.

    Tracking plant (1, 5) after its change: every parameter within 1.4 std of the older fit,
    5.2 std along the covariance's weakest direction (cond 4.5e10), W 62.6 against 27.9. The
    test leaves out the directions of the correlation matrix below CONDITION_FLOOR of its
    largest eigenvalue: they are not what a fit of a few hundred samples honours
    (rpem/window.py).
    """
    rotation, values, covariance = ROTATION, np.array([1.0, 1e-2, 1e-10]), DECADES
    step = 6.0 * np.sqrt(values[2]) * rotation[:, 2]  # W = 6^2 times (N2/N1 - 1)^-1
    assert not moved(step * np.sqrt(0.5), covariance, 300.0, 200.0)
    # the same size along a parameter's own std is a move
    assert moved(6.0 * np.sqrt(covariance[0, 0] * 0.5) * np.eye(3)[0], covariance, 300.0, 200.0)
