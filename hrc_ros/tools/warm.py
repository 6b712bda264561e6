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
import tempfile
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
    """The MDP sweep for a model with a queue and for one without (other types), and the
    queue's continuations: in one process, since both solves write the sweep's numba index,
    which numba rewrites without a lock."""
    from ..core.mdp.solver import solve
    solve(_small('stream_queue'))
    solve(_small())


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


# the longest first (seconds on the 2-core machine with an empty cache, both builds: 52, 46,
# 8, 7); no two groups compile the same kernel, so none waits on another's work or rewrites
# another's numba index
GROUPS = {'pomdp': warm_pomdp, 'mdp': warm_mdp, 'fit': warm_fit, 'robot': warm_robot}
KERNEL_FILES = ('core/mdp/_kernels.py', 'core/pomdp/_kernels.py', 'core/learning/_kernels.py',
                'core/robot/_kernels.py', 'core/parallel.py')
GROUP_TIMEOUT = 900.0      # s: a group still compiling then is stopped (its kernels compile later)
STAMP = 'hrc_warm.stamp'   # in core/__pycache__: what the last complete warm-up compiled


def stamp_path(root: Path = PACKAGE) -> Path:
    """Where the stamp of the last complete warm-up of the package at `root` is."""
    return root / 'core' / '__pycache__' / STAMP


def stamp_text(root: Path = PACKAGE) -> str:
    """What a warm-up compiles: the kernels' sources, numba's and Python's versions, the mode."""
    import hashlib
    import numba
    from ..core.parallel import current_mode
    digest = hashlib.sha256(f'{numba.__version__} {sys.version} {current_mode()}'.encode())
    for name in KERNEL_FILES:
        digest.update(name.encode() + b'\0' + (root / name).read_bytes() + b'\0')
    return digest.hexdigest() + '\n'


def needed(root: Path = PACKAGE) -> list[str]:
    """What says a warm-up is due, empty if none: the stamp of the last complete warm-up
    missing or of other sources, versions or mode; a kernel file (relative to the package
    `root`) without a numba index in its __pycache__ at least as new as the source (the cache
    deleted; not checked where NUMBA_CACHE_DIR puts the cache elsewhere)."""
    stale = []
    stamp = stamp_path(root)
    if not stamp.is_file() or stamp.read_text() != stamp_text(root):
        stale.append(STAMP)
    if os.environ.get('NUMBA_CACHE_DIR'):
        return stale
    for name in KERNEL_FILES:
        source = root / name
        if source.name != '_kernels.py':
            continue
        built = [p.stat().st_mtime
                 for p in (source.parent / '__pycache__').glob(f'{source.stem}.*.nbi')]
        if not built or max(built) < source.stat().st_mtime:
            stale.append(name)
    return stale


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='python -m hrc_ros.tools.warm',
        description="compile the package's numba kernels into numba's cache (scripts/test.sh "
                    'runs it with --if-needed before the whole suite)')
    parser.add_argument('--jobs', type=int, default=min(2, os.cpu_count() or 1),
                        help='groups compiled at once (default: 2, or 1 on one CPU)')
    parser.add_argument('--if-needed', action='store_true',
                        help='only if the kernels changed since the last complete warm-up, or '
                             'their cache is gone: what scripts/test.sh runs before the suite')
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
    try:
        while waiting or running:
            while waiting and len(running) < args.jobs:
                name = waiting.pop(0)
                err = tempfile.TemporaryFile('w+')      # not a pipe: nothing can fill it
                running[name] = (time.monotonic(), err, subprocess.Popen(
                    [sys.executable, '-m', 'hrc_ros.tools.warm', '--group', name],
                    stdout=subprocess.DEVNULL, stderr=err, text=True))
            for name, (started, err, proc) in list(running.items()):
                late = time.monotonic() - started > GROUP_TIMEOUT
                if proc.poll() is None and not late:
                    continue
                if late and proc.poll() is None:
                    proc.kill()
                    proc.wait()
                del running[name]
                err.seek(0)
                lines = err.read().strip().splitlines()
                err.close()
                if proc.returncode:
                    failed.append(name)
                    why = (f'stopped after {GROUP_TIMEOUT:.0f} s' if late
                           else (lines[-1:] or ['no output'])[0][:300])
                    print(f'warm: {name}: failed (exit {proc.returncode}): {why}',
                          file=sys.stderr)
                else:
                    print(f'warm: {name} kernels ready in {time.monotonic() - started:.1f} s',
                          file=sys.stderr)
            time.sleep(0.05)
    except KeyboardInterrupt:
        print('warm: interrupted; the kernels not cached compile on first use', file=sys.stderr)
        return 130
    finally:                                # interrupted: no group is left compiling
        for _, err, proc in running.values():
            proc.kill()
            proc.wait()
            err.close()
    print(f'warm: numba kernels compiled and cached in {time.monotonic() - t0:.1f} s'
          + (f' ({len(failed)} group(s) failed: they compile on first use)' if failed else ''),
          file=sys.stderr)
    if failed:
        return 1
    stamp = stamp_path()
    try:
        stamp.parent.mkdir(exist_ok=True)
        stamp.write_text(stamp_text())
    except OSError as exc:                  # the next --if-needed warms again (a few seconds)
        print(f'warm: could not write {stamp}: {exc.strerror}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
