"""The cobot arm: a UR5e of capsules in MuJoCo, its distance to a person, and joint motion.

**Kinematics.** Universal Robots' published DH parameters of the UR5e (standard DH,
T_i = Rot_z(theta_i) Trans_z(d_i) Trans_x(a_i) Rot_x(alpha_i), metres and radians):

| joint | d | a | alpha |
|---|---|---|---|
| 1 shoulder_pan | 0.1625 | 0 | pi/2 |
| 2 shoulder_lift | 0 | -0.425 | 0 |
| 3 elbow | 0 | -0.3922 | 0 |
| 4 wrist_1 | 0.1333 | 0 | pi/2 |
| 5 wrist_2 | 0.0997 | 0 | -pi/2 |
| 6 wrist_3 | 0.0996 | 0 | 0 |

`ur5e_mjcf` writes them as an MJCF model (no meshes, nothing downloaded): body i+1 sits at
(a_i, 0, d_i) with the orientation Rot_x(alpha_i) in body i, whose hinge turns about its own z
(DH frame i-1's z). The flange is the site `flange` at DH frame 6. MuJoCo gives the forward
kinematics (`Arm.forward`); test_robot.py checks them against a plain numpy DH chain.

**Geometry.** Capsules cover the links (radii 0.045-0.075 m): the base column, the shoulder,
the upper arm and forearm tubes at UR's lateral offsets (shoulder offset 0.138 m, elbow offset
0.131 m, from UR's visual parameters of the ROS description; the DH chain itself runs through
the joint axes), the elbow and the three wrist housings, and a tool stub of 0.06 m on the
flange. A person is capsules too (`BodyCapsules`): bones between the 32 Azure Kinect Body
Tracking joints (`body_capsules`, torso 0.15 m, limbs 0.045-0.08 m), or a sphere around each
keypoint of an unlabelled skeleton (the suite's `human/skeleton`).

**Separation** (`separation`). The distance of two capsules is the distance of their axis
segments less both radii; the closest points of two segments come from the clamped closed form
(Ericson, Real-Time Collision Detection, 5.1.9), here over every arm x body pair at once in
numpy. S is the minimum over the pairs (negative: the capsules overlap), with both closest
points on the capsules' surfaces. test_robot.py checks it against MuJoCo's own
`mj_geomDistance` on the same capsules.

**Link speed** (`Arm.link_speed`, the v_r that SSM bounds). A point p of body b moves at
v(p) = sum_{j <= b} qd_j z_j x (p - o_j) (z_j, o_j joint j's axis and anchor from MuJoCo).
Velocity is affine along a rigid segment, so over a capsule's axis the fastest point is an
end; its surface adds |omega_b| r. The link speed is the maximum over the capsules.

**Motion.** `Trajectory`: joint waypoints with segment durations, each segment the cubic
q(u) = q0 + (q1 - q0)(3u^2 - 2u^3), u = t / T, at rest at both ends (a cubic Hermite segment
with zero end velocities, which is what a joint_trajectory_controller interpolates from points
with zero velocities). Peak joint speed 1.5 |dq| / T, peak acceleration 6 |dq| / T^2, so
`segment_duration` is the shortest T within the joint limits. `TrajectoryFollower` is a scaled
joint trajectory controller: the trajectory's clock advances at the override s (dtau = s dt),
and s follows the commanded override with |ds/dt| <= a / v_nominal (v_nominal the
trajectory's top link speed at s = 1), so the speed bound s v_nominal of its links changes at
no more than the stopping deceleration a of SSM. Joint accelerations stay within the limits as
long as the segments' own do at s = 1 and s changes at that rate.

**No rendering.** Nothing here draws, so MuJoCo is imported with `MUJOCO_GL=disable` unless the
environment names a backend (`import_mujoco`). With the default backend `import mujoco` imports
pyglfw, which starts a second Python interpreter (`sys.executable -c ...`) to read the GLFW
library's version: 40 ms and more of every node that builds an Arm, and a child in the node's
process group, so a Ctrl-C (or a launcher's SIGINT to the group) during that child's start-up
printed "Fatal Python error: init_import_site ... KeyboardInterrupt" into the node's log although
the node itself stopped cleanly (bench/README.md, "Stopping").
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass

import numpy as np


_KERNELS = None


def _kernels():
    """The numba kernels, imported at their first use: numba's import is 0.2 s of CPU in the
    start of every node that imports this module, and the nodes of a cell without the arm
    never call them. Kept once imported (the batch cell calls them every control step)."""
    global _KERNELS
    if _KERNELS is None:
        from . import _kernels as kernels
        _KERNELS = kernels
    return _KERNELS


JOINT_NAMES = ('shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
               'wrist_2_joint', 'wrist_3_joint')
N_JOINTS = len(JOINT_NAMES)


@dataclass(frozen=True)
class DhParameters:
    """Standard DH parameters of a 6-axis arm (metres, radians)."""

    d: tuple
    a: tuple
    alpha: tuple


UR5E_DH = DhParameters(d=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
                       a=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
                       alpha=(math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0))
SHOULDER_OFFSET = 0.138    # m, the upper arm's tube from the base axis along the shoulder axis
ELBOW_OFFSET = 0.131       # m, the forearm's tube steps back by this at the elbow
TOOL_LENGTH = 0.06         # m, a stub on the flange

# Capsules of the UR5e: (name, body 1..6, from (3,), to (3,), radius), in the body's frame
# (DH frame i-1 turned by joint i). The numbers come from the DH table and the offsets above.
_F = SHOULDER_OFFSET - ELBOW_OFFSET
UR5E_CAPSULES = (
    ('base', 1, (0, 0, 0), (0, 0, UR5E_DH.d[0]), 0.075),
    ('shoulder', 2, (0, 0, -0.03), (0, 0, SHOULDER_OFFSET), 0.075),
    ('upper_arm', 2, (0, 0, SHOULDER_OFFSET), (UR5E_DH.a[1], 0, SHOULDER_OFFSET), 0.06),
    ('elbow', 3, (0, 0, _F), (0, 0, SHOULDER_OFFSET), 0.06),
    ('forearm', 3, (0, 0, _F), (UR5E_DH.a[2], 0, _F), 0.05),
    ('wrist_1', 4, (0, 0, _F), (0, 0, UR5E_DH.d[3]), 0.045),
    ('wrist_2', 5, (0, 0, 0), (0, 0, UR5E_DH.d[4]), 0.045),
    ('wrist_3', 6, (0, 0, 0), (0, 0, UR5E_DH.d[5]), 0.045),
    ('tool', 6, (0, 0, UR5E_DH.d[5]), (0, 0, UR5E_DH.d[5] + TOOL_LENGTH), 0.045),
)


def _rot_x_quat(alpha: float) -> tuple:
    return (math.cos(alpha / 2), math.sin(alpha / 2), 0.0, 0.0)


def ur5e_mjcf(dh: DhParameters = UR5E_DH, capsules=UR5E_CAPSULES) -> str:
    """The arm as an MJCF string: six hinge bodies from the DH table, capsule geoms, a flange
    site. Collisions are off (the separation is computed, not simulated as contacts)."""
    lines = ['<mujoco model="ur5e_capsules">',
             '  <compiler angle="radian" autolimits="true"/>',
             '  <option gravity="0 0 0"/>',
             '  <default><geom contype="0" conaffinity="0" rgba="0.6 0.7 0.8 1"/></default>',
             '  <worldbody>']
    indent = '    '
    for i in range(N_JOINTS):
        if i == 0:
            pos, quat = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)
        else:
            pos = (dh.a[i - 1], 0.0, dh.d[i - 1])
            quat = _rot_x_quat(dh.alpha[i - 1])
        lines.append(f'{indent}<body name="link{i + 1}" pos="{_xyz(pos)}" quat="{_xyz(quat)}">')
        lines.append(f'{indent}  <joint name="{JOINT_NAMES[i]}" type="hinge" axis="0 0 1" '
                     f'range="{-2 * math.pi:.6f} {2 * math.pi:.6f}"/>')
        lines.append(f'{indent}  <inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>')
        for name, body, p0, p1, radius in capsules:
            if body == i + 1:
                lines.append(f'{indent}  <geom name="{name}" type="capsule" size="{radius}" '
                             f'fromto="{_xyz(p0)} {_xyz(p1)}"/>')
        if i == N_JOINTS - 1:
            flange = (dh.a[i], 0.0, dh.d[i])
            lines.append(f'{indent}  <site name="flange" pos="{_xyz(flange)}" '
                         f'quat="{_xyz(_rot_x_quat(dh.alpha[i]))}"/>')
        indent += '  '
    for _ in range(N_JOINTS):
        indent = indent[:-2]
        lines.append(f'{indent}</body>')
    lines += ['  </worldbody>', '</mujoco>']
    return '\n'.join(lines) + '\n'


def _xyz(values) -> str:
    return ' '.join(f'{float(v):.9g}' for v in values)


# -- capsule geometry -------------------------------------------------------------------------
@dataclass(frozen=True)
class BodyCapsules:
    """A person as capsules: axis segments (m, 2, 3) in the robot base frame, radii (m,),
    part names (m,)."""

    segments: np.ndarray
    radii: np.ndarray
    names: tuple

    def __post_init__(self):
        seg = np.asarray(self.segments, dtype=float)
        rad = np.asarray(self.radii, dtype=float)
        if seg.ndim != 3 or seg.shape[1:] != (2, 3) or seg.shape[0] == 0 \
                or rad.shape != (seg.shape[0],) or len(self.names) != seg.shape[0]:
            raise ValueError(f'body capsules need segments (m, 2, 3), radii (m,) and m names, '
                             f'got {seg.shape}, {rad.shape}, {len(self.names)}')
        if not (np.all(np.isfinite(seg)) and np.all(np.isfinite(rad)) and np.all(rad >= 0)):
            raise ValueError('body capsules must be finite with radii >= 0')
        object.__setattr__(self, 'segments', seg)
        object.__setattr__(self, 'radii', rad)


# Bones of an Azure Kinect Body Tracking skeleton (tracking.K4ABT_JOINTS names), with radii.
BONES = (
    ('torso', 'pelvis', 'neck', 0.15),
    ('head', 'neck', 'head', 0.11),
    ('upper_arm_left', 'shoulder_left', 'elbow_left', 0.05),
    ('forearm_left', 'elbow_left', 'wrist_left', 0.045),
    ('hand_left', 'wrist_left', 'handtip_left', 0.05),
    ('upper_arm_right', 'shoulder_right', 'elbow_right', 0.05),
    ('forearm_right', 'elbow_right', 'wrist_right', 0.045),
    ('hand_right', 'wrist_right', 'handtip_right', 0.05),
    ('thigh_left', 'hip_left', 'knee_left', 0.08),
    ('shin_left', 'knee_left', 'ankle_left', 0.06),
    ('thigh_right', 'hip_right', 'knee_right', 0.08),
    ('shin_right', 'knee_right', 'ankle_right', 0.06),
)
KEYPOINT_RADIUS = 0.1    # m, the sphere around each keypoint of an unlabelled skeleton


_BONE_CACHE: dict = {}


def _bones(joints: tuple):
    """(bone end-point indices (m, 2), radii, names) of the BONES a joint list spans."""
    cached = _BONE_CACHE.get(joints)
    if cached is None:
        index = {name: i for i, name in enumerate(joints)}
        bones = [b for b in BONES if b[1] in index and b[2] in index]
        if not bones:
            raise ValueError(f'joints {list(joints)} span no bone of {[b[0] for b in BONES]}')
        cached = (np.array([(index[b[1]], index[b[2]]) for b in bones]),
                  np.array([b[3] for b in bones]), tuple(b[0] for b in bones))
        if len(_BONE_CACHE) < 64:
            _BONE_CACHE[joints] = cached
    return cached


def _trusted(segments, radii, names) -> BodyCapsules:
    body = object.__new__(BodyCapsules)
    object.__setattr__(body, 'segments', segments)
    object.__setattr__(body, 'radii', radii)
    object.__setattr__(body, 'names', names)
    return body


def body_capsules(points, joints=None, keypoint_radius: float = KEYPOINT_RADIUS) -> BodyCapsules:
    """A person's capsules from skeleton keypoints (n, 3), metres, robot base frame.

    `joints`: the keypoints' Azure Kinect joint names (a multiple of one body's names: every
    body in view, as `human/skeleton` carries them): the `BONES` of each body. None: an
    unlabelled skeleton, a sphere of `keypoint_radius` around each keypoint."""
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f'keypoints must have shape (n, 3) with n >= 1, got {pts.shape}')
    if not np.isfinite(pts).all():
        raise ValueError('keypoints must be finite (no NaN or inf)')
    if joints is None:
        if not (math.isfinite(keypoint_radius) and keypoint_radius >= 0):
            raise ValueError(f'keypoint_radius must be >= 0, got {keypoint_radius!r}')
        return _trusted(np.stack([pts, pts], axis=1), np.full(len(pts), float(keypoint_radius)),
                        tuple(f'keypoint_{i}' for i in range(len(pts))))
    joints = tuple(joints)
    if len(pts) % len(joints) != 0:
        raise ValueError(f'{len(pts)} keypoints are not whole bodies of the {len(joints)} '
                         'joints named')
    pairs, radii, names = _bones(joints)
    bodies = len(pts) // len(joints)
    if bodies == 1:
        return _trusted(pts[pairs], radii, names)
    offsets = (np.arange(bodies) * len(joints))[:, None, None]
    segments = pts[(pairs[None, :, :] + offsets).reshape(-1, 2)]
    return _trusted(segments, np.tile(radii, bodies),
                    names + tuple(f'{n}_{b}' for b in range(1, bodies) for n in names))


def people(body: BodyCapsules) -> int:
    """How many people a skeleton frame holds: `body_capsules` names the second body's bones
    `<bone>_1`, the third's `<bone>_2`, ... (no bone name of `BONES` ends in a number); an
    unlabelled frame (spheres `keypoint_<i>`) counts as one."""
    if not body.names or body.names[0].startswith('keypoint_'):
        return 1
    return len({n.rsplit('_', 1)[1] if n.rsplit('_', 1)[-1].isdigit() else ''
                for n in body.names})


@dataclass(frozen=True)
class Separation:
    """The closest approach of the arm to a person: S (m, negative where the capsules
    overlap), the closest points on the arm's and on the body's surface (base frame), and the
    two capsules' names."""

    distance: float
    arm_point: np.ndarray
    human_point: np.ndarray
    arm_link: str
    body_part: str


def separation(arm_segments, arm_radii, arm_names, body: BodyCapsules) -> Separation:
    """The `Separation` of arm capsules (n, 2, 3) / (n,) from a person's capsules."""
    points = np.empty((2, 3))
    distance, i, j = _kernels().capsule_separation(arm_segments, arm_radii, body.segments,
                                                   body.radii, points, True)
    return Separation(float(distance), points[0], points[1], arm_names[i], body.names[j])


# -- the arm in MuJoCo ------------------------------------------------------------------------
@dataclass(frozen=True)
class ArmPose:
    """The arm at one joint configuration: capsule axis segments (n, 2, 3), the flange
    position (3,) and rotation (3, 3), joint axes and anchors (6, 3) in the base frame."""

    q: np.ndarray
    segments: np.ndarray
    flange_position: np.ndarray
    flange_rotation: np.ndarray
    axes: np.ndarray
    anchors: np.ndarray


def import_mujoco():
    """`mujoco`, imported without an OpenGL backend unless `MUJOCO_GL` names one (module
    docstring, "No rendering")."""
    if 'mujoco' not in sys.modules and not os.environ.get('MUJOCO_GL'):
        os.environ['MUJOCO_GL'] = 'disable'
    import mujoco
    return mujoco


class Arm:
    """The UR5e of capsules in MuJoCo: forward kinematics, link speeds, separation."""

    def __init__(self, dh: DhParameters = UR5E_DH, capsules=UR5E_CAPSULES):
        mujoco = import_mujoco()
        self._mujoco = mujoco
        self.mjcf = ur5e_mjcf(dh, capsules)
        self.model = mujoco.MjModel.from_xml_string(self.mjcf)
        self.data = mujoco.MjData(self.model)
        self.joint_names = JOINT_NAMES
        self.capsule_names = tuple(c[0] for c in capsules)
        self.radii = np.array([c[4] for c in capsules], dtype=float)
        ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, n)
               for n in self.capsule_names]
        if ids != list(range(ids[0], ids[0] + len(ids))):
            raise ValueError('the capsules must be listed body by body, in body order')
        self._geoms = slice(ids[0], ids[0] + len(ids))
        self.half_lengths = self.model.geom_size[self._geoms, 1].copy()
        # Capsule c is moved by joints 0 .. last_joint[c] (it sits on body last_joint[c] + 1).
        self.last_joint = np.array([c[1] for c in capsules], dtype=np.int64) - 1
        self.flange_site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, 'flange')
        self._segments = np.empty((len(ids), 2, 3))
        self._points = np.empty((2, 3))
        self._q = np.full(N_JOINTS, np.nan)

    def _kinematics(self, q) -> np.ndarray:
        """Capsule axis segments at q (a buffer reused until q changes: copy to keep)."""
        q = np.asarray(q, dtype=float)
        if q.tobytes() != self._q.tobytes():
            self.data.qpos[:] = q
            self._mujoco.mj_kinematics(self.model, self.data)
            _kernels().capsule_ends(self.data.geom_xpos[self._geoms],
                                    self.data.geom_xmat[self._geoms], self.half_lengths,
                                    self._segments)
            self._q[:] = q
        return self._segments

    def forward(self, q) -> ArmPose:
        """MuJoCo's forward kinematics at joint angles q (6,) radians."""
        segments = self._kinematics(q).copy()
        data = self.data
        return ArmPose(self._q.copy(), segments, data.site_xpos[self.flange_site].copy(),
                       data.site_xmat[self.flange_site].reshape(3, 3).copy(),
                       data.xaxis.copy(), data.xanchor.copy())

    def segments(self, q) -> np.ndarray:
        """The capsules' axis segments (n, 2, 3) at q (a copy)."""
        return self._kinematics(q).copy()

    def link_speed(self, q, qd) -> float:
        """The fastest point of the arm's capsules (m/s) at joint angles q moving at qd."""
        segments = self._kinematics(q)
        return float(_kernels().link_speed(segments, self.radii, self.last_joint,
                                           self.data.xaxis, self.data.xanchor,
                                           np.asarray(qd, dtype=float)))

    def separation(self, q, body: BodyCapsules) -> Separation:
        """The closest approach of the arm at q to the person's capsules."""
        return separation(self._kinematics(q), self.radii, self.capsule_names, body)

    def distance(self, q, body: BodyCapsules) -> float:
        """Only S of `separation` (m): the fast path of the batch cell's checks."""
        return float(_kernels().capsule_separation(self._kinematics(q), self.radii,
                                                   body.segments, body.radii, self._points,
                                                   False)[0])


# -- motion -----------------------------------------------------------------------------------
def smoothstep(u):
    """h(u) = 3u^2 - 2u^3 and its derivative h'(u) = 6u(1 - u), u in [0, 1]."""
    return u * u * (3.0 - 2.0 * u), 6.0 * u * (1.0 - u)


def segment_duration(q0, q1, velocity, acceleration) -> float:
    """The shortest duration (s) of a cubic segment q0 -> q1 within the joint speed and
    acceleration limits (peak speed 1.5 |dq| / T, peak acceleration 6 |dq| / T^2)."""
    dq = np.abs(np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float))
    t_v = 1.5 * dq / np.asarray(velocity, dtype=float)
    t_a = np.sqrt(6.0 * dq / np.asarray(acceleration, dtype=float))
    return float(max(np.max(t_v), np.max(t_a), 0.0))


@dataclass(frozen=True)
class Trajectory:
    """Joint waypoints (n + 1, 6) from the start configuration, segment durations (n,) s,
    the top link speed at override 1 (m/s), and per segment the program segment it completes
    (-1: none; `bridge` counts a program's progress by them)."""

    joint_names: tuple
    positions: np.ndarray
    durations: np.ndarray
    nominal_speed: float
    marks: tuple = ()
    kind: str = ''

    def __post_init__(self):
        object.__setattr__(self, '_times', np.cumsum(self.durations))
        object.__setattr__(self, '_duration', float(np.sum(self.durations)))

    @property
    def times(self) -> np.ndarray:
        """time_from_start of each waypoint after the start (s), at override 1."""
        return self._times.copy()

    @property
    def duration(self) -> float:
        return self._duration

    def sample(self, tau: float):
        """(q, dq/dtau, segment index) at trajectory time tau (s, clamped to the ends)."""
        if len(self.durations) == 0:
            return self.positions[-1].copy(), np.zeros(N_JOINTS), -1
        ends = self._times
        i = int(np.searchsorted(ends, tau, side='right'))
        if i >= len(ends):
            return self.positions[-1].copy(), np.zeros(N_JOINTS), len(ends) - 1
        start = ends[i - 1] if i > 0 else 0.0
        u = (tau - start) / self.durations[i]
        u = min(max(u, 0.0), 1.0)
        h, dh = smoothstep(u)
        dq = self.positions[i + 1] - self.positions[i]
        return self.positions[i] + dq * h, dq * (dh / self.durations[i]), i


def peak_link_speed(arm: Arm, q0, q1, duration: float, samples: int = 9) -> float:
    """The top link speed (m/s) of the cubic segment q0 -> q1 over `duration` s, sampled at
    `samples` interior points (the speed profile is smooth, peaking mid-segment), with a 5%
    allowance for what falls between the samples."""
    if duration <= 0:
        return 0.0
    q0 = np.asarray(q0, dtype=float)
    dq = np.asarray(q1, dtype=float) - q0
    best = 0.0
    for u in np.linspace(0.0, 1.0, samples + 2)[1:-1]:
        h, dh = smoothstep(u)
        best = max(best, arm.link_speed(q0 + dq * h, dq * (dh / duration)))
    return 1.05 * best


def warm_up(*arms: Arm, stopped=None) -> bool:
    """Run every numba kernel of the arm once (kinematics, separation with its closest
    points, distance, link speed, a segment's peak), so that a node's first real call does not
    compile them on its control thread (9 s on a fresh install) or load them from numba's
    cache (about 0.5 s). `stopped()` (optional) is asked before each kernel: once it is true
    the rest is skipped and False returned, so that a node asked to stop while it compiles
    stops within one kernel's compilation, not after all of them (a node stopped at its first
    start on a loaded machine took more than 10 s)."""
    from .guard import nearest_on_path
    body = body_capsules(np.array([[1.5, 0.0, 0.5], [1.5, 0.2, 0.9]]))
    q0 = np.array([1.4, -1.9, 1.9, -1.57, -1.57, 0.0])
    steps = []
    for arm in arms:
        steps += [lambda a=arm: a.separation(q0, body), lambda a=arm: a.distance(q0, body),
                  lambda a=arm: a.link_speed(q0, np.full(N_JOINTS, 0.1)),
                  lambda a=arm: peak_link_speed(a, q0, q0 + 0.1, 1.0, samples=1)]
    steps.append(lambda: nearest_on_path(np.zeros(N_JOINTS),
                                         np.array([np.zeros(N_JOINTS), np.ones(N_JOINTS)])))
    for step in steps:
        if stopped is not None and stopped():
            return False
        step()
    return True


@dataclass
class FollowerState:
    q: np.ndarray
    qd: np.ndarray
    scale: float
    speed_bound: float     # s * v_nominal: what the links' speed stays below (m/s)


class TrajectoryFollower:
    """A scaled joint trajectory controller (see the module docstring): `follow` a
    `Trajectory` from the current configuration, `step(dt, override)`."""

    def __init__(self, q0, deceleration: float):
        self.q = np.asarray(q0, dtype=float).copy()
        self.qd = np.zeros(N_JOINTS)
        self.deceleration = float(deceleration)
        self.trajectory: Trajectory | None = None
        self.tau = 0.0
        self.scale = 0.0

    def follow(self, trajectory: Trajectory) -> None:
        """Replace the running trajectory. It must start where the arm is, at rest (the
        bridge sends one only at a safe point), so the scaling starts again from 0."""
        if not np.allclose(trajectory.positions[0], self.q, atol=1e-6):
            raise ValueError('a trajectory must start at the arm\'s configuration')
        self.trajectory = trajectory
        self.tau = 0.0
        self.scale = 0.0

    @property
    def done(self) -> bool:
        return self.trajectory is None or self.tau >= self.trajectory.duration

    @property
    def speed_bound(self) -> float:
        if self.trajectory is None or self.done:
            return 0.0
        return self.scale * self.trajectory.nominal_speed

    def step(self, dt: float, override: float) -> FollowerState:
        target = min(max(float(override), 0.0), 1.0)
        traj = self.trajectory
        if traj is None or self.done:
            self.scale = 0.0
            self.qd = np.zeros(N_JOINTS)
            return FollowerState(self.q, self.qd, self.scale, 0.0)
        rate = self.deceleration / traj.nominal_speed if traj.nominal_speed > 0 else math.inf
        previous = self.scale
        change = max(-rate * dt, min(rate * dt, target - previous))
        self.scale = previous + change
        self.tau = min(traj.duration, self.tau + 0.5 * (previous + self.scale) * dt)
        q, dq_dtau, _ = traj.sample(self.tau)
        self.q = q
        self.qd = dq_dtau * self.scale
        return FollowerState(self.q, self.qd, self.scale, self.speed_bound)
