"""The operator's event log: what happened in the cell, each with its time and reason in words.

Entries (newest last here; the page shows them newest first), at most `KEPT`:

- ``protective stop``: the robot side stopped the arm (`hrc/protective_stop` true), with the
  bridge's reason (its `ssm` status on /diagnostics, which it publishes with the stop; the
  entry waits for it at most `REASON_WAIT_S`); while it holds, again when the reason changes
  in words (its figures apart: "frozen tracker" then "separation below the protective
  distance"), and ``protective stop over`` with how long;
- ``fail-safe``: the decision node failed safe (its epoch report gives reasons), once when it
  begins and again when the reasons change, and ``fail-safe over`` with how many epochs;
- ``order refused``: the task manager refused an order (this HMI's or another publisher's);
- ``policy``: the decision node swapped its policy, or refused or staged a new one.

Each entry is a dict: ``t_ms`` (the source timestamp of the message that told it, system
clock, ms), ``kind``, ``text`` (words) and ``detail`` (the node's own words, for the curious and
the CSV). `take()` hands the entries added since the last call to the pages.
"""

from __future__ import annotations

import re
from collections import deque

from . import words

KEPT = 200
REASON_WAIT_S = 2.0         # the bridge's health (every second) has the reason too
STOP, STOP_OVER, FAIL_SAFE, FAIL_SAFE_OVER, ORDER_REFUSED, POLICY = (
    'protective stop', 'protective stop over', 'fail-safe', 'fail-safe over', 'order refused',
    'policy')
S = 1_000_000_000


def _words_of(reason: str) -> str:
    """A reason without its figures: what it says, not how much."""
    return re.sub(r'-?\d+(\.\d+)?', '#', reason)


def duration_words(seconds: float) -> str:
    if seconds < 60:
        return f'{seconds:.1f} s'
    minutes, rest = divmod(int(round(seconds)), 60)
    return f'{minutes} min {rest:02d} s'


class EventLog:
    def __init__(self, kept: int = KEPT):
        self.entries: deque[dict] = deque(maxlen=kept)
        self._new: list[dict] = []
        self.stopped = False
        self._stop_since: int | None = None
        self._pending_stop: int | None = None        # a stop waiting for its reason
        self._stop_reason: tuple | None = None       # (t, reason) of the bridge's last report
        self._logged_reason: str | None = None       # the words of the reason last logged
        self._fail_safe: tuple | None = None         # (first epoch, reasons) while failing safe
        self._fail_safe_last = 0

    def add(self, t: int, kind: str, text: str, detail: str = '') -> dict:
        entry = {'t_ms': int(t) // 1_000_000, 'kind': kind, 'text': text, 'detail': detail}
        self.entries.append(entry)
        self._new.append(entry)
        del self._new[:-self.entries.maxlen]
        return entry

    def take(self) -> list[dict]:
        """The entries added since the last call, oldest first."""
        new, self._new = self._new, []
        return new

    # -- protective stops ------------------------------------------------------------------
    def protective_stop(self, t: int, stopped: bool) -> None:
        if bool(stopped) == self.stopped:
            return
        self.stopped = bool(stopped)
        if stopped:
            self._stop_since = self._pending_stop = int(t)
            reason = self._stop_reason
            if reason is not None and abs(reason[0] - t) <= REASON_WAIT_S * S:
                self._emit_stop(reason[1])
        else:
            if self._pending_stop is not None:
                self._emit_stop('')
            took = '' if self._stop_since is None else \
                f' after {duration_words((t - self._stop_since) / S)}'
            self.add(t, STOP_OVER, f'the arm moves again: protective stop over{took}')

    def stop_reason(self, t: int, stopped: bool, reason: str) -> None:
        """The bridge's `ssm` status: stopped and why (reported with each new stop, and while
        the reason's figures change, at most once a second)."""
        if stopped and reason:
            self._stop_reason = (int(t), reason)
            if self._pending_stop is not None and abs(t - self._pending_stop) <= \
                    REASON_WAIT_S * S:
                self._emit_stop(reason)
            elif self.stopped and self._pending_stop is None \
                    and _words_of(reason) != self._logged_reason:
                self._logged_reason = _words_of(reason)
                self.add(t, STOP, f'the arm stays stopped for safety: {reason}', reason)

    def _emit_stop(self, reason: str) -> None:
        t, self._pending_stop = self._pending_stop, None
        self._logged_reason = _words_of(reason)
        self.add(t, STOP, 'the arm stopped for safety' + (f': {reason}' if reason else
                                                          ' (the robot side gave no reason)'),
                 reason)

    def expire(self, now: int) -> None:
        """A stop whose reason did not come within REASON_WAIT_S is logged without it."""
        if self._pending_stop is not None and now - self._pending_stop > REASON_WAIT_S * S:
            self._emit_stop('')

    # -- fail-safes ------------------------------------------------------------------------
    def decision(self, t: int, epoch: int, faults: list[str]) -> None:
        """The decision node's report of `epoch`: its fail-safe reasons ([] none). A new entry
        when a fail-safe begins or its reasons change in words (not when only an age does)."""
        if faults:
            reasons = words.fail_safe_words(faults)
            if self._fail_safe is None or self._fail_safe[1] != reasons:
                first = epoch if self._fail_safe is None else self._fail_safe[0]
                self._fail_safe = (first, reasons)
                self.add(t, FAIL_SAFE, f'the robot stopped for safety at step {epoch}: '
                         f'{reasons}', '; '.join(faults))
            self._fail_safe_last = epoch
        elif self._fail_safe is not None:
            count = max(1, self._fail_safe_last - self._fail_safe[0] + 1)
            self._fail_safe = None
            self.add(t, FAIL_SAFE_OVER, f'the robot decides again at step {epoch}: fail-safe '
                     f'over after {words.steps(count)}')

    # -- orders and policies ---------------------------------------------------------------
    def order_refused(self, t: int, task, text: str, source: str) -> None:
        what = words.task_words(*task) if task is not None and len(task) == 3 else \
            'a malformed order'
        self.add(t, ORDER_REFUSED, f'order from {source} refused ({what}): '
                 f'{text.removeprefix("refused: ")}', text)

    def policy(self, t: int, level: str, message: str, values: dict) -> None:
        """The decision node's `policy` status: a swap (OK), staged (WARN) or refused."""
        if level == 'OK' and values.get('policy_file'):
            epoch, before = values.get('epoch', '?'), values.get('previous_policy_file', '?')
            self.add(t, POLICY, f'new policy in use from step {epoch}: '
                     f'{values["policy_file"]} (before: {before})', message)
        elif level == 'WARN':
            self.add(t, POLICY, 'a new configuration is set but not in use; the robot keeps its '
                     f'policy {values.get("policy_file", "")}', message)
        elif level == 'ERROR':
            self.add(t, POLICY, 'a new policy was refused; the robot keeps '
                     f'{values.get("policy_file", "its policy")}: {values.get("error", "")}',
                     message)
