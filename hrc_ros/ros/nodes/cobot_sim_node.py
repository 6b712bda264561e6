"""cobot_sim: a simulated UR5e that follows JointTrajectory goals under the speed override
(docs/ROBOT.md, sections 2 and 5).

Contract: an `Arm` (MuJoCo, capsule links) and the core `TrajectoryFollower` (a scaled joint
trajectory controller: the trajectory's clock runs at the override, which it follows at the
SSM deceleration's rate). It subscribes

- `joint_trajectory_topic` (trajectory_msgs/JointTrajectory): a goal as a
  joint_trajectory_controller takes it, the points after the arm's current configuration with
  cumulative `time_from_start` (velocities are not read: the segments are cubic, at rest at
  every point), or one point at time 0 (stay). Refused with a diagnostic, the arm held (it brakes
  along its current path at the override's ramp and stands until a valid goal comes): a goal
  naming a joint the description does not have or lacking one, a point outside the limits, a
  goal that does not start at the arm (its first segment faster than the joint limits allow
  from where the arm is, or a stay away from it), a goal while the arm moves (a joint faster
  than the description's `rest_speed`: goals replace each other at a safe point only);
- `speed_override_topic` (std_msgs/Float64, 0..1): the trajectory's speed scaling. A value
  outside [0, 1] is refused and taken as 0; none for `override_timeout` is 0 too; so is every
  value while a second writer publishes there (`core.protocol.SingleWriter`, by publication
  sequence numbers: refused, and 0 until it has been silent for `bridge.SECOND_WRITER_HOLD`):
  another node's 1.0 must not outvote the bridge's 0;
- `human/skeleton` (geometry_msgs/PoseArray in `robot_frame`), for the separation.

It steps the follower at `rate` Hz (with the elapsed time, so the arm moves in wall time on a
loaded machine) and publishes `joint_states` (sensor_msgs/JointState, position and velocity of
the description's joints) at `joint_state_rate` Hz and, with them while a skeleton
at most `ssm.human_timeout` old is held, `hrc/separation` (std_msgs/Float64MultiArray
`[S, arm_x, arm_y, arm_z, human_x, human_y, human_z, S_p, speed]`: the separation and its two
closest points in the base frame, S_p at the arm's speed bound as ISO/TS 15066 gives it, and
that bound, m/s: the override times the goal's top link speed; `S < S_p` with `speed` above
`ssm.MOVING_SPEED` is an SSM violation).

The motion runs in a thread of its own (`_motion`), not on an executor timer (docs/ROBOT.md,
section 5, and bench/README.md): an rclpy timer costs the executor's whole wait-set round per
call, three quarters of the node's CPU at 250 Hz, and a call that comes later than a period
loses that period, so on a loaded machine the timer fell to half its rate and the joint states,
counted in steps (every 2nd), with it (64 Hz at load 20-30). The thread sleeps to a fixed grid
of `rate` Hz and publishes at the first step in each period of a `joint_state_rate` grid, so a
late step delays a joint state but does not drop it while steps come at least once a period;
periods without any step are skipped, not caught up in a burst. Each joint state is the
follower's state at the step it was published at, stamped with the time of that step. The
executor thread only handles the inputs; the follower is touched under a lock (a goal is
checked against the arm's configuration and taken as one step), and a goal is checked on an
`Arm` of its own (a MuJoCo model's data is not shared between threads).
"""

from __future__ import annotations

import math
import sys
import threading
import time
import traceback

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from ...core.protocol import InputError, SingleWriter, Stamp
from ...core.robot.arm import Arm, Trajectory, TrajectoryFollower, peak_link_speed
from ...core.robot.arm import segment_duration
from ...core.robot.bridge import SECOND_WRITER_HOLD
from ...core.robot.ssm import protective_distance
from .. import conversions as conv
from .. import qos
from ..node_support import (STATUS_PERIOD_SEC, Inputs, NodeParameters, ParamSpec, SampledInputs,
                            StartupError, run, warm_up_before_the_node)
from .robot_bridge_node import (KEYPOINT_JOINTS, OVERRIDE_TOPIC, ROBOT_DESCRIPTION, ROBOT_FRAME,
                                TRAJECTORY_TOPIC, check_names, last_refusals,
                                load_description, skeleton_converter)

T = Parameter.Type
MAX_STEP_SEC = 1.0       # a longer stall of the motion thread is stepped as this at most
TIME_SLACK = 1e-3        # s (and relative): a segment may be this much faster than computed
MAX_GOAL_POINTS = 1000   # points of a goal this controller takes
PEAKS_KEPT = 4096        # segments' top link speeds remembered (a program repeats its segments)
REST_CREEP = 1e-3        # rad an arm at rest may creep while its next goal is checked
GIL_SWITCH = 0.001       # s: the interpreter's thread switch interval in this node
# The controller's watchdog on the monitor's override (docs/ROBOT.md 5): the bridge sends one
# each joint state (8 ms at 125 Hz) and plans each to hold for its control_period (0.01 s);
# an override older than 3 of those is taken as 0, so the arm brakes rather than run on at a
# speed planned for a separation it no longer has. With 0.25 s, a CI run on a loaded host had
# the node's executor hold the overrides back ~60 ms while the arm ran on at the older, higher
# one: 1 sample of S < S_p (0.806 < 0.827 m) in 2,179 with the arm moving.
OVERRIDE_TIMEOUT = 0.03
PARAMETERS = (
    ROBOT_DESCRIPTION, TRAJECTORY_TOPIC, OVERRIDE_TOPIC, KEYPOINT_JOINTS, ROBOT_FRAME,
    ParamSpec('rate', T.DOUBLE, 250.0, 'Hz the follower steps at', read_only=True,
              range=(10.0, 2000.0)),
    ParamSpec('joint_state_rate', T.DOUBLE, 125.0, 'Hz of joint_states and hrc/separation '
              '(at most rate)', read_only=True, range=(1.0, 2000.0)),
    ParamSpec('initial_positions', T.DOUBLE_ARRAY, [], 'the arm\'s configuration at start, '
              'rad in the description\'s joint order ([] = its home pose)', read_only=True),
    ParamSpec('override_timeout', T.DOUBLE, OVERRIDE_TIMEOUT, 'seconds without a speed override '
              'after which it is taken as 0 (the arm brakes)', range=(0.01, 10.0),
              read_only=True),    # the bridge plans each override for command_latency
)


class CobotSimNode(Node):
    NODE_NAME = 'cobot_sim'

    def __init__(self, **kwargs):
        arm, goal_arm = Arm(), Arm()
        warm_up_before_the_node(arm, goal_arm)
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_names)    # all read-only
        values = self.params.values()
        self.description = d = load_description(values['robot_description'])
        q0 = np.asarray(values['initial_positions'] or d.poses['home'], dtype=float)
        if q0.shape != (len(d.joint_names),) or d.outside(q0):
            raise StartupError(f'initial_positions must be {len(d.joint_names)} angles within '
                               f'the limits, got {q0.tolist()} ({d.outside(q0) or "wrong size"})')
        self.arm = arm                # the motion thread's (separation)
        self.goal_arm = goal_arm      # the executor's (goal checks)
        self._peaks: dict = {}
        self._lock = threading.Lock()   # the follower, between the two threads
        self.follower = TrajectoryFollower(q0, d.ssm.deceleration)
        self.override = 0.0
        self._override_at: float | None = None
        self.override_timeout = values['override_timeout']
        self.override_writer = SingleWriter(f'the speed override on '
                                            f'{values["speed_override_topic"]}',
                                            self.override_timeout, SECOND_WRITER_HOLD)
        self.held = ''                # why the arm holds ('' = it follows its goal)
        self.body = None
        self._body_stamp = 0
        self.accepted = self.refused = 0
        self.steps = 0
        self.published = 0             # joint states
        self._rate_mark = (time.monotonic(), 0)
        self.step_period = 1.0 / values['rate']
        self.publish_period = max(1.0 / values['joint_state_rate'], self.step_period)
        self._last_step = time.monotonic()
        self.joint_pub = self.create_publisher(JointState, 'joint_states', qos.SENSOR_DATA)
        self.separation_pub = self.create_publisher(Float64MultiArray, 'hrc/separation',
                                                    qos.SENSOR_DATA)
        self.inputs = Inputs(self)
        self.inputs.subscribe(JointTrajectory, values['joint_trajectory_topic'], qos.RELIABLE,
                              lambda msg: msg, self._on_trajectory, name='trajectory')
        self.inputs.subscribe(Float64, values['speed_override_topic'], qos.RELIABLE,
                              lambda msg: msg, self._on_override, name='speed_override',
                              with_stamp=True)
        # The skeleton is taken by the motion thread, newest first, at each joint state: through
        # the executor (beside 125 overrides a second) the skeleton cobot_sim held was up to
        # 200 ms older than the one the bridge held on a loaded machine, and hrc/separation's
        # S_p, which counts that age, showed S < S_p where the bridge had acted on fresh data.
        self.sampled = SampledInputs(self, self.inputs)
        self.sampled.subscribe(PoseArray, 'human/skeleton', qos.SENSOR_DATA,
                               skeleton_converter(values['robot_frame'],
                                                  values['keypoint_joints'] or None),
                               name='skeleton', latest_only=True)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        self._halt = threading.Event()
        # The motion thread waits for the GIL while the executor runs a callback: at most the
        # switch interval (5 ms by default, half a joint-state period), here 1 ms.
        sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH))
        self._motion_thread = threading.Thread(target=self._motion, name='cobot_sim motion',
                                               daemon=True)
        self._motion_thread.start()

    def destroy_node(self):
        """The motion thread ends (it publishes) before the node's entities go."""
        self._halt.set()
        if self._motion_thread.is_alive() \
                and self._motion_thread is not threading.current_thread():
            self._motion_thread.join(timeout=5.0)
        self.sampled.destroy()
        return super().destroy_node()

    # -- inputs ------------------------------------------------------------------------------
    def _on_trajectory(self, msg: JointTrajectory) -> None:
        """A goal; anything refused (the conversion's refusals too) holds the arm. It is checked
        and timed outside the follower's lock (the motion thread keeps stepping and publishing
        meanwhile), then taken under the lock if the arm still stands where it was checked."""
        try:
            with self._lock:
                q, qd = self.follower.q.copy(), self.follower.qd.copy()
            trajectory = self._goal(*conv.trajectory_from_msg(msg), q=q, qd=qd)
            with self._lock:
                moved = float(np.max(np.abs(self.follower.q - q)))
                if moved > REST_CREEP:
                    raise InputError(f'trajectory refused, the arm holds: the arm moved '
                                     f'{moved:.4f} rad while the goal was checked (a goal '
                                     'while the arm moves)')
                positions = trajectory.positions.copy()
                positions[0] = self.follower.q      # the last creep of a stop, below rest_speed
                self.follower.follow(Trajectory(trajectory.joint_names, positions,
                                                trajectory.durations, trajectory.nominal_speed,
                                                trajectory.marks, trajectory.kind))
        except InputError as exc:
            with self._lock:
                self.refused += 1
                self.held = str(exc)
            raise
        self.accepted += 1
        self.held = ''

    def _goal(self, names, positions, times, q=None, qd=None) -> Trajectory:
        """The core trajectory of a goal from the arm's configuration `q` (moving at `qd`);
        InputError (the arm then holds) for what the module docstring lists."""
        d = self.description
        q = self.follower.q if q is None else q
        qd = self.follower.qd if qd is None else qd
        index = {name: i for i, name in enumerate(names)}
        unknown = [n for n in names if n not in d.joint_names]
        lack = [n for n in d.joint_names if n not in index]
        if unknown or lack:
            raise InputError('trajectory refused, the arm holds: '
                             + (f'unknown joints {conv.quote(unknown)}' if unknown else
                                f'no {", ".join(lack)}')
                             + f' (the arm\'s joints are {", ".join(d.joint_names)})')
        points = positions[:, [index[n] for n in d.joint_names]]
        for i, point in enumerate(points):
            why = d.outside(point)
            if why:
                raise InputError(f'trajectory refused, the arm holds: point {i}: {why}')
        if len(points) > MAX_GOAL_POINTS:
            raise InputError(f'trajectory refused, the arm holds: {len(points)} points, more than '
                             f'the {MAX_GOAL_POINTS} this controller takes')
        fastest = float(np.max(np.abs(qd)))
        if fastest > d.rest_speed:
            raise InputError(f'trajectory refused, the arm holds: a goal while the arm moves '
                             f'({fastest:.3f} rad/s, rest_speed {d.rest_speed}); goals replace '
                             'each other at rest only')
        if len(points) == 1 and times[0] == 0.0:
            away = float(np.max(np.abs(points[0] - q)))
            if away > d.waypoint_tolerance:
                raise InputError(f'trajectory refused, the arm holds: a stay {away:.4f} rad '
                                 'away from the arm (a goal must start at the arm)')
            return Trajectory(d.joint_names, q[None].copy(), np.zeros(0), 0.0, (), 'stay')
        shortest = segment_duration(q, points[0], d.velocity, d.acceleration)
        if shortest > times[0] * (1.0 + TIME_SLACK) + TIME_SLACK:
            raise InputError(
                f'trajectory refused, the arm holds: it does not start at the arm (its first '
                f'point is {float(np.max(np.abs(points[0] - q))):.3f} rad away, at least '
                f'{shortest:.3f} s within the joint limits, given {times[0]:.3f} s)')
        path = np.vstack([q[None], points])
        durations = np.diff(np.concatenate([[0.0], times]))
        # Every segment within the joint speed and acceleration limits, as ros2_control's
        # controller would hold it (a later segment beyond them ran at 42 rad/s before).
        for i in range(1, len(durations)):
            shortest = segment_duration(path[i], path[i + 1], d.velocity, d.acceleration)
            if shortest > durations[i] * (1.0 + TIME_SLACK) + TIME_SLACK:
                raise InputError(
                    f'trajectory refused, the arm holds: segment {i + 1} moves '
                    f'{float(np.max(np.abs(path[i + 1] - path[i]))):.3f} rad in '
                    f'{durations[i]:.3f} s, faster than the joint speed and acceleration limits '
                    f'allow ({shortest:.3f} s at least)')
        # a program's goal repeats its cycle's few segments: each is timed once. A goal of
        # many distinct segments takes its executor a while (about 2 s for 1,000 on a loaded
        # machine), no override is taken meanwhile, and the arm brakes: safe, slow.
        nominal = max(self._peak(a, b, t) for a, b, t in zip(path[:-1], path[1:], durations))
        return Trajectory(d.joint_names, path, durations, float(nominal), (), 'goal')

    def _peak(self, start, end, duration) -> float:
        key = (start.tobytes(), end.tobytes(), float(duration))
        peak = self._peaks.get(key)
        if peak is None:
            peak = peak_link_speed(self.goal_arm, start, end, duration)
            if len(self._peaks) < PEAKS_KEPT:
                self._peaks[key] = peak
        return peak

    def _on_override(self, msg: Float64, source: Stamp) -> None:
        """The speed override; a refused one (outside [0, 1], NaN, a second writer's) is
        taken as 0."""
        try:
            self.override_writer.check(source.sequence, time.monotonic())
            value = conv.speed_override_from_msg(msg)
        except InputError:
            self.override = 0.0
            raise
        # The override counts from when the bridge sent it, not from its arrival: one that
        # spent 25 ms on the way holds 30 ms less 25 (the bridge plans each for its period plus
        # command_latency, the watchdog's 30 ms, from when it computed it). A sender's clock
        # ahead of this one's cannot make it last longer than from its arrival.
        transit = max(0.0, time.time() - source.published_ns * 1e-9)
        self.override, self._override_at = value, time.monotonic() - transit

    # -- the arm ------------------------------------------------------------------------------
    def _commanded(self, now: float) -> float:
        if self.held or self._override_at is None \
                or now - self._override_at > self.override_timeout \
                or self.override_writer.held(now):
            return 0.0
        return self.override

    def _motion(self) -> None:
        """The motion thread: a step on each tick of the `rate` grid, a joint state at the
        first step in each period of the `joint_state_rate` grid (module docstring)."""
        schedule = MotionSchedule(time.monotonic(), self.step_period, self.publish_period)
        while not self._halt.wait(max(0.0, schedule.next_step - time.monotonic())):
            now = time.monotonic()
            publish = schedule.step(now)
            try:
                self._step(now, publish)
            except Exception:  # noqa: BLE001 - a bug must not stop the arm's thread; reported
                self.inputs.internal_error('motion', 'the motion thread',
                                           traceback.format_exc())

    def _step(self, now: float, publish: bool = True) -> None:
        """One step of the follower to `now` (time.monotonic()), and the joint state (and the
        separation) it gives when `publish`."""
        clock = self.get_clock().now()    # the stamp of the state at `now`
        elapsed = min(max(now - self._last_step, 0.0), MAX_STEP_SEC)
        last, self._last_step = self._last_step, now
        # A late step (the machine stalled this thread) is stepped in step periods, each with
        # the override the watchdog gave at its time: a real controller runs through the stall
        # and brakes once the override is older than override_timeout, so neither does the arm
        # stand still nor run on at a stale override for the whole stall.
        parts = max(1, math.ceil(elapsed / self.step_period - 1e-9))
        with self._lock:
            for i in range(1, parts + 1):
                at = now - elapsed + elapsed * i / parts if i < parts else now
                state = self.follower.step(elapsed / parts, self._commanded(max(at, last)))
        self.steps += 1
        if not publish:
            return
        self.joint_pub.publish(conv.joint_state_to_msg(
            self.description.joint_names, state.qd, state.q, clock.to_msg()))
        self.published += 1
        for _, _, (body, stamp) in self.sampled.take():
            self.body, self._body_stamp = body, stamp
        body = self.body
        if body is None or (clock.nanoseconds - self._body_stamp) * 1e-9 \
                > self.description.ssm.human_timeout:
            return
        sep = self.arm.separation(state.q, body)
        speed = state.speed_bound
        # S_p as the bridge computes it: the person may have moved for the skeleton's age.
        age = max(0.0, (clock.nanoseconds - self._body_stamp) * 1e-9)
        self.separation_pub.publish(conv.separation_to_msg(
            sep.distance, sep.arm_point, sep.human_point,
            float(protective_distance(speed, sep.distance, self.description.ssm, age)), speed))

    def _publish_status(self) -> None:
        follower = self.follower
        now = time.monotonic()
        (since, count), self._rate_mark = self._rate_mark, (now, self.published)
        rate = (self.published - count) / (now - since) if now > since else 0.0
        self.inputs.publish_health('arm', {
            'held': self.held, 'override': self._commanded(time.monotonic()),
            'scale': round(follower.scale, 4), 'speed_bound_m_s': round(follower.speed_bound, 4),
            'goal_done': follower.done, 'goals_accepted': self.accepted,
            'goals_refused': self.refused, 'steps': self.steps,
            'override_second_writer': self.override_writer.held(now),
            'joint_states_hz': round(rate, 1), **last_refusals(self.inputs)})


def next_tick(tick: float, now: float, period: float) -> float:
    """The first tick of the grid `tick + k period` (k >= 1) after `now`: the ticks `now` is
    past are skipped, not caught up."""
    return tick + period * (math.floor(max(now - tick, 0.0) / period) + 1)


class MotionSchedule:
    """When the motion thread steps and publishes (module docstring): a grid of steps every
    `step_period` s and one of joint states every `publish_period` s from `start`. `step(now)`
    at a step: the next step is the first tick of its grid after `now`, and True if this step
    publishes (the first step in a publish period; the periods it is past are skipped)."""

    def __init__(self, start: float, step_period: float, publish_period: float):
        self.step_period, self.publish_period = step_period, publish_period
        self.next_step = self.next_publish = start

    def step(self, now: float) -> bool:
        self.next_step = next_tick(self.next_step, now, self.step_period)
        if now < self.next_publish:
            return False
        self.next_publish = next_tick(self.next_publish, now, self.publish_period)
        return True


def main(args=None):
    return run(CobotSimNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
