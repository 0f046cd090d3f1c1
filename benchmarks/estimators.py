"""
Per-sample estimator cost against the floor, the naive batch way and a peer, in one run.

Each per-sample figure is the best of three repeats (by median), floor and peer alike.

The floor is a bare textbook numpy RLS update of the same size written inline here
(rpem, OE and ARMAX, is held at 3× it: its median is the recursion, its mean adds the
batch fits of its start);
the naive way re-solves the batch problem over all data so far at every sample
(timed at N = 1000); the peer is padasip's FilterRLS of the same size.

Many plants: the batched rls and bcrls update all K plants of the `joints` scenario
(n = 2, r = 1) in one call, with the single-plant safeguards at their defaults (units,
transaction, the gate at its 1e6 limit, validity); the figure is the median time of one
call divided by K, against the single-plant update of the same structure timed in the same
run. The
JointState demultiplexer (names matched to joints, both fields taken out) is timed per
message on messages shaped as rclpy delivers them, the joints listed in reverse order.
"""

from __future__ import annotations

import array
import importlib.util
import time
import types

import numpy as np

from benchmarks.common import best_of, per_sample_us, Result, summary, time_each
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators import make_batched_estimator
from bcid_ros.estimators.bcrls import bcls_fixed_point
from bcid_ros.estimators.regressor import ArxRegressor
from bcid_ros.identifier.joint_demux import JointStateDemux
from bcid_ros.identifier.parameters import (check_identifier_parameters, estimator_from_parameters,
                                            load_yaml_parameters)
from bcid_ros.resources import config_file
from bcid_ros.simulation import make_scenario

SECTION = 'estimator cost'
NAIVE_N = 1000
#: Plant counts of the batched update, and the one the target is held at.
BATCHED_PLANTS = (10, 100, 1000)
BATCHED_TARGET_PLANTS = 100
BATCHED_TARGET_US = 2.0


def floor_rls_us(phi: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Time a bare inline numpy RLS update per sample (the floor)."""
    p = 1e6 * np.eye(phi.shape[1])
    theta = np.zeros(phi.shape[1])
    clock = time.perf_counter_ns
    times = np.empty(len(y))
    for t in range(len(y)):
        start = clock()
        x = phi[t]
        g = p @ x
        k = g / (1.0 + x @ g)
        theta = theta + k * (y[t] - x @ theta)
        p = p - np.outer(k, g)
        times[t] = clock() - start
    return times / 1000.0


def naive_lstsq_us(y: np.ndarray, u: np.ndarray, at: int, repeats: int = 30) -> float:
    """Time building Phi from the first ``at`` samples and one np.linalg.lstsq (median, us)."""
    regressor = ArxRegressor(2, 2, False)
    times = []
    for _ in range(repeats):
        start = time.perf_counter_ns()
        phi = regressor.regressors(y[:at], u[:at])
        np.linalg.lstsq(phi, y[2:at], rcond=None)
        times.append(time.perf_counter_ns() - start)
    return float(np.median(times)) / 1000.0


def naive_bcls_us(y: np.ndarray, u: np.ndarray, at: int, repeats: int = 30) -> float:
    """Time one batch BCLS fixed point (eq. 24) over the first ``at`` samples (median, us)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter_ns()
        bcls_fixed_point(y[:at], u[:at], order=2, num_inputs=2)
        times.append(time.perf_counter_ns() - start)
    return float(np.median(times)) / 1000.0


def padasip_us(phi: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """Time padasip's FilterRLS.adapt per sample, or None if padasip is not installed."""
    if importlib.util.find_spec('padasip') is None:
        return None
    import padasip
    peer = padasip.filters.FilterRLS(phi.shape[1], mu=1.0, eps=1e-6)
    clock = time.perf_counter_ns
    times = np.empty(len(y))
    for t in range(len(y)):
        start = clock()
        peer.adapt(y[t], phi[t])
        times[t] = clock() - start
    return times / 1000.0


def run(quick: bool = False) -> list[Result]:
    """Measure everything of section 1 in one run and return the rows."""
    samples = 3000 if quick else 20000
    plant = make_scenario('ding_miso')
    y, u = plant.simulate(samples, 7)
    phi = ArxRegressor(2, 2, False).regressors(y, u)
    target = y[2:]

    floor_med, floor_p99 = summary(best_of(lambda: floor_rls_us(phi, target)))
    rows = [Result(SECTION, 'floor: bare inline numpy RLS (p = 6), median', floor_med, 'µs'),
            Result(SECTION, 'floor p99', floor_p99, 'µs')]
    costs = {}
    for name in ('rls', 'bcrls'):
        med, p99 = summary(best_of(lambda: per_sample_us(
            make_estimator(name, order=2, num_inputs=2).update, y, u)))
        costs[name] = med
        rows.append(Result(SECTION, f'{name} update (n = 2, r = 2), median', med, 'µs',
                           note=f'p99 {p99:.1f} µs; {med / floor_med:.2f}× floor'))
    rows.append(Result(SECTION, 'bcrls / floor', costs['bcrls'] / floor_med, '×', '≤ 1.5',
                       costs['bcrls'] / floor_med <= 1.5))
    rows.extend(_rpem(y, u, floor_med))

    # best of three medians, as for the per-sample figures
    lstsq = min(naive_lstsq_us(y, u, NAIVE_N) for _ in range(3))
    bcls = min(naive_bcls_us(y, u, NAIVE_N) for _ in range(3))
    rows.append(Result(SECTION, f'naive: build Phi + lstsq over all data at N = {NAIVE_N}',
                       lstsq, 'µs'))
    rows.append(Result(SECTION, f'naive: batch BCLS fixed point at N = {NAIVE_N}', bcls, 'µs'))
    rows.append(Result(SECTION, 'naive lstsq / rls', lstsq / costs['rls'], '×', '≥ 20',
                       lstsq / costs['rls'] >= 20))
    rows.append(Result(SECTION, 'naive batch BCLS / bcrls', bcls / costs['bcrls'], '×', '≥ 20',
                       bcls / costs['bcrls'] >= 20))

    peer = None if padasip_us(phi[:10], target[:10]) is None else best_of(
        lambda: padasip_us(phi, target))
    if peer is None:
        rows.append(Result(SECTION, 'padasip FilterRLS', float('nan'), 'µs',
                           note='padasip not installed: make bench installs it'))
    else:
        peer_med, _ = summary(peer)
        rows.append(Result(SECTION, 'peer: padasip FilterRLS (p = 6), median', peer_med, 'µs'))
        for name in ('rls', 'bcrls'):
            rows.append(Result(SECTION, f'{name} / padasip', costs[name] / peer_med, '×',
                               '≤ 1', costs[name] <= peer_med))
    rows.extend(_other_estimators(floor_med, quick))
    rows.extend(_batched(quick))
    return rows


def _rpem(y: np.ndarray, u: np.ndarray, floor_med: float) -> list[Result]:
    """
    Time rpem (OE and ARMAX, n = 2, r = 2) per sample against the floor.

    The median is the recursion's step; the mean adds the batch fits of its
    start (each time the stored samples grow by FIT_GROWTH, up to BATCH_LIMIT),
    which are spread over the first samples and stop after them.
    """
    rows = []
    for model in ('oe', 'armax'):
        times = best_of(lambda: per_sample_us(
            make_estimator('rpem', order=2, num_inputs=2, model=model).update, y, u))
        med, p99 = summary(times)
        rows.append(Result(SECTION, f'rpem ({model}) update (n = 2, r = 2), median', med, 'µs',
                           note=f'p99 {p99:.1f} µs, mean with the fits {times.mean():.1f} µs, '
                           f'largest {times.max() / 1000:.0f} ms (a fit); '
                           f'{med / floor_med:.2f}× floor'))
        rows.append(Result(SECTION, f'rpem ({model}) / floor', med / floor_med, '×', '≤ 3',
                           med / floor_med <= 3.0))
    return rows


def per_step_us(update, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Return the time of ``update(y[t], u[t])`` (rows of all plants) for every t, in µs."""
    clock = time.perf_counter_ns
    times = np.empty(y.shape[0])
    for t in range(y.shape[0]):
        y_t, u_t = y[t], u[t]
        start = clock()
        update(y_t, u_t)
        times[t] = clock() - start
    return times / 1000.0


def _batched(quick: bool) -> list[Result]:
    """Time the batched rls and bcrls per plant-sample at several K against the single plant."""
    rows = []
    largest = make_scenario('joints', num_joints=max(BATCHED_PLANTS), seed=1)
    y, u = largest.simulate(1000 if quick else 5000, 2)
    single = {}
    for name in ('rls', 'bcrls'):
        med, p99 = summary(best_of(lambda: per_sample_us(
            make_estimator(name, order=2).update, y[:, 0], u[:, :1])))
        single[name] = med
        rows.append(Result(SECTION, f'{name} update, one plant (n = 2, r = 1), median', med,
                           'µs', note=f'p99 {p99:.1f} µs'))
    for plants in BATCHED_PLANTS:
        steps = (300 if quick else 3000) if plants <= 100 else (200 if quick else 1000)
        for name in ('rls', 'bcrls'):
            estimator = make_batched_estimator(name, plants, order=2)

            def fresh_run():
                estimator.reset()
                return per_step_us(estimator.update, y[:steps, :plants], u[:steps, :plants])
            med, p99 = summary(best_of(fresh_run))
            per_plant = med / plants
            at_target = plants == BATCHED_TARGET_PLANTS
            rows.append(Result(
                SECTION, f'batched {name}, K = {plants}: per plant-sample', per_plant, 'µs',
                f'≤ {BATCHED_TARGET_US:g} µs' if at_target else '',
                per_plant <= BATCHED_TARGET_US if at_target else None,
                note=f'{med:.0f} µs per call (p99 {p99:.0f}); {single[name] / per_plant:.1f}× '
                f'faster than one plant; state {estimator.nbytes / plants:.0f} B per plant'))
        med = float(np.median(best_of(lambda: demux_us(plants, 300 if quick else 2000))))
        rows.append(Result(SECTION, f'JointState demux, K = {plants}: per joint', med / plants,
                           'µs', note=f'{med:.0f} µs per message'))
    return rows


def demux_us(plants: int, messages: int) -> np.ndarray:
    """Time JointStateDemux.take on messages of ``plants`` joints, in µs per message."""
    names = [f'joint_{k}' for k in range(1, plants + 1)]
    values = np.arange(plants, dtype=float)
    demux = JointStateDemux(names)
    # a fresh message every time, as a subscription delivers them
    message_list = [types.SimpleNamespace(
        name=list(reversed(names)), position=array.array('d', values),
        velocity=array.array('d', values + t), effort=array.array('d', values - t))
        for t in range(messages)]
    return time_each([lambda m=m: demux.take(m) for m in message_list])


def _other_estimators(floor_med: float, quick: bool) -> list[Result]:
    """Time bciv (white, coloured) and cl_bcls with their scenario configs, where they exist."""
    rows = []
    cases = [('ikenoue_white_input', '≤ 100 µs'), ('ikenoue_colored', '≤ 100 µs'),
             ('ikeda_closed_loop', '≤ 3× floor')]
    for scenario, target in cases:
        try:
            values = check_identifier_parameters(load_yaml_parameters(config_file(scenario)))
            est = estimator_from_parameters(values)
        except (FileNotFoundError, ImportError, ValueError) as error:
            rows.append(Result(SECTION, f'estimator of {scenario}', float('nan'), 'µs',
                               note=f'not available: {error}'))
            continue
        plant = make_scenario(scenario)
        y, u = plant.simulate(3000 if quick else 10000, 11)

        def fresh_run():
            est.reset()
            return per_sample_us(est.update, y, u)
        times = best_of(fresh_run)
        med, p99 = summary(times)
        mean = float(times.mean())
        label = f'{est.name} on {scenario}'
        if est.name == 'bciv':
            label += f' (l = {values["iv_lag"]}, {values["input_noise"]} input noise)'
            met, value, unit = med <= 100.0, med, 'µs'
        else:
            # cl_bcls does its window work every redesign_period samples: amortised = mean
            met, value, unit = mean <= 3 * floor_med, mean / floor_med, '× floor (amortised)'
        rows.append(Result(SECTION, label, value, unit, target, met,
                           note=f'median {med:.1f} µs, mean {mean:.1f} µs, p99 {p99:.1f} µs, '
                           f'{med / floor_med:.1f}× floor'))
    return rows
