"""Belief filter: Table 5 rows, the bayes likelihood, the filter vs brute force, robustness."""

import numpy as np
import pytest

from hrc_ros.core.pomdp.belief import BeliefFilter, validate_belief
from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTIONS, HRCModel, chain_matrix
from hrc_ros.core.paths import default_config_path

TABLE5 = np.array([
    [0.80, 0.10, 0.00, 0.10, 0.00, 0.00, 0.00, 0.00, 0.00],
    [0.00, 0.10, 0.00, 0.10, 0.70, 0.05, 0.00, 0.05, 0.00],
    [0.00, 0.00, 0.05, 0.00, 0.00, 0.10, 0.05, 0.10, 0.70],
])


@pytest.fixture(scope='module')
def model():
    return HRCModel(load_config(default_config_path()))


def test_defaults_come_from_the_configuration(model):
    f = BeliefFilter(model)
    np.testing.assert_array_equal(f.table, TABLE5)
    assert f.epsilon == 0.01 and f.mode == 'bayes'
    f = BeliefFilter(model, epsilon=0.0, mode='table')
    assert f.epsilon == 0.0 and f.mode == 'table'


# -- table mode --------------------------------------------------------------------------
def test_table_mode_is_the_table5_row_whatever_came_before(model):
    f = BeliefFilter(model, mode='table')
    rng = np.random.default_rng(0)
    for o in (1, 2, 3):
        np.testing.assert_array_equal(f.initial(o), TABLE5[o - 1])
        for action in ACTIONS:
            prior = rng.dirichlet(np.ones(9))
            np.testing.assert_array_equal(f.update(prior, action, o), TABLE5[o - 1])


def test_table_mode_with_a_likelihood_vector_reproduces_the_rows(model):
    # With epsilon = 0 the evidence vector of level O is L0[O]; table mode then gives row O.
    f = BeliefFilter(model, epsilon=0.0, mode='table')
    for o in (1, 2, 3):
        evidence = f.likelihood[o - 1].copy()
        np.testing.assert_allclose(f.update(f.initial(), 'nw', evidence), TABLE5[o - 1],
                                   atol=1e-15)
        np.testing.assert_allclose(f.initial(evidence * 1e-200), TABLE5[o - 1], atol=1e-15)


def test_returned_rows_are_copies(model):
    f = BeliefFilter(model, mode='table')
    b = f.update(f.initial(), 'dn', 1)
    b[:] = 0.0
    np.testing.assert_array_equal(f.table[0], TABLE5[0])
    np.testing.assert_array_equal(f.initial(1), TABLE5[0])
    with pytest.raises(ValueError):
        f.likelihood[0, 0] = 1.0   # read-only: the precomputed products depend on it


# -- the bayes likelihood ----------------------------------------------------------------
def test_likelihood_columns_sum_to_one_over_o(model):
    for eps in (0.0, 0.01, 0.3, 1.0):
        f = BeliefFilter(model, epsilon=eps)
        assert f.likelihood.shape == (3, 9)
        np.testing.assert_allclose(f.likelihood.sum(axis=0), np.ones(9), atol=1e-15)
        assert (f.likelihood >= eps / 3 - 1e-15).all()


def test_likelihood_known_values(model):
    f = BeliefFilter(model, epsilon=0.01)
    e = 0.01 / 3
    # h = 0: column (0.8, 0, 0) -> (1, 0, 0); h = 1: (0.1, 0.1, 0) -> (1/2, 1/2, 0);
    # h = 5: (0, 0.05, 0.1) -> (0, 1/3, 2/3).
    np.testing.assert_allclose(f.likelihood[:, 0], [0.99 + e, e, e])
    np.testing.assert_allclose(f.likelihood[:, 1], [0.99 / 2 + e, 0.99 / 2 + e, e])
    np.testing.assert_allclose(f.likelihood[:, 5], [e, 0.99 / 3 + e, 0.99 * 2 / 3 + e])
    np.testing.assert_allclose(BeliefFilter(model, epsilon=1.0).likelihood, np.full((3, 9), 1 / 3))


# -- the bayes filter against independent formulations ------------------------------------
def _emotion(model, action):
    """P(h' | h, a) rebuilt from the configuration's chains, loop by loop."""
    group = {'mh': 'motivate', 'rh1': 'request', 'rh2': 'request'}.get(ACTIONS[action], 'base')
    em = chain_matrix(*model.config.emotion_chain(group, 'em'))
    ea = chain_matrix(*model.config.emotion_chain(group, 'ea'))
    e = np.zeros((9, 9))
    for h in range(9):
        for h2 in range(9):
            e[h, h2] = em[h // 3, h2 // 3] * ea[h % 3, h2 % 3]
    return e


def test_bayes_update_equals_the_formula_written_out(model):
    f = BeliefFilter(model)
    rng = np.random.default_rng(1)
    for _ in range(50):
        b = rng.dirichlet(np.full(9, 0.5))
        a = int(rng.integers(8))
        o = int(rng.integers(1, 4))
        e = _emotion(model, a)
        post = np.array([f.likelihood[o - 1, h2] * sum(e[h, h2] * b[h] for h in range(9))
                         for h2 in range(9)])
        np.testing.assert_allclose(f.update(b, ACTIONS[a], o), post / post.sum(), rtol=1e-12)


def test_bayes_filter_equals_brute_force_over_all_paths(model):
    """P(h_T | O_1..T) by summing the joint probability of every path h_1..h_T (9^5 paths)."""
    f = BeliefFilter(model)
    rng = np.random.default_rng(2)
    for _ in range(5):
        obs = [int(o) for o in rng.integers(1, 4, size=5)]
        actions = [int(a) for a in rng.integers(0, 8, size=4)]
        joint = np.full(9, 1 / 9) * f.likelihood[obs[0] - 1]
        for a, o in zip(actions, obs[1:]):
            joint = joint[..., None] * _emotion(model, a) * f.likelihood[o - 1]
        expected = joint.reshape(-1, 9).sum(axis=0)
        b = f.initial(obs[0])
        for a, o in zip(actions, obs[1:]):
            b = f.update(b, a, o)
        np.testing.assert_allclose(b, expected / expected.sum(), rtol=1e-10)


def test_initial_belief(model):
    f = BeliefFilter(model)
    np.testing.assert_array_equal(f.initial(), np.full(9, 1 / 9))
    for o in (1, 2, 3):
        row = f.likelihood[o - 1]
        np.testing.assert_allclose(f.initial(o), row / row.sum())
        np.testing.assert_allclose(f.initial(np.asarray(row)), row / row.sum())


PRIOR = [0.5, 0.2, 0.0, 0.1, 0.1, 0.0, 0.05, 0.05, 0.0]


def test_person_prior_starts_the_filter(model):
    """observation.prior: b_1 ∝ prior * L[O_1] in bayes and posterior mode (initial and
    initial_many), the prior itself before any observation; table mode reads Table 5."""
    cfg = model.config.with_overrides({'observation': {'prior': PRIOR}})
    prior = np.array(PRIOR)
    for mode in ('bayes', 'posterior'):
        f = BeliefFilter(HRCModel(cfg), mode=mode)
        np.testing.assert_allclose(f.initial(), prior)
        for o in (1, 2, 3):
            want = f.likelihood[o - 1] * prior
            np.testing.assert_allclose(f.initial(o), want / want.sum())
            assert f.initial(o)[2] == 0.0          # no mass where the prior has none
        np.testing.assert_allclose(f.initial_many(np.array([3, 1, 2])),
                                   np.stack([f.initial(o) for o in (3, 1, 2)]))
        lik = np.linspace(0.1, 0.9, 9)
        np.testing.assert_allclose(f.initial(lik), lik * prior / (lik * prior).sum())
    table = BeliefFilter(HRCModel(cfg), mode='table')
    np.testing.assert_allclose(table.initial(2), TABLE5[1])


def test_person_prior_that_rules_out_the_evidence_falls_back_to_it(model):
    """A prior with all its mass where O_1 has none (epsilon 0): the evidence alone, not NaN."""
    cfg = model.config.with_overrides({'observation': {'epsilon': 0.0,
                                                       'prior': [0, 0, 0, 0, 0, 0, 0, 0, 1]}})
    f = BeliefFilter(HRCModel(cfg))
    row = f.likelihood[0]
    assert row[8] == 0.0
    np.testing.assert_allclose(f.initial(1), row / row.sum())
    np.testing.assert_allclose(f.initial_many(np.array([1])), [row / row.sum()])


def test_person_prior_hashes(model):
    """Left out and null hash the same (the shipped policies and estimators keep their
    identity); a prior changes the filter's hash and the POMDP's, never the MDP policy's."""
    from hrc_ros.core.pomdp.policy import observation_hash
    base = model.config
    null = base.with_overrides({'observation': {'prior': None}})
    given = base.with_overrides({'observation': {'prior': PRIOR}})
    assert null.belief_hash == base.belief_hash
    assert observation_hash(null) == observation_hash(base)
    assert given.belief_hash != base.belief_hash
    assert observation_hash(given) != observation_hash(base)
    assert given.policy_hash == base.policy_hash


@pytest.mark.parametrize('prior, message', [
    ([0.5] * 9, 'sums to'), ([1.0] * 8, 'list of 9'), ([1.5] + [-0.0625] * 8, 'probability'),
    ('uniform', 'list of 9')])
def test_bad_person_prior_is_refused_by_name(model, prior, message):
    from hrc_ros.core.config import ConfigError
    with pytest.raises(ConfigError, match=message) as err:
        model.config.with_overrides({'observation': {'prior': prior}})
    assert 'observation.prior' in str(err.value)


def test_likelihood_vector_equals_the_level(model):
    f = BeliefFilter(model)
    rng = np.random.default_rng(3)
    for _ in range(20):
        b = rng.dirichlet(np.ones(9))
        a = int(rng.integers(8))
        o = int(rng.integers(1, 4))
        evidence = f.likelihood[o - 1] * rng.uniform(0.1, 10.0)   # only ratios matter
        np.testing.assert_allclose(f.update(b, a, evidence), f.update(b, a, o), rtol=1e-12)


def test_update_is_pure(model):
    f = BeliefFilter(model)
    b = np.random.default_rng(4).dirichlet(np.ones(9))
    before = b.copy()
    out = f.update(b, 'mh', 2)
    np.testing.assert_array_equal(b, before)
    assert out is not b
    np.testing.assert_array_equal(f.update(b, 'mh', 2), out)


# -- robustness --------------------------------------------------------------------------
def _random_evidence(rng):
    """A sparse random likelihood vector over h (several features' product, say)."""
    while True:
        lik = rng.uniform(0.0, 1.0, size=9) * (rng.random(9) < 0.4)
        if lik.max() > 0:
            return lik


@pytest.mark.parametrize('mode', ['bayes', 'table'])
@pytest.mark.parametrize('epsilon', [0.01, 0.0])
def test_long_random_sequences_stay_probability_vectors(model, mode, epsilon):
    f = BeliefFilter(model, epsilon=epsilon, mode=mode)
    rng = np.random.default_rng(5)
    b = f.initial()
    for step in range(3000):
        a = ACTIONS[int(rng.integers(8))] if step % 2 else int(rng.integers(8))
        if step % 5 == 4:
            observation = _random_evidence(rng)
        else:
            observation = int(rng.integers(1, 4))
        b = f.update(b, a, observation)
        assert b.shape == (9,)
        assert np.all(np.isfinite(b)) and (b >= 0).all()
        assert abs(b.sum() - 1.0) < 1e-12


def test_survives_an_observation_the_prior_calls_impossible(model):
    # A calm human for sure (h = 0); under dn it can only reach h in {0, 1, 3, 4}, which
    # Table 5 never shows as O = 3. With epsilon = 0 the posterior mass is exactly 0.
    calm = np.eye(9)[0]
    strict = BeliefFilter(model, epsilon=0.0)
    b = strict.update(calm, 'dn', 3)
    assert np.all(np.isfinite(b)) and b.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(b, strict.likelihood[2] / strict.likelihood[2].sum())
    # The filter recovers: the next consistent observations are handled normally.
    b = strict.update(b, 'dn', 3)
    assert np.all(np.isfinite(b)) and b[[2, 5, 6, 7, 8]].sum() == pytest.approx(1.0)
    assert b[[2, 5, 6, 7, 8]].min() > 0.1
    # With epsilon > 0 it is merely unlikely: every reachable h has the same likelihood
    # epsilon/3, so the posterior is the prediction itself.
    soft = BeliefFilter(model, epsilon=0.01)
    np.testing.assert_allclose(soft.update(calm, 'dn', 3), _emotion(model, 7)[0], rtol=1e-12)
    # A vector evidence that excludes every reachable state falls back the same way.
    evidence = np.zeros(9)
    evidence[8] = 1.0
    np.testing.assert_array_equal(strict.update(calm, 'dn', evidence), evidence)


@pytest.mark.parametrize('epsilon', [0.01, 0.0])
def test_concentrates_on_an_identifiable_h(model, epsilon):
    f = BeliefFilter(model, epsilon=epsilon)
    b = f.initial()
    for _ in range(30):
        b = f.update(b, 'dn', 1)
    assert int(np.argmax(b)) == 0 and b[0] > 0.9
    # Medium velocity under dn points to h = 4 (em = ea = 1), most likely by far.
    for _ in range(30):
        b = f.update(b, 'dn', 2)
    assert int(np.argmax(b)) == 4 and b[4] > 0.8


def test_tracks_a_simulated_human(model):
    """Sample h and O from the model itself: the filter puts more mass on the truth than 1/9."""
    f = BeliefFilter(model)
    rng = np.random.default_rng(6)
    h = 4
    b = f.initial(int(rng.choice(3, p=f.likelihood[:, h])) + 1)
    mass = []
    for _ in range(2000):
        a = int(rng.integers(8))
        h = int(rng.choice(9, p=f.emotion[a][h]))
        o = int(rng.choice(3, p=f.likelihood[:, h])) + 1
        b = f.update(b, a, o)
        mass.append(b[h])
    assert np.mean(mass) > 0.35


# -- bad inputs --------------------------------------------------------------------------
@pytest.mark.parametrize('belief, message', [
    (np.full(8, 1 / 8), 'shape'), (np.full((3, 3), 1 / 9), 'shape'),
    (np.r_[1.1, -0.1, np.zeros(7)], 'negative'), (np.r_[np.nan, np.zeros(8)], 'NaN'),
    (np.r_[np.inf, np.zeros(8)], 'NaN or inf'), (np.full(9, 0.1), 'sums to'),
    (np.zeros(9), 'sums to'), (['a'] * 9, 'belief'), (None, 'belief'),
])
def test_bad_belief_is_rejected_by_name(model, belief, message):
    f = BeliefFilter(model)
    with pytest.raises(ValueError, match='belief') as err:
        f.update(belief, 'nw', 1)
    assert message in str(err.value)


@pytest.mark.parametrize('action', ['fly', 8, -1, None, 1.0, 'NW'])
def test_unknown_action_is_rejected(model, action):
    with pytest.raises(ValueError, match='action'):
        BeliefFilter(model).update(np.full(9, 1 / 9), action, 1)


@pytest.mark.parametrize('observation', [0, 4, -1, True, 2.0, 'low', np.ones(8),
                                         np.r_[np.nan, np.ones(8)], -np.ones(9), np.zeros(9)])
def test_bad_observation_is_rejected(model, observation):
    f = BeliefFilter(model)
    with pytest.raises(ValueError, match='observation'):
        f.update(np.full(9, 1 / 9), 'nw', observation)
    with pytest.raises(ValueError, match='observation'):
        f.initial(observation)


@pytest.mark.parametrize('kwargs, field', [
    ({'mode': 'kalman'}, 'mode'), ({'epsilon': 1.5}, 'epsilon'), ({'epsilon': -0.1}, 'epsilon'),
    ({'epsilon': 'small'}, 'epsilon'), ({'table': np.ones((2, 9)) / 2}, 'table'),
    ({'table': -TABLE5}, 'table'), ({'table': TABLE5 * 2}, 'table'),
    ({'table': np.r_[[np.eye(9)[0]] * 3]}, 'table column h=1'),
])
def test_bad_construction_is_rejected(model, kwargs, field):
    with pytest.raises(ValueError, match=field):
        BeliefFilter(model, **kwargs)


def test_validate_belief_accepts_lists_and_small_rounding():
    b = validate_belief([1 / 9] * 9)
    assert b.shape == (9,)
    validate_belief(np.r_[0.5 + 5e-7, 0.5, np.zeros(7)])
