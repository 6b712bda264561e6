"""The ROS epoch protocol of docs/DESIGN.md as pure state machines (the sans-IO pattern).

Each node of the ring owns publishers, subscriptions, parameters and timers, and nothing else:
it converts a message, feeds the value here with its source timestamp (the writer's
publication time) and the node's clock value, and publishes what comes back. Every rule about
message order, holds, timeouts, late answers and restarts lives in this module, so each case
is a deterministic unit test (test/test_protocol.py) and the DDS tests only check the wiring.

Times are integer nanoseconds. ``now`` is the node's control clock (monotonic, or the ROS
clock under use_sim_time); ``published_ns`` is a writer's source timestamp (the system clock
of the publishing host; hosts must agree, as tf needs). A machine that waits says so through
its `deadline` (an absolute ``now`` value, or None): the node arms a timer for it and calls
`expire(now)` when it fires; `expire` re-checks the time, so an early or stale call does
nothing.

- `EpochFollower`: which `hrc/epoch` values a follower takes: one writer's line (the next one;
  1 after a higher one is a restart; a forger's jump is refused; anything else is refused).
- `StreamLock`: one writer of a sensor stream (the body tracker's frames). `SingleWriter`: a
  command or state stream that must have one writer (the arm's joint states, its goals and
  speed override): another writer's messages are refused and hold the consumer.
- `TaskEpochs`: the task manager's bookkeeping of epoch k: hold for a_{k-1} and the answer to
  an eligible request, finalise, begin epoch k; screen late answers; follow restarts.
  `RequestCounts`: every task request accepted, refused or lost, once.
- `DecisionGate`: the decision node's inputs of epoch k (fresh, stale, malformed, missing),
  the fail-safe rules and the decision itself.
- `ClockStart`: when the decision node's epoch clock may start (graph ready, or waited long
  enough); `ClockOwner`: which decision node decides for the cell (the oldest `Claim`).
- `EstimatorEpochs`: the belief estimator's epochs: its windows split by the signal's source
  timestamp (`SampleWindows`), the posterior held for x_k (`PosteriorHold`), O_k, d_k and the
  belief update.
- `ActionPairing`: the simulated cell's pairing of a_k with the task state x_k.
- `PeriodEstimate`, `timeout_ns`, `PeriodTimeout`: timeouts that follow the epoch period (a
  parameter of 0 means a fraction of the period; the followers learn the period from the
  epochs they receive), each defined once, and the order they must keep
  (`check_timeout_order`).

`InputError` is the one exception for an unusable input: the ring drops the message with a
throttled warning and a diagnostic.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .model import ACTIONS, DN, OBSERVATION_LEVELS, TASK_VARIABLES, request_eligible
from .quoting import quote
from .decision.observation import window_level
from .tasks import TaskBook, TaskRecord, robot_cycle_done

OK, WARN, ERROR = 'OK', 'WARN', 'ERROR'
RECENT = 2048   # samples per stream kept with their publication time, to split a window:
#                2 s of joint states at 1 kHz, a minute of skeletons at 30 Hz
NO_EVIDENCE = np.ones(9)   # the likelihood of an epoch without an observation: predict only
PROGRESS_KEPT = 64         # changes of the robot's progress kept to find the one at a signal


class InputError(ValueError):
    """An input cannot be used (malformed, out of its domain, out of order); the text says why."""


@dataclass(frozen=True)
class Report:
    """A diagnostic the node publishes: level, the part of the node it concerns, a message and
    key-values. `log` asks the node to also log the message at that level, throttled per
    (`what`, `kind`): reports of one kind repeat, say, every epoch of a fault."""

    level: str
    what: str
    message: str
    values: dict = field(default_factory=dict)
    log: bool = True
    kind: str = ''


def _seconds(ns: int) -> float:
    return ns * 1e-9


# -- timeouts that follow the epoch period ------------------------------------------------------
class PeriodEstimate:
    """The epoch period a follower sees: the median of the last intervals between the source
    timestamps of a periodic input (hrc/epoch, hrc/action); None before two of them."""

    def __init__(self, window: int = 5):
        self._stamps: deque = deque(maxlen=window + 1)

    def observe(self, published_ns: int) -> None:
        if self._stamps and published_ns <= self._stamps[-1]:
            self._stamps.clear()          # a restart, or a clock step: start again
        self._stamps.append(published_ns)

    @property
    def period_ns(self) -> int | None:
        if len(self._stamps) < 2:
            return None
        stamps = list(self._stamps)
        return int(np.median(np.diff(stamps)))


def timeout_ns(explicit_s: float, fraction: float, period_ns: int | None,
               fallback_s: float) -> int:
    """A timeout parameter's value: `explicit_s` seconds if it is > 0, else `fraction` of the
    epoch period (`fallback_s` while the period is unknown)."""
    if explicit_s > 0:
        return int(explicit_s * 1e9)
    if period_ns is None:
        return int(fallback_s * 1e9)
    return int(fraction * period_ns)


@dataclass(frozen=True)
class PeriodTimeout:
    """A timeout parameter that follows the epoch period T: 0 (the default) means
    `fraction` x T, or `fallback_s` while the node does not know T yet (the followers learn it
    from the source stamps of two epochs); an explicit value > 0 is taken as it is."""

    node: str
    parameter: str
    fraction: float
    fallback_s: float

    def ns(self, explicit_s: float, period_ns: int | None) -> int:
        return timeout_ns(explicit_s, self.fraction, period_ns, self.fallback_s)

    def describe(self, explicit_s: float, period_s: float) -> str:
        value = explicit_s if explicit_s > 0 else self.fraction * period_s
        how = f'{value:g} s' if explicit_s > 0 else \
            f'{self.fraction:g} x the period = {value:g} s'
        return f"{self.node}'s {self.parameter} ({how})"


# Every timeout that follows the period, defined once (docs/DESIGN.md "Node parameters").
TASK_HOLD = PeriodTimeout('task_manager', 'input_timeout', 0.25, 0.25)
ESTIMATOR_HOLD = PeriodTimeout('belief_estimator', 'task_state_timeout', 0.4, 0.3)
DECISION_WAIT = PeriodTimeout('decision', 'input_timeout', 0.5, 0.5)
STALE = PeriodTimeout('decision', 'stale_timeout', 3.0, 3.0)
CELL_HOLD = PeriodTimeout('cell_sim', 'task_state_timeout', 0.25, 0.25)
# The holds nest: after epoch k the task manager waits for a_{k-1} and the answer, then
# publishes x_k; the posterior estimator holds b_k for x_k; the decision node waits for b_k
# and x_k; all within the period, and an input is stale only after more than one period:
#     TASK_HOLD < ESTIMATOR_HOLD < DECISION_WAIT < epoch period < STALE
# A hold that ends after the one that waits for it turns every late input into dn.
NESTED_TIMEOUTS = (TASK_HOLD, ESTIMATOR_HOLD, DECISION_WAIT)
ESTIMATOR_HOLD_FRACTION = ESTIMATOR_HOLD.fraction
ESTIMATOR_HOLD_FALLBACK_S = ESTIMATOR_HOLD.fallback_s


def check_timeout_order(period_s: float | None, explicit: dict) -> str | None:
    """Why the timeouts break the order of `NESTED_TIMEOUTS` for an epoch period of
    `period_s` (None: not known yet), or None. `explicit` maps a `PeriodTimeout` to its
    parameter value (0: follow the period); the others are at their defaults. A node checks
    its own values against the others' defaults, the one order every node computes the same
    way; without a period, only explicit values can be compared."""
    given = {t: float(v) for t, v in explicit.items() if float(v) > 0}
    return _period_reason(period_s, given) or _nesting_reason(period_s, given)


def _period_reason(period_s: float | None, given: dict) -> str | None:
    """An explicit hold not shorter than the period, or a stale_timeout not longer."""
    if period_s is None:
        return None
    for timeout in NESTED_TIMEOUTS:
        if timeout in given and not given[timeout] < period_s:
            return (f'{timeout.parameter} ({given[timeout]:g} s) must be shorter than '
                    f'epoch_period ({period_s:g} s); 0 follows the period '
                    f'({timeout.fraction:g} x)')
    if STALE in given and not given[STALE] > period_s:
        return (f'stale_timeout ({given[STALE]:g} s) must be longer than epoch_period '
                f'({period_s:g} s), or every input would be stale at every epoch; 0 follows '
                f'the period ({STALE.fraction:g} x)')
    return None


def _nesting_reason(period_s: float | None, given: dict) -> str | None:
    """Two holds of the chain, one of them explicit, in the wrong order."""
    def value(timeout):
        if timeout in given:
            return given[timeout]
        return None if period_s is None else timeout.fraction * period_s

    def name(timeout):
        if timeout in given:
            return f"{timeout.node}'s {timeout.parameter} ({given[timeout]:g} s)"
        return timeout.describe(0.0, period_s)

    chain = [t for t in NESTED_TIMEOUTS if value(t) is not None]
    pairs = [(a, b) for i, a in enumerate(chain) for b in chain[i + 1:]
             if (a in given or b in given) and not value(a) < value(b)]
    if not pairs:
        return None
    early, late = pairs[0]
    order = ' < '.join(f'{t.node} {t.parameter}' for t in NESTED_TIMEOUTS)
    return (f'{name(early)} must be shorter than {name(late)}: the holds nest ({order} < '
            'epoch_period); 0 follows the period')


# -- hrc/epoch ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stamp:
    """Where a message came from: the writer's source timestamp and its publication sequence
    number (per writer, +1 for every message it sends; None where the middleware gives none)."""

    published_ns: int
    sequence: int | None = None


SILENT_PERIODS = 2.5        # the followed epoch source is gone after this many silent periods
SILENT_MIN_S = 1.0          # ... and never sooner than this (a scheduling stall is no silence)
SILENT_FALLBACK_S = 3.0     # ... or these seconds while the period is unknown
REFUSED_KEPT = 256          # sequence numbers of refused epochs kept to explain a writer's gap


class EpochFollower:
    """Which `hrc/epoch` messages a follower takes: one epoch source at a time.

    The follower locks onto the source of the first epoch it takes and follows that writer's
    line of sequence numbers (per writer, +1 for every message it sends). A message continues
    the line when

    - its sequence number and its epoch both advance by one (the decision node and a bag
      player publish one message per epoch);
    - both advance by the same step (epochs lost on the way), or the epoch is the next one and
      every sequence number in between belongs to a message this follower refused since the
      last epoch it took (the writer's own repeat or stray in between, `refused`): both only
      while no other writer is in evidence.

    Another writer is in evidence, for `silence_ns` from the moment it shows, when a refused
    message carries a sequence number the followed writer has already passed, or when the
    followed writer's next epoch carries a lower number than one refused before it: one
    writer's numbers only grow, and arrive in order. So a forger that sends refused epochs
    (value 0, a stray count) to push its numbers past the decision node's, then k+1 right
    after the decision node's k, is refused: the gap it jumps is not the followed writer's.
    Anything that does not continue is refused with `InputError`, so one stray epoch of
    4294967295 cannot stop the cell. When the followed source has been silent for
    `SILENT_PERIODS` epoch periods, and at least `SILENT_MIN_S` (it stopped or restarted), the
    next source is followed from where it is: a count that starts again at 1 is a restart (a
    WARN report), another one a new source. Without sequence numbers the rule falls back to
    the count alone: the next epoch, or 1 after silence.

    Not defended: a writer that copies the followed one's sequence numbers exactly (it must
    know them) cannot be told apart without a publisher id in the message info, which rclpy
    (Jazzy) does not give; its epochs are still refused unless they come first, and the graph
    names it (docs/ROBUSTNESS.md).
    """

    def __init__(self):
        self.last = 0                       # the last epoch taken
        self._sequence: int | None = None
        self.last_published_ns: int | None = None
        self.period = PeriodEstimate()
        self.ignored = 0                    # messages of another source
        self._refused: list[int] = []       # sequence numbers refused since the last take
        self._refused_overflow = False      # more than REFUSED_KEPT of them
        self._foreign_ns: int | None = None  # when another writer last showed (source time)
        self.lines = 0                      # writers followed so far (a restart is a new one)

    @property
    def silence_ns(self) -> int:
        return max(timeout_ns(0.0, SILENT_PERIODS, self.period.period_ns, SILENT_FALLBACK_S),
                   int(SILENT_MIN_S * 1e9))

    def foreign_in_evidence(self, published_ns: int) -> bool:
        """Another writer showed on hrc/epoch less than `silence_ns` before `published_ns`."""
        return self._foreign_ns is not None and \
            published_ns - self._foreign_ns <= self.silence_ns

    def refused(self, stamp: Stamp) -> None:
        """Note an hrc/epoch message that was not taken (`check` refused it, or the conversion
        did: an epoch of 0): its sequence number may explain the followed writer's next gap,
        or show another writer."""
        sequence = stamp.sequence
        if sequence is None or self._sequence is None:
            return
        if sequence <= self._sequence:
            self._foreign_ns = stamp.published_ns      # a number the followed writer passed
        elif len(self._refused) < REFUSED_KEPT:
            self._refused.append(sequence)
        else:
            self._refused_overflow = True

    def _continues(self, k: int, stamp: Stamp) -> bool:
        if self._sequence is None or stamp.sequence is None:
            return k == self.last + 1
        advance, step = stamp.sequence - self._sequence, k - self.last
        if advance <= 0 or step <= 0:
            return False
        if advance == step == 1:
            return True
        if self.foreign_in_evidence(stamp.published_ns):
            return False
        if advance == step:                      # messages lost on the way
            return True
        gap = range(self._sequence + 1, stamp.sequence)
        return step == 1 and not self._refused_overflow and sorted(set(self._refused)) == \
            list(gap)

    def check(self, k: int, stamp: Stamp) -> Report | None:
        """Raise `InputError` if epoch k comes from another source; a WARN report if it starts
        a new count (a restart, or a new source after silence). Call `take` once acted on."""
        if self.last_published_ns is None or self._continues(k, stamp):
            return None
        silent = stamp.published_ns - self.last_published_ns > self.silence_ns
        if not silent:
            self.ignored += 1
            self.refused(stamp)
            raise InputError(
                f'ignored hrc/epoch {k}: it does not continue the epoch source followed (last '
                f'epoch {self.last}); a second epoch source, or a stray message')
        if k == 1:
            message = (f'hrc/epoch restarted at 1 after {self.last} (the epoch source '
                       'restarted); following it')
        else:
            message = (f'following a new epoch source at epoch {k} (the last one, at epoch '
                       f'{self.last}, fell silent)')
        return Report(WARN, 'epoch', message, {'epoch': k, 'previous_epoch': self.last},
                      kind='restart')

    def take(self, k: int, stamp: Stamp) -> None:
        restarted = self.last_published_ns is not None and not self._continues(k, stamp)
        if restarted or self.last_published_ns is None:
            self.lines += 1
        if restarted:
            self.period = PeriodEstimate()
            self._foreign_ns = None
        elif stamp.sequence is not None and any(s > stamp.sequence for s in self._refused):
            self._foreign_ns = stamp.published_ns      # numbers ahead of the followed writer
        self.last, self._sequence, self.last_published_ns = k, stamp.sequence, stamp.published_ns
        self._refused, self._refused_overflow = [], False
        self.period.observe(stamp.published_ns)


STREAM_MAX_SKIP = 64        # sequence numbers a followed stream may skip (frames lost on the way)
# what rmw calls a node until discovery has its name (ros/sources.py, robot.bridge)
UNKNOWN_NODE_NAME = '_NODE_NAME_UNKNOWN_'


class StreamLock:
    """One writer per sensor stream (the body tracker's frames): is a message the followed
    writer's?

    rclpy (Jazzy) gives no publisher id with a message, but every writer numbers its messages
    (publication sequence numbers, +1 per message). The lock follows the line of the first
    writer heard: a message continues it when its number is above the line's last one by at
    most `max_skip` (best-effort messages lost on the way), and is `FOLLOWED`. Any other is
    `OTHER`: a second writer (a second tracker, a bag played on a live cell) or the followed
    writer started again (its numbers restart). Once the followed line has been silent for
    `silence` (receive time, the node's clock: two writers' stamps cannot be compared), the
    next message's writer is followed (`NEW`). Without sequence numbers every message is taken
    as the followed writer's. Two writers whose numbers run within `max_skip` of each other
    (started together) cannot be told apart; the body tracker's nearer rule still holds for
    them (`core.cell.tracking`)."""

    FOLLOWED, OTHER, NEW = 'followed', 'other', 'new'

    def __init__(self, max_skip: int = STREAM_MAX_SKIP):
        self.max_skip = int(max_skip)
        self.last: int | None = None        # the followed line's last sequence number
        self.last_heard: float | None = None
        self.others = 0                     # messages of another writer

    def classify(self, sequence: int | None, now: float, silence: float) -> str:
        if sequence is None:
            self.last_heard = now
            return self.FOLLOWED
        if self.last is None:
            self.last, self.last_heard = sequence, now
            return self.FOLLOWED
        if 0 < sequence - self.last <= self.max_skip:
            self.last, self.last_heard = sequence, now
            return self.FOLLOWED
        if now - self.last_heard > silence:
            self.last, self.last_heard = sequence, now
            return self.NEW
        self.others += 1
        return self.OTHER

    def forget(self) -> None:
        """Follow the next writer heard (the clock stepped back: the line's times lie in its
        future, and a writer that restarted with it numbers from 1 again)."""
        self.last = self.last_heard = None


class SingleWriter:
    """A stream that must have one writer (the arm's joint states, goals, speed override):
    `check(sequence, now)` raises InputError for a message of a writer other than the followed
    one (`StreamLock`, lines silent for `silence` s give way), and `held(now)` is True until the
    other writer has been silent for `hold` s: which of two is right cannot be known, so the
    consumer holds (the arm stops). Times in seconds of one clock."""

    def __init__(self, what: str, silence: float, hold: float):
        self.what, self.silence, self.hold = what, float(silence), float(hold)
        self.lock = StreamLock()
        self.other_at: float | None = None

    def check(self, sequence: int | None, now: float) -> None:
        if self.lock.classify(sequence, now, self.silence) == StreamLock.OTHER:
            self.other_at = now
            raise InputError(f'{self.what} of a second writer: refused, and the arm holds while '
                             'two write (which is right is unknown)')

    def held(self, now: float) -> bool:
        return self.other_at is not None and now - self.other_at <= self.hold

    def clock_stepped_back(self, now: float) -> None:
        """The next writer heard is followed (`StreamLock.forget`); a second writer's hold
        lasts `hold` from `now` at most (it was counted from a time in the clock's future)."""
        self.lock.forget()
        if self.other_at is not None:
            self.other_at = min(self.other_at, now)

    @property
    def reason(self) -> str:
        return (f'a second writer of {self.what} (within {self.hold:g} s): which is right is '
                'unknown')


class SequenceGaps:
    """Messages a writer sent that never arrived: its publication sequence numbers skip.

    Only meaningful while one writer publishes (without a publisher id in the message info,
    two writers' numbers interleave): the caller checks that. A number that does not increase
    starts again (a new writer)."""

    def __init__(self):
        self.last: int | None = None
        self.lost = 0

    def observe(self, sequence: int | None) -> int:
        """The count of messages missing before this one (0 for the first, or a new writer)."""
        last, self.last = self.last, sequence
        if last is None or sequence is None or sequence <= last:
            return 0
        self.lost += sequence - last - 1
        return sequence - last - 1


class RequestCounts:
    """The fate of every `hrc/task_request`: accepted (queued), refused (malformed, out of its
    domain, or beyond the queue) or lost (the one publisher sent it and it never arrived: the
    writer's sequence numbers skip). Each request that arrives is counted exactly once, as
    accepted or refused, whatever refused it, so a refused request never reads as lost; lost
    ones are known only while one publisher sends (two writers' numbers interleave)."""

    def __init__(self):
        self.gaps = SequenceGaps()
        self.accepted = self.refused = self.lost = 0

    def arrived(self, sequence: int | None, one_publisher: bool) -> int:
        """A request arrived (before it is checked): the requests lost before it."""
        lost = self.gaps.observe(sequence)
        if not one_publisher:
            return 0
        self.lost += lost
        return lost

    def accept(self) -> None:
        self.accepted += 1

    def refuse(self) -> None:
        self.refused += 1

    def counts(self) -> dict:
        return {'requests_accepted': self.accepted, 'requests_refused': self.refused,
                'requests_lost': self.lost}


# -- the task manager -------------------------------------------------------------------------
@dataclass
class TaskStep:
    """What the task manager publishes after an input: the task state of a new epoch (None:
    nothing to publish) and reports."""

    task_state: dict | None = None
    reports: list[Report] = field(default_factory=list)


class TaskEpochs:
    """The task manager's epoch bookkeeping around a `TaskBook` (docs/DESIGN.md).

    On epoch k: finalise a_{k-1} (``book.apply(a_{k-1}, accepted)``), then ``begin_epoch(k)``
    and publish the task state. a_{k-1} is the last action received since epoch k-1; accepted
    is the latest published response in the window (the window opens at the epoch, so an
    answer that overtakes its action still counts). When epoch k arrives before a_{k-1}, or
    before the answer to an eligible a_{k-1}, finalisation is held until it arrives, at most
    `input_timeout_ns`; then a missing action counts as dn and a missing answer as a refusal,
    with a WARN report. In the window after such a refusal, a response published before that
    window's action is the late answer to the refused request: it is ignored, with a report.
    A restarted count finalises the old count's last action like any epoch, then renumbers.

    With `robot_progress` the robot's counter bc follows the arm's physical work, as in the
    batch cell (docs/ROBOT.md, "physical progress"): a_{k-1} is applied with ``robot_runs`` =
    `robot_cycle_done` of the robot's progress ``(nature, cycles, cycles_done)`` (the bridge's
    `hrc/robot_progress`) published last *before* epoch k's signal, the end of epoch k-1,
    whenever it arrives; no progress published yet, or cycles 0 (no robot share): the robot
    has not run. Without it bc runs
    as MODEL.md 3.2 says (every action but dn).

    Epochs come through an `EpochFollower` (one source; a stray or second source is refused).
    The task book counts the epochs taken (from 1, and from 1 again after a restart), not the
    numbers on `hrc/epoch`, so a number that jumps (lost epochs, a source followed mid-count)
    never releases the schedule early: the schedule's epochs are the cell's epochs.
    """

    def __init__(self, book: TaskBook, input_timeout_ns: int, robot_progress: bool = False):
        self.book = book
        self.input_timeout_ns = int(input_timeout_ns)
        self.robot_progress = bool(robot_progress)
        # (published_ns, nature, cycles, cycles_done) at each change, the last PROGRESS_KEPT
        self.progress: deque = deque(maxlen=PROGRESS_KEPT)
        self.signal_ns: int | None = None     # epoch k's signal: where epoch k - 1 ended
        self.epochs = EpochFollower()
        self.action_taken: int | None = None          # a_{k-1}
        self.action_ns: int | None = None             # its publication time
        self.response: tuple[bool, int] | None = None  # latest answer: (value, published_ns)
        self.screening = False      # the last request was refused for want of an answer
        self.next_epoch: int | None = None            # epoch k, waiting for finalisation
        self.renumber = False                         # epoch k restarts the count
        self.hold_since: int | None = None
        self.last_finalised: tuple | None = None      # (epoch, action name, accepted)
        self.late_inputs = 0        # finalisations that timed out
        self.late_answers = 0       # responses ignored as answers to a refused request

    @property
    def deadline(self) -> int | None:
        return None if self.hold_since is None else self.hold_since + self.input_timeout_ns

    # -- inputs ----------------------------------------------------------------------------
    def epoch(self, k: int, stamp: Stamp, now: int) -> TaskStep:
        step = TaskStep()
        new_count = self.epochs.check(k, stamp)
        if new_count is not None:
            step.reports.append(new_count)
        self.epochs.take(k, stamp)
        if self.next_epoch is not None:       # epoch k came before k-1 was finalised
            self._finalise(step, now, timed_out=True)
        self.signal_ns = stamp.published_ns
        restart = new_count is not None and k == 1
        self.next_epoch = 1 if restart else self.book.epoch + 1
        self.renumber = restart               # the old count's last action is finalised first
        if self.book.epoch < 1:
            self._begin(step, self.next_epoch)
        else:
            self._finalise(step, now)
        return step

    def action(self, action: int, published_ns: int, now: int) -> TaskStep:
        step = TaskStep()
        self.action_taken, self.action_ns = action, published_ns
        self._screen(step)
        self._finalise(step, now)
        return step

    def answer(self, accepted: bool, published_ns: int, now: int) -> TaskStep:
        step = TaskStep()
        if self.response is None or published_ns >= self.response[1]:
            self.response = (bool(accepted), published_ns)   # the latest word of the human
        self._screen(step)
        self._finalise(step, now)
        return step

    def expire(self, now: int) -> TaskStep:
        step = TaskStep()
        if self.deadline is not None and now >= self.deadline:
            self._finalise(step, now, timed_out=True)
        return step

    def robot_progress_received(self, nature: int, cycles: int, cycles_done: int,
                                published_ns: int) -> None:
        """The bridge's `hrc/robot_progress`; kept at each change of its value."""
        value = (int(nature), int(cycles), int(cycles_done))
        if self.progress and self.progress[-1][1:] == value:
            return
        if self.progress and published_ns < self.progress[-1][0]:   # overtaken: in its place
            entries = sorted([*self.progress, (int(published_ns), *value)])
            self.progress.clear()
            self.progress.extend(entries)
            return
        self.progress.append((int(published_ns), *value))

    def progress_at(self, signal_ns: int | None) -> tuple | None:
        """(nature, cycles, cycles_done) published last before `signal_ns`, or None."""
        before = [entry for entry in self.progress
                  if signal_ns is None or entry[0] < signal_ns]
        return before[-1][1:] if before else None

    def robot_runs(self) -> bool | None:
        """`TaskBook.apply`'s robot_runs for the epoch being finalised (None: the model's
        rule, without robot_progress)."""
        if not self.robot_progress:
            return None
        progress = self.progress_at(self.signal_ns)
        return (progress is not None and progress[1] > 0
                and robot_cycle_done(progress[1], progress[2], self.book.state['bc']))

    def request(self, tp: int, tc: int, tx: int) -> TaskRecord:
        """Queue a requested task; `InputError` if the book refuses it (bad or queue full)."""
        try:
            return self.book.request(tp, tc, tx)
        except ValueError as exc:
            raise InputError(str(exc)) from None

    # -- the machine -----------------------------------------------------------------------
    def awaited(self) -> str | None:
        """What finalising epoch k still waits for, or None."""
        if self.action_taken is None:
            return f'hrc/action of epoch {self.book.epoch}'
        task = self.book.state
        if self.response is None and request_eligible(self.action_taken, task['tp'],
                                                      task['tx'], task['ty']):
            return (f'hrc/human_response to {ACTIONS[self.action_taken]} of epoch '
                    f'{self.book.epoch}')
        return None

    def _screen(self, step: TaskStep) -> None:
        """After a refusal for want of an answer, drop a response published before this
        window's action: it answers the refused request. Every such response is screened."""
        if not (self.screening and self.response is not None and self.action_ns is not None
                and self.response[1] < self.action_ns):
            return
        self.late_answers += 1
        step.reports.append(Report(
            WARN, 'tasks', f'ignored a late human response ({self.response[0]}): it was sent '
            f'before {ACTIONS[self.action_taken]} of epoch {self.book.epoch}, so it answers '
            'the request refused earlier for want of an answer', {'epoch': self.book.epoch},
            kind='late_answer'))
        self.response = None

    def _finalise(self, step: TaskStep, now: int, timed_out: bool = False) -> None:
        if self.next_epoch is None:
            return
        awaited = self.awaited()
        if awaited is not None and not timed_out:
            if self.hold_since is None:
                self.hold_since = now
            return
        unanswered = awaited is not None and self.action_taken is not None
        if awaited is not None:
            self.late_inputs += 1
            step.reports.append(Report(
                WARN, 'tasks', f'no {awaited} within input_timeout; taking '
                + ('dn' if self.action_taken is None else 'the request as refused'),
                {'epoch': self.book.epoch}, kind='late_input'))
        action = DN if self.action_taken is None else self.action_taken
        accepted = self.response is not None and self.response[0]
        self.book.apply(action, accepted, self.robot_runs())
        self.last_finalised = (self.book.epoch, ACTIONS[action], accepted)
        if self.renumber:
            self.book.renumber(self.next_epoch)
        self._begin(step, self.next_epoch)
        self.screening = unanswered            # for the window that begins now

    def _begin(self, step: TaskStep, k: int) -> None:
        self.hold_since = None
        self.book.begin_epoch(k)
        self.next_epoch, self.renumber, self.screening = None, False, False
        self.action_taken, self.action_ns, self.response = None, None, None
        step.task_state = self.book.state
        if self.book.model.queue is not None:    # the tasks waiting (MODEL.md 8.1)
            step.task_state = {**step.task_state, 'queued': len(self.book.queue)}

    def status(self) -> dict:
        """Key-values of the task manager's periodic status."""
        head = self.book.queue[0] if self.book.queue else None
        return {'epoch': self.book.epoch, 'task_state': list(self.book.state.values()),
                'queued_tasks': len(self.book.queue),
                'next_queued': None if head is None else (head.tp, head.tc, head.tx),
                'last_finalised': self.last_finalised,
                'waiting_for': None if self.next_epoch is None else self.awaited(),
                'late_inputs': self.late_inputs,
                'late_answers_ignored': self.late_answers,
                'completed_tasks': len(self.book.completed),
                **({'robot_progress': self.progress_at(None)} if self.robot_progress else {})}


# -- the decision node ------------------------------------------------------------------------
@dataclass
class InputSlot:
    """The latest good value of one input and the event numbers of its messages."""

    topic: str
    value: Any = None
    received_ns: int | None = None   # control clock at the last good message
    seq: int = 0                     # event number of the last good message
    bad_seq: int = 0                 # event number of the last malformed message
    bad_reason: str = ''


@dataclass(frozen=True)
class Decision:
    """One epoch's decision: the action (dn on any fault) and why."""

    epoch: int
    action: int
    faults: tuple
    collision: bool              # dn because d = 0 (the only fault then: WARN, not ERROR)
    timed_out: bool              # decided at input_timeout rather than on the last input
    selection: Any               # the selector's Selection, None when it did not run
    observable: tuple | None
    belief: Any
    ages: dict                   # <input>_age_s
    input_wait_ms: float
    compute_ms: float

    @property
    def level(self) -> str:
        if not self.faults:
            return OK
        return WARN if self.collision and len(self.faults) == 1 else ERROR

    @property
    def message(self) -> str:
        if not self.faults:
            return f'epoch {self.epoch}: {ACTIONS[self.action]}'
        return f'epoch {self.epoch}: dn (fail-safe): {"; ".join(self.faults)}'

    def values(self) -> dict:
        selection = self.selection
        return {
            'epoch': self.epoch, 'action': ACTIONS[self.action],
            'faults': '; '.join(self.faults) if self.faults else 'none',
            **self.ages,
            'input_wait_ms': self.input_wait_ms,
            'input_timed_out': self.timed_out,
            'compute_ms': self.compute_ms,
            'belief': None if self.belief is None else np.round(self.belief, 4),
            'observable': self.observable,
            'action_scores': (None if selection is None else ' '.join(
                f'{name}={score:.4g}' for name, score in zip(ACTIONS, selection.scores))),
            'selected': None if selection is None else selection.name,
        }


class DecisionGate:
    """The decision node's inputs of epoch k and its fail-safe (docs/DESIGN.md).

    `begin(k)` opens epoch k; the decision is taken as soon as every input has answered for
    it (a good or a malformed message), or at `input_timeout_ns` after the epoch began. Then
    a_k = ``select(belief, x_k)``, x_k = (task state, d) and, when the task state carries it,
    the tasks waiting (`queued`, MODEL.md 8.1: a queue policy's selector raises without it,
    which makes it dn below), unless a fault makes it dn:

    - an input never received (missing), older than `stale_timeout_ns` (stale), or whose last
      message was malformed;
    - the belief or the task state not received for this epoch (fresh: after the epoch was
      published, in timer mode; after the previous decision, in topic mode, where a replay's
      inputs may precede its epoch signal); the distance level may be an older, not stale, one;
    - d = 0: the human is inside the collision circle (WARN, not ERROR);
    - the selector raising (whatever fails, the robot stops).
    """

    INPUTS = {'belief': 'hrc/belief', 'task_state': 'hrc/task_state',
              'distance_level': 'hrc/distance_level'}
    PER_EPOCH = ('belief', 'task_state')

    def __init__(self, select: Callable[[Any, tuple], Any], stale_timeout_ns: int,
                 input_timeout_ns: int, fresh_at_epoch: bool = True):
        self.select = select
        self.stale_timeout_ns = int(stale_timeout_ns)
        self.input_timeout_ns = int(input_timeout_ns)
        self.fresh_at_epoch = fresh_at_epoch
        self.slots = {name: InputSlot(topic) for name, topic in self.INPUTS.items()}
        self.epoch = 0
        self.pending = False
        self.started_ns = 0
        self._seq = 0
        self._fresh_since = 0        # inputs with seq > this belong to the pending epoch

    @property
    def deadline(self) -> int | None:
        return self.started_ns + self.input_timeout_ns if self.pending else None

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    # -- inputs ----------------------------------------------------------------------------
    def received(self, name: str, value, now: int) -> list[Decision]:
        slot = self.slots[name]
        slot.value, slot.seq, slot.received_ns = value, self._next_seq(), now
        return self._maybe_decide(now)

    def malformed(self, name: str, reason: str, now: int) -> list[Decision]:
        slot = self.slots[name]
        slot.bad_seq, slot.bad_reason = self._next_seq(), reason
        return self._maybe_decide(now)

    def begin(self, k: int, now: int, select: Callable[[Any, tuple], Any] | None = None
              ) -> list[Decision]:
        """Open epoch k; a still pending epoch is decided first (as timed out). A new `select`
        (a policy swapped in) decides from epoch k on: never the pending epoch, never half an
        epoch."""
        decisions = [self._decide(now, timed_out=True)] if self.pending else []
        if select is not None:
            self.select = select
        self.epoch = k
        self.pending = True
        self.started_ns = now
        if self.fresh_at_epoch:
            self._fresh_since = self._next_seq()   # only what arrives from now on
        return decisions + self._maybe_decide(now)

    def expire(self, now: int) -> list[Decision]:
        if self.deadline is not None and now >= self.deadline:
            return [self._decide(now, timed_out=True)]
        return []

    # -- the decision ----------------------------------------------------------------------
    def _answered(self, slot: InputSlot) -> bool:
        return max(slot.seq, slot.bad_seq) > self._fresh_since

    def _maybe_decide(self, now: int) -> list[Decision]:
        if self.pending and all(self._answered(s) for s in self.slots.values()):
            return [self._decide(now, timed_out=False)]
        return []

    def faults(self, now: int) -> tuple[list[str], dict]:
        faults, ages = [], {}
        for name, slot in self.slots.items():
            age = None if slot.received_ns is None else _seconds(now - slot.received_ns)
            ages[f'{name}_age_s'] = age
            if slot.bad_seq > slot.seq:
                faults.append(f'{slot.topic} malformed: {slot.bad_reason}')
            elif slot.value is None:
                faults.append(f'{slot.topic} missing (never received)')
            elif now - slot.received_ns > self.stale_timeout_ns:
                faults.append(f'{slot.topic} stale ({age:.3f} s old > stale_timeout '
                              f'{_seconds(self.stale_timeout_ns):g} s)')
            elif name in self.PER_EPOCH and slot.seq <= self._fresh_since:
                faults.append(f'{slot.topic} not received for epoch {self.epoch} within '
                              'input_timeout')
        return faults, ages

    def _decide(self, now: int, timed_out: bool) -> Decision:
        self.pending = False
        start = time.perf_counter()
        selection, observable, collision = None, None, False
        try:
            faults, ages = self.faults(now)
            if not faults:
                task = self.slots['task_state'].value
                d = self.slots['distance_level'].value
                # with the tasks waiting when the task manager sends them (MODEL.md 8.1)
                observable = tuple(task[n] for n in TASK_VARIABLES) + (d,) + (
                    (task['queued'],) if task.get('queued') is not None else ())
                selection = self.select(self.slots['belief'].value, observable)
                if d == 0:
                    collision = True
                    faults.append('d = 0: the human is inside the collision circle')
        except Exception as exc:  # noqa: BLE001 - whatever fails, the robot must stop
            faults, ages, selection = [f'decision failed: {type(exc).__name__}: {exc}'], {}, None
        self._fresh_since = self._next_seq()
        return Decision(
            epoch=self.epoch, action=DN if faults else selection.action, faults=tuple(faults),
            collision=collision, timed_out=timed_out, selection=selection,
            observable=observable, belief=self.slots['belief'].value, ages=ages,
            input_wait_ms=(now - self.started_ns) * 1e-6,
            compute_ms=(time.perf_counter() - start) * 1e3)


CLAIM_PERIOD_S = 1.0       # a decision node repeats its claim this often
CLAIM_LIFETIME_S = 3.5     # a claim not heard again for this long is gone (its node stopped)
CLAIMS_KEPT = 64           # claims of other decision nodes remembered at most


@dataclass(frozen=True)
class Claim:
    """A decision node's claim to decide for the cell (`ClockOwner`): when it started (the
    system clock, ns: the hosts' clocks agree, as for source timestamps), a random id that
    breaks ties, its fully qualified name and its `epoch_source`."""

    started_ns: int
    nonce: int
    node: str
    mode: str = 'timer'

    @property
    def rank(self) -> tuple[int, int]:
        return (self.started_ns, self.nonce)

    def describe(self) -> str:
        return f'{self.node} (epoch_source {self.mode}, claim {self.nonce:016x})'


@dataclass(frozen=True)
class Endpoint:
    """A publisher of hrc/epoch or hrc/action other than this node's own, as the graph shows
    it: `node` is its fully qualified name, None while the graph does not name it yet (the
    endpoint is discovered before its node's name), so a report never names a placeholder."""

    topic: str
    node: str | None
    gid: str

    def describe(self) -> str:
        who = self.node if self.node else 'a node the graph does not name yet'
        return f'{who} on {self.topic} (gid {self.gid})'


class ClockOwner:
    """Which decision node decides for the cell: one cell, one epoch clock, one action source.

    Every decision node, in either epoch_source mode (a follower that publishes actions is an
    action source too), claims the cell (`Claim`, repeated every `CLAIM_PERIOD_S` on a latched
    topic). The owner is the live claim of the lowest rank: the oldest start, a tie broken by
    the random id. Every node computes the same owner from the same claims, so two nodes
    started at the same moment agree on one (no deadlock, never two clocks), and a node
    started beside a running cell defers to it. A claim not heard for `CLAIM_LIFETIME_S` is
    gone (the node stopped): the next oldest takes over."""

    def __init__(self, mine: Claim):
        self.mine = mine
        self._heard: dict[int, tuple[Claim, int]] = {}    # nonce -> (claim, heard at)

    def heard(self, claim: Claim, now: int) -> None:
        if claim.nonce == self.mine.nonce:
            return
        self._heard.pop(claim.nonce, None)
        self._heard[claim.nonce] = (claim, now)
        while len(self._heard) > CLAIMS_KEPT:
            self._heard.pop(next(iter(self._heard)))

    def others(self, now: int) -> list[Claim]:
        """The other live claims, oldest first."""
        lifetime = int(CLAIM_LIFETIME_S * 1e9)
        for nonce, (_, heard) in list(self._heard.items()):
            if now - heard > lifetime:
                del self._heard[nonce]
        return sorted((claim for claim, _ in self._heard.values()), key=lambda c: c.rank)

    def owner(self, now: int) -> Claim:
        return min([self.mine] + self.others(now), key=lambda c: c.rank)

    def owns(self, now: int) -> bool:
        return self.owner(now) == self.mine

    def unclaimed(self, endpoints: list[Endpoint], now: int) -> list[Endpoint]:
        """The endpoints no live claim accounts for (one per topic for each claim of that
        node name): sources that are not decision nodes of this suite (a stray publisher, an
        older version), or whose claim has not arrived yet."""
        out = []
        for topic in dict.fromkeys(e.topic for e in endpoints):
            names = Counter(c.node for c in self.others(now))
            for endpoint in (e for e in endpoints if e.topic == topic):
                if endpoint.node is not None and names[endpoint.node] > 0:
                    names[endpoint.node] -= 1
                else:
                    out.append(endpoint)
        return out


EPOCH_LISTENERS_KEPT = 256   # listeners' ready marks a decision node keeps (hrc/_epoch_ready)


@dataclass(frozen=True)
class ReadyMark:
    """A listener of hrc/epoch says which epoch writers its reader has matched
    (`hrc/_epoch_ready`): `reader` is the fully qualified name of the node that holds the
    reader, `writers` the writers' GIDs."""

    reader: str
    writers: frozenset[str]


class EpochListeners:
    """Which listeners of hrc/epoch are ready for one epoch clock (issue 37: epoch 1 lost).

    A reliable, volatile reader that matches a writer after the writer's sample was sent never
    gets it, and DDS discovery is not symmetric: the clock's writer can count a listener's
    reader (`get_subscription_count`) before that reader has matched the writer. Epoch 1 is
    certain to reach a listener only once both sides have matched. The writer side is the
    clock's graph (the node holding the reader is among the topic's subscribers there); the
    reader side is the listener's mark, kept here, the latest of each listener, at most
    `limit` listeners (a flood of invented names is refused, not grown without bound)."""

    def __init__(self, limit: int = EPOCH_LISTENERS_KEPT):
        self.limit = limit
        self.marks: dict[str, frozenset[str]] = {}

    def heard(self, mark: ReadyMark) -> None:
        if mark.reader not in self.marks and len(self.marks) >= self.limit:
            raise InputError(f'{quote(mark.reader)} said it is ready for hrc/epoch, but '
                             f'{self.limit} listeners already have: not counted')
        self.marks[mark.reader] = mark.writers

    def ready(self, writer: str | None, readers) -> list[str]:
        """The listeners ready for the clock whose writer has GID `writer` (None: not known
        yet, nobody is): their reader has matched it, and `readers` (the nodes that the
        clock's graph shows with a reader of hrc/epoch) include them."""
        if writer is None:
            return []
        readers = set(readers)
        return sorted(r for r, writers in self.marks.items() if writer in writers and r in readers)


def ready_writers(matched: list[int | None], writers: set[str]) -> frozenset[str] | None:
    """What a listener may say it has matched (`ReadyMark.writers`), from each of its readers'
    matched-writer count (None: a reader not created yet) and the GIDs of the epoch writers its
    graph shows; None: nothing new to say yet. rclpy names no matched endpoint, so the counts
    must equal the graph's count for every reader: fewer, and some writer is not matched yet;
    more, and one matched writer has left the graph while another may not be matched."""
    if not matched or any(count is None or count != len(writers) for count in matched):
        return None
    return frozenset(writers)


@dataclass(frozen=True)
class Tick:
    """What a tick of the decision node's clock does: start an epoch or wait (with a report)."""

    start_epoch: bool
    report: Report | None = None


class ClockStart:
    """When the decision node's epoch clock starts (timer mode), and a second epoch source.

    Epoch 1 comes one tick after the graph is ready (every input has a publisher, enough
    `hrc/epoch` subscribers are discovered and enough listeners are ready, `EpochListeners`),
    so that the first epochs are not lost to DDS discovery, or, at the latest, at the first
    tick after `stale_timeout_ns`, with a warning.
    Until then each tick reports that the node waits and publishes no action.

    One cell has one decision node. With an `owner` (`ClockOwner`), a node that is not the
    owner does not start its clock, and a clock that started before its node learnt of an
    older claim stops (it yields); in topic mode (`running` from the start) a node that is
    not the owner publishes no action. Other publishers of `hrc/epoch` or `hrc/action`
    (`other_sources`: `Endpoint`s, or their descriptions) that no claim accounts for keep a
    clock that has not started from starting (ERROR: both identities): the newer node stays
    silent and the cell stays deterministic. A running clock that sees another source goes on
    (the followers stay locked onto it) and reports it as ERROR at every tick.
    """

    def __init__(self, started_ns: int, stale_timeout_ns: int, running: bool = False,
                 owner: ClockOwner | None = None):
        self.started_ns = started_ns
        self.stale_timeout_ns = int(stale_timeout_ns)
        self.running = running
        self.follows = running              # topic mode: the epochs come from hrc/epoch
        self.owner = owner
        self._ready = False
        self._settled = False

    def tick(self, now: int, graph_ready: Callable[[], bool],
             graph: Callable[[], dict] = dict, other_sources: Callable[[], list] = list,
             me: str = 'this decision node',
             claim_publishers: Callable[[], int] | None = None) -> Tick:
        """One tick (timer mode) or one epoch taken (topic mode). `claim_publishers()` is the
        count of claim publishers the graph shows, this node's own included: before its first
        epoch a node waits until it has heard that many claims (`settled`)."""
        if not self.settled(now, claim_publishers):
            return Tick(False, Report(
                WARN, 'clock', f'{me} waits to hear the claims of the decision nodes the graph '
                'shows before it decides anything (one cell, one decider)', {'this_node': me},
                log=False, kind='waiting'))
        sources, unclaimed, rivals = self._sources(now, list(other_sources()))
        if self.owner is not None and not self.owner.owns(now):
            return self._yield(now, me, sources)
        names = ', '.join(sources or [c.describe() for c in rivals])
        values = {'this_node': me, 'other_sources': names}
        act = 'keeps deciding' if self.follows else 'keeps its clock'
        if self.running and (unclaimed or rivals):
            return Tick(True, Report(
                ERROR, 'clock', f'another epoch source publishes on the cell: {names}; '
                f'{me} {act} (the followers stay locked onto it). Stop one.', values,
                kind='second_source'))
        if unclaimed:
            return Tick(False, Report(
                ERROR, 'clock', f'another epoch source publishes on the cell: {names}; {me} '
                'does not start its clock while it runs (one cell, one epoch clock)', values,
                kind='second_source'))
        rival = None if not rivals else Report(
            ERROR, 'clock', f'another decision node is on the cell: '
            f'{", ".join(c.describe() for c in rivals)}; it defers to {me} (the older: one '
            'cell, one epoch clock). Stop one.', values, kind='second_source')
        return Tick(True, rival) if self.running else self._start(now, graph_ready, graph, rival)

    def settled(self, now: int, claim_publishers: Callable[[], int] | None) -> bool:
        """Every claim publisher the graph shows has been heard (or `CLAIM_LIFETIME_S` has
        passed since the start): a node started beside a running one, whose endpoints it
        already sees, does not act on an epoch before that one's claim has arrived. Once
        settled, always settled."""
        if self._settled or self.owner is None or claim_publishers is None:
            return True
        heard = len(self.owner.others(now)) + 1
        self._settled = heard >= claim_publishers() \
            or now - self.started_ns >= int(CLAIM_LIFETIME_S * 1e9)
        return self._settled

    def _sources(self, now: int, endpoints: list) -> tuple[list, list, list]:
        """(every other source described, those no claim accounts for, the rival claims)."""
        sources = [e.describe() if isinstance(e, Endpoint) else str(e) for e in endpoints]
        if self.owner is None:
            return sources, sources, []
        graph = [e for e in endpoints if isinstance(e, Endpoint)]
        unclaimed = [e.describe() for e in self.owner.unclaimed(graph, now)] \
            + [str(e) for e in endpoints if not isinstance(e, Endpoint)]
        return sources, unclaimed, self.owner.others(now)

    def _start(self, now: int, graph_ready: Callable[[], bool], graph: Callable[[], dict],
               rival: Report | None) -> Tick:
        """Epoch 1 one tick after the graph is ready, or after stale_timeout_ns anyway."""
        waited = _seconds(now - self.started_ns)
        if not (self._ready or now - self.started_ns >= self.stale_timeout_ns):
            if graph_ready():
                self._ready = True          # epoch 1 at the next tick
                return Tick(False, rival)
            return Tick(False, rival or Report(
                WARN, 'decision', 'waiting for the graph: not every input publisher, '
                'hrc/epoch subscriber and ready listener (hrc/_epoch_ready) discovered yet; no '
                'action published',
                {'waited_s': waited, **graph()}, log=False, kind='waiting'))
        self.running = True
        if self._ready:
            return Tick(True, rival)
        return Tick(True, rival or Report(WARN, 'clock', f'starting the epoch clock after '
                                          f'{waited:.1f} s without having discovered every '
                                          'input publisher, hrc/epoch subscriber and ready '
                                          'listener', {'waited_s': waited},
                                          kind='forced_start'))

    def _yield(self, now: int, me: str, sources: list[str]) -> Tick:
        first = self.owner.owner(now)
        if self.follows:
            doing = 'publishes no action'
        elif self.running:
            doing = 'stops its clock'
        else:
            doing = 'does not start its clock'
        if not self.follows:
            self.running = False
        return Tick(False, Report(
            ERROR, 'clock', f'another decision node decides for the cell: {first.describe()} '
            f'(the older claim); {me} {doing} while it runs (one cell, one epoch clock, one '
            'action source)',
            {'this_node': me, 'owner': first.node,
             'other_sources': ', '.join(sources) or first.describe()}, kind='second_source'))


# -- the belief estimator ---------------------------------------------------------------------
@dataclass
class EstimatorStep:
    """What the estimator publishes for epoch k: d_k (None: no skeleton in the window), O_k
    (None: too few joint states, a dropout), b_k (None: a dropout, or held for the epoch's
    task state in ``posterior`` mode), and reports."""

    epoch: int
    distance_level: int | None
    observation: int | None
    belief: np.ndarray | None
    reports: list[Report] = field(default_factory=list)


@dataclass
class _HeldBelief:
    """Epoch k's update, waiting for the task state x_k that shows the human's answer."""

    epoch: int
    signal_ns: int
    since_ns: int
    action: int
    action_ns: int | None      # a_{k-1}'s publication time
    screening: bool            # a_{k-2} went unanswered: its late answer may come before a_{k-1}
    observation: object        # O_k, or NO_EVIDENCE after a dropout
    publish: bool              # b_k is published (False after a dropout: predicted only)
    task_before: tuple | None  # x_{k-1}: (published_ns, task variables)
    d_before: int | None
    d_after: int | None
    x_k: tuple | None = None   # x_k of a refusal whose answer has not been seen yet


TASK_STATES_KEPT = 64           # task states and responses kept to find x_{k-1}, x_k, answers


def _split(stream: deque, signal_ns: int) -> list:
    """Remove and return the entries published before the signal; later ones stay."""
    window = [e for e in stream if e[0] < signal_ns]
    later = [e for e in stream if e[0] >= signal_ns]
    stream.clear()
    stream.extend(later)
    return window


class SampleWindows:
    """The estimator's sample windows: each joint-state sample's velocity level and each
    skeleton's distance level with its publication time, split at an epoch signal's source
    timestamp (`close`): window k holds what was published before epoch k's signal; a sample
    published after it belongs to window k+1 even if it is taken first. Only the window's level
    counts and the last `recent` (publication time, level) pairs are kept (to split the window
    at the signal), so memory is bounded at any rate."""

    def __init__(self, recent: int = RECENT):
        self.recent = recent
        self.counts = np.zeros(len(OBSERVATION_LEVELS), dtype=np.int64)  # O levels, window
        self.levels: deque = deque(maxlen=recent)      # (published_ns, O level)
        self.distances: deque = deque(maxlen=recent)   # (published_ns, d)

    def sample(self, level: int, published_ns: int) -> None:
        self.counts[level - 1] += 1
        self.levels.append((published_ns, level))

    def skeleton(self, d: int, published_ns: int) -> None:
        self.distances.append((published_ns, d))

    def close(self, signal_ns: int) -> tuple[np.ndarray, list]:
        """Window k at its signal: the count of each O level, and its skeletons
        (published_ns, d); what was published later opens window k+1."""
        _split(self.levels, signal_ns)
        counts = self.counts.copy()          # the window, less what was published later
        self.counts[:] = 0
        for _, level in self.levels:
            self.counts[level - 1] += 1
        counts -= self.counts
        return counts, _split(self.distances, signal_ns)


class PosteriorHold:
    """The held posterior of ``posterior`` mode: b_k waits for the task state x_k that shows
    the human's answer to a_{k-1} (`EstimatorEpochs` has the rule). It keeps the task states
    and responses published (the last `TASK_STATES_KEPT` of each), says when x_k completes
    the hold, and what acting revealed: the evidence of the update (`evidence`)."""

    def __init__(self):
        self.task_states: deque = deque(maxlen=TASK_STATES_KEPT)  # (published_ns, task vars)
        self.responses: deque = deque(maxlen=TASK_STATES_KEPT)    # published_ns
        self.x_last: tuple | None = None         # the x_k that completed the last hold
        self.screening = False          # the last request went unanswered (TaskEpochs' rule)
        self.held: _HeldBelief | None = None
        self.last_signal_ns: int | None = None

    def deadline(self, hold_ns: int) -> int | None:
        return None if self.held is None else self.held.since_ns + hold_ns

    def hold(self, k: int, signal_ns: int, since_ns: int, action: int, action_ns: int | None,
             observation, observed: bool, d_before: int | None, d_after: int | None) -> None:
        """Hold b_k from epoch k's signal; x_{k-1} is the x_k that completed the last hold,
        else the first task state published at or after epoch k-1's signal."""
        before = self.x_last
        if before is None or self.last_signal_ns is None or before[0] < self.last_signal_ns:
            before = self.task_after(self.last_signal_ns, signal_ns)
        self.held = _HeldBelief(k, signal_ns, since_ns, action, action_ns, self.screening,
                                observation, observed, before, d_before, d_after)

    def signalled(self, signal_ns: int) -> tuple | None:
        """Epoch k's signal is handled: x_k if it was published before the signal was taken
        (the held b_k may complete with it), else None."""
        self.screening = False
        self.last_signal_ns = signal_ns
        self.x_last = None
        return self.task_after(signal_ns) if self.held is not None else None

    def response(self, published_ns: int) -> tuple | None:
        """An `hrc/human_response` was published: x_k to complete the hold with, when x_k came
        first and shows a refusal this answer explains; else None."""
        self.responses.append(published_ns)
        held = self.held
        if held is not None and held.x_k is not None and self.answered(held, held.x_k):
            return held.x_k
        return None

    def task_state(self, state: dict, published_ns: int) -> tuple | None:
        """A task state: x_k to complete the hold with (`offer`), else None."""
        self.task_states.append((published_ns, state))
        if self.held is not None and published_ns >= self.held.signal_ns:
            return self.offer((published_ns, state))
        return None

    def offer(self, x_k: tuple) -> tuple | None:
        """x_k for the held b_k: x_k to complete it with, unless x_k shows an eligible request
        refused and its answer has not been seen: nothing orders the task manager's x_k and
        the human's answer at this node (rclpy takes ready messages in subscription order), so
        b_k waits for the answer, at most to the hold's deadline (then: unanswered). A later
        task state while it waits changes nothing: x_k is the first."""
        held = self.held
        if held.x_k is not None:
            return None
        if self.eligible(held, x_k) and x_k[1]['ty'] == 0 and not self.answered(held, x_k):
            held.x_k = x_k
            return None
        return x_k

    def take(self) -> _HeldBelief:
        held, self.held = self.held, None
        return held

    def completed(self, x_k: tuple | None, unanswered: bool) -> None:
        self.screening = unanswered
        self.x_last = x_k

    def eligible(self, held: _HeldBelief, x_k: tuple | None) -> bool:
        before = held.task_before
        return before is not None and x_k is not None and bool(
            request_eligible(held.action, before[1]['tp'], before[1]['tx'], before[1]['ty']))

    def answered(self, held: _HeldBelief, x_k: tuple) -> bool:
        """An answer to a_{k-1} was seen: x_k has the task committed (only an acceptance does
        that), or a response was published between x_{k-1} and x_k; after an unanswered
        request, one published before a_{k-1} is that request's late answer
        (`TaskEpochs._screen`)."""
        if x_k[1]['ty'] != 0:
            return True
        since = held.task_before[0] if held.task_before is not None else 0
        if held.screening and held.action_ns is not None:
            since = max(since, held.action_ns)
        return any(since <= t <= x_k[0] for t in self.responses)

    def task_after(self, signal_ns: int | None, before_ns: int | None = None) -> tuple | None:
        """The first task state published at or after a signal (and before `before_ns`):
        (published_ns, task variables)."""
        if signal_ns is None:
            return None
        later = [(t, state) for t, state in self.task_states
                 if t >= signal_ns and (before_ns is None or t < before_ns)]
        return min(later, key=lambda entry: entry[0]) if later else None

    def evidence(self, held: _HeldBelief, task_after: tuple | None, model, belief,
                 reports: list) -> np.ndarray | None:
        """P(x_k | x_{k-1}, h, a_{k-1}) of what is known (`HRCModel.transition_likelihood`):
        the answer (an accepted request commits the task, ty != 0 in x_k: a task lasts at
        least one epoch, so it cannot also complete) and the distance move. What is unknown
        or impossible is left out (a WARN in `reports`); None: no evidence at all."""
        k = held.epoch
        eligible = self.eligible(held, task_after)
        if eligible and not self.answered(held, task_after):
            eligible = False
            reports.append(Report(
                WARN, 'epoch', f'epoch {k}: no hrc/human_response to {ACTIONS[held.action]} '
                'was published before the task state; the task manager took it as refused, '
                "so the answer is left out of the posterior update", {'epoch': k},
                kind='no_answer'))
        d_before, d_after = held.d_before, held.d_after
        if d_before is not None and d_after is not None and not model.transition_likelihood(
                held.action, False, False, d_before, d_after).any():
            reports.append(Report(
                WARN, 'epoch', f'epoch {k}: the distance level moved {d_before} -> {d_after}, '
                'which the model calls impossible (a sensor fault?); the move is left out of '
                'the posterior update', {'epoch': k}, kind='impossible_move'))
            d_before = d_after = None
        evidence = model.transition_likelihood(
            held.action, eligible, eligible and task_after[1]['ty'] != 0, d_before, d_after)
        if not (belief * evidence).sum() > 0.0:
            reports.append(Report(
                WARN, 'epoch', f'epoch {k}: what acting revealed is impossible under the '
                'belief; left out of the posterior update', {'epoch': k},
                kind='impossible_evidence'))
            return None
        return evidence


class EstimatorEpochs:
    """The belief estimator's epochs (docs/DESIGN.md): the windows (`SampleWindows`), the
    held posterior (`PosteriorHold`) and the filter update, here. On epoch k:

        O_k = window_level(levels of window k's joint-state samples)   (>= min_window_samples)
        b_k = initial(O_k) at the first epoch, else update(b_{k-1}, a_{k-1}, O_k)
        d_k = the distance level of window k's latest skeleton

    A window with too few samples publishes no O and no belief; the belief is carried by the
    prediction alone (`NO_EVIDENCE`), so the next update stays consistent with the actions
    taken. A window without a skeleton publishes no distance level. A missing a_{k-1} counts
    as dn.

    In ``posterior`` mode the update also takes what acting revealed (MODEL.md 6, the exact
    posterior the POMDP plans with): the human's answer to an eligible request and the
    distance move, `HRCModel.transition_likelihood(a_{k-1}, eligible, accepted, d_{k-1},
    d_k)`. Eligibility comes from x_{k-1} (the task state that completed the previous hold,
    else the first published at or after epoch k-1's signal) and the answer from x_k (the
    first published at or after epoch k's signal: the task manager publishes it once it has
    applied a_{k-1} and the answer): accepted means a commitment. So b_k waits for x_k
    (`task_state`), at most `hold_ns` (`deadline`, `expire`; `task_state_timeout_s`, or
    `ESTIMATOR_HOLD`'s fraction of the period). What is not known is left out of the evidence,
    with a WARN: the answer without x_k, or when no `hrc/human_response` was published
    between x_{k-1} and x_k (the task manager took the request as refused for want of an
    answer: that says nothing about the human); the move when the model calls it impossible
    (a jump of the distance level, a sensor fault), so one bad skeleton cannot wipe out the
    belief. O_k and d_k are published at once.
    """

    def __init__(self, belief_filter, min_window_samples: int, recent: int = RECENT,
                 task_state_timeout_s: float = 0.0):
        self.filter = belief_filter
        self.task_state_timeout_s = float(task_state_timeout_s)
        self.min_window_samples = int(min_window_samples)
        self.windows = SampleWindows(recent)
        self.posterior = PosteriorHold()
        self.epochs = EpochFollower()
        self._known_period_ns: int | None = None
        self.hold_ns = self._hold_ns()
        self.belief: np.ndarray | None = None
        self.observation: int | None = None
        self.distance_level: int | None = None
        self._window_distance: int | None = None
        self._action: int | None = None                 # a_{k-1}: the window's last action
        self._action_ns: int | None = None              # ... and its publication time

    @property
    def epoch(self) -> int:
        return self.epochs.last

    @property
    def recent(self) -> int:
        return self.windows.recent

    @property
    def _levels(self) -> deque:
        return self.windows.levels

    @property
    def _distances(self) -> deque:
        return self.windows.distances

    # -- inputs ----------------------------------------------------------------------------
    def sample(self, level: int, published_ns: int) -> None:
        """One joint-state sample's velocity level O in 1..3."""
        self.windows.sample(level, published_ns)

    def skeleton(self, d: int, published_ns: int) -> None:
        """One skeleton's distance level."""
        self.windows.skeleton(d, published_ns)

    def action(self, action: int, published_ns: int | None = None) -> None:
        self._action, self._action_ns = action, published_ns

    def response(self, published_ns: int) -> EstimatorStep | None:
        """An `hrc/human_response` was published (its value is read from x_k's commitment);
        completes a held b_k whose x_k came first and shows a refusal this answer explains."""
        x_k = self.posterior.response(published_ns)
        return None if x_k is None else self._complete(x_k)

    def task_state(self, state: dict, published_ns: int) -> EstimatorStep | None:
        """A task state from the task manager; completes a held b_k when it is x_k."""
        x_k = self.posterior.task_state(state, published_ns)
        return None if x_k is None else self._complete(x_k)

    # -- the hold --------------------------------------------------------------------------
    def _hold_ns(self) -> int:
        """The hold (`task_state_timeout_s`, else a part of the period). The last period known
        stands in after a restart of the count, until the new one is known: the 0.3 s fallback
        is longer than the decision node's wait below a 0.6 s period."""
        period = self.epochs.period.period_ns
        if period is not None:
            self._known_period_ns = period
        return ESTIMATOR_HOLD.ns(self.task_state_timeout_s, self._known_period_ns)

    @property
    def deadline(self) -> int | None:
        return self.posterior.deadline(self.hold_ns)

    def expire(self, now: int) -> EstimatorStep | None:
        if self.deadline is not None and now >= self.deadline:
            held = self.posterior.held
            if held.x_k is not None:            # x_k came, its answer did not: unanswered
                return self._complete(held.x_k)
            step = self._complete(None)
            step.reports.append(Report(
                WARN, 'epoch', f'epoch {held.epoch}: no task state within the hold; the '
                "human's answer is left out of the posterior update", {'epoch': held.epoch},
                kind='no_task_state'))
            return step
        return None

    # -- the filter update -----------------------------------------------------------------
    def _complete(self, task_after: tuple | None) -> EstimatorStep:
        """The held b_k's update, with the evidence x_k (`task_after`) shows."""
        held = self.posterior.take()
        reports: list[Report] = []
        evidence = self.posterior.evidence(held, task_after, self.filter.model, self.belief,
                                           reports)
        self.posterior.completed(task_after, any(r.kind == 'no_answer' for r in reports))
        self.belief = self.filter.update(self.belief, held.action, held.observation, evidence)
        return EstimatorStep(held.epoch, None, None, self.belief if held.publish else None,
                             reports)

    def _observe(self, step: EstimatorStep, k: int, action: int, counts: np.ndarray,
                 posterior: bool) -> None:
        """O_k from the window's counts, and b_k now (bayes, table) or the first b_1."""
        if counts.sum() >= self.min_window_samples:
            self.observation = window_level(np.repeat(np.array(OBSERVATION_LEVELS), counts))
            if self.belief is None:
                self.belief = self.filter.initial(self.observation)
            elif not posterior:
                self.belief = self.filter.update(self.belief, action, self.observation)
            step.observation = self.observation
            step.belief = None if posterior else self.belief
            return
        self.observation = None
        if self.belief is not None and not posterior:
            self.belief = self.filter.update(self.belief, action, NO_EVIDENCE)
        step.reports.append(Report(
            WARN, 'epoch', f'epoch {k}: no joint states to observe ({int(counts.sum())} '
            f'valid samples in its window, fewer than {self.min_window_samples}); belief not '
            'published (predicted only)', {'epoch': k}, kind='no_observation'))

    def _distance(self, step: EstimatorStep, k: int, distances: list) -> int | None:
        """d_k from the window's latest skeleton; d_{k-1} (None without a skeleton)."""
        d_before = self._window_distance
        self._window_distance = max(distances)[1] if distances else None
        if distances:
            self.distance_level = step.distance_level = self._window_distance
        else:
            step.reports.append(Report(WARN, 'epoch', f'epoch {k}: no skeleton since the last '
                                       'epoch; distance level not published', {'epoch': k},
                                       kind='no_skeleton'))
        return d_before

    def epoch_signal(self, k: int, stamp: Stamp, now: int | None = None) -> EstimatorStep:
        """Close window k at the signal's source timestamp; `InputError` for an epoch of
        another source (`EpochFollower`). `now` (the node's clock) starts a posterior hold."""
        signal_ns = stamp.published_ns
        step = EstimatorStep(k, None, None, None)
        restart = self.epochs.check(k, stamp)
        if restart is not None:
            step.reports.append(restart)
        if self.posterior.held is not None:          # the previous epoch's x_k never came
            step.reports.extend(self.expire(self.posterior.held.since_ns + self.hold_ns)
                                .reports)
        self.epochs.take(k, stamp)
        self.hold_ns = self._hold_ns()              # the period is known from epoch 2 on
        action = DN if self._action is None else self._action
        counts, distances = self.windows.close(signal_ns)
        d_before = self._distance(step, k, distances)
        posterior = self.filter.mode == 'posterior' and self.belief is not None
        if posterior:
            observed = counts.sum() >= self.min_window_samples
            self.posterior.hold(
                k, signal_ns, now if now is not None else signal_ns, action, self._action_ns,
                window_level(np.repeat(np.array(OBSERVATION_LEVELS), counts)) if observed
                else NO_EVIDENCE, observed, d_before, step.distance_level)
        self._observe(step, k, action, counts, posterior)
        self._action = self._action_ns = None
        early = self.posterior.signalled(signal_ns)
        x_k = self.posterior.offer(early) if early is not None else None
        if x_k is not None:                  # x_k was delivered before the signal
            done = self._complete(x_k)
            step.belief = done.belief
            step.reports.extend(done.reports)
        return step


# -- the simulated cell -----------------------------------------------------------------------
@dataclass(frozen=True)
class Pairing:
    """React to `action` with `task_state` (None: none received yet); `late` says why the cell
    reacts without its epoch's task state, or is ''."""

    action: int
    task_state: dict | None
    late: str = ''


class ActionPairing:
    """The simulated cell's pairing of a_k with x_k (docs/DESIGN.md).

    The cell reacts to an action with the first task state received since its last reaction
    (x_k). An action that arrives first is held until x_k arrives, at most `timeout_ns`; then,
    or when a second action arrives first, the held one is answered with the latest task
    state, with a warning.
    """

    def __init__(self, timeout_ns: int):
        self.timeout_ns = int(timeout_ns)
        self.task_state: dict | None = None
        self.fresh = False           # the task state was received since the last reaction
        self.held: int | None = None
        self.held_since: int | None = None

    @property
    def deadline(self) -> int | None:
        return None if self.held_since is None else self.held_since + self.timeout_ns

    def _pair(self, action: int, late: str = '') -> Pairing:
        self.held, self.held_since, self.fresh = None, None, False
        return Pairing(action, self.task_state, late)

    def task_state_received(self, task_state: dict, now: int) -> list[Pairing]:
        self.task_state, self.fresh = task_state, True
        return [self._pair(self.held)] if self.held is not None else []

    def action_received(self, action: int, now: int) -> list[Pairing]:
        out = []
        if self.held is not None:     # two actions without a task state between them
            out.append(self._pair(self.held, 'no task state before the next action'))
        if self.fresh:
            out.append(self._pair(action))
        else:
            self.held, self.held_since = action, now
        return out

    def expire(self, now: int) -> list[Pairing]:
        if self.deadline is not None and now >= self.deadline:
            return [self._pair(self.held, 'no task state within task_state_timeout')]
        return []
