"""SimulatedHuman: reproducible draws whose frequencies match MODEL.md's probabilities."""

import numpy as np
import pytest
from scipy import stats

from hrc_ros.core.pomdp.belief import BeliefFilter
from hrc_ros.core.cell.human import SimulatedHuman, sample_index
from hrc_ros.core.config import load_config
from hrc_ros.core.cell.faults import parse_faults
from hrc_ros.core.model import ACTION_INDEX, DELTAS, HRCModel, next_distance
from hrc_ros.core.paths import default_config_path

DRAWS = 6000
# Frequencies are checked by a chi-square test at this level (a fixed seed makes the outcome
# deterministic; the level only says how far off a correct sampler could plausibly be).
P_VALUE = 1e-3


@pytest.fixture(scope='module')
def model():
    return HRCModel(load_config(default_config_path()))


OPEN_REQUEST = {'tp': 1, 'tx': 1, 'ty': 0}   # rh1 eligible
OPEN_JOINT = {'tp': 1, 'tx': 3, 'ty': 0}     # rh2 eligible
NO_TASK = {'tp': 0, 'tx': 0, 'ty': 0}


def reactions(model, action, task_state, em, ea, d, n=DRAWS, seed=7):
    """n reactions from the same start (em, ea, d), one stream."""
    human = SimulatedHuman(model, seed=seed, em=em, ea=ea, d=d)
    out = []
    for _ in range(n):
        human.em, human.ea, human.d = em, ea, d
        out.append(human.react(action, task_state))
    return out


def assert_frequencies(observed, expected_p):
    """Chi-square on the categories of positive probability; none in the others."""
    observed = np.asarray(observed, dtype=float)
    expected_p = np.asarray(expected_p, dtype=float)
    zero = expected_p <= 0
    assert observed[zero].sum() == 0, (observed, expected_p)
    keep = ~zero
    if keep.sum() < 2:
        return
    expected = expected_p[keep] / expected_p[keep].sum() * observed[keep].sum()
    assert stats.chisquare(observed[keep], expected).pvalue > P_VALUE, (observed, expected)


def test_same_seed_same_sequence(model):
    def run(seed):
        human = SimulatedHuman(model, seed=seed, em=0, ea=1, d=2)
        first = human.observation
        seq = [human.react(a, OPEN_JOINT) for a in ('mh', 'rh2', 'nw', 'dp', 'dm', 'dn') * 5]
        return first, seq

    assert run(3) == run(3)
    assert run(3) != run(4)


def test_acceptance_frequency_matches_p_accept(model):
    for em, p in enumerate(model.config.p_accept):
        answers = [r.accepted for r in reactions(model, 'rh2', OPEN_JOINT, em, 0, 3, n=4000)]
        accepted = sum(answers)
        assert stats.binomtest(accepted, len(answers), p).pvalue > P_VALUE, (em, accepted)


def test_ineligible_requests_and_other_actions_get_no_answer(model):
    human = SimulatedHuman(model, seed=0)
    assert human.react('rh2', OPEN_REQUEST).accepted is None     # rh2 needs tx = 3
    assert human.react('rh1', OPEN_JOINT).accepted is None       # rh1 needs tx in {1, 2}
    assert human.react('rh1', NO_TASK).accepted is None
    assert human.react('rh1', {'tp': 1, 'tx': 1, 'ty': 1}).accepted is None  # committed
    for action in ('nw', 'ct', 'dp', 'dm', 'mh', 'dn'):
        assert human.react(action, OPEN_JOINT).accepted is None
    assert human.react('rh1', OPEN_REQUEST).accepted in (True, False)


@pytest.mark.parametrize('action', ['nw', 'dp', 'dm'])
@pytest.mark.parametrize('ea', [0, 2])
def test_delta_and_distance_follow_p_delta(model, action, ea):
    d = 2
    rs = reactions(model, action, NO_TASK, 1, ea, d)
    counts = [sum(r.delta == delta for r in rs) for delta in DELTAS]
    assert_frequencies(counts, model.config.p_delta[ea])
    a = ACTION_INDEX[action]
    assert all(r.d == next_distance(d, a, r.delta) for r in rs)
    expected_d = model.distance_matrix(a)[ea, d]
    assert_frequencies(np.bincount([r.d for r in rs], minlength=4), expected_d)


@pytest.mark.parametrize('action', ['nw', 'mh', 'rh1'])
@pytest.mark.parametrize('em, ea', [(0, 0), (1, 1), (2, 0)])
def test_emotion_transitions_follow_the_action_groups_chain(model, action, em, ea):
    rs = reactions(model, action, OPEN_REQUEST, em, ea, 3)
    h_next = np.bincount([3 * r.em + r.ea for r in rs], minlength=9)
    expected = model.action_emotion_matrix(ACTION_INDEX[action])[3 * em + ea]
    assert_frequencies(h_next, expected)


@pytest.mark.parametrize('h', range(9))
def test_observation_follows_the_filters_likelihood_of_the_new_state(model, h):
    """O' ~ P(O | h'): checked on the draws whose new state stayed at the start h (under nw
    both chains stay with 0.9, so about 81% of the draws, whatever h)."""
    likelihood = BeliefFilter(model).likelihood
    rs = reactions(model, 'nw', NO_TASK, h // 3, h % 3, 3)
    observed = np.bincount([r.observation for r in rs if 3 * r.em + r.ea == h],
                           minlength=4)[1:]
    assert observed.sum() > 0.7 * len(rs)
    assert_frequencies(observed, likelihood[:, h])


def test_first_observation_is_drawn_from_the_initial_state(model):
    likelihood = BeliefFilter(model).likelihood
    observed = np.bincount([SimulatedHuman(model, seed=s, em=1, ea=1).observation
                            for s in range(3000)], minlength=4)[1:]
    assert_frequencies(observed, likelihood[:, 4])


def test_sample_index_never_draws_a_zero_probability_category():
    cdf = np.cumsum([0.0, 0.4, 0.0, 0.6])
    draws = sample_index(cdf, np.linspace(0, 1, 1001)[:-1])
    assert set(np.unique(draws)) == {1, 3}


@pytest.mark.parametrize('kwargs, match', [
    ({'em': 3}, 'em must be an integer in 0..2'), ({'ea': -1}, 'ea must be'),
    ({'d': 4}, 'd must be an integer in 0..3'), ({'em': 1.0}, 'em must be'),
    ({'likelihood': np.ones((3, 8))}, 'likelihood must have shape')])
def test_bad_inputs_raise(model, kwargs, match):
    with pytest.raises(ValueError, match=match):
        SimulatedHuman(model, seed=0, **kwargs)


def test_bad_react_inputs_raise(model):
    human = SimulatedHuman(model, seed=0)
    with pytest.raises(ValueError, match='unknown action'):
        human.react('wave', NO_TASK)
    with pytest.raises(ValueError, match='task_state must map tp, tx and ty'):
        human.react('nw', {'tp': 1})


def test_fault_epochs_are_kept_as_ranges():
    """A long fault span costs two integers, not a set of every epoch in it."""
    faults = parse_faults(['dropout:5', 'collision:7-1000000000'])
    assert faults['dropout'] == [(5, 5)] and faults['collision'] == [(7, 1_000_000_000)]
    with pytest.raises(ValueError, match='1 <= k <= m'):
        parse_faults(['decline:9-3'])
