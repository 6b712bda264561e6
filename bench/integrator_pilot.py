"""The pilot that chose the integrator's rule (docs/ROBOT.md 4, `robot.cell.integrator_action`):
the candidate rules an integrator would write on top of SSM, each ssm_only's work plan except
for a task either agent can do (tx 2), which goes to the person (rh1, asked every epoch until
taken) when the person is near, and to the arm otherwise:

- `near1`: the person within band 1 (d <= 1), where the arm at the side station is slowed most;
- `near2`: within band 2 (d <= 2);
- `always`: whatever the band (`integrator_action`).

Paired on the batch cell's random streams (as `hrc-evaluate --cell arm`), on a seed the
evaluation does not use (the pilot's, 1 by default; the figures of docs/ROBOT.md are seed 0's),
so that the choice is not fitted to the episodes it is judged on. The rule with the most tasks
per hour is the baseline.

    python bench/integrator_pilot.py [--episodes 100] [--seed 1]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.model import CT, RH1, TASK_VARIABLES, HRCModel  # noqa: E402
from hrc_ros.core.paths import arm_config_path  # noqa: E402
from hrc_ros.core.robot import cell as arm_cell  # noqa: E402

CANDIDATES = {'near1': 1, 'near2': 2, 'always': 3}     # hand tx 2 to the person when d <= this


class PilotCell(arm_cell.ArmCell):
    """The batch cell with the candidate rules as selectors of their own."""

    def _decide(self, selector, belief, x, hidden, level=0):
        if selector not in CANDIDATES:
            return super()._decide(selector, belief, x, hidden, level)
        task = dict(zip(TASK_VARIABLES, x[:-1]))
        if task['tp'] > 0 and task['ty'] == 0 and task['tx'] == 2:
            return RH1 if x[-1] <= CANDIDATES[selector] else CT
        return arm_cell.ssm_only_action(task)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--episodes', type=int, default=100)
    parser.add_argument('--seed', type=int, default=1)
    args = parser.parse_args(argv)
    model = HRCModel(load_config(arm_config_path()))
    selectors = ('ssm_only',) + tuple(CANDIDATES)
    t0 = time.perf_counter()
    # evaluate_arm with the pilot's cell and selectors (the module's names, for this run)
    saved = arm_cell.ArmCell, arm_cell.CELL_SELECTORS
    arm_cell.ArmCell, arm_cell.CELL_SELECTORS = PilotCell, saved[1] + tuple(CANDIDATES)
    try:
        results = arm_cell.evaluate_arm(model, np.zeros(model.n_states, dtype=np.int8),
                                        args.episodes, 50, args.seed, 0.5, selectors)
    finally:
        arm_cell.ArmCell, arm_cell.CELL_SELECTORS = saved
    print(f'the integrator\'s candidate rules, {args.episodes} episodes x 50 epochs, seed '
          f'{args.seed}, task rate 0.5 ({time.perf_counter() - t0:.0f} s)')
    print(arm_cell.format_arm_table(results))
    print(arm_cell.format_arm_paired(results, 'ssm_only'))
    best = max(CANDIDATES, key=lambda s: results[s].tasks_per_hour.mean())
    print(f'most tasks per hour: {best}')
    print(f'reproduce: python bench/integrator_pilot.py --episodes {args.episodes} --seed '
          f'{args.seed}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
