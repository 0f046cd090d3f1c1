"""``bcid analyze``: metrics, model properties, the recommendation and the command."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from bcid_ros.analysis import metrics
from bcid_ros.analysis.model import DiscreteModel
from bcid_ros.analysis.search import analyze, compared_estimators
from bcid_ros.analysis.study import noise_for_snr, random_plant, run_study, write_bag
from bcid_ros.bag.qos import LATCHED
from bcid_ros.bag.writer import BagWriter, FLOAT64_MULTI_ARRAY, float64_multi_array
from bcid_ros.cli import main
from bcid_ros.errors import BcidError
from bcid_ros.estimators.registry import names_where
from bcid_ros.simulation.custom import CustomScenario

PARAMS = 'bcid_identifier:\n  ros__parameters:\n    estimator: {}\n    order: 1\n' \
    '    num_inputs: {}\n'


def _params(tmp_path: Path, estimator: str = 'bcrls', inputs: int = 1) -> Path:
    path = tmp_path / f'{estimator}_{inputs}.yaml'
    path.write_text(PARAMS.format(estimator, inputs))
    return path


def _run(capsys, *argv):
    code = main(['analyze', *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def test_fit_is_100_for_a_perfect_model_and_0_for_the_mean():
    y = np.sin(np.arange(50.0))
    assert metrics.nrmse_fit(y, y) == pytest.approx(100.0)
    assert metrics.nrmse_fit(y, np.full(50, y.mean())) == pytest.approx(0.0)
    assert metrics.nrmse_fit(y, np.full(50, np.inf)) == float('-inf')


def test_ljung_box_passes_white_noise_and_rejects_an_ar1():
    rng = np.random.default_rng(3)
    white = rng.standard_normal(1000)
    coloured = signal.lfilter([1.0], [1.0, -0.5], white)
    assert metrics.ljung_box(white, 20)[1] > 0.01
    # r_1 = 0.5 gives Q of about 1000 * 0.25 = 250 on 20 degrees of freedom
    assert metrics.ljung_box(coloured, 20)[1] < 1e-20


def test_information_criteria_penalise_parameters():
    residual = np.random.default_rng(0).standard_normal(400)
    aic3, mdl3 = metrics.information_criteria(residual, 3)
    aic5, mdl5 = metrics.information_criteria(residual, 5)
    assert aic5 - aic3 == pytest.approx(4.0)
    assert mdl5 - mdl3 == pytest.approx(2 * np.log(400))


def test_poles_zeros_gain_and_step_of_a_delayed_model():
    model = DiscreteModel(np.array([1.0, -1.1, 0.3]), np.array([[0.0, 1.0, 0.5]]), delay=2)
    np.testing.assert_allclose(sorted(model.poles().real), [0.5, 0.6])
    np.testing.assert_allclose(model.zeros(), [-0.5])
    assert model.dc_gain()[0] == pytest.approx(1.5 / 0.2)
    step = model.step(400)[:, 0]
    np.testing.assert_array_equal(step[:3], 0.0)  # two samples of dead time, then b_1
    assert step[3] == pytest.approx(1.0)
    assert step[-1] == pytest.approx(1.5 / 0.2)


def test_continuous_equivalents_recover_a_sampled_second_order_plant():
    period, wn, zeta, tau = 0.01, 12.0, 0.3, 0.5
    # H(s) = wn^2 / (s^2 + 2 zeta wn s + wn^2) * 1 / (tau s + 1), sampled with a ZOH
    den = np.polymul([1.0, 2 * zeta * wn, wn ** 2], [tau, 1.0])
    num_d, den_d, _ = signal.cont2discrete(([wn ** 2], den), period, method='zoh')
    num_d = np.ravel(num_d)
    model = DiscreteModel(den_d / den_d[0], (num_d / den_d[0]).reshape(1, -1))
    found = model.continuous(period)
    pair = [m for m in found['modes'] if m['kind'] == 'complex'][0]
    real = [m for m in found['modes'] if m['kind'] == 'real'][0]
    # a round trip through expm, np.roots and log: the clustered poles (0.96-0.98) come out
    # ~1e-14 off and log z near -0.02 amplifies that 50-fold: measured 2e-12 relative
    # (the time constant); 1e-8 is far above it
    assert pair['natural_frequency_rad_s'] == pytest.approx(wn, rel=1e-8)
    assert pair['damping'] == pytest.approx(zeta, rel=1e-8)
    assert real['time_constant_s'] == pytest.approx(tau, rel=1e-8)
    assert found['dc_gain'] == pytest.approx(1.0, rel=1e-8)
    assert found['no_equivalent'] == []


def test_a_real_negative_pole_has_no_continuous_equivalent():
    model = DiscreteModel(np.poly([0.9, -0.4]), np.array([[0.0, 1.0, 0.0]]))
    found = model.continuous(0.1)
    # a simple root of np.poly([0.9, -0.4]) found by np.roots: a few ulps; 1e-12 is far above
    np.testing.assert_allclose(found['no_equivalent'], [[-0.4, 0.0]], atol=1e-12)
    assert len(found['modes']) == 1
    assert found['modes'][0]['time_constant_s'] == pytest.approx(-0.1 / np.log(0.9))


def test_an_arx_plant_is_found_and_estimator_restricts_the_online_comparison():
    # equation-error noise: the OE fit is consistent, its simulation error coloured (e/A)
    plant = {'plant_denominator': [1.0, -1.3, 0.6], 'plant_numerator': [0.0, 1.0, 0.5],
             'input_delay': 1}
    scenario = CustomScenario(**plant, equation_error=True,
                              noise_variance=noise_for_snr(plant, 20.0, True))
    y, u = scenario.simulate(2000, 4)
    found = analyze(y, u, {'estimator': 'bcrls', 'num_inputs': 1}, orders=(1, 4),
                    delays=(0, 3), estimator='rls')
    assert (found.recommended.order, found.recommended.delays) == (2, (1,))
    assert found.adequate and not found.residuals_white
    assert [r.name for r in found.online] == ['rls']
    # rls is the maximum-likelihood estimate of an ARX plant: close to the batch OE model
    assert found.recommended_estimator == 'rls' and found.estimator_close


def test_the_online_comparison_defaults_to_the_open_loop_estimators_and_the_files():
    open_loop = names_where(open_loop=True)
    assert compared_estimators(open_loop[0], None) == open_loop
    assert compared_estimators('cl_bcls', None) == open_loop + ('cl_bcls',)
    assert compared_estimators('bcrls', 'bciv') == ('bciv',)


def test_reduced_study_recovers_order_and_delay_through_the_command():
    # one random plant per true order 1..4 (seed 0), 2000 samples at 20 dB: the full
    # study (10 seeds per order, docs/analyze.md) runs the same code on more bags
    runs = run_study(range(1, 5), range(1), samples=2000, search_orders='1-5',
                     search_delays='0-3')
    missed = [(r.order, r.delay, r.recommended_order, r.recommended_delay)
              for r in runs if not r.recovered]
    assert not missed


def test_json_has_the_documented_keys_and_the_plot_is_written(tmp_path, capsys):
    plant = random_plant(2, np.random.default_rng([2, 1]))
    scenario = CustomScenario(**plant, noise_variance=noise_for_snr(plant, 20.0),
                              output_offset=5.0, input_offset=-2.0)
    bag = write_bag(scenario, 1500, 1, tmp_path / 'bag')
    png = tmp_path / 'out.png'
    code, out, err = _run(capsys, bag, '--params', _params(tmp_path), '--orders', '1-3',
                          '--delays', '0-3', '--sample-period', '0.01', '--plot', png,
                          '--json')
    assert code == 0, err
    summary = json.loads(out)
    assert summary['recommended_order'] == 2
    assert summary['recommended_delay'] == plant['input_delay']
    assert isinstance(summary['recommended_delay'], int)  # an integer for one input
    assert set(summary['orders']) == {'1', '2', '3'}
    assert {'fit', 'aic', 'mdl', 'whiteness_p', 'cross_correlation_p',
            'stable'} <= set(summary['orders']['2'])
    model = summary['model']
    assert {'parameters', 'parameter_std', 'poles', 'zeros', 'dc_gain', 'continuous',
            'fit'} <= set(model)
    np.testing.assert_allclose(sorted(np.hypot(*np.array(model['poles']).T)),
                               sorted(np.abs(np.roots(plant['plant_denominator']))),
                               atol=0.05)
    assert summary['operating_point']['y'] == pytest.approx(5.0, abs=0.5)
    assert summary['operating_point']['u1'] == pytest.approx(-2.0, abs=0.1)
    # every open-loop estimator ran on the chosen structure and has a validation fit
    assert set(summary['online']) == set(names_where(open_loop=True))
    for figures in summary['online'].values():
        assert {'fit', 'valid', 'stable', 'parameters', 'validity_reasons'} <= set(figures)
    assert summary['recommended_estimator'] in summary['online']
    assert isinstance(summary['recommended_estimator_close'], bool)
    assert summary['identifier_parameters']['input_delay'] == [plant['input_delay']]
    assert summary['identifier_parameters']['detrend'] == 'mean'
    assert png.stat().st_size > 20000
    assert 'order 3, delay 3 (12/12)' in err  # progress on stderr
    assert 'online bcrls' in err


def test_a_two_input_csv_gives_a_delay_per_input_and_progress_stays_off_stdout(tmp_path,
                                                                               capsys):
    rng = np.random.default_rng(8)
    count = 1500
    u = rng.standard_normal((count, 2))
    a = np.poly([0.7, 0.4])
    x = signal.lfilter([0.0, 0.0, 0.0, 1.0, 0.6], a, u[:, 0]) + \
        signal.lfilter([0.0, -0.8, 0.3], a, u[:, 1])
    y = 10.0 + x + 0.1 * x.std() * rng.standard_normal(count)
    path = tmp_path / 'plant.csv'
    np.savetxt(path, np.column_stack([y, u + 3.0]), delimiter=',', header='y,u1,u2',
               comments='')
    code, out, err = _run(capsys, path, '--params', _params(tmp_path, inputs=2),
                          '--orders', '1-3', '--delays', '0-2', '--json')
    assert code == 0, err
    assert len(out.strip().splitlines()) == 1  # one JSON object, nothing else
    summary = json.loads(out)
    assert summary['recommended_order'] == 2
    assert summary['recommended_delay'] == [2, 0]  # a list for several inputs
    assert summary['orders']['2']['delay'] == [2, 0]
    assert len(summary['candidates']) == 3 * 9
    assert err.count('bcid analyze: order ') == 27


def test_a_bag_without_samples_is_one_clear_line(tmp_path, capsys):
    bag = tmp_path / 'truth_only'
    with BagWriter(bag) as writer:
        writer.add_topic('/bcid_simulator/true_parameters', FLOAT64_MULTI_ARRAY, [LATCHED])
        writer.write_message('/bcid_simulator/true_parameters', 0,
                             float64_multi_array([('a1', 1, 1)], [0.5]))
    code, _, err = _run(capsys, bag, '--params', _params(tmp_path))
    assert code == 1
    assert 'no topic /samples' in err
    assert err.count('\n') == 1


def test_too_few_samples_for_the_order_range(tmp_path, capsys):
    bag = write_bag(CustomScenario(), 200, 0, tmp_path / 'short')
    code, _, err = _run(capsys, bag, '--params', _params(tmp_path), '--orders', '1-8')
    assert code == 1
    assert 'too few samples' in err and 'orders up to 8' in err


def test_a_constant_input_is_refused(tmp_path, capsys):
    scenario = CustomScenario(input_variance=0.0, input_offset=3.0)
    bag = write_bag(scenario, 500, 0, tmp_path / 'flat')
    code, _, err = _run(capsys, bag, '--params', _params(tmp_path))
    assert code == 1
    assert 'input u1 is constant' in err


def test_bad_ranges_are_refused():
    y = np.random.default_rng(0).standard_normal(500)
    u = np.random.default_rng(1).standard_normal((500, 1))
    with pytest.raises(BcidError, match='--validation'):
        analyze(y, u, {'num_inputs': 1}, validation=1.5)
    with pytest.raises(BcidError, match='num_inputs'):
        analyze(y, u, {'num_inputs': 2})


def test_an_integrator_gives_json_safe_figures():
    model = DiscreteModel(np.poly([1.0, 0.5]), np.array([[0.0, 1.0, 0.0]]))
    found = model.continuous(0.1)
    assert found['dc_gain'] is None
    times = sorted(m['time_constant_s'] is None for m in found['modes'])
    assert times == [False, True]
    json.dumps(found, allow_nan=False)
