"""What the bridge checks on what is measured, not only on what it commanded (docs/ROBOT.md 3,
"The monitor"): the arm's measured speed against SSM and against the bridge's own commands,
the arm's configuration against the bridge's own path, and the person's skeleton for a sensor
that froze or jumped.

SSM as `ssm.SpeedSeparationMonitor` computes it is a *command*: the speed override of the
bridge's own goal. A goal the bridge did not send (a second publisher on the controller's goal
topic, a controller that resumes an old goal, a teach pendant) runs at its own timing, which
the override (a fraction of that timing) does not bound, and a tracker that keeps sending the
same skeleton with fresh stamps makes stale data look fresh. So the bridge also watches the
result, as a cobot's safety controller supervises the measured joint and TCP speeds whoever
commanded the motion (ISO 10218-1 5.4), and a person sensor used for SSM needs fault detection
of its own (ISO 13849: a stuck sensor must be detected):

- `MeasuredSpeed`: the arm's top link speed from its joint states, from the reported
  velocities and from the positions' finite differences over at least `min_dt` (30 ms: the
  error of a difference is the stamps' jitter over its span, and 0.5 ms of jitter over one 8 ms
  period read as 0.02 m/s of motion), the larger (a driver that reports zero velocities, or
  positions that jump, both count). A difference is the mean speed over its span (`since` to
  the sample), so it is judged against the most the arm was allowed over that span, the reported
  velocity against what it is allowed at the sample: an arm braking as commanded moved faster
  over the last 30 ms than it may move now (before, 1.4 nuisance stops an episode of the honest
  batch cell, each dropping the running goal).
- `SpeedEnvelope`: the speed the bridge's own commands let the arm have at each instant: the
  commanded bound (override x its goal's top link speed at override 1), held for `latency`
  (the command's way to the controller) and then falling at the SSM deceleration (the ramp the
  controller follows); `limit(t, since)` the most it allowed at any instant of [since, t]. A
  measured speed above it plus `tolerance` is motion the bridge did not command.
- `path_deviation`, `across_path`: how far (rad, the largest joint) a configuration lies from
  the bridge's own trajectory, and how fast it moves across it. Its segments are cubic in time
  but straight in joint space (q0 + (q1 - q0) h(u)), so the path is the polyline of its
  waypoints: a configuration off it by more than `path_tolerance`, or links moving across it
  faster than `speed_tolerance`, are on somebody else's goal. The second catches a goal as it
  leaves rest, long before it is far off the path.
- `SkeletonCheck`: a frame whose every keypoint moved less than `frozen_tolerance` since the
  last one brings no new information: the data is as old as the last frame that changed, so
  SSM's age term grows and the arm slows and stops at `human_timeout` (a tracker that froze
  while its stamps advance). A real body tracker jitters by millimetres even when the person
  stands still (Azure Kinect Body Tracking: a few mm), so the default tolerance (0.5 mm) is
  below that noise floor. A frame that puts the person farther from the arm than they can have
  walked since the held one (`max_body_speed` plus `JUMP_SLACK`) is not trusted: it counts
  beside the held body (the nearer wins) until the held one has aged out.
- `JointFreezeCheck`: joint states whose positions moved less than `share` of what their
  velocities, integrated over the last `window` s, say they moved (and more than `gap` less),
  while the last `recent` samples say the arm moves, are a driver that froze (it repeats its
  last state with fresh stamps, with jitter on it, flipping between two states, or with a
  message at rest among them: none of that adds motion along what the velocities claim) or
  whose positions fall ever further behind (the bridge's second check, over a second).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from .arm import Arm, BodyCapsules, _kernels

JUMP_SLACK = 0.05            # m a skeleton may move away on top of max_body_speed * dt (noise)
ENVELOPE_KEPT = 512          # commanded bounds kept for the envelope (each dominated one goes)


class MeasuredSpeed:
    """The arm's top link speed (m/s) from its joint states (module docstring)."""

    def __init__(self, arm: Arm, min_dt: float = 0.03, max_dt: float = 0.1):
        self.arm = arm
        self.min_dt, self.max_dt = float(min_dt), float(max_dt)
        self._history: deque = deque(maxlen=16)     # (stamp ns, q)
        self.speed = 0.0
        self.reported = 0.0
        self.differenced = 0.0
        self.since: int | None = None     # the stamp (ns) the difference spans from, if any
        self.joint_rate = np.zeros(0)     # rad/s per joint from the positions' differences

    def update(self, q, qd, stamp_ns: int) -> float:
        q = np.asarray(q, dtype=float)
        self.reported = self.arm.link_speed(q, qd)
        self.differenced = 0.0
        self.since = None
        self.joint_rate = np.zeros(0)
        history = self._history
        while history and history[-1][0] >= stamp_ns:     # out of order or repeated: restart
            history.pop()
        for then, q_then in reversed(history):
            dt = (stamp_ns - then) * 1e-9
            if dt > self.max_dt:
                break
            if dt >= self.min_dt:
                self.joint_rate = (q - q_then) / dt
                self.differenced = self.arm.link_speed(q, self.joint_rate)
                self.since = int(then)
                break
        history.append((int(stamp_ns), q.copy()))
        self.speed = max(self.reported, self.differenced)
        return self.speed

    def reset(self) -> None:
        self._history.clear()
        self.speed = self.reported = self.differenced = 0.0
        self.since = None
        self.joint_rate = np.zeros(0)


class SpeedEnvelope:
    """The top link speed the bridge's own commands allow the arm at each instant (module
    docstring): each commanded bound holds for `latency` s, then falls at `deceleration`.
    Commands stay `horizon` s after they have decayed to nothing, for spans that reach back."""

    def __init__(self, deceleration: float, latency: float, horizon: float = 0.1):
        self.deceleration = float(deceleration)
        self.latency = float(latency)
        self.horizon = float(horizon)
        self._commands: deque = deque(maxlen=ENVELOPE_KEPT)    # (t ns, bound), bounds falling

    def command(self, now_ns: int, bound: float) -> None:
        """The bridge commands a top link speed `bound` (m/s) at `now_ns`."""
        bound = max(0.0, float(bound))
        commands = self._commands
        while commands and commands[-1][1] <= bound:       # dominated from now on
            commands.pop()
        commands.append((int(now_ns), bound))

    @property
    def newest(self) -> int | None:
        """The time (ns) of the last command, None before any."""
        return self._commands[-1][0] if self._commands else None

    def rebase(self, now_ns: int) -> None:
        """Commands given after `now_ns` (a clock that stepped back left them in its future,
        where each counts whole for as long as the step) are taken as given at `now_ns`: from
        there they hold for the latency and fall at the deceleration, as the arm brakes."""
        self._commands = deque(((min(then, int(now_ns)), bound)
                                for then, bound in self._commands), maxlen=ENVELOPE_KEPT)

    def limit(self, now_ns: int, since_ns: int | None = None) -> float:
        """The fastest the arm may be moving at `now_ns` (m/s), or at any instant from
        `since_ns` to `now_ns`: each command at its highest within the span (a command given
        after `now_ns`, a sample older than the tick, counts whole, as it always did: the
        dominated commands before it are gone)."""
        commands = self._commands
        since = now_ns if since_ns is None else min(int(since_ns), now_ns)
        best = 0.0
        for then, bound in commands:
            best = max(best, bound - self.deceleration
                       * max(0.0, (max(since, then) - then) * 1e-9 - self.latency))
        # the oldest commands that had decayed to nothing `horizon` ago count no more
        past = now_ns - int(self.horizon * 1e9)
        while len(commands) > 1 and commands[0][1] - self.deceleration * max(
                0.0, (past - commands[0][0]) * 1e-9 - self.latency) <= 0.0:
            commands.popleft()
        return best


def path_deviation(q, positions) -> float:
    """The largest joint's distance (rad) from `q` to the polyline through `positions`
    (n, 6): the path of a trajectory whose segments are straight in joint space."""
    return nearest_on_path(q, positions)[0]


def nearest_on_path(q, positions) -> tuple[float, np.ndarray | None]:
    """(`path_deviation`, the unit direction of the path's nearest segment in joint space, None
    for a path of one point: a stay). The projection on each segment minimises the Euclidean
    distance; the limit is on the largest joint, which is at most that distance: the check is
    conservative by at most sqrt(6). A numba loop (`_kernels.path_offset`): it runs on every
    joint state."""
    points = np.ascontiguousarray(positions, dtype=float)
    direction = np.empty(points.shape[1])
    off, segment = _kernels().path_offset(np.ascontiguousarray(q, dtype=float), points, direction)
    if segment < 0:
        return float(off), None
    return float(off), (direction if np.any(direction) else None)


def across_path(rate, direction) -> np.ndarray:
    """The part of a joint velocity `rate` (rad/s) across a path whose local direction is
    `direction` (unit, joint space; None: a stay, where every motion is across)."""
    rate = np.asarray(rate, dtype=float)
    if direction is None:
        return rate
    return rate - direction * float(rate @ direction)


class SkeletonCheck:
    """Is a skeleton of the followed tracker new information, and a plausible one (module
    docstring)? `frozen_tolerance` m, `max_body_speed` m/s."""

    def __init__(self, frozen_tolerance: float = 0.0005, max_body_speed: float = 3.0):
        for name, value in (('frozen_tolerance', frozen_tolerance),
                            ('max_body_speed', max_body_speed)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
        self.frozen_tolerance = float(frozen_tolerance)
        self.max_body_speed = float(max_body_speed)

    def unchanged(self, body: BodyCapsules, held: BodyCapsules) -> bool:
        """True when `body` repeats `held` within frozen_tolerance (a frozen tracker)."""
        if body.segments.shape != held.segments.shape or self.frozen_tolerance <= 0:
            return False
        return bool(np.max(np.abs(body.segments - held.segments)) < self.frozen_tolerance)

    def jumped_away(self, separation_new: float, separation_held: float, dt: float) -> bool:
        """True when a new skeleton puts the person farther from the arm (separations at the
        arm's current configuration) than they can have moved in `dt` s since the held one."""
        if self.max_body_speed <= 0:
            return False
        return separation_new - separation_held > self.max_body_speed * max(dt, 0.0) \
            + JUMP_SLACK


class JointFreezeCheck:
    """The joint states' positions against their velocities over the last `window` s (module
    docstring): `update` with each sample, `reason()` why they are no data ('' while they
    agree, or span less than the window). Samples are kept at least `spacing` s apart and in
    stamp order (one out of order is not kept), so the window holds at most window / spacing
    of them; the velocities' integral is kept as a running sum, so a check costs the same
    at any rate. `tolerance` rad: a claim below it is no claim; `gap` rad: positions that fell
    no further than this behind the claim are not frozen; `rest_speed` rad/s."""

    RESUM = 1024          # samples between recomputing the running sum (its rounding)

    def __init__(self, window: float, rest_speed: float, tolerance: float = 1e-4,
                 share: float = 0.25, spacing: float = 0.001, recent: int = 3, gap: float = 0.0):
        self.window_ns = int(window * 1e9)
        self.rest_speed, self.tolerance, self.share = rest_speed, tolerance, share
        self.gap = gap
        self.spacing_ns, self.recent = int(spacing * 1e9), recent
        self._samples: deque = deque()     # (stamp ns, q, qd, the step into it: qd dt)
        self._claim: np.ndarray | None = None
        self._added = 0

    def clear(self) -> None:
        self._samples.clear()
        self._claim, self._added = None, 0

    def update(self, stamp_ns: int, q: np.ndarray, qd: np.ndarray) -> None:
        samples = self._samples
        if samples and stamp_ns < samples[-1][0] + self.spacing_ns:
            return
        if samples:
            last_t, _, last_qd, _ = samples[-1]
            step = (last_qd + qd) * (0.5e-9 * (stamp_ns - last_t))      # a trapezoid
            self._claim = step if self._claim is None else self._claim + step
        else:
            step = None
        samples.append((int(stamp_ns), q, qd, step))
        horizon = stamp_ns - self.window_ns
        while len(samples) > 2 and samples[1][0] <= horizon:
            samples.popleft()
            self._claim = self._claim - samples[0][3]     # its step came from the one dropped
        self._added += 1
        if self._added >= self.RESUM:
            self._added = 0
            self._claim = np.sum([sample[3] for sample in list(samples)[1:]], axis=0)

    def reason(self) -> str:
        samples = self._samples
        if len(samples) < 2 or samples[-1][0] - samples[0][0] < self.window_ns:
            return ''
        claimed = float(np.linalg.norm(self._claim))
        if claimed <= self.tolerance:
            return ''
        moved = float(np.linalg.norm(samples[-1][1] - samples[0][1]))
        if moved >= self.share * claimed or claimed - moved <= self.gap:
            return ''
        # the velocities must say the arm moves now: a driver whose velocities lag its
        # positions (a low-pass filter) claims motion for a while after the arm came to rest
        fastest = max(float(np.abs(samples[-k][2]).max())
                      for k in range(1, min(self.recent, len(samples)) + 1))
        if fastest <= self.rest_speed:
            return ''
        span = (samples[-1][0] - samples[0][0]) * 1e-9
        return (f'the joint states\' positions moved {moved:.4f} rad in {span:.3f} s where their '
                f'velocities say {claimed:.4f} rad (up to {fastest:.3f} rad/s): a frozen '
                'driver, the arm may be anywhere along its path')


__all__ = ['JUMP_SLACK', 'JointFreezeCheck', 'MeasuredSpeed', 'SkeletonCheck', 'SpeedEnvelope',
           'across_path', 'nearest_on_path', 'path_deviation']
