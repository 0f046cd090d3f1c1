"""
A measured closed loop with friction: the EMPS benchmark, online estimators and batch references.

The electro-mechanical positioning system of Janot, Gautier and Brunot ("Data Set and Reference
Models of EMPS", Workshop on Nonlinear System Identification Benchmarks, 2019): a DC motor and a
ball screw, M q'' = g u - Fv q' - Fc sign(q') - offset, under a known position controller at
1 kHz. The record is not part of the repository: :func:`run` reads ``estimation.csv`` and
``validation.csv`` (columns ``y`` position, ``u1`` command, ``r_cl`` the reference that puts the
loop in the form u = C(q)(r_cl - y), and on validation ``pulses_N``, force pulses added to the
command) from a folder given on the command line (``benchmarks.realdata --data``).

Every estimator runs over the estimation record at order 2 as a user runs it (``bcid replay``
with the identifier's defaults: no detrending, gate off; and with the gate at 5), cl_bcls with
the benchmark's controller. A model is judged, as the benchmark asks, by the command it predicts
in closed loop on the validation record (the position hardly depends on the model under a 20 Hz
position loop): the model in the loop with the known controller, driven by r_cl and the pulses,
scored by the NRMSE fit and R^2 of the command; and by its physical parameters Fv/M and g/M
(:func:`physical`) against the published ones.

Batch references beside them: plain least squares; the instrumental variable estimate with
instruments from the noise-free closed loop driven by r_cl (:func:`closed_loop_iv`); and the
benchmark's own physical regression with the Coulomb term (:func:`physical_ls`, IDIM-LS), which
shows what the data hold when the model holds.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg

from bcid_ros.analysis.metrics import nrmse_fit
from bcid_ros.estimators import make_estimator
from bcid_ros.markdown import markdown_table

#: Sample time (s).
DT = 1e-3
#: The controller's gains kp (1/s) and kv (V s/m): nu = kp kv (r - q) - kv (q(k) - q(k-2))/(2 dt).
KP, KV = 160.18, 243.45
#: The controller in cl_bcls form (negative feedback, descending powers of q).
CONTROLLER = {'controller_numerator': [KP * KV + KV / (2 * DT), 0.0, -KV / (2 * DT)],
              'controller_denominator': [1.0, 0.0, 0.0], 'controller_sign': 'negative'}
#: The published physical values (IDIM-LS): Fv/M (1/s) and g/M (1/(V s^2)).
PHYSICAL = {'Fv/M': 203.5034 / 95.1089, 'g/M': 35.15065188 / 95.1089}
#: The goals: Fv/M within 25 %, g/M within 10 % of the published values.
GOALS = {'Fv/M': 0.25, 'g/M': 0.10}
#: The factor of the force pulses in the recorded command (least squares on the data).
PULSE_GAIN = 1.0139
#: The online estimators and their settings beyond the order.
ESTIMATORS = {
    'cl_bcls': ('cl_bcls', CONTROLLER),
    'rls': ('rls', {}),
    'rpem oe': ('rpem', {'model': 'oe'}),
    'rpem armax': ('rpem', {'model': 'armax'}),
}
#: Gates the online estimators run with (0: off, the identifier's default).
GATES = (0.0, 5.0)


def load(folder: Path) -> dict[str, dict[str, np.ndarray]]:
    """Return the columns of ``estimation.csv`` and ``validation.csv`` in ``folder``."""
    records = {}
    for name in ('estimation', 'validation'):
        table = np.genfromtxt(folder / f'{name}.csv', delimiter=',', names=True)
        records[name] = {column: np.asarray(table[column]) for column in table.dtype.names}
    return records


def physical(theta: np.ndarray) -> dict[str, float]:
    r"""
    Return Fv/M and g/M of a discrete order-2 model [a1, a2, b1, b2] at DT.

    The zero-order-hold model is mapped back to continuous time by the
    matrix logarithm of :math:`\exp([[A, B], [0, 0]]\,T)`; the continuous
    transfer function :math:`(\beta_1 s + \beta_0)/(s^2 + \alpha_1 s + \alpha_0)`
    of the benchmark's :math:`(g/M)/(s^2 + (F_v/M) s)` gives
    :math:`F_v/M = \alpha_1` and :math:`g/M = \beta_0` (:math:`\alpha_0`, the
    spring the plant has not, is returned as ``k/M``). NaN if the model has
    no real logarithm (a pole on the negative real axis).
    """
    a1, a2, b1, b2 = (float(value) for value in theta)
    augmented = np.zeros((3, 3))
    augmented[0, :2] = (-a1, -a2)
    augmented[1, 0] = 1.0
    augmented[0, 2] = 1.0
    augmented[2, 2] = 1.0
    logarithm = scipy.linalg.logm(augmented) / DT
    if not np.isfinite(logarithm).all() or np.abs(logarithm.imag).max() > 1e-6 * np.abs(
            logarithm).max():
        return {'Fv/M': math.nan, 'g/M': math.nan, 'k/M': math.nan}
    a_c, b_c = logarithm.real[:2, :2], logarithm.real[:2, 2]
    c = np.array([b1, b2])
    # the characteristic polynomial s^2 + alpha1 s + alpha0 and the numerator of c (sI - A)^-1 b
    alpha1, alpha0 = -np.trace(a_c), np.linalg.det(a_c)
    beta0 = c.dot(a_c.dot(b_c)) - np.trace(a_c) * c.dot(b_c)
    return {'Fv/M': float(alpha1), 'g/M': float(beta0), 'k/M': float(alpha0)}


def closed_loop(theta: np.ndarray,
                record: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the position and command the model predicts in the loop, driven by r_cl (and pulses).

    y_m[k] = -a1 y_m[k-1] - a2 y_m[k-2] + b1 u_m[k-1] + b2 u_m[k-2] and
    u_m[k] = C(q)(r_cl - y_m)[k] + PULSE_GAIN pulses[k], from the record's first two samples.
    """
    a1, a2, b1, b2 = (float(value) for value in theta)
    c0, _, c2 = CONTROLLER['controller_numerator']
    r, y = record['r_cl'], record['y']
    pulses = record.get('pulses_N', np.zeros_like(r))
    count = r.shape[0]
    y_model, u_model = np.zeros(count), np.zeros(count)
    y_model[:2], u_model[:2] = y[:2], record['u1'][:2]
    for k in range(2, count):
        y_model[k] = (-a1 * y_model[k - 1] - a2 * y_model[k - 2] + b1 * u_model[k - 1]
                      + b2 * u_model[k - 2])
        if not abs(y_model[k]) < 1e6:
            y_model[k:] = math.nan
            u_model[k:] = math.nan
            break
        u_model[k] = (c0 * (r[k] - y_model[k]) + c2 * (r[k - 2] - y_model[k - 2])
                      + PULSE_GAIN * pulses[k])
    return y_model, u_model


def judge(theta: np.ndarray, validation: dict[str, np.ndarray]) -> dict[str, Any]:
    """Return the command's NRMSE fit and R^2 in closed loop on validation, Fv/M, g/M."""
    _, u_model = closed_loop(theta, validation)
    u = validation['u1']
    if np.isfinite(u_model).all():
        fit = nrmse_fit(u, u_model)
        r2 = 1.0 - float(np.sum((u - u_model) ** 2) / np.sum((u - u.mean()) ** 2))
    else:
        fit = r2 = -math.inf
    values = physical(theta)
    errors = {name: abs(values[name] / PHYSICAL[name] - 1.0) for name in PHYSICAL}
    return {'command_fit': fit, 'command_r2': r2, **values,
            'goals_met': all(errors[name] <= GOALS[name] for name in GOALS),
            'theta': [float(value) for value in theta]}


def regression(y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the ARX(2, 2) rows [-y(k-1), -y(k-2), u(k-1), u(k-2)] and targets y(k)."""
    return np.column_stack((-y[1:-1], -y[:-2], u[1:-1], u[:-2])), y[2:]


def closed_loop_iv(record: dict[str, np.ndarray], start: np.ndarray,
                   iterations: int = 4) -> np.ndarray:
    r"""
    Return the IV estimate with instruments from the noise-free closed loop driven by r_cl.

    :math:`\hat\theta = (Z^T\Phi)^{-1} Z^T y`, Z the ARX rows of the position
    and command that the current model predicts in the loop
    (:func:`closed_loop`), iterated from ``start``. Consistent when what the
    linear model leaves out is uncorrelated with the reference; Coulomb
    friction, a function of the motion the reference drives, is not.
    """
    phi, target = regression(record['y'], record['u1'])
    theta = start
    for _ in range(iterations):
        y_model, u_model = closed_loop(theta, record)
        instruments, _ = regression(y_model, u_model)
        theta = np.linalg.solve(instruments.T @ phi, instruments.T @ target)
    return theta


def physical_ls(record: dict[str, np.ndarray]) -> dict[str, float]:
    r"""
    Return Fv/M, Fc/M and g/M of the benchmark's own model by least squares (IDIM-LS).

    :math:`\ddot q = (g/M)\,u - (F_v/M)\,\dot q - (F_c/M)\,\mathrm{sign}(\dot q) - o/M`
    with central differences of the position; the linear models above cannot
    hold the Coulomb term.
    """
    q, u = record['y'], record['u1']
    velocity = (q[2:] - q[:-2]) / (2 * DT)
    acceleration = (q[2:] - 2 * q[1:-1] + q[:-2]) / DT ** 2
    rows = np.column_stack((u[1:-1], -velocity, -np.sign(velocity), -np.ones_like(velocity)))
    solution = np.linalg.lstsq(rows, acceleration, rcond=None)[0]
    return {'g/M': float(solution[0]), 'Fv/M': float(solution[1]),
            'Fc/M': float(solution[2])}


def online(label: str, record: dict[str, np.ndarray], gate: float) -> dict[str, Any]:
    """Run one online estimator over the estimation record; return its end state."""
    name, settings = ESTIMATORS[label]
    estimator = make_estimator(name, order=2, outlier_threshold=gate, **settings)
    y, u = record['y'], record['u1']
    for k in range(y.shape[0]):
        estimator.update(float(y[k]), (float(u[k]),))
    return {'theta': estimator.theta[:4], 'valid': bool(estimator.valid),
            'reasons': list(estimator.validity_reasons),
            'refused': estimator.flags.get('outlier_rejected', 0) / y.shape[0],
            'flags': dict(estimator.flags)}


def run(folder: Path) -> dict[str, Any]:
    """Return every estimator's and reference's figures on the EMPS records in ``folder``."""
    records = load(folder)
    estimation, validation = records['estimation'], records['validation']
    results: dict[str, Any] = {'online': {}, 'batch': {}}
    for label in ESTIMATORS:
        for gate in GATES:
            state = online(label, estimation, gate)
            results['online'][f'{label}, gate {gate:g}'] = {
                **judge(state.pop('theta'), validation), **state}
    phi, target = regression(estimation['y'], estimation['u1'])
    least_squares = np.linalg.lstsq(phi, target, rcond=None)[0]
    results['batch']['least squares'] = judge(least_squares, validation)
    results['batch']['IV, closed-loop instruments from r_cl'] = judge(
        closed_loop_iv(estimation, least_squares), validation)
    results['batch']['physical, published (linear part)'] = judge(physical_model(), validation)
    results['physical_ls'] = physical_ls(estimation)
    return results


def physical_model() -> np.ndarray:
    """Return the discrete ZOH model [a1, a2, b1, b2] of the published linear part."""
    pole = math.exp(-PHYSICAL['Fv/M'] * DT)
    gain = PHYSICAL['g/M'] / PHYSICAL['Fv/M']
    # (g/M)/(s (s + a)) at ZOH: b1 = k (a T - 1 + e^-aT)/a, b2 = k (1 - e^-aT - a T e^-aT)/a
    a = PHYSICAL['Fv/M']
    b1 = gain * (a * DT - 1.0 + pole) / a
    b2 = gain * (1.0 - pole - a * DT * pole) / a
    return np.array([-(1.0 + pole), pole, b1, b2])


def table(results: dict[str, Any]) -> str:
    """Return the markdown table of :func:`run`'s results."""
    rows = []
    for kind in ('online', 'batch'):
        for label, entry in results[kind].items():
            verdict = '' if kind == 'batch' else (
                'valid' if entry['valid'] else 'invalid: ' + '; '.join(entry['reasons']))
            refused = '' if kind == 'batch' else f'{100 * entry["refused"]:.2f} %'
            rows.append([label, refused, verdict, f'{entry["command_fit"]:.1f}',
                         f'{entry["command_r2"]:.2f}', f'{entry["Fv/M"]:.2f}',
                         f'{entry["g/M"]:.4f}', 'yes' if entry['goals_met'] else 'no'])
    ls = results['physical_ls']
    return (markdown_table(('estimator', 'refused', 'valid', 'command fit (%)', 'command R²',
                            'Fv/M (2.14)', 'g/M (0.3696)', 'goals met'), rows)
            + f'\nIDIM-LS with the Coulomb term: Fv/M {ls["Fv/M"]:.2f}, Fc/M {ls["Fc/M"]:.3f}, '
              f'g/M {ls["g/M"]:.4f}.\n')
