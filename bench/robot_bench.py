"""The robot side's targets (issue 18), measured: batch speed, separation query, bridge compute,
SSM violations.

    python bench/robot_bench.py [--episodes 20] [--node-steps 6000] [--sim-seconds 10]
                                [--violation-episodes 1000] [--violation-epochs 20]
                                [--skip-violations]

1. Batch speed: `--episodes` seeded episodes of the cell with the arm (50 epochs of 1 s,
   ssm_only and paper), pinned to one core; simulated seconds / CPU seconds of the process
   (target >= 50x real time on one core). Wall time is printed too (the machine may be shared).
2. Separation query: `Arm.separation` (MuJoCo forward kinematics + the capsule distances of
   the 9 arm capsules x 12 body capsules) at random joint angles, 20,000 calls: p50 and p99
   (target < 0.2 ms).
3. Bridge compute per message: every call the phase-2 node makes into `Bridge` (joint state +
   tick every control period, 50 Hz here, skeleton at 30 Hz, task state and action per epoch)
   timed over the batch cell's episodes, p50 / p99 / max (target p99 < 1 ms).
4. The node's compute per message: `robot_bridge_node` in this process (real rclpy, its
   publishers on DDS, a subscriber of its override so that it ticks), each message handled
   as its subscription does (the conversion, the core, the publishing), timed from the
   message to the handler's return: `--node-steps` joint states at 100 Hz from the core's
   trajectory follower running the node's goals under its override, skeletons of a person
   walking towards the arm and away at 30 Hz, a task state and an action each second (the
   actions ct, nw, dp, nw, dm, nw, dn, nw in turn). The deserialisation and the executor are
   rclpy's and not counted. Printed as the CPU time of the node's thread per message (target
   p99 < 1 ms) and as wall time, which on a loaded machine adds the preemptions.
5. cobot_sim_node's joint_states rate: the node as a process (its console script) for
   `--sim-seconds`, its own count of what it published each second (`joint_states_hz` in its
   status) and what a subscriber in this process received (target >= 100 Hz; 125 nominal).
6. SSM violations over `--violation-episodes` batch episodes of each of ssm_only and paper
   (samples where the arm moved while the true separation was below S_p: target 0), with the
   contacts and speed-bound breaches.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from hrc_ros.core.cell.person import SimulatedPerson
from hrc_ros.core.cell.tracking import K4ABT_JOINTS
from hrc_ros.core.config import load_config
from hrc_ros.core.mdp.policy import default_policy_path, load_policy
from hrc_ros.core.model import HRCModel
from hrc_ros.core.paths import arm_config_path
from hrc_ros.core.robot import bridge as bridge_module
from hrc_ros.core.protocol import Stamp
from hrc_ros.core.robot.arm import Arm, body_capsules
from hrc_ros.core.robot.cell import ArmCell, person_seed
from hrc_ros.core.study.evaluation import episodes_of


def pin_to_one_core() -> str:
    try:
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f'pinned to CPU {cpu}'
    except (AttributeError, OSError):
        return 'not pinned'


def percentiles(samples_s) -> str:
    x = np.asarray(samples_s) * 1e3
    return (f'p50 {np.percentile(x, 50):.3f} ms, p99 {np.percentile(x, 99):.3f} ms, '
            f'max {x.max():.3f} ms ({x.size} calls)')


class TimedBridge(bridge_module.Bridge):
    """The bridge with every call the node makes timed (perf_counter)."""

    samples: list = []

    def _timed(self, name, *args):
        t0 = time.perf_counter()
        out = getattr(super(), name)(*args)
        TimedBridge.samples.append(time.perf_counter() - t0)
        return out

    def joint_state(self, *args):
        return self._timed('joint_state', *args)

    def skeleton(self, *args):
        return self._timed('skeleton', *args)

    def task_state(self, *args):
        return self._timed('task_state', *args)

    def action(self, *args):
        return self._timed('action', *args)

    def tick(self, *args):
        return self._timed('tick', *args)


NODE_ACTIONS = ('ct', 'nw', 'dp', 'nw', 'dm', 'nw', 'dn', 'nw')


def node_compute(steps: int) -> list:
    """Per-message compute of robot_bridge_node's handlers (module docstring, 4): the wall
    times and the CPU times of the calling thread (s); on a shared machine the wall times
    include the time the process was preempted."""
    import rclpy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64, String

    from hrc_ros.core.model import TASK_VARIABLES
    from hrc_ros.core.robot.arm import TrajectoryFollower
    from hrc_ros.ros import conversions as conv
    from hrc_ros.ros import qos
    from hrc_ros.ros.nodes.robot_bridge_node import RobotBridgeNode, skeleton_converter

    context = rclpy.Context()
    rclpy.init(context=context)
    from rclpy.parameter import Parameter
    node = RobotBridgeNode(context=context, parameter_overrides=[     # the probe is the arm
        Parameter('override_consumers', value=['bench_probe'])])
    probe = rclpy.create_node('bench_probe', context=context)
    probe.create_subscription(Float64, node.override_topic, lambda _: None, qos.RELIABLE)
    deadline = time.monotonic() + 10.0
    while node.override_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    follower = TrajectoryFollower(node.description.poses['home'],
                                  node.description.ssm.deceleration)
    skeleton = skeleton_converter(node.get_parameter('robot_frame').value, None)
    far, near = np.array([2.5, -1.5, 1.0]), np.array([0.5, -0.35, 0.8])
    offsets = np.array([[0, 0, 0], [0, 0, 0.3], [0, 0, 0.6], [0.15, 0, 0.3], [-0.15, 0, 0.3],
                        [0, 0.1, -0.4], [0, -0.1, -0.4]])
    wall, cpu, override = [], [], 0.0

    def timed(convert, handle, msg, *extra):
        """handle(convert(msg), *extra), as `Inputs.subscribe` calls them, timed."""
        w0, c0 = time.perf_counter(), time.thread_time()
        handle(convert(msg), *extra)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.thread_time() - c0)

    try:
        for step in range(steps):
            stamp = node.get_clock().now().to_msg()
            if step % 100 == 0:
                epoch = step // 100
                state = {name: 0 for name in TASK_VARIABLES}
                state.update(tp=1 + epoch // len(NODE_ACTIONS) % 3, tc=3, tx=0)
                timed(conv.task_state_from_msg, node._on_task_state,
                      conv.task_state_to_msg(state), Stamp(time.time_ns(), epoch + 1))
                timed(conv.action_from_msg, node._on_action,
                      String(data=NODE_ACTIONS[epoch % len(NODE_ACTIONS)]),
                      Stamp(time.time_ns(), epoch + 1))
            if step % 3 == 0:                    # 33 Hz
                u = 0.5 - 0.5 * np.cos(2 * np.pi * step / 1500)     # 15 s out and back
                msg = conv.keypoints_to_msg((far + (near - far) * u)[None] + offsets, stamp)
                timed(skeleton, node._on_skeleton, msg, Stamp(time.time_ns(), step // 3 + 1))
            state = follower.step(0.01, override)
            msg = JointState(name=list(node.description.joint_names),
                             position=state.q.tolist(), velocity=state.qd.tolist())
            msg.header.stamp = stamp
            timed(lambda m: m, node._on_joint_state, msg, Stamp(time.time_ns(), step + 1))
            command = node.command
            override = command.override
            if command.trajectory is not None:
                follower.follow(command.trajectory)
    finally:
        node.destroy_node()
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
    return wall, cpu


def sim_rate(seconds: float) -> tuple[list, float]:
    """cobot_sim_node's published joint-state rates (Hz, one per status) and the rate a
    subscriber here received over `seconds` (module docstring, 5)."""
    import tempfile

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from hrc_ros.ros import conversions as conv
    from hrc_ros.ros import qos
    from hrc_ros.ros.processes import NodeProcesses

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('bench_sim_rate', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    rates, received = [], []
    node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: rates.extend(
        float(conv.diagnostic_values(s)['joint_states_hz']) for s in m.status
        if s.name == 'cobot_sim: arm'), qos.RELIABLE)
    node.create_subscription(JointState, 'joint_states', lambda m: received.append(
        time.monotonic()), qos.SENSOR_DATA)
    suite = NodeProcesses(tempfile.mkdtemp(prefix='robot_bench_'), [])
    try:
        suite.start('cobot_sim_node')
        deadline = time.monotonic() + 120.0
        while len(rates) < 2 and time.monotonic() < deadline and not suite.dead():
            executor.spin_once(timeout_sec=0.05)
        rates.clear()
        start, first = time.monotonic(), len(received)
        while time.monotonic() - start < seconds:
            executor.spin_once(timeout_sec=0.05)
        got = (len(received) - first) / (time.monotonic() - start)
    finally:
        suite.stop()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    return rates, got


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--episodes', type=int, default=20)
    parser.add_argument('--node-steps', type=int, default=6000)
    parser.add_argument('--sim-seconds', type=float, default=10.0)
    parser.add_argument('--violation-episodes', type=int, default=1000)
    parser.add_argument('--violation-epochs', type=int, default=20)
    parser.add_argument('--skip-violations', action='store_true')
    args = parser.parse_args(argv)
    print(f'python bench/robot_bench.py {" ".join(argv or sys.argv[1:])}'.rstrip())
    print(pin_to_one_core(), f'load average {os.getloadavg()[0]:.1f}')
    config = load_config(arm_config_path())     # the arm's model, as hrc-evaluate --cell arm
    model = HRCModel(config)
    policy = load_policy(default_policy_path(config), config)

    # 2. separation query
    arm = Arm()
    person = SimulatedPerson(1, seed=0)
    body = body_capsules(person.keypoints(), K4ABT_JOINTS)
    rng = np.random.default_rng(0)
    qs = rng.uniform(-np.pi, np.pi, (20_000, 6))
    arm.separation(qs[0], body)
    times = []
    for q in qs:
        t0 = time.perf_counter()
        arm.separation(q, body)
        times.append(time.perf_counter() - t0)
    print(f'separation query (FK + 9 x 12 capsules): {percentiles(times)}  target < 0.2 ms')

    # 1 and 3. batch speed and bridge compute
    original = bridge_module.Bridge
    import hrc_ros.core.robot.cell as cell_module
    cell_module.Bridge = TimedBridge
    try:
        cell = ArmCell(model, policy)
        scenarios, seeds = episodes_of(model, 'random', args.episodes, 50, 0, 0.5)
        cell.episode(scenarios[0], seeds[0], person_seed(0, 0), 'paper')   # warm up
        TimedBridge.samples = []
        for selector in ('ssm_only', 'paper'):
            cpu0, wall0 = time.process_time(), time.perf_counter()
            simulated = 0.0
            for e, (scenario, seed) in enumerate(zip(scenarios, seeds)):
                simulated += cell.episode(scenario, seed, person_seed(0, e), selector).seconds
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
            print(f'batch {selector}: {args.episodes} episodes, {simulated:.0f} s simulated in '
                  f'{cpu:.1f} s CPU ({simulated / cpu:.0f}x real time on one core), {wall:.1f} s '
                  'wall  target >= 50x')
        print(f'bridge compute per message: {percentiles(TimedBridge.samples)}  target p99 < 1 ms')
    finally:
        cell_module.Bridge = original

    # 4. the node's compute per message
    wall, cpu = node_compute(args.node_steps)
    print(f'robot_bridge_node compute per message, CPU: {percentiles(cpu)}  target p99 < 1 ms')
    print(f'robot_bridge_node compute per message, wall: {percentiles(wall)}')

    # 5. the simulated arm's joint-state rate
    rates, received = sim_rate(args.sim_seconds)
    if rates:
        print(f'cobot_sim_node joint_states: published {min(rates):.0f} to {max(rates):.0f} Hz '
              f'(median {np.median(rates):.0f}, {len(rates)} seconds), received here '
              f'{received:.0f} Hz  target >= 100 Hz')
    else:
        print('cobot_sim_node joint_states: no status received (the node did not start?)')

    # 6. SSM violations
    if not args.skip_violations:
        cell = ArmCell(model, policy)
        scenarios, seeds = episodes_of(model, 'random', args.violation_episodes,
                                       args.violation_epochs, 1, 0.5)
        for selector in ('ssm_only', 'paper'):
            totals = dict(violations=0, contacts=0, breaches=0, samples=0)
            minimum = np.inf
            cpu0 = time.process_time()
            for e, (scenario, seed) in enumerate(zip(scenarios, seeds)):
                r = cell.episode(scenario, seed, person_seed(1, e), selector)
                totals['violations'] += r.ssm_violations
                totals['contacts'] += r.contacts
                totals['breaches'] += r.speed_breaches
                totals['samples'] += int(round(r.seconds / cell.settings.control_period))
                minimum = min(minimum, r.min_separation)
                if (e + 1) % 250 == 0:
                    print(f'  {selector}: {e + 1}/{len(scenarios)} episodes '
                          f'({time.process_time() - cpu0:.0f} s CPU)', flush=True)
            print(f'ssm violations, {selector}: {totals["violations"]} in {totals["samples"]:,} '
                  f'samples of {len(scenarios)} episodes x {args.violation_epochs} epochs '
                  f'(contacts {totals["contacts"]}, speed-bound breaches {totals["breaches"]}, '
                  f'min separation {minimum:.3f} m)  target 0')
    return 0


if __name__ == '__main__':
    sys.exit(main())
