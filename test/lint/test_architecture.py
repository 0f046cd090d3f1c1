"""
The layers of bcid_ros (docs/architecture.md): imports only point down, and nothing cycles.

Every module's imports are read with ``ast`` (those inside functions too),
so a lazy import counts as much as one at the top. A package may import its
own modules and the packages of the layers below it, never one beside or
above it; the modules form no cycle; every module of ``bcid_ros/nodes/``
imports rclpy (the nodes are the rclpy adapters), and nothing in the layers
below ``bag`` imports rclpy or a ROS message package.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / 'bcid_ros'

#: The layers, lowest first. A package imports only from layers below its own.
LAYERS = (
    ('blas_threads', 'errors', 'interrupts', 'markdown', 'resources'),
    ('parameter_spec',),
    ('estimators',),
    ('simulation',),
    ('identifier',),
    ('bag', 'control', 'reproduction'),
    ('analysis',),
    ('nodes',),
    ('cli',),
    ('entry_points',),
)
LAYER_OF = {name: rank for rank, names in enumerate(LAYERS) for name in names}

#: The layers that run without ROS: no rclpy, no message package, not even lazily.
ROS_FREE = ('blas_threads', 'errors', 'interrupts', 'markdown', 'resources', 'parameter_spec',
            'estimators', 'simulation', 'identifier')
ROS_MODULES = ('rclpy', 'std_msgs', 'sensor_msgs', 'diagnostic_msgs', 'std_srvs',
               'builtin_interfaces', 'rosidl_runtime_py', 'rosbag2_py')


def module_files(root=PACKAGE):
    """Return ``{dotted module name: path}`` of every module below ``root``."""
    modules = {}
    for path in sorted(root.rglob('*.py')):
        parts = list(path.relative_to(root.parent).with_suffix('').parts)
        if parts[-1] == '__init__':
            parts.pop()
        modules['.'.join(parts)] = path
    return modules


def imports_of(module, path):
    """Return ``[(line, imported dotted name)]`` of every import in a module, nested ones too."""
    found = []
    is_package = path.name == '__init__.py'
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parent = module.split('.')[:len(module.split('.')) - node.level + is_package]
                base = '.'.join(parent + ([node.module] if node.module else []))
            # ``from package import name``: the module package.name if there is one
            found += [(node.lineno, f'{base}.{alias.name}') for alias in node.names]
    return found


def resolve(name, modules):
    """Return the module of ``modules`` that a dotted import name lands in (or None)."""
    while name and name not in modules:
        name = name.rpartition('.')[0]
    return name or None


def package_of(module):
    """Return the top-level package or module of ``bcid_ros`` that ``module`` belongs to."""
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else None


def import_graph(modules):
    """
    Return ``{module: {imported module: first line}}`` within ``bcid_ros``.

    An import of a module's own enclosing package is left out: Python runs the
    package's ``__init__`` before the module anyway, so it is no arrow.
    """
    graph = {}
    for module, path in modules.items():
        edges = graph.setdefault(module, {})
        for line, name in imports_of(module, path):
            target = resolve(name, modules) if name.split('.')[0] == 'bcid_ros' else None
            if target and target != module and not module.startswith(target + '.'):
                edges.setdefault(target, line)
    return graph


def relative_path(module, path):
    """Return a module's file as the repository names it (``bcid_ros/nodes/demo.py``)."""
    return module.replace('.', '/') + ('/__init__.py' if path.name == '__init__.py' else '.py')


def layer_violations(graph, modules, layer_of=LAYER_OF):
    """Return one line per import that points sideways or up the layers, or from no layer."""
    found = []
    for module, edges in graph.items():
        source = package_of(module)
        for target, line in edges.items():
            goal = package_of(target)
            if source is None or goal is None or source == goal:
                continue
            where = f'{relative_path(module, modules[module])}:{line}'
            if source not in layer_of or goal not in layer_of:
                unknown = source if source not in layer_of else goal
                found.append(f'{where}: {module} imports {target}, and {unknown!r} is in '
                             'no layer of LAYERS')
            elif layer_of[goal] >= layer_of[source]:
                way = 'beside' if layer_of[goal] == layer_of[source] else 'above'
                found.append(f'{where}: {module} imports {target}: {goal!r} stands {way} '
                             f'{source!r}')
    return found


def cycles(graph):
    """Return the import cycles of ``graph``, each a sorted list of modules (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph.get(node, ()):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def imports_ros(module, path):
    """Return the ROS modules (rclpy, message packages) a module imports, anywhere in it."""
    return sorted({name.split('.')[0] for _, name in imports_of(module, path)
                   if name.split('.')[0] in ROS_MODULES})


MODULES = module_files()
GRAPH = import_graph(MODULES)


@pytest.mark.linter
def test_every_package_has_a_layer():
    packages = {package_of(module) for module in MODULES} - {None}
    assert packages <= set(LAYER_OF), f'packages in no layer: {sorted(packages - set(LAYER_OF))}'


@pytest.mark.linter
def test_imports_point_only_down():
    found = layer_violations(GRAPH, MODULES)
    assert not found, 'imports that do not point down the layers:\n' + '\n'.join(found)


@pytest.mark.linter
def test_no_import_cycle():
    found = cycles(GRAPH)
    assert not found, 'import cycles:\n' + '\n'.join(' <-> '.join(c) for c in found)


@pytest.mark.linter
def test_the_nodes_package_holds_rclpy_adapters_only():
    nodes = {m: p for m, p in MODULES.items() if m.startswith('bcid_ros.nodes.')}
    assert nodes
    without = [relative_path(m, p) for m, p in nodes.items()
               if 'rclpy' not in imports_ros(m, p)]
    assert not without, f'modules of nodes/ that do not import rclpy (move them down): {without}'


@pytest.mark.linter
def test_the_lower_layers_import_no_ros():
    found = [f'{relative_path(m, p)}: {imports_ros(m, p)}'
             for m, p in MODULES.items()
             if package_of(m) in ROS_FREE and imports_ros(m, p)]
    assert not found, 'ROS imports below bag:\n' + '\n'.join(found)


# ---------------------------------------------------------------- the checker itself
def _tree(tmp_path, files):
    root = tmp_path / 'bcid_ros'
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return module_files(root)


def test_the_checker_names_an_upward_import_inside_a_function(tmp_path):
    modules = _tree(tmp_path, {
        '__init__.py': '',
        'estimators/__init__.py': '',
        'estimators/rls.py': 'def f():\n    from bcid_ros.nodes.common import X\n',
        'nodes/__init__.py': '',
        'nodes/common.py': 'from bcid_ros.estimators import rls\nX = 1\n'})
    found = layer_violations(import_graph(modules), modules)
    assert found == ["bcid_ros/estimators/rls.py:2: bcid_ros.estimators.rls imports "
                     "bcid_ros.nodes.common: 'nodes' stands above 'estimators'"]
    assert cycles(import_graph(modules)) == [['bcid_ros.estimators.rls',
                                              'bcid_ros.nodes.common']]


def test_the_checker_resolves_relative_imports_and_ignores_the_own_package(tmp_path):
    modules = _tree(tmp_path, {
        '__init__.py': '',
        'bag/__init__.py': 'from .reader import read\n',
        'bag/reader.py': 'from . import writer\nfrom bcid_ros.bag import writer as w\n'
                         'def read():\n    from ..control import loop\n',
        'bag/writer.py': '',
        'control/__init__.py': '',
        'control/loop.py': ''})
    graph = import_graph(modules)
    assert graph['bcid_ros.bag.reader'] == {'bcid_ros.bag.writer': 1,
                                            'bcid_ros.control.loop': 4}
    found = layer_violations(graph, modules)
    assert found == ["bcid_ros/bag/reader.py:4: bcid_ros.bag.reader imports "
                     "bcid_ros.control.loop: 'control' stands beside 'bag'"]
    assert cycles(graph) == []
