"""cobot_sim_node's joint_states rate with the machine loaded (issue 18: >= 100 Hz).

    python bench/sim_rate_bench.py [--busy 0,2,4] [--seconds 15] [--warmup 3]

For each N in `--busy`: N busy processes (`python -c 'while 1: pass'`, at the bench's own
niceness) beside `cobot_sim_node` started as `hrc-case-study` starts it (its console script
with the shipped `hrc_params.yaml`: `rate` 250 Hz, `joint_state_rate` 125 Hz). This process
feeds it what the graph does: a speed override of 1.0 at 125 Hz (the bridge's tick, one per
joint state), a skeleton at 50 Hz (cell_sim's sensor rate; `SimulatedPerson`'s start pose, so
every joint state has a separation too) and one goal (home to 0.6 rad away on every joint and
back, 4 s a segment, repeated), so the arm moves through the measurement. After `--warmup` s,
over `--seconds` s:

- `published`: the node's own `joint_states_hz` (its /diagnostics, one figure a second):
  min / median;
- `received`: joint states received here (best effort as published, a deep history, so one
  taken late by this process, loaded too, still counts), per second of their stamps in the
  window, and the gaps between consecutive received stamps (p99, max);
- `separations per joint state`: hrc/separation messages received per joint state (1: every
  joint state has its separation);
- `stale`: received joint states whose position is not the follower's at the stamp, judged
  from the goal (a cubic at rest at every point): |q(stamp) - q| > 1e-3 rad, where q(stamp)
  is interpolated between the neighbours it was published between (when both are within
  50 ms); a coarse check that the
  stamp goes with the state (published with the stamp of its step);
- `cpu`: the node process's CPU time (user + system, /proc) over the window, % of one core;
- the load average at the end.

Prints the command and one line per N.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from hrc_ros.core.paths import share_dir


def cpu_seconds(pid: int) -> float:
    fields = open(f'/proc/{pid}/stat').read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def measure(busy: int, seconds: float, warmup: float) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseArray  # noqa: F401 - the skeleton type
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64, Float64MultiArray
    from trajectory_msgs.msg import JointTrajectory

    from hrc_ros.core.cell.person import SimulatedPerson
    from hrc_ros.ros import conversions as conv
    from hrc_ros.ros import qos
    from hrc_ros.ros.nodes.robot_bridge_node import load_description
    from hrc_ros.ros.processes import NodeProcesses

    hogs = [subprocess.Popen([sys.executable, '-c', 'while 1: pass']) for _ in range(busy)]
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('bench_sim_rate', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    description = load_description('')
    home = np.asarray(description.poses['home'], dtype=float)
    away = home + 0.6
    rates, received, separations = [], [], []
    node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: rates.extend(
        float(conv.diagnostic_values(s)['joint_states_hz']) for s in m.status
        if s.name == 'cobot_sim: arm'), qos.RELIABLE)
    # best effort as the node publishes, but a deep history: what DDS delivered is counted
    # by its stamps even when this process, loaded too, takes it late
    deep = QoSProfile(depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT)
    node.create_subscription(JointState, 'joint_states', lambda m: received.append(
        (m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec, np.array(m.position))), deep)
    node.create_subscription(Float64MultiArray, 'hrc/separation', lambda m: separations.append(
        m), deep)
    override = node.create_publisher(Float64, 'hrc/speed_override', qos.RELIABLE)
    skeleton = node.create_publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
    goal = node.create_publisher(JointTrajectory, 'joint_trajectory_controller/joint_trajectory',
                                 qos.RELIABLE)
    person = SimulatedPerson(1, seed=0)
    body = person.keypoints()
    node.create_timer(1 / 125, lambda: override.publish(Float64(data=1.0)))
    node.create_timer(1 / 50, lambda: skeleton.publish(
        conv.keypoints_to_msg(body, node.get_clock().now().to_msg())))
    cycles = int((warmup + seconds) / 8) + 2
    path = np.vstack([home] + [away, home] * cycles)
    msg = conv.trajectory_to_msg(description.joint_names, path, np.full(len(path) - 1, 4.0))
    params = [share_dir() / 'config' / 'hrc_params.yaml']
    suite = NodeProcesses(tempfile.mkdtemp(prefix='sim_rate_bench_'), params)
    try:
        suite.start('cobot_sim_node')
        deadline = time.monotonic() + 120.0
        while not rates and time.monotonic() < deadline and not suite.dead():
            executor.spin_once(timeout_sec=0.05)
        if not rates:
            raise RuntimeError('cobot_sim_node did not come up:\n' + suite.logs())
        while goal.get_subscription_count() == 0:
            executor.spin_once(timeout_sec=0.05)
        goal.publish(msg)
        end = time.monotonic() + warmup
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        rates.clear()
        received.clear()
        separations.clear()
        pid = suite.processes['cobot_sim_node'].pid
        cpu0, start = cpu_seconds(pid), time.monotonic()
        first = node.get_clock().now().nanoseconds * 1e-9
        while time.monotonic() - start < seconds:
            executor.spin_once(timeout_sec=0.05)
        elapsed = time.monotonic() - start
        last = node.get_clock().now().nanoseconds * 1e-9
        cpu = (cpu_seconds(pid) - cpu0) / elapsed
        load = os.getloadavg()[0]
        suite.stop()       # what is still queued here: until 0.5 s without a message
        count, quiet, end = len(received), time.monotonic(), time.monotonic() + 30.0
        while time.monotonic() - quiet < 0.5 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
            if len(received) != count:
                count, quiet = len(received), time.monotonic()
    finally:
        suite.stop()
        for hog in hogs:
            hog.kill()
            hog.wait()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    per_state = len(separations) / max(len(received), 1)      # both since the window opened
    received = sorted((r for r in received if first <= r[0] < last), key=lambda r: r[0])
    stamps = np.array([s for s, _ in received])
    gaps = np.diff(stamps) * 1e3
    # the follower's state at each stamp, from the goal: it starts within the first override
    # ramp, so compare each state with the straight interpolation of its neighbours instead
    stale = 0
    for (t0, q0), (t1, q1), (t2, q2) in zip(received, received[1:], received[2:]):
        if 0 < t2 - t0 < 0.05:
            between = q0 + (q2 - q0) * (t1 - t0) / (t2 - t0)
            stale += int(np.max(np.abs(between - q1)) > 1e-3)
    return dict(busy=busy, published_min=min(rates) if rates else float('nan'),
                published_median=float(np.median(rates)) if rates else float('nan'),
                received=len(received) / (last - first), separation=per_state,
                gap_p99=float(np.percentile(gaps, 99)) if gaps.size else float('nan'),
                gap_max=float(gaps.max()) if gaps.size else float('nan'),
                stale=stale, cpu=100 * cpu, load=load, n=len(received))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--busy', default='0,2,4')
    parser.add_argument('--seconds', type=float, default=15.0)
    parser.add_argument('--warmup', type=float, default=3.0)
    args = parser.parse_args(argv)
    print(f'python bench/sim_rate_bench.py {" ".join(argv or sys.argv[1:])}'.rstrip(),
          flush=True)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    for busy in (int(b) for b in args.busy.split(',')):
        r = measure(busy, args.seconds, args.warmup)
        print(f'busy {r["busy"]}: published min {r["published_min"]:.0f} Hz, median '
              f'{r["published_median"]:.0f} Hz; received {r["received"]:.1f} Hz '
              f'({r["n"]} states), gap p99 {r["gap_p99"]:.1f} ms, max {r["gap_max"]:.1f} ms; '
              f'separations per joint state {r["separation"]:.2f}; stale {r["stale"]}; node cpu '
              f'{r["cpu"]:.0f}% of a core; load average {r["load"]:.1f}  target >= 100 Hz',
              flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
