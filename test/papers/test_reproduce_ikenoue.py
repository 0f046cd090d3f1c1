"""Reduced reproduction of Ikenoue et al. (2008), Tables 1 and 2 (M = 50 runs, N = 10000)."""

import numpy as np
import pytest

from bcid_ros.reproduction.common import mean_and_stderr
from bcid_ros.reproduction.ikenoue import PAPER, reproduce, run_section

RUNS = 50


@pytest.fixture(scope='module')
def colored():
    return run_section('5.1', RUNS, printed=False)


@pytest.fixture(scope='module')
def white():
    return run_section('5.2', RUNS)


def test_colored_bciv_l5_is_unbiased(colored):
    # Issue 6: a within 3 s.e. and within 0.02 of the truth, b within 0.04. Over 200 runs
    # we measured mean [-1.4999, 0.6999, 0.9948, 0.4979] and std [0.012, 0.008, 0.022,
    # 0.055]; with M = 50 the s.e. of a is ~0.002 and that of b2 ~0.008, so 0.04 on b is
    # about 5 s.e. of b2 (the neutral direction makes b the loose part).
    mean, se = mean_and_stderr(colored.final('BCIV (l=5)'))
    truth = colored.truth
    assert (np.abs(mean[:2] - truth[:2]) < 3 * se[:2]).all()
    assert (np.abs(mean[:2] - truth[:2]) < 0.02).all()
    assert (np.abs(mean[2:] - truth[2:]) < 0.04).all()


def test_colored_ls_reproduces_the_papers_bias(colored):
    # Table 1, LS: a1 = -0.7046, b2 = 1.9223 against the truth -1.5 and 0.5.
    mean = colored.final('LS').mean(axis=0)
    paper = np.array(PAPER['5.1']['LS'][0])
    assert np.abs(mean - paper).max() < 0.05
    assert abs(mean[0] + 0.70) < 0.05 and abs(mean[3] - 1.92) < 0.05


def test_colored_iv_type_is_biased_in_b_and_bciv_removes_it(colored):
    # theta_IV (l = 5) has a biased b: 1.010, 0.469 for 1.0, 0.5 (docs/reproduction_ikenoue.md).
    iv_mean, iv_se = mean_and_stderr(colored.final('IV-type (l=5)'))
    bc_mean, bc_se = mean_and_stderr(colored.final('BCIV (l=5)'))
    assert iv_mean[3] + 3 * iv_se[3] < colored.truth[3]
    assert abs(bc_mean[3] - colored.truth[3]) < abs(iv_mean[3] - colored.truth[3])


def test_white_bciv_reproduces_table_2(white):
    # Issue 6 asks for the 5.2 BCIV means within 3 s.e. of the truth. That does not hold
    # at N = 10000: over 200 runs we measured mean [-1.5544, 0.5805, 0.1629, 0.1375], i.e.
    # (mean - true)/std = [+0.35, -0.37, -0.19, -0.19], z = [+5.0, -5.3, -2.6, -2.7]. The
    # paper's own Table 2 has the same offsets (+0.41, -0.41, -0.17, -0.10 std), and they
    # shrink with N (N = 1e5: a = [-1.5685, 0.5985]). So we test what holds: our means
    # agree with the paper's BCIV means within 3 combined standard errors (paper M = 100).
    mean, se = mean_and_stderr(white.final('BCIV (l=4)'))
    paper_mean, paper_std = (np.array(v) for v in PAPER['5.2']['BCIV (l=4)'])
    combined = np.sqrt(se ** 2 + (paper_std / np.sqrt(100)) ** 2)
    assert (np.abs(mean - paper_mean) < 3 * combined).all()
    # ... and the offsets are a small fraction of the LS bias.
    ls_mean = white.final('LS').mean(axis=0)
    assert (np.abs(mean - white.truth) < 0.1 * np.abs(ls_mean - white.truth)).all()


def test_white_ls_reproduces_the_papers_bias(white):
    mean = white.final('LS').mean(axis=0)
    assert np.abs(mean - np.array(PAPER['5.2']['LS'][0])).max() < 0.05


@pytest.mark.slow
def test_reproduce_quick_writes_the_report_and_figures(tmp_path):
    calls = []

    def progress(iterable, total, what=''):
        yield from iterable
        calls.append((what, total))

    paths = reproduce(runs=3, quick=True, out_dir=tmp_path, progress=progress)
    assert [p.name for p in paths] == ['reproduction_ikenoue.md', 'reproduction_ikenoue_fig1.png',
                                       'reproduction_ikenoue_fig2.png']
    text = paths[0].read_text()
    assert '| LS | paper | -0.7046 ± 0.0162 |' in text
    assert '| BCIV (l=4) | paper | -1.5518 ± 0.0572 |' in text
    assert 'BCIV printed (l=5) | ours' in text
    assert all(p.stat().st_size > 10000 for p in paths[1:])
    assert calls == [('section 5.1', 3), ('section 5.2', 3), ('limits', 3)]
