"""The operator's timeline: the last `SPAN_S` seconds of the cell, as rows the console plots.

- ``epochs``: one row an epoch, at its action's source time: ``[t, k, action, motivation,
  aggression, d]``; motivation and aggression are the belief's mean level (0 low .. 2 high, from
  its marginals), d the distance level, action the model's name (the page names it in words);
- ``robot``: the arm, in buckets of `BUCKET_S`: ``[t, S, S_p, override]``, the smallest
  separation of the bucket (at its time) with the protective distance S_p of that sample, and
  the latest speed override; nothing while the robot side is silent;
- ``stops``: the protective stops' edges, ``[t, 1]`` when one begins and ``[t, 0]`` when it ends.

Times are seconds of the system clock (the messages' source timestamps), what the chart's time
axis reads. The rows are kept for `SPAN_S` (a fixed bound: at most a row an epoch and one a
bucket), and `take` hands what is new to the pages at most every `FLUSH_S`, so a page gets a
few small messages a second whatever the rates of the topics.
"""

from __future__ import annotations

from collections import deque

import numpy as np

SPAN_S = 600.0
BUCKET_S = 0.5
FLUSH_S = 0.5
LEVELS = np.arange(3)
S = 1_000_000_000
SERIES = ('epochs', 'robot', 'stops')
MAX_NEW = 5000                # rows waiting for a take, per series


def _seconds(t_ns: int) -> float:
    return round(t_ns / S, 3)


def belief_means(belief) -> tuple[float, float] | tuple[None, None]:
    """(motivation, aggression) mean levels of a 9-probability belief over h = 3*em + ea."""
    if belief is None or np.size(belief) != 9:
        return None, None
    grid = np.asarray(belief, dtype=float).reshape(3, 3)
    return (round(float(grid.sum(axis=1) @ LEVELS), 3),
            round(float(grid.sum(axis=0) @ LEVELS), 3))


class Timeline:
    def __init__(self, span_s: float = SPAN_S, bucket_s: float = BUCKET_S,
                 flush_s: float = FLUSH_S):
        self.span_ns = int(span_s * S)
        self.bucket_ns = int(bucket_s * S)
        self.flush_ns = int(flush_s * S)
        self.rows = {name: deque() for name in SERIES}
        self._new = {name: [] for name in SERIES}
        self._bucket: list | None = None      # [number, t_ns, S, S_p]
        self._override: float | None = None
        self._flushed: int | None = None
        self._newest = 0
        self._last_epoch: int | None = None

    def _append(self, name: str, t_ns: int, row: list) -> None:
        self.rows[name].append(row)
        self._new[name].append(row)
        self._newest = max(self._newest, t_ns)
        self._trim()

    def _trim(self) -> None:
        oldest = (self._newest - self.span_ns) / S
        for rows in self.rows.values():
            while rows and rows[0][0] < oldest:
                rows.popleft()
        for rows in self._new.values():
            if len(rows) > MAX_NEW:
                del rows[:len(rows) - MAX_NEW]     # nobody takes them: a bounded tail

    # -- what the cell publishes -----------------------------------------------------------
    def epoch(self, t_ns: int, k: int, action: str, belief, d: int | None) -> None:
        if k == self._last_epoch:
            return
        self._last_epoch = k
        motivation, aggression = belief_means(belief)
        self._append('epochs', t_ns, [_seconds(t_ns), int(k), action, motivation, aggression,
                                      None if d is None else int(d)])

    def arm_sample(self, t_ns: int, separation: float, protective: float) -> None:
        number = t_ns // self.bucket_ns
        bucket = self._bucket
        if bucket is not None and number != bucket[0]:
            self._close_bucket()
            bucket = None
        if bucket is None:
            self._bucket = [number, t_ns, float(separation), float(protective)]
        elif separation < bucket[2]:
            bucket[1:] = [t_ns, float(separation), float(protective)]

    def override_sample(self, value: float) -> None:
        self._override = float(value)

    def _close_bucket(self) -> None:
        _, t_ns, separation, protective = self._bucket
        self._bucket = None
        self._append('robot', t_ns, [_seconds(t_ns), round(separation, 4), round(protective, 4),
                                     None if self._override is None
                                     else round(self._override, 3)])

    def protective_stop(self, t_ns: int, stopped: bool) -> None:
        self._append('stops', t_ns, [_seconds(t_ns), int(bool(stopped))])

    # -- to the pages ----------------------------------------------------------------------
    def take(self, now_ns: int) -> dict | None:
        """The rows added since the last take, at most every FLUSH_S (None: nothing to send
        yet); a bucket whose time is over is closed first."""
        if self._bucket is not None and now_ns // self.bucket_ns > self._bucket[0]:
            self._close_bucket()
        if not any(self._new.values()):
            return None
        if self._flushed is not None and now_ns - self._flushed < self.flush_ns:
            return None
        self._flushed = now_ns
        new, self._new = self._new, {name: [] for name in SERIES}
        return {name: rows for name, rows in new.items() if rows}

    def snapshot(self) -> dict:
        return {name: list(rows) for name, rows in self.rows.items()}
