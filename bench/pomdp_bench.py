"""POMDP benchmark: solve time and memory, policy size, the bound gap, decision time, and the
selectors' achieved cost from the case study's first belief against the bounds.

    .venv/bin/python bench/pomdp_bench.py                        # default configuration
    .venv/bin/python bench/pomdp_bench.py --config config/fail_safe_unaware.yaml
    .venv/bin/python bench/pomdp_bench.py --skip-solve           # the shipped policy only

1. Solve (unless --skip-solve): `hrc-solve --method pomdp` in its own process (wall time and
   peak RSS of that process, numba's compile cache warm), the file's size, and the report: the
   lower and upper bound at the case study's first beliefs b_1 = initial(O_1), O_1 = 1, 2, 3,
   and the gap over all belief points. Targets: < 10 min, < 4 GB, < 20 MB, gap < 1%.
2. Decision time: `ActionSelector.select` (validation included, as the decision node calls
   it) for the pomdp, fib and paper selectors on 20,000 (b, x) pairs from the solved states;
   p50 and p99. Target: pomdp p99 < 1 ms. (The decision node's own compute figure, with the
   fault checks, is `bench/loop_latency.py --selector pomdp`.)
3. The case study's start as the POMDP sees it: the case study's task (1, 1, 3) at d = 1, the
   human drawn uniformly (so that P(h | O_1) is b_1), no further tasks, 150 epochs, the exact
   posterior, the fail-safe as the model plans it (on for the default, off for
   fail_safe_unaware, whose model counts on actions at d = 0). Every selector runs the same
   episodes; their mean discounted cost is printed
   with its 95% interval, the paired difference to pomdp, and the bounds' prediction
   -E[lower] .. -E[upper] over O_1.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from types import SimpleNamespace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CASE_TASK = (1, 1, 3, 0, 0, 0, 0, 0)
SELECTORS = ('pomdp', 'fib', 'qmdp', 'paper', 'mls', 'mdp')


def solve(config: str, out: Path) -> dict:
    script = Path(sys.executable).parent / 'hrc-solve'
    command = [str(script), '--method', 'pomdp', '--config', config, '-o', str(out), '-q']
    code = ('import resource, subprocess, sys, time, json; t = time.perf_counter(); '
            f'r = subprocess.run({command!r}, capture_output=True, text=True); '
            'print(json.dumps({"seconds": time.perf_counter() - t, "code": r.returncode, '
            '"out": r.stdout + r.stderr, "peak_kb": resource.getrusage('
            'resource.RUSAGE_CHILDREN).ru_maxrss}))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            env=os.environ.copy())
    info = json.loads(result.stdout.strip().splitlines()[-1])
    if info['code'] != 0:
        raise SystemExit(f'hrc-solve failed:\n{info["out"]}')
    return info


def decision_times(model, mdp, pomdp, rng, calls: int = 20_000) -> dict:
    from hrc_ros.core.decision.selection import ActionSelector
    alphas = pomdp.policy
    columns = rng.choice(alphas.columns, size=calls)
    beliefs = rng.dirichlet(np.full(9, 0.4), size=calls)
    observables = []
    for column in columns.tolist():
        y, d = divmod(column, 4)
        observables.append(tuple(int(model.task_grid[n][y]) for n in
                                 ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc')) + (d,))
    out = {}
    for method in ('pomdp', 'fib', 'paper'):
        selector = ActionSelector(model, mdp, method=method, pomdp=pomdp)
        for b, x in zip(beliefs[:200], observables[:200]):     # warm-up
            selector.select(b, x)
        times = np.empty(calls)
        for i, (b, x) in enumerate(zip(beliefs, observables)):
            t = time.perf_counter()
            selector.select(b, x)
            times[i] = time.perf_counter() - t
        out[method] = {'p50_us': 1e6 * float(np.percentile(times, 50)),
                       'p99_us': 1e6 * float(np.percentile(times, 99))}
    return out


def case_study_start(model, mdp, pomdp, per_h: int, epochs: int = 150) -> dict:
    from hrc_ros.core.pomdp.belief import BeliefFilter
    from hrc_ros.core.study.evaluation import BatchSimulator, paired_difference
    from hrc_ros.core.study.simulation import Scenario
    targets = pomdp.meta['report']['targets']
    p_o = BeliefFilter(model).likelihood.sum(axis=1) / 9.0
    lower = float(sum(p * t['lower'] for p, t in zip(p_o, targets)))
    upper = float(sum(p * t['upper'] for p, t in zip(p_o, targets)))
    scenarios = [Scenario((h // 3, h % 3) + CASE_TASK + (1,), (), epochs)
                 for h in range(9) for _ in range(per_h)]
    seeds = [[101, e] for e in range(len(scenarios))]
    # the model's own process: the fail-safe is part of it only when the model plans with it
    sim = BatchSimulator(model, mdp, mode='posterior', pomdp=pomdp,
                         fail_safe=model.config.fail_safe_aware)
    costs = {}
    for selector in SELECTORS:
        costs[selector] = np.concatenate([
            sim.run(scenarios[i:i + 1000], seeds[i:i + 1000], selector).discounted_cost
            for i in range(0, len(scenarios), 1000)])
    rows = {}
    for selector, c in costs.items():
        d = paired_difference(SimpleNamespace(discounted_cost=c),
                              SimpleNamespace(discounted_cost=costs['pomdp']))
        rows[selector] = {'mean': float(c.mean()),
                          'half_width': float(1.96 * c.std(ddof=1) / np.sqrt(c.size)),
                          'minus_pomdp': d}
    return {'episodes': len(scenarios), 'epochs': epochs, 'minus_lower': -lower,
            'minus_upper': -upper, 'selectors': rows}


def main() -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--config', default=str(REPO / 'config' / 'default.yaml'))
    parser.add_argument('--skip-solve', action='store_true',
                        help='measure the shipped POMDP policy of the configuration')
    parser.add_argument('--per-h', type=int, default=1000,
                        help='case-study episodes per hidden state (9 x this in all)')
    args = parser.parse_args()
    from hrc_ros.core.config import load_config
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.pomdp.solver import report_lines
    from hrc_ros.core.pomdp.policy import default_pomdp_policy_path, load_pomdp_policy
    command = ' '.join(shlex.quote(a) for a in ['.venv/bin/python', 'bench/pomdp_bench.py',
                                                *sys.argv[1:]])
    config = load_config(args.config)
    model = HRCModel(config)
    mdp = load_policy(default_policy_path(config), config)
    print(f'hrc_ros POMDP benchmark: {config.source}, {os.cpu_count()} CPUs')
    if args.skip_solve:
        path = default_pomdp_policy_path(config)
    else:
        path = Path(tempfile.mkdtemp(prefix='hrc_pomdp_')) / 'pomdp.npz'
        info = solve(args.config, path)
        print(f'solve: {info["seconds"]:.1f} s wall, peak RSS {info["peak_kb"] / 1024:.0f} MB '
              f'(targets < 600 s, < 4096 MB)')
    pomdp = load_pomdp_policy(path, config)
    print(f'policy {path}: {path.stat().st_size / 1e6:.2f} MB (target < 20 MB); gaps (target '
          '< 1% at the case study):')
    for line in report_lines(pomdp.meta['report']):
        print(f'  {line}')
    rng = np.random.default_rng(0)
    times = decision_times(model, mdp, pomdp, rng)
    for method, t in times.items():
        print(f'decision time, {method:<5} ActionSelector.select: p50 {t["p50_us"]:.1f} us, '
              f'p99 {t["p99_us"]:.1f} us' + (' (target p99 < 1000 us)' if method == 'pomdp'
                                             else ''))
    start = case_study_start(model, mdp, pomdp, args.per_h)
    print(f'case study start, {start["episodes"]} episodes x {start["epochs"]} epochs (h '
          f'uniform, no new tasks, posterior belief, fail-safe '
          f'{"on" if config.fail_safe_aware else "off"}): bounds predict an optimal cost in '
          f'[{start["minus_upper"]:.3f}, {start["minus_lower"]:.3f}]')
    for selector, row in start['selectors'].items():
        d = row['minus_pomdp']
        print(f'  {selector:<6} {row["mean"]:8.3f} ± {row["half_width"]:.3f}'
              + ('' if selector == 'pomdp' else
                 f'   - pomdp {d["mean"]:+.3f} ± {d["half_width"]:.3f} '
                 f'[{d["low"]:+.3f}, {d["high"]:+.3f}]'))
    print(f'reproduce: {command}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
