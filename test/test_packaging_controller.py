"""The controller node's executable is installed where `ros2 run` looks, like the others."""

import pytest

from test_packaging import run_in_workspace, workspace  # noqa: F401 (the fixture)


@pytest.mark.slow
def test_adaptive_controller_node_is_where_ros2_run_looks(workspace):  # noqa: F811
    path = workspace / 'install' / 'bcid_ros' / 'lib' / 'bcid_ros' / 'adaptive_controller_node'
    assert path.is_file()
    result = run_in_workspace(workspace, f'{path} --help')
    assert result.returncode == 0, result.stderr
    assert 'closed_loop_poles' in result.stdout
    installed = workspace / 'install' / 'bcid_ros' / 'share' / 'bcid_ros' / 'config'
    assert (installed / 'adaptive_loop.yaml').is_file()
