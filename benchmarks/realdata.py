"""
Measured data (DaISy): the online estimators' validation fit beside the batch OE model's.

Usage: ``.venv/bin/python -m benchmarks.realdata --data DIR [--estimators rls,bcrls]
[--orders 1-6] [--delays 0-4] [--json OUT]`` from the repository root, where DIR holds one
folder per plant with ``data.csv`` (or ``data_y1.csv``, ``data_y2.csv``, one MISO problem
each), header ``y,u1[,u2]``, one sample per row: the DaISy records (De Moor, KU Leuven,
"DaISy: Database for the Identification of Systems") are not part of the repository.
Progress goes to stderr, the markdown tables to stdout (docs/accuracy.md). A folder ``emps``
with ``estimation.csv`` and ``validation.csv`` (the EMPS closed-loop benchmark) is run by
:mod:`benchmarks.emps`.

Protocol, per record: the first half estimates, the second validates. The operating point
is the means of the estimation half; the batch model is fitted to the centred estimation
half, and each online estimator runs sample by sample over the raw estimation half with
``detrend: mean``, as a user would, and its own operating point. The fit of a model is
the NRMSE fit 100 (1 - ||y - yhat|| / ||y - mean(y)||) on the validation half of its
simulated output, yhat = y0 + sum_i B_i/F (u_i - u0_i), simulated from rest over the whole
record so that the start-up transient falls in the estimation half (as ``bcid analyze``
does). The batch OE structure is chosen by that validation fit over the orders and
per-input delays given: the smallest order within ``MARGIN`` points of the best fit,
then its best delays. Each online estimator runs with that structure and with the one
the plant's literature gives (:data:`PUBLISHED`), with the outlier gate at 5 and off
(0), and reports its fit, whether it is ``valid`` at the end of the estimation half and
the share of samples its gate refused (flag ``outlier_rejected``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path
import sys
import time
from typing import Any, Sequence

import numpy as np

from benchmarks import emps
from benchmarks.realistic import default_estimators
from bcid_ros.analysis.metrics import nrmse_fit
from bcid_ros.analysis.pem import fit_oe, simulate_oe, Structure
from bcid_ros.estimators import ESTIMATORS, make_estimator
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from bcid_ros.markdown import markdown_table

#: A structure within this many fit points of the best one counts as as good.
MARGIN = 1.0
#: Outlier thresholds the online estimators run with (0 = off).
GATES = (5.0, 0.0)
#: Structures from the literature, per plant folder: (order n, delay per input) in bcid
#: terms, with where they come from (each folder's README).
PUBLISHED = {
    'dryer': (2, (2,), "MATLAB System Identification Toolbox dryer demo, arx(ze, [2 2 3])"),
    'robot_arm': (4, (0,), 'SLICOT DaISy demo: "a 4-order model is good enough"'),
    'thermic_res_wall': (2, (0, 0), 'Markovsky (2013), lag 2'),
    'cd_player_arm': (2, (0, 0), 'Markovsky (2013), lag 1 for the 2x2 system (order 2)'),
}


def records(folder: Path) -> list[tuple[str, str, np.ndarray]]:
    """Return (name, plant folder, data [y, u1, ...]) of every record under ``folder``."""
    found = []
    for path in sorted(folder.glob('*/data*.csv')):
        data = np.loadtxt(path, delimiter=',', skiprows=1, ndmin=2)
        suffix = path.stem[len('data'):].lstrip('_')
        name = path.parent.name + (f'/{suffix}' if suffix else '')
        found.append((name, path.parent.name, data))
    return found


def validation_fit(theta: np.ndarray, structure: Structure, y: np.ndarray, u: np.ndarray,
                   point: np.ndarray, split: int) -> float:
    """Return the NRMSE fit (%) on samples ``split:`` of the model simulated over the record."""
    if not np.isfinite(theta).all():
        return -math.inf
    if not is_stable(monic_coefficients(structure.split(theta)[0]), 0.0):
        return -math.inf
    simulated = point[0] + simulate_oe(theta, u - point[1:], structure)
    return nrmse_fit(y[split:], simulated[split:])


def search(y: np.ndarray, u: np.ndarray, split: int, orders: Sequence[int],
           delays: Sequence[int]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Fit batch OE for every order and delays; return the chosen candidate and all."""
    point = np.concatenate([[y[:split].mean()], u[:split].mean(axis=0)])
    centred_y, centred_u = y - point[0], u - point[1:]
    candidates = []
    for order in orders:
        for delay in itertools.product(delays, repeat=u.shape[1]):
            structure = Structure(order, u.shape[1], delay)
            try:
                result = fit_oe(centred_y[:split], centred_u[:split], structure)
            except ValueError as error:
                candidates.append({'order': order, 'delay': list(delay), 'error': str(error)})
                continue
            candidates.append({'order': order, 'delay': list(delay),
                               'fit': validation_fit(result.theta, structure, y, u, point,
                                                     split),
                               'theta': result.theta.tolist(), 'stable': result.stable})
    usable = [c for c in candidates if math.isfinite(c.get('fit', -math.inf))]
    best = max(c['fit'] for c in usable)
    good = [c for c in usable if c['fit'] >= best - MARGIN]
    smallest = min(c['order'] for c in good)
    chosen = max((c for c in good if c['order'] == smallest), key=lambda c: c['fit'])
    return chosen, candidates


def batch_fit(y: np.ndarray, u: np.ndarray, split: int, order: int,
              delay: Sequence[int]) -> float:
    """Return the validation fit of the batch OE model of one structure."""
    point = np.concatenate([[y[:split].mean()], u[:split].mean(axis=0)])
    structure = Structure(order, u.shape[1], delay)
    result = fit_oe(y[:split] - point[0], u[:split] - point[1:], structure)
    return validation_fit(result.theta, structure, y, u, point, split)


def online(name: str, y: np.ndarray, u: np.ndarray, split: int, order: int,
           delay: Sequence[int], gate: float) -> dict[str, Any]:
    """Run one online estimator over the raw estimation half; return fit, validity, refusals."""
    structure = Structure(order, u.shape[1], delay)
    try:
        estimator = make_estimator(name, order=order, num_inputs=u.shape[1], input_delay=delay,
                                   detrend='mean', outlier_threshold=gate)
        for t in range(split):
            estimator.update(float(y[t]), u[t])
    except Exception as error:  # noqa: B902 -- a crash is a finding, recorded per case
        return {'error': f'{type(error).__name__}: {error}', 'fit': -math.inf, 'valid': False}
    theta = estimator.theta
    return {'fit': validation_fit(theta, structure, y, u, estimator.operating_point, split),
            'valid': bool(estimator.valid), 'reasons': list(estimator.validity_reasons),
            'refused': estimator.flags.get('outlier_rejected', 0) / split,
            'flags': dict(estimator.flags), 'theta': theta.tolist(), 'error': None}


def text(fit: float) -> str:
    """Return a fit for the table ('unstable' when the simulation diverged)."""
    return f'{fit:.1f}' if math.isfinite(fit) else 'unstable'


def evaluate(name: str, plant: str, data: np.ndarray, estimators: Sequence[str],
             orders: Sequence[int], delays: Sequence[int]) -> dict[str, Any]:
    """Return the JSON row of one record."""
    y, u = data[:, 0], data[:, 1:]
    split = y.size // 2
    start = time.perf_counter()
    chosen, candidates = search(y, u, split, orders, delays)
    seconds = time.perf_counter() - start
    structures = {'chosen': (chosen['order'], tuple(chosen['delay']), 'batch OE search')}
    if plant in PUBLISHED and len(PUBLISHED[plant][1]) == u.shape[1]:
        structures['published'] = PUBLISHED[plant]
    row: dict[str, Any] = {'record': name, 'samples': int(y.size), 'inputs': int(u.shape[1]),
                           'search_seconds': seconds, 'candidates': candidates,
                           'structures': {}}
    for kind, (order, delay, source) in structures.items():
        entry: dict[str, Any] = {'order': order, 'delay': list(delay), 'source': source,
                                 'batch_fit': batch_fit(y, u, split, order, delay),
                                 'online': {}}
        for estimator in estimators:
            entry['online'][estimator] = {str(gate): online(estimator, y, u, split, order,
                                                            delay, gate) for gate in GATES}
        row['structures'][kind] = entry
    return row


def tables(rows: list[dict[str, Any]], estimators: Sequence[str]) -> str:
    """Return the markdown tables: structures and batch fits, then the online estimators."""
    first = []
    for row in rows:
        for kind, entry in row['structures'].items():
            first.append([row['record'], kind, f'n={entry["order"]} d={entry["delay"]}',
                          text(entry['batch_fit']), entry['source']])
    gate, off = (str(g) for g in GATES)
    second = []
    for row in rows:
        for kind, entry in row['structures'].items():
            for estimator in estimators:
                on, free = entry['online'][estimator][gate], entry['online'][estimator][off]
                second.append([
                    row['record'], kind, estimator, text(entry['batch_fit']),
                    text(on['fit']) + (' (error)' if on['error'] else ''),
                    _validity(on), f'{100 * on.get("refused", 0.0):.1f} %',
                    text(free['fit']) + (' (error)' if free['error'] else ''),
                    _validity(free)])
    return (markdown_table(('record', 'structure', 'n, delays', 'batch OE fit (%)', 'source'),
                           first) + '\n'
            + markdown_table(('record', 'structure', 'estimator', 'batch OE fit',
                              f'fit, gate {GATES[0]:g}', f'valid, gate {GATES[0]:g}',
                              'refused by the gate', 'fit, gate off', 'valid, gate off'),
                             second))


def _validity(result: dict[str, Any]) -> str:
    if result['error']:
        return result['error']
    if result['valid']:
        return 'valid'
    return 'invalid: ' + '; '.join(result['reasons']) if result['reasons'] else 'invalid'


def _range(value: str) -> list[int]:
    low, _, high = value.partition('-')
    return list(range(int(low), int(high or low) + 1))


def _finite(value: Any) -> Any:
    """Return ``value`` with non-finite floats as None (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(item) for item in value]
    return value


def main(argv: list[str] | None = None) -> int:
    """Run every record under --data and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument('--data', type=Path, required=True,
                        help='folder with one sub-folder of data*.csv per plant')
    parser.add_argument('--estimators', default=None,
                        help='comma-separated registry names (default: the open-loop ones)')
    parser.add_argument('--orders', default='1-6', help='batch OE orders searched, A-B')
    parser.add_argument('--delays', default='0-4', help='delays searched per input, A-B')
    parser.add_argument('--json', type=Path, default=None, help='write the rows here')
    args = parser.parse_args(argv)
    names = args.estimators.split(',') if args.estimators else default_estimators()
    unknown = [name for name in names if name not in ESTIMATORS]
    if unknown:
        parser.error(f'unknown estimator(s) {", ".join(unknown)}')
    found = records(args.data)
    closed_loop = args.data / 'emps'
    if not found and not (closed_loop / 'estimation.csv').exists():
        parser.error(f'no */data*.csv or emps/estimation.csv under {args.data}')
    rows = []
    for name, plant, data in found:
        row = evaluate(name, plant, data, names, _range(args.orders), _range(args.delays))
        rows.append(row)
        chosen = row['structures']['chosen']
        print(f'{name}: batch OE n={chosen["order"]} d={chosen["delay"]} fit '
              f'{text(chosen["batch_fit"])} ({row["search_seconds"]:.1f} s search)',
              file=sys.stderr, flush=True)
    if found:
        print('Data: DaISy (De Moor, KU Leuven, "DaISy: Database for the Identification of '
              'Systems").\n')
        print(tables(rows, names))
    output: dict[str, Any] = {'records': rows}
    if (closed_loop / 'estimation.csv').exists():
        output['emps'] = emps.run(closed_loop)
        print('\nEMPS (Janot, Gautier and Brunot 2019), closed loop, order 2:\n')
        print(emps.table(output['emps']))
    if args.json is not None:
        args.json.write_text(json.dumps(_finite(output), indent=1))
        print(f'wrote {args.json}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
