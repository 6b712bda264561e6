"""robot_bridge: the decision layer's actions into arm motion, under speed and separation
monitoring (docs/ROBOT.md, sections 3 and 5).

Contract: one core `Bridge` (`core.robot.bridge`, every rule there) fed from

- `hrc/action` (std_msgs/String), paired with the epoch's `hrc/task_state` by
  `core.protocol.ActionPairing` as `cell_sim_node` does (an action that arrives before its
  epoch's task state waits for it, at most `task_state_timeout`);
- `hrc/task_state` (std_msgs/UInt8MultiArray), also fed on arrival (a task that ends drops the
  robot's share at once);
- `joint_states` (sensor_msgs/JointState, the arm's): each message is a tick of the bridge
  (`Bridge.joint_state` then `Bridge.tick`); a refused one (a joint missing, NaN, outside its
  limits) ticks with the last state kept, which ages out into a protective stop after the
  description's `joint_state_timeout`; no joint state at all for that long ticks from a watchdog
  timer, so the override falls to 0 without them;
- `human/skeleton` (geometry_msgs/PoseArray in `robot_frame`): `arm.body_capsules` of the
  keypoints (`keypoint_joints`: K4ABT names of each body's keypoints, bones between them; []:
  a sphere around each keypoint).

Both sensor inputs pass the writer's publication sequence number to the core: a second writer's
skeletons count beside the first's (SSM takes the nearest body), a second writer's joint states
hold the arm (`core.robot.bridge`, "One arm, every person"); so does another publisher of the
goal topic, which the watchdog timer counts every `joint_state_timeout / 2`. `hrc/action` and
`hrc/task_state` have one owner each (`action_source`, `task_state_source`): while the graph
shows another publisher (checked by the watchdog and on every message), or a message comes off
the followed writer's sequence numbers, the message is refused and the arm holds (docs/ROBOT.md
7, "One action source"). The core's monitor checks the arm's measured speed and path on every
joint state, whoever sent its goal (`core.robot.guard`).

It publishes the `JointTrajectory` goals on `joint_trajectory_topic`, the speed override
(std_msgs/Float64, 0..1) on `speed_override_topic` every tick, `hrc/protective_stop`
(std_msgs/Bool, latched, on change), `hrc/robot_progress` (UInt8MultiArray `[nature, cycles,
cycles_done]`, latched, on change; cycles 0: no share) and /diagnostics: the stop and its reason
(on change, and at most once per `STOP_REPORT_SEC` while the reason's figures change), once a
second the separation, S_p, the allowed speed, the motion and the compute time per message, and
refused inputs (node_support.Inputs: throttled, size-capped).

Nobody subscribed to the speed override: SSM cannot act on the arm, so the bridge does not tick
(no new trajectory goes out), publishes override 0 and a protective stop, and reports
`robot_bridge: speed override` naming the topic once a second until someone listens: WARN for
OVERRIDE_GRACE_SEC after the start (the controller may come up after the bridge), then ERROR;
OK once someone listens.

Times: the stamps of the joint states and skeletons are compared with this node's ROS clock
(the system clock, or /clock under use_sim_time), the clock their publishers stamp with.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64, String, UInt8MultiArray
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ...core.cell.tracking import joint_indices
from ...core.model import ACTIONS
from ...core.protocol import (CELL_HOLD, ERROR, OK, WARN, ActionPairing, PeriodEstimate, Report,
                              Stamp)
from ...core.protocol import InputError
from ...core.robot.arm import Arm, body_capsules
from ...core.robot.bridge import (OVERRIDE_CONSUMERS, WRITER_HOLD, Bridge,
                                  RobotDescriptionError, load_programs, load_robot_description,
                                  unconsumed_reason, writers_reason)
from .. import conversions as conv
from .. import qos
from ..node_support import (STATUS_PERIOD_SEC, WARNING_THROTTLE_SEC, DeadlineTimer, Inputs,
                            NodeParameters, ParamSpec, StartupError, check_core, run,
                            warm_up_before_the_node)
from ..sources import endpoints

T = Parameter.Type
DEFAULT_TRAJECTORY_TOPIC = 'joint_trajectory_controller/joint_trajectory'
DEFAULT_OVERRIDE_TOPIC = 'hrc/speed_override'
STOP_REPORT_SEC = 1.0         # a stop whose reason only changes its figures: reported this often
COMPUTE_WINDOW = 2000         # per-message compute times kept for the status's p99

ROBOT_DESCRIPTION = ParamSpec(
    'robot_description', T.STRING, '', "robot description YAML (joints, limits, poses, SSM; "
    "'' = the shipped UR5e, config/robot/ur5e.yaml; docs/ROBOT.md 3)", read_only=True)
TRAJECTORY_TOPIC = ParamSpec(
    'joint_trajectory_topic', T.STRING, DEFAULT_TRAJECTORY_TOPIC, 'topic of the '
    'trajectory_msgs/JointTrajectory goals (a ros2_control joint_trajectory_controller\'s)',
    read_only=True, constraints='non-empty')
OVERRIDE_TOPIC = ParamSpec(
    'speed_override_topic', T.STRING, DEFAULT_OVERRIDE_TOPIC, 'topic of the std_msgs/Float64 '
    'speed override 0..1 (a scaled joint trajectory controller\'s scaling, a speed slider '
    'adapter: docs/ROBOT.md 3)', read_only=True, constraints='non-empty')
KEYPOINT_JOINTS = ParamSpec(
    'keypoint_joints', T.STRING_ARRAY, [], 'the K4ABT joint names of each body\'s keypoints on '
    'human/skeleton, as body_tracking_node\'s parameter (the person is then capsules over '
    'their bones); [] = an unlabelled skeleton, a 0.1 m sphere around each keypoint',
    read_only=True)
ROBOT_FRAME = ParamSpec(
    'robot_frame', T.STRING, conv.ROBOT_BASE_FRAME, 'the arm\'s base frame: frame_id of '
    'human/skeleton (a skeleton in another frame is refused)', read_only=True,
    constraints='non-empty')
PARAMETERS = (
    ROBOT_DESCRIPTION,
    ParamSpec('motion_programs', T.STRING, '', "motion programs YAML, per task nature a cycle "
              "of joint waypoints with durations ('' = the shipped config/robot/"
              "ur5e_programs.yaml)", read_only=True),
    TRAJECTORY_TOPIC, OVERRIDE_TOPIC, KEYPOINT_JOINTS, ROBOT_FRAME,
    ParamSpec('control_period', T.DOUBLE, 0.01, 'seconds between the arm\'s joint states at '
              'most (each is a tick): SSM holds each override for this long', read_only=True,
              range=(0.001, 0.1)),
    ParamSpec('task_state_timeout', T.DOUBLE, 0.0, 'seconds an action waits for its epoch\'s '
              'hrc/task_state before the bridge takes it with the latest one; 0 = '
              f'{CELL_HOLD.fraction:g} x the epoch period seen on hrc/action', range=(0.0, 60.0)),
    ParamSpec('action_source', T.STRING, 'decision', 'the node that owns the cell\'s actions: '
              'hrc/action is taken only while it is the topic\'s one publisher (a name relative '
              "to this node's namespace, or absolute; '' = any one publisher); another "
              'publisher or a second writer holds the arm (docs/ROBOT.md 5)', read_only=True),
    ParamSpec('task_state_source', T.STRING, 'task_manager', 'the node that owns '
              "hrc/task_state, as action_source ('' = any one publisher)", read_only=True),
    ParamSpec('override_consumers', T.STRING_ARRAY, list(OVERRIDE_CONSUMERS), 'node names (any '
              'namespace) that act on the speed override: the arm moves only while one of them '
              'subscribes to it (a display, a recorder or an echo reads it but cannot stop the '
              "arm); a vendor's adapter adds its name; [] = any subscriber", read_only=True),
)
OVERRIDE_GRACE_SEC = 5.0      # a start-up without the override's subscriber is a WARN this long


def check_names(values) -> str | None:
    for name in ('joint_trajectory_topic', 'speed_override_topic', 'robot_frame'):
        if name in values and not values[name]:
            return f'{name} must not be empty'
    if values.get('keypoint_joints'):
        return check_core(values, 'keypoint_joints', joint_indices)
    return None


def load_description(path: str):
    """The robot description a node's `robot_description` names; StartupError with the file's
    one-line reason when it cannot be used."""
    try:
        return load_robot_description(path or None)
    except RobotDescriptionError as exc:
        raise StartupError(str(exc)) from None


def stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def last_refusals(inputs: Inputs) -> dict:
    """last_refused_<input>: the reason the input's last dropped message was refused."""
    return {f'last_refused_{name}': reason
            for name, reason in sorted(inputs.last_drop_reason.items())}


def skeleton_converter(robot_frame: str, joints):
    """human/skeleton -> (BodyCapsules, stamp ns); MessageError for what the core refuses."""
    def convert(msg: PoseArray):
        points = conv.keypoints_from_msg(msg, robot_frame)
        try:
            body = body_capsules(points, joints)
        except ValueError as exc:
            raise conv.MessageError(f'skeleton: {exc}') from None
        return body, stamp_ns(msg.header.stamp)
    return convert


class RobotBridgeNode(Node):
    NODE_NAME = 'robot_bridge'

    def __init__(self, **kwargs):
        arm = Arm()
        warm_up_before_the_node(arm)
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_names, self._apply)
        values = self.params.values()
        self.description = load_description(values['robot_description'])
        try:
            programs = load_programs(self.description, values['motion_programs'] or None)
        except RobotDescriptionError as exc:
            raise StartupError(str(exc)) from None
        self.bridge = Bridge(self.description, programs, arm, values['control_period'])
        self.owners = {'action': self._owner(values['action_source']),
                       'task_state': self._owner(values['task_state_source'])}
        self.started = time.monotonic()
        self.period = PeriodEstimate()
        self.task_state_timeout = values['task_state_timeout']
        self.pairing = ActionPairing(self._hold_ns())
        self.trajectory_topic = values['joint_trajectory_topic']
        self.override_topic = values['speed_override_topic']
        self.command = None
        self.stop: bool | None = None
        self.stop_reason = ''
        self._stop_reported = -float('inf')
        self._reported_reason = ''
        self.progress: tuple | None = None
        self.sent = 0
        self.ticks = 0
        self.compute = deque(maxlen=COMPUTE_WINDOW)
        self._last_tick = time.monotonic()
        self._listening: bool | None = None
        self.consumers = tuple(values['override_consumers'])
        self._unconsumed = 'the speed override\'s readers are not known yet'

        self.trajectory_pub = self.create_publisher(JointTrajectory, self.trajectory_topic,
                                                    qos.RELIABLE)
        self.override_pub = self.create_publisher(Float64, self.override_topic, qos.RELIABLE)
        self.stop_pub = self.create_publisher(Bool, 'hrc/protective_stop', qos.LATCHED)
        self.progress_pub = self.create_publisher(UInt8MultiArray, 'hrc/robot_progress',
                                                  qos.LATCHED)
        self.inputs = Inputs(self)
        self.inputs.subscribe(JointState, 'joint_states', qos.SENSOR_DATA, lambda msg: msg,
                              self._on_joint_state, with_stamp=True)
        self.inputs.subscribe(PoseArray, 'human/skeleton', qos.SENSOR_DATA,
                              skeleton_converter(values['robot_frame'],
                                                 values['keypoint_joints'] or None),
                              self._on_skeleton, name='skeleton', with_stamp=True)
        self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.STATE_INPUT,
                              conv.task_state_from_msg, self._on_task_state, with_stamp=True)
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              self._on_action, with_stamp=True)
        self.hold = DeadlineTimer(self, lambda now: self._react(self.pairing.expire(now)))
        self.watchdog = self.create_timer(self.description.joint_state_timeout / 2,
                                          self._watchdog)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        self.create_service(Trigger, '~/clear_lost_person', self._on_clear_lost)
        self._publish_progress()
        self._refresh_readers()
        self._set_stop(True, 'no joint state yet')

    def _apply(self, values) -> None:
        self.task_state_timeout = values['task_state_timeout']
        self.pairing.timeout_ns = self._hold_ns()

    def _hold_ns(self) -> int:
        return CELL_HOLD.ns(self.task_state_timeout, self.period.period_ns)

    def _now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _owner(self, name: str) -> str:
        """A node name of action_source / task_state_source, fully qualified ('' stays '')."""
        if not name or name.startswith('/'):
            return name
        return f'{self.get_namespace().rstrip("/")}/{name}'

    def _writers(self, kind: str) -> str:
        """The graph's publishers of hrc/<kind> against its owner (`writers_reason`); the
        bridge holds while the reason is not ''."""
        topic = f'hrc/{kind}'
        reason = writers_reason(self.resolve_topic_name(topic),
                                [e.node for e in endpoints(self, topic, skip_own=False)],
                                self.owners[kind])
        self.bridge.graph_hold(kind, reason)
        return reason

    def _check_source(self, kind: str, source: Stamp) -> None:
        """InputError (the message is refused, the arm holds) for a message of hrc/<kind>
        while the graph shows a publisher other than its owner, or from a writer other than the
        one followed (publication sequence numbers: a short-lived publisher the graph no longer
        shows is still another line)."""
        reason = self._writers(kind)
        if reason:
            raise InputError(f'refused: {reason}')
        self.bridge.check_writer(kind, source.sequence, self._now())

    # -- inputs ------------------------------------------------------------------------------
    def _on_joint_state(self, msg: JointState, source: Stamp) -> None:
        started = time.perf_counter()
        try:
            self.bridge.joint_state(msg.name, msg.position, msg.velocity,
                                    stamp_ns(msg.header.stamp), self._now(), source.sequence)
        finally:                # a refused state still ticks: the last one kept ages out
            self._tick(started)

    def _on_skeleton(self, converted, source: Stamp) -> None:
        body, stamp = converted
        self.bridge.skeleton(body, stamp, self._now(), source.sequence)

    def _on_task_state(self, task_state: dict, source: Stamp) -> None:
        self._check_source('task_state', source)
        self.bridge.task_state(task_state, self._now())
        self._react(self.pairing.task_state_received(task_state, self._now()))

    def _on_action(self, action: int, source: Stamp) -> None:
        self._check_source('action', source)
        self.period.observe(source.published_ns)
        self.pairing.timeout_ns = self._hold_ns()
        if self.period.period_ns:
            # two writers interleaving once an epoch keep the arm held: a hold longer than it
            hold = max(WRITER_HOLD, 2.5 * self.period.period_ns * 1e-9)
            for writer in self.bridge.writers.values():
                writer.hold = writer.silence = hold
        self._react(self.pairing.action_received(action, self._now()))

    def _react(self, pairings) -> None:
        for pairing in pairings:
            if pairing.late:
                self.get_logger().warning(
                    f'{pairing.late}; taking {ACTIONS[pairing.action]} with the latest task '
                    'state', throttle_duration_sec=WARNING_THROTTLE_SEC)
            now = self._now()
            if pairing.task_state is not None:
                self.bridge.task_state(pairing.task_state, now)
            self.bridge.action(pairing.action, now)
        self.hold.sync(self.pairing.deadline)

    # -- the tick ----------------------------------------------------------------------------
    def _watchdog(self) -> None:
        """No joint state for `joint_state_timeout`: tick anyway (the bridge then stops). Also
        tells the bridge how many publishers the goal topic has (another one: a stop)."""
        self.bridge.goal_publishers(self.count_publishers(self.trajectory_pub.topic_name))
        self._refresh_readers()
        for kind in self.owners:
            self._writers(kind)
        if time.monotonic() - self._last_tick > self.description.joint_state_timeout:
            self._tick(time.perf_counter())

    def _tick(self, started: float) -> None:
        self._last_tick = time.monotonic()
        self.ticks += 1
        if self._unconsumed or not self.override_pub.get_subscription_count():
            self._refresh_readers()      # at once while held; the watchdog's 20 Hz otherwise
        listening = not self._unconsumed
        if listening:
            command = self.command = self.bridge.tick(self._now())
            if command.trajectory is not None:
                traj = command.trajectory
                self.trajectory_pub.publish(conv.trajectory_to_msg(
                    traj.joint_names, traj.positions, traj.durations))
                self.sent += 1
            override, stop, reason = command.override, command.stop, command.reason
        else:
            self.command = None
            override, stop, reason = 0.0, True, self._unconsumed
        self.override_pub.publish(Float64(data=float(override)))
        self.compute.append(time.perf_counter() - started)
        if listening != self._listening:
            self._listening = listening
            self._report_listening()
        self._set_stop(stop, reason)
        self._publish_progress()

    def _set_stop(self, stop: bool, reason: str) -> None:
        """Latch the stop on change and report it. The core's own stop reports
        (`BridgeCommand.reports`) are not forwarded: they come with every change of the
        reason's text, which holds the data's age, so at every tick of a timeout; and the stop
        for an override nobody listens to is this node's."""
        changed = stop != self.stop
        if changed:
            self.stop = stop
            self.stop_pub.publish(Bool(data=bool(stop)))
        self.stop_reason = reason if stop else ''
        now = time.monotonic()
        if changed or (stop and reason != self._reported_reason
                       and now - self._stop_reported >= STOP_REPORT_SEC):
            self._stop_reported, self._reported_reason = now, self.stop_reason
            self.inputs.report(Report(
                WARN if stop else OK, 'ssm',
                f'protective stop: {reason}' if stop else 'protective stop cleared',
                {'reason': reason if stop else ''}, kind='stop'))

    def _refresh_readers(self) -> None:
        """Whether one of override_consumers reads the override (`unconsumed_reason`): the
        graph's subscribers of the topic, once the publisher has matched any."""
        topic = self.override_pub.topic_name
        readers = ([info.node_name for info in self.get_subscriptions_info_by_topic(topic)]
                   if self.override_pub.get_subscription_count() else [])
        self._unconsumed = unconsumed_reason(topic, readers, self.consumers)

    def _report_listening(self) -> None:
        """OK once someone listens; until then WARN for OVERRIDE_GRACE_SEC after the start
        (the controller may start after the bridge), then ERROR."""
        topic = self.override_pub.topic_name
        values = {'topic': topic, 'subscribers': self.override_pub.get_subscription_count(),
                  'consumers': ', '.join(self.consumers) or '(any subscriber)'}
        if self._listening:
            self.inputs.report(Report(OK, 'speed override', f'the speed override on {topic} '
                                      'has a consumer', values, log=False))
            return
        waited = time.monotonic() - self.started
        if waited < OVERRIDE_GRACE_SEC:
            self.inputs.report(Report(
                WARN, 'speed override', f'waiting for the controller or adapter to subscribe to '
                f'the speed override on {topic} ({waited:.1f} s of a {OVERRIDE_GRACE_SEC:g} s '
                'start-up grace); the arm is held until it does',
                values, kind='no_subscriber', log=False))
            return
        self.inputs.report(Report(
            ERROR, 'speed override', f'{self._unconsumed or "no consumer of the override yet"};'
            ' the arm is held (protective stop, no trajectory sent) until its controller or '
            'adapter listens', values,
            kind='no_subscriber'))

    def _publish_progress(self) -> None:
        progress = self.bridge.progress
        values = (0, 0, 0) if progress is None else (progress.nature, progress.cycles,
                                                      progress.cycles_done)
        if values != self.progress:
            self.progress = values
            self.progress_pub.publish(conv.robot_progress_to_msg(*values))

    def _on_clear_lost(self, request, response):
        """~/clear_lost_person (std_srvs/Trigger): the operator looked, and nobody is where
        the tracker lost a person; SSM decides again on what the tracker shows."""
        reason = self.bridge.lost
        response.success = self.bridge.clear_lost()
        response.message = ('cleared: ' + reason if response.success else
                            'no lost person holds the arm')
        if response.success:
            self.get_logger().warning(f'lost person\'s hold cleared by a service call ({reason})')
        return response

    # -- status ------------------------------------------------------------------------------
    def _publish_status(self) -> None:
        command = self.command
        ssm = command.ssm if command is not None else None
        sep = command.separation if command is not None else None
        compute = np.asarray(self.compute) * 1e3
        values = {
            'motion': command.motion if command is not None else 'hold',
            'override': command.override if command is not None else 0.0,
            'protective_stop': self.stop, 'stop_reason': self.stop_reason,
            'separation_m': None if sep is None else round(sep.distance, 4),
            'closest': '' if sep is None else f'{sep.arm_link} - {sep.body_part}',
            'protective_distance_m': (None if ssm is None or ssm.protective_distance is None
                                      else round(ssm.protective_distance, 4)),
            'allowed_speed_m_s': (None if ssm is None or ssm.allowed_speed is None
                                  else round(ssm.allowed_speed, 4)),
            'progress': '/'.join(map(str, self.progress or ())),
            'last_action': ('' if self.bridge.last_action is None
                            else ACTIONS[self.bridge.last_action]),
            'trajectories_sent': self.sent, 'ticks': self.ticks,
            'compute_p99_ms': (round(float(np.percentile(compute, 99)), 3) if compute.size
                               else None),
            'override_subscribers': self.override_pub.get_subscription_count(),
            'measured_speed_m_s': round(self.bridge.measured.speed, 4),
            'monitor': self.bridge.fault,
            'lost_person': self.bridge.lost,
            **{f'monitor_{k}': v for k, v in self.bridge.counts.items()},
            'action_source': self.owners['action'] or '(any one publisher)',
            'task_state_source': self.owners['task_state'] or '(any one publisher)',
            **last_refusals(self.inputs),
        }
        self.inputs.publish_health('bridge', values)
        if not self._listening:
            self._report_listening()


def main(args=None):
    return run(RobotBridgeNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
