"""Start and stop the case study's whole graph N times at random moments; count the nodes that
did not exit 0 and the nodes that hung, per node.

    python bench/stop_bench.py [--rounds 200] [--seed 0] [--timeout 10] [--out out/stop_bench]

Each round starts the node set of `hrc-case-study` as it does (`cell_sim_node`,
`task_manager_node`, `belief_estimator_node`, `cell_view_node`, then `decision_node`: console
scripts in their own process groups, `processes.NodeProcesses`, with the shipped
`hrc_params.yaml`, the case study's and the run's parameters as hrc-case-study writes them), and
stops them with SIGINT as hrc-case-study does (`NodeProcesses.stop`; `--order sequential`, the
default: one after the other, the last started first, each once the one before has exited;
`--order together`: every process group at once) at a moment drawn for the round, one of three
phases in turn:

- `import`: all five started at once, SIGINT after a uniform 0-1.5 s (interpreter start-up,
  the imports of rclpy, numpy and the model, and for the fastest the node's construction);
- `start-up`: the first four on the graph, the decision node started, SIGINT after a uniform
  0-1.5 s (the decision node importing or building, the others connecting to it);
- `mid-epoch`: after epoch k (uniform 1-5) was published, plus a uniform fraction of the
  epoch period (0.5 s; `--robot sim`: 1 s) (every node in its loop, the 50 Hz motion streaming).

A node that has not exited `--timeout` s after its signal is a hang: `NodeProcesses.stop` then
writes its stacks into its log and kills it (then signals the next). A log line with a traceback,
KeyboardInterrupt, "Exception ignored" or "Fatal Python error" is counted too. The logs of a round
where anything went wrong are kept under `<out>/failures/`. Printed: per node the exits by code,
the hangs, the bad logs and the stop time (SIGINT to exit), and the command to reproduce the run.

`--launch` measures the stop as `ros2 launch hrc_ros hrc.launch.py robot:=sim hmi:=true` gets it
from a Ctrl-C in its terminal: the launch file's eight nodes (`launch_plan.cell_nodes`, started
with the arguments launch_ros gives them, `launch_plan.ros_arguments`; the HMI on a free port)
all get one SIGINT at the same moment (`--order together`), after epoch k (uniform 1-3) plus a
uniform fraction of the 1 s epoch, beside `--busy N` processes that spin on the CPU for the
whole run (default 8, on this 2-core machine). launch escalates to SIGTERM after 5 s
(`sigterm_timeout`); the target is every node out with 0 within `--within` s (default 3) in
every round. Printed also: the rounds in which every node made it.

    python bench/stop_bench.py --launch [--rounds 50] [--busy 8] [--within 3]
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

from hrc_ros.core.paths import share_dir
from hrc_ros.core.study.simulation import case_study
from hrc_ros.ros import stop
from hrc_ros.ros.case_study import (NODE_NAMES, ROBOT_EPOCH_PERIOD, cell_nodes,
                                    write_run_params,
                                    write_scenario_params)
from hrc_ros.ros import launch_plan
from hrc_ros.ros.processes import STOP_ORDER, STOP_ORDERS, NodeProcesses

PHASES = ('import', 'start-up', 'mid-epoch')
BAD_LOG_LINES = ('Traceback', 'KeyboardInterrupt', 'Exception ignored', 'Fatal Python error')
EPOCH_PERIOD = 0.5
GRAPH_TIMEOUT = 60.0


class Interrupted(Exception):
    pass


class Observer:
    """An rclpy node of its own context: the graph's node names and the published epochs."""

    def __init__(self):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from std_msgs.msg import UInt32
        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, **stop.init_options())
        self.node = rclpy.create_node('stop_bench_observer', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.epoch = 0
        self.node.create_subscription(UInt32, 'hrc/epoch', self._on_epoch,
                                      QoSProfile(depth=10,
                                                 reliability=ReliabilityPolicy.RELIABLE))

    def _on_epoch(self, msg) -> None:
        self.epoch = max(self.epoch, int(msg.data))

    def up(self, names) -> bool:
        return {NODE_NAMES[n] for n in names} <= self.present()

    def present(self) -> set:
        return {n for n, _ in self.node.get_node_names_and_namespaces()}

    def spin_until(self, predicate, timeout: float, nodes: NodeProcesses) -> bool:
        deadline = time.monotonic() + timeout
        while not predicate():
            if stop.requested():
                raise Interrupted()
            if time.monotonic() > deadline or nodes.dead():
                return False
            self.executor.spin_once(timeout_sec=0.005)
        return True

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=0)
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def run_args(robot: str = 'none') -> argparse.Namespace:
    """The parameters hrc-case-study gives a default run (`robot='sim'`: `--robot sim`'s)."""
    period = ROBOT_EPOCH_PERIOD if robot == 'sim' else EPOCH_PERIOD
    return argparse.Namespace(config='', epoch_period=period, view=True, selector='paper',
                              policy='', seed=0, belief_mode='', faults=[],
                              input='joint_states', hmi='', robot=robot)


def one_round(index: int, phase: str, rng: random.Random, work: Path, observer: Observer,
              timeout: float, robot: str = 'none', stop_order: str = STOP_ORDER) -> dict:
    """Start the graph, stop it at the phase's random moment; per node (code, stop seconds,
    bad log lines, stacks dumped)."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    args = run_args(robot)
    params = [share_dir() / 'config' / 'hrc_params.yaml',
              write_scenario_params(work / 'case_study_params.yaml', case_study()),
              write_run_params(work / 'run_params.yaml', args)]
    nodes = NodeProcesses(work, params)
    order = cell_nodes(args)
    observer.epoch = 0
    moment = ''
    try:
        if phase == 'import':
            for executable in order:
                nodes.start(executable)
            delay = rng.uniform(0.0, 1.5)
            moment = f'{delay:.3f} s after the start'
            observer.spin_until(lambda: False, delay, nodes)
        else:
            for executable in order[:-1]:
                nodes.start(executable)
            if not observer.spin_until(lambda: observer.up(order[:-1]), GRAPH_TIMEOUT, nodes):
                moment = 'the first nodes did not come up'
            nodes.start(order[-1])
            if phase == 'start-up':
                delay = rng.uniform(0.0, 1.5)
                moment = moment or f'{delay:.3f} s after the decision node started'
                observer.spin_until(lambda: False, delay, nodes)
            else:
                epoch = rng.randint(1, 5)
                fraction = rng.uniform(0.0, 1.0)
                if observer.spin_until(lambda: observer.epoch >= epoch, GRAPH_TIMEOUT, nodes):
                    observer.spin_until(lambda: False, fraction * args.epoch_period, nodes)
                    moment = f'{fraction:.2f} of epoch {epoch}'
                else:
                    moment = moment or f'epoch {epoch} never came'
        alive = {name for name, p in nodes.processes.items() if p.poll() is None}
        sent = time.monotonic()
        codes = nodes.stop(timeout=timeout, order=stop_order)   # a hang: stacks, killed
        total = time.monotonic() - sent
    finally:
        codes = nodes.stop(timeout=0.1, signum=None)    # after an error: none left running
    return round_result(phase, moment, total, nodes, codes, alive)


def round_result(phase: str, moment: str, total: float, nodes: NodeProcesses, codes: dict,
                 alive: set) -> dict:
    """A round's figures per node: exit code, hang, stop seconds, bad log lines, stacks."""
    stopped = nodes.stop_seconds
    result = {'phase': phase, 'moment': moment, 'nodes': {}, 'total': total}
    for name in nodes.processes:
        log = nodes.log(name, tail=10 ** 6)
        result['nodes'][name] = {
            'code': codes.get(name), 'hang': name in alive and name not in stopped,
            'seconds': stopped.get(name),
            'bad': [line for line in log.splitlines() if any(b in line for b in BAD_LOG_LINES)],
            'stacks': name in nodes.stacks_dumped}
    return result


LAUNCH_ARGUMENTS = {'robot': 'sim', 'hmi': 'true'}


def launch_round(index: int, rng: random.Random, work: Path, observer: Observer,
                 timeout: float) -> dict:
    """`--launch`: the launch file's nodes up and deciding, then one SIGINT to each at once."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    plan = launch_plan.cell_nodes(share_dir(), **LAUNCH_ARGUMENTS)
    nodes = NodeProcesses(work, [])
    observer.epoch = 0
    moment = ''
    try:
        for node in plan:
            # not 8080, held elsewhere; named for the node, which the params file's own
            # `hmi: port: 8080` would outrank
            extra = ['-p', f'{node.name}:port:=0'] if node.name == 'hmi' else []
            nodes.start(node.executable, ros_args=launch_plan.ros_arguments(node, work) + extra)
        epoch = rng.randint(1, 3)
        fraction = rng.uniform(0.0, 1.0)
        names = {node.name for node in plan}
        if observer.spin_until(lambda: names <= observer.present() and observer.epoch >= epoch,
                               GRAPH_TIMEOUT, nodes):
            observer.spin_until(lambda: False, fraction * ROBOT_EPOCH_PERIOD, nodes)
            moment = f'{fraction:.2f} of epoch {epoch}'
        else:
            moment = f'not up or no epoch {epoch} within {GRAPH_TIMEOUT:g} s'
        alive = {name for name, p in nodes.processes.items() if p.poll() is None}
        sent = time.monotonic()
        codes = nodes.stop(timeout=timeout, order='together')
        total = time.monotonic() - sent
    finally:
        codes = nodes.stop(timeout=0.1, signum=None)
    return round_result('launch', moment, total, nodes, codes, alive)


def busy_processes(count: int) -> list:
    """`count` processes that spin on the CPU until killed (the load beside the nodes)."""
    import subprocess
    return [subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                             stdin=subprocess.DEVNULL) for _ in range(count)]


def within_report(results: list[dict], within: float) -> list[str]:
    """The rounds in which every node exited 0 within `within` s of its signal."""
    def clean(row):
        return row['code'] == 0 and not row['hang'] and row['seconds'] is not None \
            and row['seconds'] <= within
    good = sum(all(clean(row) for row in r['nodes'].values()) for r in results)
    stops = [row for r in results for row in r['nodes'].values()]
    return [f'rounds with every node out with 0 within {within:g} s: {good} of {len(results)} '
            f'({sum(map(clean, stops))} of {len(stops)} node stops)']


def report(results: list[dict], args, elapsed: float) -> str:
    names = [n for n in NODE_NAMES if any(n in r['nodes'] for r in results)]  # the graph's
    phases = Counter(r['phase'] for r in results)
    lines = [f'stop_bench: {len(results)} rounds ('
             + ', '.join(f'{p} {phases[p]}' for p in PHASES + ('launch',) if phases[p])
             + f'), seed {args.seed}, stop timeout {args.timeout:g} s, '
             f'{elapsed / 60:.1f} min' + (f', beside {args.busy} busy processes' if args.busy
                                          else '') + f', load average {load()}',
             f'{"node":<24}{"exit 0":>8}{"other exits":>14}{"hangs":>7}{"bad logs":>10}'
             f'{"stop median":>13}{"p99":>8}{"max":>8}']
    totals = Counter()
    for name in names:
        rows = [r['nodes'][name] for r in results if name in r['nodes']]
        zero = sum(row['code'] == 0 and not row['hang'] for row in rows)
        hangs = sum(row['hang'] for row in rows)
        other = Counter(row['code'] for row in rows if row['code'] != 0 and not row['hang'])
        bad = sum(bool(row['bad']) for row in rows)
        times = sorted(row['seconds'] for row in rows if row['seconds'] is not None)
        p99 = times[min(len(times) - 1, int(0.99 * len(times)))] if times else float('nan')
        lines.append(f'{name:<24}{zero:>8}{sum(other.values()):>14}{hangs:>7}{bad:>10}'
                     f'{statistics.median(times) if times else float("nan"):>12.2f}s'
                     f'{p99:>7.2f}s{(times[-1] if times else float("nan")):>7.2f}s'
                     + (f'   codes {dict(other)}' if other else ''))
        totals.update(nonzero=sum(other.values()), hangs=hangs, bad=bad)
    totals_s = sorted(r['total'] for r in results)
    if totals_s:
        lines.append(f'whole stop (first signal to last exit, {args.order}): median '
                     f'{statistics.median(totals_s):.2f} s, max {totals_s[-1]:.2f} s')
    if args.launch:
        lines += within_report(results, args.within)
    for phase in PHASES:
        times = sorted(row['seconds'] for r in results if r['phase'] == phase
                       for row in r['nodes'].values() if row['seconds'] is not None)
        if times:
            lines.append(f'stop time in phase {phase}: median {statistics.median(times):.2f} s, '
                         f'max {times[-1]:.2f} s (every node)')
    lines.append(f'total: {totals["nonzero"]} non-zero exits, {totals["hangs"]} hangs, '
                 f'{totals["bad"]} logs with a traceback or "Exception ignored"')
    for r in results:
        for name, row in r['nodes'].items():
            slow = args.launch and (row['seconds'] or 0) > args.within
            if row['code'] != 0 or row['hang'] or row['bad'] or slow:
                lines.append(f'  round {r["round"]} ({r["phase"]}, {r["moment"]}): {name} '
                             f'exit {row["code"]}{" HANG" if row["hang"] else ""} '
                             + (f'after {row["seconds"]:.2f} s ' if slow else '')
                             + f'{row["bad"][:2]}')
    lines.append('reproduce: python bench/stop_bench.py '
                 f'--rounds {args.rounds} --seed {args.seed} --timeout {args.timeout:g}'
                 + (f' --launch --busy {args.busy} --within {args.within:g}' if args.launch
                    else f' --busy {args.busy}' if args.busy else '')
                 + (f' --phases {args.phases}' if args.phases != ','.join(PHASES)
                    and not args.launch else '')
                 + (f' --robot {args.robot}' if args.robot != 'none' and not args.launch
                    else '')
                 + (f' --order {args.order}' if args.order != STOP_ORDER and not args.launch
                    else ''))
    if args.launch:
        lines.append('(a node\'s stop time is read in turn after the ones before it: an upper '
                     'bound, at most the whole stop)')
    return '\n'.join(lines)


def load() -> str:
    return ' '.join(Path('/proc/loadavg').read_text().split()[:3])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--rounds', type=int, default=200)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--timeout', type=float, default=10.0,
                        help='seconds after SIGINT before a node counts as hung')
    parser.add_argument('--out', default='out/stop_bench')
    parser.add_argument('--phases', default=','.join(PHASES),
                        help=f'the phases to cycle through (default {",".join(PHASES)})')
    parser.add_argument('--robot', default='none', choices=('none', 'sim'),
                        help="sim: the graph of hrc-case-study --robot sim (seven nodes)")
    parser.add_argument('--order', default=STOP_ORDER, choices=STOP_ORDERS,
                        help='how the nodes are signalled (processes.NodeProcesses.stop): one '
                        'after the other, the last started first, each once the one before '
                        f'has exited, or all together (default {STOP_ORDER})')
    parser.add_argument('--launch', action='store_true',
                        help='the stop as ros2 launch gets it: the eight nodes of robot:=sim '
                        'hmi:=true, one SIGINT to each at once (module docstring)')
    parser.add_argument('--busy', type=int, default=None,
                        help='processes spinning on the CPU beside the nodes (default 8 with '
                        '--launch, else 0)')
    parser.add_argument('--within', type=float, default=3.0,
                        help='--launch: the stop time each node must keep (default 3 s)')
    args = parser.parse_args(argv)
    if args.busy is None:
        args.busy = 8 if args.launch else 0
    if args.launch:
        args.order = 'together'          # what a Ctrl-C in launch's terminal does
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if not os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE'):
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(
            share_dir() / 'config' / 'fastdds_fast_discovery.xml')
    phases = [p for p in args.phases.split(',') if p]
    if not phases or set(phases) - set(PHASES):
        parser.error(f'--phases takes some of {",".join(PHASES)}')
    out = Path(args.out)
    failures = out / 'failures'
    shutil.rmtree(failures, ignore_errors=True)
    rng = random.Random(args.seed)
    results: list[dict] = []
    started = time.monotonic()
    busy = busy_processes(args.busy)
    with stop.regime():
        observer = Observer()
        try:
            for index in range(args.rounds):
                phase = 'launch' if args.launch else phases[index % len(phases)]
                if args.launch:
                    result = launch_round(index, rng, out / 'round', observer, args.timeout)
                else:
                    result = one_round(index, phase, rng, out / 'round', observer,
                                       args.timeout, args.robot, args.order)
                result['round'] = index
                results.append(result)
                bad = [n for n, row in result['nodes'].items()
                       if row['code'] != 0 or row['hang'] or row['bad']
                       or (args.launch and (row['seconds'] or 0) > args.within)]
                slowest = max((row['seconds'] or 0 for row in result['nodes'].values()),
                              default=0)
                print(f'round {index:>3} {phase:<9} {result["moment"]:<40} '
                      + (f'FAILED: {", ".join(bad)}' if bad else 'all exit 0')
                      + f' (slowest {slowest:.2f} s, load {load()})', flush=True)
                if bad:
                    shutil.copytree(out / 'round', failures / f'round_{index}')
        except Interrupted:
            print('stop_bench: interrupted', file=sys.stderr)
        finally:
            observer.close()
            for process in busy:
                process.kill()
                process.wait()
    print()
    print(report(results, args, time.monotonic() - started))
    return 0


if __name__ == '__main__':
    sys.exit(main())
