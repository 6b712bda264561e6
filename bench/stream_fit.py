"""The task stream (MODEL.md 8) fitted on recorded runs of hrc-evaluate's scenarios.

    .venv/bin/python bench/stream_fit.py [--episodes 500] [--seed 0] [--prior [--bootstrap 200]]
    .venv/bin/python bench/stream_fit.py --queue [--episodes 500] [--seed 0]

Records `--episodes` runs of each scenario hrc-evaluate runs (the random streams: 50 epochs,
task rate 0.2; the paper's case study at its 20 epochs and at 150) with the default
configuration's policy and the paper selector, the posterior belief (the robot's view only: the
recordings hold no emotions), and prints the stream that `core.learning.stream` (hrc-fit
--stream) counts from each, with bootstrap 95% intervals: the numbers of config/stream.yaml
(random) and config/case_study_stream.yaml (the case study's 20 epochs).

`--prior` also fits the person prior (hrc-fit --prior: every family of the model free, the
default configuration as the base, `--bootstrap` resamples of the episodes) on the recordings
of each case-study scenario, whose person always starts at em = ea = 0, and prints it with
its bootstrap 95% intervals and as the `observation.prior` line of a configuration (the
random streams' people are uniform by construction: not fitted).

`--queue` records hrc-evaluate's random streams (50 epochs, task rate 0.2) with
config/stream_queue.yaml and its policy (policies/stream_queue.npz, the paper selector, the
posterior belief) instead, and prints the stream with a queue (MODEL.md 8.1) that hrc-fit
--stream counts from them on that base (`fit_queue_stream`, from the tasks waiting per epoch):
the truth is arrival_idle = arrival_busy = 0.2 (a release per epoch whatever the cell does;
the task every episode has at epoch 1 is its start, not a trial), q uniform over the 16 tasks.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.learning import fit as fitting  # noqa: E402
from hrc_ros.core.learning.stream import fit_queue_stream, fit_stream  # noqa: E402
from hrc_ros.core.mdp.policy import load_policy  # noqa: E402
from hrc_ros.core.model import HRCModel  # noqa: E402
from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of  # noqa: E402

SCENARIOS = (('random', 50, 0.2), ('case-study', 20, 0.0), ('case-study', 150, 0.0))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--episodes', type=int, default=500)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--prior', action='store_true',
                        help='also fit the person prior on the case-study recordings')
    parser.add_argument('--bootstrap', type=int, default=fitting.BOOTSTRAP,
                        help='resamples for the prior\'s intervals (with --prior)')
    parser.add_argument('--queue', action='store_true',
                        help='fit the stream with a queue on random streams recorded with '
                        'config/stream_queue.yaml (MODEL.md 8.1)')
    args = parser.parse_args(argv)
    if args.queue:
        return queue_main(args)
    config = load_config(ROOT / 'config' / 'default.yaml')
    model = HRCModel(config)
    policy = load_policy(ROOT / 'policies' / 'default.npz', config).policy
    print(f'stream_fit: {args.episodes} recorded episodes per scenario, seed {args.seed}; '
          f'command: .venv/bin/python bench/stream_fit.py --episodes {args.episodes} '
          f'--seed {args.seed}'
          + (f' --prior --bootstrap {args.bootstrap}' if args.prior else ''))
    for scenario, epochs, rate in SCENARIOS:
        scenarios, seeds = episodes_of(model, scenario, args.episodes, epochs, args.seed, rate)
        run = BatchSimulator(model, policy, mode='posterior').run(scenarios, seeds, 'paper',
                                                                   record=True)
        fitted = fit_stream(run.recordings(model), seed=args.seed)
        print(f'\n{scenario}, {epochs} epochs, task rate {rate}: '
              f'{np.mean(run.tasks_completed):.2f} tasks completed per episode')
        print('\n'.join(fitted.lines()))
        print(f'  section: {fitted.section()}')
        if args.prior and scenario == 'case-study':
            print_prior(run.recordings(model), config, args)
    return 0


def queue_main(args) -> int:
    """--queue: the queue's stream fitted on recorded random streams (the module docstring)."""
    config = load_config(ROOT / 'config' / 'stream_queue.yaml')
    model = HRCModel(config)
    policy = load_policy(ROOT / 'policies' / 'stream_queue.npz', config).policy
    epochs, rate = 50, 0.2
    print(f'stream_fit --queue: {args.episodes} recorded random episodes, {epochs} epochs, task '
          f'rate {rate}, config/stream_queue.yaml, seed {args.seed}; command: .venv/bin/python '
          f'bench/stream_fit.py --queue --episodes {args.episodes} --seed {args.seed}')
    scenarios, seeds = episodes_of(model, 'random', args.episodes, epochs, args.seed, rate)
    run = BatchSimulator(model, policy, mode='posterior').run(scenarios, seeds, 'paper',
                                                               record=True)
    fitted = fit_queue_stream(run.recordings(model), config.queue,
                              config.data['stream']['waiting_cost'], seed=args.seed)
    print(f'{np.mean(run.tasks_completed):.2f} tasks completed per episode, '
          f'{np.mean(run.waiting_epochs):.2f} waiting task-epochs')
    print('\n'.join(fitted.lines()))
    covered = [name for name in ('arrival_idle', 'arrival_busy')
               if fitted.intervals[name][0] <= rate <= fitted.intervals[name][1]]
    print(f'  the truth {rate} is inside the interval of: {", ".join(covered) or "neither"}')
    print(f'  section: {fitted.section()}')
    return 0


def print_prior(recordings, config, args) -> None:
    """hrc-fit --prior on `recordings`, printed: the prior with its intervals."""
    data = fitting.prepare(recordings)
    result = fitting.fit(data, config, seed=args.seed, bootstrap=args.bootstrap, prior=True)
    print(f'  person prior (hrc-fit --prior, {result.prior_starts} episode starts, '
          f'{result.epochs} epochs, {len(result.issues)} rows or transitions cut or left '
          f'out; EM {result.iterations} iterations, '
          f'{"converged" if result.converged else "NOT converged"}; '
          f'{result.seconds.get("fit", 0) + result.seconds.get("bootstrap", 0):.0f} s):')
    for h in range(len(result.params.pi)):
        low, high = ((np.nan, np.nan) if result.prior_interval is None
                     else result.prior_interval[:, h])
        value = None if result.prior_effective is None else result.prior_effective[h]
        effective = ('-' if value is None else 'no spread' if value >= 1e12
                     else f'{value:.0f}')
        print(f'    h={h} (em={h // 3}, ea={h % 3}): {result.params.pi[h]:.6f}  95% '
              f'[{low:.6f}, {high:.6f}]  effective {effective}')
    print(f'  observation.prior: {fitting._row(result.params.pi)}')
    for warning in result.warnings:
        if warning.startswith('observation.prior'):
            print(f'  warning: {warning}')


if __name__ == '__main__':
    sys.exit(main())
