"""
The nodes' ROS interface by name: nodes, topics, message types, diagnostic keys (no ROS).

Every name a user or a tool sees is defined here once: the node and topic
names, the type names written into bags, the table of the message types the
separate input and output topics take, and the keys of the identifier's
``/diagnostics`` values. The module imports nothing from ROS, so the offline
tools (``bcid replay``, ``bcid simulate``, the bag reader) share the names
with the nodes. The messages' layouts are :mod:`bcid_ros.identifier.layouts`'s,
the rclpy side (message classes, building messages) is
:mod:`bcid_ros.nodes.messages`; docs/nodes.md describes the interface.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

# ----------------------------------------------------------------- nodes and topics
#: Default node names.
IDENTIFIER_NODE = 'bcid_identifier'
SIMULATOR_NODE = 'bcid_simulator'
CONTROLLER_NODE = 'bcid_controller'

#: Inputs of the identifier (relative names, so that a namespace moves them).
SAMPLES = 'samples'
INPUT = 'input'
OUTPUT = 'output'
#: The one topic of ``input_mode: joint_state`` (sensor_msgs/JointState, relative).
JOINT_STATES = 'joint_states'
#: The adaptive controller's setpoint input (relative).
REFERENCE = 'reference'

#: The identifier's estimates, the validity flag and the reset service (private names).
PARAMETERS = '~/parameters'
PARAMETERS_UNCOMPENSATED = '~/parameters_uncompensated'
NOISE_VARIANCE = '~/noise_variance'
VALID = '~/valid'
PARAMETER_STD = '~/parameter_std'
PARAMETER_COVARIANCE = '~/parameter_covariance'
#: The estimate with the stamp of the last sample used (sensor_msgs/JointState, latched):
#: ``name`` the parameter names, ``position`` the values of ``~/parameters``.
PARAMETERS_STAMPED = '~/parameters_stamped'
#: The operating point [y0, u1, ..., ur] of ``detrend: mean`` (latched).
OPERATING_POINT = '~/operating_point'
RESET = '~/reset'

#: The adaptive controller's feedback C(q) in the loop (private, latched).
CONTROLLER = '~/controller'

#: The simulator's truth (private names).
TRUE_PARAMETERS = '~/true_parameters'
TRUE_NOISE_VARIANCE = '~/true_noise_variance'

DIAGNOSTICS = '/diagnostics'


def resolve(topic: str, node: str, namespace: str = '/') -> str:
    """
    Return the absolute name of ``topic`` as node ``node`` in ``namespace`` resolves it.

    >>> resolve(PARAMETERS, IDENTIFIER_NODE)
    '/bcid_identifier/parameters'
    >>> resolve(SAMPLES, IDENTIFIER_NODE)
    '/samples'
    """
    prefix = namespace.rstrip('/')
    if topic.startswith('/'):
        return topic
    if topic.startswith('~/'):
        return f'{prefix}/{node}/{topic[2:]}'
    return f'{prefix}/{topic}'


def basename(topic: str) -> str:
    """Return the last token of a topic name (``'~/true_parameters'``: ``'true_parameters'``)."""
    return topic.rsplit('/', 1)[-1]


# ------------------------------------------------------------------- message types
FLOAT64 = 'std_msgs/msg/Float64'
FLOAT64_MULTI_ARRAY = 'std_msgs/msg/Float64MultiArray'
JOINT_STATE = 'sensor_msgs/msg/JointState'
BOOL = 'std_msgs/msg/Bool'


def _float64_input(message: Any, count: int, field: str, joints: Sequence[str]) -> list[float]:
    return [message.data]


def _array_input(message: Any, count: int, field: str, joints: Sequence[str]) -> list[float]:
    values = list(message.data)
    if not values:
        raise ValueError('empty input message')
    if len(values) != count:
        raise ValueError(f'input has {len(values)} values; expected num_inputs = {count}')
    return values


def _joint_values(message: Any, field: str, joints: Sequence[str], count: int,
                  side: str) -> list[float]:
    values = list(getattr(message, field))
    if joints:
        names = list(message.name)
        try:
            return [values[names.index(joint)] for joint in joints]
        except (ValueError, IndexError):
            raise ValueError(f'{side} JointState lacks {field} of joints {list(joints)} '
                             f'(has {names})') from None
    if len(values) < count:
        raise ValueError(f'{side} JointState has {len(values)} {field} values; '
                         f'expected {count}')
    return values[:count]


def _joint_state_input(message: Any, count: int, field: str,
                       joints: Sequence[str]) -> list[float]:
    return _joint_values(message, field, joints, count, 'input')


def _float64_output(message: Any, field: str, joint: str) -> float:
    return message.data


def _joint_state_output(message: Any, field: str, joint: str) -> float:
    return _joint_values(message, field, [joint] if joint else [], 1, 'output')[0]


def _build_float64(cls: type, values: Sequence[float], names: Sequence[str], field: str,
                   stamp_ns: int) -> Any:
    return cls(data=float(values[0]))


def _build_array(cls: type, values: Sequence[float], names: Sequence[str], field: str,
                 stamp_ns: int) -> Any:
    return cls(data=[float(v) for v in values])


def _build_joint_state(cls: type, values: Sequence[float], names: Sequence[str], field: str,
                       stamp_ns: int) -> Any:
    message = cls(name=list(names))
    setattr(message, field, [float(v) for v in values])
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    return message


def stamp_ns(message: Any) -> int:
    """Return a stamped message's header stamp in integer nanoseconds."""
    stamp = message.header.stamp
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@dataclasses.dataclass(frozen=True)
class MessageType:
    """
    A message type of the separate ``input`` and ``output`` topics.

    Attributes
    ----------
    ros_type : str
        The full ROS type name, e.g. ``'sensor_msgs/msg/JointState'``.
    stamped : bool
        Whether it has a header stamp (``sync: stamp`` needs one on both topics).
    width : int or None
        Most values it carries (Float64: 1); None for any number.
    read_input : callable or None
        ``(message, num_inputs, field, joints) -> [u1, ..., ur]``; None if it
        cannot be an input. Raises ValueError for a message without them.
    read_output : callable or None
        ``(message, field, joint) -> y``; None if it cannot be an output.
    build : callable
        ``(cls, values, names, field, stamp_ns) -> message``, the simulator's
        message of ``values`` (names and field for JointState).

    """

    ros_type: str
    stamped: bool
    width: int | None
    read_input: Callable[..., list[float]] | None
    read_output: Callable[..., float] | None
    build: Callable[..., Any]


#: The separate topics' message types, by the value of ``input_type``/``output_type``.
#: Adding a type is one entry here (and, if it is stamped, nothing else).
MESSAGE_TYPES: dict[str, MessageType] = {
    'float64': MessageType(FLOAT64, False, 1, _float64_input, _float64_output,
                           _build_float64),
    'float64_multi_array': MessageType(FLOAT64_MULTI_ARRAY, False, None, _array_input, None,
                                       _build_array),
    'joint_state': MessageType(JOINT_STATE, True, None, _joint_state_input,
                               _joint_state_output, _build_joint_state),
}

#: ``input_type`` and ``output_type`` choices.
INPUT_TYPES = tuple(name for name, kind in MESSAGE_TYPES.items() if kind.read_input)
OUTPUT_TYPES = tuple(name for name, kind in MESSAGE_TYPES.items() if kind.read_output)


def reader(side: str, settings: dict[str, Any]) -> Callable[[Any], Any]:
    """
    Return the function that reads u or y from a message of the configured type.

    Parameters
    ----------
    side : str
        ``'input'`` (the function returns ``[u1, ..., ur]``) or ``'output'`` (y).
    settings : dict
        The identifier parameters: ``input_type``, ``num_inputs``,
        ``input_field`` and ``input_joints``, or ``output_type``,
        ``output_field`` and ``output_joint``.

    """
    kind = MESSAGE_TYPES[settings[f'{side}_type']]
    if side == 'input':
        count, field = settings['num_inputs'], settings['input_field']
        joints = list(settings['input_joints'])
        return lambda message: kind.read_input(message, count, field, joints)
    field, joint = settings['output_field'], settings['output_joint']
    return lambda message: kind.read_output(message, field, joint)


def check_input_width(input_type: str, num_inputs: int, parameter: str = 'input_type') -> None:
    """
    Check that ``input_type`` can carry ``num_inputs`` values.

    Raises
    ------
    ValueError
        Naming the parameter, the types that can and the value given.

    """
    width = MESSAGE_TYPES[input_type].width
    if width is not None and num_inputs > width:
        able = [name for name in INPUT_TYPES
                if (MESSAGE_TYPES[name].width or num_inputs) >= num_inputs]
        raise ValueError(f'parameter {parameter!r} must be one of {", ".join(able)} for '
                         f'{num_inputs} inputs, got {input_type!r}')


# ---------------------------------------------------------------- diagnostics
def fully_qualified(node: str, namespace: str = '/') -> str:
    """
    Return a node's fully qualified name (a name that starts with ``/`` already is one).

    >>> fully_qualified('bcid_identifier', '/robot1')
    '/robot1/bcid_identifier'
    """
    if node.startswith('/'):
        return node
    return f'{namespace.rstrip("/")}/{node}'


def status_name(node: str, namespace: str = '/') -> str:
    """
    Return the identifier's ``DiagnosticStatus.name``: its fully qualified name first.

    Two identifiers in two namespaces never share a status:

    >>> status_name('bcid_identifier', '/robot1')
    '/robot1/bcid_identifier: identifier'
    """
    return f'{fully_qualified(node, namespace)}: identifier'


class DiagnosticKey:
    """The keys of the identifier's ``/diagnostics`` values (docs/nodes.md lists them)."""

    ESTIMATOR = 'estimator'
    VALID = 'valid'
    NOT_VALID_BECAUSE = 'not valid because'
    SAMPLES_USED = 'samples used'
    SAMPLES_SINCE_RESET = 'samples since reset'
    SAMPLES_DROPPED = 'samples dropped'
    BAD_SAMPLES = 'bad samples'
    MESSAGES = 'messages received'
    ESTIMATES_PUBLISHED = 'estimates published'
    SAMPLE_RATE = 'sample rate (1/s)'
    UPDATES = 'updates in the last period'
    UPDATE_MEAN_US = 'update time mean (µs)'
    UPDATE_MAX_US = 'update time max (µs)'
    COVARIANCE_TRACE = 'covariance trace'
    FORGETTING_FACTOR = 'forgetting factor'
    PUBLISH_PERIOD = 'publish period (samples)'
    ADAPT = 'adapt'
    SAMPLES_HELD = 'samples held (adaptation off)'
    #: Staleness (``stale_after``): seconds since the last sample, and the limit in force.
    LAST_SAMPLE_AGE = 'seconds since the last sample'
    STALE_AFTER = 'stale after (s)'
    #: Prefix of ``incompatible QoS <topic>``: publishers refused for their QoS.
    INCOMPATIBLE_QOS = 'incompatible QoS '
    #: Prefixes of ``flag <name>`` (estimator flag counts) and ``noise <name>``.
    FLAG = 'flag '
    NOISE = 'noise '


#: The identifier's counters of bad or lost samples, with their diagnostic keys.
COUNTERS = {
    'nonfinite': 'bad samples: NaN or Inf',
    'bad_layout': 'bad messages: wrong length or layout',
    'empty': 'bad messages: empty',
    'duplicate': 'dropped: duplicated stamp',
    'out_of_order': 'dropped: stamp out of order',
    'unpaired': 'dropped: unpaired',
    'lost': 'lost in transport (messages, by sequence number)',
    'gaps': 'gaps in the stamps (regressor restarted)',
    'time_jumps': 'stamps that jumped back (pairing started over)',
    'unexcited': 'samples without excitation (input constant)',
    'estimator_errors': 'estimator errors',
    'nonfinite_estimates': 'non-finite estimates withheld',
}
#: Counters summed under ``samples dropped`` and ``bad samples``.
DROPPED = ('unpaired', 'lost', 'duplicate', 'out_of_order')
BAD = ('nonfinite', 'bad_layout', 'empty')
#: Counters that make the status ERROR (the estimator is failing).
FAILING = ('estimator_errors', 'nonfinite_estimates')


__all__ = ['BAD', 'BOOL', 'COUNTERS', 'DIAGNOSTICS', 'DROPPED', 'DiagnosticKey', 'FAILING',
           'FLOAT64', 'FLOAT64_MULTI_ARRAY', 'IDENTIFIER_NODE', 'INPUT',
           'INPUT_TYPES', 'JOINT_STATE', 'MESSAGE_TYPES', 'MessageType', 'NOISE_VARIANCE',
           'OUTPUT', 'OUTPUT_TYPES', 'PARAMETER_COVARIANCE', 'PARAMETER_STD', 'PARAMETERS',
           'PARAMETERS_STAMPED', 'PARAMETERS_UNCOMPENSATED', 'RESET',
           'SAMPLES', 'SIMULATOR_NODE', 'TRUE_NOISE_VARIANCE', 'TRUE_PARAMETERS', 'VALID',
           'basename', 'check_input_width', 'fully_qualified', 'reader', 'resolve',
           'stamp_ns', 'status_name']
