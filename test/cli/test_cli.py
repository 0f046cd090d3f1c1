"""The ``bcid`` argument parser: one subcommand's parser alone parses as the full one."""

import pytest

from bcid_ros.cli import build_parser, COMMANDS

ARGV = {
    'replay': ['replay', 'bag', '--params', 'p.yaml', '--estimator', 'rls', '--json'],
    'simulate': ['simulate', '--scenario', 'ding_miso', '--samples', '10', '--out', 'o'],
    'reproduce': ['reproduce', 'ding', '--quick'],
    'record': ['record', 'o', '--topics', '/a', '/b'],
    'play': ['play', 'bag', '--rate', '0'],
    'info': ['--debug', 'info', 'bag'],
    'reindex': ['reindex', 'bag'],
    'demo': ['demo', '--scenario', 'adaptive_loop'],
    'analyze': ['analyze', 'bag', '--params', 'p.yaml', '--orders', '1-2'],
    'import': ['import', 'log.csv', '--out', 'o', '--columns', 'temp,heater', '--rate', '20'],
}


def test_every_subcommand_has_a_summary_and_arguments():
    assert list(COMMANDS) == list(ARGV)
    for command in COMMANDS.values():
        assert command.summary and callable(command.arguments)


@pytest.mark.parametrize('name', list(ARGV))
def test_a_subcommand_parsed_alone_parses_as_in_the_full_parser(name):
    full = build_parser().parse_args(ARGV[name])
    alone = build_parser(name)
    assert vars(alone.parse_args(ARGV[name])) == vars(full)
    assert list(alone._subparsers._group_actions[0].choices) == [name]


def test_every_handler_is_a_function_of_its_module():
    import importlib

    for command in COMMANDS.values():
        location = command.handler
        module, function = location.split(':')
        assert callable(getattr(importlib.import_module(module), function)), location


@pytest.mark.parametrize('scenario, module, function', [
    ('adaptive_loop', 'bcid_ros.nodes.demo_loop', 'run_adaptive_loop'),
    ('ding_miso', 'bcid_ros.nodes.demo', 'run'),
])
def test_demo_runs_the_adaptive_loop_or_a_scenario_demo(monkeypatch, scenario, module, function):
    import importlib

    from bcid_ros import cli

    monkeypatch.setattr(importlib.import_module(module), function, lambda args: 7)
    assert cli.demo(build_parser().parse_args(['demo', '--scenario', scenario])) == 7


def test_a_sigint_while_the_command_loads_exits_130_before_it_runs():
    # deferred while the command's modules load (a C extension's import could swallow it
    # or make another error of it), then raised: the command does not run. In a fresh
    # process, as bcid starts: a SIGINT to the test process could meet what earlier tests
    # left there (rclpy's and DDS's threads, other handlers)
    import signal
    import subprocess
    import sys
    code = (
        'import os, signal, time, types\n'
        'from bcid_ros import cli\n'
        'ran = []\n'
        'def import_module(name):\n'
        '    os.kill(os.getpid(), signal.SIGINT)\n'
        '    time.sleep(0.05)     # Python runs its handler here: only noted\n'
        '    return types.SimpleNamespace(info=lambda args: ran.append(args) or 0)\n'
        'cli.importlib.import_module = import_module\n'
        'print(cli.main(["info", "some.bag"]), ran)\n')
    result = subprocess.run(
        [sys.executable, '-c', code], capture_output=True, text=True, timeout=60,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert result.stdout == '130 []\n', result.stderr
