"""Every ROS message <-> numpy/Python conversion of hrc_ros, with the validation of inputs.

The nodes read a message, convert it here, call the ROS-free core and convert the result back
(the py_trees_ros `conversions.py` split). A `*_from_msg` function either returns a value the
core accepts or raises `MessageError` (a `ValueError`) whose message says what is wrong, so a
node can drop the message with a warning and a diagnostic and carry on. A `*_to_msg` function
builds the message of a value the core produced.

Wire formats (INTERFACES.md, plus the decisions below):

- `human/joint_states` (sensor_msgs/JointState): names non-empty, unique, at most
  `MAX_JOINTS`; `velocity` (rad/s) and `position` (rad), when present, one per name and
  finite, the velocities at most `observation.MAX_JOINT_SPEED` in magnitude. If `velocity`
  is empty it is derived from two successive messages with the same names:
  ``v = (q_k - q_{k-1}) / (t_k - t_{k-1})`` with t the header stamps (`joint_velocities`),
  bounded alike.
- `human/skeleton` (geometry_msgs/PoseArray): keypoint positions in metres in the robot base
  frame `ROBOT_BASE_FRAME`; 1 to `MAX_KEYPOINTS` keypoints; finite and within
  `observation.MAX_KEYPOINT_RANGE` of the frame's origin (a keypoint beyond any tracker's
  range is malformed, never "far"). Orientations are ignored.
- `hrc/task_state` (std_msgs/UInt8MultiArray): ``[tp, tc, tx, ty, hp, hc, bp, bc]`` with one
  layout dimension per variable, labelled by its name (size 1, stride 1): a labelled record,
  not a tensor; a task manager whose model has a queue (MODEL.md 8.1) appends ``queued``, the
  tasks waiting (capped at 255), as a ninth labelled value. An empty layout is accepted (a
  hand-typed message); a layout with other labels is refused. `hrc/sim/true_state` is the same
  with the 11 state variables ``em .. d``.
- `hrc/task_request` (std_msgs/UInt8MultiArray): ``[tp, tc, tx]``; the layout is not read.
- `hrc/task_request_result` (diagnostic_msgs/DiagnosticStatus): the task manager's report on
  each request, key-values `accepted`, `tp`, `tc`, `tx`, `request`, `reason`, `published_ns`
  (the request's source timestamp), `sequence`, `queued` (docs/INTERFACES.md).
- `hrc/belief` (std_msgs/Float64MultiArray): 9 probabilities over h = 3*em + ea (row-major
  em, ea), layout dims ``motivation`` (size 3, stride 9) and ``aggression`` (size 3, stride 3).
  Non-negative, finite, summing to 1 within `BELIEF_TOLERANCE`.
- `hrc/action` (std_msgs/String): one of ``nw rh1 rh2 ct dp dm mh dn``, exactly.
- `hrc/estimator_config` (std_msgs/String): ``"<sha256> <source>"``, the `Config.belief_hash`
  (64 hex digits) of the configuration the belief estimator runs, a space, and its file.
- `hrc/_clock_claim` (std_msgs/String, hidden): a decision node's claim to decide for the
  cell, ``"<started_ns> <id> <timer|topic> <node>"`` (`core.protocol.Claim`).
- `hrc/_epoch_ready` (std_msgs/String, hidden): a listener of `hrc/epoch` names the node that
  holds its reader and the epoch writers that reader has matched, ``"<node> <gid> ..."``
  (`core.protocol.ReadyMark`).
- `hrc/observation`, `hrc/distance_level` (std_msgs/UInt8), `hrc/epoch` (std_msgs/UInt32),
  `hrc/human_response` (std_msgs/Bool).
- `/diagnostics` (diagnostic_msgs/DiagnosticArray): `diagnostic_status` formats key-values.
- `body_tracking_data` (visualization_msgs/MarkerArray, the Azure Kinect / Orbbec drivers'
  layout, `core.cell.tracking`): ADD markers, one per joint, ``id = body * 100 + joint`` with the
  joint < 32, all in `camera_frame`, all with one stamp, finite, every body with all 32
  joints; other actions (DELETE, DELETEALL) carry no joint and are skipped. An array without
  ADD markers is a frame without bodies.
- `hrc/markers` (visualization_msgs/MarkerArray): `core.cell.view` shapes after a DELETEALL.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseArray
from sensor_msgs.msg import JointState
from std_msgs.msg import (Bool, Float64, Float64MultiArray, MultiArrayDimension, String, UInt8,
                          UInt8MultiArray, UInt32)
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import Marker, MarkerArray

from ..core.pomdp.belief import BELIEF_TOLERANCE
from ..core.model import (ACTION_INDEX, ACTIONS, DISTANCE_LEVELS, N_HIDDEN, OBSERVATION_LEVELS,
                          STATE_VARIABLES, TASK_VARIABLES, action_index)
from ..core.decision.observation import HUMAN_JOINTS  # noqa: F401 - the joint names, re-exported
from ..core.decision.observation import (MAX_JOINTS, MAX_KEYPOINTS, check_joint_speeds,
                                         check_keypoint_range)
from ..core.protocol import Claim, InputError, ReadyMark
from ..core.quoting import QUOTE_LIMIT, cap, quote  # noqa: F401 - the one home, re-exported
from ..core.cell.tracking import (K4ABT_JOINTS, MARKER_ID_STRIDE, MAX_BODIES, MAX_RANGE, BodyFrame,
                                  split_marker_id)
from ..core.cell.view import Shape

ROBOT_BASE_FRAME = 'base_link'
BELIEF_DIMS = (('motivation', 3, 9), ('aggression', 3, 3))
# Domain of each task variable besides the priorities / counters (whose top is rho / sigma).
_NATURE_COMMITMENT_TOP = 3
# hrc/task_state's optional ninth value: the tasks waiting in the task manager's queue (MODEL.md
# 8.1), published by a task manager whose model has a queue; a UInt8, so capped
QUEUED = 'queued'
QUEUED_LABELS = TASK_VARIABLES + (QUEUED,)
MAX_QUEUED = 255

LEVEL_NAMES = {DiagnosticStatus.OK: 'OK', DiagnosticStatus.WARN: 'WARN',
               DiagnosticStatus.ERROR: 'ERROR', DiagnosticStatus.STALE: 'STALE'}


class MessageError(InputError):
    """A received message cannot be used; the text says why (the core's `InputError`, raised
    by a conversion)."""


# -- time -------------------------------------------------------------------------------------
def stamp_to_seconds(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def seconds_to_stamp(seconds: float) -> Time:
    sec = math.floor(seconds)
    return Time(sec=int(sec), nanosec=min(int(round((seconds - sec) * 1e9)), 999_999_999))


# -- human/joint_states -----------------------------------------------------------------------
@dataclass(frozen=True)
class JointSample:
    """One validated JointState: names, positions / velocities (None when absent), stamp (s)."""

    names: tuple
    position: np.ndarray | None
    velocity: np.ndarray | None
    stamp: float


def _finite_vector(values, what: str, n: int) -> np.ndarray | None:
    if len(values) == 0:
        return None
    if len(values) != n:
        raise MessageError(f'JointState has {n} names but {len(values)} {what} values')
    array = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(array)):
        raise MessageError(f'JointState {what} holds NaN or inf: {quote(array)}')
    return array


def _bounded_speeds(velocity: np.ndarray, what: str) -> np.ndarray:
    try:
        return check_joint_speeds(velocity, what)
    except ValueError as exc:
        raise MessageError(f'JointState {exc}') from None


def joint_sample_from_msg(msg: JointState) -> JointSample:
    """Validate a JointState: names (at most `MAX_JOINTS`), lengths, finiteness, velocities
    within `MAX_JOINT_SPEED`; velocity or position present."""
    if len(msg.name) > MAX_JOINTS:
        raise MessageError(f'JointState has {len(msg.name)} joints, more than {MAX_JOINTS}: '
                           "not one person's arm")
    names = tuple(msg.name)
    if not names:
        raise MessageError('JointState is empty (no joint names)')
    if len(set(names)) != len(names):
        raise MessageError(f'JointState names are not unique: {quote(names)}')
    velocity = _finite_vector(msg.velocity, 'velocity', len(names))
    position = _finite_vector(msg.position, 'position', len(names))
    if velocity is None and position is None:
        raise MessageError('JointState has neither velocities nor positions')
    if velocity is not None:
        _bounded_speeds(velocity, 'velocity')
    return JointSample(names, position, velocity, stamp_to_seconds(msg.header.stamp))


def joint_velocities(sample: JointSample, previous: JointSample | None = None
                     ) -> np.ndarray | None:
    """Joint velocities (rad/s) of a sample; derived from `previous` when it has none.

    Returns None when the velocity cannot be derived yet (no previous sample with positions of
    the same joints); raises `MessageError` when the stamps do not increase.
    """
    if sample.velocity is not None:
        return sample.velocity
    if previous is None or previous.position is None or previous.names != sample.names:
        return None
    dt = sample.stamp - previous.stamp
    if not dt > 0.0:
        raise MessageError(f'JointState without velocities and a header stamp ({sample.stamp:.9f}'
                           f' s) not after the previous one ({previous.stamp:.9f} s): cannot '
                           'derive velocities from positions')
    with np.errstate(over='ignore', invalid='ignore'):
        velocity = (sample.position - previous.position) / dt
    if not np.all(np.isfinite(velocity)):
        raise MessageError(f'JointState positions {quote(sample.position)} after '
                           f'{quote(previous.position)} in {dt:.3g} s give a velocity that is '
                           'not finite')
    return _bounded_speeds(velocity, f'velocity derived from positions {dt:.3g} s apart')


def joint_state_to_msg(names: Sequence[str], velocity, position=None,
                       stamp: Time | None = None) -> JointState:
    msg = JointState()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.name = list(names)
    msg.velocity = [float(v) for v in velocity]
    if position is not None:
        msg.position = [float(q) for q in position]
    return msg


# -- human/skeleton ---------------------------------------------------------------------------
def keypoints_from_msg(msg: PoseArray, frame_id: str = ROBOT_BASE_FRAME) -> np.ndarray:
    """Keypoint positions (n, 3) in metres; the header frame must be the robot base frame."""
    if msg.header.frame_id != frame_id:
        raise MessageError(f'PoseArray is in frame {quote(msg.header.frame_id)}, expected '
                           f'{frame_id!r} (keypoints must be in the robot base frame)')
    if not msg.poses:
        raise MessageError('PoseArray holds no keypoints')
    if len(msg.poses) > MAX_KEYPOINTS:
        raise MessageError(f'PoseArray holds {len(msg.poses)} keypoints, more than '
                           f'{MAX_KEYPOINTS} (16 bodies of 32 joints)')
    points = np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses],
                      dtype=float)
    if not np.all(np.isfinite(points)):
        raise MessageError('PoseArray keypoints hold NaN or inf')
    try:
        check_keypoint_range(points)
    except ValueError as exc:
        raise MessageError(f'PoseArray {exc}') from None
    return points


def keypoints_to_msg(points, stamp: Time | None = None,
                     frame_id: str = ROBOT_BASE_FRAME) -> PoseArray:
    msg = PoseArray()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    for x, y, z in np.asarray(points, dtype=float).reshape(-1, 3).tolist():
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = x, y, z
        pose.orientation.w = 1.0
        msg.poses.append(pose)
    return msg


# -- the robot: trajectories, override, progress, separation ---------------------------------
MAX_TRAJECTORY_POINTS = 10_000     # a goal of more points is refused (a program is a few dozen)
SEPARATION_LABELS = ('S', 'arm_x', 'arm_y', 'arm_z', 'human_x', 'human_y', 'human_z', 'S_p',
                     'speed')
PROGRESS_LABELS = ('nature', 'cycles', 'cycles_done')


def duration_to_seconds(duration: Duration) -> float:
    return duration.sec + duration.nanosec * 1e-9


def trajectory_to_msg(joint_names: Sequence[str], positions, durations,
                      stamp: Time | None = None) -> JointTrajectory:
    """A joint_trajectory_controller goal from a core `Trajectory`'s waypoints (n + 1, 6, the
    first the start) and segment durations (n,): one point per waypoint after the start, zero
    velocities, time_from_start the cumulative durations. A trajectory of no segment is one
    point at the start, time 0 (stay where the arm stands). The header stamp is left 0 (start
    at once) unless `stamp` is given."""
    msg = JointTrajectory()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.joint_names = list(joint_names)
    positions = np.asarray(positions, dtype=float)
    zeros = [0.0] * len(msg.joint_names)
    if len(durations) == 0:
        msg.points = [JointTrajectoryPoint(positions=positions[-1].tolist(), velocities=zeros,
                                           time_from_start=seconds_to_duration(0.0))]
        return msg
    times = np.cumsum(np.asarray(durations, dtype=float))
    msg.points = [JointTrajectoryPoint(positions=q.tolist(), velocities=zeros,
                                       time_from_start=seconds_to_duration(float(t)))
                  for q, t in zip(positions[1:], times)]
    return msg


def trajectory_from_msg(msg: JointTrajectory) -> tuple[tuple, np.ndarray, np.ndarray]:
    """(joint names, positions (n, joints), time_from_start (n,) s) of a JointTrajectory;
    refused unless the names are unique and non-empty, every point has one finite position per
    joint, and the times are finite, >= 0 and strictly increasing (a single point may be at
    time 0: stay). Velocities and accelerations are not read (the segments are at rest at
    every point)."""
    names = tuple(msg.joint_names)
    if not names or len(set(names)) != len(names) or not all(names):
        raise MessageError(f'JointTrajectory joint_names must be unique and non-empty, got '
                           f'{quote(list(names))}')
    if not msg.points:
        raise MessageError('JointTrajectory holds no points')
    if len(msg.points) > MAX_TRAJECTORY_POINTS:
        raise MessageError(f'JointTrajectory holds {len(msg.points)} points, more than '
                           f'{MAX_TRAJECTORY_POINTS}')
    if any(len(p.positions) != len(names) for p in msg.points):
        raise MessageError(f'JointTrajectory points must hold {len(names)} positions (one per '
                           'joint name)')
    positions = np.array([list(p.positions) for p in msg.points], dtype=float)
    times = np.array([duration_to_seconds(p.time_from_start) for p in msg.points])
    if not (np.isfinite(positions).all() and np.isfinite(times).all()):
        raise MessageError('JointTrajectory positions or times hold NaN or inf')
    if times[0] < 0 or np.any(np.diff(times) <= 0) or (len(times) > 1 and times[0] <= 0):
        raise MessageError(f'JointTrajectory time_from_start must increase strictly from > 0 '
                           f'(a single point may be at 0), got {quote(times.tolist())}')
    return names, positions, times


def speed_override_from_msg(msg: Float64) -> float:
    """The speed override, a fraction in [0, 1]."""
    value = float(msg.data)
    if not 0.0 <= value <= 1.0:        # (NaN fails too)
        raise MessageError(f'speed override must lie in [0, 1], got {value!r}')
    return value


def robot_progress_to_msg(nature: int, cycles: int, cycles_done: int) -> UInt8MultiArray:
    """hrc/robot_progress: the robot's share of the current task (cycles 0: none)."""
    return _labelled_record([min(max(int(v), 0), 255) for v in (nature, cycles, cycles_done)],
                            PROGRESS_LABELS)


def robot_progress_from_msg(msg: UInt8MultiArray) -> dict:
    return _record_from_msg(msg, PROGRESS_LABELS, 'robot progress', None)


def separation_to_msg(distance: float, arm_point, human_point, protective: float,
                      speed: float) -> Float64MultiArray:
    """hrc/separation: S, the closest points on the arm and on the person (base frame), S_p at
    the arm's speed bound, and that speed bound (m, m/s), labelled (`SEPARATION_LABELS`)."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label='separation', size=len(SEPARATION_LABELS),
                                          stride=len(SEPARATION_LABELS))]
    msg.data = [float(distance), *map(float, arm_point), *map(float, human_point),
                float(protective), float(speed)]
    return msg


def separation_from_msg(msg: Float64MultiArray) -> dict:
    values = list(msg.data)
    if len(values) != len(SEPARATION_LABELS):
        raise MessageError(f'separation must hold {len(SEPARATION_LABELS)} values '
                           f'({" ".join(SEPARATION_LABELS)}), got {len(values)}')
    if not all(math.isfinite(v) for v in values):
        raise MessageError('separation holds NaN or inf')
    return {'S': values[0], 'arm': np.array(values[1:4]), 'human': np.array(values[4:7]),
            'S_p': values[7], 'speed': values[8]}


# -- levels and epochs ------------------------------------------------------------------------
def _level_from_msg(msg, allowed: Sequence[int], what: str) -> int:
    value = int(msg.data)
    if value not in allowed:
        raise MessageError(f'{what} {value} is not one of {tuple(allowed)}')
    return value


def observation_from_msg(msg: UInt8) -> int:
    return _level_from_msg(msg, OBSERVATION_LEVELS, 'observation level')


def observation_to_msg(level: int) -> UInt8:
    return UInt8(data=int(level))


def distance_level_from_msg(msg: UInt8) -> int:
    return _level_from_msg(msg, DISTANCE_LEVELS, 'distance level')


def distance_level_to_msg(d: int) -> UInt8:
    return UInt8(data=int(d))


def epoch_from_msg(msg: UInt32) -> int:
    k = int(msg.data)
    if k < 1:
        raise MessageError(f'epoch {k}: epochs are numbered from 1')
    return k


def epoch_to_msg(k: int) -> UInt32:
    return UInt32(data=int(k))


def human_response_from_msg(msg: Bool) -> bool:
    return bool(msg.data)


def human_response_to_msg(accepted: bool) -> Bool:
    return Bool(data=bool(accepted))


# -- task state, requests, the simulator's true state -----------------------------------------
def _labelled_record(values: Sequence[int], labels: Sequence[str]) -> UInt8MultiArray:
    msg = UInt8MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=name, size=1, stride=1) for name in labels]
    msg.data = [int(v) for v in values]
    return msg


def _record_from_msg(msg: UInt8MultiArray, labels: Sequence[str], what: str,
                     tops: Sequence[int] | None) -> dict:
    values = list(msg.data)
    if len(values) != len(labels):
        raise MessageError(f'{what} must hold {len(labels)} values ({" ".join(labels)}), '
                           f'got {len(values)}')
    got = [dim.label for dim in msg.layout.dim]
    if got and got != list(labels):
        raise MessageError(f'{what} layout labels {quote(got)} are not {list(labels)}')
    if tops is not None:
        for name, value, top in zip(labels, values, tops):
            if value > top:
                raise MessageError(f'{what}: {name} = {value} is out of its domain 0..{top}')
    return {name: int(v) for name, v in zip(labels, values)}


def task_domain(rho: int, sigma: int) -> tuple:
    """Largest value of each task variable (tp tc tx ty hp hc bp bc) for a model's rho, sigma."""
    top = _NATURE_COMMITMENT_TOP
    return (rho, sigma, top, top, rho, sigma, rho, sigma)


def task_state_to_msg(state: Mapping[str, int]) -> UInt8MultiArray:
    """The eight task variables, and `queued` (the tasks waiting) as a ninth labelled value
    when `state` holds it (a task manager whose model has a queue, MODEL.md 8.1), capped at
    `MAX_QUEUED`."""
    values = [state[name] for name in TASK_VARIABLES]
    if state.get(QUEUED) is None:
        return _labelled_record(values, TASK_VARIABLES)
    return _labelled_record(values + [min(int(state[QUEUED]), MAX_QUEUED)], QUEUED_LABELS)


def task_state_from_msg(msg: UInt8MultiArray, rho: int | None = None,
                        sigma: int | None = None) -> dict:
    """The eight task variables, and `queued` when the message holds a ninth value (labelled
    `queued`, or an empty layout); with rho and sigma, each is checked against its domain."""
    tops = None if rho is None or sigma is None else task_domain(rho, sigma)
    if len(msg.data) == len(QUEUED_LABELS):
        return _record_from_msg(msg, QUEUED_LABELS, 'task state',
                                None if tops is None else tops + (MAX_QUEUED,))
    return _record_from_msg(msg, TASK_VARIABLES, 'task state (or 9 with queued)', tops)


def true_state_to_msg(state: Mapping[str, int]) -> UInt8MultiArray:
    return _labelled_record([state[name] for name in STATE_VARIABLES], STATE_VARIABLES)


def true_state_from_msg(msg: UInt8MultiArray) -> dict:
    return _record_from_msg(msg, STATE_VARIABLES, 'true state', None)


def task_request_from_msg(msg: UInt8MultiArray, rho: int | None = None,
                          sigma: int | None = None) -> tuple:
    """A task request (tp, tc, tx): priority 1..rho, duration 1..sigma, nature 0..3."""
    values = [int(v) for v in msg.data]
    if len(values) != 3:
        raise MessageError('task request must be [priority, duration, nature], got '
                           f'{quote(values)}')
    tp, tc, tx = values
    limits = (('tp (priority)', tp, rho), ('tc (duration)', tc, sigma),
              ('tx (nature)', tx, _NATURE_COMMITMENT_TOP))
    for name, value, top in limits:
        low = 0 if name.startswith('tx') else 1
        if value < low or (top is not None and value > top):
            span = f'{low}..{top}' if top is not None else f'>= {low}'
            raise MessageError(f'task request {values}: {name} must be in {span}, got {value}')
    return tp, tc, tx


def task_request_to_msg(tp: int, tc: int, tx: int) -> UInt8MultiArray:
    return _labelled_record((tp, tc, tx), ('tp', 'tc', 'tx'))


def task_request_result_to_msg(name: str, hardware_id: str, accepted: bool, reason: str,
                               task: tuple | None, request, published_ns: int,
                               sequence: int | None, queued: int) -> DiagnosticStatus:
    """The task manager's report on one `hrc/task_request` (`hrc/task_request_result`): OK and
    'accepted: ...' when queued, WARN and 'refused: <reason>' otherwise; the request's content
    (tp, tc, tx when it had three values, refused or not; the data quoted), its writer's source
    timestamp and sequence number, and the tasks waiting after it."""
    tp, tc, tx = task if task is not None else (None, None, None)
    message = (f'accepted: task ({tp}, {tc}, {tx}) queued; {queued} waiting' if accepted
               else f'refused: {reason}')
    return diagnostic_status(
        name, DiagnosticStatus.OK if accepted else DiagnosticStatus.WARN, cap(message),
        {'accepted': accepted, 'tp': tp, 'tc': tc, 'tx': tx, 'request': quote(request),
         'reason': cap(reason), 'published_ns': int(published_ns), 'sequence': sequence,
         'queued': queued}, hardware_id=hardware_id)


def task_request_result_from_msg(msg: DiagnosticStatus) -> dict:
    """``{accepted, task, reason, published_ns, sequence, queued, source}`` of a report on
    `hrc/task_request_result` (task: the request's (tp, tc, tx), None when it had not three
    values)."""
    values = diagnostic_values(msg)

    def number(key: str, required: bool = False) -> int | None:
        text = values.get(key, 'none')
        if text == 'none' and not required:
            return None
        if not text.isdigit():
            raise MessageError(f'task request result: {key} must be a whole number, got '
                               f'{quote(text)}')
        return int(text)

    accepted = values.get('accepted')
    if accepted not in ('true', 'false'):
        raise MessageError(f'task request result: accepted must be true or false, got '
                           f'{quote(accepted)}')
    task = tuple(number(key) for key in ('tp', 'tc', 'tx'))
    return {'accepted': accepted == 'true', 'task': None if None in task else task,
            'reason': values.get('reason', ''), 'published_ns': number('published_ns', True),
            'sequence': number('sequence'), 'queued': number('queued'),
            'source': msg.hardware_id}


# -- belief -----------------------------------------------------------------------------------
def belief_to_msg(belief) -> Float64MultiArray:
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=stride)
                      for label, size, stride in BELIEF_DIMS]
    msg.data = [float(p) for p in np.asarray(belief, dtype=float).reshape(-1)]
    return msg


def belief_from_msg(msg: Float64MultiArray) -> np.ndarray:
    """The belief (9,) over h = 3*em + ea; refused unless it is a probability vector."""
    values = np.asarray(msg.data, dtype=float)
    if values.shape != (N_HIDDEN,):
        raise MessageError(f'belief must hold 9 probabilities (h = 3*em + ea), got '
                           f'{values.size}')
    dims = [(d.label, d.size) for d in msg.layout.dim]
    if dims and dims != [(label, size) for label, size, _ in BELIEF_DIMS]:
        raise MessageError(f'belief layout {quote(dims)} is not motivation (3) x aggression (3)')
    if msg.layout.data_offset != 0:
        raise MessageError(f'belief layout data_offset must be 0, got {msg.layout.data_offset}')
    if not np.all(np.isfinite(values)):
        raise MessageError(f'belief holds NaN or inf: {quote(values)}')
    if np.any(values < 0.0):
        raise MessageError(f'belief holds a negative probability: {quote(values)}')
    total = float(values.sum())
    if abs(total - 1.0) > BELIEF_TOLERANCE:
        raise MessageError(f'belief sums to {total:.9g}, not 1')
    return values


# -- action -----------------------------------------------------------------------------------
def action_from_msg(msg: String) -> int:
    if msg.data not in ACTION_INDEX:
        raise MessageError(f'unknown action {quote(msg.data)}; expected one of '
                           f'{" ".join(ACTIONS)}')
    return ACTION_INDEX[msg.data]


def action_to_msg(action) -> String:
    return String(data=ACTIONS[action_index(action)])


# -- hrc/estimator_config ---------------------------------------------------------------------
def config_identity_to_msg(sha256: str, source: str) -> String:
    return String(data=f'{sha256} {source}')


def config_identity_from_msg(msg: String) -> tuple[str, str]:
    """(belief sha256, source) of the configuration the belief estimator announces."""
    sha, _, source = msg.data.partition(' ')
    if len(sha) != 64 or any(c not in '0123456789abcdef' for c in sha):
        raise MessageError(f'expected "<sha256> <configuration file>", got {msg.data[:80]!r}')
    return sha, source


# -- hrc/_clock_claim -------------------------------------------------------------------------
CLAIM_MODES = ('timer', 'topic')


def claim_to_msg(claim: Claim) -> String:
    return String(data=f'{claim.started_ns} {claim.nonce:016x} {claim.mode} {claim.node}')


def claim_from_msg(msg: String) -> Claim:
    """A decision node's claim: ``"<started_ns> <id, 16 hex digits> <timer|topic> <node>"``."""
    parts = msg.data.split(' ', 3)
    try:
        started, nonce, mode, node = parts
        claim = Claim(int(started), int(nonce, 16), node, mode)
    except ValueError:
        raise MessageError('expected a claim "<started_ns> <id> <timer|topic> <node>", got '
                           f'{quote(msg.data)}') from None
    if claim.started_ns < 0 or len(nonce) != 16 or mode not in CLAIM_MODES \
            or not node.startswith('/') or len(node) > 256:
        raise MessageError(f'not a decision node claim: {quote(msg.data)}')
    return claim


# -- hrc/_epoch_ready --------------------------------------------------------------------------
READY_WRITERS_MAX = 32      # epoch writers one mark may name (sources.PUBLISHERS_KEPT)
NODE_NAME = re.compile(r'(/[A-Za-z_][A-Za-z0-9_]*)+')    # a fully qualified ROS node name
GID_HEX = 32                # a GID as text: 16 bytes (sources.gid_text)


def epoch_ready_to_msg(mark: ReadyMark) -> String:
    return String(data=' '.join([mark.reader, *sorted(mark.writers)]))


def epoch_ready_from_msg(msg: String) -> ReadyMark:
    """A listener's ready mark: ``"<reader node> <writer GID> ..."`` (GIDs as 32 hex digits)."""
    if len(msg.data) > 256 + (GID_HEX + 1) * READY_WRITERS_MAX:
        raise MessageError(f'epoch ready mark of {len(msg.data)} characters: too long')
    reader, *writers = msg.data.split(' ')
    if len(reader) > 256 or not NODE_NAME.fullmatch(reader) or len(writers) > READY_WRITERS_MAX \
            or any(len(w) != GID_HEX or w.strip('0123456789abcdef') for w in writers):
        raise MessageError('expected an epoch ready mark "<reader node> <writer gid> ...", '
                           f'got {quote(msg.data)}')
    return ReadyMark(reader, frozenset(writers))


# -- body tracking: visualization_msgs/MarkerArray of the Azure Kinect / Orbbec drivers -------
# The drivers' colour per body id (cycled), as they draw their markers.
BODY_COLORS = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0),
               (1.0, 0.0, 1.0), (0.0, 1.0, 1.0))
BODY_MARKER_LIFETIME = 0.25    # seconds, as the Azure Kinect driver sets it
BODY_MARKER_SIZE = 0.05        # metres


def body_frame_from_msg(msg: MarkerArray, camera_frame: str) -> BodyFrame:
    """One body frame: each body's 32 joints (metres, `camera_frame`) and the stamp (s; None
    for an array without joints, which has no stamp)."""
    joints = [m for m in msg.markers if m.action == Marker.ADD]
    if not joints:
        return BodyFrame(None, {})
    if len(joints) > MAX_BODIES * len(K4ABT_JOINTS):
        raise MessageError(f'body-tracking array of {len(joints)} joint markers: more than '
                           f'{MAX_BODIES} bodies of {len(K4ABT_JOINTS)} joints')
    frames = sorted({m.header.frame_id for m in joints})
    if frames != [camera_frame]:
        raise MessageError(f'body-tracking markers are in frame(s) {frames}, expected '
                           f'{camera_frame!r} (the camera_frame that camera_translation and '
                           'camera_rotation place in the robot frame)')
    stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in joints}
    if len(stamps) != 1:
        raise MessageError(f'body-tracking markers of one array carry {len(stamps)} stamps; a '
                           'body frame has one capture stamp')
    bodies: dict[int, np.ndarray] = {}
    for m in joints:
        if m.id < 0:
            raise MessageError(f'body-tracking marker id {m.id} is negative')
        body, joint = split_marker_id(m.id)
        if joint >= len(K4ABT_JOINTS):
            raise MessageError(f'body-tracking marker id {m.id}: joint {joint} is not one of the '
                               f'{len(K4ABT_JOINTS)} joints (id = body * {MARKER_ID_STRIDE} + '
                               'joint)')
        position = bodies.setdefault(body, np.full((len(K4ABT_JOINTS), 3), np.nan))
        if not np.isnan(position[joint, 0]):
            raise MessageError(f'body-tracking marker id {m.id} (body {body}, joint '
                               f'{K4ABT_JOINTS[joint]}) appears twice')
        p = m.pose.position
        position[joint] = (p.x, p.y, p.z)
        if not np.all(np.isfinite(position[joint])):
            raise MessageError(f'body {body} joint {K4ABT_JOINTS[joint]} holds NaN or inf')
        if not np.linalg.norm(position[joint]) <= MAX_RANGE:
            raise MessageError(f'body {body} joint {K4ABT_JOINTS[joint]} is '
                               f'{np.linalg.norm(position[joint]):.3g} m from the camera, beyond '
                               f'{MAX_RANGE:g} m: positions must be in metres')
    for body, position in bodies.items():
        missing = [K4ABT_JOINTS[j] for j in np.flatnonzero(np.isnan(position[:, 0]))]
        if missing:
            raise MessageError(f'body {body} lacks joints {missing}: a body frame holds all '
                               f'{len(K4ABT_JOINTS)}')
    return BodyFrame(stamp_to_seconds(joints[0].header.stamp), bodies)


def body_frame_to_msg(bodies: Mapping[int, np.ndarray], stamp: Time,
                      camera_frame: str) -> MarkerArray:
    """A body frame as the drivers publish it: a SPHERE per joint, id = body * 100 + joint."""
    msg = MarkerArray()
    for body, joints in sorted(bodies.items()):
        r, g, b = BODY_COLORS[body % len(BODY_COLORS)]
        for joint, (x, y, z) in enumerate(np.asarray(joints, dtype=float).tolist()):
            marker = Marker(id=int(body) * MARKER_ID_STRIDE + joint, type=Marker.SPHERE,
                            action=Marker.ADD)
            marker.header.frame_id = camera_frame
            marker.header.stamp = stamp
            marker.lifetime = seconds_to_duration(BODY_MARKER_LIFETIME)
            marker.color.r, marker.color.g, marker.color.b, marker.color.a = r, g, b, 1.0
            marker.scale.x = marker.scale.y = marker.scale.z = BODY_MARKER_SIZE
            marker.pose.position.x, marker.pose.position.y, marker.pose.position.z = x, y, z
            marker.pose.orientation.w = 1.0
            msg.markers.append(marker)
    return msg


def seconds_to_duration(seconds: float) -> Duration:
    sec = math.floor(seconds)
    return Duration(sec=int(sec), nanosec=int(round((seconds - sec) * 1e9)))


# -- hrc/markers ------------------------------------------------------------------------------
MARKER_TYPES = {'disc': Marker.CYLINDER, 'sphere': Marker.SPHERE, 'spheres': Marker.SPHERE_LIST,
                'line': Marker.LINE_LIST, 'text': Marker.TEXT_VIEW_FACING}


def delete_all_markers_msg() -> MarkerArray:
    """One DELETEALL: the viewers drop every marker of the topic."""
    return MarkerArray(markers=[Marker(action=Marker.DELETEALL)])


def markers_to_msg(shapes: Iterable[Shape], frame_id: str, stamp: Time) -> MarkerArray:
    """A whole picture: DELETEALL, then one marker per shape (`core.cell.view`)."""
    msg = delete_all_markers_msg()
    for shape in shapes:
        marker = Marker(ns=shape.ns, id=int(shape.id), type=MARKER_TYPES[shape.kind],
                        action=Marker.ADD, text=shape.text)
        marker.header.frame_id = frame_id
        marker.header.stamp = stamp
        marker.pose.orientation.w = 1.0
        marker.scale.x, marker.scale.y, marker.scale.z = (float(v) for v in shape.scale)
        marker.color.r, marker.color.g, marker.color.b, marker.color.a = (
            float(v) for v in shape.color)
        points = np.asarray(shape.points, dtype=float).reshape(-1, 3)
        if shape.kind in ('spheres', 'line'):
            marker.points = [Point(x=x, y=y, z=z) for x, y, z in points.tolist()]
        else:
            marker.pose.position.x, marker.pose.position.y, marker.pose.position.z = \
                points[0].tolist()
        msg.markers.append(marker)
    return msg


# -- diagnostics ------------------------------------------------------------------------------
def _format_value(value) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, np.bool_)):
        return 'true' if value else 'false'
    if isinstance(value, (float, np.floating)):
        return f'{float(value):.6g}'
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_format_value(v) for v in value) + ']'
    if value is None:
        return 'none'
    return str(value)


def key_values(values: Mapping[str, object] | Iterable[tuple]) -> list[KeyValue]:
    items = values.items() if isinstance(values, Mapping) else values
    return [KeyValue(key=str(k), value=_format_value(v)) for k, v in items]


def diagnostic_status(name: str, level: bytes, message: str,
                      values: Mapping[str, object] | None = None,
                      hardware_id: str = '') -> DiagnosticStatus:
    if level not in LEVEL_NAMES:
        raise ValueError(f'diagnostic level must be one of DiagnosticStatus OK/WARN/ERROR/STALE, '
                         f'got {level!r}')
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=key_values(values or {}))


def diagnostic_array(statuses: Iterable[DiagnosticStatus], stamp: Time | None = None
                     ) -> DiagnosticArray:
    msg = DiagnosticArray()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.status = list(statuses)
    return msg


def diagnostic_values(status: DiagnosticStatus) -> dict:
    """The key-values of a status as a dict (for tests and tools)."""
    return {kv.key: kv.value for kv in status.values}
