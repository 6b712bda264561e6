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

- `EpochFollower`: which `hrc/epoch` values a follower takes (the next one; 1 after a higher
  one is a restart; anything else is refused).
- `TaskEpochs`: the task manager's bookkeeping of epoch k: hold for a_{k-1} and the answer to
  an eligible request, finalise, begin epoch k; screen late answers; follow restarts.
- `DecisionGate`: the decision node's inputs of epoch k (fresh, stale, malformed, missing),
  the fail-safe rules and the decision itself.
- `ClockStart`: when the decision node's epoch clock may start (graph ready, or waited long
  enough).
- `EstimatorEpochs`: the belief estimator's epoch windows split by the signal's source
  timestamp, O_k, d_k and the belief update.
- `ActionPairing`: the simulated cell's pairing of a_k with the task state x_k.
- `PeriodEstimate`, `timeout_ns`: timeouts that follow the epoch period (a parameter of 0 means
  a fraction of the period; the followers learn the period from the epochs they receive).

`InputError` is the one exception for an unusable input: the ring drops the message with a
throttled warning and a diagnostic.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .model import ACTIONS, DN, OBSERVATION_LEVELS, TASK_VARIABLES, request_eligible
from .decision.observation import window_level
from .tasks import TaskBook, TaskRecord

OK, WARN, ERROR = 'OK', 'WARN', 'ERROR'
RECENT = 2048   # samples per stream kept with their publication time, to split a window:
#                2 s of joint states at 1 kHz, a minute of skeletons at 30 Hz
NO_EVIDENCE = np.ones(9)   # the likelihood of an epoch without an observation: predict only


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


class EpochFollower:
    """Which `hrc/epoch` messages a follower takes: one epoch source at a time.

    The follower locks onto the source of the first epoch it takes. A message of the same
    source continues its count: its writer's sequence number and its epoch advance together
    (the decision node and a bag player publish one message per epoch), or the epoch is the
    next one and the sequence has moved on (the writer's own refused message in between).
    Anything else is another source (a stray `ros2 topic pub`, a second decision node) and is
    refused with `InputError`, so one stray epoch of 4294967295 cannot stop the cell. When the
    followed source has been silent for `SILENT_PERIODS` epoch periods, and at least
    `SILENT_MIN_S` (it stopped or restarted), the next source is followed from where it is:
    a count that starts again at 1 is a restart (a WARN report), another one a new source.
    Without sequence numbers the rule falls back to the count alone: the next epoch, or 1
    after silence.
    """

    def __init__(self):
        self.last = 0                       # the last epoch taken
        self._sequence: int | None = None
        self.last_published_ns: int | None = None
        self.period = PeriodEstimate()
        self.ignored = 0                    # messages of another source

    @property
    def silence_ns(self) -> int:
        return max(timeout_ns(0.0, SILENT_PERIODS, self.period.period_ns, SILENT_FALLBACK_S),
                   int(SILENT_MIN_S * 1e9))

    def _continues(self, k: int, stamp: Stamp) -> bool:
        if self._sequence is None or stamp.sequence is None:
            return k == self.last + 1
        advance = stamp.sequence - self._sequence
        return advance > 0 and k - self.last in (advance, 1)

    def check(self, k: int, stamp: Stamp) -> Report | None:
        """Raise `InputError` if epoch k comes from another source; a WARN report if it starts
        a new count (a restart, or a new source after silence). Call `take` once acted on."""
        if self.last_published_ns is None or self._continues(k, stamp):
            return None
        silent = stamp.published_ns - self.last_published_ns > self.silence_ns
        if not silent:
            self.ignored += 1
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
        if restarted:
            self.period = PeriodEstimate()
        self.last, self._sequence, self.last_published_ns = k, stamp.sequence, stamp.published_ns
        self.period.observe(stamp.published_ns)


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

    Epochs come through an `EpochFollower` (one source; a stray or second source is refused).
    The task book counts the epochs taken (from 1, and from 1 again after a restart), not the
    numbers on `hrc/epoch`, so a number that jumps (lost epochs, a source followed mid-count)
    never releases the schedule early: the schedule's epochs are the cell's epochs.
    """

    def __init__(self, book: TaskBook, input_timeout_ns: int):
        self.book = book
        self.input_timeout_ns = int(input_timeout_ns)
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
        self.book.apply(action, accepted)
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
                'completed_tasks': len(self.book.completed)}


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
    a_k = ``select(belief, x_k)``, x_k = (task state, d), unless a fault makes it dn:

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
                observable = tuple(task[n] for n in TASK_VARIABLES) + (d,)
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


@dataclass(frozen=True)
class Tick:
    """What a tick of the decision node's clock does: start an epoch or wait (with a report)."""

    start_epoch: bool
    report: Report | None = None


class ClockStart:
    """When the decision node's epoch clock starts (timer mode), and a second epoch source.

    Epoch 1 comes one tick after the graph is ready (every input has a publisher and enough
    `hrc/epoch` subscribers are discovered), so that the first epochs are not lost to DDS
    discovery, or, at the latest, at the first tick after `stale_timeout_ns`, with a warning.
    Until then each tick reports that the node waits and publishes no action.

    One cell has one epoch clock. While another node publishes `hrc/epoch` or `hrc/action`
    (`other_sources`), a clock that has not started does not start (ERROR: both identities):
    the newer decision node stays silent and the cell stays deterministic. A running clock
    that sees another source goes on (the followers stay locked onto it) and reports it as
    ERROR at every tick.
    """

    def __init__(self, started_ns: int, stale_timeout_ns: int, running: bool = False):
        self.started_ns = started_ns
        self.stale_timeout_ns = int(stale_timeout_ns)
        self.running = running
        self._ready = False

    def tick(self, now: int, graph_ready: Callable[[], bool],
             graph: Callable[[], dict] = dict, other_sources: Callable[[], list] = list,
             me: str = 'this decision node') -> Tick:
        others = other_sources()
        if others:
            names = ', '.join(others)
            if self.running:
                return Tick(True, Report(
                    ERROR, 'clock', f'another epoch source publishes on the cell: {names}; '
                    f'{me} keeps its clock (the followers stay locked onto it). Stop one.',
                    {'this_node': me, 'other_sources': names}, kind='second_source'))
            return Tick(False, Report(
                ERROR, 'clock', f'another epoch source publishes on the cell: {names}; {me} '
                'does not start its clock while it runs (one cell, one epoch clock)',
                {'this_node': me, 'other_sources': names}, kind='second_source'))
        if self.running:
            return Tick(True)
        waited = _seconds(now - self.started_ns)
        if not (self._ready or now - self.started_ns >= self.stale_timeout_ns):
            if graph_ready():
                self._ready = True          # epoch 1 at the next tick
                return Tick(False)
            return Tick(False, Report(
                WARN, 'decision', 'waiting for the graph: no hrc/epoch subscriber or no input '
                'publisher discovered yet; no action published',
                {'waited_s': waited, **graph()}, log=False, kind='waiting'))
        self.running = True
        if self._ready:
            return Tick(True)
        return Tick(True, Report(WARN, 'clock', f'starting the epoch clock after '
                                 f'{waited:.1f} s without having discovered every input '
                                 'publisher', {'waited_s': waited}, kind='forced_start'))


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


ESTIMATOR_HOLD_FRACTION = 0.4   # posterior hold (task_state_timeout 0): this part of the
ESTIMATOR_HOLD_FALLBACK_S = 0.3  # period (these seconds until it is known). Longer than the
# task manager's hold for the answer (0.25 of the period) so that x_k comes within it, and
# shorter than the decision node's wait for b_k (0.5 of the period).
TASK_STATES_KEPT = 64           # task states and responses kept to find x_{k-1}, x_k, answers


class EstimatorEpochs:
    """The belief estimator's windows (docs/DESIGN.md).

    Window k holds the samples received since epoch k-1's signal that were published before
    epoch k's signal (by source timestamp); a sample published after the signal belongs to
    window k+1 even if it is taken first. On epoch k:

        O_k = window_level(levels of window k's joint-state samples)   (>= min_window_samples)
        b_k = initial(O_k) at the first epoch, else update(b_{k-1}, a_{k-1}, O_k)
        d_k = the distance level of window k's latest skeleton

    A window with too few samples publishes no O and no belief; the belief is carried by the
    prediction alone (`NO_EVIDENCE`), so the next update stays consistent with the actions
    taken. A window without a skeleton publishes no distance level. A missing a_{k-1} counts
    as dn. Only the window's level counts and the last `RECENT` (publication time, level)
    pairs are kept (to split the window at the signal), so memory is bounded at any rate.

    In ``posterior`` mode the update also takes what acting revealed (MODEL.md 6, the exact
    posterior the POMDP plans with): the human's answer to an eligible request and the
    distance move, `HRCModel.transition_likelihood(a_{k-1}, eligible, accepted, d_{k-1},
    d_k)`. Eligibility comes from x_{k-1} (the task state that completed the previous hold,
    else the first published at or after epoch k-1's signal) and the answer from x_k (the
    first published at or after epoch k's signal: the task manager publishes it once it has
    applied a_{k-1} and the answer): accepted means a commitment. So b_k waits for x_k
    (`task_state`), at most `hold_ns` (`deadline`, `expire`; `task_state_timeout_s`, or
    `ESTIMATOR_HOLD_FRACTION` of the period). What is not known is left out of the evidence,
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
        self._task_states: deque = deque(maxlen=TASK_STATES_KEPT)  # (published_ns, task vars)
        self._responses: deque = deque(maxlen=TASK_STATES_KEPT)    # published_ns
        self._x_last: tuple | None = None               # the x_k that completed the last hold
        self._screening = False         # the last request went unanswered (TaskEpochs' rule)
        self._held: _HeldBelief | None = None
        self._last_signal_ns: int | None = None
        self._window_distance: int | None = None
        self.min_window_samples = int(min_window_samples)
        self.recent = recent
        self.epochs = EpochFollower()
        self._known_period_ns: int | None = None
        self.hold_ns = self._hold_ns()
        self.belief: np.ndarray | None = None
        self.observation: int | None = None
        self.distance_level: int | None = None
        self._counts = np.zeros(len(OBSERVATION_LEVELS), dtype=np.int64)  # O levels, window
        self._levels: deque = deque(maxlen=recent)      # (published_ns, O level), window
        self._distances: deque = deque(maxlen=recent)   # (published_ns, d), window
        self._action: int | None = None                 # a_{k-1}: the window's last action
        self._action_ns: int | None = None              # ... and its publication time

    @property
    def epoch(self) -> int:
        return self.epochs.last

    def sample(self, level: int, published_ns: int) -> None:
        """One joint-state sample's velocity level O in 1..3."""
        self._counts[level - 1] += 1
        self._levels.append((published_ns, level))

    def skeleton(self, d: int, published_ns: int) -> None:
        """One skeleton's distance level."""
        self._distances.append((published_ns, d))

    def action(self, action: int, published_ns: int | None = None) -> None:
        self._action, self._action_ns = action, published_ns

    def response(self, published_ns: int) -> EstimatorStep | None:
        """An `hrc/human_response` was published (its value is read from x_k's commitment);
        completes a held b_k whose x_k came first and shows a refusal this answer explains."""
        self._responses.append(published_ns)
        held = self._held
        if held is not None and held.x_k is not None and self._answered(held, held.x_k):
            return self._complete(held.x_k)
        return None

    def _hold_ns(self) -> int:
        """The hold (`task_state_timeout_s`, else a part of the period). The last period known
        stands in after a restart of the count, until the new one is known: the 0.3 s fallback
        is longer than the decision node's wait below a 0.6 s period."""
        period = self.epochs.period.period_ns
        if period is not None:
            self._known_period_ns = period
        return timeout_ns(self.task_state_timeout_s, ESTIMATOR_HOLD_FRACTION,
                          self._known_period_ns, ESTIMATOR_HOLD_FALLBACK_S)

    @property
    def deadline(self) -> int | None:
        return None if self._held is None else self._held.since_ns + self.hold_ns

    def task_state(self, state: dict, published_ns: int) -> EstimatorStep | None:
        """A task state from the task manager; completes a held b_k when it is x_k."""
        self._task_states.append((published_ns, state))
        if self._held is not None and published_ns >= self._held.signal_ns:
            return self._offer((published_ns, state))
        return None

    def _offer(self, x_k: tuple) -> EstimatorStep | None:
        """x_k for the held b_k: complete it, unless x_k shows an eligible request refused and
        its answer has not been seen: nothing orders the task manager's x_k and the human's
        answer at this node (rclpy takes ready messages in subscription order), so b_k waits
        for the answer, at most to the hold's deadline (then: unanswered). A later task state
        while it waits changes nothing: x_k is the first."""
        held = self._held
        if held.x_k is not None:
            return None
        if self._eligible(held, x_k) and x_k[1]['ty'] == 0 and not self._answered(held, x_k):
            held.x_k = x_k
            return None
        return self._complete(x_k)

    def _eligible(self, held: _HeldBelief, x_k: tuple | None) -> bool:
        before = held.task_before
        return before is not None and x_k is not None and bool(
            request_eligible(held.action, before[1]['tp'], before[1]['tx'], before[1]['ty']))

    def _answered(self, held: _HeldBelief, x_k: tuple) -> bool:
        """An answer to a_{k-1} was seen: x_k has the task committed (only an acceptance does
        that), or a response was published between x_{k-1} and x_k; after an unanswered
        request, one published before a_{k-1} is that request's late answer
        (`TaskEpochs._screen`)."""
        if x_k[1]['ty'] != 0:
            return True
        since = held.task_before[0] if held.task_before is not None else 0
        if held.screening and held.action_ns is not None:
            since = max(since, held.action_ns)
        return any(since <= t <= x_k[0] for t in self._responses)

    def expire(self, now: int) -> EstimatorStep | None:
        if self.deadline is not None and now >= self.deadline:
            held = self._held
            if held.x_k is not None:            # x_k came, its answer did not: unanswered
                return self._complete(held.x_k)
            step = self._complete(None)
            step.reports.append(Report(
                WARN, 'epoch', f'epoch {held.epoch}: no task state within the hold; the '
                "human's answer is left out of the posterior update", {'epoch': held.epoch},
                kind='no_task_state'))
            return step
        return None

    def _task_after(self, signal_ns: int | None, before_ns: int | None = None) -> tuple | None:
        """The first task state published at or after a signal (and before `before_ns`):
        (published_ns, task variables)."""
        if signal_ns is None:
            return None
        later = [(t, state) for t, state in self._task_states
                 if t >= signal_ns and (before_ns is None or t < before_ns)]
        return min(later, key=lambda entry: entry[0]) if later else None

    def _evidence(self, held: _HeldBelief, task_after: tuple | None,
                  reports: list) -> np.ndarray | None:
        """P(x_k | x_{k-1}, h, a_{k-1}) of what is known (`HRCModel.transition_likelihood`):
        the answer (an accepted request commits the task, ty != 0 in x_k: a task lasts at
        least one epoch, so it cannot also complete) and the distance move. What is unknown
        or impossible is left out (a WARN in `reports`); None: no evidence at all."""
        model, k = self.filter.model, held.epoch
        eligible = self._eligible(held, task_after)
        if eligible and not self._answered(held, task_after):
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
        if not (self.belief * evidence).sum() > 0.0:
            reports.append(Report(
                WARN, 'epoch', f'epoch {k}: what acting revealed is impossible under the '
                'belief; left out of the posterior update', {'epoch': k},
                kind='impossible_evidence'))
            return None
        return evidence

    def _complete(self, task_after: tuple | None) -> EstimatorStep:
        held, self._held = self._held, None
        reports: list[Report] = []
        evidence = self._evidence(held, task_after, reports)
        self._screening = any(r.kind == 'no_answer' for r in reports)
        self.belief = self.filter.update(self.belief, held.action, held.observation, evidence)
        self._x_last = task_after
        return EstimatorStep(held.epoch, None, None, self.belief if held.publish else None,
                             reports)

    def _split(self, stream: deque, signal_ns: int) -> list:
        """Remove and return the entries published before the signal; later ones stay."""
        window = [e for e in stream if e[0] < signal_ns]
        later = [e for e in stream if e[0] >= signal_ns]
        stream.clear()
        stream.extend(later)
        return window

    def epoch_signal(self, k: int, stamp: Stamp, now: int | None = None) -> EstimatorStep:
        """Close window k at the signal's source timestamp; `InputError` for an epoch of
        another source (`EpochFollower`). `now` (the node's clock) starts a posterior hold."""
        signal_ns = stamp.published_ns
        step = EstimatorStep(k, None, None, None)
        restart = self.epochs.check(k, stamp)
        if restart is not None:
            step.reports.append(restart)
        if self._held is not None:          # the previous epoch's x_k never came
            step.reports.extend(self.expire(self._held.since_ns + self.hold_ns).reports)
        self.epochs.take(k, stamp)
        self.hold_ns = self._hold_ns()              # the period is known from epoch 2 on
        action = DN if self._action is None else self._action
        self._split(self._levels, signal_ns)
        counts = self._counts.copy()          # the window, less what was published later
        self._counts[:] = 0
        for _, level in self._levels:
            self._counts[level - 1] += 1
        counts -= self._counts
        distances = self._split(self._distances, signal_ns)
        d_before = self._window_distance              # d_{k-1}, None without a skeleton
        self._window_distance = max(distances)[1] if distances else None
        if distances:
            self.distance_level = step.distance_level = self._window_distance
        else:
            step.reports.append(Report(WARN, 'epoch', f'epoch {k}: no skeleton since the last '
                                       'epoch; distance level not published', {'epoch': k},
                                       kind='no_skeleton'))
        posterior = self.filter.mode == 'posterior' and self.belief is not None
        if posterior:
            before = self._x_last
            if before is None or self._last_signal_ns is None or before[0] < self._last_signal_ns:
                before = self._task_after(self._last_signal_ns, signal_ns)
            observed = counts.sum() >= self.min_window_samples
            self._held = _HeldBelief(
                k, signal_ns, now if now is not None else signal_ns, action, self._action_ns,
                self._screening,
                window_level(np.repeat(np.array(OBSERVATION_LEVELS), counts)) if observed
                else NO_EVIDENCE, observed, before, d_before, step.distance_level)
        if counts.sum() >= self.min_window_samples:
            self.observation = window_level(np.repeat(np.array(OBSERVATION_LEVELS), counts))
            if self.belief is None:
                self.belief = self.filter.initial(self.observation)
            elif not posterior:
                self.belief = self.filter.update(self.belief, action, self.observation)
            step.observation = self.observation
            step.belief = None if posterior else self.belief
        else:
            self.observation = None
            if self.belief is not None and not posterior:
                self.belief = self.filter.update(self.belief, action, NO_EVIDENCE)
            step.reports.append(Report(
                WARN, 'epoch', f'epoch {k}: no joint states to observe ({int(counts.sum())} '
                f'valid samples in its window, fewer than {self.min_window_samples}); belief not '
                'published (predicted only)', {'epoch': k}, kind='no_observation'))
        self._action = self._action_ns = None
        self._screening = False
        self._last_signal_ns = signal_ns
        self._x_last = None
        early = self._task_after(signal_ns) if self._held is not None else None
        done = self._offer(early) if early is not None else None
        if done is not None:            # x_k was delivered before the signal
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
