"""Liveness of every shipped MDP policy (issue 34): P(a committed task completes within 50
epochs), by the exact evaluation on its own model (core.mdp.liveness, as `hrc-solve` prints it
and test/test_liveness.py asserts), from every state with a committed task, beside the model's
bound (the best any policy of the model reaches).

Per shipped configuration: the policy's minimum, its minimum at d >= 1, its minimum over the
states where some policy reaches the 0.95 target, the bound's minimum, and whether the check
passes (no state below min(0.95, the bound)).

    python bench/liveness_bench.py [--configs arm,default,...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.mdp.liveness import TARGET, check_liveness  # noqa: E402
from hrc_ros.core.mdp.policy import load_policy  # noqa: E402
from hrc_ros.core.model import N_DISTANCE, HRCModel  # noqa: E402
from hrc_ros.core.paths import share_dir, shipped_config_path  # noqa: E402


def shipped() -> list[str]:
    """The shipped configurations with a shipped MDP policy of the same name."""
    policies = share_dir() / 'policies'
    return sorted(p.stem for p in policies.glob('*.npz')
                  if shipped_config_path(p.stem).exists())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--configs', default=None,
                        help='comma-separated shipped configurations (default: every one with a '
                        'shipped policy)')
    args = parser.parse_args(argv)
    names = args.configs.split(',') if args.configs else shipped()
    print(f'{"policy":<26} {"states":>9} {"min":>7} {"min d>=1":>9} {"min reach.":>10} '
          f'{"bound min":>9}  check')
    for name in names:
        t0 = time.perf_counter()
        config = load_config(shipped_config_path(name))
        model = HRCModel(config)
        policy = load_policy(share_dir() / 'policies' / f'{name}.npz', config)
        check = check_liveness(model, policy)
        p, b = check.policy, check.bound
        near = p.probability[p.states % N_DISTANCE > 0]
        reachable = p.probability[b.probability >= TARGET]
        print(f'{name:<26} {len(p.states):>9,} {p.minimum:>7.4f} {near.min():>9.4f} '
              f'{reachable.min():>10.4f} {b.minimum:>9.4f}  '
              f'{"met" if check.passed else "FAILED"} ({time.perf_counter() - t0:.0f} s)')
    print(f'reproduce: python bench/liveness_bench.py --configs {",".join(names)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
