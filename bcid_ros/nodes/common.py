"""
What both nodes share: QoS profiles, parameter declaration from the tables, main().

The parameter tables live in :mod:`bcid_ros.identifier.parameters` (pure Python), so
the offline tools use the same names, defaults and ranges.
"""

from __future__ import annotations

import difflib
import sys
import time
from typing import Any, Callable, Sequence

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions, QoSPolicyKind

from bcid_ros.blas_threads import set_one_blas_thread
from bcid_ros.interrupts import handle_interrupts_in_finalizers, sigint_noted
from bcid_ros.parameter_spec import ParameterSpec

#: Sample topics: reliable and volatile, deep enough for bursts of 1 kHz data.
SAMPLES_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

#: The QoS policies of a sample subscription that ROS 2's standard override parameters
#: ``qos_overrides./<topic>.subscription.<policy>`` set (read-only, at start-up).
SAMPLES_QOS_POLICIES = (QoSPolicyKind.RELIABILITY, QoSPolicyKind.DURABILITY,
                        QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH)


def samples_qos() -> QoSProfile:
    """
    Return the QoS of a sample subscription: reliable, volatile, KEEP_ALL (a fresh profile).

    KEEP_ALL, unlike the publishers' KEEP_LAST 1000, makes the flow control
    end to end: a reliable publisher that keeps all too (``bcid play --rate
    0``) waits while the node is busy instead of having its samples
    overwritten in the node's queue; a KEEP_LAST or best-effort publisher
    loses the samples on its side, which the sequence numbers count. The
    depth (1000) applies when ``qos_overrides./<topic>.subscription.history``
    is ``keep_last``. rclpy writes the overrides into the profile, hence a
    fresh one per subscription.
    """
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=SAMPLES_QOS.depth,
                      reliability=SAMPLES_QOS.reliability, durability=SAMPLES_QOS.durability)


def samples_qos_overrides() -> QoSOverridingOptions:
    """Return the override options of a sample subscription (:data:`SAMPLES_QOS_POLICIES`)."""
    return QoSOverridingOptions(policy_kinds=SAMPLES_QOS_POLICIES)


def qos_override_names(resolved_topic: str) -> list[str]:
    """Return the override parameter names of a sample subscription to ``resolved_topic``."""
    return [f'qos_overrides.{resolved_topic}.subscription.{policy.name.lower()}'
            for policy in SAMPLES_QOS_POLICIES]


#: Estimate, validity and truth topics: latched, so late joiners get the last one.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: A samples callback goes on taking the messages already queued for at most this long
#: before it returns to the executor (see :func:`create_draining_subscription`).
DRAIN_SECONDS = 0.02


def create_draining_subscription(node: Node, message_type: type, topic: str,
                                 callback: Callable[[Any, dict], None],
                                 qos: QoSProfile, **options: Any) -> Any:
    """
    Subscribe ``callback(message, info)``; each call also takes the messages already waiting.

    rclpy's executor rebuilds its wait set and waits on it before every
    callback, which costs about 0.3 ms of the node's thread per message on a
    2-core machine with the identifier's dozen entities: a third of the thread
    at 1,000 frames/s. When messages are queued, the callback takes them too,
    in order and with their message info, until none is left or
    :data:`DRAIN_SECONDS` have passed; then timers, services and parameter
    changes get their turn as before. A node that keeps up never has a queue,
    and its callbacks go one by one as with a plain subscription. ``options``
    go to ``create_subscription`` (event callbacks, QoS overriding options).
    """
    subscription = None

    def take_waiting(message: Any, info: dict) -> None:
        callback(message, info)
        handle = subscription.handle
        deadline = time.perf_counter() + DRAIN_SECONDS
        while time.perf_counter() < deadline:
            with handle:
                taken = handle.take_message(message_type, False)
            if taken is None:
                return
            callback(*taken)

    subscription = node.create_subscription(message_type, topic, take_waiting, qos, **options)
    return subscription


_ROS_TYPES = {
    'bool': Parameter.Type.BOOL,
    'integer': Parameter.Type.INTEGER,
    'double': Parameter.Type.DOUBLE,
    'string': Parameter.Type.STRING,
    'double_array': Parameter.Type.DOUBLE_ARRAY,
    'string_array': Parameter.Type.STRING_ARRAY,
    'integer_array': Parameter.Type.INTEGER_ARRAY,
}

INT64_MAX = 2 ** 63 - 1


def descriptor(spec: ParameterSpec) -> ParameterDescriptor:
    """Return the ROS descriptor of a table entry: description, constraints, range, read_only."""
    result = ParameterDescriptor(description=spec.description,
                                 additional_constraints=spec.allowed(),
                                 read_only=spec.read_only)
    if spec.type == 'integer' and (spec.low is not None or spec.high is not None):
        low = -INT64_MAX if spec.low is None else int(spec.low)
        high = INT64_MAX if spec.high is None else int(min(spec.high, INT64_MAX))
        result.integer_range = [IntegerRange(from_value=low, to_value=high, step=0)]
    elif spec.type == 'double' and (spec.low is not None or spec.high is not None):
        low = -sys.float_info.max if spec.low is None else float(spec.low)
        high = sys.float_info.max if spec.high is None else float(spec.high)
        result.floating_point_range = [FloatingPointRange(from_value=low, to_value=high,
                                                          step=0.0)]
    return result


def _as_declared_type(spec: ParameterSpec, parameter: Parameter) -> Parameter:
    """Return ``parameter`` as the number type ``spec`` declares, where an integer was given."""
    # `rate_hz: 1000` in YAML, `-p rate_hz:=1000` or a live set of `1000` gives an
    # INTEGER, which rclpy refuses for a DOUBLE parameter; take it as the number it is.
    given = parameter.type_
    if spec.type == 'double' and given == Parameter.Type.INTEGER:
        return Parameter(spec.name, Parameter.Type.DOUBLE, float(parameter.value))
    if spec.type == 'double_array' and given == Parameter.Type.INTEGER_ARRAY:
        return Parameter(spec.name, Parameter.Type.DOUBLE_ARRAY,
                         [float(v) for v in parameter.value])
    if spec.type == 'integer_array' and given == Parameter.Type.INTEGER:
        # `input_delay: 3`: one integer for all inputs
        return Parameter(spec.name, Parameter.Type.INTEGER_ARRAY, [parameter.value])
    return parameter


def _coerce_integer_overrides(node: Node, table: Sequence[ParameterSpec]) -> None:
    overrides = getattr(node, '_parameter_overrides', None)
    if not isinstance(overrides, dict):
        return
    for spec in table:
        if spec.name in overrides:
            overrides[spec.name] = _as_declared_type(spec, overrides[spec.name])


def _coerce_live_integers(node: Node, table: Sequence[ParameterSpec]) -> None:
    """Take a live integer for a double parameter as at start-up (a pre-set callback)."""
    specs = {spec.name: spec for spec in table}

    def coerce(parameters: list[Parameter]) -> list[Parameter]:
        return [_as_declared_type(specs[p.name], p) if p.name in specs else p
                for p in parameters]
    node.add_pre_set_parameters_callback(coerce)


def declare_table(node: Node, table: Sequence[ParameterSpec]) -> dict[str, Any]:
    """
    Declare every parameter of a table on ``node`` and return their values.

    A parameter whose default is ``None`` (or an empty list) is declared
    statically typed without a value, and reads back as the default.

    Raises
    ------
    ValueError
        If an override has the wrong type or is out of the descriptor's
        range; the message names the parameter.

    """
    _coerce_integer_overrides(node, table)
    _coerce_live_integers(node, table)
    for spec in table:
        try:
            if spec.default is None or spec.default == []:
                node.declare_parameter(spec.name, _ROS_TYPES[spec.type], descriptor(spec))
            else:
                node.declare_parameter(spec.name, spec.default, descriptor(spec))
        except Exception as error:  # rclpy's InvalidParameter*Exception and TypeError
            raise ValueError(f'parameter {spec.name!r} must be {spec.allowed()}: '
                             f'{error}') from None
    return read_table(node, table)


def read_table(node: Node, table: Sequence[ParameterSpec]) -> dict[str, Any]:
    """Return the current values of a declared table (no value: the table's default)."""
    values = {}
    for spec in table:
        try:
            value = node.get_parameter(spec.name).value
        except ParameterUninitializedException:  # statically typed, declared without a value
            value = None
        if value is None:
            value = spec.default
        elif spec.type in ('double_array', 'string_array', 'integer_array'):
            value = list(value)
        values[spec.name] = value
    return values


def undeclared_overrides(node: Node, also_known: Sequence[str] = ()) -> list[tuple[str, str]]:
    """
    Return the parameters given to ``node`` (file or command line) that it does not declare.

    Each comes with the closest declared (or ``also_known``) name, or ``''``
    when none is close (difflib). ROS ignores such a parameter without a
    word; a typo such as ``forgeting_factor`` would leave the default in force.
    """
    overrides = getattr(node, '_parameter_overrides', None) or {}
    known = sorted(set(node._parameters) | set(also_known))
    result = []
    for name in sorted(overrides):
        if name in known:
            continue
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
        result.append((name, close[0] if close else ''))
    return result


def warn_undeclared(node: Node, also_known: Sequence[str] = ()) -> None:
    """Log one warning per parameter given to ``node`` that it does not declare."""
    for name, close in undeclared_overrides(node, also_known):
        hint = f'; did you mean {close!r}?' if close else ''
        node.get_logger().warning(f'parameter {name!r} is not a parameter of this node and is '
                                  f'ignored{hint}')


def make_parameter_check(specs: dict[str, ParameterSpec]
                         ) -> Callable[[list[Parameter]], SetParametersResult]:
    """Return an on-set-parameters callback that checks values against the table."""
    def check(parameters: list[Parameter]) -> SetParametersResult:
        for parameter in parameters:
            spec = specs.get(parameter.name)
            if spec is None:
                continue
            try:
                spec.check(parameter.value)
            except ValueError as error:
                return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)
    return check


class Throttle:
    """Log a warning at most once per ``period`` seconds per kind, with a repeat count."""

    def __init__(self, logger: Any, period: float = 5.0) -> None:
        self._logger = logger
        self._period = period
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, kind: str, text: str) -> None:
        """Log ``text`` unless a ``kind`` warning was logged less than a period ago."""
        now = time.monotonic()
        last = self._last.get(kind)
        if last is not None and now - last < self._period:
            self._suppressed[kind] = self._suppressed.get(kind, 0) + 1
            return
        suppressed = self._suppressed.pop(kind, 0)
        if suppressed:
            text += f' ({suppressed} more since the last such warning)'
        self._last[kind] = now
        self._logger.warning(text)


def usage(program: str, summary: str, table: Sequence[ParameterSpec]) -> str:
    """Return the ``--help`` text of a node: how to run it and every parameter."""
    lines = [f'usage: {program} [-h] [--ros-args [--params-file FILE] [-p NAME:=VALUE ...]]',
             '', summary, '', 'parameters (name: type = default; description; allowed):']
    for spec in table:
        default = 'estimator default' if spec.default is None else repr(spec.default)
        flags = ', read-only' if spec.read_only else ', live'
        lines.append(f'  {spec.name}: {spec.type} = {default}{flags}')
        lines.append(f'      {spec.description} Allowed: {spec.allowed()}.')
    return '\n'.join(lines)


def help_requested(argv: list[str] | None) -> bool:
    """Return whether -h/--help stands among the non-ROS arguments."""
    args = sys.argv[1:] if argv is None else argv
    if '--ros-args' in args:
        args = args[:args.index('--ros-args')]
    return '-h' in args or '--help' in args


def run_node(factory: Callable[..., Node], argv: list[str] | None, program: str,
             until: Callable[[Node], bool] | None = None, help_text: str = '') -> int:
    """
    Run a node: init, spin until shutdown (or ``until(node)``), clean up.

    Parameters
    ----------
    factory : callable
        Builds the node (after ``rclpy.init``).
    argv : list of str or None
        Command line (``None``: ``sys.argv``).
    program : str
        Name for error messages.
    until : callable, optional
        Stop spinning once this returns True.
    help_text : str
        Printed, without starting ROS, when ``-h`` or ``--help`` is given.

    Returns
    -------
    int
        0, or 2 if the node refused its parameters.

    """
    if help_requested(argv):
        print(help_text or f'usage: {program} [--ros-args ...]')
        return 0
    executor = node = None
    try:
        rclpy.init(args=argv if argv is not None else sys.argv)
    except KeyboardInterrupt:  # SIGINT while starting: stop quietly, as while spinning
        rclpy.try_shutdown()
        return 0
    try:
        # from here rclpy's signal handler shuts the context down on SIGINT; one raised
        # before (after entry_points loaded the node's modules) may have been swallowed
        if sigint_noted():
            return 0
        handle_interrupts_in_finalizers(deliver_again=False)
        executor = SingleThreadedExecutor()
        node = factory()
        # one BLAS thread (the libraries the node has loaded by now): its matrices are
        # small, and OpenBLAS's threads, waiting for each other on busy cores, made one
        # update take up to 38 ms of CPU instead of 7 (docs/nodes.md, "One BLAS thread")
        set_one_blas_thread()
        executor.add_node(node)
        if until is None:
            executor.spin()
        else:
            while rclpy.ok() and not until(node):
                executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except rclpy_implementation.RCLError:
        # SIGINT/SIGTERM can shut the context down between two waits of the
        # executor, which then fails to build its wait set: that is a shutdown too
        if rclpy.ok():
            raise
    except ValueError as error:
        print(f'{program}: error: {error}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            executor.remove_node(node)
            node.destroy_node()
        if executor is not None:
            executor.shutdown()
        rclpy.try_shutdown()
    return 0
