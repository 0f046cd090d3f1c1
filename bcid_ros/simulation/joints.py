"""
Many joints: independent random stable second-order plants, one per joint.

Joint k is the output-error plant of Ding et al. (2006) with one input:

    y_k(t) = (b_k1 z^-1 + b_k2 z^-2) / (1 + a_k1 z^-1 + a_k2 z^-2) u_k(t) + v_k(t),

u_k (the effort) white Gaussian with unit variance and v_k white Gaussian
with variance sigma2_k. The plants are drawn from ``seed``: poles inside
the unit circle (a complex pair or two real poles), a zero kept away from
the poles so every plant is identifiable, and a noise level per joint. The
samples are drawn from the stream's generator, as for the other scenarios.
"""

from __future__ import annotations

import numpy as np

from bcid_ros.estimators.base import check_int, parameter_names
from bcid_ros.simulation.base import SampleStream, Scenario, Truth

#: Largest pole radius: slow enough to be a joint, fast enough to identify in seconds.
POLE_RADIUS = (0.5, 0.95)
#: Angle range (rad) of a complex pole pair.
POLE_ANGLE = (0.05, 2.5)
#: Smallest distance between the zero of B and a pole (no near-cancellation).
ZERO_POLE_DISTANCE = 0.2
#: Range of the output noise standard deviation.
NOISE_STD = (0.05, 0.2)
#: Mixed into the seed so that the plants and a stream with the same seed differ.
PLANT_STREAM = 0x6A6F696E


def joint_names(num_joints: int) -> tuple[str, ...]:
    """Return the joint names ``joint_1`` ... ``joint_K`` (valid ROS name tokens)."""
    return tuple(f'joint_{k}' for k in range(1, num_joints + 1))


def draw_plants(num_joints: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """
    Draw random stable second-order plants and their noise levels.

    Parameters
    ----------
    num_joints : int
        K.
    rng : numpy.random.Generator
        Source of the draws.

    Returns
    -------
    theta : numpy.ndarray, shape ``(K, 4)``
        ``[a1, a2, b1_1, b1_2]`` of each joint.
    sigma2 : numpy.ndarray, shape ``(K,)``
        Output noise variance of each joint.

    """
    theta = np.empty((num_joints, 4))
    for k in range(num_joints):
        theta[k] = _draw_plant(rng)
    sigma2 = rng.uniform(*NOISE_STD, size=num_joints) ** 2
    return theta, sigma2


def _draw_plant(rng: np.random.Generator) -> np.ndarray:
    """Draw one plant ``[a1, a2, b1, b2]``, redrawing the zero until it is off the poles."""
    if rng.random() < 0.5:
        radius, angle = rng.uniform(*POLE_RADIUS), rng.uniform(*POLE_ANGLE)
        poles = radius * np.exp(np.array([1j, -1j]) * angle)
    else:
        poles = rng.uniform(*POLE_RADIUS, size=2) * rng.choice([-1.0, 1.0], size=2)
    a1, a2 = np.real(np.poly(poles))[1:]
    gain = rng.uniform(0.2, 1.0) * rng.choice([-1.0, 1.0])
    while True:
        zero = rng.uniform(-0.5, 0.5)
        if np.abs(poles - zero).min() >= ZERO_POLE_DISTANCE:
            break
    # B(z) = b1 z^-1 (1 - zero z^-1)
    return np.array([a1, a2, gain, -gain * zero])


class JointsScenario(Scenario):
    """
    K independent joints, each a random stable second-order output-error plant.

    The whole is a diagonal system with K inputs (the efforts) and K outputs
    (the velocities): :meth:`stream` yields y and u of shape ``(count, K)``,
    column k belonging to joint k, and ``num_inputs`` is K, the columns of u.
    Each joint alone is a single-input plant of order 2 (:attr:`joint_order`,
    :attr:`inputs_per_joint`), which is what one identifier per joint fits.

    Parameters
    ----------
    num_joints : int
        K >= 1.
    seed : int
        Seed of the plants (their samples come from the stream's generator).

    Raises
    ------
    ValueError
        If ``num_joints`` or ``seed`` is out of range.

    """

    name = 'joints'
    order = 2
    joint_order = 2
    inputs_per_joint = 1
    feedthrough = False

    def __init__(self, *, num_joints: int = 6, seed: int = 0) -> None:
        self.num_joints = check_int('num_joints', num_joints, 1)
        self.seed = check_int('seed', seed, 0)
        self.num_inputs = self.num_joints
        self.joint_names = joint_names(self.num_joints)
        self.parameters, self.sigma2 = draw_plants(
            self.num_joints, np.random.default_rng([PLANT_STREAM, self.seed]))

    def joint_truths(self) -> dict[str, Truth]:
        """Return each joint's true parameters ``a1, a2, b1_1, b1_2`` and ``sigma2``."""
        names = parameter_names(self.joint_order, self.inputs_per_joint, self.feedthrough)
        return {joint: Truth(names, self.parameters[k].copy(), ('sigma2',),
                             self.sigma2[k:k + 1].copy())
                for k, joint in enumerate(self.joint_names)}

    def truth(self) -> Truth:
        """Return all joints' truths in one, named ``<joint>/<parameter>``."""
        truths = self.joint_truths()
        return Truth(
            tuple(f'{joint}/{name}' for joint, truth in truths.items()
                  for name in truth.parameter_names),
            np.concatenate([truth.parameters for truth in truths.values()]),
            tuple(f'{joint}/{name}' for joint, truth in truths.items()
                  for name in truth.noise_names),
            np.concatenate([truth.noise for truth in truths.values()]))

    def stream(self, rng: np.random.Generator) -> SampleStream:
        """Return a stream of ``(y, u)``, each of shape ``(count, K)``, drawing from ``rng``."""
        return _JointsStream(rng, self.parameters, np.sqrt(self.sigma2))

    def __repr__(self) -> str:
        return f'JointsScenario(num_joints={self.num_joints}, seed={self.seed})'


class _JointsStream(SampleStream):
    """
    All joints' samples, one vectorised recursion step per sample.

    The recursion is the same arithmetic whatever the block size, so the
    samples do not depend on how they are taken.
    """

    def __init__(self, rng: np.random.Generator, theta: np.ndarray,
                 noise_std: np.ndarray) -> None:
        self.rng = rng
        self.a1, self.a2, self.b1, self.b2 = (theta[:, i].copy() for i in range(4))
        self.noise_std = noise_std
        joints = theta.shape[0]
        # x(t-1), x(t-2) (noise-free outputs) and u(t-1), u(t-2)
        self.x1, self.x2, self.u1, self.u2 = (np.zeros(joints) for _ in range(4))

    def take(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        joints = self.a1.shape[0]
        # one (count, 2K) draw per block keeps the samples independent of blocking
        draws = self.rng.standard_normal((count, 2 * joints))
        u = np.ascontiguousarray(draws[:, :joints])
        x = np.empty((count, joints))
        x1, x2, u1, u2 = self.x1, self.x2, self.u1, self.u2
        for t in range(count):
            # x(t) = b1 u(t-1) + b2 u(t-2) - a1 x(t-1) - a2 x(t-2)
            x[t] = self.b1 * u1 + self.b2 * u2 - self.a1 * x1 - self.a2 * x2
            x1, x2, u1, u2 = x[t], x1, u[t], u1
        # copies: the caller owns the returned arrays and may change them
        self.x1, self.x2, self.u1, self.u2 = x1.copy(), x2.copy(), u1.copy(), u2.copy()
        return x + draws[:, joints:] * self.noise_std, u
