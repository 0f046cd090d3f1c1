"""
The bag subcommands of ``bcid``: replay, simulate, record, play, info, reindex, import.

``replay``, ``simulate``, ``info``, ``reindex`` and ``import`` work offline and never import
rclpy; ``record`` and ``play`` import it (lazily, in their own modules).
"""

from __future__ import annotations

import argparse
import sys

from bcid_ros.errors import BcidError


def replay(args: argparse.Namespace) -> int:
    """Run ``bcid replay``: the estimator over a bag, a summary, an optional trajectory."""
    from bcid_ros.bag.csv_samples import samples_source
    from bcid_ros.bag.replay import replay as run, write_output
    from bcid_ros.parameter_spec import load_yaml_parameters

    if not args.params.is_file():
        raise BcidError(f'--params {args.params}: no such file')
    source = samples_source(args.bag, args.columns, args.time_column, args.rate)
    # The trajectory is kept only for --output; the final estimate is the same either way.
    result = run(source, load_yaml_parameters(args.params), estimator=args.estimator,
                 trajectory=args.output is not None)
    if not result.in_file_order:
        print('bcid replay: note: the samples were not stored in log-time order; '
              'replayed in log-time order', file=sys.stderr)
    if args.output is not None:
        write_output(result, args.output)
    if args.json:
        import json

        print(json.dumps(result.summary()))
        return 0
    rate = result.samples / result.elapsed_s if result.elapsed_s > 0 else float('inf')
    print(f'{result.estimator}: {result.samples} samples from {result.messages} messages '
          f'in {result.elapsed_s:.3f} s ({rate:,.0f} samples/s)')
    unused = {cause: count for cause, count in result.unused.items() if count}
    if unused:
        print('not used: ' + ', '.join(f'{count} {cause.replace("_", " ")}'
                                       for cause, count in unused.items()))
    if not result.ready:
        print(f'the estimator {result.not_ready_reason}')
    elif not result.valid:
        print('the final estimate is not valid: '
              + (', '.join(result.validity_reasons) or 'the estimator gives no reason'))
    truth = result.truth.as_dict()['parameters'] if result.truth is not None else {}
    width = max(len(n) for n in result.parameter_names)
    print(f'{"":{width}}  {"estimate":>12}  {"uncompensated":>13}' + ('  {:>10}'.format('true')
                                                                      if truth else ''))
    for k, name in enumerate(result.parameter_names):
        line = (f'{name:{width}}  {result.theta[k]:12.6f}  '
                f'{result.theta_uncompensated[k]:13.6f}')
        if name in truth:
            line += f'  {truth[name]:10.6f}'
        print(line)
    for name, value in zip(result.noise_names, result.noise):
        true_noise = result.truth.as_dict()['noise'] if result.truth is not None else {}
        extra = f' (true {true_noise[name]:.6g})' if name in true_noise else ''
        print(f'{name} = {value:.6g}{extra}')
    if result.delta is not None:
        print(f'delta = ||theta_hat - theta|| / ||theta|| = {100 * result.delta:.3f} %')
    if args.output is not None:
        print(f'wrote {args.output}')
    return 0


def simulate(args: argparse.Namespace) -> int:
    """Run ``bcid simulate``: write a scenario bag offline."""
    from bcid_ros.bag.simulate import simulate_bag

    out = simulate_bag(args.scenario, args.samples, args.seed, args.rate, args.out)
    print(f'wrote {out}')
    return 0


def info(args: argparse.Namespace) -> int:
    """Run ``bcid info``: topics, counts, duration and truth of a bag."""
    from bcid_ros.bag.info import describe_bag

    print(describe_bag(args.bag))
    return 0


def reindex(args: argparse.Namespace) -> int:
    """Run ``bcid reindex``: rewrite the summary, CRCs and metadata.yaml of a killed recording."""
    from bcid_ros.bag.recovery import reindex_bag

    print(reindex_bag(args.bag))
    return 0


def import_csv(args: argparse.Namespace) -> int:
    """Run ``bcid import``: write the samples of a CSV log to a rosbag2 MCAP bag."""
    from bcid_ros.bag.csv_samples import read_csv_samples, write_samples_bag
    from bcid_ros.bag.replay import SAMPLES_TOPIC
    from bcid_ros.identifier.layouts import sample_label

    samples = read_csv_samples(args.csv, args.columns, args.time_column, args.rate, load=False)
    out = write_samples_bag(samples, args.out)
    stats = samples.stats
    count = stats.rows
    span = (stats.last_ns - stats.first_ns) / 1e9
    stamps = (f'times from column {samples.time_column!r}' if samples.time_column is not None
              else f'stamped at {samples.rate_hz:g} Hz')
    print(f'wrote {out}: {count} samples on {SAMPLES_TOPIC} ({sample_label(samples.num_inputs)} '
          f'from columns {",".join(samples.columns)}), {stamps}, {span:.6g} s')
    if stats.nonfinite_rows:
        print(f'{stats.nonfinite_rows} row(s) with an empty, NaN or infinite value: written '
              'as they are (empty as NaN); the identifier skips such samples')
    return 0


def record(args: argparse.Namespace) -> int:
    """Run ``bcid record``: record topics over rclpy until SIGINT or --duration."""
    from bcid_ros.bag.record import record_bag

    counts = record_bag(args.out, args.topics, duration=args.duration)
    total = sum(counts.values())
    print(f'wrote {args.out}: {total} messages '
          f'({", ".join(f"{t}: {n}" for t, n in counts.items()) or "no topics found"})',
          file=sys.stderr)
    return 0


def play(args: argparse.Namespace) -> int:
    """Run ``bcid play``: publish a bag over rclpy with its timing and QoS."""
    from bcid_ros.bag.play import play_bag

    stats = play_bag(args.bag, rate=args.rate, topics=args.topics,
                     wait_for_subscribers=args.wait_for_subscribers, delay=args.delay,
                     clock=args.clock)
    print(stats.describe(), file=sys.stderr)
    return 1 if stats.shortfall else 0


__all__ = ['import_csv', 'info', 'play', 'record', 'reindex', 'replay', 'simulate']
