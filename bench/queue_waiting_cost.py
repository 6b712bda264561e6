"""The cost scale the queue's waiting charge is chosen from (MODEL.md 8.1): the mean cost J of
an epoch with a task in the cell and of an idle one, under the shipped policy of
config/default.yaml (the paper selector, posterior belief, hrc-evaluate's random streams).

    .venv/bin/python bench/queue_waiting_cost.py [--episodes 1000]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.mdp.policy import default_policy_path, load_policy  # noqa: E402
from hrc_ros.core.model import N_DISTANCE, HRCModel  # noqa: E402
from hrc_ros.core.paths import shipped_config_path  # noqa: E402
from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--episodes', type=int, default=1000)
    args = parser.parse_args(argv)
    config = load_config(shipped_config_path('default'))
    model = HRCModel(config)
    policy = load_policy(default_policy_path(config), config)
    scenarios, seeds = episodes_of(model, 'random', args.episodes, 50)
    sim = BatchSimulator(model, policy, mode='posterior')
    t = sim.run(scenarios, seeds, 'paper', record=True).trajectory
    h = 3 * t['em'] + t['ea']
    cost = (sim.state_cost[h * sim.columns + t['y'] * N_DISTANCE + t['d']]
            + sim.action_cost[t['action']])
    busy = model.task_grid['tp'][t['y']] > 0
    print(f'mean J per epoch: with a task in the cell {cost[busy].mean():.3f}, idle '
          f'{cost[~busy].mean():.3f} (a task adds {cost[busy].mean() - cost[~busy].mean():.3f}); '
          f'{busy.mean():.1%} of the epochs have a task')
    return 0


if __name__ == '__main__':
    sys.exit(main())
