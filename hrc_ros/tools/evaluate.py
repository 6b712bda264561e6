"""hrc-evaluate: the action selectors compared over many seeded episodes (core.study.evaluation).

    hrc-evaluate [--episodes 1000] [--epochs 50] [--selectors paper,qmdp,mls,mdp]
                 [--baseline pomdp] [--true-config TRUE.yaml [--true-policy TRUE.npz]]
                 [--waiting-cost W]
    hrc-evaluate --cell arm [--episodes 200] [--selectors ssm_only,paper,qmdp,integrator]
                 [--baseline ssm_only]

With `--cell arm` the episodes run in the cell with the arm (core.robot.cell: the bridge, SSM,
the MuJoCo UR5e, the person walking around it) and the table is in physical units: tasks per
hour, idle and protective-stop time, the minimum separation, SSM violations, refused requests,
with every selector's paired differences to the baseline (ssm_only, SSM alone, by default).
Besides the decision layer's selectors it runs the two baselines outside it: ssm_only and
integrator (an integrator's rule on top of SSM, docs/ROBOT.md 4).
Without `--config` it plans with the arm's model, `config/arm.yaml` (the robot's counter paused
under dp and dm, MODEL.md 3.2), and its shipped policy.

Prints the table of means with 95% intervals and writes `summary.csv`, `summary.json`,
`episodes.csv` and `summary.png` into `--out`. With `--baseline S`, also every selector's
paired difference to S (same episodes) with its 95% interval (`paired.csv`).

The queue (MODEL.md 8.1): with a configuration whose stream has a queue the robot observes the
queue length (up to L) and the cost charges every waiting task its stream.waiting_cost per
epoch; `--waiting-cost W` charges W in any configuration (so a model without a queue is scored
the same way; its decisions do not change). Then the table has the waiting task-epochs and
episodes.csv `waiting_epochs` and `discounted_waiting` (the charge is W times the latter).

Model mismatch: with `--true-config` the human and the costs are drawn from that configuration
(the world) while the robot plans with `--config` and its policy (policy and belief filter); in
random episodes the people start from the world's person prior when it has one
(`observation.prior`), uniformly otherwise and always without `--true-config`. The same
episodes are also run planning with the true configuration (its `--true-policy`, else the
shipped one solved for it, else solved here), and the regret of each selector is the paired
difference of the two costs, with its 95% interval. The POMDP selectors (pomdp, fib) are left
out of that comparison: they would need a POMDP policy solved for the true configuration too.
"""

from __future__ import annotations

import csv
import json
import sys
import time

from ..core.cell.scenarios import SCENARIOS as PERSON_SCENARIOS
from ..core.config import BELIEF_MODES, ConfigError, load_config
from ..core.study.evaluation import (METRICS, QUEUE_METRICS, SCENARIOS, charged_waiting_cost,
                                     evaluate, format_paired, format_regret, format_table,
                                     paired_difference, summarize)
from ..core.model import HRCModel
from ..core.mdp.policy import PolicyError, default_policy_path, load_policy
from ..core.paths import arm_config_path, write_text, written
from ..core.study.plots import plot_summaries
from ..core.study.simulation import SIMULATION_SELECTORS
from ..core.names import BadName, items
from .common import (MAX_EPISODES, MAX_EPISODE_EPOCHS, MAX_EPOCHS, MAX_SEED, Parser, ToolError,
                     add_model_arguments, add_pomdp_argument, bounded_float, bounded_int,
                     check_cell, command, fail, load_model, load_pomdp, output_folder,
                     path_text)


def write_summary_csv(path, summaries: dict, metrics) -> None:
    """summary.csv: per selector and metric the count, mean and 95% interval."""
    with written(path) as f:
        writer = csv.writer(f)
        writer.writerow(['selector', 'metric', 'n', 'mean', 'ci95_low', 'ci95_high'])
        for s, summary in summaries.items():
            for metric, _ in metrics:
                m = summary[metric]
                writer.writerow([s, metric, m['n'], f'{m["mean"]:.6g}', f'{m["low"]:.6g}',
                                 f'{m["high"]:.6g}'])


def load_world(config_path: str, policy_path: str | None, planning: HRCModel):
    """(the true model, its policy or None when it must be solved); ToolError otherwise."""
    try:
        config = load_config(config_path)
    except ConfigError as exc:
        raise ToolError(f'--true-config: {exc}') from None
    world = HRCModel(config)
    if world.dims != planning.dims:
        raise ToolError(f'--true-config has rho {world.rho}, sigma {world.sigma}; the planning '
                        f'configuration {planning.rho}, {planning.sigma}: they must describe '
                        'the same cell')
    path = policy_path or default_policy_path(config)
    try:
        return world, load_policy(path, config)
    except PolicyError as exc:
        if policy_path:
            raise ToolError(f'--true-policy: {exc}') from None
    return world, None


def _selectors(parser, text: str, known) -> tuple:
    try:
        selectors = items(text, '--selectors')
    except BadName as exc:
        parser.error(f'{exc}; choose from {", ".join(known)}')
    for s in selectors:
        if s not in known:
            parser.error(f'unknown selector {s!r} in --selectors; choose from '
                         f'{", ".join(known)}')
    return selectors


def evaluate_arm_cell(args, parser) -> int:
    """--cell arm: the selectors in the cell with the arm (core.robot.cell)."""
    from ..core.robot.bridge import RobotDescriptionError
    from ..core.robot.cell import (CELL_SELECTORS, DEFAULT_SELECTORS, METRICS, ArmCellSettings,
                                   evaluate_arm, format_arm_paired, format_arm_table,
                                   format_scenario_figures, paired_arm, scenario_figures,
                                   summarize_arm)
    for flag, value in (('--true-config', args.true_config), ('--true-policy', args.true_policy),
                        ('--no-fail-safe', args.no_fail_safe)):
        if value:
            parser.error(f'{flag} is for the model\'s cell; --cell arm does not take it')
    if args.scenario != 'random':
        parser.error('--cell arm runs random task streams (--scenario random)')
    episodes = 200 if args.episodes is None else args.episodes
    task_rate = 0.5 if args.task_rate is None else args.task_rate
    epochs = 50 if args.epochs is None else args.epochs
    selectors = _selectors(parser, ','.join(DEFAULT_SELECTORS) if args.selectors is None
                           else args.selectors, CELL_SELECTORS)
    baseline = args.baseline
    if baseline is None and 'ssm_only' in selectors:
        baseline = 'ssm_only'
    if baseline is not None and baseline not in selectors:
        parser.error(f'--baseline {baseline!r} must be one of --selectors '
                     f'({", ".join(selectors)})')
    if episodes * epochs > MAX_EPISODE_EPOCHS // 1000:
        parser.error(f'--episodes x --epochs = {episodes * epochs:,} is more than '
                     f'{MAX_EPISODE_EPOCHS // 1000:,} epochs per selector in the cell with the '
                     'arm (about an hour)')
    if not args.config:   # the arm's model: its program waits under dp and dm (docs/ROBOT.md)
        args.config = str(arm_config_path())
    try:
        config, model, policy = load_model(args)
        pomdp = load_pomdp(args, config, selectors)
        out = output_folder(args.out)
    except ToolError as exc:
        return fail('hrc-evaluate', exc)
    t0 = time.perf_counter()
    progress = lambda m: print(m, flush=True)   # noqa: E731
    try:
        results = evaluate_arm(model, policy, episodes, epochs, args.seed, task_rate, selectors,
                               args.mode, pomdp, progress=progress, person=args.person)
    except RobotDescriptionError as exc:
        return fail('hrc-evaluate', exc)
    elapsed = time.perf_counter() - t0
    cpu = sum(r.seconds for r in results.values())
    simulated = sum(r.simulated for r in results.values())
    mode = args.mode or config.belief_mode
    print(f'the cell with the arm (UR5e, SSM, bridge; docs/ROBOT.md), {config.source}, policy '
          f'{policy.path}')
    print(f'{episodes} episodes x {epochs} epochs of 1 s, seed {args.seed}, task rate '
          f'{task_rate}, belief {mode}, person {args.person}; {elapsed:.1f} s '
          f'({simulated / max(cpu, 1e-9):.0f}x real time on one core)')
    print(format_arm_table(results))
    control_period = ArmCellSettings().control_period
    print(format_scenario_figures(results, args.person, control_period))
    paired = {}
    if baseline is not None:
        print(format_arm_paired(results, baseline))
        paired = {s: paired_arm(r, results[baseline]) for s, r in results.items()
                  if s != baseline}
    summaries = {s: summarize_arm(r) for s, r in results.items()}
    write_summary_csv(out / 'summary.csv', summaries, METRICS)
    names = [m for m, _ in METRICS] + ['contacts', 'speed_breaches', 'tasks_completed',
                                       'min_margin', 'appearance_violations',
                                       'rest_after_event', 'stop_delay']
    with written(out / 'episodes.csv') as f:
        writer = csv.writer(f)
        writer.writerow(['selector', 'episode'] + names)
        for s, r in results.items():
            for e in range(episodes):
                writer.writerow([s, e] + [f'{getattr(r, n)[e]:.6g}' for n in names])
    report = {'settings': {'cell': 'arm', 'config': config.source, 'policy': policy.path,
                           'episodes': episodes, 'epochs': epochs, 'seed': args.seed,
                           'task_rate': task_rate, 'belief_mode': mode,
                           'person': args.person, 'seconds': round(elapsed, 3)},
              'person': {s: scenario_figures(r, control_period) for s, r in results.items()},
              'selectors': summaries,
              'checks': {s: {'contacts': int(r.contacts.sum()),
                             'speed_breaches': int(r.speed_breaches.sum())}
                         for s, r in results.items()},
              **({'baseline': baseline, 'minus_baseline': paired} if baseline else {})}
    write_text(out / 'summary.json', json.dumps(report, indent=2) + '\n')
    for path in (out / 'summary.csv', out / 'summary.json', out / 'episodes.csv'):
        print(f'wrote {path}')
    return 0


@command('hrc-evaluate')
def main(argv=None) -> int:
    parser = Parser(
        prog='hrc-evaluate',
        description='Compare the action selectors (and the full-information MDP bound) over '
                    'many seeded episodes with random task streams.')
    add_model_arguments(parser)
    add_pomdp_argument(parser)
    parser.add_argument('--cell', default='model', choices=('model', 'arm'),
                        help="'model': the decision model's cell (default); 'arm': the cell "
                             'with the arm, in physical units (docs/ROBOT.md)')
    parser.add_argument('--scenario', default='random', choices=SCENARIOS,
                        help="'random' task streams and humans (default), or the paper's "
                             "'case-study' with human seeds seed, seed+1, ... (as hrc-simulate "
                             '--seed)')
    parser.add_argument('--episodes', type=bounded_int(1, MAX_EPISODES), default=None,
                        help='episodes per selector (default 1000, with --cell arm 200)')
    parser.add_argument('--epochs', type=bounded_int(1, MAX_EPOCHS), default=None,
                        help='epochs per episode (default: 50, the case study 20)')
    parser.add_argument('--seed', type=bounded_int(0, MAX_SEED), default=0)
    parser.add_argument('--task-rate', type=bounded_float(0.0, 1.0), default=None,
                        help='probability of a new task per epoch (one always at epoch 1; '
                             'default 0.2, with --cell arm 0.5: a queue that keeps the cell busy)')
    parser.add_argument('--selectors', default=None,
                        help='comma-separated, from ' + ', '.join(SIMULATION_SELECTORS)
                             + ' (default paper,qmdp,mls,mdp); with --cell arm also the '
                             'baselines ssm_only and integrator (default '
                             'ssm_only,paper,qmdp,integrator)')
    parser.add_argument('--baseline', default=None,
                        help='also print every selector\'s paired cost difference to this one '
                             '(one of --selectors), with 95%% intervals')
    parser.add_argument('--mode', default=None, choices=BELIEF_MODES,
                        help="belief mode (default: the configuration's)")
    parser.add_argument('--no-fail-safe', action='store_true',
                        help='let the selectors act at d = 0 (for studying the fail-safe)')
    parser.add_argument('--true-config', default=None,
                        help='the world the episodes are drawn from, when it is not the '
                        'configuration the robot plans with: adds the regret against planning '
                        'with it')
    parser.add_argument('--true-policy', default=None,
                        help="policy solved for --true-config (default: the shipped one, else "
                        'solved here, about 2 s)')
    parser.add_argument('--waiting-cost', type=bounded_float(0.0, 1e6), default=None,
                        help='charge this per waiting task per epoch (MODEL.md 8.1) and report '
                             "the waiting task-epochs (default: the configuration's "
                             'stream.waiting_cost with a queue, else nothing is charged)')
    parser.add_argument('--person', default='honest', choices=PERSON_SCENARIOS,
                        help="with --cell arm: the person in the cell: 'honest' (default, "
                             "the model's person) or a scenario that tests SSM (walk_in, "
                             'run_in, appear, reach, frozen_tracker, lost_tracker: docs/ROBOT.md '
                             '4); the figures then add SSM against the true bodies')
    parser.add_argument('--out', default='out/evaluate', type=path_text, help='output folder')
    args = parser.parse_args(argv)
    if args.cell != 'arm' and args.person != 'honest':
        parser.error('--person is for the cell with the arm (--cell arm)')
    if args.cell == 'arm' and args.waiting_cost is not None:
        parser.error('--waiting-cost is for the model\'s cell; --cell arm does not take it')
    if args.cell == 'arm':
        return evaluate_arm_cell(args, parser)
    if args.episodes is None:
        args.episodes = 1000
    if args.task_rate is None:
        args.task_rate = 0.2
    if args.true_policy and not args.true_config:
        parser.error('--true-policy needs --true-config')
    selectors = _selectors(parser, 'paper,qmdp,mls,mdp' if args.selectors is None
                           else args.selectors, SIMULATION_SELECTORS)
    if args.true_config and {'pomdp', 'fib'} & set(selectors):
        parser.error('--true-config compares the selectors that read a policy file (paper, '
                     'qmdp, mls, mdp); pomdp and fib would need a POMDP policy of the true '
                     'configuration too')
    if args.baseline is not None and args.baseline not in selectors:
        parser.error(f'--baseline {args.baseline!r} must be one of --selectors '
                     f'({", ".join(selectors)})')
    if args.epochs is None:
        args.epochs = 20 if args.scenario == 'case-study' else 50
    if args.episodes * args.epochs > MAX_EPISODE_EPOCHS:
        parser.error(f'--episodes x --epochs = {args.episodes * args.epochs:,} is more than '
                     f'{MAX_EPISODE_EPOCHS:,} epochs per selector (about an hour)')
    try:
        config, model, policy = load_model(args)
        pomdp = load_pomdp(args, config, selectors)
        world = true_policy = None
        if args.true_config:
            world, true_policy = load_world(args.true_config, args.true_policy, model)
        check_cell(world or model)
        out = output_folder(args.out)
    except ToolError as exc:
        return fail('hrc-evaluate', exc)
    t0 = time.perf_counter()
    if world is not None and true_policy is None:
        from ..core.mdp.solver import solve
        print(f'solving {world.config.source} (no shipped policy was solved for it) ...',
              flush=True)
        true_policy = solve(world)
    progress = lambda m: print(m, flush=True)   # noqa: E731
    # the world's charge, for both runs: the regret compares costs measured the same way
    waiting_cost = charged_waiting_cost(world or model, args.waiting_cost)
    metrics = METRICS if waiting_cost is None else QUEUE_METRICS
    results = evaluate(model, policy, args.episodes, args.epochs, args.seed, args.task_rate,
                       selectors, args.mode, not args.no_fail_safe, progress=progress,
                       scenario=args.scenario, pomdp=pomdp, world=world,
                       waiting_cost=waiting_cost)
    true_results = None
    if world is not None:
        true_results = evaluate(world, true_policy, args.episodes, args.epochs, args.seed,
                                args.task_rate, selectors, args.mode, not args.no_fail_safe,
                                progress=progress, scenario=args.scenario, world=world,
                                waiting_cost=waiting_cost)
    elapsed = time.perf_counter() - t0
    summaries = {s: summarize(r, metrics) for s, r in results.items()}
    differences = ({s: paired_difference(r, results['mdp']) for s, r in results.items()}
                   if 'mdp' in results else {})
    mode = args.mode or config.belief_mode
    planning = ('plans with the fail-safe (only dn at d = 0)' if config.fail_safe_aware
                else 'plans with every action at d = 0')
    print(f'{config.source} ({planning}), policy {policy.path}'
          + ('' if pomdp is None else f', POMDP policy {pomdp.path}'))
    print(f'{args.episodes} episodes x {args.epochs} epochs of scenario {args.scenario}, seed '
          f'{args.seed}' + (f', task rate {args.task_rate}' if args.scenario == 'random' else '')
          + f', belief {mode}, fail-safe {"off" if args.no_fail_safe else "on"}, gamma '
          f'{config.gamma}; {elapsed:.1f} s')
    if waiting_cost is not None:
        print(f'the cost includes {waiting_cost:g} per waiting task per epoch (MODEL.md 8.1)'
              + ('' if config.queue is None else f'; the robot observes the queue length up to '
                 f'{config.queue}'))
    print(format_table(summaries, differences, metrics))
    paired = {}
    if args.baseline is not None:
        print(format_paired(results, args.baseline))
        paired = {s: paired_difference(r, results[args.baseline])
                  for s, r in results.items() if s != args.baseline}
    regret = {}
    if true_results is not None:
        regret = {s: paired_difference(r, true_results[s]) for s, r in results.items()}
        print(f'\nthe world is {world.config.source}: planning with {config.source} against '
              f'planning with the true configuration (policy '
              f'{getattr(true_policy, "path", "solved here")}), same episodes')
        print(format_regret(results, true_results))

    write_summary_csv(out / 'summary.csv', summaries, metrics)
    with written(out / 'episodes.csv') as f:
        writer = csv.writer(f)
        fields = ([m for m, _ in METRICS]
                  + ['longest_collision_run', 'requests', 'tasks_released'])
        if waiting_cost is not None:   # the charge is waiting_cost * discounted_waiting
            fields += ['waiting_epochs', 'discounted_waiting']
        writer.writerow(['selector', 'episode'] + fields)
        for s, r in results.items():
            for e in range(args.episodes):
                writer.writerow([s, e] + [f'{getattr(r, f)[e]:.6g}' for f in fields])
    settings = {'config': config.source, 'config_sha256': config.policy_hash,
                'policy': policy.path, 'pomdp_policy': None if pomdp is None else pomdp.path,
                'episodes': args.episodes, 'epochs': args.epochs,
                'fail_safe_aware': config.fail_safe_aware, 'scenario': args.scenario,
                'seed': args.seed, 'task_rate': args.task_rate, 'belief_mode': mode,
                'fail_safe': not args.no_fail_safe, 'gamma': config.gamma,
                'seconds': round(elapsed, 3)}
    if waiting_cost is not None:
        settings['waiting_cost'] = waiting_cost
    report = {'settings': settings, 'selectors': summaries, 'cost_minus_mdp_cost': differences,
              **({'baseline': args.baseline, 'cost_minus_baseline_cost': paired}
                 if args.baseline else {})}
    if true_results is not None:
        settings.update(true_config=world.config.source,
                        true_config_sha256=world.config.policy_hash,
                        true_policy=getattr(true_policy, 'path', None))
        report.update(true_model={s: summarize(r, metrics) for s, r in true_results.items()},
                      regret=regret)
    write_text(out / 'summary.json', json.dumps(report, indent=2) + '\n')
    outputs = [out / 'summary.csv', out / 'summary.json', out / 'episodes.csv',
               plot_summaries(summaries, out / 'summary.png', differences)]
    if args.baseline is not None:
        with written(out / 'paired.csv') as f:
            writer = csv.writer(f)
            writer.writerow(['selector', 'baseline', 'mean_difference', 'ci95_low',
                             'ci95_high'])
            for s, d in paired.items():
                writer.writerow([s, args.baseline, f'{d["mean"]:.6g}', f'{d["low"]:.6g}',
                                 f'{d["high"]:.6g}'])
        outputs.append(out / 'paired.csv')
    for path in outputs:
        print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
