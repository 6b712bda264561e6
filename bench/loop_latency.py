"""Latency of the decision loop on the real ROS graph, against the middleware's own floor.

    .venv/bin/python bench/loop_latency.py                  # ~75 s
    .venv/bin/python bench/loop_latency.py --seconds 20 --lag-seconds 30 --epoch 0.05
    .venv/bin/python bench/loop_latency.py --skip-lag --view   # phase 1 with cell_view_node
    .venv/bin/python bench/loop_latency.py --view-pairs 6 --seconds 20   # paired, ~6 min

Phase 1, the decision loop (separate processes: `belief_estimator_node`, `decision_node`, an
echo node, and this bench, which plays the skeleton tracker and the task manager):

- the bench streams joint states and skeletons at 100 Hz to the belief estimator;
- on each `hrc/epoch` k it waits for the estimator's belief b_k, then publishes the task state
  x_k, the epoch's last input, and takes the time t_in; the decision node decides at once and
  the bench takes t_out when `hrc/action` arrives. Input -> action latency = t_out - t_in: one
  hop into the decision node, the decision, one hop back;
- right after each action the bench sends a ping to the echo node (a bare rclpy node that
  republishes it) and times the round trip: the same two hops with no work, the middleware
  floor. Targets: end-to-end p99 within 2 ms of the echo p99;
- the decision's compute time alone (fault checks and selection, without publishing) is what
  the decision node reports per epoch on /diagnostics (`compute_ms`). Target: p99 < 1 ms.
- with `--view`, `cell_view_node` runs beside them (it listens to the epoch, the belief, the
  distance, the task state, the action, every skeleton and /diagnostics, and draws
  `hrc/markers`, which this bench also subscribes, as RViz would): nothing of the loop waits for
  it, so the figures must not change. `--view-pairs N` runs phase 1 N times without and N
  times with it, alternating which comes first, and prints the paired differences (with - without)
  of the p50 / p99 latencies and of the fail-safe epochs with 95% t intervals: on a shared
  machine the background load drifts, and pairs cancel the drift.

Phase 2, the belief estimator under load: a fresh `belief_estimator_node` gets joint states at
1 kHz (and epochs at 1 Hz) for `--lag-seconds`; its per-second status reports the lag, receive
time - header stamp, of the joint states. The bench compares the mean lag of the first and the
last 5 s (flat = no queue building up) and samples the process's RSS (/proc) at 5 s and at the
end. Joint states are published from a paced thread so the bench's own executor does not
limit the rate.

The bench runs in a private DDS domain (random ROS_DOMAIN_ID 100..199, localhost discovery).
"""

from __future__ import annotations

import argparse
import os
import random
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if __name__ == '__main__' and '--echo' not in sys.argv:
    os.environ['ROS_DOMAIN_ID'] = os.environ.get('HRC_BENCH_DOMAIN_ID',
                                                 str(random.SystemRandom().randint(100, 199)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseArray  # noqa: E402
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32  # noqa: E402

from hrc_ros.core.decision.observation import (synthesize_joint_velocities,  # noqa: E402
                                               synthesize_skeleton)
from hrc_ros.core.config import load_config  # noqa: E402
from hrc_ros.core.mdp.policy import default_policy_path  # noqa: E402
from hrc_ros.ros import conversions as conv  # noqa: E402
from hrc_ros.ros import qos  # noqa: E402

TASK_STATE = dict(zip(('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc'), (1, 1, 3, 0, 0, 0, 0, 0)))
WARMUP_EPOCHS = 20
COMPUTE_TARGET_MS = 1.0
FLOOR_MARGIN_MS = 2.0


def echo_main() -> int:
    """The middleware floor: republish every bench/ping on bench/pong."""
    rclpy.init()
    node = rclpy.create_node('bench_echo')
    pong = node.create_publisher(String, 'bench/pong', qos.RELIABLE)
    node.create_subscription(String, 'bench/ping', pong.publish, qos.RELIABLE)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def script(name: str) -> str:
    beside = Path(sys.executable).parent / name
    return str(beside) if beside.is_file() else name


class Processes:
    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.running: dict[str, subprocess.Popen] = {}

    def start(self, name: str, command: list[str]) -> subprocess.Popen:
        log = open(self.log_dir / f'{name}.log', 'w')
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                   start_new_session=True, env=dict(os.environ))
        log.close()
        self.running[name] = process
        return process

    def stop(self, name: str) -> None:
        process = self.running.pop(name)
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGINT)
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()

    def stop_all(self) -> None:
        for name in list(self.running):
            self.stop(name)


class SensorThread(threading.Thread):
    """Publish joint states (and a skeleton every `skeleton_every` samples) at `rate` Hz."""

    def __init__(self, node, rate: float, skeleton_every: int):
        super().__init__(daemon=True)
        self.joints = node.create_publisher(JointState, 'human/joint_states', qos.SENSOR_DATA)
        self.skeleton = node.create_publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
        self.clock = node.get_clock()
        self.period = 1.0 / rate
        self.skeleton_every = skeleton_every
        rng = np.random.default_rng(0)
        self.velocities = [synthesize_joint_velocities(1 + i % 3, 6, rng=rng) for i in range(30)]
        self.keypoints = synthesize_skeleton(2, rng=rng)
        self.sent = 0
        self.elapsed = 0.0
        self.stop_event = threading.Event()

    @property
    def rate(self) -> float:
        return self.sent / self.elapsed if self.elapsed else 0.0

    def run(self) -> None:
        start = next_time = time.monotonic()
        while not self.stop_event.is_set():
            msg = conv.joint_state_to_msg(conv.HUMAN_JOINTS, self.velocities[self.sent % 30],
                                          stamp=self.clock.now().to_msg())
            self.joints.publish(msg)
            if self.sent % self.skeleton_every == 0:
                self.skeleton.publish(conv.keypoints_to_msg(self.keypoints, msg.header.stamp))
            self.sent += 1
            next_time += self.period
            delay = next_time - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.1:          # fell far behind: do not burst to catch up
                next_time = time.monotonic()
        self.elapsed = time.monotonic() - start


def spin_until(executor, predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.005)
    return True


def percentiles(values, qs=(50, 99)) -> dict:
    arr = np.asarray(values, dtype=float)
    return {q: float(np.percentile(arr, q)) for q in qs} if arr.size else {q: float('nan')
                                                                          for q in qs}


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (/proc/<pid>/stat)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def rss_kib(pid: int) -> int:
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1])
    return -1


# -- phase 1 ----------------------------------------------------------------------------------
class LoopBench:
    def __init__(self, node, executor, queued: int | None = None):
        self.node, self.executor = node, executor
        # a configuration with a queue (MODEL.md 8.1): the task state carries the tasks waiting
        self.task_state = TASK_STATE if queued is None else {**TASK_STATE, 'queued': queued}
        self.task_pub = node.create_publisher(UInt8MultiArray, 'hrc/task_state', qos.LATCHED)
        self.ping_pub = node.create_publisher(String, 'bench/ping', qos.RELIABLE)
        self.epoch = 0
        self.awaiting_belief = False
        self.t_in: float | None = None
        self.t_ping: float | None = None
        self.latency_ms: list[float] = []
        self.epoch_to_action_ms: list[float] = []
        self.echo_ms: list[float] = []
        self.compute_ms: list[float] = []
        self.fail_safe = 0
        self.t_epoch = 0.0
        node.create_subscription(UInt32, 'hrc/epoch', self.on_epoch, qos.RELIABLE)
        node.create_subscription(Float64MultiArray, 'hrc/belief', self.on_belief, qos.LATCHED)
        node.create_subscription(String, 'hrc/action', self.on_action, qos.RELIABLE)
        node.create_subscription(String, 'bench/pong', self.on_pong, qos.RELIABLE)
        node.create_subscription(DiagnosticArray, '/diagnostics', self.on_diagnostics,
                                 qos.RELIABLE)
        node.create_subscription(UInt8, 'hrc/distance_level', lambda m: None, qos.LATCHED)

    def on_epoch(self, msg) -> None:
        self.epoch = msg.data
        self.t_epoch = time.perf_counter()
        self.awaiting_belief = True

    def on_belief(self, msg) -> None:
        if not self.awaiting_belief:
            return
        self.awaiting_belief = False
        task = conv.task_state_to_msg(self.task_state)
        self.t_in = time.perf_counter()
        self.task_pub.publish(task)

    def on_action(self, msg) -> None:
        t_out = time.perf_counter()
        if self.t_in is not None and self.epoch > WARMUP_EPOCHS:
            self.latency_ms.append((t_out - self.t_in) * 1e3)
            self.epoch_to_action_ms.append((t_out - self.t_epoch) * 1e3)
        self.t_in = None
        self.t_ping = time.perf_counter()
        self.ping_pub.publish(String(data='ping'))

    def on_pong(self, msg) -> None:
        if self.t_ping is not None and self.epoch > WARMUP_EPOCHS:
            self.echo_ms.append((time.perf_counter() - self.t_ping) * 1e3)
        self.t_ping = None

    def on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if status.name == 'decision: decision':
                values = conv.diagnostic_values(status)
                if 'compute_ms' in values and int(values.get('epoch', 0)) > WARMUP_EPOCHS:
                    self.compute_ms.append(float(values['compute_ms']))
                    self.fail_safe += values['faults'] != 'none'


def phase_loop(args, processes: Processes, policy: str) -> dict:
    from visualization_msgs.msg import MarkerArray
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('bench_loop', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    queue = load_config(args.config).queue
    bench = LoopBench(node, executor, queued=None if queue is None else queue)
    sensors = SensorThread(node, 100.0, skeleton_every=1)
    pictures = []
    node.create_subscription(MarkerArray, 'hrc/markers', lambda m: pictures.append(1),
                             qos.LATCHED)
    try:
        processes.start('echo', [sys.executable, str(Path(__file__).resolve()), '--echo'])
        view = None
        if args.view:
            view = processes.start('cell_view', [script('cell_view_node')])
            spin_until(executor, lambda: pictures, 60)
        processes.start('belief_estimator', [script('belief_estimator_node'), '--ros-args',
                                             '-p', f'config:={args.config}'])
        spin_until(executor, lambda: node.count_subscribers('human/joint_states') > 0
                   and node.count_subscribers('bench/ping') > 0, 60)
        sensors.start()
        processes.start('decision', [
            script('decision_node'), '--ros-args', '-p', f'policy:={policy}',
            '-p', f'config:={args.config}', '-p', f'selector:={args.selector}',
            '-p', f'epoch_period:={args.epoch}', '-p', f'input_timeout:={0.8 * args.epoch}',
            '-p', 'stale_timeout:=5.0'])
        if not spin_until(executor, lambda: bench.epoch > WARMUP_EPOCHS, 60):
            raise RuntimeError('the decision loop did not start; see the logs in '
                               f'{processes.log_dir}')
        cpu_start, wall_start = (cpu_seconds(view.pid) if view else 0.0), time.monotonic()
        spin_until(executor, lambda: False, args.seconds)
        view_cpu = (100.0 * (cpu_seconds(view.pid) - cpu_start)
                    / (time.monotonic() - wall_start)) if view else 0.0
    finally:
        sensors.stop_event.set()
        sensors.join()
        processes.stop_all()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    return {'latency': bench.latency_ms, 'epoch_to_action': bench.epoch_to_action_ms,
            'echo': bench.echo_ms, 'compute': bench.compute_ms, 'fail_safe': bench.fail_safe,
            'sensor_rate': sensors.rate, 'pictures': len(pictures), 'view_cpu': view_cpu}


# -- phase 2 ----------------------------------------------------------------------------------
def phase_lag(args, processes: Processes) -> dict:
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('bench_lag', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    periods: list[tuple[float, dict]] = []

    def on_diagnostics(msg):
        for status in msg.status:
            if status.name == 'belief_estimator: estimator':
                periods.append((time.monotonic(), conv.diagnostic_values(status)))

    node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, qos.RELIABLE)
    epoch_pub = node.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
    sensors = SensorThread(node, 1000.0, skeleton_every=100)
    rss = {}
    try:
        process = processes.start('belief_estimator_1khz', [script('belief_estimator_node')])
        spin_until(executor, lambda: node.count_subscribers('human/joint_states') > 0, 60)
        spin_until(executor, lambda: False, 1.0)
        sensors.start()
        start = time.monotonic()
        k = 0
        while time.monotonic() - start < args.lag_seconds:
            k += 1
            epoch_pub.publish(UInt32(data=k))
            spin_until(executor, lambda: False, min(1.0, args.lag_seconds
                                                    - (time.monotonic() - start)))
            elapsed = time.monotonic() - start
            if 'early' not in rss and elapsed >= 5.0:
                rss['early'] = rss_kib(process.pid)
        rss['end'] = rss_kib(process.pid)
        sensors.stop_event.set()
        sensors.join()
        spin_until(executor, lambda: False, 1.5)    # the last status
    finally:
        sensors.stop_event.set()
        if sensors.is_alive():
            sensors.join()
        processes.stop_all()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)

    def window(lo, hi):
        rows = [v for t, v in periods if lo <= t - start < hi
                and v.get('joint_state_lag_ms_mean') not in (None, 'none')]
        count = sum(int(v['joint_states_in_period']) for v in rows)
        mean = (sum(float(v['joint_state_lag_ms_mean']) * int(v['joint_states_in_period'])
                    for v in rows) / count) if count else float('nan')
        peak = max((float(v['joint_state_lag_ms_max']) for v in rows), default=float('nan'))
        return mean, peak, count

    first = window(1.0, 6.0)          # statuses cover the preceding second
    last = window(args.lag_seconds - 4.0, args.lag_seconds + 1.0)
    received = sum(int(v['joint_states_in_period']) for _, v in periods)
    return {'first': first, 'last': last, 'rss': rss, 'sent': sensors.sent,
            'rate': sensors.rate, 'received': received}


def compare_view(args, processes: Processes, policy: str) -> None:
    """Phase 1 in `args.view_pairs` pairs, without and with cell_view_node (module docstring)."""
    from scipy import stats
    metrics = ('input->action p50', 'input->action p99', 'epoch->action p50',
               'epoch->action p99', 'fail-safe epochs %')
    rows = {False: [], True: []}
    view_cpu = []
    for pair in range(args.view_pairs):
        for view in ((False, True) if pair % 2 == 0 else (True, False)):
            loop = phase_loop(argparse.Namespace(**{**vars(args), 'view': view}), processes,
                              policy)
            lat, e2a = percentiles(loop['latency']), percentiles(loop['epoch_to_action'])
            fail_safe = 100.0 * loop['fail_safe'] / max(len(loop['compute']), 1)
            rows[view].append((lat[50], lat[99], e2a[50], e2a[99], fail_safe))
            if view:
                view_cpu.append(loop['view_cpu'])
            print(f'  pair {pair + 1} {"view   " if view else "no view"}: '
                  + ', '.join(f'{m} {v:.3f}' for m, v in zip(metrics, rows[view][-1])),
                  flush=True)
    without, with_view = np.array(rows[False]), np.array(rows[True])
    print(f'\nphase 1 with cell_view_node - without, {args.view_pairs} pairs of '
          f'{args.seconds:.0f} s (mean difference, 95% t interval; ms, fail-safe in %); the '
          f'view used {np.mean(view_cpu):.1f}% of a core:')
    for i, metric in enumerate(metrics):
        diff = with_view[:, i] - without[:, i]
        half = stats.t.ppf(0.975, len(diff) - 1) * diff.std(ddof=1) / np.sqrt(len(diff))
        mean = diff.mean()
        print(f'  {metric:20s} without {without[:, i].mean():8.3f}  with '
              f'{with_view[:, i].mean():8.3f}  difference {mean:+8.3f} '
              f'[{mean - half:+.3f}, {mean + half:+.3f}]')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--seconds', type=float, default=30.0,
                        help='measured duration of the decision loop (after warm-up)')
    parser.add_argument('--epoch', type=float, default=0.05, help='epoch_period, seconds')
    parser.add_argument('--lag-seconds', type=float, default=30.0,
                        help='duration of the 1 kHz belief estimator run')
    parser.add_argument('--policy', default='', help="policy file ('' = the shipped one "
                        'solved for --config)')
    parser.add_argument('--config', default=str(ROOT / 'config' / 'default.yaml'),
                        help='model configuration of the nodes (e.g. config/case_study_stream.'
                        'yaml: a task-stream policy, MODEL.md 8)')
    parser.add_argument('--selector', default='paper',
                        help="the decision node's selector (e.g. pomdp: its compute figure)")
    parser.add_argument('--skip-lag', action='store_true', help='phase 1 only')
    parser.add_argument('--view', action='store_true',
                        help='phase 1 with cell_view_node running (hrc/markers)')
    parser.add_argument('--view-pairs', type=int, default=0, metavar='N',
                        help='phase 1 only, N times without and N times with cell_view_node; '
                        'paired differences')
    parser.add_argument('--echo', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        return echo_main()
    policy = args.policy or str(default_policy_path(load_config(args.config)))
    log_dir = Path(os.environ.get('TMPDIR', '/tmp')) / f'hrc_loop_latency_{os.getpid()}'
    log_dir.mkdir(parents=True, exist_ok=True)
    processes = Processes(log_dir)
    command = ' '.join(shlex.quote(a) for a in [sys.executable, 'bench/loop_latency.py',
                                                *(argv if argv is not None else sys.argv[1:])])
    print(f'hrc_ros loop latency (ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]}, '
          f'{os.cpu_count()} CPUs, policy {policy}, selector {args.selector})')
    if args.view_pairs:
        try:
            compare_view(args, processes, policy)
        finally:
            processes.stop_all()
        print(f'\nlogs: {log_dir}\nreproduce: {command}')
        return 0
    try:
        loop = phase_loop(args, processes, policy)
        lag = None if args.skip_lag else phase_lag(args, processes)
    finally:
        processes.stop_all()

    lat, e2a = percentiles(loop['latency']), percentiles(loop['epoch_to_action'])
    echo, compute = percentiles(loop['echo']), percentiles(loop['compute'])
    margin = lat[99] - echo[99]
    print(f'\nphase 1: decision loop, {len(loop["latency"])} epochs of {args.epoch} s, joint '
          f'states at {loop["sensor_rate"]:.0f} Hz, fail-safe epochs {loop["fail_safe"]}, '
          + (f'cell_view_node running ({loop["pictures"]} pictures on hrc/markers, '
             f'{loop["view_cpu"]:.1f}% of a core)' if args.view else 'no view'))
    print(f'  input -> action (task state published -> action received): '
          f'p50 {lat[50]:.3f} ms, p99 {lat[99]:.3f} ms')
    print(f'  echo node round trip (middleware floor):                   '
          f'p50 {echo[50]:.3f} ms, p99 {echo[99]:.3f} ms')
    print(f'  p99 above the floor: {margin:.3f} ms (target < {FLOOR_MARGIN_MS} ms): '
          f'{"PASS" if margin < FLOOR_MARGIN_MS else "FAIL"}')
    print(f'  decision compute alone (node-reported): p50 {compute[50]:.4f} ms, '
          f'p99 {compute[99]:.4f} ms (target < {COMPUTE_TARGET_MS} ms): '
          f'{"PASS" if compute[99] < COMPUTE_TARGET_MS else "FAIL"}')
    print(f'  epoch published -> action received (estimator + task state + decision): '
          f'p50 {e2a[50]:.3f} ms, p99 {e2a[99]:.3f} ms')
    if lag is not None:
        (m1, x1, n1), (m2, x2, n2) = lag['first'], lag['last']
        flat = abs(m2 - m1) < max(1.0, 0.5 * m1)
        growth = (lag['rss']['end'] - lag['rss']['early']) / 1024.0
        print(f'\nphase 2: belief estimator, joint states at {lag["rate"]:.0f} Hz for '
              f'{args.lag_seconds:.0f} s: sent '
              f'{lag["sent"]}, received {lag["received"]} '
              f'({100.0 * lag["received"] / max(lag["sent"], 1):.1f}%)')
        print(f'  lag (receive - stamp), first 5 s: mean {m1:.3f} ms, max {x1:.3f} ms '
              f'({n1} samples)')
        print(f'  lag (receive - stamp), last 5 s:  mean {m2:.3f} ms, max {x2:.3f} ms '
              f'({n2} samples): {"flat" if flat else "NOT flat"}')
        print(f'  RSS at 5 s {lag["rss"]["early"] / 1024:.1f} MiB, at the end '
              f'{lag["rss"]["end"] / 1024:.1f} MiB: growth {growth:+.2f} MiB')
    print(f'\nlogs: {log_dir}\nreproduce: {command}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
