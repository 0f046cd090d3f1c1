"""
Batch prediction-error fits (bcid_ros.analysis.pem): the time of one fit on 10,000 samples.

Each plant has the order it is fitted with: poles spread from 0.3 to 0.99 (a complex pair
from n = 2 on), one input held 5 samples (a PRBS-like binary signal) or two with delays 1
and 3, coloured output noise at 20 dB SNR. A figure is the fastest of three fits (the
machine is shared; a disturbed fit is only ever slower), in CPU time of this process against
the target, and in wall time in the note: other processes on a shared machine disturb the
CPU time far less, and with one OpenBLAS thread it is the work done. The OE fit runs every
start (ARX and SRIV) to its end; the ARX least-squares fit of the same structure is the
floor. OpenBLAS threads: whatever ``OPENBLAS_NUM_THREADS`` says (the note); on a loaded
2-core machine its default threads slow the SVDs of the tall Jacobians several times.
"""

from __future__ import annotations

import os
import time
from typing import Callable

import numpy as np
from scipy import signal

from benchmarks.common import Result
from bcid_ros.analysis.pem import fit_arx, fit_oe, Structure

SECTION = 'batch prediction-error fit'
SAMPLES = 10000
TARGET_MS = 1000.0
#: Poles of the plant of each order.
POLES = {1: [0.95], 2: [0.9 * np.exp(0.3j), 0.9 * np.exp(-0.3j)],
         3: [0.99, 0.8 * np.exp(0.5j), 0.8 * np.exp(-0.5j)],
         4: [0.99, 0.7, 0.85 * np.exp(0.4j), 0.85 * np.exp(-0.4j)],
         5: [0.99, 0.9, 0.3, 0.85 * np.exp(0.4j), 0.85 * np.exp(-0.4j)]}


def plant_data(order: int, delays: tuple[int, ...],
               count: int) -> tuple[np.ndarray, np.ndarray, Structure]:
    """Return (y, u, structure) of the benchmark plant of ``order`` with these delays."""
    rng = np.random.default_rng(order * 10 + len(delays))
    f = np.real(np.poly(POLES[order]))
    u = np.repeat(rng.choice([-1.0, 1.0], size=(count // 5 + 1, len(delays))), 5,
                  axis=0)[:count]
    x = np.zeros(count)
    for i, delay in enumerate(delays):
        numerator = np.concatenate([np.zeros(delay + 1), rng.uniform(0.2, 1.0, order)])
        x += signal.lfilter(numerator, f, u[:, i])
    v = signal.lfilter([1.0, 0.5], [1.0, -0.8], rng.standard_normal(count))
    y = x + v * x.std() / v.std() * 0.1
    return y, u, Structure(order, len(delays), delays)


def fastest_ms(call: Callable[[], object], repeats: int = 3) -> tuple[float, float]:
    """Return the fastest of ``repeats`` calls in milliseconds: (wall time, CPU time)."""
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        call()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return 1000.0 * min(wall), 1000.0 * min(cpu)


def run(quick: bool = False) -> list[Result]:
    """Time one OE and one ARX fit per plant."""
    count = SAMPLES // 5 if quick else SAMPLES
    threads = os.environ.get('OPENBLAS_NUM_THREADS', 'default')
    rows = []
    cases = [(order, (0,)) for order in range(1, 6)] + [(3, (1, 3)), (5, (1, 3))]
    for order, delays in cases:
        y, u, structure = plant_data(order, delays, count)
        result = fit_oe(y, u, structure)
        oe, oe_cpu = fastest_ms(lambda: fit_oe(y, u, structure))
        arx, arx_cpu = fastest_ms(lambda: fit_arx(y, u, structure))
        rows.append(Result(
            SECTION, f'OE fit, n = {order}, r = {len(delays)}, N = {count}, CPU time', oe_cpu,
            'ms', f'< {TARGET_MS:.0f} ms', oe_cpu < TARGET_MS,
            f'wall {oe:.0f} ms; {oe_cpu / arx_cpu:.0f} x the ARX fit (CPU {arx_cpu:.1f} ms); '
            f'{result.evaluations} evaluations of the best run, initial {result.initial}; '
            f'OpenBLAS threads {threads}'))
    return rows


def main() -> None:
    """Print the rows."""
    for row in run():
        print(' | '.join(row.cells()))


if __name__ == '__main__':
    main()
