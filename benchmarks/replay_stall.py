"""
The slowest updates of rls and bcrls at their detected plant changes (SPEC §16: no update waits).

At a detection the estimate restarts and replays the kept samples after the change point
(at most RESTART_SPAN), spread over the next updates (rls.REPLAY_SLICE rows each). On the
tracking cases (benchmarks/tracking.py, each estimator on plants of its own model, as
``--model-holds``) this feeds every sample by ``update`` and times it in the CPU time of
the feeding thread (on a shared machine the wall time of an update also counts the time
other processes held the core), and prints per seed and estimator the slowest update
within ``WINDOW`` updates from each detection (the detection's own and its catch-up's),
the slowest update anywhere, and the cases whose slowest detection update is over 5 ms.
``--batched K`` runs the batched estimator over the seed's first K cases of one structure
instead (one frame per sample) and times the frames. ``--joints K`` runs it over K joints
of the simulator's ``joints`` scenario (random second-order plants, PRBS efforts) whose
gains all grow by half at one sample (a payload on every joint), so that the plants detect
and catch up together. Run the same command on two commits to compare.

    .venv/bin/python -m benchmarks.replay_stall [--seeds 0,1,2] [--count 30] [--batched K]
        [--joints K]
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from scipy import signal

from benchmarks.tracking import MODELS, TrackingCase
from bcid_ros.blas_threads import single_threaded_blas
from bcid_ros.estimators import make_batched_estimator, make_estimator
from bcid_ros.simulation.joints import draw_plants

#: A detection's update and the next ones, over which its replay's cost is counted.
WINDOW = 16

#: ``--joints``: the samples, the sample at which every gain changes, and by what factor.
JOINT_SAMPLES, JOINT_CHANGE, JOINT_GAIN = 6000, 3000, 1.5


def detection_times(times: np.ndarray, detections: np.ndarray) -> np.ndarray:
    """Return, per detection, the slowest of the ``WINDOW`` updates from it."""
    return np.array([times[t:t + WINDOW].max() for t in np.flatnonzero(detections)])


def timed_updates(estimator: Any, y: np.ndarray, u: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Feed every sample (or frame); return each update's CPU seconds and its detections."""
    times = np.zeros(y.shape[0])
    detections = np.zeros(y.shape[0], dtype=bool)
    before = 0
    for t in range(y.shape[0]):
        start = time.thread_time()
        estimator.update(y[t], u[t])
        times[t] = time.thread_time() - start
        # (a batched estimator counts per plant)
        flagged = int(np.sum(estimator.flags.get('plant_change', 0)))
        detections[t], before = flagged > before, flagged
    times[:10] = 0.0  # the first updates load modules
    return times, detections


def single_run(case: TrackingCase, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Feed one case to a single-plant estimator; return each update's CPU seconds and flags."""
    estimator = make_estimator(name, order=case.order, num_inputs=case.num_inputs)
    return timed_updates(estimator, case.y, case.u)


def batched_run(cases: list[TrackingCase], name: str) -> tuple[np.ndarray, np.ndarray]:
    """Feed K cases of one structure to the batched estimator; return each frame's CPU seconds."""
    count = min(case.samples for case in cases)
    estimator = make_batched_estimator(name, len(cases), order=cases[0].order,
                                       num_inputs=cases[0].num_inputs)
    y = np.column_stack([case.y[:count] for case in cases])
    u = np.stack([case.u[:count] for case in cases], axis=1)
    return timed_updates(estimator, y, u)


def joints_data(num_joints: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Return y, u of shape (N, K), (N, K, 1): K joints, every gain JOINT_GAIN x at once."""
    rng = np.random.default_rng(seed)
    theta, sigma2 = draw_plants(num_joints, rng)
    u = rng.choice([-1.0, 1.0], size=(JOINT_SAMPLES, num_joints))
    y = np.sqrt(sigma2) * rng.standard_normal((JOINT_SAMPLES, num_joints))
    gain = np.where(np.arange(JOINT_SAMPLES) < JOINT_CHANGE, 1.0, JOINT_GAIN)
    for k in range(num_joints):
        # B(q) scaled: the output of the new plant is the old one's times the factor
        y[:, k] += gain * signal.lfilter(np.r_[0.0, theta[k, 2:]], np.r_[1.0, theta[k, :2]],
                                         u[:, k])
    return y, u[:, :, None]


def report(label: str, runs: list[tuple[str, np.ndarray, np.ndarray]]) -> None:
    """Print the slowest detection updates of ``runs`` (case label, times, detections)."""
    at = [(case, detection_times(times, detections)) for case, times, detections in runs]
    slowest = max((float(d.max()) for _, d in at if d.size), default=0.0)
    count = sum(d.size for _, d in at)
    over = sum(int((d > 0.010).sum()) for _, d in at)
    anywhere = max(float(times.max()) for _, times, _ in runs)
    median = float(np.median(np.concatenate([times[10:] for _, times, _ in runs])))
    print(f'{label}: {count} detections; slowest update within {WINDOW} of one '
          f'{1e3 * slowest:.1f} ms (over 10 ms at {over}); slowest anywhere '
          f'{1e3 * anywhere:.1f} ms; median {1e6 * median:.0f} us')
    worst = [f'{case} {1e3 * float(d.max()):.1f}' for case, d in at if d.size and d.max() > 0.005]
    if worst:
        print('  over 5 ms (case ms):', ', '.join(worst))


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--seeds', default='0,1,2')
    parser.add_argument('--count', type=int, default=30)
    parser.add_argument('--estimators', default='rls,bcrls')
    parser.add_argument('--batched', type=int, default=0, help='plants of a batched run')
    parser.add_argument('--joints', type=int, default=0,
                        help='joints of a batched run, all changing at once')
    args = parser.parse_args(argv)
    with single_threaded_blas():  # as in a node (docs/nodes.md, "One BLAS thread")
        run(args)
    return 0


def run(args: argparse.Namespace) -> None:
    """Print the figures of every seed and estimator ``args`` names."""
    for seed in (int(s) for s in args.seeds.split(',')):
        for name in args.estimators.split(','):
            if args.joints:
                estimator = make_batched_estimator(name, args.joints, order=2, num_inputs=1)
                times, detections = timed_updates(estimator, *joints_data(args.joints, seed))
                report(f'seed {seed} {name} {args.joints} joints changing at once',
                       [('frames', times, detections)])
                continue
            cases = [TrackingCase((seed, k), MODELS[name]) for k in range(args.count)]
            if args.batched:
                first = cases[0]
                same = [c for c in cases if (c.order, c.num_inputs) ==
                        (first.order, first.num_inputs)][:args.batched]
                times, detections = batched_run(same, name)
                report(f'seed {seed} {name} batched x{len(same)} (order {first.order}, '
                       f'{first.num_inputs} inputs)', [('frames', times, detections)])
                continue
            runs = [(f'({seed},{k})', *single_run(case, name)) for k, case in enumerate(cases)]
            report(f'seed {seed} {name}', runs)


if __name__ == '__main__':
    raise SystemExit(main())
