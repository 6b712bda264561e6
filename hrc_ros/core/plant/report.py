"""The plant report: one entry per cell (`plant_report.json`), a table and plots
(`plant_report.md`, `plant_costs.png`), and each cell's shadow-check plot.

An entry holds at least `cell`, `decision` (promote, keep or failed), `reason`, `drift_p` and
`cost_difference` (the new policy's discounted cost minus the running one's per episode: the
in-sample figure corrected for the fit's optimism, with `low` and `high`, its 95% interval
carrying the fitting error, what the promotion rule decides on, and `in_sample`,
`optimism`, `optimism_sd`, `refits`; null when no shadow check ran), and also the drift
test's figures, every other metric of the check alike (`collision_epochs`,
`refused_requests`, `tasks_completed`, `collision_stuck`), `guards` (the safety guard, the
plant's, and those that kept the cell with the cost they gave up), `shadow` (the world, the
refits' errors, the in-sample figures), the fit's warnings, the fitted parameters that moved
(whose 95% interval leaves out the base value) with their intervals, the stages' seconds, the
files written, the stage tasks Ray ran more than once (`retries`) and, with --apply, what the
swap did. The plant's entry has `lost_nodes` and `retried_tasks`.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ..paths import save_figure
from . import check, drift


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


def plot_shadow(entry: dict, in_sample: np.ndarray, path) -> Path:
    """The shadow check of one cell: the per-episode cost differences in the fitted world
    (in-sample), their mean, and the estimate the rule decides on (in-sample minus the
    refits' mean error) with its 95% interval; each refit's error marks where that refit
    would have put the estimate."""
    plt = _pyplot()
    cost = entry['cost_difference']
    errors = np.asarray(entry['shadow']['errors']['discounted_cost'], dtype=float)
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.hist(in_sample, bins=60, color='0.75', label='per episode, in-sample')
    ax.axvline(cost['in_sample'], color='tab:orange', lw=2,
               label=f'in-sample mean {cost["in_sample"]:+.3f} (optimistic)')
    ax.axvspan(cost['low'], cost['high'], color='tab:blue', alpha=0.2,
               label=f'decides: {cost["mean"]:+.3f} [{cost["low"]:+.3f}, {cost["high"]:+.3f}]')
    ax.axvline(cost['mean'], color='tab:blue', lw=2)
    if errors.size:
        ax.plot(cost['in_sample'] - errors, np.zeros(errors.size), '|', color='tab:blue',
                ms=14, label=f'in-sample minus each refit\'s error ({errors.size})')
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


COLOURS = {'promote': 'tab:green', 'keep': 'tab:blue', 'failed': 'tab:red'}


def plot_plant(entries: list[dict], path) -> Path:
    """`plant_figure`, saved."""
    plt = _pyplot()
    fig = plant_figure(entries)
    try:
        save_figure(fig, path, dpi=100)
    finally:
        plt.close(fig)
    return Path(path)


def plant_figure(entries: list[dict]):
    """Every cell's cost difference (the estimate the rule decides on) with its 95% interval,
    coloured by the decision, the in-sample figure beside it; cells without a shadow check
    are named, without a bar. A legend says which is which."""
    from matplotlib.lines import Line2D
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 0.45 * len(entries) + 1.8))
    for i, e in enumerate(entries):
        c = e.get('cost_difference')
        colour = COLOURS.get(e['decision'], 'k')
        if c:
            ax.errorbar(c['mean'], i, xerr=[[c['mean'] - c['low']], [c['high'] - c['mean']]],
                        fmt='o', color=colour, capsize=3, ls='--' if episodes_only(c) else '-',
                        mfc='white' if episodes_only(c) else colour)
            if c.get('in_sample') is not None:
                ax.plot(c['in_sample'], i, 'x', color='tab:orange')
        else:
            ax.text(0, i, f'  {e["decision"]}: no shadow check', va='center', fontsize=8,
                    color=colour)
    ax.axvline(0.0, color='0.3', lw=1)
    ax.set_yticks(range(len(entries)), [e['cell'] for e in entries])
    ax.invert_yaxis()
    ax.set_xlabel('discounted cost per episode, new - running')
    handles = [Line2D([], [], color=COLOURS[d], marker='o', label=f'{d}: estimate, 95% '
                      'interval (fitting error and episodes)')
               for d in ('promote', 'keep') if any(e['decision'] == d for e in entries)]
    if any(episodes_only(e.get('cost_difference')) for e in entries):
        handles.append(Line2D([], [], color='0.3', marker='o', mfc='white', ls='--',
                              label=f'open: {EPISODES_ONLY} (too few episodes: kept)'))
    handles.append(Line2D([], [], color='tab:orange', marker='x', ls='',
                          label='in-sample (optimistic, does not decide)'))
    ax.legend(handles=handles, fontsize=7, loc='best')
    fig.tight_layout()
    return fig


EPISODES_ONLY = 'episodes only: no refits, fitting error not bounded'


def episodes_only(m: dict | None) -> bool:
    """A figure the check could not correct (fewer than 2 refits, `check.corrected`): its
    interval is the episodes' alone and leaves the fitting error out."""
    return bool(m) and m.get('optimism') is None and 'in_sample' in m


def _interval(m: dict | None, digits: int = 3) -> str:
    if not m:
        return '-'
    text = f'{m["mean"]:+.{digits}f} [{m["low"]:+.{digits}f}, {m["high"]:+.{digits}f}]'
    return f'{text} ({EPISODES_ONLY})' if episodes_only(m) else text


def _both(m: dict | None) -> str:
    return '-' if not m else f'{m["new"]:.2f} / {m["running"]:.2f}'


RUN_WORDS = {'always': 'run: always (fitted and checked whatever the drift test says)',
             'on_drift': 'run: on_drift (fitted and checked only when drift is found)'}


def _check_table(entry: dict) -> list[str]:
    """Each metric of the shadow check: in-sample, the refits' error, the estimate."""
    shadow = entry.get('shadow')
    if not shadow:
        return []
    lines = [f'Shadow check ({shadow["episodes"]} paired episodes of {shadow["epochs"]} '
             f'epochs, selector {shadow["selector"]}, seed {shadow["seed"]}; '
             f'{shadow["refits"]} refits'
             + (f', {shadow["refits_not_converged"]} of them with EM not converged'
                if shadow.get('refits_not_converged') else '')
             + f'): {shadow["world"]}.', '',
             '| new - running, per episode | in-sample (episodes\' 95%) | refits\' mean error '
             '(sd) | estimate (95%): decides |', '|---|---|---|---|']
    for metric, (words, _) in check.METRICS.items():
        m = entry.get('cost_difference' if metric == check.COST else metric)
        if not m:
            continue
        error = ('-' if m.get('optimism') is None else
                 f'{m["optimism"]:+.3f} ({m["optimism_sd"]:.3f})')
        lines.append(f'| {words} | {m["in_sample"]:+.3f} +- {m["in_sample_half_width"]:.3f} | '
                     f'{error} | {_interval(m)} |')
    return lines + ['']


def _guard_lines(entry: dict) -> list[str]:
    guards = entry.get('guards')
    if not guards:
        return []
    plant = ', '.join(guards['plant']) or 'none (promote.guards)'
    lines = [f'Guards: safety, always: {check.METRICS[guards["safety"]][0]} not higher with '
             f'95% confidence; the plant\'s: {plant}.']
    for b in guards['kept_by']:
        lines.append(f'Kept by the guard {b["guard"]}: {_interval(b["figure"])} per episode; '
                     f'the cost it gave up: {_interval(b["cost_given_up"])} per episode.')
    return lines + ['']


# below this many recorded episodes a keep says little (bench/shadow_bench.py, docs/FLEET.md:
# the check's power by recording size)
POWER_EPISODES = 200


def _warning_lines(entry: dict) -> list[str]:
    warnings = cell_warnings(entry)
    if not warnings:
        return []
    return ['Warnings:', ''] + [f'- {w}' for w in warnings] + ['']


def cell_warnings(entry: dict) -> list[str]:
    """Every warning of a cell: the fit's, a keep on few episodes, the stream fit's, the rows
    the read left out (the table's count and the cell's Warnings section)."""
    read = entry.get('read') or {}
    warnings = list((entry.get('fit') or {}).get('warnings') or [])
    episodes = read.get('episodes')
    checked = entry.get('cost_difference') is not None     # the shadow check ran
    if entry.get('decision') == check.KEEP and checked and episodes is not None \
            and episodes < POWER_EPISODES:
        warnings.append(f'kept on {episodes} recorded episode{"s" if episodes != 1 else ""}: '
                        'the fitting error of so few keeps most truly cheaper policies from '
                        'promotion (of cells truly cheaper by >= 1 per episode, 4 of 16 '
                        'promoted at 20 episodes; bench/shadow_bench.py, docs/FLEET.md by '
                        'recording size), so this keep is weak evidence that no better '
                        f'policy exists: record {POWER_EPISODES} episodes or more')
    stream = (entry.get('fit') or {}).get('stream') or {}
    warnings += [f'stream: {w}' for w in stream.get('warnings') or []]
    if read.get('issues'):
        warnings.append(f'{read["issues"]} row{"s" if read["issues"] != 1 else ""} of the '
                        'recordings left out or episodes cut (the fit\'s rules): '
                        + '; '.join(read.get('first_issues') or []))
    return warnings


def _retry_lines(entry: dict) -> list[str]:
    retries = entry.get('retries') or []
    if not retries:
        return []
    return ['Ray ran ' + '; '.join(
        f'{r["stage"]} {r["attempts"]} times (workers ' + ', '.join(
            f'pid {w["pid"]} on {w["node"]}' for w in r['workers']) + ')'
        for r in retries) + ': a worker died or its node was lost, and the task was retried '
        '(the seeds do not depend on where it ran, so the figures are those of a run '
        'without it).', '']


def _moved_lines(entry: dict) -> list[str]:
    moved = entry.get('moved') or []
    if not moved:
        return []
    return (['Moved (the fitted value\'s 95% interval leaves out the base value; the interval '
             'is the bootstrap\'s over episodes, widened to hold the fitted value and to at '
             'least the binomial interval of the parameter\'s support):', '',
             '| parameter | base | fitted | 95% interval | support (epochs) |',
             '|---|---|---|---|---|']
            + [f'| {m["name"]} | {m["base"]:.4f} | {m["fitted"]:.4f} | '
               f'[{m["ci95"][0]:.4f}, {m["ci95"][1]:.4f}] | {m.get("support", 0):.0f} |'
               for m in moved] + [''])


SERIAL_ENGINE = 'one process (serial)'     # hrc-fleet --serial's engine


def _engine_lines(plant: dict) -> list[str]:
    lost = plant.get('lost_nodes') or []
    retried = plant.get('retried_tasks', 0)
    words = ('no node lost' if not lost else 'nodes lost: ' + '; '.join(
        f'{n["node"][:12]} ({n["address"]}) after {n["after_seconds"]:.0f} s: {n["reason"]}'
        for n in lost))
    words += ('; no task retried' if not retried else
              f'; {retried} stage task{"s" if retried != 1 else ""} retried (per cell below)')
    if plant['engine'] == SERIAL_ENGINE:         # no Ray, no ray.log
        return [f'Engine: {plant["engine"]}, without Ray.', '']
    return [f'Engine: {plant["engine"]}; {words}. Ray\'s own output: [ray.log](ray.log) '
            '(when this run started or joined Ray).', '']


def markdown(plant: dict) -> str:
    """plant_report.md: the table, the plot, then per cell what decided, what the fit warned
    of, what moved and what Ray had to redo."""
    entries = plant['cells']
    lines = [f'# Plant report: {plant["plant"]}', '',
             f'{plant["started"]}, {len(entries)} cells, {plant["seconds"]:.1f} s. Decisions: '
             + ', '.join(f'{k} {v}' for k, v in plant['decisions'].items()) + '.', '']
    lines += _engine_lines(plant)
    lines += ['Cost difference: the new policy\'s discounted cost (the cost it minimises, which '
              'prices requests, refusals and the person\'s emotions) minus the running one\'s '
              'over the same episodes, per episode. In-sample (both in the world fitted from '
              'the recordings) it is optimistic for the new policy; the estimate subtracts '
              'the optimism measured by refits (resamples of the recordings\' episodes, drawn '
              'with replacement, each fitted and solved as the cell was), and its 95% '
              'interval carries the fitting error as well as the episodes\' noise (a cell with '
              'too few episodes for refits is kept, and its interval is marked as the '
              'episodes\' alone). '
              'Promote when that interval is below zero, unless the collision epochs are '
              'higher with 95% confidence (the safety guard) or a guard of the plant file '
              'says the new policy is worse (docs/FLEET.md).', '',
              '| cell | namespace | run | decision | drift p | cost new - running (95%) | '
              'in-sample | collision epochs new - running (95%) | refused new - running '
              '(95%) | moved | warnings | reason |',
              '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for e in entries:
        p = '-' if e.get('drift_p') is None else f'{e["drift_p"]:.3f}'
        reason = str(e.get('reason') or '').replace('|', '/')
        cost = e.get('cost_difference') or {}
        inside = '-' if cost.get('in_sample') is None else f'{cost["in_sample"]:+.3f}'
        warnings = len(cell_warnings(e))
        lines.append(f'| {e["cell"]} | {e["namespace"]} | {e.get("run", "-")} | '
                     f'**{e["decision"]}** | {p} | {_interval(cost or None)} | {inside} | '
                     f'{_interval(e.get("collision_epochs"))} | '
                     f'{_interval(e.get("refused_requests"))} | {len(e.get("moved") or [])} | '
                     f'{warnings} | {reason} |')
    lines += ['', '![cost differences](plant_costs.png)', '']
    for e in entries:
        lines += [f'## {e["cell"]} ({e["namespace"]}): {e["decision"]}', '', str(e['reason']),
                  '']
        read = e.get('read')
        lines.append(RUN_WORDS.get(e.get('run'), f'run: {e.get("run")}') + '.'
                     + (f' Recordings: {read["epochs"]} epochs in {read["episodes"]} '
                        f'episode{"s" if read["episodes"] != 1 else ""}.' if read else ''))
        lines.append('')
        d = e.get('drift')
        if d:
            lines += [f'Drift: {drift.describe(d)}.', '']
        lines += _warning_lines(e)
        lines += _check_table(e)
        lines += _guard_lines(e)
        lines += _retry_lines(e)
        if e.get('applied'):
            lines += [f'Applied: {e["applied"]["status"]}: {e["applied"]["detail"]}', '']
        lines += _moved_lines(e)
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
