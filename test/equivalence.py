"""
Comparing two arithmetic paths within a bound derived from the problem.

Two runs of one code path on one machine give the same bits, and the tests
assert that (node against replay, save and restore). Two *different* paths
to the same numbers (batched against single plant, BLAS against numpy
element-wise, block against per-sample, a fast solver against the dense
equations) round differently, and numpy and OpenBLAS choose their kernels
per CPU at run time: on one machine they may agree to the last bit and on
another differ in 60 % of the steps. Such pairs are compared here within
``PATH_FACTOR`` times the *rounding spread* of the problem: how far the
reference path's results move when every input value is moved by one unit in
the last place. That spread is the problem's own amplification of a
last-bit difference (through the ill-conditioned start, the conditioning of
P and the number of steps), measured in the same test on the same machine,
so the bound is as tight as the problem allows and no tighter. Each test
that uses it also shows that one changed sample breaks it.

Where both sides are computed in the test (an estimator against its batch
formula, a solver against another), :func:`two_path_spread` adds the spreads of
both paths. Where a bound follows more simply from the sizes of the numbers (a
sum of N terms, one step, a solve of known condition), the test writes it down
with its reason and checks it with :func:`assert_within`.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

#: The bound is PATH_FACTOR times the rounding spread (and the summation term of
#: path_bound). The nudge puts one ulp into each of the 1 + r values of a sample; a
#: different path rounds a step's O(p^2) results (the p x p downdate) in other
#: places, p^2 <= 169 in these tests. On the five OpenBLAS kernels of an AVX-512
#: machine the largest ratio measured was 20 (bcrls in its first 60 samples); one
#: changed sample stays 3 decades or more above the bound (the tests check it).
PATH_FACTOR = 256.0
#: Nudged runs whose largest deviation is the spread: two, so that a
#: perturbation that happens to cancel in one quantity is not the measure.
NUDGED_RUNS = 2
#: The unit roundoff of a float64 operation is EPS / 2; bounds here are written in EPS.
EPS = float(np.finfo(float).eps)


def nudged(values: Any, rng: np.random.Generator) -> np.ndarray:
    """Return a copy with every finite non-zero value moved one ulp up or down at random."""
    values = np.asarray(values, dtype=float)
    up = rng.random(values.shape) < 0.5
    moved = np.where(up, np.nextafter(values, np.inf), np.nextafter(values, -np.inf))
    return np.where(np.isfinite(values) & (values != 0.0), moved, values)


def rows_of(values: Any) -> np.ndarray:
    """Return ``values`` as float rows: one row for a scalar or vector, else the last axis."""
    values = np.asarray(values, dtype=float)
    return values.reshape(1, -1) if values.ndim < 2 else values.reshape(-1, values.shape[-1])


def row_deviation(first: Any, second: Any) -> np.ndarray:
    """Return max |first - second| per row; NaN in either entry is skipped, equal infinities 0."""
    first, second = rows_of(first), rows_of(second)
    with np.errstate(invalid='ignore'):
        deviation = np.where(first == second, 0.0, np.abs(first - second))
    deviation[np.isnan(deviation)] = 0.0
    return deviation.max(axis=1, initial=0.0)


def rounding_spread(compute: Callable[..., dict[str, Any]], *data: Any,
                    seed: int = 0) -> dict[str, np.ndarray]:
    """
    Return, per quantity, how far ``compute``'s results move when ``data`` move by one ulp.

    ``compute(*data)`` returns a dict of float arrays (or floats, or None);
    it is run on the data and on ``NUDGED_RUNS`` nudged copies. The spread of
    a quantity is the largest absolute deviation over the runs, per row
    (:func:`rows_of`: per sample of a series of estimates, per row of a
    matrix), so that the ill-conditioned first estimates do not set the
    bound of the later ones.
    """
    rng = np.random.default_rng(seed)
    reference = compute(*data)
    spread = {key: np.zeros(rows_of(value).shape[0]) for key, value in reference.items()
              if value is not None}
    for _ in range(NUDGED_RUNS):
        other = compute(*(nudged(item, rng) for item in data))
        for key in spread:
            if other[key] is not None:
                spread[key] = np.maximum(spread[key], row_deviation(other[key], reference[key]))
    return spread


def two_path_spread(first: Callable[..., dict[str, Any]],
                    second: Callable[..., dict[str, Any]], *data: Any,
                    seed: int = 0) -> dict[str, np.ndarray]:
    """
    Return the rounding spreads of two paths on the same ``data``, added per quantity.

    Each path rounds its own way, so the difference of their results may hold
    the amplified last-bit errors of both: the sum of the two spreads of
    :func:`rounding_spread` (``first`` and ``second`` return dicts with the same
    keys).
    """
    one = rounding_spread(first, *data, seed=seed)
    other = rounding_spread(second, *data, seed=seed + 1)
    return {key: one[key] + other[key] for key in one}


def path_bound(expected: Any, spread: Any, steps: int) -> np.ndarray:
    """
    Return the bound of |actual - expected| per row, for ``expected`` and its ``spread``.

    ``PATH_FACTOR`` times the rounding spread plus ``steps`` ulps of the
    row's size: the two paths also round the running sums (a loss, a
    weighted count, moment sums) in other places, and a sum of ``steps``
    terms may carry up to ``steps`` roundings of its size (the classical
    bound of recursive summation), which no perturbation of the data shows.
    """
    magnitude = np.abs(rows_of(expected))
    magnitude[~np.isfinite(magnitude)] = 0.0
    size = magnitude.max(axis=1, initial=0.0)
    return PATH_FACTOR * (spread + max(steps, 1) * np.finfo(float).eps * size)


def assert_paths_agree(actual: dict[str, Any], expected: dict[str, Any],
                       spread: dict[str, Any], steps: int, what: str = '',
                       allowance: dict[str, Any] | None = None) -> None:
    """
    Assert that every quantity of two paths agrees within :func:`path_bound`.

    ``steps`` is the number of samples the paths went through; ``spread``
    comes from :func:`rounding_spread` (or is 0 where no arithmetic separates
    the two). ``allowance`` adds, per quantity (and row), what separates the
    paths besides rounding, derived by the test (an iteration's stopping
    tolerance). NaN must sit in the same entries in both, and None where the
    other is None.
    """
    allowance = allowance or {}
    assert actual.keys() == expected.keys(), (what, actual.keys() ^ expected.keys())
    for key, value in expected.items():
        if value is None or actual[key] is None:
            assert value is None and actual[key] is None, f'{what} {key}: {actual[key]} {value}'
            continue
        mine, theirs = np.asarray(actual[key], float), np.asarray(value, float)
        assert mine.shape == theirs.shape, f'{what} {key}: shape {mine.shape} {theirs.shape}'
        np.testing.assert_array_equal(np.isnan(mine), np.isnan(theirs),
                                      err_msg=f'{what} {key}: NaN entries')
        deviation = row_deviation(mine, theirs)
        bound = path_bound(theirs, spread[key], steps) + allowance.get(key, 0.0)
        # where the bound is 0 (exact zeros both), any deviation is too much
        excess = np.divide(deviation, bound, out=np.where(deviation > 0.0, np.inf, 0.0),
                           where=bound > 0.0)
        worst = int(np.argmax(excess))
        assert not excess[worst] > 1.0, (
            f'{what} {key}: the paths differ by {excess[worst]:.3g} times the bound '
            f'({PATH_FACTOR:g} x the rounding spread) in row {worst}')


def assert_within(actual: Any, expected: Any, bound: Any, what: str = '') -> None:
    """
    Assert that ``|actual - expected| <= bound`` in every entry (``bound`` broadcasts).

    For bounds derived a priori (the test states how). NaN must sit in the
    same entries in both; the message gives the worst ratio of the deviation
    to the bound.
    """
    actual, expected = np.asarray(actual, float), np.asarray(expected, float)
    assert actual.shape == expected.shape, f'{what}: shape {actual.shape} {expected.shape}'
    np.testing.assert_array_equal(np.isnan(actual), np.isnan(expected),
                                  err_msg=f'{what}: NaN entries')
    with np.errstate(invalid='ignore', divide='ignore'):
        deviation = np.where(actual == expected, 0.0, np.abs(actual - expected))
        deviation[np.isnan(deviation)] = 0.0
        excess = np.where(deviation > 0.0, deviation / np.broadcast_to(bound, deviation.shape),
                          0.0)
    worst = float(excess.max(initial=0.0))
    assert not worst > 1.0, (
        f'{what}: the two differ by {worst:.3g} times the bound at '
        f'{np.unravel_index(int(np.argmax(excess)), excess.shape)}')
