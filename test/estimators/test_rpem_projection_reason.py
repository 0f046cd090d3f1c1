"""
rpem names a stability projection active on most updates, apart from its drift watch.

The drift watch (rpem/watch.py) names it too; the estimator counts it from its own flag so
that the reason does not depend on the watch (which is being rewritten for change detection).
Here the watch's own rule is switched off to see the estimator's.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.rpem import watch
from test_cl_bcls_friction_loop import friction_loop


def run(y, u):
    estimator = make_estimator('rpem', order=2)
    for k in range(y.size):
        estimator.update(y[k], [u[k]])
    return estimator


def test_a_projection_on_most_updates_is_a_reason(monkeypatch):
    monkeypatch.setattr(watch, 'PROJECTION_SHARE', 2.0)  # the watch never names it
    # an output-error model of a position loop: its F keeps pushing against the boundary
    estimator = run(*friction_loop(1))
    assert estimator.flags['stability_projection'] > 0.5 * 5000
    assert any(r.startswith('stability projection active') for r in estimator.validity_reasons)


def test_a_stable_plant_has_no_such_reason(monkeypatch):
    monkeypatch.setattr(watch, 'PROJECTION_SHARE', 2.0)
    rng = np.random.default_rng(3)
    u = np.repeat(rng.choice([-1.0, 1.0], 300), 10)
    y = signal.lfilter([0.0, 0.5, 0.2], [1.0, -1.2, 0.5], u) + 0.1 * rng.standard_normal(u.size)
    estimator = run(y, u)
    assert not any('stability projection' in r for r in estimator.validity_reasons)
