"""How fast the robot's program progresses in the cell with the arm: the data for
`model.robot_rate` (MODEL.md 3.2, docs/ROBOT.md 4; config/arm.yaml sets what it measured),
counted by the code `hrc-fit --rate` counts recordings with (core.learning.rate).

Seeded episodes of the batch cell with the arm (`core.robot.cell.ArmCell`, random task streams
as `hrc-evaluate --cell arm` draws them, task rate 0.5) under each selector named, recorded as
the robot records them (task state, d, action per epoch) and counted: per task nature (the
station the program runs at) and band d at the epoch's start, the share of the epochs in which
the robot worked that ended with its counter down, with bootstrap 95% intervals. The seed is
not the evaluation's (2 by default; docs/ROBOT.md's paired figures are seed 0's), so that the
model is not fitted to the episodes it is judged on.

    python bench/progress_bench.py [--episodes 100] [--seed 2] [--selectors ssm_only,integrator]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrc_ros.core.config import RATE_NATURES, load_config  # noqa: E402
from hrc_ros.core.learning.rate import fit_rate  # noqa: E402
from hrc_ros.core.learning.recordings import NO_OBSERVATION, UNANSWERED, Recording  # noqa: E402
from hrc_ros.core.mdp.policy import default_policy_path, load_policy  # noqa: E402
from hrc_ros.core.model import ACTION_INDEX, HRCModel  # noqa: E402
from hrc_ros.core.paths import arm_config_path  # noqa: E402
from hrc_ros.core.robot.cell import ArmCell, person_seed  # noqa: E402
from hrc_ros.core.study.evaluation import episodes_of  # noqa: E402


def recording(episode, name: str) -> Recording:
    """A batch episode as the robot records it (no O: the rate does not read it)."""
    epochs = np.arange(1, len(episode.actions) + 1)
    accepted = [UNANSWERED if a is None else int(a) for a in episode.accepted]
    return Recording('batch', name, epochs, np.array(episode.task_states, dtype=np.int64),
                     np.array(episode.distances, dtype=np.int64),
                     np.full(epochs.size, NO_OBSERVATION), np.array(
                         [ACTION_INDEX[a] for a in episode.actions], dtype=np.int64),
                     np.array(accepted, dtype=np.int64), epochs)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--episodes', type=int, default=100)
    parser.add_argument('--epochs', type=int, default=50)
    parser.add_argument('--seed', type=int, default=2)
    parser.add_argument('--selectors', default='ssm_only,integrator',
                        help='whose episodes are counted (each selector\'s, then all together)')
    parser.add_argument('--config', default=str(arm_config_path()),
                        help='the model whose rules read the recordings (its robot_paused_by)')
    args = parser.parse_args(argv)
    config = load_config(args.config)
    model = HRCModel(config)
    cell = ArmCell(model, load_policy(default_policy_path(config), config))
    scenarios, seeds = episodes_of(model, 'random', args.episodes, args.epochs, args.seed, 0.5)
    t0 = time.perf_counter()
    everything = []
    for selector in args.selectors.split(','):
        recordings = [recording(cell.episode(s, h, person_seed(args.seed, e), selector,
                                             record=True), f'{selector} {e}')
                      for e, (s, h) in enumerate(zip(scenarios, seeds))]
        everything += recordings
        print(f'{selector}:')
        print('\n'.join(fit_rate(recordings, model, seed=args.seed).lines()))
    fitted = fit_rate(everything, model, seed=args.seed)
    print(f'all ({time.perf_counter() - t0:.0f} s):')
    print('\n'.join(fitted.lines()))
    print("as a configuration writes it (model.robot_rate; a band without an epoch keeps the "
          "base's value):")
    print('  robot_rate:')
    for tx in RATE_NATURES:
        print(f'    {tx}: [{", ".join(f"{v:.4f}" for v in fitted.rate[tx])}]')
    print(f'reproduce: python bench/progress_bench.py --episodes {args.episodes} --epochs '
          f'{args.epochs} --seed {args.seed} --selectors {args.selectors}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
