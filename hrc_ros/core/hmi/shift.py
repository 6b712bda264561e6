"""The figures of the shift on the operator's console, over a window the operator picks.

Counted with `core.robot.metrics`, the definitions `hrc-evaluate --cell arm` uses, from what
the cell publishes (docs/HMI.md, "The figures of the shift"):

- the arm's time, from `hrc/separation` (its speed bound) and `hrc/protective_stop`: the
  arm's state (protective stop, idle, moving: `metrics.arm_activity`) holds from one message to
  the next, as a control sample of the batch cell holds for its period, and at most
  `ARM_HOLD_S` after the last separation (the robot side went quiet: its time is not measured).
  The idle share and the protective-stop share are per cent of the arm's measured time (the
  batch measures all of it: there the two are the same);
- tasks per hour: tasks completed (a task leaving the cell in `hrc/task_state`) per hour of the
  window;
- refused requests: eligible requests the task manager closed as declined or unanswered;
- the smallest separation S, of every `hrc/separation` sample (while the arm runs);
- fail-safe epochs: epochs whose decision report gives a fail-safe reason.

Times are the messages' source timestamps (the publishers' system clock, ns) and the figures'
`now` is the same clock. The shift begins with the cell's first sign of life the HMI takes
(the decision node's first epoch signal or action, `begin`), so what it counts is what it heard
from then on (a message before is state, not counted). The windows end now and begin
`WINDOWS[name]` seconds before, never before the shift began; counts are kept in bins of
`BIN_S` seconds for the last `KEPT_S`, so a window's start is its bin's (a window is whole
seconds); the shift's totals are kept whole. Nothing here grows with time: a fixed ring of
bins and a few totals.
"""

from __future__ import annotations

import math

import numpy as np

from ..robot.metrics import IDLE, STOP, arm_activity, per_hour, share

ARM_HOLD_S = 2.0              # the arm's state counts this long after its last separation
REORDER_S = 1.0               # the first signs of life may arrive this far out of order
BIN_S = 1                     # seconds per bin
WINDOWS = {'10min': 600, 'hour': 3600, 'shift': None}
WINDOW_WORDS = {'10min': 'last 10 minutes', 'hour': 'last hour', 'shift': 'this shift'}
KEPT_S = 3600                 # the longest window that is not the whole shift
# the columns of a bin: seconds measured / stopped / idle, and counts
ARM, STOPPED, IDLED, TASKS, REFUSED, FAIL_SAFE = range(6)
COLUMNS = 6
FIGURES = ('tasks_per_hour', 'idle_share', 'protective_stop_share', 'refused_requests',
           'min_separation', 'fail_safe_epochs')
S = 1_000_000_000


class ShiftFigures:
    """The shift's counts since `start_ns` (see the module docstring); None: it begins with
    `begin`."""

    def __init__(self, start_ns: int | None = None, bin_s: int = BIN_S, kept_s: int = KEPT_S):
        self.start_ns = None if start_ns is None else int(start_ns)
        self._first = self.start_ns
        self.bin_ns = int(bin_s) * S
        self.slots = int(kept_s) // int(bin_s) + 2
        self._bins = np.zeros((self.slots, COLUMNS))
        self._min = np.full(self.slots, math.inf)
        self._stamp = np.full(self.slots, -1, dtype=np.int64)   # the bin each slot holds
        self.total = np.zeros(COLUMNS)
        self.total_min = math.inf
        self.stopped = False                 # the latest hrc/protective_stop
        self._bound: float | None = None     # the latest speed bound (m/s)
        self._since: int | None = None       # the arm's state holds from here ...
        self._heard: int | None = None       # ... until ARM_HOLD_S after this separation
        self.decisions_seen = False
        self._fail_safe_epoch: int | None = None
        self.changed = False                 # a count, a stop or a new smallest separation

    def begin(self, t: int) -> None:
        """The shift begins at `t` if it has not begun; an earlier first sign of life that
        arrives just after (the first epoch signal overtaken by its action: two topics) moves
        the start back to it, so the start is the first by the cell's clock."""
        t = int(t)
        if self.start_ns is None:
            self.start_ns = self._first = t
        elif self._first - REORDER_S * S <= t < self.start_ns:
            self.start_ns = t

    # -- bins ------------------------------------------------------------------------------
    def _slot(self, t: int) -> int:
        number = t // self.bin_ns
        slot = int(number % self.slots)
        if self._stamp[slot] != number:
            self._stamp[slot] = number
            self._bins[slot] = 0.0
            self._min[slot] = math.inf
        return slot

    def _add(self, t: int, column: int, value: float = 1.0) -> None:
        if self.start_ns is None or t < self.start_ns:
            return                      # before the shift (a latched message from before)
        self._bins[self._slot(t), column] += value
        self.total[column] += value
        self.changed = True

    def _account(self, until: int) -> None:
        """The arm's state from `_since` to `until` (cut at ARM_HOLD_S after the last
        separation), into the bins it spans; `_since` moves on to `until`."""
        since = self._since
        if since is None or self._bound is None or self.start_ns is None:
            if since is not None:
                self._since = max(since, until)
            return
        end = min(until, self._heard + int(ARM_HOLD_S * S))
        start = max(since, self.start_ns)
        if end > start:
            activity = arm_activity(self.stopped, self._bound)
            columns = [ARM] + ([STOPPED] if activity == STOP else [IDLED] if activity == IDLE
                               else [])
            t = start
            while t < end:
                edge = min(end, (t // self.bin_ns + 1) * self.bin_ns)
                slot = self._slot(t)
                for column in columns:
                    self._bins[slot, column] += (edge - t) / S
                t = edge
            for column in columns:
                self.total[column] += (end - start) / S
        self._since = max(since, until)

    # -- what the cell publishes -----------------------------------------------------------
    def arm_sample(self, t: int, separation: float, speed_bound: float) -> None:
        """An `hrc/separation` sample: S (m) and the arm's speed bound (m/s)."""
        t = int(t)
        if self._heard is not None and t - self._heard > ARM_HOLD_S * S:
            self._account(t)            # the robot side was quiet: up to its hold, no further
            self._since = t
        elif self._since is None:
            self._since = t
        else:
            self._account(t)
        self._bound = float(speed_bound)
        self._heard = t if self._heard is None else max(self._heard, t)
        if self.start_ns is not None and t >= self.start_ns:
            slot = self._slot(t)
            self._min[slot] = min(self._min[slot], float(separation))
            if separation < self.total_min:
                self.total_min = float(separation)
                self.changed = True

    def protective_stop(self, t: int, stopped: bool) -> None:
        """`hrc/protective_stop` (published on change)."""
        if bool(stopped) != self.stopped:
            self._account(int(t))
            self.stopped = bool(stopped)
            self.changed = True

    def task_completed(self, t: int) -> None:
        self._add(int(t), TASKS)

    def request_refused(self, t: int) -> None:
        self._add(int(t), REFUSED)

    def decision(self, t: int, epoch: int, failed_safe: bool) -> None:
        """The decision node's report of `epoch`: a fail-safe epoch counts once."""
        self.decisions_seen = True
        if failed_safe and epoch != self._fail_safe_epoch:
            self._fail_safe_epoch = epoch
            self._add(int(t), FAIL_SAFE)

    # -- the figures -----------------------------------------------------------------------
    def window_start(self, now: int, window: str) -> int:
        """Where `window` begins when it ends at `now`: the shift's start, or the start of
        the bin `WINDOWS[window]` seconds before now (never before the shift)."""
        seconds = WINDOWS[window]
        if seconds is None:
            return self.start_ns
        return max(self.start_ns, (int(now) - seconds * S) // self.bin_ns * self.bin_ns)

    def figures(self, now: int, window: str) -> dict | None:
        """The figures over `window` (a key of WINDOWS) ending at `now` (ns); None before the
        shift began."""
        now = int(now)
        if self.start_ns is None:
            return None
        start = self.window_start(now, window)
        if WINDOWS[window] is None:
            sums, smallest = self.total.copy(), self.total_min
        else:
            first, last = start // self.bin_ns, now // self.bin_ns
            inside = (self._stamp >= first) & (self._stamp <= last)
            sums = self._bins[inside].sum(axis=0)
            smallest = float(self._min[inside].min()) if inside.any() else math.inf
        self._open_interval(sums, start, now)
        seconds = max(0, now - start) / S
        arm = float(sums[ARM])
        return {
            'window': window, 'since_ns': start, 'as_of_ns': now, 'seconds': seconds,
            'tasks_completed': int(round(sums[TASKS])),
            'tasks_per_hour': float(per_hour(sums[TASKS], seconds)) if seconds > 0 else None,
            'arm_seconds': arm,
            'idle_share': float(share(sums[IDLED], arm)) if arm > 0 else None,
            'protective_stop_share': float(share(sums[STOPPED], arm)) if arm > 0 else None,
            'refused_requests': int(round(sums[REFUSED])),
            'min_separation': None if math.isinf(smallest) else smallest,
            'fail_safe_epochs': int(round(sums[FAIL_SAFE])) if self.decisions_seen else None,
        }

    def _open_interval(self, sums: np.ndarray, start: int, now: int) -> None:
        """Add the arm's state since its last change, up to now, to `sums` without committing
        it: a message published before now that arrives later is still counted at its time."""
        if self._since is None or self._bound is None:
            return
        begin = max(self._since, self.start_ns, start)
        end = min(now, self._heard + int(ARM_HOLD_S * S))
        if end > begin:
            activity = arm_activity(self.stopped, self._bound)
            sums[ARM] += (end - begin) / S
            if activity in (STOP, IDLE):
                sums[STOPPED if activity == STOP else IDLED] += (end - begin) / S

    def all_windows(self, now: int) -> dict | None:
        """The figures of every window (None before the shift began); `changed` is
        cleared."""
        self.changed = False
        if self.start_ns is None:
            return None
        return {name: self.figures(now, name) for name in WINDOWS}


# How the console shows them (and the browser test compares them): decimals per figure
DECIMALS = {'seconds': 1, 'tasks_per_hour': 1, 'arm_seconds': 1, 'idle_share': 1,
            'protective_stop_share': 1, 'min_separation': 3}


def rounded(figures: dict) -> dict:
    """The figures as the console shows them: times in ms, the rest to DECIMALS."""
    out = {}
    for name, value in figures.items():
        if name.endswith('_ns'):
            out[name[:-3] + '_ms'] = value // 1_000_000
        elif name in DECIMALS and value is not None:
            out[name] = round(value, DECIMALS[name])
        else:
            out[name] = value
    return out
