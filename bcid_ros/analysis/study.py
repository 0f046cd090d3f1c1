"""
Order-recovery study: whether ``bcid analyze`` finds the true order and delay.

For each order n and seed, a random stable plant q^-d B(q)/A(q) of order n
with a dead time d is drawn from the seed (:func:`random_plant`), simulated
with the custom scenario (white unit-variance input, white output noise at
the chosen signal-to-noise ratio), written to a bag as the simulator node
would (``/samples`` in frames, and the truth), and analysed by the
``bcid analyze`` command itself. A run recovers the plant when the
recommended order and delay are the true ones.

Run ``python -m bcid_ros.analysis.study --help``; docs/analyze.md holds the
results of the default study.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
import subprocess
import sys
import tempfile
from typing import Any, Callable

import numpy as np
from scipy import signal

from bcid_ros.bag.qos import LATCHED
from bcid_ros.bag.writer import BagWriter, FLOAT64_MULTI_ARRAY, float64_multi_array
from bcid_ros.identifier.interface import resolve, SAMPLES, SIMULATOR_NODE, TRUE_PARAMETERS
from bcid_ros.identifier.layouts import estimate_layout, samples_layout
from bcid_ros.simulation.custom import CustomScenario

#: Pole magnitudes are drawn in this range: slower poles need longer records,
#: faster ones hardly show in the data (a pole at 0.1 is gone after one sample).
POLE_RADIUS = (0.3, 0.9)
#: Poles at least this far apart, and zeros at least this far from the poles:
#: closer ones nearly cancel, and the plant then has a lower effective order.
SEPARATION = 0.2
#: The first and the last input coefficients, b_1 and b_n, are at least this
#: fraction of the largest one: a negligible b_1 makes the dead time one
#: sample longer in the data, a negligible b_n lets a model with one sample
#: less of dead time fit as well.
END_COEFFICIENTS = 0.3
#: Samples per /samples message (a frame, docs/nodes.md) in the study's bags.
FRAME = 50


@dataclasses.dataclass
class StudyRun:
    """One simulated bag and what ``bcid analyze`` recommended for it."""

    order: int
    delay: int
    seed: int
    recommended_order: int | None
    recommended_delay: int | None
    fit: float | None
    residuals_white: bool

    @property
    def recovered(self) -> bool:
        """Return whether the recommended order and delay are the true ones."""
        return (self.recommended_order, self.recommended_delay) == (self.order, self.delay)


def random_plant(order: int, rng: np.random.Generator, max_delay: int = 3
                 ) -> dict[str, Any]:
    """
    Draw a stable plant of ``order`` with a dead time in 0..max_delay.

    Poles: complex pairs (probability 1/2 while two or more are left) with
    magnitude uniform in :data:`POLE_RADIUS` and angle uniform in [0.3, 2.5]
    rad, or real poles of magnitude in the same range and either sign.
    B = b_1 q^-1 + ... + b_n q^-n with standard normal b_k. Draws are
    repeated until the separations of :data:`SEPARATION` and
    :data:`END_COEFFICIENTS` hold.

    Returns
    -------
    dict
        ``plant_denominator``, ``plant_numerator`` and ``input_delay`` for
        :class:`~bcid_ros.simulation.custom.CustomScenario`.

    """
    while True:
        poles: list[complex] = []
        while len(poles) < order:
            radius = rng.uniform(*POLE_RADIUS)
            if order - len(poles) >= 2 and rng.random() < 0.5:
                angle = rng.uniform(0.3, 2.5)
                poles += [radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]
            else:
                poles.append(complex(radius * rng.choice([-1.0, 1.0])))
        b = rng.standard_normal(order)
        delay = int(rng.integers(0, max_delay + 1))
        zeros = np.roots(b) if order > 1 else np.zeros(0)
        gaps = [abs(p - q) for i, p in enumerate(poles) for q in poles[i + 1:]]
        gaps += [abs(p - z) for p in poles for z in zeros]
        if min(gaps, default=1.0) >= SEPARATION and \
                min(abs(b[0]), abs(b[-1])) >= END_COEFFICIENTS * np.abs(b).max():
            return {'plant_denominator': np.real(np.poly(poles)).tolist(),
                    'plant_numerator': [0.0, *b.tolist()], 'input_delay': delay}


def noise_for_snr(plant: dict[str, Any], snr_db: float, equation_error: bool = False
                  ) -> float:
    """
    Return the variance of e that gives ``snr_db`` at the output for a white unit input.

    The ratio is that of the variances of B/A u and of the noise as it
    appears in y: e itself (output error) or e/A (equation error).
    """
    impulse = np.zeros(5000)
    impulse[0] = 1.0
    response = signal.lfilter(plant['plant_numerator'], plant['plant_denominator'], impulse)
    gain = 1.0
    if equation_error:
        gain = float(np.sum(signal.lfilter([1.0], plant['plant_denominator'], impulse) ** 2))
    return float(np.sum(response ** 2) / 10 ** (snr_db / 10) / gain)


def write_bag(scenario: CustomScenario, samples: int, seed: int, out: Path,
              rate_hz: float = 100.0) -> Path:
    """Write ``samples`` of ``scenario`` (seed ``seed``) as the simulator node's bag."""
    y, u = scenario.simulate(samples, seed)
    truth = scenario.truth()
    rows = np.column_stack([y, u])
    samples_topic = resolve(SAMPLES, SIMULATOR_NODE)
    truth_topic = resolve(TRUE_PARAMETERS, SIMULATOR_NODE)
    with BagWriter(out) as writer:
        writer.add_topic(samples_topic, FLOAT64_MULTI_ARRAY)
        writer.add_topic(truth_topic, FLOAT64_MULTI_ARRAY, [LATCHED])
        writer.write_message(truth_topic, 0, float64_multi_array(
            [estimate_layout(truth.parameter_names)], truth.parameters))
        for start in range(0, samples, FRAME):
            block = rows[start:start + FRAME]
            writer.write_message(samples_topic, round((start + block.shape[0]) * 1e9 / rate_hz),
                                 float64_multi_array(samples_layout(block.shape[0],
                                                                    u.shape[1]), block.ravel()))
    return out


def analyze_bag(bag: Path, params: Path, extra: list[str]) -> dict[str, Any]:
    """Run the ``bcid analyze`` command on a bag, as a user would, and return its JSON."""
    # a process of its own: the study is a user of the command line, which stands above it
    done = subprocess.run([sys.executable, '-m', 'bcid_ros.cli', 'analyze', str(bag),
                           '--params', str(params), '--json', *extra],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f'bcid analyze failed on {bag}: {done.stderr.strip()}')
    return json.loads(done.stdout)


def run_study(orders: range, seeds: range, *, samples: int = 3000, snr_db: float = 20.0,
              max_delay: int = 3, search_orders: str = '1-6', search_delays: str = '0-4',
              estimator: str = 'bcrls', equation_error: bool = False,
              progress: Callable[[str], None] | None = None) -> list[StudyRun]:
    """
    Simulate, write and analyse one bag per (order, seed); return the runs.

    The plant of (n, seed) is drawn from ``numpy.random.default_rng([n, seed])``
    and its data from seed ``seed``.
    """
    runs = []
    with tempfile.TemporaryDirectory(prefix='bcid_study_') as directory:
        params = Path(directory) / 'params.yaml'
        params.write_text('bcid_identifier:\n  ros__parameters:\n'
                          f'    estimator: {estimator}\n    order: 1\n    num_inputs: 1\n')
        for n in orders:
            for seed in seeds:
                plant = random_plant(n, np.random.default_rng([n, seed]), max_delay)
                scenario = CustomScenario(
                    **plant, equation_error=equation_error,
                    noise_variance=noise_for_snr(plant, snr_db, equation_error))
                bag = write_bag(scenario, samples, seed, Path(directory) / f'n{n}_s{seed}')
                found = analyze_bag(bag, params, ['--orders', search_orders,
                                                  '--delays', search_delays])
                chosen = found['orders'].get(str(found['recommended_order']), {})
                run = StudyRun(n, plant['input_delay'], seed, found['recommended_order'],
                               found['recommended_delay'], chosen.get('fit'),
                               found['residuals_white'])
                runs.append(run)
                if progress is not None:
                    progress(f'order {n} delay {run.delay} seed {seed}: recommended '
                             f'{run.recommended_order}/{run.recommended_delay}'
                             + ('' if run.recovered else '  <- missed'))
    return runs


def table(runs: list[StudyRun]) -> str:
    """Return the Markdown table of a study: per order, the runs that recovered the plant."""
    lines = ['| true order | runs | order and delay recovered | recommended (order/delay) '
             'where missed | median validation fit (%) |', '|---|---|---|---|---|']
    for n in sorted({r.order for r in runs}):
        rows = [r for r in runs if r.order == n]
        missed = ', '.join(f'seed {r.seed}: {r.recommended_order}/{r.recommended_delay} '
                           f'(true {r.order}/{r.delay})' for r in rows if not r.recovered)
        fits = [r.fit for r in rows if r.fit is not None]
        lines.append(f'| {n} | {len(rows)} | {sum(r.recovered for r in rows)} | '
                     f'{missed or "none"} | {np.median(fits):.1f} |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the study from the command line and print its table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--orders', default='1-4', help='true orders A-B')
    parser.add_argument('--seeds', type=int, default=10, help='seeds per order')
    parser.add_argument('--samples', type=int, default=3000)
    parser.add_argument('--snr', type=float, default=20.0, help='signal-to-noise ratio (dB)')
    parser.add_argument('--estimator', default='bcrls',
                        help="the parameter file's estimator (compared online, beside the "
                        'batch model)')
    parser.add_argument('--equation-error', action='store_true',
                        help='ARX plants (A y = B u + e) instead of output error')
    args = parser.parse_args(argv)
    first, last = (int(v) for v in args.orders.split('-'))
    runs = run_study(range(first, last + 1), range(args.seeds), samples=args.samples,
                     snr_db=args.snr, estimator=args.estimator,
                     equation_error=args.equation_error,
                     progress=lambda line: print(line, file=sys.stderr, flush=True))
    print(table(runs))
    return 0


if __name__ == '__main__':
    sys.exit(main())
