"""The epoch protocol (docs/DESIGN.md) as pure state machines: every message order, late
answer, timeout and restart, deterministically and without DDS (core.protocol)."""

import numpy as np
import pytest

from hrc_ros.core.pomdp.belief import BeliefFilter
from hrc_ros.core.model import CT, DN, DP, MH, NW, RH1, RH2, TASK_VARIABLES, HRCModel
from hrc_ros.core.protocol import (ERROR, NO_EVIDENCE, OK, WARN, ActionPairing, ClockStart,
                                   SILENT_FALLBACK_S, SILENT_MIN_S, PeriodEstimate, SequenceGaps,
                                   Stamp, timeout_ns, DecisionGate, EpochFollower, EstimatorEpochs,
                                   InputError, TaskEpochs)
from hrc_ros.core.decision.selection import Selection
from hrc_ros.core.tasks import TaskBook

MS = 1_000_000
TIMEOUT = 250 * MS


def signal(k, published_ns, sequence=None):
    """The stamp of hrc/epoch k from one source: its writer's sequence number is k."""
    return Stamp(published_ns, k if sequence is None else sequence)


@pytest.fixture(scope='module')
def model(default_config):
    return HRCModel(default_config)


def state(step):
    return None if step.task_state is None else tuple(step.task_state[n] for n in TASK_VARIABLES)


def book_after(model, initial, *epochs):
    """The task book's state after epochs of (action, accepted), begun at 1."""
    book = TaskBook(model, initial_task=initial)
    book.begin_epoch(1)
    for k, (action, accepted) in enumerate(epochs, start=2):
        book.apply(action, accepted)
        book.begin_epoch(k)
    return tuple(book.state[n] for n in TASK_VARIABLES)


# -- EpochFollower ----------------------------------------------------------------------------
def follow(epochs, k, published_ms, sequence=None):
    stamp = signal(k, published_ms * MS, sequence)
    report = epochs.check(k, stamp)
    epochs.take(k, stamp)
    return report


def test_the_epoch_follower_locks_onto_one_source():
    """Issue 13: one stray hrc/epoch of 4294967295 made every follower drop every real epoch
    as 'does not follow', and the robot sat in dn for good."""
    epochs = EpochFollower()
    for k in (1, 2, 3):
        assert follow(epochs, k, 1000 * k) is None
    for stray in ((4294967295, 1), (3, 3), (2, 9), (30, 1)):   # a stray, a repeat, two others
        with pytest.raises(InputError, match='does not continue'):
            epochs.check(stray[0], signal(stray[0], 3500 * MS, stray[1]))
    assert epochs.ignored == 4 and epochs.last == 3
    assert follow(epochs, 4, 4000) is None                     # the source goes on
    assert follow(epochs, 7, 7000) is None                     # lost epochs: k and sequence
    assert epochs.last == 7                                    # advance together


def test_a_restarted_or_new_source_is_followed_once_the_old_one_fell_silent():
    epochs = EpochFollower()
    for k in (1, 2, 3, 4):
        follow(epochs, k, 1000 * k)
    assert epochs.silence_ns == 2500 * MS                      # 2.5 periods of 1 s
    with pytest.raises(InputError):                            # the old source is alive
        epochs.check(1, signal(1, 5000 * MS, 1))
    restart = follow(epochs, 1, 6600, sequence=1)              # silent for 2.6 s
    assert restart.level == WARN and 'restarted at 1 after 4' in restart.message
    assert epochs.silence_ns == SILENT_FALLBACK_S * 1e9        # the period is learnt again
    assert follow(epochs, 2, 7600, sequence=2) is None
    assert epochs.silence_ns == 2500 * MS
    new = follow(epochs, 57, 20_000, sequence=3)               # a replay started mid-count
    assert 'new epoch source at epoch 57' in new.message and epochs.last == 57


def test_silence_is_never_shorter_than_a_second():
    """Fast epochs (50 ms) and a scheduling stall: 2.5 periods would be 125 ms."""
    epochs = EpochFollower()
    for k in (1, 2, 3):
        follow(epochs, k, 50 * k)
    assert epochs.silence_ns == SILENT_MIN_S * 1e9
    with pytest.raises(InputError):
        epochs.check(4294967295, signal(4294967295, 800 * MS, 1))


def test_without_sequence_numbers_the_count_alone_decides():
    epochs = EpochFollower()
    follow(epochs, 1, 0, sequence=None)
    epochs.take(1, Stamp(0, None))
    assert epochs.check(2, Stamp(1000 * MS, None)) is None
    with pytest.raises(InputError):
        epochs.check(4294967295, Stamp(1000 * MS, None))


# -- TaskEpochs -------------------------------------------------------------------------------
def tasks_for(model, initial=(1, 1, 3), schedule=(), max_queue=None):
    return TaskEpochs(TaskBook(model, initial_task=initial, schedule=schedule,
                               max_queue=max_queue), TIMEOUT)


def test_task_epochs_follow_the_task_book(model):
    tasks = tasks_for(model)
    assert state(tasks.epoch(1, signal(1, 0), 0)) == book_after(model, (1, 1, 3))
    assert state(tasks.action(MH, 10 * MS, 11 * MS)) is None      # waits for epoch 2
    assert state(tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)) == \
        book_after(model, (1, 1, 3), (MH, False))
    tasks.action(RH2, 1010 * MS, 1011 * MS)
    tasks.answer(True, 1020 * MS, 1021 * MS)
    assert state(tasks.epoch(3, signal(3, 2000 * MS), 2000 * MS)) == \
        book_after(model, (1, 1, 3), (MH, False), (RH2, True))
    assert tasks.last_finalised == (2, 'rh2', True) and tasks.deadline is None


def test_an_epoch_that_overtakes_the_action_and_the_answer_is_held(model):
    """The order that failed CI: epoch k taken before a_{k-1} and its answer."""
    tasks = tasks_for(model)
    tasks.epoch(1, signal(1, 0), 0)
    step = tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)
    assert step.task_state is None and tasks.deadline == 1000 * MS + TIMEOUT
    assert tasks.awaited() == 'hrc/action of epoch 1'
    assert tasks.action(RH2, 990 * MS, 1001 * MS).task_state is None   # now the answer
    assert 'human_response to rh2' in tasks.awaited()
    assert tasks.deadline == 1000 * MS + TIMEOUT                        # not restarted
    step = tasks.answer(True, 995 * MS, 1002 * MS)
    assert state(step) == book_after(model, (1, 1, 3), (RH2, True))
    assert step.task_state['ty'] == 3 and not step.reports and tasks.late_inputs == 0


def test_an_answer_that_overtakes_its_action_counts(model):
    tasks = tasks_for(model)
    tasks.epoch(1, signal(1, 0), 0)
    tasks.answer(True, 995 * MS, 996 * MS)
    tasks.action(RH2, 990 * MS, 997 * MS)
    assert state(tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)) == \
        book_after(model, (1, 1, 3), (RH2, True))


def test_a_missing_action_is_dn_at_the_deadline_and_not_before(model):
    tasks = tasks_for(model, initial=(1, 2, 0), schedule=())
    tasks.epoch(1, signal(1, 0), 0)
    tasks.action(CT, 10 * MS, 10 * MS)
    tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)   # ct: the robot works (bc = 2)
    tasks.epoch(3, signal(3, 2000 * MS), 2000 * MS)   # a_2 missing: held
    assert tasks.expire(2000 * MS + TIMEOUT - 1).task_state is None
    step = tasks.expire(2000 * MS + TIMEOUT)
    assert state(step) == book_after(model, (1, 2, 0), (CT, False), (DN, False))
    assert step.task_state['bc'] == 2, 'dn pauses the robot: its counter must not run'
    assert step.reports[0].level == WARN and 'no hrc/action of epoch 2' in step.reports[0].message
    assert tasks.late_inputs == 1 and tasks.last_finalised == (2, 'dn', False)


def test_an_epoch_while_the_previous_is_held_finalises_it_first(model):
    tasks = tasks_for(model, initial=(1, 2, 0))
    tasks.epoch(1, signal(1, 0), 0)
    tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)   # a_1 missing: held
    step = tasks.epoch(3, signal(3, 1100 * MS), 1100 * MS)   # before the deadline
    assert tasks.last_finalised == (1, 'dn', False) and tasks.book.epoch == 2
    assert step.task_state is not None and tasks.next_epoch == 3   # a_2 awaited now
    assert tasks.deadline == 1100 * MS + TIMEOUT


def test_an_unanswered_request_is_refused_and_its_late_yes_screened(model):
    """A yes sent before the next request answers the refused one: never consent to the next."""
    tasks = tasks_for(model)
    tasks.epoch(1, signal(1, 0), 0)
    tasks.action(RH2, 10 * MS, 11 * MS)
    tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)
    step = tasks.expire(1000 * MS + TIMEOUT)             # no answer: refused
    assert step.task_state['ty'] == 0 and 'the request as refused' in step.reports[0].message
    # the late yes, pressed twice, then the same request again; a third late yes sent before
    # that action but taken after it (two writers) is screened too
    tasks.answer(True, 1300 * MS, 1301 * MS)
    tasks.answer(True, 1310 * MS, 1311 * MS)
    tasks.action(RH2, 1400 * MS, 1401 * MS)
    screened = tasks.answer(True, 1390 * MS, 1402 * MS)
    assert tasks.late_answers == 2 and 'late human response' in screened.reports[0].message
    step = tasks.epoch(3, signal(3, 2000 * MS), 2000 * MS)   # no answer to the new rh2: held
    assert step.task_state is None
    step = tasks.expire(2000 * MS + TIMEOUT)
    assert step.task_state['ty'] == 0, 'a late answer was taken as consent'
    # an answer sent after the request is its answer
    tasks.action(RH2, 2400 * MS, 2401 * MS)
    tasks.answer(True, 2410 * MS, 2411 * MS)
    assert tasks.epoch(4, signal(4, 3000 * MS), 3000 * MS).task_state['ty'] == 3


def test_of_several_answers_the_latest_published_counts(model):
    tasks = tasks_for(model)
    tasks.epoch(1, signal(1, 0), 0)
    tasks.action(RH2, 10 * MS, 11 * MS)
    tasks.answer(False, 30 * MS, 31 * MS)                 # the human changed their mind...
    tasks.answer(True, 20 * MS, 32 * MS)                  # ...this one was sent earlier
    assert tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS).task_state['ty'] == 0


def test_a_restart_finalises_the_old_count_then_renumbers(model):
    tasks = tasks_for(model, initial=(1, 2, 0), schedule=('3:2,2,1',))
    tasks.epoch(1, signal(1, 0), 0)
    tasks.action(CT, 10 * MS, 10 * MS)
    tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)
    step = tasks.epoch(1, signal(1, 5000 * MS), 5000 * MS)   # the decision node restarted
    assert step.reports[0].level == WARN and 'restarted at 1 after 2' in step.reports[0].message
    assert step.task_state is None                        # a_2 is still awaited, held
    step = tasks.action(NW, 1990 * MS, 5001 * MS)
    assert state(step) == book_after(model, (1, 2, 0), (CT, False), (NW, False))
    assert tasks.book.epoch == 1 and tasks.book.queue == type(tasks.book.queue)()
    tasks.action(NW, 5100 * MS, 5101 * MS)
    tasks.epoch(2, signal(2, 6000 * MS), 6000 * MS)
    tasks.action(NW, 6100 * MS, 6101 * MS)
    step = tasks.epoch(3, signal(3, 7000 * MS), 7000 * MS)
    assert step.task_state['tp'] == 2                     # the schedule follows the new count


def test_a_repeat_or_a_second_source_is_refused_without_effect(model):
    tasks = tasks_for(model)
    tasks.epoch(1, signal(1, 0), 0)
    tasks.action(MH, 10 * MS, 11 * MS)
    tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)
    before = (tasks.book.state, tasks.book.epoch, tasks.last_finalised)
    with pytest.raises(InputError, match='does not continue'):
        tasks.epoch(2, signal(2, 1100 * MS), 1100 * MS)
    assert (tasks.book.state, tasks.book.epoch, tasks.last_finalised) == before
    tasks.action(MH, 1110 * MS, 1111 * MS)
    tasks.epoch(3, signal(3, 2000 * MS), 2000 * MS)
    with pytest.raises(InputError, match='does not continue'):
        tasks.epoch(2, signal(2, 2100 * MS), 2100 * MS)   # a second source's count
    assert tasks.book.epoch == 3 and tasks.next_epoch is None


def test_a_stray_or_jumping_epoch_never_releases_the_schedule(model):
    """Issue 13: the task manager ran begin_epoch(4294967295), releasing every task at once."""
    tasks = tasks_for(model, initial=None, schedule=('5:1,1,0', '6:2,1,1'))
    tasks.epoch(1, signal(1, 0), 0)
    with pytest.raises(InputError):                        # a stray epoch: ignored
        tasks.epoch(4294967295, signal(4294967295, 500 * MS, 1), 500 * MS)
    assert tasks.book.pending == [] and tasks.book.epoch == 1
    tasks.action(DN, 600 * MS, 600 * MS)
    tasks.epoch(2, signal(2, 1000 * MS), 1000 * MS)
    tasks.action(DN, 1100 * MS, 1100 * MS)
    step = tasks.epoch(40, signal(40, 10_000 * MS, 1), 10_000 * MS)   # a new source, mid-count
    assert 'new epoch source' in step.reports[0].message
    assert tasks.book.epoch == 3 and step.task_state['tp'] == 0 and tasks.book.pending == []


def test_a_request_beyond_max_queue_is_refused(model):
    tasks = tasks_for(model, initial=None, max_queue=1)
    tasks.request(1, 1, 0)
    with pytest.raises(InputError, match='queue is full'):
        tasks.request(2, 1, 0)
    with pytest.raises(InputError, match='tx'):
        tasks.request(1, 1, 7)
    assert tasks.book.pending == [(1, 1, 0)]


# -- DecisionGate -----------------------------------------------------------------------------
TASK = {'tp': 1, 'tc': 1, 'tx': 3, 'ty': 0, 'hp': 0, 'hc': 0, 'bp': 0, 'bc': 0}
BELIEF = np.full(9, 1 / 9)


def fixed_selector(action=MH, calls=None):
    def select(belief, observable):
        if calls is not None:
            calls.append((tuple(belief), observable))
        return Selection(action, np.eye(8)[action], 'paper')
    return select


def gate_for(select=None, fresh_at_epoch=True):
    return DecisionGate(select or fixed_selector(), stale_timeout_ns=3000 * MS,
                        input_timeout_ns=500 * MS, fresh_at_epoch=fresh_at_epoch)


def feed(gate, now, d=1, belief=BELIEF, task=TASK):
    out = gate.received('distance_level', d, now)
    out += gate.received('task_state', task, now)
    return out + gate.received('belief', belief, now)


def test_the_gate_decides_when_every_input_answered_for_the_epoch():
    calls = []
    gate = gate_for(fixed_selector(MH, calls))
    assert gate.begin(1, 0) == [] and gate.deadline == 500 * MS
    decisions = feed(gate, 20 * MS, d=2)
    assert len(decisions) == 1
    decision = decisions[0]
    assert (decision.epoch, decision.action, decision.faults, decision.level) == (1, MH, (), OK)
    assert calls == [(tuple(BELIEF), (1, 1, 3, 0, 0, 0, 0, 0, 2))]
    assert decision.input_wait_ms == pytest.approx(20.0) and not decision.timed_out
    assert gate.deadline is None and gate.expire(500 * MS) == []   # decided: no timeout


def test_inputs_of_the_previous_epoch_do_not_count_for_this_one():
    gate = gate_for()
    gate.begin(1, 0)
    feed(gate, 10 * MS)
    gate.begin(2, 1000 * MS)
    assert gate.received('distance_level', 1, 1010 * MS) == []     # d may be an older one
    assert gate.expire(1000 * MS + 499 * MS) == []
    decision, = gate.expire(1500 * MS)
    assert decision.action == DN and decision.timed_out and decision.level == ERROR
    assert any('hrc/belief not received for epoch 2' in f for f in decision.faults)
    assert any('hrc/task_state not received for epoch 2' in f for f in decision.faults)


def test_a_malformed_input_answers_at_once_and_fails_safe():
    gate = gate_for()
    gate.begin(1, 0)
    gate.received('distance_level', 1, 1 * MS)
    gate.received('task_state', TASK, 2 * MS)
    decision, = gate.malformed('belief', 'belief sums to 2', 3 * MS)
    assert decision.action == DN and not decision.timed_out
    assert decision.faults == ('hrc/belief malformed: belief sums to 2',)
    # a good message afterwards clears it for the next epoch
    gate.begin(2, 1000 * MS)
    assert feed(gate, 1010 * MS)[0].action == MH


def test_missing_and_stale_inputs_fail_safe():
    gate = gate_for()
    gate.begin(1, 0)
    decision, = gate.expire(500 * MS)
    assert sorted(decision.faults) == sorted(f'{t} missing (never received)'
                                             for t in DecisionGate.INPUTS.values())
    gate.received('distance_level', 1, 600 * MS)            # then never again
    for k, start in ((2, 1000 * MS), (3, 4000 * MS)):
        gate.begin(k, start)
        gate.received('task_state', TASK, start + 1)
        gate.received('belief', BELIEF, start + 2)
        decision, = gate.expire(start + 500 * MS)            # d did not answer: the timeout
    assert decision.faults == ('hrc/distance_level stale (3.900 s old > stale_timeout 3 s)',)


def test_a_collision_is_dn_with_a_warning():
    gate = gate_for()
    gate.begin(1, 0)
    decision, = feed(gate, 1 * MS, d=0)
    assert decision.action == DN and decision.collision and decision.level == WARN
    assert decision.selection.action == MH       # what the policy wanted, for the report
    assert 'collision circle' in decision.message


def test_a_failing_selector_stops_the_robot():
    def broken(belief, observable):
        raise KeyError('policy lookup')
    gate = gate_for(broken)
    gate.begin(1, 0)
    decision, = feed(gate, 1 * MS)
    assert decision.action == DN and decision.faults[0].startswith('decision failed: KeyError')


def test_a_new_epoch_decides_the_pending_one_first():
    gate = gate_for()
    gate.begin(1, 0)
    gate.received('distance_level', 1, 1 * MS)
    decisions = gate.begin(2, 400 * MS)                      # before the input timeout
    assert [(d.epoch, d.action, d.timed_out) for d in decisions] == [(1, DN, True)]
    assert gate.epoch == 2 and gate.pending


def test_a_swapped_selector_decides_from_the_new_epoch_never_the_pending_one():
    """A policy swapped in at epoch k's boundary (the live swap) never decides epoch k - 1,
    even when k - 1 is still pending, and decides all of epoch k."""
    old_calls, new_calls = [], []
    gate = gate_for(fixed_selector(MH, old_calls))
    gate.begin(1, 0)
    assert feed(gate, 1 * MS)[0].action == MH
    gate.begin(2, 1000 * MS)
    feed(gate, 1001 * MS, belief=np.eye(9)[4])
    gate.begin(3, 2000 * MS)
    gate.received('task_state', TASK, 2001 * MS)              # epoch 3 still pending ...
    decisions = gate.begin(4, 2400 * MS, select=fixed_selector(CT, new_calls))
    assert [(d.epoch, d.action) for d in decisions] == [(3, DN)]   # ... decided by the old rules
    decision, = feed(gate, 2410 * MS)
    assert (decision.epoch, decision.action) == (4, CT)
    assert len(old_calls) == 2 and len(new_calls) == 1
    gate.begin(5, 3400 * MS)                                   # the new one stays
    assert feed(gate, 3410 * MS)[0].action == CT


def test_topic_mode_counts_inputs_that_precede_the_epoch_signal():
    """A replay may play an epoch's inputs before its epoch signal."""
    gate = gate_for(fresh_at_epoch=False)
    assert feed(gate, 10 * MS) == []                         # no epoch yet
    decision, = gate.begin(1, 20 * MS)
    assert decision.action == MH and decision.epoch == 1
    decision, = gate.begin(2, 1000 * MS) + gate.expire(1500 * MS)
    assert decision.action == DN                             # nothing new since the decision


def test_the_clock_waits_for_the_graph_then_starts():
    clock = ClockStart(started_ns=0, stale_timeout_ns=3000 * MS)
    tick = clock.tick(100 * MS, lambda: False, lambda: {'epoch_subscribers': 0})
    assert not tick.start_epoch and tick.report.level == WARN
    assert tick.report.values == {'waited_s': 0.1, 'epoch_subscribers': 0}
    assert clock.tick(200 * MS, lambda: True) == type(tick)(False)   # ready: epoch 1 next
    assert clock.tick(300 * MS, lambda: False).start_epoch             # no more graph checks
    assert clock.running and clock.tick(400 * MS, None).start_epoch


def test_the_clock_starts_anyway_after_stale_timeout():
    clock = ClockStart(started_ns=0, stale_timeout_ns=1000 * MS)
    assert not clock.tick(999 * MS, lambda: False).start_epoch
    tick = clock.tick(1000 * MS, lambda: False)
    assert tick.start_epoch and 'without having discovered' in tick.report.message


# -- EstimatorEpochs --------------------------------------------------------------------------
def estimator(model, min_samples=3):
    return EstimatorEpochs(BeliefFilter(model), min_samples)


def window(est, level, d, start_ns, n=5):
    for i in range(n):
        est.sample(level, start_ns + i * MS)
        est.skeleton(d, start_ns + i * MS)


def test_estimator_epochs_follow_the_belief_filter(model):
    f = BeliefFilter(model)
    est = estimator(model)
    window(est, 1, 2, 0)
    step = est.epoch_signal(1, signal(1, 100 * MS))
    assert (step.observation, step.distance_level, step.reports) == (1, 2, [])
    np.testing.assert_allclose(step.belief, f.initial(1))
    est.action(MH)
    window(est, 3, 1, 200 * MS)
    step = est.epoch_signal(2, signal(2, 1000 * MS))
    np.testing.assert_allclose(step.belief, f.update(f.initial(1), MH, 3))
    assert step.distance_level == 1


def test_a_sample_published_after_the_signal_counts_in_the_next_window(model):
    """The order that failed CI: the cell's first sample after its reaction, taken first."""
    est = estimator(model)
    window(est, 1, 3, 0)
    est.sample(3, 150 * MS)                                    # after the signal...
    est.skeleton(0, 150 * MS)
    step = est.epoch_signal(1, signal(1, 100 * MS))                       # ...taken before it
    assert (step.observation, step.distance_level) == (1, 3)
    window(est, 3, 0, 200 * MS, n=2)                           # 2 + the early one = 3
    step = est.epoch_signal(2, signal(2, 1000 * MS))
    assert (step.observation, step.distance_level) == (3, 0)


def test_a_dropout_publishes_nothing_and_predicts_only(model):
    f = BeliefFilter(model)
    est = estimator(model)
    window(est, 2, 2, 0)
    first = est.epoch_signal(1, signal(1, 100 * MS)).belief
    est.action(MH)
    est.sample(2, 200 * MS)                                    # 1 sample < 3
    step = est.epoch_signal(2, signal(2, 1000 * MS))
    assert step.observation is None and step.belief is None and step.distance_level is None
    kinds = sorted(r.kind for r in step.reports)
    assert kinds == ['no_observation', 'no_skeleton']
    np.testing.assert_allclose(est.belief, f.update(first, MH, NO_EVIDENCE))
    window(est, 2, 2, 1100 * MS)                               # no action: dn
    step = est.epoch_signal(3, signal(3, 2000 * MS))
    np.testing.assert_allclose(step.belief, f.update(f.update(first, MH, NO_EVIDENCE), DN, 2))


def test_the_estimator_follows_a_restart_and_refuses_a_repeat(model):
    est = estimator(model)
    window(est, 1, 1, 0)
    est.epoch_signal(4, signal(4, 100 * MS))
    with pytest.raises(InputError):
        est.epoch_signal(4, signal(4, 200 * MS))
    window(est, 2, 2, 300 * MS)
    step = est.epoch_signal(1, signal(1, 3200 * MS))       # after 3 s of silence
    assert step.reports[0].kind == 'restart' and step.observation == 2 and est.epoch == 1


def test_the_estimator_memory_is_bounded(model):
    est = EstimatorEpochs(BeliefFilter(model), 3, recent=64)
    for i in range(10_000):
        est.sample(1 + i % 3, i)
        est.skeleton(i % 4, i)
    assert len(est._levels) == 64 and len(est._distances) == 64
    step = est.epoch_signal(1, signal(1, 20_000))
    # the vote counts every sample of the window (3334 of level 1), not only the kept pairs
    assert step.observation == 1 and step.distance_level == 9_999 % 4


# -- EstimatorEpochs, posterior mode ----------------------------------------------------------
HOLD = 200 * MS
OPEN = {'tp': 2, 'tc': 3, 'tx': 1, 'ty': 0, 'hp': 0, 'hc': 0, 'bp': 0, 'bc': 0}   # rh1 eligible
TAKEN = {**OPEN, 'ty': 1, 'hp': 2, 'hc': 3}                         # x_k after an accepted rh1


def posterior_epoch_one(model, answered=True):
    """Epoch 1 (O 2, d 2) closed at 100 ms, x_1 with an open task (published after the
    signal), then rh1 and the human's answer at 300 ms (unless not `answered`)."""
    f = BeliefFilter(model, mode='posterior')
    est = EstimatorEpochs(f, 3, task_state_timeout_s=HOLD / 1e9)
    window(est, 2, 2, 0)
    first = est.epoch_signal(1, signal(1, 100 * MS), now=100 * MS).belief
    assert est.task_state(OPEN, 150 * MS) is None and est.deadline is None
    est.action(RH1)
    if answered:
        est.response(300 * MS)
    return f, est, first


def posterior_start(model, answered=True, d_after=1):
    """Epoch 1 (O 2, d 2), x_1 with an open task (published after the signal), then rh1, the
    human's answer (unless not `answered`) and epoch 2's window (O 1, d `d_after`) closed at
    1000 ms: b_2 is held for x_2."""
    f, est, first = posterior_epoch_one(model, answered)
    window(est, 1, d_after, 200 * MS)
    step = est.epoch_signal(2, signal(2, 1000 * MS), now=1001 * MS)
    return f, est, first, step


@pytest.mark.parametrize('after, accepted', [(TAKEN, True), (OPEN, False)])
def test_posterior_b_k_waits_for_x_k_and_takes_the_answer_and_the_move(model, after, accepted):
    f, est, first, step = posterior_start(model)
    assert (step.observation, step.distance_level, step.belief) == (1, 1, None)   # O_k at once
    assert est.deadline == 1001 * MS + HOLD
    assert est.task_state(after, 990 * MS) is None          # published before the signal: x_1
    done = est.task_state(after, 1050 * MS)
    want = f.update(first, RH1, 1, model.transition_likelihood(RH1, True, accepted, 2, 1))
    np.testing.assert_allclose(done.belief, want)
    assert done.reports == [] and est.deadline is None
    # the answer moved the belief: bayes (the answer ignored) is another belief
    assert not np.allclose(done.belief, BeliefFilter(model).update(first, RH1, 1), atol=1e-3)


def test_posterior_without_x_k_leaves_the_answer_out_after_the_hold(model):
    f, est, first, _ = posterior_start(model)
    assert est.expire(1001 * MS + HOLD - 1) is None
    done = est.expire(1001 * MS + HOLD)
    np.testing.assert_allclose(done.belief, f.update(
        first, RH1, 1, model.transition_likelihood(RH1, False, False, 2, 1)))
    assert [r.kind for r in done.reports] == ['no_task_state'] and done.reports[0].level == WARN
    assert est.deadline is None and est.expire(10_000 * MS) is None


def test_posterior_x_k_delivered_before_its_signal_completes_at_the_signal(model):
    f, est, first = posterior_epoch_one(model)
    window(est, 1, 1, 200 * MS)
    assert est.task_state(TAKEN, 1010 * MS) is None        # x_2, overtaking the signal
    step = est.epoch_signal(2, signal(2, 1000 * MS), now=1020 * MS)
    np.testing.assert_allclose(step.belief, f.update(
        first, RH1, 1, model.transition_likelihood(RH1, True, True, 2, 1)))
    assert est.deadline is None


def test_posterior_after_a_dropout_or_without_a_skeleton_predicts_with_what_is_known(model):
    f, est, first = posterior_epoch_one(model)
    est.sample(1, 200 * MS)                                  # 1 sample < 3, no skeleton
    step = est.epoch_signal(2, signal(2, 1000 * MS), now=1000 * MS)
    assert (step.observation, step.distance_level, step.belief) == (None, None, None)
    done = est.task_state(OPEN, 1050 * MS)                   # refused
    assert done.belief is None                               # a dropout: predicted only
    # the move is unknown (no skeleton): only the refusal counts
    move_unknown = model.transition_likelihood(RH1, True, False, None, None)
    np.testing.assert_allclose(move_unknown, 1.0 - model.config.p_accept[np.arange(9) // 3])
    np.testing.assert_allclose(est.belief, f.update(first, RH1, NO_EVIDENCE, move_unknown))


def test_a_new_signal_closes_a_held_posterior_update_first(model):
    f, est, first, _ = posterior_start(model)
    est.action(DN)
    window(est, 3, 1, 1100 * MS)
    step = est.epoch_signal(3, signal(3, 2000 * MS), now=2000 * MS)
    assert 'no_task_state' in [r.kind for r in step.reports]
    held = f.update(first, RH1, 1, model.transition_likelihood(RH1, False, False, 2, 1))
    done = est.task_state(OPEN, 2050 * MS)
    np.testing.assert_allclose(done.belief, f.update(
        held, DN, 3, model.transition_likelihood(DN, False, False, 1, 1)))


def test_posterior_leaves_an_unanswered_request_out(model):
    """No hrc/human_response between x_1 and x_2: the task manager took rh1 as refused for want
    of an answer (ty stays 0). That says nothing about the human's motivation; it once counted
    as a refusal. b_2 waits for the answer to the hold's deadline, then only the move counts,
    with a WARN."""
    f, est, first, _ = posterior_start(model, answered=False)
    assert est.task_state(OPEN, 1150 * MS) is None and est.deadline == 1001 * MS + HOLD
    done = est.expire(1001 * MS + HOLD)
    np.testing.assert_allclose(done.belief, f.update(
        first, RH1, 1, model.transition_likelihood(RH1, False, False, 2, 1)))
    assert [r.kind for r in done.reports] == ['no_answer'] and done.reports[0].level == WARN
    # an answer published after x_2 (late: the task manager had finalised) is not one either
    f, est, first, _ = posterior_start(model, answered=False)
    assert est.task_state(OPEN, 1150 * MS) is None
    assert est.response(1160 * MS) is None
    assert [r.kind for r in est.expire(1001 * MS + HOLD).reports] == ['no_answer']


def test_posterior_takes_an_answer_delivered_after_its_task_state(model):
    """The task manager's x_2 and the human's answer come from two publishers, and nothing
    orders them at the estimator: with both ready at one wake, rclpy ran the task state first
    and the answer, unseen, was read as missing. A refusal (ty 0) now waits for the answer
    published before x_2; a commitment (ty 1) proves an answer at once."""
    f, est, first, _ = posterior_start(model, answered=False)
    assert est.task_state(OPEN, 1050 * MS) is None
    assert est.task_state(TAKEN, 1060 * MS) is None      # a later task state: x_2 stands
    done = est.response(300 * MS)                        # published long before, taken now
    np.testing.assert_allclose(done.belief, f.update(
        first, RH1, 1, model.transition_likelihood(RH1, True, False, 2, 1)))
    assert done.reports == [] and est.deadline is None

    f, est, first, _ = posterior_start(model, answered=False)
    done = est.task_state(TAKEN, 1050 * MS)
    np.testing.assert_allclose(done.belief, f.update(
        first, RH1, 1, model.transition_likelihood(RH1, True, True, 2, 1)))
    assert done.reports == [] and est.deadline is None


def test_posterior_screens_the_late_answer_to_an_unanswered_request(model):
    """rh1 of epoch 1 went unanswered (x_2 shows it refused for want of an answer); its late
    answer is published after x_2 but before a_2. The task manager ignores it (it answers the
    refused request), so a_2 is unanswered too; the estimator once read it as a_2's answer
    and took x_3's refusal as evidence. An answer after a_2 is a_2's."""
    for late_ns, answered in ((1350 * MS, False), (1450 * MS, True)):
        f, est, first, _ = posterior_start(model, answered=False)
        est.task_state(OPEN, 1150 * MS)
        b2 = est.expire(1001 * MS + HOLD).belief                   # no_answer
        est.response(late_ns)
        est.action(RH1, 1400 * MS)
        window(est, 1, 1, 1500 * MS)
        est.epoch_signal(3, signal(3, 2000 * MS), now=2000 * MS)
        done = est.task_state(OPEN, 2050 * MS) or est.expire(2000 * MS + HOLD)
        np.testing.assert_allclose(done.belief, f.update(
            b2, RH1, 1, model.transition_likelihood(RH1, answered, False, 1, 1)))
        assert [r.kind for r in done.reports] == ([] if answered else ['no_answer'])


def test_posterior_leaves_an_impossible_distance_move_out(model):
    """d 2 -> 0 in one epoch is impossible under the model (moves of one level at most): the
    whole move likelihood is 0, and the filter once restarted from O_2 alone, wiping out
    everything learnt. Now the move is left out (a WARN) and the answer still counts."""
    assert not model.transition_likelihood(RH1, False, False, 2, 0).any()
    f, est, first, step = posterior_start(model, d_after=0)
    done = est.task_state(OPEN, 1050 * MS)
    want = f.update(first, RH1, 1, model.transition_likelihood(RH1, True, False, None, None))
    np.testing.assert_allclose(done.belief, want)
    assert [r.kind for r in done.reports] == ['impossible_move']
    assert not np.allclose(done.belief, f.initial(1), atol=1e-3)


def test_posterior_leaves_out_evidence_the_belief_calls_impossible():
    """A cell whose most motivated humans always accept (p_accept 1.0) and a belief sure of
    such a human: a refusal is impossible under the belief (b . e = 0), and the filter once
    restarted from O alone. The evidence is left out instead, with a WARN."""
    from hrc_ros.core.config import load_config
    from hrc_ros.core.paths import default_config_path
    certain = HRCModel(load_config(default_config_path(),
                                   {'model': {'p_accept': [0.3, 0.8, 1.0]}}))
    f = BeliefFilter(certain, mode='posterior')
    est = EstimatorEpochs(f, 3, task_state_timeout_s=HOLD / 1e9)
    window(est, 2, 2, 0)
    est.epoch_signal(1, signal(1, 100 * MS), now=100 * MS)
    est.belief = sure = np.eye(9)[7]                         # em 2 (always accepts), ea 1
    est.task_state(OPEN, 150 * MS)
    est.action(RH1)
    est.response(300 * MS)
    window(est, 1, 2, 200 * MS)
    est.epoch_signal(2, signal(2, 1000 * MS), now=1000 * MS)
    done = est.task_state(OPEN, 1050 * MS)                   # refused
    np.testing.assert_allclose(done.belief, f.update(sure, RH1, 1))
    assert [r.kind for r in done.reports] == ['impossible_evidence']


def test_posterior_hold_follows_the_period_known_at_the_signal(model):
    """task_state_timeout 0: the hold is 0.4 of the period. At epoch 2 the period is known
    only once epoch 2 is taken; the node once computed the hold before, from the 0.2 s
    fallback, shorter than the task manager's 0.25 s wait for the answer."""
    from hrc_ros.core.protocol import ESTIMATOR_HOLD_FALLBACK_S, ESTIMATOR_HOLD_FRACTION
    f = BeliefFilter(model, mode='posterior')
    est = EstimatorEpochs(f, 3)
    assert est.hold_ns == int(ESTIMATOR_HOLD_FALLBACK_S * 1e9) > TIMEOUT
    window(est, 2, 2, 0)
    est.epoch_signal(1, signal(1, 100 * MS), now=100 * MS)
    window(est, 1, 1, 200 * MS)
    est.epoch_signal(2, signal(2, 1100 * MS), now=1100 * MS)
    assert est.deadline == 1100 * MS + int(ESTIMATOR_HOLD_FRACTION * 1000 * MS)
    window(est, 1, 1, 1200 * MS)
    # the count restarts (the decision node restarted): the period starts again, but the last
    # one known stands in; the 0.3 s fallback was longer than a 0.5 s period's input wait
    step = est.epoch_signal(1, signal(1, 6000 * MS, sequence=1), now=6000 * MS)
    assert [r.kind for r in step.reports][:2] == ['restart', 'no_task_state']
    assert est.epochs.period.period_ns is None
    assert est.deadline == 6000 * MS + int(ESTIMATOR_HOLD_FRACTION * 1000 * MS)
    est.task_state_timeout_s = 0.35                         # an explicit value wins
    window(est, 1, 1, 6200 * MS)
    est.epoch_signal(2, signal(2, 7000 * MS), now=7000 * MS)
    assert est.deadline == 7000 * MS + 350 * MS


def test_posterior_keeps_the_x_k_that_completed_the_hold_against_a_flood(model):
    """x_2 (rh1 taken, ty 1) completes b_2's hold; then a flood of stray task states (an open
    task) is published before epoch 3. x_2 is what epoch 3's eligibility is read from, not
    whatever the bounded store still holds: rh1 is not eligible at x_2, so no answer counts."""
    f, est, first, _ = posterior_start(model)
    b2 = est.task_state(TAKEN, 1050 * MS).belief
    for i in range(200):
        est.task_state(OPEN, 1100 * MS + i * MS)
    est.action(RH1)
    est.response(1400 * MS)
    window(est, 1, 1, 1500 * MS)
    est.epoch_signal(3, signal(3, 2000 * MS), now=2000 * MS)
    done = est.task_state(TAKEN, 2050 * MS)
    np.testing.assert_allclose(done.belief, f.update(
        b2, RH1, 1, model.transition_likelihood(RH1, False, False, 1, 1)))


def test_a_held_update_closes_at_the_next_signal_after_a_swap_to_bayes(model):
    """A configuration swap from posterior to bayes while b_2 is held: the next signal closes
    b_2 first (without the answer), then b_3 is a bayes update of it."""
    f, est, first, _ = posterior_start(model)
    est.filter = BeliefFilter(model, mode='bayes')
    est.action(DN)
    window(est, 3, 1, 1100 * MS)
    step = est.epoch_signal(3, signal(3, 2000 * MS), now=2000 * MS)
    assert 'no_task_state' in [r.kind for r in step.reports] and est.deadline is None
    b2 = est.filter.update(first, RH1, 1)
    np.testing.assert_allclose(step.belief, est.filter.update(b2, DN, 3))


def test_the_bayes_estimator_ignores_task_states(model):
    est = estimator(model)
    window(est, 2, 2, 0)
    est.epoch_signal(1, signal(1, 100 * MS))
    est.task_state(OPEN, 150 * MS)
    est.action(RH1)
    window(est, 1, 1, 200 * MS)
    step = est.epoch_signal(2, signal(2, 1000 * MS))
    assert step.belief is not None and est.deadline is None
    assert est.task_state(TAKEN, 1050 * MS) is None


# -- ActionPairing ----------------------------------------------------------------------------
X1, X2 = {'tp': 1}, {'tp': 2}


def test_the_cell_reacts_with_the_task_state_of_the_epoch():
    pairing = ActionPairing(TIMEOUT)
    assert pairing.task_state_received(X1, 0) == []
    reaction, = pairing.action_received(RH2, 10 * MS)
    assert (reaction.action, reaction.task_state, reaction.late) == (RH2, X1, '')


def test_an_action_before_its_task_state_is_held():
    """The order that failed CI: a_k taken before x_k."""
    pairing = ActionPairing(TIMEOUT)
    pairing.task_state_received(X1, 0)
    pairing.action_received(NW, 10 * MS)
    assert pairing.action_received(RH1, 1000 * MS) == [] and pairing.held == RH1
    assert pairing.expire(1000 * MS + TIMEOUT - 1) == []
    reaction, = pairing.task_state_received(X2, 1001 * MS)
    assert (reaction.action, reaction.task_state, reaction.late) == (RH1, X2, '')
    assert pairing.deadline is None


def test_a_held_action_reacts_with_the_latest_state_at_the_timeout_or_the_next_action():
    pairing = ActionPairing(TIMEOUT)
    assert pairing.action_received(DP, 0) == []
    reaction, = pairing.expire(TIMEOUT)
    assert reaction.task_state is None and 'task_state_timeout' in reaction.late
    pairing.task_state_received(X1, 300 * MS)
    pairing.action_received(NW, 310 * MS)
    pairing.action_received(DP, 1000 * MS)                   # x_2 never came
    first, = pairing.action_received(RH2, 2000 * MS)
    assert (first.action, first.task_state) == (DP, X1) and 'before the next action' in first.late
    assert pairing.held == RH2



# -- timeouts that follow the period ----------------------------------------------------------
def test_a_follower_learns_the_epoch_period_from_source_stamps():
    period = PeriodEstimate()
    assert period.period_ns is None
    assert timeout_ns(0.0, 0.25, period.period_ns, 0.25) == 250 * MS    # unknown: fallback
    for k, jitter in enumerate((0, 0, 0, 40, 40, 40)):                   # one late epoch
        period.observe(k * 200 * MS + jitter * MS)
    assert period.period_ns == 200 * MS                                  # the median
    assert timeout_ns(0.0, 0.25, period.period_ns, 0.25) == 50 * MS
    assert timeout_ns(0.4, 0.25, period.period_ns, 0.25) == 400 * MS    # explicit wins
    period.observe(0)                                                    # a restart
    assert period.period_ns is None


def test_sequence_gaps_count_what_a_writer_sent_and_never_arrived():
    gaps = SequenceGaps()
    assert [gaps.observe(s) for s in (1, 2, 5, 6, 10)] == [0, 0, 2, 0, 3] and gaps.lost == 5
    assert gaps.observe(1) == 0 and gaps.observe(None) == 0     # a new writer; no numbers
