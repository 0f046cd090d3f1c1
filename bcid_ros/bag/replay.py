"""
Offline replay: run the identifier's estimator over a bag's samples, no ROS graph.

The estimator is built from the same parameter file through
:func:`bcid_ros.parameters.estimator_from_parameters`, and every message
goes through the node's own per-message rule,
:meth:`bcid_ros.samples.SampleFeeder.take_message`, which also decides the
samples where estimates are published. So the replay's final estimate
equals what ``identifier_node`` publishes for the same bag, to the last bit.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
import shutil
import time
from typing import Any

import numpy as np

from bcid_ros.bag.qos import LATCHED
from bcid_ros.bag.reader import BagReader, BagTruth
from bcid_ros.bag.writer import BagWriter, float64_multi_array
from bcid_ros.errors import BcidError
from bcid_ros.nodes.interface import (FLOAT64_MULTI_ARRAY, IDENTIFIER_NODE, NOISE_VARIANCE,
                                      PARAMETERS, PARAMETERS_UNCOMPENSATED, resolve, SAMPLES)
from bcid_ros.parameters import check_identifier_parameters, estimator_from_parameters
from bcid_ros.samples import estimate_layout, SampleFeeder

#: The topic the identifier reads (combined input mode).
SAMPLES_TOPIC = resolve(SAMPLES, IDENTIFIER_NODE)

#: The node's estimate topics (node name ``bcid_identifier``), as written by ``--output``.
OUTPUT_TOPICS = {
    'parameters': resolve(PARAMETERS, IDENTIFIER_NODE),
    'uncompensated': resolve(PARAMETERS_UNCOMPENSATED, IDENTIFIER_NODE),
    'noise': resolve(NOISE_VARIANCE, IDENTIFIER_NODE),
}


@dataclasses.dataclass
class ReplayResult:
    """
    What a replay found: the final estimates, the counters and the trajectory.

    The trajectory has one row per published estimate (every
    ``publish_period`` samples once the estimator is valid), stamped with
    the log time of the message that completed it.
    """

    estimator: str
    parameter_names: tuple[str, ...]
    noise_names: tuple[str, ...]
    theta: np.ndarray
    theta_uncompensated: np.ndarray
    noise: np.ndarray
    valid: bool
    validity_reasons: tuple[str, ...]
    flags: dict[str, int]
    samples: int
    messages: int
    malformed: int
    failures: int
    nonfinite: int
    truth: BagTruth | None
    elapsed_s: float
    times_ns: np.ndarray
    sample_counts: np.ndarray
    theta_trajectory: np.ndarray
    uncompensated_trajectory: np.ndarray
    noise_trajectory: np.ndarray
    #: The final operating point (``detrend: mean``) and its names, else None.
    operating_point: np.ndarray | None = None
    operating_point_names: tuple[str, ...] = ()

    @property
    def delta(self) -> float | None:
        """Return ||theta_hat - theta|| / ||theta|| against the bag's truth, if comparable."""
        if self.truth is None or self.truth.parameter_names != self.parameter_names:
            return None
        true = self.truth.parameters
        return float(np.linalg.norm(self.theta - true) / np.linalg.norm(true))

    def summary(self) -> dict[str, Any]:
        """
        Return the ``bcid replay --json`` object (docs/bags.md).

        Keys: ``estimator``, ``samples``, ``valid`` (whether the final
        estimate is valid, as ``~/valid`` would say), ``parameters``,
        ``uncompensated``, ``noise``, ``flags`` (the estimator's flag counts,
        ``{name: count}``), with ``detrend: mean`` ``operating_point``
        (``{'y': y0, 'u1': ..., ...}``) and, when the bag carries the truth, ``truth``
        (``{'parameters': {...}, 'noise': {...}}``) and ``delta``
        (the relative error ||theta_hat - theta|| / ||theta||, a fraction).
        """
        out: dict[str, Any] = {
            'estimator': self.estimator,
            'samples': self.samples,
            'valid': self.valid,
            'parameters': _named(self.parameter_names, self.theta),
            'uncompensated': _named(self.parameter_names, self.theta_uncompensated),
            'noise': _named(self.noise_names, self.noise),
            'flags': dict(self.flags),
        }
        if self.operating_point is not None:
            out['operating_point'] = _named(self.operating_point_names, self.operating_point)
        if self.truth is not None:
            out['truth'] = self.truth.as_dict()
            delta = self.delta
            if delta is not None:
                out['delta'] = delta
        return out


def _named(names: tuple[str, ...], values: np.ndarray) -> dict[str, float]:
    return {name: float(value) for name, value in zip(names, values)}


def replay(bag: str | Path | BagReader, parameters: dict[str, Any],
           estimator: str | None = None, topic: str = SAMPLES_TOPIC) -> ReplayResult:
    """
    Run the configured estimator over the samples of a bag.

    Parameters
    ----------
    bag : str, pathlib.Path or BagReader
        The bag.
    parameters : dict
        Identifier parameters (``bcid_identifier`` section of a parameter file).
    estimator : str, optional
        Overrides the ``estimator`` parameter.
    topic : str
        The samples topic.

    Returns
    -------
    ReplayResult

    Raises
    ------
    BcidError
        If the bag cannot be read, lacks the topic, or it has another type.
    ValueError
        If a parameter is not allowed (named in the message).

    """
    reader = bag if isinstance(bag, BagReader) else BagReader(bag)
    values = dict(parameters)
    if estimator is not None:
        values['estimator'] = estimator
    values = check_identifier_parameters(values)
    if values['input_mode'] != 'combined':
        raise BcidError("replay reads the combined samples topic; set input_mode: combined "
                        f"(got {values['input_mode']!r})")
    reader.require(topic, FLOAT64_MULTI_ARRAY)
    truth = reader.truth()
    est = estimator_from_parameters(values)
    feeder = SampleFeeder(est, values['excitation_window'], values['publish_period'],
                          values['freeze_unexcited'])

    times: list[int] = []
    counts: list[int] = []
    thetas: list[np.ndarray] = []
    uncompensated: list[np.ndarray] = []
    noises: list[np.ndarray] = []
    messages = malformed = failures = 0
    start = time.perf_counter()
    for log_time, message in reader.float64_multi_arrays(topic):
        messages += 1
        # The node's own per-message rule (SampleFeeder), so that the estimates are equal.
        result = feeder.take_message(message)
        if result.dropped == 'estimator_errors':
            failures += 1
        elif result.dropped:
            malformed += 1
        estimates = result.estimates
        if estimates is not None:
            times.append(log_time)
            counts.append(feeder.used)
            thetas.append(estimates[0])
            uncompensated.append(estimates[1])
            noises.append(estimates[2])
    elapsed = time.perf_counter() - start
    if messages == 0:
        raise BcidError(f'{reader.path}: topic {topic} has no messages')
    p, q = est.num_parameters, len(est.noise_names)
    return ReplayResult(
        estimator=values['estimator'], parameter_names=est.parameter_names,
        noise_names=tuple(est.noise_names), theta=est.theta,
        theta_uncompensated=est.theta_uncompensated, noise=est.noise, valid=bool(est.valid),
        validity_reasons=tuple(est.validity_reasons), flags=dict(est.flags),
        samples=feeder.used, messages=messages, malformed=malformed, failures=failures,
        nonfinite=feeder.nonfinite, truth=truth, elapsed_s=elapsed,
        times_ns=np.array(times, dtype=np.int64), sample_counts=np.array(counts, dtype=np.int64),
        theta_trajectory=np.array(thetas).reshape(-1, p),
        uncompensated_trajectory=np.array(uncompensated).reshape(-1, p),
        noise_trajectory=np.array(noises).reshape(-1, q),
        operating_point=est.operating_point,
        operating_point_names=est.operating_point_names)


def write_output(result: ReplayResult, path: Path) -> None:
    """
    Write the estimate trajectory as a bag (``.mcap``) or a table (``.csv``).

    A ``.mcap`` file holds the node's three estimate topics in the node's
    format and QoS (a rosbag2 MCAP, playable with ``ros2 bag play``); a
    ``.csv`` has one row per published estimate. An existing file is
    replaced.

    Raises
    ------
    BcidError
        If the suffix is neither ``.mcap`` nor ``.csv``, or the bag exists.

    """
    suffix = path.suffix.lower()
    if suffix == '.csv':
        _write_csv(result, path)
    elif suffix == '.mcap':
        _write_mcap(result, path)
    else:
        raise BcidError(f'--output {path}: use a .mcap or a .csv file name')


def _write_csv(result: ReplayResult, path: Path) -> None:
    names = result.parameter_names
    header = (['time_s', 'samples'] + list(names) + [f'uncompensated_{n}' for n in names]
              + list(result.noise_names))
    with path.open('w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(header)
        for k in range(result.times_ns.shape[0]):
            writer.writerow([f'{result.times_ns[k] / 1e9:.9f}', int(result.sample_counts[k])]
                            + [repr(float(v)) for v in result.theta_trajectory[k]]
                            + [repr(float(v)) for v in result.uncompensated_trajectory[k]]
                            + [repr(float(v)) for v in result.noise_trajectory[k]])


def _write_mcap(result: ReplayResult, path: Path) -> None:
    series = (('parameters', result.parameter_names, result.theta_trajectory),
              ('uncompensated', result.parameter_names, result.uncompensated_trajectory),
              ('noise', result.noise_names, result.noise_trajectory))
    # rosbags writes a bag directory; keep only its MCAP file, under the name asked for.
    directory = path.with_name(path.name + '.partial')
    shutil.rmtree(directory, ignore_errors=True)
    with BagWriter(directory) as writer:
        for key, names, _ in series:
            if names:
                writer.add_topic(OUTPUT_TOPICS[key], FLOAT64_MULTI_ARRAY, [LATCHED])
        for k in range(result.times_ns.shape[0]):
            for key, names, rows in series:
                if names:
                    writer.write_message(OUTPUT_TOPICS[key], int(result.times_ns[k]),
                                         float64_multi_array([estimate_layout(names)], rows[k]))
    (directory / f'{directory.name}_0.mcap').replace(path)
    shutil.rmtree(directory)


__all__ = ['OUTPUT_TOPICS', 'ReplayResult', 'SAMPLES_TOPIC', 'replay', 'write_output']
