"""
Where rpem places a plant change: the estimated change point against the true one.

Usage: ``.venv/bin/python -m benchmarks.change_points [--count 30] [--seed 0]
[--estimators rpem,rpem_0.999]`` from the repository root (docs/tracking_log.md, "Limits and
what is left", 2026-11-28, session 10). One line per detection goes to stderr, the table to
stdout.

After a detection rpem's fits start at the change point the detection names, ``plant changed
(sample k)`` (k the first sample of the new plant, counted from 1): a point late keeps the new
plant's first samples out of the fits, one early blends the old plant's into every fit of the
new one. Each abrupt case of the tracking family (:class:`~benchmarks.tracking.TrackingCase`,
its new plant's first sample ``change_at + 1``) is run, and every detection after the change
is scored by k less that sample (the first detection after the change; later ones, of the
restarted model, are counted apart), per test that found it, read from the reason's end: the
whitened variance CUSUM (or the gate: no note), the block-mean test
(:data:`~bcid_ros.estimators.rpem.online.BLOCK_NOTE`) or the simulation check
(:data:`~bcid_ros.estimators.rpem.online.SIMULATION_NOTE`, which names the first sample of its
last window, all after the change by construction). Only rpem's configurations are scored
(rls and bcrls restart from at most 400 kept samples).
"""

from __future__ import annotations

import re
import sys
from typing import Any, Sequence

import numpy as np

from benchmarks.tracking import CONFIGS, family_run_options, TrackingCase
from bcid_ros.blas_threads import single_threaded_blas
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.rpem.online import BLOCK_NOTE, SIMULATION_NOTE
from bcid_ros.markdown import markdown_table

#: The change's reason: ``plant changed (sample k)`` and the test's note.
_REASON = re.compile(r'^plant changed \(sample (\d+)\)(.*)$')
#: The tests, by the note their reason ends with.
TESTS = {'': 'whitened test (or gate)', BLOCK_NOTE: 'block test',
         SIMULATION_NOTE: 'simulation check'}


def detections(case: TrackingCase, config: str) -> list[dict[str, Any]]:
    """Run ``config`` over ``case``; return each plant_change: its sample, change point, test."""
    name, settings = CONFIGS[config]
    if name != 'rpem':
        raise ValueError(f'estimators: {config!r} is not an rpem configuration')
    estimator = make_estimator(name, order=case.order, num_inputs=case.num_inputs, **settings)
    found = []
    before = 0
    with single_threaded_blas():  # as the tracking benchmark runs it
        for t in range(case.samples):
            estimator.update(float(case.y[t]), case.u[t])
            flagged = estimator.flags.get('plant_change', 0)
            if flagged > before:
                match = next(filter(None, map(_REASON.match, estimator.validity_reasons)))
                found.append({'sample': t + 1, 'point': int(match[1]),
                              'test': TESTS.get(match[2], match[2])})
            before = flagged
    return found


def summary(errors: Sequence[int]) -> list[str]:
    """Return count, median absolute error, shares late and early, extremes of ``errors``."""
    if not errors:
        return ['0', '-', '-', '-', '-']
    values = np.array(errors)
    return [str(values.size), f'{np.median(np.abs(values)):.0f}',
            f'{np.mean(values > 0):.2f}', f'{np.mean(values < 0):.2f}',
            f'{values.min():+d} .. {values.max():+d}']


def main(argv: Sequence[str] | None = None) -> int:
    """Run the cases; print the table of change-point errors per configuration and test."""
    args, configs = family_run_options(argv, __doc__.splitlines()[1])
    errors: dict[tuple[str, str], list[int]] = {}
    again = {config: 0 for config in configs}
    for k in range(args.count):
        case = TrackingCase((args.seed, k), 'family')
        if case.kind != 'abrupt':
            continue
        first = case.change_at + 1
        for config in configs:
            # before the change: false detections (benchmarks.tracking counts those)
            after = [found for found in detections(case, config) if found['sample'] >= first]
            for number, found in enumerate(after):
                error = found['point'] - first
                if number == 0:
                    errors.setdefault((config, found['test']), []).append(error)
                else:
                    again[config] += 1
                print(f'({args.seed}, {k}) {config}: detected at {found["sample"]}, change '
                      f'point {found["point"]}, true {first}: {error:+d} ({found["test"]})'
                      f'{" again" if number else ""}', file=sys.stderr, flush=True)
    rows = [[config, test] + summary(errors.get((config, test), []))
            for config in configs for test in TESTS.values()]
    rows += [[config, 'later detections (not scored)', str(again[config]), '', '', '', '']
             for config in configs]
    print(markdown_table([f'seed {args.seed}', 'test', 'first detections', 'median abs. error',
                          'late', 'early', 'range'], rows))
    return 0


if __name__ == '__main__':
    sys.exit(main())
