"""hrc-simulate: the case study (MODEL.md 7) in closed loop without ROS.

    hrc-simulate [--config YAML] [--policy NPZ] [--selector paper|qmdp|mls|pomdp|fib|mdp]
                 [--seed N]

Prints the run as the paper's Table 6 and writes `trajectory.csv` and the plots into `--out`.
With a queue (stream.queue, MODEL.md 8.1) the robot reads the tasks waiting, the cost charges
them and the table and CSV gain the column `queued`.
"""

from __future__ import annotations

import sys

from ..core.config import BELIEF_MODES
from ..core.study.plots import plot_trajectory
from ..core.study.simulation import SIMULATION_SELECTORS, Scenario, case_study, simulate
from .common import (MAX_EPOCHS, MAX_SEED, Parser, ToolError, add_model_arguments,
                     add_pomdp_argument, bounded_int, check_cell, command, fail, load_model,
                     load_pomdp, output_folder, path_text)


@command('hrc-simulate')
def main(argv=None) -> int:
    parser = Parser(
        prog='hrc-simulate',
        description='Run the case study (MODEL.md 7) in closed loop; print it as the paper\'s '
                    'Table 6, write a CSV and PNG plots.')
    add_model_arguments(parser)
    add_pomdp_argument(parser)
    parser.add_argument('--selector', default='paper', choices=SIMULATION_SELECTORS,
                        help='action selection (mdp = the true state, an upper bound)')
    parser.add_argument('--mode', default=None, choices=BELIEF_MODES,
                        help='belief mode (default: the configuration\'s)')
    parser.add_argument('--seed', type=bounded_int(0, MAX_SEED), default=0,
                        help='seed of the simulated human')
    parser.add_argument('--epochs', type=bounded_int(1, MAX_EPOCHS), default=None,
                        help='number of epochs (default: the case study\'s 20)')
    parser.add_argument('--out', default='out/simulate', type=path_text, help='output folder')
    args = parser.parse_args(argv)
    try:
        config, model, policy = load_model(args)
        check_cell(model)
        pomdp = load_pomdp(args, config, (args.selector,))
        out = output_folder(args.out)
    except ToolError as exc:
        return fail('hrc-simulate', exc)
    scenario = case_study()
    if args.epochs is not None:
        scenario = Scenario(scenario.initial_state, scenario.schedule, args.epochs,
                            scenario.name)
    trajectory = simulate(model, policy, scenario, selector=args.selector, mode=args.mode,
                          seed=args.seed, pomdp=pomdp)
    print(trajectory.table())
    written = [trajectory.to_csv(out / 'trajectory.csv')] + plot_trajectory(trajectory, out)
    for path in written:
        print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
