"""The factored Bellman operator and the solvers against independent formulations."""

import numpy as np
import pytest
from reference import rule_q
from scipy import sparse

from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTIONS, DN, NW, HRCModel
from hrc_ros.core.paths import default_config_path, shipped_config_path
from hrc_ros.core.mdp.solver import (FactoredBellman, greedy_policy, policy_iteration, solve,
                                     value_iteration)

CONFIG = default_config_path()
REDUCED = {'model': {'rho': 1, 'sigma': 1}}


@pytest.fixture(scope='module')
def reduced():
    return HRCModel(load_config(CONFIG, overrides=REDUCED))


@pytest.fixture(scope='module')
def full():
    return HRCModel(load_config(CONFIG))


def explicit_q(model, value, matrices):
    states = np.stack(np.unravel_index(np.arange(model.n_states), model.dims), axis=-1)
    q = np.stack([-model.cost(states, a) + model.gamma * (matrices[a] @ value)
                  for a in range(len(ACTIONS))])
    q[~model.availability[:, states[:, 10]]] = -np.inf     # only dn at d = 0 (MODEL.md 5)
    return q


def test_factored_q_equals_rule_by_rule_q_on_the_reduced_arm_model():
    """The arm's model as shipped (its pauses, reach, approach, queue), reduced: the factored
    Q against the rule-by-rule one on every state with a committed task and a sample."""
    model = HRCModel(load_config(shipped_config_path('arm'), overrides=REDUCED))
    rng = np.random.default_rng(7)
    value = rng.normal(size=model.n_states) * 20
    sample = rng.choice(model.n_states, size=3000, replace=False)
    np.testing.assert_allclose(FactoredBellman(model).q(value)[:, sample].T,
                               rule_q(model, value, sample), atol=1e-10)


RATE = {0: [0.0, 0.1, 0.5, 0.9], 2: [0.2, 0.3, 0.6, 1.0], 3: [0.0, 0.05, 0.4, 0.7]}


def test_the_robot_rate_makes_the_working_robots_counter_a_draw():
    """model.robot_rate (MODEL.md 3.2): where the robot works (committed, bc > 0, an action
    that does not pause it) its counter runs down with rate[tx, d] and stays otherwise; under
    a pausing action, and without a rate, the step is the paper's one deterministic branch."""
    rated = HRCModel(load_config(CONFIG, overrides={**REDUCED, 'model': {
        **REDUCED['model'], 'robot_rate': RATE, 'robot_paused_by': ['dn', 'dp', 'dm']}}))
    plain = HRCModel(load_config(CONFIG, overrides=REDUCED))
    state = (0, 0, 1, 1, 2, 2, 0, 0, 1, 1, 2)     # tx 2, robot committed, bc 1, d 2
    source = rated.index(state)
    for action, expected in (('nw', RATE[2][2]), ('mh', RATE[2][2]), ('dn', None),
                             ('dm', None)):
        t = rated.transition([source], ACTIONS.index(action))
        y = (t.target // 4) % rated.n_task
        done = rated.task_grid['tp'][y] == 0           # the last cycle ran: complete
        if expected is None:                           # paused: the counter stays
            assert not done.any()
        else:
            assert t.probability[done].sum() == pytest.approx(expected)
    assert rated.run_probability(NW, 2, 2) == RATE[2][2]
    assert rated.run_probability(DN, 2, 2) is None and plain.run_probability(NW, 2, 2) is None
    assert len(plain.task_steps({n: np.array([v]) for n, v in zip(
        ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc'), state[2:10])}, NW, False, 2)) == 1


@pytest.mark.parametrize('config', ['default', 'arm', 'stream'])
def test_factored_q_and_the_sweep_with_a_robot_rate_equal_the_rule_by_rule_model(config):
    """The rate in both forms of the operator: the factored Q against the rule-by-rule one
    (with the arm's pauses and queue, the paper's pauses, the queue-less stream) and the fused
    sweep against the max of the Q."""
    model = HRCModel(load_config(shipped_config_path(config), overrides={
        **REDUCED, 'model': {**REDUCED['model'], 'robot_rate': RATE}}))
    rng = np.random.default_rng(9)
    value = rng.normal(size=model.n_states) * 20
    op = FactoredBellman(model)
    q = op.q(value)
    sample = rng.choice(model.n_states, size=2000, replace=False)
    np.testing.assert_allclose(q[:, sample].T, rule_q(model, value, sample), atol=1e-10)
    np.testing.assert_allclose(op.apply(value)[0], q.max(axis=0), atol=1e-10)


@pytest.mark.parametrize('config', ['default'])
def test_factored_q_equals_explicit_sparse_on_reduced_model(config):
    reduced = HRCModel(load_config(shipped_config_path(config), overrides=REDUCED))
    matrices = reduced.sparse_matrices()
    for m in matrices:
        assert isinstance(m, sparse.csr_matrix)
        np.testing.assert_allclose(np.asarray(m.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    rng = np.random.default_rng(7)
    op = FactoredBellman(reduced)
    for value in (rng.normal(size=reduced.n_states) * 20, np.zeros(reduced.n_states)):
        np.testing.assert_allclose(op.q(value), explicit_q(reduced, value, matrices),
                                   atol=1e-10)


def test_factored_q_equals_rule_by_rule_q_on_sampled_full_states(full):
    rng = np.random.default_rng(11)
    value = rng.normal(size=full.n_states) * 20
    q = FactoredBellman(full).q(value)
    sample = rng.choice(full.n_states, size=3000, replace=False)
    np.testing.assert_allclose(q[:, sample].T, rule_q(full, value, sample), atol=1e-10)


@pytest.mark.parametrize('paused', [['dn'], ['dn', 'dp'], ['dn', 'dm'], ['dn', 'dp', 'dm']])
def test_the_robot_counter_pauses_under_the_actions_the_configuration_names(paused):
    """model.robot_paused_by (MODEL.md 3.2): a committed robot's counter bc stays under the
    named actions, as under dn, and runs down under the others; the factored operator's task
    maps follow the same rule, and the fused sweep equals the max of its Q."""
    model = HRCModel(load_config(CONFIG, overrides={**REDUCED,
                                                    'model': {**REDUCED['model'],
                                                              'robot_paused_by': paused}}))
    busy = {'tp': 1, 'tc': 1, 'tx': 0, 'ty': 2, 'hp': 0, 'hc': 0, 'bp': 1, 'bc': 1}
    task = {n: np.array([v]) for n, v in busy.items()}
    for a in ('nw', 'dp', 'dm', 'mh', 'dn'):
        after = model.step_task(task, ACTIONS.index(a), False)
        assert int(after['bc'][0]) == (1 if a in paused else 0), a
        assert int(after['tp'][0]) == (1 if a in paused else 0), a   # else the task completes
    op = FactoredBellman(model)
    y = int(model.task_index(task)[0])
    assert op.t_dp[y] == (op.t_pause[y] if 'dp' in paused else op.t_default[y])
    assert op.t_dm[y] == (op.t_pause[y] if 'dm' in paused else op.t_default[y])
    assert op.t_pause[y] != op.t_default[y]
    value = np.random.default_rng(5).normal(size=model.n_states) * 20
    np.testing.assert_allclose(op.apply(value)[0], op.q(value).max(axis=0), atol=1e-10)


@pytest.mark.parametrize('reach', [None, 2, 1])
def test_a_retreat_gains_a_band_only_below_the_configured_reach(reach):
    """model.retreat_reach (MODEL.md 3.3): dp raises d by one from d < reach (every d without
    one), the human's Delta as ever; the distance matrices the solvers use follow it."""
    model = HRCModel(load_config(CONFIG, overrides={**REDUCED, 'model': {
        **REDUCED['model'], 'retreat_reach': reach}}))
    for d in range(4):
        for delta in (-1, 0, 1):
            gain = 1 if reach is None or d < reach else 0
            assert int(model.next_distance(d, ACTIONS.index('dp'), delta)) == \
                min(3, d + gain - delta)
            assert int(model.next_distance(d, NW, delta)) == min(3, max(0, d - delta))
    p_delta = model.config.p_delta
    matrix = model.distance_matrix(ACTIONS.index('dp'))
    # ea = 0 at d = 2: without a reach dp lands on 3 unless the human steps closer (Delta = +1)
    expected = {None: [0, 0, p_delta[0, 2], p_delta[0, 0] + p_delta[0, 1]],
                2: [0, p_delta[0, 2], p_delta[0, 1], p_delta[0, 0]],
                1: [0, p_delta[0, 2], p_delta[0, 1], p_delta[0, 0]]}[reach]
    np.testing.assert_allclose(matrix[0, 2], expected)
    assert matrix[0, 1, 2] == pytest.approx(p_delta[0, 1] if reach != 1 else p_delta[0, 0])


@pytest.mark.parametrize('aware', [False, True], ids=['model', 'fail_safe_aware'])
@pytest.mark.parametrize('overrides', [REDUCED, {}], ids=['reduced', 'full'])
def test_fast_sweeps_equal_the_max_of_q(overrides, aware):
    overrides = {**overrides, 'solver': {'fail_safe_aware': aware}}
    model = HRCModel(load_config(CONFIG, overrides=overrides))
    op = FactoredBellman(model)
    value = np.random.default_rng(3).normal(size=model.n_states) * 20
    q_max = op.q(value).max(axis=0)
    new, residual = op.apply(value)
    np.testing.assert_allclose(new, q_max, atol=1e-10)
    assert residual == pytest.approx(np.max(np.abs(q_max - value)), abs=1e-10)


def test_value_and_policy_iteration_agree(reduced):
    vi = solve(reduced)
    pi = solve(reduced, method='policy_iteration')
    assert (vi.method, pi.method) == ('value_iteration', 'policy_iteration')
    assert vi.converged and vi.residual < reduced.config.eta
    # the fields mean the same for both: PI's value is exact, its Bellman residual tiny
    assert pi.converged and pi.residual < 1e-8 and 1 <= pi.iterations < vi.iterations
    op = FactoredBellman(reduced)
    for result in (vi, pi):
        assert result.residual == pytest.approx(op.residual(result.value), abs=1e-12)
    # |V_VI - V*| <= gamma * eta / (1 - gamma)
    assert np.max(np.abs(vi.value - pi.value)) < 2 * 0.95 * 1e-6 / 0.05
    q = FactoredBellman(reduced).q(pi.value)
    differ = np.flatnonzero(vi.policy != pi.policy)
    gaps = np.abs(q[vi.policy[differ], differ] - q[pi.policy[differ], differ])
    assert np.all(gaps < 1e-6), 'policies differ beyond ties'


def test_value_iteration_is_a_fixed_point_and_counts_sweeps(reduced):
    res = value_iteration(reduced)
    assert res.iterations == 280  # MODEL.md 5: about 280 sweeps with the defaults
    op = FactoredBellman(reduced)
    assert np.max(np.abs(op.q(res.value).max(axis=0) - res.value)) < reduced.config.eta
    fixed = solve(reduced, sweeps=20)  # the paper's k = 20
    assert fixed.iterations == 20 and not fixed.converged


def test_value_iteration_from_a_nearby_models_values_reaches_the_same_fixed_point(reduced):
    """`start` (the plant's refits start from the fit's values): a nearby model's values give
    the same fixed point within VI's error bound, in fewer sweeps; a start of the wrong
    size is refused."""
    near = HRCModel(load_config(CONFIG, overrides={**REDUCED, 'model': {
        **REDUCED['model'], 'p_accept': [0.25, 0.75, 0.97]}}))
    cold = value_iteration(reduced)
    warm = value_iteration(reduced, start=value_iteration(near).value)
    assert warm.converged and warm.iterations < cold.iterations
    assert np.max(np.abs(warm.value - cold.value)) < 2 * 0.95 * reduced.config.eta / 0.05
    q = FactoredBellman(reduced).q(cold.value)
    differ = np.flatnonzero(warm.policy != cold.policy)
    assert np.all(np.abs(q[warm.policy[differ], differ] - q[cold.policy[differ], differ])
                  < 1e-6), 'policies differ beyond ties'
    with pytest.raises(ValueError, match='start has shape'):
        value_iteration(reduced, start=np.zeros(3))


def test_solve_dispatches_and_refuses_bad_arguments(reduced):
    with pytest.raises(ValueError, match='unknown method'):
        solve(reduced, method='simplex')
    with pytest.raises(ValueError, match='sweeps'):
        value_iteration(reduced, sweeps=0)
    with pytest.raises(ValueError, match='max_iterations'):
        policy_iteration(reduced, max_iterations=0)
    capped = policy_iteration(reduced, max_iterations=1)
    assert capped.iterations == 1 and not capped.converged


def test_safety_tie_order():
    q = np.zeros((8, 3))
    q[:, 1] = -5.0
    q[NW, 1] = -1.0           # strict best: nw
    q[:, 2] = -2.0
    q[DN, 2] = -2.0 - 1e-12   # within the tie tolerance: dn still wins the tie
    assert list(greedy_policy(q)) == [DN, NW, DN]


def test_shipped_policy_behaviour_matches_the_paper(full):
    """MODEL.md 7, policy-level facts of the shipped default policy."""
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    policy = load_policy(default_policy_path(full.config), full.config).policy

    def act(state):
        return ACTIONS[policy[full.index(state)]]

    assert act((0, 0, 1, 1, 3, 0, 0, 0, 0, 0, 2)) == 'mh'   # joint task, unmotivated
    assert act((1, 0, 1, 1, 3, 0, 0, 0, 0, 0, 2)) == 'rh2'  # motivated: ask for joint work
    assert act((1, 0, 1, 1, 3, 0, 0, 0, 0, 0, 1)) == 'dp'   # not in the inner circle (issue 14)
    assert act((0, 0, 2, 2, 1, 0, 0, 0, 0, 0, 3)) == 'mh'   # human-only task, unmotivated
    assert act((1, 1, 2, 2, 1, 0, 0, 0, 0, 0, 3)) == 'rh1'  # then ask the human
    assert act((0, 0, 2, 2, 2, 0, 0, 0, 0, 0, 3)) == 'ct'   # either task: the robot commits
    assert act((1, 1, 2, 2, 2, 2, 0, 0, 2, 2, 3)) == 'nw'   # and works
    assert act((1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1)) == 'dp'   # idle and close: move away
    assert act((1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 3)) == 'dn'   # idle and far: stop
    for em in range(3):  # a human-only task is never committed by the robot
        assert act((em, 1, 2, 2, 1, 0, 0, 0, 0, 0, 3)) != 'ct'


def test_fail_safe_aware_plans_dn_at_collision():
    """The default plans with the fail-safe (MODEL.md 5, revised); the switch turns it off."""
    aware = HRCModel(load_config(CONFIG, overrides=REDUCED))
    assert aware.config.fail_safe_aware
    reduced = HRCModel(load_config(CONFIG, overrides={**REDUCED,
                                                      'solver': {'fail_safe_aware': False}}))
    collision = aware.state(np.arange(aware.n_states))[:, 10] == 0
    vi = solve(aware)
    assert np.all(vi.policy[collision] == DN)
    plain = solve(reduced)
    assert not np.all(plain.policy[collision] == DN)   # planning through collision: dm there
    # restricting the actions can only cost: V_aware <= V_plain everywhere
    assert np.all(vi.value <= plain.value + 1e-9)
    pi = solve(aware, method='policy_iteration')
    assert np.max(np.abs(vi.value - pi.value)) < 2 * 0.95 * 1e-6 / 0.05
    assert np.all(pi.policy[collision] == DN)
    # outside collision the operator is the model's: Q of the allowed actions is unchanged
    value = np.random.default_rng(5).normal(size=aware.n_states)
    q_aware = FactoredBellman(aware).q(value)
    q_plain = FactoredBellman(reduced).q(value)
    np.testing.assert_array_equal(q_aware[:, ~collision], q_plain[:, ~collision])
    np.testing.assert_array_equal(q_aware[DN, collision], q_plain[DN, collision])
    assert np.all(np.isneginf(np.delete(q_aware[:, collision], DN, axis=0)))
