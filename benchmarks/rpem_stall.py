"""
The slowest single update of rpem while its batch fits run (SPEC §16: no update waits on a fit).

A second-order output-error plant (config/payload_change.yaml's: its gain and poles change
at sample 12,000 of 20,000), a binary input held 4 samples, rpem with lambda 0.999 (fits on
a sliding schedule), the samples fed at a real rate (1 kHz by default; the feeding sleeps
between samples, as a node waits for its next message) so that the fits have the time a
node gives them. Prints the five slowest updates, how many took over 10 ms (the bound) and
over 5 ms (the margin aimed at), and delta at the end, in wall time and in the CPU time of
the feeding thread (on a shared machine the wall time of an update also counts the time
other processes held the core). Run the same command on two commits to compare
(docs/tracking.md quotes one run).

    .venv/bin/python -m benchmarks.rpem_stall [--rate HZ] [--samples N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bcid_ros.estimators import make_estimator
from bcid_ros.simulation.custom import CustomScenario
from bcid_ros.simulation.plant import ChangingStream

PLANT = dict(plant_denominator=[1.0, -1.5, 0.7], plant_numerator=[0.0, 1.0, 0.5],
             noise_variance=0.04, input_signal='binary', input_hold=4)
AFTER = dict(PLANT, plant_denominator=[1.0, -1.6, 0.8], plant_numerator=[0.0, 0.6, 0.3])


def update_times(samples: int, change: int, rate: float, seed: int = 0) -> dict:
    """Feed rpem at ``rate`` Hz; return every update's seconds, the final delta and the flags."""
    before, after = CustomScenario(**PLANT), CustomScenario(**AFTER)
    y, u = ChangingStream(before, np.random.default_rng(seed), after=after,
                          change_after=change).take(samples)
    estimator = make_estimator('rpem', order=2, forgetting_factor=0.999)
    seconds, cpu = np.zeros(samples), np.zeros(samples)
    start = time.perf_counter()
    for t in range(samples):
        wait = start + t / rate - time.perf_counter()
        if wait > 0.0:
            time.sleep(wait)
        began, began_cpu = time.perf_counter(), time.thread_time()
        estimator.update(float(y[t]), u[t])
        seconds[t] = time.perf_counter() - began
        cpu[t] = time.thread_time() - began_cpu
    truth = after.truth().parameters
    return {'seconds': seconds, 'cpu': cpu, 'fits': estimator.fits, 'flags': dict(estimator.flags),
            'delta': float(np.linalg.norm(estimator.theta - truth) / np.linalg.norm(truth))}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--rate', type=float, default=1000.0)
    parser.add_argument('--samples', type=int, default=20000)
    args = parser.parse_args(argv)
    result = update_times(args.samples, int(0.6 * args.samples), args.rate)
    for clock in ('seconds', 'cpu'):
        seconds = result[clock]
        slowest = np.argsort(seconds)[::-1][:5]
        print(f'slowest updates ({clock}, ms):',
              ', '.join(f'{1e3 * seconds[k]:.1f} at {k}' for k in slowest))
        print(f'updates over 10 ms: {int((seconds > 0.01).sum())}; over 5 ms: '
              f'{int((seconds > 0.005).sum())}; median {1e6 * float(np.median(seconds)):.1f} us')
    print(f'fits {result["fits"]}; flags {result["flags"]}; final delta '
          f'{100 * result["delta"]:.2f} %')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
