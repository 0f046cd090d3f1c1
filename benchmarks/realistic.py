"""
Accuracy of the online estimators on a seeded family of realistic plants, against batch OE.

Usage: ``.venv/bin/python -m benchmarks.realistic [--count 40] [--seed 0]
[--estimators rls,bcrls] [--all-estimators] [--json OUT]`` from the repository root
(docs/accuracy.md). Progress goes to stderr, the markdown table to stdout.

For every case of :func:`bcid_ros.analysis.realistic.realistic_family` the batch
output-error fit with the true structure (:func:`bcid_ros.analysis.pem.fit_oe`; with the
sample means removed and an output offset fitted when the record has an operating point)
gives the
reference error delta_ref = ||theta_ref - theta|| / ||theta|| (the rows also hold the batch
ARX error delta_arx: with equation-error noise ARX is the maximum-likelihood estimate and OE
only consistent, so there rls may beat the reference), and each online estimator
runs sample by sample (``update``, as in the node) over the same record, built with the true
order, inputs and dead times and the ``detrend`` the record needs (``mean`` when it has an
operating point). Per estimator:

* **accurate**: delta <= max(2 delta_ref, 1 %), the share of cases;
* **median delta / delta_ref**;
* **valid but wrong**: ``valid`` at the end while delta > 10 %;
* **accurate but invalid**: not ``valid`` while accurate;
* **coverage**: of the valid estimates with a ``parameter_std``, the share with every
  parameter within 3 std of the truth;
* **diverged**: theta not finite, delta > 10, or the estimator raised.

The default estimators are the registered ones for open-loop input/output data (the
registry's ``open_loop``: not errors in variables, not closed loop); an estimator registered
later (``rpem``) is included by itself.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
import time
from typing import Any, Sequence
import warnings

import numpy as np

from bcid_ros.analysis.pem import fit_arx, fit_oe, Structure
from bcid_ros.analysis.realistic import realistic_family, RealisticCase
from bcid_ros.estimators import ESTIMATORS, make_estimator
from bcid_ros.estimators.registry import names_where
from bcid_ros.markdown import markdown_table
from bcid_ros.reproduction.common import relative_error

#: delta at or below this counts as accurate whatever delta_ref is.
ACCURATE_FLOOR = 0.01
#: delta at or below this many times delta_ref counts as accurate.
ACCURATE_RATIO = 2.0
#: A valid estimate further than this from the truth is "valid but wrong".
WRONG_DELTA = 0.10
#: An estimate further than this from the truth (ten times its size) has diverged.
DIVERGED_DELTA = 10.0
#: A parameter is covered when it lies within this many std of the truth.
COVERAGE_STD = 3.0


def default_estimators() -> list[str]:
    """Return the registered estimators for open-loop input/output data, in registry order."""
    return list(names_where(open_loop=True))


def centred(case: RealisticCase) -> tuple[np.ndarray, np.ndarray]:
    """Return the record with the sample means removed when it has an operating point."""
    if case.detrend == 'mean':
        return case.y - case.y.mean(), case.u - case.u.mean(axis=0)
    return case.y, case.u


def reference(case: RealisticCase) -> dict[str, Any]:
    """Fit the batch OE model with the true structure; return its row figures."""
    y, u = centred(case)
    start = time.perf_counter()
    # at an operating point the sample means leave an output offset (a slow plant over a
    # finite record), which the reference fits with the model
    result = fit_oe(y, u, Structure(case.order, case.num_inputs, case.input_delay),
                    offset=case.detrend == 'mean')
    seconds = time.perf_counter() - start
    z = np.abs(result.theta - case.theta) / result.std
    arx = fit_arx(y, u, Structure(case.order, case.num_inputs, case.input_delay))
    return {'delta_ref': float(relative_error(result.theta, case.theta)),
            'ref_seconds': seconds, 'ref_converged': result.converged,
            'ref_max_z': float(z.max()), 'ref_theta': result.theta.tolist(),
            'ref_initial': result.initial,
            'delta_arx': float(relative_error(arx.theta, case.theta))}


def run_estimator(name: str, case: RealisticCase) -> dict[str, Any]:
    """Run one online estimator over the case; return delta, validity, std figures."""
    row: dict[str, Any] = {'error': None}
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        try:
            estimator = make_estimator(name, order=case.order, num_inputs=case.num_inputs,
                                       input_delay=case.input_delay, detrend=case.detrend)
            y, u = case.y.tolist(), case.u
            for t, value in enumerate(y):
                estimator.update(value, u[t])
        except Exception as error:  # noqa: B902 -- a crash is a finding, recorded per case
            row['error'] = f'{type(error).__name__}: {error}'
    row['seconds'] = time.perf_counter() - start
    row['warnings'] = len(caught)
    if row['error'] is not None:
        row.update(delta=math.nan, valid=False, reasons=[], std=None, diverged=True)
        return row
    theta = estimator.theta
    delta = float(relative_error(theta, case.theta))
    std = estimator.parameter_std
    row.update(delta=delta, valid=bool(estimator.valid),
               reasons=list(estimator.validity_reasons), theta=theta.tolist(),
               std=None if std is None else std.tolist(),
               diverged=bool(not np.isfinite(theta).all() or not delta <= DIVERGED_DELTA),
               flags=dict(estimator.flags))
    if std is not None:
        with np.errstate(divide='ignore', invalid='ignore'):
            row['covered'] = bool(np.all(np.abs(theta - case.theta) <= COVERAGE_STD * std))
    return row


def evaluate(case: RealisticCase, estimators: Sequence[str]) -> dict[str, Any]:
    """Return the JSON row of one case: its description, the reference and each estimator."""
    row: dict[str, Any] = {
        'case': case.description, 'seed': list(case.seed), 'order': case.order,
        'num_inputs': case.num_inputs, 'input_delay': list(case.input_delay),
        'samples': case.samples, 'snr_db': case.snr_db, 'noise': case.noise,
        'excitation': list(case.excitation), 'detrend': case.detrend,
        'predicted_error': case.predicted_error, 'theta': case.theta.tolist(),
        'parameter_names': list(case.parameter_names)}
    row.update(reference(case))
    row['estimators'] = {name: run_estimator(name, case) for name in estimators}
    for result in row['estimators'].values():
        result['accurate'] = bool(result['delta'] <= max(ACCURATE_RATIO * row['delta_ref'],
                                                         ACCURATE_FLOOR))
    return row


def summarise(rows: list[dict[str, Any]], name: str) -> list[str]:
    """Return the table cells of one estimator over all case rows."""
    results = [row['estimators'][name] for row in rows]
    count = len(results)
    ratios = [r['delta'] / max(row['delta_ref'], 1e-12)
              for r, row in zip(results, rows) if math.isfinite(r['delta'])]
    valid = [r for r in results if r['valid']]
    with_std = [r for r in valid if 'covered' in r]
    covered = sum(r['covered'] for r in with_std)
    finite = [r['delta'] for r in results if math.isfinite(r['delta'])]
    return [
        name, f'{sum(r["accurate"] for r in results)}/{count}',
        f'{np.median(ratios):.2f}' if ratios else '-',
        f'{100 * np.median(finite):.2f} %' if finite else '-',
        f'{len(valid)}/{count}',
        f'{sum(r["valid"] and r["delta"] > WRONG_DELTA for r in results)}',
        f'{sum(r["accurate"] and not r["valid"] for r in results)}',
        f'{covered}/{len(with_std)}' + (
            f' ({len(valid) - len(with_std)} without std)' if len(with_std) < len(valid)
            else ''),
        f'{sum(r["diverged"] for r in results)}',
    ]


def table(rows: list[dict[str, Any]], estimators: Sequence[str]) -> str:
    """Return the markdown summary: the reference line and one row per estimator."""
    deltas = np.array([row['delta_ref'] for row in rows])
    seconds = np.array([row['ref_seconds'] for row in rows])
    z = np.array([row['ref_max_z'] for row in rows])
    arx = np.array([row['delta_arx'] for row in rows])
    head = (f'Batch OE reference over {len(rows)} cases: median delta_ref '
            f'{100 * np.median(deltas):.2f} %, largest {100 * deltas.max():.2f} %; '
            f'largest |error|/std of a parameter {np.median(z):.2f} (median), '
            f'{z.max():.2f} (largest); fit time median {1000 * np.median(seconds):.0f} ms, '
            f'largest {1000 * seconds.max():.0f} ms. Batch ARX: median delta '
            f'{100 * np.median(arx):.2f} %, below delta_ref in {int(np.sum(arx < deltas))} '
            'cases.\n')
    headers = ('estimator', 'accurate (<= 2 delta_ref or 1 %)', 'median delta/delta_ref',
               'median delta', 'valid at end', 'valid but wrong (delta > 10 %)',
               'accurate but invalid', 'coverage (valid, all within 3 std)', 'diverged')
    return (head + '\n' + markdown_table(headers, [summarise(rows, name) for name in estimators])
            + '\n' + by_noise(rows, estimators))


def by_noise(rows: list[dict[str, Any]], estimators: Sequence[str]) -> str:
    """Return the markdown table of accurate cases per kind of noise."""
    lines = []
    for kind in sorted({row['noise'] for row in rows}):
        chosen = [row for row in rows if row['noise'] == kind]
        lines.append([kind, len(chosen),
                      f'{100 * np.median([row["delta_ref"] for row in chosen]):.2f} %',
                      f'{100 * np.median([row["delta_arx"] for row in chosen]):.2f} %']
                     + [f'{sum(row["estimators"][name]["accurate"] for row in chosen)}'
                        for name in estimators])
    return markdown_table(['noise', 'cases', 'median delta_ref', 'median delta, batch ARX']
                          + [f'{name} accurate' for name in estimators], lines)


def main(argv: list[str] | None = None) -> int:
    """Run the family and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument('--count', type=int, default=40, help='cases in the family')
    parser.add_argument('--seed', type=int, default=0, help='seed of the family')
    parser.add_argument('--estimators', default=None,
                        help='comma-separated registry names (default: the open-loop ones)')
    parser.add_argument('--all-estimators', action='store_true',
                        help='also run the estimators for other settings (errors in '
                        'variables, closed loop)')
    parser.add_argument('--json', type=Path, default=None, help='write the per-case rows here')
    args = parser.parse_args(argv)
    names = (args.estimators.split(',') if args.estimators else
             list(ESTIMATORS) if args.all_estimators else default_estimators())
    unknown = [name for name in names if name not in ESTIMATORS]
    if unknown:
        parser.error(f'unknown estimator(s) {", ".join(unknown)}; '
                     f'registered: {", ".join(ESTIMATORS)}')
    rows = []
    started = time.perf_counter()
    for index, case in enumerate(realistic_family(args.count, args.seed)):
        row = evaluate(case, names)
        rows.append(row)
        figures = ' '.join(
            f'{name} {100 * r["delta"]:.2f}%{"" if r["valid"] else " invalid"}'
            f'{" ERROR" if r["error"] else ""}' for name, r in row['estimators'].items())
        print(f'[{index + 1}/{args.count}] ref {100 * row["delta_ref"]:.2f}% {figures} | '
              f'{case.description}', file=sys.stderr, flush=True)
    print(f'{time.perf_counter() - started:.0f} s', file=sys.stderr)
    print(table(rows, names))
    if args.json is not None:
        args.json.write_text(json.dumps({'count': args.count, 'seed': args.seed,
                                         'estimators': names, 'rows': rows}, indent=1))
        print(f'wrote {args.json}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
