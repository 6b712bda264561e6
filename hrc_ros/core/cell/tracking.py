"""Body-tracking streams -> the human's arm angles and keypoints in the robot frame.

The body-tracking ROS drivers of the Azure Kinect (`Azure_Kinect_ROS_Driver`, topic
`body_tracking_data`) and of the Orbbec Femto Bolt / Mega (the same driver on Orbbec's K4A
wrapper) publish one `visualization_msgs/MarkerArray` per body frame: one SPHERE marker per
joint of every tracked body, ``id = body_id * 100 + joint`` with ``joint`` the Azure Kinect Body
Tracking SDK's index (`K4ABT_JOINTS`, 32 joints), the position in metres in the depth camera's
frame (`depth_camera_link`), every marker of a frame with the capture stamp; a frame without
bodies is an empty array. This module is the ROS-free part of reading them (the messages are
converted in `hrc_ros.ros.conversions`; `BodyFrame` is what they become):

Frame transform. There is no tf2 in the pip wheels, so the camera's pose in the robot frame is a
static parameter (translation t, unit quaternion q = (x, y, z, w)):

    p_robot = R(q) p_camera + t                                        (`RigidTransform`)

Arm angles. The estimator's velocity level is the mean |joint velocity| in rad/s of the six arm
joints of `HUMAN_JOINTS`; a tracker gives positions, so each joint becomes the angle between two
segments, angle(a, b) = atan2(|a x b|, a . b) in [0, pi] (`arm_angles`):

    shoulder  angle(pelvis - spine_chest, elbow - shoulder)    0 = the arm hangs along the trunk
    elbow     angle(elbow - shoulder, wrist - elbow)           0 = a straight arm
    wrist     angle(wrist - elbow, hand - wrist)               0 = a straight wrist

and the velocities come from successive frames of the *same* followed body,
``v = (theta_k - theta_{k-1}) / (t_k - t_{k-1})`` with t the frames' stamps, only for
0 < t_k - t_{k-1} <= max_gap: after a gap, a change of the followed body or a relocation the
first frame gives angles only.

Keypoints (the distance). The skeleton handed to the estimator holds the keypoint joints of
*every* body in view, the followed body's first: the distance level is the closest keypoint to
the robot, and every person near the robot counts, so the choice of the followed body never
changes the distance level.

Body selection (`BodyTracking`). The followed body is the one whose angles feed the belief: by
default the one nearest to the robot (closest keypoint), kept until another is nearer by more
than `switch_margin` metres (hysteresis: two people at about the same distance do not make the
choice flicker), or a fixed body id. Between frames the followed body is found again by
position, not only by id: the same id within the motion gate, else the body within the gate of
its last centroid (two bodies that swap ids keep the right person; the velocities restart).

Bad streams. Every frame either gives the estimator a truthful input or nothing (`InputError`,
which the node turns into a dropped message with a throttled warning and a diagnostic); a frame
never yields joint states without the skeleton of the same instant:

- no body in view: nothing (the human is a missing input, so the decision node fails safe);
- a body whose centroid moved more than ``max_speed * dt + JUMP_SLACK`` since the last accepted
  frame (a jump of metres in one frame): the frame is dropped; if the bodies stay at the new
  place for `confirm_frames` frames, that is where they are (accepted, the followed body chosen
  again and the velocities restarted). Never in the unsafe direction: a jumped frame whose
  closest keypoint is nearer to the robot than the last accepted frame's still gives its
  skeleton (the distance, with a WARN), only its joint states wait for the confirmation;
- a stamp that does not increase: dropped (the velocities would divide by zero or go back);
  frames more than `max_gap` behind the last are a restarted tracker or a stepped clock (a
  looped bag) once `confirm_frames` of them come in a row, with no newer frame between (a
  second stream, such as a bag played on a live cell, never does): the adapter starts again
  from them, with a WARN;
- NaN joints, missing joints, foreign frames, joints farther than `MAX_RANGE` from the camera
  (millimetres for metres) and more than `MAX_BODIES` bodies are refused by the conversion;
  a joint farther than `observation.MAX_KEYPOINT_RANGE` from the robot frame's origin once
  transformed (a camera pose off the cell) is refused here: beyond range is malformed, never
  "far".

One tracker per cell (`BodyTracking.frame` with the message's `Stamp` and the node's clock).
The adapter locks onto one publisher of the stream (`core.protocol.StreamLock`: its writer's
sequence numbers, as the epoch followers do) and only that stream's frames make joint states
and move the stamp, jump and selection rules: a second stream (a second tracker, a bag played
on a live cell) stamped seconds ahead can no longer make the live frames "go back" and be
dropped. Its frames are reported (the node names the publishers on /diagnostics), and they
still count for the distance, on the safe side: when two streams disagree about where a
person is, the nearer wins. Every frame that is not taken for timing or stream reasons (a
second stream's, a stamp that does not increase) is kept for `max_gap` seconds of the node's
clock as a reading; a reading nearer to the robot than the skeleton published is published
at once (its skeleton, no joint states, a WARN), and every skeleton published while it is
recent carries its keypoints too, so the estimator's latest skeleton always holds the nearest
person any stream saw.

The synthetic tracker (`SyntheticBody`) is the inverse, for simulation and tests: it turns a
stream of joint speeds and distance levels (the simulated cell's `human/joint_states` and
`human/skeleton`) into the joints of one body whose arm angles move at exactly those speeds and
whose closest keypoint stays inside the distance level's band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from collections import deque

from ..decision.observation import (HUMAN_JOINTS, MAX_KEYPOINT_RANGE, check_keypoint_range,
                                    distance_band)
from ..protocol import WARN, InputError, Report, Stamp, StreamLock

# The Azure Kinect Body Tracking SDK's joints (k4abt_joint_id_t), in index order.
K4ABT_JOINTS = (
    'pelvis', 'spine_navel', 'spine_chest', 'neck',
    'clavicle_left', 'shoulder_left', 'elbow_left', 'wrist_left', 'hand_left', 'handtip_left',
    'thumb_left',
    'clavicle_right', 'shoulder_right', 'elbow_right', 'wrist_right', 'hand_right',
    'handtip_right', 'thumb_right',
    'hip_left', 'knee_left', 'ankle_left', 'foot_left',
    'hip_right', 'knee_right', 'ankle_right', 'foot_right',
    'head', 'nose', 'eye_left', 'ear_left', 'eye_right', 'ear_right')
JOINT_INDEX = {name: i for i, name in enumerate(K4ABT_JOINTS)}
MARKER_ID_STRIDE = 100      # marker id = body id * 100 + joint index
# Each arm angle of HUMAN_JOINTS as (joint, segment a, segment b), a segment a (from, to) pair.
ARM_ANGLES = (
    ('l_shoulder', ('spine_chest', 'pelvis'), ('shoulder_left', 'elbow_left')),
    ('r_shoulder', ('spine_chest', 'pelvis'), ('shoulder_right', 'elbow_right')),
    ('l_elbow', ('shoulder_left', 'elbow_left'), ('elbow_left', 'wrist_left')),
    ('r_elbow', ('shoulder_right', 'elbow_right'), ('elbow_right', 'wrist_right')),
    ('l_wrist', ('elbow_left', 'wrist_left'), ('wrist_left', 'hand_left')),
    ('r_wrist', ('elbow_right', 'wrist_right'), ('wrist_right', 'hand_right')),
)
assert tuple(name for name, _, _ in ARM_ANGLES) == HUMAN_JOINTS
_SEGMENTS = np.array([[JOINT_INDEX[j] for j in a + b] for _, a, b in ARM_ANGLES])
MIN_SEGMENT = 1e-3          # metres: a shorter segment has no direction
JUMP_SLACK = 0.15           # metres a centroid may move on top of max_speed * dt (tracker noise)
QUATERNION_TOLERANCE = 1e-3  # |norm - 1| accepted (and normalised) in a rotation parameter
MAX_RANGE = 10.0            # metres from the camera: farther is no depth camera's (millimetres?)
MAX_BODIES = 16             # bodies in one frame (the Azure Kinect SDK tracks a handful)
READINGS_KEPT = 64          # readings of frames not taken, kept for the nearer rule

# Defaults of the body_tracking node (docs/DESIGN.md).
DEFAULT_SWITCH_MARGIN = 0.3
DEFAULT_MAX_SPEED = 3.0
DEFAULT_MAX_GAP = 0.5
DEFAULT_CONFIRM_FRAMES = 3


def split_marker_id(marker_id: int) -> tuple[int, int]:
    """(body id, joint index) of a body-tracking marker id."""
    return divmod(int(marker_id), MARKER_ID_STRIDE)


def joint_indices(names: Sequence[str]) -> np.ndarray:
    """Indices of K4ABT joint names; ValueError names the unknown ones."""
    names = list(names)
    unknown = [n for n in names if n not in JOINT_INDEX]
    if unknown or not names:
        raise ValueError(f'unknown body-tracking joints {unknown}; known: '
                         f'{", ".join(K4ABT_JOINTS)}' if unknown else 'no joints given')
    if len(set(names)) != len(names):
        raise ValueError(f'joints repeat: {names}')
    return np.array([JOINT_INDEX[n] for n in names])


# -- the camera's pose in the robot frame -----------------------------------------------------
@dataclass(frozen=True)
class RigidTransform:
    """p_out = R(rotation) p_in + translation; rotation a unit quaternion (x, y, z, w)."""

    translation: np.ndarray
    rotation: np.ndarray

    @classmethod
    def from_parameters(cls, translation, rotation) -> 'RigidTransform':
        t = np.asarray(translation, dtype=float)
        q = np.asarray(rotation, dtype=float)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f'translation must be 3 finite numbers (x, y, z), got {t.tolist()}')
        if not float(np.abs(t).max()) <= MAX_KEYPOINT_RANGE:
            raise ValueError(f'translation {t.tolist()} puts the camera farther than '
                             f'{MAX_KEYPOINT_RANGE:g} m from the robot frame: metres expected')
        if q.shape != (4,) or not np.all(np.isfinite(q)):
            raise ValueError(f'rotation must be 4 finite numbers (x, y, z, w), got {q.tolist()}')
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise ValueError(f'rotation must be a unit quaternion (x, y, z, w), got {q.tolist()} '
                             f'of norm {norm:.6g}')
        return cls(t, q / norm)

    @property
    def matrix(self) -> np.ndarray:
        x, y, z, w = self.rotation
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

    def apply(self, points) -> np.ndarray:
        return np.asarray(points, dtype=float) @ self.matrix.T + self.translation

    def inverse(self) -> 'RigidTransform':
        x, y, z, w = self.rotation
        conjugate = np.array([-x, -y, -z, w])
        return RigidTransform(-(self.matrix.T @ self.translation), conjugate)


IDENTITY = RigidTransform(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))


# -- angles -----------------------------------------------------------------------------------
def arm_angles(joints) -> np.ndarray:
    """The six arm angles (rad, `HUMAN_JOINTS` order) of one body's joints (32, 3)."""
    j = np.asarray(joints, dtype=float)
    if j.shape != (len(K4ABT_JOINTS), 3):
        raise ValueError(f'joints must have shape (32, 3), got {j.shape}')
    a = j[_SEGMENTS[:, 1]] - j[_SEGMENTS[:, 0]]
    b = j[_SEGMENTS[:, 3]] - j[_SEGMENTS[:, 2]]
    short = (np.linalg.norm(a, axis=1) < MIN_SEGMENT) | (np.linalg.norm(b, axis=1) < MIN_SEGMENT)
    if np.any(short):
        names = [HUMAN_JOINTS[i] for i in np.flatnonzero(short)]
        raise ValueError(f'a segment of {names} is shorter than {MIN_SEGMENT * 1e3:.0f} mm: '
                         'no angle')
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


# -- the tracker ------------------------------------------------------------------------------
@dataclass(frozen=True)
class BodyFrame:
    """One body frame: its stamp (s; None for a frame without bodies) and each body's 32
    joints (metres, camera frame)."""

    stamp: float | None
    bodies: Mapping[int, np.ndarray]


@dataclass
class TrackingStep:
    """What one accepted frame gives the estimator.

    `keypoints` (n, 3), robot frame: every body's keypoint joints, the followed body's first.
    `angles` / `velocities` (6,) of the followed body (`HUMAN_JOINTS`), None when no body is
    followed / on its first frame. `bodies` maps each body id to its closest keypoint distance."""

    stamp: float
    keypoints: np.ndarray
    followed: int | None
    angles: np.ndarray | None
    velocities: np.ndarray | None
    bodies: dict = field(default_factory=dict)
    reports: list[Report] = field(default_factory=list)


class BodyTracking:
    """The body-tracking adapter's machine: body frames in, the estimator's inputs out.

    `follow_body` -1 follows the body nearest to the robot (with `switch_margin` hysteresis), a
    body id >= 0 that body only. See the module docstring for the rules."""

    def __init__(self, transform: RigidTransform = IDENTITY, reference_point=(0.0, 0.0, 0.0),
                 keypoint_joints: Sequence[str] = K4ABT_JOINTS, follow_body: int = -1,
                 switch_margin: float = DEFAULT_SWITCH_MARGIN,
                 max_speed: float = DEFAULT_MAX_SPEED, max_gap: float = DEFAULT_MAX_GAP,
                 confirm_frames: int = DEFAULT_CONFIRM_FRAMES):
        self.transform = transform
        self.reference_point = np.asarray(reference_point, dtype=float)
        self.keypoints = joint_indices(keypoint_joints)
        self.follow_body = int(follow_body)
        self.switch_margin = float(switch_margin)
        self.max_speed = float(max_speed)
        self.max_gap = float(max_gap)
        self.confirm_frames = int(confirm_frames)
        self.lock = StreamLock()
        self.followed: int | None = None
        self.last_stamp: float | None = None              # of any frame taken
        self._accepted: tuple[float, dict] | None = None  # stamp, body id -> centroid
        self._nearest: float | None = None    # closest keypoint distance of the last accepted
        self._back: tuple[float, int] | None = None   # frames far back in a row: (stamp, count)
        self._candidate: tuple[float, dict, int] | None = None  # a relocation being confirmed
        self._followed_at: tuple[float, int, np.ndarray, np.ndarray] | None = None
        #                  stamp, body, centroid, angles of the followed body's last frame
        self._readings: deque = deque(maxlen=READINGS_KEPT)  # (now, keypoints, nearest)
        self._published: tuple[float, np.ndarray, float] | None = None  # now, keypoints, nearest

    def gate(self, dt: float) -> float:
        """Metres a centroid may move in dt seconds."""
        return self.max_speed * dt + JUMP_SLACK

    def _restart(self) -> None:
        """Forget the followed body: it is chosen again, its velocities start again."""
        self.followed = None
        self._followed_at = None

    def frame(self, frame: BodyFrame, source: Stamp | None = None,
              now: float | None = None) -> TrackingStep:
        """Take one frame: its step, or `InputError` when it gives the estimator nothing.

        `source` is the message's writer stamp (its sequence number tells the streams apart,
        `StreamLock`) and `now` the node's clock in seconds (the readings' age; the frame's
        stamp when not given). Without `source` every frame is taken as one stream's."""
        now = float(frame.stamp or 0.0) if now is None else float(now)
        stream = self.lock.classify(None if source is None else source.sequence, now,
                                    self.max_gap)
        if stream == StreamLock.OTHER:
            return self._other_stream(frame, now)
        restarted = self._new_stream(frame) if stream == StreamLock.NEW else []
        if not frame.bodies:
            return self._nobody(frame, now)
        stamp = float(frame.stamp)
        joints, keypoints, distances = self._place(frame)
        nearest = min(distances.values())
        taken = self._check_stamp(stamp, keypoints, nearest, now)
        if isinstance(taken, TrackingStep):
            return taken
        reports = restarted + taken
        centroids = {b: k.mean(axis=0) for b, k in keypoints.items()}
        try:
            reports += self._check_continuity(stamp, centroids)
        except InputError as exc:
            if self._nearest is None or not nearest < self._nearest:
                raise
            # never drop in the unsafe direction: the distance stands, joint states wait
            return self._publish(TrackingStep(
                stamp, np.vstack(list(keypoints.values())), None, None, None, distances,
                reports + [Report(WARN, 'tracking', f'{exc}; its skeleton is kept: it is '
                                  f'nearer to the robot ({nearest:.2f} m) than the last '
                                  f'accepted ({self._nearest:.2f} m)', {'nearest_m': nearest},
                                  kind='jump_nearer')]), nearest, now)
        self._nearest = nearest
        reports += self._select(stamp, centroids, distances)
        angles, velocities = self._arm(joints, centroids, stamp)
        order = ([self.followed] if self.followed is not None else []) \
            + [b for b in keypoints if b != self.followed]
        return self._publish(TrackingStep(stamp, np.vstack([keypoints[b] for b in order]),
                                          self.followed, angles, velocities, distances,
                                          reports), nearest, now)

    def _new_stream(self, frame: BodyFrame) -> list[Report]:
        """The stream followed fell silent and another writer's frame came: start again."""
        if self.last_stamp is None:
            return []
        self._accepted = self._candidate = self._nearest = self.last_stamp = None
        self._back = None
        self._restart()
        return [Report(WARN, 'tracking', 'following a new body-tracking stream (the one '
                       f'followed was silent for more than {self.max_gap:g} s)',
                       {'stamp': frame.stamp if frame.stamp is not None else 'none'},
                       kind='new_stream')]

    def _nobody(self, frame: BodyFrame, now: float) -> TrackingStep:
        """A frame without bodies: nothing, unless a recent reading shows someone."""
        lost = self.followed is not None
        if self._accepted is not None:
            self._accept(self._accepted[0], {})    # whoever comes next comes into view
        self._nearest = None
        self._restart()
        nearer = self._nearer_step(frame.stamp, None, now, 'the stream followed sees no body')
        if nearer is not None:
            return nearer
        raise InputError('no body in view' + (' (the followed body left)' if lost else ''))

    def _check_stamp(self, stamp: float, keypoints: dict, nearest: float,
                     now: float) -> list[Report] | TrackingStep:
        """The stamp rules (module docstring): the reports of a frame taken, or the step of a
        frame not taken (`_not_taken`: a nearer skeleton, else `InputError`)."""
        reports = []
        if self.last_stamp is not None and not stamp > self.last_stamp:
            message = (f'body frame stamp {stamp:.9f} s is not after the previous one '
                       f'({self.last_stamp:.9f} s)')
            if self.last_stamp - stamp <= self.max_gap:
                return self._not_taken(message, keypoints, nearest, stamp, now)
            # far back: a restarted tracker, a stepped clock, a looped bag; or a second stream
            # (a bag played on a live cell) whose frames must not pass between the live ones.
            # Taken once it alone has gone on for confirm_frames frames.
            back = self._back
            count = back[1] + 1 if back is not None and stamp > back[0] else 1
            if count < self.confirm_frames:
                self._back = (stamp, count)
                return self._not_taken(
                    f'{message}: {self.last_stamp - stamp:.3f} s back, taken as a restarted '
                    f'stream once it holds for {self.confirm_frames} frames', keypoints,
                    nearest, stamp, now)
            reports = [Report(WARN, 'tracking', f'body frame stamps went back '
                              f'{self.last_stamp - stamp:.3f} s for {count} frames (a '
                              'restarted tracker, a stepped clock, a looped bag): starting '
                              'again from them', {'stamp': stamp,
                                                  'previous_stamp': self.last_stamp},
                              kind='stamp_back')]
            self._accepted = self._candidate = self._nearest = None
            self._restart()
        self._back = None
        self.last_stamp = stamp
        return reports

    def _arm(self, joints: dict, centroids: dict, stamp: float) -> tuple:
        """The followed body's arm angles and, after its previous frame, their velocities."""
        if self.followed is None:
            self._followed_at = None
            return None, None
        try:
            angles = arm_angles(joints[self.followed])
        except ValueError as exc:
            raise InputError(f'body {self.followed}: {exc}') from None
        velocities = None
        last = self._followed_at
        if last is not None and last[1] == self.followed and stamp - last[0] <= self.max_gap \
                and _dist(centroids[self.followed], last[2]) <= self.gate(stamp - last[0]):
            velocities = (angles - last[3]) / (stamp - last[0])
        self._followed_at = (stamp, self.followed, centroids[self.followed], angles)
        return angles, velocities

    def _place(self, frame: BodyFrame) -> tuple[dict, dict, dict]:
        """Each body's joints and keypoints in the robot frame, and its closest keypoint
        distance; `InputError` for a joint beyond the cell's range."""
        joints = {b: self.transform.apply(j) for b, j in sorted(frame.bodies.items())}
        try:
            for b, j in joints.items():
                check_keypoint_range(j, f'body {b} in the robot frame')
        except ValueError as exc:
            raise InputError(str(exc)) from None
        keypoints = {b: j[self.keypoints] for b, j in joints.items()}
        distances = {b: float(np.min(np.linalg.norm(k - self.reference_point, axis=1)))
                     for b, k in keypoints.items()}
        return joints, keypoints, distances

    # -- the nearer rule -------------------------------------------------------------------
    def _recent(self, now: float) -> list[tuple[float, np.ndarray, float]]:
        while self._readings and now - self._readings[0][0] > self.max_gap:
            self._readings.popleft()
        return [r for r in self._readings if now - r[0] <= self.max_gap]

    def _publish(self, step: TrackingStep, nearest: float, now: float) -> TrackingStep:
        """The step with the recent readings nearer than its own nearest keypoint added (the
        nearer is the safe side); noted as what the estimator holds."""
        nearer = [r[1] for r in self._recent(now) if r[2] < nearest]
        if nearer:
            step.keypoints = np.vstack([step.keypoints, *nearer])
            nearest = min(r[2] for r in self._recent(now) if r[2] < nearest)
        self._published = (now, step.keypoints, nearest)
        return step

    def _nearer_step(self, stamp: float | None, reading, now: float,
                     why: str) -> TrackingStep | None:
        """A skeleton-only step when a recent reading is nearer than the skeleton published
        within `max_gap` (or none was), else None."""
        if reading is not None:
            self._readings.append(reading)
        recent = self._recent(now)
        if not recent:
            return None
        published = self._published
        if published is not None and now - published[0] > self.max_gap:
            published = None
        nearest = min(r[2] for r in recent)
        if published is not None and not nearest < published[2]:
            return None
        base = [] if published is None else [published[1]]
        keypoints = np.vstack(base + [r[1] for r in recent
                                      if published is None or r[2] < published[2]])
        step = TrackingStep(stamp if stamp is not None else (self.last_stamp or 0.0), keypoints,
                            None, None, None, {}, [Report(
                                WARN, 'tracking', f'{why}; a frame not taken shows a person '
                                f'nearer to the robot ({nearest:.2f} m): its skeleton is '
                                'published (the nearer is the safe side), no joint states',
                                {'nearest_m': nearest}, kind='nearer_reading')])
        self._published = (now, keypoints, nearest)
        return step

    def _not_taken(self, message: str, keypoints: dict, nearest: float, stamp: float,
                   now: float) -> TrackingStep:
        """A frame of the followed stream refused for its stamp: its skeleton if it is nearer
        than the one published, else `InputError`."""
        step = self._nearer_step(stamp, (now, np.vstack(list(keypoints.values())), nearest),
                                 now, message)
        if step is None:
            raise InputError(message)
        return step

    def _other_stream(self, frame: BodyFrame, now: float) -> TrackingStep:
        """A frame of another writer: never followed; its skeleton counts when it is nearer."""
        why = ('a frame of a second body-tracking stream (one tracker per cell: the adapter '
               'follows one publisher)')
        reading = None
        if frame.bodies:
            _, keypoints, distances = self._place(frame)
            reading = (now, np.vstack(list(keypoints.values())), min(distances.values()))
        step = self._nearer_step(frame.stamp, reading, now, why)
        if step is None:
            raise InputError(f'{why}: not followed, and no nearer to the robot than the stream '
                             'followed')
        return step

    def _check_continuity(self, stamp: float, centroids: dict) -> list[Report]:
        """Accept the frame's positions, or raise `InputError` for a jump (module docstring)."""
        accepted = self._accepted
        if accepted is None or stamp - accepted[0] > self.max_gap:
            self._restart()
            self._accept(stamp, centroids)
            return []
        jumped = _jump(centroids, accepted[1], self.gate(stamp - accepted[0]))
        if jumped is None:
            self._accept(stamp, centroids)
            return []
        count = 1
        candidate = self._candidate
        if candidate is not None and stamp - candidate[0] <= self.max_gap and _jump(
                centroids, candidate[1], self.gate(stamp - candidate[0]), arrivals=False) is None:
            count = candidate[2] + 1
        body, moved = jumped
        if count >= self.confirm_frames:
            self._restart()
            self._accept(stamp, centroids)
            return [Report(WARN, 'tracking', f'body {body} is {moved:.2f} m from where the bodies '
                           f'were {stamp - accepted[0]:.3f} s ago, for {count} frames: taken as '
                           'its new place; the followed body is chosen again',
                           {'body': body, 'moved_m': moved}, kind='relocated')]
        self._candidate = (stamp, centroids, count)
        raise InputError(f'body {body} moved {moved:.2f} m in {stamp - accepted[0]:.3f} s, more '
                         f'than max_speed {self.max_speed:g} m/s allows: a tracking jump, frame '
                         f'dropped (taken once it holds for {self.confirm_frames} frames)')

    def _accept(self, stamp: float, centroids: dict) -> None:
        self._accepted = (stamp, centroids)
        self._candidate = None

    def _select(self, stamp: float, centroids: dict, distances: dict) -> list[Report]:
        """Find the followed body again, apply the selection rule; a report when it changes."""
        before = self.followed
        same = None      # the body followed before, found again by position (any id)
        last = self._followed_at
        if before is not None and last is not None:
            gate = self.gate(stamp - last[0])
            near = sorted((_dist(c, last[2]), b != before, b) for b, c in centroids.items()
                          if _dist(c, last[2]) <= gate)
            same = near[0][2] if near else None
        if self.follow_body >= 0:
            chosen = self.follow_body if self.follow_body in centroids else None
        else:
            nearest = min(distances, key=lambda b: (distances[b], b))
            keep = same is not None and distances[nearest] >= distances[same] - self.switch_margin
            chosen = same if keep else nearest
        self.followed = chosen
        if chosen == before:
            return []
        if chosen is None:
            return [Report(WARN, 'tracking', f'body {self.follow_body} is not in view: no joint '
                           'states (every body in view still gives the distance)',
                           {'followed': 'none'}, kind='follow')]
        if self.follow_body >= 0:
            why = 'the follow_body parameter'
        elif chosen == same:
            why = f'the body followed as {before}, under a new id'
        else:
            why = 'the nearest body' + (f', nearer than body {same} by more than '
                                        f'{self.switch_margin:g} m' if same is not None else '')
        return [Report('OK', 'tracking', f'following body {chosen}: {why}',
                       {'followed': chosen, 'previous': 'none' if before is None else before},
                       log=False, kind='follow')]


def _dist(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)))


def _jump(centroids: dict, before: dict, gate: float, arrivals: bool = True):
    """(body, metres) of the first body farther than `gate` from every centroid of `before`,
    or None. With `arrivals`, a body whose id `before` does not hold has just come into view
    and is not a jump."""
    for body, c in centroids.items():
        if arrivals and body not in before:
            continue
        moved = min((_dist(c, b) for b in before.values()), default=math.inf)
        if moved > gate:
            return body, moved
    return None


# -- the synthetic tracker --------------------------------------------------------------------
# A standing body in its own frame (x forward, y left, z up, metres, the pelvis at the origin):
# the joints that do not move. The arms are set from the angles (`SyntheticBody.local_joints`).
_BODY = {
    'pelvis': (0.0, 0.0, 0.0), 'spine_navel': (0.0, 0.0, 0.2), 'spine_chest': (0.0, 0.0, 0.4),
    'neck': (0.0, 0.0, 0.55), 'head': (0.0, 0.0, 0.68), 'nose': (0.1, 0.0, 0.66),
    'eye_left': (0.08, 0.035, 0.7), 'eye_right': (0.08, -0.035, 0.7),
    'ear_left': (0.0, 0.075, 0.68), 'ear_right': (0.0, -0.075, 0.68),
    'clavicle_left': (0.0, 0.06, 0.48), 'clavicle_right': (0.0, -0.06, 0.48),
    'hip_left': (0.0, 0.1, -0.02), 'knee_left': (0.0, 0.1, -0.45),
    'ankle_left': (0.0, 0.1, -0.85), 'foot_left': (0.08, 0.1, -0.9),
    'hip_right': (0.0, -0.1, -0.02), 'knee_right': (0.0, -0.1, -0.45),
    'ankle_right': (0.0, -0.1, -0.85), 'foot_right': (0.08, -0.1, -0.9),
}
_SHOULDER = {'left': (0.0, 0.18, 0.5), 'right': (0.0, -0.18, 0.5)}
_ARM = (0.3, 0.26, 0.08, 0.06)  # upper arm, forearm, hand, hand tip (metres)
FRONT_JOINT = 'nose'           # the frontmost joint: nothing of the body is nearer the robot
ANGLE_RANGE = (0.35, 2.8)      # rad: the synthetic angles stay inside (no fold at 0 or pi)
INITIAL_ANGLES = (0.6, 0.6, 1.2, 1.2, 0.7, 0.7)
DEFAULT_WALK_SPEED = 3.0       # m/s toward a new distance band


class SyntheticBody:
    """One body for a synthetic body-tracking stream (module docstring).

    The arms move in the frontal plane (x = 0 of the body), behind the nose, so the nose is the
    frontmost joint whatever the angles: the body stands on the ray from the reference point
    along `direction`, facing it, with the nose at distance rho, hence rho is exactly the
    closest keypoint distance. Each step turns every arm angle by |v| dt (v the given joint
    speeds), reversing a joint's direction rather than leaving `ANGLE_RANGE`, so the angles'
    speeds are exactly |v|; rho walks (at most `walk_speed`) into the band of the given distance
    level and stays while it is inside."""

    def __init__(self, reference_point=(0.0, 0.0, 0.0), radii=(0.2, 0.6, 1.2),
                 direction=(1.0, 0.0, 0.0), walk_speed: float = DEFAULT_WALK_SPEED):
        self.reference_point = np.asarray(reference_point, dtype=float)
        self.radii = tuple(radii)
        u = np.asarray(direction, dtype=float)
        u = np.array([u[0], u[1], 0.0])
        if not np.linalg.norm(u) > 0:
            raise ValueError(f'direction must have a horizontal part, got {direction}')
        self.direction = u / np.linalg.norm(u)
        up = np.array([0.0, 0.0, 1.0])
        forward = -self.direction
        self.rotation = np.column_stack([forward, np.cross(up, forward), up])
        self.walk_speed = float(walk_speed)
        self.angles = np.array(INITIAL_ANGLES, dtype=float)
        self.turning = np.ones(len(HUMAN_JOINTS))
        self.rho: float | None = None
        self.stamp: float | None = None

    def step(self, speeds, level: int, stamp: float) -> np.ndarray:
        """The body's 32 joints (robot frame) at `stamp`, after moving since the last step."""
        speeds = np.abs(np.asarray(speeds, dtype=float))
        lo, hi = distance_band(level, self.radii)
        dt = 0.0 if self.stamp is None else float(stamp) - self.stamp
        if self.stamp is not None and not dt > 0.0:
            raise ValueError(f'stamp {stamp} is not after the previous one {self.stamp}')
        self.stamp = float(stamp)
        turn = speeds * dt
        ahead = self.angles + self.turning * turn
        outside = (ahead < ANGLE_RANGE[0]) | (ahead > ANGLE_RANGE[1])
        self.turning[outside] *= -1.0
        # a turn longer than the range (a long gap) still ends inside it: fold (a triangle wave)
        low, span = ANGLE_RANGE[0], ANGLE_RANGE[1] - ANGLE_RANGE[0]
        folded = np.mod(self.angles + self.turning * turn - low, 2.0 * span)
        back = folded > span
        self.angles = low + np.where(back, 2.0 * span - folded, folded)
        self.turning[back] *= -1.0
        if self.rho is None:
            self.rho = 0.5 * (lo + hi)
        elif not lo <= self.rho <= hi:
            target = lo if self.rho < lo else hi
            stride = self.walk_speed * dt
            self.rho = target if abs(target - self.rho) <= stride \
                else self.rho + math.copysign(stride, target - self.rho)
        return self.place(self.local_joints(self.angles), self.rho)

    @staticmethod
    def local_joints(angles) -> np.ndarray:
        """The 32 joints in the body frame with the arms at `angles` (HUMAN_JOINTS order)."""
        joints = np.zeros((len(K4ABT_JOINTS), 3))
        for name, p in _BODY.items():
            joints[JOINT_INDEX[name]] = p
        shoulder_a, elbow_a, wrist_a = {}, {}, {}
        for (name, _, _), angle in zip(ARM_ANGLES, angles):
            side = 'left' if name.startswith('l_') else 'right'
            {'shoulder': shoulder_a, 'elbow': elbow_a, 'wrist': wrist_a}[name[2:]][side] = angle
        for side, sign in (('left', 1.0), ('right', -1.0)):
            # Directions in the frontal (y, z) plane, turning away from the body's midline.
            heading = 0.0
            points = [np.array(_SHOULDER[side])]
            for angle, length in zip((shoulder_a[side], elbow_a[side], wrist_a[side], 0.0),
                                     _ARM):
                heading += angle
                points.append(points[-1] + length * np.array(
                    [0.0, sign * math.sin(heading), -math.cos(heading)]))
            shoulder, elbow, wrist, hand, handtip = points
            for joint, p in (('shoulder', shoulder), ('elbow', elbow), ('wrist', wrist),
                             ('hand', hand), ('handtip', handtip)):
                joints[JOINT_INDEX[f'{joint}_{side}']] = p
            joints[JOINT_INDEX[f'thumb_{side}']] = hand + np.array([0.0, 0.0, 0.03])
        return joints

    def place(self, local, rho: float) -> np.ndarray:
        """Body-frame joints -> robot frame, the front joint at distance rho along the ray."""
        rotated = np.asarray(local) @ self.rotation.T
        offset = self.reference_point + rho * self.direction - rotated[JOINT_INDEX[FRONT_JOINT]]
        return rotated + offset
