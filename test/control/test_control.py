"""
The adaptive controller without ROS: pole placement, runtime, trust gate, references.

The closed loops are simulated here with a small ARX plant at an operating
point, y_t = y0 + B/A (u - u0), with the timing of the simulator's plant mode:
the input computed from y_t is applied at t + 1 (``computation_delay``).
"""

import math

import numpy as np
import pytest
from scipy import signal

from bcid_ros.control import (AdaptiveController, closed_loop_poles, Controller,
                              ControllerRuntime, DesignRefused, ModelStructure, place_poles,
                              Plant)
from bcid_ros.control.design import (check_estimate, closed_loop_polynomial, parse_names,
                                     required_pole_count)
from bcid_ros.control.loop import EVENTS, REFUSALS
from bcid_ros.control.parameters import check_controller_parameters
from bcid_ros.control.reference import ReferenceGenerator
from equivalence import assert_paths_agree, assert_within, EPS, two_path_spread

#: The paper's plant 0.5/(q - 0.8) and its names.
IKEDA = ModelStructure(1)
IKEDA_THETA = [-0.8, 0.5]


class ArxPlant:
    """y_t = y0 + x_t with A(q^-1) x = B(q^-1) (u - u0), strictly proper (lags >= 1)."""

    def __init__(self, theta, structure, y0=0.0, u0=0.0):
        assert structure.lags[0] >= 1
        self.a = np.asarray(theta[:structure.order], float)
        self.b = dict(zip(structure.lags, theta[structure.order:]))
        self.y0, self.u0 = y0, u0
        self.x = [0.0] * structure.order
        self.past = [0.0] * max(self.b)  # u_(t-1), u_(t-2), ... minus u0

    def output(self):
        """Return y_t (from the inputs applied up to t - 1)."""
        x = -np.dot(self.a, self.x) + sum(b * self.past[lag - 1] for lag, b in self.b.items())
        self.x = [x] + self.x[:-1]
        return self.y0 + x

    def apply(self, u):
        """Hold u over the sample after the last output."""
        self.past = [u - self.u0] + self.past[:-1]


def run_loop(loop, plant, samples, delayed=True):
    """Run plant and controller; return y, the applied u and r'."""
    ys, us, rs = [], [], []
    pending = 0.0
    for _ in range(samples):
        y = plant.output()
        computed = loop.step(y)
        # delayed: the input computed from y_t is applied at t + 1 (zero-order hold)
        applied, pending = (pending, computed) if delayed else (computed, computed)
        plant.apply(applied)
        ys.append(y)
        us.append(applied)
        rs.append(loop.last_reference)
    return np.array(ys), np.array(us), np.array(rs)


class RuntimeLoop:
    """A ControllerRuntime with a reference, stepped like AdaptiveController."""

    def __init__(self, runtime, reference):
        self.runtime, self.reference = runtime, reference
        self.last_reference = 0.0

    def step(self, y):
        self.last_reference = self.reference.next()
        return self.runtime.step(self.last_reference - y)


def settings(**values):
    """Return controller parameters for the Ikeda plant with the given changes."""
    base = dict(order=1, closed_loop_poles=[0.5, 0.5], input_limit=100.0,
                fallback_numerator=[0.2289], fallback_denominator=[1.0, -0.09004],
                max_relative_std=0.1)
    base.update(values)
    return base


def random_plant(rng, order, unstable, delay=0, feedthrough=False):
    """Return a random plant with poles and zeros 0.15 apart from each other and from 1."""
    structure = ModelStructure(order, feedthrough, delay)
    while True:
        poles = rng.uniform(-0.9, 0.9, order)
        if unstable:
            poles[0] = rng.choice([-1.0, 1.0]) * rng.uniform(1.1, 1.5)
        zeros = rng.uniform(-1.5, 1.5, len(structure.lags) - 1)
        points = np.concatenate([poles, zeros, [1.0]])
        gaps = np.abs(points[:, None] - points[None, :]) + 10 * np.eye(points.size)
        if gaps.min() > 0.15:
            break
    gain = rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 2.0)
    theta = np.concatenate([np.poly(poles)[1:], gain * np.atleast_1d(np.poly(zeros))])
    return structure, theta


def assert_design_places(structure, theta, poles, **options):
    """
    Assert that the design for ``theta`` places ``poles``: A R + B S = A_cl(q), and its roots.

    The design's solve and products against np.poly of the poles: two
    arithmetic paths, within the rounding spreads of both (test/equivalence.py;
    the roots' conditioning is in their spread). Return the controller.
    """
    def design(theta, poles):
        plant = Plant.from_estimate(theta, structure)
        controller = place_poles(plant, poles, **options)
        achieved = closed_loop_poles(plant, controller)
        order = np.argsort(achieved.real)
        return {'A R + B S': closed_loop_polynomial(plant, controller),
                'poles': achieved.real[order], 'imaginary parts': achieved.imag[order]}

    def requested(theta, poles):
        return {'A R + B S': np.poly(poles), 'poles': np.sort(poles),
                'imaginary parts': np.zeros(len(poles))}

    theta, poles = np.asarray(theta, float), np.asarray(poles, float)
    spread = two_path_spread(design, requested, theta, poles)
    assert_paths_agree(design(theta, poles), requested(theta, poles), spread, 1, 'design')
    # the plant's B moved by 1e-10 of its size: the bound sees it
    moved = theta.copy()
    moved[structure.order:] *= 1.0 + 1e-10
    plant = Plant.from_estimate(theta, structure)
    controller = place_poles(Plant.from_estimate(moved, structure), poles, **options)
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree({'A R + B S': closed_loop_polynomial(plant, controller)},
                           {'A R + B S': np.poly(poles)}, spread, 1)
    return place_poles(plant, poles, **options)


def spread_poles(rng, count):
    """Return ``count`` real poles in (-0.9, 0.9), evenly spread with a small jitter."""
    grid = np.linspace(-0.85, 0.85, count) if count > 1 else np.array([0.3])
    return grid + rng.uniform(-0.02, 0.02, count)


@pytest.mark.parametrize('order', [1, 2, 3])
@pytest.mark.parametrize('integral', [False, True])
@pytest.mark.parametrize('strict', [False, True])
@pytest.mark.parametrize('unstable', [False, True])
def test_designed_poles_are_the_requested_ones(order, integral, strict, unstable):
    rng = np.random.default_rng(1000 * order + 100 * integral + 10 * strict + unstable)
    for _ in range(5):
        structure, theta = random_plant(rng, order, unstable)
        count = required_pole_count(structure, integral=integral, strictly_proper=strict)
        poles = spread_poles(rng, count + int(rng.integers(2)))  # sometimes an extra pole
        controller = assert_design_places(structure, theta, poles, integral=integral,
                                          strictly_proper=strict)
        # causal, strictly proper when asked, monic R with the integrator when asked
        assert controller.numerator.size <= controller.denominator.size - int(strict)
        assert controller.denominator[0] == 1.0
        if integral:
            # R = R' (q - 1): its coefficients and their sum round by 2 size eps sum |r_k|
            denominator = controller.denominator
            assert abs(np.polyval(denominator, 1.0)) <= (
                2 * denominator.size * EPS * np.abs(denominator).sum())


@pytest.mark.parametrize('delay, feedthrough', [(1, False), (2, True), (0, True)])
def test_delayed_and_feedthrough_plants_get_a_causal_exact_design(delay, feedthrough):
    rng = np.random.default_rng(7 + delay)
    structure, theta = random_plant(rng, 2, False, delay, feedthrough)
    plant = Plant.from_estimate(theta, structure)
    count = required_pole_count(structure, integral=True, strictly_proper=False)
    poles = spread_poles(rng, count)
    controller = assert_design_places(structure, theta, poles, integral=True,
                                      strictly_proper=False)
    if structure.lags[0] == 0:  # a lag-0 feedthrough needs a strictly proper controller
        assert controller.strictly_proper
    with pytest.raises(ValueError, match='at least'):
        place_poles(plant, poles[:-1], integral=True, strictly_proper=False)


@pytest.mark.parametrize('delayed', [False, True])
def test_runtime_in_the_loop_is_the_designed_transfer_function(delayed):
    # y = B S / (A R + B S) r' when nothing saturates: the runtime, the timing convention
    # and the design agree, to rounding over 300 samples of an unstable plant
    structure, theta = random_plant(np.random.default_rng(3), 2, True)
    plant = Plant.from_estimate(theta, structure)
    poles = spread_poles(np.random.default_rng(4), required_pole_count(
        structure, integral=True, strictly_proper=delayed))
    controller = place_poles(plant, poles, integral=True, strictly_proper=delayed)

    def runtime(theta):
        loop = RuntimeLoop(ControllerRuntime(controller, input_limit=1e9, delayed=delayed),
                           ReferenceGenerator('square', amplitude=1.0, period=40))
        ys, _, rs = run_loop(loop, ArxPlant(theta, structure), 300, delayed)
        return {'y': ys, 'r': rs}

    def transfer_function(theta):
        plant = Plant.from_estimate(theta, structure)
        denominator = closed_loop_polynomial(plant, controller)
        numerator = np.polymul(plant.numerator, controller.numerator)
        # in powers of q^-1 both need the same length: pad B S with leading zeros
        numerator = np.concatenate([np.zeros(denominator.size - numerator.size), numerator])
        return {'y': signal.lfilter(numerator, denominator, rs), 'r': rs}

    rs = runtime(theta)['r']
    # the loop stepped sample by sample against lfilter of its transfer function: two
    # arithmetic paths, within the rounding spreads of both (test/equivalence.py)
    spread = two_path_spread(runtime, transfer_function, theta)
    assert_paths_agree(runtime(theta), transfer_function(theta), spread, 300, 'loop')
    with pytest.raises(AssertionError, match='the paths differ by'):
        assert_paths_agree(runtime(theta * (1.0 + 1e-9)), transfer_function(theta), spread, 300)


def trusted_loop(theta=IKEDA_THETA, **values):
    """Return an AdaptiveController that has designed on a trusted ``theta``."""
    loop = AdaptiveController(settings(**values))
    names = loop.structure.names
    loop.offer_parameters(names, theta, 0.0)
    loop.offer_std(names, 0.01 * np.abs(theta))
    loop.offer_valid(True)
    assert loop.redesign(0.0).kind == 'switched'
    return loop


@pytest.mark.parametrize('integral', [True, False])
def test_integral_action_tracks_a_step_at_an_operating_point(integral):
    # plant 0.5/(q - 0.8) around (u0, y0) = (1, 2); setpoint 3; no noise
    poles = [0.5, 0.5, 0.4] if integral else [0.5, 0.5]
    loop = trusted_loop(closed_loop_poles=poles, integral_action=integral,
                        reference_offset=3.0)
    ys, us, _ = run_loop(loop, ArxPlant(IKEDA_THETA, IKEDA, y0=2.0, u0=1.0), 200)
    error = abs(ys[-1] - 3.0)
    if integral:
        # poles 0.5: the error decays as ~t^2 0.5^t, below 1e-9 long before 200 samples
        assert error < 1e-9
        assert abs(us[-1] - 1.4) < 1e-9  # u0 + (3 - 2) / static gain 2.5
    else:  # without the integrator the offset stays: the test can fail
        assert error > 0.1


def test_saturation_bounds_the_input_and_anti_windup_limits_the_overshoot():
    # a setpoint step of 10 needs u = 4 in steady state; the limit is 2, so it saturates
    # for the whole step; then the setpoint returns to 1 (reachable). With anti-windup the
    # integrator does not wind up and y settles near 1 without a long excursion.
    def run(antiwindup):
        loop = trusted_loop(closed_loop_poles=[0.5, 0.5, 0.4], integral_action=True,
                            input_limit=2.0)
        if not antiwindup:  # the same controller with the limit applied outside it
            loop.runtime.input_limit = 1e12
        plant = ArxPlant(IKEDA_THETA, IKEDA)
        ys, us, pending = [], [], 0.0
        for t in range(300):
            loop.set_reference(10.0 if t < 100 else 1.0)
            y = plant.output()
            computed = loop.step(y)
            applied, pending = pending, min(max(computed, -2.0), 2.0)
            plant.apply(applied)
            ys.append(y)
            us.append(computed)
        return np.array(ys), np.array(us), loop

    ys, us, loop = run(antiwindup=True)
    assert np.all(np.abs(us) <= 2.0)
    assert loop.counters['saturated'] > 90
    assert np.max(np.abs(ys[150:] - 1.0)) < 1e-3  # settled within 50 samples after the step
    wound_ys, wound_us, _ = run(antiwindup=False)
    assert np.max(np.abs(wound_us)) > 50  # the unprotected integrator winds up
    assert np.max(np.abs(wound_ys[150:] - 1.0)) > 0.5


def test_switching_keeps_a_steady_state_input_without_a_bump():
    loop = trusted_loop(closed_loop_poles=[0.5, 0.5, 0.4], integral_action=True,
                        reference_offset=3.0)
    plant = ArxPlant(IKEDA_THETA, IKEDA, y0=2.0, u0=1.0)
    ys, us, _ = run_loop(loop, plant, 200)
    # a different (but still integral) design on a slightly wrong estimate
    names = loop.structure.names
    loop.offer_parameters(names, [-0.75, 0.6], 1.0)
    loop.offer_std(names, [0.01, 0.01])
    assert loop.redesign(1.0).kind == 'switched'
    after = loop.step(plant.output())
    assert abs(after - us[-1]) < 1e-9  # e = 0 and R(1) = 0: the input does not move


def test_near_pole_zero_cancellation_is_refused():
    structure = ModelStructure(2)
    a = np.poly([0.8, 0.5])[1:]
    poles = [0.5, 0.4, 0.3, 0.2]
    for gap, refused in ((1e-7, True), (0.3, False)):
        plant = Plant.from_estimate(np.concatenate([a, np.poly([0.8 + gap])]), structure)
        if refused:
            with pytest.raises(DesignRefused, match='condition') as caught:
                place_poles(plant, poles, strictly_proper=True)
            assert caught.value.reason == 'ill_conditioned'
        else:
            controller = place_poles(plant, poles, strictly_proper=True)
            assert controller.condition < 1e3
    # with the condition check off, a gap of 1e-13 leaves a solution that misses (D) by
    # ~1e-4 (condition ~1e14 times the rounding), far above the 1e-8 accepted
    plant = Plant.from_estimate(np.concatenate([a, 0.5 * np.poly([0.8 + 1e-13])]), structure)
    with pytest.raises(DesignRefused, match='misses') as caught:
        place_poles(plant, poles, strictly_proper=True, max_condition=1e300)
    assert caught.value.reason == 'design_residual'
    # a plant zero at 1 makes integral action impossible
    plant = Plant.from_estimate(np.concatenate([a, np.poly([1.0])]), structure)
    with pytest.raises(DesignRefused, match='condition'):
        place_poles(plant, poles + [0.1], integral=True)
    with pytest.raises(DesignRefused, match='B = 0'):
        place_poles(Plant.from_estimate([-0.8, 0.0], IKEDA), [0.5, 0.5])


BAD_ESTIMATES = [
    # (names, values, std names, std values, valid, reason)
    (['x1', 'b1_1'], [-0.8, 0.5], None, None, True, 'bad_names'),
    (['a1', 'b2_1'], [-0.8, 0.5], None, None, True, 'bad_names'),
    (['a1', 'b1_1', 'b1_2'], [-0.8, 0.5, 0.1], None, None, True, 'wrong_order'),
    (['a1', 'b1_1'], [-0.8], None, None, True, 'bad_names'),
    (['a1', 'a2', 'b1_1', 'b1_2'], [-0.8, 0.1, 0.5, 0.1], None, None, True, 'wrong_order'),
    (['a1', 'b1_0', 'b1_1'], [-0.8, 0.0, 0.5], None, None, True, 'wrong_order'),
    (['a1', 'b1_2'], [-0.8, 0.5], None, None, True, 'wrong_order'),
    (['a1', 'b1_1'], [math.nan, 0.5], None, None, True, 'nonfinite_estimate'),
    (['a1', 'b1_1'], [-0.8, 0.5], ['a1', 'b1_1'], [0.01, 0.01], False, 'not_valid'),
    (['a1', 'b1_1'], [-0.8, 0.5], ['a1', 'b1_1'], [0.01, 0.01], None, 'not_valid'),
    (['a1', 'b1_1'], [-0.8, 0.5], None, None, True, 'no_std'),
    (['a1', 'b1_1'], [-0.8, 0.5], ['b1_1', 'a1'], [0.01, 0.01], True, 'std_mismatch'),
    (['a1', 'b1_1'], [-0.8, 0.5], ['a1', 'b1_1'], [0.01, math.nan], True, 'std_mismatch'),
    (['a1', 'b1_1'], [-0.8, 0.5], ['a1', 'b1_1'], [0.2, 0.01], True, 'std_too_large'),
    # b uncertain (sign unknown) though |std| / |theta| over all parameters is small
    (['a1', 'b1_1'], [-3.0, 0.01], ['a1', 'b1_1'], [0.001, 0.02], True, 'std_too_large'),
]


@pytest.mark.parametrize('names, values, std_names, std, valid, reason', BAD_ESTIMATES)
@pytest.mark.parametrize('after_trust', [False, True])
def test_every_untrusted_estimate_is_refused_counted_and_keeps_the_controller(
        names, values, std_names, std, valid, reason, after_trust):
    loop = trusted_loop() if after_trust else AdaptiveController(settings())
    kept = loop.controller
    loop._valid = None  # as if no valid message had come yet
    loop._std = None
    loop.offer_parameters(names, values, 1.0)
    if std_names is not None:
        loop.offer_std(std_names, std)
    if valid is not None:
        loop.offer_valid(valid)
    outcome = loop.redesign(1.0)
    assert (outcome.kind, outcome.reason) == ('refused', reason)
    assert ('last designed' if after_trust else 'fallback') in outcome.message
    assert loop.counters[reason] == 1 and loop.refusals == 1
    assert loop.controller is kept
    assert loop.redesign(1.5).kind == 'none'  # an estimate is looked at once
    assert loop.counters[reason] == 1
    assert math.isfinite(loop.step(0.3))


def test_an_ill_conditioned_estimate_is_refused_by_the_loop():
    loop = trusted_loop([-1.3, 0.4, 0.5, -0.1], order=2, closed_loop_poles=[0.5, 0.4, 0.3, 0.2])
    kept = loop.controller
    names = loop.structure.names
    # B = 0.5 (q - 0.8 - 1e-8) against A = (q - 0.8)(q - 0.5): a near cancellation
    loop.offer_parameters(names, [-1.3, 0.4, 0.5, -0.5 * (0.8 + 1e-8)], 1.0)
    loop.offer_std(names, [0.001] * 4)
    outcome = loop.redesign(1.0)
    assert (outcome.kind, outcome.reason) == ('refused', 'ill_conditioned')
    assert 'near pole-zero cancellation' in outcome.message
    assert loop.counters['ill_conditioned'] == 1 and loop.controller is kept


def test_the_fallback_runs_until_a_trusted_estimate_then_the_design():
    loop = AdaptiveController(settings())
    assert loop.controller is loop.fallback and not loop.trusted
    np.testing.assert_allclose(loop.fallback.numerator, [0.2289])
    loop = trusted_loop()
    # 0.5/(q - 0.8) with poles 0.5, 0.5 and a strictly proper C: C = 0.18/(q - 0.2), from a
    # solve of 2 unknowns: within its condition number times 2 x 2 eps, relative
    bound = 4 * 2 * loop.controller.condition * EPS
    assert_within(loop.controller.numerator, [0.18], bound * 0.18, 'S')
    assert_within(loop.controller.denominator, [1.0, -0.2], bound * 0.2, 'R')
    np.testing.assert_allclose(loop.predicted_poles(), [0.5, 0.5], atol=1e-6)
    assert loop.counters['redesigns'] == 1


def test_max_relative_std_zero_needs_no_std():
    loop = AdaptiveController(settings(max_relative_std=0.0))
    loop.offer_parameters(['a1', 'b1_1'], IKEDA_THETA, 0.0)
    loop.offer_valid(True)
    assert loop.redesign(0.0).kind == 'switched'


def test_bad_outputs_and_references_are_refused_and_never_reach_the_input():
    loop = trusted_loop(reference_offset=1.0)
    first = loop.step(0.0)
    for bad in (math.nan, math.inf, -math.inf):
        assert loop.step(bad) == first
        assert loop.set_reference(bad) is False
    assert loop.counters['nonfinite_output'] == 3
    assert loop.counters['nonfinite_reference'] == 3
    assert loop.setpoint == 1.0
    assert loop.samples == 1
    assert math.isfinite(loop.step(0.1))


def test_silence_and_invalidation_are_reported_once():
    loop = trusted_loop(estimate_timeout=2.0)
    assert loop.redesign(1.0).kind == 'none'
    outcome = loop.redesign(2.5)
    assert outcome.kind == 'silent' and 'last designed' in outcome.message
    assert loop.redesign(3.0).kind == 'none'
    assert loop.counters['estimates_silent'] == 1
    loop.offer_parameters(['a1', 'b1_1'], IKEDA_THETA, 4.0)
    assert loop.offer_valid(False).kind == 'invalidated'
    assert loop.offer_valid(False).kind == 'none'
    assert loop.counters['estimate_invalidated'] == 1
    assert set(loop.counters) == set(REFUSALS) | set(EVENTS)


def test_names_parse_into_the_structure():
    assert parse_names(['a1', 'a2', 'b1_1', 'b1_2']) == ModelStructure(2)
    assert parse_names(['a1', 'b1_0', 'b1_1']) == ModelStructure(1, True)
    assert parse_names(['a1', 'a2', 'b1_3', 'b1_4']) == ModelStructure(2, False, 2)
    assert parse_names(['a1', 'b1_2', 'b1_3']) == ModelStructure(1, True, 2)
    for bad in (['a2', 'b1_1'], ['b1_1', 'a1'], ['a1'], ['a1', 'b1_1', 'b1_3'], [],
                ['a1', 'b1_01']):
        with pytest.raises(DesignRefused) as caught:
            parse_names(bad)
        assert caught.value.reason == 'bad_names'
    values = check_estimate(['a1', 'b1_1'], [-0.8, 0.5], IKEDA)
    assert values.dtype == float
    plant = Plant.from_estimate([0.1, 0.2, 0.5, 0.25], ModelStructure(2, False, 1))
    np.testing.assert_array_equal(plant.denominator, [1.0, 0.1, 0.2, 0.0])
    np.testing.assert_array_equal(plant.numerator, [0.5, 0.25])


def test_configured_controllers_are_checked():
    controller = Controller.from_coefficients([0.0, 0.4], [2.0, -0.2])
    np.testing.assert_array_equal(controller.numerator, [0.2])
    np.testing.assert_array_equal(controller.denominator, [1.0, -0.1])
    assert controller.strictly_proper
    assert Controller.from_coefficients([0.0], [1.0]).strictly_proper  # zero: no feedthrough
    with pytest.raises(ValueError, match='causal'):
        Controller.from_coefficients([1.0, 0.0, 0.0], [1.0, 0.0])
    with pytest.raises(ValueError, match='non-zero leading'):
        Controller.from_coefficients([1.0], [0.0, 1.0])
    with pytest.raises(ValueError, match='finite'):
        Controller.from_coefficients([math.nan], [1.0])


@pytest.mark.parametrize('changes, match', [
    (dict(closed_loop_poles=[]), "'closed_loop_poles' must be at least 2"),
    (dict(closed_loop_poles=[0.5]), "'closed_loop_poles' must be at least 2"),
    (dict(closed_loop_poles=[0.5, 0.5], integral_action=True), 'at least 3'),
    (dict(closed_loop_poles=[0.5, 1.0]), 'inside the unit circle'),
    (dict(closed_loop_poles=[0.5, 1.5]), r"'closed_loop_poles' must be a list of numbers"),
    (dict(fallback_numerator=[1.0], fallback_denominator=[1.0]), 'strictly proper'),
    (dict(fallback_numerator=[1.0, 0.0], fallback_denominator=[1.0]), 'causal'),
    (dict(fallback_denominator=[0.0]), 'non-zero leading'),
    (dict(input_limit=0.0), "'input_limit' must be a number in \\(0"),
    (dict(reference_signal='sine'), "'reference_signal' must be one of"),
    (dict(reference_signal='square', reference_period=1), "'reference_period'"),
    (dict(max_relative_std=-1.0), "'max_relative_std'"),
    (dict(antiwindup_pole=1.0), "'antiwindup_pole'"),
    (dict(order=0), "'order'"),
    (dict(gain=1.0), "unknown parameter 'gain'"),
])
def test_bad_parameters_are_refused_with_a_clear_message(changes, match):
    with pytest.raises(ValueError, match=match):
        check_controller_parameters(settings(**changes))


def test_a_same_sample_controller_may_be_proper():
    values = settings(computation_delay=False, closed_loop_poles=[0.5],
                      fallback_numerator=[0.1], fallback_denominator=[1.0])
    loop = AdaptiveController(values)
    loop.offer_parameters(['a1', 'b1_1'], IKEDA_THETA, 0.0)
    loop.offer_std(['a1', 'b1_1'], [0.01, 0.01])
    loop.offer_valid(True)
    assert loop.redesign(0.0).kind == 'switched'
    np.testing.assert_allclose(loop.controller.numerator, [0.6])  # (q - 0.8) + 0.5 k = q - 0.5


def test_reference_generators():
    square = ReferenceGenerator('square', amplitude=2.0, period=4)
    assert [square.next() for _ in range(8)] == [2.0, 2.0, -2.0, -2.0] * 2
    odd = ReferenceGenerator('square', amplitude=1.0, period=3)
    assert [odd.next() for _ in range(6)] == [1.0, 1.0, -1.0] * 2
    draws = [[ReferenceGenerator('prbs', amplitude=0.5, period=3, seed=seed)
              for seed in (1, 1, 2)]]
    sequences = [[g.next() for _ in range(300)] for g in draws[0]]
    assert sequences[0] == sequences[1] != sequences[2]
    assert set(sequences[0]) == {0.5, -0.5}
    held = np.array(sequences[0]).reshape(100, 3)
    assert np.all(held == held[:, :1])
    assert 30 < np.sum(held[:, 0] > 0) < 70  # 100 fair coin flips: 50 +- 4 sigma (sigma 5)
    none = ReferenceGenerator('none')
    assert [none.next() for _ in range(3)] == [0.0, 0.0, 0.0]


class Oracle:
    """An 'estimator' that knows the plant: the loop's design must then be exact."""

    def __init__(self, theta, change_at=None, theta_after=None):
        self.theta_now, self.change_at, self.theta_after = theta, change_at, theta_after
        self.samples = 0
        self.valid = True

    def update(self, y, u):
        self.samples += 1
        if self.change_at is not None and self.samples > self.change_at:
            self.theta_now = self.theta_after

    @property
    def theta(self):
        return np.asarray(self.theta_now, float)


def test_offline_loop_with_the_true_plant_places_the_poles_and_readapts():
    from bcid_ros.control.offline import simulate_adaptive_loop

    after = [-0.9, 0.3]
    oracle = Oracle(IKEDA_THETA, change_at=3000, theta_after=after)
    values = settings(max_relative_std=0.0, reference_signal='square', reference_period=200,
                      reference_amplitude=0.5, integral_action=True,
                      closed_loop_poles=[0.5, 0.5, 0.4])
    run = simulate_adaptive_loop(lambda controller: oracle, values, IKEDA_THETA,
                                 samples=6000, noise_std=0.0, rng=np.random.default_rng(0),
                                 redesign_every=1000, y0=2.0, u0=1.0, change_at=3000,
                                 theta_after=after)
    # the same estimate again is met by the controller in the loop: no switch
    assert run.outcomes == ['switched', 'kept', 'kept', 'switched', 'kept', 'kept']
    for poles in run.poles:
        np.testing.assert_allclose(np.sort(poles.real), [0.4, 0.5, 0.5], atol=1e-6)
    # at sample 3000 (plant changed, old controller) the poles are off; at 4000 redesigned
    assert run.look_samples.tolist() == [1000, 2000, 3000, 4000, 5000, 6000]
    # offset-free tracking of the square wave around the operating point (0 +- 0.5, the
    # plant's y0 = 2 and u0 = 1 unknown to the design): at the end of each half period
    # the error of the triple pole transient, ~ t^2 0.5^t at t = 100, is far below 1e-9
    settled = np.abs(run.y - run.r)[np.arange(6000) % 100 == 99]
    assert np.max(settled[:10]) > 0.1  # the fallback (no integrator) leaves an offset
    assert np.max(settled[10:30]) < 1e-9  # designed from sample 1000
    assert np.max(settled[30:40]) > 1e-8  # plant changed at 3000, old design until 4000
    assert np.max(settled[40:]) < 1e-9  # re-adapted
    assert np.all(np.isfinite(run.u)) and np.max(np.abs(run.u)) <= 100.0


@pytest.mark.parametrize('tolerance, kind', [(0.0, 'switched'), (0.02, 'kept'),
                                             (0.001, 'switched')])
def test_a_trusted_estimate_close_to_the_last_one_keeps_the_controller(tolerance, kind):
    loop = trusted_loop(redesign_tolerance=tolerance)
    designed = loop.controller
    # the controller 0.18/(q - 0.2) on a1 = -0.8 + 1e-4 gives poles 0.49995 +- 0.0055j:
    # the double pole splits by about sqrt(1e-4 * 0.3)
    loop.offer_parameters(['a1', 'b1_1'], [-0.8 + 1e-4, 0.5], 1.0)
    outcome = loop.redesign(1.0)
    assert outcome.kind == kind
    assert (loop.controller is designed) == (kind == 'kept')
    assert loop.counters['kept'] == (kind == 'kept')
    assert loop.refusals == 0


def test_pole_distance():
    from bcid_ros.control.design import pole_distance

    assert pole_distance([0.5, 0.5], [0.5, 0.5]) == 0.0
    assert pole_distance([0.5 + 0.01j, 0.5 - 0.01j], [0.5, 0.5]) == pytest.approx(0.01)
    assert pole_distance([0.5, 0.9], [0.5, 0.5]) == pytest.approx(0.4)
    assert pole_distance([0.5, 0.5], [0.5, 0.9]) == pytest.approx(0.4)
