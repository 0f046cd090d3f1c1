r"""
Indirect pole placement for a single-input plant estimated by the identifier.

The plant is the ARX model of the estimate topics,

.. math::

    A(q^{-1}) y_t = B(q^{-1}) u_t, \qquad
    A = 1 + a_1 q^{-1} + \dots + a_n q^{-n}, \quad
    B = \sum_{l \in L} b_{1,l} q^{-l},

with the lags L of the parameter names ``b1_<lag>`` (``1..n``; ``0..n``
with feedthrough; shifted by the input delay d). Multiplied by
:math:`q^N`, :math:`N = \max(n, \max L)`, it becomes the rational plant
B(q)/A(q) in positive powers of q with A monic of degree N (``N - n``
roots at 0 carry the delay) and :math:`\deg B = N - \min L`.

The controller is :math:`C(q) = S(q)/R(q)` in negative feedback,
:math:`u = C(q)(r' - y)`, so the closed-loop characteristic polynomial is

.. math::

    A R + B S = A_{cl}, \qquad A_{cl} = \prod_k (q - p_k).       \qquad (D)

With integral action :math:`R = (q - 1) R'`; write :math:`\bar A = A (q - 1)`
(else :math:`\bar A = A`, :math:`R = R'`), :math:`\nu = \deg \bar A`. The
solution with :math:`R'` monic of degree m and :math:`\deg S = \nu - 1`
solves the square linear system of the :math:`\nu + m` coefficients below
the leading one of :math:`\bar A R' + B S = A_{cl}`, whose matrix is the
Sylvester matrix of :math:`\bar A` and B (columns :math:`q^k \bar A` and
:math:`q^k B`). It is nonsingular exactly when :math:`\bar A` and B are
coprime: a near-singular matrix means a near pole-zero cancellation (or,
with integral action, a plant zero near 1), and the design is refused.

**Degrees.** The leading coefficient of (D) stays that of :math:`\bar A R'`
when :math:`\deg B \le m`. The controller is proper when
:math:`\deg S \le \deg R`, strictly proper when :math:`\deg S < \deg R`,
which it must be when the plant has feedthrough (else the loop is
algebraic) or when the input computed from :math:`y_t` is applied at
:math:`t + 1` (``computation_delay``). The smallest m is

.. math::

    m = N - 1 \text{ (proper allowed)}, \qquad
    m = N \text{ (strictly proper required)},

and :math:`\deg A_{cl} = \nu + m`: the number of closed-loop poles to give.
More poles raise m (the extra ones act as observer poles).
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Sequence

import numpy as np

#: Default largest condition number of the scaled Sylvester matrix.
DEFAULT_MAX_CONDITION = 1e4
#: Largest relative residual of (D) accepted after the solve.
MAX_RESIDUAL = 1e-8
#: The parameter names this module understands: ``a<i>`` and ``b1_<lag>``.
_NAME = re.compile(r'^(?:a(?P<a>[1-9][0-9]*)|b(?P<input>[1-9][0-9]*)_(?P<lag>0|[1-9][0-9]*))$')


class DesignRefused(ValueError):
    """
    A design (or an estimate it was asked for) is refused.

    Attributes
    ----------
    reason : str
        A short key, counted in the diagnostics: ``bad_names``,
        ``wrong_order``, ``nonfinite_estimate``, ``ill_conditioned`` or
        ``design_residual``.

    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclasses.dataclass(frozen=True)
class ModelStructure:
    """
    The ARX structure a controller is configured for.

    Attributes
    ----------
    order : int
        n, the number of ``a`` coefficients.
    feedthrough : bool
        Whether ``b1_<d>`` (lag equal to the delay) is estimated.
    input_delay : int
        Dead time d in samples.

    """

    order: int
    feedthrough: bool = False
    input_delay: int = 0

    @property
    def lags(self) -> tuple[int, ...]:
        """Return the input lags, ascending."""
        first = self.input_delay + (0 if self.feedthrough else 1)
        return tuple(range(first, self.input_delay + self.order + 1))

    @property
    def names(self) -> tuple[str, ...]:
        """Return the estimate's parameter names ``a1..an, b1_<lag>...``."""
        return tuple(f'a{i}' for i in range(1, self.order + 1)) + \
            tuple(f'b1_{lag}' for lag in self.lags)

    @property
    def plant_degree(self) -> int:
        """Return N = deg A(q) in positive powers of q."""
        return max(self.order, self.lags[-1])

    @property
    def numerator_degree(self) -> int:
        """Return the formal deg B(q) = N - smallest lag."""
        return self.plant_degree - self.lags[0]


def parse_names(names: Sequence[str]) -> ModelStructure:
    """
    Return the structure of a single-input estimate from its parameter names.

    Parameters
    ----------
    names : sequence of str
        As in the label of ``~/parameters``: ``a1..an`` then ``b1_<lag>``
        for consecutive lags.

    Returns
    -------
    ModelStructure

    Raises
    ------
    DesignRefused
        ``bad_names`` if a name is not of that form, the ``a`` are not
        ``a1..an`` in order, there is more than one input, or the lags are
        not consecutive and end at ``d + n``.

    """
    names = tuple(names)
    orders, lags = [], []
    for name in names:
        match = _NAME.match(name)
        if match is None:
            raise DesignRefused('bad_names', f'parameter name {name!r} is neither a<i> nor '
                                f'b<input>_<lag> (names {",".join(names)!r})')
        if match['a'] is not None:
            if lags:
                raise DesignRefused('bad_names', f'a coefficient {name!r} after the b ones '
                                    f'(names {",".join(names)!r})')
            orders.append(int(match['a']))
        elif match['input'] != '1':
            raise DesignRefused('bad_names', f'the controller is single-input, got {name!r} '
                                f'(names {",".join(names)!r})')
        else:
            lags.append(int(match['lag']))
    order = len(orders)
    if order == 0 or orders != list(range(1, order + 1)) or not lags:
        raise DesignRefused('bad_names', f'expected a1..an then b1_<lag>, got '
                            f'{",".join(names)!r}')
    delay = lags[-1] - order
    structure = None
    if delay >= 0:
        feedthrough = len(lags) == order + 1
        structure = ModelStructure(order, feedthrough, delay)
    if structure is None or tuple(lags) != structure.lags:
        raise DesignRefused('bad_names', f'the lags of b1 must run from d + 1 (d with '
                            f'feedthrough) to d + n, got {",".join(names)!r}')
    return structure


def check_estimate(names: Sequence[str], values: Sequence[float],
                   structure: ModelStructure) -> np.ndarray:
    """
    Return an estimate as a float array after checking it against the configuration.

    Raises
    ------
    DesignRefused
        ``bad_names`` (unparsable names, or not one value per name),
        ``wrong_order`` (a valid structure other than the configured one),
        ``nonfinite_estimate`` (NaN or Inf among the values).

    """
    names = tuple(names)
    values = np.asarray(values, dtype=float)
    if values.shape != (len(names),):
        raise DesignRefused('bad_names', f'{values.size} values for {len(names)} names '
                            f'({",".join(names)!r})')
    found = parse_names(names)
    if found != structure:
        raise DesignRefused('wrong_order', f'estimate names {",".join(names)!r} do not '
                            f'match the configuration {",".join(structure.names)!r}')
    if not np.all(np.isfinite(values)):
        raise DesignRefused('nonfinite_estimate', 'the estimate holds NaN or Inf')
    return values


@dataclasses.dataclass(frozen=True)
class Plant:
    """
    A rational plant B(q)/A(q), coefficients in descending powers of q.

    Attributes
    ----------
    denominator : numpy.ndarray
        A(q), monic, shape ``(N + 1,)``.
    numerator : numpy.ndarray
        B(q), shape ``(deg B + 1,)`` with the formal degree of the structure.

    """

    denominator: np.ndarray
    numerator: np.ndarray

    @classmethod
    def from_estimate(cls, values: Sequence[float], structure: ModelStructure) -> 'Plant':
        """Return the plant of an estimate ``[a1..an, b1_<lags>]`` of ``structure``."""
        values = np.asarray(values, dtype=float)
        n, degree = structure.order, structure.plant_degree
        # A(q) = q^N + a1 q^(N-1) + ... + an q^(N-n)
        denominator = np.zeros(degree + 1)
        denominator[0] = 1.0
        denominator[1:n + 1] = values[:n]
        # B(q) = sum_l b_l q^(N-l), kept at its formal degree N - min lag
        numerator = np.zeros(degree + 1)
        for lag, value in zip(structure.lags, values[n:]):
            numerator[lag] = value
        return cls(denominator, numerator[structure.lags[0]:])


@dataclasses.dataclass(frozen=True)
class Controller:
    """
    A feedback C(q) = S(q)/R(q) for u = C(q)(r' - y), descending powers of q.

    Attributes
    ----------
    numerator : numpy.ndarray
        S(q), at most as long as the denominator.
    denominator : numpy.ndarray
        R(q), monic.
    condition : float
        Condition number of the scaled Sylvester matrix of the design
        (``nan`` for a configured controller).

    """

    numerator: np.ndarray
    denominator: np.ndarray
    condition: float = math.nan

    @classmethod
    def from_coefficients(cls, numerator: Sequence[float],
                          denominator: Sequence[float]) -> 'Controller':
        """
        Return a configured controller, normalised so that R is monic.

        Raises
        ------
        ValueError
            If a coefficient is not finite, R is empty or its leading
            coefficient is 0, or deg S > deg R (not causal).

        """
        num = np.atleast_1d(np.asarray(numerator, dtype=float))
        den = np.atleast_1d(np.asarray(denominator, dtype=float))
        if num.size == 0 or den.size == 0 or not np.all(np.isfinite(num)) or \
                not np.all(np.isfinite(den)) or den[0] == 0.0:
            raise ValueError(f'controller must have finite coefficients and a non-zero '
                             f'leading denominator coefficient, got numerator '
                             f'{num.tolist()}, denominator {den.tolist()}')
        num = np.trim_zeros(num, 'f')
        if num.size == 0:
            num = np.zeros(1)
        if num.size > den.size:
            raise ValueError(f'controller must be causal (numerator degree <= denominator '
                             f'degree), got numerator {num.tolist()}, denominator '
                             f'{den.tolist()}')
        return cls(num / den[0], den / den[0])

    @property
    def strictly_proper(self) -> bool:
        """Return whether deg S < deg R or S = 0 (u_t does not depend on e_t)."""
        return self.numerator.size < self.denominator.size or not np.any(self.numerator)

    def message_data(self) -> tuple[list[float], list[float]]:
        """Return (numerator, denominator) as lists for the ``~/controller`` topic."""
        return [float(v) for v in self.numerator], [float(v) for v in self.denominator]


#: The ``layout.dim`` labels of a ``~/controller`` message, in order.
CONTROLLER_LABELS = ('numerator', 'denominator')


def controller_from_message(labels: Sequence[str], sizes: Sequence[int],
                            data: Sequence[float]) -> Controller:
    """
    Return the controller of a ``~/controller`` message, or say why it is malformed.

    Parameters
    ----------
    labels, sizes : sequence
        ``layout.dim[k].label`` and ``.size``: exactly ``numerator``,
        ``denominator``.
    data : sequence of float
        The numerator then the denominator, descending powers of q.

    Raises
    ------
    ValueError
        If the layout is not (numerator, denominator), the sizes do not add
        up to the data, or the controller is not finite and causal.

    """
    if tuple(labels) != CONTROLLER_LABELS:
        raise ValueError(f'controller message layout must be dim labels '
                         f'{list(CONTROLLER_LABELS)}, got {list(labels)}')
    sizes = [int(size) for size in sizes]
    values = np.asarray(data, dtype=float)
    if min(sizes) < 1 or sum(sizes) != values.size:
        raise ValueError(f'controller message sizes {sizes} must be >= 1 and add up to the '
                         f'{values.size} values of data')
    return Controller.from_coefficients(values[:sizes[0]], values[sizes[0]:])


def closed_loop_polynomial(plant: Plant, controller: Controller) -> np.ndarray:
    """Return A R + B S, descending powers of q."""
    return np.polyadd(np.polymul(plant.denominator, controller.denominator),
                      np.polymul(plant.numerator, controller.numerator))


def closed_loop_poles(plant: Plant, controller: Controller) -> np.ndarray:
    """Return the roots of A R + B S, sorted by decreasing modulus."""
    roots = np.roots(closed_loop_polynomial(plant, controller))
    return roots[np.argsort(-np.abs(roots), kind='stable')]


def pole_distance(achieved: Sequence[complex], target: Sequence[complex]) -> float:
    """
    Return the distance between two sets of poles (Hausdorff, in the complex plane).

    The largest distance from a pole of either set to the nearest pole of
    the other: 0 when the sets are equal, at most d when every pole is
    within d of one of the other set and the other way round.
    """
    a = np.asarray(achieved, dtype=complex).reshape(-1, 1)
    b = np.asarray(target, dtype=complex).reshape(1, -1)
    if a.size == 0 or b.size == 0:
        return 0.0 if a.size == b.size else math.inf
    gaps = np.abs(a - b)
    return float(max(gaps.min(axis=1).max(), gaps.min(axis=0).max()))


def format_poles(poles: Sequence[complex] | None, number: str = '.4g',
                 missing: str = '?') -> str:
    """
    Return poles as text, largest real part first, a complex one as a+bj.

    Parameters
    ----------
    poles : sequence of complex or None
        The poles; None gives ``missing``.
    number : str
        The format of each real and imaginary part (``'.3f'``, ``'.4g'``).
    missing : str
        The text for no poles (None).

    """
    if poles is None:
        return missing
    return ', '.join(f'{p.real:{number}}' if abs(p.imag) < 1e-9 else
                     f'{p.real:{number}}{p.imag:+{number}}j'
                     for p in sorted(np.asarray(poles, complex), key=lambda p: -p.real))


def controller_degree(structure: ModelStructure, *, strictly_proper: bool) -> int:
    """Return the smallest m = deg R' of a causal design (module docstring, Degrees)."""
    must_be_strict = strictly_proper or structure.lags[0] == 0
    return structure.plant_degree if must_be_strict else structure.plant_degree - 1


def required_pole_count(structure: ModelStructure, *, integral: bool,
                        strictly_proper: bool) -> int:
    """Return the fewest closed-loop poles of a design: deg A + [integral] + m."""
    return structure.plant_degree + int(integral) + \
        controller_degree(structure, strictly_proper=strictly_proper)


def sylvester_matrix(abar: np.ndarray, numerator: np.ndarray, m: int) -> np.ndarray:
    r"""
    Return the matrix of :math:`(R', S) \mapsto \bar A R' + B S` below the leading row.

    Parameters
    ----------
    abar : numpy.ndarray
        :math:`\bar A`, monic, degree :math:`\nu`, shape ``(nu + 1,)``.
    numerator : numpy.ndarray
        B, degree at most m, shape ``(<= m + 1,)``.
    m : int
        deg R'.

    Returns
    -------
    numpy.ndarray
        Shape ``(nu + m, nu + m)``: columns for :math:`r'_1..r'_m` (the
        coefficients of :math:`q^{m-1}..q^0` of R') then :math:`s_0..s_{\nu-1}`
        (of :math:`q^{\nu-1}..q^0`); rows for :math:`q^{\nu+m-1}..q^0`.

    """
    nu = abar.size - 1
    size = nu + m
    if numerator.size > m + 1:
        raise ValueError(f'deg B must be at most m = {m} (deg R\'), got {numerator.size - 1}')
    matrix = np.zeros((size + 1, size))
    for k in range(1, m + 1):
        # column of r'_k: the coefficients of q^(m-k) Abar in a degree nu + m vector
        matrix[k:k + nu + 1, k - 1] = abar
    for j in range(nu):
        # column of s_j: q^(nu-1-j) B, whose last coefficient sits at row size - (nu-1-j)
        end = size + 1 - (nu - 1 - j)
        matrix[end - numerator.size:end, m + j] = numerator
    # deg B <= m keeps the leading row (q^(nu+m)) empty: it is R' monic
    return matrix[1:]


def place_poles(plant: Plant, poles: Sequence[float], *, integral: bool = False,
                strictly_proper: bool = True,
                max_condition: float = DEFAULT_MAX_CONDITION) -> Controller:
    r"""
    Solve the Diophantine equation (D) for the controller with the given closed-loop poles.

    Parameters
    ----------
    plant : Plant
        The (estimated) plant; ``numerator`` at its formal degree.
    poles : sequence of float
        The desired closed-loop poles; their number fixes
        :math:`m = \text{len(poles)} - \nu`.
    integral : bool
        Put the factor (q - 1) in R (zero steady-state error on steps).
    strictly_proper : bool
        Require deg S < deg R (the input is applied one sample after the
        measurement it is computed from).
    max_condition : float
        Refuse when the Sylvester matrix, with the columns of
        :math:`\bar A` and of B scaled to unit norm, has a larger condition
        number (near pole-zero cancellation).

    Returns
    -------
    Controller
        S/R with R monic, ``condition`` set.

    Raises
    ------
    ValueError
        If there are too few poles for a causal design.
    DesignRefused
        ``ill_conditioned`` (near-singular Sylvester matrix, also B = 0) or
        ``design_residual`` (the solution does not satisfy (D)).

    """
    abar = np.polymul(plant.denominator, [1.0, -1.0]) if integral else plant.denominator
    nu = abar.size - 1
    numerator = plant.numerator
    m = len(poles) - nu
    must_be_strict = strictly_proper or numerator.size == plant.denominator.size
    smallest = plant.denominator.size - 1 - (0 if must_be_strict else 1)
    if m < smallest:
        raise ValueError(f'parameter \'closed_loop_poles\' must hold at least '
                         f'{nu + smallest} poles for this plant and controller, got '
                         f'{len(poles)}')
    target = np.real(np.poly(np.asarray(poles, dtype=float)))
    norm_a, norm_b = np.linalg.norm(abar), np.linalg.norm(numerator)
    if norm_b == 0.0:
        raise DesignRefused('ill_conditioned', 'the estimated plant has B = 0 (no input '
                            'effect); keeping the last controller')
    matrix = sylvester_matrix(abar, numerator, m)
    scale = np.concatenate([np.full(m, 1.0 / norm_a), np.full(nu, 1.0 / norm_b)])
    scaled = matrix * scale
    with np.errstate(all='ignore'):
        condition = float(np.linalg.cond(scaled))
    if not math.isfinite(condition) or condition > max_condition:
        raise DesignRefused('ill_conditioned', f'Sylvester matrix condition {condition:.3g} '
                            f'> max_condition {max_condition:g} (near pole-zero '
                            f'cancellation); keeping the last controller')
    # right-hand side: A_cl - q^m Abar, below the leading coefficient
    rhs = (target - np.concatenate([abar, np.zeros(m)]))[1:]
    solution = np.linalg.solve(scaled, rhs) * scale
    r_prime = np.concatenate([[1.0], solution[:m]])
    denominator = np.polymul(r_prime, [1.0, -1.0]) if integral else r_prime
    controller = Controller(solution[m:].copy(), denominator, condition)
    achieved = closed_loop_polynomial(plant, controller)
    residual = np.linalg.norm(achieved - target) / np.linalg.norm(target)
    if not np.all(np.isfinite(achieved)) or residual > MAX_RESIDUAL:
        raise DesignRefused('design_residual', f'the design misses A R + B S = A_cl by '
                            f'{residual:.3g} (relative); keeping the last controller')
    return controller


__all__ = ['CONTROLLER_LABELS', 'Controller', 'DEFAULT_MAX_CONDITION', 'DesignRefused',
           'ModelStructure', 'Plant', 'check_estimate', 'closed_loop_polynomial',
           'closed_loop_poles', 'controller_degree', 'controller_from_message', 'format_poles',
           'parse_names', 'place_poles', 'pole_distance', 'required_pole_count',
           'sylvester_matrix']
