"""
identifier_node throughput, latency, CPU and memory, with the node in its own process.

A benchmark process publishes Ding MISO samples (bcrls, publishing every sample) at a fixed
rate for a fixed time and reads the node's `samples used` and `lost` counters from
`/diagnostics`; loss is what was sent minus what the node used. Latency is a ping-pong: one
sample out, wait for the estimate it produces, against a bare rclpy echo node (subscribe,
republish) measured in the same run. CPU per sample comes from the node's /proc stat, memory
from its VmRSS.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

import numpy as np

from benchmarks.common import Result
from bcid_ros.identifier.interface import DiagnosticKey

SECTION = 'node throughput and latency'
ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / 'config' / 'ding_miso.yaml'
ECHO = Path(__file__).resolve().parent / 'echo_node.py'
CLOCK_TICK = os.sysconf('SC_CLK_TCK')


def cpu_seconds(pid: int, thread: int | None = None) -> float:
    """Return user + system CPU seconds of process ``pid`` (or of its thread ``thread``)."""
    path = f'/proc/{pid}/stat' if thread is None else f'/proc/{pid}/task/{thread}/stat'
    fields = Path(path).read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICK


def rss_mb(pid: int) -> float:
    """Return the resident set size of process ``pid`` in MB."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


class Bench:
    """The benchmark's own ROS node: sample publisher, estimate and diagnostics listener."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import Float64MultiArray

        from bcid_ros.identifier import interface
        from bcid_ros.nodes.common import LATCHED_QOS, SAMPLES_QOS

        self.rclpy = rclpy
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('bcid_bench', context=self.context)
        self.samples = self.node.create_publisher(Float64MultiArray, interface.SAMPLES,
                                                  SAMPLES_QOS)
        self._status_name = interface.status_name(interface.IDENTIFIER_NODE)
        self.counters: dict[str, float] = {}
        self.arrived = threading.Event()
        self.node.create_subscription(DiagnosticArray, interface.DIAGNOSTICS,
                                      self._on_diagnostics, 10)
        self.node.create_subscription(
            Float64MultiArray, interface.resolve(interface.PARAMETERS, interface.IDENTIFIER_NODE),
            lambda _: self.arrived.set(), LATCHED_QOS)
        self.node.create_subscription(Float64MultiArray, 'echo',
                                      lambda _: self.arrived.set(), SAMPLES_QOS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # shutdown while spinning
            pass

    def _on_diagnostics(self, message) -> None:
        for status in message.status:
            if status.name == self._status_name:
                for pair in status.values:
                    try:
                        self.counters[pair.key] = float(pair.value)
                    except ValueError:
                        pass

    def wait_for_subscriber(self, timeout: float = 20.0) -> None:
        """Block until something subscribes to samples."""
        deadline = time.monotonic() + timeout
        while self.samples.get_subscription_count() < 1:
            if time.monotonic() > deadline:
                raise RuntimeError('no subscriber on /samples')
            time.sleep(0.05)
        time.sleep(0.5)

    def message(self, rows: np.ndarray):
        """Return a samples message of one sample or a frame (docs/nodes.md)."""
        from bcid_ros.nodes.messages import samples_message

        return samples_message(rows)

    def publish_at_rate(self, rows: np.ndarray, frame: int, rate: float,
                        seconds: float) -> int:
        """Publish frames of ``frame`` samples at ``rate`` samples/s; return samples sent."""
        rows = rows[:int(rate * seconds) + frame]  # what the time allows, no more to build
        starts = range(0, len(rows) - frame + 1, frame)
        frames = [self.message(rows[k:k + frame]) for k in starts]
        per_second = rate / frame
        start = time.perf_counter()
        sent = 0
        while True:
            elapsed = time.perf_counter() - start
            if elapsed >= seconds or sent >= len(frames):
                break
            due = min(int(elapsed * per_second) + 1, len(frames))
            while sent < due:
                self.samples.publish(frames[sent])
                sent += 1
            time.sleep(0.0005)
        return sent * frame

    def used(self, settle: float = 3.0) -> float:
        """Wait until `samples used` stops changing (diagnostics are 1 Hz) and return it."""
        last, stable_since = None, time.monotonic()
        while time.monotonic() - stable_since < settle:
            value = self.counters.get(DiagnosticKey.SAMPLES_USED)
            if value != last:
                last, stable_since = value, time.monotonic()
            time.sleep(0.1)
        return last or 0.0

    def ping(self, rows: np.ndarray, count: int) -> np.ndarray:
        """Return round-trip times (us) of ``count`` one-sample pings."""
        times = []
        for k in range(count):
            message = self.message(rows[k:k + 1])
            self.arrived.clear()
            start = time.perf_counter_ns()
            self.samples.publish(message)
            if not self.arrived.wait(2.0):
                continue
            times.append(time.perf_counter_ns() - start)
        return np.array(times) / 1000.0

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self.executor.shutdown()
        self.thread.join(5.0)
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def start(command: list[str]) -> subprocess.Popen:
    """Start a process quietly in its own process group."""
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


def stop(process: subprocess.Popen) -> None:
    """SIGINT, then kill if it does not exit."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def identifier(publish_period: int = 1) -> subprocess.Popen:
    """Start identifier_node with the Ding MISO config."""
    binary = str(Path(sys.executable).parent / 'identifier_node')
    return start([binary, '--ros-args', '--params-file', str(CONFIG),
                  '-p', f'publish_period:={publish_period}'])


def max_rate(bench: Bench, rows: np.ndarray, frame: int, rates: list[float],
             seconds: float) -> tuple[list[Result], float]:
    """Try ``rates`` in order on fresh nodes; return rows and the highest rate with no loss."""
    results, best = [], 0.0
    for rate in rates:
        node = identifier()
        try:
            bench.counters.clear()
            bench.wait_for_subscriber()
            cpu_before = cpu_seconds(node.pid)
            # the main thread runs the executor and every callback: it is what saturates
            thread_before = cpu_seconds(node.pid, node.pid)
            sent = bench.publish_at_rate(rows, frame, rate, seconds)
            used = bench.used()
            cpu = cpu_seconds(node.pid) - cpu_before
            thread = cpu_seconds(node.pid, node.pid) - thread_before
        finally:
            stop(node)
        loss = sent - used
        per_sample = thread / max(used, 1)
        results.append(Result(SECTION, f'{rate:,.0f} samples/s, frames of {frame}, '
                              f'{seconds:.0f} s', loss, 'samples lost',
                              note=f'sent {sent:,}, used {used:,.0f}; node CPU '
                              f'{cpu / max(used, 1) * 1e6:.1f} µs/sample, of it the main '
                              f'thread {per_sample * 1e6:.1f} ({per_sample * rate:.0%} of a '
                              'core at this rate)'))
        if loss == 0:
            best = rate
        else:
            break
    return results, best


def run(quick: bool = False) -> list[Result]:
    """Measure throughput (single samples and frames), latency, CPU and memory growth."""
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))
    from bcid_ros.simulation import make_scenario

    y, u = make_scenario('ding_miso').simulate(3_100_000 if not quick else 600_000, 3)
    rows = np.column_stack([y, u])
    seconds = 3.0 if quick else 10.0
    bench = Bench()
    results: list[Result] = []
    try:
        single, best_single = max_rate(bench, rows, 1,
                                       [1000, 2000, 3000, 4000, 5000, 6000], seconds)
        results += single
        results.append(Result(SECTION, 'highest zero-loss rate, one sample per message',
                              best_single, 'samples/s', '≥ 2,000', best_single >= 2000))
        framed, best_framed = max_rate(bench, rows, 50, FRAME_RATES, seconds)
        results += framed
        results.append(Result(SECTION, 'highest zero-loss rate, frames of 50', best_framed,
                              'samples/s', '≥ 50,000', best_framed >= 50000))
        # The margin: the queue (1,000 messages, 1 s of frames at this rate) hides a node
        # slightly too slow for a 10 s run, so the target rate again, for a minute.
        held, _ = max_rate(bench, rows, 50, [50000], 10.0 if quick else 60.0)
        results.append(dataclasses.replace(held[0], metric='margin: ' + held[0].metric))
        results.append(frame_callback_capacity(bench, rows, 50, 400 if quick else 2000))
        results += latency(bench, rows, 100 if quick else 1000)
        results += memory(bench, rows, 200_000 if quick else 1_000_000)
    finally:
        bench.close()
    results += joints(quick)
    return results


#: The frames ladder (samples/s); it stops at the first rate with a loss.
FRAME_RATES = [20000, 30000, 40000, 50000, 60000, 80000, 100000]


def frame_callback_capacity(bench: Bench, rows: np.ndarray, frame: int,
                            frames: int) -> Result:
    """
    Return the CPU cost of identifier_node's samples callback per sample, for frames.

    An IdentifierNode in this process (Ding MISO, bcrls, publishing after
    every frame) takes ``frames`` deserialised frames straight into its
    callback, without the transport: the CPU time of the callback (decode,
    feed, publish) bounds the node's rate on one free core, which a loaded
    machine does not show in the ladder above.
    """
    from rclpy.parameter import Parameter
    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import Float64MultiArray

    from bcid_ros.identifier.parameters import load_yaml_parameters
    from bcid_ros.nodes.identifier_node import IdentifierNode

    values = load_yaml_parameters(CONFIG)
    # In a namespace of its own, so that the benchmark's node does not hear its estimates.
    node = IdentifierNode(context=bench.context, namespace='capacity_probe',
                          parameter_overrides=[Parameter(name, value=value)
                                               for name, value in values.items()])
    messages = [deserialize_message(serialize_message(bench.message(
        rows[k * frame:(k + 1) * frame])), Float64MultiArray) for k in range(frames)]
    try:
        start = time.thread_time()  # this thread only: the benchmark's executor spins too
        for k, message in enumerate(messages):
            node.on_samples(message, {'publication_sequence_number': k + 1})
        cpu = time.thread_time() - start
    finally:
        node.destroy_node()
    samples = frames * frame
    per_sample = cpu / samples * 1e6
    bare, fed = callback_parts(values, rows[:samples], messages)
    return Result(SECTION, f'samples callback CPU, frames of {frame} (in process, no '
                  'transport)', per_sample, 'µs/sample',
                  note=f'{1e6 / per_sample:,.0f} samples/s on one free core; '
                  f'{samples:,} samples; of it, same run: bare update {bare:.1f}, '
                  f'SampleFeeder.take_message {fed:.1f} µs/sample (decode, checks, updates, '
                  'the due estimates read); the rest is the covariance and the publications')


def callback_parts(values: dict, rows: np.ndarray, messages: list) -> tuple[float, float]:
    """
    Return the CPU µs a sample of a bare update loop and of SampleFeeder over ``messages``.

    The parts of the samples callback, measured in this thread: the bare
    ``update`` loop over ``rows`` and ``SampleFeeder.take_message`` on
    each message (what the callback does before it publishes).
    """
    from bcid_ros.identifier.feeder import SampleFeeder
    from bcid_ros.identifier.parameters import (check_identifier_parameters,
                                                estimator_from_parameters)

    checked = check_identifier_parameters(values)
    update = estimator_from_parameters(checked).update
    outputs, inputs = rows[:, 0].tolist(), list(rows[:, 1:])
    start = time.thread_time()
    for k, value in enumerate(outputs):
        update(value, inputs[k])
    bare = time.thread_time() - start
    feeder = SampleFeeder(estimator_from_parameters(checked), checked['excitation_window'],
                          checked['publish_period'], checked['freeze_unexcited'])
    start = time.thread_time()
    for message in messages:
        feeder.take_message(message)
    fed = time.thread_time() - start
    return bare / len(outputs) * 1e6, fed / len(outputs) * 1e6


def latency(bench: Bench, rows: np.ndarray, count: int) -> list[Result]:
    """Ping-pong through identifier_node and through a bare echo node, same run."""
    results = []
    medians = {}
    for label, command in (
            ('bare rclpy echo node', [sys.executable, str(ECHO)]),
            ('identifier_node (bcrls, publish every sample)', None)):
        process = start(command) if command else identifier()
        try:
            bench.wait_for_subscriber()
            bench.ping(rows, 50)  # warm up: the regressor fills, the estimate gets valid
            times = bench.ping(rows[50:], count)
        finally:
            stop(process)
        medians[label] = float(np.median(times))
        results.append(Result(SECTION, f'round trip via {label}, median', medians[label], 'µs',
                              note=f'p99 {np.percentile(times, 99):.0f} µs over {len(times)}'))
    ratio = medians['identifier_node (bcrls, publish every sample)'] / medians[
        'bare rclpy echo node']
    results.append(Result(SECTION, 'latency median / bare echo median', ratio, '×', '≤ 1.3',
                          ratio <= 1.3))
    return results


def memory(bench: Bench, rows: np.ndarray, total: int) -> list[Result]:
    """Feed ``total`` samples in frames of 100; RSS growth from 10 % of them to the end."""
    node = identifier(publish_period=100)
    try:
        bench.counters.clear()
        bench.wait_for_subscriber()
        tenth = total // 10
        bench.publish_at_rate(rows[:tenth], 100, 40000, 1e9)
        bench.used()
        early = rss_mb(node.pid)
        bench.publish_at_rate(rows[tenth:total], 100, 40000, 1e9)
        used = bench.used()
        late = rss_mb(node.pid)
    finally:
        stop(node)
    growth = late - early
    return [Result(SECTION, f'RSS growth from {tenth:,} to {total:,} samples', growth, 'MB',
                   '< 5 MB', growth < 5.0,
                   note=f'{early:.1f} MB → {late:.1f} MB; node used {used:,.0f} samples')]


# ------------------------------------------------------------------ many joints
#: The joint_state cases: (joints, JointState messages per second), publishing every 10th.
JOINT_CASES = ((100, 100.0), (1000, 10.0))
JOINTS_PUBLISH_PERIOD = 10
#: Node CPU target of every joint_state case (cores).
JOINTS_CPU_TARGET = 0.5


class JointsBench:
    """The benchmark's node for the joint_state cases: JointState publisher, diagnostics."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import JointState

        from bcid_ros.identifier import interface
        from bcid_ros.identifier.joint_feeder import JOINT_STATES
        from bcid_ros.nodes.common import SAMPLES_QOS

        self.rclpy = rclpy
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('bcid_joints_bench', context=self.context)
        self.joint_states = self.node.create_publisher(JointState, JOINT_STATES, SAMPLES_QOS)
        self._status_name = interface.status_name(interface.IDENTIFIER_NODE)
        self.counters: dict[str, float] = {}
        self.statuses = 0
        self.node.create_subscription(DiagnosticArray, interface.DIAGNOSTICS,
                                      self._on_diagnostics, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # shutdown while spinning
            pass

    def _on_diagnostics(self, message) -> None:
        for status in message.status:
            if status.name == self._status_name:
                self.statuses = len(message.status)
                for pair in status.values:
                    try:
                        self.counters[pair.key] = float(pair.value)
                    except ValueError:
                        pass

    def wait_for_subscriber(self, timeout: float = 120.0) -> float:
        """Block until the identifier subscribes to joint_states; return the seconds waited."""
        start = time.monotonic()
        while self.joint_states.get_subscription_count() < 1:
            if time.monotonic() - start > timeout:
                raise RuntimeError('no subscriber on joint_states')
            time.sleep(0.05)
        return time.monotonic() - start

    def publish_at_rate(self, messages: list, rate: float) -> int:
        """Publish the messages at ``rate`` per second; return how many were sent."""
        start = time.perf_counter()
        sent = 0
        while sent < len(messages):
            due = min(int((time.perf_counter() - start) * rate) + 1, len(messages))
            while sent < due:
                self.joint_states.publish(messages[sent])
                sent += 1
            time.sleep(0.001)
        return sent

    def settled(self, key: str, settle: float = 3.0) -> float:
        """Wait until the diagnostic value ``key`` stops changing (1 Hz) and return it."""
        last, stable_since = None, time.monotonic()
        while time.monotonic() - stable_since < settle:
            value = self.counters.get(key)
            if value != last:
                last, stable_since = value, time.monotonic()
            time.sleep(0.1)
        return last or 0.0

    def estimates(self, joints: list[str], timeout: float = 60.0) -> dict[str, np.ndarray]:
        """Subscribe to every joint's latched estimate and return the latest of each."""
        from std_msgs.msg import Float64MultiArray

        from bcid_ros.identifier import interface
        from bcid_ros.identifier.joint_feeder import joint_topic
        from bcid_ros.nodes.common import LATCHED_QOS

        received: dict[str, np.ndarray] = {}
        subscriptions = []
        for joint in joints:
            topic = interface.resolve(joint_topic(joint, interface.PARAMETERS),
                                      interface.IDENTIFIER_NODE)
            subscriptions.append(self.node.create_subscription(
                Float64MultiArray, topic,
                lambda message, joint=joint: received.__setitem__(joint, np.array(message.data)),
                LATCHED_QOS))
        deadline = time.monotonic() + timeout
        while len(received) < len(joints) and time.monotonic() < deadline:
            time.sleep(0.1)
        for subscription in subscriptions:
            self.node.destroy_subscription(subscription)
        return received

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self.executor.shutdown()
        self.thread.join(5.0)
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def joints_identifier(joints: list[str], directory: Path) -> subprocess.Popen:
    """Start identifier_node in joint_state mode (bcrls, n = 2) for ``joints``."""
    import yaml

    path = directory / f'joints_{len(joints)}.yaml'
    path.write_text(yaml.safe_dump({'bcid_identifier': {'ros__parameters': {
        'estimator': 'bcrls', 'order': 2, 'input_mode': 'joint_state', 'joints': joints,
        'publish_period': JOINTS_PUBLISH_PERIOD}}}))
    binary = str(Path(sys.executable).parent / 'identifier_node')
    return start([binary, '--ros-args', '--params-file', str(path)])


def joint_state_messages(scenario, samples: int,
                         seed: int) -> tuple[list, np.ndarray, np.ndarray]:
    """Return one JointState per sample of the joints scenario, and its (y, u)."""
    from sensor_msgs.msg import JointState

    from bcid_ros.nodes.messages import as_doubles

    y, u = scenario.simulate(samples, seed)
    names = list(scenario.joint_names)
    messages = []
    for t in range(samples):
        message = JointState(name=names)
        message.velocity = as_doubles(y[t])
        message.effort = as_doubles(u[t])
        messages.append(message)
    return messages, y, u


def joints_case(bench: JointsBench, joints: int, rate: float, seconds: float,
                directory: Path) -> tuple[list[Result], float]:
    """Run one joint_state case; return its rows and the node's RSS after the run (MB)."""
    from bcid_ros.estimators import make_batched_estimator
    from bcid_ros.simulation import make_scenario

    samples = int(rate * seconds) // JOINTS_PUBLISH_PERIOD * JOINTS_PUBLISH_PERIOD
    scenario = make_scenario('joints', num_joints=joints, seed=11)
    messages, y, u = joint_state_messages(scenario, samples, 12)
    label = f'{joints:,} joints at {rate:g} Hz, every {JOINTS_PUBLISH_PERIOD}th published'
    deadline = time.monotonic() + 30.0
    while bench.joint_states.get_subscription_count() and time.monotonic() < deadline:
        time.sleep(0.1)  # the last case's node has left the graph
    node = joints_identifier(list(scenario.joint_names), directory)
    try:
        bench.counters.clear()
        startup = bench.wait_for_subscriber()
        time.sleep(2.0)  # discovery of the per-joint endpoints settles
        cpu_before = cpu_seconds(node.pid)
        start = time.perf_counter()
        sent = bench.publish_at_rate(messages, rate)
        elapsed = time.perf_counter() - start
        received = bench.settled(DiagnosticKey.MESSAGES)
        cpu = cpu_seconds(node.pid) - cpu_before
        lost = bench.counters.get('lost in transport (messages, by sequence number)', 0.0)
        statuses = bench.statuses
        rss = rss_mb(node.pid)
        estimates = bench.estimates(list(scenario.joint_names))
    finally:
        stop(node)
    # the node's estimates against the same samples run offline (the same code path: the
    # same bits), and both against the truth
    offline = make_batched_estimator('bcrls', joints, order=2)
    for t in range(samples):
        offline.update(y[t], u[t])
    truth = scenario.parameters
    scale = np.linalg.norm(truth, axis=1)
    node_theta = np.array([estimates.get(joint, np.full(4, np.nan))
                           for joint in scenario.joint_names])
    delta_node = np.linalg.norm(node_theta - truth, axis=1) / scale
    delta_single = np.linalg.norm(offline.theta - truth, axis=1) / scale
    complete = bool(np.all(delta_node <= delta_single + 1e-9)) and len(estimates) == joints
    cores = cpu / elapsed
    loss = sent - received
    return [
        Result(SECTION, f'{label}: messages lost', loss, 'messages', '0', loss == 0 and not lost,
               note=f'sent {sent:,} in {elapsed:.1f} s, node took {received:,.0f}; lost in '
               f'transport {lost:.0f}; {statuses} statuses per /diagnostics message'),
        Result(SECTION, f'{label}: node CPU', cores, 'cores', f'≤ {JOINTS_CPU_TARGET}',
               cores <= JOINTS_CPU_TARGET,
               note=f'{cpu / max(received, 1) * 1e6:.0f} µs per message, '
               f'{cpu / max(received * joints, 1) * 1e6:.2f} µs per joint sample; start-up '
               f'(to the subscription) {startup:.1f} s'),
        Result(SECTION, f'{label}: joints with δ within the single-plant δ',
               joints if complete else 0, f'of {joints}', f'all {joints}', complete,
               note=f'δ median {np.nanmedian(delta_node):.3g}, max {np.nanmax(delta_node):.3g} '
               f'after {samples:,} samples; largest |δ node − δ single| '
               f'{np.nanmax(np.abs(delta_node - delta_single)):.2g}; estimates of '
               f'{len(estimates)} joints received'),
    ], rss


def joints_baseline_rss(bench: JointsBench, directory: Path) -> float:
    """Return the RSS (MB) of an identifier with one joint, after start-up."""
    node = joints_identifier(['joint_1'], directory)
    try:
        bench.wait_for_subscriber()
        time.sleep(2.0)
        return rss_mb(node.pid)
    finally:
        stop(node)


def joints_diagnostics_cost(count: int, repeats: int = 10) -> Result:
    """Time one 1 Hz /diagnostics message of ``count`` joints: compose and serialise."""
    from bcid_ros.estimators import make_batched_estimator
    from bcid_ros.identifier.cdr import DiagnosticArrayEncoder
    from bcid_ros.identifier.joint_feeder import JointFeeder
    from bcid_ros.nodes.joint_diagnostics import JointStatuses
    from bcid_ros.simulation import make_scenario

    scenario = make_scenario('joints', num_joints=count, seed=11)
    messages, _, _ = joint_state_messages(scenario, 50, 12)
    feeder = JointFeeder(scenario.joint_names, make_batched_estimator('bcrls', count, order=2))
    for message in messages:
        feeder.take(message)
    statuses = JointStatuses('bcid_identifier', feeder)
    encoder = DiagnosticArrayEncoder()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        encoder.encode((0, 0), statuses.statuses())
        times.append(time.perf_counter() - start)
    best = min(times)
    return Result(SECTION, f'{count:,} joints: one /diagnostics message (statuses composed '
                  'and serialised)', best * 1e3, 'ms',
                  note=f'{best * 100:.1f} % of a core at 1 Hz; best of {repeats}')


def joints(quick: bool = False) -> list[Result]:
    """Measure the joint_state cases: loss, node CPU, δ per joint, memory per joint."""
    import tempfile

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))
    seconds = 10.0 if quick else 60.0
    bench = JointsBench()
    results: list[Result] = []
    try:
        with tempfile.TemporaryDirectory() as directory:
            baseline = joints_baseline_rss(bench, Path(directory))
            for count, rate in JOINT_CASES:
                rows, rss = joints_case(bench, count, rate, seconds, Path(directory))
                results += rows
                results.append(Result(
                    SECTION, f'{count:,} joints: memory per joint', (rss - baseline) * 1024 /
                    (count - 1), 'KB', note=f'node RSS {rss:.0f} MB against {baseline:.0f} MB '
                    'with one joint, divided by the joints added'))
    finally:
        bench.close()
    results.append(joints_diagnostics_cost(JOINT_CASES[-1][0]))
    return results


def main(argv: list[str] | None = None) -> int:
    """Run the joint_state cases alone: ``python -m benchmarks.node joints [--quick]``."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument('part', choices=['joints'])
    parser.add_argument('--quick', action='store_true', help='10 s per case instead of 60 s')
    args = parser.parse_args(argv)
    for row in joints(quick=args.quick):
        print(' | '.join(row.cells()))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
