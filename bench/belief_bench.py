"""Online cost of one decision epoch: one belief update plus one action selection.

    .venv/bin/python bench/belief_bench.py    # the venv scripts/bootstrap.sh creates
    python bench/belief_bench.py --repeat 50000 --policy policies/default.npz

On the full-size default model (N = 419,904), it times `BeliefFilter.update` (bayes mode) and
`ActionSelector.select` (method `paper`) call by call with `time.perf_counter_ns`, over
pre-drawn random actions, observations and observable states (so no input is reused in a way
a cache could exploit), and prints the median and the 99th percentile in microseconds. The
target for the pair is 50 microseconds: far below a decision epoch (1 s), so the belief and
the decision are never the bottleneck of a node.

The policy is the shipped `policies/default.npz` when it exists (and matches the
configuration), else it is solved first (a few seconds, not timed).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hrc_ros.core.pomdp.belief import BeliefFilter  # noqa: E402
from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.model import ACTIONS, HRCModel  # noqa: E402
from hrc_ros.core.decision.selection import ActionSelector  # noqa: E402

TARGET_US = 50.0


def load_or_solve(model, policy_path: Path):
    from hrc_ros.core.mdp.policy import PolicyError, load_policy

    try:
        policy = load_policy(policy_path, model.config)
        return policy.policy, f'{policy_path}'
    except PolicyError:
        from hrc_ros.core.mdp.solver import solve

        t0 = time.perf_counter()
        result = solve(model)
        return result.policy, f'solved here in {time.perf_counter() - t0:.1f} s'


def percentiles(ns: np.ndarray) -> tuple[float, float]:
    us = ns / 1000.0
    return float(np.median(us)), float(np.percentile(us, 99))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--config', type=Path, default=ROOT / 'config' / 'default.yaml')
    parser.add_argument('--policy', type=Path, default=ROOT / 'policies' / 'default.npz')
    parser.add_argument('--repeat', type=int, default=20000, help='timed calls (default 20000)')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args(argv)

    model = HRCModel(load_config(args.config))
    policy, source = load_or_solve(model, args.policy)
    belief_filter = BeliefFilter(model, mode='bayes')
    selector = ActionSelector(model, policy, method='paper')

    rng = np.random.default_rng(args.seed)
    n = args.repeat
    actions = [ACTIONS[a] for a in rng.integers(0, len(ACTIONS), size=n)]
    observations = [int(o) for o in rng.integers(1, 4, size=n)]
    observables = [model.state(int(i))[2:] for i in rng.integers(0, model.n_states, size=n)]

    update_ns = np.empty(n, dtype=np.int64)
    select_ns = np.empty(n, dtype=np.int64)
    clock = time.perf_counter_ns
    belief = belief_filter.initial(2)
    for _ in range(min(n, 2000)):  # warm-up
        selector.select(belief_filter.update(belief, 'nw', 2), observables[0])
    for k in range(n):
        t0 = clock()
        belief = belief_filter.update(belief, actions[k], observations[k])
        t1 = clock()
        selector.select(belief, observables[k])
        t2 = clock()
        update_ns[k] = t1 - t0
        select_ns[k] = t2 - t1

    print(f'belief_bench: N = {model.n_states} states, policy {source}, {n} timed calls')
    rows = (('BeliefFilter.update (bayes)', update_ns),
            ("ActionSelector.select ('paper')", select_ns),
            ('update + select', update_ns + select_ns))
    for name, ns in rows:
        median, p99 = percentiles(ns)
        print(f'  {name:32s} median {median:7.2f} us   p99 {p99:7.2f} us')
    median, p99 = percentiles(update_ns + select_ns)
    met = median < TARGET_US
    print(f'target: update + select under {TARGET_US:.0f} us (median): '
          f'{"met" if met else "NOT met"} ({median:.2f} us; p99 {p99:.2f} us)')
    print(f'reproduce: {sys.executable} bench/belief_bench.py --repeat {args.repeat}')
    return 0 if met else 1


if __name__ == '__main__':
    sys.exit(main())
