"""People who test SSM: the cell with the arm's person, honest or hostile, and its tracker.

`hrc-evaluate --cell arm --person SCENARIO` (and `cell_sim_node`'s `person_scenario`) runs the
cell with one of these scenes instead of only today's person (`honest`). A scene is the true
world (every person's body, `bodies`) and what the body tracker reports of it (`frame`); the
cell checks SSM against the true bodies and feeds the bridge the frames. The model's human
(`human.SimulatedHuman`: answers, emotions) reacts to every action as before in every scene; the
scripted people below ignore its Delta while they act.

- `honest`: today's person (`person.SimulatedPerson`): the model's Delta moves them around
  their workstation, at most 1.1 m/s, never nearer the base than the shared table's edge.
- `walk_in`: a person who comes into the cell and walks straight at the arm at 1.6 m/s (ISO
  13855's whole-body approach speed, SSM's v_h) until they touch its capsules (separation
  `TOUCH`) or stand at its base, stays `DWELL` s and walks back out at `LEAVE_SPEED`. They
  start standing `START_RANGE` m from the base, from any side, hands forward, and set off at a
  moment drawn in `EVENT_WINDOW`.
- `run_in`: the same at 2.0 m/s everywhere (faster than SSM's 1.6 m/s beyond 0.5 m).
- `appear`: a second person appears within `APPEAR_SEPARATION` m of the arm's links (from
  behind the arm, occluded until then), stays `DWELL` s and walks away. The SSM check counts
  the samples from the appearance until the arm is at rest apart (`appearance` violations):
  no monitor can stop in time for a person who appears inside S_p(0); what it owes is a quick
  protective stop once the skeleton arrives.
- `reach`: a person standing at the shared table's edge, hands down, leans over the table and
  reaches with the right hand at the arm's nearest point at 2.0 m/s (ISO 13855's approach speed
  within 0.5 m), holds `DWELL` / 2 s and draws back at `LEAVE_SPEED`.
- `frozen_tracker`: a walk-in whose tracker freezes mid-walk: frames keep coming with fresh
  stamps and the same keypoints for `FAULT_TIME` s while the person walks on.
- `lost_tracker`: a walk-in whose tracker stops mid-walk: no frames for `FAULT_TIME` s.

**The tracker** reports every body in view with `TRACKER_NOISE` m of Gaussian noise per
keypoint coordinate: a real body tracker jitters by millimetres even when the person stands
still (Azure Kinect Body Tracking's joint error is a few mm), and the bridge takes a frame
that repeats the last one exactly as a frozen tracker's (`robot.guard.SkeletonCheck`).

No point of a scripted body moves faster than its scenario says (the walk is radial, the
posture fixed, the reach paced by its fastest keypoint). Keypoints are the 32 Azure Kinect
joints of each body in view (`tracking.K4ABT_JOINTS` order), in the robot base frame.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from .person import MIN_STANDOFF, SimulatedPerson
from .tracking import JOINT_INDEX

SCENARIOS = ('honest', 'walk_in', 'run_in', 'appear', 'reach', 'frozen_tracker',
             'lost_tracker')
TRACKER_NOISE = 0.0015          # m, standard deviation per keypoint coordinate
EVENT_WINDOW = (2.0, 0.5)       # the event starts in [2 s, half the episode]
START_RANGE = (2.0, 3.5)        # m from the base axis: where a walk-in starts
WALK_SPEED = {'walk_in': 1.6, 'run_in': 2.0, 'frozen_tracker': 1.6, 'lost_tracker': 1.6}
REACH_SPEED = 2.0               # m/s of the fastest keypoint of a reach
REACH_LEAN = 0.25               # m the upper body leans over the table in a reach
TOUCH = 0.05                    # m: a walk-in stops at this separation to the arm's capsules
MIN_RHO = 0.3                   # m: nor nearer the base axis (the pelvis)
DWELL = 2.0                     # s a scripted person stays at the arm
LEAVE_SPEED = 1.0               # m/s walking back out
APPEAR_SEPARATION = 0.25        # m: how close to the arm's links a person appears
FAULT_TIME = 3.0                # s a tracker fault lasts
UPPER_BODY = tuple(JOINT_INDEX[n] for n in (
    'spine_chest', 'neck', 'head', 'nose', 'eye_left', 'eye_right', 'ear_left', 'ear_right',
    'clavicle_left', 'clavicle_right', 'shoulder_left', 'shoulder_right', 'elbow_left',
    'wrist_left', 'hand_left', 'handtip_left', 'thumb_left', 'elbow_right', 'wrist_right',
    'hand_right', 'handtip_right', 'thumb_right'))
RIGHT_ARM = {name: JOINT_INDEX[f'{name}_right'] for name in
             ('elbow', 'wrist', 'hand', 'handtip', 'thumb')}
ARM_LENGTHS = {'elbow': 0.30, 'wrist': 0.55, 'hand': 0.62, 'handtip': 0.72, 'thumb': 0.64}

# probe(keypoints of one body (32, 3)) -> (separation m, closest arm point (3,)) at the arm now
Probe = Callable[[np.ndarray], tuple]


def check_scenario(name: str) -> str:
    if name not in SCENARIOS:
        raise ValueError(f'unknown person scenario {name!r}; expected one of '
                         f'{", ".join(SCENARIOS)}')
    return name


class Scene:
    """The true world of one episode and its tracker (module docstring). `begin_epoch` takes
    the model's reaction as `SimulatedPerson` does, `step(dt, t, probe)` moves everyone, and
    `bodies()` / `frame(t)` give the truth and the tracker's report at time t."""

    name = 'honest'

    def __init__(self, band: int, seed, em: int = 0, ea: int = 0, radii=(0.2, 0.6, 1.2),
                 duration: float = 50.0):
        self.person = SimulatedPerson(band, seed=seed, em=em, ea=ea, radii=radii)
        self.rng = np.random.default_rng([*np.atleast_1d(seed).tolist(), 7])
        self.duration = float(duration)
        low, high = EVENT_WINDOW[0], max(EVENT_WINDOW[0], EVENT_WINDOW[1] * self.duration)
        self.event = float(self.rng.uniform(low, high))     # drawn in every scene alike
        self.scripted = False         # the model's Delta does not move the person now

    def begin_epoch(self, delta: int, em: int, ea: int, separation: float) -> None:
        if not self.scripted:
            self.person.begin_epoch(delta, em, ea, separation)

    def step(self, dt: float, t: float, probe: Probe, separation: float | None = None) -> None:
        """Move everyone for dt s at time t; `separation`: the true separation of `bodies()`
        to the arm if the caller has it (saves a probe)."""
        if separation is None:
            separation = probe(self.person.keypoints())[0]
        self.person.step(dt, separation)

    def bodies(self) -> np.ndarray:
        return self.person.keypoints()

    def frame(self, t: float) -> np.ndarray | None:
        truth = self.bodies()
        return truth + self.rng.normal(0.0, TRACKER_NOISE, truth.shape)

    appears = False       # a person appears in this scene (the appearance exception)

    @property
    def appeared(self) -> float | None:
        """When a person appeared inside the cell (the `appear` scene), else None."""
        return None


class WalkIn(Scene):
    """walk_in, run_in, frozen_tracker, lost_tracker (module docstring)."""

    def __init__(self, name: str, band: int, seed, **kwargs):
        super().__init__(band, seed, **kwargs)
        self.name = name
        self.speed = WALK_SPEED[name]
        self.home = float(self.rng.uniform(*START_RANGE))
        self.person.rho = self.home
        self.person.theta = self.person.theta_target = float(self.rng.uniform(-math.pi, math.pi))
        self.person.reach = self.person.reach_target = 1.0        # hands forward
        self.scripted = True
        self.phase = 'waiting'        # waiting, walking, dwelling, leaving, standing
        self.phase_since = 0.0
        walk_time = max(0.2, (self.home - 0.6) / self.speed)
        self.fault = None
        if name in ('frozen_tracker', 'lost_tracker'):
            self.fault = self.event + float(self.rng.uniform(0.2, 0.8)) * walk_time
        self._last_frame: np.ndarray | None = None

    def step(self, dt: float, t: float, probe: Probe, separation: float | None = None) -> None:
        p = self.person
        if self.phase == 'waiting' and t >= self.event:
            self.phase, self.phase_since = 'walking', t
        if self.phase == 'walking':
            near = separation if separation is not None else probe(p.keypoints())[0]
            if near <= TOUCH or p.rho <= MIN_RHO:
                self.phase, self.phase_since = 'dwelling', t
            else:
                p.rho = max(MIN_RHO, p.rho - self.speed * dt)
        elif self.phase == 'dwelling' and t - self.phase_since >= DWELL:
            self.phase = 'leaving'
        elif self.phase == 'leaving':
            p.rho = min(self.home, p.rho + LEAVE_SPEED * dt)
            if p.rho >= self.home:
                self.phase = 'standing'

    def frame(self, t: float) -> np.ndarray | None:
        if self.fault is not None and self.fault <= t < self.fault + FAULT_TIME:
            if self.name == 'lost_tracker' or self._last_frame is None:
                return None
            return self._last_frame            # the same keypoints, a fresh stamp
        self._last_frame = super().frame(t)
        return self._last_frame


class Appear(Scene):
    """appear (module docstring): today's person, and a second one who appears by the arm."""

    name = 'appear'
    appears = True

    def __init__(self, band: int, seed, **kwargs):
        super().__init__(band, seed, **kwargs)
        self.second: SimulatedPerson | None = None
        self.since = None
        self.leaving = False

    @property
    def appeared(self) -> float | None:
        return self.since

    def step(self, dt: float, t: float, probe: Probe, separation: float | None = None) -> None:
        super().step(dt, t, probe, None if self.second is not None else separation)
        if self.second is None and t >= self.event:
            self.second = self._place(probe)
            self.since = t
        elif self.second is not None:
            if not self.leaving and t - self.since >= DWELL:
                self.leaving = True
            if self.leaving:
                self.second.rho = min(START_RANGE[1], self.second.rho + LEAVE_SPEED * dt)

    def _place(self, probe: Probe) -> SimulatedPerson:
        """A body facing the base on the radial line through the arm's nearest point to
        today's person, at the distance from the base where it comes APPEAR_SEPARATION m from
        the arm's capsules (bisection)."""
        body = SimulatedPerson(3, seed=self.rng.integers(1 << 31))
        _, point = probe(self.person.keypoints())
        body.theta = body.theta_target = math.atan2(point[1], point[0])
        body.reach = body.reach_target = 1.0
        low, high = MIN_RHO, START_RANGE[1]
        body.rho = high
        if probe(body.keypoints())[0] > APPEAR_SEPARATION:
            for _ in range(30):
                body.rho = 0.5 * (low + high)
                if probe(body.keypoints())[0] > APPEAR_SEPARATION:
                    high = body.rho
                else:
                    low = body.rho
            body.rho = low
        return body

    def bodies(self) -> np.ndarray:
        if self.second is None:
            return self.person.keypoints()
        return np.vstack([self.person.keypoints(), self.second.keypoints()])


class Reach(Scene):
    """reach (module docstring): today's person reaches over the table at the arm."""

    name = 'reach'

    def __init__(self, band: int, seed, **kwargs):
        super().__init__(band, seed, **kwargs)
        self.person.rho = MIN_STANDOFF       # at the table's edge, hands down
        self.person.reach = self.person.reach_target = 0.0
        self.scripted = True
        self.phase = 'waiting'
        self.phase_since = 0.0
        self.r = 0.0                          # 0: as the person stands, 1: reached out
        self.rate_out = self.rate_back = 0.0
        self._rest: np.ndarray | None = None  # the posture the reach starts from
        self._out: np.ndarray | None = None   # reached out

    def step(self, dt: float, t: float, probe: Probe, separation: float | None = None) -> None:
        if self.phase == 'waiting':
            if t >= self.event:
                self._aim(probe)
                self.phase = 'out'
            return
        if self.phase == 'out':
            self.r = min(1.0, self.r + self.rate_out * dt)
            if self.r >= 1.0:
                self.phase, self.phase_since = 'holding', t
        elif self.phase == 'holding' and t - self.phase_since >= DWELL / 2:
            self.phase = 'back'
        elif self.phase == 'back':
            self.r = max(0.0, self.r - self.rate_back * dt)
            if self.r <= 0.0:
                self.phase = 'done'

    def _aim(self, probe: Probe) -> None:
        rest = self.person.keypoints()
        _, target = probe(rest)
        out = rest.copy()
        toward = np.asarray(target, dtype=float) - rest[JOINT_INDEX['pelvis']]
        toward[2] = 0.0
        lean = REACH_LEAN * toward / max(np.linalg.norm(toward), 1e-9)
        out[list(UPPER_BODY)] += lean
        shoulder = out[JOINT_INDEX['shoulder_right']]
        direction = np.asarray(target, dtype=float) - shoulder
        direction /= max(np.linalg.norm(direction), 1e-9)
        for name, index in RIGHT_ARM.items():
            out[index] = shoulder + ARM_LENGTHS[name] * direction
        fastest = float(np.max(np.linalg.norm(out - rest, axis=1)))
        self.rate_out = REACH_SPEED / max(fastest, 1e-9)
        self.rate_back = LEAVE_SPEED / max(fastest, 1e-9)
        self._rest, self._out = rest, out

    def bodies(self) -> np.ndarray:
        if self.phase in ('waiting', 'done') or self._rest is None:
            return self.person.keypoints()
        return self._rest + self.r * (self._out - self._rest)


def make_scene(name: str, band: int, seed, **kwargs) -> Scene:
    """The scene of scenario `name` (module docstring) for one episode."""
    check_scenario(name)
    if name == 'honest':
        return Scene(band, seed, **kwargs)
    if name == 'appear':
        return Appear(band, seed, **kwargs)
    if name == 'reach':
        return Reach(band, seed, **kwargs)
    return WalkIn(name, band, seed, **kwargs)


__all__ = ['SCENARIOS', 'Scene', 'TRACKER_NOISE', 'check_scenario', 'make_scene']
