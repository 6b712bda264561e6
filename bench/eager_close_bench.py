"""Issue 35's first case, against the truth: people who accept readily and drift closer, where
planning with the default costs a regret of about 3 per episode and the world's own optimal
policy refuses more requests than the running one (so a fixed guard on refused requests would
block the optimum itself).

    nice -n 5 .venv/bin/python bench/eager_close_bench.py [--seeds 3,4] [--out DIR]

Per recording seed, a plant cell of 80 generated episodes of 50 epochs in that world (the
cell of test_fleet.py's
`test_a_truly_better_cell_is_promoted_and_a_cell_of_the_default_world_kept`, `run: always`,
the plant's defaults otherwise) runs through `hrc-fleet run --serial`; then the
promoted (or kept) policy, the running one and the world's optimum (the MDP solved for the
world) are evaluated in that world on the same 1000 paired episodes (`hrc-evaluate
--true-config`'s machinery, seed 10003): the plant's decision and estimate beside the true
difference, each policy's regret against the optimum, and the refused requests per episode.
About 45 s a seed and 20 s for the truth on one core.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

EAGER_CLOSE = {'model': {'p_accept': [0.7, 0.95, 0.99],
                         'p_delta': [[0.05, 0.65, 0.30], [0.05, 0.55, 0.40],
                                     [0.02, 0.38, 0.60]]}}
TRUTH = {'episodes': 1000, 'epochs': 50, 'task_rate': 0.2}
TRUTH_SEED = 10_003


def interval(new: np.ndarray, reference: np.ndarray) -> str:
    """new - reference, paired per episode, with its 95% interval (`stages.paired`, the
    plant's own rule)."""
    from hrc_ros.core.plant.stages import paired
    d = paired(new, reference)
    return f'{d["mean"]:+.3f} +- {d["half_width"]:.3f}'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--seeds', default='3,4', help='recording seeds, comma-separated')
    parser.add_argument('--out', default='out/eager_close_bench')
    args = parser.parse_args(argv)
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.mdp.solver import solve
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import default_config_path
    from hrc_ros.core.plant import stages
    from hrc_ros.core.plant.spec import load_plant
    from hrc_ros.tools.fleet import Progress, run_plant
    seeds = [int(s) for s in args.seeds.split(',')]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f'command: nice -n {os.nice(0)} .venv/bin/python bench/eager_close_bench.py '
          f'{" ".join(sys.argv[1:] if argv is None else argv)}; load average '
          f'{os.getloadavg()[0]:.1f}', flush=True)
    cells = ''.join(f'  - name: eager_close_{s}\n    seed: {s}\n    generate: {{world: '
                    f'{json.dumps(EAGER_CLOSE)}, episodes: 80, epochs: 50, seed: {s}}}\n'
                    for s in seeds)
    (out / 'plant.yaml').write_text(f'defaults:\n  run: always\ncells:\n{cells}')
    t0 = time.perf_counter()
    report = run_plant(load_plant(out / 'plant.yaml'), out / 'plant', serial=True,
                       progress=Progress(quiet=True))
    print(f'plant of {len(seeds)} cells, --serial: {time.perf_counter() - t0:.0f} s')
    base = load_config(default_config_path())
    running = {'config': base, 'policy': load_policy(default_policy_path(base), base),
               'pomdp': None}
    world = stages.world_config(base, EAGER_CLOSE)
    optimum = solve(HRCModel(world))
    best = stages._both_in(world, running, world, optimum, None, 'paper', TRUTH, TRUTH_SEED)
    print(f'\nthe optimum refuses {best["refused_requests"][0].mean():.2f} requests per '
          f'episode, the running policy {best["refused_requests"][1].mean():.2f}; the running '
          f'policy\'s regret {interval(best["discounted_cost"][1], best["discounted_cost"][0])}'
          '\n')
    print('| seed | decision | estimate (95%) | true new - running | regret of the new policy '
          '| refused requests, new |')
    print('|---|---|---|---|---|---|')
    for seed, entry in zip(seeds, report['cells']):
        folder = out / 'plant' / 'cells' / entry['cell']
        c = entry['cost_difference']
        fitted = load_config(folder / 'fitted.yaml')
        both = stages._both_in(world, running, fitted, load_policy(folder / 'policy.npz', fitted),
                               None, 'paper', TRUTH, TRUTH_SEED)
        new, old = both['discounted_cost']
        print(f'| {seed} | {entry["decision"]} | {c["mean"]:+.2f} [{c["low"]:+.2f}, '
              f'{c["high"]:+.2f}] | {interval(new, old)} | '
              f'{interval(new, best["discounted_cost"][0])} | '
              f'{both["refused_requests"][0].mean():.2f} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
