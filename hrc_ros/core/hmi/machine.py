"""The HMI as a sans-IO state machine: requests, answers, orders and the two views.

The HMI node feeds `HmiMachine` the cell's messages in publication order (the writers' source
timestamps, as `SampledInputs.take` gives them) with its control clock ``now`` (monotonic ns),
and the pages' commands; the machine says what to publish and what to answer. Nothing here
touches a socket, rclpy or a web framework, so every rule below is a unit test
(test/test_hmi_core.py).

When is a request open (docs/DESIGN.md, "ROS epoch protocol")? Epoch k begins with the epoch
signal; the task manager then publishes x_k, the decision node a_k. A request a_k in {rh1,
rh2} is open when it is eligible on x_k (`model.request_eligible`, the one home of the rule,
which the task manager applies too). It stays open until the task manager closes it: it
finalises a_k when epoch k+1 arrives, holding for the answer at most its `input_timeout`, and
then publishes x_{k+1}. So the first task state published after the signal of epoch k+1 closes
the request, and its content says how it ended: x_{k+1} equals `model.step_task(x_k, a_k,
accepted)` for accepted true (the task was committed) or false (refused). The HMI keeps no
timer of its own that could disagree with the task manager's. A later action (x_{k+1} lost), a
restarted epoch count or a silent cell (`cell_timeout`) closes it too.

One answer per request. An answer is published only for the open request the page names (its
id carries this HMI's instance, so a page left open across a restart of the HMI cannot answer
a new request by accident), only once (a double tap, a second tab: refused, and the page says
who answered), never after the request closed (a late tap: refused with how it ended), never
while the cell is silent, and never when `worker_answers` is off (the simulated person answers
and the page only shows it). An answer the HMI sees on `hrc/human_response` for the open
request that it did not send is another source's (the simulated person, a perception node):
the request counts as answered, and a later different value replaces it, as the task manager
takes the latest answer.

The answer can still reach the task manager too late: a tap in the last milliseconds of its
hold arrives after it took the request as refused. The task manager then ignores it (its
late-answer rule), and the HMI, seeing x_{k+1} uncommitted after an accept, says "too late".
"""

from __future__ import annotations

import secrets
from collections import OrderedDict, deque
from dataclasses import dataclass

import numpy as np

from ..model import ACTIONS, DN, MH, RH1, RH2, TASK_VARIABLES, request_eligible, step_task
from ..protocol import EpochFollower, InputError, Stamp
from ..robot.metrics import request_refused
from . import words
from .events import EventLog
from .orders import Order, Orders, OrderStep
from .shift import WINDOW_WORDS, ShiftFigures, rounded
from .timeline import Timeline

OTHER = 'elsewhere'            # answered_by: another publisher of hrc/human_response
CELL_TIMEOUT_PERIODS = 3.0     # cell_timeout 0: this many epoch periods ...
CELL_TIMEOUT_MIN_S = 3.0       # ... and at least this (also before the period is known)
ROBOT_TIMEOUT_S = 2.0          # the robot side's topics count as running this long
ROBOT_VIEW_S = 0.25            # the arm's figures on the console change this often at most
CLOSED_KEPT = 32               # closed requests remembered to tell a late tap what happened
TASKS_KEPT = 20                # tasks in the operator's history
RECENT = 8                     # task states and actions kept to pair a_k with x_k
MS = 1_000_000
# the console's fixed words: the actions as a person names them, the figures' windows
CONSOLE_WORDS = {'actions': words.ACTION_NAMES, 'windows': WINDOW_WORDS}
FIGURES_PERIOD_S = 1.0         # the figures of the shift are counted again this often at least

# AnswerResult codes
SENT, ALREADY, CLOSED, STALE, NO_REQUEST, NO_CELL, SHOW_ONLY, BAD = (
    'sent', 'already_answered', 'closed', 'stale', 'no_request', 'no_cell', 'show_only', 'bad')
# Request outcomes
ACCEPTED, DECLINED, LATE, UNANSWERED, MOVED_ON, CELL_LOST, RESTARTED, UNKNOWN = (
    'accepted', 'declined', 'late', 'unanswered', 'moved_on', 'cell_lost', 'restarted',
    'unknown')


@dataclass
class Request:
    """An eligible request of epoch `epoch`, as the worker sees it."""

    id: str
    epoch: int
    action: int                 # RH1 or RH2
    task: dict                  # x_k, the task state it was eligible on
    task_number: int | None
    published_ns: int           # a_k's source timestamp
    opened_ns: int
    task_ns: int = 0            # x_k's source timestamp
    answer: bool | None = None
    answered_by: str | None = None    # the page client that answered, or OTHER
    outcome: str | None = None
    outcome_text: str = ''
    refine: bool = False        # closed by a_{k+1}: the next task state says how it ended

    @property
    def text(self) -> str:
        return words.request_words(self.action, self.task_number)


@dataclass(frozen=True)
class AnswerResult:
    """What to do with a tap: `publish` the answer on hrc/human_response (None: nothing), and
    the words for the page that sent it (`code` in SENT, ALREADY, CLOSED, ...)."""

    publish: bool | None
    code: str
    text: str


@dataclass
class TaskEntry:
    """A task the HMI saw in the cell (the operator's history)."""

    number: int
    tp: int
    tc: int
    tx: int
    seen_epoch: int
    ty: int = 0
    commit_epoch: int | None = None
    done_epoch: int | None = None


def _same_task(a: dict, b: dict) -> bool:
    return all(int(a[n]) == int(b[n]) for n in TASK_VARIABLES)


class HmiMachine:
    """The HMI's state and rules for one cell of model `rho`, `sigma`."""

    def __init__(self, rho: int, sigma: int, worker_answers: bool = True,
                 cell_timeout_s: float = 0.0, order_timeout_s: float = 3.0,
                 instance: str | None = None, start_ns: int | None = None):
        self.rho, self.sigma = rho, sigma
        self.worker_answers = worker_answers
        self.cell_timeout_s = cell_timeout_s
        self.instance = instance or secrets.token_hex(4)
        self.epochs = EpochFollower()
        self.last_cell_ns: int | None = None       # control clock: the last epoch or action
        self.task_state: dict | None = None         # the newest, by publication time
        self.task_ns: int | None = None
        self.action: int | None = None
        self.action_ns: int | None = None
        self.action_epoch = 0
        self._task_states: deque = deque(maxlen=RECENT)    # (published_ns, x)
        self._actions: deque = deque(maxlen=RECENT)        # published_ns
        self._pending: tuple | None = None                 # (a_k, published_ns) awaiting x_k
        self.request: Request | None = None
        self.closed: OrderedDict[str, Request] = OrderedDict()
        self.last_closed: Request | None = None
        self._requests = 0
        self.tasks: deque[TaskEntry] = deque(maxlen=TASKS_KEPT)
        self._task_count = 0
        self.belief: np.ndarray | None = None
        self.distance: int | None = None
        self.decision: dict | None = None           # the decision node's last epoch report
        self.task_manager: dict | None = None       # the task manager's last status
        self.speed_override: tuple | None = None    # (value, received now)
        self.separation: tuple | None = None        # ((S, S_p, speed), received now)
        self.stop: tuple | None = None              # (stopped, reason) of the robot side
        self.orders = Orders(rho, sigma, int(order_timeout_s * 1e9))
        # the console: the shift's figures, the timeline, the event log (system clock, ns)
        self.shift = ShiftFigures(start_ns)
        self.timeline = Timeline()
        self.events = EventLog()
        self._figures: dict | None = None
        self._figures_ns: int | None = None
        self._robot: tuple | None = None    # (view, at now, stop) of the arm, see _robot_view
        self.counts = {'answers_sent': 0, 'answers_refused': 0, 'requests_opened': 0,
                       'answered_elsewhere': 0, 'epochs_ignored': 0}

    # -- the cell's messages ---------------------------------------------------------------
    @property
    def epoch(self) -> int:
        return self.epochs.last

    def epoch_signal(self, k: int, published_ns: int, now: int) -> None:
        stamp = Stamp(published_ns)
        try:
            restart = self.epochs.check(k, stamp)
        except InputError:
            self.counts['epochs_ignored'] += 1
            return
        self.epochs.take(k, stamp)
        self.last_cell_ns = now
        self.shift.begin(published_ns)
        if restart is not None and self.request is not None:
            self._close(RESTARTED, 'closed: the cell restarted its epochs')

    def task_state_message(self, state: dict, published_ns: int, now: int) -> None:
        """A task state (the task manager publishes x_k after the signal of epoch k)."""
        state = {n: int(state[n]) for n in TASK_VARIABLES}
        if self.task_ns is not None and published_ns <= self.task_ns:
            return                  # older than the newest one: it overtook nothing
        self._task_states.append((published_ns, state))
        request, last = self.request, self.last_closed
        if request is not None and published_ns > request.task_ns:
            self._close_on(state, published_ns)         # x_{k+1}
        elif last is not None and last.outcome == MOVED_ON and last.refine \
                and published_ns > last.task_ns:
            self.request, last.refine = last, False     # x_{k+1} came after a_{k+1} (which
            self._close_on(state, published_ns)         # may even be published first: a
            #                                             decision node that timed out)
        self._see_task(state, published_ns)
        self.task_state, self.task_ns = state, published_ns
        if self._pending is not None:
            self._pair(*self._pending, now)

    def action_message(self, action: int, published_ns: int, now: int) -> None:
        self.last_cell_ns = now
        if self.action_ns is not None and published_ns <= self.action_ns:
            return
        self.shift.begin(published_ns)
        request = self.request
        if request is not None and published_ns > request.published_ns:
            self._close(MOVED_ON, 'closed: the robot moved on')
            request.refine = True
        self._actions.append(published_ns)
        self.action, self.action_ns, self.action_epoch = action, published_ns, self.epoch
        self.timeline.epoch(published_ns, self.epoch, ACTIONS[action], self.belief,
                            self.distance)
        self._pending = None
        if action in (RH1, RH2):
            self._pair(action, published_ns, now)

    def _pair(self, action: int, published_ns: int, now: int) -> None:
        """Open a request for a_k once x_k is known: the newest task state published before
        a_k with no other action published between them (each epoch has one of each). Either
        may arrive first: DDS orders messages only per writer, so a_k waits for x_k
        (`_pending`) until a later task state or action shows x_k will not come."""
        before = [(t, x) for t, x in self._task_states if t < published_ns]
        task = max(before, key=lambda e: e[0]) if before else None
        if task is not None and any(task[0] < t < published_ns for t in self._actions):
            task = None                                 # that one was an earlier action's
        later = self.task_ns is not None and self.task_ns > published_ns
        if task is None:
            self._pending = None if later else (action, published_ns)
            return
        self._pending = None
        if later or not request_eligible(action, task[1]['tp'], task[1]['tx'], task[1]['ty']):
            return                  # x_{k+1} is here already: the request is over
        self._requests += 1
        self.request = Request(f'{self.instance}-{self._requests}', self.epoch, action,
                               dict(task[1]), self._current_task_number(), published_ns, now,
                               task[0])
        self.counts['requests_opened'] += 1

    def response_message(self, accepted: bool, published_ns: int, now: int) -> None:
        """An answer on hrc/human_response (this HMI's own, or another source's)."""
        request = self.request
        if request is None or published_ns < request.published_ns:
            return                       # no request, or an answer to an earlier one
        if request.answer is None:
            request.answer, request.answered_by = bool(accepted), OTHER
            self.counts['answered_elsewhere'] += 1
        elif bool(accepted) != request.answer:
            request.answer, request.answered_by = bool(accepted), OTHER   # the latest counts

    def belief_message(self, belief) -> None:
        self.belief = np.asarray(belief, dtype=float).reshape(-1)

    def distance_message(self, d: int) -> None:
        self.distance = int(d)

    def decision_report(self, epoch: int, action: str, faults: str, level: str,
                        published_ns: int) -> None:
        """The decision node's per-epoch /diagnostics status."""
        reasons = [] if faults in ('', 'none') else [f.strip() for f in faults.split(';')]
        self.decision = {'epoch': epoch, 'action': action, 'faults': reasons, 'level': level}
        self.shift.decision(published_ns, epoch, bool(reasons))
        self.events.decision(published_ns, epoch, reasons)

    def policy_report(self, level: str, message: str, values: dict, published_ns: int) -> None:
        """The decision node's `policy` status: a swap, or a new policy staged or refused."""
        self.events.policy(published_ns, level, message, values)

    def task_manager_report(self, values: dict) -> None:
        self.task_manager = dict(values)

    def speed_override_message(self, value: float, now: int) -> None:
        self.speed_override = (float(value), now)
        self.timeline.override_sample(value)

    def separation_message(self, separation: float, protective: float, speed: float,
                           published_ns: int, now: int) -> None:
        """The robot side's hrc/separation: S and S_p (m), and the arm's speed bound (m/s)."""
        self.separation = ((float(separation), float(protective), float(speed)), now)
        self.shift.arm_sample(published_ns, separation, speed)
        self.timeline.arm_sample(published_ns, separation, protective)

    def protective_stop_message(self, stopped: bool, published_ns: int) -> None:
        """hrc/protective_stop (the bridge publishes it on change)."""
        reason = self.stop[1] if self.stop is not None and stopped else ''
        if self.stop is None or self.stop[0] != bool(stopped):
            self.timeline.protective_stop(published_ns, stopped)
        self.stop = (bool(stopped), reason)
        self.shift.protective_stop(published_ns, stopped)
        self.events.protective_stop(published_ns, stopped)

    def stop_report(self, stopped: bool, reason: str, published_ns: int) -> None:
        """The bridge's `ssm` status: the protective stop and its reason."""
        if self.stop is not None and self.stop[0] and stopped:
            self.stop = (True, reason)
        self.events.stop_reason(published_ns, stopped, reason)

    def task_request_result(self, result: dict, published_ns: int) -> Order | None:
        """The task manager's report on a request; the HMI's order it decides, if any."""
        order = self.orders.report(result)
        if not result.get('accepted'):
            self.events.order_refused(published_ns, result.get('task'),
                                      self.orders.words(result),
                                      'this console' if order is not None else
                                      'another publisher')
        return order

    # -- liveness and time -----------------------------------------------------------------
    def cell_timeout_ns(self) -> int:
        """`cell_timeout_s`, else CELL_TIMEOUT_PERIODS epoch periods, at least
        CELL_TIMEOUT_MIN_S."""
        if self.cell_timeout_s > 0:
            return int(self.cell_timeout_s * 1e9)
        period = self.epochs.period.period_ns
        return max(int(CELL_TIMEOUT_MIN_S * 1e9),
                   0 if period is None else int(CELL_TIMEOUT_PERIODS * period))

    def cell_alive(self, now: int) -> bool:
        """The decision node was heard (an epoch or an action) within the cell timeout."""
        return self.last_cell_ns is not None and now - self.last_cell_ns <= self.cell_timeout_ns()

    def expire(self, now: int) -> list[Order]:
        """Close a request of a silent cell; the orders whose outcome did not come in time."""
        if self.request is not None and not self.cell_alive(now):
            self._close(CELL_LOST, 'closed: no connection to the cell')
        return self.orders.expire(now)

    def expire_events(self, wall_ns: int) -> None:
        """A protective stop whose reason did not come in time is logged without it."""
        self.events.expire(wall_ns)

    # -- the pages' commands ---------------------------------------------------------------
    def answer(self, request_id, accept, client: str, now: int) -> AnswerResult:
        """A tap on Accept (`accept` true) or Decline for the request `request_id`."""
        result = self._answer(request_id, accept, client, now)
        self.counts['answers_sent' if result.publish is not None else 'answers_refused'] += 1
        return result

    def _answer(self, request_id, accept, client: str, now: int) -> AnswerResult:
        if not isinstance(accept, bool) or not isinstance(request_id, str):
            return AnswerResult(None, BAD, 'an answer names the request and accept: true or '
                                'false')
        if not self.worker_answers:
            return AnswerResult(None, SHOW_ONLY, 'this page only shows the answers: here the '
                                'simulated person answers (worker_answers is off)')
        request = self.request
        if request is None or request.id != request_id:
            closed = self.closed.get(request_id)
            if closed is not None:
                return AnswerResult(None, CLOSED, f'too late: {closed.outcome_text}')
            if request is not None:
                return AnswerResult(None, STALE, 'that request is no longer open: the robot '
                                    'asks something else now')
            return AnswerResult(None, NO_REQUEST, 'no request is open')
        if not self.cell_alive(now):
            return AnswerResult(None, NO_CELL, 'no connection to the cell: nothing sent')
        if request.answer is not None:
            where = ('on this screen' if request.answered_by == client else
                     'elsewhere' if request.answered_by == OTHER else 'on another screen')
            given = 'accepted' if request.answer else 'declined'
            return AnswerResult(None, ALREADY, f'already answered {where}: {given}')
        request.answer, request.answered_by = accept, client
        return AnswerResult(accept, SENT, 'sent: ' + ('accepted' if accept else 'declined'))

    def order(self, fields, client: str, now: int, listening: bool) -> OrderStep:
        """The operator's task form; `listening`: a task manager subscribes hrc/task_request."""
        return self.orders.submit(fields, client, now, listening)

    def order_sent(self, order: Order, before_ns: int, after_ns: int) -> None:
        self.orders.sent(order, before_ns, after_ns)

    def forget_client(self, client: str) -> None:
        self.orders.forget(client)

    # -- requests and tasks ----------------------------------------------------------------
    def _close_on(self, state: dict, published_ns: int) -> None:
        """Close the open request with x_{k+1}: how the task manager finalised it; a refusal
        (declined, unanswered, an accept too late) counts in the shift's figures."""
        request = self.request
        task = {n: np.int64(v) for n, v in request.task.items()}
        committed = {n: int(v) for n, v in step_task(task, request.action, True).items()}
        refused = {n: int(v) for n, v in step_task(task, request.action, False).items()}
        name = f'task {request.task_number}' if request.task_number else 'the task'
        if _same_task(state, committed):
            taken = True
            self._close(ACCEPTED, f'accepted: you do {name}' if request.action == RH1
                        else f'accepted: we do {name} together')
        elif not _same_task(state, refused):
            self._close(UNKNOWN, 'closed')
            return
        else:
            taken = False
            if request.answer is True:
                self._close(LATE, 'the accept reached the robot after it moved on: taken as '
                            'declined')
            elif request.answer is False:
                self._close(DECLINED, 'declined: the robot carries on')
            else:
                self._close(UNANSWERED, 'no answer in time: taken as declined')
        if request_refused(taken):
            self.shift.request_refused(published_ns)

    def _close(self, outcome: str, text: str) -> None:
        request, self.request = self.request, None
        request.outcome, request.outcome_text = outcome, text
        self.closed[request.id] = request
        while len(self.closed) > CLOSED_KEPT:
            self.closed.popitem(last=False)
        self.last_closed = request

    def _see_task(self, state: dict, published_ns: int) -> None:
        """Number the tasks as they enter the cell; note commitments and completions (a task
        leaving the cell is completed: the task book lets a task go only when done)."""
        current = self.tasks[-1] if self.tasks and self.tasks[-1].done_epoch is None else None
        before = self.task_state
        new = state['tp'] > 0 and (
            current is None or before is None or before['tp'] == 0
            or (before['ty'] != 0 and state['ty'] == 0)
            or (state['tp'], state['tx']) != (before['tp'], before['tx']))
        if current is not None and (new or state['tp'] == 0):
            current.done_epoch = self.epoch
            self.shift.task_completed(published_ns)
        if new:
            self._task_count += 1
            self.tasks.append(TaskEntry(self._task_count, state['tp'], state['tc'], state['tx'],
                                        self.epoch))
        elif current is not None and state['tp'] > 0 and state['ty'] != 0 and current.ty == 0:
            current.ty, current.commit_epoch = state['ty'], self.epoch

    def _current_task_number(self) -> int | None:
        if self.tasks and self.tasks[-1].done_epoch is None:
            return self.tasks[-1].number
        return None

    # -- the views -------------------------------------------------------------------------
    def _request_view(self) -> dict | None:
        request = self.request
        if request is None:
            return None
        return {'id': request.id, 'kind': ACTIONS[request.action], 'text': request.text,
                'epoch': request.epoch, 'answer': request.answer,
                'answered_by': request.answered_by,
                'answerable': self.worker_answers and request.answer is None}

    def _present(self, now: int, who: str) -> dict:
        """What both pages show: the robot now, its request, the distance (`who` the page's
        reader: the worker, or the operator about the worker)."""
        alive = self.cell_alive(now)
        faults = self.decision['faults'] if self.decision is not None \
            and self.decision['epoch'] == self.action_epoch else []
        task = self.task_state
        last = self.last_closed
        request = self._request_view() if alive else None
        if request is not None and who == words.OPERATOR:
            request['text'] = words.request_words(self.request.action,
                                                  self.request.task_number, who)
        return {
            'view': who,
            'connection': words.CONNECTED if alive else words.NO_CELL,
            'cell': alive,
            'epoch': self.epoch,
            'action': (words.action_words(self.action, task, self._current_task_number(),
                                          self.distance, faults, self.request is not None,
                                          who)
                       if alive else words.NO_CELL),
            'action_code': ACTIONS[self.action] if self.action is not None and alive else None,
            'request': request,
            'last_request': None if last is None else {
                'id': last.id, 'outcome': last.outcome, 'epoch': last.epoch,
                'outcome_text': (last.outcome_text if who == words.WORKER else
                                 words.outcome_words(last.outcome, last.outcome_text,
                                                     last.action, last.task_number)),
                'text': last.text if who == words.WORKER else
                words.request_words(last.action, last.task_number, who)},
            'motivation': (words.motivation_words(self.epoch)
                           if alive and self.action == MH else None),
            'distance': words.distance_band(self.distance if alive else None),
            'worker_answers': self.worker_answers,
            'stopped': alive and self.action == DN,
        }

    def worker_view(self, now: int) -> dict:
        return self._present(now, words.WORKER)

    def figures(self, wall_ns: int) -> dict:
        """The shift's figures over each window (rounded as the console shows them), counted
        again every FIGURES_PERIOD_S or at once when one changed (a task done, a refusal, a
        fail-safe epoch, a protective stop, a new smallest separation); times in whole ms."""
        wall_ns = int(wall_ns) // MS * MS
        if self._figures_ns is None or self.shift.changed \
                or wall_ns - self._figures_ns >= FIGURES_PERIOD_S * 1e9:
            self._figures_ns = wall_ns
            windows = self.shift.all_windows(wall_ns)
            self._figures = None if windows is None else {
                name: rounded(figures) for name, figures in windows.items()}
        return self._figures

    def operator_view(self, now: int, wall_ns: int) -> dict:
        """The console: the present, the task and the queue, the orders, the tasks seen, the
        belief, the last decision, the arm and the figures of the shift (`wall_ns`: the
        system clock, the figures' time). The timeline and the event log go to the pages as
        they grow (`timeline.take`, `events.take`), not in every view."""
        view = self._present(now, words.OPERATOR)
        task = self.task_state
        view['task'] = {'text': words.task_details(self._current_task_number(), task),
                        'state': task}
        manager = self.task_manager or {}
        view['queue'] = {'waiting': manager.get('queued_tasks'),
                         'next': manager.get('next_queued'),
                         'completed': manager.get('completed_tasks'),
                         'waiting_for': manager.get('waiting_for')}
        view['history'] = [
            {'number': t.number, 'task': [t.tp, t.tc, t.tx],
             'words': words.task_words(t.tp, t.tc, t.tx),
             'nature': words.OPERATOR_NATURES[t.tx], 'seen_epoch': t.seen_epoch,
             'committed': words.OPERATOR_COMMITMENTS[t.ty], 'commit_epoch': t.commit_epoch,
             'done_epoch': t.done_epoch}
            for t in reversed(self.tasks)]
        view['orders'] = [
            {'number': o.number, 'task': list(o.task), 'status': o.status, 'text': o.text,
             'words': (words.task_words(*o.task) if len(o.task) == 3 else 'a malformed order'),
             'from': 'this console' if o.number else 'another publisher'}
            for o in reversed(self.orders.history)]
        if self.belief is not None and self.belief.size == 9:
            grid = self.belief.reshape(3, 3)
            view['belief'] = {'levels': list(words.EMOTION_LEVELS),
                              'motivation': [round(float(p), 4) for p in grid.sum(axis=1)],
                              'aggression': [round(float(p), 4) for p in grid.sum(axis=0)]}
        else:
            view['belief'] = None
        decision = self.decision
        view['fail_safe'] = None if decision is None else {
            'epoch': decision['epoch'], 'action': decision['action'],
            'reasons': decision['faults'], 'level': decision['level'],
            'text': (f'stopped for safety at step {decision["epoch"]}: '
                     f'{words.fail_safe_words(decision["faults"])}' if decision['faults'] else
                     f'no safety stop at step {decision["epoch"]}: the robot '
                     f'{words.ACTION_NAMES.get(decision["action"], decision["action"])}')}
        view['robot'] = self._robot_view(now)
        view['figures'] = self.figures(wall_ns)
        period = self.epochs.period.period_ns
        view['limits'] = {'priority': [1, self.rho], 'duration': [1, self.sigma],
                          'nature': [0, 3], 'natures': words.OPERATOR_NATURES,
                          'step_s': None if period is None else round(period * 1e-9, 2)}
        view['words'] = CONSOLE_WORDS
        return view

    def _robot_view(self, now: int) -> dict | None:
        """The arm now, while the robot side publishes (ROBOT_TIMEOUT_S). Its separation
        changes at the arm's rate (125 Hz): the console shows it anew every ROBOT_VIEW_S (the
        timeline has the detail), a protective stop, its reason or its end at once."""
        if self._robot is not None and now - self._robot[1] < ROBOT_VIEW_S * 1e9 \
                and self._robot[2] == self.stop:
            return self._robot[0]
        view = self._robot_now(now)
        self._robot = (view, now, self.stop)
        return view

    def _robot_now(self, now: int) -> dict | None:
        fresh = {name: value[0] for name, value in (('speed_override', self.speed_override),
                                                    ('separation', self.separation))
                 if value is not None and now - value[1] <= ROBOT_TIMEOUT_S * 1e9}
        if not fresh:
            return None
        robot = {}
        if 'speed_override' in fresh:
            robot['speed_override'] = round(fresh['speed_override'], 2)
        if 'separation' in fresh:
            separation, protective, _ = fresh['separation']
            robot['separation'] = round(separation, 2)
            robot['protective_distance'] = round(protective, 2)
        if self.stop is not None:
            robot['stopped'], robot['stop_reason'] = self.stop
        return robot
