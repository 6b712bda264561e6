"""The task stream with a queue (MODEL.md 8.1): configuration, the queue step rule by rule, the
factored solver and the fused sweep against it, policy files, the evaluation reading the queue
length, the epoch-by-epoch simulation following it as the evaluation does, and the refusals
where the queue is not built yet (the cell with the arm)."""

import json

import numpy as np
import pytest
from reference import assert_shipped_policy_solves_todays_model, rule_q

from hrc_ros.core.config import ConfigError, load_config
from hrc_ros.core.decision.selection import ActionSelector
from hrc_ros.core.mdp.policy import PolicyError, load_policy, save_policy
from hrc_ros.core.mdp.solver import FactoredBellman, evaluate_policy, solve
from hrc_ros.core.model import ACTIONS, DN, DP, NW, TASK_VARIABLES, HRCModel
from hrc_ros.core.paths import default_config_path, shipped_config_path
from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of, evaluate
from hrc_ros.core.study.simulation import Scenario

CONFIG = default_config_path()
SMALL = {'model': {'rho': 1, 'sigma': 1}}
QUEUE = {'queue': 2, 'arrival_idle': 0.3, 'arrival_busy': 0.6, 'waiting_cost': 0.7,
         'q': [[1, 1, 0, 0.5], [1, 1, 3, 0.2], [1, 1, 2, 0.3]]}


def queue_config(stream=QUEUE, **sections):
    return load_config(CONFIG, overrides={**SMALL, 'stream': stream, **sections})


@pytest.fixture(scope='module')
def small_queue():
    return HRCModel(queue_config())


@pytest.fixture(scope='module')
def small_queue_mdp(small_queue):
    """The small queue model's MDP solve, once for the tests that read it (none changes it)."""
    return solve(small_queue)


# -- configuration ----------------------------------------------------------------------------
def test_a_queue_multiplies_the_states_and_keeps_the_other_configurations_as_they_were():
    plain = load_config(CONFIG)
    model = HRCModel(plain)
    assert plain.queue is None and model.queue is None and model.n_levels == 1
    assert model.n_states == model.n_base == 419_904
    full = load_config(shipped_config_path('stream_queue'))
    m = HRCModel(full)
    assert full.queue == 2 and m.n_states == 3 * 419_904 and m.n_base == 419_904
    assert m.arrivals is None       # the queue-less stream's arrivals do not apply
    assert m.queue.drop_cost == pytest.approx(full.waiting_cost / (1 - full.gamma))
    # the queue is part of the policy hash: another L, another policy
    other = load_config(shipped_config_path('stream_queue'),
                        overrides={'stream': {'queue': 3}})
    assert other.policy_hash != full.policy_hash


@pytest.mark.parametrize('stream, message', [
    ({**QUEUE, 'arrival_complete': 0.5}, 'stream.arrival_complete belongs to the stream '
                                         'without a queue'),
    ({k: v for k, v in QUEUE.items() if k != 'arrival_busy'}, 'missing key stream.arrival_busy'),
    ({k: v for k, v in QUEUE.items() if k != 'waiting_cost'}, 'missing key stream.waiting_cost'),
    ({**QUEUE, 'queue': 0}, r'stream.queue .* integer in 1..4'),
    ({**QUEUE, 'queue': 5}, r'stream.queue .* integer in 1..4'),
    ({**QUEUE, 'queue': True}, r'stream.queue .* integer in 1..4'),
    ({**QUEUE, 'waiting_cost': -1.0}, 'stream.waiting_cost'),
    ({'arrival_idle': 0.2, 'arrival_complete': 0.5, 'arrival_busy': 0.2},
     'stream.arrival_busy needs stream.queue'),
    ({'arrival_idle': 0.2, 'arrival_complete': 0.5, 'waiting_cost': 1.0},
     'stream.waiting_cost needs stream.queue'),
])
def test_a_bad_queue_section_is_refused_naming_the_field(stream, message):
    with pytest.raises(ConfigError, match=message):
        queue_config(stream)


# -- the queue step, rule by rule -------------------------------------------------------------
def scalar_queue_step(model, level, s0, action):
    """The queue's epoch of MODEL.md 8.1 for one state, in plain Python: {(l', y'): P} of the
    task and queue part (before the emotion and distance steps) and P(a task is dropped)."""
    queue = model.queue
    state = model.state(s0)
    em = state[0]
    task = {n: np.array([v]) for n, v in zip(TASK_VARIABLES, state[2:10])}
    p_acc = float(model.acceptance_probability(action, em, task['tp'], task['tx'],
                                               task['ty'])[0])
    p_release = queue.arrivals.p_complete if state[2] > 0 else queue.arrivals.p_idle
    tasks = model.config.stream[2]
    out, dropped = {}, 0.0
    for accepted, p_a in ((True, p_acc), (False, 1 - p_acc)):
        nxt = {n: int(v[0]) for n, v in model.step_task(task, action, accepted).items()}
        for released, p_r in ((1, p_release), (0, 1 - p_release)):
            p = p_a * p_r
            if p == 0:
                continue
            waiting = level + released
            if nxt['tp'] == 0 and waiting > 0:          # the head enters the idle cell
                for (tp, tc, tx), q_k in zip(tasks, queue.arrivals.q):
                    entered = dict(nxt, tp=int(tp), tc=int(tc), tx=int(tx), ty=0)
                    key = (min(waiting - 1, queue.levels), int(model.task_index(entered)))
                    out[key] = out.get(key, 0.0) + p * q_k
            else:
                if waiting > queue.levels:
                    dropped += p
                key = (min(waiting, queue.levels), int(model.task_index(nxt)))
                out[key] = out.get(key, 0.0) + p
    return out, dropped


def test_the_vectorised_queue_step_is_the_scalar_rule(small_queue):
    m = small_queue
    rng = np.random.default_rng(3)
    sources = rng.choice(m.n_states, size=300, replace=False)
    for a in range(len(ACTIONS)):
        branches, dropped, _ = m._queue_steps(sources, a)
        for i, s in enumerate(sources):
            got = {}
            for l_next, y_next, p in branches:
                if p[i] > 0:
                    key = (int(l_next[i]), int(y_next[i]))
                    got[key] = got.get(key, 0.0) + float(p[i])
            want, want_drop = scalar_queue_step(m, *(int(v) for v in m.split(s)), a)
            assert got.keys() == want.keys()
            for key in want:
                assert got[key] == pytest.approx(want[key], abs=1e-12)
            assert dropped[i] == pytest.approx(want_drop, abs=1e-12)


def test_queue_cases_by_hand(small_queue):
    """Three cases of MODEL.md 8.1 written out: a release into a busy cell waits; into a full
    queue it is dropped and charged; an idle cell takes the head of the queue."""
    m = small_queue
    n0, w, drop = m.n_base, m.queue.waiting_cost, m.queue.drop_cost
    p_busy, p_idle = m.queue.arrivals.p_complete, m.queue.arrivals.p_idle
    # robot committed to a 1-epoch robot task it has just started (bc = 1): nw completes it
    busy = m.index((0, 0, 1, 1, 0, 2, 0, 0, 1, 1, 3))
    # an uncommitted task (ct not taken): under dn the cell stays busy
    waiting_task = m.index((0, 0, 1, 1, 0, 0, 0, 0, 0, 0, 3))
    idle = m.index((0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 3))
    # l = 2, busy and staying busy under dn: a release is dropped
    _, dropped = scalar_queue_step(m, 2, waiting_task, DN)
    assert dropped == pytest.approx(p_busy)
    cost = m.flat_cost([2 * n0 + waiting_task], DN)[0]
    assert cost == pytest.approx(m.cost(np.array([m.state(waiting_task)]), DN)[0]
                                 + 2 * w + p_busy * drop)
    # l = 0, the task completes under nw: a release enters right away, else the cell is idle
    steps, dropped = scalar_queue_step(m, 0, busy, NW)
    assert dropped == 0
    assert sum(p for (lv, y), p in steps.items() if lv == 0 and m.task_grid['tp'][y] > 0) \
        == pytest.approx(p_busy)
    # l = 1, idle: the head enters whether or not a task is released, l' = l - 1 + release
    steps, _ = scalar_queue_step(m, 1, idle, DN)
    assert all(m.task_grid['tp'][y] > 0 for (lv, y) in steps)
    assert sum(p for (lv, y), p in steps.items() if lv == 1) == pytest.approx(p_idle)
    assert sum(p for (lv, y), p in steps.items() if lv == 0) == pytest.approx(1 - p_idle)


@pytest.mark.parametrize('overrides', [
    {},
    {'solver': {'fail_safe_aware': False}},
    {'stream': {**QUEUE, 'queue': 1, 'arrival_idle': 0.9, 'arrival_busy': 0.1, 'q': None}},
])
def test_factored_q_and_the_fused_sweep_equal_the_rule_by_rule_queue(overrides):
    """On every state of the reduced model (rho = sigma = 1, L + 1 queue levels)."""
    model = HRCModel(load_config(CONFIG, overrides={**SMALL, 'stream': QUEUE, **overrides}))
    op = FactoredBellman(model)
    value = np.random.default_rng(5).normal(size=model.n_states) * 20
    q = op.q(value)
    checked = []

    def rows_are_distributions(a, t):
        np.testing.assert_allclose(np.bincount(t.source, weights=t.probability), 1.0,
                                   atol=1e-12)
        checked.append(a)
    # every state, in blocks: the rule-by-rule rows are enumerated per source, so the blocks'
    # rows are the whole's; blocks of 16,384 keep its arrays in cache (about 40% less CPU)
    block = 16384
    for start in range(0, model.n_states, block):
        sources = np.arange(start, min(start + block, model.n_states))
        np.testing.assert_allclose(q[:, sources].T,
                                   rule_q(model, value, sources, rows_are_distributions),
                                   atol=1e-10)
    n_blocks = -(-model.n_states // block)
    assert checked == list(range(len(ACTIONS))) * n_blocks
    new, residual = op.apply(value)
    np.testing.assert_allclose(new, q.max(axis=0), atol=1e-10)
    assert residual == pytest.approx(np.max(np.abs(q.max(axis=0) - value)), abs=1e-10)


def test_factored_q_equals_rule_by_rule_on_sampled_full_queue_states():
    model = HRCModel(load_config(shipped_config_path('stream_queue')))
    rng = np.random.default_rng(17)
    value = rng.normal(size=model.n_states) * 20
    sample = np.concatenate([lv * model.n_base + rng.choice(model.n_base, 500, replace=False)
                             for lv in range(model.n_levels)])
    op = FactoredBellman(model)
    q = op.q(value)
    np.testing.assert_allclose(q[:, sample].T, rule_q(model, value, sample), atol=1e-10)
    new, _ = op.apply(value)
    np.testing.assert_allclose(new, q.max(axis=0), atol=1e-10)


def test_without_releases_the_empty_queue_is_the_papers_model():
    """arrival 0: at l = 0 no task ever comes, so V and the policy there are the paper's."""
    zero = HRCModel(queue_config({**QUEUE, 'arrival_idle': 0.0, 'arrival_busy': 0.0}))
    plain = HRCModel(load_config(CONFIG, overrides=SMALL))
    a, b = solve(zero), solve(plain)
    np.testing.assert_allclose(a.value[:zero.n_base], b.value, atol=1e-9)
    np.testing.assert_array_equal(a.policy[:zero.n_base], b.policy)


def test_the_solved_value_is_the_exact_value_of_its_policy(small_queue, small_queue_mdp):
    """Policy evaluation by the sparse rule-by-rule matrix (`HRCModel.transition`,
    `flat_cost` with the drop charge) gives value iteration's value back, within its bound."""
    result = small_queue_mdp
    exact = evaluate_policy(small_queue, result.policy)
    bound = small_queue.config.eta * small_queue.gamma / (1 - small_queue.gamma)
    assert np.max(np.abs(exact - result.value)) < 2 * bound


def test_waiting_costs_and_a_full_queue_costs_more(small_queue, small_queue_mdp):
    v = small_queue_mdp.value.reshape(small_queue.n_levels, -1)
    assert np.all(v[1] < v[0] - 1e-6) and np.all(v[2] < v[1] - 1e-6)


# -- policy files -----------------------------------------------------------------------------
def test_a_queue_policy_round_trips_and_is_refused_by_the_queue_less_model(tmp_path,
                                                                          small_queue,
                                                                          small_queue_mdp):
    cfg = small_queue.config
    result = small_queue_mdp
    path = save_policy(tmp_path / 'queue.npz', result, cfg)
    loaded = load_policy(path, cfg)
    assert loaded.policy.shape == (small_queue.n_states,)
    np.testing.assert_array_equal(loaded.policy, result.policy)
    plain = load_config(CONFIG, overrides=SMALL)
    with pytest.raises(PolicyError, match='policy holds 110592 states, the configuration has '
                                          '36864'):
        load_policy(path, plain)
    other_w = queue_config({**QUEUE, 'waiting_cost': 0.8})     # the same size, another model
    with pytest.raises(PolicyError, match='solved for configuration'):
        load_policy(path, other_w)


@pytest.mark.parametrize('name', ['stream_queue', 'stream_queue_w1'])
def test_the_shipped_queue_policies_load_and_solve_todays_model(name):
    _, shipped = assert_shipped_policy_solves_todays_model(name)
    assert shipped.policy.size == 3 * 419_904


# -- the evaluation reads the queue ------------------------------------------------------------
def test_the_evaluation_reads_the_policy_at_the_observed_queue_length(small_queue):
    """A policy that says dn at l < 2 and dp at l = 2: with the task never done (dn does not
    commit anyone) the waiting tasks are the releases after the first, so the robot's action
    follows min(waiting, 2), and the cost charges every waiting task, uncapped."""
    m = small_queue
    policy = np.full(m.n_states, DN, dtype=np.int8)
    policy[2 * m.n_base:] = DP
    releases = (1, 3, 4, 6, 7, 9)       # a task (1, 1, 3) at each: waiting = released - 1
    scenario = Scenario((0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 3),
                        tuple((k, (1, 1, 3)) for k in releases), 10, name='queue')
    for w in (None, 0.0, 2.5):
        sim = BatchSimulator(m, policy, mode='posterior', waiting_cost=w)
        for selector in ('mdp', 'paper', 'mls'):
            r = sim.run([scenario], [[0, 0]], selector, keep_actions=True, record=True)
            waiting = np.array([sum(1 for j in releases if j <= k) - 1 for k in range(1, 11)])
            d = r.trajectory['d'][0]
            expected = np.where(np.minimum(waiting, 2) == 2, DP, DN)
            np.testing.assert_array_equal(r.actions[0][d > 0], expected[d > 0])
            np.testing.assert_array_equal(r.trajectory['waiting'][0], waiting)
            assert r.waiting_epochs[0] == waiting.sum()
            np.testing.assert_allclose(r.discounted_waiting[0],
                                       (m.gamma ** np.arange(10) * waiting).sum())
        base = BatchSimulator(m, policy, mode='posterior', waiting_cost=0.0).run(
            [scenario], [[0, 0]], 'mdp')
        charged = (m.config.waiting_cost if w is None else w) * base.discounted_waiting
        np.testing.assert_allclose(sim.run([scenario], [[0, 0]], 'mdp').discounted_cost,
                                   base.discounted_cost + charged)


def test_qmdp_reads_q_at_the_queue_level(small_queue, small_queue_mdp):
    m = small_queue
    result = small_queue_mdp
    sim = BatchSimulator(m, result.policy, value=result.value, mode='posterior')
    rng = np.random.default_rng(2)
    column = rng.integers(0, sim.columns, size=40)
    level = rng.integers(0, m.n_levels, size=40)
    h = rng.integers(0, 9, size=40)
    belief = np.eye(9)[h]
    got = sim._qmdp(belief, column, level)
    want = result.policy[level * m.n_base + h * sim.columns + column]
    np.testing.assert_array_equal(got, want)


def test_the_selector_reads_the_policy_and_q_at_the_observed_queue_length(small_queue,
                                                                         small_queue_mdp):
    """ActionSelector (the decision node's) with a queue: the observable's tenth value l picks
    the block l * N0 + h * n_task * 4 + (y, d) for every selector, as the evaluation does
    (mls and qmdp against the flat arrays; the vote against its definition), more than L
    waiting reads as L, a negative or missing l is refused by name; a model without a queue
    does not read a tenth value."""
    m = small_queue
    result = small_queue_mdp
    selector = ActionSelector(m, result.policy, value=result.value)
    q = FactoredBellman(m).q(result.value)
    grid, rng = m.task_grid, np.random.default_rng(4)
    n_columns = m.n_base // 9
    for _ in range(60):
        y, d, level = int(rng.integers(m.n_task)), int(rng.integers(4)), int(rng.integers(3))
        observable = tuple(int(grid[n][y]) for n in TASK_VARIABLES) + (d, level)
        b = rng.dirichlet(np.full(9, 0.5))
        index = level * m.n_base + np.arange(9) * n_columns + y * 4 + d
        np.testing.assert_array_equal(selector.candidate_indices(observable), index)
        assert selector.select(b, observable, 'mls').action == result.policy[index[b.argmax()]]
        np.testing.assert_allclose(selector.select(b, observable, 'qmdp').scores,
                                   b @ q[:, index].T)
        votes = np.bincount(result.policy[index], weights=b, minlength=8)
        np.testing.assert_allclose(selector.select(b, observable, 'paper').scores, votes)
    many = tuple(int(grid[n][5]) for n in TASK_VARIABLES) + (2,)
    np.testing.assert_array_equal(selector.candidate_indices(many + (7,)),  # min(7, L = 2)
                                  selector.candidate_indices(many + (2,)))
    with pytest.raises(ValueError, match=r'l \(tasks waiting.*>= 0, got -1'):
        selector.select(np.full(9, 1 / 9), (0,) * 9 + (-1,))
    with pytest.raises(ValueError, match='the tasks waiting l >= 0 .*got 9 values'):
        selector.select(np.full(9, 1 / 9), (0,) * 9)
    plain = HRCModel(load_config(CONFIG, overrides=SMALL))
    unqueued = ActionSelector(plain, np.zeros(plain.n_states, dtype=np.int8))
    np.testing.assert_array_equal(unqueued.candidate_indices((0,) * 9 + (4,)),
                                  unqueued.candidate_indices((0,) * 9))


def test_charging_a_queue_less_run_changes_its_cost_and_nothing_else():
    """--waiting-cost on a configuration without a queue: the same decisions (l is always 0
    there), the cost plus w times the discounted waiting tasks."""
    config = load_config(CONFIG, overrides=SMALL)
    model = HRCModel(config)
    result = solve(model)
    plain = evaluate(model, result, episodes=60, epochs=30, selectors=('paper', 'mdp'),
                     mode='posterior')
    charged = evaluate(model, result, episodes=60, epochs=30, selectors=('paper', 'mdp'),
                       mode='posterior', waiting_cost=3.0)
    for s in ('paper', 'mdp'):
        np.testing.assert_array_equal(plain[s].tasks_completed, charged[s].tasks_completed)
        np.testing.assert_array_equal(plain[s].waiting_epochs, charged[s].waiting_epochs)
        np.testing.assert_allclose(charged[s].discounted_cost,
                                   plain[s].discounted_cost + 3.0 * plain[s].discounted_waiting)
    assert plain['paper'].waiting_epochs.sum() > 0


# -- the nodes take it ---------------------------------------------------------------------------
def test_the_nodes_take_a_queue_and_the_episodes_do_not_depend_on_it(small_queue):
    from hrc_ros.core.swap import load_node_config
    assert load_node_config(str(shipped_config_path('stream_queue'))).queue == 2
    a, _ = episodes_of(small_queue, 'random', 3, 10)
    b, _ = episodes_of(HRCModel(load_config(CONFIG, overrides=SMALL)), 'random', 3, 10)
    assert a == b


def test_the_nodes_start_with_a_queue_and_refuse_to_add_or_drop_one_live():
    """A queue configuration loads in a node; a live swap that adds a queue, drops it or
    changes L is refused (the task manager publishes the tasks waiting by the rule it started
    with), one that keeps it is not."""
    from hrc_ros.core.swap import check_swap
    from hrc_ros.ros.node_support import load_node_config
    path = str(shipped_config_path('stream_queue'))
    assert load_node_config(path).queue == 2
    verdict = check_swap(2, 2, '', path, running_policy='', policy_value='', queue=None)
    assert verdict.refused and 'has a queue of 2, the running configuration no queue' in \
        verdict.reason
    back = check_swap(2, 2, path, '', running_policy='', policy_value='', queue=2)
    assert back.refused and 'has no queue, the running configuration a queue of 2' in \
        back.reason
    assert not check_swap(2, 2, '', str(shipped_config_path('stream_queue_w1')),
                          running_policy='', policy_value='', queue=2).refused
    assert not check_swap(2, 2, '', str(shipped_config_path('stream')), queue=None).refused


def test_hrc_evaluate_writes_the_waiting_columns_only_where_waiting_is_charged(tmp_path):
    """Without a queue and without --waiting-cost the files have the columns they always had."""
    import csv

    from hrc_ros.tools import evaluate as evaluate_tool
    old = ['selector', 'episode', 'discounted_cost', 'epochs_to_complete', 'collision_epochs',
           'collision_stuck', 'refused_requests', 'tasks_completed', 'longest_collision_run',
           'requests', 'tasks_released']
    runs = {'plain': [], 'charged': ['--waiting-cost', '1.5'],
            'queue': ['--config', str(shipped_config_path('stream_queue'))]}
    headers, metrics = {}, {}
    for name, extra in runs.items():
        out = tmp_path / name
        assert evaluate_tool.main(['--episodes', '4', '--epochs', '12', '--selectors',
                                   'paper,mdp', '--out', str(out)] + extra) == 0
        with open(out / 'episodes.csv') as f:
            headers[name] = next(csv.reader(f))
        with open(out / 'summary.csv') as f:
            metrics[name] = {row['metric'] for row in csv.DictReader(f)}
    assert headers['plain'] == old and 'waiting_epochs' not in metrics['plain']
    for name in ('charged', 'queue'):
        assert headers[name] == old + ['waiting_epochs', 'discounted_waiting']
        assert 'waiting_epochs' in metrics[name]


def test_waiting_is_charged_by_the_world_in_a_mismatch(small_queue):
    """--true-config: the costs are the world's, the waiting charge too. A plan without a queue
    in a world with one is charged the world's w (as the true run planning with that world
    is), a queue plan in a world without one is not charged: the regret compares costs
    measured the same way."""
    plain = HRCModel(load_config(CONFIG, overrides=SMALL))
    plain_policy = np.zeros(plain.n_states, dtype=np.int8)
    queue_policy = np.zeros(small_queue.n_states, dtype=np.int8)
    w = small_queue.config.waiting_cost
    assert BatchSimulator(plain, plain_policy, world=small_queue).waiting_cost == w
    assert BatchSimulator(small_queue, queue_policy, world=small_queue).waiting_cost == w
    assert BatchSimulator(small_queue, queue_policy, world=plain).waiting_cost is None
    assert BatchSimulator(small_queue, queue_policy, world=plain,
                          waiting_cost=1.5).waiting_cost == 1.5


def test_hrc_evaluate_charges_both_runs_of_a_mismatch_the_worlds_waiting(tmp_path):
    """hrc-evaluate --config default --true-config stream_queue: the regret with no flag is
    the one with the world's w given explicitly (both runs charged w = 4), not a comparison of
    an uncharged plan with a charged truth."""
    from hrc_ros.tools import evaluate as evaluate_tool
    regrets = []
    for extra in ([], ['--waiting-cost', str(load_config(
            shipped_config_path('stream_queue')).waiting_cost)]):
        out = tmp_path / f'run{len(regrets)}'
        assert evaluate_tool.main(['--config', str(shipped_config_path('default')),
                                   '--true-config', str(shipped_config_path('stream_queue')),
                                   '--episodes', '30', '--epochs', '10', '--selectors', 'paper',
                                   '--out', str(out), *extra]) == 0
        regrets.append(json.loads((out / 'summary.json').read_text())['regret']['paper'])
    assert regrets[0] == regrets[1]


def test_the_arm_cell_reads_the_queue_as_the_batch_does(small_queue, monkeypatch):
    """The arm's batch cell (issue 34: config/arm.yaml has a queue) reads l = min(tasks
    waiting, L), as the model's batch does: a policy that holds (dn) only at l = 2 and works
    (nw) elsewhere is followed level by level."""
    from hrc_ros.core.robot import cell as arm_cell
    from hrc_ros.core.tasks import TaskBook
    waiting = []

    class Book(TaskBook):
        def begin_epoch(self, k):
            state = super().begin_epoch(k)
            waiting.append(len(self.queue))
            return state

    monkeypatch.setattr(arm_cell, 'TaskBook', Book)
    model = small_queue
    policy = np.full(model.n_states, NW, dtype=np.int8)
    policy[2 * model.n_base:] = DN               # every state with l = 2: hold
    scenarios, seeds = episodes_of(model, 'random', 1, 12, 0, 0.9)
    episode = arm_cell.ArmCell(model, policy).episode(scenarios[0], seeds[0], [0, 0, 2], 'mdp',
                                                      record=True)
    expected = ['dn' if min(n, 2) == 2 or d == 0 else 'nw'
                for n, d in zip(waiting, episode.distances)]
    assert episode.actions == expected
    assert max(waiting) > 2 and min(waiting) < 2


@pytest.fixture(scope='module')
def small_queue_solved(small_queue, small_queue_mdp):
    """The small queue model's MDP solve and a quick POMDP solve (its quality does not matter
    here, only that the batch and `simulate` read it alike: 25 sweeps a phase, not 136, leave
    some 700 vectors whose actions are as varied as the converged set's)."""
    from hrc_ros.core.pomdp.solver import solve_pomdp
    pomdp = solve_pomdp(small_queue, episodes=20, per_state=4, rounds=0, seed=4, tol=5e-2,
                        max_sweeps=25)
    return small_queue_mdp, pomdp.policy()


@pytest.mark.parametrize('mode', ['bayes', 'table', 'posterior'])
@pytest.mark.parametrize('selector', ['paper', 'qmdp', 'mls', 'mdp', 'pomdp', 'fib'])
def test_simulate_follows_the_queue_as_the_batch_does_episode_by_episode(
        small_queue, small_queue_solved, mode, selector):
    """The epoch-by-epoch `simulate` with a queue: the same actions, discounted cost (every
    waiting task charged) and tasks waiting per epoch as `BatchSimulator`, episode by episode,
    on streams busy enough that the queue fills (more than L tasks wait)."""
    from hrc_ros.core.study.evaluation import human_seed, random_scenarios
    from hrc_ros.core.study.simulation import simulate
    m = small_queue
    result, alphas = small_queue_solved
    scenarios = random_scenarios(m, 10, 30, seed=5, task_rate=0.6)
    seeds = [human_seed(5, e) for e in range(10)]
    batch = BatchSimulator(m, result, mode=mode, pomdp=alphas).run(
        scenarios, seeds, selector, keep_actions=True, record=True)
    assert batch.trajectory['waiting'].max() > m.queue_length       # more than L wait
    for e, scenario in enumerate(scenarios):
        t = simulate(m, result, scenario, selector=selector, mode=mode, seed=seeds[e],
                     pomdp=alphas)
        assert [ACTIONS[a] for a in batch.actions[e]] == t.actions
        np.testing.assert_array_equal(t.column('queued'), batch.trajectory['waiting'][e])
        assert batch.discounted_cost[e] == pytest.approx(t.discounted_cost, rel=1e-12)
        assert batch.waiting_epochs[e] == t.column('queued').sum()
        assert batch.tasks_completed[e] == sum(r.complete_epoch is not None for r in t.tasks)


def test_hrc_simulate_runs_a_queue_configuration_and_writes_the_tasks_waiting(tmp_path,
                                                                             capsys):
    """hrc-simulate on the shipped queue configuration with a human (seed 29) slow enough that
    the case study's next task is released while one is still in the cell (tasks wait at
    epochs 9, 16 and 17): its table and CSV carry `queued`, and each epoch's cost is
    J(s, a) + w * queued, the discounted sum the one printed; a configuration without a queue
    writes no such column."""
    import csv as csv_module
    from hrc_ros.tools import simulate as simulate_tool
    path = str(shipped_config_path('stream_queue'))
    assert simulate_tool.main(['--config', path, '--seed', '29', '--out', str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert 'queued' in out.splitlines()[1]
    with open(tmp_path / 'trajectory.csv') as f:
        rows = list(csv_module.DictReader(f))
    assert len(rows) == 20
    queued = np.array([int(r['queued']) for r in rows])
    assert queued.sum() > 0, 'seed 29 no longer has a task waiting: pick a seed that does'
    model = HRCModel(load_config(path))
    columns = ('em', 'ea', 'tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc', 'd')
    for r, waiting in zip(rows, queued):
        state = tuple(int(r[c]) for c in columns)
        a = ACTIONS.index(r['action'])
        want = (model.state_cost_vector[model.index(state)] + model.action_cost[a]
                + model.config.waiting_cost * waiting)
        assert float(r['cost']) == pytest.approx(want, rel=1e-5), r['epoch']
    discounted = float(np.sum(np.array([float(r['cost']) for r in rows])
                              * model.gamma ** np.arange(20)))
    assert f'discounted cost {discounted:.3f}' in out
    # without a queue the trajectory is as it always was: no such column
    assert simulate_tool.main(['--out', str(tmp_path / 'plain')]) == 0
    with open(tmp_path / 'plain' / 'trajectory.csv') as f:
        assert 'queued' not in next(csv_module.reader(f))
