"""
rpem names a stability projection active on most updates, and does not restart on it in vain.

The watch (rpem/watch.py) counts the projection's refusals and names them as a reason; a
projection stuck at the boundary restarts the estimator only where a refit can move it: not
when the fit is itself on the boundary, and not twice on the same samples (a position loop,
an integrator in feedback: its refits all land at the boundary).
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from bcid_ros.estimators import make_estimator
from test_cl_bcls_friction_loop import friction_loop


def run(y, u):
    estimator = make_estimator('rpem', order=2)
    for k in range(y.size):
        estimator.update(y[k], [u[k]])
    return estimator


def test_a_projection_on_most_updates_is_a_reason_not_a_restart():
    # an output-error model of a position loop: its F keeps pushing against the boundary
    estimator = run(*friction_loop(1))
    assert estimator.flags['stability_projection'] > 0.5 * 5000
    assert any(r.startswith('stability projection active') for r in estimator.validity_reasons)
    # its fits are on the boundary too: no restart (34 in these 5000 samples before the
    # watch asked whether a refit can move it)
    assert 'restarted' not in estimator.flags


def test_a_stable_plant_has_no_such_reason():
    rng = np.random.default_rng(3)
    u = np.repeat(rng.choice([-1.0, 1.0], 300), 10)
    y = signal.lfilter([0.0, 0.5, 0.2], [1.0, -1.2, 0.5], u) + 0.1 * rng.standard_normal(u.size)
    estimator = run(y, u)
    assert not any('stability projection' in r for r in estimator.validity_reasons)
    assert 'restarted' not in estimator.flags
