"""A Ctrl-C that lands in a finalizer prints nothing, and still ends a ``bcid`` command."""

from pathlib import Path
import signal
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = '''
import time
from bcid_ros.interrupts import handle_interrupts_in_finalizers
if {mode} is not None:
    handle_interrupts_in_finalizers(deliver_again={mode})
    handle_interrupts_in_finalizers(deliver_again={mode})    # twice: one hook, no chain


class Dying:
    def __del__(self):
        raise {error}


try:
    Dying()
    deadline = time.monotonic() + {wait}
    while time.monotonic() < deadline:     # busy: the interrupt raised again is no signal
        pass
    print("went on")
except KeyboardInterrupt:
    print("interrupted")
'''


def _default_sigint() -> None:
    # a background job (nohup ... &) starts with SIGINT ignored, and then there is no
    # interrupt to deliver; a terminal or ros2 launch gives the default
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _run(mode: bool | None, error: str, wait: float) -> subprocess.CompletedProcess:
    script = SCRIPT.format(mode=mode, error=error, wait=wait)
    return subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                          cwd=ROOT, timeout=60, preexec_fn=_default_sigint)


def test_python_alone_loses_an_interrupt_in_a_finalizer_with_a_traceback():
    # what the hook is for
    result = _run(None, 'KeyboardInterrupt', wait=0.5)
    assert result.stdout == 'went on\n'
    assert 'Exception ignored' in result.stderr and 'KeyboardInterrupt' in result.stderr


def test_a_command_gets_the_interrupt_again_in_its_main_thread_quietly():
    result = _run(True, 'KeyboardInterrupt', wait=10.0)
    assert result.stdout == 'interrupted\n', result.stderr
    assert result.stderr == ''


def test_a_node_drops_the_interrupt_quietly():
    # rclpy's own handler has shut the node's context down: nothing more to deliver
    result = _run(False, 'KeyboardInterrupt', wait=0.5)
    assert result.stdout == 'went on\n'
    assert result.stderr == ''


@pytest.mark.parametrize('mode', [True, False])
@pytest.mark.parametrize('error', ['ValueError("from a finalizer")', 'SystemExit(3)'])
def test_other_errors_in_a_finalizer_are_reported_as_before(mode, error):
    result = _run(mode, error, wait=0.5)
    assert result.stdout == 'went on\n'
    assert 'Exception ignored' in result.stderr and error.split('(')[0] in result.stderr
