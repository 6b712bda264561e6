"""The simulated person's body in 3D: where they walk around the arm and how fast.

`human.SimulatedHuman` draws the epoch's hidden state and events from MODEL.md's dynamics; this
module gives the same person a body, for the cell with an arm (`robot.cell`) and the phase-2
simulated cell. It decides nothing the model decides; it turns the model's events into motion:

- **Approach and retreat** follow the model's Delta (+1 a step closer, drawn from p_delta[ea]
  by `SimulatedHuman`), relative to the arm as the model's distance is: at the start of an
  epoch whose Delta is not 0, the person takes the band of their current separation S to the
  arm's links (`safety_radii`: 0 collision < r0 <= 1 inner < r1 <= 2 middle < r2 <= 3 outer),
  aims at the band b' = min(3, max(0, b - Delta)) and walks along their line to the robot base
  until the separation is at that band's middle (`band_targets`: r0 / 2, (r0 + r1) / 2,
  (r1 + r2) / 2, r2 + 0.4 m), then stands. With Delta = 0 they stand where they are. The cell
  bounds the walk: the person stands no nearer the robot base than the shared table's edge
  (`MIN_STANDOFF`, 1.35 m; the hands on the table reach to 0.8 m of the base axis), so the
  inner bands are reached when the arm comes to the person's side (the shared station, the
  collaboration pose), as in a real cell. The arm's own motion changes S as well: that is what
  the decision layer's d then shows, since d is the band of the real separation.
- **Speed**: the hidden emotions drive it, v = min(`MAX_WALK`, 0.4 + 0.15 em + 0.3 ea) m/s
  (a motivated person walks with purpose, an aggressive one rushes); the hands move toward the
  table when the person aims at the inner band or nearer, down otherwise, at `REACH_RATE`
  (about 0.26 m/s). No point of the body moves faster than ISO 13855's 1.6 m/s, the speed
  SSM assumes (test_robot.py checks it).
- **Where**: the person faces the robot base from the angle theta around their workstation
  (`STATION_ANGLE`, the side of the robot's shared station), drifting in polar coordinates
  (around the arm, not through it) toward an angle theta* drawn again with probability
  `WANDER` at each epoch from their own random stream (`seed`), which no action changes.

Keypoints are the 32 Azure Kinect Body Tracking joints (`tracking.K4ABT_JOINTS` order) in the
robot base frame (metres; the robot stands on a table, its base at z = 0, the floor at
z = -`TABLE_HEIGHT`), so the same body feeds `arm.body_capsules` and a body-tracking stream.
"""

from __future__ import annotations

import math

import numpy as np

from .tracking import JOINT_INDEX, K4ABT_JOINTS

START = (1.35, 1.35, 1.9, 2.6)         # m, pelvis to the base axis at the start, per band
STATION_ANGLE = math.radians(-31.0)    # rad, the person's workstation around the robot base
STATION_SPREAD = math.radians(25.0)    # rad, how far their wandering goes around it
WANDER = 0.3                           # chance per epoch of a new angle
MAX_WALK = 1.1                         # m/s (plus the hands, and turning: <= 1.6 m/s)
REACH_RATE = 0.45                      # of the way per second: the hands move at ~0.26 m/s
TABLE_HEIGHT = 0.85                    # m, the robot base above the floor
MIN_STANDOFF = 1.35                    # m: the shared table's edge, nearer the person cannot stand
MAX_STANDOFF = 3.5                     # m, nor farther from it
ARRIVED = 0.05                         # m from the band's middle: the person stands
OUTER_MARGIN = 0.4                     # m beyond r2: the middle of the outer band

# Body frame (forward toward the robot, left, up from the floor), metres. Joints not listed
# in the two arm postures are the same in both.
_BODY = {
    'pelvis': (0, 0, 0.95), 'spine_navel': (0, 0, 1.10), 'spine_chest': (0, 0, 1.30),
    'neck': (0, 0, 1.50), 'head': (0, 0, 1.65), 'nose': (0.10, 0, 1.63),
    'eye_left': (0.08, 0.03, 1.67), 'eye_right': (0.08, -0.03, 1.67),
    'ear_left': (0, 0.07, 1.65), 'ear_right': (0, -0.07, 1.65),
    'clavicle_left': (0, 0.07, 1.45), 'clavicle_right': (0, -0.07, 1.45),
    'shoulder_left': (0, 0.19, 1.43), 'shoulder_right': (0, -0.19, 1.43),
    'hip_left': (0, 0.10, 0.92), 'hip_right': (0, -0.10, 0.92),
    'knee_left': (0.02, 0.10, 0.50), 'knee_right': (0.02, -0.10, 0.50),
    'ankle_left': (0, 0.10, 0.08), 'ankle_right': (0, -0.10, 0.08),
    'foot_left': (0.12, 0.10, 0.02), 'foot_right': (0.12, -0.10, 0.02),
}
_HANGING = {'elbow': (0, 0.21, 1.15), 'wrist': (0, 0.21, 0.90), 'hand': (0, 0.20, 0.83),
            'handtip': (0, 0.20, 0.75), 'thumb': (0.03, 0.19, 0.80)}
_REACHING = {'elbow': (0.22, 0.22, 1.12), 'wrist': (0.42, 0.19, 0.93),
             'hand': (0.49, 0.18, 0.90), 'handtip': (0.56, 0.17, 0.88),
             'thumb': (0.49, 0.14, 0.91)}


def _postures() -> tuple[np.ndarray, np.ndarray]:
    """The 32 joints (forward, left, up) in the body frame, hands hanging, and the change to
    the hands on the table: the posture at reach r is hanging + r * change."""
    out = np.zeros((2, len(K4ABT_JOINTS), 3))
    for name, p in _BODY.items():
        out[:, JOINT_INDEX[name]] = p
    for part in _HANGING:
        for k, pose in enumerate((_HANGING, _REACHING)):
            p = np.array(pose[part], dtype=float)
            out[k, JOINT_INDEX[f'{part}_left']] = p
            out[k, JOINT_INDEX[f'{part}_right']] = p * (1, -1, 1)
    return out[0], out[1] - out[0]


_POSTURE, _REACH = _postures()


def walking_speed(em: int, ea: int) -> float:
    """The person's walking speed (m/s) for their hidden emotions."""
    return min(MAX_WALK, 0.4 + 0.15 * em + 0.3 * ea)


def band_targets(radii) -> tuple:
    """The separation (m) a person aiming at band 0, 1, 2, 3 walks to: each band's middle."""
    r0, r1, r2 = (float(r) for r in radii)
    return (r0 / 2, (r0 + r1) / 2, (r1 + r2) / 2, r2 + OUTER_MARGIN)


class SimulatedPerson:
    """One person's body moving around the robot (see the module docstring)."""

    def __init__(self, band: int, seed=0, em: int = 0, ea: int = 0,
                 radii=(0.2, 0.6, 1.2)):
        if isinstance(band, bool) or band not in (0, 1, 2, 3):
            raise ValueError(f'band must be 0..3, got {band!r}')
        self.rng = np.random.default_rng(seed)
        self.radii = tuple(float(r) for r in radii)
        self.targets = band_targets(self.radii)
        self.theta = STATION_ANGLE + STATION_SPREAD * (2 * self.rng.random() - 1)
        self.theta_target = self.theta
        self.rho = START[band]
        self.aim: float | None = None          # the separation walked to, None: standing
        self.reach_target = 1.0 if band <= 1 else 0.0
        self.reach = self.reach_target
        self.speed = walking_speed(em, ea)

    def begin_epoch(self, delta: int, em: int, ea: int, separation: float) -> None:
        """The epoch's Delta (+1 closer), the person's emotions after it and the separation
        to the arm now (m)."""
        self.speed = walking_speed(em, ea)
        if int(delta) != 0:
            band = int(np.searchsorted(self.radii, separation, side='right'))
            aim_band = min(3, max(0, band - int(delta)))
            self.aim = self.targets[aim_band]
            self.reach_target = 1.0 if aim_band <= 1 else 0.0
        else:
            self.aim = None
        if self.rng.random() < WANDER:
            self.theta_target = STATION_ANGLE + STATION_SPREAD * (2 * self.rng.random() - 1)

    def step(self, dt: float, separation: float) -> None:
        """Walk for dt seconds given the separation to the arm now (m)."""
        d_rho = 0.0
        if self.aim is not None:
            error = separation - self.aim
            if abs(error) <= ARRIVED:
                self.aim = None
            else:
                d_rho = -error
        d_arc = (self.theta_target - self.theta) * self.rho
        gap = math.hypot(d_rho, d_arc)
        move = min(gap, self.speed * dt)
        if gap > 1e-9:
            self.rho = min(MAX_STANDOFF, max(MIN_STANDOFF, self.rho + d_rho * move / gap))
            self.theta += (d_arc * move / gap) / self.rho
        self.reach += max(-REACH_RATE * dt, min(REACH_RATE * dt, self.reach_target - self.reach))

    def keypoints(self) -> np.ndarray:
        """The 32 joints (32, 3) in the robot base frame, metres."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        # Columns of the body frame in the base frame: forward (to the base), left, up.
        frame = np.array([[-c, s, 0.0], [-s, -c, 0.0], [0.0, 0.0, 1.0]])
        body = _POSTURE + self.reach * _REACH
        return body @ frame.T + (self.rho * c, self.rho * s, -TABLE_HEIGHT)
