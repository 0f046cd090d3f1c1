r"""
With ``window`` 0: the moments of all rows since the controller change, Algorithm 1 on them.

Ikeda (2008), eq. (13) written as :math:`y_f[k] = \psi[k]^T [a \mid b] + \varepsilon[k]`,
:math:`\psi = D\varphi`, :math:`D = \mathrm{diag}(-I_n, I_n)`: its parameter
does not depend on the prefilter f, so rows filtered by different
prefilters stack in one LS. Each row of epoch e (filtered by :math:`f_e`)
carries the noise moments of Theorem 1, :math:`E\{\psi\varepsilon\} = D c_e
\sigma_\nu^2`, :math:`E\{\varepsilon^2\} = \beta_e \sigma_\nu^2` (eqs. 37,
57). With weights :math:`w_k = \lambda^{N-k}` the statistics are

.. math::

    M = \sum w_k \psi\psi^T, \quad P = M^{-1}, \quad
    \hat\theta_{LS} = P \sum w_k \psi\, y_f, \quad
    J = \sum w_k (y_f - \psi^T\hat\theta_{LS})^2, \\
    C = \sum_e W_e D c_e, \quad B = \sum_e W_e \beta_e, \quad
    W_e = \sum_{k \in e} w_k,

and since :math:`J \approx B\sigma_\nu^2 - \sigma_\nu^4 C^T P C`, eqs. (58),
(59) become

.. math::

    \hat\sigma_\nu^2 = \frac{2J}{B + \sqrt{B^2 - 4 (C^T P C) J}}, \qquad
    \hat\theta_{BC} = \hat\theta_{LS} - \hat\sigma_\nu^2 P C,

which with one epoch and :math:`\lambda = 1` is exactly eqs. (53),
(56)-(59) (:math:`B = N\beta`, :math:`C^TPC = N \alpha`).
:class:`PrefilteredMoments` keeps the sums and the epochs; its
:meth:`~PrefilteredMoments.fixed_point` is the iteration of Algorithm 1's
steps 3-5 on them (the exact LS from the moments, no refiltering).
:class:`AllDataMemory` is what the online estimator remembers with
``window`` 0: these moments, the running LS and the redesign schedule
(redesigns after ``10 * 2n + n`` rows, then each time the rows double,
until they are ``redesign_period`` rows apart).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from bcid_ros.estimators.cl_bcls.bias import bias_terms
from bcid_ros.estimators.cl_bcls.compensation import Compensation, Redesign
from bcid_ros.estimators.cl_bcls.regression import (CompensationFailure, definite_inverse,
                                                    moment_loss)
from bcid_ros.estimators.cl_bcls.running_ls import (PrefilterBank, REFUSED, REPAIR, RunningLs,
                                                    STEPPED, UNSAFE)
from bcid_ros.estimators.lti import Controller, stable_reflection
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from bcid_ros.estimators.recursion import innovation

#: With ``window`` 0 a redesign changes the prefilter only when the new f(q) differs from
#: the one in use by more than this (2-norm of the coefficients; docs/cl_bcls.md).
PREFILTER_STEP = 0.05


class MomentCompensation(NamedTuple):
    """
    The fixed point of steps 3-5 on the moments, as :meth:`PrefilteredMoments.fixed_point` ends.

    Attributes
    ----------
    theta : numpy.ndarray, shape ``(2n,)``
        theta_BC, plant form [a | b].
    directions : numpy.ndarray, shape ``(epochs, 2n)``
        D c_e of every epoch at the estimate before the last step.
    betas : numpy.ndarray, shape ``(epochs,)``
        beta_e of every epoch, likewise.
    pc : numpy.ndarray, shape ``(2n,)``
        P C.
    direction : numpy.ndarray, shape ``(2n,)``
        C = sum_e W_e D c_e.
    total_beta : float
        B = sum_e W_e beta_e.
    iterations : int
        Steps made.
    converged : bool
        Whether the stopping rule was met within the cap.

    """

    theta: np.ndarray
    directions: np.ndarray
    betas: np.ndarray
    pc: np.ndarray
    direction: np.ndarray
    total_beta: float
    iterations: int
    converged: bool


class PrefilteredMoments:
    """
    The weighted moments of the rows since the change, and the epochs of their prefilters.

    The sums are :attr:`information` M, :attr:`cross` sum w psi y_f and
    :attr:`energy` sum w y_f^2; each epoch has its prefilter, weight W_e,
    D c_e and beta_e.

    Parameters
    ----------
    prefilter : numpy.ndarray, shape ``(n + 1,)``
        The prefilter of the first epoch.
    num_parameters : int
        p = 2n.

    """

    def __init__(self, prefilter: np.ndarray, num_parameters: int) -> None:
        p = num_parameters
        self.information = np.zeros((p, p))
        self.cross = np.zeros(p)
        self.energy = 0.0
        self.prefilters = [prefilter.copy()]
        self.weights = np.zeros(1)
        self.directions = np.zeros((1, p))
        self.betas = np.ones(1)

    def weighted_count(self) -> float:
        """Return tau, the weighted count of the rows."""
        return float(self.weights.sum())

    def add(self, psi: np.ndarray, target: float, lam: float) -> None:
        """Add the row (psi, y_f) after one forgetting step of everything."""
        if lam != 1.0:
            self.information *= lam
            self.cross *= lam
            self.energy *= lam
            self.weights *= lam
        self.information += psi[:, None] * psi
        self.cross += psi * target
        self.energy += target * target
        self.weights[-1] += 1.0

    def cut(self, keep: float) -> None:
        """Keep the share ``keep`` of the memory (one extra forgetting step)."""
        self.information *= keep
        self.cross *= keep
        self.energy *= keep
        self.weights *= keep

    def sums(self) -> np.ndarray:
        """Return [M, sum w psi y_f, sum w y_f^2] flat (for the block means)."""
        return np.concatenate((self.information.reshape(-1), self.cross, [self.energy]))

    def open_epoch(self, prefilter: np.ndarray, direction: np.ndarray, beta: float) -> None:
        """Start a new epoch: the following rows come through ``prefilter``."""
        self.prefilters.append(prefilter)
        self.weights = np.append(self.weights, 0.0)
        self.directions = np.vstack((self.directions, direction))
        self.betas = np.append(self.betas, beta)

    # ------------------------------------------------------------ Algorithm 1
    def exact_ls(self) -> tuple[np.ndarray, np.ndarray, float]:
        """
        Return (theta_LS, P, J) solved from the moments (plant form).

        Raises
        ------
        CompensationFailure
            ``singular_information`` if M is not positive definite or the
            solution is not finite.

        """
        inverse = definite_inverse(self.information, 'the information matrix')
        theta = inverse.dot(self.cross)
        loss = moment_loss(self.information, self.cross, self.energy, theta)
        if not (np.isfinite(theta).all() and np.isfinite(inverse).all()):
            raise CompensationFailure('singular_information', 'the LS solution is not finite')
        return theta, 0.5 * (inverse + inverse.T), loss

    def fixed_point(self, starts: Sequence[np.ndarray], theta_ls: np.ndarray,
                    inverse: np.ndarray, loss: float, controller: Controller,
                    unit_weights: np.ndarray, max_iterations: int,
                    tolerance: float) -> MomentCompensation:
        """
        Iterate steps (3)-(5) on the moments to a fixed point, from the first start that works.

        Each start is tried in turn until one iterates without a
        :class:`~bcid_ros.estimators.cl_bcls.regression.CompensationFailure`
        (raised from the last). The iteration converges linearly (factor rho
        about 0.6-0.98 on the paper's loop, the larger the farther f is from
        a_p), so it stops when the estimated distance to the fixed point,
        step * rho / (1 - rho) with rho the ratio of the last two steps, is
        below ``tolerance``; the step is measured on ``unit_weights`` times
        the estimate (b times s_u / s_y), so that the stopping point does not
        depend on the units of y and u.
        """
        for number, start in enumerate(starts):
            try:
                return self._iterate(start, theta_ls, inverse, loss, controller, unit_weights,
                                     max_iterations, tolerance)
            except CompensationFailure:
                if number == len(starts) - 1:
                    raise
        raise ValueError('starts must not be empty')

    def _iterate(self, estimate: np.ndarray, theta_ls: np.ndarray, inverse: np.ndarray,
                 loss: float, controller: Controller, unit_weights: np.ndarray,
                 max_iterations: int, tolerance: float) -> MomentCompensation:
        """Iterate steps (3)-(5) from ``estimate`` (see :meth:`fixed_point`)."""
        last_step = math.inf
        converged = False
        for iterations in range(1, max_iterations + 1):
            # c_e, beta_e of every epoch from the current estimate            (37), (57)
            directions, betas = self.epoch_terms(estimate, controller)
            compensated, pc, direction, total_beta = self.compensation(
                theta_ls, inverse, loss, directions, betas)
            step = float(np.linalg.norm((compensated - estimate) * unit_weights))
            estimate = compensated
            rate = step / last_step  # 0 at the first iteration: never stops there
            if step == 0.0 or (0.0 < rate < 1.0
                               and step * rate / (1.0 - rate) < tolerance):
                converged = True
                break
            last_step = step
        return MomentCompensation(estimate, directions, betas, pc, direction, total_beta,
                                  iterations, converged)

    def epoch_terms(self, theta: np.ndarray, controller: Controller
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Return D c_e and beta_e of every epoch for the plant ``theta`` (eqs. 37, 57)."""
        n = theta.shape[0] // 2
        prefilters = self.prefilters
        directions = np.empty((len(prefilters), 2 * n))
        betas = np.empty(len(prefilters))
        for index, prefilter in enumerate(prefilters):
            c_e, betas[index] = bias_terms(theta, prefilter, controller)
            directions[index] = np.concatenate((-c_e[:n], c_e[n:]))
        return directions, betas

    def compensation(self, theta_ls: np.ndarray, inverse: np.ndarray, loss: float,
                     directions: np.ndarray, betas: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """
        Return (theta_BC, P C, C, B) of the generalised eqs. (58), (59).

        Raises
        ------
        CompensationFailure
            ``negative_variance_argument`` if B^2 - 4 C'PC J < 0,
            ``lyapunov_failed`` if theta_BC is not finite.

        """
        direction = self.weights.dot(directions)
        total_beta = float(self.weights.dot(betas))
        pc = inverse.dot(direction)
        discriminant = total_beta * total_beta - 4.0 * direction.dot(pc) * loss
        if not discriminant >= 0.0:
            raise CompensationFailure('negative_variance_argument',
                                      'B^2 - 4 C\'PC J < 0 in eq. (58)')
        sigma2 = 2.0 * loss / (total_beta + math.sqrt(discriminant))
        compensated = theta_ls - sigma2 * pc
        if not np.isfinite(compensated).all():
            raise CompensationFailure('lyapunov_failed', 'compensated estimate not finite')
        return compensated, pc, direction, total_beta

    # ------------------------------------------------------------ the state
    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the state (not copied)."""
        arrays = {'information': self.information, 'cross': self.cross}
        scalars = {'energy': self.energy,
                   'epoch_prefilters': [f.tolist() for f in self.prefilters],
                   'epoch_weights': self.weights.tolist(),
                   'epoch_directions': self.directions.tolist(),
                   'epoch_betas': self.betas.tolist()}
        return arrays, scalars

    @classmethod
    def from_state(cls, arrays: dict[str, np.ndarray], scalars: dict[str, Any]
                   ) -> PrefilteredMoments:
        """Return the moments of a state made by :meth:`state_items`."""
        prefilters = [np.array(f, dtype=float) for f in scalars['epoch_prefilters']]
        p = arrays['cross'].shape[0]
        moments = cls(prefilters[0], p)
        moments.information = arrays['information']
        moments.cross = arrays['cross']
        moments.energy = float(scalars['energy'])
        moments.prefilters = prefilters
        moments.weights = np.array(scalars['epoch_weights'], dtype=float)
        moments.directions = np.array(scalars['epoch_directions'], dtype=float).reshape(
            len(prefilters), p)
        moments.betas = np.array(scalars['epoch_betas'], dtype=float)
        return moments

    def snapshot(self) -> tuple:
        """Return what a step may change (the sums and weights in place too, the epochs)."""
        return (self.information, self.information.copy(), self.cross, self.cross.copy(),
                self.energy, self.weights, self.weights.copy(), list(self.prefilters),
                self.directions, self.betas)

    def restore(self, saved: tuple) -> None:
        """Go back to a :meth:`snapshot`."""
        (self.information, information, self.cross, cross, self.energy, self.weights, weights,
         prefilters, self.directions, self.betas) = saved
        self.information[:] = information
        self.cross[:] = cross
        self.weights[:] = weights
        self.prefilters[:] = prefilters


class AllDataMemory:
    """
    What the online estimator remembers with ``window`` 0: moments, running LS, schedule.

    Every row since the controller change enters the moments
    (:class:`PrefilteredMoments`) and the running LS in the form
    y_f = psi' [a | b] (:class:`~bcid_ros.estimators.cl_bcls.running_ls.RunningLs`,
    weighted by the forgetting factor); a redesign is one iteration of
    Algorithm 1 on the moments, and a prefilter that moved opens a new epoch.

    Parameters
    ----------
    prefilter : numpy.ndarray, shape ``(n + 1,)``
        The prefilter in use.
    initial_p : numpy.ndarray, shape ``(2n, 2n)``
        P(0) of the running LS.
    min_window : int
        The rows before the first redesign (``10 * 2n + n``).
    redesign_period : int
        The most rows between two redesigns.

    """

    def __init__(self, prefilter: np.ndarray, initial_p: np.ndarray, min_window: int,
                 redesign_period: int) -> None:
        self.redesign_period = redesign_period
        self._order = prefilter.shape[0] - 1
        # psi = D phi, D = diag(-I_n, I_n) (eq. 13)
        self._psi_signs = np.repeat([-1.0, 1.0], self._order)
        self.ls = RunningLs(initial_p)
        self.moments = PrefilteredMoments(prefilter, initial_p.shape[0])
        self.rows = 0
        self.next_redesign = min_window
        #: memory cuts so far (a step redoes its a-priori part after one)
        self.cuts = 0

    # ------------------------------------------------------------------ a row
    def weighted_count(self) -> float:
        """Return tau, the weighted count of the rows."""
        return self.moments.weighted_count()

    def step_row(self, y: float, filters: PrefilterBank, lam: float,
                 passes_gate: Callable[[float, float, float], bool]) -> str:
        """
        Gate the row of sample y, then add it to the moments and do the RLS step.

        ``passes_gate(e, s, tau)`` is the estimator's gate; a memory cut it
        makes (:meth:`cut`) grows P, and the a-priori part is redone. Returns
        ``STEPPED``, ``REFUSED`` (by the gate), ``UNSAFE`` (the update may not
        be finite; nothing changed) or ``REPAIR`` (s not positive: the row is
        in the moments, P needs a repair).
        """
        phi = filters.phi
        # y_f[k] = y[k] - f_1 y_f[k-1] - ... - f_n y_f[k-n]; psi = D phi       (10), (13)
        target = y - filters.prefilter[1:].dot(phi[:self._order])
        psi = phi * self._psi_signs
        ls = self.ls
        # e = y_f - psi' theta, g = P psi, s = lambda + psi' P psi
        e, g, s = innovation(ls.theta, ls.p, psi, target, lam)
        cuts = self.cuts
        if not passes_gate(e, s, float(self.moments.weights.sum())):
            return REFUSED
        if self.cuts != cuts:
            # a plant change cut the memory (P grew): redo the a-priori part
            g = ls.p.dot(psi)
            s = lam + psi.dot(g)
        positive = s > 0.0
        # (the RLS step and the moments change apart: the step first, as it may refuse)
        if positive and not ls.forgetting_step(g, s, e, lam):
            return UNSAFE
        self.moments.add(psi, target, lam)
        self.rows += 1
        return STEPPED if positive else REPAIR

    def compensate(self, compensation: Compensation) -> str:
        """Compensate theta_LS with C and B of the moments' epochs (return the failure flag)."""
        moments = self.moments
        # C = sum_e W_e D c_e ; B = sum_e W_e beta_e
        total = moments.weights.dot(moments.directions)
        total_beta = moments.weights.dot(moments.betas)
        ls = self.ls
        return compensation.apply(ls.theta, ls.p.dot(total), total, total_beta, ls.loss)

    def cut(self, keep: float) -> None:
        """Keep the share ``keep`` of the memory (one extra forgetting step)."""
        self.cuts += 1
        self.ls.cut(keep)
        self.moments.cut(keep)

    def restart(self) -> None:
        """Keep everything after a gap (the moments have no lags)."""

    # -------------------------------------------------------------- redesign
    def may_redesign(self) -> bool:
        """Whether the next row may be a redesign's."""
        return self.rows + 1 >= self.next_redesign

    def after_sample(self, y: float, u0: float, compensated: bool) -> bool:
        """Return whether a redesign is due now (and schedule the next one)."""
        rows = self.rows
        if rows < self.next_redesign:
            return False
        self.next_redesign = rows + min(rows, self.redesign_period)
        return True

    def redesign(self, controller: Controller, prefilter: np.ndarray,
                 warm_start: np.ndarray | None, unit_weights: np.ndarray,
                 max_iterations: int, tolerance: float) -> Redesign:
        """
        Run Algorithm 1 on the moments of every row since the change (no refiltering).

        The exact LS from the moments, the fixed point of steps (3)-(5) from
        ``warm_start`` (the last compensated estimate: the fixed point moves
        little between redesigns) or else from theta_LS, and steps (6), (7):
        the next prefilter f = a_BC with the unstable roots mirrored (Remark
        3), taken (a new epoch) only once the rows reach ``redesign_period``
        and f moved by more than ``PREFILTER_STEP``. On success the running
        LS continues from the exact one.
        """
        n = prefilter.shape[0] - 1
        moments = self.moments
        flags = []
        try:
            theta_ls, inverse, loss = moments.exact_ls()
            starts = [theta_ls] if warm_start is None else [warm_start, theta_ls]
            result = moments.fixed_point(starts, theta_ls, inverse, loss, controller,
                                         unit_weights, max_iterations, tolerance)
            if not result.converged:
                flags.append('not_converged')
            # steps (6), (7): f = a_BC with the unstable roots mirrored (Remark 3)
            following = stable_reflection(np.concatenate(([1.0], result.theta[:n])))
            next_terms = None
            if not is_stable(monic_coefficients(following)):
                flags.append('unstable_prefilter')
            elif (self.rows >= self.redesign_period
                  and np.linalg.norm(following - prefilter) > PREFILTER_STEP):
                next_terms = bias_terms(result.theta, following, controller)
        except CompensationFailure as error:
            return Redesign(tuple(flags) + (error.flag,), True)
        self.ls.restart_from(theta_ls, inverse, loss, self.ls.count)
        moments.directions = result.directions
        moments.betas = result.betas
        if next_terms is not None:
            c_next, beta_next = next_terms
            moments.open_epoch(following, np.concatenate((-c_next[:n], c_next[n:])), beta_next)
        return Redesign(tuple(flags), False, iterations=result.iterations,
                        direction=result.direction,
                        terms=(theta_ls, result.pc, result.direction, result.total_beta),
                        prefilter=following if next_terms is not None else None,
                        new_epoch=next_terms is not None)

    # ------------------------------------------------------------ the state
    def plant_form(self, theta: np.ndarray, prefilter: np.ndarray) -> np.ndarray:
        """Return theta (of the form y_f = psi' [a | b]: the plant form already)."""
        return theta

    #: theta_LS and theta_BC are in the plant form (see :meth:`plant_form`).
    regression_form = False

    @property
    def window_length(self) -> int:
        """Return the rows the next redesign would use (all since the change)."""
        return self.rows

    @property
    def epochs(self) -> int:
        """Return the number of prefilters used since the last restart."""
        return len(self.moments.prefilters)

    def epoch_shares(self, prefilter: np.ndarray) -> list[tuple[float, np.ndarray]]:
        """Return (W_e / tau, f_e) of every epoch with a weight (copies)."""
        weights = self.moments.weights
        shares = weights / weights.sum()
        return [(share, f.copy()) for share, f in zip(shares, self.moments.prefilters)
                if share > 0.0]

    def moment_sums(self) -> np.ndarray:
        """Return the weighted sums [M, sum w psi y_f, sum w y_f^2] (for the block means)."""
        return self.moments.sums()

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the state (not copied)."""
        arrays, scalars = self.moments.state_items()
        ls = self.ls
        arrays.update({'buffer': np.zeros((0, 2)), 'theta_ls': ls.theta, 'p': ls.p})
        scalars.update({'pos': 0, 'filled': 0, 'loss': ls.loss, 'count': ls.count,
                        'since_redesign': 0, 'rows': self.rows,
                        'next_redesign': self.next_redesign})
        return arrays, scalars

    def load(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over a state made by :meth:`state_items`."""
        self.moments = PrefilteredMoments.from_state(arrays, scalars)
        self.ls.restart_from(arrays['theta_ls'], arrays['p'], float(scalars['loss']),
                             float(scalars['count']))
        self.rows = int(scalars['rows'])
        self.next_redesign = int(scalars['next_redesign'])

    def snapshot(self) -> tuple:
        """Return what a step may change."""
        return (self.ls.snapshot(), self.moments, self.moments.snapshot(), self.rows,
                self.next_redesign)

    def restore(self, saved: tuple) -> None:
        """Go back to a :meth:`snapshot`."""
        ls, self.moments, moments, self.rows, self.next_redesign = saved
        self.ls.restore(ls)
        self.moments.restore(moments)
