"""Action selection: the paper's vote with its tie rules, qmdp, mls, input validation."""

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTION_INDEX, DN, SAFETY_ORDER, HRCModel
from hrc_ros.core.paths import default_config_path
from hrc_ros.core.decision.selection import SELECTORS, ActionSelector
from hrc_ros.core.mdp.solver import FactoredBellman, solve

X = (1, 1, 3, 0, 0, 0, 0, 0, 1)   # the paper's initial observable state (reduced model)


@pytest.fixture(scope='module')
def model():
    return HRCModel(load_config(default_config_path(),
                                overrides={'model': {'rho': 1, 'sigma': 1}}))


@pytest.fixture(scope='module')
def solved(model):
    return solve(model)


def hand_policy(model, x, actions_by_h, default=DN):
    """A policy that is `default` everywhere except pi((h, x)) = actions_by_h[h]."""
    policy = np.full(model.n_states, default, dtype=np.int8)
    for h, name in actions_by_h.items():
        policy[model.index((h // 3, h % 3) + tuple(x))] = ACTION_INDEX[name]
    return policy


def belief(*weights):
    b = np.zeros(9)
    b[:len(weights)] = weights
    return b


def paper(model, actions_by_h, b, x=X):
    return ActionSelector(model, hand_policy(model, x, actions_by_h)).select(b, x)


def test_candidate_indices_equal_the_model_index(model):
    selector = ActionSelector(model, np.zeros(model.n_states, dtype=np.int8))
    rng = np.random.default_rng(0)
    for i in rng.integers(0, model.n_states, size=300):
        x = model.state(int(i))[2:]
        expected = [model.index((h // 3, h % 3) + x) for h in range(9)]
        np.testing.assert_array_equal(selector.candidate_indices(x), expected)
        np.testing.assert_array_equal(selector.candidate_indices(np.array(x)), expected)


# -- paper vote --------------------------------------------------------------------------
def test_paper_picks_the_largest_vote_sum_not_the_largest_weight(model):
    s = paper(model, {0: 'nw', 1: 'nw', 2: 'nw', 3: 'ct'}, belief(0.2, 0.2, 0.2, 0.4))
    assert s.name == 'nw' and s.method == 'paper'
    np.testing.assert_allclose(s.scores, [0.6, 0, 0, 0.4, 0, 0, 0, 0])


def test_paper_scores_are_the_vote_sums(model):
    b = np.random.default_rng(1).dirichlet(np.ones(9))
    names = ['nw', 'rh1', 'rh2', 'ct', 'dp', 'dm', 'mh', 'dn', 'nw']
    s = paper(model, dict(enumerate(names)), b)
    expected = np.zeros(8)
    for h, name in enumerate(names):
        expected[ACTION_INDEX[name]] += b[h]
    np.testing.assert_allclose(s.scores, expected, rtol=1e-15)
    assert s.action == int(np.argmax(expected))


def test_paper_equal_sums_go_to_the_largest_single_weight(model):
    s = paper(model, {0: 'nw', 1: 'nw', 2: 'ct'}, belief(0.3, 0.2, 0.5))
    assert s.scores[ACTION_INDEX['nw']] == s.scores[ACTION_INDEX['ct']]
    assert s.name == 'ct'
    # Sums equal up to rounding (0.1 + 0.2 = 0.30000000000000004 vs 0.3) are equal.
    s = paper(model, {0: 'nw', 1: 'nw', 2: 'ct', 3: 'dn', 4: 'dp'},
              belief(0.1, 0.2, 0.3, 0.2, 0.2))
    assert s.scores[ACTION_INDEX['nw']] > s.scores[ACTION_INDEX['ct']]
    assert s.name == 'ct'


@pytest.mark.parametrize('first, second, winner', [
    ('mh', 'dp', 'dp'), ('dm', 'rh1', 'rh1'), ('ct', 'nw', 'nw'), ('nw', 'dn', 'dn'),
    ('rh2', 'mh', 'rh2'), ('dm', 'mh', 'mh'),
])
def test_paper_full_ties_go_to_the_safety_order(model, first, second, winner):
    assert paper(model, {0: first, 1: second}, belief(0.5, 0.5)).name == winner
    assert paper(model, {0: second, 1: first}, belief(0.5, 0.5)).name == winner
    # Two h each: equal sums and equal largest weights.
    assert paper(model, {0: first, 1: first, 2: second, 3: second},
                 belief(0.25, 0.25, 0.25, 0.25)).name == winner


def test_paper_three_way_tie(model):
    third = 1 / 3
    s = paper(model, {0: 'mh', 1: 'rh2', 2: 'ct'}, belief(third, third, third))
    assert s.name == 'ct'


def test_zero_weight_votes_do_not_count(model):
    # h = 3..8 all vote dn with weight 0: dn must not win a tie it has no weight in.
    s = paper(model, {0: 'mh', 1: 'rh2'}, belief(0.5, 0.5))
    assert s.name == 'rh2' and s.scores[DN] == 0.0


# -- against the solved policy -------------------------------------------------------------
def test_point_mass_beliefs_give_the_policy_action(model, solved):
    selector = ActionSelector(model, solved)
    rng = np.random.default_rng(2)
    for i in rng.integers(0, model.n_states, size=150):
        state = model.state(int(i))
        b = np.eye(9)[3 * state[0] + state[1]]
        for method in ('paper', 'qmdp', 'mls'):    # pomdp and fib are not the MDP's policy
            assert selector.select(b, state[2:], method).action == solved.policy[i], method


def test_qmdp_scores_equal_the_solver_q(model, solved):
    q_all = FactoredBellman(model).q(solved.value)     # an independent formulation
    selector = ActionSelector(model, solved.policy, solved.value, method='qmdp')
    rng = np.random.default_rng(3)
    for i in rng.integers(0, model.n_states, size=50):
        x = model.state(int(i))[2:]
        b = rng.dirichlet(np.full(9, 0.5))
        b[rng.integers(9)] = 0.0
        b /= b.sum()
        s = selector.select(b, x)
        q = q_all[:, selector.candidate_indices(x)].T            # -inf: not available at d = 0
        with np.errstate(invalid='ignore'):
            expected = np.where(b[:, None] > 0, b[:, None] * q, 0.0).sum(axis=0)
        np.testing.assert_allclose(s.scores, expected, rtol=1e-12)
        best = expected.max()
        tied = [a for a in range(8) if expected[a] >= best - 1e-9 * max(1.0, abs(best))]
        assert s.action == min(tied, key=SAFETY_ORDER.index)


def test_qmdp_differs_from_paper_voting(model, solved):
    # A policy that always stops: the vote must say dn; qmdp ignores the policy.
    stop = np.full(model.n_states, DN, dtype=np.int8)
    selector = ActionSelector(model, stop, solved.value)
    b = belief(0.6, 0.4)
    assert selector.select(b, X).name == 'dn'
    q = selector.select(b, X, 'qmdp')
    assert q.name != 'dn' and q.action == int(np.argmax(q.scores))
    # With the solved policy itself: some mixed beliefs split the two, and then qmdp's choice
    # has the larger expected Q while the vote's has the larger summed weight.
    selector = ActionSelector(model, solved)
    rng = np.random.default_rng(4)
    found = 0
    for _ in range(200):
        x = model.state(int(rng.integers(model.n_states)))[2:]
        b = rng.dirichlet(np.full(9, 0.3))
        vote, qmdp = selector.select(b, x, 'paper'), selector.select(b, x, 'qmdp')
        if vote.action != qmdp.action:
            found += 1
            assert qmdp.scores[qmdp.action] > qmdp.scores[vote.action]
            assert vote.scores[vote.action] >= vote.scores[qmdp.action]
    assert found > 0


def test_qmdp_ties_go_to_the_safety_order(model):
    # A value function and state where several actions have equal Q: all-zero V makes
    # Q = -J(s, a), and J differs between actions only by g(a) (nw, ct, dn have g = 0).
    zero = np.zeros(model.n_states)
    selector = ActionSelector(model, np.zeros(model.n_states, dtype=np.int8), zero, 'qmdp')
    s = selector.select(belief(1.0), (0, 0, 0, 0, 0, 0, 0, 0, 3))
    assert s.name == 'dn'
    assert s.scores[ACTION_INDEX['nw']] == s.scores[DN]


# -- mls -----------------------------------------------------------------------------------
def test_mls_follows_the_most_likely_h(model):
    policy = {0: 'nw', 1: 'ct', 2: 'mh', 3: 'dp', 4: 'rh2'}
    s = ActionSelector(model, hand_policy(model, X, policy), method='mls').select(
        belief(0.1, 0.15, 0.2, 0.25, 0.3), X)
    assert s.name == 'rh2' and s.method == 'mls'
    np.testing.assert_array_equal(s.scores, np.eye(8)[ACTION_INDEX['rh2']])
    # Ties in h go to the lowest h (here h = 1, not h = 3, although dp is safer than ct).
    s = ActionSelector(model, hand_policy(model, X, policy), method='mls').select(
        belief(0.0, 0.4, 0.0, 0.4, 0.2), X)
    assert s.name == 'ct'


# -- bad inputs --------------------------------------------------------------------------
@pytest.mark.parametrize('b, message', [
    (np.full(8, 1 / 8), 'shape'), (np.r_[1.2, -0.2, np.zeros(7)], 'negative'),
    (np.r_[np.nan, np.ones(8) / 8], 'NaN'), (np.full(9, 0.2), 'sums to'),
])
def test_bad_belief_is_rejected(model, solved, b, message):
    selector = ActionSelector(model, solved)
    for method in SELECTORS:
        with pytest.raises(ValueError, match='belief') as err:
            selector.select(b, X, method)
        assert message in str(err.value)


@pytest.mark.parametrize('x, field', [
    ((1, 1, 3, 0, 0, 0, 0, 0), 'observable'), ((1, 1, 3, 0, 0, 0, 0, 0, 1, 0, 0), 'observable'),
    ((1, 1, 3, 0, 0, 0, 0, 0, 4), 'observable d'), ((2, 1, 3, 0, 0, 0, 0, 0, 1), 'observable tp'),
    ((1, 1, 4, 0, 0, 0, 0, 0, 1), 'observable tx'),
    ((1, 1, 3, 0, 0, -1, 0, 0, 1), 'observable hc'),
    ((1, 1, 3, 0, 0, 0, 0, 1.0, 1), 'observable bc'),
    ((1, 1, 3, 'a', 0, 0, 0, 0, 1), 'observable ty'),
    (None, 'observable'), ((1, 1, 3, 0, 0, 0, True, 0, 1), 'observable bp'),
])
def test_bad_observable_is_rejected(model, solved, x, field):
    with pytest.raises(ValueError, match=field):
        ActionSelector(model, solved).select(np.full(9, 1 / 9), x)


def test_bad_construction_is_rejected(model, solved):
    with pytest.raises(ValueError, match='method'):
        ActionSelector(model, solved, method='vote')
    with pytest.raises(ValueError, match='value'):
        ActionSelector(model, solved.policy, method='qmdp')
    with pytest.raises(ValueError, match='value'):
        ActionSelector(model, solved.policy).select(np.full(9, 1 / 9), X, 'qmdp')
    with pytest.raises(ValueError, match='policy'):
        ActionSelector(model, solved.policy[:-1])
    with pytest.raises(ValueError, match='policy'):
        ActionSelector(model, np.full(model.n_states, 8))
    with pytest.raises(ValueError, match='policy'):
        ActionSelector(model, np.zeros(model.n_states))
    with pytest.raises(ValueError, match='value'):
        ActionSelector(model, solved.policy, np.full(model.n_states, np.nan))


def test_a_full_tie_goes_through_the_whole_safety_order(model):
    """Equal votes and equal single weights: the earliest of the model's safety order wins,
    pair by pair along the order (dn, dp, nw, ct, rh1, rh2, mh, dm)."""
    names = {a: name for name, a in ACTION_INDEX.items()}
    for first, later in zip(SAFETY_ORDER, SAFETY_ORDER[1:]):
        for order in ((first, later), (later, first)):
            s = paper(model, {0: names[order[0]], 1: names[order[1]]}, belief(0.5, 0.5))
            assert s.action == first, (names[first], names[later])
