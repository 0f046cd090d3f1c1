"""
Write test/data/bciv_reference.npz: BCIV trajectories at fixed seeds, for regression tests.

The committed file was written with the implementation of commit 0e9bcaf (before the
per-sample speed-up of issue 7)::

    git show 0e9bcaf:bcid_ros/estimators/bciv.py > /tmp/old_bciv.py
    .venv/bin/python test/data/make_bciv_reference.py --module-file /tmp/old_bciv.py

Without ``--module-file`` it uses the installed ``bcid_ros.estimators.bciv``.
"""

import argparse
import importlib.util
import json
from pathlib import Path
import sys

import numpy as np

from bcid_ros.simulation import make_scenario

SAMPLES = 3000
SEED = 21
#: Rows kept: every STRIDE-th sample (0-based index STRIDE - 1, 2 STRIDE - 1, ...).
STRIDE = 50
#: name: (scenario, Bciv settings)
CASES = {
    'colored': ('ikenoue_colored', {'order': 2, 'iv_lag': 5}),
    'white': ('ikenoue_white_input', {'order': 2, 'iv_lag': 4, 'input_noise': 'white'}),
    'printed': ('ikenoue_colored', {'order': 2, 'iv_lag': 5, 'bciv_update': 'printed'}),
    'colored_forgetting': ('ikenoue_colored', {'order': 2, 'iv_lag': 5, 'idle_samples': 40,
                                               'forgetting_factor': 0.999}),
}


def load_module(path):
    """Import a bciv.py from a file (e.g. an older commit's) under its own name."""
    if path is None:
        from bcid_ros.estimators import bciv
        return bciv
    spec = importlib.util.spec_from_file_location('reference_bciv', path)
    module = importlib.util.module_from_spec(spec)
    sys.modules['reference_bciv'] = module
    spec.loader.exec_module(module)
    return module


def trajectories(module):
    """Return {key: array} of every case: theta, theta_uncompensated, noise rows, flags."""
    out = {}
    rows = np.arange(STRIDE - 1, SAMPLES, STRIDE)
    for name, (scenario, settings) in CASES.items():
        y, u = make_scenario(scenario).simulate(SAMPLES, SEED)
        est = module.Bciv(**settings)
        run = est.run(y, u)
        out[f'{name}/theta'] = run.theta[rows]
        out[f'{name}/theta_uncompensated'] = run.theta_uncompensated[rows]
        out[f'{name}/noise'] = run.noise[rows]
        out[f'{name}/flags'] = np.array(json.dumps(est.flags, sort_keys=True))
    return out


def main():
    """Write the reference file."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--module-file', default=None)
    parser.add_argument('--output', default=str(Path(__file__).with_name('bciv_reference.npz')))
    args = parser.parse_args()
    np.savez_compressed(args.output, **trajectories(load_module(args.module_file)))


if __name__ == '__main__':
    main()
