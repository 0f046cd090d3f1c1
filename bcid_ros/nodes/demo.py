"""
``bcid demo``: the simulator and identifier nodes, converging live.

``bcid demo --scenario payload_change`` runs a plant that changes at mid-run
(config/payload_change.yaml): the demo prints when the identifier flags the
change and when ``~/valid`` turns false and true again, and its PNG adds
``~/valid`` over time, with the change marked.

``bcid demo --scenario adaptive_loop`` runs the adaptive loop instead
(:mod:`bcid_ros.nodes.demo_loop`, docs/adaptive_loop.md); the two share the
child processes and the watching node of :mod:`bcid_ros.nodes.demo_graph`.

Starts ``simulator_node`` and ``identifier_node`` as two processes with the
scenario's config file, as a user would, and watches them from a small
in-process node: one line per second (samples, the current estimate, its
relative error delta against the truth, sigma^2), then a summary table of
the final estimate against the truth, and a PNG of delta(t) and the
parameter trajectories (each against the truth in effect at its sample).
The child processes are stopped on every way out.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from bcid_ros.errors import BcidError
from bcid_ros.identifier import interface
from bcid_ros.identifier.interface import COUNTERS, DiagnosticKey as Key
from bcid_ros.nodes.demo_graph import (AfterDiscovery, Child, demo_graph, DEMO_DEFAULTS,
                                       executable, START_TIMEOUT)
from bcid_ros.reproduction.common import relative_error
from bcid_ros.resources import config_file

#: Seconds to wait for the last estimate after the simulator has finished.
SETTLE_TIMEOUT = 10.0
#: The scenario whose plant changes at mid-run (its own config; the demo sets the sample).
PAYLOAD_CHANGE = 'payload_change'
#: The estimator flag of a detected plant change, as /diagnostics counts it.
CHANGE_FLAG = 'plant_change'


class Monitor:
    """The demo's own node: listens to the estimates, the truth, the samples and diagnostics."""

    def __init__(self, node: Any, identifier: str, simulator: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import Bool, Float64MultiArray

        from bcid_ros.nodes.common import LATCHED_QOS, SAMPLES_QOS

        self.node = node
        self.samples = 0
        self.names: tuple[str, ...] = ()
        self.truth: np.ndarray | None = None
        #: (samples received, truth) at each publication of the truth (a plant change)
        self.truths: list[tuple[int, np.ndarray]] = []
        #: (samples received, ~/valid) at each publication of ~/valid (it is latched and
        #: published when it changes)
        self.valid: list[tuple[int, bool]] = []
        #: (samples received, 'flag plant_change' count, reason) when the count grows
        self.changes: list[tuple[int, int, str]] = []
        #: Lines to print as they happen (changes flagged, ~/valid turning)
        self.events: list[str] = []
        #: Whether the simulator has published all its samples
        self.finished = False
        self.true_noise: np.ndarray | None = None
        self.noise_names: tuple[str, ...] = ()
        self.theta: np.ndarray | None = None
        self.uncompensated: np.ndarray | None = None
        self.noise: np.ndarray | None = None
        self.history: list[tuple[int, np.ndarray]] = []
        self.history_uncompensated: list[tuple[int, np.ndarray]] = []
        self.diagnostics: dict[str, str] = {}
        self.level = 0
        self.update_us = ''
        self.last_estimate_time = 0.0
        self._identifier_status = interface.status_name(identifier)
        latched = (
            (interface.PARAMETERS, identifier, self.on_parameters),
            (interface.PARAMETERS_UNCOMPENSATED, identifier, self.on_uncompensated),
            (interface.NOISE_VARIANCE, identifier, self.on_noise),
            (interface.TRUE_PARAMETERS, simulator, self.on_truth),
            (interface.TRUE_NOISE_VARIANCE, simulator, self.on_true_noise))
        self.subscriptions = [
            node.create_subscription(Float64MultiArray, interface.resolve(topic, owner),
                                     callback, LATCHED_QOS)
            for topic, owner, callback in latched]
        valid = interface.resolve(interface.VALID, identifier)
        self.subscriptions += [
            node.create_subscription(DiagnosticArray, interface.DIAGNOSTICS,
                                     self.on_diagnostics, 10),
            node.create_subscription(Bool, valid, self.on_valid, LATCHED_QOS),
        ]
        #: The samples, taken once the identifier is discovered (the simulator waits for them)
        self.samples_subscription = AfterDiscovery(node, valid, lambda: node.create_subscription(
            Float64MultiArray, interface.resolve(interface.SAMPLES, identifier),
            self.on_samples, SAMPLES_QOS))

    def on_samples(self, message: Any) -> None:
        """Count samples (a frame's first dimension is its sample count)."""
        dims = message.layout.dim
        self.samples += dims[0].size if len(dims) == 2 else 1

    def on_parameters(self, message: Any) -> None:
        """Keep the compensated estimate and its trajectory."""
        from bcid_ros.identifier.layouts import parse_names_label

        self.names = parse_names_label(message.layout.dim[0].label)
        self.theta = np.array(message.data)
        self.history.append((self.samples, self.theta))
        self.last_estimate_time = time.monotonic()

    def on_uncompensated(self, message: Any) -> None:
        """Keep the uncompensated estimate and its trajectory."""
        self.uncompensated = np.array(message.data)
        self.history_uncompensated.append((self.samples, self.uncompensated))

    def on_noise(self, message: Any) -> None:
        """Keep the noise estimate."""
        self.noise = np.array(message.data)

    def on_truth(self, message: Any) -> None:
        """Keep the true parameters, and when they took effect (a plant change)."""
        self.truth = np.array(message.data)
        self.truths.append((self.samples, self.truth))
        if len(self.truths) > 1:
            self.events.append(f'sample {self.samples}: the plant changed (simulator)')

    def on_valid(self, message: Any) -> None:
        """Keep ~/valid's trajectory; note a turn after the first."""
        valid = bool(message.data)
        if self.valid and self.valid[-1][1] != valid:
            after = ' (after the last sample: no samples for stale_after)' if self.finished \
                else ''
            self.events.append(f'sample {self.samples}: ~/valid {str(valid).lower()}{after}')
        self.valid.append((self.samples, valid))

    def on_true_noise(self, message: Any) -> None:
        """Keep the true noise figures and their names."""
        from bcid_ros.identifier.layouts import parse_names_label

        self.true_noise = np.array(message.data)
        self.noise_names = parse_names_label(message.layout.dim[0].label)

    def on_diagnostics(self, message: Any) -> None:
        """Keep the identifier's latest diagnostic values."""
        for status in message.status:
            if status.name == self._identifier_status:
                self.level = int.from_bytes(status.level, 'little') \
                    if isinstance(status.level, bytes) else int(status.level)
                self.diagnostics = {kv.key: kv.value for kv in status.values}
                self.diagnostics['message'] = status.message
                self._note_change()
                if self.diagnostics.get(Key.UPDATES, '0') != '0':
                    self.update_us = self.diagnostics.get(Key.UPDATE_MEAN_US, '')

    def _note_change(self) -> None:
        """Note a growth of the identifier's plant-change count, with its reason if given."""
        count = int(self.diagnostics.get(Key.FLAG + CHANGE_FLAG, '0') or 0)
        if count > (self.changes[-1][1] if self.changes else 0):
            reason = self.diagnostics.get(Key.NOT_VALID_BECAUSE, '')
            self.changes.append((self.samples, count, reason))
            said = f': not valid because {reason}' if 'plant changed' in reason else ''
            self.events.append(f'sample {self.samples}: the identifier flagged a plant change '
                               f'(count {count}){said}')

    def truth_at(self, samples: int) -> np.ndarray | None:
        """Return the truth in effect when ``samples`` had been received (None before any)."""
        current = None
        for since, truth in self.truths:
            if since > samples:
                break
            current = truth
        return current if current is not None or not self.truths else self.truths[0][1]

    def delta(self, theta: np.ndarray | None, truth: np.ndarray | None = None) -> float:
        """Return delta of an estimate against ``truth`` (default the latest; NaN if missing)."""
        truth = self.truth if truth is None else truth
        if theta is None or truth is None or theta.shape != truth.shape:
            return float('nan')
        return float(relative_error(theta, truth))


def live_line(monitor: Monitor, total: int, elapsed: float) -> str:
    """Return one status line: samples, delta, sigma^2 and the estimate."""
    parts = [f'{elapsed:5.1f} s', f'samples {monitor.samples:6d}/{total}']
    used = monitor.diagnostics.get(Key.SAMPLES_USED)
    if used is not None:  # the identifier's own count, at its last diagnostics
        parts.append(f'used {used}')
    if monitor.theta is None:
        parts.append('waiting for the first valid estimate')
    else:
        parts.append(f'delta {100 * monitor.delta(monitor.theta):6.2f} %')
        if monitor.noise is not None and monitor.noise.size:
            parts.append(f'sigma2^ {monitor.noise[0]:.4g}')
        parts.append('theta^ [' + ' '.join(f'{v:+.3f}' for v in monitor.theta) + ']')
    return '  '.join(parts)


def summary(monitor: Monitor) -> str:
    """Return the final table: estimate and uncompensated estimate against the truth."""
    from bcid_ros.markdown import markdown_table

    rows = []
    for k, name in enumerate(monitor.names):
        true = monitor.truth[k] if monitor.truth is not None else float('nan')
        unc = monitor.uncompensated[k] if monitor.uncompensated is not None else float('nan')
        rows.append([name, f'{true:.4f}', f'{monitor.theta[k]:.4f}', f'{unc:.4f}'])
    rows.append(['delta (%)', '0', f'{100 * monitor.delta(monitor.theta):.3f}',
                 f'{100 * monitor.delta(monitor.uncompensated):.3f}'])
    if monitor.noise is not None and monitor.true_noise is not None:
        for k, name in enumerate(monitor.noise_names[:monitor.noise.size]):
            if k < monitor.true_noise.size:
                rows.append([name, f'{monitor.true_noise[k]:.4g}', f'{monitor.noise[k]:.4g}',
                             ''])
    return markdown_table(['parameter', 'true', 'estimate', 'uncompensated'], rows)


def plot(monitor: Monitor, scenario: str, path: Path) -> None:
    """
    Write the PNG of delta(t) and the parameter trajectories, and ~/valid when it turned.

    Each estimate is compared with the truth in effect when it came; a plant
    change is a dotted vertical line in every panel, and the truth a dashed
    step.
    """
    from bcid_ros.reproduction.common import pyplot

    plt = pyplot()
    with_valid = len(monitor.truths) > 1 or scenario == PAYLOAD_CHANGE
    fig, axes = plt.subplots(3 if with_valid else 2, 1, figsize=(8, 9 if with_valid else 7),
                             sharex=True)
    top, bottom = axes[0], axes[1]
    samples = np.array([s for s, _ in monitor.history])
    theta = np.array([t for _, t in monitor.history])
    if monitor.truth is not None:
        deltas = [monitor.delta(t, monitor.truth_at(s)) for s, t in monitor.history]
        top.semilogy(samples, 100 * np.array(deltas), label='~/parameters')
        if monitor.history_uncompensated:
            unc_samples = np.array([s for s, _ in monitor.history_uncompensated])
            unc = [monitor.delta(t, monitor.truth_at(s))
                   for s, t in monitor.history_uncompensated]
            # the LS (or IV) estimate before compensation; rpem's: its fit's ARX least squares
            top.semilogy(unc_samples, 100 * np.array(unc), label='~/parameters_uncompensated',
                         alpha=0.7)
        top.legend()
    top.set_ylabel('delta (%)')
    top.set_title(f'bcid demo: {scenario}')
    top.grid(True, which='both', alpha=0.3)
    end = max(monitor.samples, int(samples[-1]) if samples.size else 0)
    for k, name in enumerate(monitor.names):
        line, = bottom.plot(samples, theta[:, k], label=name)
        if monitor.truths:
            steps = [s for s, _ in monitor.truths] + [end]
            values = [t[k] if t.size > k else np.nan for _, t in monitor.truths]
            bottom.step(steps, values + values[-1:], where='post', color=line.get_color(),
                        linestyle='--', linewidth=0.8)
    bottom.set_ylabel('estimate (dashed: truth)')
    bottom.legend(ncol=min(len(monitor.names), 4), fontsize='small')
    bottom.grid(True, alpha=0.3)
    if with_valid:
        valid = axes[2]
        if monitor.valid:
            steps = [s for s, _ in monitor.valid] + [end]
            values = [float(v) for _, v in monitor.valid]
            valid.step(steps, values + values[-1:], where='post')
        valid.set_yticks([0.0, 1.0], ['false', 'true'])
        valid.set_ylabel('~/valid')
        valid.grid(True, alpha=0.3)
    for axis in axes:
        for since, _ in monitor.truths[1:]:
            axis.axvline(since, color='k', linestyle=':', linewidth=1.0)
    axes[-1].set_xlabel('samples received (dotted: the plant changed)')
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def change_summary(monitor: Monitor) -> str:
    """Return a line on the plant changes: when they came, were flagged, and ~/valid's turns."""
    changed = [since for since, _ in monitor.truths[1:]]
    flagged = [since for since, _, _ in monitor.changes]
    turns = ', '.join(f'{str(v).lower()} at {s}' for s, v in monitor.valid[1:]) or 'none'
    return (f'plant changed at sample {changed or "-"}; change flagged by sample {flagged or "-"} '
            "(the identifier's diagnostics, once a second); ~/valid turned: " + turns)


def _one_decimal(text: str) -> str:
    """Return a diagnostic number with one decimal, or '?' if there is none."""
    try:
        return f'{float(text):.1f}'
    except (TypeError, ValueError):
        return '?'


def run(args: argparse.Namespace) -> int:
    """Run ``bcid demo``; return the exit code."""
    samples, rate, frame = DEMO_DEFAULTS[args.scenario]
    samples = args.samples or samples
    rate = args.rate or rate
    if samples < 0 or rate < 0:
        raise BcidError('--samples and --rate must be positive')
    config = config_file(args.scenario)
    simulator_overrides = []
    if args.scenario == PAYLOAD_CHANGE:
        simulator_overrides = ['-p', f'change_after_samples:={samples // 2}']
    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    from rclpy.executors import ExternalShutdownException

    try:
        with demo_graph() as (node, executor, children):
            monitor = Monitor(node, interface.IDENTIFIER_NODE, interface.SIMULATOR_NODE)
            print(f'bcid demo: {args.scenario}, {samples} samples at {rate:g} Hz '
                  f'({frame} per message), config {config}, ROS_DOMAIN_ID='
                  f'{os.environ.get("ROS_DOMAIN_ID", "0")}', flush=True)
            params = ['--ros-args', '--params-file', str(config)]
            children.append(Child('identifier_node', executable('identifier_node') + params,
                                  out_dir / 'identifier.log'))
            # The simulator waits for two subscribers on /samples: the identifier and this monitor.
            children.append(Child('simulator_node', executable('simulator_node') + params + [
                '-p', f'num_samples:={samples}', '-p', f'rate_hz:={float(rate)}',
                '-p', f'frame_size:={frame}', '-p', 'wait_for_subscribers:=2',
                '-p', 'start_delay:=0.3'] + simulator_overrides, out_dir / 'simulator.log'))
            identifier, simulator = children
            start = time.monotonic()
            next_line = start + 1.0
            finished_at = None
            while True:
                executor.spin_once(timeout_sec=0.05)
                monitor.samples_subscription.poll()
                now = time.monotonic()
                code = identifier.poll()
                if code is not None:
                    raise BcidError(f'identifier_node exited with code {code}:\n'
                                    f'{identifier.tail()}')
                code = simulator.poll()
                if code is not None and code != 0:
                    raise BcidError(f'simulator_node exited with code {code}:\n{simulator.tail()}')
                if monitor.samples == 0 and now - start > START_TIMEOUT:
                    raise BcidError(f'no samples after {START_TIMEOUT:.0f} s'
                                    f'{monitor.samples_subscription.note()}; simulator log:\n'
                                    f'{simulator.tail()}\nidentifier log:\n{identifier.tail()}')
                for line in monitor.events:
                    print(line, flush=True)
                monitor.events.clear()
                if now >= next_line:
                    print(live_line(monitor, samples, now - start), flush=True)
                    next_line += 1.0
                monitor.finished = monitor.samples >= samples
                if code == 0 and finished_at is None:
                    finished_at = now
                if finished_at is not None:
                    used = int(monitor.diagnostics.get(Key.SAMPLES_USED, '0') or 0)
                    lost = int(monitor.diagnostics.get(COUNTERS['lost'], '0') or 0)
                    settled = used + lost * frame >= samples and \
                        now - monitor.last_estimate_time > 0.3
                    if settled or now - finished_at > SETTLE_TIMEOUT:
                        break
            wall = time.monotonic() - start
    except (KeyboardInterrupt, ExternalShutdownException):
        print('bcid demo: interrupted', file=sys.stderr)
        return 130

    if monitor.theta is None:
        raise BcidError('the identifier published no valid estimate; see '
                        f'{out_dir / "identifier.log"}')
    print(live_line(monitor, samples, wall))
    print()
    print(summary(monitor))
    diag = monitor.diagnostics
    print(f'identifier: {diag.get(Key.SAMPLES_USED, "?")} samples used, '
          f'{diag.get(Key.SAMPLES_DROPPED, "?")} dropped, {diag.get(Key.BAD_SAMPLES, "?")} bad; '
          f'update time mean {_one_decimal(monitor.update_us)} µs (while running)')
    if len(monitor.truths) > 1 or monitor.changes:
        print(change_summary(monitor))
    png = out_dir / f'demo_{args.scenario}.png'
    plot(monitor, args.scenario, png)
    print(f'wall time {wall:.1f} s; final delta {100 * monitor.delta(monitor.theta):.3f} %; '
          f'wrote {png}')
    return 0
