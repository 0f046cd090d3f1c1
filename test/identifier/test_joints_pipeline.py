"""JointState messages of the joints scenario through the demux and one batched estimator."""

import array
import types

import numpy as np
import pytest

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators import make_batched_estimator
from bcid_ros.identifier.feeder import SampleFeeder
from bcid_ros.identifier.joint_demux import JointStateDemux
from bcid_ros.simulation import make_scenario
from equivalence import assert_paths_agree, rounding_spread


def messages(names, y, u, seed):
    """Yield JointState-like messages of y, u: shuffled joints, some left out, some NaN."""
    rng = np.random.default_rng(seed + 1)
    names = np.array(names)
    for t in range(y.shape[0]):
        order = rng.permutation(len(names))
        order = order[rng.random(len(order)) >= 0.02]
        velocity, effort = y[t, order].copy(), u[t, order].copy()
        velocity[rng.random(len(order)) < 0.01] = np.nan
        yield types.SimpleNamespace(name=names[order].tolist(),
                                    position=array.array('d', np.zeros(len(order))),
                                    velocity=array.array('d', velocity),
                                    effort=array.array('d', effort))


def single_feeders(name, names, y, u, seed):
    """Return one single-plant estimator per joint behind the identifier's feeder, fed."""
    demux = JointStateDemux(names)
    feeders = [SampleFeeder(make_estimator(name, order=2)) for _ in names]
    for message in messages(names, y, u, seed):
        samples = demux.take(message)
        for k, feeder in enumerate(feeders):
            if samples.present[k]:
                feeder.feed(np.array([[samples.y[k], samples.u[k]]]))
            else:
                feeder.gap()
    return feeders


def figures(theta, noise):
    """Return the compared quantities of one joint by name."""
    return {'theta': theta, 'noise': noise}


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
def test_each_joint_equals_the_single_plant_identifier_path(name):
    scenario = make_scenario('joints', num_joints=6, seed=4)
    names = scenario.joint_names
    y, u = scenario.simulate(1500, 7)
    demux = JointStateDemux(names)
    batched = make_batched_estimator(name, 6, order=2)
    for message in messages(names, y, u, 7):
        samples = demux.take(message)
        batched.update(samples.y, samples.u, samples.present)
    feeders = single_feeders(name, names, y, u, 7)

    # The batched step is another arithmetic path than the single plant's (test_batched.py):
    # each joint within the rounding spread of its single-plant run (test/equivalence.py).
    def compute(y, u):
        return {(k, key): value for k, feeder in enumerate(single_feeders(name, names, y, u, 7))
                for key, value in figures(feeder.estimator.theta,
                                          feeder.estimator.noise).items()}

    spread = rounding_spread(compute, y, u)
    for k, feeder in enumerate(feeders):
        single = feeder.estimator
        assert_paths_agree(figures(batched.theta[k], batched.noise[k]),
                           figures(single.theta, single.noise),
                           {key: spread[k, key] for key in ('theta', 'noise')},
                           int(batched.used[k] + batched.nonfinite[k] + batched.missing[k]),
                           f'joint {k}')
        assert batched.samples[k] == single.samples
        assert batched.valid[k] == single.valid
        assert batched.plant_validity_reasons(k) == single.validity_reasons
        assert batched.plant_flags(k) == single.flags
        assert batched.nonfinite[k] == feeder.nonfinite == demux.nonfinite[k]
        assert batched.used[k] == feeder.used
    np.testing.assert_array_equal(batched.missing, demux.missing)
    assert demux.missing.min() > 0 and demux.nonfinite.min() > 0
