"""
The measurements of docs/trust.md: the residual monitor and the HAC covariance.

``python -m benchmarks.trust monitor --input low_pass --residual white`` runs one Monte Carlo
of :class:`~bcid_ros.estimators.adequacy.AdequacyMonitor` over many plants at once (its plant
axis) and prints one JSON line: the share of plants in alarm at a moment and over the run, the
mean statistic, and where a residual is correlated with an input, the share that names the lag.
``python -m benchmarks.trust hac --noise ar0.9 --samples 1000`` runs the coverage of
:class:`~bcid_ros.estimators.hac.HacCovariance` against the plain LS covariance and Newey-West
on an output-error regression. ``python -m benchmarks.trust cost`` measures the per-sample cost
against an rls update in the same process, for one plant and per plant of K plants that record
together or apart. Run them under ``nice -n 10``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

import numpy as np
from scipy import signal

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.simulation import make_scenario

#: The oversampled plant of the HAC study: poles 0.95 and 0.9.
PLANT = (np.array([0.0, 0.05, 0.04]), np.array([1.0, -1.85, 0.855]))
#: Rows are added to the moments from this time on before shares are counted (steady state).
STEADY = 3000


def coloured(kind: str, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """
    Return unit-variance noise of ``kind`` along axis 0 (2000 samples of burn-in).

    ``white``; ``arR``: AR(1) with pole R; ``maC``: 1 + C q^-1; ``oversampled``: poles
    0.9 +- 0.1j; ``t3``: Student t with 3 degrees of freedom; ``low_pass``: AR(1) 0.9;
    ``held_prbsH``: +-1 held for H samples.
    """
    count = shape[0] + 2000
    white = rng.standard_normal((count,) + shape[1:])
    if kind.startswith('held_prbs'):
        hold = int(kind[len('held_prbs'):])
        levels = np.sign(rng.standard_normal((count // hold + 1,) + shape[1:]))
        noise = np.repeat(levels, hold, axis=0)[:count]
    elif kind == 'low_pass':
        noise = signal.lfilter([1.0], [1.0, -0.9], white, axis=0)
    elif kind.startswith('ar'):
        noise = signal.lfilter([1.0], [1.0, -float(kind[2:])], white, axis=0)
    elif kind.startswith('ma'):
        noise = signal.lfilter([1.0, float(kind[2:])], [1.0], white, axis=0)
    elif kind == 'oversampled':
        noise = signal.lfilter([1.0], [1.0, -1.8, 0.82], white, axis=0)
    elif kind == 't3':
        noise = rng.standard_t(3, white.shape)
    else:
        noise = white
    noise = noise[2000:]
    return noise / noise.std()


# ------------------------------------------------------------------ the monitor
def monitor_study(args: argparse.Namespace) -> dict[str, Any]:
    """Run the monitor over ``args.plants`` plants; return its shares in alarm and more."""
    rng = np.random.default_rng(args.seed)
    samples, plants = args.samples, args.plants
    inputs = coloured(args.input, (samples, plants, args.inputs), rng)
    residual = coloured(args.residual, (samples, plants), rng)
    if args.correlation:  # the residual correlated with u1 at lag args.lag
        gain = args.correlation / math.sqrt(1.0 - args.correlation ** 2)
        residual[args.lag:] += gain * inputs[:-args.lag, :, 0]
    if args.recover_at:  # the residual white from then on
        residual[args.recover_at:] = rng.standard_normal((samples - args.recover_at, plants))
    monitor = AdequacyMonitor(num_inputs=args.inputs, model=args.model, plants=plants,
                              lags=args.lags, forgetting_factor=args.forgetting_factor,
                              false_alarm=args.false_alarm)
    alarms, times = [], []
    for t in range(samples):
        checks = monitor.checks
        monitor.record(residual[t], inputs[t])
        if (monitor.checks > checks).any():  # every plant records: they check together
            alarms.append(monitor.alarm.copy())
            times.append(t + 1)
    alarms, times = np.array(alarms), np.array(times)
    result: dict[str, Any] = {'study': 'monitor', **vars(args), 'window': monitor.window,
                              'thresholds': [round(x, 2) for x in monitor.thresholds]}
    steady = times >= STEADY
    if args.recover_at:
        result.update(recovery(alarms, times, args.recover_at))
    elif steady.any():
        result['in_alarm_at_a_moment'] = float(alarms[steady].mean())
        result['alarmed_during_the_run'] = float(alarms[steady].any(axis=0).mean())
        rises = (alarms[steady][1:] & ~alarms[steady][:-1]).sum()
        result['alarms_raised_per_plant'] = float(rises / plants)
        result['mean_statistic'] = np.round(np.nanmean(monitor.statistics, axis=0), 2).tolist()
    if args.correlation:
        named = [plant for plant in monitor.reasons
                 if any(f'u1 at lag {args.lag} ' in reason for reason in plant)]
        result['names_the_lag'] = len(named) / plants
    return result


def recovery(alarms: np.ndarray, times: np.ndarray, moment: int) -> dict[str, Any]:
    """Return the share in alarm at ``moment``, the times to the first clear, and at the end."""
    before = alarms[times <= moment][-1]
    after, later = alarms[times > moment], times[times > moment]
    first = [later[np.flatnonzero(~after[:, plant])[0]] - moment
             if (~after[:, plant]).any() else np.inf for plant in np.flatnonzero(before)]
    return {'in_alarm_before': float(before.mean()),
            'first_clear_after_quantiles_50_90_100': np.quantile(first, [0.5, 0.9, 1.0]).tolist(),
            'in_alarm_at_the_end': float(after[-1].mean())}


# ------------------------------------------------------------------ the HAC
def hac_study(args: argparse.Namespace) -> dict[str, Any]:
    """Return the coverage of the plain, Newey-West and prewhitened std of LS, coloured noise."""
    rng = np.random.default_rng(args.seed)
    runs, samples, lam = args.runs, args.samples, args.forgetting_factor
    numerator, denominator = PLANT
    u = coloured(args.input, (samples + 2, runs), rng)
    x = signal.lfilter(numerator, denominator, u, axis=0)
    y = x + 0.5 * coloured(args.noise, (samples + 2, runs), rng)
    # psi(t) = [-x(t-1), -x(t-2), u(t-1), u(t-2)]: the regression of an OE model at the truth
    psi = np.swapaxes(np.stack([-x[1:-1], -x[:-2], u[1:-1], u[:-2]], axis=-1), 0, 1)
    target = y[2:].T
    weights = lam ** np.arange(samples - 1, -1, -1, dtype=float)
    p = np.linalg.inv(np.einsum('ktp,t,ktq->kpq', psi, weights, psi))
    theta = np.einsum('kpq,ktq,t,kt->kp', p, psi, weights, target)
    residual = target - np.einsum('ktp,kp->kt', psi, theta)
    tau, tau2 = weights.sum(), (weights ** 2).sum()
    sigma2 = np.einsum('t,kt->k', weights, residual ** 2) / (tau - 4 * tau2 / tau)
    stds = {'plain': np.sqrt(np.einsum('kii->ki', p) * (sigma2 * tau2 / tau)[:, None])}
    rule = 4.0 * (tau * tau / tau2 / 100.0) ** (2.0 / 9.0)  # Newey-West (1994) rule of thumb
    variants = {'newey_west_rule': dict(prewhitening='none', bandwidth=rule, max_lag=64),
                'newey_west_auto': dict(prewhitening='none', max_lag=64),
                'prewhitened (shipped)': {},
                'larger (rpem)': dict(prewhitening='larger')}
    bandwidths = {}
    for name, settings in variants.items():
        hac = HacCovariance(dimension=4, forgetting_factor=lam, plants=runs, **settings)
        scores = psi * residual[:, :, None]
        for t in range(samples):
            hac.record(scores[:, t])
        stds[name] = np.sqrt(np.einsum('kii->ki', hac.covariance(p)))
        bandwidths[name] = np.quantile(hac.bandwidths, [0.5, 0.9]).round(1).tolist()
    truth = np.r_[denominator[1:], numerator[1:]]
    spread = theta.std(axis=0, ddof=1)
    result: dict[str, Any] = {'study': 'hac', **vars(args), 'bandwidths_50_90': bandwidths}
    for name, std in stds.items():
        ratio = np.abs(theta - truth) / std
        result[name] = {'within_2_std': (ratio <= 2).mean(axis=0).round(3).tolist(),
                        'within_3_std': (ratio <= 3).mean(axis=0).round(3).tolist(),
                        'spread_over_mean_std': (spread / std.mean(axis=0)).round(2).tolist()}
    return result


# ------------------------------------------------------------------ the cost
def cost_study(args: argparse.Namespace) -> dict[str, Any]:
    """Return the per-sample cost of the monitor and the HAC over that of an rls update."""
    y, u = make_scenario('ding_miso').simulate(args.samples, seed=1)
    residual = np.random.default_rng(2).standard_normal(args.samples).tolist()
    inputs = list(u)
    scores = list(np.random.default_rng(3).standard_normal((args.samples, 6)))
    rows = []
    for _ in range(args.repeats):
        estimator = make_estimator('rls', order=2, num_inputs=2)
        start = time.perf_counter()
        for t in range(args.samples):
            estimator.update(float(y[t]), u[t])
        rls = time.perf_counter() - start
        row = {'rls_us': 1e6 * rls / args.samples}
        for model in ('arx', 'oe'):
            monitor = AdequacyMonitor(num_inputs=2, model=model)
            start = time.perf_counter()
            for t in range(args.samples):
                monitor.record(residual[t], inputs[t])
            row[f'monitor_{model}_over_rls'] = (time.perf_counter() - start) / rls
        hac = HacCovariance(dimension=6)
        start = time.perf_counter()
        for t in range(args.samples):
            hac.record(scores[t])
        row['hac_p6_over_rls'] = (time.perf_counter() - start) / rls
        start = time.perf_counter()
        for _ in range(100):
            hac.covariance(np.eye(6))
        row['hac_read_us'] = 1e6 * (time.perf_counter() - start) / 100
        row.update(plants_cost(args.samples // 4, args.plants, rls))
        rows.append({key: round(value, 3) for key, value in row.items()})
    return {'study': 'cost', 'samples': args.samples, 'plants': args.plants, 'runs': rows}


def plants_cost(samples: int, plants: int, rls: float) -> dict[str, float]:
    """
    Return the cost per plant and sample of K-plant monitors and HACs over an rls update.

    ``together``: every plant records every sample (:meth:`record`, one shared cursor).
    ``apart``: plant k skipped its first k samples, then all record every sample (cursors that
    differ: the blocks complete at K different times). ``skipping``: one plant at random skips
    each sample (``record_rows`` with the others). ``rls`` is the time of 4 x ``samples`` rls
    updates.
    """
    rng = np.random.default_rng(4)
    residual = rng.standard_normal((samples, plants))
    inputs = rng.standard_normal((samples, plants, 2))
    scores = rng.standard_normal((samples, plants, 6))
    every = np.arange(plants)
    skipping = [np.delete(every, k) for k in rng.integers(plants, size=samples).tolist()]
    apart = [every[every < t] if t < plants else slice(None) for t in range(samples)]
    per_update = rls / (4 * samples)
    result = {}
    for mode, rows in (('together', [slice(None)] * samples), ('apart', apart),
                       ('skipping', skipping)):
        monitor = AdequacyMonitor(num_inputs=2, plants=plants)
        hac = HacCovariance(dimension=6, plants=plants)
        start = time.perf_counter()
        for t in range(samples):
            monitor.record_rows(rows[t], residual[t, rows[t]], inputs[t, rows[t]])
        middle = time.perf_counter()
        for t in range(samples):
            hac.record_rows(rows[t], scores[t, rows[t]])
        end = time.perf_counter()
        result[f'monitor_arx_k{plants}_{mode}_per_plant_over_rls'] = (
            (middle - start) / (samples * plants) / per_update)
        result[f'hac_p6_k{plants}_{mode}_per_plant_over_rls'] = (
            (end - middle) / (samples * plants) / per_update)
    return result


def main(argv: list[str] | None = None) -> None:
    """Run one study and print its JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    studies = parser.add_subparsers(dest='study', required=True)
    monitor = studies.add_parser('monitor')
    monitor.add_argument('--model', default='arx')
    monitor.add_argument('--input', default='low_pass')
    monitor.add_argument('--inputs', type=int, default=2)
    monitor.add_argument('--residual', default='white')
    monitor.add_argument('--correlation', type=float, default=0.0)
    monitor.add_argument('--lag', type=int, default=3)
    monitor.add_argument('--recover-at', type=int, default=0)
    monitor.add_argument('--lags', type=int, default=10)
    monitor.add_argument('--forgetting-factor', type=float, default=1.0)
    monitor.add_argument('--false-alarm', type=float, default=0.01)
    monitor.add_argument('--samples', type=int, default=6000)
    monitor.add_argument('--plants', type=int, default=1000)
    monitor.add_argument('--seed', type=int, default=1)
    hac = studies.add_parser('hac')
    hac.add_argument('--noise', default='ar0.9')
    hac.add_argument('--input', default='low_pass')
    hac.add_argument('--samples', type=int, default=1000)
    hac.add_argument('--runs', type=int, default=400)
    hac.add_argument('--forgetting-factor', type=float, default=1.0)
    hac.add_argument('--seed', type=int, default=1)
    cost = studies.add_parser('cost')
    cost.add_argument('--samples', type=int, default=25600)
    cost.add_argument('--repeats', type=int, default=5)
    cost.add_argument('--plants', type=int, default=8)
    args = parser.parse_args(argv)
    study = {'monitor': monitor_study, 'hac': hac_study, 'cost': cost_study}[args.study]
    start = time.perf_counter()
    result = study(args)
    result['seconds'] = round(time.perf_counter() - start, 1)
    print(json.dumps(result))


if __name__ == '__main__':
    main()
