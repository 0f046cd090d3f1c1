r"""
The stability region D_M of RPEM: the test of a step and the projection of a fit into it.

Ljung and Söderström (1983), *Theory and Practice of Recursive
Identification* (L&S), the projection of the recursive prediction-error
algorithm into the stability region D_M; Ljung, *System Identification*,
2nd ed. (1999), ch. 11. The filter of the predictor and of its gradient
(F for OE; A and C for ARMAX) must keep its roots strictly within
``STABILITY_RADIUS``: :func:`~bcid_ros.estimators.polynomials.is_stable` with
``REGION_MARGIN`` tests a candidate (the recursion halves its step up to
``HALVINGS`` times until one passes), :func:`pull_inside` moves the roots of a
batch fit's start inside.

The test is not a comparison of the spectral radius: the rulebook's radius
answers whether a published model is unstable (radius beyond 1.01); here a
strict test against a radius below 1 runs on every candidate step (up to
``HALVINGS`` + 1 per sample). Jury's conditions decide it without computing
a root: for n = 2 a third of the cost of ``spectral_radius(a) < R`` and, on
roots within 1e-15 of R, a decision that differs from it in 4 % of draws (the
radius's square root rounds), measured.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

#: Largest pole (and, for ARMAX, zero of C) radius of an estimate: the
#: stability region D_M of L&S (F, or A and C, kept inside it).
STABILITY_RADIUS = 0.999
#: The same as the distance from the unit circle that ``polynomials.is_stable`` takes
#: (1 - (1 - 0.999) is 0.999 again in floats).
REGION_MARGIN = 1.0 - STABILITY_RADIUS
#: Step halvings tried before a step that leaves D_M is not taken at all.
HALVINGS = 8
#: A root within this of the unit circle is on the region's edge (beyond 0.9985: within half
#: the region's margin of its boundary): rpem/watch.py's on_boundary, edge_mode_cancelled.
EDGE_MARGIN = 1.5 * REGION_MARGIN
#: A zero of a numerator this close to a root on the edge cancels it (edge_mode_cancelled).
CANCELLING_DISTANCE = 0.01


def pull_inside(a: np.ndarray, radius: float = STABILITY_RADIUS) -> np.ndarray:
    """
    Return the coefficients with their roots moved inside ``radius``.

    A root z with |z| > 1 becomes 1/conj(z) (the same magnitude response up
    to a gain), then every root at or beyond ``radius`` is moved radially
    to 0.99 ``radius``. Non-finite coefficients give all zeros.
    """
    if not np.isfinite(a).all():
        return np.zeros_like(a)
    roots = np.roots(np.concatenate(([1.0], a)))
    size = np.abs(roots)
    roots = np.where(size > 1.0, 1.0 / np.conj(roots), roots)
    size = np.abs(roots)
    roots = np.where(size >= radius, roots * (0.99 * radius / np.maximum(size, 1e-300)), roots)
    return np.real(np.poly(roots))[1:]


def edge_mode_cancelled(f: np.ndarray, numerators: Sequence[np.ndarray]) -> bool:
    """
    Return whether a root of 1 + f q^-1 + ... on the region's edge is cancelled in every input.

    On the edge: within ``EDGE_MARGIN`` of the unit circle. Cancelled: each numerator (an
    input's b coefficients, lags in order) has a zero within ``CANCELLING_DISTANCE`` of it,
    or is all zero. Such a mode leaves the inputs' response all but alone, and in a fit with
    each segment's initial state free it serves that state: a slow exponential that fits the
    slow part of the disturbance (a drift, coloured noise), where the plant's own modes fit
    worse. The data do not push the model there as they push an integrator's pole, which no
    zero cancels (tracking plant (8, 22): a fit during a drift took poles 0.998 with zeros
    0.997, and rpem stayed 180 % off for the record's last 4400 samples; docs/tracking_log.md,
    session 19).
    """
    if not (np.isfinite(f).all() and all(np.isfinite(b).all() for b in numerators)):
        return False
    roots = np.roots(np.concatenate(([1.0], f)))
    for root in roots[np.abs(roots) > 1.0 - EDGE_MARGIN]:
        if all(_has_zero_near(b, root) for b in numerators):
            return True
    return False


def _has_zero_near(b: np.ndarray, root: complex) -> bool:
    """Return whether the polynomial of ``b`` has a zero within CANCELLING_DISTANCE of root."""
    b = np.trim_zeros(b, 'f')
    if not b.size:  # (no response at all through this input)
        return True
    zeros = np.roots(b)
    return bool(zeros.size) and float(np.min(np.abs(zeros - root))) < CANCELLING_DISTANCE
