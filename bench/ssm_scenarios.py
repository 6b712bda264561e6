"""SSM against people who test it, in the batch cell with the arm (docs/ROBOT.md 4, "People who
test SSM"): per person scenario and selector, SSM violations against the true bodies (the
appearance exception apart), the smallest margin S - S_p while the arm moved, the time from the
event to the arm at rest, and the time from an appeared person's first skeleton to the stop;
then per scenario each selector against the first, paired on the same episodes: the time to
rest's mean difference and its p95's, with 95% intervals (t over the episodes; a paired
bootstrap over the episodes for the p95), and the share of episodes where it took longer.

The same episodes as `hrc-evaluate --cell arm --person SCENARIO` (random task streams at task
rate 0.5, seed 0, the arm's model and policy), shorter (--epochs, default 20: every episode has
its event in [2 s, half the episode]), in worker processes (--jobs; a chunk of episodes each,
merged in episode order: the figures do not depend on --jobs).

    python bench/ssm_scenarios.py [--episodes 1000] [--epochs 20] [--jobs 2]
        [--scenarios walk_in,run_in,appear,reach,frozen_tracker,lost_tracker]
        [--selectors ssm_only,paper] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from hrc_ros.core.cell.scenarios import SCENARIOS  # noqa: E402

CHUNK = 25      # episodes per task of a worker
_CELLS: dict = {}   # a worker's cells, by scenario


def _chunk(job):
    """Episodes [start, stop) of one scenario and selector: their per-episode figures."""
    scenario, selector, start, stop, epochs, seed = job
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import arm_config_path
    from hrc_ros.core.robot.cell import ArmCell, person_seed
    from hrc_ros.core.study.evaluation import episodes_of
    config = load_config(arm_config_path())
    model = HRCModel(config)
    cell = _CELLS.get(scenario)
    if cell is None:
        cell = _CELLS[scenario] = ArmCell(
            model, load_policy(default_policy_path(config), config), person=scenario)
    scenarios, seeds = episodes_of(model, 'random', stop, epochs, seed, 0.5)
    rows = []
    for e in range(start, stop):
        r = cell.episode(scenarios[e], seeds[e], person_seed(seed, e), selector)
        rows.append((r.ssm_violations, r.appearance_violations, r.contacts, r.speed_breaches,
                     r.min_margin, r.rest_after_event, r.stop_delay, r.tasks_completed,
                     r.stop_time / r.seconds))
    return rows


def summary(rows, control_period: float) -> dict:
    a = np.array(rows, dtype=float)
    margin, rest, delay = a[:, 4], a[:, 5], a[:, 6]
    margin, rest, delay = (x[np.isfinite(x)] for x in (margin, rest, delay))
    violating = int((a[:, 0] > 0).sum())
    n = len(a)
    # 95% upper bound on the share of episodes with a violation (rule of three when none)
    upper = 3.0 / n if violating == 0 else None
    return {
        'episodes': n, 'ssm_violations': int(a[:, 0].sum()),
        'episodes_with_violations': violating, 'violating_share_upper95': upper,
        'appearance_violations': int(a[:, 1].sum()), 'contacts': int(a[:, 2].sum()),
        'speed_breaches': int(a[:, 3].sum()),
        'min_margin_m': float(margin.min()) if margin.size else None,
        'rest_after_event_s': ({'mean': float(rest.mean()), 'p95': float(np.percentile(rest, 95)),
                                'max': float(rest.max())} if rest.size else None),
        'stop_delay_control_periods': ({'max': float(delay.max() / control_period),
                                        'appearances_inside_sp0': int(delay.size)}
                                       if delay.size else None),
        'tasks_per_episode': float(a[:, 7].mean()), 'stop_share': float(a[:, 8].mean()),
    }


BOOTSTRAP = 2000    # paired resamples of the episodes for the p95's interval


def paired_rest(base_rows, rows, seed: int = 0) -> dict | None:
    """The time to rest after the event, `rows` minus `base_rows`, paired on the episodes
    where both have one (the same episodes: same streams, people and seeds)."""
    a = np.array(base_rows, dtype=float)[:, 5]
    b = np.array(rows, dtype=float)[:, 5]
    both = np.isfinite(a) & np.isfinite(b)
    a, b = a[both], b[both]
    n = len(a)
    if n < 2:
        return None
    diff = b - a
    half = 1.96 * diff.std(ddof=1) / np.sqrt(n)     # normal: the runs reported have n >= 200
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, n, size=(BOOTSTRAP, n))
    p95 = np.percentile(b[picks], 95, axis=1) - np.percentile(a[picks], 95, axis=1)
    return {'episodes': n, 'mean': float(diff.mean()), 'mean_half_width': float(half),
            'p95': float(np.percentile(b, 95) - np.percentile(a, 95)),
            'p95_interval': [float(np.percentile(p95, 2.5)), float(np.percentile(p95, 97.5))],
            'longer_share': float((diff > 1e-9).mean()),
            'shorter_share': float((diff < -1e-9).mean())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--episodes', type=int, default=1000)
    parser.add_argument('--epochs', type=int, default=20)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--jobs', type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument('--scenarios', default=','.join(SCENARIOS[1:]))
    parser.add_argument('--selectors', default='ssm_only,paper')
    parser.add_argument('--json', default='')
    args = parser.parse_args(argv)
    from hrc_ros.core.robot.cell import ArmCellSettings
    control_period = ArmCellSettings().control_period
    scenarios = [s for s in args.scenarios.split(',') if s]
    selectors = [s for s in args.selectors.split(',') if s]
    results, paired = {}, {}
    started = time.perf_counter()
    by_selector: dict = {}
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for scenario in scenarios:
            for selector in selectors:
                t0 = time.perf_counter()
                jobs = [(scenario, selector, s, min(s + CHUNK, args.episodes), args.epochs,
                         args.seed) for s in range(0, args.episodes, CHUNK)]
                rows = [row for part in pool.map(_chunk, jobs) for row in part]
                by_selector.setdefault(scenario, {})[selector] = rows
                figures = summary(rows, control_period)
                results.setdefault(scenario, {})[selector] = figures
                rest = figures['rest_after_event_s']
                delay = figures['stop_delay_control_periods']
                margin = figures['min_margin_m']
                print(f'{scenario:<15} {selector:<9} {figures["episodes"]} episodes: '
                      f'{figures["ssm_violations"]} violations in '
                      f'{figures["episodes_with_violations"]} episodes'
                      + (f' (< {100 * figures["violating_share_upper95"]:.2f}% at 95%)'
                         if figures['violating_share_upper95'] is not None else '')
                      + f', appearance {figures["appearance_violations"]}, contacts '
                      f'{figures["contacts"]}, breaches {figures["speed_breaches"]}, smallest '
                      'margin ' + ('-' if margin is None else f'{margin:+.3f} m')
                      + ', rest after the event ' + ('-' if rest is None else
                                                     f'{rest["mean"]:.2f} s (p95 '
                                                     f'{rest["p95"]:.2f}, max {rest["max"]:.2f})')
                      + (f', stop after an appeared skeleton <= {delay["max"]:.0f} control '
                         f'periods ({delay["appearances_inside_sp0"]} inside S_p(0))'
                         if delay else '')
                      + f'; {time.perf_counter() - t0:.0f} s', flush=True)
            base = selectors[0]
            for selector in selectors[1:]:
                d = paired_rest(by_selector[scenario][base], by_selector[scenario][selector])
                paired.setdefault(scenario, {})[f'{selector} - {base}'] = d
                if d is not None:
                    lo, hi = d['p95_interval']
                    print(f'{scenario:<15} {selector} - {base}, paired on {d["episodes"]} '
                          f'episodes: rest after the event {d["mean"]:+.3f} '
                          f'+- {d["mean_half_width"]:.3f} s (95%), p95 {d["p95"]:+.3f} s '
                          f'[{lo:+.3f}, {hi:+.3f}]; longer in {100 * d["longer_share"]:.1f}%, '
                          f'shorter in {100 * d["shorter_share"]:.1f}% of them', flush=True)
    print(f'{time.perf_counter() - started:.0f} s in all, {args.jobs} jobs, load '
          f'{os.getloadavg()[0]:.1f}')
    print(f'reproduce: python bench/ssm_scenarios.py --episodes {args.episodes} --epochs '
          f'{args.epochs} --seed {args.seed} --scenarios {",".join(scenarios)} --selectors '
          f'{",".join(selectors)}')
    if args.json:
        Path(args.json).write_text(json.dumps({'scenarios': results, 'paired': paired},
                                              indent=2) + '\n')
    bad = [(s, x) for s, by in results.items() for x, f in by.items()
           if f['ssm_violations'] or f['contacts'] or f['speed_breaches']]
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
