"""Does the node suite keep its decisions exact when the machine is overloaded?

    python bench/load_robustness.py                        # 5 runs, 3 busy processes, ~2 min
    python bench/load_robustness.py --runs 10 --busy 4 --seed 3 --epoch-period 0.5
    python bench/load_robustness.py --runs 4 --busy 4 --selector pomdp --belief-mode posterior

Each run starts `--busy` processes that spin a CPU core each (on a 2-core machine, 3 of them
leave the four node processes and the observer about a third of the CPU), runs the main job
(`hrc-case-study`, four node processes over DDS) and compares its trajectory, epoch by epoch
(state, observation, action, belief to 1e-5), with the ROS-free simulator for the same seed
and selector and belief mode (posterior: the estimator holds b_k for the task manager's x_k).
A mismatch means that timing, not the inputs' content, decided something: that is a bug in
the ROS layer, which the epoch protocol of docs/DESIGN.md is meant to rule out. The node logs'
warnings are printed with each run, so a legitimate fail-safe `dn` (an input that missed
`input_timeout`) shows as such rather than as a wrong decision.

Before the ordering fixes of docs/DESIGN.md ("Message order") this failed 2 of 3 runs at
`--busy 3` (the cell answered an eligible request with the previous epoch's task state).
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hrc_ros.core.config import BELIEF_MODES, load_config
from hrc_ros.core.model import STATE_VARIABLES, HRCModel
from hrc_ros.core.paths import default_config_path
from hrc_ros.core.mdp.policy import default_policy_path, load_policy
from hrc_ros.core.decision.selection import SELECTORS
from hrc_ros.core.study.simulation import case_study, simulate


def spin(stop) -> None:
    while not stop.is_set():
        pass


def mismatches(out: Path, expected) -> list[int]:
    with open(out / 'trajectory.csv') as f:
        rows = list(csv.DictReader(f))
    if len(rows) != len(expected.rows):
        return [-1]
    return [want['epoch'] for got, want in zip(rows, expected.rows)
            if [int(got[n]) for n in STATE_VARIABLES] != [want[n] for n in STATE_VARIABLES]
            or int(got['O']) != want['O'] or got['action'] != want['action']
            or max(abs(float(got[f'b{h}']) - want[f'b{h}']) for h in range(9)) > 1e-5]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--busy', type=int, default=3, help='CPU-spinning processes')
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--epoch-period', type=float, default=0.5)
    parser.add_argument('--selector', default='paper', choices=SELECTORS)
    parser.add_argument('--belief-mode', default='', choices=('',) + BELIEF_MODES)
    args = parser.parse_args(argv)
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(100, 199)))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    config = load_config(default_config_path())
    expected = simulate(HRCModel(config), load_policy(default_policy_path(), config),
                        case_study(), selector=args.selector, seed=args.seed,
                        mode=args.belief_mode or None)
    print(f'{args.runs} runs of hrc-case-study --seed {args.seed} --epoch-period '
          f'{args.epoch_period} --selector {args.selector} --belief-mode '
          f'{args.belief_mode or expected.mode} with {args.busy} busy processes on '
          f'{os.cpu_count()} cores',
          flush=True)
    exact = 0
    with tempfile.TemporaryDirectory() as tmp:
        for run in range(1, args.runs + 1):
            stop = multiprocessing.Event()
            busy = [multiprocessing.Process(target=spin, args=(stop,), daemon=True)
                    for _ in range(args.busy)]
            for p in busy:
                p.start()
            out = Path(tmp) / f'run{run}'
            start = time.monotonic()
            try:
                proc = subprocess.run(
                    [sys.executable, '-m', 'hrc_ros.ros.case_study', '--out', str(out), '--seed',
                     str(args.seed), '--epoch-period', str(args.epoch_period), '--selector',
                     args.selector, '--belief-mode', args.belief_mode],
                    capture_output=True, text=True, timeout=300)
            finally:
                stop.set()
                for p in busy:
                    p.join()
            took = time.monotonic() - start
            if proc.returncode != 0:
                print(f'run {run}: hrc-case-study failed ({proc.returncode}):\n'
                      f'{proc.stdout[-1500:]}{proc.stderr[-1500:]}')
                continue
            bad = mismatches(out, expected)
            exact += not bad
            warnings = sorted({line.split(']: ', 1)[-1][:110] for log in (out / 'logs').glob(
                '*.log') for line in log.read_text().splitlines() if '[WARN]' in line})
            print(f'run {run}: {"exact" if not bad else f"MISMATCH from epoch {bad[0]}"} '
                  f'({took:.0f} s)' + ''.join(f'\n    warning: {w}' for w in warnings),
                  flush=True)
    print(f'exact trajectories: {exact}/{args.runs}')
    print(f'reproduce: python bench/load_robustness.py --runs {args.runs} --busy {args.busy} '
          f'--seed {args.seed} --epoch-period {args.epoch_period} --selector {args.selector}'
          + (f' --belief-mode {args.belief_mode}' if args.belief_mode else ''))
    return 0 if exact == args.runs else 1


if __name__ == '__main__':
    raise SystemExit(main())
