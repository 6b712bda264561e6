"""The promotion rule's error rates: the in-sample shadow check against the held-out one.

    nice -n 10 .venv/bin/python bench/shadow_bench.py                 # 100 / 30 / 20 cells
    nice -n 10 .venv/bin/python bench/shadow_bench.py --minutes 60 --results cells.jsonl

Each simulated cell runs the default configuration and its shipped policy and has 1000
recorded epochs (20 episodes of 50, the paper selector with 20% exploration, hrc-evaluate's
random task streams: what `generate:` makes), in one of three worlds:

- `unchanged`: the default people themselves; a promotion is a false promotion;
- `reluctant`: people who decline most requests and drift closer (the tests' drifted cell);
- `mild`: only p_accept lower (0.2 / 0.65 / 0.95 against 0.3 / 0.8 / 0.99).

Every cell goes through the stages of `core/plant/stages.py` as hrc-fleet runs them with `run:
always` (no drift gate: the rule alone is measured), without the bootstrap and the plots, which
do not enter the decision: `read`, `fit_point` + `fit_summary` + `solve_mdp` (the new policy),
`shadow` (in-sample: both policies in the world fitted from all 1000 epochs), `fold` x 2 and
`heldout` (the held-out check), `evaluate: {episodes: 1000, epochs: 50}`. The rule
(`pipeline.decide`) is then applied to three sets of figures of the same cell: in-sample (the
old rule), held out in the two halves' fitted worlds (`evaluate.worlds: 0`, the default) and
held out in 10 bootstrap worlds of each half (`evaluate.worlds: 10`), so the columns are paired
cell by cell. Printed per world: the share of cells each rule promotes with its 95% Wilson
interval, the cells where the rules disagree (McNemar's discordant pairs), and the mean cost
differences. One Ray task per cell on `--cpus` CPUs; every seed comes from the cell's index, so
a run is reproducible.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

os.environ.setdefault('RAY_worker_niceness', '0')
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fleet_bench import MILD, RELUCTANT, wilson  # noqa: E402

WORLDS = {'unchanged': {}, 'reluctant': RELUCTANT, 'mild': MILD}
FIT = {'bootstrap': 0, 'starts': 2, 'tol': 1e-7, 'max_iter': 1000, 'hold': (),
       'window': None}
EVALUATE = {'episodes': 1000, 'epochs': 50, 'task_rate': 0.2, 'worlds': 10}


def one_cell(world: str, seed: int) -> dict:
    """Both rules' figures and decisions for one generated cell (module docstring)."""
    import numba

    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.paths import default_config_path
    from hrc_ros.core.plant import stages
    from hrc_ros.core.plant.pipeline import decide
    numba.set_num_threads(1)
    t0 = time.perf_counter()
    base = load_config(default_config_path())
    policy = load_policy(default_policy_path(base), base)
    running = {'config': base, 'policy': policy, 'pomdp': None}
    generate = {'world': WORLDS[world], 'episodes': 20, 'epochs': 50, 'explore': 0.2,
                'seed': 1000 + seed}
    _, text = stages.generate(base, policy, generate, 'paper')
    with tempfile.TemporaryDirectory(prefix='shadow_bench_') as folder:
        path = Path(folder) / 'cell.csv'
        path.write_text(text)
        _, data = stages.read([str(path)], base.rho, base.sigma, '/', 1000)
    _, point = stages.fit_point(data, base, FIT, seed)
    _, summary = stages.fit_summary(point, base, ['generated'])
    _, mdp = stages.solve_mdp(summary, None)
    inside, _ = stages.shadow(running, summary, mdp, None, 'paper', EVALUATE, seed)
    folds = [stages.fold(data, half, base, FIT, seed, None, None, EVALUATE['worlds'])[1]
             for half in (0, 1)]
    held, _ = stages.heldout(running, *folds, 'paper', EVALUATE, seed)
    point, _ = stages.heldout(running, *({**f, 'worlds': []} for f in folds), 'paper',
                              EVALUATE, seed)                      # evaluate.worlds: 0
    each = all(decide({**f, 'episodes': point['episodes']})[0] == 'promote'
               for f in point['folds'])
    # the truth, which no rule can see: the new policy and the running one in the world the
    # recordings were made in, on other episodes
    true = stages._both_in(stages.world_config(base, WORLDS[world]), running,
                           summary['config'], mdp['result'], None, 'paper', EVALUATE,
                           seed + 10_000)
    truth = {metric: stages.paired(*true[metric]) for metric in stages.SHADOW_METRICS}
    truth['episodes'] = EVALUATE['episodes']
    rules = (('in_sample', inside), ('held_out_point', point), ('held_out', held))
    return {'world': world, 'seed': seed, 'seconds': time.perf_counter() - t0,
            **{rule: decide(figures)[0] for rule, figures in rules},
            **{f'cost_{rule}': figures['discounted_cost'] for rule, figures in rules},
            'held_out_each': 'promote' if each and decide(point)[0] == 'promote' else 'keep',
            'truth': decide(truth)[0], 'cost_truth': truth['discounted_cost']}


COLUMNS = {'in_sample': 'in-sample rule (old)',
           'held_out_point': 'held out, point worlds (worlds: 0)',
           'held_out_each': 'held out, point worlds, each fold alone too',
           'held_out': 'held out, 10 bootstrap worlds (worlds: 10)',
           'truth': 'the rule in the true world'}


def _ci(m: dict) -> str:
    return f'{m["mean"]:+.2f} [{m["low"]:+.2f}, {m["high"]:+.2f}]'


def interrupted(args, t0: float) -> bool:
    """--minutes spent: stop waiting and report the cells done (said in the output)."""
    if args.minutes and time.perf_counter() - t0 > 60 * args.minutes:
        print(f'stopped after {args.minutes} minutes: the table is of the cells done')
        return True
    return False


def table(results: list) -> None:
    """The rates per world (module docstring) of the cells in `results`."""
    print('| world | cells | ' + ' | '.join(f'{COLUMNS[c]}: promoted (95%)' for c in COLUMNS)
          + ' | promoted by the in-sample rule only / by the held-out one (worlds: 0) only | '
          'mean cost difference in-sample / held out (worlds: 0) / (worlds: 10) / true |')
    print('|---|---|' + '---|' * (len(COLUMNS) + 2))
    for world in WORLDS:
        rs = [r for r in results if r['world'] == world]
        if not rs:
            continue
        n = len(rs)
        row = [world, str(n)]
        for rule in COLUMNS:
            k = sum(r[rule] == 'promote' for r in rs)
            low, high = wilson(k, n)
            row.append(f'{k} = {100 * k / n:.1f}% [{100 * low:.1f}%, {100 * high:.1f}%]')
        only_in = sum(r['in_sample'] == 'promote' != r['held_out_point'] for r in rs)
        only_out = sum(r['held_out_point'] == 'promote' != r['in_sample'] for r in rs)
        row.append(f'{only_in} / {only_out}')
        row.append(' / '.join(f'{sum(r["cost_" + c]["mean"] for r in rs) / n:+.2f}'
                              for c in COLUMNS if 'cost_' + c in rs[0]))
        print('| ' + ' | '.join(row) + ' |')
    print('\nAgainst the truth (the rule on 1000 paired episodes in the world the recordings '
          'were made in, which no rule can see), all cells:')
    print('| rule | promoted when the truth says promote | promoted when the truth says keep |')
    print('|---|---|---|')
    for rule in list(COLUMNS)[:-1]:
        row = [COLUMNS[rule]]
        for verdict in ('promote', 'keep'):
            rs = [r for r in results if r['truth'] == verdict]
            k = sum(r[rule] == 'promote' for r in rs)
            low, high = wilson(k, len(rs)) if rs else (float('nan'),) * 2
            row.append(f'{k} of {len(rs)} [{100 * low:.1f}%, {100 * high:.1f}%]')
        print('| ' + ' | '.join(row) + ' |')
    seconds = sorted(r['seconds'] for r in results)
    print(f'(seconds per cell, one CPU each: median {seconds[len(seconds) // 2]:.0f}, the '
          f'slowest {seconds[-1]:.0f})')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--unchanged', type=int, default=100)
    parser.add_argument('--drifted', type=int, default=30, help='cells of reluctant people')
    parser.add_argument('--mild', type=int, default=20)
    parser.add_argument('--cpus', type=int, default=2)
    parser.add_argument('--results', default=None,
                        help='append each cell\'s figures to this file (JSON lines)')
    parser.add_argument('--minutes', type=float, default=0,
                        help='report the cells done after this long (default: all cells)')
    parser.add_argument('--table', default=None, metavar='RESULTS',
                        help='only print the table of a --results file')
    args = parser.parse_args(argv)
    if args.table:
        table([json.loads(line) for line in Path(args.table).read_text().splitlines()])
        return 0
    print(f'command: nice -n 10 .venv/bin/python bench/shadow_bench.py '
          f'{" ".join(sys.argv[1:])}'.rstrip())
    print(f'started {datetime.now(timezone.utc).isoformat(timespec="minutes")}, load average '
          f'{os.getloadavg()[0]:.1f}', flush=True)
    import ray
    ray.init(num_cpus=args.cpus, include_dashboard=False, logging_level='warning')
    task = ray.remote(one_cell)
    t0 = time.perf_counter()
    try:
        counts = {'unchanged': args.unchanged, 'reluctant': args.drifted, 'mild': args.mild}
        # interleaved, so that a run stopped early (Ctrl-C: the table of the cells done) has
        # every world in its proportion
        cells = sorted(((w, s) for w, n in counts.items() for s in range(n)),
                       key=lambda c: (c[1] + 0.5) / counts[c[0]])
        pending = {task.remote(w, s): (w, s) for w, s in cells}
        results = []
        while pending and not interrupted(args, t0):
            ready, _ = ray.wait(list(pending), num_returns=1)
            r = ray.get(ready[0])
            del pending[ready[0]]
            results.append(r)
            if args.results:
                with open(args.results, 'a') as out:
                    out.write(json.dumps(r) + '\n')
            print(f'  {r["world"]:<9} seed {r["seed"]:>3}: '
                  + '  '.join(f'{rule} {r[rule]:<7}' + (f' ({_ci(r["cost_" + rule])})'
                                                           if 'cost_' + rule in r else '')
                              for rule in COLUMNS) + f'  {r["seconds"]:.0f} s', flush=True)
    finally:
        ray.shutdown()
    print(f'\n{len(results)} cells in {time.perf_counter() - t0:.0f} s on {args.cpus} CPUs, '
          f'load average at the end {os.getloadavg()[0]:.1f}')
    table(results)
    return 0


if __name__ == '__main__':
    sys.exit(main())
