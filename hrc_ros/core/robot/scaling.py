"""The speed override onto a controller's speed scaling: the logic of `speed_scaling_node`
(docs/ROBOT.md 3, "Speed override onto a real arm"), here so that it runs and is tested where
`control_msgs` (whose `SpeedScalingFactor` the node publishes) is not installed.

The bridge publishes the override (std_msgs/Float64, 0..1, reliable, volatile) with every tick
of SSM. ros2_controllers' joint_trajectory_controller with speed scaling reads
`~/speed_scaling_input` as control_msgs/msg/SpeedScalingFactor (`factor`, 1.0 normal speed, 0.0 a
full pause), reliable and transient local, and keeps the last factor it got. So the factor it
holds must never outlive the override it came from: `ScalingAdapter` turns each override into a
factor and falls to 0 (the arm pauses on its path) when

- no override has come yet (a controller that starts before the bridge holds),
- the last one is older than `timeout` (the bridge or the link stopped: SSM cannot act),
- the value is no finite number (NaN, +-inf): 0, counted as refused,
- a second writer publishes overrides (`core.protocol.SingleWriter`: which one is right is
  unknown, so the arm holds until the other has been silent for `SECOND_WRITER_HOLD`).

A finite value outside [0, 1] is clamped (and counted): below 0 is a pause, above 1 would run
the trajectory faster than it was planned, which SSM never allows. The factor goes out with
every override and every watchdog tick, changed or not: the controller keeps the last factor
it got from anyone, and a value another node writes to its topic (one forged `factor: 1.0`
while the bridge holds the arm at 0) must not outlive the next tick (it published only changes
before: a held 0 was never sent again, and the forged 1.0 ran the paused goal). The topic is
transient local: a controller that joins later gets the last one. Times are seconds of one
monotonic clock.
"""

from __future__ import annotations

import math

from ..protocol import InputError, SingleWriter

# s without an override before the factor is 0: the bridge's SSM plans each override for its
# control period plus command_latency (0.03 s), so an older one must not drive the arm; the
# same as cobot_sim's override_timeout
DEFAULT_TIMEOUT = 0.03
SECOND_WRITER_HOLD = 1.0        # s a second override writer holds the arm after its last value
# s the followed override writer may be silent before another is followed: not the timeout
# (a 30 ms gap in the bridge's overrides, common under load, would hand the line to another
# writer unflagged)
WRITER_SILENCE = 0.1


def safe_factor(value) -> float:
    """The scaling factor of an override value: a finite number clamped to [0, 1]; anything
    else (NaN, +-inf, not a number) is 0, a pause."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return 0.0
    if not math.isfinite(number):
        return 0.0
    return min(1.0, max(0.0, number))


class ScalingAdapter:
    """Overrides in, scaling factors out (module docstring). `start`, `override` and `tick`
    return the factor to publish now (every time: module docstring)."""

    def __init__(self, timeout: float = DEFAULT_TIMEOUT, what: str = 'the speed override'):
        if not (isinstance(timeout, (int, float)) and math.isfinite(timeout) and timeout > 0):
            raise ValueError(f'timeout must be a positive number of seconds, got {timeout!r}')
        self.timeout = float(timeout)
        self.factor: float | None = None       # the last published (None: none yet)
        self.heard_at: float | None = None     # the last override of the followed writer
        self.reason = 'no override received yet'
        self.writers = SingleWriter(what, max(self.timeout, WRITER_SILENCE), SECOND_WRITER_HOLD)
        self.received = self.refused = self.clamped = self.timeouts = self.second_writer = 0

    @property
    def watchdog_period(self) -> float:
        """s between the node's watchdog ticks: an override is dropped at most this long after
        `timeout` (with the 0.03 s default, 37.5 ms in all: within the 40 ms of control period
        and command latency that the bridge's SSM plans each override for)."""
        return min(self.timeout / 4, 0.05)

    def start(self) -> float:
        """The factor to publish at start: 0, until an override says otherwise."""
        return self._set(0.0, self.reason)

    def override(self, value, now: float, sequence: int | None = None) -> float:
        """An override of the bridge's (its publication sequence number, if known)."""
        self.received += 1
        try:
            self.writers.check(sequence, now)
        except InputError:
            self.second_writer += 1
            return self._set(0.0, self.writers.reason)
        self.heard_at = now
        factor = safe_factor(value)
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        if not math.isfinite(number):
            self.refused += 1
            return self._set(0.0, f'the override {value!r} is no finite number')
        if factor != number:
            self.clamped += 1
        if self.writers.held(now):
            return self._set(0.0, self.writers.reason)
        return self._set(factor, '' if factor > 0 else 'the override is 0')

    def tick(self, now: float) -> float:
        """The watchdog, called at least every `timeout`: the factor again, 0 once the
        override is too old."""
        if self.heard_at is None:
            return self._set(0.0, 'no override received yet')
        if now - self.heard_at > self.timeout:
            if self.factor:
                self.timeouts += 1
            return self._set(0.0, f'no override for {now - self.heard_at:.3f} s (more than '
                                  f'{self.timeout:g} s)')
        if self.writers.held(now):
            return self._set(0.0, self.writers.reason)
        return self.factor

    def _set(self, factor: float, reason: str) -> float:
        self.reason, self.factor = reason, factor
        return factor

    def values(self, now: float) -> dict:
        """The figures of the node's status."""
        return {'factor': self.factor, 'held_because': self.reason,
                'override_age_s': None if self.heard_at is None else now - self.heard_at,
                'timeout_s': self.timeout, 'received': self.received, 'refused': self.refused,
                'clamped': self.clamped, 'timeouts': self.timeouts,
                'second_writer_values': self.second_writer}
