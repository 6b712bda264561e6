"""The HMI's rules without ROS or a web server (`hrc_ros.core.hmi`): every rule a unit test.

- Requests: open exactly when the task manager would wait for an answer (checked against
  `core.protocol.TaskEpochs` itself on every (tp, tx, ty) of the model, for rh1 and rh2), closed
  by the task manager's next task state with the outcome it shows (checked against the task
  book's finalisation), or by a later action, a restart, a silent cell.
- One answer per request: double tap, second tab, late tap, stale page, another HMI instance,
  another source on hrc/human_response, show-only mode, a silent cell; each publishes nothing
  and says why.
- The task form (each field's range, stated in the refusal; the task book's rule), order rate
  limits, the outcome matched to the task manager's report, orders without a report.
- The access rules (binding, the worker's and the operator's tokens, Host, Origin), the token
  bucket, the words (the worker's and the operator's) and the views.

The console's figures, timeline and event log are test/test_hmi_shift.py's.
"""

from __future__ import annotations

import re

import pytest

from hrc_ros.core.hmi import AccessError, AccessPolicy, HmiMachine, TokenBucket, is_loopback
from hrc_ros.core.hmi import access
from hrc_ros.core.hmi import machine as m
from hrc_ros.core.hmi import orders as o
from hrc_ros.core.hmi import words
from hrc_ros.core.model import ACTION_INDEX, DN, MH, NW, RH1, RH2, TASK_VARIABLES
from hrc_ros.core.protocol import Stamp, TaskEpochs
from hrc_ros.core.tasks import TaskBook, check_task

S = 1_000_000_000       # ns in a second
PERIOD = S


def task(tp=0, tc=0, tx=0, ty=0, hp=0, hc=0, bp=0, bc=0) -> dict:
    return dict(zip(TASK_VARIABLES, (tp, tc, tx, ty, hp, hc, bp, bc)))


class Cell:
    """Feeds a machine the messages of one epoch as the cell publishes them, in order: the
    epoch signal, x_k, a_k; the clock and the source timestamps advance together."""

    def __init__(self, machine: HmiMachine):
        self.machine = machine
        self.t = 10 * S
        self.k = 0

    def tick(self, dt=1_000_000) -> int:
        self.t += dt
        return self.t

    def epoch(self, state: dict, action: int | None = None) -> None:
        self.k += 1
        self.t = 10 * S + self.k * PERIOD
        self.machine.epoch_signal(self.k, self.t, self.t)
        self.machine.task_state_message(state, self.tick(), self.t)
        if action is not None:
            self.machine.action_message(action, self.tick(), self.t)

    def answer(self, request_id, accept, client='page-1'):
        return self.machine.answer(request_id, accept, client, self.tick())


@pytest.fixture
def hmi() -> HmiMachine:
    return HmiMachine(rho=2, sigma=2, instance='test')


@pytest.fixture
def cell(hmi) -> Cell:
    return Cell(hmi)


JOINT = task(1, 1, 3)        # rh2 is eligible
ALONE = task(2, 2, 1)        # rh1 is eligible


# -- when a request is open --------------------------------------------------------------------
def test_an_eligible_request_opens_with_its_words(hmi, cell):
    cell.epoch(JOINT, RH2)
    request = hmi.request
    assert request is not None and request.id == 'test-1' and request.epoch == 1
    assert request.text == "Let's do task 1 together"
    view = hmi.worker_view(cell.t)
    assert view['request']['answerable'] and view['request']['kind'] == 'rh2'
    assert view['action'] == 'waiting for your answer'
    cell.epoch(task(), DN)          # (the task manager would not do this; only for the words)
    cell.epoch(ALONE, RH1)
    assert hmi.request.text == 'Please do task 2 alone'


@pytest.mark.parametrize('state, action', [
    (JOINT, RH1), (ALONE, RH2), (task(1, 1, 3, ty=3, hp=1, hc=1, bp=1, bc=1), RH2),
    (task(), RH1), (JOINT, MH), (JOINT, DN)])
def test_no_request_opens_when_it_is_not_eligible(hmi, cell, state, action):
    cell.epoch(state, action)
    assert hmi.request is None and hmi.worker_view(cell.t)['request'] is None


def test_no_request_without_the_epochs_task_state(hmi, cell):
    """a_k without x_k (the task manager is down): nothing tells whether it is eligible."""
    cell.epoch(JOINT, NW)
    cell.k += 1
    hmi.epoch_signal(cell.k, cell.tick(), cell.t)
    hmi.action_message(RH2, cell.tick(), cell.t)
    assert hmi.request is None


def _task_manager_waits(model, state: dict, action: int) -> bool:
    """Whether the task manager (TaskEpochs) holds epoch 2 for an answer to `action`."""
    tasks = TaskEpochs(TaskBook(model, initial_task=state), PERIOD // 4)
    tasks.epoch(1, Stamp(1), 1)
    tasks.action(action, 2, 2)
    tasks.epoch(2, Stamp(3), 3)
    return tasks.deadline is not None


def test_a_request_is_open_exactly_when_the_task_manager_waits_for_its_answer(model):
    """The HMI mirrors the task manager's rule (both call model.request_eligible): on every
    (tp, tx, ty) of the model, with counters consistent with the commitment."""
    checked = 0
    for tp in range(model.rho + 1):
        for tx in range(4):
            for ty in range(4):
                active = tp > 0 and ty > 0
                state = task(tp, 1 if tp else 0, tx, ty,
                             hp=tp if active and ty in (1, 3) else 0,
                             hc=1 if active and ty in (1, 3) else 0,
                             bp=tp if active and ty in (2, 3) else 0,
                             bc=1 if active and ty in (2, 3) else 0)
                for action in (RH1, RH2):
                    hmi = HmiMachine(model.rho, model.sigma, instance='x')
                    Cell(hmi).epoch(TaskBook(model, initial_task=state).state, action)
                    waits = _task_manager_waits(model, state, action)
                    assert (hmi.request is not None) == waits, (state, action)
                    checked += 1
    assert checked == (model.rho + 1) * 16 * 2


@pytest.mark.parametrize('answer, outcome', [(True, m.ACCEPTED), (False, m.DECLINED),
                                             (None, m.UNANSWERED)])
@pytest.mark.parametrize('state, action', [(JOINT, RH2), (ALONE, RH1), (task(2, 1, 2), RH1)])
def test_the_next_task_state_closes_the_request_with_the_task_managers_outcome(
        model, state, action, answer, outcome):
    """x_{k+1} from the task book's own finalisation of (a_k, answer) closes the request with
    the outcome that answer had."""
    book = TaskBook(model, initial_task=state)
    book.begin_epoch(1)
    hmi = HmiMachine(model.rho, model.sigma, instance='x')
    cell = Cell(hmi)
    cell.epoch(book.state, action)
    request = hmi.request
    if answer is not None:
        assert cell.answer(request.id, answer).publish is answer
    book.apply(action, bool(answer))
    book.begin_epoch(2)
    cell.epoch(book.state)
    assert hmi.request is None and request.outcome == outcome
    assert hmi.worker_view(cell.t)['last_request']['outcome'] == outcome


def test_an_accept_the_task_manager_did_not_take_is_reported_too_late(hmi, cell):
    cell.epoch(JOINT, RH2)
    request = hmi.request
    assert cell.answer(request.id, True).code == m.SENT
    cell.epoch(JOINT)                # x_{k+1}: still uncommitted, the hold had timed out
    assert request.outcome == m.LATE and 'taken as declined' in request.outcome_text


def test_a_later_action_without_task_state_closes_the_request(hmi, cell):
    cell.epoch(JOINT, RH2)
    request = hmi.request
    cell.k += 1
    hmi.epoch_signal(cell.k, cell.tick(), cell.t)
    hmi.action_message(NW, cell.tick(), cell.t)
    assert hmi.request is None and request.outcome == m.MOVED_ON


def test_a_restarted_epoch_count_closes_the_request(hmi, cell):
    cell.epoch(JOINT, NW)
    cell.epoch(JOINT, RH2)
    request = hmi.request
    quiet = cell.t + 5 * S                              # the old source fell silent
    hmi.epoch_signal(1, quiet, quiet)
    assert hmi.request is None and request.outcome == m.RESTARTED


def test_a_stray_epoch_is_ignored(hmi, cell):
    cell.epoch(JOINT, RH2)
    hmi.epoch_signal(4294967295, cell.tick(), cell.t)
    assert hmi.epoch == 1 and hmi.request is not None
    assert hmi.counts['epochs_ignored'] == 1


def test_an_action_that_overtakes_its_task_state_waits_for_it(hmi):
    """DDS orders messages only per writer: a_k (the decision node's) may reach the HMI before
    x_k (the task manager's), and x_{k+1} before the signal of epoch k+1."""
    hmi.epoch_signal(1, 100, 100)
    hmi.action_message(RH2, 300, 101)
    assert hmi.request is None and hmi._pending == (RH2, 300)
    hmi.task_state_message(JOINT, 200, 102)
    assert hmi.request is not None and hmi.request.task_ns == 200
    committed = task(1, 1, 3, 3, 1, 1, 1, 1)
    hmi.task_state_message(committed, 500, 103)         # before epoch 2's signal
    assert hmi.request is None and hmi.last_closed.outcome == m.ACCEPTED
    hmi.epoch_signal(2, 400, 104)
    assert hmi.epoch == 2 and hmi.request is None


def test_the_next_action_before_the_next_task_state_closes_then_tells_the_outcome(hmi):
    hmi.epoch_signal(1, 100, 100)
    hmi.task_state_message(JOINT, 200, 100)
    hmi.action_message(RH2, 300, 100)
    first = hmi.request
    hmi.epoch_signal(2, 400, 101)
    hmi.action_message(RH2, 600, 101)                    # a_2 before x_2
    assert hmi.request is None and first.outcome == m.MOVED_ON
    assert hmi.answer(first.id, True, 'p', 102).code == m.CLOSED     # no answer any more
    hmi.task_state_message(JOINT, 500, 102)              # x_2: refused, a_2 asks again
    assert first.outcome == m.UNANSWERED
    assert hmi.request is not None and hmi.request.id != first.id


def test_a_task_state_published_after_a_timed_out_action_still_tells_the_outcome(hmi):
    """The task manager held epoch 2 for the answer longer than the decision node waited: dn
    (a_2) is published before x_2, which still finalises a_1 with the answer."""
    hmi.epoch_signal(1, 100, 100)
    hmi.task_state_message(JOINT, 200, 100)
    hmi.action_message(RH2, 300, 100)
    first = hmi.request
    hmi.answer(first.id, False, 'page', 101)
    hmi.epoch_signal(2, 400, 101)
    hmi.action_message(DN, 500, 102)                     # the decision node timed out
    assert first.outcome == m.MOVED_ON
    hmi.task_state_message(JOINT, 600, 103)              # x_2, published after a_2
    assert first.outcome == m.DECLINED
    hmi.task_state_message(JOINT, 900, 104)              # x_3 changes nothing of it
    assert first.outcome == m.DECLINED and hmi.counts['requests_opened'] == 1


def test_a_lost_task_state_opens_no_request(hmi):
    hmi.epoch_signal(1, 100, 100)
    hmi.task_state_message(JOINT, 50, 100)               # the previous epoch's x
    hmi.action_message(NW, 60, 100)
    hmi.action_message(RH2, 300, 100)                    # x_1 (published at 200) is lost
    assert hmi.request is None and hmi._pending == (RH2, 300)
    hmi.task_state_message(JOINT, 500, 101)              # x_2: a_1's x will not come
    assert hmi.request is None and hmi._pending is None


def _orders(chains):
    """Every interleaving of the chains that keeps each chain's own order (one writer each)."""
    if not any(chains):
        yield []
        return
    for i, chain in enumerate(chains):
        if chain:
            rest = chains[:i] + [chain[1:]] + chains[i + 1:]
            for tail in _orders(rest):
                yield [chain[0]] + tail


def test_every_arrival_order_of_two_epochs_gives_the_same_story():
    """The signals, the task states, the actions and another source's answer of epochs 1 and
    2 in every order DDS may deliver them (each writer's own order kept: 630 orders): the
    request of epoch 1 is shown exactly when x_1 and a_1 both came before x_2 and a_2, and
    then it ends accepted (x_2 shows the task committed); the last state is epoch 2's."""
    committed = task(1, 1, 3, 3, 1, 1, 1, 1)
    signals = [('epoch', 1, 100), ('epoch', 2, 500)]
    states = [('task', JOINT, 200), ('task', committed, 600)]
    actions = [('action', RH2, 300), ('action', NW, 700)]
    answer = [('response', True, 400)]
    seen = 0
    for order in _orders([signals, states, actions, answer]):
        hmi = HmiMachine(2, 2, instance='x')
        for now, (kind, value, stamp) in enumerate(order):
            {'epoch': hmi.epoch_signal, 'task': hmi.task_state_message,
             'action': hmi.action_message, 'response': hmi.response_message}[kind](
                value, stamp, now)
        at = {event[2]: i for i, event in enumerate(order)}
        shown = max(at[200], at[300]) < min(at[600], at[700])
        assert (hmi.counts['requests_opened'] == 1) == shown, order
        if shown:
            assert hmi.last_closed.outcome == m.ACCEPTED, order
        assert hmi.request is None and hmi.epoch == 2 and hmi.task_state == committed, order
        assert hmi.action == NW, order
        seen += 1
    assert seen == 630


# -- one answer per request --------------------------------------------------------------------
def test_one_answer_per_request(hmi, cell):
    cell.epoch(JOINT, RH2)
    rid = hmi.request.id
    first = cell.answer(rid, True, 'tab-a')
    assert (first.publish, first.code, first.text) == (True, m.SENT, 'sent: accepted')
    double = cell.answer(rid, True, 'tab-a')
    assert double.publish is None and double.code == m.ALREADY
    assert double.text == 'already answered on this screen: accepted'
    second_tab = cell.answer(rid, False, 'tab-b')
    assert second_tab.publish is None and second_tab.text == \
        'already answered on another screen: accepted'
    view = hmi.worker_view(cell.t)['request']
    assert view['answer'] is True and view['answered_by'] == 'tab-a' and not view['answerable']
    assert hmi.counts['answers_sent'] == 1 and hmi.counts['answers_refused'] == 2


def test_a_late_tap_after_the_robot_moved_on_says_how_the_request_ended(hmi, cell):
    cell.epoch(JOINT, RH2)
    rid = hmi.request.id
    cell.epoch(JOINT, NW)              # unanswered: taken as declined
    late = cell.answer(rid, True)
    assert late.publish is None and late.code == m.CLOSED
    assert late.text == 'too late: no answer in time: taken as declined'


def test_a_stale_page_cannot_answer_the_next_request(hmi, cell):
    cell.epoch(JOINT, RH2)
    old = hmi.request.id
    cell.epoch(JOINT, RH2)             # asked again
    assert hmi.request.id != old
    result = cell.answer(old, True)
    assert result.publish is None and result.code == m.CLOSED
    for _ in range(m.CLOSED_KEPT + 1):   # once forgotten, still nothing is sent
        cell.epoch(JOINT, RH2)
    result = cell.answer(old, True)
    assert result.publish is None and result.code == m.STALE


def test_an_answer_for_another_hmi_instance_is_refused(hmi, cell):
    cell.epoch(JOINT, RH2)
    assert hmi.request.id == 'test-1'
    result = cell.answer('other-1', True)
    assert result.publish is None and result.code == m.STALE
    cell.epoch(JOINT, NW)
    assert cell.answer('other-1', True).code == m.NO_REQUEST


@pytest.mark.parametrize('request_id, accept', [('test-1', 'yes'), ('test-1', 1),
                                                ('test-1', None), (1, True), (None, False)])
def test_malformed_answers_are_refused(hmi, cell, request_id, accept):
    cell.epoch(JOINT, RH2)
    result = cell.answer(request_id, accept)
    assert result.publish is None and result.code == m.BAD
    assert hmi.request.answer is None


def test_another_sources_answer_counts_and_the_latest_wins(hmi, cell):
    cell.epoch(JOINT, RH2)
    request = hmi.request
    hmi.response_message(False, request.published_ns - 1, cell.tick())   # before a_k: not it
    assert request.answer is None
    hmi.response_message(True, cell.tick(), cell.t)
    assert (request.answer, request.answered_by) == (True, m.OTHER)
    result = cell.answer(request.id, False)
    assert result.publish is None and result.text == 'already answered elsewhere: accepted'
    hmi.response_message(False, cell.tick(), cell.t)
    assert request.answer is False


def test_its_own_answer_echoed_back_changes_nothing(hmi, cell):
    cell.epoch(JOINT, RH2)
    request = hmi.request
    cell.answer(request.id, True, 'tab-a')
    hmi.response_message(True, cell.tick(), cell.t)
    assert (request.answer, request.answered_by) == (True, 'tab-a')
    assert hmi.counts['answered_elsewhere'] == 0


def test_show_only_mode_never_answers(cell):
    hmi = HmiMachine(2, 2, worker_answers=False, instance='test')
    cell = Cell(hmi)
    cell.epoch(JOINT, RH2)
    assert not hmi.worker_view(cell.t)['request']['answerable']
    result = cell.answer(hmi.request.id, True)
    assert result.publish is None and result.code == m.SHOW_ONLY
    hmi.response_message(True, cell.tick(), cell.t)            # the simulated person
    assert hmi.worker_view(cell.t)['request']['answered_by'] == m.OTHER


def test_a_silent_cell_closes_the_request_and_takes_no_answer(hmi, cell):
    cell.epoch(JOINT, NW)
    cell.epoch(JOINT, RH2)
    rid = hmi.request.id
    assert hmi.cell_timeout_ns() == m.CELL_TIMEOUT_MIN_S * S     # 3 periods of 1 s: 3 s
    silent = cell.t + hmi.cell_timeout_ns() + 1
    result = hmi.answer(rid, True, 'page', silent)
    assert result.publish is None and result.code == m.NO_CELL
    view = hmi.worker_view(silent)
    assert view['connection'] == words.NO_CELL and view['action'] == words.NO_CELL
    assert view['request'] is None and not view['cell']
    hmi.expire(silent)
    assert hmi.request is None and hmi.closed[rid].outcome == m.CELL_LOST
    cell.epoch(JOINT, NW)                                          # it is back
    assert hmi.worker_view(cell.t)['connection'] == words.CONNECTED


def test_the_cell_timeout_follows_the_epoch_period():
    hmi = HmiMachine(2, 2)
    assert not hmi.cell_alive(0)
    for k in range(1, 5):
        hmi.epoch_signal(k, k * 2 * S, k * 2 * S)        # a 2 s period
    assert hmi.cell_timeout_ns() == 6 * S
    assert hmi.cell_alive(8 * S + 6 * S) and not hmi.cell_alive(8 * S + 6 * S + 1)
    assert HmiMachine(2, 2, cell_timeout_s=0.5).cell_timeout_ns() == S // 2


# -- the task form and the orders --------------------------------------------------------------
def test_the_task_form_takes_what_the_task_book_takes():
    assert o.parse_order({'priority': 2, 'duration': '1', 'nature': 3}, 2, 2) == (2, 1, 3)
    assert o.parse_order({'priority': ' 2 ', 'duration': '+1', 'nature': '0'}, 2, 2) == (2, 1, 0)
    for tp in range(-1, 5):                  # exactly what the task book takes
        for tx in range(-1, 5):
            fields = {'priority': tp, 'duration': 1, 'nature': tx}
            try:
                check_task((tp, 1, tx), 2, 2)
            except ValueError:
                with pytest.raises(ValueError):
                    o.parse_order(fields, 2, 2)
            else:
                assert o.parse_order(fields, 2, 2) == (tp, 1, tx)


PRIORITY = 'priority must be a whole number from 1 to 2, got '


@pytest.mark.parametrize('fields, refusal', [
    ({'priority': 3, 'duration': 1, 'nature': 0}, PRIORITY + '3'),
    ({'priority': '-1', 'duration': 1, 'nature': 0}, PRIORITY + '-1'),        # the issue's
    ({'priority': 'abc', 'duration': 1, 'nature': 0}, PRIORITY + "'abc'"),    # letters typed
    ({'priority': '', 'duration': 1, 'nature': 0}, PRIORITY + 'nothing'),
    ({'priority': '\u00b2', 'duration': 1, 'nature': 0}, PRIORITY + "'\u00b2'"),   # a superscript
    ({'priority': '\u0663', 'duration': 1, 'nature': 0}, PRIORITY + "'\u0663'"),   # Arabic-Indic 3
    ({'priority': 1.5, 'duration': 1, 'nature': 0}, PRIORITY + '1.5'),
    ({'priority': True, 'duration': 1, 'nature': 0}, PRIORITY + 'True'),
    ({'priority': '1e3', 'duration': 1, 'nature': 0}, PRIORITY + "'1e3'"),
    ({'priority': 1, 'duration': 0, 'nature': 0},
     'duration must be a whole number from 1 to 2, got 0'),
    ({'priority': 1, 'duration': 1, 'nature': 4},
     "nature (who does it) must be one of 0 (the robot's job), 1 (the worker's job), 2 (either "
     'of them), 3 (a job for both), got 4'),
    ({'priority': 1, 'duration': 1}, 'nature (who does it) missing: a task order has a '
     'priority, a duration and who does it'),
    ([1, 1, 0], 'a task order has the fields priority, duration and nature'),
])
def test_a_refused_form_names_the_field_and_its_range_in_plain_words(fields, refusal):
    with pytest.raises(ValueError) as refused:
        o.parse_order(fields, 2, 2)
    assert str(refused.value) == refusal
    assert not any(word in refusal for word in ('tp', 'tx', 'integer', 'literal', 'int()'))


def test_a_long_refused_value_is_cut():
    with pytest.raises(ValueError, match=r"got 'xxx.*\.\.\.$"):
        o.parse_order({'priority': 'x' * 10_000, 'duration': 1, 'nature': 0}, 2, 2)


def test_a_deeply_nested_field_is_refused_in_words_not_by_recursion():
    """A page's order whose priority nests lists 5,000 deep (JSON parses up to about 1,000 in
    the web thread; the executor's stack is deeper): its repr raised RecursionError, which
    ended hmi_node. Now it is named by its kind."""
    nested: list = []
    for _ in range(5000):
        nested = [nested]
    for value, shown in ((nested, 'a list'), ({'a': nested}, 'a set of fields')):
        with pytest.raises(ValueError) as refused:
            o.parse_order({'priority': value, 'duration': 1, 'nature': 0}, 2, 2)
        assert str(refused.value) == PRIORITY + shown


ORDER = {'priority': 1, 'duration': 2, 'nature': 0}


def test_an_order_is_sent_and_its_report_decides_it(hmi):
    step = hmi.order(ORDER, 'op', 0, listening=True)
    assert step.publish == (1, 2, 0) and step.status == o.CHECKING
    hmi.order_sent(step.order, 100, 200)
    other = hmi.task_request_result({'accepted': True, 'task': (1, 2, 0), 'published_ns': 99,
                                     'queued': 1}, 99)
    assert other is None                         # same content, outside the window: not ours
    mine = hmi.task_request_result({'accepted': True, 'task': (1, 2, 0), 'published_ns': 150,
                                    'queued': 2}, 150)
    assert mine is step.order and mine.status == o.ACCEPTED
    assert mine.text == 'accepted: queued, 2 waiting'
    refused = hmi.order(ORDER, 'op', 1, listening=True)
    hmi.order_sent(refused.order, 300, 400)
    hmi.task_request_result({'accepted': False, 'task': (1, 2, 0), 'published_ns': 350,
                             'reason': 'task (1, 2, 0) refused: the queue is full'}, 350)
    assert refused.order.status == o.REFUSED and refused.order.text == \
        'refused: the queue is full'
    listed = hmi.operator_view(0, 0)['orders']
    assert [(e['from'], e['status'], e['words']) for e in listed] == [
        ('this console', 'refused', "priority 1, 2 steps, the robot's job"),
        ('another publisher', 'accepted', "priority 1, 2 steps, the robot's job"),
        ('this console', 'accepted', "priority 1, 2 steps, the robot's job")]


def test_orders_are_not_sent_without_a_task_manager_or_beyond_the_limits(hmi):
    step = hmi.order(ORDER, 'op', 0, listening=False)
    assert step.publish is None and 'no task manager listens' in step.text
    bad = hmi.order({'priority': 9, 'duration': 1, 'nature': 0}, 'op', 0, listening=True)
    assert bad.publish is None and bad.text == f'refused: {PRIORITY}9'
    sent = [hmi.order(ORDER, 'op', 0, listening=True) for _ in range(5)]
    assert [s.publish is not None for s in sent] == [True, True, False, False, False]
    assert 'too many orders' in sent[2].text          # one bucket was spent on the refusal
    assert hmi.order(ORDER, 'op2', 0, listening=True).publish is not None   # another page
    assert hmi.order(ORDER, 'op', 2 * S, listening=True).publish is not None  # in a while


def test_pending_orders_are_bounded_and_lapse_without_a_report(hmi):
    orders = hmi.orders
    for i in range(orders.max_pending):
        step = hmi.order(ORDER, f'op{i}', 0, listening=True)
        hmi.order_sent(step.order, i, i)
    full = hmi.order(ORDER, 'another', 0, listening=True)
    assert full.publish is None and 'still wait' in full.text
    assert hmi.expire(orders.timeout_ns - 1) == []
    lapsed = hmi.expire(orders.timeout_ns)
    assert len(lapsed) == orders.max_pending and {x.status for x in lapsed} == {o.UNKNOWN}
    assert 'no report from the task manager within 3 s' in lapsed[0].text
    assert hmi.order(ORDER, 'another', orders.timeout_ns, listening=True).publish is not None


def test_order_rate_state_of_closed_pages_is_forgotten_and_bounded(hmi):
    for i in range(o.MAX_CLIENTS + 50):
        hmi.order(ORDER, f'page{i}', 0, listening=False)
    assert len(hmi.orders._buckets) == o.MAX_CLIENTS
    hmi.forget_client(f'page{o.MAX_CLIENTS + 49}')
    assert len(hmi.orders._buckets) == o.MAX_CLIENTS - 1


# -- access rules ------------------------------------------------------------------------------
def test_loopback_addresses():
    assert all(map(is_loopback, ('127.0.0.1', '127.1.2.3', 'localhost', '::1', '[::1]')))
    assert not any(map(is_loopback, ('0.0.0.0', '::', '', '10.0.0.5', 'hmi.local', '192.0.2.1')))


def test_the_server_refuses_to_start_off_loopback_without_both_good_tokens():
    AccessPolicy('127.0.0.1').check_start()
    AccessPolicy('127.0.0.1', operator_token=OPERATOR).check_start()   # the worker's open
    for worker, operator, reason in (
            ('', '', "without the worker's and the operator's access token"),
            (WORKER, '', "without the operator's access token"),
            ('', OPERATOR, "without the worker's access token"),
            ('short', OPERATOR, "the worker's access token has 5 characters; use at least 16"),
            (WORKER, 'short', "the operator's access token has 5 characters"),
            (WORKER, WORKER, "the worker's and the operator's access tokens are the same")):
        with pytest.raises(AccessError, match=re.escape(reason)):
            AccessPolicy('0.0.0.0', worker, operator).check_start()
    with pytest.raises(AccessError, match="operator's console open to anyone"):
        AccessPolicy('127.0.0.1', worker_token=WORKER).check_start()
    AccessPolicy('0.0.0.0', WORKER, OPERATOR).check_start()
    with pytest.raises(AccessError, match='allowed_origins'):
        AccessPolicy('127.0.0.1', allowed_origins=['hmi.example.com']).check_start()


WORKER = 'the-workers-token-123'
OPERATOR = 'the-operators-token-45'


def test_each_request_needs_a_token_and_the_token_gives_its_role():
    policy = AccessPolicy('0.0.0.0', WORKER, OPERATOR)
    host = '10.0.0.5:8080'
    assert policy.check(host, None, None, None, None).status == 401
    assert 'required' in policy.check(host, None, None, None, None).reason
    assert policy.check(host, None, 'Bearer nope', None, None).reason == \
        'the access token is wrong'
    assert policy.check(host, None, f'Bearer {WORKER}', None, None).role == access.WORKER
    assert policy.check(host, None, f'Bearer {OPERATOR}', None, None).role == access.OPERATOR
    assert policy.check(host, None, None, WORKER, None).role == access.WORKER
    by_url = policy.check(host, None, None, None, OPERATOR)
    assert by_url.allowed and by_url.remember and by_url.role == access.OPERATOR
    assert by_url.token == OPERATOR                       # the cookie the server sets
    # a link with the worker's token makes this browser the worker's, whatever its cookie
    switched = policy.check(host, None, None, OPERATOR, WORKER)
    assert switched.role == access.WORKER and switched.remember and switched.token == WORKER
    assert policy.check(host, None, f'Bearer {WORKER}', OPERATOR, None).role == access.OPERATOR
    assert policy.check('evil.example', None, None, WORKER, None).allowed  # the token decides


def test_a_token_that_is_not_utf_8_is_a_wrong_token_not_an_error():
    """aiohttp hands a header's bytes that are not UTF-8 over as lone surrogates: the token
    check's encode raised UnicodeEncodeError, a 500 and a logged traceback for every such
    request, no token needed. Now it is a wrong token (401)."""
    policy = AccessPolicy('0.0.0.0', WORKER, OPERATOR)
    host = '10.0.0.5:8080'
    bad = b'\xff\xfe'.decode('utf-8', 'surrogateescape')
    for given in ((f'Bearer {bad}', None, None), (None, bad, None), (None, None, bad)):
        verdict = policy.check(host, None, *given)
        assert verdict.status == 401 and verdict.reason == 'the access token is wrong'


def test_the_workers_token_opens_the_workers_page_only_and_queues_nothing():
    assert access.may_open(access.WORKER, 'worker').allowed
    refused = access.may_open(access.WORKER, 'operator')
    assert refused.status == 403 and "needs the operator's access token" in refused.reason
    assert access.may_open(access.OPERATOR, 'operator').allowed
    assert access.may_open(access.OPERATOR, 'worker').allowed
    assert not access.may_order(access.WORKER) and access.may_order(access.OPERATOR)
    # on loopback without tokens both pages open, as the operator
    assert AccessPolicy('127.0.0.1').check('127.0.0.1:8080', None, None, None,
                                           None).role == access.OPERATOR
    # on loopback with the operator's token only, a page without a token is the worker's
    policy = AccessPolicy('127.0.0.1', operator_token=OPERATOR)
    assert policy.check('127.0.0.1:8080', None, None, None, None).role == access.WORKER
    assert policy.check('evil.example', None, None, None, None).status == 403   # rebinding
    assert policy.check('127.0.0.1:8080', None, None, OPERATOR, None).role == access.OPERATOR


def test_on_loopback_without_a_token_the_host_must_be_this_machine():
    policy = AccessPolicy('127.0.0.1')
    for host in ('127.0.0.1:8080', 'localhost:8080', '[::1]:8080', 'localhost'):
        assert policy.check(host, None, None, None, None).allowed, host
    rebound = policy.check('evil.example:8080', None, None, None, None)
    assert rebound.status == 403 and 'is not this machine' in rebound.reason
    assert AccessPolicy('127.0.0.1', allowed_hosts=['hmi.plant']).check(
        'hmi.plant:443', None, None, None, None).allowed


def test_cross_origin_websockets_are_refused():
    policy = AccessPolicy('127.0.0.1', allowed_origins=['https://hmi.plant'])
    host = '127.0.0.1:8080'
    assert policy.check(host, 'http://127.0.0.1:8080', None, None, None, websocket=True).allowed
    assert policy.check(host, None, None, None, None, websocket=True).allowed   # not a browser
    assert policy.check(host, 'https://hmi.plant', None, None, None, websocket=True).allowed
    for origin in ('http://evil.example', 'null', 'http://127.0.0.1:9999',
                   'http://localhost:8080'):
        verdict = policy.check(host, origin, None, None, None, websocket=True)
        assert verdict.status == 403 and 'cross-origin' in verdict.reason, origin
    assert policy.check(host, 'http://evil.example', None, None, None).allowed  # a page GET


def test_token_bucket():
    bucket = TokenBucket(rate=10.0, burst=3, now=0)
    assert [bucket.take(0) for _ in range(4)] == [True, True, True, False]
    assert not bucket.take(S // 20)                  # half a token
    assert bucket.take(S // 10) and not bucket.take(S // 10)
    assert sum(bucket.take(S + i) for i in range(100)) == 3    # refilled to the burst only
    with pytest.raises(ValueError):
        TokenBucket(0, 1)


# -- words and views ---------------------------------------------------------------------------
@pytest.mark.parametrize('action, state, d, faults, expected', [
    (DN, JOINT, 0, [], 'stopped: you are too close'),
    (DN, JOINT, 1, ['d = 0: the human is inside the collision circle'],
     'stopped: you are too close'),
    (DN, JOINT, 2, ['hrc/belief missing (never received)'],
     'stopped for safety: the robot is missing some of its inputs'),
    (DN, task(), 3, [], 'stopped: no task to do'),
    (NW, task(2, 2, 2, 2, bp=2, bc=2), 2, [], 'working on task 3: either of us'),
    (NW, task(2, 2, 1, 1, hp=2, hc=2), 2, [], 'waiting while you do task 3: your job'),
    (ACTION_INDEX['ct'], task(2, 2, 2), 2, [], 'taking task 3: either of us'),
    (ACTION_INDEX['ct'], task(2, 2, 1), 2, [], 'carrying on'),
    (ACTION_INDEX['dp'], JOINT, 1, [], 'moving away to give you room'),
    (ACTION_INDEX['dm'], JOINT, 3, [], 'coming closer to work with you'),
    (MH, JOINT, 2, [], 'cheering you on'),
    (None, None, None, [], 'waiting for the robot')])
def test_what_the_robot_does_in_words(action, state, d, faults, expected):
    assert words.action_words(action, state, 3, d, faults, False) == expected


def test_distance_band_in_the_views_colours():
    assert words.distance_band(0) == {'level': 0, 'text': 'too close: the robot stops',
                                      'colour': '#d91a1a'}
    assert words.distance_band(3)['colour'] == '#33b24c'
    assert words.distance_band(None)['text'] == 'distance unknown'


@pytest.mark.parametrize('action, state, d, faults, expected', [
    (DN, JOINT, 0, [], 'stopped: the worker is too close'),
    (NW, task(2, 2, 1, 1, hp=2, hc=2), 2, [], "waiting while the worker does task 3: the "
     "worker's job"),
    (NW, task(2, 2, 2, 2, bp=2, bc=2), 2, [], 'working on task 3: either of them'),
    (ACTION_INDEX['dp'], JOINT, 1, [], 'moving away to give the worker room'),
    (ACTION_INDEX['dm'], JOINT, 3, [], 'coming closer to work with the worker'),
    (MH, JOINT, 2, [], 'cheering the worker on'),
    (RH2, JOINT, 2, [], "waiting for the worker's answer")])
def test_the_operator_reads_about_the_worker(action, state, d, faults, expected):
    """The console speaks of the worker; "you" is the worker's page's (the issue: the operator
    page said the robot waited for *your* answer)."""
    said = words.action_words(action, state, 3, d, faults, True, words.OPERATOR)
    assert said == expected and 'you' not in said.split()


@pytest.mark.parametrize('fault, expected', [
    ('d = 0: the human is inside the collision circle',
     'the worker is too close (inside the collision circle)'),
    ('hrc/belief missing (never received)', "the estimate of the worker's state never arrived"),
    ('hrc/task_state stale (3.012 s old > stale_timeout 3 s)',
     "the task manager's task state is out of date"),
    ('hrc/distance_level not received for epoch 4 within input_timeout',
     "the worker's distance did not arrive in time"),
    ('hrc/belief malformed: 8 values, expected 9', "the estimate of the worker's state arrived "
     'garbled'),
    ('decision failed: ValueError: x', "the decision failed (a software error: see the decision "
     "node's log)")])
def test_fail_safe_reasons_in_words(fault, expected):
    assert words.fault_words(fault) == expected


def test_the_worker_sees_the_fail_safe_of_its_epoch(hmi, cell):
    cell.epoch(JOINT, DN)
    hmi.decision_report(1, 'dn', 'hrc/belief missing (never received)', 'ERROR', cell.t)
    hmi.distance_message(2)
    assert hmi.worker_view(cell.t)['action'].startswith('stopped for safety')
    fail_safe = hmi.operator_view(cell.t, cell.t)['fail_safe']
    assert fail_safe['reasons'] == ['hrc/belief missing (never received)']
    assert fail_safe['text'] == ("stopped for safety at step 1: the estimate of the worker's "
                                 'state never arrived')
    cell.epoch(JOINT, MH)
    hmi.decision_report(2, 'mh', 'none', 'OK', cell.t)
    view = hmi.worker_view(cell.t)
    assert view['action'] == 'cheering you on' and view['motivation'] in words.MOTIVATION
    assert hmi.operator_view(cell.t, cell.t)['fail_safe']['text'] == \
        'no safety stop at step 2: the robot cheers the worker on'


def test_the_operator_view(hmi, cell):
    cell.epoch(JOINT, RH2)
    assert hmi.operator_view(cell.t, cell.t)['request']['text'] == \
        'asks the worker to do task 1 together'
    hmi.answer(hmi.request.id, True, 'p', cell.tick())
    cell.epoch(task(1, 1, 3, 3, 1, 1, 1, 1), NW)
    view = hmi.operator_view(cell.t, cell.t)
    assert view['last_request']['outcome_text'] == 'accepted: they do task 1 together'
    assert hmi.worker_view(cell.t)['last_request']['outcome_text'] == \
        'accepted: we do task 1 together'
    cell.epoch(ALONE, NW)
    hmi.belief_message([0.1, 0.0, 0.0, 0.2, 0.1, 0.0, 0.3, 0.2, 0.1])
    hmi.task_manager_report({'queued_tasks': '2', 'next_queued': '[1, 1, 0]'})
    view = hmi.operator_view(cell.t, cell.t)
    assert view['belief']['motivation'] == [0.1, 0.3, 0.6]
    assert view['belief']['aggression'] == [0.6, 0.3, 0.1]
    assert [(t['number'], t['words'], t['commit_epoch'], t['committed'], t['done_epoch'])
            for t in view['history']] == [
        (2, "priority 2, 2 steps, the worker's job", None, 'not taken yet', None),
        (1, 'priority 1, 1 step, a job for both', 2, 'both together', 3)]
    assert view['task']['text'] == ("task 2: the worker's job; priority 2, 2 steps left; "
                                    'not taken yet')
    assert view['queue']['waiting'] == '2' and view['limits']['priority'] == [1, 2]
    assert view['limits']['step_s'] == 1.0
    assert view['robot'] is None
    hmi.speed_override_message(0.5, cell.t)
    hmi.separation_message(0.8123456, 0.61, 0.2, cell.t, cell.t)
    hmi.protective_stop_message(True, cell.t)
    hmi.stop_report(True, 'separation 0.812 m below the protective distance 0.9 m', cell.t)
    assert hmi.operator_view(cell.t, cell.t)['robot'] == {
        'speed_override': 0.5, 'separation': 0.81, 'protective_distance': 0.61,
        'stopped': True, 'stop_reason': 'separation 0.812 m below the protective distance '
                                        '0.9 m'}
    assert hmi.operator_view(cell.t + 3 * S, cell.t)['robot'] is None   # the robot side stopped
    view = hmi.operator_view(cell.t, cell.t)
    said = ' '.join([view['action'], view['task']['text'], view['fail_safe'] or '',
                     *(t['words'] for t in view['history'])])
    assert not re.search(r'\b(tp|tc|tx|ty|epoch|rh1|rh2)\b', said), said


def test_the_console_shows_the_arm_anew_four_times_a_second_and_a_stop_at_once(hmi, cell):
    """hrc/separation comes at 125 Hz: a view each would be a view a refresh."""
    cell.epoch(JOINT, NW)
    t = cell.t
    hmi.separation_message(0.90, 0.5, 0.2, t, t)
    assert hmi.operator_view(t, t)['robot']['separation'] == 0.9
    hmi.separation_message(0.70, 0.5, 0.2, t + 1, t + S // 10)
    assert hmi.operator_view(t + S // 10, t)['robot']['separation'] == 0.9      # not yet
    assert hmi.operator_view(t + m.ROBOT_VIEW_S * S, t)['robot']['separation'] == 0.7
    hmi.protective_stop_message(True, t + 2)
    assert hmi.operator_view(t + m.ROBOT_VIEW_S * S + 1, t)['robot']['stopped'] is True


def test_the_hmi_core_imports_neither_ros_nor_a_web_framework():
    """The rules are the core's: every core.hmi module imports with rclpy, the ROS messages and
    aiohttp made unimportable (test_layout's guard, with aiohttp added)."""
    import pkgutil
    import subprocess
    import sys

    import hrc_ros.core.hmi as package
    from test_layout import IMPORT_WITHOUT_ROS, ROS_MODULES
    modules = ['hrc_ros.core.hmi'] + [f'hrc_ros.core.hmi.{m.name}'
                                      for m in pkgutil.iter_modules(package.__path__)]
    assert {'hrc_ros.core.hmi.machine', 'hrc_ros.core.hmi.access'} <= set(modules)
    blocked = ','.join(ROS_MODULES + ('aiohttp', 'fastapi', 'starlette', 'playwright'))
    result = subprocess.run([sys.executable, '-c', IMPORT_WITHOUT_ROS, blocked, *modules],
                            capture_output=True, text=True, timeout=120, cwd='/')
    assert result.returncode == 0, result.stderr[-3000:]
