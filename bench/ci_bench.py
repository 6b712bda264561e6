"""Run the test suite as CI does (`CI=true bash .ci/run`), optionally beside busy processes, and
print its time, its result and its time per file.

    nice -n 10 .venv/bin/python bench/ci_bench.py [--runs 1] [--busy 0] [--workers 2] [--out DIR]

`--busy N` starts N processes that spin on the CPU for the whole bench (the load CI meets on a
shared machine; on this 2-core machine `--busy 6` gives a load average of about 8 with the
suite's own). Each run writes its log and its per-file figures (conftest's HRC_TEST_TIMES JSON)
to `<out>/run_<i>.log` / `.json`; printed per run: the exit code, the wall time, the load
average (1 min) at the start and the end and its mean over the run, the passed / failed counts
and the failed tests; then the per-file table of the last run (wall and CPU seconds) and the
command to reproduce. Targets (issue 37): <= 8 min quiet, <= 12 min at load 8, 0 failures in 5
runs in a row at load 8.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load1() -> float:
    return float(Path('/proc/loadavg').read_text().split()[0])


class LoadSampler:
    """The 1-minute load average every 5 s while a run lasts."""

    def __init__(self):
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(5.0):
            self.samples.append(load1())

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return sum(self.samples) / len(self.samples) if self.samples else load1()


def one_run(index: int, out: Path, workers: int) -> dict:
    log, figures = out / f'run_{index}.log', out / f'run_{index}.json'
    env = {**os.environ, 'CI': 'true', 'HRC_TEST_TIMES': str(figures),
           'HRC_TEST_WORKERS': str(workers)}
    start_load = load1()
    sampler = LoadSampler()
    started = time.monotonic()
    with open(log, 'w') as handle:
        code = subprocess.call(['bash', '.ci/run'], cwd=REPO, env=env, stdin=subprocess.DEVNULL,
                               stdout=handle, stderr=subprocess.STDOUT)
    wall = time.monotonic() - started
    mean_load = sampler.stop()
    text = log.read_text(errors='replace')
    # pytest -q ends with the bare line, without -q it is framed in '='
    summary = re.findall(r'^(?:=+ )?(\d.*(?:passed|failed|error).*) in [\d.]+s', text,
                         re.MULTILINE)
    failed = re.findall(r'^(?:FAILED|ERROR) (\S+)', text, re.MULTILINE)
    return {'code': code, 'wall': wall, 'load_start': start_load, 'load_end': load1(),
            'load_mean': mean_load, 'summary': summary[-1] if summary else '(no summary)',
            'failed': failed,
            'files': json.loads(figures.read_text())['files'] if figures.exists() else {}}


def table(files: dict) -> str:
    lines = [f'{"wall s":>8} {"cpu s":>8} {"tests":>6}  file']
    for name, row in sorted(files.items(), key=lambda item: -item[1]['seconds']):
        lines.append(f'{row["seconds"]:8.1f} {row["cpu"]:8.1f} {row["tests"]:6d}  {name}')
    lines.append(f'{sum(r["seconds"] for r in files.values()):8.1f} '
                 f'{sum(r["cpu"] for r in files.values()):8.1f} '
                 f'{sum(r["tests"] for r in files.values()):6d}  all files (summed over workers)')
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--runs', type=int, default=1)
    parser.add_argument('--busy', type=int, default=0, help='busy processes beside the suite')
    parser.add_argument('--workers', type=int, default=2,
                        help='pytest-xdist workers (HRC_TEST_WORKERS; 0: none)')
    parser.add_argument('--out', default='out/ci_bench')
    args = parser.parse_args(argv)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    busy = [subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                             stdin=subprocess.DEVNULL) for _ in range(args.busy)]
    results = []
    try:
        for index in range(args.runs):
            result = one_run(index, out, args.workers)
            results.append(result)
            print(f'run {index}: exit {result["code"]}, {result["wall"]:.0f} s '
                  f'({result["wall"] / 60:.1f} min), load {result["load_start"]:.1f} -> '
                  f'{result["load_end"]:.1f} (mean {result["load_mean"]:.1f}), '
                  f'{result["summary"]}'
                  + (f'; failed: {", ".join(result["failed"])}' if result['failed'] else ''),
                  flush=True)
    finally:
        for process in busy:
            process.kill()
            process.wait()
    if results and results[-1]['files']:
        print()
        print(table(results[-1]['files']))
    failing = sum(r['code'] != 0 for r in results)
    print(f'\n{len(results)} run(s), {failing} failing; walls '
          + ', '.join(f'{r["wall"]:.0f} s' for r in results) + f'; beside {args.busy} busy '
          f'processes, {args.workers} workers, {os.cpu_count()} cores')
    print(f'reproduce: nice -n 10 .venv/bin/python bench/ci_bench.py --runs {args.runs} '
          f'--busy {args.busy} --workers {args.workers}')
    return 0 if failing == 0 else 1


if __name__ == '__main__':
    sys.exit(main())
