"""hrc-solve: solve the HRC model of a configuration into a policy file.

    hrc-solve --config config/default.yaml -o policies/default.npz
    hrc-solve --method pomdp --config config/default.yaml -o policies/pomdp/default.npz

Prints the residual and elapsed time of every sweep (every `--every` sweeps), the policy's
liveness (the probability that a committed task completes within 50 epochs, exactly, beside the
model's bound: core.mdp.liveness), then the policy file it wrote. `--method pomdp` solves the
POMDP over the belief (core.pomdp.solver: point-based sweeps between a lower and an upper
bound) and prints their progress and final gap.
"""

from __future__ import annotations

import sys

from ..core.config import MAX_SWEEPS
from ..core.model import ACTIONS
from ..core.mdp.liveness import check_liveness
from ..core.mdp.policy import save_policy
from ..core.mdp.solver import memory_estimate, solve
from .common import (MAX_SEED, Parser, ToolError, add_model_arguments, bounded_int, check_memory,
                     command, fail, load_model, output_file, path_text)

POMDP = 'pomdp'
MAX_ROUNDS = 20
MAX_POMDP_EPISODES = 100_000   # x 50 epochs of 9 floats: under 2 GB of gathered beliefs


@command('hrc-solve')
def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog='hrc-solve', description=__doc__.split('\n')[1])
    add_model_arguments(parser, policy=False)
    parser.add_argument('-o', '--output', required=True, type=path_text,
                        help='policy file to write (a name ending in .npz)')
    parser.add_argument('--method', default='value_iteration', choices=('value_iteration', POMDP),
                        help='value_iteration (the MDP, default) or pomdp '
                             '(alpha vectors over the belief; see docs/POMDP.md)')
    parser.add_argument('--episodes', type=bounded_int(1, MAX_POMDP_EPISODES), default=2000,
                        help='pomdp: simulated episodes per round that gather belief points')
    parser.add_argument('--rounds', type=bounded_int(0, MAX_ROUNDS), default=1,
                        help='pomdp: rounds of gathering with the solved policy after the '
                             'first')
    parser.add_argument('--seed', type=bounded_int(0, MAX_SEED), default=0,
                        help='pomdp: seed of the gathering')
    parser.add_argument('--sweeps', type=bounded_int(1, MAX_SWEEPS), default=None,
                        help='run exactly this many sweeps (overrides solver.sweeps)')
    parser.add_argument('--every', type=bounded_int(1, MAX_SWEEPS), default=1,
                        help='print every N sweeps')
    parser.add_argument('-q', '--quiet', action='store_true', help='print only the summary')
    args = parser.parse_args(argv)
    try:
        config, model, _ = load_model(args)
        output = output_file(args.output, suffix='.npz')   # checked before the solve
        check_memory(memory_estimate(model), f'solving {model.n_states:,} states')
    except ToolError as exc:
        return fail('hrc-solve', exc)
    if args.method == POMDP:
        return _solve_pomdp(args, config, model, output)
    sweeps = args.sweeps or config.sweeps
    print(f'hrc-solve: {config.source}: {model.n_states:,} states x {len(ACTIONS)} actions, '
          f'gamma={config.gamma}, eta={config.eta:g}, '
          f'sweeps={"to eta" if sweeps is None else sweeps}', flush=True)

    def progress(sweep: int, residual: float, elapsed: float) -> None:
        if not args.quiet and (sweep % args.every == 0 or sweep == 1):
            print(f'  sweep {sweep:4d}  residual {residual:.3e}  elapsed {elapsed:7.3f} s',
                  flush=True)

    result = solve(model, sweeps=args.sweeps, progress=progress)
    try:
        path = save_policy(output, result, config)
    except OSError as exc:
        return fail('hrc-solve', f'cannot write {output}: {exc.strerror or exc}')
    counts = ' '.join(f'{a}={int((result.policy == i).sum())}' for i, a in enumerate(ACTIONS))
    print(f'hrc-solve: {"converged" if result.converged else "stopped"} after '
          f'{result.iterations} sweeps, Bellman residual {result.residual:.3e}, '
          f'{result.timings["total"]:.2f} s, peak memory {peak_megabytes():.0f} MB')
    print(f'hrc-solve: actions {counts}')
    for line in check_liveness(model, result.policy).lines(model):
        print(f'hrc-solve: {line}')
    print(f'hrc-solve: wrote {path} (config sha256 {config.policy_hash[:12]})')
    return 0


def peak_megabytes() -> float:
    """The process's peak resident memory so far (MB; ru_maxrss is in KiB on Linux)."""
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _solve_pomdp(args, config, model, output) -> int:
    from ..core.pomdp.solver import report_lines, solve_pomdp
    from ..core.pomdp.policy import save_pomdp_policy

    print(f'hrc-solve: {config.source}: POMDP over the belief, {model.n_states:,} states '
          f'({args.episodes} episodes per round, {args.rounds} rounds after the first)',
          flush=True)
    quiet = args.quiet
    result = solve_pomdp(model, episodes=args.episodes, rounds=args.rounds, seed=args.seed,
                         progress=None if quiet else (lambda m: print(f'  {m}', flush=True)))
    try:
        path = save_pomdp_policy(output, result, config)
    except OSError as exc:
        return fail('hrc-solve', f'cannot write {output}: {exc.strerror or exc}')
    for line in report_lines(result.report):
        print(f'hrc-solve: {line}')
    print(f'hrc-solve: wrote {path} ({path.stat().st_size / 1e6:.2f} MB, config sha256 '
          f'{config.policy_hash[:12]})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
