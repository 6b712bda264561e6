"""Human motion -> discrete observations (MODEL.md section 6), and the inverse for simulation.

The paper's observation set (eq. observations) is 14 variables: the position of the human centre
of mass q0 and the joint angles of the left/right shoulder, elbow and hand (ls, rs, le, re, lh,
rh), and their velocities. Each is discretised into a few levels; the planner only sees levels.
The case study uses one of them, the human velocity level

    O = 1  if  mean_j |qdot_j| <  t1          (low)
    O = 2  if  t1 <= mean_j |qdot_j| < t2     (medium)
    O = 3  otherwise                          (high),

with thresholds t1 < t2 in rad/s (`velocity_level`). A decision epoch spans many sensor
samples; each sample gets a level and the epoch's O is their majority, ties to the higher (the
more cautious) level (`window_level`). A vote makes O independent of how many samples a window
happens to hold, so a replay with other timing yields the same O.

The distance level d of the tri-circle safety approach comes from the skeleton keypoints
(metres, robot base frame) and three radii r0 < r1 < r2 around the robot reference point p:

    rmin = min_k ||x_k - p||;   d = 0 if rmin < r0 (collision), 1 if < r1 (inner),
                                    2 if < r2 (middle), 3 otherwise (outer or beyond).

Both inputs are bounded to the cell, so that a finite but absurd value is malformed, never a
level (1e308 would overflow to an infinite distance, read d = 3, the unsafe side, or to an
infinite speed, O = 3): a keypoint farther than `MAX_KEYPOINT_RANGE` from the frame's origin
(no tracker in a cell sees that far: millimetres for metres, a bad transform), a joint speed
above `MAX_JOINT_SPEED` (no human arm joint turns that fast: a glitch, or degrees for radians),
more than `MAX_JOINTS` joints in a sample or `MAX_KEYPOINTS` keypoints in a skeleton
(`check_keypoint_range`, `check_joint_speeds`; the conversions refuse such messages first).

`synthesize_joint_velocities` and `synthesize_skeleton` invert these maps for the simulated
cell: they draw motion whose level is, by construction, the requested one (strictly inside the
band, so no rounding at an edge can flip it).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..model import DISTANCE_LEVELS, OBSERVATION_LEVELS

# The six arm joints of the paper's observation set (shoulder, elbow, hand/wrist, left and
# right), REP-155 style names: the joint names of `human/joint_states`.
HUMAN_JOINTS = ('l_shoulder', 'r_shoulder', 'l_elbow', 'r_elbow', 'l_wrist', 'r_wrist')
# Node defaults of DESIGN.md (rad/s and metres).
DEFAULT_VELOCITY_THRESHOLDS = (0.3, 0.8)
DEFAULT_SAFETY_RADII = (0.2, 0.6, 1.2)
# How far the synthesized level-3 speeds and d = 3 distances reach beyond the last edge.
LEVEL3_SPEED_FACTOR = 2.0
OUTER_BAND_WIDTH = 1.0  # metres beyond the middle radius for d = 3
# Synthesized values stay this fraction of the band width away from the band's edges.
BAND_MARGIN = 0.05
# Offsets of the other keypoints from the closest one (metres): a body-sized cluster.
BODY_EXTENT = 0.5
# The cell's bounds on the inputs (module docstring).
MAX_KEYPOINT_RANGE = 20.0    # metres from the robot frame's origin
MAX_JOINT_SPEED = 50.0       # rad/s (about 2900 deg/s)
MAX_JOINTS = 100             # joints in one joint-state sample
MAX_KEYPOINTS = 512          # keypoints in one skeleton (16 bodies of 32 joints)


def _increasing_positive(name: str, values, length: int) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be {length} numbers, got {values!r}') from None
    if arr.shape != (length,):
        raise ValueError(f'{name} must be {length} numbers, got shape {arr.shape}')
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f'{name} must be finite and positive, got {arr.tolist()}')
    if np.any(np.diff(arr) <= 0):
        raise ValueError(f'{name} must be strictly increasing, got {arr.tolist()}')
    return arr


def _finite_array(name: str, values) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be numbers, got {values!r}') from None
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite (no NaN or inf), got {arr.tolist()}')
    return arr


def _level_arg(name: str, level, allowed: Sequence[int]) -> int:
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) \
            or int(level) not in allowed:
        raise ValueError(f'{name} must be one of {tuple(allowed)}, got {level!r}')
    return int(level)


def check_joint_speeds(speeds, what: str = 'speeds') -> np.ndarray:
    """The joint velocities (rad/s) as an array; ValueError when one is not finite or its
    magnitude is above `MAX_JOINT_SPEED`, or there are more than `MAX_JOINTS`."""
    arr = _finite_array(what, speeds)
    if arr.size > MAX_JOINTS:
        raise ValueError(f'{what}: {arr.size} joints, more than {MAX_JOINTS}')
    if arr.size and not np.abs(arr).max() <= MAX_JOINT_SPEED:
        raise ValueError(f'{what}: a joint velocity of {np.abs(arr).max():.3g} rad/s, above '
                         f'{MAX_JOINT_SPEED:g} rad/s: no human joint turns that fast (a sensor '
                         'glitch, or degrees for radians)')
    return arr


def check_keypoint_range(points, what: str = 'keypoints') -> np.ndarray:
    """Points (n, 3) as an array; ValueError when one is not finite or farther than
    `MAX_KEYPOINT_RANGE` from the frame's origin (checked before squaring: no overflow)."""
    arr = _finite_array(what, points)
    flat = arr.reshape(-1, 3) if arr.size % 3 == 0 else arr.reshape(1, -1)
    if flat.size and not np.abs(flat).max() <= MAX_KEYPOINT_RANGE:
        raise ValueError(f'{what}: a coordinate of {np.abs(flat).max():.3g} m, farther than '
                         f'{MAX_KEYPOINT_RANGE:g} m from the frame origin: beyond any tracker '
                         'of the cell (metres expected)')
    if flat.size and flat.shape[1] == 3:
        norm = float(np.sqrt((flat ** 2).sum(axis=1)).max())
        if not norm <= MAX_KEYPOINT_RANGE:
            raise ValueError(f'{what}: a point {norm:.3g} m from the frame origin, farther '
                             f'than {MAX_KEYPOINT_RANGE:g} m: beyond any tracker of the cell')
    return arr


def mean_speed(speeds) -> float:
    """Mean absolute value of joint velocities (rad/s); finite, non-empty, bounded
    (`check_joint_speeds`)."""
    arr = check_joint_speeds(speeds)
    if arr.size == 0:
        raise ValueError('speeds is empty: a velocity level needs at least one joint velocity')
    return float(np.mean(np.abs(arr)))


def velocity_level(speeds, thresholds=DEFAULT_VELOCITY_THRESHOLDS) -> int:
    """O in {1, 2, 3} of joint velocities: mean |v| below t1 -> 1, below t2 -> 2, else 3."""
    t = _increasing_positive('thresholds', thresholds, 2)
    v = mean_speed(speeds)
    return 1 if v < t[0] else 2 if v < t[1] else 3


def window_level(levels) -> int:
    """Majority of per-sample levels over an epoch window; a tie goes to the higher level."""
    values = levels.reshape(-1).tolist() if isinstance(levels, np.ndarray) else list(levels)
    if not values:
        raise ValueError('levels is empty: an epoch window needs at least one sample')
    counts: dict[int, int] = {}
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f'levels must be non-negative integers, got {v!r}')
        counts[int(v)] = counts.get(int(v), 0) + 1
    return max(counts, key=lambda level: (counts[level], level))


def closest_distance(keypoints, robot_point) -> float:
    """min_k ||x_k - p|| of keypoints (n, 3) to the robot reference point p (3,), metres; both
    within `MAX_KEYPOINT_RANGE` of the frame's origin, so the distance is finite."""
    kp = _finite_array('keypoints', keypoints)
    if kp.ndim != 2 or kp.shape[1] != 3 or kp.shape[0] == 0:
        raise ValueError(f'keypoints must have shape (n, 3) with n >= 1, got {kp.shape}')
    p = _finite_array('robot_point', robot_point)
    if p.shape != (3,):
        raise ValueError(f'robot_point must have shape (3,), got {p.shape}')
    check_keypoint_range(kp)
    check_keypoint_range(p[None], 'robot_point')
    return float(np.sqrt(np.min(np.sum((kp - p) ** 2, axis=1))))


def distance_level(keypoints, robot_point=(0.0, 0.0, 0.0), radii=DEFAULT_SAFETY_RADII) -> int:
    """d in {0..3}: closest keypoint < r0 -> 0 (collision), < r1 -> 1, < r2 -> 2, else 3."""
    return level_of_distance(closest_distance(keypoints, robot_point), radii)


def level_of_distance(distance: float, radii=DEFAULT_SAFETY_RADII) -> int:
    """d in {0..3} of a distance (m; below 0, overlapping bodies, is a collision) against the
    three safety radii: < r0 -> 0, < r1 -> 1, < r2 -> 2, else 3. The one home of the bands,
    for the closest keypoint to a reference point and for the separation to an arm's links."""
    r = _increasing_positive('radii', radii, 3)
    if not np.isfinite(distance):
        raise ValueError(f'a distance must be finite, got {distance!r}')
    return int(np.searchsorted(r, distance, side='right'))


def distance_band(d: int, radii=DEFAULT_SAFETY_RADII) -> tuple[float, float]:
    """The closest distances (lo, hi) that the synthesized motion of level d keeps to: d's band
    between its radii (d = 3: up to OUTER_BAND_WIDTH beyond the middle radius), less
    BAND_MARGIN of its width at either edge, so no rounding at an edge can flip the level."""
    d = _level_arg('d', d, DISTANCE_LEVELS)
    r = _increasing_positive('radii', radii, 3)
    edges = (0.0, r[0], r[1], r[2], r[2] + OUTER_BAND_WIDTH)
    pad = BAND_MARGIN * (edges[d + 1] - edges[d])
    return float(edges[d] + pad), float(edges[d + 1] - pad)


def _inside(lo: float, hi: float, rng: np.random.Generator) -> float:
    """A uniform draw strictly inside (lo, hi), BAND_MARGIN of the width from either edge."""
    pad = BAND_MARGIN * (hi - lo)
    return float(rng.uniform(lo + pad, hi - pad))


def synthesize_joint_velocities(level: int, n_joints: int,
                                thresholds=DEFAULT_VELOCITY_THRESHOLDS,
                                rng: np.random.Generator | None = None) -> np.ndarray:
    """Signed joint velocities (n_joints,) whose mean |v| lies strictly inside `level`'s band.

    Bands: level 1 (0, t1), level 2 (t1, t2), level 3 (t2, 2*t2). A target mean m is drawn
    inside the band; the magnitudes spread around m (uniform weights in [0.5, 1.5], rescaled so
    that their mean is exactly m) and the signs are random.
    """
    level = _level_arg('level', level, OBSERVATION_LEVELS)
    if isinstance(n_joints, bool) or not isinstance(n_joints, (int, np.integer)) \
            or n_joints < 1:
        raise ValueError(f'n_joints must be an integer >= 1, got {n_joints!r}')
    t = _increasing_positive('thresholds', thresholds, 2)
    rng = np.random.default_rng() if rng is None else rng
    edges = (0.0, t[0], t[1], LEVEL3_SPEED_FACTOR * t[1])
    target = _inside(edges[level - 1], edges[level], rng)
    weights = rng.uniform(0.5, 1.5, size=int(n_joints))
    magnitudes = weights * (target / weights.mean())
    signs = rng.choice((-1.0, 1.0), size=int(n_joints))
    return signs * magnitudes


def synthesize_skeleton(d: int, radii=DEFAULT_SAFETY_RADII, robot_point=(0.0, 0.0, 0.0),
                        rng: np.random.Generator | None = None,
                        n_keypoints: int = 7) -> np.ndarray:
    """Keypoints (n_keypoints, 3) whose closest distance to the robot is strictly inside d's band.

    Bands: d=0 (0, r0), 1 (r0, r1), 2 (r1, r2), 3 (r2, r2 + 1 m). The closest keypoint sits at a
    drawn distance r along a random direction u; the others are offsets o from it with
    u.o > 0 (pointing away from the robot), so ||r u + o||^2 = r^2 + 2 r u.o + |o|^2 > r^2 and
    the closest distance is exactly r. The keypoint order is shuffled.
    """
    lo, hi = distance_band(d, radii)
    if isinstance(n_keypoints, bool) or not isinstance(n_keypoints, (int, np.integer)) \
            or n_keypoints < 1:
        raise ValueError(f'n_keypoints must be an integer >= 1, got {n_keypoints!r}')
    p = _finite_array('robot_point', robot_point)
    if p.shape != (3,):
        raise ValueError(f'robot_point must have shape (3,), got {p.shape}')
    rng = np.random.default_rng() if rng is None else rng
    distance = float(rng.uniform(lo, hi))
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    closest = distance * u
    offsets = rng.uniform(-BODY_EXTENT, BODY_EXTENT, size=(int(n_keypoints) - 1, 3))
    along = offsets @ u
    # Reflect the component along u so that every offset points away from the robot.
    offsets += np.outer(np.abs(along) - along + 1e-3, u)
    points = np.vstack([closest, closest + offsets])
    rng.shuffle(points, axis=0)
    return points + p
