"""
The units of BCIV: the signal scales and the M_0 = rho S^-2 term of Step 1 they set.

Ikenoue et al. (2008), Step 1 of the recursive algorithm (eq. 38 with
M_0 = rho I), read in normalised units: z and w are divided by the smallest
powers of two at or above their peaks in the first full window of the
IV-type vector (54), and M_0 = rho I on the normalised signals, mapped back,
is M_0 = rho S^-2 on the signals as given. The estimates then do not depend
on the units of z and w (the "Units" paragraph of
:class:`~bcid_ros.estimators.bciv.online.Bciv`).
"""

from __future__ import annotations

import numpy as np

from bcid_ros.estimators import rules


def regularisation_weights(z_scale: float, w_scale: float, order: int,
                           num_parameters: int) -> np.ndarray:
    r"""
    Return the diagonal :math:`S^2` that puts :math:`M_0 = \rho I` in normalised units.

    Column k of :math:`\bar R` sums :math:`w\,z` (a-part) or :math:`w\,w` (b-part).
    Step 1 on the normalised signals :math:`z/s_z`, :math:`w/s_w` with
    :math:`M_0 = \rho I`, mapped back, is Step 1 on the signals as given with
    :math:`M_0^{-1} = \rho^{-1} S^2`, :math:`S = s_w\,\mathrm{diag}(s_z I_n, s_w I)`.
    """
    weights = np.full(num_parameters, w_scale * w_scale)
    weights[:order] = w_scale * z_scale
    return weights * weights


def window_scales(z: np.ndarray, w: np.ndarray, m: int) -> tuple[float, float]:
    """
    Return the scales that the recursive estimator gives z and w on these arrays.

    As :class:`~bcid_ros.estimators.bciv.online.Bciv` chooses them: each is
    the power of two at or above the peak of the first m-sample window
    (ending at sample m - 1 or later) in which the channel is not all zero;
    1 for a channel that is zero throughout.
    """
    scales = []
    for x in (z, w):
        nonzero = np.flatnonzero(x)
        if nonzero.size == 0:
            scales.append(1.0)
            continue
        end = max(int(nonzero[0]), m - 1)
        scales.append(rules.powers_of_two_at_least(float(np.abs(x[end - m + 1:end + 1]).max())))
    return scales[0], scales[1]
