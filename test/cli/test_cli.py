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
