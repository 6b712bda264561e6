"""Compile the package's numba kernels into numba's cache, all at once and each once.

    python -m hrc_ros.tools.warm [--jobs N] [--if-needed]

Why. Every kernel (core/mdp, core/pomdp, core/learning, core/robot) is compiled on its first
call and cached beside its source (``cache=True``), so that later processes load it in a
fraction of a second. Until the cache exists, every process that calls a kernel compiles it,
and processes that start together (the test suite's two workers, hrc-fleet's Ray workers, the
nodes of one launch) each compile the same kernel at once: the MDP sweep alone takes about 17 s
of CPU (its ``parallel=True`` build most of it). scripts/test.sh runs this (`--if-needed`)
before the whole suite: from a fresh clone the suite took 738 s with the kernels compiled as
the tests reached them and 589 s after this warm-up (bench/README.md, "The test suite"); the
warm-up itself takes about 59 s on two cores (35 s for the serial builds alone, which left the
parallel ones to the tests: 677 s). Run it after an install before a plant run
(hrc-fleet's Ray workers would each compile the MDP sweep otherwise).

How. Small instances of the real work, each in its own process (`GROUPS`), `--jobs` at a time:
the same call paths as the real runs, so the kernels are compiled for the types those runs
pass (a signature the warm-up misses is compiled on first use, as without it: arrays that are
read-only or not contiguous, as some callers pass, are other signatures). It compiles the
builds the mode in force runs (``HRC_KERNEL_THREADS``, core/parallel.py): in auto mode each
parallel kernel's serial build on its first call and its parallel one on a later call, so
both; with ``serial`` (the test suite's) the serial builds alone, a fraction of the time.
Prints one line per group and the total on stderr; exit 1 if a group failed (its last
line of error with it: its kernels then compile on first use, as without the warm-up; nothing
else is lost).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

# a tiny model: the kernels' types do not depend on the model's size
PACKAGE = Path(__file__).resolve().parents[1]
SMALL = {'model': {'rho': 1, 'sigma': 1}}


def _small(name: str | None = None):
    from ..core.config import load_config
    from ..core.model import HRCModel
    from ..core.paths import default_config_path, shipped_config_path
    config = load_config(default_config_path() if name is None else shipped_config_path(name))
    return HRCModel(config.with_overrides(SMALL))


def warm_mdp() -> None:
    """The MDP sweep (value iteration) for a model without a queue."""
    from ..core.mdp.solver import solve
    solve(_small())


def warm_queue_mdp() -> None:
    """The MDP sweep for a model with a queue (other types), and the queue's continuations."""
    from ..core.mdp.solver import solve
    solve(_small('stream_queue'))


def warm_pomdp() -> None:
    """The POMDP backups and bounds (Perseus) and the successors' sums of a queue's model,
    whose types the model without a queue shares."""
    from ..core.pomdp.solver import solve_pomdp
    solve_pomdp(_small('stream_queue'), episodes=4, rounds=0)
    solve_pomdp(_small(), episodes=4, rounds=0)


def warm_fit() -> None:
    """The fit's E-step (its batch kernel and the segments), on a few episodes recorded with
    the shipped policy."""
    from ..core.config import load_config
    from ..core.learning import fit as fitting
    from ..core.mdp.policy import default_policy_path, load_policy
    from ..core.model import HRCModel
    from ..core.paths import default_config_path
    from ..core.study.evaluation import BatchSimulator, episodes_of
    config = load_config(default_config_path())
    model = HRCModel(config)
    scenarios, seeds = episodes_of(model, 'random', 4, 20, 0)
    result = BatchSimulator(model, load_policy(default_policy_path(config), config)).run(
        scenarios, seeds, 'paper', explore=0.2, record=True)
    fitting.fit(fitting.prepare(result.recordings(model)), config, n_init=1, seed=0,
                max_iter=3, bootstrap=0)


def warm_robot() -> None:
    """The arm's kernels (separation, link speed, path offset): one short episode of the cell
    with the arm, under SSM alone."""
    from ..core.config import load_config
    from ..core.mdp.policy import default_policy_path, load_policy
    from ..core.model import HRCModel
    from ..core.paths import shipped_config_path
    from ..core.robot.cell import evaluate_arm
    config = load_config(shipped_config_path('arm'))
    evaluate_arm(HRCModel(config), load_policy(default_policy_path(config), config),
                 episodes=1, epochs=3, selectors=('ssm_only',))


# the longest first (seconds on the 2-core machine with an empty cache, both builds: 52, 28, 18,
# 8, 7; the serial builds alone: 35, 10, 7, 6, 9);
# no two groups compile the same kernel for the same types, so none waits on another's work
GROUPS = {'pomdp': warm_pomdp, 'queue_mdp': warm_queue_mdp, 'mdp': warm_mdp,
          'fit': warm_fit, 'robot': warm_robot}
KERNEL_FILES = ('core/mdp/_kernels.py', 'core/pomdp/_kernels.py', 'core/learning/_kernels.py',
                'core/robot/_kernels.py')


def needed(root: Path = PACKAGE) -> list[str]:
    """The kernel files (relative to the package `root`) with no numba index in their
    __pycache__ at least as new as the source: not compiled since they last changed."""
    stale = []
    for name in KERNEL_FILES:
        source = root / name
        cache = source.parent / '__pycache__'
        built = [p.stat().st_mtime for p in cache.glob(f'{source.stem}.*.nbi')]
        if not built or max(built) < source.stat().st_mtime:
            stale.append(name)
    return stale


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='python -m hrc_ros.tools.warm',
        description="compile the package's numba kernels into numba's cache (run once after "
                    'an install; scripts/bootstrap.sh does)')
    parser.add_argument('--jobs', type=int, default=min(2, os.cpu_count() or 1),
                        help='groups compiled at once (default: 2, or 1 on one CPU)')
    parser.add_argument('--if-needed', action='store_true',
                        help='only if a kernel file changed since its cache was written (or '
                             'has none): what scripts/test.sh runs before the whole suite')
    parser.add_argument('--group', choices=sorted(GROUPS), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error(f'--jobs must be at least 1, got {args.jobs}')
    if args.group:                                  # one group, in this process
        GROUPS[args.group]()
        return 0
    if args.if_needed and not needed():
        return 0
    t0 = time.monotonic()
    waiting, running, failed = list(GROUPS), {}, []
    while waiting or running:
        while waiting and len(running) < args.jobs:
            name = waiting.pop(0)
            running[name] = (time.monotonic(), subprocess.Popen(
                [sys.executable, '-m', 'hrc_ros.tools.warm', '--group', name],
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
        for name, (started, proc) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[name]
            err = proc.stderr.read()
            if proc.returncode:
                failed.append(name)
                last = err.strip().splitlines()[-1:] or ['no output']
                print(f'warm: {name}: failed (exit {proc.returncode}): {last[0][:300]}',
                      file=sys.stderr)
            else:
                print(f'warm: {name} kernels ready in {time.monotonic() - started:.1f} s',
                      file=sys.stderr)
        time.sleep(0.05)
    print(f'warm: numba kernels compiled and cached in {time.monotonic() - t0:.1f} s'
          + (f' ({len(failed)} group(s) failed: they compile on first use)' if failed else ''),
          file=sys.stderr)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
