"""Paired differences between any two selectors of one `hrc-evaluate --cell arm` run, from its
episodes.csv (issue 34: the default decision against both baselines, ssm_only and the
integrator's rule, on the same episodes), without running the episodes again.

Per metric of the cell (core.robot.cell.METRICS, and tasks completed): the mean of the
per-episode difference A - B with its 95% normal interval, as `hrc-evaluate --baseline B`
prints it, and the relative difference of the means where it is a rate.

    python bench/arm_paired.py OUT/episodes.csv [--pairs paper-ssm_only,paper-integrator]
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrc_ros.core.robot.cell import METRICS, _interval  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('episodes', help='episodes.csv of hrc-evaluate --cell arm')
    parser.add_argument('--pairs', default='paper-ssm_only,paper-integrator,qmdp-integrator,'
                        'integrator-ssm_only', help='comma-separated A-B')
    args = parser.parse_args(argv)
    rows: dict = defaultdict(dict)
    with open(args.episodes, newline='') as f:
        for row in csv.DictReader(f):
            rows[row['selector']][int(row['episode'])] = row
    metrics = list(METRICS) + [('tasks_completed', 'tasks completed')]
    for pair in args.pairs.split(','):
        a, b = pair.split('-')
        if a not in rows or b not in rows:
            print(f'{pair}: {a if a not in rows else b} is not in {args.episodes}')
            continue
        episodes = sorted(set(rows[a]) & set(rows[b]))
        print(f'{a} - {b} ({len(episodes)} paired episodes, 95%):')
        for metric, label in metrics:
            x = np.array([float(rows[a][e][metric]) for e in episodes])
            y = np.array([float(rows[b][e][metric]) for e in episodes])
            d = _interval(x - y)
            verdict = ('higher' if d['low'] > 0 else 'lower' if d['high'] < 0
                       else 'not distinguishable')
            relative = (f' ({100 * d["mean"] / y.mean():+.1f}%)'
                        if metric == 'tasks_per_hour' and y.mean() else '')
            print(f'  {label:<20} {d["mean"]:+10.3f} ± {d["half_width"]:.3f}{relative}  '
                  f'{verdict}  [{a} {x.mean():.3f}, {b} {y.mean():.3f}]')
    print(f'reproduce: python bench/arm_paired.py {args.episodes} --pairs {args.pairs}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
