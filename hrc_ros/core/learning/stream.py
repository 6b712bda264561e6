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

With a queue (MODEL.md 8.1; `fit_queue_stream`, hrc-fit --stream on a base with
`stream.queue`) the releases are counted from the tasks waiting, `Recording.queued`: for a pair
k, k+1 as above, the step of x_k under a_k says whether the cell was left idle; if it was and
x_{k+1} has a task, that task entered (entered = 1, a draw of q), else entered = 0 (x_{k+1} must
then be the step's task, or idle with nothing waiting). released_k = queued_{k+1} - queued_k +
entered, a trial of `arrival_busy` if x_k had a task (tp > 0), of `arrival_idle` if not. The
model releases at most one task per epoch (a Bernoulli): an epoch with two or more releases is
one success, and counted (`multiple`, `multiple_tasks`) with a warning. A pair the step cannot
explain or with a negative release is left out and counted; a pair with `queued` unknown (-1)
or at the ROS cap (255: "255 or more") at either end is skipped. `queue` and `waiting_cost`
are the base configuration's: L is a design choice and w a cost the user sets, not fitted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model import TASK_VARIABLES, step_task
from .recordings import MAX_QUEUED, Recording

BOOTSTRAP = 1000


class _Counted:
    """What the two counted streams share: q from the entered tasks' counts, the printed
    estimate lines and the q lines (`tasks`, `counts`, `intervals` are the subclass's)."""

    @staticmethod
    def share(hits: int, trials: int) -> float | None:
        return hits / trials if trials else None

    @property
    def q(self) -> np.ndarray:
        total = self.counts.sum()
        return self.counts / total if total else self.counts.astype(float)

    def estimate_line(self, name: str, value, n: int) -> str:
        lo, hi = self.intervals.get(name, (float('nan'), float('nan')))
        shown = 'n/a' if value is None else f'{value:.4f}'
        return f'  {name}: {shown} [{lo:.4f}, {hi:.4f}] from {n} trials'

    def q_lines(self) -> list[str]:
        out = []
        for t, p in zip(self.tasks, self.q):
            lo, hi = self.intervals.get(f'q{tuple(int(v) for v in t)}', (np.nan, np.nan))
            out.append(f'  q{tuple(int(v) for v in t)}: {p:.4f} [{lo:.4f}, {hi:.4f}]')
        return out

    def q_report(self) -> list:
        return [[*map(int, t), float(p)] for t, p in zip(self.tasks, self.q)]


@dataclass
class StreamFit(_Counted):
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
        return self.share(self.idle_arrivals, self.idle_trials)

    @property
    def arrival_complete(self) -> float | None:
        return self.share(self.complete_arrivals, self.complete_trials)

    def section(self) -> dict:
        """The configuration's `stream` section (q null when nothing arrived: the model's
        uniform tasks). A kind of trial never seen gives probability 0, with a warning."""
        return {'arrival_idle': round(self.arrival_idle or 0.0, 6),
                'arrival_complete': round(self.arrival_complete or 0.0, 6),
                'q': _q_rows(self.tasks, self.counts, self.q)}

    def header(self) -> str:
        """The fitted configuration's header line about the stream."""
        return (f'Stream (MODEL.md 8) counted: arrival_idle from {self.idle_trials} '
                f'idle epochs, arrival_complete from {self.complete_trials} completions, '
                f'q from {int(self.counts.sum())} arrivals; intervals in the report.')

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
                'q': self.q_report(),
                'intervals': {k: list(v) for k, v in self.intervals.items()},
                'left_out': self.left_out, 'gaps': self.gaps, 'warnings': self.warnings()}

    def lines(self) -> list[str]:
        est = self.estimate_line
        out = ['stream (MODEL.md 8):', est('arrival_idle', self.arrival_idle, self.idle_trials),
               est('arrival_complete', self.arrival_complete, self.complete_trials)]
        out += self.q_lines()
        out.append(f'  {self.left_out} pair(s) the task step cannot explain, {self.gaps} skipped '
                   '(epoch gap or no action)')
        out += [f'  warning: {w}' for w in self.warnings()]
        return out


def _q_rows(tasks, counts, q):
    """q as the configuration's rows to 6 decimals (None when nothing arrived), the rounding's
    remainder on the most frequent task, where it cannot push an entry below 0."""
    if not counts.sum():
        return None
    rows = [[int(tp), int(tc), int(tx), round(float(p), 6)] for (tp, tc, tx), p in zip(tasks, q)]
    top = int(np.argmax(counts))
    rows[top][3] = round(1.0 - sum(r[3] for i, r in enumerate(rows) if i != top), 6)
    return rows


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
    _bootstrap(fitted, ('arrival_idle', 'arrival_complete'), arrived, kinds, unique, counts,
               bootstrap, seed)
    return fitted


def _bootstrap(fitted, names, hits, kinds, unique, counts, bootstrap: int, seed: int) -> None:
    """Percentile intervals into `fitted.intervals`: each rate (`names` for the trial kinds
    0 and 1) by resampling its trials, q by multinomial draws of the entered tasks."""
    if not bootstrap:
        return
    rng = np.random.default_rng(seed)
    for kind, name in enumerate(names):
        trials = hits[kinds == kind].astype(float)
        if trials.size:
            means = rng.choice(trials, size=(bootstrap, trials.size)).mean(axis=1)
            fitted.intervals[name] = tuple(float(v) for v in
                                           np.quantile(means, [0.025, 0.975]))
    if counts.sum():
        draws = rng.multinomial(counts.sum(), fitted.q, size=bootstrap) / counts.sum()
        for j, t in enumerate(unique):
            fitted.intervals[f'q{tuple(int(v) for v in t)}'] = tuple(
                float(v) for v in np.quantile(draws[:, j], [0.025, 0.975]))


# -- the stream with a queue (MODEL.md 8.1) ---------------------------------------------------
class StreamError(ValueError):
    """The recordings cannot give the stream the base configuration asks for (one line)."""


def check_queued(recordings: list[Recording]) -> None:
    """StreamError naming the first recording without the tasks waiting per epoch, which the
    queue's releases are counted from."""
    for rec in recordings:
        if rec.queued is None or not (rec.queued >= 0).any():
            raise StreamError(
                f'{rec.name} has no queued (the tasks waiting per epoch), which --stream needs '
                'for a base with stream.queue (MODEL.md 8.1): record hrc/task_state from a task '
                'manager with a queue (its ninth value) or give the CSV a queued column; '
                'releases are not counted from hrc/task_request')


@dataclass
class QueueStreamFit(_Counted):
    """The counted release trials of the queue's stream, the estimates and their intervals
    (the module docstring); `queue`, `waiting_cost` are the base's, written as they are."""

    queue: int
    waiting_cost: float
    idle_trials: int
    idle_releases: int
    busy_trials: int
    busy_releases: int
    tasks: np.ndarray                 # (K, 3) the tasks that entered (tp, tc, tx), sorted
    counts: np.ndarray                # (K,) how often each entered
    left_out: int                     # pairs the step or the count cannot explain
    gaps: int                         # pairs skipped: epoch gap, no action, queued unknown
    multiple: int                     # epochs with two or more releases (counted as one)
    multiple_tasks: int               # the releases in those epochs
    intervals: dict = field(default_factory=dict)   # name -> (low, high)

    @property
    def arrival_idle(self) -> float | None:
        return self.share(self.idle_releases, self.idle_trials)

    @property
    def arrival_busy(self) -> float | None:
        return self.share(self.busy_releases, self.busy_trials)

    def section(self) -> dict:
        """The configuration's `stream` section with the base's queue and waiting_cost."""
        return {'queue': int(self.queue), 'arrival_idle': round(self.arrival_idle or 0.0, 6),
                'arrival_busy': round(self.arrival_busy or 0.0, 6),
                'waiting_cost': self.waiting_cost,
                'q': _q_rows(self.tasks, self.counts, self.q)}

    def header(self) -> str:
        return (f'Stream with a queue (MODEL.md 8.1) counted from the tasks waiting: '
                f'arrival_idle from {self.idle_trials} epochs started idle, arrival_busy from '
                f'{self.busy_trials} started with a task, q from {int(self.counts.sum())} tasks '
                f'entered; queue (L = {self.queue}) and waiting_cost (w = {self.waiting_cost:g}) '
                "are the base's, not fitted; intervals in the report.")

    def warnings(self) -> list[str]:
        out = []
        if not self.idle_trials:
            out.append('no epoch started idle: arrival_idle is not identified (0)')
        if not self.busy_trials:
            out.append('no epoch started with a task: arrival_busy is not identified (0)')
        if not self.counts.sum():
            out.append('no task entered: q is the model\'s (every task equally likely)')
        if self.multiple:
            out.append(f'{self.multiple} epoch(s) released two or more tasks '
                       f'({self.multiple_tasks} in all), each counted as one release: the model '
                       'releases at most one per epoch, so the rate is underestimated '
                       '(shorten the epoch)')
        return out

    def report(self) -> dict:
        return {'queue': self.queue, 'waiting_cost': self.waiting_cost,
                'arrival_idle': self.arrival_idle, 'arrival_busy': self.arrival_busy,
                'idle_trials': self.idle_trials, 'idle_releases': self.idle_releases,
                'busy_trials': self.busy_trials, 'busy_releases': self.busy_releases,
                'multiple': self.multiple, 'multiple_tasks': self.multiple_tasks,
                'q': self.q_report(),
                'intervals': {k: list(v) for k, v in self.intervals.items()},
                'left_out': self.left_out, 'gaps': self.gaps, 'warnings': self.warnings()}

    def lines(self) -> list[str]:
        est = self.estimate_line
        out = [f'stream with a queue (MODEL.md 8.1; queue {self.queue} and waiting_cost '
               f'{self.waiting_cost:g} from the base, not fitted):',
               est('arrival_idle', self.arrival_idle, self.idle_trials),
               est('arrival_busy', self.arrival_busy, self.busy_trials)]
        out += self.q_lines()
        out.append(f'  {self.left_out} pair(s) the task step or the queue count cannot explain, '
                   f'{self.gaps} skipped (epoch gap, no action or queued unknown)')
        out += [f'  warning: {w}' for w in self.warnings()]
        return out


def queue_trials(recordings: list[Recording]):
    """(kind, released, entered task or None) per trial, kind 0 idle / 1 busy (x_k had a task),
    and the counts of pairs left out and skipped (the module docstring)."""
    kinds, released, tasks = [], [], []
    left_out = gaps = 0
    for rec in recordings:
        if len(rec) < 2:
            continue
        queued = (np.full(len(rec), -1, dtype=np.int64) if rec.queued is None
                  else np.asarray(rec.queued, dtype=np.int64))
        known = (queued >= 0) & (queued < MAX_QUEUED)
        now, nxt = rec.task[:-1], rec.task[1:]
        ok = ((np.diff(rec.epoch) == 1) & (rec.action[:-1] >= 0) & known[:-1] & known[1:])
        gaps += int((~ok).sum())
        for k in np.flatnonzero(ok):
            x = {n: np.asarray(now[k, i]) for i, n in enumerate(TASK_VARIABLES)}
            step = step_task(x, int(rec.action[k]), bool(rec.accepted[k] == 1))
            task = tuple(int(nxt[k, i]) for i in range(3))
            entered = None
            if int(step['tp']) != 0:
                if task != tuple(int(step[n]) for n in ('tp', 'tc', 'tx')):
                    left_out += 1      # busy after the step: the next state must be its task
                    continue
            elif task[0] != 0:
                if int(nxt[k, 3]) != 0:
                    left_out += 1      # a task that entered is uncommitted
                    continue
                entered = task
            elif queued[k + 1] > 0:
                left_out += 1          # idle with tasks waiting: the head would have entered
                continue
            count = int(queued[k + 1] - queued[k]) + (entered is not None)
            if count < 0:
                left_out += 1          # fewer waiting than the entry explains
                continue
            kinds.append(0 if int(now[k, 0]) == 0 else 1)
            released.append(count)
            tasks.append(entered)
    return (np.array(kinds, dtype=np.int64), np.array(released, dtype=np.int64), tasks,
            left_out, gaps)


def fit_queue_stream(recordings: list[Recording], queue: int, waiting_cost: float,
                     bootstrap: int = BOOTSTRAP, seed: int = 0) -> QueueStreamFit:
    """Count the queue's release trials in `recordings` (each needs `queued`: `check_queued`)
    and bootstrap their 95% intervals; `queue`, `waiting_cost`: the base's L and w."""
    check_queued(recordings)
    kinds, released, entered, left_out, gaps = queue_trials(recordings)
    success = released >= 1
    came = np.array([t for t in entered if t is not None], dtype=np.int64).reshape(-1, 3)
    unique, inverse = (np.unique(came, axis=0, return_inverse=True) if len(came)
                       else (np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)))
    counts = np.bincount(inverse.reshape(-1), minlength=len(unique))
    many = released >= 2
    fitted = QueueStreamFit(int(queue), waiting_cost,
                            int((kinds == 0).sum()), int((success & (kinds == 0)).sum()),
                            int((kinds == 1).sum()), int((success & (kinds == 1)).sum()),
                            unique, counts, left_out, gaps, int(many.sum()),
                            int(released[many].sum()))
    _bootstrap(fitted, ('arrival_idle', 'arrival_busy'), success, kinds, unique, counts,
               bootstrap, seed)
    return fitted


# -- the stream a base configuration asks for (hrc-fit --stream, the plant's fit.stream) -----
def check_stream(recordings: list[Recording], base) -> None:
    """StreamError (`check_queued`) when `base` has `stream.queue` and a recording lacks the
    tasks waiting per epoch, which the queue's releases are counted from; nothing otherwise:
    the check hrc-fit --stream makes before any work."""
    if base.queue is not None:
        check_queued(recordings)


def fit_stream_for(recordings: list[Recording], base, bootstrap: int = BOOTSTRAP,
                   seed: int = 0) -> 'StreamFit | QueueStreamFit':
    """The stream of `recordings` in the form `base` (a Config) runs: the counted stream of
    MODEL.md 8 (`fit_stream`), or with `stream.queue` the queue's releases (MODEL.md 8.1,
    `fit_queue_stream`, with the base's queue and waiting_cost); StreamError when the
    recordings cannot give it."""
    if base.queue is None:
        return fit_stream(recordings, bootstrap=bootstrap, seed=seed)
    return fit_queue_stream(recordings, base.queue, base.data['stream']['waiting_cost'],
                            bootstrap=bootstrap, seed=seed)
