"""Independent reference forms the tests hold the package against (not a test module)."""

import numpy as np

from hrc_ros.core.model import ACTIONS


def rule_q(model, value, sources, each_transition=None):
    """Q(s, a) = -J(s, a) + gamma * E[V(s')] of a few states, from `HRCModel.transition` (the
    model enumerated rule by rule), shape (len(sources), 8). `each_transition(a, t)`, if
    given, sees each action's transition too (a test's own checks of it, without building
    it a second time)."""
    sources = np.atleast_1d(np.asarray(sources, dtype=np.int64))
    states = model.state(model.split(sources)[1])     # the queue level aside (MODEL.md 8.1)
    q = np.empty((len(sources), len(ACTIONS)))
    for a in range(len(ACTIONS)):
        t = model.transition(sources, a)
        if each_transition is not None:
            each_transition(a, t)
        expected = np.bincount(t.source, weights=t.probability * value[t.target],
                               minlength=len(sources))
        q[:, a] = -model.flat_cost(sources, a) + model.gamma * expected
    q[~model.availability[:, states[:, 10]].T] = -np.inf      # an action not available there
    return q


def assert_shipped_policy_solves_todays_model(name):
    """policies/<name>.npz is value iteration's answer for today's shipped configuration
    `name`, checked at the fixed point instead of by a solve from zero: its values move by
    less than the configuration's eta under one Bellman update of today's model (the solve's
    own stopping rule, MODEL.md 5), and its policy is, action for action, the greedy policy
    of today's Q at those values. A change of the model that changes any state's best action
    at those values fails it, as it fails a fresh solve; so does one that moves the fixed point
    by more than about eta / (1 - gamma) (the shipped residuals are 0.91-0.94 eta). Smaller
    moves of the values pass, where a fresh solve held them to 1e-9: test_config_policy and
    test_stream still solve the default and the fail-safe-unaware policies from zero and hold
    them bit for bit. The update costs one sweep where a solve takes hundreds (the arm's fresh
    solve alone was 45 s of the suite's CPU, 2026-12-07)."""
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import load_policy
    from hrc_ros.core.mdp.solver import FactoredBellman, greedy_policy
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import share_dir, shipped_config_path
    config = load_config(shipped_config_path(name))
    assert config.sweeps is None, f'{name} solves a fixed number of sweeps: solve it afresh'
    shipped = load_policy(share_dir() / 'policies' / f'{name}.npz', config)
    q = FactoredBellman(HRCModel(config)).q(shipped.value)
    change = float(np.max(np.abs(q.max(axis=0) - shipped.value)))
    assert change < config.eta, (name, change, config.eta)
    np.testing.assert_array_equal(greedy_policy(q), shipped.policy)
    return config, shipped


def solved_successors(pomdp, columns, a, h, n_keys):
    """P(x' | x, a, h) of every solved state x as the POMDP's successor lists hold it, shape
    (n_x, n_keys): row x, column `columns[x']` (the observable key of x'), summed over the
    lists' entries, for a test to hold against the rule-by-rule transition."""
    rows = np.arange(pomdp.n_x)
    got = np.zeros((pomdp.n_x, n_keys))
    for k in range(pomdp.succ_x.shape[2]):
        has = pomdp.succ_x[:, a, k] >= 0
        np.add.at(got, (rows[has], columns[pomdp.succ_x[has, a, k]]),
                  pomdp.succ_l[has, a, k, h])
    return got


def read_only(*arrays):
    """`arrays` made read-only, for a module fixture that several tests share: none can change
    them for the next."""
    for array in arrays:
        array.flags.writeable = False
    return arrays
