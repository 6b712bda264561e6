"""The cell in the worker's words: what the robot does, its requests, the distance band.

The model's symbols (MODEL.md) become short sentences a person reads at arm's length:

- the action a_k with the task state x_k: ``nw`` "working on task 2: a job for both of us"
  (the robot is committed, ty in {2, 3}) or "waiting while you do task 2" (ty = 1); ``ct``
  "taking task 2"; ``dp`` "moving away to give you room"; ``dm`` "coming closer to work with
  you"; ``mh`` "cheering you on" with a short message; ``dn`` "stopped: you are too close" when
  d = 0 (the fail-safe), "stopped for safety: ..." when the decision node failed safe for
  another reason, else "stopped"; ``rh1`` and ``rh2`` "waiting for your answer" to the request
  "Please do task N alone" or "Let's do task N together" (eligible requests: `machine`
  decides that);
- a task by the number the HMI gives it (1, 2, ... in the order it saw them) and its nature
  tx: 0 the robot's job, 1 your job, 2 either of us, 3 a job for both of us;
- the distance level d as a colour band, in the view's colours (`core.cell.view.LEVEL_COLORS`).
"""

from __future__ import annotations

from ..cell.view import LEVEL_COLORS
from ..model import ACTIONS, CT, DM, DN, DP, MH, NW, RH1, RH2, commit_effective

NATURES = {0: "the robot's job", 1: 'your job', 2: 'either of us', 3: 'a job for both of us'}
COMMITMENTS = {0: 'not taken yet', 1: 'you do it', 2: 'the robot does it', 3: 'done together'}
DISTANCE_WORDS = {0: 'too close: the robot stops', 1: 'close to the robot',
                  2: 'middle distance', 3: 'at a safe distance'}
EMOTION_LEVELS = ('low', 'medium', 'high')
MOTIVATION = ('Nice work: you are a great help in this cell.',
              'Thanks! The next task is ready when you are.',
              'Good going: together we get the work done.')
CONNECTED, NO_CELL = 'connected', 'no connection to the cell'


def task_label(number: int | None, task: dict | None) -> str:
    """'task 2: a job for both of us' (the task in the cell), or 'no task'."""
    if task is None or task['tp'] == 0:
        return 'no task'
    name = f'task {number}' if number else 'the task'
    return f'{name}: {NATURES[task["tx"]]}'


def task_details(number: int | None, task: dict | None) -> str:
    """The operator's line for the task in the cell."""
    if task is None:
        return 'no task state yet'
    if task['tp'] == 0:
        return 'no task: the cell is idle'
    return (f'{task_label(number, task)}; priority {task["tp"]}, {task["tc"]} epoch(s) left; '
            f'{COMMITMENTS[task["ty"]]}')


def request_words(action: int, number: int | None) -> str:
    name = f'task {number}' if number else 'the task'
    return f'Please do {name} alone' if action == RH1 else f"Let's do {name} together"


def action_words(action: int | None, task: dict | None, number: int | None, d: int | None,
                 faults: list[str], request_open: bool) -> str:
    """What the robot does now, in words."""
    if action is None:
        return 'waiting for the robot'
    label = task_label(number, task)
    busy = task is not None and task['tp'] > 0
    if action == DN:
        if d == 0 or any('collision' in f for f in faults):
            return 'stopped: you are too close'
        if faults:
            return 'stopped for safety: the robot is missing some of its inputs'
        return 'stopped' if busy else 'stopped: no task to do'
    if action == NW:
        if busy and task['ty'] in (2, 3):
            return f'working on {label}'
        if busy and task['ty'] == 1:
            return f'waiting while you do {label}'
        return 'carrying on'
    if action == CT:
        effective = busy and bool(commit_effective(task['tp'], task['tx'], task['ty']))
        return f'taking {label}' if effective else 'carrying on'
    if action == DP:
        return 'moving away to give you room'
    if action == DM:
        return 'coming closer to work with you'
    if action == MH:
        return 'cheering you on'
    if action in (RH1, RH2):
        return 'waiting for your answer' if request_open else 'waiting'
    return ACTIONS[action]


def motivation_words(epoch: int) -> str:
    return MOTIVATION[epoch % len(MOTIVATION)]


def distance_band(d: int | None) -> dict:
    """The colour band of distance level d (None: unknown)."""
    if d is None:
        return {'level': None, 'text': 'distance unknown', 'colour': '#888888'}
    r, g, b = (round(255 * c) for c in LEVEL_COLORS[d])
    return {'level': d, 'text': DISTANCE_WORDS[d], 'colour': f'#{r:02x}{g:02x}{b:02x}'}
