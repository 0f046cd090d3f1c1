"""
The shipped configs: the identifier's parameters under ``/**:``, read alike online and offline.

rcl applies a parameter file's sections in file order (a later one
overrides an earlier one), and ``-p name:=value`` joins the ``/**`` section.
The shipped files put the node sections (``/**/bcid_simulator:``, ...) first
and the identifier's ``/**:`` last, so that the command line overrides every
node's values; a name in ``/**`` that another node also declares must then
mean the same to it. The reader of ``bcid replay --params`` follows the same
rule, and still reads the old ``bcid_identifier:`` key.
"""

from pathlib import Path

import pytest
import yaml

from bcid_ros.control.parameters import check_controller_parameters, CONTROLLER_PARAMETERS
from bcid_ros.identifier.parameters import (check_identifier_parameters,
                                            check_simulator_parameters, SIMULATOR_PARAMETERS)
from bcid_ros.parameter_spec import load_yaml_parameters

CONFIGS = sorted((Path(__file__).resolve().parents[2] / 'config').glob('*.yaml'))

#: The other nodes a shipped file may configure, with their tables and checks.
OTHER_NODES = {
    'bcid_simulator': (SIMULATOR_PARAMETERS, check_simulator_parameters),
    'bcid_controller': (CONTROLLER_PARAMETERS, check_controller_parameters),
}


@pytest.mark.parametrize('path', CONFIGS, ids=[p.stem for p in CONFIGS])
def test_shipped_config_has_the_identifier_under_the_wildcard_last(path):
    document = yaml.safe_load(path.read_text())
    keys = list(document)
    assert keys[-1] == '/**', keys
    assert all(key.startswith('/**/') and key[4:] in OTHER_NODES for key in keys[:-1]), keys
    identifier = check_identifier_parameters(load_yaml_parameters(path))
    assert identifier == check_identifier_parameters(document['/**']['ros__parameters'])
    wildcard = document['/**']['ros__parameters']
    for key in keys[:-1]:
        node = key[4:]
        table, check = OTHER_NODES[node]
        declared = {spec.name for spec in table}
        own = document[key]['ros__parameters']
        values = check(load_yaml_parameters(path, node, declared))
        # a wildcard name the node declares means the same there: the same value as the
        # node's own section, or what it would use anyway
        for name in set(wildcard) & declared:
            assert own.get(name, wildcard[name]) == wildcard[name], (node, name)
            assert values[name] == wildcard[name]


def write(tmp_path, text):
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    return path


def test_reader_takes_the_old_key_and_follows_the_file_order(tmp_path):
    old = write(tmp_path, 'bcid_identifier:\n  ros__parameters:\n    order: 3\n')
    assert load_yaml_parameters(old) == {'order': 3}
    ordered = write(tmp_path, '/**:\n  ros__parameters:\n    order: 3\n    seed: 1\n'
                    '/**/bcid_identifier:\n  ros__parameters:\n    order: 4\n'
                    '/robot1/bcid_simulator:\n  ros__parameters:\n    seed: 2\n')
    assert load_yaml_parameters(ordered) == {'order': 4, 'seed': 1}
    # a wildcard's names the node does not declare are left out, as ROS leaves them
    assert load_yaml_parameters(ordered, 'bcid_simulator', {'seed'}) == {'seed': 2}
    reversed_ = write(tmp_path, '/**/bcid_identifier:\n  ros__parameters:\n    order: 4\n'
                      '/**:\n  ros__parameters:\n    order: 3\n')
    assert load_yaml_parameters(reversed_) == {'order': 3}


def test_reader_refuses_a_typo_and_a_file_without_a_section(tmp_path):
    typo = write(tmp_path, '/**:\n  ros__parameters:\n    forgeting_factor: 0.99\n')
    with pytest.raises(ValueError, match="unknown parameter 'forgeting_factor'"):
        check_identifier_parameters(load_yaml_parameters(typo))
    other = write(tmp_path, '/**/bcid_simulator:\n  ros__parameters:\n    seed: 1\n')
    with pytest.raises(ValueError, match='no section for node'):
        load_yaml_parameters(other)
