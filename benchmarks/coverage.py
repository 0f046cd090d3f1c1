"""
Monte Carlo coverage of ``parameter_std`` for bciv and cl_bcls (docs/estimators.md).

Each run simulates a committed scenario with its own seed, runs the estimator
of the scenario's config over it and counts, per parameter, whether the truth
lies within theta +- 2 std. Run ``nice -n 10 .venv/bin/python -m
benchmarks.coverage CASE --samples N --runs R`` (CASE: see :data:`CASES`);
it prints one markdown table row. A run whose std is None counts as a miss.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import numpy as np

from bcid_ros.estimators import make_estimator
from bcid_ros.identifier.parameters import (check_identifier_parameters, estimator_from_parameters,
                                            load_yaml_parameters)
from bcid_ros.resources import config_file
from bcid_ros.simulation import make_scenario

#: Case -> (scenario, estimator source): 'config' is the scenario's committed
#: config/<scenario>.yaml, 'scenario' the estimator defaults with the
#: scenario's own settings (cl_bcls: window 0, every sample since the change).
CASES = {
    'bciv_colored': ('ikenoue_colored', 'config'),
    'bciv_white': ('ikenoue_white_input', 'config'),
    'cl_bcls_all_data': ('ikeda_closed_loop', 'scenario'),
    'cl_bcls_window': ('ikeda_closed_loop', 'config'),
}
#: P(|z| <= 2) for a standard normal z.
NOMINAL = math.erf(2.0 / math.sqrt(2.0))


def build(case: str) -> Any:
    """Return a fresh estimator of ``case``."""
    scenario, source = CASES[case]
    if source == 'config':
        values = check_identifier_parameters(load_yaml_parameters(config_file(scenario)))
        return estimator_from_parameters(values)
    return make_estimator('cl_bcls', **make_scenario(scenario).estimator_settings())


def coverage(case: str, samples: int, runs: int,
             seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the per-run, per-parameter inside indicator, the z-scores and ``valid``."""
    scenario = make_scenario(CASES[case][0])
    truth = scenario.truth().parameters
    inside = np.zeros((runs, truth.shape[0]), dtype=bool)
    scores = np.full((runs, truth.shape[0]), np.nan)
    valid = np.zeros(runs, dtype=bool)
    for run in range(runs):
        y, u = scenario.simulate(samples, seed + run)
        estimator = build(case)
        estimator.run(y, u)
        valid[run] = estimator.valid
        std = estimator.parameter_std
        if std is None:
            continue
        scores[run] = (estimator.theta - truth) / std
        inside[run] = np.abs(scores[run]) <= 2.0
    return inside, scores, valid


def main(argv: list[str] | None = None) -> None:
    """Print the coverage row of one case."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('case', choices=sorted(CASES))
    parser.add_argument('--samples', type=int, default=1000)
    parser.add_argument('--runs', type=int, default=200)
    parser.add_argument('--seed', type=int, default=50_000)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    inside, scores, valid = coverage(args.case, args.samples, args.runs, args.seed)
    shares = ' '.join(f'{100 * s:.1f}' for s in inside.mean(axis=0))
    # the median |z| of a standard normal is 0.674: a robust check of the std's scale
    medians = ' '.join(f'{s:.2f}' for s in np.nanmedian(np.abs(scores), axis=0))
    missing = int(np.isnan(scores[:, 0]).sum())
    on_valid = f'{100 * inside[valid].mean():.1f}' if valid.any() else '-'
    print(f'| {args.case} | {args.samples} | {args.runs} | {shares} | '
          f'{100 * inside.mean():.1f} | {valid.sum()}: {on_valid} | median abs z {medians}; '
          f'no std {missing}; {time.perf_counter() - start:.0f} s |')


if __name__ == '__main__':
    main()
