"""Task and activity bookkeeping of the cell: the observable half of MODEL.md 3.2.

The model treats new tasks as exogenous: `model.step_task` moves a task through commitment and
completion, but it never creates one. Someone has to hold the pending tasks and hand them to the
cell one at a time; that is the task book. It keeps the paper's eight observable task/activity
variables (symbols as in the paper)

    tp, tc, tx, ty    task priority (0 = no task), remaining epochs, nature, commitment
    hp, hc, bp, bc    human / robot activity priority and remaining epochs

and a FIFO queue of released tasks (tp, tc, tx). One epoch k (docs/DESIGN.md) is

    begin_epoch(k)           scheduled tasks due at k join the queue; an idle cell (tp = 0)
                             takes the queue head, uncommitted (ty = 0);
    observable(d)            (tp, tc, tx, ty, hp, hc, bp, bc, d) for the decision;
    apply(action, accepted)  the rules of MODEL.md 3.2 via `model.step_task`, nothing else.

So a released task enters the cell only when the previous one is complete, which is how the
paper's case study feeds its three tasks. The book also keeps a record of every task (release,
start, commitment and completion epochs) so that a simulation or the ROS task manager can report
how long tasks took. Schedules are written ``"epoch:tp,tc,tx"`` (the `schedule` parameter of the
task manager node); `parse_schedule` reads them.
"""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np

from .model import TASK_VARIABLES, HRCModel, action_index

_ENTRY = re.compile(r'^\s*(\d+)\s*:\s*(\d+)\s*,\s*(\d+)\s*,\s*(\d+)\s*$')


def robot_cycle_done(cycles: int, cycles_done: int, bc: int) -> bool:
    """The physical progress rule (docs/ROBOT.md, "physical progress"): the robot's counter bc
    runs down this epoch (`TaskBook.apply`'s `robot_runs`) only if its program, asked for
    `cycles` cycles of which `cycles_done` are complete at the epoch's end, has completed a
    cycle that bc has not counted yet (bc cycles were left at the epoch's start). The batch
    cell with the arm and the task manager with `robot_progress` apply this one rule."""
    return int(cycles_done) > int(cycles) - int(bc)


@dataclass
class TaskRecord:
    """One task's life in the cell; epochs are None until the event happens."""

    task_id: int
    tp: int
    tc: int
    tx: int
    release_epoch: int                   # joined the queue (or was present at epoch 1)
    start_epoch: int | None = None       # entered the cell (tp, tc, tx set, ty = 0)
    commit_epoch: int | None = None      # the epoch whose action committed it (ty != 0)
    complete_epoch: int | None = None    # the epoch whose action completed it

    @property
    def epochs_to_complete(self) -> int | None:
        """Epochs from release through completion, both counted (None if not complete)."""
        if self.complete_epoch is None:
            return None
        return self.complete_epoch - self.release_epoch + 1


def parse_schedule_entry(text: str) -> tuple[int, tuple[int, int, int]]:
    """``"9:2,2,1"`` -> ``(9, (2, 2, 1))``: release epoch, then (tp, tc, tx)."""
    if not isinstance(text, str):
        raise ValueError(f'a schedule entry is a string "epoch:tp,tc,tx", got {text!r}')
    match = _ENTRY.match(text)
    if not match:
        raise ValueError(f'bad schedule entry {text!r}: expected "epoch:tp,tc,tx" with '
                         'non-negative integers, for example "9:2,2,1"')
    epoch, tp, tc, tx = (int(g) for g in match.groups())
    if epoch < 1:
        raise ValueError(f'bad schedule entry {text!r}: epochs are numbered from 1')
    return epoch, (tp, tc, tx)


def parse_schedule(entries: str | Iterable[str]) -> list[tuple[int, tuple[int, int, int]]]:
    """Parse schedule entries: a list of strings, or one string separated by ';' or spaces."""
    if isinstance(entries, str):
        parts = entries.split(';') if ';' in entries else entries.split()
        entries = [e for e in parts if e.strip()]
    return [parse_schedule_entry(e) for e in entries]


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


TASK_FIELDS = {'tp': 'priority', 'tc': 'duration in epochs',
               'tx': 'nature (0 robot, 1 human, 2 either, 3 both)'}


def check_task(task, rho: int, sigma: int) -> tuple[int, int, int]:
    """A new task (tp, tc, tx) as integers, or `ValueError` naming the field: tp in 1..rho,
    tc in 1..sigma, tx in 0..3 (the one home of the rule: the task book, and the HMI's task
    form, check with it)."""
    try:
        tp, tc, tx = task
    except (TypeError, ValueError):
        raise ValueError(f'a task is (tp, tc, tx), got {task!r}') from None
    for name, v, lo, hi in (('tp', tp, 1, rho), ('tc', tc, 1, sigma), ('tx', tx, 0, 3)):
        if not _is_int(v) or not lo <= v <= hi:
            raise ValueError(f'bad task {tuple(task)!r}: {name} (task {TASK_FIELDS[name]}) '
                             f'must be an integer in {lo}..{hi}, got {v!r}')
    return int(tp), int(tc), int(tx)


class TaskBook:
    """The cell's task/activity variables, a FIFO queue of pending tasks and a schedule.

    `initial_task`: None (idle cell), ``(tp, tc, tx)`` (an uncommitted task present at
    epoch 1), or a mapping of all eight task variables (any state of the model, for example a
    scenario's initial state). `schedule`: ``(release_epoch, (tp, tc, tx))`` pairs or
    ``"epoch:tp,tc,tx"`` strings. `max_queue`: requests beyond this many waiting tasks are
    refused (None: no limit).
    """

    def __init__(self, model: HRCModel, initial_task=None, schedule=(),
                 max_queue: int | None = None):
        self.model = model
        self.max_queue = max_queue
        self.rho, self.sigma = model.rho, model.sigma
        self.epoch = 0
        self.queue: deque[TaskRecord] = deque()
        self.records: list[TaskRecord] = []
        self.current: TaskRecord | None = None
        self._state = {name: 0 for name in TASK_VARIABLES}
        pending = []
        for entry in ([schedule] if isinstance(schedule, str) else schedule):
            if isinstance(entry, str):
                entry = parse_schedule_entry(entry)
            try:
                epoch, task = entry
                epoch = int(epoch) if _is_int(epoch) else epoch
            except (TypeError, ValueError):
                raise ValueError(f'bad schedule entry {entry!r}: expected '
                                 '(release_epoch, (tp, tc, tx)) or "epoch:tp,tc,tx"') from None
            if not _is_int(epoch) or epoch < 1:
                raise ValueError(f'bad schedule entry {entry!r}: the release epoch must be an '
                                 'integer >= 1')
            pending.append((epoch, self._checked_task(task)))
        # Stable sort: entries of the same epoch keep their given order in the queue.
        self.schedule = sorted(pending, key=lambda e: e[0])
        self._next_release = 0
        if initial_task is not None:
            self._set_initial(initial_task)

    # -- inputs ----------------------------------------------------------------------------
    def _checked_task(self, task) -> tuple[int, int, int]:
        return check_task(task, self.rho, self.sigma)

    def _set_initial(self, initial_task) -> None:
        if isinstance(initial_task, Mapping):
            missing = set(TASK_VARIABLES) - set(initial_task)
            extra = set(initial_task) - set(TASK_VARIABLES)
            if missing or extra:
                raise ValueError(f'an initial task state maps exactly {TASK_VARIABLES}; '
                                 f'missing {sorted(missing)}, unknown {sorted(extra)}')
            state = {n: initial_task[n] for n in TASK_VARIABLES}
            # Validate the ranges with the model's own index check (d = 0 is a dummy).
            self.model.index((0, 0, *(state[n] for n in TASK_VARIABLES), 0))
            self._state = {n: int(v) for n, v in state.items()}
            if state['tp'] > 0:
                record = TaskRecord(0, self._state['tp'], self._state['tc'], self._state['tx'],
                                    release_epoch=1, start_epoch=1,
                                    commit_epoch=0 if state['ty'] else None)
                self.records.append(record)
                self.current = record
        else:
            tp, tc, tx = self._checked_task(initial_task)
            record = TaskRecord(0, tp, tc, tx, release_epoch=1, start_epoch=1)
            self.records.append(record)
            self.current = record
            self._state.update(tp=tp, tc=tc, tx=tx, ty=0)

    def request(self, tp, tc, tx) -> TaskRecord:
        """Queue a task (tp, tc, tx); its release epoch is the next `begin_epoch`'s."""
        tp, tc, tx = self._checked_task((tp, tc, tx))
        if self.max_queue is not None and len(self.queue) >= self.max_queue:
            raise ValueError(f'task ({tp}, {tc}, {tx}) refused: the queue is full '
                             f'({len(self.queue)} tasks waiting, max_queue {self.max_queue})')
        record = TaskRecord(len(self.records), tp, tc, tx, release_epoch=self.epoch + 1)
        self.records.append(record)
        self.queue.append(record)
        return record

    # -- the epoch -------------------------------------------------------------------------
    def begin_epoch(self, k: int) -> dict:
        """Release scheduled tasks due at or before epoch k; an idle cell takes the queue head."""
        if not _is_int(k) or k < 1:
            raise ValueError(f'epochs are integers numbered from 1, got {k!r}')
        if k <= self.epoch:
            raise ValueError(f'epoch {k} does not follow the previous epoch {self.epoch}')
        self.epoch = int(k)
        while (self._next_release < len(self.schedule)
               and self.schedule[self._next_release][0] <= k):
            release, (tp, tc, tx) = self.schedule[self._next_release]
            self._next_release += 1
            record = TaskRecord(len(self.records), tp, tc, tx, release_epoch=release)
            self.records.append(record)
            self.queue.append(record)
        if self._state['tp'] == 0 and self.queue:
            record = self.queue.popleft()
            record.start_epoch = self.epoch
            self.current = record
            self._state.update(tp=record.tp, tc=record.tc, tx=record.tx, ty=0)
        return self.state

    def renumber(self, k: int) -> None:
        """Let the epoch count restart so that epoch k comes next (the epoch source restarted);
        the task state, the queue and the records stay, and scheduled releases not yet made
        follow the new numbers."""
        if not _is_int(k) or k < 1:
            raise ValueError(f'epochs are integers numbered from 1, got {k!r}')
        self.epoch = int(k) - 1

    def apply(self, action, accepted=None, robot_runs=None) -> dict:
        """Apply the epoch's action and the human's answer (None: no eligible request);
        `robot_runs` as `model.step_task` (None: the model's rule for the robot's counter)."""
        a = action_index(action)
        if accepted is not None and not isinstance(accepted, (bool, np.bool_)):
            raise ValueError(f'accepted must be None, True or False, got {accepted!r}')
        before = self._state
        after = self.model.step_task({n: np.int64(v) for n, v in before.items()}, a,
                                     bool(accepted),
                                     None if robot_runs is None else bool(robot_runs))
        self._state = {n: int(after[n]) for n in TASK_VARIABLES}
        if self.current is not None:
            if before['ty'] == 0 and self._state['ty'] != 0:
                self.current.commit_epoch = self.epoch
            if before['tp'] > 0 and self._state['tp'] == 0:
                self.current.complete_epoch = self.epoch
                if self.current.commit_epoch is None:
                    self.current.commit_epoch = self.epoch
                self.current = None
        return self.state

    # -- views -----------------------------------------------------------------------------
    @property
    def state(self) -> dict:
        """The eight task/activity variables (a copy)."""
        return dict(self._state)

    def observable(self, d: int) -> tuple:
        """The observable part x = (tp, tc, tx, ty, hp, hc, bp, bc, d)."""
        if not _is_int(d) or not 0 <= d <= 3:
            raise ValueError(f'the distance level d must be an integer in 0..3, got {d!r}')
        return (*(self._state[n] for n in TASK_VARIABLES), int(d))

    @property
    def idle(self) -> bool:
        return self._state['tp'] == 0

    @property
    def pending(self) -> list[tuple[int, int, int]]:
        """Queued tasks (tp, tc, tx), head first."""
        return [(r.tp, r.tc, r.tx) for r in self.queue]

    @property
    def completed(self) -> list[TaskRecord]:
        return [r for r in self.records if r.complete_epoch is not None]
