"""
``bcid demo --scenario adaptive_loop``: plant, identifier and adaptive controller, live.

Starts the three processes with config/adaptive_loop.yaml, as a user would,
and watches them from a small in-process node: once a second the estimate,
its relative error delta against the truth, and the closed-loop poles of
(true plant, controller in the loop) against the target; at the end a
summary per phase (before and after the plant change at mid-run) and a PNG
of y and r', u, the estimates against the truth, and the achieved against
the target closed-loop poles. :class:`LoopRecord` (no ROS) holds what was
seen and computes the figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from bcid_ros.control.design import (closed_loop_poles, Controller, format_poles,
                                     ModelStructure, Plant, pole_distance)
from bcid_ros.control.parameters import CONTROLLER_PARAMETERS
from bcid_ros.control.reference import ReferenceGenerator
from bcid_ros.errors import BcidError
from bcid_ros.estimators.registry import entry
from bcid_ros.identifier import interface
from bcid_ros.nodes.demo_graph import (AfterDiscovery, Child, demo_graph, DEMO_DEFAULTS,
                                       executable, START_TIMEOUT)
from bcid_ros.reproduction.common import relative_error
from bcid_ros.resources import config_file

#: Largest distance between the achieved and the target poles that counts as converged.
POLE_TOLERANCE = 0.05


@dataclasses.dataclass
class LoopRecord:
    """
    What the demo saw of the loop, indexed by plant samples (no ROS).

    Attributes
    ----------
    target : tuple of float
        The controller's ``closed_loop_poles``.
    structure : ModelStructure
        The estimate's structure (the controller's ``order``).
    change_at : int
        Sample at which the plant changes (0: no change).

    """

    target: tuple[float, ...]
    structure: ModelStructure
    change_at: int = 0
    y: list[float] = dataclasses.field(default_factory=list)
    u: list[float] = dataclasses.field(default_factory=list)
    truths: list[tuple[int, np.ndarray]] = dataclasses.field(default_factory=list)
    estimates: list[tuple[int, np.ndarray, bool]] = dataclasses.field(default_factory=list)
    controllers: list[tuple[int, Controller]] = dataclasses.field(default_factory=list)
    valid: bool = False

    # ---------------------------------------------------------------- input
    def add_truth(self, values: np.ndarray) -> None:
        """Take the truth: the first at sample 0, the republished one at the change."""
        # the plant changes at change_at exactly; the message may arrive a few samples later
        index = 0 if not self.truths else (self.change_at or len(self.y))
        self.truths.append((index, np.asarray(values, dtype=float)))

    def add_estimate(self, values: np.ndarray) -> None:
        """Take an estimate, with the validity last received."""
        self.estimates.append((len(self.y), np.asarray(values, dtype=float), self.valid))

    def add_controller(self, controller: Controller) -> None:
        """Take the controller now in the loop."""
        self.controllers.append((len(self.y), controller))

    # -------------------------------------------------------------- queries
    def truth_at(self, sample: int) -> np.ndarray | None:
        """Return the true parameters at ``sample`` (None before the first truth)."""
        found = None
        for index, values in self.truths:
            if index <= sample:
                found = values
        return found

    def controller_at(self, sample: int) -> Controller | None:
        """Return the controller in the loop at ``sample``."""
        found = None
        for index, controller in self.controllers:
            if index <= sample:
                found = controller
        return found

    def achieved_poles(self, sample: int) -> np.ndarray | None:
        """Return the closed-loop poles of (true plant, controller) at ``sample``."""
        truth, controller = self.truth_at(sample), self.controller_at(sample)
        if truth is None or controller is None or truth.size != len(self.structure.names):
            return None
        return closed_loop_poles(Plant.from_estimate(truth, self.structure), controller)

    def pole_error(self, sample: int) -> float:
        """Return the distance of the achieved poles from the target (NaN if unknown)."""
        poles = self.achieved_poles(sample)
        return math_nan() if poles is None else pole_distance(poles, self.target)

    def delta(self, sample: int, values: np.ndarray) -> float:
        """Return delta of an estimate against the truth at ``sample``."""
        truth = self.truth_at(sample)
        if truth is None or truth.shape != values.shape:
            return math_nan()
        return float(relative_error(values, truth))

    def events(self) -> list[int]:
        """Return the samples at which the achieved poles may change, sorted."""
        marks = {0, len(self.y)} | {i for i, _ in self.controllers} | {i for i, _ in self.truths}
        return sorted(marks)

    def converged_at(self, start: int, stop: int) -> int | None:
        """
        Return when the loop converged in the phase [start, stop).

        That is the first sample from which the achieved poles stay within
        :data:`POLE_TOLERANCE` of the target until ``stop`` (None if never).
        """
        marks = [m for m in self.events() if start <= m < stop]
        if not marks or marks[0] != start:
            marks.insert(0, start)
        found = None
        for mark in marks:
            if self.pole_error(mark) <= POLE_TOLERANCE:
                if found is None:
                    found = mark
            else:
                found = None
        return found

    def phases(self) -> list[tuple[str, int, int]]:
        """Return (name, first sample, end) of the phases before and after the change."""
        end = len(self.y)
        if self.change_at and self.change_at < end:
            return [('before the change', 0, self.change_at),
                    ('after the change', self.change_at, end)]
        return [('whole run', 0, end)]

    def last_estimate_before(self, stop: int) -> tuple[int, np.ndarray, bool] | None:
        """Return the last estimate received before sample ``stop``."""
        found = None
        for record in self.estimates:
            if record[0] < stop:
                found = record
        return found


def math_nan() -> float:
    """Return NaN (a name that reads in the expressions above)."""
    return float('nan')


def live_line(record: LoopRecord, total: int, elapsed: float, switches: int) -> str:
    """Return one status line: samples, estimate, delta, poles against the target."""
    sample = len(record.y)
    parts = [f'{elapsed:5.1f} s', f'samples {sample:6d}/{total}']
    if record.estimates:
        _, values, valid = record.estimates[-1]
        parts.append('theta^ [' + ' '.join(f'{v:+.3f}' for v in values) + ']'
                     + ('' if valid else ' (not valid)'))
        parts.append(f'delta {100 * record.delta(sample, values):6.2f} %')
    else:
        parts.append('no estimate yet')
    achieved, target = record.achieved_poles(sample), record.target
    parts.append(f'poles (true plant, controller) {format_poles(achieved, ".3f")}'
                 f' vs {format_poles(target, ".3f")}')
    parts.append(f'{switches} switches')
    return '  '.join(parts)


def summary(record: LoopRecord, rate: float) -> str:
    """Return the per-phase table: final estimate, delta, pole error, convergence time."""
    from bcid_ros.markdown import markdown_table

    rows = []
    for name, start, stop in record.phases():
        last = record.last_estimate_before(stop)
        truth = record.truth_at(stop - 1)
        converged = record.converged_at(start, stop)
        estimate = '-' if last is None else ' '.join(f'{v:+.4f}' for v in last[1])
        rows.append([
            name, ' '.join(f'{v:+.4f}' for v in truth) if truth is not None else '?',
            estimate, '-' if last is None else f'{100 * record.delta(stop - 1, last[1]):.2f}',
            format_poles(record.achieved_poles(stop - 1), '.3f'),
            f'{record.pole_error(stop - 1):.4f}',
            'never' if converged is None else
            f'{converged - start} samples ({(converged - start) / rate:.1f} s)'])
    return markdown_table(['phase', 'true', 'last estimate', 'delta (%)',
                           'achieved poles at the end', 'pole error',
                           f'within {POLE_TOLERANCE} from'], rows)


def plot(record: LoopRecord, reference: np.ndarray, title: str, path: Path) -> None:
    """Write the PNG: y and r', u, estimates against the truth, achieved and target poles."""
    from bcid_ros.reproduction.common import pyplot

    plt = pyplot()
    fig = plt.figure(figsize=(9, 12))
    grid = fig.add_gridspec(4, 2)
    t = np.arange(len(record.y))
    y, reference = np.asarray(record.y), reference[:t.size]
    # y and r' are readable over a few reference periods: around the change and at the end
    windows = [('at the end', max(0, t.size - 200), t.size)]
    if record.change_at and record.change_at < t.size:
        windows.insert(0, ('at the plant change', max(0, record.change_at - 60),
                           min(t.size, record.change_at + 140)))
    else:
        windows.insert(0, ('at the start', 0, min(t.size, 200)))
    for column, (name, start, stop) in enumerate(windows):
        axis = fig.add_subplot(grid[0, column])
        axis.step(t[start:stop], y[start:stop], where='post', linewidth=0.8, label='y')
        axis.step(t[start:stop], reference[start:stop], where='post', linewidth=0.8,
                  label="r'")
        axis.set_title(f"y and r' {name}", fontsize='small')
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize='small')
    axes = [fig.add_subplot(grid[row, :]) for row in (1, 2, 3)]
    axes.insert(0, None)
    axes[1].plot(t, record.u, linewidth=0.5, color='tab:green', label='u')
    axes[1].set_ylabel('input')
    names = record.structure.names
    if record.estimates:
        samples = np.array([s for s, _, _ in record.estimates])
        values = np.array([v for _, v, _ in record.estimates])
        for k, name in enumerate(names):
            line, = axes[2].plot(samples, values[:, k], '.-', markersize=2,
                                 label=f'{name} estimate')
            truth = [record.truth_at(s)[k] if record.truth_at(s) is not None else np.nan
                     for s in t[::max(1, t.size // 2000)]]
            axes[2].plot(t[::max(1, t.size // 2000)], truth, '--', color=line.get_color(),
                         linewidth=1.0, label=f'{name} true')
    axes[2].set_ylabel('parameters')
    axes[2].set_ylim(-2, 2)
    marks = record.events()
    for start, stop in zip(marks[:-1], marks[1:]):
        poles = record.achieved_poles(start)
        if poles is None:
            continue
        for pole in poles:
            style = '-' if abs(pole.imag) < 1e-9 else ':'
            axes[3].plot([start, stop], [abs(pole)] * 2 if style == ':' else [pole.real] * 2,
                         style, color='tab:red', linewidth=1.5)
    for pole in record.target:
        axes[3].axhline(pole, color='gray', linestyle='--', linewidth=0.8)
    axes[3].set_ylabel('closed-loop poles')
    axes[3].set_xlabel('samples')
    axes[3].set_title('achieved (true plant, controller in the loop; dotted: |p| of complex '
                      'poles) against the target (dashed)', fontsize='small')
    for axis in axes[1:]:
        if record.change_at and record.change_at < len(record.y):
            axis.axvline(record.change_at, color='black', linewidth=0.8, alpha=0.5)
        axis.grid(True, alpha=0.3)
        handles, _ = axis.get_legend_handles_labels()
        if handles:
            axis.legend(fontsize='small', ncol=4, loc='upper right')
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


class LoopMonitor:
    """The demo's own node: samples, truth, estimates, validity, controller, diagnostics."""

    def __init__(self, node: Any, record: LoopRecord) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import Bool, Float64MultiArray

        from bcid_ros.nodes.common import LATCHED_QOS, SAMPLES_QOS

        deep = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.record = record
        self.controller_status: dict[str, str] = {}
        self.last_sample_time = time.monotonic()
        identifier, simulator = interface.IDENTIFIER_NODE, interface.SIMULATOR_NODE
        controller = interface.CONTROLLER_NODE
        valid = interface.resolve(interface.VALID, identifier)
        #: The samples, taken once the identifier is discovered (the simulator waits for them)
        self.samples_subscription = AfterDiscovery(node, valid, lambda: node.create_subscription(
            Float64MultiArray, '/' + interface.SAMPLES, self.on_samples, SAMPLES_QOS))
        self.subscriptions = [
            node.create_subscription(Float64MultiArray,
                                     interface.resolve(interface.TRUE_PARAMETERS, simulator),
                                     lambda m: record.add_truth(np.array(m.data)), deep),
            node.create_subscription(Bool, valid, self.on_valid, LATCHED_QOS),
            node.create_subscription(Float64MultiArray,
                                     interface.resolve(interface.PARAMETERS, identifier),
                                     lambda m: record.add_estimate(np.array(m.data)),
                                     LATCHED_QOS),
            node.create_subscription(Float64MultiArray,
                                     interface.resolve(interface.CONTROLLER, controller),
                                     self.on_controller, deep),
            node.create_subscription(DiagnosticArray, interface.DIAGNOSTICS,
                                     self.on_diagnostics, 10),
        ]
        self._controller_status = f'{controller}: controller'

    def on_samples(self, message: Any) -> None:
        """Keep y_t and u_t."""
        self.record.y.append(float(message.data[0]))
        self.record.u.append(float(message.data[1]))
        self.last_sample_time = time.monotonic()

    def on_valid(self, message: Any) -> None:
        """Keep the identifier's validity."""
        self.record.valid = bool(message.data)

    def on_controller(self, message: Any) -> None:
        """Keep the controller now in the loop."""
        from bcid_ros.control.design import controller_from_message

        dims = message.layout.dim
        self.record.add_controller(controller_from_message(
            [d.label for d in dims], [d.size for d in dims], message.data))

    def on_diagnostics(self, message: Any) -> None:
        """Keep the controller's latest diagnostic values."""
        for status in message.status:
            if status.name == self._controller_status:
                self.controller_status = {kv.key: kv.value for kv in status.values}


def _reference(settings: dict[str, Any], samples: int) -> np.ndarray:
    """Return r' as the controller builds it (setpoint + excitation, one value per output)."""
    generator = ReferenceGenerator(settings.get('reference_signal', 'none'),
                                   amplitude=settings.get('reference_amplitude', 1.0),
                                   period=settings.get('reference_period', 100),
                                   seed=settings.get('reference_seed', 0))
    offset = settings.get('reference_offset', 0.0)
    return np.array([offset + generator.next() for _ in range(samples)])


def run_adaptive_loop(args: argparse.Namespace) -> int:
    """Run ``bcid demo --scenario adaptive_loop``; return the exit code."""
    from bcid_ros.parameter_spec import load_yaml_parameters

    samples, rate, _ = DEMO_DEFAULTS['adaptive_loop']
    samples = args.samples or samples
    rate = args.rate or rate
    if samples <= 0 or rate <= 0:
        raise BcidError('--samples and --rate must be positive')
    estimator = getattr(args, 'estimator', None) or 'cl_bcls'
    config = config_file('adaptive_loop')
    controller_settings = load_yaml_parameters(
        config, interface.CONTROLLER_NODE, {spec.name for spec in CONTROLLER_PARAMETERS})
    change_at = samples // 2
    record = LoopRecord(tuple(controller_settings['closed_loop_poles']),
                        ModelStructure(int(controller_settings.get('order', 2))), change_at)
    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    from rclpy.executors import ExternalShutdownException

    params = ['--ros-args', '--params-file', str(config)]
    identifier_overrides = ['-p', f'estimator:={estimator}']
    if not entry(estimator).takes_controller:
        identifier_overrides += ['-p', 'controller_topic:=""']
    switches = 0
    try:
        with demo_graph() as (node, executor, children):
            monitor = LoopMonitor(node, record)
            print(f'bcid demo: adaptive_loop with {estimator}, {samples} samples at {rate:g} Hz, '
                  f'plant change at sample {change_at}, config {config}, ROS_DOMAIN_ID='
                  f'{os.environ.get("ROS_DOMAIN_ID", "0")}', flush=True)
            children.append(Child('identifier_node', executable('identifier_node') + params
                                  + identifier_overrides, out_dir / 'identifier.log'))
            children.append(Child('adaptive_controller_node',
                                  executable('adaptive_controller_node') + params,
                                  out_dir / 'controller.log'))
            # the plant waits for two subscribers on samples (identifier, this monitor) and the
            # controller on output
            children.append(Child('simulator_node', executable('simulator_node') + params + [
                '-p', f'num_samples:={samples}', '-p', f'rate_hz:={float(rate)}',
                '-p', f'change_after_samples:={change_at}', '-p', 'wait_for_subscribers:=2',
                '-p', 'start_delay:=0.5'], out_dir / 'simulator.log'))
            simulator = children[-1]
            start = time.monotonic()
            next_line = start + 1.0
            while True:
                executor.spin_once(timeout_sec=0.05)
                monitor.samples_subscription.poll()
                now = time.monotonic()
                for child in children[:-1]:
                    code = child.poll()
                    if code is not None:
                        raise BcidError(f'{child.name} exited with code {code}:\n{child.tail()}')
                code = simulator.poll()
                if code is not None and code != 0:
                    raise BcidError(f'simulator_node exited with code {code}:\n{simulator.tail()}')
                if not record.y and now - start > START_TIMEOUT:
                    raise BcidError(f'no samples after {START_TIMEOUT:.0f} s'
                                    f'{monitor.samples_subscription.note()}; simulator log:\n'
                                    f'{simulator.tail()}')
                switches = max(len(record.controllers) - 1, 0)
                if now >= next_line:
                    print(live_line(record, samples, now - start, switches), flush=True)
                    next_line += 1.0
                if code == 0 and (len(record.y) >= samples
                                  or now - monitor.last_sample_time > 2.0):
                    break
            wall = time.monotonic() - start
    except (KeyboardInterrupt, ExternalShutdownException):
        print('bcid demo: interrupted', file=sys.stderr)
        return 130

    print(live_line(record, samples, wall, switches))
    print()
    print(summary(record, rate))
    status = monitor.controller_status
    refusals = status.get('refusals (all reasons)', '?')
    saturated = status.get('samples with the input saturated', '?')
    print(f'controller: {switches} switches, {refusals} estimates refused, {saturated} '
          f'samples saturated; plant: {_plant_summary(simulator)}')
    png = out_dir / f'demo_adaptive_loop_{estimator}.png'
    plot(record, _reference(controller_settings, len(record.y)),
         f'bcid demo: adaptive loop with {estimator} (plant change at sample {change_at})', png)
    print(f'wall time {wall:.1f} s ({len(record.y) / wall:.0f} samples/s); wrote {png}')
    return 0


def _plant_summary(simulator: Child) -> str:
    """Return the simulator's counter line from its log ('?' if absent)."""
    try:
        text = simulator.log.read_text(errors='replace')
    except OSError:
        return '?'
    for line in reversed(text.splitlines()):
        if 'plant mode:' in line:
            return line.split('plant mode:', 1)[1].strip()
    return '?'


__all__ = ['LoopRecord', 'POLE_TOLERANCE', 'run_adaptive_loop']
