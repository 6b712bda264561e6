"""What a retreat (dp) gains in the cell with the arm: the data behind config/arm.yaml's
`model.retreat_reach` (MODEL.md 3.3, docs/ROBOT.md 4).

Runs seeded episodes of the batch cell with the arm (`core.robot.cell.ArmCell`, random task
streams as `hrc-evaluate --cell arm` draws them) under a policy that retreats often (default:
the shipped default policy, solved for the paper's rule), counts the distance band after each
epoch by the band before it and the action, and scores each choice of `retreat_reach` by the
log-likelihood of the epochs after dp: P(d' | d, dp) = sum over Delta with
next_distance(d, dp, Delta, reach) = d' of p_delta[ea, Delta], ea averaged uniformly (the
person's aggression is hidden; the averaging is the same for every choice).

    python bench/retreat_bench.py [--episodes 40] [--epochs 50] [--seed 0] [--config C]
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.mdp.policy import default_policy_path, load_policy  # noqa: E402
from hrc_ros.core.model import DELTAS, DP, HRCModel, next_distance  # noqa: E402
from hrc_ros.core.paths import default_config_path  # noqa: E402
from hrc_ros.core.robot.cell import ArmCell, person_seed  # noqa: E402
from hrc_ros.core.study.evaluation import episodes_of  # noqa: E402

REACHES = (None, 2, 1)


def transitions(config_path, episodes: int, epochs: int, seed: int):
    config = load_config(config_path)
    model = HRCModel(config)
    cell = ArmCell(model, load_policy(default_policy_path(config), config))
    return model, count_moves(cell, model, episodes, epochs, seed)


def print_moves(counts, actions) -> None:
    """The table of d' by (action, d) of `count_moves`'s counts (also approach_bench's)."""
    print("action  d   epochs   P(d' = 0, 1, 2, 3)")
    for action in actions:
        for d in range(4):
            row = [counts[(action, d, e)] for e in range(4)]
            if sum(row):
                share = ', '.join(f'{x / sum(row):.3f}' for x in row)
                print(f'{action:6}  {d}  {sum(row):7}   {share}')


def count_moves(cell, model, episodes: int, epochs: int, seed: int) -> collections.Counter:
    """(action, d, d') -> epochs, over the cell's seeded random episodes under paper (also
    bench/approach_bench.py's count)."""
    scenarios, seeds = episodes_of(model, 'random', episodes, epochs, seed, 0.5)
    counts = collections.Counter()
    for e, (scenario, human) in enumerate(zip(scenarios, seeds)):
        ep = cell.episode(scenario, human, person_seed(seed, e), 'paper', record=True)
        for k in range(len(ep.actions) - 1):
            counts[(ep.actions[k], ep.distances[k], ep.distances[k + 1])] += 1
    return counts


def log_likelihood(model, counts, reach) -> float:
    p_delta = model.config.p_delta.mean(axis=0)          # ea averaged uniformly
    total = 0.0
    for (action, d, d_next), n in counts.items():
        if action != 'dp':
            continue
        p = sum(p_delta[k] for k, delta in enumerate(DELTAS)
                if int(next_distance(d, DP, delta, reach)) == d_next)
        total += n * np.log(max(p, 1e-12))
    return total


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--episodes', type=int, default=40)
    parser.add_argument('--epochs', type=int, default=50)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--config', default=str(default_config_path()),
                        help='the configuration whose shipped policy drives the cell')
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    model, counts = transitions(args.config, args.episodes, args.epochs, args.seed)
    print(f'{args.episodes} episodes x {args.epochs} epochs of the cell with the arm, seed '
          f'{args.seed}, policy of {args.config} ({time.perf_counter() - t0:.0f} s)')
    print_moves(counts, ('dp', 'nw', 'ct', 'dn'))
    print('log-likelihood of the epochs after dp, by retreat_reach:')
    scores = {reach: log_likelihood(model, counts, reach) for reach in REACHES}
    for reach, score in scores.items():
        print(f'  {"null" if reach is None else reach:>4}: {score:10.1f}')
    best = max(scores, key=scores.get)
    print(f'best: retreat_reach {"null" if best is None else best}')
    print(f'reproduce: python bench/retreat_bench.py --episodes {args.episodes} --epochs '
          f'{args.epochs} --seed {args.seed}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
