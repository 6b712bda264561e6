"""cobot_sim_node's start: how long until its first joint state, and the longest gap between
joint states from the first one on, including when its first goal arrives (issue 33: the first
distance query compiled on the arm's thread and froze it for 9 s; the first goal stopped
joint_states for 0.3 s).

    python bench/startup_gaps.py [--rounds 3] [--fresh] [--busy 2]

Each round starts `cobot_sim_node` (its console script, the shipped parameters), feeds it what
the graph does (a speed override of 1.0 at 125 Hz and a skeleton at 50 Hz), and 1 s after its
first joint state sends its first goal (home to the robot station's first waypoint, 2 s).
Over 4 s from the first joint state it reports the largest gap between the stamps of
consecutive joint states received, overall and within 0.5 s of the goal, against 3 control
periods (3 x 0.01 s, the bridge's control_period). `--fresh` gives every round an empty numba
cache (NUMBA_CACHE_DIR), as a fresh install has: the kernels compile in the node's start.
`--busy N` runs N busy processes beside it.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
import rclpy.executors  # noqa: E402
from geometry_msgs.msg import PoseArray  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402
from trajectory_msgs.msg import JointTrajectory  # noqa: E402

from hrc_ros.core.cell.person import SimulatedPerson  # noqa: E402
from hrc_ros.core.robot.bridge import load_programs, load_robot_description  # noqa: E402
from hrc_ros.ros import conversions as conv  # noqa: E402
from hrc_ros.ros import qos  # noqa: E402
from hrc_ros.ros.processes import node_command  # noqa: E402

CONTROL_PERIOD = 0.01


def one_round(fresh: bool) -> dict:
    description = load_robot_description()
    programs = load_programs(description)
    env = dict(os.environ)
    cache = tempfile.TemporaryDirectory(prefix='hrc_numba_') if fresh else None
    if cache:
        env['NUMBA_CACHE_DIR'] = cache.name
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('startup_gaps', context=context)
    stamps: list[int] = []
    node.create_subscription(JointState, 'joint_states',
                             lambda m: stamps.append(m.header.stamp.sec * 10**9
                                                     + m.header.stamp.nanosec), qos.SENSOR_DATA)
    override = node.create_publisher(Float64, 'hrc/speed_override', qos.RELIABLE)
    skeleton = node.create_publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
    goal = node.create_publisher(JointTrajectory, 'joint_trajectory_controller/joint_trajectory',
                                 qos.RELIABLE)
    person = SimulatedPerson(3, seed=0).keypoints()
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    started = time.monotonic()
    process = subprocess.Popen(node_command('cobot_sim_node'), env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first_at = goal_sent = goal_stamp = None
    last_override = last_skeleton = 0.0
    try:
        while time.monotonic() - started < 120:
            executor.spin_once(timeout_sec=0.002)
            now = time.monotonic()
            if now - last_override >= 0.008:
                override.publish(Float64(data=1.0))
                last_override = now
            if now - last_skeleton >= 0.02:
                noisy = person + np.random.normal(0, 0.0015, person.shape)
                skeleton.publish(conv.keypoints_to_msg(noisy, node.get_clock().now().to_msg()))
                last_skeleton = now
            if stamps and first_at is None:
                first_at = now
            if first_at is not None and goal_sent is None and now - first_at >= 1.0:
                start = description.poses['home']
                goal.publish(conv.trajectory_to_msg(description.joint_names,
                                                    [start, programs[0].waypoints[0]], [2.0]))
                goal_sent, goal_stamp = now, node.get_clock().now().nanoseconds
            if first_at is not None and now - first_at >= 4.0:
                break
    finally:
        process.send_signal(2)
        process.wait(20)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        if cache:
            cache.cleanup()
    s = np.array(stamps, dtype=np.int64)
    gaps = np.diff(s) * 1e-9
    near = np.abs(s[1:] - goal_stamp) * 1e-9 <= 0.5 if goal_stamp else np.zeros(0, bool)
    return {'first_s': first_at - started if first_at else None,
            'max_gap_s': float(gaps.max()) if gaps.size else None,
            'max_gap_at_s': float((s[int(np.argmax(gaps))] - s[0]) * 1e-9) if gaps.size else None,
            'max_gap_near_goal_s': float(gaps[near].max()) if near.any() else None,
            'joint_states': len(s)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--fresh', action='store_true')
    parser.add_argument('--busy', type=int, default=0)
    args = parser.parse_args(argv)
    busy = [subprocess.Popen([sys.executable, '-c', 'while 1: pass'])
            for _ in range(args.busy)]
    worst = 0.0
    try:
        for i in range(args.rounds):
            r = one_round(args.fresh)
            worst = max(worst, r['max_gap_s'] or 0.0, r['max_gap_near_goal_s'] or 0.0)
            print(f'round {i + 1}: first joint state {r["first_s"]:.2f} s after the start; '
                  f'{r["joint_states"]} joint states in 4 s; largest gap '
                  f'{1e3 * r["max_gap_s"]:.1f} ms ({r["max_gap_at_s"]:.2f} s after the first), '
                  'within 0.5 s of the first goal '
                  f'{1e3 * r["max_gap_near_goal_s"]:.1f} ms', flush=True)
    finally:
        for p in busy:
            p.kill()
    met = 'met' if worst <= 3 * CONTROL_PERIOD else 'NOT met'
    print(f'largest gap {1e3 * worst:.1f} ms against 3 control periods '
          f'({1e3 * 3 * CONTROL_PERIOD:.0f} ms): {met}; '
          f'{"fresh numba cache, " if args.fresh else ""}{args.busy} busy processes, load '
          f'{os.getloadavg()[0]:.1f}')
    print(f'reproduce: python bench/startup_gaps.py --rounds {args.rounds}'
          + (' --fresh' if args.fresh else '') + f' --busy {args.busy}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
