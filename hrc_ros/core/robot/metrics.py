"""The figures of a cell with the arm, defined once: `hrc-evaluate --cell arm` (`cell`) and the
operator's console (`core.hmi.shift`) both count with these.

- the arm's time: a control sample is in a **protective stop** when SSM (the bridge) stops the
  arm; otherwise **idle** when the arm is at rest, its speed bound (the override times the
  goal's top link speed) at most `ssm.MOVING_SPEED`; otherwise **moving**. The idle share and
  the protective-stop share are per cent of the time measured;
- **tasks per hour**: tasks completed per hour of cell time;
- **refused requests**: eligible requests (rh1 / rh2) answered no; a request left unanswered
  is taken as refused by the task manager (docs/DESIGN.md) and counts too;
- **minimum separation**: the smallest separation S (m) of the person from the arm's links
  over the samples;
- **fail-safe epochs**: epochs in which the decision layer failed safe (`dn` forced: d = 0,
  a missing, stale or malformed input).

They take numbers or numpy arrays alike (the batch computes them over arrays of episodes).
"""

from __future__ import annotations

from .ssm import MOVING_SPEED

STOP, IDLE, MOVING = 'stop', 'idle', 'moving'
SECONDS_PER_HOUR = 3600.0


def arm_activity(stop: bool, speed_bound: float) -> str:
    """What the arm does in one sample: STOP (a protective stop), IDLE (at rest) or MOVING."""
    if stop:
        return STOP
    return IDLE if speed_bound <= MOVING_SPEED else MOVING


def per_hour(count, seconds):
    """`count` events over `seconds` of cell time, per hour."""
    return count / (seconds / SECONDS_PER_HOUR)


def share(part_seconds, seconds):
    """`part_seconds` of `seconds`, in per cent."""
    return 100.0 * part_seconds / seconds


def request_refused(accepted) -> bool:
    """An eligible request's answer (True, False; None: no answer, which the task manager takes
    as no) counts as refused."""
    return accepted is not True
