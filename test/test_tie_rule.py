"""One tie rule (model.TIE_TOLERANCE, model.SAFETY_ORDER): every fast path that breaks ties
between actions equals the rule as MODEL.md 5 states it, on scores built to hold exact ties,
chains of near-ties and unavailable actions."""

import numpy as np
import pytest

from hrc_ros.core import model
from hrc_ros.core.mdp.solver import greedy_policy
from hrc_ros.core.model import ACTIONS, N_HIDDEN, SAFETY_ORDER, TIE_TOLERANCE
from hrc_ros.core.pomdp import _kernels as pomdp_kernels
from hrc_ros.core.pomdp.solver import AlphaPolicy, AlphaSet, MixedPOMDP, first_of_best

N_ACTIONS = len(ACTIONS)


def rule(scores, order=SAFETY_ORDER) -> int:
    """MODEL.md 5 read literally: the actions within TIE_TOLERANCE * max(1, |best|) of the
    best are tied; the tie goes to the first of them in the safety order."""
    best = max(scores)
    tied = [a for a in range(len(scores)) if scores[a] >= best - TIE_TOLERANCE * max(1.0,
                                                                                      abs(best))]
    return min(tied, key=list(order).index)


def tricky_scores(n: int, seed: int = 0) -> np.ndarray:
    """(n, 8) rows: exact ties, chains of steps just under and over the tolerance, large and
    small magnitudes, unavailable actions (-inf)."""
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n):
        scale = rng.choice([1e-3, 1.0, 37.0, 1e4])
        base = rng.normal() * scale
        unit = TIE_TOLERANCE * max(1.0, abs(base))
        steps = rng.choice([0.0, 0.45, 0.6, 0.9, 1.1, 5.0], size=N_ACTIONS)
        row = base + np.cumsum(steps)[rng.permutation(N_ACTIONS)] * unit
        row[rng.random(N_ACTIONS) < 0.2] = -np.inf
        if np.all(np.isneginf(row)):
            row[rng.integers(N_ACTIONS)] = base
        rows.append(row)
    return np.array(rows)


SCORES = tricky_scores(3000)


def test_the_scores_exercise_every_kind_of_tie():
    expected = np.array([rule(row) for row in SCORES])
    plain = np.argmax(SCORES, axis=1)
    assert (expected != plain).mean() > 0.3          # the tie rule decides often
    assert len(set(expected.tolist())) == N_ACTIONS  # every action wins somewhere
    def running_best(row):          # keep the first until one beats it by the tolerance
        kept = None
        for a in SAFETY_ORDER:
            if np.isfinite(row[a]) and (kept is None or row[a] > row[kept] + TIE_TOLERANCE
                                        * max(1.0, abs(row[kept]))):
                kept = a
        return kept
    assert any(rule(row) != running_best(row) for row in SCORES)   # chains of near-ties


def test_the_array_and_the_loop_forms_are_the_rule():
    expected = np.array([rule(row) for row in SCORES])
    np.testing.assert_array_equal(model.safest_best(SCORES), expected)
    np.testing.assert_array_equal(model.safest_best(SCORES.T, axis=0), expected)
    assert [model.safest_best_one(row, SAFETY_ORDER) for row in SCORES] == expected.tolist()
    assert [model.safest_best_one(row.tolist(), SAFETY_ORDER) for row in SCORES] == \
        expected.tolist()
    best = SCORES.max(axis=1)
    np.testing.assert_array_equal(model.tie_floor(best),
                                  [b - TIE_TOLERANCE * max(1.0, abs(b)) for b in best])


def test_the_mdp_greedy_policy_and_the_pomdp_fast_paths_are_the_rule():
    expected = np.array([rule(row) for row in SCORES])
    np.testing.assert_array_equal(greedy_policy(SCORES.T), expected)
    np.testing.assert_array_equal(first_of_best(SCORES), expected)
    order = np.array([3, 0, 7, 1, 6, 2, 5, 4])      # another order (a general MixedPOMDP's)
    np.testing.assert_array_equal(first_of_best(SCORES, order),
                                  [rule(row, order) for row in SCORES])


def test_the_alpha_policy_scalar_and_batch_selections_are_the_rule():
    """One observable state, one alpha vector per action whose value at b is the row's score
    (unavailable actions have no vector)."""
    b = np.full(N_HIDDEN, 1.0 / N_HIDDEN)
    for row in SCORES[:300]:
        actions = [a for a in range(N_ACTIONS) if np.isfinite(row[a])]
        alpha = np.array([[row[a]] * N_HIDDEN for a in actions])
        policy = AlphaPolicy(columns=[0], alpha=alpha, action=actions, offsets=[0, len(actions)],
                             q_fib=np.repeat(np.where(np.isfinite(row), row, 0.0)[None, :, None],
                                             N_HIDDEN, axis=2),
                             available=np.isfinite(row)[None], n_columns=1)
        action, scores = policy.pomdp(b, 0)
        expected = rule(list(scores))
        assert action == expected
        assert list(policy.pomdp_many(b[None], [0])) == [expected]
        assert policy.fib(b, 0)[0] == rule(list(policy.fib(b, 0)[1]))
        assert list(policy.fib_many(b[None], [0])) == [policy.fib(b, 0)[0]]


def chain_pomdp(rewards: np.ndarray, order) -> MixedPOMDP:
    """One observable state, two hidden ones, actions whose one-step value is their reward
    (the state ends there: its only vector is 0)."""
    n_a = len(rewards)
    return MixedPOMDP(succ_x=np.zeros((1, n_a, 1), dtype=np.intp),
                      succ_l=np.ones((1, n_a, 1, 2)),
                      reward=np.repeat(rewards[None, :, None], 2, axis=2),
                      available=np.ones((1, n_a), dtype=bool), group=np.zeros(n_a, np.intp),
                      kernel=np.full((1, 1, 2, 2), 0.5), gamma=0.0, order=np.asarray(order))


@pytest.mark.parametrize('mode', ['serial', '2'])
def test_the_pomdp_backups_choose_by_the_rule(mode):
    """A chain 0, 0.9, 1.8 (x 1e-9): the first two are tied, the last two are tied, only the
    best and the first are not. The rule ties the second with the best: a1. A running best
    (keep the first until one beats it by the tolerance) picked a2."""
    from hrc_ros.core import parallel
    points = np.array([[0.5, 0.5], [1.0, 0.0]])
    x = np.zeros(2, dtype=np.intp)
    for rewards, order in (((0.0, 0.9e-9, 1.8e-9), (0, 1, 2)),
                           ((5.0, 5.0 + 0.9e-8, 5.0 + 1.8e-8, 4.0), (3, 0, 1, 2)),
                           ((-7.0, -7.0, -7.0 + 2e-8), (1, 0, 2))):
        rewards = np.array(rewards)
        pomdp = chain_pomdp(rewards, order)
        expected = rule(rewards.tolist(), order)
        alphas = AlphaSet(np.zeros((1, 2)), np.zeros(1, dtype=np.int8), np.array([0, 1]))
        proj = np.ascontiguousarray(np.einsum('gohk,ik->goih', pomdp.kernel, alphas.alpha))
        vec, act, val = np.empty((2, 2)), np.empty(2, np.intp), np.empty(2)
        ub_val, ub_act = np.empty(2), np.empty(2, np.intp)
        none = np.full((1, len(rewards)), -1, dtype=np.intp)   # no shared backups
        with parallel.mode(mode):
            pomdp_kernels.lb_backup(points, x, pomdp.succ_x, pomdp.succ_l, pomdp.reward,
                                    pomdp.available, pomdp.group, pomdp.order, proj,
                                    alphas.offsets, pomdp.gamma, none, vec, act, val)
            pomdp_kernels.ub_backup(points, x, pomdp.succ_x, pomdp.succ_l, pomdp.reward,
                                    pomdp.available, pomdp.group, pomdp.order, pomdp.kernel,
                                    pomdp.gamma, np.zeros((1, len(rewards), 2)),
                                    np.zeros((1, 2)), np.zeros((0, 2)), np.zeros(0),
                                    np.zeros(2, np.int64), none, ub_val, ub_act)
        assert act.tolist() == [expected, expected]
        assert ub_act.tolist() == [expected, expected]
        np.testing.assert_array_equal(val, rewards[expected])   # the chosen vector's value
        np.testing.assert_array_equal(vec, np.full((2, 2), rewards[expected]))
        np.testing.assert_array_equal(ub_val, rewards.max())    # the bound: the largest


def test_the_batch_simulator_and_the_selector_break_qmdp_ties_alike():
    """Both qmdp paths, on Q tables whose nine rows h of a column are one tricky row (so the
    expected Q under any belief is that row, to rounding far below the engineered steps)."""
    from hrc_ros.core.decision.selection import ActionSelector
    from hrc_ros.core.study.evaluation import BatchSimulator
    scores = SCORES[np.all(np.isfinite(SCORES), axis=1)][:300]
    n = len(scores)
    belief = np.random.default_rng(1).dirichlet(np.ones(N_HIDDEN), size=n)
    sim = BatchSimulator.__new__(BatchSimulator)
    sim.columns, sim._q = 0, scores                  # candidates h * 0 + e: row e for every h
    sim.n_base = 0                                   # one queue level (MODEL.md 8.1): l = 0
    batch = sim._qmdp(belief, np.arange(n), np.zeros(n, dtype=np.intp))
    selector = ActionSelector.__new__(ActionSelector)
    selector._q = np.ascontiguousarray(scores.T)
    for e in range(n):
        chosen = selector._qmdp(belief[e], np.full(N_HIDDEN, e))
        assert chosen.action == rule(list(chosen.scores)) == batch[e] == rule(scores[e])
