"""Unit tests of the LTI helpers in bcid_ros.estimators.lti."""

import numpy as np
import pytest
import scipy.linalg
from scipy import signal

from bcid_ros.estimators import lti
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from equivalence import assert_paths_agree, assert_within, EPS, two_path_spread


def random_stable_polynomial(rng, degree, radius=0.9):
    """Return a monic real polynomial with random roots of modulus < radius."""
    roots = []
    while len(roots) < degree:
        if degree - len(roots) >= 2 and rng.random() < 0.5:
            root = radius * rng.random() * np.exp(1j * np.pi * rng.random())
            roots += [root, np.conj(root)]
        else:
            roots.append(radius * rng.uniform(-1, 1))
    return np.real(np.poly(roots))


def test_controller_sign_folds_into_the_numerator():
    negative = lti.make_controller([0.2289], [1.0, -0.09004], 'negative')
    positive = lti.make_controller([-0.2289], [1.0, -0.09004], 'positive')
    np.testing.assert_array_equal(negative.feedback_numerator, positive.feedback_numerator)
    np.testing.assert_array_equal(negative.numerator, [0.0, 0.2289])


def test_stable_reflection_is_all_pass_and_stable():
    a_p = np.real(np.poly([1.25, 0.5, 1.1 + 0.6j, 1.1 - 0.6j]))
    bar = lti.stable_reflection(a_p)
    assert is_stable(monic_coefficients(bar))
    gain = np.abs(np.polyval(a_p, np.exp(1j * np.linspace(0, np.pi, 50))) /
                  np.polyval(bar, np.exp(1j * np.linspace(0, np.pi, 50))))
    # quartics with no root within 0.1 of the circle, evaluated on it: ~1e-15 relative
    # each, and the mirrored roots a few ulps off; 1e-10 is far above that
    np.testing.assert_allclose(gain, gain[0], rtol=1e-10)
    np.testing.assert_array_equal(lti.stable_reflection([1.0, -0.8]), [1.0, -0.8])


def test_stein_solver_against_residual_and_scipy():
    rng = np.random.default_rng(4)
    for _ in range(20):
        rows, cols = rng.integers(1, 6, size=2)
        a = rng.standard_normal((rows, rows))
        a *= 0.95 / max(np.abs(np.linalg.eigvals(a)).max(), 1e-3)
        b = rng.standard_normal((cols, cols))
        b *= 0.95 / max(np.abs(np.linalg.eigvals(b)).max(), 1e-3)
        c = rng.standard_normal((rows, cols))
        x = lti.solve_stein(a, b, c)
        # the residual of a backward-stable solve: a few roundings of the sizes in A X B + C
        # per entry, whatever the conditioning (the rows * cols terms of each product)
        size = np.abs(a) @ np.abs(x) @ np.abs(b) + np.abs(c) + np.abs(x)
        assert_within(x, a @ x @ b + c, 4 * rows * cols * EPS * size, 'residual')
        q = c @ c.T if rows == cols else np.eye(rows)

        def ours(a, q):
            return {'x': lti.solve_stein(a, a.T, q)}

        def theirs(a, q):
            return {'x': scipy.linalg.solve_discrete_lyapunov(a, q)}

        # a Kronecker solve against scipy's: two paths, within the rounding spreads of both
        assert_paths_agree(ours(a, q), theirs(a, q), two_path_spread(ours, theirs, a, q), 1,
                           'lyapunov')


def test_stein_solver_equals_the_direct_kronecker_solve():
    rng = np.random.default_rng(6)
    for _ in range(20):
        rows, cols = rng.integers(1, 5, size=2)
        a = 0.5 * rng.standard_normal((rows, rows))
        b = 0.5 * rng.standard_normal((cols, cols))
        c = rng.standard_normal((rows, cols))

        def direct(a, b, c):
            # vec(A X B) = (B' kron A) vec(X), column-major vec
            lhs = np.eye(rows * cols) - np.kron(b.T, a)
            x = np.linalg.solve(lhs, c.flatten(order='F'))
            return {'x': x.reshape((rows, cols), order='F')}

        def ours(a, b, c):
            return {'x': lti.solve_stein(a, b, c)}

        # scipy's solve against numpy's (each with its own LAPACK and BLAS): two paths,
        # within the rounding spreads of both
        spread = two_path_spread(ours, direct, a, b, c)
        assert_paths_agree(ours(a, b, c), direct(a, b, c), spread, 1, 'stein')
    # the last system with one entry of C moved by a millionth: the bound sees it
    moved = c.copy()
    moved[0, 0] *= 1.0 + 1e-6
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(ours(a, b, moved), direct(a, b, c), spread, 1)


def test_stein_solver_refuses_mismatched_shapes_and_a_singular_system():
    with pytest.raises(ValueError, match=r'solve_stein needs A \(r, r\), B \(c, c\) and '
                                         r'C \(r, c\); got A \(2, 2\), B \(3, 3\), C \(2, 2\)'):
        lti.solve_stein(np.eye(2), np.eye(3), np.ones((2, 2)))
    # eigenvalue 1 of A times eigenvalue 1 of B: I - B' kron A is singular
    with pytest.raises(np.linalg.LinAlgError):
        lti.solve_stein(np.eye(2), np.eye(2), np.ones((2, 2)))


# ------------------------------------------------------------ realisations
@pytest.mark.parametrize('seed', range(5))
def test_controller_canonical_round_trip(seed):
    rng = np.random.default_rng(seed)
    degree = int(rng.integers(1, 6))
    d = random_stable_polynomial(rng, degree, radius=0.95)
    c = rng.standard_normal(degree)
    impulse = np.zeros(30)
    impulse[0] = 1.0

    def realisation(tail, c):
        a, b = lti.controller_canonical(np.r_[1.0, tail])
        state, response = np.zeros(degree), []
        for w in impulse:
            response.append(c @ state)
            state = a @ state + b * w
        # the characteristic polynomial of A (eigenvalues, then their polynomial)
        return {'polynomial': np.poly(a), 'response': np.array(response)}

    def transfer_function(tail, c):
        # c' (qI - A)^-1 b = c(q)/d(q): the impulse response of (A, b, c') is that of c/d
        return {'polynomial': np.r_[1.0, tail],
                'response': signal.lfilter(np.concatenate(([0.0], c)), np.r_[1.0, tail],
                                           impulse)}

    # eigenvalues and the state recursion against d itself and lfilter: two paths, within
    # the rounding spreads of both (the roots' conditioning is in the eigenvalues' spread)
    data = (d[1:], c)
    spread = two_path_spread(realisation, transfer_function, *data)
    assert_paths_agree(realisation(*data), transfer_function(*data), spread, 30, f'seed {seed}')
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(realisation(d[1:] * (1.0 + 1e-6), c), transfer_function(*data),
                           spread, 30)


def test_controller_canonical_refuses_a_non_monic_or_constant_polynomial():
    with pytest.raises(ValueError, match=r'polynomial must be monic of degree >= 1 .*'
                                         r'got \[2.0, -1.0\]'):
        lti.controller_canonical(np.array([2.0, -1.0]))
    with pytest.raises(ValueError, match=r'got \[1.0\]'):
        lti.controller_canonical(np.array([1.0]))


def test_closed_loop_polynomial_of_the_paper_example():
    # (q - 0.8)(q - 0.09004) + 0.5 * 0.2289: eq. (8) for the plant and controller (60)
    controller = lti.make_controller([0.2289], [1.0, -0.09004])
    d_cl = lti.closed_loop_polynomial(np.array([1.0, -0.8]), np.array([0.5]), controller)
    expected = [1.0, -0.89004, 0.8 * 0.09004 + 0.5 * 0.2289]
    # each coefficient a sum of at most three products, in another order than here: a few
    # roundings of the sum of their sizes
    bound = 4 * EPS * np.array([1.0, 0.8 + 0.09004, 0.8 * 0.09004 + 0.5 * 0.2289])
    assert_within(d_cl, expected, bound, 'eq. (8)')
    with pytest.raises(AssertionError, match='times the bound'):
        assert_within(d_cl, np.array(expected) + [0.0, 0.0, 1e-14], bound)
    flipped = lti.make_controller([-0.2289], [1.0, -0.09004], 'positive')
    np.testing.assert_array_equal(
        lti.closed_loop_polynomial(np.array([1.0, -0.8]), np.array([0.5]), flipped), d_cl)


def test_make_controller_normalises_and_names_the_parameter():
    controller = lti.make_controller([0.4], [2.0, -0.2])
    np.testing.assert_array_equal(controller.denominator, [1.0, -0.1])
    np.testing.assert_array_equal(controller.numerator, [0.0, 0.2])
    assert controller.order == 1
    with pytest.raises(ValueError, match=r'controller_numerator must be a list of finite floats'):
        lti.make_controller(['a'], [1.0])
    with pytest.raises(ValueError, match=r"controller_sign must be one of negative, positive, "
                                         r"got 'up'"):
        lti.make_controller([1.0], [1.0], 'up')
