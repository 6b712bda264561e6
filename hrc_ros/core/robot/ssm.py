"""Speed and separation monitoring (ISO/TS 15066:2016, 5.5.4) as pure functions and one
sans-IO monitor.

The protective separation distance at time t0 is

    S_p = S_h + S_r + S_s + C + Z_d + Z_r                                    (ISO/TS 15066 eq. 1)

    S_h = the person's travel while the robot reacts and stops, v_h (T_r + T_s)
    S_r = the robot's travel during its reaction time,           v_r T_r
    S_s = the robot's stopping distance from speed v_r
    C   = intrusion distance (a body part reaching past what is sensed, ISO 13855)
    Z_d = the person's position uncertainty (the sensor), Z_r = the robot's

SSM holds while the separation S (closest point of the person's body to the robot's links) is
at least S_p for the robot's current speed v_r. The monitor below turns that into a speed
limit: the largest v_r with S_p(v_r) <= S, the speed override v_r / v_nominal in [0, 1] for the
running motion, and a protective stop when even the slowest motion the controller still makes
(`min_speed`) is too fast, or when the human data is older than `human_timeout` (the person
may be anywhere).

**Stopping model** (constant deceleration a, the brake ramp every stop of this package follows,
`arm.TrajectoryFollower`): from speed v_r the robot stops in T_s = v_r / a over
S_s = v_r^2 / (2 a). A robot maker's stopping data (ISO 10218-1 annex B: stopping time and
distance per joint, speed, extension and payload; the UR5e's user manual tabulates them) give
a as the worst case v / T_s over the tables; `SsmParameters.from_stopping_time` takes that
form. a is the deceleration of the fastest point of the links, the quantity v_r measures.

**The person's speed** (ISO 13855, 6.2-6.3: K = 1600 mm/s for a whole-body approach, 2000 mm/s
for an approach closer than 500 mm). Modelled, continuously: the person walks at
v_h = 1.6 m/s until they are within `near_distance` = 0.5 m, then reaches at
v_near = 2.0 m/s. Their worst-case travel within a time T from a separation S is

    w = max(S - 0.5, 0);  D(S, T) = v_h T                    if v_h T <= w   (still walking)
                          D(S, T) = w + v_near (T - w / v_h) otherwise       (then reaching)

so S_h = D(S, T_r + T_s); far from the robot (v_h (T_r + T_s) <= S - 0.5) this is ISO/TS
15066's S_h = 1.6 (T_r + T_s) exactly, and S_p never jumps at 0.5 m as a switch of v_h would.
`near_distance = 0` gives the single speed v_h everywhere.

**Time since the data** (what a monitor fed by a sensor must add). S is measured from the
skeleton captured at its stamp and the arm's current joint state, and the override holds until
the next update. In the data's age plus the hold the person may have moved in a way the data
does not show, at up to `human_speed_near` (ISO 13855's fastest approach, a reach at 2.0 m/s:
a hand can come at that speed from farther than 0.5 m too, faster than the 1.6 m/s walk the
standard assumes there), so the monitor takes them nearer by that reach, R = v_near (age + dt),
and ISO's S_p from there, the robot moving for one control period more:

    S_p(v) = R + D(S - R, T_r + T_s(v)) + v (T_r + dt) + v^2 / (2 a) + C + Z_d + Z_r,

and the check of a sample (`ssm_violated`: the true separation at that instant, age = dt = 0)
is ISO/TS 15066's formula as written. (Before, the age and the hold were added to the
person's time at the regime's speed, D(S, T_r + age + dt + T_s): a reach at 2.0 m/s from 0.8 m
came 0.4 m/s x age nearer than that allowed, and the batch's reach scenario broke SSM by up to
3.5 cm.)

**Largest speed** (closed form). f(v) = S_p(v) - S is continuous and strictly increasing in
v; in each regime of D it is the quadratic A v^2 + B v + K with A = 1 / (2 a) and

    walking:  B = v_h / a + T_rob,     K = v_h T_hum + M - S
    reaching: B = v_near / a + T_rob,  K = w + v_near (T_hum - w / v_h) + M - S

(T_hum = T_r, T_rob = T_r + dt, M = C + Z_d + Z_r, S the separation less R). The regimes
meet at v_w = a (w / v_h - T_hum): the largest safe speed is the walking root if it is <= v_w,
else the reaching root, v = (-B + sqrt(B^2 - 4 A K)) / (2 A); none (K > 0 at v = 0) is a stop.

Parameters (metres, seconds; `SsmParameters`; docs/ROBOT.md has their sources in full):

- `reaction_time` T_r = 0.1 s: from the monitor's decision to the start of braking (the
  controller's cycle, the drives); the sensing delay is the data's age, added per sample. A
  placeholder: measure it on the cell (ISO/TS 15066 5.5.4.2.3).
- `deceleration` a = 2.0 m/s^2 of the links in a stop (1 m/s, the UR5e's tool speed limit,
  stops in 0.5 s over 0.25 m). A placeholder: take the arm's stopping data.
- `intrusion` C = 0.05 m: fingers beyond the tracked hand tip (the body is capsules over the
  skeleton, so ISO 13855's reach allowances for a sensing field do not apply).
- `human_uncertainty` Z_d = 0.05 m (body tracking's joint error), `robot_uncertainty` Z_r =
  0.01 m (the capsule model, the encoders).
- `human_speed` 1.6 m/s, `human_speed_near` 2.0 m/s within `near_distance` 0.5 m: ISO 13855.
- `min_speed` 0.02 m/s: slower is a protective stop (creeping does no work).
- `human_timeout` 0.5 s without human data: protective stop (15 frames at 30 Hz).
- `resume_time` 0.2 s: a protective stop clears once motion has been allowed this long.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

MOVING_SPEED = 1e-3     # m/s: a link speed below this is an arm at rest (no SSM check due)


@dataclass(frozen=True)
class SsmParameters:
    """The parameters of speed and separation monitoring (see the module docstring)."""

    reaction_time: float = 0.1
    deceleration: float = 2.0
    intrusion: float = 0.05
    human_uncertainty: float = 0.05
    robot_uncertainty: float = 0.01
    human_speed: float = 1.6
    human_speed_near: float = 2.0
    near_distance: float = 0.5
    min_speed: float = 0.02
    human_timeout: float = 0.5
    resume_time: float = 0.2

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) \
                    or not math.isfinite(value) or value < 0:
                raise ValueError(f'SSM parameter {f.name} must be a finite number >= 0 (metres, '
                                 f'seconds), got {value!r}')
        for name in ('deceleration', 'human_speed', 'human_timeout'):
            if getattr(self, name) <= 0:
                raise ValueError(f'SSM parameter {name} must be > 0, got {getattr(self, name)!r}')
        if self.human_speed_near < self.human_speed:
            raise ValueError(f'SSM parameter human_speed_near ({self.human_speed_near}) must be '
                             f'at least human_speed ({self.human_speed}): a person reaches no '
                             'slower than they walk')

    @classmethod
    def from_stopping_time(cls, stopping_time: float, speed: float, **others) -> SsmParameters:
        """Parameters whose deceleration stops `speed` (m/s) in `stopping_time` (s): a robot
        maker's stopping data read as a = speed / stopping_time."""
        if not (stopping_time > 0 and speed > 0):
            raise ValueError(f'stopping_time and speed must be > 0, got {stopping_time!r}, '
                             f'{speed!r}')
        return cls(deceleration=speed / stopping_time, **others)

    @classmethod
    def from_mapping(cls, values) -> SsmParameters:
        """From a YAML mapping of the field names; unknown names are refused by name."""
        if values is None:
            return cls()
        if not isinstance(values, dict):
            raise ValueError(f'ssm must be a mapping of parameters, got {values!r}')
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f'unknown SSM parameters {unknown}; known: '
                             f'{", ".join(sorted(known))}')
        return cls(**values)

    @property
    def margin(self) -> float:
        """C + Z_d + Z_r (m)."""
        return self.intrusion + self.human_uncertainty + self.robot_uncertainty


def directed_speeds(p: SsmParameters, approach: float) -> SsmParameters:
    """The parameters with the person's speeds raised to a measured directed speed toward the
    robot where it exceeds them: ISO/TS 15066 5.5.4.2.2 takes v_h as the operator's directed
    speed, ISO 13855's 1.6 m/s (2.0 m/s within 0.5 m) when it is not measured. A person
    measured coming faster (a run at the arm, a fast reach) is planned for at that speed."""
    if not approach > p.human_speed:           # (NaN: not measured)
        return p
    return replace(p, human_speed=float(approach),
                   human_speed_near=max(p.human_speed_near, float(approach)))


def _is_scalar(*values) -> bool:
    for v in values:
        if not isinstance(v, (int, float)):
            return False
    return True


def human_travel(separation, time, p: SsmParameters):
    """D(S, T): how far the person can come within `time` s from `separation` m (walking at
    v_h, reaching at v_near inside `near_distance`). Broadcasts."""
    if _is_scalar(separation, time):
        w = max(separation - p.near_distance, 0.0)
        walk = p.human_speed * time
        return walk if walk <= w else w + p.human_speed_near * (time - w / p.human_speed)
    w = np.maximum(np.asarray(separation, dtype=float) - p.near_distance, 0.0)
    walk = p.human_speed * np.asarray(time, dtype=float)
    reach = w + p.human_speed_near * (time - w / p.human_speed)
    return np.where(walk <= w, walk, reach)


def unseen_reach(p: SsmParameters, age: float = 0.0, period: float = 0.0) -> float:
    """How much nearer the person may be than the data shows (m): they may have moved at
    `human_speed_near` (ISO 13855's fastest approach, a reach) for the data's age and the
    command's hold (module docstring, "Time since the data")."""
    return p.human_speed_near * (age + period)


def protective_distance(speed, separation, p: SsmParameters, age: float = 0.0,
                        period: float = 0.0):
    """S_p (m) for robot speed `speed` (m/s) at separation `separation` (m), with the human
    data `age` s old and the command held for `period` s (module docstring). Broadcasts."""
    v = speed if _is_scalar(speed) else np.asarray(speed, dtype=float)
    stop_time = v / p.deceleration
    reach = unseen_reach(p, age, period)
    return (reach + human_travel(separation - reach, p.reaction_time + stop_time, p)
            + v * (p.reaction_time + period) + v * v / (2.0 * p.deceleration) + p.margin)


def _root(a: float, b: float, k: float) -> float:
    """The non-negative root of v^2 / (2 a) + b v + k = 0 (k <= 0)."""
    return a * (-b + math.sqrt(b * b - 2.0 * k / a))


def max_speed(separation: float, p: SsmParameters, age: float = 0.0,
              period: float = 0.0) -> float | None:
    """The largest robot speed v_r (m/s) with S_p(v_r) <= S, in closed form; None when no
    speed is safe (S < S_p(0): the robot must stand still)."""
    s = float(separation)
    if not math.isfinite(s):
        raise ValueError(f'separation must be a finite number of metres, got {separation!r}')
    a = p.deceleration
    s -= unseen_reach(p, age, period)      # where the person may be by the hold's end
    t_hum = p.reaction_time
    t_rob = p.reaction_time + period
    w = max(s - p.near_distance, 0.0)
    v_switch = a * (w / p.human_speed - t_hum)
    if v_switch >= 0.0:
        k = p.human_speed * t_hum + p.margin - s
        if k > 0:
            return None
        v = _root(a, p.human_speed / a + t_rob, k)
        if v <= v_switch:
            return v
    k = w + p.human_speed_near * (t_hum - w / p.human_speed) + p.margin - s
    if k > 0:
        return None
    return _root(a, p.human_speed_near / a + t_rob, k)


BRAKING_STEP = 0.02      # s between the look-ahead times of `braking_speed`
BRAKING_HORIZON = 0.4    # s: the look-ahead's last time
# The look-ahead binds only where the allowed speed falls faster than the robot brakes, below
# a quarter of v_near (0.42 m/s at most with ISO's speeds, never with a directed speed: the
# grid of test_robot.py); above this it is max_speed itself and is not computed.
BRAKING_SKIP = 0.25
BRAKING_SKIP_MARGIN = 0.1


def braking_speed(separation: float, p: SsmParameters, age: float = 0.0,
                  period: float = 0.0) -> float | None:
    """The largest speed the robot may have now so that, braking at `deceleration`, it stays
    within `max_speed` at every separation the person can bring about while it brakes, coming
    at `human_speed_near`: min over tau of max_speed(S - v_near tau) + a tau (0 where no speed
    is safe). Near 0.5 m the allowed speed falls faster than the robot can brake (ISO 13855's
    switch to 2.0 m/s makes the person's assumed travel grow as S falls); a command of
    max_speed(S) alone then leaves the robot behind it (the batch's reach scenario: S < S_p by
    1-2 mm). Far away it is max_speed(S) itself. None when max_speed(S) is."""
    now = max_speed(separation, p, age, period)
    if now is None or now >= BRAKING_SKIP * p.human_speed_near + BRAKING_SKIP_MARGIN:
        return now           # (it binds only below a quarter of v_near: test_robot.py)
    best = now
    a = p.deceleration
    for k in range(1, int(round(BRAKING_HORIZON / BRAKING_STEP)) + 1):
        tau = k * BRAKING_STEP
        if a * tau >= best:
            break                       # no later separation can lower it further
        later = max_speed(separation - p.human_speed_near * tau, p, age, period) or 0.0
        best = min(best, later + a * tau)
    return best


def speed_override(allowed: float | None, nominal: float) -> float:
    """The override in [0, 1] that keeps a motion whose top link speed at override 1 is
    `nominal` (m/s) at or below `allowed` (None: 0)."""
    if allowed is None:
        return 0.0
    if nominal <= 0.0:
        return 1.0
    return min(1.0, allowed / nominal)


def ssm_violated(separation, speed, p: SsmParameters):
    """True where a sample breaks SSM: the arm moves (`speed` > MOVING_SPEED) while the
    separation is below S_p at that speed (ISO/TS 15066's formula, the true separation)."""
    if _is_scalar(separation, speed):
        return speed > MOVING_SPEED and separation < protective_distance(speed, separation, p)
    s = np.asarray(separation, dtype=float)
    v = np.asarray(speed, dtype=float)
    return (v > MOVING_SPEED) & (s < protective_distance(v, s, p))


@dataclass(frozen=True)
class SsmState:
    """What the monitor allows now: the override of the running motion (0..1), the speed
    limit (m/s, None: none is safe), S_p at the allowed speed, and a protective stop with its
    reason ('' when none)."""

    override: float
    allowed_speed: float | None
    protective_distance: float | None
    separation: float | None
    stop: bool
    reason: str


class SpeedSeparationMonitor:
    """Sans-IO SSM: fed the separation with the stamp of the human data it came from and the
    clock, it says how fast the running motion may go.

    `update(separation, human_stamp_ns, now_ns, nominal_speed)` returns an `SsmState`.
    `separation` None means no human data is held. The state is a protective stop when the
    data is older than `human_timeout` (or missing), or when the allowed speed is below
    `min_speed`; a stop clears only after motion has been allowed for `resume_time`. Times
    are integer nanoseconds of one clock (the node's); `period` is the control period the
    override is held for (s).
    """

    def __init__(self, parameters: SsmParameters | None = None, period: float = 0.01):
        self.p = parameters or SsmParameters()
        if not (math.isfinite(period) and period >= 0):
            raise ValueError(f'period must be a finite number of seconds >= 0, got {period!r}')
        self.period = float(period)
        self.stopped = True            # no data yet: the arm stands until it has some
        self.reason = 'no human data yet'
        self._clear_since: int | None = None

    def update(self, separation: float | None, human_stamp_ns: int | None, now_ns: int,
               nominal_speed: float, approach: float = 0.0) -> SsmState:
        """`approach`: the person's measured directed speed toward the arm (m/s, 0: none
        measured); where it exceeds the parameters' speeds it takes their place
        (`directed_speeds`)."""
        p = directed_speeds(self.p, approach)
        allowed = bound = None
        if separation is None or human_stamp_ns is None:
            reason = 'no human data yet' if self.reason == 'no human data yet' else \
                'no human data'
        else:
            age = max(0.0, (now_ns - human_stamp_ns) * 1e-9)
            if age > p.human_timeout:
                reason = (f'human data {age:.2f} s old (human_timeout {p.human_timeout} s): '
                          'the person may be anywhere')
            else:
                allowed = braking_speed(separation, p, age, self.period)
                reason = ''
                if allowed is None or allowed < p.min_speed:
                    least = protective_distance(p.min_speed, separation, p, age, self.period)
                    reason = (f'separation {separation:.3f} m below the protective distance '
                              f'{least:.3f} m at the slowest motion ({p.min_speed} m/s)')
                else:
                    bound = protective_distance(allowed, separation, p, age, self.period)
        if reason:
            self.stopped = True
            self.reason = reason
            self._clear_since = None
        elif self.stopped:
            if self._clear_since is None:
                self._clear_since = now_ns
            if (now_ns - self._clear_since) * 1e-9 >= p.resume_time:
                self.stopped = False
                self.reason = ''
        if self.stopped:
            return SsmState(0.0, allowed, bound, separation, True, self.reason)
        return SsmState(speed_override(allowed, nominal_speed), allowed, bound, separation,
                        False, '')
