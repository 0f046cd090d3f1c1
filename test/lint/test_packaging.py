"""The ament_python packaging: colcon builds it, and `ros2 run` finds its executables."""

from pathlib import Path
import shutil
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[2]
VENV_BIN = Path(sys.executable).parent


def source_files():
    """Return the files git tracks or would track (the clean-clone content)."""
    listing = subprocess.run(
        ['git', 'ls-files', '--cached', '--others', '--exclude-standard'], cwd=ROOT,
        capture_output=True, text=True, check=True).stdout.split()
    return [name for name in listing if (ROOT / name).is_file()]


@pytest.fixture(scope='module')
def workspace(tmp_path_factory):
    colcon = shutil.which('colcon', path=str(VENV_BIN))
    if colcon is None:
        pytest.fail('colcon is not installed in the test venv (requirements-dev.txt)')
    ws = tmp_path_factory.mktemp('ws')
    for name in source_files():
        target = ws / 'src' / 'bcid_ros' / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, target)
    result = subprocess.run([colcon, 'build', '--base-paths', 'src'], cwd=ws,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    return ws


def run_in_workspace(ws, command):
    """Run ``command`` in bash after sourcing the workspace, as a ROS user would."""
    script = f'. install/setup.sh && {command}'
    return subprocess.run(['bash', '-c', script], cwd=ws, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.slow
@pytest.mark.parametrize('executable', ['identifier_node', 'identifier_lifecycle_node',
                                        'simulator_node', 'bcid'])
def test_executables_are_where_ros2_run_looks(workspace, executable):
    path = workspace / 'install' / 'bcid_ros' / 'lib' / 'bcid_ros' / executable
    assert path.is_file()
    result = run_in_workspace(workspace, f'{path} --help')
    assert result.returncode == 0, result.stderr
    assert 'usage' in result.stdout.lower()


@pytest.mark.slow
def test_installed_package_is_the_one_imported_and_finds_its_config(workspace):
    result = run_in_workspace(
        workspace, 'python3 -c "import bcid_ros, bcid_ros.resources as r; '
        'print(bcid_ros.__file__); print(r.share_directory())"')
    assert result.returncode == 0, result.stderr
    module_file, share = result.stdout.split()
    install = workspace / 'install' / 'bcid_ros'
    assert Path(module_file).is_relative_to(install)
    assert Path(share) == install / 'share' / 'bcid_ros'
    installed = sorted(p.name for p in (Path(share) / 'config').glob('*.yaml'))
    assert installed == sorted(p.name for p in (ROOT / 'config').glob('*.yaml'))
    assert (Path(share) / 'package.xml').is_file()
    launch = sorted(p.name for p in (Path(share) / 'launch').glob('*.launch.py'))
    assert launch == sorted(p.name for p in (ROOT / 'launch').glob('*.launch.py'))
    assert len(launch) == 3
    marker = workspace / 'install' / 'bcid_ros' / 'share' / 'ament_index' / \
        'resource_index' / 'packages' / 'bcid_ros'
    assert marker.is_file()


def test_package_xml_declares_the_runtime_and_test_dependencies():
    text = (ROOT / 'package.xml').read_text()
    for dep in ('rclpy', 'std_msgs', 'std_srvs', 'sensor_msgs', 'diagnostic_msgs',
                'python3-numpy', 'python3-scipy'):
        assert f'<exec_depend>{dep}</exec_depend>' in text
    for dep in ('ament_flake8', 'ament_pep257', 'python3-pytest'):
        assert f'<test_depend>{dep}</test_depend>' in text
    assert '<build_type>ament_python</build_type>' in text


def test_setup_does_not_force_the_pypi_ros_wheels():
    # On a ROS system rclpy comes from apt; pip must not pull the PyPI wheels over it.
    text = (ROOT / 'setup.py').read_text()
    assert "install_requires=['setuptools', 'numpy', 'scipy']," in text
    assert 'ros-jazzy' not in text


@pytest.mark.slow
def test_adaptive_controller_node_is_where_ros2_run_looks(workspace):
    path = workspace / 'install' / 'bcid_ros' / 'lib' / 'bcid_ros' / 'adaptive_controller_node'
    assert path.is_file()
    result = run_in_workspace(workspace, f'{path} --help')
    assert result.returncode == 0, result.stderr
    assert 'closed_loop_poles' in result.stdout
    installed = workspace / 'install' / 'bcid_ros' / 'share' / 'bcid_ros' / 'config'
    assert (installed / 'adaptive_loop.yaml').is_file()


#: requirements.txt name -> the package.xml keys that provide it on a ROS system.
REQUIREMENT_KEYS = {
    'ros-jazzy-rclpy': ['rclpy'],
    'ros-jazzy-common-interfaces': ['std_msgs', 'std_srvs', 'sensor_msgs', 'diagnostic_msgs'],
    'numpy': ['python3-numpy'],
    'scipy': ['python3-scipy'],
    'mcap': ['python3-mcap-pip'],
    'mcap-ros2-support': ['python3-mcap-ros2-support-pip'],
    'rosbags': ['python3-rosbags-pip'],
    'matplotlib': ['python3-matplotlib'],
    'pyyaml': ['python3-yaml'],
}

#: Imported modules that are ROS packages (their own rosdep keys).
ROS_PACKAGES = ('rclpy', 'std_msgs', 'std_srvs', 'sensor_msgs', 'diagnostic_msgs',
                'lifecycle_msgs', 'builtin_interfaces', 'rcl_interfaces', 'rosgraph_msgs',
                'ament_index_python', 'launch', 'launch_ros')


def exec_depends():
    """Return the exec_depend keys of package.xml."""
    import re

    return set(re.findall(r'<exec_depend>([^<]+)</exec_depend>',
                          (ROOT / 'package.xml').read_text()))


def test_every_requirement_has_an_exec_depend():
    import re

    declared = exec_depends()
    for line in (ROOT / 'requirements.txt').read_text().splitlines():
        line = line.split('#')[0].strip()
        if not line:
            continue
        name = re.split(r'[\[<>=!~ ]', line, maxsplit=1)[0].lower()
        assert name in REQUIREMENT_KEYS, f'requirements.txt: {name} has no package.xml key here'
        missing = set(REQUIREMENT_KEYS[name]) - declared
        assert not missing, f'{name}: package.xml lacks exec_depend {sorted(missing)}'


def test_every_imported_ros_package_has_an_exec_depend():
    import ast

    declared = exec_depends()
    imported = set()
    for path in list((ROOT / 'bcid_ros').rglob('*.py')) + list((ROOT / 'launch').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name.split('.')[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                imported.add(node.module.split('.')[0])
    missing = sorted((imported & set(ROS_PACKAGES)) - declared)
    assert not missing, f'imported without an exec_depend: {missing}'


def test_the_pip_keys_are_defined_in_the_shipped_rosdep_file():
    import yaml

    defined = yaml.safe_load((ROOT / 'rosdep.yaml').read_text())
    for key in sorted(k for k in exec_depends() if k.endswith('-pip')):
        assert defined[key]['ubuntu']['pip']['packages'], key
