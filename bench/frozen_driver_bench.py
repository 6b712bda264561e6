"""Joint-state drivers that freeze or lag, and honest ones, against the bridge's frozen-driver
rule (docs/ROBOT.md 7, "Joint states that freeze ..."; `guard.JointFreezeCheck`).

    python bench/frozen_driver_bench.py

A bridge and a simulated controller (`TrajectoryFollower`) stepped at 100 Hz, as
test/test_robot_monitor.py's Cell does, the program running with a person 2.5 m away; at 0 s
the driver starts to lie while the controller goes on (a goal planned from lying positions is
refused and the arm held, as cobot_sim does). Printed per driver: the first protective stop
after that (s), the stopped share of the next 3 s, how far the reported positions lay from the
arm at worst (rad, largest joint: it includes the arm's braking after the stop, about 0.5 rad
from the program's speed) and the rule's count. Then honest drivers fed
straight into a bridge (500 Hz, 1 s): how many ticks the rule stopped them (0 is right). The
figures are deterministic (seeded); a few seconds on one core.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from hrc_ros.core.cell.person import SimulatedPerson  # noqa: E402
from hrc_ros.core.cell.tracking import K4ABT_JOINTS  # noqa: E402
from hrc_ros.core.robot.arm import (JOINT_NAMES, Arm, TrajectoryFollower,  # noqa: E402
                                    body_capsules)
from hrc_ros.core.robot.bridge import Bridge, load_programs, load_robot_description  # noqa: E402

MS = 1_000_000
SECONDS = 3.0


def run_lying(description, programs, arm, lie) -> tuple:
    """(first stop s or None, stopped share, worst lag rad, count) for `lie(k, history)` ->
    (q, qd) the driver reports at tick k after the lie began (`history`: the arm's true
    (q, qd) at every tick since)."""
    bridge = Bridge(description, programs, arm, period=0.01)
    follower = TrajectoryFollower(description.poses['home'], description.ssm.deceleration)
    person = SimulatedPerson(3, seed=0)
    person.rho, person.theta, person.reach = 2.5, math.radians(-31), 0.0
    noise = np.random.default_rng(33)
    keypoints = person.keypoints()
    t, held = 0, False
    history, stops, worst = [], [], 0.0

    def tick(k=None):
        nonlocal t, worst, held
        bridge.skeleton(body_capsules(keypoints + noise.normal(0, 0.0015, keypoints.shape),
                                      K4ABT_JOINTS), t, t)
        q, qd = follower.q.copy(), follower.qd.copy()
        if k is not None:
            history.append((q, qd))
            q, qd = lie(k, history)
            worst = max(worst, float(np.abs(history[-1][0] - q).max()))
        bridge.joint_state(JOINT_NAMES, q, qd, t, t)
        command = bridge.tick(t)
        if command.trajectory is not None:
            try:
                follower.follow(command.trajectory)
                held = False
            except ValueError:      # planned from lying positions: refused, the arm held, as
                held = True         # cobot_sim does, until a goal that starts at the arm
        follower.step(0.01, 0.0 if held else command.override)
        t += 10 * MS
        return command

    for _ in range(30):
        tick()
    bridge.task_state(dict(tp=1, tc=3, tx=0, ty=0, hp=0, hc=0, bp=0, bc=0), t)
    bridge.action('ct', t)
    for _ in range(60):
        tick()
    for k in range(int(SECONDS * 100)):
        stops.append(tick(k).stop)
    first = next((k * 0.01 for k, s in enumerate(stops) if s), None)
    return first, sum(stops) / len(stops), worst, bridge.counts['frozen_joint_states']


def lying_drivers(rest_speed):
    rng = np.random.default_rng(5)

    def frozen(k, history):
        return history[0]

    def jitter(k, history):
        return history[0][0] + rng.uniform(-2e-4, 2e-4, 6), history[0][1]

    def two_states(k, history):
        return history[0][0] + 1.5e-4 * (k % 2), history[0][1]

    def rest_one_in(n, rest):
        def lie(k, history):
            return history[0][0], (np.zeros(6) if k % n < rest else history[0][1])
        return lie

    def replay(rate):
        def lie(k, history):
            return history[int(k * rate)]
        return lie

    def at_rest_speed(k, history):
        return history[0][0], np.sign(history[0][1]) * rest_speed

    return [('frozen: its last state repeated', frozen),
            ('frozen, 2e-4 rad of jitter', jitter),
            ('frozen, flipping between two states 1.5e-4 rad apart', two_states),
            ('frozen, one message in 9 at rest', rest_one_in(9, 1)),
            ('frozen, three messages in 4 at rest', rest_one_in(4, 3)),
            ('a replay at 0.5 of the real rate', replay(0.5)),
            ('a replay at 0.3 of the real rate', replay(0.3)),
            ('frozen, velocities at rest_speed (a known limit)', at_rest_speed)]


def honest(description, programs, arm, velocity, rate=500, hw_rate=None, quantum=0.0,
           lag=0.0, seconds=1.0) -> int:
    """Ticks an honest driver was stopped as frozen: joint 0 at `velocity(t)` rad/s, published
    at `rate` Hz from hardware read at `hw_rate` Hz, its positions in steps of `quantum` rad,
    its velocities low-passed with time constant `lag` s."""
    bridge = Bridge(description, programs, arm, period=1 / rate)
    q, filtered = description.poses['home'].copy(), np.zeros(6)
    read_q, read_qd, next_read = q.copy(), np.zeros(6), 0.0
    stopped = 0
    for k in range(int(seconds * rate)):
        t = k / rate
        qd = np.zeros(6)
        qd[0] = velocity(t)
        q = q + qd / rate
        filtered = filtered + (qd - filtered) * (min(1.0, 1 / (rate * lag)) if lag else 1.0)
        if hw_rate is None or t >= next_read - 1e-12:
            read_q = np.round(q / quantum) * quantum if quantum else q.copy()
            read_qd, next_read = filtered.copy(), next_read + (1 / hw_rate if hw_rate else 0)
        stamp = int(round(t * 1e9))
        bridge.joint_state(JOINT_NAMES, read_q, read_qd, stamp, stamp)
        stopped += 'frozen driver' in bridge.tick(stamp).reason
    return stopped


def main() -> int:
    description = load_robot_description()
    programs, arm = load_programs(description), Arm()
    rest = description.rest_speed
    print(f'lying drivers (100 Hz, the program running, {SECONDS:g} s from the lie):')
    print(f'  {"driver":52s} {"first stop":>10s} {"stopped":>8s} {"worst lag":>10s} {"count":>5s}')
    for name, lie in lying_drivers(rest):
        first, share, worst, count = run_lying(description, programs, arm, lie)
        shown = 'none' if first is None else f'{first:.2f} s'
        print(f'  {name:52s} {shown:>10s} {share:8.0%} {worst:8.3f} rad {count:5d}')

    def brake(t):
        return max(0.0, 0.5 - 2.0 * t)
    print('honest drivers (500 Hz, 1 s): ticks stopped as frozen')
    cases = [('joint 0 at 1.01 rest_speed', dict(velocity=lambda t: 1.01 * rest)),
             ('0.3 rad/s', dict(velocity=lambda t: 0.3)),
             ('braking 0.5 rad/s to rest at 2 rad/s^2', dict(velocity=brake)),
             ('the same, velocities low-passed (tau 30 ms)', dict(velocity=brake, lag=0.03)),
             ('the same, velocities low-passed (tau 50 ms)', dict(velocity=brake, lag=0.05)),
             ('0.3 rad/s, hardware read at 10 Hz', dict(velocity=lambda t: 0.3, hw_rate=10)),
             ('0.012 rad/s, encoder steps of 5e-4 rad',
              dict(velocity=lambda t: 0.012, quantum=5e-4)),
             ('0.012 rad/s, encoder steps of 1.5e-3 rad',
              dict(velocity=lambda t: 0.012, quantum=1.5e-3))]
    for name, case in cases:
        print(f'  {name:52s} {honest(description, programs, arm, **case):5d} of 500')
    print('reproduce: python bench/frozen_driver_bench.py')
    return 0


if __name__ == '__main__':
    sys.exit(main())
