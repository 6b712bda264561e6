"""The plant report: one entry per cell (`plant_report.json`), a table and plots
(`plant_report.md`, `plant_costs.png`), and each cell's shadow-check plot.

An entry holds at least `cell`, `decision` (promote, keep or failed), `reason`, `drift_p` and
`cost_difference` (the paired mean of the new policy's discounted cost minus the running one's,
with `low` and `high`, its 95% interval, held out: what the promotion rule decides on; null
when no shadow check ran), and also the drift test's figures, the collision epochs and
refused requests both ways (held out too), `shadow` (each fold's figures and the in-sample
ones, each with the world it was measured in), the fitted parameters
that moved (whose 95% interval leaves out the base value) with their intervals, the stages'
seconds, the files written and, with --apply, what the swap did.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ..paths import save_figure


def figure_bytes(plot, *args) -> bytes:
    """The PNG `plot(*args, path)` draws, as bytes (plots are made where the data are; the
    driver writes the files)."""
    with tempfile.TemporaryDirectory(prefix='hrc_plant_') as folder:
        path = Path(folder) / 'figure.png'
        plot(*args, path)
        return path.read_bytes()


def plot_fit(result, path) -> Path:
    from ..study.plots import plot_fit as draw
    return draw(result, path)


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def plot_shadow(entry: dict, heldout: np.ndarray, in_sample: np.ndarray, path) -> Path:
    """The shadow check of one cell: the per-episode cost differences held out (what the
    rule decides on) and in-sample (the new policy in its own fitted world), means and
    intervals."""
    plt = _pyplot()
    cost, inside = entry['cost_difference'], entry['shadow']['in_sample']['discounted_cost']
    fig, ax = plt.subplots(figsize=(7, 3.6))
    bins = np.histogram_bin_edges(np.concatenate([heldout, in_sample]), bins=60)
    for values, c, colour, label in ((heldout, cost, 'tab:blue', 'held out (decides)'),
                                     (in_sample, inside, 'tab:orange', 'in-sample')):
        ax.hist(values, bins=bins, color=colour, alpha=0.45)
        ax.axvline(c['mean'], color=colour, lw=2,
                   label=f'{label}: {c["mean"]:+.3f} [{c["low"]:+.3f}, {c["high"]:+.3f}]')
        ax.axvspan(c['low'], c['high'], color=colour, alpha=0.2)
    ax.axvline(0.0, color='0.3', lw=1)
    ax.set_xlabel('discounted cost, new policy - running policy (same episode)')
    ax.set_ylabel('episodes')
    ax.set_title(f'{entry["cell"]}: {entry["decision"]}', fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=100)
    finally:
        plt.close(fig)
    return Path(path)


def plot_plant(entries: list[dict], path) -> Path:
    """Every cell's paired cost difference with its 95% interval (cells without a shadow
    check are named, without a bar)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 0.45 * len(entries) + 1.4))
    colours = {'promote': 'tab:green', 'keep': 'tab:blue', 'failed': 'tab:red'}
    for i, e in enumerate(entries):
        c = e.get('cost_difference')
        if c:
            ax.errorbar(c['mean'], i, xerr=[[c['mean'] - c['low']], [c['high'] - c['mean']]],
                        fmt='o', color=colours.get(e['decision'], 'k'), capsize=3)
        else:
            ax.text(0, i, f'  {e["decision"]}: no shadow check', va='center', fontsize=8,
                    color=colours.get(e['decision'], 'k'))
    ax.axvline(0.0, color='0.3', lw=1)
    ax.set_yticks(range(len(entries)), [e['cell'] for e in entries])
    ax.invert_yaxis()
    ax.set_xlabel('discounted cost, new - running (paired, 95%)')
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=100)
    finally:
        plt.close(fig)
    return Path(path)


def _interval(m: dict | None, digits: int = 3) -> str:
    if not m:
        return '-'
    return f'{m["mean"]:+.{digits}f} [{m["low"]:+.{digits}f}, {m["high"]:+.{digits}f}]'


def _both(m: dict | None) -> str:
    return '-' if not m else f'{m["new"]:.2f} / {m["running"]:.2f}'


def _in_sample(entry: dict) -> dict:
    return (entry.get('shadow') or {}).get('in_sample') or {}


def _shadow_table(entry: dict) -> list[str]:
    """Each figure of the shadow check with the world it was measured in."""
    shadow = entry.get('shadow')
    if not shadow:
        return []
    rows = [(f'policy fitted from {f["policy_fitted_from"]}', f'fitted from '
             f'{f["world_fitted_from"]}', f) for f in shadow['folds']]
    held = {'discounted_cost': entry['cost_difference'],
            'collision_epochs': entry['collision_epochs'],
            'refused_requests': entry['refused_requests']}
    rows.append(('both folds, per episode averaged', 'held out (the rule decides on this)',
                 held))
    rows.append(('fitted from all the recordings', f'{shadow["in_sample"]["world"]}; the rule '
                 f'there would say {shadow["in_sample"]["decision"]}', shadow['in_sample']))
    lines = [f'Shadow check ({shadow["episodes"]} paired episodes of {shadow["epochs"]} epochs, '
             f'selector {shadow["selector"]}, seed {shadow["seed"]}):', '',
             '| new policy | world | cost new - running (95%) | collision epochs new - '
             'running | refused new - running |', '|---|---|---|---|---|']
    for policy, world, m in rows:
        lines.append(f'| {policy} | {world} | {_interval(m["discounted_cost"])} | '
                     f'{_interval(m["collision_epochs"])} | {_interval(m["refused_requests"])} |')
    return lines + ['']


def markdown(plant: dict) -> str:
    """plant_report.md: the table, the plot, then per cell what moved and why."""
    entries = plant['cells']
    lines = [f'# Plant report: {plant["plant"]}', '',
             f'{plant["started"]}, {len(entries)} cells on {plant["engine"]}, '
             f'{plant["seconds"]:.1f} s. Decisions: '
             + ', '.join(f'{k} {v}' for k, v in plant['decisions'].items()) + '.', '',
             'Cost difference: the new policy\'s discounted cost minus the running one\'s over '
             'the same episodes (mean, 95% interval), held out: the policy fitted and solved '
             'from one half of the recordings, both policies in the world fitted from the '
             'other half, the two folds averaged. Promote only when that interval is below '
             'zero and collision epochs and refused requests (held out too) are not above the '
             'running policy\'s. In-sample: the new policy in the world fitted from all the '
             'recordings, the ones it was solved from; optimistic for it, reported, never '
             'deciding (docs/FLEET.md).', '',
             '| cell | namespace | decision | drift p | cost new - running, held out (95%) | '
             'in-sample (not deciding) | collision epochs new / running, held out | '
             'refused new / running | moved | reason |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for e in entries:
        p = '-' if e.get('drift_p') is None else f'{e["drift_p"]:.3f}'
        reason = str(e.get('reason') or '').replace('|', '/')
        lines.append(f'| {e["cell"]} | {e["namespace"]} | **{e["decision"]}** | {p} | '
                     f'{_interval(e.get("cost_difference"))} | '
                     f'{_interval(_in_sample(e).get("discounted_cost"))} | '
                     f'{_both(e.get("collision_epochs"))} | {_both(e.get("refused_requests"))}'
                     f' | {len(e.get("moved") or [])} | {reason} |')
    lines += ['', '![cost differences](plant_costs.png)', '']
    for e in entries:
        lines += [f'## {e["cell"]} ({e["namespace"]}): {e["decision"]}', '', str(e['reason']),
                  '']
        d = e.get('drift')
        if d:
            median = '-' if d['null_median'] is None else f'{d["null_median"]:.2f}'
            lines.append(f'Drift: likelihood ratio {d["statistic"]:.2f} over the last '
                         f'{d["window_epochs"]} epochs, p = {d["p"]:.3f} ({d["simulations"]} '
                         f'simulations under the running model, their median {median}); '
                         f'{"drift" if d["drifted"] else "no drift"} at alpha {d["alpha"]:g}.')
            lines.append('')
        lines += _shadow_table(e)
        if e.get('applied'):
            lines += [f'Applied: {e["applied"]["status"]}: {e["applied"]["detail"]}', '']
        moved = e.get('moved') or []
        if moved:
            lines += ['| parameter | base | fitted | 95% interval |', '|---|---|---|---|']
            lines += [f'| {m["name"]} | {m["base"]:.4f} | {m["fitted"]:.4f} | '
                      f'[{m["ci95"][0]:.4f}, {m["ci95"][1]:.4f}] |' for m in moved]
            lines.append('')
        files = e.get('files') or []
        for name, title in (('fitted.png', 'fitted parameters'), ('shadow.png', 'shadow check')):
            if name in files:
                lines.append(f'![{title}](cells/{e["cell"]}/{name})')
        if files:
            lines += ['', 'Files: ' + ', '.join(f'[{n}](cells/{e["cell"]}/{n})' for n in files),
                      '']
    return '\n'.join(lines) + '\n'


def plot_bytes(entries: list[dict]) -> bytes:
    return figure_bytes(plot_plant, entries)
