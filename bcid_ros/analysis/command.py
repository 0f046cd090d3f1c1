"""``bcid analyze``: structure search, validation, model properties and online estimators."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from bcid_ros.analysis.batch import NEAR_PAIR
from bcid_ros.analysis.data import read_samples
from bcid_ros.analysis.search import (Analysis, analyze, FIT_MARGIN, FIT_POINTS, parse_delays,
                                      parse_orders, short_error, TEST_LEVEL)
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

        write_plot(analysis, args.plot, title=f'{args.bag.name}: recommended '
                   f'{_recommended(analysis)}')
        _progress(f'wrote {args.plot}')
    if args.json:
        print(json.dumps(analysis.summary()))
    else:
        print(report(analysis))
    return 0


def _recommended(analysis: Analysis) -> str:
    chosen = analysis.recommended
    return 'none' if chosen is None else f'order {chosen.order}, delay {chosen.delay_text}'


def _number(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '-'
    return f'{value:.{digits}f}'


def _p_value(value: float) -> str:
    return '-' if not math.isfinite(value) else f'{value:.3g}'


def report(analysis: Analysis) -> str:
    """Return the human-readable tables, the model and the identifier configuration."""
    lines = [f'batch output-error fits: {analysis.estimation_samples} samples for estimation, '
             f'{analysis.validation_samples} for validation; tests of the simulation error '
             '(xcorr: against the present and past inputs; white: Ljung-Box)',
             f'{"order":>5} {"delay":>7} {"fit %":>8} {"1-step %":>9} {"AIC":>11} '
             f'{"MDL":>11} {"xcorr p":>8} {"white p":>8} {"stable":>6} redundant']
    for c in analysis.candidates:
        mark = ' *' if c is analysis.recommended else ''
        if c.error is not None:
            lines.append(f'{c.order:5d} {c.delay_text:>7}  not fitted: {short_error(c.error)}')
            continue
        fit = _number(c.fit) if c.stable else 'unstable'
        lines.append(f'{c.order:5d} {c.delay_text:>7} {fit:>8} '
                     f'{_number(c.prediction_fit):>9} {_number(c.aic, 1):>11} '
                     f'{_number(c.mdl, 1):>11} {_p_value(c.cross_correlation_p):>8} '
                     f'{_p_value(c.whiteness_p):>8} {"yes" if c.stable else "NO":>6} '
                     f'{"yes" if c.redundant else "no":>9}{mark}')
    lines.extend(_pair_lines(analysis))
    chosen = analysis.recommended
    if chosen is None:
        lines.append('no recommendation: no candidate gave a stable model with a finite fit')
        return '\n'.join(lines)
    lines.append(f'recommended: order {chosen.order}, delay {chosen.delay_text} (*): '
                 + _rule_text(analysis))
    lines.append('the simulation error of the recommended model is '
                 + ('white: the output noise looks white (the OE fit is efficient, the '
                    'assumption of bcrls holds)' if analysis.residuals_white else
                    'NOT white: the output noise is coloured (the OE fit is still consistent; '
                    'bcrls assumes white noise)'))
    lines.extend(_model_lines(analysis))
    lines.extend(_online_lines(analysis))
    return '\n'.join(lines)


def _pair_lines(analysis: Analysis) -> list[str]:
    """Return one line per candidate with near-cancelling pole-zero pairs (none: no line)."""
    lines = []
    for c in analysis.candidates:
        if c.pole_zero_pairs:
            pairs = ', '.join(f'u{pair["input"]}: pole {_complex(pair["pole"])} / zero '
                              f'{_complex(pair["zero"])}' for pair in c.pole_zero_pairs)
            lines.append(f'order {c.order}, delay {c.delay_text}: near-cancelling pole-zero '
                         f'pairs (within {NEAR_PAIR:g}): {pairs}')
    return lines


def _rule_text(analysis: Analysis) -> str:
    """Return why the recommended candidate was chosen, in one sentence."""
    chosen = analysis.recommended
    margin = (f'within {100 * FIT_MARGIN:.0f} % of the best validation RMS error and '
              f'{FIT_POINTS:g} fit points')
    if analysis.adequate:
        return (f'the smallest order {margin} whose simulation error is uncorrelated with '
                f'the inputs (p >= {TEST_LEVEL}) and that no smaller structure describes, the '
                'lowest MDL at that order')
    why = ('its simulation error is correlated with the inputs' if not chosen.uncorrelated
           else 'a smaller structure describes it (' + '; '.join(chosen.redundancy) + ')')
    return (f'the smallest order {margin}, the lowest MDL at that order; NO candidate within '
            f'the margin is adequate ({why}): the plant is not exactly in the model set '
            '(nonlinear, time-varying, or the ranges miss it), or the record is in closed loop')


def _online_lines(analysis: Analysis) -> list[str]:
    chosen = analysis.recommended
    lines = [f'online estimators on this structure (sample by sample over the estimation '
             f'part, detrend: {analysis.detrend}), validation fit beside the batch model\'s '
             f'{chosen.fit:.2f} %:']
    for result in analysis.online:
        if result.error is not None:
            lines.append(f'  {result.name:>8}: not run: {short_error(result.error)}')
            continue
        fit = f'{result.fit:8.2f} %' if result.stable else '  unstable'
        why = '' if result.valid else ' (' + '; '.join(result.reasons) + ')'
        lines.append(f'  {result.name:>8}: {fit}, {"valid" if result.valid else "NOT valid"}'
                     f'{why}')
    name = analysis.recommended_estimator
    if name is None:
        lines.append('recommended estimator: none (no online estimate was stable)')
    elif analysis.estimator_close and analysis.estimator_valid:
        lines.append(f'recommended estimator: {name} (the best valid online fit, within '
                     f'{100 * FIT_MARGIN:.0f} % of the batch model\'s validation RMS error)')
    elif analysis.estimator_close:
        lines.append(f'recommended estimator: {name}: the best online fit within '
                     f'{100 * FIT_MARGIN:.0f} % of the batch model\'s validation RMS error, '
                     'but NOT valid at the end of the estimation part (its reasons above; no '
                     'valid estimate was as close): check them before a controller trusts it')
    else:
        lines.append(f'recommended estimator: {name}, but NONE is close to the batch model '
                     f'(within {100 * FIT_MARGIN:.0f} % of its validation RMS error): use the '
                     'batch model, or a longer record for the online estimate')
    config = analysis.identifier_parameters()
    lines.append('identifier configuration (bcid_identifier: ros__parameters:):')
    lines.extend(f'  {key}: {_yaml(value)}' for key, value in config.items())
    return lines


def _yaml(value: Any) -> str:
    return f'[{", ".join(map(str, value))}]' if isinstance(value, list) else str(value)


def _complex(pair: list[float]) -> str:
    re, im = pair
    return f'{re:.4f}' if im == 0 else f'{re:.4f}{im:+.4f}j'


def _model_lines(analysis: Analysis) -> list[str]:
    summary = analysis.model_summary()
    stds = summary['parameter_std']
    lines = [f'batch model (validation fit {summary["fit"]:.2f} %), parameters +- one '
             'standard deviation: ' + ', '.join(f'{k} = {v:.6g} +- {_number(stds[k], 3)}'
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
        dead = continuous['dead_time_s']
        dead = ', '.join(f'{d:g}' for d in dead) if isinstance(dead, list) else f'{dead:g}'
        lines.append(f'continuous time (T = {continuous["sample_period_s"]:g} s, dead time '
                     f'{dead} s):')
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
