"""The task stream fitted from recordings (MODEL.md 8; `hrc-fit --stream`, docs/LEARNING.md).

The stream's parameters are seen directly in what a robot records (the task states per epoch),
so they are counted, not learned by EM: for every pair of consecutive epochs k, k+1 of an
episode (the `epoch` column continues by one: a gap leaves the pair out) with a known action,
the model's task step of x_k under a_k and the answer (`model.step_task`) says whether the
epoch left the cell without a task. If it did, x_{k+1} says whether a task arrived: a trial of
`arrival_idle` when x_k had no task, of `arrival_complete` when x_k's task just completed. The
(tp, tc, tx) of every arrival is a draw of q. A pair whose x_{k+1} the step cannot produce
(a task there that the step leaves none of, or a different one) is left out and counted.

The estimates are the frequencies; the 95% intervals are percentile bootstraps over the
trials (each trial resampled with replacement within its kind, and the arrivals for q), seeded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model import TASK_VARIABLES, step_task
from .recordings import Recording

BOOTSTRAP = 1000


@dataclass
class StreamFit:
    """The counted trials, the estimates and their intervals (see the module docstring)."""

    idle_trials: int
    idle_arrivals: int
    complete_trials: int
    complete_arrivals: int
    tasks: np.ndarray                 # (K, 3) the arrived tasks (tp, tc, tx), sorted
    counts: np.ndarray                # (K,) how often each arrived
    left_out: int                     # pairs the step cannot explain
    gaps: int                         # pairs skipped for an epoch gap or a missing action
    intervals: dict = field(default_factory=dict)   # name -> (low, high)

    @property
    def arrival_idle(self) -> float | None:
        return self.idle_arrivals / self.idle_trials if self.idle_trials else None

    @property
    def arrival_complete(self) -> float | None:
        return self.complete_arrivals / self.complete_trials if self.complete_trials else None

    @property
    def q(self) -> np.ndarray:
        total = self.counts.sum()
        return self.counts / total if total else self.counts.astype(float)

    def section(self) -> dict:
        """The configuration's `stream` section (q null when nothing arrived: the model's
        uniform tasks). A kind of trial never seen gives probability 0, with a warning."""
        rows = None
        if self.counts.sum():
            rows = [[int(tp), int(tc), int(tx), round(float(p), 6)]
                    for (tp, tc, tx), p in zip(self.tasks, self.q)]
            top = int(np.argmax(self.counts))   # the rounding's remainder, where it cannot
            rows[top][3] = round(1.0 - sum(r[3] for i, r in enumerate(rows) if i != top), 6)
        return {'arrival_idle': round(self.arrival_idle or 0.0, 6),
                'arrival_complete': round(self.arrival_complete or 0.0, 6), 'q': rows}

    def warnings(self) -> list[str]:
        out = []
        if not self.idle_trials:
            out.append('no epoch started and ended idle: arrival_idle is not identified (0)')
        if not self.complete_trials:
            out.append('no task completed: arrival_complete is not identified (0)')
        if not self.counts.sum():
            out.append('no task arrived: q is the model\'s (every task equally likely)')
        return out

    def report(self) -> dict:
        return {'arrival_idle': self.arrival_idle, 'arrival_complete': self.arrival_complete,
                'idle_trials': self.idle_trials, 'idle_arrivals': self.idle_arrivals,
                'complete_trials': self.complete_trials,
                'complete_arrivals': self.complete_arrivals,
                'q': [[*map(int, t), float(p)] for t, p in zip(self.tasks, self.q)],
                'intervals': {k: list(v) for k, v in self.intervals.items()},
                'left_out': self.left_out, 'gaps': self.gaps, 'warnings': self.warnings()}

    def lines(self) -> list[str]:
        def est(name, value, n):
            lo, hi = self.intervals.get(name, (float('nan'), float('nan')))
            shown = 'n/a' if value is None else f'{value:.4f}'
            return f'  {name}: {shown} [{lo:.4f}, {hi:.4f}] from {n} trials'
        out = ['stream (MODEL.md 8):', est('arrival_idle', self.arrival_idle, self.idle_trials),
               est('arrival_complete', self.arrival_complete, self.complete_trials)]
        for t, p in zip(self.tasks, self.q):
            lo, hi = self.intervals.get(f'q{tuple(int(v) for v in t)}', (np.nan, np.nan))
            out.append(f'  q{tuple(int(v) for v in t)}: {p:.4f} [{lo:.4f}, {hi:.4f}]')
        out.append(f'  {self.left_out} pair(s) the task step cannot explain, {self.gaps} skipped '
                   '(epoch gap or no action)')
        out += [f'  warning: {w}' for w in self.warnings()]
        return out


def stream_trials(recordings: list[Recording]):
    """(kind, arrived, task) per trial, kind 0 idle / 1 complete, and the counts of pairs left
    out and skipped."""
    kinds, arrived, tasks = [], [], []
    left_out = gaps = 0
    for rec in recordings:
        if len(rec) < 2:
            continue
        now, nxt = rec.task[:-1], rec.task[1:]
        ok = (np.diff(rec.epoch) == 1) & (rec.action[:-1] >= 0)
        gaps += int((~ok).sum())
        for k in np.flatnonzero(ok):
            x = {n: np.asarray(now[k, i]) for i, n in enumerate(TASK_VARIABLES)}
            accepted = bool(rec.accepted[k] == 1)
            step = step_task(x, int(rec.action[k]), accepted)
            tp, tc, tx = (int(nxt[k, i]) for i in range(3))
            if int(step['tp']) != 0:
                # busy after the step: the next task state must be that task
                if (tp, tc, tx) != tuple(int(step[n]) for n in ('tp', 'tc', 'tx')):
                    left_out += 1
                continue
            if tp != 0 and int(nxt[k, 3]) != 0:
                left_out += 1          # a task that arrived is uncommitted
                continue
            kinds.append(0 if int(now[k, 0]) == 0 else 1)
            arrived.append(tp != 0)
            tasks.append((tp, tc, tx))
    return (np.array(kinds, dtype=np.int64), np.array(arrived, dtype=bool),
            np.array(tasks, dtype=np.int64).reshape(-1, 3), left_out, gaps)


def fit_stream(recordings: list[Recording], bootstrap: int = BOOTSTRAP, seed: int = 0
               ) -> StreamFit:
    """Count the stream's trials in `recordings` and bootstrap their 95% intervals."""
    kinds, arrived, tasks, left_out, gaps = stream_trials(recordings)
    came = tasks[arrived]
    unique, inverse = (np.unique(came, axis=0, return_inverse=True) if len(came)
                       else (np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)))
    counts = np.bincount(inverse.reshape(-1), minlength=len(unique))
    fitted = StreamFit(int((kinds == 0).sum()), int((arrived & (kinds == 0)).sum()),
                       int((kinds == 1).sum()), int((arrived & (kinds == 1)).sum()),
                       unique, counts, left_out, gaps)
    if bootstrap:
        rng = np.random.default_rng(seed)
        for name, kind in (('arrival_idle', 0), ('arrival_complete', 1)):
            trials = arrived[kinds == kind].astype(float)
            if trials.size:
                means = rng.choice(trials, size=(bootstrap, trials.size)).mean(axis=1)
                fitted.intervals[name] = tuple(float(v) for v in
                                               np.quantile(means, [0.025, 0.975]))
        if counts.sum():
            draws = rng.multinomial(counts.sum(), fitted.q, size=bootstrap) / counts.sum()
            for j, t in enumerate(unique):
                fitted.intervals[f'q{tuple(int(v) for v in t)}'] = tuple(
                    float(v) for v in np.quantile(draws[:, j], [0.025, 0.975]))
    return fitted
