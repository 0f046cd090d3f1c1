"""
``bcid simulate``: write a scenario bag offline, in the simulator node's format.

The bag holds what ``simulator_node`` publishes (docs/nodes.md): one
``/samples`` message ``[y, u1, ..., ur]`` per sampling instant, stamped
``k / rate`` seconds from t = 0, and the latched truth topics
``/bcid_simulator/true_parameters`` and ``/bcid_simulator/true_noise_variance``
at t = 0. The samples are those of ``make_scenario(name).simulate(N, seed)``,
which the node reproduces for the same seed at any rate.
"""

from __future__ import annotations

from pathlib import Path

from bcid_ros.bag.qos import LATCHED, make_qos
from bcid_ros.bag.writer import BagWriter, float64_multi_array
from bcid_ros.errors import BcidError
from bcid_ros.identifier.interface import (FLOAT64_MULTI_ARRAY, resolve, SAMPLES, SIMULATOR_NODE,
                                           TRUE_NOISE_VARIANCE, TRUE_PARAMETERS)
from bcid_ros.identifier.layouts import estimate_layout, samples_layout
from bcid_ros.simulation import make_scenario

SAMPLES_TOPIC = resolve(SAMPLES, SIMULATOR_NODE)
TRUE_PARAMETERS_TOPIC = resolve(TRUE_PARAMETERS, SIMULATOR_NODE)
TRUE_NOISE_TOPIC = resolve(TRUE_NOISE_VARIANCE, SIMULATOR_NODE)

#: QoS of the simulator's samples topic: reliable, volatile, keep_last 1000.
SAMPLES_QOS = make_qos(reliable=True, transient_local=False, depth=1000)


def simulate_bag(scenario: str, samples: int, seed: int, rate_hz: float, out: Path) -> Path:
    """
    Simulate ``samples`` samples of ``scenario`` with ``seed`` and write them to a new bag.

    Returns
    -------
    pathlib.Path
        The bag directory.

    Raises
    ------
    BcidError
        If an argument is out of range or ``out`` exists.

    """
    if samples < 1:
        raise BcidError(f'--samples must be >= 1, got {samples}')
    if not rate_hz > 0:
        raise BcidError(f'--rate must be > 0, got {rate_hz}')
    if seed < 0:
        raise BcidError(f'--seed must be >= 0, got {seed}')
    model = make_scenario(scenario)
    truth = model.truth()
    y, u = model.simulate(samples, seed)
    period_ns = 1e9 / rate_hz
    with BagWriter(out) as writer:
        writer.add_topic(SAMPLES_TOPIC, FLOAT64_MULTI_ARRAY, [SAMPLES_QOS])
        writer.add_topic(TRUE_PARAMETERS_TOPIC, FLOAT64_MULTI_ARRAY, [LATCHED])
        writer.add_topic(TRUE_NOISE_TOPIC, FLOAT64_MULTI_ARRAY, [LATCHED])
        writer.write_message(TRUE_PARAMETERS_TOPIC, 0, float64_multi_array(
            [estimate_layout(truth.parameter_names)], truth.parameters))
        writer.write_message(TRUE_NOISE_TOPIC, 0, float64_multi_array(
            [estimate_layout(truth.noise_names)], truth.noise))
        layout = samples_layout(1, model.num_inputs)
        for k in range(samples):
            row = [y[k], *u[k]]
            writer.write_message(SAMPLES_TOPIC, round(k * period_ns),
                                 float64_multi_array(layout, row))
    return out


__all__ = ['SAMPLES_QOS', 'SAMPLES_TOPIC', 'TRUE_NOISE_TOPIC', 'TRUE_PARAMETERS_TOPIC',
           'simulate_bag']
