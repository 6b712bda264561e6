"""The graph with the arm, ROS-free: the rules the nodes of docs/ROBOT.md 5 add to the cell.

- the task manager's `robot_progress` (`core.protocol.TaskEpochs`): the robot's counter bc
  runs down in an epoch only when the bridge's progress, published before the epoch's end,
  shows a cycle bc has not counted (the batch cell's `robot_cycle_done`);
"""

from hrc_ros.core.model import CT, NW, TASK_VARIABLES, HRCModel
from hrc_ros.core.protocol import Stamp, TaskEpochs
from hrc_ros.core.tasks import TaskBook, robot_cycle_done

import pytest

MS = 1_000_000
TIMEOUT = 250 * MS


@pytest.fixture(scope='module')
def model(default_config):
    return HRCModel(default_config)


def bc_of(step):
    return None if step.task_state is None else step.task_state['bc']


def test_the_physical_progress_rule_counts_each_completed_cycle_once():
    # a task of 3 cycles: bc = 3 after the commit, then one per cycle completed
    assert not robot_cycle_done(3, 0, 3)          # nothing done yet
    assert robot_cycle_done(3, 1, 3)              # the first cycle: 3 -> 2
    assert not robot_cycle_done(3, 1, 2)          # the same cycle is not counted twice
    assert robot_cycle_done(3, 3, 2)              # two more done: one a epoch, 2 -> 1
    assert robot_cycle_done(3, 3, 1) and not robot_cycle_done(3, 3, 0)


def run_epochs(tasks, actions, progress):
    """Epochs 1.. at 1 s; `progress` = [(published_ms, (nature, cycles, done))] fed before
    each signal they precede. Returns bc of every epoch's task state."""
    out, fed = [], 0
    for k in range(1, len(actions) + 2):
        t = (k - 1) * 1000 * MS
        while fed < len(progress) and progress[fed][0] * MS < t:
            tasks.robot_progress_received(*progress[fed][1], progress[fed][0] * MS)
            fed += 1
        out.append(bc_of(tasks.epoch(k, Stamp(t, k), t)))
        if k <= len(actions):
            tasks.action(actions[k - 1], t + 10 * MS, t + 11 * MS)
    return out


def test_without_robot_progress_bc_runs_by_the_model(model):
    tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT)
    # ct commits (bc = tc = 2), then every nw runs bc down, whatever the arm does
    assert run_epochs(tasks, [CT, NW, NW], [(1500, (0, 2, 0))]) == [0, 2, 1, 0]


def test_with_robot_progress_bc_follows_the_cycles_the_arm_completed(model):
    tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT, robot_progress=True)
    # epoch 1 ct; the bridge starts the run (0 of 2) in epoch 1, completes cycle 1 in epoch
    # 2, nothing in epoch 3 (SSM held the arm), cycle 2 in epoch 4
    progress = [(300, (0, 2, 0)), (1700, (0, 2, 1)), (3400, (0, 2, 2))]
    assert run_epochs(tasks, [CT, NW, NW, NW], progress) == [0, 2, 1, 1, 0]
    assert tasks.book.completed and tasks.book.completed[0].complete_epoch == 4
    assert tasks.status()['robot_progress'] == (0, 2, 2)


def test_progress_counts_by_its_publication_time_not_its_arrival(model):
    tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT, robot_progress=True)
    tasks.epoch(1, Stamp(0, 1), 0)
    tasks.action(CT, 10 * MS, 11 * MS)
    tasks.robot_progress_received(0, 2, 0, 300 * MS)
    assert bc_of(tasks.epoch(2, Stamp(1000 * MS, 2), 1000 * MS)) == 2
    # epoch 3's signal comes first; the action of epoch 2 is late, and so is a progress
    # published before the signal: it counts. One published after the signal does not.
    assert tasks.epoch(3, Stamp(2000 * MS, 3), 2000 * MS).task_state is None
    tasks.robot_progress_received(0, 2, 2, 2005 * MS)        # epoch 3's, delivered first
    tasks.robot_progress_received(0, 2, 1, 1990 * MS)        # epoch 2's, overtaken
    assert tasks.progress_at(2000 * MS) == (0, 2, 1)
    assert bc_of(tasks.action(NW, 1010 * MS, 2010 * MS)) == 1
    # epoch 3 ends with both cycles done: bc 1 -> 0, the task completes
    tasks.action(NW, 2020 * MS, 2021 * MS)
    assert bc_of(tasks.epoch(4, Stamp(3000 * MS, 4), 3000 * MS)) == 0


def test_no_share_or_no_progress_is_no_robot_work(model):
    for progress in ([], [(300, (0, 0, 0))]):     # nothing published; cycles 0: no share
        tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT,
                           robot_progress=True)
        assert run_epochs(tasks, [CT, NW, NW], progress) == [0, 2, 2, 2]
    state = tuple(tasks.book.state[n] for n in TASK_VARIABLES)
    assert state[3] == 2 and state[7] == 2        # committed, bc untouched
