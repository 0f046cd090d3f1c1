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

# The contract of the batched estimator against one plant (see test_batched.py).
TOLERANCE = 1e-12


def messages(scenario, samples, seed):
    """Yield JointState-like messages: shuffled joints, some left out, some NaN."""
    y, u = scenario.simulate(samples, seed)
    rng = np.random.default_rng(seed + 1)
    names = np.array(scenario.joint_names)
    for t in range(samples):
        order = rng.permutation(len(names))
        order = order[rng.random(len(order)) >= 0.02]
        velocity, effort = y[t, order].copy(), u[t, order].copy()
        velocity[rng.random(len(order)) < 0.01] = np.nan
        yield types.SimpleNamespace(name=names[order].tolist(),
                                    position=array.array('d', np.zeros(len(order))),
                                    velocity=array.array('d', velocity),
                                    effort=array.array('d', effort))


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
def test_each_joint_equals_the_single_plant_identifier_path(name):
    scenario = make_scenario('joints', num_joints=6, seed=4)
    demux = JointStateDemux(scenario.joint_names)
    batched = make_batched_estimator(name, 6, order=2)
    # the reference: one single-plant estimator per joint behind the identifier's feeder
    feeders = [SampleFeeder(make_estimator(name, order=2)) for _ in range(6)]
    for message in messages(scenario, 1500, 7):
        samples = demux.take(message)
        batched.update(samples.y, samples.u, samples.present)
        for k, feeder in enumerate(feeders):
            if samples.present[k]:
                feeder.feed(np.array([[samples.y[k], samples.u[k]]]))
            else:
                feeder.gap()
    for k, feeder in enumerate(feeders):
        single = feeder.estimator
        np.testing.assert_allclose(batched.theta[k], single.theta, rtol=TOLERANCE,
                                   atol=TOLERANCE)
        np.testing.assert_allclose(batched.noise[k], single.noise, rtol=TOLERANCE,
                                   atol=TOLERANCE)
        assert batched.samples[k] == single.samples
        assert batched.valid[k] == single.valid
        assert batched.plant_validity_reasons(k) == single.validity_reasons
        assert batched.plant_flags(k) == single.flags
        assert batched.nonfinite[k] == feeder.nonfinite == demux.nonfinite[k]
        assert batched.used[k] == feeder.used
    np.testing.assert_array_equal(batched.missing, demux.missing)
    assert demux.missing.min() > 0 and demux.nonfinite.min() > 0
