"""
Measured data (DaISy): the online estimators' validation fit beside the batch OE model's.

Usage: ``.venv/bin/python -m benchmarks.realdata --data DIR [--estimators rls,bcrls]
[--orders 1-6] [--delays 0-4] [--json OUT] [--no-emps]`` from the repository root, where DIR
holds one folder per plant with ``data.csv`` (or ``data_y1.csv``, ``data_y2.csv``, one MISO problem
each), header ``y,u1[,u2]``, one sample per row: the DaISy records (De Moor, KU Leuven,
"DaISy: Database for the Identification of Systems") are not part of the repository.
Progress goes to stderr, the markdown tables to stdout (docs/accuracy.md). A folder ``emps``
with ``estimation.csv`` and ``validation.csv`` (the EMPS closed-loop benchmark) is run by
:mod:`benchmarks.emps`.

Protocol, per record: the first half estimates, the second validates. The operating point
is the means of the estimation half; the batch model is fitted to the centred estimation
half. The fit of a model is the NRMSE fit 100 (1 - ||y - yhat|| / ||y - mean(y)||) on the
validation half of its simulated output, yhat = y0 + sum_i B_i/F (u_i - u0_i), simulated from
rest over the whole record so that the start-up transient falls in the estimation half (as
``bcid analyze`` does). The batch OE structure is chosen by that validation fit over the
orders and per-input delays given: the smallest order within ``MARGIN`` points of the best
fit, then its best delays. Each online estimator is replayed as a user runs it: ``bcid
replay`` (:func:`bcid_ros.bag.replay.replay`) of a CSV log of the raw estimation half with
that structure (and with the one the plant's literature gives, :data:`PUBLISHED`) and
``detrend: mean``, every other parameter at the identifier's default; its own operating point
enters its simulation. Per record and structure the three goals of :func:`checks` are printed:
no estimator valid while more than ``FAR`` points below the batch OE model; rpem within
``RPEM_CLOSE`` points, and valid wherever within ``RPEM_VALID`` points of a linear plant; a
bcrls estimate that ends unstable names it as its first reason.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path
import sys
import tempfile
import time
from typing import Any, Sequence

import numpy as np

from benchmarks import emps
from benchmarks.realistic import default_estimators
from bcid_ros.analysis.metrics import nrmse_fit
from bcid_ros.analysis.pem import fit_oe, simulate_oe, Structure
from bcid_ros.bag.replay import replay
from bcid_ros.estimators import ESTIMATORS
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients, spectral_radii
from bcid_ros.markdown import markdown_table

#: A structure within this many fit points of the best one counts as as good.
MARGIN = 1.0
#: Goal: no estimator valid while more than this many fit points below the batch OE model.
FAR = 15.0
#: Goal: rpem within this many fit points of the batch OE model on every record ...
RPEM_CLOSE = 5.0
#: ... and valid wherever it is within this many points of a linear plant's batch OE model.
RPEM_VALID = 2.0
#: Words of a reason that names an unstable or diverging estimate (rules.unstable_models,
#: bcrls's compensation checks).
INSTABILITY_WORDS = ('unstable', 'diverg')
#: Plants whose literature does not treat them as linear (the rpem validity goal is waived):
#: none of the four DaISy plants (each is published with linear models).
NONLINEAR: dict[str, str] = {}
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
           delay: Sequence[int], folder: Path) -> dict[str, Any]:
    """
    Replay one online estimator over the raw estimation half as ``bcid replay`` does.

    The estimation half is written to a CSV log in ``folder`` (header ``y,u1,...``, every
    float in full) and replayed through :func:`bcid_ros.bag.replay.replay` with the
    parameters a user sets: the estimator, the structure and ``detrend: mean``, everything
    else at the identifier's defaults. Returns the fit, the verdict, its reasons, the pole
    radius of the final model and the flag counts.
    """
    structure = Structure(order, u.shape[1], delay)
    log = folder / 'estimation.csv'
    if not log.exists():
        header = ','.join(['y'] + [f'u{i + 1}' for i in range(u.shape[1])])
        np.savetxt(log, np.column_stack([y[:split], u[:split]]), delimiter=',', fmt='%.17g',
                   header=header, comments='')
    parameters = {'estimator': name, 'order': order, 'num_inputs': int(u.shape[1]),
                  'input_delay': [int(d) for d in delay], 'detrend': 'mean'}
    try:
        result = replay(log, parameters, trajectory=False)
    except Exception as error:  # noqa: B902 -- a crash is a finding, recorded per case
        return {'error': f'{type(error).__name__}: {error}', 'fit': -math.inf, 'valid': False,
                'reasons': [], 'radius': math.inf}
    theta = np.asarray(result.theta, dtype=float)
    point = (result.operating_point if result.operating_point is not None
             else np.zeros(1 + u.shape[1]))
    return {'fit': validation_fit(theta, structure, y, u, np.asarray(point), split),
            'valid': bool(result.valid), 'reasons': list(result.validity_reasons),
            'radius': float(spectral_radii(theta[None, :order])[0]),
            'flags': dict(result.flags), 'theta': theta.tolist(), 'error': None}


def checks(entry: dict[str, Any], linear: bool) -> dict[str, dict[str, Any]]:
    """
    Return the three goals of one record and structure, each ``{'passed', 'detail'}``.

    ``far_and_valid``: no estimator valid while more than :data:`FAR` fit points below the
    batch OE model. ``rpem``: within :data:`RPEM_CLOSE` points, and valid wherever within
    :data:`RPEM_VALID` points of a ``linear`` plant. ``bcrls_unstable``: a final bcrls model
    with a pole on or beyond the unit circle (or a simulation that diverges) names it as its
    first reason.
    """
    batch = entry['batch_fit']
    runs = entry['online']
    gaps = {name: batch - run['fit'] for name, run in runs.items()}
    far = [f'{name} valid at {text(runs[name]["fit"])} ({_gap(gaps[name])})'
           for name in runs if runs[name]['valid'] and gaps[name] > FAR]
    out = {'far_and_valid': {'passed': not far, 'detail': '; '.join(far) or 'none'}}
    if 'rpem' in runs:
        run, gap = runs['rpem'], gaps['rpem']
        close = gap <= RPEM_CLOSE
        owes_validity = linear and gap <= RPEM_VALID
        out['rpem'] = {'passed': close and (run['valid'] or not owes_validity),
                       'detail': f'{text(run["fit"])}, {_gap(gap)}, ' + _validity(run)}
    if 'bcrls' in runs and not runs['bcrls']['error']:
        run = runs['bcrls']
        unstable = not (run['radius'] < 1.0) or not math.isfinite(run['fit'])
        named = next((k for k, reason in enumerate(run['reasons'])
                      if any(word in reason for word in INSTABILITY_WORDS)), None)
        waiting = next((k for k, reason in enumerate(run['reasons']) if 'not ready' in reason),
                       None)
        said = named is not None and (waiting is None or named < waiting)
        out['bcrls_unstable'] = {
            'passed': not unstable or (not run['valid'] and said),
            'detail': (f'pole radius {run["radius"]:.3g}: '
                       + (f'says "{run["reasons"][named]}"' if said else 'NOT said')
                       if unstable else f'stable (pole radius {run["radius"]:.3g})')}
    return out


def _gap(gap: float) -> str:
    """Return a fit difference to the batch model in words."""
    return f'{abs(gap):.1f} points ' + ('below' if gap >= 0 else 'above')


def text(fit: float) -> str:
    """Return a fit for the table ('unstable' when the simulation diverged)."""
    return f'{fit:.1f}' if math.isfinite(fit) else 'unstable'


def run_text(run: dict[str, Any]) -> str:
    """Return an online estimator's fit for the table ('refused' when it did not run)."""
    return 'refused' if run['error'] else text(run['fit'])


def evaluate(name: str, plant: str, data: np.ndarray, estimators: Sequence[str],
             orders: Sequence[int], delays: Sequence[int]) -> dict[str, Any]:
    """Return the JSON row of one record: its structures, the replays and the goals."""
    y, u = data[:, 0], data[:, 1:]
    split = y.size // 2
    start = time.perf_counter()
    chosen, candidates = search(y, u, split, orders, delays)
    seconds = time.perf_counter() - start
    structures = {'chosen': (chosen['order'], tuple(chosen['delay']), 'batch OE search')}
    if plant in PUBLISHED and len(PUBLISHED[plant][1]) == u.shape[1]:
        structures['published'] = PUBLISHED[plant]
    row: dict[str, Any] = {'record': name, 'samples': int(y.size), 'inputs': int(u.shape[1]),
                           'linear': plant not in NONLINEAR,
                           'search_seconds': seconds, 'candidates': candidates,
                           'structures': {}}
    with tempfile.TemporaryDirectory() as folder:
        for kind, (order, delay, source) in structures.items():
            entry: dict[str, Any] = {'order': order, 'delay': list(delay), 'source': source,
                                     'batch_fit': batch_fit(y, u, split, order, delay),
                                     'online': {}}
            for estimator in estimators:
                entry['online'][estimator] = online(estimator, y, u, split, order, delay,
                                                    Path(folder))
            entry['checks'] = checks(entry, row['linear'])
            row['structures'][kind] = entry
    return row


def tables(rows: list[dict[str, Any]], estimators: Sequence[str]) -> str:
    """Return the markdown tables: structures and batch fits, the replays, the goals."""
    first, second, third = [], [], []
    for row in rows:
        for kind, entry in row['structures'].items():
            first.append([row['record'], kind, f'n={entry["order"]} d={entry["delay"]}',
                          text(entry['batch_fit']), entry['source']])
            for estimator in estimators:
                run = entry['online'][estimator]
                second.append([row['record'], kind, estimator, text(entry['batch_fit']),
                               run_text(run), '' if run['error'] else f'{run["radius"]:.3g}',
                               _validity(run)])
            for goal, result in entry['checks'].items():
                third.append([row['record'], kind, goal, 'pass' if result['passed'] else 'FAIL',
                              result['detail']])
    return (markdown_table(('record', 'structure', 'n, delays', 'batch OE fit (%)', 'source'),
                           first) + '\n'
            + markdown_table(('record', 'structure', 'estimator', 'batch OE fit', 'fit',
                              'pole radius', 'verdict'), second) + '\n'
            + markdown_table(('record', 'structure', 'goal', 'result', 'detail'), third))


def summary(rows: list[dict[str, Any]]) -> str:
    """Return one line per goal: on how many record-structures it holds, and where not."""
    lines = []
    goals = dict.fromkeys(goal for row in rows for entry in row['structures'].values()
                          for goal in entry['checks'])
    for goal in goals:
        results = [(f'{row["record"]} ({kind})', entry['checks'][goal]['passed'])
                   for row in rows for kind, entry in row['structures'].items()
                   if goal in entry['checks']]
        failed = [where for where, passed in results if not passed]
        lines.append(f'{goal}: {len(results) - len(failed)} of {len(results)} pass'
                     + (f'; fails on {", ".join(failed)}' if failed else ''))
    return '\n'.join(lines)


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
    parser.add_argument('--no-emps', action='store_true', help='skip the EMPS closed loop')
    args = parser.parse_args(argv)
    names = args.estimators.split(',') if args.estimators else default_estimators()
    unknown = [name for name in names if name not in ESTIMATORS]
    if unknown:
        parser.error(f'unknown estimator(s) {", ".join(unknown)}')
    found = records(args.data)
    closed_loop = args.data / 'emps'
    has_loop = not args.no_emps and (closed_loop / 'estimation.csv').exists()
    if not found and not has_loop:
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
        print(summary(rows))
    output: dict[str, Any] = {'records': rows}
    if has_loop:
        output['emps'] = emps.run(closed_loop)
        print('\nEMPS (Janot, Gautier and Brunot 2019), closed loop, order 2:\n')
        print(emps.table(output['emps']))
    if args.json is not None:
        args.json.write_text(json.dumps(_finite(output), indent=1))
        print(f'wrote {args.json}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
