"""
The ``bcid`` command: replay, simulate, reproduce, record, play, info, demo, analyze, import.

Each subcommand is a small function in the module that owns the work; this
file only parses arguments and turns :class:`~bcid_ros.errors.BcidError`
(and other expected failures) into one line on stderr and a non-zero exit.
The offline commands never import rclpy.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import os
from pathlib import Path
import sys
import traceback
from typing import Callable

from bcid_ros.errors import BcidError
from bcid_ros.estimators.registry import ESTIMATOR_NAMES
from bcid_ros.interrupts import (defer_sigints, handle_interrupts_in_finalizers,
                                 interrupt_on_sigints)
from bcid_ros.simulation import SCENARIOS


@dataclasses.dataclass(frozen=True)
class Command:
    """
    One ``bcid`` subcommand: everything the parser and :func:`main` ask about it.

    ``handler`` is ``'module:function(args) -> int'``, imported only when the
    command runs (an offline command never imports rclpy); ``summary`` its
    one-line help; ``arguments`` the function that adds its arguments.
    """

    handler: str
    summary: str
    arguments: Callable[[argparse.ArgumentParser], None]


#: The papers' scenarios; ``custom`` takes its plant from ROS parameters, which the CLI lacks.
SCENARIO_NAMES = tuple(name for name in SCENARIOS if name != 'custom')


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """
    Return the argument parser of ``bcid`` with all subcommands.

    With ``only``, the parser has that subcommand alone: argparse formats
    help and looks up gettext translations for every parser and argument,
    and all eight cost a few milliseconds of every ``bcid`` start-up.
    """
    fmt = argparse.ArgumentDefaultsHelpFormatter
    parser = argparse.ArgumentParser(
        prog='bcid', formatter_class=fmt,
        description='Online bias-compensated system identification: offline tools.')
    parser.add_argument('--debug', action='store_true', help='show tracebacks on errors')
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    for name, command in COMMANDS.items():
        if only is None or only == name:
            command.arguments(sub.add_parser(name, formatter_class=fmt, help=command.summary))
    return parser


#: How a CSV log's columns are read (``bcid replay``, ``analyze`` and ``import``).
CSV_COLUMNS_HELP = (
    'A CSV log has a header row, then one row per sample. By default the columns named y, '
    'u1, u2, ... are the output and the inputs; other columns are ignored. An empty cell, '
    'nan or inf is a missing sample, skipped as the identifier skips a NaN. Rows are numbered '
    'as lines of the file in error messages.')


def _csv_arguments(parser: argparse.ArgumentParser, rate: bool = True) -> None:
    group = parser.add_argument_group('CSV logs', CSV_COLUMNS_HELP)
    group.add_argument('--columns', metavar='NAMES',
                       help='the output column, then the input columns, comma-separated '
                       '(e.g. temp,heater); if none, the columns y,u1,...,ur')
    group.add_argument('--time-column', metavar='NAME',
                       help='the column of the sample times in seconds (>= 0, in time '
                       'order); if none, one sample per row')
    if rate:
        group.add_argument('--rate', type=float, metavar='HZ',
                           help='the sample rate of rows without --time-column: row k is '
                           'stamped k/HZ s; if none, 100 Hz')


def _replay_arguments(replay: argparse.ArgumentParser) -> None:
    replay.add_argument('bag', type=Path, help='rosbag2 directory, .mcap file or .csv log')
    replay.add_argument('--params', type=Path, required=True,
                        help='identifier parameter YAML (bcid_identifier: ros__parameters:)')
    replay.add_argument('--estimator', choices=ESTIMATOR_NAMES,
                        help='override the estimator of the parameter file')
    replay.add_argument('--output', type=Path, help='write the estimate trajectory '
                        '(.mcap in the node topic format, or .csv)')
    replay.add_argument('--json', action='store_true', help='print one JSON summary to stdout')
    _csv_arguments(replay)


def _simulate_arguments(simulate: argparse.ArgumentParser) -> None:
    simulate.add_argument('--scenario', choices=SCENARIO_NAMES, required=True)
    simulate.add_argument('--samples', type=int, required=True)
    simulate.add_argument('--seed', type=int, default=0)
    simulate.add_argument('--rate', type=float, default=100.0,
                          help='sample rate for the bag time stamps (Hz)')
    simulate.add_argument('--out', type=Path, required=True, help='output bag directory')


def _reproduce_arguments(reproduce: argparse.ArgumentParser) -> None:
    reproduce.add_argument('paper', choices=('ding', 'ikenoue', 'ikeda', 'all'))
    reproduce.add_argument('--runs', type=int, help="Monte Carlo runs (default: the paper's)")
    reproduce.add_argument('--quick', action='store_true', help='a small, fast version')
    reproduce.add_argument('--out-dir', type=Path, default=Path('docs'),
                           help='where to write the Markdown and PNG files')


def _record_arguments(record: argparse.ArgumentParser) -> None:
    record.add_argument('out', type=Path, help='output bag directory')
    record.add_argument('--topics', nargs='+', required=True, help='topics to record')
    record.add_argument('--duration', type=float, default=0.0,
                        help='stop after this many seconds (0: until SIGINT)')


def _play_arguments(play: argparse.ArgumentParser) -> None:
    play.add_argument('bag', type=Path)
    play.add_argument('--rate', type=float, default=1.0,
                      help='time scale; 0 plays as fast as possible, without losing a sample '
                      'to a subscriber that keeps all (the identifier), and exits 1 if an '
                      'identifier on /diagnostics lost some')
    play.add_argument('--topics', nargs='+', help='play only these topics (default: all)')
    play.add_argument('--wait-for-subscribers', type=float, default=None, metavar='SECONDS',
                      help='first wait up to SECONDS until every volatile topic has a '
                      'subscriber (0: do not wait; default 0, or 10 with --rate 0)')
    play.add_argument('--clock', type=float, nargs='?', const=100.0, default=0.0,
                      metavar='HZ', help='publish /clock (rosgraph_msgs/Clock) from the '
                      "bag's time, HZ times per second of bag time (default 100), for nodes "
                      'with use_sim_time')
    play.add_argument('--delay', type=float, default=0.0, metavar='SECONDS',
                      help='wait this long after creating the publishers, before playing')


def _info_arguments(info: argparse.ArgumentParser) -> None:
    info.add_argument('bag', type=Path)


def _demo_arguments(demo: argparse.ArgumentParser) -> None:
    demo.add_argument('--scenario', choices=SCENARIO_NAMES + ('payload_change', 'adaptive_loop'),
                      default='ding_miso', help='a paper scenario; payload_change: a plant that '
                      'changes at mid-run, detected and followed by rpem; or adaptive_loop: '
                      'plant, identifier and adaptive controller as three processes')
    demo.add_argument('--estimator', choices=ESTIMATOR_NAMES, default=None,
                      help="adaptive_loop: the identifier's estimator (default: the config's "
                      'cl_bcls)')
    demo.add_argument('--samples', type=int, default=0,
                      help="samples to simulate (0: the scenario's default)")
    demo.add_argument('--rate', type=float, default=0.0,
                      help="sample rate in Hz (0: the scenario's default)")
    demo.add_argument('--out-dir', type=Path, default=Path('demo_output'),
                      help='where to write the PNG of the run')


def _analyze_arguments(analyze: argparse.ArgumentParser) -> None:
    analyze.add_argument('bag', type=Path, help='rosbag2 directory, .mcap file or .csv log')
    analyze.description = (
        'Choose the order and the dead time of every input with batch output-error fits '
        'validated on the end of the record, describe the chosen model, and run the online '
        'estimators on that structure beside it (docs/analyze.md).')
    analyze.add_argument('--params', type=Path, required=True,
                         help='identifier parameter YAML: the settings of the online '
                         'estimators (order and input_delay come from the search; detrend is '
                         'mean unless the file sets it)')
    analyze.add_argument('--orders', default='1-4', help='order range A-B')
    analyze.add_argument('--delays', default='0', help='dead-time range A-B in samples, '
                         'searched per input (all combinations for up to two inputs, one '
                         'input at a time beyond)')
    analyze.add_argument('--estimator', choices=ESTIMATOR_NAMES,
                         help='compare only this online estimator (default: every open-loop '
                         'estimator and the parameter file\'s own)')
    analyze.add_argument('--validation', type=float, default=0.3,
                         help='fraction of the bag, at its end, kept for validation')
    analyze.add_argument('--sample-period', type=float, metavar='T',
                         help='sample period in seconds: adds continuous-time equivalents')
    analyze.add_argument('--plot', type=Path, metavar='OUT.png', help='write the figure')
    analyze.add_argument('--json', action='store_true', help='print one JSON object to stdout')
    _csv_arguments(analyze, rate=False)


def _import_arguments(imports: argparse.ArgumentParser) -> None:
    imports.description = (
        'Write the samples of a CSV log to a new rosbag2 MCAP bag: one '
        'std_msgs/msg/Float64MultiArray [y, u1, ..., ur] per row on /samples, labelled '
        'y,u1,...,ur, in the simulator\'s format and QoS, which bcid replay, bcid play and '
        'ros2 bag play take.')
    imports.add_argument('csv', type=Path, help='the CSV log')
    imports.add_argument('--out', type=Path, required=True, help='the new bag directory')
    _csv_arguments(imports)


#: The subcommands, in the order the help lists them: the one table of ``bcid``.
COMMANDS = {
    'replay': Command('bcid_ros.bag.commands:replay',
                      "run an estimator over a bag's /samples, no ROS graph", _replay_arguments),
    'simulate': Command('bcid_ros.bag.commands:simulate',
                        'write a scenario bag offline, no ROS graph', _simulate_arguments),
    'reproduce': Command('bcid_ros.cli:reproduce', "run a paper's Monte Carlo study, write docs/",
                         _reproduce_arguments),
    'record': Command('bcid_ros.bag.commands:record',
                      'record topics to a rosbag2 MCAP over rclpy', _record_arguments),
    'play': Command('bcid_ros.bag.commands:play', 'play a bag over rclpy', _play_arguments),
    'info': Command('bcid_ros.bag.commands:info', 'topics, counts, duration and truth of a bag',
                    _info_arguments),
    'reindex': Command('bcid_ros.bag.commands:reindex',
                       'repair a bag whose recording was killed (summary, CRCs, metadata.yaml)',
                       _info_arguments),
    'demo': Command('bcid_ros.cli:demo', 'simulator + identifier nodes, converging live',
                    _demo_arguments),
    'analyze': Command('bcid_ros.analysis.command:run',
                       'choose the order and delay, validate and describe the model',
                       _analyze_arguments),
    'import': Command('bcid_ros.bag.commands:import_csv',
                      'write a CSV log as a rosbag2 MCAP bag of /samples', _import_arguments),
}


def reproduce(args: argparse.Namespace) -> int:
    """Run ``bcid reproduce`` and list the files it wrote."""
    from bcid_ros.reproduction import reproduce as run

    if args.runs is not None and args.runs < 2:
        raise BcidError('--runs must be at least 2 (a standard error needs two runs)')
    for path in run(args.paper, args.runs, args.quick, args.out_dir):
        print(f'wrote {path}')
    return 0


def demo(args: argparse.Namespace) -> int:
    """Run ``bcid demo``: a scenario's simulator and identifier, or the adaptive loop's three."""
    if args.scenario == 'adaptive_loop':
        from bcid_ros.nodes.demo_loop import run_adaptive_loop as run
    else:
        from bcid_ros.nodes.demo import run
    return run(args)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``bcid``; returns the process exit code."""
    words = sys.argv[1:] if argv is None else argv
    # The first word that is not an option names the subcommand; only it needs its arguments.
    command = next((word for word in words if not word.startswith('-')), None)
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(argv)
    module, function = COMMANDS[args.command].handler.split(':')
    handle_interrupts_in_finalizers(deliver_again=True)
    try:
        # a SIGINT while the command's modules load is only noted, and raised once they
        # have: raised inside them, a C extension's import could swallow it or make
        # another error of it (interrupts.py)
        defer_sigints()
        handler = getattr(importlib.import_module(module), function)
        interrupt_on_sigints()
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader of stdout went away (`bcid info ... | head`): not an error of ours;
        # point stdout at devnull so the interpreter's final flush stays quiet
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (BcidError, FileNotFoundError, ValueError, OSError) as error:
        if args.debug:
            traceback.print_exc()
        print(f'bcid {args.command}: error: {error}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
