"""The model of MODEL.md against hand-worked next-state distributions and costs.

Expected distributions are written from MODEL.md's tables by hand (the factor tables below),
not from the model code: each case lists the task/activity outcome(s) of acceptance, the
distance outcomes of Delta, and the emotion chains, and the test multiplies them out.
"""

import itertools
import math

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTIONS, HRCModel
from hrc_ros.core.paths import default_config_path, shipped_config_path

CONFIG = default_config_path()
S0 = (0, 0, 1, 1, 3, 0, 0, 0, 0, 0, 1)  # the paper's initial state

# MODEL.md 3.3 / 3.4 defaults
P_DELTA = {0: {-1: 0.15, 0: 0.75, 1: 0.10}, 1: {-1: 0.10, 0: 0.70, 1: 0.20},
           2: {-1: 0.05, 0: 0.55, 1: 0.40}}
CHAINS = {'base': ((0.05, 0.90, 0.05), (0.05, 0.90, 0.05)),
          'motivate': ((0.00, 0.40, 0.60), (0.20, 0.75, 0.05)),
          'request': ((0.10, 0.85, 0.05), (0.05, 0.80, 0.15))}


@pytest.fixture(scope='module')
def model():
    return HRCModel(load_config(CONFIG))


def chain_step(level, down_stay_up):
    """P(level') from a bounded chain, written out by hand."""
    down, stay, up = down_stay_up
    out = {level: stay}
    out[max(level - 1, 0)] = out.get(max(level - 1, 0), 0) + down
    out[min(level + 1, 2)] = out.get(min(level + 1, 2), 0) + up
    return {k: v for k, v in out.items() if v > 0}


def expected(state, group, task_outcomes, distance_outcomes):
    """Multiply out: task_outcomes {task8: p}, distance_outcomes {d': p} (already for ea)."""
    em, ea = state[0], state[1]
    em_chain, ea_chain = CHAINS[group]
    out = {}
    for (task, p_t), (d, p_d), (em2, p_m), (ea2, p_a) in itertools.product(
            task_outcomes.items(), distance_outcomes.items(),
            chain_step(em, em_chain).items(), chain_step(ea, ea_chain).items()):
        key = (em2, ea2) + tuple(task) + (d,)
        out[key] = out.get(key, 0.0) + p_t * p_d * p_m * p_a
    return out


def actual(model, state, action):
    t = model.transition(np.array([model.index(state)]), ACTIONS.index(action))
    out = {}
    for target, p in zip(t.target, t.probability):
        key = model.state(int(target))
        out[key] = out.get(key, 0.0) + float(p)
    return {k: v for k, v in out.items() if v > 0}


def assert_same_distribution(got, want):
    assert set(got) == set(want), (sorted(set(got) ^ set(want))[:5])
    for key in want:
        assert got[key] == pytest.approx(want[key], abs=1e-12), key
    assert sum(got.values()) == pytest.approx(1.0, abs=1e-12)


def other_distance(d, ea):
    """d' = min(3, max(0, d - Delta))."""
    out = {}
    for delta, p in P_DELTA[ea].items():
        d2 = min(3, max(0, d - delta))
        out[d2] = out.get(d2, 0) + p
    return out


def test_flat_index_of_initial_state(model):
    dims = [3, 3, 3, 3, 4, 4, 3, 3, 3, 3, 4]
    assert model.n_states == 419_904
    assert model.index(S0) == np.ravel_multi_index(S0, dims)
    assert model.state(model.index(S0)) == S0


def test_rh2_eligible_at_initial_state(model):
    # tp=1, ty=0, tx=3: eligible; em=0 -> accepted with 0.3: joint venture with tc=1.
    tasks = {(1, 1, 3, 3, 1, 1, 1, 1): 0.3,    # accepted: ty'=3, both take (tp, tc)
             (1, 1, 3, 0, 0, 0, 0, 0): 0.7}    # refused: the task waits, counters stay 0
    want = expected(S0, 'request', tasks, {2: 0.15, 1: 0.75, 0: 0.10})
    assert_same_distribution(actual(model, S0, 'rh2'), want)


def test_rh1_ineligible_for_a_joint_task(model):
    # tx=3: rh1 is never accepted, but the request chain still moves the emotions.
    want = expected(S0, 'request', {(1, 1, 3, 0, 0, 0, 0, 0): 1.0}, other_distance(1, 0))
    assert_same_distribution(actual(model, S0, 'rh1'), want)


def test_ct_ineffective_on_a_joint_task_equals_nw(model):
    want = expected(S0, 'base', {(1, 1, 3, 0, 0, 0, 0, 0): 1.0}, other_distance(1, 0))
    assert_same_distribution(actual(model, S0, 'ct'), want)
    assert_same_distribution(actual(model, S0, 'nw'), want)


def test_ct_effective_on_either_task(model):
    s = (1, 1, 2, 2, 2, 0, 0, 0, 0, 0, 3)
    # ty'=2, bp'=tp=2, bc'=tc=2, tc'=bc'=2; d=3, ea=1: Delta -1/0 -> 3, +1 -> 2
    want = expected(s, 'base', {(2, 2, 2, 2, 0, 0, 2, 2): 1.0}, {3: 0.80, 2: 0.20})
    assert_same_distribution(actual(model, s, 'ct'), want)


def test_rh1_accepted_by_a_motivated_human(model):
    s = (2, 0, 2, 2, 1, 0, 0, 0, 0, 0, 3)
    tasks = {(2, 2, 1, 1, 2, 2, 0, 0): 0.95, (2, 2, 1, 0, 0, 0, 0, 0): 0.05}
    want = expected(s, 'request', tasks, other_distance(3, 0))
    assert_same_distribution(actual(model, s, 'rh1'), want)


def test_dn_pauses_the_robot(model):
    s = (1, 1, 2, 2, 2, 2, 0, 0, 2, 2, 3)
    want_dn = expected(s, 'base', {(2, 2, 2, 2, 0, 0, 2, 2): 1.0}, other_distance(3, 1))
    assert_same_distribution(actual(model, s, 'dn'), want_dn)
    want_nw = expected(s, 'base', {(2, 1, 2, 2, 0, 0, 2, 1): 1.0}, other_distance(3, 1))
    assert_same_distribution(actual(model, s, 'nw'), want_nw)


def test_task_completion_resets_the_task_and_lets_priority_linger(model):
    s = (1, 1, 2, 1, 2, 2, 0, 0, 2, 1, 3)
    # bc 1 -> 0 completes the robot's task; bp stays 2 this epoch (bc was != 0).
    want = expected(s, 'base', {(0, 0, 0, 0, 0, 0, 2, 0): 1.0}, other_distance(3, 1))
    assert_same_distribution(actual(model, s, 'nw'), want)


def test_joint_task_completes_when_both_counters_reach_zero(model):
    s = (1, 1, 1, 1, 3, 3, 1, 1, 1, 1, 1)
    want = expected(s, 'base', {(0, 0, 0, 0, 1, 0, 1, 0): 1.0}, other_distance(1, 1))
    assert_same_distribution(actual(model, s, 'nw'), want)


def test_joint_task_runs_on_the_longer_counter(model):
    s = (1, 1, 2, 2, 3, 3, 2, 2, 2, 1, 2)
    # hc 2 -> 1, bc 1 -> 0: not complete (human still busy), tc' = max(1, 0) = 1
    want = expected(s, 'base', {(2, 1, 3, 3, 2, 1, 2, 0): 1.0}, other_distance(2, 1))
    assert_same_distribution(actual(model, s, 'nw'), want)


def test_mh_chain_and_distance_moves(model):
    s = (2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    want = expected(s, 'motivate', {(0,) * 8: 1.0}, other_distance(0, 0))
    assert_same_distribution(actual(model, s, 'mh'), want)
    # dm at d=0: max(1, 0 - 1 - Delta) = 1 always; dp at d=3 stays 3
    assert_same_distribution(actual(model, s, 'dm'),
                             expected(s, 'base', {(0,) * 8: 1.0}, {1: 1.0}))
    s3 = s[:10] + (3,)
    assert_same_distribution(actual(model, s3, 'dp'),
                             expected(s3, 'base', {(0,) * 8: 1.0}, {3: 1.0}))
    # dp at d=1, ea=2: min(3, 1 + 1 - Delta): -1 -> 3, 0 -> 2, +1 -> 1
    s1 = (0, 2, 0, 0, 0, 0, 0, 0, 0, 0, 1)
    assert_same_distribution(actual(model, s1, 'dp'),
                             expected(s1, 'base', {(0,) * 8: 1.0}, {3: 0.05, 2: 0.55, 1: 0.40}))
    # dm at d=3, ea=2: max(1, 3 - 1 - Delta): -1 -> 3, 0 -> 2, +1 -> 1
    s2 = (0, 2, 0, 0, 0, 0, 0, 0, 0, 0, 3)
    assert_same_distribution(actual(model, s2, 'dm'),
                             expected(s2, 'base', {(0,) * 8: 1.0}, {3: 0.05, 2: 0.55, 1: 0.40}))


def test_costs_of_named_states(model):
    states = np.array([S0, (1, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0), (1, 1, 1, 1, 3, 3, 1, 1, 1, 1, 2),
                       (0, 1, 2, 2, 2, 0, 0, 0, 1, 1, 2)])
    f_s0 = 5 + 2 + math.exp(-3) + math.exp(-1)
    f_collision = 10 + 3 + 1 + 1 + 2          # alpha10 = 10; f2 = 3 + e^0 + e^0 + 2 e^0
    f_joint = 2 + 1 + 1 + 1                   # a1*d*hc*bc + a8*bc + a9*hc + b1*(3-d)
    # either-task pending, robot busy on priority 1: a2 + a4 + a5*2 + a7 + a8*1 ; f2 at d=2, ea=1
    f_either = 1 + 1 + 2 + 1 + 1 + 1 + math.exp(-4) + math.exp(-2) + math.exp(-2)
    want = np.array([f_s0, f_collision, f_joint, f_either])
    np.testing.assert_allclose(model.state_cost(states), want, rtol=1e-12)
    np.testing.assert_allclose(model.cost(states, ACTIONS.index('mh')), want + 1, rtol=1e-12)
    np.testing.assert_allclose(model.cost(states, ACTIONS.index('dm')), want + 1, rtol=1e-12)
    np.testing.assert_allclose(model.cost(states, ACTIONS.index('rh2')), want + 1, rtol=1e-12)
    np.testing.assert_allclose(model.cost(states, ACTIONS.index('dn')), want, rtol=1e-12)
    paper = HRCModel(load_config(shipped_config_path('paper')))
    assert paper.state_cost(states[1:2])[0] == pytest.approx(f_collision - 9)
    # the by-parts vector agrees with the direct formula
    idx = [model.index(tuple(s)) for s in states]
    np.testing.assert_allclose(model.state_cost_vector[idx], want, rtol=1e-12)


def test_every_distribution_sums_to_one_over_the_whole_space(model):
    chunk = 1 << 17
    for a in range(len(ACTIONS)):
        for start in range(0, model.n_states, chunk):
            sources = np.arange(start, min(start + chunk, model.n_states))
            t = model.transition(sources, a)
            assert np.all(t.probability > 0)
            assert np.all((t.target >= 0) & (t.target < model.n_states))
            total = np.bincount(t.source, weights=t.probability, minlength=sources.size)
            np.testing.assert_allclose(total, 1.0, atol=1e-12, err_msg=ACTIONS[a])


def test_bad_states_and_actions_raise(model):
    with pytest.raises(ValueError, match='tp'):
        model.index((0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 0))
    with pytest.raises(ValueError, match='11 variables'):
        model.index((0, 0, 1))
    with pytest.raises(ValueError, match='unknown action'):
        model.transition([0], 'fly')
    with pytest.raises(ValueError, match='out of range'):
        model.transition([0], 8)
