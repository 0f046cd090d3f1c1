"""The ``bcid analyze --plot`` figure (matplotlib is imported only here, when called)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bcid_ros.analysis import metrics
from bcid_ros.analysis.search import Analysis, FIT_MARGIN, WHITENESS_LEVEL
from bcid_ros.errors import BcidError

#: At most this many validation samples are drawn, so that the traces stay readable.
SHOWN_SAMPLES = 200


def write_plot(analysis: Analysis, path: str | Path, title: str = '') -> Path:
    """
    Draw the recommended model against the data and write a PNG.

    Six panels: validation output against the simulated output; the
    autocorrelation of the tested residual with its confidence band; the
    step response; the Bode magnitude and phase; the validation fit of
    every order (each delay one line).

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
    figure, axes = plt.subplots(3, 2, figsize=(13, 11))
    figure.suptitle(title or f'{analysis.estimator}: recommended order {chosen.order}, '
                    f'delay {chosen.delay}', fontsize=13)
    _validation(axes[0, 0], analysis, scale, unit)
    _autocorrelation(axes[0, 1], analysis)
    _step(axes[1, 0], analysis, scale, unit)
    _fit_against_order(axes[1, 1], analysis)
    _bode(axes[2, 0], axes[2, 1], analysis)
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
    ax.plot(t, chosen.simulated[:shown], color='tab:orange', lw=1.4, ls='--',
            label=f'simulated (fit {chosen.fit:.1f} %)')
    part = '' if shown == analysis.validation_samples else \
        f', first {shown} of {analysis.validation_samples}'
    ax.set_title(f'Validation data vs simulated output{part}')
    ax.set_xlabel(f'time ({unit})')
    ax.set_ylabel('y - operating point')
    ax.legend(loc='upper right', fontsize=9)


def _autocorrelation(ax, analysis: Analysis) -> None:
    chosen = analysis.recommended
    residual = chosen.residual
    lags = metrics.whiteness_lags(residual.size)
    r = metrics.autocorrelation(residual, lags)
    # pointwise band of a white sequence: r_k ~ N(0, 1/N), two-sided at the test level
    band = _normal_quantile(1 - WHITENESS_LEVEL / 2) / math.sqrt(residual.size)
    ax.axhspan(-band, band, color='tab:blue', alpha=0.15,
               label=f'{100 * (1 - WHITENESS_LEVEL):.0f} % band of white noise')
    ax.vlines(np.arange(1, lags + 1), 0, r, color='tab:blue', lw=2)
    ax.plot(np.arange(1, lags + 1), r, 'o', color='tab:blue', ms=4)
    ax.axhline(0, color='k', lw=0.8)
    ax.set_xlim(0, lags + 1)
    limit = max(3 * band, 1.2 * float(np.abs(r).max()))
    ax.set_ylim(-limit, limit)
    ax.set_title(f'Autocorrelation of the {analysis.residual_kind} '
                 f'(Ljung-Box p = {chosen.whiteness_p:.3g})')
    ax.set_xlabel('lag (samples)')
    ax.legend(loc='upper right', fontsize=9)


def _step(ax, analysis: Analysis, scale: float, unit: str) -> None:
    model = analysis.recommended.model
    count = model.settling_samples()
    response = model.step(count)
    t = np.arange(count) * scale
    for i in range(model.num_inputs):
        ax.step(t, response[:, i], where='post', lw=1.4, label=f'from u{i + 1}')
    ax.axhline(0, color='k', lw=0.8)
    ax.set_title('Step response of the recommended model')
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
    delays = sorted({c.delay for c in analysis.candidates})
    fits = [c.fit for c in analysis.candidates if c.usable]
    best = max(fits)
    bottom = max(min(fits), -50.0) - 5
    top = min(100.0, best + 0.2 * (100.0 - best) + 1)
    for d in delays:
        rows = [(c.order, c.fit) for c in analysis.candidates if c.delay == d and c.usable]
        if rows:
            orders, values = zip(*rows)
            ax.plot(orders, values, 'o-', lw=1.2, ms=5,
                    label=f'delay {d}' if len(delays) > 1 else 'validation fit')
    limit = 100.0 - (100.0 - best) * (1.0 + FIT_MARGIN)
    ax.axhline(limit, color='0.4', ls=':', lw=1.2, label='margin below the best')
    rejected = [c for c in analysis.candidates if c.usable and not c.white]
    ax.plot([c.order for c in rejected], [c.fit for c in rejected], 'x', color='tab:red',
            ms=9, mew=1.5, label='residuals not white', zorder=4)
    failed = sorted({c.order for c in analysis.candidates if not c.usable}
                    - {c.order for c in analysis.candidates if c.usable})
    if failed:
        ax.plot(failed, [bottom + 0.06 * (top - bottom)] * len(failed), 'v',
                color='tab:purple', ms=9, label='unstable or not fitted')
    ax.plot(chosen.order, chosen.fit, '*', color='gold', mec='k', ms=18, zorder=5,
            label=f'recommended: n = {chosen.order}, d = {chosen.delay}')
    ax.set_ylim(bottom, top)
    ax.set_xticks(sorted({c.order for c in analysis.candidates}))
    ax.set_title('Validation fit against order')
    ax.set_xlabel('order n')
    ax.set_ylabel('fit (%)')
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc='best', ncol=2)


def _normal_quantile(probability: float) -> float:
    from scipy import stats

    return float(stats.norm.ppf(probability))


__all__ = ['write_plot']
