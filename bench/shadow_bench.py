"""The promotion check against the truth: coverage, false promotions and power, on generated
cells whose truth is computed in the world they came from.

    nice -n 10 .venv/bin/python bench/shadow_bench.py --results out/shadow.jsonl   # 250 cells
    nice -n 10 .venv/bin/python bench/shadow_bench.py --results F --shard 1/2      # half of them
    .venv/bin/python bench/shadow_bench.py --table --results F                     # the table
    nice -n 10 .venv/bin/python bench/shadow_bench.py --drift --results F2 --episodes 200 \
        --directions unchanged                          # the defaults' figure (run: on_drift)
    nice -n 10 .venv/bin/python bench/shadow_bench.py --drift --check-all --results F3 \
        --episodes 200                                  # power on the defaults

A cell runs the default configuration and its shipped policy (the paper selector) and has
`--episodes` x 50 recorded epochs (the running policy with 20% exploration, hrc-evaluate's
random task streams: what `generate:` makes), in a world that differs from the default by a
known amount: `amount` t of the way from the default's people to those of a direction,
every probability of the direction's families mixed (1 - t) default + t direction:

- `unchanged` (t = 0): the default people themselves; a promotion there is a false one;
- `reluctant` (t in 0.25, 0.5, 0.75, 1): people who decline requests and drift closer (the
  tests' drifted cell, bench/fleet_bench.py);
- `mild` (t in 0.25 .. 1): only p_accept lower (0.2 / 0.65 / 0.95 at t = 1, the
  default's 0.3 / 0.8 / 0.95).

Every cell goes through the plant's own stages (`core/plant/stages.py`) as hrc-fleet runs them
with `run: always` (no drift gate: the check alone is measured): `read`, `fit_point` +
`fit_summary` + `solve_mdp` (the new policy), `shadow` (in-sample, `evaluate.episodes` 1000)
and `refits` (`--refits` of them, draws 0..R-1: each a resample of the episodes fitted and
solved as the cell was, and its error). The truth, which no rule can see: the new policy and
the running one over `--truth-episodes` other paired episodes in the world the recordings
were made in (`hrc-evaluate --true-config`'s machinery), every metric of the check; and the
regret of each against the policy solved for that world (in the default world, the running
policy itself).

The table (`--table`, printed at the end of a run too), per number of refits R (the first R
of each cell's, so the columns are paired cell by cell) and over the cells done:

- coverage: the share of cells whose 95% interval of the cost difference holds the true one,
  overall, in unchanged and in changed cells (95% Wilson intervals); the truth has its own
  noise (its 95% half-width is printed; it makes the measured coverage a little low);
- false promotions: unchanged cells promoted (and, below the table, the true differences of
  those promoted: the shipped policy is not the default world's optimum under the selector,
  so a refit of an unchanged cell can be truly cheaper);
- power: cells truly better by >= 1 cost unit per episode promoted, and by bands of the truth;
- wrong promotions: changed cells promoted whose new policy is truly not cheaper;
- the in-sample rule (the in-sample interval over the episodes alone, the old rule before the
  held-out check) on the same cells, for comparison.

`--drift` measures the plant on its defaults (`run: on_drift`), where a cell is checked only
when the drift test calls drift: each cell's drift test as the plant runs it (the last
`drift.window` epochs of its recordings, the default `simulations`, alpha 0.05; the null
simulations seeded from the cell's index, as the plant seeds them from a cell's `seed`), and
the check above only for the cells where it calls drift. Its table: drift called,
and promotions (the check's, 10 refits) on the defaults, both per world over all the cells run.
`--drift --check-all` runs the check on every cell as well, so that the truth of the cells the
drift test lets pass is known: its table adds false promotions, power and wrong promotions on
the defaults beside the check alone's, over the same cells.

Resumable and shardable: a cell is its index (its world, amount and seeds follow from it);
`--results` gets one JSON line per cell as it finishes, and a run skips the cells already
there; `--shard K/N` runs the cells whose index is K - 1 modulo N. `--cpus` worker processes
(one cell each, numba on one thread).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from datetime import datetime, timezone
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DIRECTIONS = {
    'reluctant': {'p_accept': [0.05, 0.35, 0.7],
                  'p_delta': [[0.05, 0.65, 0.30], [0.05, 0.55, 0.40], [0.02, 0.38, 0.60]]},
    'mild': {'p_accept': [0.2, 0.65, 0.95]},
}
AMOUNTS = (0.25, 0.5, 0.75, 1.0)
CELLS = 250           # 100 unchanged, then the changed ones in turn
UNCHANGED_EVERY = 5   # cells 0, 5, 10, ... and 1, 6, 11, ... are unchanged (2 in 5)
EVALUATE = {'episodes': 1000, 'epochs': 50, 'task_rate': 0.2}
FIT = {'bootstrap': 0, 'starts': 2, 'tol': 1e-7, 'max_iter': 1000, 'hold': (),
       'window': None, 'prior': False, 'stream': False}


def cell_of(index: int) -> dict:
    """The world, amount and seeds of cell `index` (the same on every run and shard)."""
    if index % UNCHANGED_EVERY in (0, 1):
        return {'index': index, 'direction': 'unchanged', 'amount': 0.0, 'seed': index}
    changed = index - 2 * (index // UNCHANGED_EVERY) - 2
    direction = ('reluctant', 'mild')[changed % 2]
    amount = AMOUNTS[(changed // 2) % len(AMOUNTS)]
    return {'index': index, 'direction': direction, 'amount': amount, 'seed': index}


def world_of(cell: dict) -> dict:
    """The world's overrides: each family of the direction mixed with the default's."""
    if cell['direction'] == 'unchanged':
        return {}
    from hrc_ros.core.config import load_config
    from hrc_ros.core.paths import default_config_path
    default = load_config(default_config_path()).data['model']
    t = cell['amount']
    target = DIRECTIONS[cell['direction']]
    return {'model': {k: (np.asarray(default[k]) * (1 - t) + np.asarray(v) * t).tolist()
                      for k, v in target.items()}}


def recorded(cell: dict, episodes: int, window: int = 100_000) -> tuple:
    """The cell's running configuration and policy, its world's overrides and its generated
    recordings read as the plant reads them (`stages.read`; `window`: the drift test's last
    epochs, which only the drift test reads)."""
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.paths import default_config_path
    from hrc_ros.core.plant import stages
    base = load_config(default_config_path())
    policy = load_policy(default_policy_path(base), base)
    world = world_of(cell)
    generate = {'world': world, 'episodes': episodes, 'epochs': 50, 'explore': 0.2,
                'seed': 1000 + cell['seed']}
    _, text = stages.generate(base, policy, generate, 'paper')
    with tempfile.TemporaryDirectory(prefix='shadow_bench_') as folder:
        path = Path(folder) / 'cell.csv'
        path.write_text(text)
        _, data = stages.read([str(path)], base.rho, base.sigma, '/', window)
    return base, policy, world, data


def run_cell(cell: dict, episodes: int, refits: int, truth_episodes: int,
             recordings: tuple | None = None) -> dict:
    """The plant's check of one generated cell and its truth (module docstring);
    `recordings`: the cell's `recorded` when the caller has them already."""
    import numba

    from hrc_ros.core.mdp.solver import solve
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.plant import stages
    numba.set_num_threads(1)
    t0 = time.perf_counter()
    seed = cell['seed']
    base, policy, world, data = recordings or recorded(cell, episodes)
    running = {'config': base, 'policy': policy, 'pomdp': None}
    _, point = stages.fit_point(data, base, FIT, seed)
    _, summary = stages.fit_summary(point, base, ['generated'], data, FIT, seed)
    _, mdp = stages.solve_mdp(summary, None)
    settings = dict(EVALUATE, refits=refits)
    inside, _ = stages.shadow(running, summary, mdp, None, 'paper', settings, seed)
    t_refits = time.perf_counter()
    done, _ = stages.refits(running, data, point, summary, mdp, base, 'paper', FIT, None,
                            settings, seed, None, list(range(refits)))
    t_refits = time.perf_counter() - t_refits
    # the truth: the new policy and the running one in the world the recordings came from
    true_world = stages.world_config(base, world)
    truth_settings = dict(EVALUATE, episodes=truth_episodes)
    true = stages._both_in(true_world, running, summary['config'], mdp['result'], None,
                           'paper', truth_settings, seed + 10_000)
    truth = {m: stages.paired(*true[m]) for m in stages.CHECK_METRICS}
    if world:
        optimum = solve(HRCModel(true_world))
        best = stages._both_in(true_world, running, true_world, optimum, None, 'paper',
                               truth_settings, seed + 10_000)['discounted_cost'][0]
    else:       # the default world's optimum is the running policy, solved for it
        best = true['discounted_cost'][1]
    regret = {'running': float(np.mean(true['discounted_cost'][1] - best)),
              'new': float(np.mean(true['discounted_cost'][0] - best))}
    return {**cell, 'episodes': episodes, 'epochs': data['all'].epochs,
            'in_sample': {m: inside[m] for m in stages.CHECK_METRICS},
            'rows': done['rows'], 'truth': truth, 'regret': regret,
            'seconds': time.perf_counter() - t0, 'refit_seconds': t_refits}


def drift_cell(cell: dict, episodes: int, refits: int, truth_episodes: int,
               check_all: bool = False) -> dict:
    """The plant's drift test of the cell's recordings on the defaults (`spec.SECTIONS`'
    drift: the window, the simulations, alpha, the plant's seeds for the cell), and, when it
    calls drift (`check_all`: always, so that the truth of the cells it lets pass is known
    too), the check (`run_cell`, on the same recordings, read once) under 'check'."""
    import numba

    from hrc_ros.core.plant import drift, stages
    from hrc_ros.core.plant.pipeline import seeds
    from hrc_ros.core.plant.spec import SECTIONS
    numba.set_num_threads(1)
    t0 = time.perf_counter()
    settings = {k: default for k, (_, default) in SECTIONS['drift'].items()}
    recordings = recorded(cell, episodes, settings['window'])
    base, _, _, data = recordings
    observed, pi = stages.drift_observed(data, base, settings)
    null: list = []
    if not observed['impossible']:
        for chunk in seeds(cell['seed'], 1, settings['simulations']):
            null += stages.drift_null(data, base, pi, settings, chunk)[0]['statistics']
    p = drift.p_value(observed['statistic'], null) if null else 0.0
    result = {**cell, 'episodes': episodes, 'window': settings['window'],
              'simulations': len(null), 'alpha': settings['alpha'],
              'statistic': observed['statistic'], 'drift_p': p,
              'drift': p < settings['alpha'], 'drift_seconds': time.perf_counter() - t0}
    if result['drift'] or check_all:
        result['check'] = run_cell(cell, episodes, refits, truth_episodes, recordings)
    result['check_all'] = check_all
    result['seconds'] = time.perf_counter() - t0
    return result


def true_cost(r: dict) -> float:
    """A checked cell's true cost difference, new - running, per episode."""
    return r['truth']['discounted_cost']['mean']


def checked(r: dict, refits: int) -> tuple[str, dict]:
    """The check of a --drift cell decided on its first `refits` refits (all, if fewer)."""
    return decisions(r['check'], min(refits, len(r['check']['rows'])))


def covers(figures: dict, truth: float) -> bool:
    """The 95% interval of the cost difference holds the truth."""
    m = figures['discounted_cost']
    return m['low'] <= truth <= m['high']


def drift_table(results: list[dict], refits: int = 10) -> None:
    """Drift called and promotions on the defaults (a promotion needs drift and the check)."""
    if not results:
        print('no cells run yet')
        return
    first = results[0]
    print(f'{len(results)} cells, the drift test on the defaults (window {first["window"]} '
          f'epochs, {max(r["simulations"] for r in results)} simulations, alpha '
          f'{first["alpha"]:g}); a cell is promoted when the drift test calls drift and the '
          f'check ({refits} refits) promotes\n')
    print('| world | amount | cells | drift called | promoted on the defaults | of those, truly '
          'not cheaper |')
    print('|---|---|---|---|---|---|')
    for direction, amount in sorted({(r['direction'], r['amount']) for r in results}):
        rs = [r for r in results if (r['direction'], r['amount']) == (direction, amount)]
        promoted = [r for r in rs if r['drift'] and checked(r, refits)[0] == 'promote']
        worse = sum(true_cost(r['check']) >= 0 for r in promoted)
        print(f'| {direction} | {amount:g} | {len(rs)} | '
              f'{wilson(sum(r["drift"] for r in rs), len(rs))} | '
              f'{wilson(len(promoted), len(rs))} | {worse} |')
    known = [r for r in results if r.get('check_all')]
    if known:
        # --check-all: the check ran on every cell, so the truth of the cells the drift test
        # let pass is known, and power on the defaults can be counted over all of them
        def made(r):
            return checked(r, refits)[0]

        def on_defaults(r):
            return r['drift'] and made(r) == 'promote'
        better = [r for r in known if true_cost(r['check']) <= -1.0]
        unchanged = [r for r in known if r['direction'] == 'unchanged']
        changed = [r for r in known if r['direction'] != 'unchanged']
        not_cheaper = [r for r in changed if true_cost(r['check']) >= 0]
        print(f'\nWith the truth of every cell ({len(known)} cells checked whatever the drift '
              f'test said, {len(better)} truly better by >= 1.0 per episode):\n')
        print('| run mode | false promotions (unchanged) | power (truly better by >= 1.0) | '
              'wrong promotions (changed, truly not cheaper) |')
        print('|---|---|---|---|')
        for name, rule in (('on_drift (the defaults)', on_defaults),
                           ('always (the check alone)', lambda r: made(r) == 'promote')):
            print(f'| {name} | {wilson(sum(map(rule, unchanged)), len(unchanged))} | '
                  f'{wilson(sum(map(rule, better)), len(better))} | '
                  f'{wilson(sum(map(rule, not_cheaper)), len(not_cheaper))} |')
        def covered(rs):
            return wilson(sum(covers(checked(r, refits)[1], true_cost(r['check'])) for r in rs),
                          len(rs))
        print(f'\nCoverage of the check\'s 95% interval (the same in both modes): all '
              f'{covered(known)}, unchanged {covered(unchanged)}, changed {covered(changed)}')
        missed = [r for r in better if not on_defaults(r)]
        print('Truly better by >= 1.0 and not promoted on the defaults: '
              + (', '.join(f'cell {r["index"]} ({r["direction"]} {r["amount"]:g}, true '
                           f'{true_cost(r["check"]):+.2f}, drift p '
                           f'{r["drift_p"]:.3f}, check: {made(r)})' for r in missed)
                 or 'none'))
    ps = np.array([r['drift_p'] for r in results])
    seconds = sorted(r['drift_seconds'] for r in results)
    print(f'\ndrift p quartiles {", ".join(f"{q:.3f}" for q in np.percentile(ps, [25, 50, 75]))}'
          f'; seconds per cell for its recordings and drift test, one CPU: median '
          f'{seconds[len(seconds) // 2]:.0f}, the slowest {seconds[-1]:.0f}')
    for r in results:
        if 'check' in r:
            c = checked(r, refits)
            m = c[1]['discounted_cost']
            print(f'  cell {r["index"]} ({r["direction"]} {r["amount"]:g}): p = '
                  f'{r["drift_p"]:.3f}{"" if r["drift"] else " (no drift)"}, check: {c[0]} '
                  f'(estimate {m["mean"]:+.2f} '
                  f'[{m["low"]:+.2f}, {m["high"]:+.2f}], true '
                  f'{true_cost(r["check"]):+.2f})')


# -- the table --------------------------------------------------------------------------------
def wilson(k: int, n: int) -> str:
    from hrc_ros.core.plant.stages import own_interval
    if not n:
        return '-'
    low, high = own_interval(k / n, n)
    return f'{k}/{n} = {100 * k / n:.1f}% [{100 * low:.1f}, {100 * high:.1f}]'


def decisions(r: dict, refits: int | None, guards=()) -> tuple[str, dict]:
    """The plant's rule on the cell's figures with its first `refits` refits (None: the
    in-sample rule, the interval over the episodes alone)."""
    from hrc_ros.core.plant import check
    rows = [] if refits is None else r['rows'][:refits]
    figures = check.combine(r['in_sample'], rows)
    if refits is None:
        for m in figures.values():
            m['refits'] = 2          # the old rule: decide on the in-sample interval
    return check.decide(figures, guards)[0], figures


def table(results: list[dict], refit_counts=(5, 10, 20)) -> None:
    refit_counts = [k for k in refit_counts if all(len(r['rows']) >= k for r in results)]
    unchanged = [r for r in results if r['direction'] == 'unchanged']
    changed = [r for r in results if r['direction'] != 'unchanged']
    better = [r for r in results if true_cost(r) <= -1.0]
    not_cheaper = [r for r in changed if true_cost(r) >= 0]
    truth_half = np.median([r['truth']['discounted_cost']['half_width'] for r in results])
    print(f'{len(results)} cells ({len(unchanged)} unchanged, {len(changed)} changed; '
          f'{len(better)} truly better by >= 1.0 per episode); the truth\'s own 95% half-width '
          f'{truth_half:.3f} (median)\n')
    print('| rule | coverage, all | unchanged | changed | false promotions (unchanged) | '
          'power (truly better by >= 1.0) | wrong promotions (changed, truly not cheaper) |')
    print('|---|---|---|---|---|---|---|')
    for refits in [None] + refit_counts:
        name = 'in-sample (episodes only)' if refits is None else f'{refits} refits'
        made = {id(r): decisions(r, refits) for r in results}

        def covered(rs, made=made):
            return wilson(sum(covers(made[id(r)][1], true_cost(r)) for r in rs), len(rs))

        def promoted(rs, made=made):
            return wilson(sum(made[id(r)][0] == 'promote' for r in rs), len(rs))
        print(f'| {name} | {covered(results)} | {covered(unchanged)} | {covered(changed)} | '
              f'{promoted(unchanged)} | {promoted(better)} | {promoted(not_cheaper)} |')
    if not refit_counts:
        return
    k = refit_counts[-1] if 10 not in refit_counts else 10
    print(f'\nPower by the true difference ({k} refits):\n')
    print('| true cost difference per episode | cells | promoted |')
    print('|---|---|---|')
    for low, high in ((-math.inf, -3.0), (-3.0, -2.0), (-2.0, -1.0), (-1.0, 0.0),
                      (0.0, math.inf)):
        rs = [r for r in results if low < true_cost(r) <= high]
        print(f'| ({low:+.0f}, {high:+.0f}] | {len(rs)} | '
              f'{wilson(sum(decisions(r, k)[0] == "promote" for r in rs), len(rs))} |')
    print(f'\nBy world ({k} refits): mean in-sample / estimate / true difference, promoted\n')
    print('| world | amount | cells | in-sample | estimate | true | true regret of the running '
          'policy / the new one | promoted |')
    print('|---|---|---|---|---|---|---|---|')
    groups = sorted({(r['direction'], r['amount']) for r in results})
    for direction, amount in groups:
        rs = [r for r in results if (r['direction'], r['amount']) == (direction, amount)]
        est = np.mean([decisions(r, k)[1]['discounted_cost']['mean'] for r in rs])
        print(f'| {direction} | {amount:g} | {len(rs)} | '
              f'{np.mean([r["in_sample"]["discounted_cost"]["mean"] for r in rs]):+.2f} | '
              f'{est:+.2f} | {np.mean([true_cost(r) for r in rs]):+.2f}'
              f' | {np.mean([r["regret"]["running"] for r in rs]):+.2f} / '
              f'{np.mean([r["regret"]["new"] for r in rs]):+.2f} | '
              f'{wilson(sum(decisions(r, k)[0] == "promote" for r in rs), len(rs))} |')
    z = []
    for r in results:
        m = decisions(r, k)[1]['discounted_cost']
        z.append((m['mean'] - true_cost(r)) / (m['half_width'] / 1.96))
    z = np.array(z)
    print(f'\nThe estimate\'s error in units of its own standard error ({k} refits): mean '
          f'{z.mean():+.2f}, sd {z.std(ddof=1):.2f}, quartiles '
          + ', '.join(f'{q:+.2f}' for q in np.percentile(z, [25, 50, 75])))
    false = [true_cost(r) for r in unchanged
             if decisions(r, k)[0] == 'promote']
    print(f'Unchanged cells promoted ({k} refits): {len(false)}, of which truly not cheaper '
          f'(the truth\'s mean >= 0): {sum(t >= 0 for t in false)}; their true differences '
          + ', '.join(f'{t:+.2f}' for t in false))
    guard = sum(decisions(r, k)[0] == 'promote'
                and r['truth']['collision_epochs']['low'] > 0 for r in results)
    print(f'Promoted although truly more collision epochs (the truth\'s interval above zero): '
          f'{guard} of {sum(decisions(r, k)[0] == "promote" for r in results)} promoted')
    seconds = sorted(r['seconds'] for r in results)
    refit = sorted(r['refit_seconds'] / max(1, len(r['rows'])) for r in results)
    print(f'Seconds per cell, one CPU each: median {seconds[len(seconds) // 2]:.0f} (a refit: '
          f'median {refit[len(refit) // 2]:.1f}), the slowest {seconds[-1]:.0f}')


# -- running ----------------------------------------------------------------------------------
def append(path: Path, line: str) -> None:
    """One line, in one write to a file opened for appending: shards running side by side
    into the same file never interleave their lines."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, line.encode())
    finally:
        os.close(fd)


def load(path: Path, drift: bool = False) -> list[dict]:
    """The cells of a results file; a file of the other mode (--drift or not) is refused."""
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass        # a line cut by a stopped run: that cell runs again
    other = [r['index'] for r in out if ('drift_p' in r) != drift]
    if other:
        sys.exit(f'shadow_bench: {path} holds cells of the {"check" if drift else "--drift"} '
                 f'mode ({len(other)}, cell {other[0]} first): give this mode a file of its own')
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--results', required=True, help='JSON lines, appended and resumed')
    parser.add_argument('--cells', type=int, default=CELLS)
    parser.add_argument('--shard', default='1/1', help='K/N: the cells K - 1 modulo N')
    parser.add_argument('--episodes', type=int, default=20, help='recorded episodes of 50')
    parser.add_argument('--refits', type=int, default=20)
    parser.add_argument('--truth-episodes', type=int, default=4000)
    parser.add_argument('--cpus', type=int, default=2)
    parser.add_argument('--table', action='store_true', help='only print the table')
    parser.add_argument('--drift', action='store_true',
                        help='the defaults (run: on_drift): the drift test of every cell, the '
                        'check only where it calls drift')
    parser.add_argument('--check-all', action='store_true',
                        help='with --drift: the check on every cell, also where the drift test '
                        'calls none, so that power on the defaults is counted over the truth '
                        'of every cell')
    parser.add_argument('--directions', default='unchanged,reluctant,mild',
                        help='the worlds whose cells run (comma-separated)')
    args = parser.parse_args(argv)
    path = Path(args.results)
    show = drift_table if args.drift else table
    if args.table:
        show(load(path, args.drift))
        return 0
    k, n = (int(v) for v in args.shard.split('/'))
    done = {r['index'] for r in load(path, args.drift)}
    directions = {d.strip() for d in args.directions.split(',')}
    unknown = directions - {'unchanged', *DIRECTIONS}
    if unknown:
        parser.error(f'--directions: no world {", ".join(sorted(unknown))} (unchanged, '
                     f'{", ".join(DIRECTIONS)})')
    todo = [cell_of(i) for i in range(args.cells) if i % n == k - 1 and i not in done
            and cell_of(i)['direction'] in directions]
    if args.check_all and not args.drift:
        parser.error('--check-all goes with --drift (without it every cell is checked anyway)')
    work = partial(drift_cell, check_all=True) if args.check_all else (
        drift_cell if args.drift else run_cell)
    print(f'command: nice -n {os.nice(0)} .venv/bin/python bench/shadow_bench.py '
          f'{" ".join(sys.argv[1:] if argv is None else argv)}')
    print(f'started {datetime.now(timezone.utc).isoformat(timespec="minutes")}, load average '
          f'{os.getloadavg()[0]:.1f}; {len(todo)} cells to run, {len(done)} already done',
          flush=True)
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.cpus) as pool:
        pending = {pool.submit(work, c, args.episodes, args.refits, args.truth_episodes): c
                   for c in todo}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in finished:
                cell = pending.pop(future)
                try:
                    r = future.result()
                except Exception as exc:   # noqa: BLE001 - one cell's failure is printed
                    print(f'  cell {cell["index"]} failed: {type(exc).__name__}: {exc}',
                          flush=True)
                    continue
                append(path, json.dumps(r) + '\n')
                if args.drift:
                    print(f'  {r["index"]:>3} {r["direction"]:<9} {r["amount"]:.2f}: drift p '
                          f'{r["drift_p"]:.3f}' + (f', checked: {decisions(r["check"], 10)[0]}'
                                                   if r['drift'] else '')
                          + f'  {r["seconds"]:.0f} s', flush=True)
                    continue
                _, m = decisions(r, min(10, len(r['rows'])))
                c = m['discounted_cost']
                print(f'  {r["index"]:>3} {r["direction"]:<9} {r["amount"]:.2f}: in-sample '
                      f'{c["in_sample"]:+6.2f}, estimate {c["mean"]:+6.2f} [{c["low"]:+6.2f}, '
                      f'{c["high"]:+6.2f}], true {true_cost(r):+6.2f}'
                      f'  {r["seconds"]:.0f} s', flush=True)
    print(f'\n{len(todo)} cells in {time.perf_counter() - t0:.0f} s on {args.cpus} CPUs, load '
          f'average at the end {os.getloadavg()[0]:.1f}\n')
    show(load(path, args.drift))
    return 0


if __name__ == '__main__':
    sys.exit(main())
