"""
Monte Carlo of the committed bags' replay error, to set the replay-test tolerances.

For each scenario bag, run the estimator of ``config/<scenario>.yaml`` over M
fresh realisations of the bag's length (seeds 1000 ... 1000 + M - 1, never the
bag's own seed) and print the mean, standard deviation and largest value of
the relative error delta = ||theta_hat - theta|| / ||theta|| of the final
estimate, compensated and uncompensated: mean, std, median, 99th percentile
and largest value. ``test/bag/test_bag.py`` bounds the committed bag's delta by
the 99th percentile (some of these distributions are heavy-tailed, so a
mean + k std bound would mean little).

Run from the repository root (about 5 minutes on one core):

    nice -n 10 .venv/bin/python bags/convergence_mc.py --runs 100
"""

import argparse
import time

import numpy as np

from bcid_ros.identifier.parameters import estimator_from_parameters, load_yaml_parameters
from bcid_ros.reproduction.common import markdown_table
from bcid_ros.simulation import make_scenario

BAGS = {'ding_miso': 10000, 'ding_miso_nonstationary': 10000, 'ikenoue_colored': 10000,
        'ikenoue_white_input': 10000, 'ikeda_closed_loop': 4096}


def delta(estimate, truth):
    """Return ||estimate - truth|| / ||truth||."""
    return float(np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def main():
    """Print one Markdown table row per bag."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--runs', type=int, default=100)
    parser.add_argument('scenarios', nargs='*', default=list(BAGS))
    args = parser.parse_args()
    rows = []
    for name in args.scenarios:
        values = load_yaml_parameters(f'config/{name}.yaml')
        scenario = make_scenario(name)
        truth = scenario.truth().parameters
        compensated, uncompensated = [], []
        start = time.perf_counter()
        for run in range(args.runs):
            estimator = estimator_from_parameters(values)
            y, u = scenario.simulate(BAGS[name], 1000 + run)
            for t in range(y.shape[0]):
                estimator.update(y[t], u[t])
            compensated.append(delta(estimator.theta, truth))
            uncompensated.append(delta(estimator.theta_uncompensated, truth))
        c, w = np.array(compensated), np.array(uncompensated)
        rows.append([name, values['estimator'], BAGS[name], args.runs,
                     f'{100 * c.mean():.3f}', f'{100 * c.std(ddof=1):.3f}',
                     f'{100 * np.median(c):.3f}', f'{100 * np.percentile(c, 99):.3f}',
                     f'{100 * c.max():.3f}', f'{100 * w.mean():.3f}',
                     f'{100 * np.median(w):.3f}', f'{time.perf_counter() - start:.0f}'])
        print(' | '.join(str(x) for x in rows[-1]), flush=True)
    print(markdown_table(['bag', 'estimator', 'N', 'M', 'δ mean %', 'δ std %', 'δ median %',
                          'δ p99 %', 'δ max %', 'uncompensated δ mean %',
                          'uncompensated δ median %', 'wall s'], rows))


if __name__ == '__main__':
    main()
