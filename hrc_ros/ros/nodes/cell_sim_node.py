"""cell_sim: a simulated human and cell that closes the loop with no hardware.

Contract: streams `human/joint_states` (the six arm joints of `conversions.HUMAN_JOINTS`,
velocities, and positions integrated from them) and `human/skeleton` (7 keypoints in
`robot_frame`) at `sensor_rate` Hz, every sample inside the velocity band of the human's current
O and the distance band of the current d, so the belief estimator recovers both; reacts to each
`hrc/action` a_k with the epoch's `hrc/task_state` x_k (`core.protocol.ActionPairing`) through a
seeded `core.cell.human.SimulatedHuman` (the same draws as `hrc-simulate` for the same seed),
answers
requests on `hrc/human_response` (false for an ineligible one; with `answer_requests` false it
leaves the answers to the HMI page), and publishes the debug topic
`hrc/sim/true_state` (latched: the 11 state variables after each reaction). `faults` injects
`core.cell.faults` (dropout, nan_velocity, decline, collision) without changing the random draws.

`person` says what the skeleton is. `point` (the default): 7 keypoints inside the band of the
model's d around `robot_reference_point` (`synthesize_skeleton`). `3d` (the cell with the arm,
docs/ROBOT.md): the same `SimulatedHuman` drives a body walking around the arm
(`core.cell.person.SimulatedPerson`, seeded ``[seed, 2]``, the batch cell's person for that
seed): each reaction's Delta and emotions set where and how fast they walk, relative to the
separation to the arm's links, which it reads on `hrc/separation` (std_msgs/Float64MultiArray
``[S, arm xyz, human xyz, S_p, ...]`` from `cobot_sim_node`); `human/skeleton` carries the
body's 32 Azure Kinect joints (`tracking.K4ABT_JOINTS` order, `keypoint_joints` of the readers),
and the true state's d is the band of that separation (`safety_radii`). `human/joint_states`
stays the six arm angles in the body-tracking adapter's form, their velocities in the band of
the model's O (the observation is the model's event, which the walk does not simulate). The
`collision` fault needs `point` (a 3D person's distance is the arm's to make).
"""

from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray, String, UInt8MultiArray

from ...core.cell import faults
from ...core.cell.human import SimulatedHuman
from ...core.cell.scenarios import SCENARIOS, make_scene
from ...core.cell.tracking import K4ABT_JOINTS
from ...core.model import ACTIONS, RH1, RH2, TASK_VARIABLES
from ...core.decision.observation import (level_of_distance, synthesize_joint_velocities,
                                          synthesize_skeleton)
from ...core.protocol import CELL_HOLD, ActionPairing, InputError, PeriodEstimate
from ...core.robot.arm import JOINT_NAMES, Arm, body_capsules, warm_up
from .. import conversions as conv
from .. import qos
from .. import stop as stop_regime
from ..node_support import (CONFIG, STATUS_PERIOD_SEC, WARNING_THROTTLE_SEC, DeadlineTimer, Inputs,
                            ParamSpec, StartupError, check_array, control_clock, node_setup, run)
from .belief_estimator_node import MOTION_PARAMETERS, check_motion_parameters

SENSOR_STREAM = 1   # the sensor samples' RNG stream: default_rng([seed, SENSOR_STREAM])
PERSON_STREAM = 2   # the 3D person's walk: SimulatedPerson(seed=[seed, PERSON_STREAM])
PERSONS = ('point', '3d')
WALK_STEP_S = 0.02      # s: the 3D person's longest step (the truth's sample interval at most)
MAX_WALK_STEPS = 500    # steps of one late timer call (10 s); a longer stall walks coarser
IDLE_TASK = {name: 0 for name in TASK_VARIABLES}

T = Parameter.Type
PARAMETERS = (
    CONFIG,
    ParamSpec('seed', T.INTEGER, 0, 'seed of the simulated human', read_only=True,
              range=(0, 2**31 - 1)),
    ParamSpec('initial_emotions', T.INTEGER_ARRAY, [0, 0], '(em, ea) at epoch 1, each 0..2',
              read_only=True, constraints='2 integers in 0..2'),
    ParamSpec('initial_distance', T.INTEGER, 1, 'distance level d at epoch 1', read_only=True,
              range=(0, 3)),
    ParamSpec('sensor_rate', T.DOUBLE, 50.0, 'Hz of joint states and skeletons',
              range=(0.1, 1000.0)),
    *MOTION_PARAMETERS,
    ParamSpec('task_state_timeout', T.DOUBLE, 0.0, 'seconds an action waits for its '
              "epoch's hrc/task_state before the cell reacts with the latest one; 0 = "
              f'{CELL_HOLD.fraction:g} x the epoch period seen on hrc/action '
              f'({CELL_HOLD.fallback_s:g} s '
              'before two actions)', range=(0.0, 60.0)),
    ParamSpec('faults', T.STRING_ARRAY, [], 'injected faults "KIND:EPOCHS" with KIND one of '
              + ', '.join(faults.FAULT_KINDS) + ' and EPOCHS "7" or "7-9"', read_only=True),
    ParamSpec('answer_requests', T.BOOL, True, "the simulated person answers the robot's "
              'requests on hrc/human_response; false: a person answers them on the HMI page '
              '(hmi_node) and the simulated one only reacts (its emotions and distance move '
              'as before, with the same random draws)'),
    ParamSpec('person', T.STRING, 'point', "the simulated person's body: point (7 keypoints in "
              "the model's distance band around robot_reference_point) or 3d (a body of 32 "
              'joints walking around the arm, its approach relative to the separation on '
              'hrc/separation; the cell with the arm)', read_only=True,
              constraints="'point' or '3d'"),
    ParamSpec('person_scenario', T.STRING, 'honest', 'with person 3d: who is in the cell and what '
              "the tracker reports: 'honest' (the model's person) or a scenario that tests SSM: "
              + ', '.join(SCENARIOS[1:]) + ' (docs/ROBOT.md 4); the others read the arm\'s '
              'joint_states to walk at it', read_only=True,
              constraints=' or '.join(SCENARIOS)),
    ParamSpec('scenario_window', T.DOUBLE, 20.0, 'seconds from the first action in which a '
              "person scenario's event is drawn (in [2 s, half of it]), as the batch draws it in "
              'an episode of that length', read_only=True, range=(4.0, 3600.0)),
)


def arm_configuration(msg: JointState) -> np.ndarray | None:
    """The UR5e's six angles (arm.JOINT_NAMES) of a joint state, None without them or NaN."""
    where = {name: i for i, name in enumerate(msg.name)}
    if any(name not in where for name in JOINT_NAMES) or len(msg.position) != len(msg.name):
        return None
    q = np.array([msg.position[where[name]] for name in JOINT_NAMES], dtype=float)
    return q if np.isfinite(q).all() else None


def check_parameters(values) -> str | None:
    person = values.get('person', PERSONS[0])
    if person not in PERSONS:
        return f"person must be {' or '.join(PERSONS)}, got {person!r}"
    scenario = values.get('person_scenario', SCENARIOS[0])
    if scenario not in SCENARIOS:
        return f"person_scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}"
    if scenario != SCENARIOS[0] and person != '3d':
        return f"person_scenario {scenario} needs person '3d' (a body walking at the arm)"
    if 'faults' in values:
        try:
            parsed = faults.parse_faults(values['faults'])
        except ValueError as exc:
            return str(exc)
        if person == '3d' and parsed['collision']:
            return ("fault collision needs person 'point' (a 3D person's distance is the "
                    "separation to the arm)")
    return (check_array(values, 'initial_emotions', 2, low=0, high=2)
            or check_motion_parameters(values))


class CellSimNode(Node):
    NODE_NAME = 'cell_sim'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params, values, self.config, self.model = node_setup(
            self, PARAMETERS, check_parameters, self._apply_parameters)
        em, ea = (int(v) for v in values['initial_emotions'])
        self.initial_distance = values['initial_distance']
        try:
            self.human = SimulatedHuman(self.model, seed=values['seed'], em=em, ea=ea,
                                        d=values['initial_distance'])
        except ValueError as exc:
            raise StartupError(f'simulated human: {exc}') from None
        self.sensor_rng = np.random.default_rng([values['seed'], SENSOR_STREAM])
        self.faults = faults.parse_faults(values['faults'])
        self.clock = control_clock(self)
        self.period = PeriodEstimate()
        self.task_state_timeout = values['task_state_timeout']
        self.answer_requests = values['answer_requests']
        self.pairing = ActionPairing(self._hold_ns())
        self.reactions = 0
        self._position = np.zeros(len(conv.HUMAN_JOINTS))
        self._last_sample_ns: int | None = None
        self._apply_motion(values)
        self.person = self.scene = None
        self.separation: float | None = None    # S on hrc/separation (person 3d)
        self._walked_ns: int | None = None
        self._scene_start_ns: int | None = None  # the first action: the scene's clock starts
        self.arm = self.arm_q = None
        if values['person'] == '3d':
            self.scene = make_scene(values['person_scenario'], values['initial_distance'],
                                    [values['seed'], PERSON_STREAM], em=em, ea=ea,
                                    radii=self.safety_radii,
                                    duration=values['scenario_window'])
            self.person = self.scene.person
            if values['person_scenario'] != SCENARIOS[0]:
                self.arm = Arm()       # the scripted people walk at the arm's true links
                warm_up(self.arm, stopped=stop_regime.requested)

        self.joint_pub = self.create_publisher(JointState, 'human/joint_states',
                                               qos.SENSOR_DATA)
        self.skeleton_pub = self.create_publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
        self.response_pub = self.create_publisher(Bool, 'hrc/human_response', qos.RELIABLE)
        self.true_state_pub = self.create_publisher(UInt8MultiArray, 'hrc/sim/true_state',
                                                    qos.LATCHED)
        # The truth the sensors may not tell (person 3d): every body in the cell now, for the
        # SSM check against the true position (docs/ROBOT.md 4).
        self.true_skeleton_pub = self.create_publisher(PoseArray, 'hrc/sim/true_skeleton',
                                                       qos.RELIABLE) if self.scene else None
        self.inputs = Inputs(self)
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              self._on_action, with_published=True)
        self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.STATE_INPUT,
                              self._task_state_from_msg, self._on_task_state)
        if self.person is not None:
            self.inputs.subscribe(Float64MultiArray, 'hrc/separation', qos.SENSOR_DATA,
                                  conv.separation_from_msg, self._on_separation)
        if self.arm is not None:
            self.inputs.subscribe(JointState, 'joint_states', qos.SENSOR_DATA, lambda msg: msg,
                                  self._on_arm, name='arm joint_states')
        self.sensor_timer = self.create_timer(1.0 / values['sensor_rate'], self._stream)
        self.hold = DeadlineTimer(self, lambda now: self._react(self.pairing.expire(now)))
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        self._enter_epoch()
        self._publish_true_state()

    @property
    def epoch(self) -> int:
        """The epoch the cell is in: k after k - 1 reactions."""
        return self.reactions + 1

    @property
    def task_state(self) -> dict | None:
        return self.pairing.task_state

    def _fault(self, kind: str) -> bool:
        return faults.active(self.faults, kind, self.epoch)

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
        self.task_state_timeout = values['task_state_timeout']
        self.answer_requests = values['answer_requests']
        self.pairing.timeout_ns = self._hold_ns()

    def _task_state_from_msg(self, msg):
        return conv.task_state_from_msg(msg, self.model.rho, self.model.sigma)

    def _on_separation(self, separation: dict) -> None:
        self.separation = separation['S']

    def _on_arm(self, msg: JointState) -> None:
        """The arm's configuration, which the scripted people walk at (the simulator knows it;
        a real person sees the arm)."""
        q = arm_configuration(msg)
        if q is None:
            raise InputError('arm joint_states without the UR5e\'s six joints or not finite')
        self.arm_q = q

    def _probe(self, keypoints):
        """(S m, the arm's closest point) of a body of `keypoints` to the arm now; before any
        joint state, far away."""
        if self.arm_q is None:
            return math.inf, np.zeros(3)
        sep = self.arm.separation(self.arm_q, body_capsules(keypoints, K4ABT_JOINTS))
        return sep.distance, sep.arm_point

    def _person_separation(self) -> float:
        """The separation the 3D person walks by: the latest on hrc/separation, before any
        the middle of the band they start in."""
        if self.separation is not None:
            return self.separation
        return self.person.targets[self.initial_distance]

    # -- inputs ----------------------------------------------------------------------------
    def _on_task_state(self, task_state: dict) -> None:
        self._react(self.pairing.task_state_received(task_state, self.clock.now().nanoseconds))

    def _hold_ns(self) -> int:
        return CELL_HOLD.ns(self.task_state_timeout, self.period.period_ns)

    def _on_action(self, action: int, published_ns: int) -> None:
        self.period.observe(published_ns)
        self.pairing.timeout_ns = self._hold_ns()
        self._react(self.pairing.action_received(action, self.clock.now().nanoseconds))

    def _react(self, pairings) -> None:
        for pairing in pairings:
            if pairing.late:
                self.get_logger().warning(
                    f'{pairing.late} in epoch {self.epoch}; reacting to '
                    f'{ACTIONS[pairing.action]} with the latest one',
                    throttle_duration_sec=WARNING_THROTTLE_SEC)
            self._reaction(pairing.action, pairing.task_state)
        self.hold.sync(self.pairing.deadline)

    def _reaction(self, action: int, task_state: dict | None) -> None:
        if task_state is None:
            task_state = IDLE_TASK
            self.get_logger().warning('no task state received yet; reacting as in an idle '
                                      'cell', throttle_duration_sec=WARNING_THROTTLE_SEC)
        reaction = self.human.react(action, task_state)
        if self.scene is not None:
            if self._scene_start_ns is None:
                self._scene_start_ns = self.get_clock().now().nanoseconds
            self.scene.begin_epoch(reaction.delta, reaction.em, reaction.ea,
                                   self._person_separation())
        accepted = reaction.accepted is True and not self._fault('decline')
        if action in (RH1, RH2) and self.answer_requests:
            if reaction.accepted and not accepted:
                self.get_logger().warning(f'fault injected: request declined in epoch '
                                          f'{self.epoch}')
            self.response_pub.publish(conv.human_response_to_msg(accepted))
        self.reactions += 1
        self._enter_epoch()
        self._publish_true_state()
        self._stream()

    # -- outputs ---------------------------------------------------------------------------
    def _walk(self, now_ns: int) -> None:
        """The 3D person walks up to now (also while the sensors drop out), in steps of at most
        WALK_STEP_S however late the timer came (a loaded machine), each published as the truth
        on hrc/sim/true_skeleton, stamped when it was so; a scene's clock runs from the first
        action."""
        last, self._walked_ns = self._walked_ns, now_ns
        total = 0 if last is None else max(0, now_ns - last)
        steps = min(MAX_WALK_STEPS, max(1, math.ceil(total * 1e-9 / WALK_STEP_S)))
        for i in range(1, steps + 1):
            at = now_ns - total + total * i // steps
            dt = total / steps * 1e-9
            t = -1.0 if self._scene_start_ns is None else (at - self._scene_start_ns) * 1e-9
            if self.arm is None:
                self.scene.step(dt, t, None, self._person_separation())
            else:
                self.scene.step(dt, t, self._probe)
            self.true_skeleton_pub.publish(conv.keypoints_to_msg(
                self.scene.bodies(), Time(nanoseconds=at).to_msg(), self.robot_frame))

    def _stream(self) -> None:
        now = self.get_clock().now()
        if self.person is not None:
            self._walk(now.nanoseconds)          # the truth too, also in a dropout
        if self._fault('dropout'):
            return
        dt = 0.0 if self._last_sample_ns is None else (now.nanoseconds
                                                       - self._last_sample_ns) * 1e-9
        self._last_sample_ns = now.nanoseconds
        velocity = synthesize_joint_velocities(self.human.observation, len(conv.HUMAN_JOINTS),
                                               self.velocity_thresholds, self.sensor_rng)
        self._position += velocity * dt
        stamp = now.to_msg()
        if self.person is None:
            keypoints = synthesize_skeleton(self.human.d, self.safety_radii,
                                            self.robot_reference_point, self.sensor_rng)
        else:
            t = -1.0 if self._scene_start_ns is None else \
                (now.nanoseconds - self._scene_start_ns) * 1e-9
            keypoints = self.scene.frame(t)      # what the tracker reports: None, nothing
        if self._fault('nan_velocity'):
            velocity = np.full_like(velocity, np.nan)
        self.joint_pub.publish(conv.joint_state_to_msg(conv.HUMAN_JOINTS, velocity,
                                                       self._position, stamp))
        if keypoints is not None:
            self.skeleton_pub.publish(conv.keypoints_to_msg(keypoints, stamp, self.robot_frame))

    def true_state(self) -> dict:
        task = self.task_state or IDLE_TASK
        d = self.human.d
        if self.person is not None:
            d = level_of_distance(self._person_separation(), self.safety_radii)
        return {'em': self.human.em, 'ea': self.human.ea, **task, 'd': d}

    def _publish_true_state(self) -> None:
        self.true_state_pub.publish(conv.true_state_to_msg(self.true_state()))

    def _publish_status(self) -> None:
        values = {'reactions': self.reactions,
                  'held_action': (None if self.pairing.held is None
                                  else ACTIONS[self.pairing.held]),
                  'em': self.human.em, 'ea': self.human.ea,
                  'd': self.true_state()['d'], 'observation': self.human.observation}
        if self.person is not None:
            values.update({'person': '3d', 'separation_m': self.separation,
                           'person_xy': np.round(self.person.keypoints()[0, :2], 3)})
        self.inputs.publish_health('simulation', values)


def main(args=None):
    return run(CellSimNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
