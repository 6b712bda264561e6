"""Paired differences across two hrc-evaluate runs of the same episodes (different planning
models: the task-stream configuration against the paper's model, or the stream with a queue
against either).

    .venv/bin/python bench/stream_paired.py OUT_A/episodes.csv OUT_B/episodes.csv
                                            [--baseline pomdp] [--waiting-cost W]
                                            [--by-selector]

Both runs must have the same scenario, episodes, epochs, seed and task rate (the episodes and
the human's draws depend on none of the planning model's numbers, so the rows are paired by
episode). Prints, for every selector of either run, its discounted cost minus the baseline of
run A (the stream model's pomdp by default), with the 95% paired interval
(`evaluation.paired_difference`), and the mean tasks completed.

Runs that charged waiting tasks (MODEL.md 8.1: a configuration with a queue, or `hrc-evaluate
--waiting-cost`) carry `waiting_epochs` and `discounted_waiting` (the discounted count of
waiting tasks) in episodes.csv and their w in summary.json beside it; for them the cost is
also given without the charge, and `--waiting-cost W` scores every such run with W instead of
its own w (cost without the charge + W * discounted_waiting), so one run of the queue-less
configurations serves every w. Also printed then: epochs per task and waiting task-epochs.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hrc_ros.core.study.evaluation import Z95  # noqa: E402

COLUMNS = ('discounted_cost', 'tasks_completed', 'epochs_to_complete', 'waiting_epochs',
           'discounted_waiting')


def read(path, waiting_cost: float | None) -> dict:
    """selector -> {episode, cost, plain (without the charge, or None), column: array}."""
    summary = Path(path).with_name('summary.json')
    charged = None
    if summary.exists():
        charged = json.loads(summary.read_text())['settings'].get('waiting_cost')
    rows: dict = {}
    with open(path) as f:
        for row in csv.DictReader(f):
            rows.setdefault(row['selector'], []).append(
                [int(row['episode'])] + [float(row[c]) if c in row else np.nan for c in COLUMNS])
    out = {}
    for selector, values in rows.items():
        a = np.array(sorted(values))
        r = {'episode': a[:, 0]} | {c: a[:, 1 + i] for i, c in enumerate(COLUMNS)}
        r['plain'] = None
        r['cost'] = r['discounted_cost']
        if charged is not None and np.all(np.isfinite(r['discounted_waiting'])):
            r['plain'] = r['discounted_cost'] - charged * r['discounted_waiting']
            if waiting_cost is not None:
                r['cost'] = r['plain'] + waiting_cost * r['discounted_waiting']
        out[selector] = r
    return out


def paired(x, y) -> tuple[float, float]:
    diff = x - y
    return float(diff.mean()), float(Z95 * diff.std(ddof=1) / np.sqrt(diff.size))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('a')
    parser.add_argument('b')
    parser.add_argument('--baseline', default='pomdp')
    parser.add_argument('--by-selector', action='store_true',
                        help='also every selector of run B minus the same selector of run A')
    parser.add_argument('--waiting-cost', type=float, default=None,
                        help='score the runs that charged waiting tasks with this w instead')
    args = parser.parse_args(argv)
    a, b = read(args.a, args.waiting_cost), read(args.b, args.waiting_cost)
    base = a[args.baseline]
    print(f'baseline: {args.baseline} of {args.a} ({len(base["episode"])} episodes), mean cost '
          f'{base["cost"].mean():.3f}'
          + ('' if args.waiting_cost is None else f' (w = {args.waiting_cost:g})'))
    for label, runs in (('A', a), ('B', b)):
        for selector, r in runs.items():
            if not np.array_equal(r['episode'], base['episode']):
                raise SystemExit(f'{selector} of run {label}: not the same episodes')
            mean, half = paired(r['cost'], base['cost'])
            line = (f'  {label} {selector:<6} cost {r["cost"].mean():8.3f}  minus baseline '
                    f'{mean:+7.3f} ± {half:.3f}  tasks completed '
                    f'{r["tasks_completed"].mean():.2f}')
            if r['plain'] is not None and base['plain'] is not None:
                mean, half = paired(r['plain'], base['plain'])
                line += (f'  epochs per task {np.nanmean(r["epochs_to_complete"]):.2f}  waiting '
                         f'task-epochs {r["waiting_epochs"].mean():.2f}  without the charge '
                         f'{r["plain"].mean():8.3f} minus baseline {mean:+7.3f} ± {half:.3f}')
            print(line)
    if args.by_selector:
        print('run B minus run A, selector by selector (paired):')
        for selector in (s for s in b if s in a):
            x, y = b[selector], a[selector]
            mean, half = paired(x['cost'], y['cost'])
            line = f'  {selector:<6} cost {mean:+7.3f} ± {half:.3f}'
            if x['plain'] is not None and y['plain'] is not None:
                mean, half = paired(x['plain'], y['plain'])
                line += f'  without the charge {mean:+7.3f} ± {half:.3f}'
            mean, half = paired(x['tasks_completed'], y['tasks_completed'])
            print(line + f'  tasks completed {mean:+.3f} ± {half:.3f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
