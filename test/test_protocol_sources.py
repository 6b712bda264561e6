"""One source per input, one decider per cell, one swap rule, one timeout order (issue 17),
as pure machines without DDS: `EpochFollower` against a forged epoch source, `ClockOwner` and
`ClockStart` (two decision nodes), `StreamLock` (two body trackers), `RequestCounts`,
`check_timeout_order` and `core.swap.check_swap`."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from hrc_ros.core.protocol import (CLAIM_LIFETIME_S, DECISION_WAIT, ERROR, ESTIMATOR_HOLD,
                                   STALE, TASK_HOLD, Claim, ClockOwner, ClockStart, Endpoint,
                                   EpochFollower, EpochListeners, InputError, ReadyMark,
                                   RequestCounts, Stamp, StreamLock, TaskEpochs,
                                   check_timeout_order, ready_writers)
from hrc_ros.core.tasks import TaskBook

MS = 1_000_000
S = 1_000_000_000


def follow(epochs, k, published_ns, sequence):
    stamp = Stamp(published_ns, sequence)
    report = epochs.check(k, stamp)
    epochs.take(k, stamp)
    return report


def running_source(n=5):
    """A follower that took epochs 1..n of one writer (sequence = epoch), one per second."""
    epochs = EpochFollower()
    for k in range(1, n + 1):
        follow(epochs, k, k * S, k)
    return epochs


# -- a forged epoch source ----------------------------------------------------------------------
@pytest.mark.parametrize('zeros_first', [True, False], ids=['zeros-before-k', 'zeros-after-k'])
def test_a_forger_that_pushes_its_numbers_past_the_source_is_refused(zeros_first):
    """Issue 17: 1,000 refused epochs of value 0 (sequence 1..1000), then k+1 right after the
    decision node's k: the follower took it as the same writer (its sequence had 'moved on')
    and refused every real epoch after it."""
    epochs = running_source(5)
    zeros = [Stamp(5 * S + 300 * MS + i, i) for i in range(1, 1001)]
    if zeros_first:
        for stamp in zeros:
            epochs.refused(stamp)                 # the conversion refused them: epoch 0
        follow(epochs, 6, 6 * S, 6)               # the decision node's k
    else:
        follow(epochs, 6, 6 * S, 6)
        for stamp in zeros:
            epochs.refused(stamp)
    with pytest.raises(InputError, match='does not continue'):
        epochs.check(7, Stamp(6 * S + 10 * MS, 1001))            # k+1, right after k
    for jump in (1001 - 6 + 6, 8):                                 # lost epochs, or k+2
        with pytest.raises(InputError):
            epochs.check(jump, Stamp(6 * S + 20 * MS, 1002))
    assert follow(epochs, 7, 7 * S, 7) is None and epochs.last == 7   # the source goes on
    with pytest.raises(InputError):
        epochs.check(8, Stamp(7 * S + 10 * MS, 1003))
    assert follow(epochs, 8, 8 * S, 8) is None


def test_the_task_manager_stays_with_the_legitimate_source(model):
    tasks = TaskEpochs(TaskBook(model, initial_task=(1, 1, 0), schedule=('4:2,2,1',)),
                       250 * MS)
    for k in (1, 2, 3):
        tasks.epoch(k, Stamp(k * S, k), k * S)
        tasks.action(0, k * S + 100 * MS, k * S + 100 * MS)
    for i in range(1, 1001):
        tasks.epochs.refused(Stamp(3 * S + 200 * MS, i))
    with pytest.raises(InputError):
        tasks.epoch(4, Stamp(3 * S + 300 * MS, 1001), 3 * S + 300 * MS)
    assert tasks.book.epoch == 3 and tasks.book.pending == []       # not released early
    step = tasks.epoch(4, Stamp(4 * S, 4), 4 * S)
    assert step.task_state is not None and tasks.book.epoch == 4


def test_the_same_writers_refused_message_still_explains_its_gap():
    """A replay of a bag holding a stray epoch, or a repeat: one writer, its own refused
    message between k and k+1, and no other writer in evidence."""
    epochs = EpochFollower()
    follow(epochs, 1, 1 * S, 1)
    with pytest.raises(InputError):
        epochs.check(1, Stamp(1 * S + 100 * MS, 2))                # its own repeat
    epochs.refused(Stamp(1 * S + 200 * MS, 3))                     # its own epoch 0
    assert follow(epochs, 2, 2 * S, 4) is None and epochs.last == 2
    assert follow(epochs, 5, 5 * S, 7) is None                     # epochs lost on the way
    # a gap nothing explains is not the writer's own: refused
    with pytest.raises(InputError):
        epochs.check(6, Stamp(6 * S, 12))


def test_another_writer_is_in_evidence_for_a_silence_only():
    epochs = running_source(5)
    epochs.refused(Stamp(5 * S + 100 * MS, 2))                    # a number already passed
    assert epochs.foreign_in_evidence(6 * S)
    with pytest.raises(InputError):                                # lost epochs: not now
        epochs.check(7, Stamp(6 * S, 7))
    assert not epochs.foreign_in_evidence(5 * S + 100 * MS + epochs.silence_ns + 1)


# -- one decider per cell -------------------------------------------------------------------------
def claim(started_s, nonce=1, node='/decision', mode='timer'):
    return Claim(int(started_s * S), nonce, node, mode)


def test_the_owner_is_the_oldest_claim_and_both_sides_agree():
    a, b = claim(10, 7, '/a'), claim(10, 3, '/b')                 # the same moment: the id
    first, second = ClockOwner(a), ClockOwner(b)
    first.heard(b, 0)
    second.heard(a, 0)
    assert first.owner(0) == second.owner(0) == b
    assert second.owns(0) and not first.owns(0)
    older = claim(5, 9, '/c')
    second.heard(older, 0)
    assert not second.owns(0) and second.owner(0) == older
    assert second.owns(int(CLAIM_LIFETIME_S * S) + 1)               # its claim fell silent


def ready():
    return True


def test_two_decision_nodes_started_at_once_do_not_deadlock():
    """Issue 17: two started at the same moment each saw the other's publishers and neither
    started its clock (0 actions). The claims decide: exactly one starts."""
    a, b = claim(10, 7, '/a'), claim(10, 3, '/b')
    clocks = {}
    for mine, other in ((a, b), (b, a)):
        owner = ClockOwner(mine)
        owner.heard(other, 0)
        clocks[mine.node] = ClockStart(0, 3 * S, owner=owner)
    endpoints = {'/a': [Endpoint('/hrc/epoch', '/b', 'bb'), Endpoint('/hrc/action', '/b', 'bb')],
                 '/b': [Endpoint('/hrc/epoch', '/a', 'aa'), Endpoint('/hrc/action', '/a', 'aa')]}
    started, messages = {}, {'/a': [], '/b': []}
    for now in (100 * MS, 200 * MS, 300 * MS):
        for node, clock in clocks.items():
            tick = clock.tick(now, ready, other_sources=lambda n=node: endpoints[n], me=node)
            started[node] = started.get(node, False) or tick.start_epoch
            assert tick.report is not None and tick.report.level == ERROR
            messages[node].append(tick.report.message)
    assert started == {'/a': False, '/b': True}
    assert 'another decision node is on the cell: /a' in messages['/b'][0]
    assert 'defers to /b' in messages['/b'][0] and 'keeps its clock' in messages['/b'][-1]
    assert all('decides for the cell: /b' in m and 'does not start its clock' in m
               for m in messages['/a'])


def test_a_clock_that_learns_of_an_older_claim_yields_and_a_follower_publishes_nothing():
    mine = ClockOwner(claim(20, 1, '/new'))
    clock = ClockStart(0, 3 * S, owner=mine)
    clock.tick(100 * MS, ready)
    assert clock.tick(200 * MS, ready).start_epoch and clock.running    # it started alone
    mine.heard(claim(5, 2, '/old'), 250 * MS)                           # then heard the older
    tick = clock.tick(300 * MS, ready)
    assert not tick.start_epoch and not clock.running
    assert 'stops its clock' in tick.report.message and '/old' in tick.report.message
    follower = ClockOwner(claim(20, 1, '/replay', 'topic'))
    follower.heard(claim(5, 2, '/old'), 0)
    tick = ClockStart(0, 3 * S, running=True, owner=follower).tick(0, ready)
    assert not tick.start_epoch and 'publishes no action' in tick.report.message


def test_a_new_node_decides_nothing_before_it_has_heard_the_claims_the_graph_shows():
    """The follower of a running cell once took an epoch before the running node's claim
    arrived, and published an action for it: a second action in that epoch."""
    follower = ClockOwner(claim(20, 1, '/replay', 'topic'))
    clock = ClockStart(0, 3 * S, running=True, owner=follower)
    tick = clock.tick(10 * MS, ready, claim_publishers=lambda: 2)   # its own and one other
    assert not tick.start_epoch and 'waits to hear the claims' in tick.report.message
    follower.heard(claim(5, 2, '/old'), 20 * MS)
    tick = clock.tick(30 * MS, ready, claim_publishers=lambda: 2)
    assert not tick.start_epoch and 'publishes no action' in tick.report.message
    alone = ClockStart(0, 3 * S, running=True, owner=ClockOwner(claim(20, 1, '/replay')))
    assert alone.tick(0, ready, claim_publishers=lambda: 1).start_epoch     # a replay: at once
    silent = ClockStart(0, 3 * S, running=True, owner=ClockOwner(claim(20, 1, '/x')))
    late = int(CLAIM_LIFETIME_S * S)
    assert silent.tick(late, ready, claim_publishers=lambda: 2).start_epoch  # not for ever


def test_an_unclaimed_source_keeps_a_clock_from_starting_and_is_named_only_once_known():
    owner = ClockOwner(claim(10))
    clock = ClockStart(0, 3 * S, owner=owner)
    unknown = Endpoint('/hrc/epoch', None, '0f0e')
    tick = clock.tick(100 * MS, ready, other_sources=lambda: [unknown])
    assert not tick.start_epoch and 'does not start its clock' in tick.report.message
    assert 'UNKNOWN' not in tick.report.message and 'gid 0f0e' in tick.report.message
    from hrc_ros.ros.sources import endpoint_node
    placeholder = SimpleNamespace(node_name='_NODE_NAME_UNKNOWN_',
                                  node_namespace='_NODE_NAMESPACE_UNKNOWN_')
    assert endpoint_node(placeholder) is None
    assert endpoint_node(SimpleNamespace(node_name='decision', node_namespace='/')) == \
        '/decision'


# -- two body-tracking streams ----------------------------------------------------------------
def test_a_listener_is_ready_for_a_clock_once_both_ends_have_matched():
    """Issue 37: a reader that matches the clock's writer after epoch 1 was sent misses it, so
    a listener counts for a clock only when its own mark names that clock's writer and the
    clock's graph shows the listener's reader; the latest mark of a listener counts."""
    listeners = EpochListeners(limit=3)
    listeners.heard(ReadyMark('/task_manager', frozenset({'a'})))
    listeners.heard(ReadyMark('/belief_estimator', frozenset({'b'})))   # another clock's
    listeners.heard(ReadyMark('/view_inputs', frozenset({'a', 'b'})))
    readers = ['/task_manager', '/belief_estimator']        # the view's reader not discovered
    assert listeners.ready('a', readers) == ['/task_manager']
    assert listeners.ready('a', readers + ['/view_inputs']) == ['/task_manager', '/view_inputs']
    assert listeners.ready(None, readers) == []               # this clock's GID not known yet
    listeners.heard(ReadyMark('/task_manager', frozenset()))  # its writer left: not ready
    assert listeners.ready('a', readers) == []
    with pytest.raises(InputError, match='3 listeners already'):
        listeners.heard(ReadyMark('/a_fourth', frozenset({'a'})))   # bounded, not grown
    listeners.heard(ReadyMark('/belief_estimator', frozenset({'a'})))  # a known one still is
    assert listeners.ready('a', readers) == ['/belief_estimator']


def test_a_listener_says_it_has_matched_the_writers_only_when_each_reader_counts_them_all():
    """rclpy names no matched endpoint: a reader's count must equal the graph's for the mark to
    name the graph's writers (the interleavings one process cannot produce on DDS)."""
    assert ready_writers([0], set()) == frozenset()                    # nothing yet, said
    assert ready_writers([0], {'w'}) is None                            # w not matched yet
    assert ready_writers([1], {'w'}) == frozenset({'w'})
    assert ready_writers([1], {'w', 'v'}) is None                       # which one? wait
    assert ready_writers([2], {'w'}) is None      # one left the graph, still matched: wait
    assert ready_writers([1, None], {'w'}) is None                      # the bag's not made yet
    assert ready_writers([1, 0], {'w'}) is None                         # the bag's not matched
    assert ready_writers([1, 1], {'w'}) == frozenset({'w'})
    assert ready_writers([], {'w'}) is None                             # no reader at all


def test_the_stream_lock_follows_one_writer_and_the_next_after_silence():
    lock = StreamLock(max_skip=64)
    assert lock.classify(5000, 0.0, 0.5) == StreamLock.FOLLOWED
    assert lock.classify(1, 0.01, 0.5) == StreamLock.OTHER          # a second writer
    assert lock.classify(5003, 0.02, 0.5) == StreamLock.FOLLOWED    # two frames lost
    assert lock.classify(9000, 0.03, 0.5) == StreamLock.OTHER       # not its numbers
    assert lock.classify(2, 0.6, 0.5) == StreamLock.NEW             # the followed one is gone
    assert lock.classify(3, 0.63, 0.5) == StreamLock.FOLLOWED and lock.others == 2
    assert lock.classify(None, 0.7, 0.5) == StreamLock.FOLLOWED     # no numbers: one stream


# -- requests ---------------------------------------------------------------------------------
def test_every_request_is_in_exactly_one_count():
    counts = RequestCounts()
    for sequence in range(1, 31):
        assert counts.arrived(sequence, one_publisher=True) == 0
        counts.refuse() if sequence % 3 == 0 else counts.accept()
    assert (counts.accepted, counts.refused, counts.lost) == (20, 10, 0)
    assert counts.arrived(35, one_publisher=True) == 4 and counts.lost == 4
    assert counts.arrived(40, one_publisher=False) == 0 and counts.lost == 4


# -- the order of the timeouts ----------------------------------------------------------------
def test_the_timeouts_nest_and_a_value_that_breaks_the_order_is_refused_with_the_reason():
    assert check_timeout_order(1.0, {}) is None                    # the defaults nest
    assert TASK_HOLD.fraction < ESTIMATOR_HOLD.fraction < DECISION_WAIT.fraction < 1.0 \
        < STALE.fraction
    reason = check_timeout_order(1.0, {DECISION_WAIT: 0.3})
    assert "belief_estimator's task_state_timeout (0.4 x the period = 0.4 s) must be " \
        "shorter than decision's input_timeout (0.3 s)" in reason
    assert 'task_manager' in check_timeout_order(1.0, {TASK_HOLD: 0.45})
    assert 'shorter than epoch_period' in check_timeout_order(1.0, {DECISION_WAIT: 1.0})
    assert 'longer than epoch_period' in check_timeout_order(1.0, {STALE: 0.9})
    assert check_timeout_order(None, {TASK_HOLD: 0.45}) is None    # no period: nothing to say
    assert check_timeout_order(None, {TASK_HOLD: 0.45, ESTIMATOR_HOLD: 0.3}) is not None
    assert check_timeout_order(0.2, {DECISION_WAIT: 0.12}) is None


# -- the swap rule ------------------------------------------------------------------------------
def test_the_swap_rule(default_config, policy_path):
    from hrc_ros.core.paths import share_dir
    from hrc_ros.core.swap import ACCEPTED, REFUSED, SAME, STAGED, check_swap
    other_config_policy_path = str(share_dir() / 'policies' / 'paper.npz')   # paper.yaml's
    small = default_config.with_overrides({'model': {'rho': 1, 'sigma': 1}})
    other = default_config.with_overrides({'model': {'p_accept': [0.1, 0.5, 0.8]}})
    files = {'small.yaml': small, 'other.yaml': other, '': default_config}

    def load(value):
        if value not in files:
            raise OSError(f'{value}: cannot read')
        return files[value]

    def verdict(config, policy=None, running_policy=None):
        return check_swap(default_config.rho, default_config.sigma, '', config,
                          running_policy, policy, load=load).verdict

    assert verdict('') == SAME and verdict('other.yaml') == ACCEPTED
    assert verdict('small.yaml') == verdict('nowhere.yaml') == REFUSED
    assert verdict('', policy_path, policy_path) == SAME
    assert verdict('other.yaml', policy_path, policy_path) == STAGED      # config alone
    assert verdict('', other_config_policy_path, policy_path) == REFUSED
    reason = check_swap(2, 2, '', 'small.yaml', load=load).reason
    assert 'restart the nodes to change the state space' in reason
    # the decision node: another rule for the robot's counter than the task manager keeps
    files['arm.yaml'] = default_config.with_overrides({'model': {'robot_paused_by':
                                                                 ['dn', 'dp', 'dm']}})
    refused = check_swap(2, 2, '', 'arm.yaml', policy_path, policy_path, load=load,
                         paused=default_config.robot_paused_by)
    assert refused.verdict == REFUSED and 'restart the nodes' in refused.reason
    assert 'under dn, dp, dm' in refused.reason
    assert check_swap(2, 2, '', 'other.yaml', policy_path, policy_path, load=load,
                      paused=('dn',)).verdict == STAGED
    assert verdict('arm.yaml', policy_path, policy_path) == STAGED   # the estimator's rule


def test_the_swap_rule_checks_the_pomdp_policy_the_selector_reads(default_config, policy_path,
                                                                  tmp_path):
    """pomdp_policy (the decision node's POMDP policy, for the pomdp and fib selectors): set
    in the change and wrong, refused; unchanged and no longer matching, staged; checked by
    the configuration's hash and the observation model's; '' finds the shipped one."""
    import shutil
    from hrc_ros.core.config import load_config
    from hrc_ros.core.paths import share_dir, shipped_config_path
    from hrc_ros.core.swap import ACCEPTED, REFUSED, SAME, STAGED, check_swap
    unaware = load_config(shipped_config_path('fail_safe_unaware'))
    unaware_policy = str(share_dir() / 'policies' / 'fail_safe_unaware.npz')
    copy = tmp_path / 'unaware_pomdp.npz'      # not in policies/pomdp/: found by its path only
    shutil.copyfile(share_dir() / 'policies' / 'pomdp' / 'fail_safe_unaware.npz', copy)
    default_pomdp = str(share_dir() / 'policies' / 'pomdp' / 'default.npz')
    # the same cell with a person prior: the configuration and the observation hashes move
    prior = default_config.with_overrides({'observation': {'prior': [1.0] + [0.0] * 8}})
    files = {'': default_config, 'unaware.yaml': unaware, 'prior.yaml': prior}

    def check(config, policy, pomdp, running_pomdp='', needed=True):
        return check_swap(2, 2, '', config, policy_path, policy, load=files.__getitem__,
                          running_pomdp=running_pomdp, pomdp_value=pomdp, pomdp_needed=needed)

    assert check('', policy_path, '').verdict == SAME
    assert check('', policy_path, default_pomdp).verdict == ACCEPTED    # the same file, named
    assert check('unaware.yaml', unaware_policy, str(copy)).verdict == ACCEPTED
    # '' is the shipped POMDP policy solved for the configuration set: there is one for it
    assert check('unaware.yaml', unaware_policy, '').verdict == ACCEPTED
    refused = check('unaware.yaml', unaware_policy, default_pomdp)
    assert refused.verdict == REFUSED and refused.reason.startswith('pomdp_policy refused: ')
    assert 'was solved for configuration' in refused.reason
    missing = check('', policy_path, str(tmp_path / 'none.npz'))
    assert missing.verdict == REFUSED and 'does not exist' in missing.reason
    not_pomdp = check('', policy_path, policy_path)               # an MDP policy file
    assert not_pomdp.verdict == REFUSED and 'is not a POMDP policy file' in not_pomdp.reason
    # set while the configuration waits for its MDP policy (staged), a wrong one is refused
    # at once, on its own set, not when the policy comes (hrc-fleet --apply's order)
    for wrong in (default_pomdp, str(tmp_path / 'none.npz'), unaware_policy):
        early = check('unaware.yaml', policy_path, wrong)
        assert early.verdict == REFUSED and early.reason.startswith('pomdp_policy refused: ')
    assert check('unaware.yaml', policy_path, str(copy)).verdict == STAGED    # right: waits
    # the running pomdp_policy unchanged, no longer solved for the new configuration: staged
    staged = check('unaware.yaml', unaware_policy, default_pomdp, running_pomdp=default_pomdp)
    assert staged.verdict == STAGED and 'set pomdp_policy' in staged.reason
    # a person prior leaves the MDP's hash as it is, not the observation model's: no shipped
    # POMDP policy is solved for it, so '' (unchanged) stages it until one is named
    staged = check('prior.yaml', policy_path, '')
    assert staged.verdict == STAGED and 'no POMDP policy in' in staged.reason
    assert 'name it in pomdp_policy' in staged.reason
    # a selector that reads no POMDP policy: an unchanged one is not checked, a new one is
    assert check('unaware.yaml', unaware_policy, default_pomdp, running_pomdp=default_pomdp,
                 needed=False).verdict == ACCEPTED
    assert check('', policy_path, str(tmp_path / 'none.npz'),
                 needed=False).verdict == REFUSED
