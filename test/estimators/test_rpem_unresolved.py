"""
rpem's std where the data do not pin the parameters down (rpem/uncertainty.py).

The fitted-state share P E P lost the conditioning of the fit's information twice (negative
variances, so no std at all); it is kept as a square root (docs/trust.md, HAC "Limits").
"""

import numpy as np

from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.rpem.uncertainty import (fitted_state_excess, normalised_covariance,
                                                  parameter_covariance)


def test_the_fitted_state_share_survives_an_information_of_twelve_decades():
    """
    At the hand-over P = P_f, so the share P E P is D exactly (E = P_f^-1 D P_f^-1).

    The scores' columns span six decades, the information twelve (a slow plant's fits reach
    cond 1e12-1e13). Computed through the root, P R loses about cond(P_f) times the rounding
    error, 2e-4 of D here: the test allows 1e-2. Through E, the plain P E P lost cond(P_f)
    squared and gave negative variances.
    """
    rng = np.random.default_rng(11)
    count, size, samples = 5, 6, 4000
    # six decades of scale in directions that mix every parameter (an oversampled plant's
    # gradients are nearly collinear), so that no coordinate carries one scale alone
    rotation = np.linalg.qr(rng.standard_normal((size, size)))[0]
    scores = (rng.standard_normal((samples, size)) * np.logspace(0.0, -6.0, size)) @ rotation.T
    information = scores.T @ scores
    prior = 1e-12
    p = np.linalg.inv(information + prior * np.eye(size))
    hac = HacCovariance(dimension=size, forgetting_factor=1.0)
    hac.record_all(scores)
    held = normalised_covariance(hac, p, float(samples), 1.0)
    # the profiled information: a quarter of the held one, its scores half as large
    profiled_scores = 0.5 * scores[:, :count]
    profiled_information = 0.25 * information[:count, :count]
    root = fitted_state_excess(held, information, profiled_information, profiled_scores, prior,
                               float(samples), 1.0)
    profiled_hac = HacCovariance(dimension=count, forgetting_factor=1.0)
    profiled_hac.record_all(profiled_scores)
    profiled = normalised_covariance(
        profiled_hac, np.linalg.inv(profiled_information + prior * np.eye(count)),
        float(samples), 1.0)
    values, vectors = np.linalg.eigh(profiled - held[:count, :count])
    share = (vectors * np.maximum(values, 0.0)) @ vectors.T  # D
    assert np.linalg.cond(information) > 1e11
    covariance = parameter_covariance(hac, p, float(samples), 1.0, count, np.ones(count), root)
    assert covariance is not None
    carried = covariance - held[:count, :count]
    assert np.all(np.diagonal(covariance) > 0.0)
    assert np.allclose(carried, share, rtol=1e-2, atol=1e-2 * np.abs(share).max())

