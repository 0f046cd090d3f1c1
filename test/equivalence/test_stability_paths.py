"""
One stability module: its answers against the two algorithms it replaced.

``bcid_ros.estimators.polynomials`` decides degrees 1 and 2 by Jury's conditions and takes
the spectral radius from closed forms and the companion matrix. Before it, the LTI helpers
ran the Schur-Cohn recursion on every degree and took the radius from ``numpy.roots`` of the
polynomial written out; the closed-loop estimator, the batch prediction-error fits and the
closed-loop scenario used those. Above degree 2 the test is the same arithmetic, moved;
below, the decisions may differ only where a root lies within the rounding of the
coefficients of the circle, and the radii within the rounding spread.
"""

import numpy as np

from bcid_ros.estimators.polynomials import is_stable, monic_coefficients, spectral_radius
from equivalence import assert_paths_agree, EPS, path_bound, two_path_spread

#: Roundings in the two paths' scaled coefficients: the division by the lead and by
#: radius^i (itself rounded) and, in Schur-Cohn, 1 - k^2, its inverse and one product and
#: difference per step: at most 8 unit roundoffs in each path, 16 u = 8 eps between them.
ROUNDINGS = 8.0


def schur_cohn(polynomial, margin):
    """Return the former ``lti.is_stable`` of degree 1 or 2: its Schur-Cohn steps written out."""
    c = [float(v) for v in polynomial]
    radius = 1.0 - margin
    a1 = c[1] / (c[0] * radius)
    if len(c) == 2:
        return abs(a1) < 1.0
    k2 = c[2] / (c[0] * radius ** 2)
    # the step down from degree 2: a1 <- (a1 - k2 a1) / (1 - k2^2)
    return abs(k2) < 1.0 and abs((a1 - k2 * a1) * (1.0 / (1.0 - k2 * k2))) < 1.0


def root_condition(polynomial):
    """
    Return max over roots z of sum |c_i| |z|^(n-i) / |p'(z)|: the move of a root per unit.

    A relative change delta of every coefficient moves a simple root by at most this times
    delta (first order), so a radius closer than that to the circle may be decided either way.
    """
    roots = np.roots(polynomial)
    degree = len(polynomial) - 1
    size = sum(abs(c) * np.abs(roots) ** (degree - i) for i, c in enumerate(polynomial))
    derivative = np.abs(np.polyval(np.polyder(polynomial), roots))
    with np.errstate(divide='ignore'):
        return float(np.max(size / derivative))


def random_polynomials(rng, degree, count):
    """Return monic polynomials with roots near and on both sides of radius 1 - margin."""
    polynomials = []
    for _ in range(count):
        roots = []
        while len(roots) < degree:
            modulus = rng.choice([rng.uniform(0.2, 1.3), 1.0 + rng.normal(0.0, 1e-13)])
            if degree - len(roots) >= 2 and rng.random() < 0.5:
                root = modulus * np.exp(1j * np.pi * rng.random())
                roots += [root, np.conj(root)]
            else:
                roots.append(modulus * rng.choice([-1.0, 1.0]))
        polynomials.append(np.real(np.poly(roots)) * rng.choice([1.0, 1.7]))
    return polynomials


def test_stability_decisions_agree_but_within_the_rounding_of_the_circle():
    rng = np.random.default_rng(11)
    near = 0
    for degree in (1, 2):
        for polynomial in random_polynomials(rng, degree, 4000):
            for margin in (0.0, 1e-6, 0.001):
                new = is_stable(monic_coefficients(polynomial), margin)
                old = schur_cohn(polynomial, margin)
                radius = np.abs(np.roots(polynomial)).max()
                bound = ROUNDINGS * EPS * root_condition(polynomial)
                if abs(radius - (1.0 - margin)) <= bound:
                    near += 1
                else:
                    assert new == old, (polynomial, margin, radius)
    assert near > 100  # the test reached the circle
    # a wrong decision (a root 1e-9 beyond the circle taken as inside) is outside the bound
    assert not is_stable(monic_coefficients([1.0, -(1.0 + 1e-9)]), 0.0)


def test_spectral_radius_agrees_with_the_roots_within_the_rounding_spread():
    rng = np.random.default_rng(12)
    polynomials = np.array([np.real(np.poly(rng.uniform(-0.95, 0.95, 2))) for _ in range(400)]
                           + [np.real(np.poly(r * np.exp([1j, -1j])))
                              for r in rng.uniform(0.1, 1.2, 400)])
    polynomials[:, :] *= rng.choice([1.0, 3.0], (polynomials.shape[0], 1))

    def new(coefficients):
        return {'radius': np.array([[spectral_radius(monic_coefficients(c))]
                                    for c in coefficients])}

    def old(coefficients):
        return {'radius': np.array([[np.abs(np.roots(c)).max()] for c in coefficients])}

    spread = two_path_spread(new, old, polynomials)
    assert_paths_agree(new(polynomials), old(polynomials), spread, steps=1, what='radius')
    # a real change (one coefficient moved by 1e-6) is far beyond the bound
    moved = polynomials.copy()
    moved[0, 2] += 1e-6
    deviation = abs(new(moved)['radius'][0, 0] - old(polynomials)['radius'][0, 0])
    assert deviation > path_bound(old(polynomials)['radius'][:1], spread['radius'][:1], 1)[0]
