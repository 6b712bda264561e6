"""The figures of hrc_ros: a trajectory (the paper's Figs 9-12 and the belief) and the
selector comparison of `hrc-evaluate`. matplotlib is imported on first use, with the Agg
backend (files only, no screen needed)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .evaluation import METRICS
from ..model import ACTIONS
from ..paths import save_figure

if TYPE_CHECKING:
    from .simulation import Trajectory


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def _save_figure(plt, fig, path) -> Path:
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=110)
    finally:
        plt.close(fig)
    return path


def _step_panels(plt, trajectory, names, labels, title, path):
    epochs = trajectory.column('epoch')
    fig, axes = plt.subplots(len(names), 1, sharex=True, figsize=(9, 1.7 * len(names) + 0.8))
    for ax, name in zip(axes, names):
        values = trajectory.column(name)
        ax.step(epochs, values, where='post', color='tab:blue', lw=2)
        ax.plot(epochs, values, 'o', color='tab:blue', ms=3)
        top = max(3, int(values.max()))
        ax.set_ylim(-0.3, top + 0.3)
        ax.set_yticks(range(top + 1))
        ax.set_ylabel(labels.get(name, name), rotation=0, ha='right', va='center')
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel('epoch')
    axes[-1].set_xticks(epochs)
    fig.suptitle(title)
    return _save_figure(plt, fig, path)


def plot_trajectory(trajectory: Trajectory, out_dir) -> list:
    """PNG plots of a trajectory (paper Figs 9-12 and the belief); returns the paths."""
    plt = _pyplot()

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    subtitle = f'({trajectory.scenario.name}, selector {trajectory.selector})'
    labels = {'tp': 'tp\npriority', 'tc': 'tc\nremaining', 'tx': 'tx\nnature',
              'ty': 'ty\ncommitment', 'hp': 'hp\nhuman prio.', 'hc': 'hc\nhuman rem.',
              'bp': 'bp\nrobot prio.', 'bc': 'bc\nrobot rem.'}
    paths = [
        _step_panels(plt, trajectory, ('tp', 'tc', 'tx', 'ty'), labels,
                     f'Status of the active task {subtitle}', out / 'task_status.png'),
        _step_panels(plt, trajectory, ('hp', 'hc', 'bp', 'bc'), labels,
                     f'Human and robot activity {subtitle}', out / 'activity.png'),
    ]
    epochs = trajectory.column('epoch')

    fig, ax = plt.subplots(figsize=(9, 3.2))
    ax.step(epochs, trajectory.column('d'), where='post', lw=2, color='tab:red')
    ax.plot(epochs, trajectory.column('d'), 'o', color='tab:red', ms=4)
    ax.set_yticks(range(4), ['0 collision', '1 inner', '2 middle', '3 outer'])
    ax.set_ylim(-0.3, 3.3)
    ax.set_xticks(epochs)
    ax.set_xlabel('epoch')
    ax.grid(alpha=0.3)
    ax.set_title(f'Distance level d {subtitle}')
    paths.append(_save_figure(plt, fig, out / 'distance.png'))

    fig, ax = plt.subplots(figsize=(9, 3.8))
    index = np.array([ACTIONS.index(a) for a in trajectory.actions])
    ax.step(epochs, index, where='mid', color='0.7', lw=1)
    accepted = np.array([row['accepted'] for row in trajectory.rows], dtype=object)
    fail = trajectory.column('fail_safe').astype(bool)
    plain = np.array([a is None for a in accepted]) & ~fail
    ax.plot(epochs[plain], index[plain], 'o', color='tab:blue', ms=7, label='action')
    yes = np.array([a is True for a in accepted])
    no = np.array([a is False for a in accepted])
    ax.plot(epochs[yes], index[yes], 's', color='tab:green', ms=8, label='request accepted')
    ax.plot(epochs[no], index[no], 's', mfc='none', color='tab:orange', ms=8,
            label='request refused')
    ax.plot(epochs[fail], index[fail], 'X', color='tab:red', ms=9, label='fail-safe dn')
    ax.set_yticks(range(len(ACTIONS)), ACTIONS)
    ax.set_ylim(-0.5, len(ACTIONS) - 0.5)
    ax.set_xticks(epochs)
    ax.set_xlabel('epoch')
    ax.grid(alpha=0.3)
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.set_title(f'Sequence of the actions {subtitle}')
    paths.append(_save_figure(plt, fig, out / 'actions.png'))

    fig, ax = plt.subplots(figsize=(10, 4.5))
    image = ax.imshow(trajectory.beliefs.T, aspect='auto', origin='lower', cmap='viridis',
                      vmin=0.0, vmax=1.0, extent=(epochs[0] - 0.5, epochs[-1] + 0.5, -0.5, 8.5))
    true_h = 3 * trajectory.column('em') + trajectory.column('ea')
    ax.plot(epochs, true_h, 'o', mfc='none', mec='red', ms=9, mew=1.5, label='true (em, ea)')
    ax.set_yticks(range(9), [f'h={h} ({h // 3},{h % 3})' for h in range(9)])
    ax.set_xticks(epochs)
    ax.set_xlabel('epoch')
    ax.set_ylabel('hidden state (em, ea)')
    ax.legend(loc='upper left', bbox_to_anchor=(1.15, 1.0), fontsize=8)
    fig.colorbar(image, ax=ax, label='belief b(h)')
    ax.set_title(f'Belief over the hidden emotions ({trajectory.mode} filter)\n{subtitle}',
                 fontsize=11)
    paths.append(_save_figure(plt, fig, out / 'belief.png'))
    return paths


def plot_summaries(summaries: dict, path, differences: dict | None = None) -> Path:
    """Bars with 95% error bars per metric; with `differences`, a panel of cost - mdp cost."""
    plt = _pyplot()

    selectors = list(summaries)
    colors = [{'paper': 'tab:blue', 'qmdp': 'tab:orange', 'mls': 'tab:green',
               'mdp': '0.45'}.get(s, 'tab:purple') for s in selectors]
    panels = [(label, [summaries[s][metric] for s in selectors]) for metric, label in METRICS]
    if differences:
        panels.append(('cost - mdp cost (paired)', [differences[s] for s in selectors]))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.1 * len(panels), 3.8))
    for ax, (label, stats) in zip(axes, panels):
        ax.bar(selectors, [m['mean'] for m in stats], yerr=[m['half_width'] for m in stats],
               capsize=4, color=colors)
        ax.set_title(label, fontsize=10)
        ax.tick_params(axis='x', labelrotation=30)
        ax.grid(axis='y', alpha=0.3)
    fig.suptitle('Selectors over the same episodes (mean, 95% confidence interval)')
    return _save_figure(plt, fig, Path(path))


def plot_fit(result, path) -> Path:
    """`hrc-fit --plot`: each fitted parameter beside the base configuration's, with its
    bootstrap 95% interval; one panel per family group (a `fit.FitResult`)."""
    from ..learning.fit import PARAMETER_FAMILIES, PARAMETER_NAMES
    plt = _pyplot()
    fitted, base = result.params.vector(), result.base.vector()
    families = np.array(PARAMETER_FAMILIES)
    panels = (('acceptance and distance', ('p_accept', 'p_delta')),
              ('emotion chains (down, stay, up)', tuple(f for f in dict.fromkeys(families)
                                                        if f.startswith('emotion.'))),
              ('observation likelihood P(O | h)', ('likelihood',)))
    fig, axes = plt.subplots(len(panels), 1, figsize=(13, 11))
    for ax, (title, names) in zip(axes, panels):
        index = np.flatnonzero(np.isin(families, names))
        x = np.arange(len(index))
        ax.plot(x, base[index], 's', mfc='none', mec='0.4', ms=6, label='base')
        if result.interval is not None:
            low, high = result.interval[:, index]
            ax.errorbar(x, fitted[index], yerr=[fitted[index] - np.minimum(low, fitted[index]),
                                                np.maximum(high, fitted[index]) - fitted[index]],
                        fmt='o', color='tab:blue', ms=4, capsize=2, label='fitted, 95% interval')
        else:
            ax.plot(x, fitted[index], 'o', color='tab:blue', ms=4, label='fitted')
        held = np.isin(families[index], result.hold)
        if held.any():
            ax.plot(x[held], fitted[index][held], 'x', color='tab:red', ms=7, label='held')
        ax.set_xticks(x, [PARAMETER_NAMES[i] for i in index], rotation=90, fontsize=6)
        ax.set_ylim(-0.03, 1.03)
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc='upper right')
    fig.suptitle(f'hrc-fit: {result.epochs} epochs, {result.episodes} episodes, log likelihood '
                 f'{result.loglik:.2f}')
    return _save_figure(plt, fig, Path(path))
