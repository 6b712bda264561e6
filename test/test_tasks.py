"""TaskBook: MODEL.md 3.2 bookkeeping, the FIFO queue, the schedule and input checks."""

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTIONS, TASK_VARIABLES, HRCModel, request_eligible
from hrc_ros.core.paths import default_config_path
from hrc_ros.core.tasks import TaskBook, parse_schedule, parse_schedule_entry


@pytest.fixture(scope='module')
def model():
    return HRCModel(load_config(default_config_path()))


def task(**values):
    state = {n: 0 for n in TASK_VARIABLES}
    state.update(values)
    return state


def test_joint_task_commits_runs_and_completes(model):
    book = TaskBook(model, initial_task=(1, 1, 3))
    book.begin_epoch(1)
    assert book.state == task(tp=1, tc=1, tx=3)
    book.apply('ct')                      # the robot cannot start a joint task alone
    assert book.state == task(tp=1, tc=1, tx=3)
    book.apply('rh2', accepted=False)     # refused: the task waits
    assert book.state == task(tp=1, tc=1, tx=3)
    book.begin_epoch(2)
    book.apply('rh2', accepted=True)
    assert book.state == task(tp=1, tc=1, tx=3, ty=3, hp=1, hc=1, bp=1, bc=1)
    book.begin_epoch(3)
    book.apply('nw')
    # complete: the task resets; the activity priorities fall one epoch later (paper eqs.)
    assert book.state == task(hp=1, bp=1)
    book.begin_epoch(4)
    book.apply('dn')
    assert book.state == task()
    record = book.records[0]
    assert (record.release_epoch, record.commit_epoch, record.complete_epoch) == (1, 2, 3)
    assert record.epochs_to_complete == 3


def test_robot_task_counts_down_and_dn_pauses_the_robot(model):
    book = TaskBook(model, initial_task=(2, 2, 2))
    book.begin_epoch(1)
    book.apply('ct')
    assert book.state == task(tp=2, tc=2, tx=2, ty=2, bp=2, bc=2)
    book.begin_epoch(2)
    book.apply('dn')                      # paused: bc stays
    assert book.state == task(tp=2, tc=2, tx=2, ty=2, bp=2, bc=2)
    book.begin_epoch(3)
    book.apply('nw')
    assert book.state == task(tp=2, tc=1, tx=2, ty=2, bp=2, bc=1)
    book.begin_epoch(4)
    book.apply('dp')                      # moving away also works
    assert book.state == task(bp=2)
    assert book.completed[0].complete_epoch == 4


def test_human_only_task(model):
    book = TaskBook(model, initial_task=(2, 2, 1))
    book.begin_epoch(1)
    book.apply('ct')                      # the robot cannot take a human-only task
    book.apply('rh2', accepted=True)      # rh2 is not eligible for tx = 1
    assert book.state == task(tp=2, tc=2, tx=1)
    book.apply('rh1', accepted=True)
    assert book.state == task(tp=2, tc=2, tx=1, ty=1, hp=2, hc=2)


def test_apply_agrees_with_the_models_transition(model):
    """The book's next task part is a support point of model.transition, per acceptance."""
    rng = np.random.default_rng(1)
    for _ in range(300):
        s = tuple(int(rng.integers(n)) for n in model.dims)
        a = int(rng.integers(len(ACTIONS)))
        y = dict(zip(TASK_VARIABLES, s[2:10]))
        t = model.transition(model.index(s), a)
        targets = model.state(t.target[t.probability > 0])
        support = {tuple(row[2:10]) for row in targets}
        eligible = bool(request_eligible(a, y['tp'], y['tx'], y['ty']))
        outcomes = {}
        for accepted in ((True, False) if eligible else (None,)):
            book = TaskBook(model, initial_task=y)
            book.begin_epoch(1)
            book.apply(a, accepted)
            outcomes[accepted] = tuple(book.state[n] for n in TASK_VARIABLES)
        assert set(outcomes.values()) == support, (s, ACTIONS[a])


def test_queue_is_fifo_and_enters_only_an_idle_cell(model):
    book = TaskBook(model)
    book.request(1, 1, 0)
    book.request(2, 2, 1)
    book.request(2, 1, 3)
    book.begin_epoch(1)
    assert (book.state['tp'], book.state['tc'], book.state['tx']) == (1, 1, 0)
    assert book.pending == [(2, 2, 1), (2, 1, 3)]
    book.begin_epoch(2)                   # task 1 not done: the queue waits
    assert book.state['tx'] == 0 and len(book.pending) == 2
    book.apply('ct')
    book.apply('nw')                      # robot done -> complete
    assert book.idle
    book.begin_epoch(3)
    assert (book.state['tp'], book.state['tc'], book.state['tx'], book.state['ty']) == \
        (2, 2, 1, 0)
    assert book.pending == [(2, 1, 3)]


def test_schedule_releases_when_due_and_only_into_an_idle_cell(model):
    book = TaskBook(model, initial_task=(1, 1, 3), schedule=['3:2,2,1', (2, (2, 2, 2))])
    book.begin_epoch(1)
    assert book.pending == []
    book.begin_epoch(2)                   # due, but task 1 is open: queued
    assert book.pending == [(2, 2, 2)] and book.state['tx'] == 3
    book.begin_epoch(3)
    assert book.pending == [(2, 2, 2), (2, 2, 1)]
    book.apply('rh2', accepted=True)
    book.begin_epoch(4)
    book.apply('nw')                      # task 1 completes during epoch 4
    assert book.idle and book.pending == [(2, 2, 2), (2, 2, 1)]
    book.begin_epoch(5)                   # the head, released at 2, enters uncommitted
    assert book.state['tx'] == 2 and book.state['ty'] == 0
    assert book.records[1].release_epoch == 2 and book.records[1].start_epoch == 5


def test_request_release_epoch_is_the_next_epoch(model):
    book = TaskBook(model)
    book.begin_epoch(1)
    record = book.request(1, 1, 0)
    assert record.release_epoch == 2
    assert book.idle                      # not in the cell before the next epoch
    book.begin_epoch(2)
    assert book.state['tp'] == 1


@pytest.mark.parametrize('bad', [(0, 1, 0), (3, 1, 0), (1, 0, 0), (1, 3, 0), (1, 1, 4),
                                 (1, 1, -1), (1.5, 1, 0), (True, 1, 0), ('1', 1, 0)])
def test_bad_task_requests_raise(model, bad):
    book = TaskBook(model)
    with pytest.raises(ValueError, match=r'bad task .*must be an integer in'):
        book.request(*bad)
    with pytest.raises(ValueError, match='bad task'):
        TaskBook(model, schedule=[(1, bad)])


def test_bad_schedule_strings_and_epochs_raise(model):
    for text in ('9-2,2,1', 'x:1,1,1', '9:1,1', '9:1,1,1,1', '', '9:a,1,1'):
        with pytest.raises(ValueError, match='bad schedule entry'):
            parse_schedule_entry(text)
    with pytest.raises(ValueError, match='numbered from 1'):
        parse_schedule_entry('0:1,1,1')
    with pytest.raises(ValueError, match='bad task'):
        TaskBook(model, schedule=['9:3,1,1'])
    with pytest.raises(ValueError, match='bad schedule entry'):
        TaskBook(model, schedule=[(0, (1, 1, 1))])
    book = TaskBook(model)
    book.begin_epoch(2)
    with pytest.raises(ValueError, match='does not follow'):
        book.begin_epoch(2)
    with pytest.raises(ValueError, match='must be None, True or False'):
        book.apply('rh1', accepted='yes')
    with pytest.raises(ValueError, match='unknown action'):
        book.apply('jump')
    with pytest.raises(ValueError, match='distance level'):
        book.observable(4)
    with pytest.raises(ValueError, match='must lie in'):
        TaskBook(model, initial_task=task(tp=1, tc=1, tx=3, ty=5))


def test_parse_schedule_forms():
    expected = [(9, (2, 2, 1)), (16, (2, 2, 2))]
    assert parse_schedule(['9:2,2,1', '16:2,2,2']) == expected
    assert parse_schedule('9:2,2,1; 16: 2, 2, 2') == expected
    assert parse_schedule('9:2,2,1 16:2,2,2') == expected


def test_observable_and_state_copy(model):
    book = TaskBook(model, initial_task=(1, 1, 3))
    assert book.observable(2) == (1, 1, 3, 0, 0, 0, 0, 0, 2)
    state = book.state
    state['tp'] = 0
    assert book.state['tp'] == 1
