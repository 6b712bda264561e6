"""The plant on Ray against the same work in one process, and the drift test's calibration.

    .venv/bin/python bench/fleet_bench.py --repeat 4 --control  # 8 cells on 2 CPUs, every way
    .venv/bin/python bench/fleet_bench.py --drift            # false-alarm rate and power
    .venv/bin/python bench/fleet_bench.py --cells 4 --cpus 2 --skip-serial
    .venv/bin/python bench/fleet_bench.py --repeat 3 --serial-threads 1

1. Plant (`--cells 8 --cpus 2`). Cells of the full-size model, each with recordings generated
   by the batch simulator (1000 epochs: 20 episodes x 50; half in the default world, half in
   the `reluctant` world of fit_bench.py), `run: always` so every cell runs every stage (read,
   drift test with 99 simulations, fit with 50 bootstrap resamples, value iteration, the
   shadow check over 1000 paired episodes in-sample and its 10 refits (each a fit, a solve
   and four evaluations), outputs). A round runs the same plant (a) on an embedded Ray with
   `--cpus` CPUs (hrc-fleet's scheduler, numba's threads per task as Ray assigns CPUs), then
   (b) serially in one new process, `hrc-fleet run --serial`'s call, once on one CPU
   (`--serial-threads 1`: numba's kernels serial and numpy's BLAS on one thread, as Ray's
   one-CPU tasks run: T_1, the run time on one processor that a speed-up is measured
   against) and once with numba's and BLAS's
   threads free to use every core (`0`: the solves' parallel kernels on both CPUs, so that
   process is itself partly parallel). Each serial run is a new process, so that it pays
   numba's cache loads as Ray's new workers do. All are timed over the same call
   (`fleet.run_plant`: prepare, run, report, write the plant report); Ray's start is not in it
   (the cluster exists). `--repeat N` runs N rounds and gives each speed-up as the mean log
   ratio of the rounds with a 95% t interval, and whether the goal (1.7x) is met (interval
   above it), missed (below) or not settled. Printed per run: wall time, peak memory (the
   largest sum of the proportional set sizes, PSS, shared pages split between the processes
   that map them, of this process and every process it started: Ray's workers, raylet, GCS,
   object store; sampled once a second, `PeakMemory`: faster sampling took CPU from the Ray
   run's busy CPUs; a serial run's is its process's alone), the CPU seconds the machine was
   busy and those the hypervisor stole (/proc/stat: the runs are only comparable on a machine
   that gives them the same CPUs); per serial mode the CPUs it kept busy; per stage the seconds
   per cell. `--timeline JSON` writes Ray's task timeline (chrome://tracing) and prints how
   full the CPUs were kept. Every run must reach the same decisions and figures (the seeds do
   not depend on the scheduling); the script checks it. `--control` adds a last run to each
   round: the plant in two halves (cells 0..3 and 4..7), each serially in its own new one-CPU
   process, both at once, no Ray: what two CPUs of this machine give this work with nothing
   shared but the machine, so `serial / control` is the machine's ceiling for any scheduler
   against that serial run and `control / Ray` what Ray itself costs; the halves must reach
   Ray's decisions and figures.

2. Scaling model. From the per-stage seconds of the plant run: T_cell = the CPU seconds of
   one cell's stages (one CPU each), so a cluster of C cores works through
   3600 * C / T_cell cells per hour at full occupancy; a cell's own critical path (its
   stages in order, the fan-outs on as many cores as they have tasks) bounds how soon one
   cell can finish. Printed for a plant of 100 cells on 2, 16, 64 and 128 cores.

3. Drift (`--drift`). For each world (the default one: false alarms; `reluctant` and `mild`:
   power), `--runs` recordings of `--window` epochs made in closed loop by the running policy
   (paper selector, 20% exploration) with fresh seeds, each tested against the default
   configuration with `--simulations` null simulations at alpha 0.05; printed: the share of
   runs called drift with its 95% Wilson interval. The runs are Ray tasks on `--cpus` CPUs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from scipy.stats import t as student_t

# Ray starts its workers at nice 15 (RAY_worker_niceness) so that the node stays responsive;
# on a machine shared with other work that starves them against this one nice-0 process, and
# the comparison would measure the neighbours. Both runs compete at nice 0 here.
os.environ.setdefault('RAY_worker_niceness', '0')
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hrc_ros.core import parallel  # noqa: E402
from hrc_ros.core.parallel import descendants  # noqa: E402
from hrc_ros.core.plant.spec import load_plant  # noqa: E402
from hrc_ros.tools import fleet  # noqa: E402

RELUCTANT = {'model': {'p_accept': [0.05, 0.35, 0.7],
                       'p_delta': [[0.05, 0.65, 0.30], [0.05, 0.55, 0.40],
                                   [0.02, 0.38, 0.60]]}}
MILD = {'model': {'p_accept': [0.2, 0.65, 0.95]}}     # the default's [0.3, 0.8, 0.99]


def plant_text(cells: int, first: int = 0) -> str:
    """The bench's plant: cells `first` .. `first + cells - 1` (a cell's work depends on its
    index only, so two halves are the whole plant's work)."""
    lines = ['plant: bench', 'defaults:', '  run: always',
             '  drift: {window: 1000, simulations: 99}', '  fit: {bootstrap: 50}',
             '  evaluate: {episodes: 1000}', 'cells:']
    for i in range(first, first + cells):
        world = json.dumps(RELUCTANT if i % 2 else {})
        lines += [f'  - name: cell{i}',
                  f'    generate: {{world: {world}, episodes: 20, epochs: 50, seed: {i}}}']
    return '\n'.join(lines) + '\n'


def pss_kib(pid: int) -> int:
    try:
        for line in Path(f'/proc/{pid}/smaps_rollup').read_text().splitlines():
            if line.startswith('Pss:'):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


class PeakMemory:
    """The largest PSS sum over this process and its descendants, sampled in a thread once a
    `period`. Sampling costs CPU (about 7 ms a sample beside Ray's nine processes: /proc walked
    for the descendants, smaps_rollup read per process), taken from whatever runs: at the 5 Hz
    this bench first sampled, 3.7% of a CPU, which fell on Ray's two busy CPUs but on the idle
    second core of a one-thread serial run; once a second it is 0.7%, and the process list is
    walked every `walk` samples only."""

    def __init__(self, period: float = 1.0, walk: int = 5):
        self.period, self.walk, self.peak, self._stop = period, walk, 0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        pids, samples = set(), 0
        while not self._stop.is_set():
            if samples % self.walk == 0:
                pids = {os.getpid()} | descendants(os.getpid())
            samples += 1
            self.peak = max(self.peak, sum(pss_kib(p) for p in pids))
            self._stop.wait(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def summary(report: dict) -> list:
    return [(e['cell'], e['decision'], e['drift_p'],
             None if e['cost_difference'] is None else round(e['cost_difference']['mean'], 9))
            for e in report['cells']]


LOAD = []


def cpu_times() -> tuple[float, float]:
    """(busy, stolen) seconds of every CPU so far, from /proc/stat: the hypervisor's steal
    is time this VM's vCPUs wanted to run and could not (another guest had the core)."""
    try:
        fields = [int(x) for x in Path('/proc/stat').read_text().split('\n')[0].split()[1:]]
    except (OSError, ValueError):
        return math.nan, math.nan
    hz = os.sysconf('SC_CLK_TCK')
    user, nice, system, idle, iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return (user + nice + system + irq + softirq) / hz, steal / hz


def timed(name: str, run) -> tuple:
    """(wall seconds, peak PSS KiB, report, busy CPU s, stolen CPU s) of `run()`."""
    busy0, stolen0 = cpu_times()
    with PeakMemory() as memory:
        t0 = time.perf_counter()
        report = run()
        seconds = time.perf_counter() - t0
    busy1, stolen1 = cpu_times()
    print(f'  {name:<15} wall {seconds:7.1f} s   peak memory (PSS, all processes) '
          f'{memory.peak / 1024:7.0f} MiB   CPU busy {busy1 - busy0:6.1f} s, stolen by the '
          f'hypervisor {stolen1 - stolen0:4.1f} s   decisions {report["decisions"]}',
          flush=True)
    return seconds, memory.peak, report, busy1 - busy0, stolen1 - stolen0


def ray_run(plant, folder: Path, args) -> dict:
    import ray
    ray.init(num_cpus=args.cpus, include_dashboard=False, logging_level='warning',
             object_store_memory=args.object_store_mb * 2 ** 20)
    try:
        result = timed('ray', lambda: fleet.run_plant(plant, folder,
                                                      progress=fleet.Progress(quiet=True)))
        if args.timeline:
            ray.timeline(filename=args.timeline)
            occupancy(args.timeline, args.cpus, result[0])
    finally:
        ray.shutdown()
    return result


def serial_child(plant_path: str, folder: str, threads: int, name: str | None = None) -> tuple:
    """The serial run in a new process (`serial_run`): `hrc-fleet run --serial`'s call, timed
    over the same span as the Ray run's (`fleet.run_plant`: the cells prepared, run, reported
    and the plant report written); its result ends with the epoch times of its start and end."""
    parallel.limit_threads(threads or None)
    plant = load_plant(Path(plant_path))
    start = time.time()
    result = timed('serial' if name is None else name,
                   lambda: fleet.run_plant(plant, Path(folder), serial=True,
                                           progress=fleet.Progress(quiet=True)))
    return result + (start, time.time())


BLAS_THREADS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')


class one_blas_thread:
    """With `on`, new processes started meanwhile run numpy's BLAS (OpenBLAS) on one thread,
    as Ray's one-CPU workers do (Ray sets OMP_NUM_THREADS to a task's CPUs): a process told
    to use one thread in the kernels but left two in BLAS keeps both CPUs busy (OpenBLAS's
    threads wait spinning), which is not one CPU's work."""

    def __init__(self, on: bool):
        self.on, self.saved = on, {}

    def __enter__(self):
        if self.on:
            self.saved = {k: os.environ.get(k) for k in BLAS_THREADS}
            os.environ.update({k: '1' for k in BLAS_THREADS})

    def __exit__(self, *exc):
        for k, v in self.saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def serial_run(plant_path: Path, folder: Path, threads: int) -> tuple:
    """The same plant serially in a new process, as Ray's workers are new processes: each
    run pays its imports and numba's cache loads once (a second run in this process would
    find them done and be the faster for it). `threads`: 1 is one CPU (numba's kernels
    serial, numpy's BLAS on one thread), 0 numba's and BLAS's threads on every core."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    with one_blas_thread(threads == 1), \
            ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn')) as pool:
        name = 'serial, one CPU' if threads == 1 else 'serial, threads'
        return pool.submit(serial_child, str(plant_path), str(folder), threads,
                           name).result()[:5]


def control_run(folder: Path, args) -> tuple:
    """The control (`--control`): the plant split in two halves, each run serially in its
    own new process, one thread each, both at once. No scheduler, no object store, no
    messages between them: what two CPUs of this machine give the same work when nothing
    but the work itself is shared. Returns (wall from the first start to the last end, the
    two halves' reports)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    half = args.cells // 2
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, (first, count) in enumerate(((0, half), (half, args.cells - half))):
        paths.append(folder / f'half{k}.yaml')
        paths[-1].write_text(plant_text(count, first))
    with one_blas_thread(True), \
            ProcessPoolExecutor(2, mp_context=multiprocessing.get_context('spawn')) as pool:
        futures = [pool.submit(serial_child, str(path), str(folder / path.stem), 1,
                               f'half {k + 1}') for k, path in enumerate(paths)]
        results = [f.result() for f in futures]
    wall = max(r[6] for r in results) - min(r[5] for r in results)
    print(f'  control wall {wall:5.1f} s   (two halves of {half} cells in two processes '
          f'at once, one thread each: no Ray)', flush=True)
    return wall, [r[2] for r in results]


SERIAL_NAMES = {1: 'one CPU (T_1: numba serial, BLAS on one thread)',
                0: "one process with numba's and BLAS's threads on every core"}


def run_plant_bench(args) -> None:
    LOAD.append(f'{os.getloadavg()[0]:.1f}')
    folder = Path(tempfile.mkdtemp(prefix='fleet_bench_'))
    (folder / 'plant.yaml').write_text(plant_text(args.cells))
    plant = load_plant(folder / 'plant.yaml')
    modes = [] if args.skip_serial else args.serial_threads
    print(f'plant of {args.cells} cells (full-size model, 1000 epochs each, run: always), '
          f'Ray on {args.cpus} CPUs against the same plant serially in one process ('
          + '; '.join(SERIAL_NAMES[m] for m in modes) + f'); {args.repeat} round(s), '
          'alternating', flush=True)
    rays, serials, controls = [], {m: [] for m in modes}, []
    for i in range(args.repeat):
        ray_result = ray_run(plant, folder / f'ray{i}', args)
        rays.append(ray_result)
        for m in modes:
            result = serial_run(folder / 'plant.yaml', folder / f'serial{m}_{i}', m)
            serials[m].append(result)
            same = summary(result[2]) == summary(ray_result[2])
            print(f'  round {i + 1}: speed-up {result[0] / ray_result[0]:.2f}x over '
                  f'{SERIAL_NAMES[m]}; same decisions and figures: {same}', flush=True)
        if args.control:
            wall, halves = control_run(folder / f'control{i}', args)
            controls.append(wall)
            same = summary(ray_result[2]) == sum((summary(h) for h in halves), [])
            print(f'  control {i + 1}: Ray {wall / ray_result[0]:.2f}x the control; the same '
                  f'decisions and figures: {same}', flush=True)
    print(f'load average before and after: {LOAD[0]} / {os.getloadavg()[0]:.1f}')
    for m in modes:
        ratios = [s[0] / r[0] for r, s in zip(rays, serials[m])]
        low, high, text = interval_of(ratios)
        verdict = 'met' if low >= 1.7 else ('missed' if high < 1.7 else
                                            'not settled: the interval holds 1.7')
        print(f'  speed-up over {SERIAL_NAMES[m]}: {text} (each '
              + ', '.join(f'{r:.2f}' for r in ratios) + f'); goal >= 1.7x: {verdict}')
        if controls:
            print(f'    the machine\'s ceiling for any scheduler (that serial run / the '
                  f'control): {interval_of([s[0] / c for s, c in zip(serials[m], controls)])[2]}')
        busy = [s[3] / s[0] for s in serials[m]]
        print(f'    CPUs the serial run kept busy on average: {np.mean(busy):.2f}')
    if controls:
        print('  Ray against the control (what Ray itself costs): '
              + interval_of([c / r[0] for r, c in zip(rays, controls)])[2])
    if modes:
        compare_stages(rays[-1][2], serials[modes[0]][-1][2])
    scaling(rays[-1][2], args)


def interval_of(ratios: list) -> tuple[float, float, str]:
    """(low, high, text): the mean log ratio as a ratio with its 95% t interval (each round
    run back to back, so a slow stretch of the machine shows in both sides of a ratio rather
    than in one); one ratio is its own interval."""
    logs = np.log(np.asarray(ratios, dtype=float))
    if len(logs) < 2:
        value = float(np.exp(logs[0]))
        return value, value, f'{value:.2f}x (one round)'
    half = student_t.ppf(0.975, len(logs) - 1) * logs.std(ddof=1) / math.sqrt(len(logs))
    low, high = float(np.exp(logs.mean() - half)), float(np.exp(logs.mean() + half))
    return low, high, (f'{np.exp(logs.mean()):.2f}x [95% t interval {low:.2f}, {high:.2f}] '
                       f'over {len(logs)} rounds')


def stage_means(report: dict) -> dict:
    stages: dict = {}
    for e in report['cells']:
        for k, v in e['seconds'].items():
            stages.setdefault(k, []).append(v)
    return {k: float(np.mean(v)) for k, v in stages.items()}


def compare_stages(ray_report: dict, serial_report: dict) -> None:
    """Each stage's seconds per cell on Ray against the same stage in the serial run: where
    a task on one of two busy CPUs runs slower than the same work alone."""
    ray_s, serial_s = stage_means(ray_report), stage_means(serial_report)
    print('  stage seconds per cell, Ray / serial: ' + ', '.join(
        f'{k} {ray_s[k]:.2f}/{serial_s.get(k, float("nan")):.2f}' for k in ray_s))
    print(f'  in all {sum(ray_s.values()):.1f} / {sum(serial_s.values()):.1f} s per cell')


def occupancy(path: str, cpus: int, wall: float) -> None:
    """From Ray's timeline: the seconds the workers spent in tasks (with their arguments'
    fetching and the results' storing), the time with fewer tasks than CPUs, and the stretch
    at the end when the last tasks run alone."""
    events = [e for e in json.loads(Path(path).read_text()) if e.get('ph') == 'X']
    spans = [(e['ts'] / 1e6, (e['ts'] + e['dur']) / 1e6) for e in events
             if e.get('cat') == 'task::stage_task']
    parts = {what: sum(e['dur'] for e in events if e.get('cat') == f'task:{what}') / 1e6
             for what in ('deserialize_arguments', 'execute', 'store_outputs')}
    if not spans:
        print(f'  timeline {path}: no task spans found')
        return
    start, end = min(s for s, _ in spans), max(e for _, e in spans)
    marks = sorted([(s, 1) for s, _ in spans] + [(e, -1) for _, e in spans])
    busy, below, running, last = 0.0, 0.0, 0, start
    for t, step in marks:
        busy += running * (t - last)
        if running < cpus:
            below += t - last
        running, last = running + step, t
    print(f'  timeline {path}: tasks from first start to last end {end - start:.1f} s of '
          f'{wall:.1f} s wall; task seconds {busy:.1f} ({busy / (cpus * (end - start)):.0%} '
          f'of {cpus} CPUs); fewer tasks than CPUs for {below:.1f} s; in the tasks: '
          + ', '.join(f'{k.replace("_", " ")} {v:.1f} s' for k, v in parts.items()))


def scaling(report: dict, args) -> None:
    """Cells per hour per core from the stages' CPU seconds (module docstring)."""
    per_cell = [sum(e['seconds'].values()) for e in report['cells'] if e['seconds']]
    stages: dict = {}
    for e in report['cells']:
        for k, v in e['seconds'].items():
            stages.setdefault(k, []).append(v)
    t_cell = float(np.mean(per_cell))
    print('  stage seconds per cell (mean over cells, summed over its tasks): '
          + ', '.join(f'{k} {np.mean(v):.2f}' for k, v in stages.items()))
    # the refits run beside each other (one per task) and beside the in-sample shadow
    chunks = {'null': math.ceil(99 / 10), 'boot': math.ceil(50 / 10), 'refit': 10}
    path = sum(np.mean(v) / chunks.get(k, 1) for k, v in stages.items())
    print(f'  one cell: {t_cell:.1f} CPU s in all; critical path with its fan-outs spread '
          f'{path:.1f} s; {3600 / t_cell:.0f} cells per hour per core')
    for cores in (2, 16, 64, 128):
        hours = 100 * t_cell / (3600 * cores)
        print(f'  100 cells on {cores:>3} cores: {60 * max(hours, path / 3600):6.1f} min '
              f'(at full occupancy; no less than one cell\'s critical path)')


# -- the drift test's calibration ---------------------------------------------------------------
def drift_run(world: dict, seed: int, window: int, simulations: int) -> float:
    """The p-value of one closed-loop recording of `window` epochs of world `world`."""
    from hrc_ros.core.config import load_config
    from hrc_ros.core.learning.fit import prepare
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import default_config_path
    from hrc_ros.core.plant import drift
    from hrc_ros.core.plant.stages import tail
    from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of
    base = load_config(default_config_path())
    model = HRCModel(base)
    policy = load_policy(default_policy_path(base), base)
    truth = HRCModel(base.with_overrides(world)) if world else model
    scenarios, seeds = episodes_of(model, 'random', math.ceil(window / 50), 50, 10_000 + seed)
    result = BatchSimulator(model, policy, world=truth).run(scenarios, seeds, 'paper',
                                                            explore=0.2, record=True)
    data = prepare(tail(result.recordings(truth), window))
    s = drift.statistic(data, base)
    null = drift.null_statistics(data, base, s.pi_running,
                                 [[seed, 1, b] for b in range(simulations)])
    return drift.p_value(s.lr, null)


def wilson(k: int, n: int) -> tuple[float, float]:
    z = 1.959964
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def run_drift_bench(args) -> None:
    import ray
    ray.init(num_cpus=args.cpus, include_dashboard=False, logging_level='warning')
    task = ray.remote(drift_run)
    try:
        for name, world, runs in (('default (false alarms)', {}, args.runs),
                                  ('reluctant (power)', RELUCTANT, args.power_runs),
                                  ('mild: p_accept 0.2/0.65/0.95 (power)', MILD,
                                   args.power_runs)):
            t0 = time.perf_counter()
            ps = ray.get([task.remote(world, r, args.window, args.simulations)
                          for r in range(runs)])
            k = sum(p < 0.05 for p in ps)
            low, high = wilson(k, runs)
            print(f'{name:<40} drift called in {k}/{runs} = {k / runs:.3f} '
                  f'[{low:.3f}, {high:.3f}] at alpha 0.05; p quartiles '
                  f'{np.round(np.percentile(ps, [25, 50, 75]), 3)}; '
                  f'{time.perf_counter() - t0:.0f} s', flush=True)
    finally:
        ray.shutdown()
    print(f'(window {args.window} epochs, {args.simulations} simulations per test, '
          f'{args.cpus} CPUs)')


def serial_modes(text: str) -> list[int]:
    modes = [int(v) for v in text.split(',') if v.strip()]
    if not modes or any(m not in SERIAL_NAMES for m in modes):
        raise argparse.ArgumentTypeError(f'a comma list of 1 and 0, got {text!r}')
    return modes


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--cells', type=int, default=8)
    parser.add_argument('--cpus', type=int, default=2)
    parser.add_argument('--object-store-mb', type=int, default=500)
    parser.add_argument('--skip-serial', action='store_true')
    parser.add_argument('--repeat', type=int, default=1,
                        help='rounds of runs (Ray, then each serial run, then the control): '
                        'each speed-up as the mean log ratio with a 95%% t interval')
    parser.add_argument('--serial-threads', type=serial_modes, default=[1, 0],
                        help="the serial runs of a round: 1 one CPU (T_1), 0 numba's and "
                        "BLAS's threads on every core (default: 1,0, both)")
    parser.add_argument('--control', action='store_true',
                        help='in each round, the control: the plant in two halves, two '
                        'one-thread processes at once, no Ray (what the machine gives the '
                        'work on two CPUs)')
    parser.add_argument('--timeline', default=None, metavar='JSON',
                        help="write Ray's task timeline (chrome://tracing) and print how busy "
                        'the CPUs were')
    parser.add_argument('--drift', action='store_true', help='the drift calibration instead')
    parser.add_argument('--runs', type=int, default=200, help='--drift: runs in the default '
                        'world')
    parser.add_argument('--power-runs', type=int, default=50)
    parser.add_argument('--window', type=int, default=1000)
    parser.add_argument('--simulations', type=int, default=39)
    args = parser.parse_args(argv)
    print(f'command: .venv/bin/python bench/fleet_bench.py {" ".join(sys.argv[1:])}')
    if args.drift:
        run_drift_bench(args)
    else:
        run_plant_bench(args)
    return 0


if __name__ == '__main__':
    sys.exit(main())
