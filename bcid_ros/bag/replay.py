"""
Offline replay: run the identifier's estimator over a bag's samples, no ROS graph.

The estimator is built from the same parameter file through
:func:`bcid_ros.identifier.parameters.estimator_from_parameters`, and every message
goes through the node's own per-message rule,
:class:`bcid_ros.identifier.feeder.SampleFeeder`, which also decides the samples where
estimates are published. So the replay's final estimate equals what
``identifier_node`` publishes for the same bag on the same machine, to the
last bit (another CPU may get other BLAS and SIMD kernels).

The bag is read in blocks (:meth:`bcid_ros.bag.reader.BagReader.blocks`):
runs of messages with the same layout, in log-time order, fed with
:meth:`~bcid_ros.identifier.feeder.SampleFeeder.take_messages`, which applies the
per-message rule to a whole block in one loop. A block whose layout is
wrong goes message by message through
:meth:`~bcid_ros.identifier.feeder.SampleFeeder.take_message`, as the node would. A CSV
log (:mod:`bcid_ros.bag.csv_samples`) comes in blocks of one-sample messages,
the messages of the bag that ``bcid import`` writes from it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
import time
from typing import Any

import numpy as np

from bcid_ros.bag.blocks import MessageBlock
from bcid_ros.bag.csv_samples import CsvSamples, is_csv, read_csv_samples
from bcid_ros.bag.reader import BagReader, BagTruth
from bcid_ros.blas_threads import single_threaded_blas
from bcid_ros.errors import BcidError
from bcid_ros.identifier.feeder import SampleFeeder
from bcid_ros.identifier.interface import (FLOAT64_MULTI_ARRAY, IDENTIFIER_NODE, NOISE_VARIANCE,
                                           PARAMETERS, PARAMETERS_UNCOMPENSATED, resolve, SAMPLES)
from bcid_ros.identifier.layouts import decode_samples, estimate_layout, row_order
from bcid_ros.identifier.parameters import check_identifier_parameters, estimator_from_parameters

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
    the log time of the message that completed it; it is empty when the
    replay was asked for none (``trajectory=False``).
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
    #: The final parameter standard deviations (None if the estimator has none).
    std: np.ndarray | None = None
    #: Whether the bag's file order was its log-time order (else it was sorted).
    in_file_order: bool = True
    #: The final operating point (``detrend: mean``) and its names, else None.
    operating_point: np.ndarray | None = None
    operating_point_names: tuple[str, ...] = ()
    #: Whether the estimator became ready (it publishes estimates from then on).
    ready: bool = True
    #: Empty messages dropped.
    empty: int = 0
    #: Why the first malformed message was refused ('' if none was).
    first_malformed: str = ''

    @property
    def unused(self) -> dict[str, int]:
        """
        Return what was not used, by cause (``--json``'s ``unused``).

        ``malformed`` and ``empty`` count messages (a malformed message has no
        sure number of samples), ``estimator_errors`` messages whose update
        raised, ``nonfinite`` samples with NaN/Inf, ``undone`` updates the
        estimator took back (its state would have become unsound), ``refused``
        samples its outlier test refused.
        """
        return {'malformed': self.malformed, 'empty': self.empty,
                'estimator_errors': self.failures, 'nonfinite': self.nonfinite,
                'undone': int(self.flags.get('update_undone', 0)),
                'refused': int(self.flags.get('outlier_rejected', 0))}

    @property
    def not_ready_reason(self) -> str:
        """Return why the estimator never became ready, from the counts ('' if it did)."""
        if self.ready:
            return ''
        unused = {cause: count for cause, count in self.unused.items() if count}
        causes = ', '.join(f'{count} {cause.replace("_", " ")}' for cause, count
                           in sorted(unused.items(), key=lambda item: -item[1]))
        if self.samples == 0:
            text = f'no sample was used of {self.messages} messages'
            text += f' ({causes})' if causes else ''
        else:
            taken = self.samples - unused.get('undone', 0) - unused.get('refused', 0)
            text = f'{self.samples} samples went in, {taken} were kept'
            text += f' ({causes})' if causes else ' (too few samples)'
        if self.first_malformed:
            text += f'; first malformed message: {self.first_malformed}'
        return 'never became ready: ' + text
    #: ``~/valid`` with each published estimate, and the flags raised since the one before.
    valid_trajectory: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(0, dtype=bool))
    events: list[tuple[str, ...]] = dataclasses.field(default_factory=list)

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
        estimate is valid, as ``~/valid`` would say), ``validity_reasons`` (why it
        is not, as /diagnostics says; empty when valid), ``parameters``,
        ``uncompensated``, ``noise``, ``flags`` (the estimator's flag counts,
        ``{name: count}``), ``std`` (the standard deviations of the final
        parameters, for estimators that have them: rls, bcrls), with ``detrend: mean``
        ``operating_point`` (``{'y': y0, 'u1': ..., ...}``) and, when the bag carries the
        truth, ``truth`` (``{'parameters': {...}, 'noise': {...}}``) and ``delta``
        (the relative error ||theta_hat - theta|| / ||theta||, a fraction).
        """
        out: dict[str, Any] = {
            'estimator': self.estimator,
            'samples': self.samples,
            'valid': self.valid,
            'validity_reasons': list(self.validity_reasons),
            'parameters': _named(self.parameter_names, self.theta),
            'uncompensated': _named(self.parameter_names, self.theta_uncompensated),
            'noise': _named(self.noise_names, self.noise),
            'flags': dict(self.flags),
            'unused': self.unused,
        }
        if not self.ready:
            out['not_ready'] = self.not_ready_reason
        if self.std is not None:
            out['std'] = _named(self.parameter_names, self.std)
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


def replay(bag: str | Path | BagReader | CsvSamples, parameters: dict[str, Any],
           estimator: str | None = None, topic: str = SAMPLES_TOPIC,
           trajectory: bool = True) -> ReplayResult:
    """
    Run the configured estimator over the samples of a bag or a CSV log.

    A CSV log (:class:`~bcid_ros.bag.csv_samples.CsvSamples`, or a path
    ending in ``.csv``, read with the default columns) goes through the same
    per-message rule as the bag that ``bcid import`` writes from it: blocks
    of one-sample messages.

    Parameters
    ----------
    bag : str, pathlib.Path, BagReader or CsvSamples
        The bag, or the CSV log.
    parameters : dict
        Identifier parameters (``bcid_identifier`` section of a parameter file).
    estimator : str, optional
        Overrides the ``estimator`` parameter.
    topic : str
        The samples topic.
    trajectory : bool
        Whether to keep every published estimate (for ``--output``); the
        final estimate is the same either way.

    Returns
    -------
    ReplayResult

    Raises
    ------
    BcidError
        If the bag cannot be read, lacks the topic, or it has another type;
        if the CSV cannot be read or has another number of inputs than
        ``num_inputs``.
    ValueError
        If a parameter is not allowed (named in the message).

    """
    if not isinstance(bag, (BagReader, CsvSamples)):
        bag = read_csv_samples(bag, load=False) if is_csv(bag) else BagReader(bag)
    values = dict(parameters)
    if estimator is not None:
        values['estimator'] = estimator
    values = check_identifier_parameters(values)
    if values['input_mode'] != 'combined':
        raise BcidError("replay reads the combined samples topic; set input_mode: combined "
                        f"(got {values['input_mode']!r})")
    if isinstance(bag, CsvSamples):
        if bag.num_inputs != values['num_inputs']:
            raise BcidError(f'{bag.path} has {bag.num_inputs} input column(s) '
                            f'({",".join(bag.columns[1:])}) but the parameter file sets '
                            f"num_inputs = {values['num_inputs']}")
        blocks, truth = bag.blocks(), None
    else:
        bag.require(topic, FLOAT64_MULTI_ARRAY)
        blocks, truth = bag.blocks(topic), bag.truth()
    est = estimator_from_parameters(values)
    feeder = SampleFeeder(est, values['excitation_window'], values['publish_period'],
                          values['freeze_unexcited'])
    published = _Published()
    messages = failures = 0
    dropped = _Dropped()
    start = time.perf_counter()
    with single_threaded_blas():  # one BLAS thread, as in the node (its arithmetic too)
        for block in blocks:
            messages += len(block)
            rows, count = _block_rows(block, est.num_inputs)
            if rows is None:
                failures += _take_one_by_one(feeder, block, published, dropped)
                continue
            # The node's per-message rule, for the whole block in one loop.
            result = feeder.take_messages(rows, count, publish=trajectory, timed=False)
            failures += len(result.failures)
            for index, used, estimates, valid, flags in zip(
                    result.published, result.used_totals, result.estimates, result.valid,
                    result.flags):
                published.add(int(block.times_ns[index]), used, estimates, valid, flags)
    elapsed = time.perf_counter() - start
    if messages == 0:
        raise BcidError(f'{bag.path}: topic {topic} has no messages')
    p, q = est.num_parameters, len(est.noise_names)
    return ReplayResult(
        estimator=values['estimator'], parameter_names=est.parameter_names,
        noise_names=tuple(est.noise_names), theta=est.theta,
        theta_uncompensated=est.theta_uncompensated, noise=est.noise, valid=bool(est.valid),
        validity_reasons=tuple(est.validity_reasons), flags=dict(est.flags),
        samples=feeder.used, messages=messages, malformed=dropped.malformed, failures=failures,
        nonfinite=feeder.nonfinite, truth=truth, elapsed_s=elapsed,
        times_ns=np.array(published.times, dtype=np.int64),
        sample_counts=np.array(published.counts, dtype=np.int64),
        theta_trajectory=published.array(0, p),
        uncompensated_trajectory=published.array(1, p),
        noise_trajectory=published.array(2, q),
        in_file_order=isinstance(bag, CsvSamples) or bag.order[topic].in_file_order,
        std=est.parameter_std,
        operating_point=est.operating_point,
        operating_point_names=est.operating_point_names,
        ready=bool(est.ready), empty=dropped.empty, first_malformed=dropped.first_reason,
        valid_trajectory=np.array(published.valid, dtype=bool), events=published.events)


class _Published:
    """The published estimates of a replay, in order."""

    def __init__(self) -> None:
        self.times: list[int] = []
        self.counts: list[int] = []
        self.estimates: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.valid: list[bool] = []
        self.events: list[tuple[str, ...]] = []
        self._flags: dict[str, int] = {}

    def add(self, stamp: int, used: int, estimates: tuple[np.ndarray, np.ndarray, np.ndarray],
            valid: bool = False, flags: dict[str, int] | None = None) -> None:
        self.times.append(stamp)
        self.counts.append(used)
        self.estimates.append(estimates)
        self.valid.append(bool(valid))
        # the flags raised since the estimate before (their counts grew)
        flags = self._flags if flags is None else flags
        self.events.append(tuple(name for name, count in flags.items()
                                 if count > self._flags.get(name, 0)))
        self._flags = dict(flags)

    def array(self, which: int, width: int) -> np.ndarray:
        """Return estimate ``which`` (0 theta, 1 uncompensated, 2 noise) of all, one per row."""
        return np.array([e[which] for e in self.estimates]).reshape(-1, width)


def _block_rows(block: MessageBlock, num_inputs: int) -> tuple[np.ndarray | None, int]:
    """
    Return the rows of all the messages of a block and the samples per message.

    The messages share their layout and length, so the first one's decoding
    (:func:`~bcid_ros.identifier.layouts.decode_samples`) holds for all. ``(None, 0)``
    if that decoding fails: the block then goes message by message.
    """
    try:
        first = decode_samples(block.message(0), num_inputs)
    except ValueError:
        return None, 0
    count, width = first.shape
    offset = int(getattr(block.layout, 'data_offset', 0) or 0)
    rows = block.data[:, offset:].reshape(len(block) * count, width)
    dims = list(block.layout.dim)
    order = row_order(dims[-1].label, width) if dims else None  # checked by decode_samples
    return (rows if order is None else rows[:, order]), count


@dataclasses.dataclass
class _Dropped:
    """Messages dropped before the estimator: malformed and empty ones, the first reason."""

    malformed: int = 0
    empty: int = 0
    first_reason: str = ''


def _take_one_by_one(feeder: SampleFeeder, block: MessageBlock, published: _Published,
                     dropped: _Dropped) -> int:
    """Feed each message of a block through take_message; count the drops; return failures."""
    failures = 0
    for index in range(len(block)):
        result = feeder.take_message(block.message(index))
        if result.dropped == 'estimator_errors':
            failures += 1
        elif result.dropped == 'empty':
            dropped.empty += 1
        elif result.dropped:
            dropped.malformed += 1
            dropped.first_reason = dropped.first_reason or result.reason
        if result.estimates is not None:
            estimator = feeder.estimator
            published.add(int(block.times_ns[index]), feeder.used, result.estimates,
                          estimator.valid, dict(estimator.flags))
    return failures


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
    import csv  # here, as the writers below: a replay without --output needs none of them

    names = result.parameter_names
    header = (['time_s', 'samples'] + list(names) + [f'uncompensated_{n}' for n in names]
              + list(result.noise_names) + ['valid', 'events'])
    with path.open('w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(header)
        for k in range(result.times_ns.shape[0]):
            writer.writerow([f'{result.times_ns[k] / 1e9:.9f}', int(result.sample_counts[k])]
                            + [repr(float(v)) for v in result.theta_trajectory[k]]
                            + [repr(float(v)) for v in result.uncompensated_trajectory[k]]
                            + [repr(float(v)) for v in result.noise_trajectory[k]]
                            + [int(result.valid_trajectory[k]), ';'.join(result.events[k])])


def _write_mcap(result: ReplayResult, path: Path) -> None:
    import shutil

    from bcid_ros.bag.qos import LATCHED
    from bcid_ros.bag.writer import BagWriter, float64_multi_array

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
