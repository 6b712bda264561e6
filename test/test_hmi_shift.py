"""The operator's console without ROS or a web server: the figures of the shift
(`core.hmi.shift`), the timeline (`core.hmi.timeline`) and the event log (`core.hmi.events`),
and the machine that feeds them.

The figures are `hrc-evaluate --cell arm`'s (`core.robot.metrics`): a batch episode of the cell
with the arm, replayed into the console's counters as the graph would publish it (the arm's
separation and speed bound, its protective stop, the task states, the answers), gives the same
tasks per hour, idle and protective-stop shares, smallest separation and refused requests as
`evaluate_arm` on that episode.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrc_ros.core.hmi import HmiMachine
from hrc_ros.core.hmi import events as ev
from hrc_ros.core.hmi.shift import ARM_HOLD_S, ShiftFigures, rounded
from hrc_ros.core.hmi.timeline import Timeline
from hrc_ros.core.model import ACTION_INDEX, TASK_VARIABLES

S = 1_000_000_000
T0 = 1_700_000_000 * S          # a system clock


# -- the figures -------------------------------------------------------------------------------
def test_the_arms_state_holds_from_one_sample_to_the_next():
    shift = ShiftFigures(T0)
    shift.arm_sample(T0, 1.0, 0.5)                  # moving
    shift.arm_sample(T0 + 2 * S, 0.8, 0.0)          # at rest from here
    shift.protective_stop(T0 + 3 * S, True)         # stopped from here
    shift.arm_sample(T0 + 3 * S + S // 2, 0.4, 0.0)
    shift.protective_stop(T0 + 4 * S, False)
    shift.arm_sample(T0 + 4 * S, 0.9, 0.3)
    f = shift.figures(T0 + 5 * S, 'shift')
    assert f['arm_seconds'] == 5.0 and f['seconds'] == 5.0
    assert f['idle_share'] == pytest.approx(20.0)        # 2..3 s
    assert f['protective_stop_share'] == pytest.approx(20.0)   # 3..4 s
    assert f['min_separation'] == 0.4


def test_a_message_that_arrives_after_the_figures_is_counted_at_its_time():
    shift = ShiftFigures(T0)
    shift.arm_sample(T0, 1.0, 0.5)
    assert shift.figures(T0 + 2 * S, 'shift')['protective_stop_share'] == 0.0
    shift.protective_stop(T0 + S, True)       # published at 1 s, taken after the figures
    assert shift.figures(T0 + 2 * S, 'shift')['protective_stop_share'] == pytest.approx(50.0)


def test_a_silent_robot_side_is_not_measured_beyond_the_hold():
    shift = ShiftFigures(T0)
    shift.arm_sample(T0, 1.0, 0.0)                  # idle, then nothing for 10 s
    shift.arm_sample(T0 + 10 * S, 1.0, 0.0)
    f = shift.figures(T0 + 11 * S, 'shift')
    assert f['arm_seconds'] == pytest.approx(ARM_HOLD_S + 1.0)
    assert f['idle_share'] == pytest.approx(100.0)
    assert f['seconds'] == 11.0
    assert ShiftFigures(T0).figures(T0 + S, 'shift')['idle_share'] is None     # no arm
    assert ShiftFigures(T0).figures(T0 + S, 'shift')['min_separation'] is None


def test_windows_count_the_last_minutes_and_the_shift_counts_everything():
    shift = ShiftFigures(T0)
    for minute in range(30):
        shift.task_completed(T0 + minute * 60 * S + 1)
    shift.request_refused(T0 + 5 * S)
    shift.decision(T0 + 6 * S, 4, True)
    shift.decision(T0 + 6 * S + 1, 4, True)          # the same epoch again: counted once
    shift.decision(T0 + 7 * S, 5, False)
    now = T0 + 30 * 60 * S
    ten, shift_all = shift.figures(now, '10min'), shift.figures(now, 'shift')
    assert ten['tasks_completed'] == 10 and ten['seconds'] == 600.0
    assert ten['tasks_per_hour'] == pytest.approx(60.0)
    assert ten['refused_requests'] == 0 and ten['fail_safe_epochs'] == 0
    assert shift_all['tasks_completed'] == 30 and shift_all['seconds'] == 1800.0
    assert (shift_all['refused_requests'], shift_all['fail_safe_epochs']) == (1, 1)
    assert shift.figures(now, 'hour')['since_ns'] == T0           # never before the shift
    assert ShiftFigures(T0).figures(now, 'shift')['fail_safe_epochs'] is None   # no report
    # what happened before the shift began (a latched message) is not counted
    late = ShiftFigures()
    late.task_completed(T0)
    late.arm_sample(T0, 0.1, 0.0)
    assert late.all_windows(T0 + S) is None                    # no shift yet
    late.begin(T0 + 2 * S)
    late.begin(T0 + S)                  # the first epoch signal, overtaken by its action
    late.begin(T0 - 5 * S)              # a stray old message moves nothing
    late.begin(T0 + 3 * S)                                     # it began once
    late.arm_sample(T0 + 3 * S, 0.5, 0.0)
    f = late.figures(T0 + 4 * S, 'shift')
    assert (f['since_ns'], f['tasks_completed'], f['min_separation']) == (T0 + S, 0, 0.5)
    assert f['arm_seconds'] == pytest.approx(2.0)   # the state heard before, from the start on


def test_the_figures_keep_a_fixed_memory_over_hours():
    shift = ShiftFigures(T0)
    for second in range(3 * 3600):
        shift.arm_sample(T0 + second * S, 1.0 + math.sin(second), 0.2 * (second % 2))
    before = shift._bins.nbytes
    f = shift.figures(T0 + 3 * 3600 * S, 'hour')
    assert f['arm_seconds'] == pytest.approx(3600.0, abs=1.0)
    assert f['idle_share'] == pytest.approx(50.0, abs=0.1)
    assert shift._bins.nbytes == before and shift._bins.shape[0] < 3700


def test_rounded_as_the_console_shows_them():
    f = rounded({'since_ns': 1_234_567_891, 'tasks_per_hour': 12.345, 'idle_share': None,
                 'min_separation': 0.123456, 'refused_requests': 3})
    assert f == {'since_ms': 1234, 'tasks_per_hour': 12.3, 'idle_share': None,
                 'min_separation': 0.123, 'refused_requests': 3}


# -- the same figures as hrc-evaluate --cell arm -----------------------------------------------
EPOCHS = 20
SEED = 1      # an episode with completed tasks, a refused request, protective stops, idle time


@pytest.fixture(scope='module')
def arm_episode():
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import arm_config_path
    from hrc_ros.core.robot.cell import ArmCell, evaluate_arm, person_seed
    from hrc_ros.core.study.evaluation import episodes_of
    config = load_config(arm_config_path())
    model = HRCModel(config)
    policy = load_policy(default_policy_path(config), config)
    scenarios, humans = episodes_of(model, 'random', 1, EPOCHS, SEED, 0.5)
    recorded = ArmCell(model, policy).episode(scenarios[0], humans[0], person_seed(SEED, 0),
                                              'paper', record=True)
    result = evaluate_arm(model, policy, episodes=1, epochs=EPOCHS, seed=SEED,
                          selectors=('paper',))['paper']
    return model, recorded, result


def test_the_console_counts_as_hrc_evaluate_cell_arm(arm_episode):
    """The episode's control samples as hrc/separation (S and the speed bound) and
    hrc/protective_stop, its completions and refusals, into the console's counters: the
    figures of the whole shift are evaluate_arm's."""
    model, recorded, result = arm_episode
    assert recorded.tasks_completed > 0 and recorded.refused_requests > 0
    assert recorded.stop_time > 0 and recorded.idle_time > 0
    shift = ShiftFigures(T0)
    for t, stop, bound, separation in recorded.samples:
        t_ns = T0 + round(t * S)
        shift.protective_stop(t_ns, stop)
        shift.arm_sample(t_ns, separation, bound)
    period = recorded.seconds / EPOCHS
    done = 0
    for k, (completed, accepted) in enumerate(zip(recorded.completed, recorded.accepted), 1):
        for _ in range(completed - done):
            shift.task_completed(T0 + round(k * period * S))
        done = completed
        if accepted is False:
            shift.request_refused(T0 + round(k * period * S))
    f = shift.figures(T0 + round(recorded.seconds * S), 'shift')
    assert f['seconds'] == recorded.seconds
    assert f['tasks_per_hour'] == pytest.approx(result.tasks_per_hour[0], rel=1e-12)
    assert f['idle_share'] == pytest.approx(result.idle_share[0], rel=1e-9)
    assert f['protective_stop_share'] == pytest.approx(result.stop_share[0], rel=1e-9)
    assert f['min_separation'] == result.min_separation[0]
    assert f['refused_requests'] == result.refused_requests[0]


def test_the_machine_sees_the_episodes_completions_and_refusals_in_its_task_states(
        arm_episode):
    """The task states, actions and answers of the episode as the cell publishes them: the
    HMI counts a task done when it leaves the cell and a request refused when the task
    manager's next task state refuses it. The last epoch's are not seen (no next task state)."""
    model, recorded, _ = arm_episode
    hmi = HmiMachine(model.rho, model.sigma, instance='test', start_ns=T0)
    for k, (action, accepted, x) in enumerate(zip(recorded.actions, recorded.accepted,
                                                  recorded.task_states), 1):
        t = T0 + k * S
        hmi.epoch_signal(k, t, t)
        hmi.task_state_message(dict(zip(TASK_VARIABLES, x)), t + 1, t)
        hmi.action_message(ACTION_INDEX[action], t + 2, t)
        if accepted is not None:
            hmi.response_message(accepted, t + 3, t)
    f = hmi.shift.figures(T0 + (EPOCHS + 1) * S, 'shift')
    assert f['tasks_completed'] == recorded.completed[-2]
    assert f['refused_requests'] == sum(a is False for a in recorded.accepted[:-1])
    assert f['refused_requests'] > 0


# -- the event log -----------------------------------------------------------------------------
def test_a_protective_stop_is_logged_with_the_bridges_reason():
    log = ev.EventLog()
    log.protective_stop(T0, True)
    assert log.take() == []                          # waits for the reason
    log.stop_reason(T0 + 1000, True, 'separation 0.412 m below the protective distance 0.5 m')
    stop, = log.take()
    assert stop == {'t_ms': T0 // 1_000_000, 'kind': ev.STOP, 'text': 'the arm stopped for '
                    'safety: separation 0.412 m below the protective distance 0.5 m',
                    'detail': 'separation 0.412 m below the protective distance 0.5 m'}
    # while it holds: a new reason is logged, new figures of the same reason are not
    log.stop_reason(T0 + S, True, 'separation 0.398 m below the protective distance 0.5 m')
    assert log.take() == []
    log.stop_reason(T0 + 2 * S, True, 'the skeleton has not changed for 0.6 s: a frozen tracker')
    log.stop_reason(T0 + 2 * S + 1, True, 'the skeleton has not changed for 1.6 s: a frozen '
                    'tracker')
    assert [e['text'] for e in log.take()] == [
        'the arm stays stopped for safety: the skeleton has not changed for 0.6 s: a frozen '
        'tracker']
    log.protective_stop(T0 + 3 * S, False)
    over, = log.take()
    assert over['kind'] == ev.STOP_OVER and over['text'].endswith('over after 3.0 s')
    # the reason first (another order of arrival), then the edge
    log.stop_reason(T0 + 10 * S, True, 'no human data yet')
    log.protective_stop(T0 + 10 * S + 5, True)
    assert log.take()[0]['text'] == 'the arm stopped for safety: no human data yet'
    # no reason at all: logged without one after REASON_WAIT_S
    log.protective_stop(T0 + 20 * S, False)
    log.protective_stop(T0 + 30 * S, True)
    log.expire(T0 + 30 * S + int(ev.REASON_WAIT_S * S) - 1)
    assert [e['kind'] for e in log.take()] == [ev.STOP_OVER]
    log.expire(T0 + 30 * S + int(ev.REASON_WAIT_S * S) + 1)
    assert log.take()[0]['text'] == 'the arm stopped for safety (the robot side gave no reason)'


def test_a_fail_safe_is_logged_when_it_begins_changes_and_ends():
    log = ev.EventLog()
    log.decision(T0, 1, [])
    log.decision(T0 + S, 2, ['d = 0: the human is inside the collision circle'])
    log.decision(T0 + 2 * S, 3, ['d = 0: the human is inside the collision circle'])
    log.decision(T0 + 3 * S, 4, ['hrc/belief stale (3.2 s old > stale_timeout 3 s)'])
    log.decision(T0 + 4 * S, 5, ['hrc/belief stale (4.2 s old > stale_timeout 3 s)'])
    log.decision(T0 + 5 * S, 6, [])
    assert [(e['kind'], e['text']) for e in log.take()] == [
        (ev.FAIL_SAFE, 'the robot stopped for safety at step 2: the worker is too close '
                       '(inside the collision circle)'),
        (ev.FAIL_SAFE, "the robot stopped for safety at step 4: the estimate of the worker's "
                       'state is out of date'),
        (ev.FAIL_SAFE_OVER, 'the robot decides again at step 6: fail-safe over after 4 steps')]


def test_refused_orders_and_policy_changes_are_logged_and_the_log_is_capped():
    log = ev.EventLog(kept=5)
    log.order_refused(T0, (1, 2, 3), 'refused: the queue is full', 'this console')
    log.policy(T0, 'OK', 'epoch 7: now deciding with b.npz', {
        'epoch': 7, 'policy_file': 'b.npz', 'previous_policy_file': 'a.npz'})
    log.policy(T0, 'ERROR', 'refused', {'policy_file': 'a.npz', 'error': 'not a policy'})
    assert [e['text'] for e in log.take()] == [
        'order from this console refused (priority 1, 2 steps, a job for both): the queue is '
        'full',
        'new policy in use from step 7: b.npz (before: a.npz)',
        'a new policy was refused; the robot keeps a.npz: not a policy']
    for i in range(20):
        log.order_refused(T0 + i, None, 'refused: malformed', 'another publisher')
    assert len(log.entries) == 5 and len(log.take()) == 5


# -- the timeline ------------------------------------------------------------------------------
def test_the_timeline_holds_ten_minutes_in_buckets_and_hands_out_what_is_new():
    line = Timeline()
    belief = np.zeros(9)
    belief[2 * 3 + 0] = 1.0                       # motivation high, aggression low
    for k in range(1, 1501):                      # 25 minutes at 1 s epochs, the arm at 50 Hz
        t = T0 + k * S
        line.epoch(t, k, 'nw' if k % 2 else 'rh2', belief, 2)
        for i in range(50):
            line.arm_sample(t + i * S // 50, 1.0 + i / 100, 0.5)
        line.override_sample(0.5)
        if k == 1490:
            line.protective_stop(t, True)
    snapshot = line.snapshot()
    assert len(snapshot['epochs']) == 601          # ten minutes: the span is bounded
    assert snapshot['epochs'][-1] == [round((T0 + 1500 * S) / S, 3), 1500, 'rh2', 2.0, 0.0, 2]
    assert 1190 <= len(snapshot['robot']) <= 1201   # two buckets a second
    last = snapshot['robot'][-1]         # the first half of the last epoch: its smallest S
    assert last[1:] == [1.0, 0.5, 0.5]   # (the second half's bucket is still open)
    assert snapshot['stops'] == [[round((T0 + 1490 * S) / S, 3), 1]]
    taken = line.take(T0 + 1501 * S)
    assert taken is not None and len(taken['epochs']) <= 5000
    assert line.take(T0 + 1501 * S + 1) is None    # nothing new, and not before FLUSH_S
    line.epoch(T0 + 1502 * S, 1502, 'dn', None, 0)
    assert line.take(T0 + 1501 * S + 2) is None    # new, but within FLUSH_S of the last take
    assert line.take(T0 + 1502 * S)['epochs'] == [[round((T0 + 1502 * S) / S, 3), 1502, 'dn',
                                                   None, None, 0]]


def test_the_machine_feeds_the_console(arm_episode):
    """An epoch's row carries the belief and distance seen before its action; the arm's samples,
    a protective stop and its reason reach the figures, the timeline and the log."""
    hmi = HmiMachine(2, 2, instance='test', start_ns=T0)
    hmi.belief_message([0, 0, 0, 0, 0, 0, 1.0, 0, 0])
    hmi.distance_message(1)
    hmi.epoch_signal(1, T0 + S, T0 + S)
    hmi.task_state_message(dict.fromkeys(TASK_VARIABLES, 0), T0 + S + 1, T0 + S)
    hmi.action_message(ACTION_INDEX['nw'], T0 + S + 2, T0 + S)
    hmi.separation_message(0.9, 0.5, 0.3, T0 + S, T0 + S)
    hmi.protective_stop_message(True, T0 + 2 * S)
    hmi.stop_report(True, 'separation 0.4 m below the protective distance 0.5 m', T0 + 2 * S)
    hmi.separation_message(0.4, 0.5, 0.0, T0 + 2 * S, T0 + 2 * S)
    rows = hmi.timeline.take(T0 + 3 * S)
    assert rows['epochs'] == [[round((T0 + S + 2) / S, 3), 1, 'nw', 2.0, 0.0, 1]]
    assert rows['stops'] == [[round(T0 / S + 2, 3), 1]]
    assert [e['kind'] for e in hmi.events.take()] == [ev.STOP]
    figures = hmi.operator_view(T0 + 3 * S, T0 + 3 * S)['figures']['shift']
    assert figures['protective_stop_share'] == 50.0 and figures['min_separation'] == 0.4
    assert figures['as_of_ms'] == (T0 + 3 * S) // 1_000_000
