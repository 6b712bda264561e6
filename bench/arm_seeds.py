"""The case study in the batch cell with the arm, seed by seed: how many of its three tasks
each seed completes within a number of epochs (docs/ROBOT.md 6, "the seed").

The batch cell as test/test_robot_case_study.py runs it (`ArmCell` with `GRAPH_SETTINGS`, the
case study's scenario, human seed s and person seed [s, 2], the paper selector), with the
shipped policy of the configuration (default: the arm's model, config/arm.yaml).

    python bench/arm_seeds.py [--seeds 40] [--epochs 20,30,40] [--config C [--policy P]]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.mdp.policy import default_policy_path, load_policy  # noqa: E402
from hrc_ros.core.model import HRCModel  # noqa: E402
from hrc_ros.core.paths import arm_config_path  # noqa: E402
from hrc_ros.core.robot.cell import GRAPH_SETTINGS, ArmCell  # noqa: E402
from hrc_ros.core.study.simulation import Scenario, case_study  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--seeds', type=int, default=40)
    parser.add_argument('--epochs', default='20,30,40',
                        help='comma-separated run lengths (the longest is simulated)')
    parser.add_argument('--config', default=str(arm_config_path()))
    parser.add_argument('--policy', default=None,
                        help="the configuration's MDP policy (default: the shipped one solved "
                        'for it)')
    args = parser.parse_args(argv)
    lengths = sorted(int(e) for e in args.epochs.split(','))
    config = load_config(args.config)
    policy = args.policy or default_policy_path(config)
    cell = ArmCell(HRCModel(config), load_policy(policy, config),
                   settings=GRAPH_SETTINGS)
    study = case_study()
    t0 = time.perf_counter()
    done_by = []                 # per seed: the epoch its third task completed, or None
    for seed in range(args.seeds):
        episode = cell.episode(Scenario(study.initial_state, study.schedule, lengths[-1],
                                        'case'), seed, [seed, 2], 'paper', record=True)
        idle = [k for k, x in enumerate(episode.task_states, start=1) if x[0] == 0]
        completed = episode.tasks_completed
        last = None
        if completed == 3:
            # the task state at the start of an epoch: the third task is complete at the end
            # of the epoch before the first idle start after the last task's release
            release = study.schedule[-1][0]
            last = next(k - 1 for k in idle if k > release)
        done_by.append(last)
        print(f'seed {seed:3}: {completed}/3 tasks in {lengths[-1]} epochs'
              + (f', the third done by epoch {last}' if last else ''), flush=True)
    print(f'{config.source}, {args.seeds} seeds ({time.perf_counter() - t0:.0f} s):')
    for n in lengths:
        count = sum(1 for k in done_by if k is not None and k <= n)
        print(f'  3/3 within {n} epochs: {count} of {args.seeds}')
    print(f'reproduce: python bench/arm_seeds.py --seeds {args.seeds} --epochs {args.epochs} '
          f'--config {args.config}' + (f' --policy {args.policy}' if args.policy else ''))
    return 0


if __name__ == '__main__':
    sys.exit(main())
