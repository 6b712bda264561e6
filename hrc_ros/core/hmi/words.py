"""The cell in plain words: what the robot does, its requests, the distance band, the tasks.

The model's symbols (MODEL.md) become short sentences a person reads at arm's length, in two
forms: the worker's, spoken to the person by the robot ("moving away to give you room"), and
the operator's, about the worker ("moving away to give the worker room"). The model's names
(rh2, tp, tx) are left to tooltips.

- the action a_k with the task state x_k: ``nw`` "working on task 2: a job for both of us"
  (the robot is committed, ty in {2, 3}) or "waiting while you do task 2" (ty = 1); ``ct``
  "taking task 2"; ``dp`` "moving away to give you room"; ``dm`` "coming closer to work with
  you"; ``mh`` "cheering you on" with a short message; ``dn`` "stopped: you are too close" when
  d = 0 (the fail-safe), "stopped for safety: ..." when the decision node failed safe for
  another reason, else "stopped"; ``rh1`` and ``rh2`` "waiting for your answer" to the request
  "Please do task N alone" or "Let's do task N together" (eligible requests: `machine`
  decides that);
- a task by the number the HMI gives it (1, 2, ... in the order it saw them) and its nature
  tx: 0 the robot's job, 1 your job (the worker's), 2 either of us, 3 a job for both of us;
- the distance level d as a colour band, in the view's colours (`core.cell.view.LEVEL_COLORS`);
- the decision node's fail-safe reasons (`fault_words`) and the form's fields (`FIELD_WORDS`).
"""

from __future__ import annotations

import re

from ..cell.view import LEVEL_COLORS
from ..model import ACTIONS, CT, DM, DN, DP, MH, NW, RH1, RH2, commit_effective

WORKER, OPERATOR = 'worker', 'operator'
NATURES = {0: "the robot's job", 1: 'your job', 2: 'either of us', 3: 'a job for both of us'}
OPERATOR_NATURES = {0: "the robot's job", 1: "the worker's job", 2: 'either of them',
                    3: 'a job for both'}
COMMITMENTS = {0: 'not taken yet', 1: 'you do it', 2: 'the robot does it', 3: 'done together'}
OPERATOR_COMMITMENTS = {0: 'not taken yet', 1: 'the worker', 2: 'the robot', 3: 'both together'}
DISTANCE_WORDS = {0: 'too close: the robot stops', 1: 'close to the robot',
                  2: 'middle distance', 3: 'at a safe distance'}
EMOTION_LEVELS = ('low', 'medium', 'high')
MOTIVATION = ('Nice work: you are a great help in this cell.',
              'Thanks! The next task is ready when you are.',
              'Good going: together we get the work done.')
CONNECTED, NO_CELL = 'connected', 'no connection to the cell'
# What a person calls each action (the operator's console's strip, its legend and the log)
ACTION_NAMES = {'nw': 'carries on', 'rh1': 'asks the worker to do the task alone',
                'rh2': 'asks the worker to work together', 'ct': 'takes the task',
                'dp': 'moves away', 'dm': 'comes closer', 'mh': 'cheers the worker on',
                'dn': 'stops'}
# The task form's fields, in words (docs/HMI.md, "Orders and their outcome")
FIELD_WORDS = {'priority': 'priority', 'duration': 'duration', 'nature': 'nature (who does it)'}
# The decision node's inputs, named as a person would (its fail-safe reasons)
INPUT_WORDS = {'hrc/belief': "the estimate of the worker's state",
               'hrc/task_state': "the task manager's task state",
               'hrc/distance_level': "the worker's distance"}


def natures(who: str = WORKER) -> dict:
    return NATURES if who == WORKER else OPERATOR_NATURES


def task_label(number: int | None, task: dict | None, who: str = WORKER) -> str:
    """'task 2: a job for both of us' (the task in the cell), or 'no task'."""
    if task is None or task['tp'] == 0:
        return 'no task'
    name = f'task {number}' if number else 'the task'
    return f'{name}: {natures(who)[task["tx"]]}'


def steps(n: int) -> str:
    return f'{n} step' + ('' if n == 1 else 's')


def task_words(tp: int, tc: int, tx: int, who: str = OPERATOR) -> str:
    """An order or a task by its fields: 'priority 2, 1 step, the robot's job'."""
    return f'priority {tp}, {steps(tc)}, {natures(who).get(tx, f"nature {tx}")}'


def task_details(number: int | None, task: dict | None, who: str = OPERATOR) -> str:
    """The operator's line for the task in the cell."""
    if task is None:
        return 'no task state yet'
    if task['tp'] == 0:
        return 'no task: the cell is idle'
    taken = OPERATOR_COMMITMENTS if who == OPERATOR else COMMITMENTS
    return (f'{task_label(number, task, who)}; priority {task["tp"]}, '
            f'{steps(task["tc"])} left; ' + ('not taken yet' if task['ty'] == 0 else
                                             f'taken by {taken[task["ty"]]}'
                                             if who == OPERATOR else taken[task['ty']]))


def request_words(action: int, number: int | None, who: str = WORKER) -> str:
    name = f'task {number}' if number else 'the task'
    if who == OPERATOR:
        return (f'asks the worker to do {name} alone' if action == RH1
                else f'asks the worker to do {name} together')
    return f'Please do {name} alone' if action == RH1 else f"Let's do {name} together"


def outcome_words(outcome: str, text: str, action: int, number: int | None) -> str:
    """How a request ended, for the operator: an accept in the third person; the other
    outcomes say the same to both (`text`, the worker's words)."""
    if outcome != 'accepted':
        return text
    name = f'task {number}' if number else 'the task'
    return (f'accepted: the worker does {name}' if action == RH1
            else f'accepted: they do {name} together')


def action_words(action: int | None, task: dict | None, number: int | None, d: int | None,
                 faults: list[str], request_open: bool, who: str = WORKER) -> str:
    """What the robot does now, in words (the worker's, or the operator's about the worker)."""
    if action is None:
        return 'waiting for the robot'
    worker = who == WORKER
    label = task_label(number, task, who)
    busy = task is not None and task['tp'] > 0
    if action == DN:
        if d == 0 or any('collision' in f for f in faults):
            return 'stopped: you are too close' if worker else \
                'stopped: the worker is too close'
        if faults:
            return 'stopped for safety: the robot is missing some of its inputs'
        return 'stopped' if busy else 'stopped: no task to do'
    if action == NW:
        if busy and task['ty'] in (2, 3):
            return f'working on {label}'
        if busy and task['ty'] == 1:
            return f'waiting while you do {label}' if worker else \
                f'waiting while the worker does {label}'
        return 'carrying on'
    if action == CT:
        effective = busy and bool(commit_effective(task['tp'], task['tx'], task['ty']))
        return f'taking {label}' if effective else 'carrying on'
    if action == DP:
        return 'moving away to give you room' if worker else \
            'moving away to give the worker room'
    if action == DM:
        return 'coming closer to work with you' if worker else \
            'coming closer to work with the worker'
    if action == MH:
        return 'cheering you on' if worker else 'cheering the worker on'
    if action in (RH1, RH2):
        if not request_open:
            return 'waiting'
        return 'waiting for your answer' if worker else "waiting for the worker's answer"
    return ACTIONS[action]


def motivation_words(epoch: int) -> str:
    return MOTIVATION[epoch % len(MOTIVATION)]


def distance_band(d: int | None) -> dict:
    """The colour band of distance level d (None: unknown)."""
    if d is None:
        return {'level': None, 'text': 'distance unknown', 'colour': '#888888'}
    r, g, b = (round(255 * c) for c in LEVEL_COLORS[d])
    return {'level': d, 'text': DISTANCE_WORDS[d], 'colour': f'#{r:02x}{g:02x}{b:02x}'}


_FAULT = re.compile(r'^(?P<topic>\S+) (?P<what>malformed|missing|stale|not received)')


def fault_words(fault: str) -> str:
    """A fail-safe reason of the decision node (`protocol.DecisionGate.faults`) in words."""
    if fault.startswith('d = 0'):
        return 'the worker is too close (inside the collision circle)'
    if fault.startswith('decision failed'):
        return 'the decision failed (a software error: see the decision node\'s log)'
    match = _FAULT.match(fault)
    if match is None:
        return fault
    noun = INPUT_WORDS.get(match['topic'], match['topic'])
    return {'malformed': f'{noun} arrived garbled',
            'missing': f'{noun} never arrived',
            'stale': f'{noun} is out of date',
            'not received': f'{noun} did not arrive in time'}[match['what']]


def fail_safe_words(faults: list[str]) -> str:
    """'the worker is too close (...); the task manager's task state is out of date'."""
    return '; '.join(dict.fromkeys(fault_words(f) for f in faults))
