"""Unit tests of the stability of polynomials in bcid_ros.estimators.polynomials."""

import numpy as np
import pytest

from bcid_ros.estimators.polynomials import (is_stable, monic_coefficients, spectral_radii,
                                             spectral_radius)


@pytest.mark.parametrize('polynomial, stable', [
    ([1.0, -0.5], True),                 # q - 0.5
    ([1.0, 0.999], True),                # root -0.999: inside the 1e-6 margin
    ([1.0, -1.0], False),                # root on the circle
    ([1.0, -1.0 + 1e-7], False),         # inside the circle but within the margin
    ([1.0, 0.0, 0.25], True),            # roots +-0.5j
    ([1.0, 0.0, 1.0], False),            # roots +-j
    ([1.0, -1.5, 0.56], True),           # (q - 0.7)(q - 0.8)
    ([1.0, -1.2, 1.1], False),           # complex pair of modulus sqrt(1.1)
    ([1.0, -2.5, 1.0], False),           # roots 2 and 0.5
    ([1.0, -2.4, 1.91, -0.504], True),   # (q - 0.7)(q - 0.8)(q - 0.9)
    ([1.0, -2.6, 2.21, -0.616], False),  # (q - 0.7)(q - 0.8)(q - 1.1)
    ([2.0, -1.0], True),                 # 2q - 1: a non-monic lead is scaled out
    ([0.0, 1.0, -0.5], True),            # leading zeros are ignored
    ([1.0], True),                       # a non-zero constant has no roots
    ([0.0, 0.0], False),                 # the zero polynomial
])
def test_is_stable_on_known_polynomials(polynomial, stable):
    a = monic_coefficients(polynomial)
    assert is_stable(a) == stable
    trimmed = np.trim_zeros(np.asarray(polynomial), 'f')
    if trimmed.size > 1:
        assert spectral_radius(a) == pytest.approx(np.abs(np.roots(trimmed)).max())


def test_monic_coefficients_divide_by_the_lead_and_drop_it():
    np.testing.assert_array_equal(monic_coefficients([0.0, 2.0, -1.0, 0.5]), [-0.5, 0.25])
    assert monic_coefficients([3.0]).size == 0
    assert spectral_radius(monic_coefficients([3.0])) == 0.0
    assert monic_coefficients([0.0]).tolist() == [np.inf]


def test_margin_moves_the_circle():
    assert is_stable([-0.9], margin=0.05)
    assert not is_stable([-0.9], margin=0.2)
    assert is_stable([-1.0], margin=0.0) is False
    # Jury's conditions on degree 2 scale by the radius as well: roots 0.85 +- 0.1j
    a = np.real(np.poly([0.85 + 0.1j, 0.85 - 0.1j]))[1:]
    assert is_stable(a, margin=0.1) and not is_stable(a, margin=0.15)


def test_the_test_agrees_with_the_roots_away_from_the_circle():
    rng = np.random.default_rng(3)
    for _ in range(600):
        a = rng.uniform(-2, 2, rng.integers(1, 7))
        radius = np.abs(np.roots(np.concatenate(([1.0], a)))).max()
        if abs(radius - 1.0) > 1e-3:
            assert is_stable(a) == (radius < 1.0), a
            assert is_stable(a, 0.0) == (radius < 1.0), a
    assert not is_stable([float('nan')])
    assert not is_stable([0.5, float('nan')])
    assert not is_stable([0.1, float('inf'), 0.1])
    assert is_stable(np.zeros(0))


def test_spectral_radius_of_a_quadratic_equals_the_companion_eigenvalues():
    rng = np.random.default_rng(3)
    pairs = np.vstack([rng.uniform(-3, 3, (2000, 2)),
                       [[-2.0, 1.0], [2.0, 1.0], [0.0, 0.0], [-0.84, 0.16], [1e-8, -1e-8]]])
    for a in pairs:
        companion = np.array([[-a[0], -a[1]], [1.0, 0.0]])
        expected = np.abs(np.linalg.eigvals(companion)).max()
        # a double root: the eigenvalues are only good to sqrt(eps)
        assert spectral_radius(a) == pytest.approx(expected, rel=1e-7, abs=1e-12), a
    assert spectral_radius(np.array([np.nan, 0.5])) == np.inf
    assert spectral_radius(np.array([1e200, 1.0])) == pytest.approx(1e200)


@pytest.mark.parametrize('order', [0, 1, 2, 3, 5])
def test_spectral_radii_of_many_plants_are_those_of_each(order):
    rng = np.random.default_rng(order)
    a = rng.uniform(-1.5, 1.5, (40, order))
    a[7, :] = np.nan if order else a[7, :]
    many = spectral_radii(a)
    # one row takes the closed forms on floats for n <= 2, the batch numpy's: the same formulas
    for k in range(a.shape[0]):
        assert many[k] == pytest.approx(spectral_radius(a[k]), rel=1e-14, abs=0.0), k
    if order:
        assert many[7] == np.inf
    else:
        np.testing.assert_array_equal(many, 0.0)
