"""``bcid analyze``: order and delay search, validation and model properties of the samples."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from bcid_ros.analysis.data import read_samples
from bcid_ros.analysis.search import (Analysis, analyze, FIT_MARGIN, parse_delays,
                                      parse_orders, short_error, WHITENESS_LEVEL)
from bcid_ros.errors import BcidError


def _progress(line: str) -> None:
    print(f'bcid analyze: {line}', file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Run ``bcid analyze`` and print the table (or the JSON object)."""
    from bcid_ros.parameter_spec import load_yaml_parameters

    if not args.params.is_file():
        raise BcidError(f'--params {args.params}: no such file')
    parameters = load_yaml_parameters(args.params)
    orders = parse_orders(args.orders)
    delays = parse_delays(args.delays)
    y, u, dropped = read_samples(args.bag, _progress, args.columns, args.time_column)
    _progress(f'{y.size} samples, {u.shape[1]} input(s)'
              + (f', {dropped} dropped (malformed or NaN/Inf)' if dropped else ''))
    analysis = analyze(y, u, parameters, orders=orders, delays=delays,
                       estimator=args.estimator, validation=args.validation,
                       sample_period=args.sample_period, progress=_progress)
    if args.plot is not None:
        from bcid_ros.analysis.plot import write_plot

        write_plot(analysis, args.plot, title=f'{args.bag.name}: {analysis.estimator}, '
                   f'recommended order {_recommended(analysis)}')
        _progress(f'wrote {args.plot}')
    if args.json:
        print(json.dumps(analysis.summary()))
    else:
        print(report(analysis))
    return 0


def _recommended(analysis: Analysis) -> str:
    chosen = analysis.recommended
    return 'none' if chosen is None else f'{chosen.order}, delay {chosen.delay}'


def _number(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '-'
    return f'{value:.{digits}f}'


def report(analysis: Analysis) -> str:
    """Return the human-readable table and model description."""
    lines = [f'{analysis.estimator}: {analysis.estimation_samples} samples for estimation, '
             f'{analysis.validation_samples} for validation; whiteness of the '
             f'{analysis.residual_kind}',
             f'{"order":>5} {"delay":>5} {"fit %":>8} {"1-step %":>9} {"AIC":>11} '
             f'{"MDL":>11} {"white p":>8} {"stable":>6}']
    for c in analysis.candidates:
        mark = ' *' if c is analysis.recommended else ''
        if c.error is not None:
            lines.append(f'{c.order:5d} {c.delay:5d}  not fitted: {short_error(c.error)}')
            continue
        fit = _number(c.fit) if c.stable else 'unstable'
        lines.append(f'{c.order:5d} {c.delay:5d} {fit:>8} '
                     f'{_number(c.prediction_fit):>9} {_number(c.aic, 1):>11} '
                     f'{_number(c.mdl, 1):>11} {c.whiteness_p:8.3g} '
                     f'{"yes" if c.stable else "NO":>6}{mark}')
    chosen = analysis.recommended
    if chosen is None:
        lines.append('no recommendation: no candidate gave a stable model with a finite fit')
        return '\n'.join(lines)
    lines.append(f'recommended: order {chosen.order}, delay {chosen.delay} (*): the smallest '
                 f'order within {100 * FIT_MARGIN:.0f} % of the best validation RMS error'
                 + (f' whose residuals pass the whiteness test (p >= {WHITENESS_LEVEL})'
                    if analysis.residuals_white else
                    f'; NO model within the margin has white residuals (p >= '
                    f'{WHITENESS_LEVEL}): check the noise model, the estimator or the ranges'))
    lines.extend(_model_lines(analysis))
    return '\n'.join(lines)


def _complex(pair: list[float]) -> str:
    re, im = pair
    return f'{re:.4f}' if im == 0 else f'{re:.4f}{im:+.4f}j'


def _model_lines(analysis: Analysis) -> list[str]:
    summary = analysis.model_summary()
    lines = ['parameters: ' + ', '.join(f'{k} = {v:.6g}'
                                        for k, v in summary['parameters'].items()),
             'poles: ' + ', '.join(_complex(p) for p in summary['poles'])]
    zeros = summary['zeros'] if analysis.num_inputs > 1 else [summary['zeros']]
    for i, row in enumerate(zeros, 1):
        lines.append(f'zeros (u{i}): ' + (', '.join(_complex(z) for z in row) or 'none'))
    gains = summary['dc_gain'] if isinstance(summary['dc_gain'], list) else [summary['dc_gain']]
    lines.append('DC gain: ' + ', '.join(f'u{i}: {_number(g, 5)}'
                                         for i, g in enumerate(gains, 1)))
    continuous = summary.get('continuous')
    if continuous:
        lines.append(f'continuous time (T = {continuous["sample_period_s"]:g} s, dead time '
                     f'{continuous["dead_time_s"]:g} s):')
        for mode in continuous['modes']:
            if mode['kind'] == 'real':
                tau = mode['time_constant_s']
                lines.append(f'  real pole s = {mode["pole"][0]:.5g} 1/s: '
                             + ('an integrator' if tau is None else
                                f'time constant {tau:.5g} s'))
            else:
                lines.append(f'  complex pair s = {mode["pole"][0]:.5g} +- '
                             f'{mode["pole"][1]:.5g}j: natural frequency '
                             f'{mode["natural_frequency_rad_s"]:.5g} rad/s, damping '
                             f'{mode["damping"]:.4f}')
        for pole in continuous['no_equivalent']:
            lines.append(f'  discrete pole z = {pole[0]:.4f} is real and <= 0: no '
                         'continuous-time pole maps to it (exp(sT) > 0), so it has no '
                         'continuous equivalent')
    return lines


__all__ = ['report', 'run']
