"""A node runs with one BLAS thread, whatever the environment asked for."""

import ast
import os
from pathlib import Path
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[2]

PROBE = '''
import numpy, scipy.linalg          # their OpenBLAS libraries, as a node loads them
from rclpy.node import Node
from bcid_ros.blas_threads import _controls, openblas_libraries
from bcid_ros.nodes.common import run_node

controls = [found for found in map(_controls, openblas_libraries()) if found is not None]
print('before', [getter() for _, getter in controls])


def until(node):
    print('running', [getter() for _, getter in controls])
    return True


print('exit', run_node(lambda: Node('blas_probe'), ['probe'], 'probe', until=until))
'''


def test_run_node_sets_every_loaded_openblas_to_one_thread():
    env = dict(os.environ, OPENBLAS_NUM_THREADS='2', ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    result = subprocess.run([sys.executable, '-c', PROBE], capture_output=True, text=True,
                            cwd=ROOT, env=env, timeout=120)
    lines = dict(line.split(' ', 1) for line in result.stdout.splitlines())
    assert lines.get('exit') == '0', result.stderr
    before, running = ast.literal_eval(lines['before']), ast.literal_eval(lines['running'])
    if not before:
        pytest.skip('no OpenBLAS loaded: another BLAS, set by its environment variable')
    assert before == [2] * len(before)  # the environment asked for two
    assert running == [1] * len(before)
