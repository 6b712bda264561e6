"""What issue 33's more conservative SSM costs the honest cell, rule by rule, and what each rule
buys against the people who test SSM (docs/ROBOT.md 7, "The price of the monitor").

SSM alone (`ssm_only`) in the batch cell with the arm, the honest person, the same episodes as
`hrc-evaluate --cell arm` (random task streams at task rate 0.5, seed 0, 50 epochs), once with
the shipped rules and once with each rule taken back, paired per episode:

- `walk_age`: the person's unseen travel during the data's age and the command's hold at the
  walking speed (1.6 m/s, the rule before issue 33) instead of ISO 13855's reach (2.0 m/s);
- `no_skew_or_tracking`: no clock skew (5 ms) in the ages, no tracking error (1 cm) off S;
- `no_braking_lookahead`: the command is max_speed(S) alone, without `braking_speed`'s look-ahead.

Each taken-back rule is then run against the reach and run_in scenarios (shorter episodes, as
bench/ssm_scenarios.py runs them): the violations against the true bodies it lets through.
The taken-back rules are patched into this process only (an ablation); nothing is shipped so.

    python bench/ssm_price.py [--episodes 200] [--scenario-episodes 200]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from hrc_ros.core.robot import ssm  # noqa: E402

SHIPPED = (ssm.unseen_reach, ssm.braking_speed)
RULES = ('shipped', 'walk_age', 'no_skew_or_tracking', 'no_braking_lookahead')


def _apply(rule: str, description):
    """Patch this process for `rule`; return the description to run with."""
    ssm.unseen_reach, ssm.braking_speed = SHIPPED
    if rule == 'walk_age':
        ssm.unseen_reach = lambda p, age=0.0, period=0.0: p.human_speed * (age + period)
    elif rule == 'no_braking_lookahead':
        ssm.braking_speed = ssm.max_speed
    elif rule == 'no_skew_or_tracking':
        return dataclasses.replace(description, clock_skew=0.0, tracking_error=0.0)
    return description


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--episodes', type=int, default=200)
    ap.add_argument('--scenario-episodes', type=int, default=200)
    args = ap.parse_args(argv)
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import arm_config_path
    from hrc_ros.core.robot.bridge import load_robot_description
    from hrc_ros.core.robot.cell import evaluate_arm
    from hrc_ros.core.study.evaluation import Z95
    config = load_config(arm_config_path())
    model = HRCModel(config)
    policy = load_policy(default_policy_path(config), config)
    shipped = load_robot_description()
    honest, scenarios = {}, {}
    for rule in RULES:
        t0 = time.time()
        description = _apply(rule, shipped)
        r = evaluate_arm(model, policy, episodes=args.episodes, selectors=('ssm_only',),
                         description=description)['ssm_only']
        honest[rule] = r
        line = (f'{rule}: honest cell {np.mean(r.tasks_per_hour):.1f} tasks per hour, '
                f'{np.mean(r.stop_share):.1f}% of the time in protective stops, '
                f'{int(r.ssm_violations.sum())} violations')
        if rule != 'shipped':
            for person in ('reach', 'run_in'):
                s = evaluate_arm(model, policy, episodes=args.scenario_episodes, epochs=15,
                                 selectors=('ssm_only',), description=description,
                                 person=person)['ssm_only']
                scenarios[rule, person] = s
                line += (f'; {person}: {int((s.ssm_violations > 0).sum())} of '
                         f'{args.scenario_episodes} episodes with violations, smallest margin '
                         f'{float(np.min(s.min_margin)):+.3f} m')
        print(f'{line} ({time.time() - t0:.0f} s)', flush=True)
    _apply('shipped', shipped)
    base = honest['shipped'].tasks_per_hour
    print(f'\nWhat each rule costs the honest cell (SSM alone, {args.episodes} paired episodes; '
          'taken back - shipped, tasks per hour, 95%):')
    for rule in RULES[1:]:
        d = honest[rule].tasks_per_hour - base
        half = Z95 * d.std(ddof=1) / math.sqrt(d.size)
        print(f'  {rule}: {d.mean():+.1f} +- {half:.1f} ({d.mean() / base.mean() * 100:+.1f}%)')
    print(f'reproduce: python bench/ssm_price.py --episodes {args.episodes} '
          f'--scenario-episodes {args.scenario_episodes}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
