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
