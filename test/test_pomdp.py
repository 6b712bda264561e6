"""The point-based POMDP solver (core.pomdp.solver) against problems with a known optimum, and its
structure against the MDP model it is built from."""

import numpy as np
import pytest

from hrc_ros.core.pomdp import _kernels as kernels
from hrc_ros.core.pomdp.solver import (AlphaSet, MixedPOMDP, backup_sweeps, fib_q, initial_bounds,
                                       mdp_q, shared_actions)

GAMMA = 0.95
LISTEN, OPEN_LEFT, OPEN_RIGHT = range(3)
TIGER_LEFT, TIGER_RIGHT = range(2)


def tiger() -> MixedPOMDP:
    """Cassandra, Kaelbling and Littman's tiger (1994): listen (-1, hears the tiger's side
    right with 0.85) or open a door (+10 at the treasure, -100 at the tiger; the problem then
    restarts with the tiger behind either door). One observable state, two hidden ones."""
    listen = np.eye(2)[:, None, :] * np.array([[0.85, 0.15], [0.15, 0.85]]).T[None, :, :]
    listen = listen.transpose(1, 0, 2)                            # (o, h, h')
    opened = np.full((2, 2, 2), 0.25)                              # uniform h' and o
    reward = np.array([[-1.0, -1.0], [-100.0, 10.0], [10.0, -100.0]])[None]
    return MixedPOMDP(succ_x=np.zeros((1, 3, 1), dtype=np.intp),
                      succ_l=np.ones((1, 3, 1, 2)), reward=reward,
                      available=np.ones((1, 3), dtype=bool), group=np.array([0, 1, 1]),
                      kernel=np.stack([listen, opened]), gamma=GAMMA,
                      order=np.array([LISTEN, OPEN_LEFT, OPEN_RIGHT]))


def tiger_controller_value(n: int) -> float:
    """Exact value at the uniform belief of 'listen until one side was heard n times more
    than the other, then open the other door' (a linear system over (count, tiger))."""
    nodes = [(c, s) for c in range(-n, n + 1) for s in (TIGER_LEFT, TIGER_RIGHT)]
    index = {node: i for i, node in enumerate(nodes)}
    a = np.eye(len(nodes))
    r = np.zeros(len(nodes))
    for (c, s), i in index.items():
        if abs(c) < n:
            r[i] = -1.0
            left = 0.85 if s == TIGER_LEFT else 0.15
            a[i, index[(c + 1, s)]] -= GAMMA * left
            a[i, index[(c - 1, s)]] -= GAMMA * (1.0 - left)
        else:       # c = +n: heard left more often -> open the right door
            r[i] = 10.0 if (s == TIGER_LEFT) == (c > 0) else -100.0
            a[i, index[(0, TIGER_LEFT)]] -= GAMMA * 0.5
            a[i, index[(0, TIGER_RIGHT)]] -= GAMMA * 0.5
    v = np.linalg.solve(a, r)
    return 0.5 * (v[index[(0, TIGER_LEFT)]] + v[index[(0, TIGER_RIGHT)]])


def brute_force(pomdp: MixedPOMDP, b: np.ndarray, horizon: int) -> float:
    """The exact finite-horizon optimum by enumerating the belief tree (x = 0 only)."""
    if horizon == 0:
        return 0.0
    best = -np.inf
    for a in range(pomdp.n_actions):
        q = float(pomdp.reward[0, a] @ b)
        for _, _, p, nb in pomdp.successor_belief(0, b, a):
            q += pomdp.gamma * p * brute_force(pomdp, nb, horizon - 1)
        best = max(best, q)
    return best


def reachable(pomdp: MixedPOMDP, b: np.ndarray, depth: int) -> np.ndarray:
    out, frontier = [b], [b]
    for _ in range(depth):
        frontier = [nb for fb in frontier for a in range(pomdp.n_actions)
                    for _, _, _, nb in pomdp.successor_belief(0, fb, a)]
        out += frontier
    return np.unique(np.round(np.array(out), 12), axis=0)


def point_backups(pomdp: MixedPOMDP, points: np.ndarray, sweeps: int) -> np.ndarray:
    """`sweeps` plain point backups (no improvement rule) from Gamma = {0}: V_sweeps."""
    n_h = pomdp.n_hidden
    alphas = AlphaSet(np.zeros((1, n_h)), np.zeros(1, dtype=np.int8), np.array([0, 1]))
    x = np.zeros(len(points), dtype=np.intp)
    vec, act, val = np.empty((len(points), n_h)), np.empty(len(points), np.intp), \
        np.empty(len(points))
    for _ in range(sweeps):
        proj = np.ascontiguousarray(np.einsum('gohk,ik->goih', pomdp.kernel, alphas.alpha))
        kernels.lb_backup(points, x, pomdp.succ_x, pomdp.succ_l, pomdp.reward,
                          pomdp.available, pomdp.group, pomdp.order, proj, alphas.offsets,
                          pomdp.gamma, shared_actions(pomdp, share=False), vec, act, val)
        alphas = AlphaSet.build(x, vec.copy(), act.copy(), 1)
    return val


def test_point_backups_are_exact_for_a_finite_horizon():
    """With every belief reachable in the horizon as a point, t backups from zero give the
    exact t-step optimum (enumerated over the whole belief tree) at the root."""
    pomdp = tiger()
    b0 = np.array([0.5, 0.5])
    points = reachable(pomdp, b0, 4)
    root = int(np.flatnonzero(np.all(np.isclose(points, b0), axis=1))[0])
    for horizon in (1, 2, 3, 4, 5):
        exact = brute_force(pomdp, b0, horizon)
        assert point_backups(pomdp, points, horizon)[root] == pytest.approx(exact, abs=1e-9)
    assert brute_force(pomdp, b0, 1) == pytest.approx(-1.0)   # listening is the best first act


def test_tiger_bounds_meet_at_the_published_value():
    """Infinite horizon, gamma = 0.95: the optimum at the uniform belief is 19.37 (the
    listen-twice controller, as published; computed exactly here). The solver's lower and upper
    bounds bracket it and meet within 0.01."""
    pomdp = tiger()
    optimum = max(tiger_controller_value(n) for n in range(1, 6))
    assert optimum == pytest.approx(19.3714, abs=1e-4)
    counts = np.arange(-8, 9)
    left = np.r_[0.0, 0.85 ** counts / (0.85 ** counts + 0.15 ** counts), 1.0]   # + corners
    points = np.column_stack([left, 1.0 - left])
    x = np.zeros(len(points), dtype=np.intp)
    alphas, upper = initial_bounds(pomdp, x, points)
    b0 = np.array([[0.5, 0.5]])
    assert upper.evaluate([0], b0)[0] >= optimum           # FIB alone is an upper bound
    alphas, upper, history = backup_sweeps(pomdp, x, points, alphas, upper, 2000, 1e-9,
                                           targets=(np.array([0]), b0), ub_every=1)
    lower = (alphas.alpha @ b0[0]).max()
    high = upper.evaluate([0], b0)[0]
    assert lower <= optimum + 1e-9 <= high + 2e-9
    assert high - lower < 0.01
    # the best vector at the uniform belief listens
    assert alphas.action[np.argmax(alphas.alpha @ b0[0])] == LISTEN


def test_fib_lies_between_the_mdp_and_the_pomdp_optimum():
    pomdp = tiger()
    q_mdp = mdp_q(pomdp)
    q_fib, _ = fib_q(pomdp)
    assert np.all(q_fib <= q_mdp + 1e-9)
    b0 = np.array([0.5, 0.5])
    assert (q_fib[0] @ b0).max() >= max(tiger_controller_value(n) for n in range(1, 6))
    # the MDP: the tiger's side known, always open the treasure door: 10 / (1 - gamma); so
    # QMDP at the uniform belief listens: -1 + gamma * 200
    np.testing.assert_allclose(q_mdp[0].max(axis=0), 10.0 / (1.0 - GAMMA), atol=1e-6)
    assert (q_mdp[0] @ b0).max() == pytest.approx(-1.0 + GAMMA * 200.0, abs=1e-6)


@pytest.mark.parametrize('seed', [0, 1])
def test_random_small_pomdps_bounds_bracket_brute_force_horizon(seed):
    """Random 3-state POMDPs with two observable states: after t backups from zero at all
    reachable points the root value is the brute-force t-step optimum (x evidence included)."""
    rng = np.random.default_rng(seed)
    n_h, n_a, n_o = 3, 2, 2
    e = rng.dirichlet(np.ones(n_h), size=(n_a, n_h))
    lik = rng.dirichlet(np.ones(n_o), size=n_h).T                   # (o, h')
    kernel = e[:, None, :, :] * lik[None, :, None, :]
    succ_l = rng.dirichlet(np.ones(2), size=(1, n_a, n_h)).transpose(0, 1, 3, 2)
    pomdp = MixedPOMDP(succ_x=np.array([[[0, 0], [0, 0]]]), succ_l=succ_l,
                       reward=rng.normal(size=(1, n_a, n_h)),
                       available=np.ones((1, n_a), dtype=bool), group=np.arange(n_a),
                       kernel=kernel, gamma=0.9, order=np.arange(n_a))
    b0 = np.full(n_h, 1.0 / n_h)
    points = reachable(pomdp, b0, 3)
    root = int(np.flatnonzero(np.all(np.isclose(points, b0), axis=1))[0])
    for horizon in (1, 2, 3, 4):
        assert point_backups(pomdp, points, horizon)[root] == pytest.approx(
            brute_force(pomdp, b0, horizon), abs=1e-9)
