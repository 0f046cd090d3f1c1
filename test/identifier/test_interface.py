"""
The nodes' interface by name: topic names, the message type table and the parameter table.

The readers are duck-typed and run without ROS; building real messages with
the table's builders needs the rclpy message packages.
"""

from pathlib import Path
import subprocess
import sys
from types import SimpleNamespace

import pytest

from bcid_ros.estimators.registry import ESTIMATOR_NAMES
from bcid_ros.identifier import interface
from bcid_ros.identifier.interface import (check_input_width, INPUT_TYPES, MESSAGE_TYPES,
                                           OUTPUT_TYPES, resolve)
from bcid_ros.identifier.parameters import (check_identifier_parameters, IDENTIFIER_PARAMETERS,
                                            markdown_table, SIMULATOR_PARAMETERS, spec_by_name)


def test_names_resolve_as_ros_resolves_them():
    assert resolve(interface.PARAMETERS, 'bcid_identifier') == '/bcid_identifier/parameters'
    assert resolve(interface.SAMPLES, 'bcid_identifier') == '/samples'
    assert resolve(interface.SAMPLES, 'x', '/robot1') == '/robot1/samples'
    assert resolve(interface.VALID, 'x', '/robot1/') == '/robot1/x/valid'
    assert resolve(interface.DIAGNOSTICS, 'x', '/robot1') == '/diagnostics'
    assert interface.basename(interface.TRUE_PARAMETERS) == 'true_parameters'


def test_parameter_choices_come_from_the_tables():
    identifier = spec_by_name(IDENTIFIER_PARAMETERS)
    simulator = spec_by_name(SIMULATOR_PARAMETERS)
    assert identifier['estimator'].choices == ESTIMATOR_NAMES
    assert identifier['input_type'].choices == INPUT_TYPES == simulator['input_type'].choices
    assert identifier['output_type'].choices == OUTPUT_TYPES == simulator['output_type'].choices
    assert set(INPUT_TYPES) | set(OUTPUT_TYPES) == set(MESSAGE_TYPES)


def test_stamp_pairing_needs_stamped_types_on_both_topics():
    values = {'input_mode': 'separate', 'sync': 'stamp', 'input_type': 'joint_state'}
    with pytest.raises(ValueError, match=r"'output_type' must be a stamped type \(one of "
                                         r"joint_state\).*got 'float64'"):
        check_identifier_parameters(values)
    check_identifier_parameters(dict(values, output_type='joint_state'))


def test_float64_carries_one_input():
    check_input_width('float64', 1)
    check_input_width('float64_multi_array', 5)
    with pytest.raises(ValueError, match=r"'input_type' must be one of float64_multi_array, "
                                         r"joint_state for 2 inputs, got 'float64'"):
        check_identifier_parameters({'input_mode': 'separate', 'num_inputs': 2})


def joint_state(**fields):
    """Return a duck-typed JointState."""
    return SimpleNamespace(**{'name': [], 'position': [], 'velocity': [], 'effort': [],
                              **fields})


def test_readers():
    float64 = MESSAGE_TYPES['float64']
    array = MESSAGE_TYPES['float64_multi_array']
    joints = MESSAGE_TYPES['joint_state']
    assert float64.read_input(SimpleNamespace(data=2.5), 1, 'effort', []) == [2.5]
    assert float64.read_output(SimpleNamespace(data=2.5), 'position', '') == 2.5
    assert array.read_input(SimpleNamespace(data=[1.0, 2.0]), 2, 'effort', []) == [1.0, 2.0]
    with pytest.raises(ValueError, match='input has 3 values; expected num_inputs = 2'):
        array.read_input(SimpleNamespace(data=[1.0, 2.0, 3.0]), 2, 'effort', [])
    with pytest.raises(ValueError, match='empty'):
        array.read_input(SimpleNamespace(data=[]), 2, 'effort', [])
    message = joint_state(name=['a', 'b', 'c'], effort=[1.0, 2.0, 3.0], position=[7.0, 8.0])
    assert joints.read_input(message, 2, 'effort', []) == [1.0, 2.0]
    assert joints.read_input(message, 2, 'effort', ['c', 'a']) == [3.0, 1.0]
    assert joints.read_output(message, 'position', 'b') == 8.0
    assert joints.read_output(message, 'position', '') == 7.0
    with pytest.raises(ValueError, match=r"input JointState lacks effort of joints \['d'\]"):
        joints.read_input(message, 1, 'effort', ['d'])
    with pytest.raises(ValueError, match='output JointState lacks position of joints'):
        joints.read_output(message, 'position', 'c')     # c has no position
    with pytest.raises(ValueError, match='input JointState has 3 effort values; expected 4'):
        joints.read_input(message, 4, 'effort', [])
    assert float64.read_output is not None and array.read_output is None
    settings = {'input_type': 'joint_state', 'num_inputs': 2, 'input_field': 'effort',
                'input_joints': ['c', 'b'], 'output_type': 'joint_state',
                'output_field': 'position', 'output_joint': 'b'}
    assert interface.reader('input', settings)(message) == [3.0, 2.0]
    assert interface.reader('output', settings)(message) == 8.0


def test_builders_make_real_messages_the_readers_read_back():
    pytest.importorskip('rclpy')
    from bcid_ros.nodes.messages import estimate_message, topic_class

    for name in INPUT_TYPES:
        kind = MESSAGE_TYPES[name]
        values = [0.5] if kind.width == 1 else [0.5, -1.5]
        message = kind.build(topic_class(name), values, ['u1', 'u2'][:len(values)], 'effort',
                             3_000_000_123)
        assert kind.read_input(message, len(values), 'effort', []) == values
        if kind.stamped:
            assert interface.stamp_ns(message) == 3_000_000_123
    for name in OUTPUT_TYPES:
        kind = MESSAGE_TYPES[name]
        message = kind.build(topic_class(name), [4.25], ['y'], 'position', 0)
        assert kind.read_output(message, 'position', '') == 4.25
    message = estimate_message(('a1', 'b1_1'), [1.0, 2.0])
    assert message.layout.dim[0].label == 'a1,b1_1' and list(message.data) == [1.0, 2.0]


def test_the_offline_modules_do_not_import_rclpy():
    code = ('import sys\n'
            'import bcid_ros.identifier.interface, bcid_ros.identifier.pairing\n'
            'import bcid_ros.bag.replay, bcid_ros.bag.simulate, bcid_ros.identifier.parameters\n'
            'assert "rclpy" not in sys.modules\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr


def test_docs_parameter_tables_are_the_tables():
    docs = (Path(__file__).resolve().parents[2] / 'docs' / 'nodes.md').read_text()
    for table in (IDENTIFIER_PARAMETERS, SIMULATOR_PARAMETERS):
        assert markdown_table(table) in docs


def test_every_list_of_estimators_derives_from_the_registry():
    from bcid_ros.estimators.registry import batched_class, entry, names_where, REGISTRY

    assert names_where(input_modes='joint_state') == ('rls', 'bcrls')
    assert names_where(model='arx') == ('rls',)
    assert set(names_where(open_loop=True)) <= set(REGISTRY)
    for name, item in REGISTRY.items():
        assert item.model in ('arx', 'output_error', 'errors_in_variables', 'closed_loop')
        # the loader gives the class that says it is this estimator
        assert make_estimator_class_name(name) == item.single().__name__
        assert item.single().name == name
        assert set(item.option_names) <= set(spec.name for spec in IDENTIFIER_PARAMETERS)
    assert batched_class('bcrls').__name__ == 'BatchedBcrls'
    with pytest.raises(ValueError, match="one of rls, bcrls for many plants; got 'bciv'"):
        batched_class('bciv')
    with pytest.raises(ValueError, match="estimator must be one of rls, bcrls, bciv, cl_bcls"):
        entry('kalman')


def make_estimator_class_name(name):
    """Return the class name of the registered single-plant estimator ``name``."""
    from bcid_ros.estimators import estimator_class

    return estimator_class(name).__name__


def test_a_dead_time_is_refused_where_the_registry_says_the_model_has_none():
    from bcid_ros.estimators.registry import REGISTRY

    refusing = [name for name, item in REGISTRY.items() if not item.supports_delay]
    assert refusing  # cl_bcls: its closed-loop model has no dead time
    for name in REGISTRY:
        values = {'estimator': name, 'order': 1, 'input_delay': [2]}
        if name in refusing:
            with pytest.raises(ValueError, match=f"'input_delay' must be 0 with estimator "
                                                 f"'{name}'"):
                check_identifier_parameters(values)
        else:
            assert check_identifier_parameters(values)['input_delay'] == [2]


def test_a_controller_topic_is_refused_where_the_registry_says_none_is_taken():
    from bcid_ros.estimators.registry import REGISTRY

    for name, item in REGISTRY.items():
        values = {'estimator': name, 'order': 1, 'controller_topic': '/controller'}
        if item.takes_controller:
            assert check_identifier_parameters(values)['controller_topic'] == '/controller'
        else:
            with pytest.raises(ValueError, match="'controller_topic' applies to estimator "
                                                 "cl_bcls only"):
                check_identifier_parameters(values)
