"""The plant stepped one sample at a time with a held input (simulator_node mode: plant)."""

import numpy as np
import pytest
from scipy import signal

from bcid_ros.control import AdaptiveController, closed_loop_poles
from bcid_ros.control.design import ModelStructure, Plant
from bcid_ros.identifier.parameters import (check_simulator_parameters, CUSTOM_SETTINGS,
                                            OPERATING_POINT_SETTINGS)
from bcid_ros.simulation.custom import CustomScenario
from bcid_ros.simulation.plant import ChangingStream, HeldInputPlant, plant_pair

NAMES = CUSTOM_SETTINGS + OPERATING_POINT_SETTINGS


def run(plant, commands):
    """Step the plant once per command, holding each command after its sample."""
    ys, us = [], []
    for command in commands:
        y, u = plant.step()
        ys.append(y)
        us.append(u)
        if command is not None:
            plant.hold(command)
    return np.array(ys), np.array(us)


def test_zero_order_hold_timing_operating_point_and_noise_match_a_filter():
    scenario = CustomScenario(plant_denominator=[1.0, -1.2, 0.5],
                              plant_numerator=[0.0, 0.4, 0.3],
                              noise_numerator=[1.0, 0.5], noise_denominator=[1.0, -0.3],
                              noise_variance=0.04, input_delay=2, input_offset=1.5,
                              output_offset=-3.0)
    rng = np.random.default_rng(1)
    commands = rng.standard_normal(300)
    ys, us = run(HeldInputPlant(scenario, np.random.default_rng(7)), commands)
    # u = 0 until the first command; the command given after sample t is applied at t + 1
    assert us[0, 0] == 0.0
    np.testing.assert_array_equal(us[1:, 0], commands[:-1])
    e = np.random.default_rng(7).standard_normal(300) * 0.2
    expected = (-3.0 + signal.lfilter([0.0, 0.0, 0.0, 0.4, 0.3], [1.0, -1.2, 0.5],
                                      us[:, 0] - 1.5)
                + signal.lfilter([1.0, 0.5], [1.0, -0.3], e))
    # the plant's difference equations against lfilter: the same recursions summed in
    # another order, a few eps of |y| < 10 carried by poles of radius 0.71 (measured
    # 3.6e-15); 1e-10 is far above that and far below a sample of wrong timing
    np.testing.assert_allclose(ys, expected, rtol=0, atol=1e-10)


def test_equation_error_feedthrough_and_two_inputs():
    scenario = CustomScenario(plant_denominator=[1.0, -0.5],
                              plant_numerator=[0.2, 1.0, 0.0, -0.7],
                              noise_variance=0.01, equation_error=True, input_delay=[0, 1])
    commands = np.random.default_rng(2).standard_normal((200, 2))
    ys, us = run(HeldInputPlant(scenario, np.random.default_rng(3)), commands)
    e = np.random.default_rng(3).standard_normal(200) * 0.1
    expected = (signal.lfilter([0.2, 1.0], [1.0, -0.5], us[:, 0])
                + signal.lfilter([0.0, 0.0, -0.7], [1.0, -0.5], us[:, 1])
                + signal.lfilter([1.0], [1.0, -0.5], e))
    # as above (measured 9e-16 on |y| < 4)
    np.testing.assert_allclose(ys, expected, rtol=0, atol=1e-10)


def test_the_plant_change_keeps_the_histories_and_changes_the_coefficients():
    before = CustomScenario(plant_denominator=[1.0, -0.8], plant_numerator=[0.0, 0.5],
                            noise_variance=0.0)
    after = CustomScenario(plant_denominator=[1.0, -0.6], plant_numerator=[0.0, 0.9],
                           noise_variance=0.0)
    plant = HeldInputPlant(before, np.random.default_rng(0), after=after, change_after=50)
    commands = np.random.default_rng(4).standard_normal(100)
    ys, us = run(plant, commands)
    x = np.zeros(100)
    for t in range(1, 100):
        a, b = (0.8, 0.5) if t < 50 else (0.6, 0.9)
        x[t] = a * x[t - 1] + b * us[t - 1, 0]
    # a first-order recursion in two orders of summation: a few eps of |y|, decaying
    # with 0.8^k; 1e-12 is far above that
    np.testing.assert_allclose(ys, x, rtol=0, atol=1e-12)
    assert plant.changed
    np.testing.assert_array_equal(plant.truth().parameters, [-0.6, 0.9])


def test_bad_commands_are_refused_and_the_held_input_kept():
    plant = HeldInputPlant(CustomScenario(), np.random.default_rng(0))
    plant.hold([2.0])
    with pytest.raises(ValueError, match='finite'):
        plant.hold([np.nan])
    with pytest.raises(ValueError, match='r = 1 values, got 2'):
        plant.hold([1.0, 2.0])
    assert plant.held.tolist() == [2.0] and plant.commands == 1
    assert plant.step()[1].tolist() == [2.0]


def test_plant_pair_from_the_simulator_parameters():
    settings = check_simulator_parameters(dict(
        scenario='custom', mode='plant', change_after_samples=10,
        plant_denominator_after=[1.0, -0.5], input_offset=[1.0], output_offset=2.0))
    before, after = plant_pair(settings, NAMES)
    assert after.a.tolist() == [1.0, -0.5] and after.b.tolist() == before.b.tolist()
    assert after.output_offset == 2.0 and before.input_offset.tolist() == [1.0]
    settings['plant_denominator_after'] = [1.0, -1.5]
    with pytest.raises(ValueError, match='after the change.*stable'):
        plant_pair(settings, NAMES)
    settings['change_after_samples'] = 0
    assert plant_pair(settings, NAMES)[1] is None


def test_the_open_loop_changing_stream_filters_its_input_and_changes_once():
    # mode: open_loop with change_after_samples: the scenario's own input, each sample held
    # and stepped; before the change y is the plant's filter of u (noise-free here), after it
    # the new coefficients act on the same histories; the samples do not depend on blocks
    before = CustomScenario(plant_denominator=[1.0, -1.5, 0.7], plant_numerator=[0.0, 1.0, 0.5],
                            noise_variance=0.0, input_signal='binary', input_hold=3)
    after = CustomScenario(plant_denominator=[1.0, -1.6, 0.8], plant_numerator=[0.0, 0.6, 0.3],
                           noise_variance=0.0)
    stream = ChangingStream(before, np.random.default_rng(5), after=after, change_after=200)
    y, u = stream.take(400)
    pieces = ChangingStream(before, np.random.default_rng(5), after=after, change_after=200)
    blocks = [pieces.take(n) for n in (1, 150, 49, 200)]
    np.testing.assert_array_equal(np.concatenate([b[0] for b in blocks]), y)
    np.testing.assert_array_equal(np.concatenate([b[1] for b in blocks]), u)
    assert set(np.unique(u)) == {-1.0, 1.0}
    np.testing.assert_allclose(y[:200], signal.lfilter(before.b[0], before.a, u[:200, 0]),
                               rtol=1e-12, atol=1e-12)
    # after the change: y(t) = -a' y(t-1..t-2) + b' u(t-1..t-2) of the new plant
    t = np.arange(202, 400)
    expected = (1.6 * y[t - 1] - 0.8 * y[t - 2] + 0.6 * u[t - 1, 0] + 0.3 * u[t - 2, 0])
    np.testing.assert_allclose(y[t], expected, rtol=1e-12, atol=1e-12)
    assert stream.plant.changed and stream.plant.truth().parameters.tolist() == [
        -1.6, 0.8, 0.6, 0.3]


def test_a_pole_placement_loop_on_the_held_input_plant_has_the_designed_poles():
    # the controller's timing (the input from y_t applied at t + 1) is the plant's: the
    # loop's output follows the designed transfer function from the reference exactly
    scenario = CustomScenario(plant_denominator=[1.0, -0.8], plant_numerator=[0.0, 0.5],
                              noise_variance=0.0)
    loop = AdaptiveController(dict(order=1, closed_loop_poles=[0.5, 0.5],
                                   max_relative_std=0.0, reference_signal='square',
                                   reference_period=20, input_limit=100.0))
    loop.offer_parameters(['a1', 'b1_1'], [-0.8, 0.5], 0.0)
    loop.offer_valid(True)
    assert loop.redesign(0.0).kind == 'switched'
    plant = HeldInputPlant(scenario, np.random.default_rng(0))
    ys, rs = [], []
    for _ in range(200):
        y, _ = plant.step()
        plant.hold([loop.step(y)])
        ys.append(y)
        rs.append(loop.last_reference)
    truth = Plant.from_estimate([-0.8, 0.5], ModelStructure(1))
    # a double pole moves by the square root of its polynomial's rounding (~1e-8)
    np.testing.assert_allclose(np.sort(closed_loop_poles(truth, loop.controller).real),
                               [0.5, 0.5], atol=1e-6)
    # y = B S / (A R + B S) r: (q - 0.5)^2 y = 0.5 * 0.18 r, to the rounding of the loop's
    # signals (below 3, decaying with 0.5^k) and of the design; 1e-12 is far above it
    ys, rs = np.array(ys), np.array(rs)
    np.testing.assert_allclose(ys[2:] - ys[1:-1] + 0.25 * ys[:-2], 0.09 * rs[:-2], atol=1e-12)
