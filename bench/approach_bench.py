"""What a move closer (dm) does to the distance in the cell with the arm: the data behind
config/arm.yaml's `model.approach_reach` (MODEL.md 3.3, docs/ROBOT.md 4), as
bench/retreat_bench.py measured dp for `retreat_reach`.

No shipped policy chooses dm in every band, so the bench probes: seeded episodes of the batch
cell with the arm (`core.robot.cell.ArmCell`, random task streams as `hrc-evaluate --cell arm`
draws them, task rate 0.5) run the arm's shipped policy (paper selector), and in each epoch
with d >= 1, with probability `--share` drawn from a stream of its own, the action is dm
instead. The distance band after each epoch is counted by the band before it and the action;
each rule for dm is scored by the log-likelihood of the epochs after dm: P(d' | d, dm) = sum
over Delta with next_distance(d, dm, Delta) = d' of p_delta[ea, Delta], ea averaged uniformly
(the person's aggression is hidden; the averaging is the same for every rule). The rules: the
paper's (d' = max(1, d - 1 - Delta)), `approach_reach` 1, 2, 3 (dm gains a band only from
above that band, no floor), and, for the record, the paper's floor without the gain
(max(1, min(3, d - Delta))). The epochs after nw from the same episodes are the control: the
share of epochs that ended a band closer, after dm and after nw, per starting band, with a 95%
interval of their difference, and nw's own log-likelihood with and without the floor (band 0
is absent after every action in this cell, so a floor scores for every action alike).

    python bench/approach_bench.py [--episodes 40] [--epochs 50] [--share 0.3] [--seed 0]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.mdp.policy import default_policy_path, load_policy  # noqa: E402
from hrc_ros.core.model import ACTIONS, DELTAS, DM, HRCModel, next_distance  # noqa: E402
from hrc_ros.core.paths import arm_config_path  # noqa: E402
from hrc_ros.core.robot.cell import ArmCell  # noqa: E402
from hrc_ros.core.study.evaluation import Z95  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from retreat_bench import count_moves, print_moves  # noqa: E402

RULES = {
    'paper (null)': lambda d, delta: int(next_distance(d, DM, delta)),
    'approach_reach 1': lambda d, delta: int(next_distance(d, DM, delta, approach=1)),
    'approach_reach 2': lambda d, delta: int(next_distance(d, DM, delta, approach=2)),
    'approach_reach 3': lambda d, delta: int(next_distance(d, DM, delta, approach=3)),
    'floor 1, no gain': lambda d, delta: max(1, min(3, d - delta)),
}


class ProbedCell(ArmCell):
    """The batch cell whose decisions are replaced by `probe` in a share of the epochs with
    d >= 1 (d = 0 is the fail-safe's), from a random stream of its own."""

    def __init__(self, *args, probe: int, share: float, seed: int, **kwargs):
        super().__init__(*args, **kwargs)
        self.probe, self.share = probe, share
        self.rng = np.random.default_rng([seed, 34])

    def _decide(self, selector, belief, x, hidden, level=0):
        action = super()._decide(selector, belief, x, hidden, level)
        if x[-1] > 0 and self.rng.random() < self.share:
            return self.probe
        return action


def transitions(config_path, episodes: int, epochs: int, seed: int, share: float):
    config = load_config(config_path)
    model = HRCModel(config)
    cell = ProbedCell(model, load_policy(default_policy_path(config), config), probe=DM,
                      share=share, seed=seed)
    return model, count_moves(cell, model, episodes, epochs, seed)


def log_likelihood(model, counts, rule, scored: str = 'dm') -> float:
    p_delta = model.config.p_delta.mean(axis=0)          # ea averaged uniformly
    total = 0.0
    for (action, d, d_next), n in counts.items():
        if action != scored:
            continue
        p = sum(p_delta[k] for k, delta in enumerate(DELTAS) if rule(d, delta) == d_next)
        total += n * np.log(max(p, 1e-12))
    return total


def closer(counts, action, d) -> tuple[int, int]:
    """(epochs after `action` from band d that ended in a nearer band, epochs)."""
    row = [counts[(action, d, e)] for e in range(4)]
    return sum(row[:d]), sum(row)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--episodes', type=int, default=40)
    parser.add_argument('--epochs', type=int, default=50)
    parser.add_argument('--share', type=float, default=0.3,
                        help='share of the epochs with d >= 1 whose action is dm')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--config', default=str(arm_config_path()),
                        help='the configuration whose shipped policy drives the cell')
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    model, counts = transitions(args.config, args.episodes, args.epochs, args.seed, args.share)
    print(f'{args.episodes} episodes x {args.epochs} epochs of the cell with the arm, seed '
          f'{args.seed}, policy of {args.config}, dm in {args.share:.0%} of the epochs with '
          f'd >= 1 ({time.perf_counter() - t0:.0f} s)')
    print_moves(counts, ACTIONS)
    print('a band closer after dm and after nw (dm - nw, 95%):')
    for d in (1, 2, 3):
        (a, n), (b, m) = closer(counts, 'dm', d), closer(counts, 'nw', d)
        if n and m:
            p, q = a / n, b / m
            half = Z95 * math.sqrt(p * (1 - p) / n + q * (1 - q) / m)
            print(f'  from d = {d}: dm {a}/{n} = {p:.3f}, nw {b}/{m} = {q:.3f}, difference '
                  f'{p - q:+.3f} ± {half:.3f}')
    print('log-likelihood of the epochs after dm, by rule:')
    scores = {name: log_likelihood(model, counts, rule) for name, rule in RULES.items()}
    for name, score in scores.items():
        print(f'  {name:>17}: {score:10.1f}')
    print(f'best: {max(scores, key=scores.get)}')
    # the floor's score is band 0's absence, which is the cell's under every action: the same
    # pattern after nw, whose rule (MODEL.md 3.3) nobody proposes to change
    nw_rule = lambda d, delta: int(next_distance(d, 0, delta))   # noqa: E731
    print('the control, the epochs after nw: the model\'s rule '
          f'{log_likelihood(model, counts, nw_rule, "nw"):.1f}, with the floor at band 1 '
          f'{log_likelihood(model, counts, RULES["floor 1, no gain"], "nw"):.1f}')
    print(f'reproduce: python bench/approach_bench.py --episodes {args.episodes} --epochs '
          f'{args.epochs} --share {args.share} --seed {args.seed}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
