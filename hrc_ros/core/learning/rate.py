"""The robot's progress rate fitted from recordings (MODEL.md 3.2, `model.robot_rate`;
`hrc-fit --rate`, docs/LEARNING.md).

In the cell with the arm the robot's counter bc falls only when its program completes a cycle,
which SSM slows whenever the person is near (docs/ROBOT.md 4, "physical progress"), so an
epoch in which the robot works ends with its counter down or not. The run does not depend on
the person's hidden emotions (MODEL.md 3.2), so it is counted, not learned by EM: for every
pair of consecutive epochs k, k+1 of an episode (the epoch column continues by one, the action
and d_k known) in which the robot works (a task committed with the robot, ty in {2, 3}, bc > 0,
and an action that does not pause it, `model.robot_paused_by`), the model's task step of x_k
under a_k with the counter running and with it staying (`model.step_task`'s robot_runs) says
which one x_{k+1} is (or a new task entering the cell the step left idle, the task book's rule):
a trial of rate[tx_k, d_k], a success if it ran. A pair that neither explains (or both, which a
working robot's step never gives) is left out and counted.

The estimates are the frequencies per (tx, d); a cell without trials keeps the base's value
(1 without a rate) and says so. The 95% intervals are percentile bootstraps over the trials
(resampled with replacement within each cell), seeded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import RATE_NATURES
from ..model import N_DISTANCE, TASK_VARIABLES, HRCModel
from .recordings import Recording

BOOTSTRAP = 1000


def successor_ok(model: HRCModel | None, task, action, accepted, nxt,
                 robot_runs=None) -> np.ndarray:
    """Whether each next task state follows from (task, action, accepted) by MODEL.md 3.2
    (the rules of `model`, the paper's without one; `robot_runs` as `model.step_task`), or is a
    new task entering the cell that the step left idle (the task book's rule)."""
    from ..model import step_task
    out = np.zeros(len(task), dtype=bool)
    for a in np.unique(action):
        rows = np.flatnonzero(action == a)
        here = {n: task[rows, i] for i, n in enumerate(TASK_VARIABLES)}
        runs = None if robot_runs is None else np.broadcast_to(robot_runs, len(task))[rows]
        stepped = (step_task(here, int(a), accepted[rows], runs) if model is None
                   else model.step_task(here, int(a), accepted[rows], runs))
        stepped = np.stack([stepped[n] for n in TASK_VARIABLES], axis=1)
        same = np.all(stepped == nxt[rows], axis=1)
        entered = ((stepped[:, 0] == 0) & (nxt[rows, 0] > 0) & (nxt[rows, 3] == 0)
                   & np.all(stepped[:, 4:] == nxt[rows, 4:], axis=1))
        out[rows] = same | entered
    return out


def working(model: HRCModel, task: np.ndarray, action: np.ndarray) -> np.ndarray:
    """Whether the robot works in each epoch: committed (ty in {2, 3}) with bc > 0, under an
    action that does not pause it (`model.paused`)."""
    ty, bc = task[:, TASK_VARIABLES.index('ty')], task[:, TASK_VARIABLES.index('bc')]
    return (ty >= 2) & (bc > 0) & ~np.isin(action, model.paused)


@dataclass
class RateFit:
    """The counted trials, the estimates and their intervals (module docstring)."""

    trials: np.ndarray              # (4, 4) working epochs by (tx, d)
    runs: np.ndarray                # (4, 4) those whose counter ran down
    base: np.ndarray                # (4, 4) the base's rate (1 without one)
    left_out: int                   # working pairs neither step explains
    intervals: dict = field(default_factory=dict)     # (tx, d) -> (low, high)

    @property
    def rate(self) -> np.ndarray:
        """(4, 4): the frequency where there are trials, the base's value elsewhere."""
        with np.errstate(invalid='ignore', divide='ignore'):
            return np.where(self.trials > 0, self.runs / np.maximum(self.trials, 1), self.base)

    def section(self) -> dict:
        """model.robot_rate as the configuration writes it: nature -> 4 rates."""
        return {tx: [round(float(v), 4) for v in self.rate[tx]] for tx in RATE_NATURES}

    def lines(self) -> list[str]:
        out = [f'robot_rate (MODEL.md 3.2): P(the robot\'s counter runs down in an epoch it '
               f'works) by the task\'s nature and d; {int(self.trials.sum())} working epochs, '
               f'{self.left_out} left out']
        for tx in RATE_NATURES:
            for d in range(N_DISTANCE):
                n = int(self.trials[tx, d])
                if n:
                    lo, hi = self.intervals.get((tx, d), (np.nan, np.nan))
                    out.append(f'  tx {tx}, d {d}: {self.rate[tx, d]:.4f} [{lo:.4f}, {hi:.4f}] '
                               f'from {n} epochs')
                else:
                    out.append(f'  tx {tx}, d {d}: no epoch; the base\'s '
                               f'{self.base[tx, d]:.4f} kept')
        return out

    def header(self) -> str:
        return (f'model.robot_rate counted from {int(self.trials.sum())} epochs in which the '
                'robot worked (core.learning.rate); a band without one keeps the base\'s value.')

    def report(self) -> dict:
        return {'rate': self.rate.tolist(), 'trials': self.trials.tolist(),
                'runs': self.runs.tolist(), 'left_out': self.left_out,
                'intervals': {f'{tx},{d}': list(v) for (tx, d), v in self.intervals.items()}}


def fit_rate(recordings: list[Recording], model: HRCModel, bootstrap: int = BOOTSTRAP,
             seed: int = 0) -> RateFit:
    """The robot's progress rate of `recordings` read with `model`'s rules (module
    docstring)."""
    trials = np.zeros((4, N_DISTANCE), dtype=np.int64)
    runs = np.zeros((4, N_DISTANCE), dtype=np.int64)
    outcomes: dict = {}
    left_out = 0
    for r in recordings:
        if len(r) < 2:
            continue
        pair = (np.diff(r.epoch) == 1) & (r.action[:-1] >= 0) & (r.d[:-1] >= 0)
        task, nxt, action = r.task[:-1], r.task[1:], r.action[:-1]
        pair &= working(model, task, action)
        rows = np.flatnonzero(pair)
        if not rows.size:
            continue
        refused = np.zeros(rows.size, dtype=bool)     # committed: no request is eligible
        ran = successor_ok(model, task[rows], action[rows], refused, nxt[rows], True)
        stayed = successor_ok(model, task[rows], action[rows], refused, nxt[rows], False)
        clear = ran != stayed
        left_out += int((~clear).sum())
        tx = task[rows, TASK_VARIABLES.index('tx')][clear]
        d = r.d[:-1][rows][clear]
        np.add.at(trials, (tx, d), 1)
        np.add.at(runs, (tx, d), ran[clear].astype(np.int64))
        for t, b, hit in zip(tx, d, ran[clear]):
            outcomes.setdefault((int(t), int(b)), []).append(bool(hit))
    base = np.ones((4, N_DISTANCE)) if model.robot_rate is None else model.robot_rate
    fitted = RateFit(trials, runs, base, left_out)
    if bootstrap:
        rng = np.random.default_rng([seed, 32])
        for key, hits in sorted(outcomes.items()):
            hits = np.asarray(hits, dtype=float)
            means = rng.choice(hits, size=(bootstrap, hits.size)).mean(axis=1)
            fitted.intervals[key] = tuple(float(v) for v in np.percentile(means, [2.5, 97.5]))
    return fitted
