"""
cl_bcls on a 1 kHz position loop with friction, under the EMPS benchmark's controller.

A motor and ball screw (M q'' = g u - Fv q' - Fc sign(q') - offset, the published EMPS
values) under the benchmark's position controller, nu = kp kv (r - q) - kv (q(k) - q(k-2)) /
(2 dt), with a 5e-8 m encoder: the lags of the position are nearly collinear (the information
matrix's condition near 1e10) and the friction is process noise, which cl_bcls's model (white
noise on the output only) excludes. Two failures of a measured record of this loop are
reproduced here: the loss solved from the moments at the first prefilter change cancelled to 0
(every later row then refused, and each refusal's restart of the near double-integrating
prefilters caused the next), and the verdict: the estimate must not be valid with friction,
and must say why.
"""

from __future__ import annotations

import numpy as np
import pytest

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.cl_bcls.regression import moment_loss

#: Sample time (s), the benchmark's.
DT = 1e-3
#: Mass (kg), viscous (N s/m) and Coulomb (N) friction, offset (N), motor gain (N/V).
MASS, VISCOUS, COULOMB, OFFSET, GAIN = 95.1089, 203.5034, 20.3935, -3.1648, 35.15065188
#: The controller's gains kp (1/s) and kv (V s/m).
KP, KV = 160.18, 243.45
#: The controller in cl_bcls form (negative feedback, descending powers of q).
CONTROLLER = dict(controller_numerator=[KP * KV + KV / (2 * DT), 0.0, -KV / (2 * DT)],
                  controller_denominator=[1.0, 0.0, 0.0], controller_sign='negative')
#: The encoder's quantum (m).
QUANTUM = 5e-8
#: Samples per record: past the first prefilter change (at 1344 rows) with room to spare.
SAMPLES = 5000
#: Integration substeps per sample.
SUBSTEPS = 10


def reference(count: int, rng: np.random.Generator) -> np.ndarray:
    """Return position moves of random size and duration between rests (m), as EMPS's."""
    positions, level = [], 0.0
    while len(positions) < count:
        target = rng.uniform(0.0, 0.2)
        steps = int(rng.integers(300, 800))
        ramp = level + (target - level) * 0.5 * (1.0 - np.cos(np.linspace(0.0, np.pi, steps)))
        positions.extend(ramp.tolist() + [target] * int(rng.integers(50, 200)))
        level = target
    return np.array(positions[:count])


def friction_loop(seed: int, coulomb: float = COULOMB, noise: float = 0.0,
                  count: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Return the measured position y and command u of the loop (encoder, optional noise)."""
    rng = np.random.default_rng(seed)
    r = reference(count, rng)
    q = v = 0.0
    y, u = np.zeros(count), np.zeros(count)
    h = DT / SUBSTEPS
    for k in range(count):
        y[k] = QUANTUM * np.round(q / QUANTUM) + noise * rng.standard_normal()
        speed = (y[k] - y[k - 2]) / (2 * DT) if k >= 2 else 0.0
        u[k] = KP * KV * (r[k] - y[k]) - KV * speed
        for _ in range(SUBSTEPS):
            force = GAIN * u[k] - VISCOUS * v - coulomb * np.sign(v) - OFFSET * (coulomb > 0)
            v += h * force / MASS
            q += h * v
    return y, u


def run(y: np.ndarray, u: np.ndarray) -> tuple[float, object]:
    """Return the share of samples cl_bcls (order 2, gate 5) refused, and the estimator."""
    estimator = make_estimator('cl_bcls', order=2, outlier_threshold=5.0, **CONTROLLER)
    for k in range(y.shape[0]):
        estimator.update(y[k], [u[k]])
    return estimator.flags.get('outlier_rejected', 0) / y.shape[0], estimator


@pytest.mark.parametrize('seed', [1, 2])
def test_the_clean_samples_of_a_friction_loop_are_kept(seed):
    share, estimator = run(*friction_loop(seed))
    assert estimator.redesigns >= 5  # past the first prefilter change
    assert estimator.epochs >= 2
    assert share <= 0.02, estimator.flags


@pytest.mark.parametrize('seed', [1, 2])
def test_the_compensation_sees_the_loss_and_the_loop_is_not_valid(seed):
    # with the loss cancelled to 0, sigma2 was 0, nothing was compensated and the plain LS
    # was called valid; cl_bcls's model (white output noise) does not hold with friction
    _, estimator = run(*friction_loop(seed))
    assert estimator.sigma2 > 0.0
    assert not estimator.valid
    assert estimator.validity_reasons


def test_the_loss_from_the_moments_survives_collinear_lags():
    y, u = friction_loop(1)
    rows = np.column_stack([-y[1:-1], -y[:-2], u[1:-1], u[:-2]])
    target = y[2:]
    information, cross, energy = rows.T @ rows, rows.T @ target, float(target @ target)
    theta = np.linalg.inv(information).dot(cross)  # as the moments solve it
    direct = float(np.sum((target - rows @ theta) ** 2))
    # the rounding of the quadratic form: a few eps times its terms
    terms = energy + 2.0 * abs(theta @ cross) + theta @ information @ theta
    bound = 64 * np.finfo(float).eps * terms
    assert bound < 0.05 * direct  # the loss stands well above the rounding
    # the form linear in theta's error (the former one) is off by far more
    assert abs(energy - cross @ theta - direct) > 10 * bound
    assert abs(moment_loss(information, cross, energy, theta) - direct) <= bound
