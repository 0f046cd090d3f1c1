"""
The parameter-spec machinery: one declared parameter, its checks, and parameter files.

A :class:`ParameterSpec` says everything about one ROS parameter: type,
default, description, allowed values or range, and whether it may change
while a node runs. The tables built from it (the identifier's and the
simulator's in :mod:`bcid_ros.identifier.parameters`, the estimators' options in the
estimator registry) declare the nodes' ROS parameters, check values offline
and online with the same messages, and generate the docs' tables. Pure
Python, no ROS, and nothing above it in the package but its Markdown
table writer (:mod:`bcid_ros.markdown`): every layer may use it.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from bcid_ros.markdown import markdown_table as table_of

#: Parameter types, named as the ROS parameter types they become.
TYPES = ('bool', 'integer', 'double', 'string', 'double_array', 'string_array',
         'integer_array')

#: Parameters every ROS node has; accepted in parameter files and ignored by the checks.
ROS_BUILTIN = ('use_sim_time', 'start_type_description_service')


@dataclasses.dataclass(frozen=True)
class ParameterSpec:
    """
    One node parameter: its type, default and allowed values.

    Attributes
    ----------
    name : str
        The ROS parameter name.
    type : str
        One of :data:`TYPES`.
    default : object
        The default value; ``None`` means not set (the estimator's default).
    description : str
        One sentence for ``ros2 param describe`` and the docs.
    choices : tuple of str
        Allowed values of a string parameter (empty: any string).
    low, high : float or None
        Inclusive range of a number (or of every element of a double array).
    low_open : bool
        Whether ``low`` itself is excluded.
    read_only : bool
        Whether the parameter is fixed after start-up.

    """

    name: str
    type: str
    default: Any
    description: str
    choices: tuple[str, ...] = ()
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    read_only: bool = True

    def allowed(self) -> str:
        """Return the allowed values in words, for messages and descriptors."""
        if self.choices:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        if self.type == 'bool':
            return 'true or false'
        if self.low is not None or self.high is not None:
            kind = {'integer': 'an integer', 'double': 'a number',
                    'double_array': 'a list of numbers',
                    'integer_array': 'a list of integers'}.get(self.type, self.type)
            each = ' each' if self.type.endswith('_array') else ''
            return f'{kind}{each} in {self._range()}'
        return {'integer': 'an integer', 'double': 'a finite number',
                'double_array': 'a list of numbers', 'string_array': 'a list of strings',
                'string': 'a string'}[self.type]

    def check(self, value: Any) -> Any:
        """
        Return ``value`` converted to this parameter's type, or raise ValueError.

        Raises
        ------
        ValueError
            If the value has the wrong type or is out of range; the message
            names the parameter, the allowed values and the value given.

        """
        if value is None:
            if self.default is None:
                return None
            raise ValueError(self._message(value))
        converted = self._convert(value)
        if converted is None:
            raise ValueError(self._message(value))
        numbers = ([converted] if self.type in ('integer', 'double')
                   else converted if self.type in ('double_array', 'integer_array') else [])
        for number in numbers:
            if not math.isfinite(number) or not self._in_range(number):
                raise ValueError(self._message(value))
        if self.choices and converted not in self.choices:
            raise ValueError(self._message(value))
        return converted

    def check_argument(self, value: Any) -> Any:
        """
        Return a keyword argument of an estimator for this number parameter, or raise ValueError.

        The constructors' form of :meth:`check`: any value ``int()`` or
        ``float()`` takes (numpy scalars too) is converted, then held to the
        same range; the message names the argument, the range and the value
        (``order must be an integer in [1, 64], got 0``).
        """
        if self.type == 'integer':
            if isinstance(value, bool) or int(value) != value or not self._in_range(value):
                raise ValueError(f'{self.name} must be an integer in {self._range()}, '
                                 f'got {value!r}')
            return int(value)
        number = float(value)
        if not math.isfinite(number) or not self._in_range(number):
            raise ValueError(f'{self.name} must be in {self._range()}, got {number!r}')
        return number

    def _range(self) -> str:
        low = '-inf' if self.low is None else f'{self.low:g}'
        high = 'inf' if self.high is None else f'{self.high:g}'
        return f'{"(" if self.low_open else "["}{low}, {high}]'

    def _convert(self, value: Any) -> Any:
        if self.type == 'bool':
            return value if isinstance(value, bool) else None
        if self.type == 'integer':
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return None
            return int(value) if float(value).is_integer() else None
        if self.type == 'double':
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            return float(value) if ok else None
        if self.type == 'string':
            return value if isinstance(value, str) else None
        if self.type == 'integer_array' and isinstance(value, int) and \
                not isinstance(value, bool):
            return [value]  # one integer for all inputs
        if not isinstance(value, (list, tuple)) and not hasattr(value, 'tolist'):
            return None
        items = list(value.tolist() if hasattr(value, 'tolist') else value)
        if self.type == 'double_array':
            if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in items):
                return None
            return [float(v) for v in items]
        if self.type == 'integer_array':
            if any(isinstance(v, bool) or not isinstance(v, (int, float))
                   or not float(v).is_integer() for v in items):
                return None
            return [int(v) for v in items]
        if any(not isinstance(v, str) for v in items):
            return None
        return items

    def _in_range(self, number: float) -> bool:
        if self.low is not None and (number <= self.low if self.low_open else number < self.low):
            return False
        return self.high is None or number <= self.high

    def _message(self, value: Any) -> str:
        return f'parameter {self.name!r} must be {self.allowed()}, got {value!r}'


def parameter(name: str, type_: str, default: Any, description: str,
              **kwargs: Any) -> ParameterSpec:
    """Return a :class:`ParameterSpec` (the tables' short form)."""
    return ParameterSpec(name, type_, default, description, **kwargs)


def spec_by_name(table: tuple[ParameterSpec, ...]) -> dict[str, ParameterSpec]:
    """Return ``{name: spec}`` of a parameter table."""
    return {spec.name: spec for spec in table}


def markdown_table(table: tuple[ParameterSpec, ...]) -> str:
    """Return a parameter table as the Markdown table of docs/nodes.md."""
    rows = [(f'`{spec.name}`', spec.type,
             'estimator default' if spec.default is None else spec.default, spec.allowed(),
             'no' if spec.read_only else 'yes', spec.description) for spec in table]
    return table_of(('parameter', 'type', 'default', 'allowed', 'live', 'description'),
                    rows).rstrip('\n')


def check_parameters(values: dict[str, Any],
                     table: tuple[ParameterSpec, ...]) -> dict[str, Any]:
    """
    Check values against a parameter table and fill in the defaults.

    Raises
    ------
    ValueError
        For an unknown parameter name or a value that is not allowed; the
        message names the parameter and its allowed values.

    """
    specs = spec_by_name(table)
    unknown = sorted(set(values) - set(specs) - set(ROS_BUILTIN))
    if unknown:
        raise ValueError(f'unknown parameter {unknown[0]!r}; known parameters: '
                         f'{", ".join(specs)}')
    return {name: spec.check(values.get(name, spec.default)) for name, spec in specs.items()}


def _flatten(tree: dict[str, Any], prefix: str = '') -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            flat.update(_flatten(value, name + '.'))
        else:
            flat[name] = value
    return flat


def _section_kind(key: object, node_name: str) -> str:
    """
    Return whether a parameter file's top-level key applies to ``node_name``.

    ``'wildcard'`` for a key that applies to every node (``/**``, ``/ns/*``),
    ``'own'`` for one that names the node (``node``, ``/node``, ``/ns/node``,
    ``/**/node``), ``''`` for any other; the namespace is not known offline,
    so every namespace matches, as the shipped configs intend.
    """
    last = str(key).rstrip('/').rsplit('/', 1)[-1]
    if last in ('**', '*'):
        return 'wildcard'
    return 'own' if last == node_name else ''


def load_yaml_parameters(path: str | Path, node_name: str = 'bcid_identifier',
                         declared: Any = None) -> dict[str, Any]:
    """
    Read the parameters of one node from a ROS 2 parameter YAML file.

    Every section whose key applies to the node is read in file order, later
    values overriding earlier ones, as rcl does: the wildcard ``/**:`` (every
    node, any namespace; the shipped configs put the identifier's parameters
    there), then e.g. ``/**/bcid_simulator:`` (that node name in any
    namespace). The old form ``<node_name>:`` (or ``/<node_name>:``, or
    ``/namespace/<node_name>:``) is read too. Nested keys are flattened with
    dots, as ROS does.

    Parameters
    ----------
    path : str or pathlib.Path
        The YAML file.
    node_name : str
        The node whose sections to read.
    declared : collection of str, optional
        The node's parameter names. When given, a wildcard section's values
        that the node does not declare are left out, as a ROS node never sees
        them (the simulator's and the controller's readers pass their tables,
        since the wildcard section holds the identifier's parameters); names
        in the node's own sections are all returned, for the caller's check
        to refuse the unknown ones.

    Returns
    -------
    dict
        ``{parameter name: value}`` as written in the file.

    Raises
    ------
    ValueError
        If the file is not a parameter file or has no section for the node.

    """
    import yaml

    text = Path(path).read_text()
    loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)  # libyaml's, where it was built
    try:
        document = yaml.load(text, Loader=loader)
    except yaml.YAMLError as error:
        raise ValueError(f'{path}: not valid YAML: {error}') from None
    if not isinstance(document, dict):
        raise ValueError(f'{path}: not a ROS 2 parameter file (expected a mapping)')
    values: dict[str, Any] = {}
    found = False
    for key, section in document.items():
        kind = _section_kind(key, node_name)
        if not kind:
            continue
        if not isinstance(section, dict) or 'ros__parameters' not in section:
            raise ValueError(f'{path}: section {key!r} has no ros__parameters')
        parameters = section['ros__parameters'] or {}
        if not isinstance(parameters, dict):
            raise ValueError(f'{path}: {key}: ros__parameters must be a mapping')
        flat = _flatten(parameters)
        if kind == 'wildcard' and declared is not None:
            flat = {name: value for name, value in flat.items()
                    if name in declared or name in ROS_BUILTIN}
        values.update(flat)
        found = True
    if not found:
        raise ValueError(f'{path}: no section for node {node_name!r} '
                         f'(expected "/**: ros__parameters:" or '
                         f'"/**/{node_name}: ros__parameters:")')
    return values


__all__ = ['ParameterSpec', 'ROS_BUILTIN', 'TYPES', 'check_parameters', 'load_yaml_parameters',
           'markdown_table', 'parameter', 'spec_by_name']
