"""
The no-change control of ``benchmarks/tracking.py``: how much of a recovery score is chance.

Usage: ``.venv/bin/python -m benchmarks.tracking_control [--count 30] [--seed 0]
[--estimators rpem,rpem_0.999]`` from the repository root (docs/tracking_log.md, "Limits and
what is left", 2026-11-28, session 9). Progress goes to stderr, the table to stdout.

Each abrupt case of the family (:class:`~benchmarks.tracking.TrackingCase`) is run twice:
as drawn, and with its plant **held** at its value before the change (:func:`held`: the
same inputs, the same output noise, the same samples; only the change is left out). Both
runs are scored exactly as ``benchmarks.tracking`` scores a run (the estimator's band, twice
its median delta over the 1000 samples before the change sample, and the samples from which
delta stays within it), and both recoveries are judged against the reference of the case as
drawn. A held plant has nothing to recover from: where the estimator is not "within 5x"
there, the band, not the recovery, is what the score measured. An estimator whose error
shrinks with its samples (no forgetting) stays within its band once in it; one with a memory
(forgetting) has an error that wanders on the time scale of that memory, and a band set by
one memory's median is exceeded by chance in the four memories a record has after the
change. The held runs are also stationary records: their ``plant_change`` flags are false
detections.
"""

from __future__ import annotations

import copy
import sys
from typing import Sequence

import numpy as np

from benchmarks.tracking import (family_run_options, reference, run_estimator, TrackingCase,
                                 within_reference)
from bcid_ros.markdown import markdown_table


def held(case: TrackingCase) -> TrackingCase:
    """
    Return ``case`` with its plant held at its value before the change, the rest kept.

    The output noise is the case's own (its output less the changing plant's noise-free
    output); the samples before the change are the case's, bit for bit.
    """
    control = copy.copy(case)
    control.theta = np.repeat(case.theta[case.change_at - 1][None, :], case.samples, axis=0)
    noise = case.y - case.simulate(case.u)
    control.y = case.y.copy()
    after = slice(case.change_at, None)
    control.y[after] = control.simulate(case.u)[after] + noise[after]
    control.kind, control.change = 'none', 'held'
    return control


def main(argv: Sequence[str] | None = None) -> int:
    """Run the control; print the table."""
    args, configs = family_run_options(argv, __doc__.splitlines()[1])
    within = {config: [0, 0] for config in configs}
    missed_held = {config: [] for config in configs}
    false = {config: 0 for config in configs}
    count = 0
    for k in range(args.count):
        case = TrackingCase((args.seed, k), 'family')
        if case.kind != 'abrupt':
            continue
        count += 1
        ref = reference(case)['recovery']
        control = held(case)
        print(f'{case.describe()}: reference recovery {ref}', file=sys.stderr)
        for config in configs:
            changed, still = run_estimator(case, config), run_estimator(control, config)
            ok = (within_reference(changed['recovery'], ref),
                  within_reference(still['recovery'], ref))
            within[config][0] += ok[0]
            within[config][1] += ok[1]
            false[config] += still['false_detections']
            if not ok[1]:
                missed_held[config].append(str(k))
            print(f'  {config}: recovery {changed["recovery"]} (band {changed["band"]:.4f}); '
                  f'held: recovery {still["recovery"]} (band {still["band"]:.4f}), false '
                  f'{still["false_detections"]}', file=sys.stderr)
    rows = [['abrupt within 5x the reference, as drawn'] +
            [f'{within[c][0]} / {count}' for c in configs],
            ['the same with the plant held (no change)'] +
            [f'{within[c][1]} / {count}' for c in configs],
            ['cases not within 5x with the plant held'] +
            [', '.join(missed_held[c]) or '-' for c in configs],
            ['plant_change on the held plants (false detections)'] +
            [str(false[c]) for c in configs]]
    print(markdown_table([f'seed {args.seed}'] + configs, rows))
    return 0


if __name__ == '__main__':
    sys.exit(main())
