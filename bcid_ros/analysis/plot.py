"""The ``bcid analyze --plot`` figure (matplotlib is imported only here, when called)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bcid_ros.analysis import metrics
from bcid_ros.analysis.search import Analysis, FIT_MARGIN, fit_limit, TEST_LEVEL
from bcid_ros.errors import BcidError

#: At most this many validation samples are drawn, so that the traces stay readable.
SHOWN_SAMPLES = 200


def write_plot(analysis: Analysis, path: str | Path, title: str = '') -> Path:
    """
    Draw the recommended model against the data and write a PNG.

    Eight panels: validation output against the simulated outputs of the
    batch model and of each online estimator; their validation fits side by
    side; the autocorrelation of the simulation error and its
    standardised cross-correlation with each input, each with the band of
    the test level; the step response; the validation fit of every
    candidate against the order; the Bode magnitude and phase.

    Raises
    ------
    BcidError
        If no model could be recommended (nothing to draw).

    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    chosen = analysis.recommended
    if chosen is None or chosen.model is None:
        raise BcidError('no usable model to plot (every candidate failed or was unstable)')
    period = analysis.sample_period
    unit = 's' if period else 'samples'
    scale = period or 1.0
    figure, axes = plt.subplots(4, 2, figsize=(13, 14))
    figure.suptitle(title or f'recommended order {chosen.order}, delay {chosen.delay_text}',
                    fontsize=13)
    _validation(axes[0, 0], analysis, scale, unit)
    _online_fits(axes[0, 1], analysis)
    _autocorrelation(axes[1, 0], analysis)
    _cross_correlation(axes[1, 1], analysis)
    _step(axes[2, 0], analysis, scale, unit)
    _fit_against_order(axes[2, 1], analysis)
    _bode(axes[3, 0], axes[3, 1], analysis)
    figure.tight_layout(rect=(0, 0, 1, 0.97))
    path = Path(path)
    figure.savefig(path, dpi=80)
    plt.close(figure)
    return path


def _validation(ax, analysis: Analysis, scale: float, unit: str) -> None:
    chosen = analysis.recommended
    shown = min(SHOWN_SAMPLES, analysis.validation_samples)
    t = (analysis.estimation_samples + np.arange(shown)) * scale
    ax.plot(t, analysis.validation_output[:shown], color='k', lw=1.0, label='measured y')
    ax.plot(t, chosen.simulated[:shown], color='tab:orange', lw=1.6,
            label=f'batch OE (fit {chosen.fit:.1f} %)')
    for result in analysis.online:
        if result.error is None and result.stable and math.isfinite(result.fit):
            ax.plot(t, result.simulated[:shown], lw=1.0, ls='--',
                    label=f'{result.name} (fit {result.fit:.1f} %'
                    + ('' if result.valid else ', not valid') + ')')
    part = '' if shown == analysis.validation_samples else \
        f', first {shown} of {analysis.validation_samples}'
    ax.set_title(f'Validation data vs simulated outputs{part}')
    ax.set_xlabel(f'time ({unit})')
    ax.set_ylabel('y - operating point')
    ax.legend(loc='upper right', fontsize=8)


def _online_fits(ax, analysis: Analysis) -> None:
    chosen = analysis.recommended
    names = ['batch OE'] + [r.name for r in analysis.online]
    fits = [chosen.fit] + [r.fit if r.error is None and r.stable else math.nan
                           for r in analysis.online]
    colours = ['tab:orange'] + ['tab:green' if r.usable else 'tab:gray'
                                for r in analysis.online]
    shown = [max(f, 0.0) if math.isfinite(f) else 0.0 for f in fits]
    bars = ax.bar(names, shown, color=colours)
    for bar, fit, result in zip(bars, fits, [None] + list(analysis.online)):
        text = f'{fit:.1f} %' if math.isfinite(fit) else (
            'not run' if result is not None and result.error else 'unstable')
        if result is not None and result.error is None and not result.valid:
            text += '\nnot valid'
        ax.text(bar.get_x() + bar.get_width() / 2, bar.get_height() + 1, text,
                ha='center', va='bottom', fontsize=9)
    limit = 100.0 - (100.0 - chosen.fit) * (1.0 + FIT_MARGIN)
    ax.axhline(limit, color='0.4', ls=':', lw=1.2,
               label=f'{100 * FIT_MARGIN:.0f} % above the batch RMS error')
    ax.set_ylim(0, 115)
    note = analysis.recommended_estimator or 'none'
    ax.set_title(f'Validation fit, same structure (recommended estimator: {note})')
    ax.set_ylabel('fit (%)')
    ax.legend(loc='lower right', fontsize=8)


def _band(count: int) -> float:
    """Return the pointwise band of a white sequence's correlations at the test level."""
    # r_k ~ N(0, 1/N), two-sided at the test level
    return _normal_quantile(1 - TEST_LEVEL / 2) / math.sqrt(max(count, 1))


def _autocorrelation(ax, analysis: Analysis) -> None:
    chosen = analysis.recommended
    residual = chosen.residual
    lags = metrics.whiteness_lags(residual.size)
    r = metrics.autocorrelation(residual, lags)
    band = _band(residual.size)
    ax.axhspan(-band, band, color='tab:blue', alpha=0.15,
               label=f'{100 * (1 - TEST_LEVEL):.0f} % band of white noise')
    ax.vlines(np.arange(1, lags + 1), 0, r, color='tab:blue', lw=2)
    ax.plot(np.arange(1, lags + 1), r, 'o', color='tab:blue', ms=4)
    ax.axhline(0, color='k', lw=0.8)
    ax.set_xlim(0, lags + 1)
    limit = max(3 * band, 1.2 * float(np.abs(r).max()))
    ax.set_ylim(-limit, limit)
    ax.set_title(f'Autocorrelation of the simulation error (white noise? Ljung-Box p = '
                 f'{chosen.whiteness_p:.3g})', fontsize=10)
    ax.set_xlabel('lag (samples)')
    ax.legend(loc='upper right', fontsize=8)


def _cross_correlation(ax, analysis: Analysis) -> None:
    chosen = analysis.recommended
    r = chosen.cross_correlation
    lags = r.shape[1]
    # each standardised correlation is about N(0, 1) when the model is right
    band = _normal_quantile(1 - TEST_LEVEL / 2)
    ax.axhspan(-band, band, color='tab:blue', alpha=0.15,
               label=f'{100 * (1 - TEST_LEVEL):.0f} % band (pointwise)')
    offsets = np.linspace(-0.2, 0.2, r.shape[0]) if r.shape[0] > 1 else [0.0]
    for i, row in enumerate(r):
        ax.plot(np.arange(lags) + offsets[i], row, 'o', ms=4, label=f'u{i + 1}')
    ax.axhline(0, color='k', lw=0.8)
    finite = r[np.isfinite(r)]
    limit = max(2 * band, 1.2 * float(np.abs(finite).max()) if finite.size else 0.0)
    ax.set_ylim(-limit, limit)
    ax.set_title(f'Standardised cross-correlation of the simulation error with u(t - k) '
                 f'(p = {chosen.cross_correlation_p:.3g})', fontsize=10)
    ax.set_xlabel('lag k (samples)')
    ax.legend(loc='upper right', fontsize=8)


def _step(ax, analysis: Analysis, scale: float, unit: str) -> None:
    model = analysis.recommended.model
    count = model.settling_samples()
    response = model.step(count)
    t = np.arange(count) * scale
    for i in range(model.num_inputs):
        ax.step(t, response[:, i], where='post', lw=1.4, label=f'from u{i + 1}')
    ax.axhline(0, color='k', lw=0.8)
    ax.set_title('Step response of the recommended batch model')
    ax.set_xlabel(f'time ({unit})')
    ax.set_ylabel('y')
    if model.num_inputs > 1:
        ax.legend(fontsize=9)


def _bode(magnitude_ax, phase_ax, analysis: Analysis) -> None:
    model = analysis.recommended.model
    w, response = model.frequency_response()
    period = analysis.sample_period
    frequency = w / (2 * np.pi * period) if period else w / np.pi
    label = 'frequency (Hz)' if period else 'frequency (x Nyquist)'
    for i in range(model.num_inputs):
        with np.errstate(divide='ignore'):
            magnitude_ax.semilogx(frequency, 20 * np.log10(np.abs(response[:, i])), lw=1.4,
                                  label=f'from u{i + 1}')
        phase_ax.semilogx(frequency, np.degrees(np.unwrap(np.angle(response[:, i]))), lw=1.4,
                          label=f'from u{i + 1}')
    magnitude_ax.set_title('Bode magnitude')
    magnitude_ax.set_ylabel('|H| (dB)')
    phase_ax.set_title('Bode phase')
    phase_ax.set_ylabel('phase (degrees)')
    for ax in (magnitude_ax, phase_ax):
        ax.set_xlabel(label)
        ax.grid(True, which='both', alpha=0.3)
        if model.num_inputs > 1:
            ax.legend(fontsize=9)


def _fit_against_order(ax, analysis: Analysis) -> None:
    chosen = analysis.recommended
    usable = [c for c in analysis.candidates if c.usable]
    fits = [c.fit for c in usable]
    best = max(fits)
    bottom = max(min(fits), -50.0) - 5
    top = min(100.0, best + 0.2 * (100.0 - best) + 1)
    if analysis.num_inputs == 1:
        delays = sorted({c.delays for c in analysis.candidates})
        for d in delays:
            rows = [(c.order, c.fit) for c in usable if c.delays == d]
            if rows:
                orders, values = zip(*rows)
                ax.plot(orders, values, 'o-', lw=1.2, ms=5,
                        label=f'delay {d[0]}' if len(delays) > 1 else 'validation fit')
    else:
        ax.plot([c.order for c in usable], fits, 'o', color='0.6', ms=4,
                label='every delay combination')
        per_order = [c for c in analysis.best_per_order().values() if c.usable]
        ax.plot([c.order for c in per_order], [c.fit for c in per_order], 'o-',
                color='tab:blue', lw=1.2, ms=5, label='delays of the lowest MDL per order')
    ax.axhline(fit_limit(best), color='0.4', ls=':', lw=1.2, label='margin below the best')
    rejected = [c for c in usable if not c.uncorrelated]
    ax.plot([c.order for c in rejected], [c.fit for c in rejected], 'x', color='tab:red',
            ms=9, mew=1.5, label='correlated with u', zorder=4)
    redundant = [c for c in usable if c.redundant]
    ax.plot([c.order for c in redundant], [c.fit for c in redundant], 's', mfc='none',
            mec='tab:brown', ms=9, mew=1.2, label='a smaller structure describes it', zorder=4)
    failed = sorted({c.order for c in analysis.candidates if not c.usable}
                    - {c.order for c in usable})
    if failed:
        ax.plot(failed, [bottom + 0.06 * (top - bottom)] * len(failed), 'v',
                color='tab:purple', ms=9, label='unstable or not fitted')
    ax.plot(chosen.order, chosen.fit, '*', color='gold', mec='k', ms=18, zorder=5,
            label=f'recommended: n = {chosen.order}, d = {chosen.delay_text}')
    ax.set_ylim(bottom, top)
    ax.set_xticks(sorted({c.order for c in analysis.candidates}))
    ax.set_title('Validation fit of the batch models against order')
    ax.set_xlabel('order n')
    ax.set_ylabel('fit (%)')
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc='best', ncol=2)


def _normal_quantile(probability: float) -> float:
    from scipy import stats

    return float(stats.norm.ppf(probability))


__all__ = ['write_plot']
