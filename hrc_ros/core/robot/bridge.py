"""Actions into motion: the robot bridge as a sans-IO state machine, and the robot description.

The decision layer ends at an action a_k (MODEL.md 2) each epoch. `Bridge` turns it into what a
joint_trajectory_controller and a speed override take, under speed and separation monitoring
(`ssm`). It is fed values with their stamps and the clock, and returns what to send, so every
rule is a unit test (test/test_robot.py) and the phase-2 node only converts messages:

    joint_state(names, q, qd, stamp, now)   the arm's sensor_msgs/JointState
    skeleton(body, stamp, now)              the person's capsules (`arm.body_capsules`)
    task_state(x, now)                      hrc/task_state: tp tc tx ty hp hc bp bc
    action(a, now)                          hrc/action
    tick(now) -> BridgeCommand              a new trajectory (or None), the override 0..1,
                                            the protective stop and its reason, the separation

**What each action does** (the task state x of the epoch decides the program):

- ct: commits to the pending task when `model.commit_effective` says it can (tp > 0, ty = 0,
  tx in {0, 2}) and runs its nature's program, tc cycles; otherwise as nw.
- nw: continues the current motion; when x shows the robot committed (ty in {2, 3}, bc > 0: a
  ct before, an accepted rh2) and its program is not done or not running (after dp, dm, a
  pause), runs it from where it stopped.
- dp: moves to the retreat pose (the program, if any, waits).
- dm: moves to the collaboration pose, its override capped at `collaboration_speed`.
- dn: holds: override 0, no new trajectory (the arm brakes along its path and stands; the
  program waits).
- rh1, rh2, mh: leave the motion as it is (requests to the person), except that a committed
  program not running runs as under nw (the model's robot works under them); a hold stays a
  hold.

**Safe point.** A new trajectory replaces the running one only where the arm is at rest (every
joint slower than `rest_speed`): the bridge first commands override 0, the controller brakes
along the *current* path at the stopping deceleration (the same ramp SSM relies on), and the new
trajectory starts from where the arm stands. An arm already at rest (between trajectories, at a
waypoint of the cubic segments, which all end at rest) switches at once. So no goal is ever
replaced mid-segment at speed, and the arm never leaves its path while braking.

**Programs and progress.** A nature's program is one cycle of joint waypoints W_0..W_{m-1}
with durations D_i (into W_i from the previous waypoint, W_0's from W_{m-1}: the cycle closes);
a task of tc epochs is tc cycles. The run approaches W_0 (not counted), then program segment n
goes from W_{n mod m} to W_{(n+1) mod m}; it counts when the arm, on the program's trajectory,
comes within `waypoint_tolerance` of its end waypoint (joint states only, so a real controller
counts the same). Pre-empted, the run resumes with a segment from wherever the arm stands to the
end waypoint of the segment it was on. `progress` reports the cycles done: the batch cell (and
the phase-2 task manager) lets the robot's counter bc fall only when a cycle has completed
(docs/ROBOT.md, "physical progress").

**SSM below everything.** Every tick computes the separation of the arm's capsules at the
latest joint state from the latest skeleton, and `SpeedSeparationMonitor` caps the override so
that the links' top speed at override 1 (`Trajectory.nominal_speed`) times the override stays
within the speed SSM allows. Whatever the action, the commanded override is the smallest of
SSM's, the action's (dn: 0; a switch waiting for its safe point: 0; dm: collaboration_speed)
and 1. No skeleton, a skeleton older than `ssm.human_timeout`, no joint state or one older
than `joint_state_timeout`: a protective stop with its reason. So are joint states whose
positions moved less than a quarter of what their velocities, integrated over the last
`joint_state_timeout`, say they moved, or less than LAG_SHARE of it and LAG_GAP behind it
over LAG_WINDOW (`guard.JointFreezeCheck`): a driver that repeats its last state with fresh
stamps, with or without jitter on it, or whose positions fall ever further behind, the arm
anywhere along its path (before, only the stall rule caught it, after about 4 s).

**One arm, every person.** Each input names its writer by its publication sequence number
(`core.protocol.StreamLock`; None where the middleware gives none: all one writer). The
skeletons of the followed writer keep the newest; a skeleton of any other writer (a second
tracker, a bag played on the cell, a forger claiming the person is far away) or one stamped
before the followed newest is kept too, for `ssm.human_timeout` from its stamp, and SSM takes
the nearest of the bodies held at the oldest of their stamps: a second writer can only slow the
arm, never free it. Joint states of a second writer are refused and hold the arm in a
protective stop until it has been silent for SECOND_WRITER_HOLD s: which of two is the arm
cannot be known, and SSM from the other's configuration would measure the wrong links. The
override is a fraction of the bridge's own goal's timing, so it bounds only the goals the bridge
sends: while the graph shows another publisher of the goal topic (`goal_publishers`), the arm is
held in a protective stop.

**Robot description** (`load_robot_description`, config/robot/ur5e.yaml): the arm's joints in
chain order with their limits, the poses home / retreat / collaboration, and the bridge's
settings; `load_programs` reads the motion programs (config/robot/ur5e_programs.yaml). Both
refuse, in one line, a missing pose or limit, an unknown joint, a value outside the limits, a
program segment faster than the limits allow.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from ..model import ACTIONS, CT, DM, DN, DP, MH, NW, RH1, RH2, TASK_VARIABLES, action_index
from ..model import commit_effective
from ..paths import read_yaml, share_dir
from ..protocol import (OK, UNKNOWN_NODE_NAME, WARN, InputError, Report, SingleWriter,
                        StreamLock)
from .arm import JOINT_NAMES, Arm, BodyCapsules, Separation, Trajectory, peak_link_speed
from .arm import people, segment_duration
from .guard import (JUMP_SLACK, JointFreezeCheck, MeasuredSpeed, SkeletonCheck, SpeedEnvelope,
                    across_path, nearest_on_path)
from .ssm import (MOVING_SPEED, SpeedSeparationMonitor, SsmParameters, SsmState,
                  directed_speeds, max_speed)

POSES = ('home', 'retreat', 'collaboration')
LIMITS = ('lower', 'upper', 'velocity', 'acceleration')
NATURES = {0: 'robot only', 1: 'human only', 2: 'either', 3: 'both together'}
ROBOT_NATURES = (0, 2, 3)          # tasks with a robot share: they need a program
LIMIT_SLACK = 1e-3                 # rad a joint state may lie beyond a position limit
VELOCITY_SLACK = 10.0              # times a joint's velocity limit a joint state may report
FUTURE_SLACK = 0.05                # s a sample's stamp may lie ahead of the bridge's clock
SECOND_WRITER_HOLD = 1.0           # s a second joint_states writer holds the arm after its last
OTHER_BODIES = 64                  # skeletons of other writers kept (each counts human_timeout)
WRITER_HOLD = 3.0                  # s a second writer of hrc/action or hrc/task_state holds it
STALL_RESEND = 1.0                 # s at rest on an unfinished goal of its own: send it again
STALL_RESENDS = 3                  # ... at most this many times in a row, then hold and report
LAG_WINDOW = 1.0                   # s: the longer check of the joint states' positions against
LAG_SHARE = 0.8                    # their velocities, the share they must move of the claim,
LAG_GAP = 0.05                     # and the rad they may fall behind it in any case (a velocity
                                   # filter's lag, a step of the velocities)
APPROACH_WINDOW = 0.1              # s over which the person's directed speed is measured
APPROACH_NOISE = 0.1               # m/s added to it: 1.5 mm of jitter on two frames over 0.1 s
DESCRIPTION_DEFAULTS = {
    'collaboration_speed': 0.3,    # override cap moving to and at the collaboration pose
    'max_link_speed': 1.0,         # m/s: top link speed a planned trajectory is slowed to
    'waypoint_tolerance': 0.02,    # rad: a waypoint is reached within this on every joint
    'rest_speed': 0.01,            # rad/s: the arm is at rest below this on every joint
    'joint_state_timeout': 0.1,    # s: an older joint state is no state (protective stop)
    # The monitor (core/robot/guard.py, docs/ROBOT.md 3): what is measured against what is
    # allowed and commanded.
    'command_latency': 0.03,       # s from the bridge's override to the arm's motion, at most
    'speed_tolerance': 0.02,       # m/s a measured link speed may exceed the allowed one by
    'path_tolerance': 0.05,        # rad the arm may lie off the bridge's own path
    'frozen_tolerance': 0.0005,    # m: a skeleton that moved less is the same data (frozen)
    'max_body_speed': 3.0,         # m/s: a skeleton farther from the arm than this allows is
                                   # not trusted (a jump away)
    'tracking_error': 0.01,        # m the tracker's keypoints may lie from the body's (SSM takes
                                   # the person this much nearer: docs/ROBOT.md 7)
    'clock_skew': 0.005,           # s the sensors' clocks may differ from the bridge's: a stamp
                                   # further ahead is refused, and every age counts it unseen
    'lost_person_distance': 1.5,   # m: a person the tracker loses nearer the arm than this holds
                                   # it until seen again or cleared (docs/ROBOT.md 7)
}


class RobotDescriptionError(ValueError):
    """A robot description or programs file cannot be used; the text says why."""


def shipped_robot_path(name: str = 'ur5e') -> Path:
    """config/robot/<name>.yaml of the share folder."""
    return share_dir() / 'config' / 'robot' / f'{name}.yaml'


def shipped_programs_path(name: str = 'ur5e') -> Path:
    """config/robot/<name>_programs.yaml of the share folder."""
    return share_dir() / 'config' / 'robot' / f'{name}_programs.yaml'


def _read_yaml(path, kind: str):
    """A robot description or motion-program file by the project's safe YAML loader
    (`paths.read_yaml`: a regular file of at most 1 MiB, nesting and aliases bounded, one line
    for any error), which must hold a mapping."""
    data = read_yaml(path, RobotDescriptionError, kind)
    if not isinstance(data, dict):
        raise RobotDescriptionError(f'{path}: a {kind} is a mapping, got {type(data).__name__}')
    return data


def _number(where: str, value, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RobotDescriptionError(f'{where} must be a finite number, got {value!r}')
    if positive and value <= 0:
        raise RobotDescriptionError(f'{where} must be > 0, got {value!r}')
    return float(value)


def _vector(where: str, value, n: int) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise RobotDescriptionError(f'{where} must be a list of {n} numbers (one per joint), '
                                    f'got {value!r}')
    return np.array([_number(f'{where}[{i}]', v) for i, v in enumerate(value)])


@dataclass(frozen=True)
class RobotDescription:
    """The arm the bridge drives (see the module docstring); arrays in `joint_names` order."""

    name: str
    joint_names: tuple
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    poses: dict
    collaboration_speed: float = DESCRIPTION_DEFAULTS['collaboration_speed']
    max_link_speed: float = DESCRIPTION_DEFAULTS['max_link_speed']
    waypoint_tolerance: float = DESCRIPTION_DEFAULTS['waypoint_tolerance']
    rest_speed: float = DESCRIPTION_DEFAULTS['rest_speed']
    joint_state_timeout: float = DESCRIPTION_DEFAULTS['joint_state_timeout']
    command_latency: float = DESCRIPTION_DEFAULTS['command_latency']
    speed_tolerance: float = DESCRIPTION_DEFAULTS['speed_tolerance']
    path_tolerance: float = DESCRIPTION_DEFAULTS['path_tolerance']
    frozen_tolerance: float = DESCRIPTION_DEFAULTS['frozen_tolerance']
    max_body_speed: float = DESCRIPTION_DEFAULTS['max_body_speed']
    tracking_error: float = DESCRIPTION_DEFAULTS['tracking_error']
    clock_skew: float = DESCRIPTION_DEFAULTS['clock_skew']
    lost_person_distance: float = DESCRIPTION_DEFAULTS['lost_person_distance']
    ssm: SsmParameters = field(default_factory=SsmParameters)
    source: str = ''

    def outside(self, q) -> str:
        """'' when q lies within the position limits, else which joint is out and by what."""
        q = np.asarray(q, dtype=float)
        if ((q >= self.lower - LIMIT_SLACK) & (q <= self.upper + LIMIT_SLACK)).all():
            return ''          # (NaN fails both comparisons, so it is named below)
        for i, name in enumerate(self.joint_names):
            if not math.isfinite(q[i]):
                return f'{name} is {q[i]}'
            if q[i] < self.lower[i] - LIMIT_SLACK or q[i] > self.upper[i] + LIMIT_SLACK:
                return (f'{name} = {q[i]:.4f} rad is outside its limits '
                        f'[{self.lower[i]:.4f}, {self.upper[i]:.4f}]')
        return ''


def robot_description(data: Mapping, source: str = '') -> RobotDescription:
    """Validate a robot description mapping (what the YAML file holds)."""
    where = source or 'robot description'
    try:
        missing = [k for k in ('joints', 'poses') if k not in data]
        if missing:
            raise RobotDescriptionError(f'missing {", ".join(missing)} (a robot description '
                                        'names its joints with their limits and the poses '
                                        f'{", ".join(POSES)})')
        known = {'robot', 'joints', 'poses', 'ssm', *DESCRIPTION_DEFAULTS}
        unknown = sorted(set(data) - known)
        if unknown:
            raise RobotDescriptionError(f'unknown keys {unknown}; known: '
                                        f'{", ".join(sorted(known))}')
        joints = data['joints']
        if not isinstance(joints, list) or len(joints) != len(JOINT_NAMES):
            raise RobotDescriptionError(f'joints must list the arm\'s {len(JOINT_NAMES)} joints '
                                        f'in chain order (base to flange), got {joints!r}')
        names, limits = [], {k: [] for k in LIMITS}
        for i, joint in enumerate(joints):
            if not isinstance(joint, dict) or not isinstance(joint.get('name'), str) \
                    or not joint['name']:
                raise RobotDescriptionError(f'joints[{i}] must be a mapping with a name and its '
                                            f'limits {", ".join(LIMITS)}, got {joint!r}')
            lack = [k for k in LIMITS if k not in joint]
            if lack:
                raise RobotDescriptionError(f'joint {joint["name"]} has no {", ".join(lack)} '
                                            '(limits: lower, upper rad; velocity rad/s; '
                                            'acceleration rad/s^2)')
            extra = sorted(set(joint) - {'name', *LIMITS})
            if extra:
                raise RobotDescriptionError(f'joint {joint["name"]}: unknown keys {extra}')
            names.append(joint['name'])
            for k in LIMITS:
                limits[k].append(_number(f'joint {joint["name"]} {k}', joint[k],
                                         positive=k in ('velocity', 'acceleration')))
        if len(set(names)) != len(names):
            raise RobotDescriptionError(f'joint names repeat: {names}')
        lower, upper = np.array(limits['lower']), np.array(limits['upper'])
        bad = [n for n, lo, hi in zip(names, lower, upper) if not lo < hi]
        if bad:
            raise RobotDescriptionError(f'joints {bad}: lower must be below upper')
        poses_in = data['poses']
        if not isinstance(poses_in, dict):
            raise RobotDescriptionError(f'poses must map {", ".join(POSES)} to joint angles')
        lack = [p for p in POSES if p not in poses_in]
        if lack:
            raise RobotDescriptionError(f'missing poses {", ".join(lack)} (the bridge needs '
                                        f'{", ".join(POSES)})')
        poses = {}
        for pose, value in poses_in.items():
            poses[pose] = _pose(f'pose {pose}', value, names)
        settings = {}
        for key, default in DESCRIPTION_DEFAULTS.items():
            settings[key] = _number(key, data.get(key, default), positive=True)
        if settings['collaboration_speed'] > 1:
            raise RobotDescriptionError('collaboration_speed is an override in (0, 1], got '
                                        f'{settings["collaboration_speed"]}')
        try:
            ssm = SsmParameters.from_mapping(data.get('ssm'))
        except ValueError as exc:
            raise RobotDescriptionError(str(exc)) from None
        description = RobotDescription(
            str(data.get('robot', 'robot')), tuple(names), lower, upper,
            np.array(limits['velocity']), np.array(limits['acceleration']), poses,
            ssm=ssm, source=source, **settings)
        for pose, q in poses.items():
            why = description.outside(q)
            if why:
                raise RobotDescriptionError(f'pose {pose}: {why}')
        return description
    except RobotDescriptionError as exc:
        raise RobotDescriptionError(f'{where}: {exc}') from None


def _pose(where: str, value, names) -> np.ndarray:
    """A pose as a list in joint order, or a mapping joint name -> angle (every joint)."""
    if isinstance(value, dict):
        unknown = sorted(set(value) - set(names))
        if unknown:
            raise RobotDescriptionError(f'{where}: unknown joints {unknown}; the description\'s '
                                        f'joints are {", ".join(names)}')
        lack = [n for n in names if n not in value]
        if lack:
            raise RobotDescriptionError(f'{where}: no angle for {", ".join(lack)}')
        value = [value[n] for n in names]
    return _vector(where, value, len(names))


def load_robot_description(path=None) -> RobotDescription:
    """Load and validate a robot description YAML file (None: the shipped UR5e)."""
    path = Path(path) if path is not None else shipped_robot_path()
    return robot_description(_read_yaml(path, 'robot description'), str(path))


@dataclass(frozen=True)
class Program:
    """One nature's motion program: a closed cycle of waypoints (m, 6) and the duration
    (s, at override 1) of the segment into each waypoint from the previous one."""

    nature: int
    name: str
    waypoints: np.ndarray
    durations: np.ndarray

    @property
    def cycle_time(self) -> float:
        return float(np.sum(self.durations))

    def segment(self, n: int) -> tuple[np.ndarray, np.ndarray, float]:
        """Program segment n (from 0): its start and end waypoints and duration."""
        m = len(self.waypoints)
        end = (n + 1) % m
        return self.waypoints[n % m], self.waypoints[end], float(self.durations[end])


def programs_from(data: Mapping, description: RobotDescription, source: str = '') -> dict:
    """Validate a programs mapping: nature -> `Program` (natures 0, 2 and 3 are required)."""
    where = source or 'motion programs'
    try:
        known = {'programs', 'joints'}
        unknown = sorted(set(data) - known)
        if unknown:
            raise RobotDescriptionError(f'unknown keys {unknown}; known: '
                                        f'{", ".join(sorted(known))}')
        joints = data.get('joints', list(description.joint_names))
        if list(joints) != list(description.joint_names):
            strange = sorted(set(joints) - set(description.joint_names))
            raise RobotDescriptionError(
                (f'unknown joints {strange}; ' if strange else '')
                + f'joints must be the robot description\'s, in its order: '
                f'{", ".join(description.joint_names)}')
        programs_in = data.get('programs')
        if not isinstance(programs_in, dict):
            raise RobotDescriptionError('programs must map task natures (0 robot only, 2 either, '
                                        '3 both together) to programs')
        programs = {}
        for key, program in programs_in.items():
            if isinstance(key, bool) or not isinstance(key, int) or key not in NATURES:
                raise RobotDescriptionError(f'program key {key!r} is no task nature '
                                            f'(0..3: {NATURES})')
            programs[key] = _program(key, program, description)
        lack = [n for n in ROBOT_NATURES if n not in programs]
        if lack:
            raise RobotDescriptionError(f'no program for natures {lack} (every nature with a '
                                        'robot share needs one: 0, 2, 3)')
        return programs
    except RobotDescriptionError as exc:
        raise RobotDescriptionError(f'{where}: {exc}') from None


def _program(nature: int, program, description: RobotDescription) -> Program:
    where = f'program {nature}'
    if not isinstance(program, dict) or 'waypoints' not in program \
            or 'durations' not in program:
        raise RobotDescriptionError(f'{where} needs waypoints and durations')
    extra = sorted(set(program) - {'name', 'waypoints', 'durations'})
    if extra:
        raise RobotDescriptionError(f'{where}: unknown keys {extra}')
    waypoints_in = program['waypoints']
    if not isinstance(waypoints_in, list) or len(waypoints_in) < 2:
        raise RobotDescriptionError(f'{where}: waypoints must list at least 2 poses')
    waypoints = np.array([_pose(f'{where} waypoint {i}', w, description.joint_names)
                          for i, w in enumerate(waypoints_in)])
    durations = _vector(f'{where} durations', program['durations'], len(waypoints))
    for i, q in enumerate(waypoints):
        why = description.outside(q)
        if why:
            raise RobotDescriptionError(f'{where} waypoint {i}: {why}')
    m = len(waypoints)
    for i in range(m):
        shortest = segment_duration(waypoints[i - 1], waypoints[i], description.velocity,
                                    description.acceleration)
        if durations[i] <= 0 or durations[i] < shortest - 1e-9:
            raise RobotDescriptionError(
                f'{where}: the segment into waypoint {i} takes {durations[i]:.3f} s, shorter '
                f'than the {shortest:.3f} s the joint speed and acceleration limits allow')
    return Program(nature, str(program.get('name', NATURES[nature])), waypoints, durations)


def load_programs(description: RobotDescription, path=None) -> dict:
    """Load and validate a motion programs YAML file (None: the shipped UR5e programs)."""
    path = Path(path) if path is not None else shipped_programs_path()
    return programs_from(_read_yaml(path, 'motion programs file'), description, str(path))


# -- the bridge -------------------------------------------------------------------------------
def writers_reason(topic: str, publishers, owner: str) -> str:
    """Why the arm holds for what the graph shows of an input that must have one writer, the
    node that owns the cell (`owner`, a fully qualified node name; '' takes any one):
    `publishers` are the publishers' node names (None: not named by the graph yet). '' when
    it need not hold."""
    publishers = list(publishers)
    if len(publishers) > 1:
        names = ', '.join(p or 'a node the graph does not name yet' for p in publishers)
        return (f'{len(publishers)} publishers of {topic} ({names}): the arm holds while more '
                'than one can write (one cell, one decider)')
    if len(publishers) == 1 and owner:
        if publishers[0] is None:
            return (f'the graph does not name the publisher of {topic} yet: the arm holds until '
                    f'it is known to be {owner}')
        if publishers[0] != owner:
            return (f'{topic} is published by {publishers[0]}, not by {owner} (the owner this '
                    'bridge follows): the arm holds')
    return ''


OVERRIDE_CONSUMERS = ('cobot_sim', 'speed_scaling')   # node names that act on the override


def unconsumed_reason(topic: str, readers, consumers) -> str:
    """Why SSM cannot act on the arm through the override on `topic`, whose subscribers'
    node names are `readers`: none of them is one of `consumers` (node names, any namespace;
    empty: any reader acts). A display (the HMI), a recorder or `ros2 topic echo` reads it
    too, but only the arm's side acts on it: counting them kept the arm moving after its
    controller's adapter died. '' when a consumer reads it."""
    readers = list(readers)
    if (readers and not consumers) or any(r in consumers for r in readers):
        return ''
    if not readers:
        return f'nobody subscribes to the speed override on {topic}: SSM cannot act on the arm'
    # rmw names a subscriber's node UNKNOWN_NODE_NAME until discovery has its name (a consumer
    # that is starting)
    shown = ', '.join(sorted({'a node the graph does not name yet' if r == UNKNOWN_NODE_NAME else r
                              for r in readers})[:5])
    return (f'none of {", ".join(consumers)} (override_consumers) subscribes to the speed '
            f'override on {topic}, only {len(readers)} reader(s) that cannot act on the arm '
            f'({shown}): SSM cannot act on the arm')


def check_stamp(what: str, stamp_ns: int, now_ns: int, slack: float = FUTURE_SLACK) -> None:
    """InputError for a sample stamped more than `slack` s ahead of the clock: its source's
    clock runs ahead, and the sample would still look fresh after its source stopped."""
    ahead = (stamp_ns - now_ns) * 1e-9
    if ahead > slack:
        raise InputError(f'{what} stamped {ahead:.3f} s ahead of this clock (more than '
                         f'{slack:g} s): its source\'s clock is not synchronised with '
                         'this one, and an age from it cannot be trusted')


@dataclass
class ProgramRun:
    """The robot's share of one task: its nature's program for `cycles` cycles."""

    nature: int
    cycles: int
    task: tuple                 # (tp, tx) of the task it belongs to
    segments_done: int = 0
    started: bool = False       # reached W_0 once
    committed: bool = False     # the task state has shown the commitment

    def total(self, program: Program) -> int:
        return self.cycles * len(program.waypoints)

    def cycles_done(self, program: Program) -> int:
        return self.segments_done // len(program.waypoints)


@dataclass(frozen=True)
class Progress:
    """The robot's share of the current task: its nature, cycles asked and done."""

    nature: int
    cycles: int
    cycles_done: int

    @property
    def complete(self) -> bool:
        return self.cycles_done >= self.cycles


class JointStateReader:
    """A sensor_msgs/JointState's arrays in the description's joint order: (q, qd), or
    InputError (nothing kept) for a missing joint, NaN, or a position outside the limits.
    Joints the description does not name (a gripper) are ignored; no velocities: zeros."""

    def __init__(self, description: RobotDescription):
        self.description = description
        self._names: tuple | None = None
        self._order = np.arange(len(description.joint_names))

    def read(self, names, positions, velocities=()) -> tuple[np.ndarray, np.ndarray]:
        names = tuple(names)
        positions = np.asarray(positions, dtype=float).reshape(-1)
        velocities = np.asarray(velocities, dtype=float).reshape(-1) if len(velocities) \
            else np.zeros(len(names))
        if len(positions) != len(names) or len(velocities) != len(names):
            raise InputError(f'joint state with {len(names)} names, {len(positions)} positions '
                             f'and {len(velocities)} velocities')
        if names != self._names:
            where = {n: i for i, n in enumerate(names)}
            # which copy is the joint? (a merged source; joints the arm ignores may repeat)
            twice = [n for n in self.description.joint_names if names.count(n) > 1]
            if twice:
                raise InputError(f'joint state names {", ".join(twice)} more than once')
            lack = [n for n in self.description.joint_names if n not in where]
            if lack:
                raise InputError(f'joint state without {", ".join(lack)} (has '
                                 f'{", ".join(names) or "no joints"})')
            self._order = np.array([where[n] for n in self.description.joint_names])
            self._names = names
        q, qd = positions[self._order], velocities[self._order]
        why = self.description.outside(q)
        if why:
            raise InputError(f'joint state refused: {why}')
        if not np.isfinite(qd).all():
            raise InputError(f'joint state refused: velocities {qd.tolist()} are not finite')
        beyond = np.abs(qd) > VELOCITY_SLACK * self.description.velocity
        if beyond.any():
            i = int(np.argmax(beyond))
            raise InputError(f'joint state refused: {self.description.joint_names[i]} velocity '
                             f'{qd[i]:.6g} rad/s is more than {VELOCITY_SLACK:g} times its limit '
                             f'({self.description.velocity[i]:g} rad/s): no arm moves so')
        return q, qd


@dataclass(frozen=True)
class BridgeCommand:
    """What to send after a tick: a new trajectory (or None), the speed override 0..1, the
    protective stop and its reason, the SSM state, the separation, and the motion's name
    (hold, program, retreat, collaboration, idle, braking: on the way to a safe point)."""

    trajectory: Trajectory | None
    override: float
    stop: bool
    reason: str
    ssm: SsmState | None
    separation: Separation | None
    motion: str
    reports: tuple = ()


MOTIONS = ('idle', 'program', 'retreat', 'collaboration')


class Bridge:
    """The robot bridge (see the module docstring). Times are integer nanoseconds of one
    clock; `period` is the control period (s) the override is held for."""

    def __init__(self, description: RobotDescription, programs: Mapping, arm: Arm | None = None,
                 period: float = 0.01, latency: float | None = None):
        self.description = d = description
        self.programs = dict(programs)
        self.arm = arm if arm is not None else Arm()
        # SSM commands for the control period plus the way to the controller (`latency`, the
        # description's command_latency unless given: the batch's controller takes each
        # override in the step it is sent); the monitor checks what is measured against SSM at
        # the instant (module docstring, "The monitor").
        latency = d.command_latency if latency is None else float(latency)
        if not (math.isfinite(latency) and latency >= 0):
            raise ValueError(f'latency must be a finite number of seconds >= 0, got {latency!r}')
        self.latency = latency
        self.monitor = SpeedSeparationMonitor(d.ssm, period + latency)
        self.index = {name: i for i, name in enumerate(d.joint_names)}
        self.q: np.ndarray | None = None
        self.qd = np.zeros(len(self.index))
        self._joint_stamp: int | None = None
        # the positions' motion against the velocities' (a frozen driver: `_frozen_joints`)
        self.joint_freeze = (JointFreezeCheck(d.joint_state_timeout, d.rest_speed),
                             JointFreezeCheck(LAG_WINDOW, d.rest_speed, share=LAG_SHARE,
                                              gap=LAG_GAP))
        self._joints_frozen, self._joints_clear_since = '', None
        self.body: BodyCapsules | None = None
        self._body_stamp: int | None = None
        self._content_stamp: int | None = None   # the stamp of the last skeleton that changed
        self._frames: deque = deque(maxlen=64)   # (stamp, body) of the followed, as they changed
        self.approach = 0.0           # m/s: the person's measured directed speed toward the arm
        self.task: dict | None = None
        self.last_action: int | None = None
        self.paused = True            # nothing asked yet: hold
        self.motion = 'idle'          # what the active trajectory does
        self.active: Trajectory | None = None
        self._next = 0                # the active trajectory's next waypoint (segment index)
        self.pending: str | None = None
        self.run: ProgramRun | None = None
        self._stop_reason = ''
        self._peaks: dict = {}
        self.joint_states = JointStateReader(d)
        self._joint_writer = SingleWriter('joint_states', d.joint_state_timeout,
                                          SECOND_WRITER_HOLD)
        self.writers = {kind: SingleWriter(f'hrc/{kind}', WRITER_HOLD, WRITER_HOLD)
                        for kind in ('action', 'task_state')}
        self._graph_holds: dict = {}
        self._skeleton_lock = StreamLock()
        self._others: deque = deque(maxlen=OTHER_BODIES)     # (body, stamp ns) to count too
        # The monitor (core/robot/guard.py).
        self.measured = MeasuredSpeed(self.arm, max_dt=d.joint_state_timeout)
        self.envelope = SpeedEnvelope(d.ssm.deceleration, latency + period,
                                     horizon=d.joint_state_timeout)
        self.skeleton_check = SkeletonCheck(d.frozen_tolerance, d.max_body_speed)
        self.fault = ''               # the monitor's protective stop ('' = none)
        self._fault_clear_since: int | None = None
        self._replace = False         # a goal of the bridge's must replace the controller's
        self.counts = {'overspeed': 0, 'foreign_motion': 0, 'implausible_skeletons': 0,
                       'frozen_skeletons': 0, 'goals_resent': 0, 'lost_people': 0,
                       'clock_steps': 0, 'frozen_joint_states': 0}
        self._still_since: int | None = None    # the arm at rest on an unfinished goal
        self._resent = 0              # goals sent again in a row without the arm moving
        # A person the followed tracker lost near the arm (`_track_loss`): (bodies in the frame
        # that last showed them, their S m) while frames that dropped them are refused as
        # jumps; `lost` the hold's reason once such a frame replaced theirs ('' = none).
        self._losing: tuple[int, float] | None = None
        self.lost, self._lost_people = '', 0
        self._seen: tuple | None = None   # (people, S m) of the last frame taken

    # -- inputs ------------------------------------------------------------------------------
    def joint_state(self, names, positions, velocities, stamp_ns: int, now_ns: int,
                    sequence: int | None = None) -> None:
        """The arm's joint state; InputError (nothing kept) for a missing joint, NaN, a
        position outside the limits (`JointStateReader`), a stamp ahead of the clock
        (`check_stamp`) or a second writer (`sequence`: its publication sequence number; the arm
        then holds, module docstring)."""
        self._joint_writer.check(sequence, now_ns * 1e-9)
        check_stamp('joint state', stamp_ns, now_ns, self.description.clock_skew)
        self.q, self.qd = self.joint_states.read(names, positions, velocities)
        self._joint_stamp = int(stamp_ns)
        for check in self.joint_freeze:
            check.update(int(stamp_ns), self.q, self.qd)
        self.measured.update(self.q, self.qd, stamp_ns)

    def skeleton(self, body: BodyCapsules | None, stamp_ns: int, now_ns: int,
                 sequence: int | None = None) -> None:
        """The person's capsules (None: nobody in view, which SSM treats as no data) from the
        writer of publication sequence number `sequence`; InputError for a stamp ahead of the
        clock. Another writer's, or one stamped before the newest held, counts beside it
        (module docstring, "One arm, every person"); so does one that jumped away from the arm
        faster than a person can move, and one that repeats the held one is no new data
        (`guard.SkeletonCheck`)."""
        if body is not None and not isinstance(body, BodyCapsules):
            raise InputError(f'a skeleton is BodyCapsules, got {type(body).__name__}')
        if body is not None:
            check_stamp('skeleton', stamp_ns, now_ns, self.description.clock_skew)
        stream = self._skeleton_lock.classify(sequence, now_ns * 1e-9,
                                              self.monitor.p.human_timeout)
        if stream == StreamLock.OTHER or (body is not None and self._body_stamp is not None
                                          and stamp_ns < self._body_stamp):
            if body is not None:
                self._others.append((body, int(stamp_ns)))
            return
        if body is None:
            self.body, self._body_stamp, self._content_stamp = None, None, None
            self._frames.clear()
            self.approach = 0.0
            return
        held = self.body
        live = held is not None and \
            (now_ns - self._content_stamp) * 1e-9 <= self.monitor.p.human_timeout
        # its separation at the arm's current configuration, once for every rule below
        distance = self.arm.distance(self.q, body) if self.q is not None else math.inf
        if live and self.q is not None and self._jumped_away(distance, stamp_ns):
            self._others.append((body, int(stamp_ns)))     # it can only slow the arm
            self.counts['implausible_skeletons'] += 1
            if self._losing is None:
                self._losing = (people(held), self.arm.distance(self.q, held))
            return
        self._track_loss(body, distance, live)
        if held is not None and self.skeleton_check.unchanged(body, held):
            self.body, self._body_stamp = body, int(stamp_ns)     # no new data: it ages
            self.counts['frozen_skeletons'] += 1
            return
        self.body, self._body_stamp, self._content_stamp = body, int(stamp_ns), int(stamp_ns)
        self._measure_approach(body, distance, int(stamp_ns))

    def _track_loss(self, body: BodyCapsules, now: float, live: bool) -> None:
        """A frame taken after frames that dropped the person nearest the arm were refused as
        jumps (`_losing`) replaces theirs only because it aged out: the tracker lost them
        (occluded, by the arm too, or a tracker that switched to someone else), and a person
        who cannot be seen can still be there. Nearer than lost_person_distance that holds the
        arm (`lost`) until a frame shows more people than the one that dropped them, one of
        them nearer the arm than lost_person_distance (another person walking in far away is
        not the lost one), or `clear_lost()` (the operator, who looked). Farther, or still
        live, it is forgotten. A frame with fewer people than the last one taken (also across
        frames of nobody) whose nearest person is farther from the arm than that one's, by
        more than the gate's JUMP_SLACK, lost someone too: the nearer person may be the one
        missing (identities are not known), so it holds the same way when that frame's nearest
        was nearer than lost_person_distance. `now`: the frame's separation (m)."""
        near = self.description.lost_person_distance
        count = people(body)
        if self.lost and count > self._lost_people and now < near:
            self.lost = ''            # someone is seen again where the lost person may be
        seen, self._seen = self._seen, (count, now)
        if seen is not None and count < seen[0] and seen[1] < near \
                and now > seen[1] + JUMP_SLACK:
            self._losing, live = self._losing or seen, False
        if self._losing is not None and not live:
            bodies, distance = self._losing
            if distance < near and not self.lost:
                self._lost_people = count
                self.lost = (f'the tracker lost a person {distance:.2f} m from the arm (a frame '
                             f'of {bodies} people became {self._lost_people}): the arm holds '
                             'until they are seen again or the stop is cleared')
                self.counts['lost_people'] += 1
        self._losing = None

    def clear_lost(self) -> bool:
        """The operator's clear of a lost person's hold (they looked: nobody is there).
        True if there was one."""
        was, self.lost, self._losing = bool(self.lost), '', None
        return was

    def _jumped_away(self, new: float, stamp_ns: int) -> bool:
        """A skeleton farther from the arm (`new`, its separation in m) than the person can
        have moved since the held one or since the followed frame at least APPROACH_WINDOW
        older (against the held one alone, the gate's slack adds up frame by frame: a skeleton
        sliding away at 30 Hz passed at 4 m/s)."""
        refs = [(self._content_stamp, self.body)]
        window = int(APPROACH_WINDOW * 1e9)
        older = [f for f in self._frames if f[0] <= stamp_ns - window]
        refs.append(older[-1] if older else (self._frames[0] if self._frames else refs[0]))
        return any(self.skeleton_check.jumped_away(new, self.arm.distance(self.q, ref),
                                                   (stamp_ns - then) * 1e-9)
                   for then, ref in refs)

    def _measure_approach(self, body: BodyCapsules, distance: float, stamp_ns: int) -> None:
        """The person's directed speed toward the arm (m/s) from the followed tracker's
        skeletons over APPROACH_WINDOW: the fall of their separation, both at the arm's current
        configuration (the arm's own motion left out), plus APPROACH_NOISE (the tracker's
        jitter over the window). SSM plans for it where it exceeds ISO 13855's speeds
        (`ssm.directed_speeds`). `distance`: the body's separation (m)."""
        history = self._frames
        while history and history[-1][0] >= stamp_ns:
            history.pop()
        history.append((stamp_ns, body))
        while len(history) > 2 and stamp_ns - history[1][0] >= APPROACH_WINDOW * 1e9:
            history.popleft()
        then, old = history[0]
        dt = (stamp_ns - then) * 1e-9
        if self.q is None or dt < APPROACH_WINDOW / 2:
            self.approach = 0.0
            return
        fall = self.arm.distance(self.q, old) - distance
        self.approach = max(0.0, fall / dt) + APPROACH_NOISE if fall > 0 else 0.0

    def _nearest(self, now_ns: int) -> tuple[Separation | None, int | None]:
        """The separation SSM takes: the nearest of the bodies held (the followed writer's
        newest, and the others' of the last human_timeout), with the oldest of their stamps
        (the followed body's: of its last change)."""
        timeout_ns = self.monitor.p.human_timeout * 1e9
        while self._others and now_ns - self._others[0][1] > timeout_ns:
            self._others.popleft()
        held = [(b, t) for b, t in self._others if now_ns - t <= timeout_ns]
        if self.body is not None:
            held.append((self.body, self._content_stamp))
        if not held:
            return None, None
        seps = [self.arm.separation(self.q, b) for b, _ in held]
        # the stamps as old as the sensors' clocks may be off (clock_skew): the age counts it
        skew = int(self.description.clock_skew * 1e9)
        return min(seps, key=lambda sep: sep.distance), min(t for _, t in held) - skew

    def goal_publishers(self, count: int) -> None:
        """How many publishers the graph shows on the goal topic (this bridge's included)."""
        count = int(count)
        self.graph_hold('goal', '' if count <= 1 else (
            f'{count - 1} other publisher(s) of the goal topic: the override bounds only the '
            'bridge\'s own goals'))

    def graph_hold(self, kind: str, reason: str) -> None:
        """Hold the arm (a protective stop with `reason`) while the graph shows what `reason`
        says of the input `kind` (another publisher of hrc/action, of the goal topic, ...);
        '' releases it."""
        self._graph_holds[kind] = str(reason)

    def check_writer(self, kind: str, sequence: int | None, now_ns: int) -> None:
        """InputError for a message of `kind` ('action', 'task_state') from a writer other than
        the one followed (publication sequence numbers, `protocol.SingleWriter`): it is
        refused, and the arm holds until that writer has been silent for its hold."""
        self.writers[kind].check(sequence, now_ns * 1e-9)

    def task_state(self, state: Mapping, now_ns: int) -> None:
        """hrc/task_state x: the eight task variables."""
        try:
            x = {n: int(state[n]) for n in TASK_VARIABLES}
        except (KeyError, TypeError, ValueError):
            raise InputError(f'task state must map {", ".join(TASK_VARIABLES)} to integers, '
                             f'got {state!r}') from None
        self.task = x
        run = self.run
        if run is None:
            return
        same_task = (x['tp'], x['tx']) == run.task
        robot_in = x['ty'] in (2, 3) and x['bc'] > 0
        if robot_in and same_task:
            run.committed = True
        elif run.committed or not same_task or x['ty'] not in (0, 2, 3):
            self._drop_run()

    def action(self, action, now_ns: int) -> None:
        """hrc/action a_k (name or index); InputError for an unknown action."""
        try:
            a = action_index(action)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        self.last_action = a
        if a == DN:
            self.paused = True
            return
        if a in (RH1, RH2, MH):
            # requests to the person: the motion stays as it is, except that a committed
            # program that is not running runs, as under nw (the model's robot works under
            # them: MODEL.md 3.2, robot_paused_by); a hold stays a hold
            if not self.paused:
                self._continue_program()
            return
        self.paused = False
        x = self.task
        if a == DP:
            self._want('retreat')
        elif a == DM:
            self._want('collaboration')
        elif a == CT and x is not None and bool(commit_effective(x['tp'], x['tx'], x['ty'])):
            if x['tx'] in self.programs:
                self._drop_run()
                self.run = ProgramRun(x['tx'], max(1, x['tc']), (x['tp'], x['tx']))
                self._want('program')
        elif a in (NW, CT):
            self._continue_program()

    # -- the tick ------------------------------------------------------------------------------
    def tick(self, now_ns: int) -> BridgeCommand:
        """What to send now (see the module docstring)."""
        reports = []
        stepped = self._clock_stepped_back(now_ns)
        if stepped:
            self._note_stop(stepped, reports)
            self.envelope.command(now_ns, 0.0)
            return BridgeCommand(None, 0.0, True, stepped, None, None, 'hold', tuple(reports))
        fresh = (self.q is not None and self._joint_stamp is not None
                 and (now_ns - self._joint_stamp) * 1e-9 <= self.description.joint_state_timeout)
        reason = ''
        if not fresh:
            reason = ('no joint state yet' if self.q is None else
                      'no joint state since the clock stepped back' if self._joint_stamp is None
                      else f'joint state {(now_ns - self._joint_stamp) * 1e-9:.3f} s old '
                      f'(joint_state_timeout {self.description.joint_state_timeout} s)')
        else:
            reason = self._frozen_joints(now_ns) or self._hold_reason(now_ns)
        if reason:
            self._note_stop(reason, reports)
            self.envelope.command(now_ns, 0.0)
            return BridgeCommand(None, 0.0, True, reason, None, None, 'hold', tuple(reports))
        self._track_progress()
        sep, human_stamp = self._nearest(now_ns)
        fault = self._watch(now_ns, sep, human_stamp)
        trajectory = None
        if self.pending is not None and self._at_rest() and (not self.paused or self._replace):
            motion = 'idle' if self.paused else self.pending
            trajectory = self._plan(motion)
            self.motion = motion if len(trajectory.durations) else 'idle'
            if not self.paused:
                self.pending = None
            self._replace = False
            self.active, self._next = trajectory, 0
        # Nothing of the bridge's own to move (a stay, no goal yet, a goal run to its end):
        # override 0, so that a goal it did not send cannot run on its override.
        own = self.active is not None and self._next < len(self.active.durations)
        nominal = self.active.nominal_speed if own else 0.0
        # SSM on the person as near as the tracker's error allows (the check of a run is on
        # the true body, with ISO's Z_d whole), and the arm as near as it may have come since
        # its joint state (the commanded speed for the state's age)
        state = self.monitor.update(None if sep is None else sep.distance - self._unseen(now_ns),
                                    human_stamp, now_ns, nominal, self.approach)
        override = state.override if own else 0.0
        motion = self.motion
        if self.paused:
            override, motion = 0.0, 'hold'
        elif self.pending is not None:
            override, motion = 0.0, 'braking'
        elif self.motion == 'collaboration':
            override = min(override, self.description.collaboration_speed)
        stop, reason = state.stop, state.reason
        if fault:
            override, stop, reason = 0.0, True, fault
        elif stop:
            reason = self._frozen_reason(now_ns, reason)
        self._stalled(now_ns, override * nominal)
        self.envelope.command(now_ns, override * nominal)
        if stop:
            self._note_stop(reason, reports)
        elif self._stop_reason:
            reports.append(Report(OK, 'ssm', 'protective stop cleared', {}, kind='stop'))
            self._stop_reason = ''
        return BridgeCommand(trajectory, override, stop, reason, state, sep, motion,
                             tuple(reports))

    def _clock_stepped_back(self, now_ns: int) -> str:
        """The clock stepped back (an NTP or PTP step, `date`, a /clock that restarted) when
        what is held is stamped more than clock_skew ahead of it: every age from those stamps
        would read 0 (a skeleton the tracker stopped sending would stay fresh for the step, and
        the frames of the tracker it follows would count as older than the held one). Then
        the joint state and the skeletons held are dropped, the commanded bounds taken as given
        now (`SpeedEnvelope.rebase`), and the arm holds until fresh data comes (a lost person's
        hold stays). '' when the clock is sane."""
        # (the followed frames of `_frames` are no newer than `_body_stamp`: not scanned)
        held = [t for t in (self._joint_stamp, self._body_stamp, self._content_stamp,
                            self.envelope.newest) if t is not None]
        held += [t for _, t in self._others]
        ahead = (max(held) - now_ns) * 1e-9 if held else 0.0
        if ahead <= self.description.clock_skew:
            return ''
        self._joint_stamp = None      # its configuration stays: where the arm was last seen
        self._restart_joint_checks()
        self.envelope.rebase(now_ns)
        self.body, self._body_stamp, self._content_stamp = None, None, None
        self._others.clear()
        self._frames.clear()
        self.approach = 0.0
        self._fault_clear_since = self._still_since = None
        # the writers' lines too: their times lie in the clock's future, and a writer that
        # restarted with the clock numbers from 1 (it was refused as a second writer until the
        # clock caught up: a replay's whole previous run)
        for writer in (self._joint_writer, *self.writers.values()):
            writer.clock_stepped_back(now_ns * 1e-9)
        self._skeleton_lock.forget()
        self.counts['clock_steps'] += 1
        return (f'the clock stepped back: data held is stamped {ahead:.3f} s ahead of it (more '
                f'than clock_skew {self.description.clock_skew} s); the joint state and '
                'skeletons held are dropped and the arm holds until fresh ones come')

    def _frozen_joints(self, now_ns: int) -> str:
        """Why the joint states are no data though fresh (module docstring): over
        joint_state_timeout their positions moved less than a quarter of what their velocities
        claim, or over LAG_WINDOW less than LAG_SHARE of it and LAG_GAP behind (positions that
        lag ever further behind: a backlog, a replay slower than real time). A stop holds until
        both checks have agreed for joint_state_timeout (messages at rest among frozen ones
        clear a check now and then), and counts once; then both checks start again from the
        next sample."""
        reason = next((r for r in (check.reason() for check in self.joint_freeze) if r), '')
        if reason:
            if not self._joints_frozen:
                self.counts['frozen_joint_states'] += 1
            self._joints_frozen, self._joints_clear_since = reason, None
            return reason
        if not self._joints_frozen:
            return ''
        if self._joints_clear_since is None:
            self._joints_clear_since = now_ns
        if (now_ns - self._joints_clear_since) * 1e-9 >= self.description.joint_state_timeout:
            # the windows start again: the frozen samples in them would read as a lag
            self._restart_joint_checks()
            return ''
        return self._joints_frozen

    def _restart_joint_checks(self) -> None:
        """Both frozen-driver checks from the next joint state on, no stop held."""
        for check in self.joint_freeze:
            check.clear()
        self._joints_frozen, self._joints_clear_since = '', None

    def _hold_reason(self, now_ns: int) -> str:
        """Why the arm holds whatever SSM says: the graph shows another writer of an input
        (`graph_hold`), or a second writer's message came (joint states, actions, task states)."""
        for reason in self._graph_holds.values():
            if reason:
                return reason
        if self.lost:
            return self.lost
        now = now_ns * 1e-9
        for writer in (self._joint_writer, *self.writers.values()):
            if writer.held(now):
                return writer.reason
        return ''

    def _unseen(self, now_ns: int) -> float:
        """How much nearer than S the arm and the person may be (m) for what no sample shows:
        the tracker's error, and the arm's travel at the speed it was allowed since its joint
        state (which may be up to joint_state_timeout old)."""
        age = max(0.0, (now_ns - self._joint_stamp) * 1e-9 + self.description.clock_skew)
        return self.description.tracking_error + self.envelope.limit(self._joint_stamp) * age

    def _at_rest(self) -> bool:
        """Every joint slower than rest_speed, by the reported velocities and by the
        positions' differences."""
        rest = self.description.rest_speed
        return bool((np.abs(self.qd) <= rest).all()
                    and (np.abs(self.measured.joint_rate) <= rest).all())

    def _watch(self, now_ns: int, sep: Separation | None, human_stamp: int | None) -> str:
        """The monitor (module docstring and `guard`): the arm's measured speed against what
        the bridge commanded and against what SSM allows now, its configuration against the
        bridge's path. A breach is a protective stop that clears once none has been seen for
        resume_time; motion the bridge did not command also drops its path, so that a goal of
        its own replaces the controller's at rest."""
        d = self.description
        p = self.monitor.p
        measured = self.measured
        speed = measured.speed
        limit = self.envelope.limit(self._joint_stamp)   # what the arm may do at the sample
        # a difference of positions is the mean speed since `measured.since`: against the
        # most the commands allowed over that span (guard's docstring)
        spanned = limit if measured.since is None else self.envelope.limit(self._joint_stamp,
                                                                            measured.since)
        breach, foreign = '', False
        if measured.reported > limit + d.speed_tolerance:
            breach, foreign = (f'the arm moves at {measured.reported:.3f} m/s (its reported '
                               f'velocities), above the {limit:.3f} m/s the bridge commanded: '
                               'motion the bridge did not send'), True
        elif measured.differenced > spanned + d.speed_tolerance:
            breach, foreign = (f'the arm moves at {measured.differenced:.3f} m/s (its positions '
                               f'over {(self._joint_stamp - measured.since) * 1e-9:.3f} s), '
                               f'above the {spanned:.3f} m/s the bridge commanded in that time: '
                               'motion the bridge did not send'), True
        elif self.active is not None:
            off, direction = nearest_on_path(self.q, self.active.positions)
            # by the reported velocities: differences of positions cut the corners of the
            # path at its waypoints (the absolute deviation covers a driver whose velocities lie)
            across = self.arm.link_speed(self.q, across_path(self.qd, direction))
            if off > d.path_tolerance:
                breach, foreign = (f'the arm is {off:.3f} rad off the bridge\'s path '
                                   f'(path_tolerance {d.path_tolerance} rad): a goal the bridge '
                                   'did not send'), True
            elif across > d.speed_tolerance:
                breach, foreign = (f'the arm moves across the bridge\'s path at {across:.3f} m/s '
                                   f'(measured; speed_tolerance {d.speed_tolerance} m/s): a goal '
                                   'the bridge did not send'), True
        if not breach and sep is not None and speed > MOVING_SPEED:
            age = max(0.0, (now_ns - human_stamp) * 1e-9)
            if age <= p.human_timeout:
                allowed = max_speed(sep.distance - self._unseen(now_ns),
                                    directed_speeds(p, self.approach), age) or 0.0
                if speed > allowed + d.speed_tolerance:
                    breach = (f'the arm moves at {speed:.3f} m/s (measured), above the '
                              f'{allowed:.3f} m/s SSM allows at a separation of '
                              f'{sep.distance:.3f} m')
        if breach:
            if not self.fault:
                self.counts['foreign_motion' if foreign else 'overspeed'] += 1
            if foreign:
                if self.active is not None:
                    self.pending = self.pending or self.motion
                self.active = None
                self._replace = True
            self.fault, self._fault_clear_since = breach, None
        elif self.fault and not self._replace:      # cleared once the bridge's goal is back
            if self._fault_clear_since is None:
                self._fault_clear_since = now_ns
            if (now_ns - self._fault_clear_since) * 1e-9 >= p.resume_time:
                self.fault = ''
        return self.fault

    def _stalled(self, now_ns: int, bound: float) -> None:
        """The arm stands still on an unfinished goal of the bridge's while it commands motion
        (at least SSM's min_speed) for STALL_RESEND s: the controller dropped or refused the
        goal (a forged goal it refused holds it until a valid one comes). The goal is sent
        again from where the arm stands."""
        active = self.active
        running = (active is not None and self._next < len(active.durations)
                   and self.pending is None and bound >= self.monitor.p.min_speed)
        if not running or not self._at_rest():
            self._still_since = None
            if running:
                self._resent = 0          # it moves: the controller follows
            return
        if self._still_since is None:
            self._still_since = now_ns
        elif (now_ns - self._still_since) * 1e-9 >= STALL_RESEND:
            self.pending, self._still_since = self.motion, None
            self.counts['goals_resent'] += 1
            self._resent += 1
            if self._resent > STALL_RESENDS:
                # the controller does not follow: hold, say why, and wait for an action
                self.paused, self._resent = True, 0
                self.fault, self._fault_clear_since = (
                    f'the controller did not follow the bridge\'s goal {STALL_RESENDS + 1} '
                    'times in a row (the arm stands while motion is commanded): the arm holds '
                    'until the next action'), None

    def _frozen_reason(self, now_ns: int, reason: str) -> str:
        """SSM's stop for old data, named for what it is when the followed skeleton's stamps
        are fresh but its content stopped changing (a frozen tracker)."""
        if self.body is None or self._content_stamp is None \
                or self._body_stamp == self._content_stamp:
            return reason
        frozen = (now_ns - self._content_stamp) * 1e-9
        if frozen <= self.monitor.p.human_timeout:
            return reason
        return (f'the skeleton has not changed (by frozen_tolerance '
                f'{self.description.frozen_tolerance} m) for {frozen:.2f} s while its stamps '
                'advance: a frozen tracker, the person may be anywhere')

    # -- views ---------------------------------------------------------------------------------
    @property
    def progress(self) -> Progress | None:
        """The robot's share of the current task, None when it has none."""
        run = self.run
        if run is None:
            return None
        return Progress(run.nature, run.cycles, run.cycles_done(self.programs[run.nature]))

    # -- internals -----------------------------------------------------------------------------
    def _note_stop(self, reason: str, reports: list) -> None:
        if reason != self._stop_reason:
            reports.append(Report(WARN, 'ssm', f'protective stop: {reason}', {}, kind='stop'))
            self._stop_reason = reason

    def _want(self, motion: str) -> None:
        self.pending = motion

    def _drop_run(self) -> None:
        if self.run is not None:
            self.run = None
            if self.motion == 'program' or self.pending == 'program':
                self.pending = 'idle'

    def _continue_program(self) -> None:
        x = self.task
        run = self.run
        if run is None and x is not None and x['ty'] in (2, 3) and x['bc'] > 0 \
                and x['tx'] in self.programs:
            # Committed without a ct of ours (an accepted rh2, a restart): start the share.
            run = self.run = ProgramRun(x['tx'], x['bc'], (x['tp'], x['tx']), committed=True)
        if run is None or run.segments_done >= run.total(self.programs[run.nature]):
            return
        if self.motion != 'program' or self.active is None:
            self._want('program')

    def _track_progress(self) -> None:
        traj = self.active
        if traj is None or self._next >= len(traj.durations):
            return
        target = traj.positions[self._next + 1]
        if np.max(np.abs(self.q - target)) > self.description.waypoint_tolerance:
            return
        mark = traj.marks[self._next] if self._next < len(traj.marks) else -1
        self._next += 1
        run = self.run
        if self.motion == 'program' and run is not None:
            if mark == -1:
                run.started = True
            else:
                run.started = True
                run.segments_done = max(run.segments_done, mark + 1)

    def _plan(self, motion: str) -> Trajectory:
        """The trajectory of `motion` from the arm's configuration; a trajectory of no
        segment (stay where the arm stands) when there is nothing to do."""
        q = self.q
        d = self.description
        if motion in ('retreat', 'collaboration'):
            return self._trajectory(q, [d.poses[motion]], [0.0], [-1], motion)
        run = self.run
        if motion == 'idle' or run is None:
            return self._trajectory(q, [], [], [], 'idle')
        program = self.programs[run.nature]
        total = run.total(program)
        if run.segments_done >= total:
            return self._trajectory(q, [], [], [], 'idle')
        targets, durations, marks = [], [], []
        k = run.segments_done
        if not run.started:
            start = program.waypoints[0]
            if np.max(np.abs(q - start)) > d.waypoint_tolerance:
                targets.append(start)
                durations.append(0.0)
                marks.append(-1)
            else:
                run.started = True
        for n in range(k, total):
            _, end, duration = program.segment(n)
            targets.append(end)
            durations.append(duration)
            marks.append(n)
        return self._trajectory(q, targets, durations, marks, 'program')

    def _trajectory(self, q, targets, durations, marks, kind) -> Trajectory:
        d = self.description
        positions = [np.asarray(q, dtype=float)]
        times, peaks = [], []
        for target, nominal in zip(targets, durations):
            start = positions[-1]
            shortest = segment_duration(start, target, d.velocity, d.acceleration)
            duration = max(float(nominal), shortest, 1e-3)
            peak = self._peak(start, target, duration)
            if peak > d.max_link_speed:
                duration *= peak / d.max_link_speed
                peak = d.max_link_speed
            positions.append(np.asarray(target, dtype=float))
            times.append(duration)
            peaks.append(peak)
        return Trajectory(d.joint_names, np.array(positions), np.array(times, dtype=float),
                          float(max(peaks, default=0.0)), tuple(marks), kind)

    def _peak(self, start, target, duration) -> float:
        key = (start.tobytes(), np.asarray(target, dtype=float).tobytes(), duration)
        peak = self._peaks.get(key)
        if peak is None:
            peak = peak_link_speed(self.arm, start, target, duration)
            if len(self._peaks) < 4096:
                self._peaks[key] = peak
        return peak


__all__ = ['ACTIONS', 'Bridge', 'BridgeCommand', 'Program', 'ProgramRun', 'Progress',
           'RobotDescription', 'RobotDescriptionError', 'load_programs',
           'load_robot_description', 'programs_from', 'robot_description', 'writers_reason']
