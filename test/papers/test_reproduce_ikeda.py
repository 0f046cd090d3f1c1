"""Reduced reproduction of Ikeda (2008), section 7 (fixed seeds, 100-150 runs)."""

import numpy as np
import pytest

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.cl_bcls_batch import closed_loop_bcls
from bcid_ros.reproduction.common import mean_and_stderr
from bcid_ros.reproduction.ikeda import (MAX_ITERATIONS_73, PREFILTER_73, reproduce, SAMPLES,
                                         SEED_72, study_71, study_72, study_73, TOLERANCE_73)
from bcid_ros.simulation.ikeda import IkedaClosedLoop
from equivalence import assert_paths_agree, two_path_spread

RUNS = 150


@pytest.fixture(scope='module')
def seventy_one():
    return study_71(100)


@pytest.fixture(scope='module')
def seventy_two():
    return study_72(RUNS, steps=(1, 50))


@pytest.fixture(scope='module')
def seventy_three():
    return study_73(RUNS)


@pytest.mark.slow
def test_71_compensation_with_the_true_terms_is_unbiased(seventy_one):
    # Theorem 1: with the true P12, P22, h the estimate is asymptotically unbiased; the
    # O(1/N) remainder at N = 4096 is far below the standard error over 100 runs
    # (std 0.012 / 0.066, so s.e. 0.0012 / 0.0066).
    for values in (seventy_one.bc, seventy_one.optimal):
        mean, se = mean_and_stderr(values)
        assert np.all(np.abs(mean - [0.8, 0.5]) < 3 * se)
    mean, se = mean_and_stderr(seventy_one.sigma2)
    assert abs(mean - 1.0) < 3 * se + 2.0 / SAMPLES


@pytest.mark.slow
def test_71_optimal_estimate_attains_its_regression_bound(seventy_one):
    # The sample variance of 100 runs has a relative s.e. of sqrt(2/99) = 14 %; 3 s.e. = 43 %.
    variance = seventy_one.optimal.var(axis=0, ddof=1)
    bound = np.diag(seventy_one.regression_bound)
    np.testing.assert_allclose(variance, bound, rtol=0.43)


@pytest.mark.slow
def test_72_ls_mean_and_the_one_step_compensation(seventy_two):
    # LS pole std is ~0.011, so its s.e. over 150 runs is ~0.001: 0.01 is about 10 s.e.
    ls_mean, ls_se = mean_and_stderr(seventy_two.ls[:, 0])
    assert abs(ls_mean - 0.544) < 0.01
    one, one_se = mean_and_stderr(seventy_two.plug_in[1][:, 0])
    converged, converged_se = mean_and_stderr(seventy_two.plug_in[50][:, 0])
    assert seventy_two.failures == {1: 0, 50: 0}
    # strictly between, with 3 standard errors of room on both sides
    assert ls_mean + 3 * ls_se < one - 3 * one_se
    assert one + 3 * one_se < converged - 3 * converged_se
    # reference implementation: 0.582 for one step (the paper prints 0.6751; see the report)
    assert abs(one - 0.582) < 3 * one_se + 0.005


@pytest.mark.slow
def test_73_iteration_counts_and_final_estimates(seventy_three):
    # Iteration std is ~2.2 (with BC) and ~3.7 (without): s.e. 0.18 / 0.30 over 150 runs,
    # so the +-1.5 windows around 10 and 16 are about 5 s.e. wide.
    its_bc, _ = mean_and_stderr(seventy_three.iterations_bc.astype(float))
    its_plain, _ = mean_and_stderr(seventy_three.iterations_plain.astype(float))
    assert abs(its_bc - 10.0) <= 1.5
    assert abs(its_plain - 16.0) <= 1.5
    saving, saving_se = mean_and_stderr(
        (seventy_three.iterations_plain - seventy_three.iterations_bc).astype(float))
    assert saving - 3 * saving_se > 0
    assert seventy_three.not_converged_bc == seventy_three.not_converged_plain == 0
    # Final std is ~0.04 (pole) and ~0.064 (b): s.e. 0.0033 / 0.0052; the reference means are
    # 0.012 / 0.011 from the truth, so 0.03 leaves > 3 s.e. beyond that.
    mean = seventy_three.bc.mean(axis=0)
    assert abs(mean[0] - 0.8) < 0.03 and abs(mean[1] - 0.5) < 0.03


def test_online_form_with_one_redesign_is_the_73_batch_estimate():
    # window = redesign_period = N: the one redesign at sample N is Algorithm 1 on all data
    loop = IkedaClosedLoop()
    result = study_73(2, samples=SAMPLES)
    settings = dict(prefilter_initial=PREFILTER_73, tolerance=TOLERANCE_73,
                    max_iterations=MAX_ITERATIONS_73, **loop.estimator_settings())

    def online(y, u):
        est = make_estimator('cl_bcls', window=SAMPLES, redesign_period=SAMPLES, **settings)
        est.run(y, u)
        return {'pole, b': [-est.theta[0], est.theta[1]]}

    def batch(y, u):
        keys = ('order', 'prefilter_initial', 'tolerance', 'max_iterations',
                'controller_numerator', 'controller_denominator', 'controller_sign')
        theta = closed_loop_bcls(y, u, **{key: settings[key] for key in keys}).theta
        return {'pole, b': [-theta[0], theta[1]]}

    for run in range(2):
        y, u = loop.simulate(SAMPLES, SEED_72 + run)
        est = make_estimator('cl_bcls', window=SAMPLES, redesign_period=SAMPLES, **settings)
        est.run(y, u)
        assert est.redesigns == 1
        assert est.last_iterations == result.iterations_bc[run]
        # study_73 is Algorithm 1 on the record: the same bits as here
        np.testing.assert_array_equal(batch(y, u)['pole, b'], result.bc[run])
        # the online form hands Algorithm 1 the columns of its sample buffer (Phi' y on a
        # strided y, another BLAS path) and maps theta through [f - a | b] and back: two
        # arithmetic paths, within the rounding spreads of both (test/equivalence.py)
        assert_paths_agree(online(y, u), batch(y, u), two_path_spread(online, batch, y, u[:, 0]),
                           SAMPLES, f'run {run}')


def test_reproduce_quick_writes_the_report_and_figures(tmp_path):
    calls = []

    def progress(iterable, total, what=''):
        calls.append((what, total))
        yield from iterable

    paths = reproduce(runs=3, quick=True, out_dir=tmp_path, progress=progress)
    assert [p.name for p in paths] == ['reproduction_ikeda.md', 'reproduction_ikeda_71.png',
                                       'reproduction_ikeda_72_73.png']
    assert calls == [('7.1', 3), ('7.2', 3), ('7.3', 3)]
    text = paths[0].read_text()
    for paper_value in ('0.5442', '0.6751', '10.15', '15.88', '32.6', '42.7'):
        assert paper_value in text
    assert 'not tuned' in text
    assert all(p.stat().st_size > 10000 for p in paths[1:])
