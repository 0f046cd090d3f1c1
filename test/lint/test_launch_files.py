"""
The launch files, checked by their structure: ``launch`` is not installed here, so none runs.

Each file under launch/ is parsed with ``ast`` (nothing of it is imported):
every node it starts must be an executable of setup.py's console_scripts in
this package, every package it names must be this one, every config file it
refers to must exist, and setup.py must install the files.
"""

import ast
from pathlib import Path
import re

import pytest

ROOT = Path(__file__).resolve().parents[2]
LAUNCH_FILES = sorted((ROOT / 'launch').glob('*.launch.py'))
PACKAGE = re.search(r'<name>(.+?)</name>', (ROOT / 'package.xml').read_text()).group(1)


def console_scripts():
    """Return the executable names that setup.py declares as console scripts (read with ast)."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == 'console_scripts':
                    return {ast.literal_eval(item).split('=')[0].strip() for item in value.elts}
    raise AssertionError('setup.py has no console_scripts')


def calls(tree, name):
    """Return the calls of ``name(...)`` in a tree, as {keyword: value or None}, with args."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == name:
            keywords = {k.arg: (k.value.value if isinstance(k.value, ast.Constant) else None)
                        for k in node.keywords}
            positional = [a.value if isinstance(a, ast.Constant) else None for a in node.args]
            found.append((positional, keywords))
    return found


def test_the_three_launch_files_ship():
    assert [p.name for p in LAUNCH_FILES] == ['adaptive_loop.launch.py', 'demo.launch.py',
                                              'identifier.launch.py']


@pytest.mark.parametrize('path', LAUNCH_FILES, ids=[p.name for p in LAUNCH_FILES])
def test_launch_file_names_what_exists(path):
    tree = ast.parse(path.read_text(), str(path))
    assert any(isinstance(n, ast.FunctionDef) and n.name == 'generate_launch_description'
               for n in tree.body)
    executables = console_scripts()
    nodes = calls(tree, 'Node') + calls(tree, 'LifecycleNode')
    assert nodes
    for _, keywords in nodes:
        assert keywords['package'] == PACKAGE
        assert keywords['executable'] in executables, keywords['executable']
        assert 'parameters' in keywords  # every node gets the parameter file
    for positional, _ in calls(tree, 'get_package_share_directory'):
        assert positional == [PACKAGE]
    # config paths: every '<name>.yaml' the file names, and the scenario argument's default
    yaml_names = {n.value for n in ast.walk(tree)
                  if isinstance(n, ast.Constant) and isinstance(n.value, str)
                  and n.value.endswith('.yaml') and not n.value.startswith('.')}
    arguments = {positional[0]: keywords.get('default_value')
                 for positional, keywords in calls(tree, 'DeclareLaunchArgument')}
    if 'scenario' in arguments:
        yaml_names.add(f'{arguments["scenario"]}.yaml')
    assert yaml_names or 'params_file' in arguments
    for name in yaml_names:
        assert (ROOT / 'config' / name).is_file(), name
    assert 'namespace' in arguments


def test_identifier_launch_takes_params_file_and_namespace():
    tree = ast.parse((ROOT / 'launch' / 'identifier.launch.py').read_text())
    arguments = {positional[0] for positional, _ in calls(tree, 'DeclareLaunchArgument')}
    assert {'params_file', 'namespace'} <= arguments


def test_setup_installs_the_launch_files():
    text = (ROOT / 'setup.py').read_text()
    assert "('share/' + package_name + '/launch', glob('launch/*.launch.py'))" in text


def test_no_launch_import_here():
    # the check above must not need launch: this module imports none of it
    source = Path(__file__).read_text()
    assert not re.search(r'^\s*(import|from)\s+launch', source, re.MULTILINE)
