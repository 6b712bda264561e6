"""cell_sim: a simulated human and cell that closes the loop with no hardware.

A `SimulatedHuman` (seeded) holds the hidden emotions (em, ea) and the distance level d, and
the observation O it currently shows. The node

- streams `human/joint_states` (the six arm joints of `conversions.HUMAN_JOINTS`, velocities
  filled and positions integrated from them) and `human/skeleton` (7 keypoints in `robot_frame`)
  at `sensor_rate` Hz, from start-up on: every sample is drawn inside the velocity band of the
  current O and the distance band of the current d (`synthesize_joint_velocities`,
  `synthesize_skeleton`), so the belief estimator recovers O and d whatever the window holds;
- reacts to each `hrc/action` a_k (DESIGN.md): ``human.react(a_k, x_k)`` with the epoch's
  `hrc/task_state` x_k; for a request (rh1, rh2) it publishes `hrc/human_response` (false for a
  request the task state makes ineligible); the new (em, ea, d, O) take effect on the next
  sample, which is sent at once.

Pairing a_k with x_k. The task manager publishes x_k before the decision node publishes a_k,
but they are two writers: DDS does not order them, and rclpy's executor runs the callbacks of
messages that are ready together in subscription order, not in arrival order. So the node
reacts to an action only with a task state received since its last reaction (x_k). An action
that arrives first is held until x_k arrives, at most `task_state_timeout`; then it reacts with
the latest task state and warns. (Reacting at once with the previous epoch's task state made a
loaded machine answer an eligible request as an ineligible one.)

Debug topic (an extension of INTERFACES.md, for tests and plots): `hrc/sim/true_state`
(std_msgs/UInt8MultiArray, latched), the 11 state variables ``em ea tp tc tx ty hp hc bp bc d``
with layout labels: the hidden (em, ea) and d after each reaction (and at start-up) with the
latest task state.

The human's random stream is `seed` itself, so the same seed gives the same hidden trajectory
as the simulator for the same actions; the sensor samples draw from a separate stream.

Fault injection (for demos, tests and the fault bags): `faults` lists ``KIND:EPOCHS`` entries,
EPOCHS one epoch ``7`` or a range ``7-9``; the cell is in epoch k after k - 1 reactions.
- ``dropout``: no joint states and no skeletons during those epochs (sensor dropout);
- ``nan_velocity``: joint states whose velocities are NaN during those epochs;
- ``decline``: the human declines every request made in those epochs;
- ``collision``: the human steps into the collision circle as those epochs begin (d = 0).
Overrides never change the random draws, so the rest of a run stays comparable with a clean one.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, String, UInt8MultiArray

from .. import conversions as conv
from .. import qos
from ..cell import SimulatedHuman
from ..model import ACTIONS, RH1, RH2, TASK_VARIABLES, HRCModel
from ..observation import synthesize_joint_velocities, synthesize_skeleton
from .belief_estimator_node import (ROBOT_FRAME, ROBOT_REFERENCE_POINT, SAFETY_RADII,
                                    VELOCITY_THRESHOLDS,
                                    check_motion_parameters)
from .common import (STATUS_PERIOD_SEC, Deadline, Inputs, NodeParameters, ParamSpec, StartupError,
                     check_array, load_node_config, run)

SENSOR_STREAM = 1   # the sensor samples' RNG stream: default_rng([seed, SENSOR_STREAM])
IDLE_TASK = {name: 0 for name in TASK_VARIABLES}

T = Parameter.Type
PARAMETERS = (
    ParamSpec('config', T.STRING, '', "model configuration YAML ('' = the shipped "
              'default.yaml)', read_only=True),
    ParamSpec('seed', T.INTEGER, 0, 'seed of the simulated human', read_only=True,
              range=(0, 2**31 - 1)),
    ParamSpec('initial_emotions', T.INTEGER_ARRAY, [0, 0], '(em, ea) at epoch 1, each 0..2',
              read_only=True, constraints='2 integers in 0..2'),
    ParamSpec('initial_distance', T.INTEGER, 1, 'distance level d at epoch 1', read_only=True,
              range=(0, 3)),
    ParamSpec('sensor_rate', T.DOUBLE, 50.0, 'Hz of joint states and skeletons',
              range=(0.1, 1000.0)),
    VELOCITY_THRESHOLDS, SAFETY_RADII, ROBOT_REFERENCE_POINT, ROBOT_FRAME,
    ParamSpec('task_state_timeout', T.DOUBLE, 0.25, 'seconds an action waits for its '
              "epoch's hrc/task_state before the cell reacts with the latest one",
              range=(0.0, 60.0)),
    ParamSpec('faults', T.STRING_ARRAY, [], 'injected faults "KIND:EPOCHS" with KIND one of '
              'dropout, nan_velocity, decline, collision and EPOCHS "7" or "7-9"',
              read_only=True),
)
FAULT_KINDS = ('dropout', 'nan_velocity', 'decline', 'collision')


def parse_faults(entries) -> dict[str, list]:
    """``["dropout:5", "collision:7-8"]`` -> {kind: [(first, last) epoch ranges]};
    ValueError if malformed."""
    faults = {kind: [] for kind in FAULT_KINDS}
    for entry in entries:
        kind, sep, span = str(entry).partition(':')
        first, dash, last = span.partition('-')
        if kind not in faults or not sep:
            raise ValueError(f'fault {entry!r}: expected KIND:EPOCHS with KIND one of '
                             f'{", ".join(FAULT_KINDS)}')
        try:
            low, high = int(first), int(last if dash else first)
        except ValueError:
            raise ValueError(f'fault {entry!r}: EPOCHS must be "k" or "k-m"') from None
        if not 1 <= low <= high:
            raise ValueError(f'fault {entry!r}: epochs must satisfy 1 <= k <= m')
        faults[kind].append((low, high))
    return faults


def check_parameters(values) -> str | None:
    if 'faults' in values:
        try:
            parse_faults(values['faults'])
        except ValueError as exc:
            return str(exc)
    return (check_array(values, 'initial_emotions', 2, low=0, high=2)
            or check_motion_parameters(values))


class CellSimNode(Node):
    NODE_NAME = 'cell_sim'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_parameters, self._apply_parameters)
        values = self.params.values()
        self.config = load_node_config(values['config'])
        self.model = HRCModel(self.config)
        em, ea = (int(v) for v in values['initial_emotions'])
        try:
            self.human = SimulatedHuman(self.model, seed=values['seed'], em=em, ea=ea,
                                        d=values['initial_distance'])
        except ValueError as exc:
            raise StartupError(f'simulated human: {exc}') from None
        self.sensor_rng = np.random.default_rng([values['seed'], SENSOR_STREAM])
        self.faults = parse_faults(values['faults'])
        self.task_state: dict | None = None
        self._task_state_fresh = False     # received since the last reaction: x_k
        self._held_action: int | None = None
        self.reactions = 0
        self._position = np.zeros(len(conv.HUMAN_JOINTS))
        self._last_sample_ns: int | None = None
        self._apply_motion(values)

        self.joint_pub = self.create_publisher(JointState, 'human/joint_states',
                                               qos.SENSOR_DATA)
        self.skeleton_pub = self.create_publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
        self.response_pub = self.create_publisher(Bool, 'hrc/human_response', qos.RELIABLE)
        self.true_state_pub = self.create_publisher(UInt8MultiArray, 'hrc/sim/true_state',
                                                    qos.LATCHED)
        self.inputs = Inputs(self)
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              self._on_action)
        self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.LATCHED,
                              self._task_state_from_msg, self._on_task_state)
        self.sensor_timer = self.create_timer(1.0 / values['sensor_rate'], self._stream)
        self.hold = Deadline(self, values['task_state_timeout'], self._on_hold_timeout)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        self._enter_epoch()
        self._publish_true_state()

    @property
    def epoch(self) -> int:
        """The epoch the cell is in: k after k - 1 reactions."""
        return self.reactions + 1

    def _fault(self, kind: str) -> bool:
        return any(low <= self.epoch <= high for low, high in self.faults[kind])

    def _enter_epoch(self) -> None:
        if self._fault('collision'):
            self.human.d = 0
            self.get_logger().warning(f'fault injected: collision (d = 0) in epoch {self.epoch}')

    def _apply_motion(self, values) -> None:
        self.velocity_thresholds = tuple(values['velocity_thresholds'])
        self.safety_radii = tuple(values['safety_radii'])
        self.robot_reference_point = tuple(values['robot_reference_point'])
        self.robot_frame = values['robot_frame']

    def _apply_parameters(self, values) -> None:
        self._apply_motion(values)
        self.sensor_timer.timer_period_ns = int(1e9 / values['sensor_rate'])
        self.hold.set_period(values['task_state_timeout'])

    def _task_state_from_msg(self, msg):
        return conv.task_state_from_msg(msg, self.model.rho, self.model.sigma)

    # -- inputs ----------------------------------------------------------------------------
    def _on_task_state(self, task_state: dict) -> None:
        self.task_state = task_state
        self._task_state_fresh = True
        if self._held_action is not None:
            self._react(self._held_action)

    def _on_action(self, action: int) -> None:
        if self._held_action is not None:
            # Two actions without a task state between them: the first one's epoch is over.
            self.get_logger().warning(f'no task state for epoch {self.epoch}; reacting to '
                                      f'{ACTIONS[self._held_action]} with the latest one',
                                      throttle_duration_sec=5.0)
            self._react(self._held_action)
        if self._task_state_fresh:
            self._react(action)
        else:
            self._held_action = action
            self.hold.start()

    def _on_hold_timeout(self) -> None:
        if self._held_action is not None:
            self.get_logger().warning(
                f'no task state for epoch {self.epoch} within task_state_timeout; reacting to '
                f'{ACTIONS[self._held_action]} with the latest one', throttle_duration_sec=5.0)
            self._react(self._held_action)

    def _react(self, action: int) -> None:
        self.hold.cancel()
        self._held_action = None
        self._task_state_fresh = False
        task_state = self.task_state
        if task_state is None:
            task_state = IDLE_TASK
            self.get_logger().warning('no task state received yet; reacting as in an idle '
                                      'cell', throttle_duration_sec=5.0)
        reaction = self.human.react(action, task_state)
        accepted = reaction.accepted is True and not self._fault('decline')
        if action in (RH1, RH2):
            if reaction.accepted and not accepted:
                self.get_logger().warning(f'fault injected: request declined in epoch '
                                          f'{self.epoch}')
            self.response_pub.publish(conv.human_response_to_msg(accepted))
        self.reactions += 1
        self._enter_epoch()
        self._publish_true_state()
        self._stream()

    # -- outputs ---------------------------------------------------------------------------
    def _stream(self) -> None:
        if self._fault('dropout'):
            return
        now = self.get_clock().now()
        dt = 0.0 if self._last_sample_ns is None else (now.nanoseconds
                                                       - self._last_sample_ns) * 1e-9
        self._last_sample_ns = now.nanoseconds
        velocity = synthesize_joint_velocities(self.human.observation, len(conv.HUMAN_JOINTS),
                                               self.velocity_thresholds, self.sensor_rng)
        self._position += velocity * dt
        keypoints = synthesize_skeleton(self.human.d, self.safety_radii,
                                        self.robot_reference_point, self.sensor_rng)
        stamp = now.to_msg()
        if self._fault('nan_velocity'):
            velocity = np.full_like(velocity, np.nan)
        self.joint_pub.publish(conv.joint_state_to_msg(conv.HUMAN_JOINTS, velocity,
                                                       self._position, stamp))
        self.skeleton_pub.publish(conv.keypoints_to_msg(keypoints, stamp, self.robot_frame))

    def true_state(self) -> dict:
        task = self.task_state or IDLE_TASK
        return {'em': self.human.em, 'ea': self.human.ea, **task, 'd': self.human.d}

    def _publish_true_state(self) -> None:
        self.true_state_pub.publish(conv.true_state_to_msg(self.true_state()))

    def _publish_status(self) -> None:
        values = {'reactions': self.reactions,
                  'held_action': (None if self._held_action is None
                                  else ACTIONS[self._held_action]),
                  'em': self.human.em, 'ea': self.human.ea,
                  'd': self.human.d, 'observation': self.human.observation}
        self.inputs.publish_health('simulation', values)


def main(args=None):
    return run(CellSimNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
