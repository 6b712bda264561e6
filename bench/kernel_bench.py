"""Parallel kernels on a shared machine (issue 17.4): every parallel kernel of core/, serial
against parallel as shipped before (always parallel) and as shipped now (core.parallel's
auto), quiet and beside busy processes this script starts.

    .venv/bin/python bench/kernel_bench.py                       # everything, 5 rounds
    .venv/bin/python bench/kernel_bench.py --rounds 9 --scenarios quiet,spin1 --kernels mdp
    .venv/bin/python bench/kernel_bench.py --skip-solve          # kernels only

Scenarios: `quiet` (nothing started), `spin1` / `spin2` (one / two processes spinning a core
in pure Python), `churn1` (one process streaming a 256 MB numpy copy, memory bandwidth and
CPU), `spin1+churn1`. Each busy process exits on its own when this script ends (it watches
its parent) or after an hour.

Kernels, each as a unit of work of a fixed size run through its `ParallelKernel` (so the
serial variant is the same function compiled without ``parallel``):
- `mdp.sweep`: 60 sweeps of the value iteration of config/default.yaml (419,904 states);
- `pomdp.lb_backup` (8 calls), `pomdp.ub_backup` (3), `pomdp.lb_values` (200),
  `pomdp.ub_values` (100): at the full-size POMDP's fixed points (corners, first beliefs,
  Table 5 rows at every observable state, 8,940 points) with the shipped POMDP policy's
  vectors and its fast informed bound;
- `fit.e_step`: 5 batched E-steps of 16 bootstrap resamples of 100,000 simulated epochs
  (`fit.e_step_batch`, parallel over the resamples; the data as bench/fit_bench.py records
  them).

Modes: `serial` (``HRC_KERNEL_THREADS=serial``), `parallel` (always parallel on 2 threads:
what every kernel did before) and `auto` (the default now; its timings are reset before every
unit, so each unit pays its warm-up and probing as a fresh process does). Within a round the
three modes run one unit each, back to back, in a rotating order; a scenario runs `--rounds`
rounds. The figures are the median seconds per unit with the range over rounds, and the
median over rounds of the paired ratio mode / serial of the same round: on a machine shared
with other work (load average printed per scenario, with the share of the cores busy before
our processes started) only such same-time ratios mean much.

`--solve`: `hrc-solve --config config/default.yaml` end to end, in its own process, with
HRC_KERNEL_THREADS=serial, =2 and unset, `--solve-repeats` times per scenario (interleaved):
the issue's headline figure.

Goal (issue 17.4): beside one or two busy processes no mode slower than 1.3 x serial; quiet,
auto as fast as parallel was.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hrc_ros.core import parallel  # noqa: E402

MODES = ('serial', 'parallel', 'auto')
MODE_VALUE = {'serial': 'serial', 'parallel': '2', 'auto': 'auto'}
SCENARIOS = {'quiet': (), 'spin1': ('spin',), 'spin2': ('spin', 'spin'),
             'churn1': ('churn',), 'spin1+churn1': ('spin', 'churn')}
KERNELS = ('mdp', 'pomdp', 'fit')

_WATCH = ('import os, sys, time\nparent, end = {parent}, time.monotonic() + 3600\n'
          'def alive():\n    return os.getppid() == parent and time.monotonic() < end\n')
BUSY = {
    'spin': _WATCH + 'while alive():\n    for _ in range(200_000):\n        pass\n',
    'churn': _WATCH + ('import numpy as np\na = np.ones(2 ** 25)\nb = np.empty_like(a)\n'
                       'while alive():\n    np.copyto(b, a)\n    np.copyto(a, b)\n'),
}


def start_busy(kinds) -> list:
    procs = [subprocess.Popen([sys.executable, '-c', BUSY[k].format(parent=os.getpid())])
             for k in kinds]
    time.sleep(1.0 if kinds else 0.0)      # let them reach their loops (allocation, import)
    return procs


def stop_busy(procs) -> None:
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def cpu_busy(seconds: float = 1.0) -> float:
    """Share of the machine's cores busy over `seconds` (/proc/stat), before our processes."""
    def read():
        with open('/proc/stat') as f:
            v = [int(x) for x in f.readline().split()[1:9]]
        return sum(v), v[3] + v[4]
    total0, idle0 = read()
    time.sleep(seconds)
    total1, idle1 = read()
    return 1.0 - (idle1 - idle0) / max(1, total1 - total0)


# -- the units of work -------------------------------------------------------------------------
def mdp_units():
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp import _kernels
    from hrc_ros.core.mdp.solver import FactoredBellman
    from hrc_ros.core.model import HRCModel
    op = FactoredBellman(HRCModel(load_config(ROOT / 'config' / 'default.yaml')))
    value, spare = np.zeros(op.model.n_states), np.empty(op.model.n_states)

    def unit():
        v, s = value, spare
        for _ in range(60):
            out, _ = op.apply(v, out=s)
            v, s = out, v
    return {'mdp.sweep': (unit, [_kernels.sweep])}


def pomdp_units():
    from hrc_ros.core.config import load_config
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.pomdp import _kernels as k
    from hrc_ros.core.pomdp import solver as s
    from hrc_ros.core.pomdp.policy import default_pomdp_policy_path, load_pomdp_policy
    config = load_config(ROOT / 'config' / 'default.yaml')
    hrc = s.hrc_pomdp(HRCModel(config))
    pomdp = hrc.pomdp
    policy = load_pomdp_policy(default_pomdp_policy_path(config), config).policy
    points_x, points = s._fixed_points(hrc)
    points_x = np.ascontiguousarray(points_x, dtype=np.intp)
    upper = s.UpperBound.from_fib(policy.q_fib, pomdp.available, points_x, points)
    order = np.ascontiguousarray(pomdp.order, dtype=np.intp)
    group = np.ascontiguousarray(pomdp.group, dtype=np.intp)
    succ_x = np.ascontiguousarray(pomdp.succ_x, dtype=np.intp)
    alpha = policy.alpha
    proj = np.ascontiguousarray(np.einsum('gohk,ik->goih', pomdp.kernel, alpha))
    n = len(points)
    vec, val, old = np.empty((n, alpha.shape[1])), np.empty(n), np.empty(n)
    act, idx = np.empty(n, dtype=np.intp), np.empty(n, dtype=np.intp)
    saw = upper.sawtooth()
    same_as = s.shared_actions(pomdp, share=False)

    def lb():
        for _ in range(8):
            k.lb_backup(points, points_x, succ_x, pomdp.succ_l, pomdp.reward, pomdp.available,
                        group, order, proj, policy.offsets, pomdp.gamma, same_as, vec, act, val,
                        work=n)

    def ub():
        for _ in range(3):
            k.ub_backup(points, points_x, succ_x, pomdp.succ_l, pomdp.reward, pomdp.available,
                        group, order, pomdp.kernel, pomdp.gamma, upper.q_fib, upper.corner,
                        *saw, same_as, val, act, work=n)

    def lb_values():
        for _ in range(200):
            k.lb_values(points, points_x, alpha, policy.offsets, old, idx, work=n)

    def ub_values():
        for _ in range(100):
            k.ub_values(points, points_x, upper.q_fib, pomdp.available, upper.corner, *saw,
                        old, work=n)
    return {'pomdp.lb_backup': (lb, [k.lb_backup]), 'pomdp.ub_backup': (ub, [k.ub_backup]),
            'pomdp.lb_values': (lb_values, [k.lb_values]),
            'pomdp.ub_values': (ub_values, [k.ub_values])}


def fit_units():
    sys.path.insert(0, str(ROOT / 'bench'))
    import fit_bench
    from hrc_ros.core.config import load_config
    from hrc_ros.core.learning import _kernels, fit
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.model import HRCModel
    base = load_config(ROOT / 'config' / 'default.yaml')
    default = HRCModel(base)
    world = HRCModel(fit_bench.true_config(base, 'eager'))
    policy = load_policy(default_policy_path(base), base)
    data = fit.prepare(fit_bench.record(world, default, policy, 100_000, seed=1))
    rng = np.random.default_rng(0)
    n = len(data.episodes)
    weights = np.stack([rng.multinomial(n, np.full(n, 1.0 / n))[data.seg_episode]
                        for _ in range(16)]).astype(float)
    x = np.repeat(fit._pack(fit.Params.from_config(base))[None], len(weights), axis=0)

    def unit():
        for _ in range(5):
            fit.e_step_batch(x, data, weights)
    return {'fit.e_step': (unit, [_kernels.e_step_batch])}


UNIT_MAKERS = {'mdp': mdp_units, 'pomdp': pomdp_units, 'fit': fit_units}


def run_unit(unit, kernels, mode: str) -> float:
    with parallel.mode(MODE_VALUE[mode]):
        if mode == 'auto':
            for kernel in kernels:
                kernel.reset()
        start = time.perf_counter()
        unit()
        return time.perf_counter() - start


def measure(units: dict, rounds: int) -> dict:
    times = {name: {m: [] for m in MODES} for name in units}
    for r in range(rounds):
        for name, (unit, kernels) in units.items():
            for i in range(len(MODES)):
                mode = MODES[(r + i) % len(MODES)]
                times[name][mode].append(run_unit(unit, kernels, mode))
    return times


def solve_times(repeats: int) -> dict:
    out = {m: [] for m in MODES}
    env_of = {'serial': 'serial', 'parallel': '2', 'auto': None}
    import tempfile
    folder = tempfile.mkdtemp(prefix='kernel_bench_')
    command = [str(Path(sys.executable).parent / 'hrc-solve'), '--config',
               str(ROOT / 'config' / 'default.yaml'), '-o', str(Path(folder) / 'p.npz'), '-q']
    for r in range(repeats):
        for i in range(len(MODES)):
            mode = MODES[(r + i) % len(MODES)]
            env = dict(os.environ)
            env.pop(parallel.ENV, None)
            if env_of[mode]:
                env[parallel.ENV] = env_of[mode]
            start = time.perf_counter()
            subprocess.run(command, env=env, check=True, stdout=subprocess.DEVNULL)
            out[mode].append(time.perf_counter() - start)
    import shutil
    shutil.rmtree(folder, ignore_errors=True)
    return out


def summary(name: str, times: dict) -> str:
    serial = np.array(times['serial'])
    cells = []
    for mode in MODES:
        t = np.array(times[mode])
        ratio = np.median(t / serial)
        cells.append(f'{mode} {statistics.median(t):7.3f} s [{t.min():.3f}-{t.max():.3f}] '
                     f'x{ratio:.2f} [{(t / serial).min():.2f}-{(t / serial).max():.2f}]')
    return f'  {name:<17}' + ' | '.join(cells)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--rounds', type=int, default=5)
    parser.add_argument('--scenarios', default=','.join(SCENARIOS))
    parser.add_argument('--kernels', default=','.join(KERNELS))
    parser.add_argument('--skip-solve', action='store_true')
    parser.add_argument('--solve-repeats', type=int, default=3)
    args = parser.parse_args(argv)
    scenarios = [s for s in args.scenarios.split(',') if s]
    kernels = [k for k in args.kernels.split(',') if k]
    for s in scenarios:
        if s not in SCENARIOS:
            parser.error(f'unknown scenario {s!r}; known: {", ".join(SCENARIOS)}')
    for k in kernels:
        if k not in UNIT_MAKERS:
            parser.error(f'unknown kernel group {k!r}; known: {", ".join(UNIT_MAKERS)}')
    print(f'machine: {os.cpu_count()} cores, affinity {len(os.sched_getaffinity(0))}, numba '
          f'threading layer and pool: ', end='', flush=True)
    units = {}
    for k in kernels:
        units.update(UNIT_MAKERS[k]())
    for unit, ks in units.values():      # compile or load every variant once
        for mode in MODES:
            run_unit(unit, ks, mode)
    import numba
    print(f'{numba.threading_layer()}, {numba.config.NUMBA_NUM_THREADS} threads', flush=True)
    print('figures: median seconds per unit [min-max over rounds] and xR = median over rounds '
          'of the ratio to serial in the same round [min-max]')
    for scenario in scenarios:
        busy_before = cpu_busy()
        load_before = os.getloadavg()
        procs = start_busy(SCENARIOS[scenario])
        try:
            times = measure(units, args.rounds)
            solved = solve_times(args.solve_repeats) if not args.skip_solve else None
        finally:
            stop_busy(procs)
        load_after = os.getloadavg()
        print(f'{scenario}: {len(procs)} busy process(es) started; before them the cores were '
              f'{100 * busy_before:.0f}% busy, load average {load_before[0]:.2f} '
              f'(after the scenario {load_after[0]:.2f})', flush=True)
        for name in units:
            print(summary(name, times[name]), flush=True)
        if solved is not None:
            print(summary('hrc-solve', solved), flush=True)
    print(f'\nreproduce: .venv/bin/python bench/kernel_bench.py --rounds {args.rounds} '
          f'--scenarios {",".join(scenarios)} --kernels {",".join(kernels)}'
          + (' --skip-solve' if args.skip_solve else f' --solve-repeats {args.solve_repeats}'))
    print(f'command line: {shlex.join(sys.argv)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
