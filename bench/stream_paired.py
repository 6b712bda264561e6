"""Paired differences across two hrc-evaluate runs of the same episodes (different planning
models: the task-stream configuration against the paper's model).

    .venv/bin/python bench/stream_paired.py OUT_A/episodes.csv OUT_B/episodes.csv
                                            [--baseline pomdp]

Both runs must have the same scenario, episodes, epochs, seed and task rate (the episodes and
the human's draws depend on none of the planning model's numbers, so the rows are paired by
episode). Prints, for every selector of either run, its discounted cost minus the baseline of
run A (the stream model's pomdp by default), with the 95% paired interval
(`evaluation.paired_difference`), and the mean tasks completed.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hrc_ros.core.study.evaluation import Z95  # noqa: E402


def read(path) -> dict:
    rows: dict = {}
    with open(path) as f:
        for row in csv.DictReader(f):
            rows.setdefault(row['selector'], []).append(
                (int(row['episode']), float(row['discounted_cost']),
                 float(row['tasks_completed'])))
    return {s: np.array(sorted(v)) for s, v in rows.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('a')
    parser.add_argument('b')
    parser.add_argument('--baseline', default='pomdp')
    args = parser.parse_args(argv)
    a, b = read(args.a), read(args.b)
    base = a[args.baseline]
    print(f'baseline: {args.baseline} of {args.a} ({len(base)} episodes), mean cost '
          f'{base[:, 1].mean():.3f}')
    for label, runs in (('A', a), ('B', b)):
        for selector, rows in runs.items():
            if not np.array_equal(rows[:, 0], base[:, 0]):
                raise SystemExit(f'{selector} of run {label}: not the same episodes')
            diff = rows[:, 1] - base[:, 1]
            half = Z95 * diff.std(ddof=1) / np.sqrt(diff.size)
            print(f'  {label} {selector:<6} cost {rows[:, 1].mean():8.3f}  minus baseline '
                  f'{diff.mean():+7.3f} ± {half:.3f}  tasks completed {rows[:, 2].mean():.2f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
