"""Tests of the seeded family of realistic plants, bcid_ros.analysis.realistic."""

import numpy as np
import pytest

from bcid_ros.analysis import realistic
from bcid_ros.analysis.pem import simulate_oe, Structure
from bcid_ros.analysis.realistic import realistic_case, realistic_family
from bcid_ros.estimators.base import parameter_names
from bcid_ros.estimators.polynomials import is_stable


@pytest.fixture(scope='module')
def family():
    return realistic_family(40, seed=0)


def test_a_case_is_a_function_of_its_seed():
    first, second = realistic_case((3, 7)), realistic_case([3, 7])
    assert first.seed == second.seed == (3, 7)
    assert np.array_equal(first.y, second.y) and np.array_equal(first.u, second.u)
    assert np.array_equal(first.theta, second.theta)
    assert first.description == second.description
    assert not np.array_equal(realistic_case((3, 8)).y[:100], first.y[:100])


def test_families_of_other_seeds_share_no_case(family):
    other = realistic_family(40, seed=1)
    assert {case.seed for case in family}.isdisjoint(case.seed for case in other)
    assert [case.seed for case in family] == [(0, k) for k in range(40)]
    assert not any(np.array_equal(a.theta, b.theta) for a in family for b in other
                   if a.theta.size == b.theta.size)


def test_the_family_spans_the_advertised_variety(family):
    assert {case.order for case in family} == {1, 2, 3}
    assert {case.num_inputs for case in family} == {1, 2}
    assert {d for case in family for d in case.input_delay} == set(range(4))
    assert {case.noise for case in family} == set(realistic.NOISES)
    assert {kind.split('/')[0] for case in family for kind in case.excitation} == set(
        realistic.EXCITATIONS)
    assert {case.detrend for case in family} == {'mean', 'none'}
    radii = np.concatenate([np.abs(case.poles) for case in family])
    assert radii.max() > 0.98 and radii.min() < 0.5
    assert any(np.iscomplexobj(case.poles) and np.abs(case.poles.imag).max() > 0.1
               for case in family)
    snr = np.array([case.snr_db for case in family])
    assert snr.min() >= 5.0 and snr.max() <= 40.0
    samples = np.array([case.samples for case in family])
    assert samples.min() >= 2000 and samples.max() <= 10000


def test_truth_and_record_agree(family):
    for case in family:
        structure = Structure(case.order, case.num_inputs, case.input_delay)
        assert case.parameter_names == parameter_names(case.order, case.num_inputs, False,
                                                       case.input_delay)
        assert case.u.shape == (case.samples, case.num_inputs)
        assert is_stable(case.theta[:case.order], 0.0)
        assert case.predicted_error <= realistic.MAX_PREDICTED_ERROR
        simulated = simulate_oe(case.theta, case.u - case.operating_point[1:], structure)
        # the same filter from the same rest, summed in another order: a few ulps of the
        # largest partial sum, times the impulse-response mass of a pole up to 0.995 (< 200)
        scale = np.abs(case.noise_free).max() + 1.0
        assert np.abs(simulated - case.noise_free).max() <= 1e3 * np.finfo(float).eps * scale
        noise = case.y - case.operating_point[0] - case.noise_free
        snr = 10.0 * np.log10(case.noise_free.var() / noise.var())
        # the noise is scaled to the SNR exactly; the adds and subtractions cost ulps
        assert snr == pytest.approx(case.snr_db, abs=1e-6)


def test_the_description_says_what_the_case_is(family):
    case = family[0]
    assert case.description.startswith('case 0,0: ')
    assert f'n={case.order}' in case.description and f'N={case.samples}' in case.description
    assert case.noise in case.description


@pytest.mark.parametrize('call, match', [
    (lambda: realistic_case(-1), 'seed'),
    (lambda: realistic_case('a'), 'seed'),
    (lambda: realistic_case(()), 'seed'),
    (lambda: realistic_case(1.5), 'seed'),
    (lambda: realistic_family(-2), 'count'),
    (lambda: realistic_family(2, seed=-1), 'seed'),
])
def test_bad_arguments_raise_value_errors_naming_them(call, match):
    with pytest.raises(ValueError, match=match):
        call()
