"""
The outlier gate keeps heavy-tailed but genuine data and still refuses spikes.

The rulebook's tail (``rules.track_tail``) lifts the gate's limit when more than
``REFUSAL_SHARE`` of the tested samples exceed the threshold, so that the refusals follow the
errors' own distribution. The estimator checks use a synthetic positioning system with
Coulomb and viscous friction, a quantised encoder, coloured sensor noise and Student-t (3
degrees of freedom) force disturbances, in closed loop (cl_bcls) and open loop (the others).
"""

import math

import numpy as np
import pytest

from bcid_ros.estimators import make_estimator, rules

GATE = 5.0
SAMPLES = 6000
#: Integration substeps per sample of the friction mechanism.
SUBSTEPS = 10


def friction_mechanism(force_in, disturbance, spring=0.0, dt=0.05, coulomb=0.3, viscous=2.0):
    """Return the generator of positions of x'' = f + d - b x' - Fc sign(x') - k x (stick-slip)."""
    x = v = 0.0
    h = dt / SUBSTEPS
    for f, d in zip(force_in, disturbance):
        yield x
        for _ in range(SUBSTEPS):
            force = f() + d - spring * x
            if v == 0.0 and abs(force) <= coulomb:
                continue
            sign = math.copysign(1.0, v if v else force)
            v_new = v + h * (force - viscous * v - coulomb * sign)
            v_new = 0.0 if v_new * v < 0.0 else v_new
            x += 0.5 * h * (v + v_new)
            v = v_new


def sensor(rng, count, quantum=1e-3, noise=2e-4):
    """Return the encoder: quantised position plus AR(1) (pole 0.9) sensor noise."""
    e = noise * rng.standard_normal(count)
    coloured = np.zeros(count)
    for k in range(1, count):
        coloured[k] = 0.9 * coloured[k - 1] + e[k]
    return lambda k, x: quantum * round(x / quantum) + coloured[k]


def held_prbs(rng, count, hold=40, amplitude=1.0):
    """Return a PRBS held for ``hold`` samples."""
    return np.repeat(rng.choice([-amplitude, amplitude], size=count // hold + 1), hold)[:count]


def open_loop(seed, count=SAMPLES):
    """Return y, u of the spring-mass system with friction driven by a held PRBS."""
    rng = np.random.default_rng(seed)
    u = 2.0 * held_prbs(rng, count)
    disturbance = 0.3 * rng.standard_t(3, size=count)
    read = sensor(rng, count)
    forces = [lambda value=value: value for value in u]
    y = np.array([read(k, x) for k, x in enumerate(
        friction_mechanism(forces, disturbance, spring=4.0))])
    return y, u


#: The lead controller u = (6 q - 5)/(q - 0.3) (r - y) of the closed loop.
NUMERATOR, DENOMINATOR = [6.0, -5.0], [1.0, -0.3]


def closed_loop(seed, count=SAMPLES):
    """Return y, u of the friction servo under the lead controller, with a held PRBS reference."""
    rng = np.random.default_rng(seed)
    r = held_prbs(rng, count)
    disturbance = 0.3 * rng.standard_t(3, size=count)
    read = sensor(rng, count)
    y, u = np.zeros(count), np.zeros(count)
    previous = {'error': 0.0, 'u': 0.0}

    def controller(k):
        def force():
            return u[k]
        return force

    positions = friction_mechanism([controller(k) for k in range(count)], disturbance)
    for k, x in enumerate(positions):
        y[k] = read(k, x)
        error = r[k] - y[k]
        u[k] = (NUMERATOR[0] * error + NUMERATOR[1] * previous['error']
                - DENOMINATOR[1] * previous['u'])
        previous.update(error=error, u=u[k])
    return y, u


CASES = [('rls', {}), ('bcrls', {}), ('rpem', {}),
         ('bciv', {'iv_lag': 4, 'input_noise': 'white'}),
         ('cl_bcls', {'window': 0}), ('cl_bcls', {'window': 1500})]


@pytest.mark.parametrize('name, settings', CASES)
def test_heavy_tailed_friction_data_is_kept(name, settings):
    if name == 'cl_bcls':
        y, u = closed_loop(0)
        settings = dict(settings, controller_numerator=NUMERATOR,
                        controller_denominator=DENOMINATOR, controller_sign='negative')
    else:
        y, u = open_loop(0)
    est = make_estimator(name, order=2, outlier_threshold=GATE, **settings)
    est.run(y, u)
    refused = est.flags.get('outlier_rejected', 0)
    # the goal: at most 2 % of genuine samples refused. Measured 0-0.3 %, cl_bcls with a
    # window of 1500 1.2-1.5 % (1.5-1.6 % before the tail; mostly its leverage term at the
    # reference steps): a guard on every estimator, the tail's own bound is tested below
    # on errors that exceed the threshold far more often
    assert refused <= 0.02 * len(y)
    if settings.get('window'):
        # a sliding window's leverage refusals at the reference steps are no plant change:
        # the change scores judge by the error alone (8 false changes on this record before)
        assert 'plant_change' not in est.flags


# ---------------------------------------------------------------- the rule itself
def gate_run(z2, limit2=GATE ** 2):
    """Run the gate over a (T, K) array of z^2; return used (T, K) and the final tails."""
    score, tail = np.zeros(z2.shape[1]), np.ones(z2.shape[1])
    used = np.zeros(z2.shape, dtype=bool)
    for t, row in enumerate(z2):
        used[t], score, tail, _ = rules.gate(row, limit2, score, tail)
    return used, tail


def heavy_z2(rng, count, plants):
    """Return z^2 of which 10 % come from an error ten times as wide: 9 % beyond 5 sigma."""
    wide = rng.random((count, plants)) < 0.1
    return (rng.standard_normal((count, plants)) * np.where(wide, 10.0, 1.0)) ** 2


def test_the_tail_bounds_the_refused_share_whatever_the_errors():
    z2 = heavy_z2(np.random.default_rng(1), 20000, 1)
    beyond = np.mean(z2 > GATE ** 2)
    used, tail = gate_run(z2)
    refused = np.sum(~used)
    # summed tail steps: refusals <= share N + log(tail) / step (track_tail's docstring),
    # exact for any sequence; the change rule only uses more samples
    assert refused <= rules.REFUSAL_SHARE * len(z2) + math.log(tail[0]) / rules.TAIL_STEP
    assert beyond > 0.05 and refused / len(z2) < 0.02


def test_gaussian_errors_keep_the_plain_threshold():
    z2 = np.random.default_rng(2).standard_normal((100000, 1)) ** 2
    used, tail = gate_run(z2)
    # P(z^2 > 25) = 5.7e-7: no sample is beyond, and the tail never leaves 1
    assert used.all() and tail[0] == 1.0


def test_a_spike_is_refused_after_the_tail_has_lifted():
    z2 = heavy_z2(np.random.default_rng(3), 5000, 1)
    score, tail = 0.0, 1.0
    for value in z2[:, 0]:
        _, score, tail, _ = rules.gate(float(value), GATE ** 2, score, tail)
    assert tail > 1.0
    # a spike of 1000 sigma, far beyond any lifted limit (10 sigma errors give tail ~ 10-20)
    used, _, _, change = rules.gate(1e6, GATE ** 2, score, tail)
    assert not used and not change


def test_the_gate_over_a_plant_axis_is_the_single_plant_gate():
    z2 = heavy_z2(np.random.default_rng(4), 3000, 4)
    together, tails = gate_run(z2)
    for plant in range(4):
        alone, tail = gate_run(z2[:, [plant]])
        # the same elementwise arithmetic per plant: bit equal
        np.testing.assert_array_equal(alone[:, 0], together[:, plant])
        assert tail[0] == tails[plant]


def test_the_scalar_fast_path_is_the_gate():
    z2 = heavy_z2(np.random.default_rng(5), 3000, 1)[:, 0]
    score, tail = 0.0, 1.0
    for value in z2:
        quiet = rules.gate_is_quiet(float(value), GATE ** 2, score, tail)
        used, new_score, new_tail, _ = rules.gate(float(value), GATE ** 2, score, tail)
        if quiet:
            # same float operations (tail * TAIL_DOWN, floored at 1): bit equal
            assert used and new_score == score == 0.0 and new_tail == quiet
        score, tail = new_score, new_tail
