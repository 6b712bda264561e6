"""Liveness of a policy: the probability that a committed task completes within a horizon.

A policy can be optimal for its model and still never finish a task: where holding a committed
task costs less per epoch than the idle cell after it, a plan that never finishes is the
cheapest (issue 34: the arm's policy chose dm 37 epochs in a row with the robot's last cycle
to run). The cost does not say so, so the solver checks it: for a fixed policy pi,

    u_0(s) = 0,    u_{t+1}(s) = sum_{s' committed} P(s' | s, pi(s)) u_t(s') + P(done | s, pi(s)),

over the states s with a committed task (ty != 0), is the probability that the task committed
at s completes within t epochs: a committed task leaves ty != 0 only by completing (MODEL.md
3.2), so the chain over the committed states with "done" (ty' = 0) absorbing is closed. It is
policy evaluation on that absorbing chain, exact (no sampling): the rows are the rule-by-rule
`HRCModel.transition` of the policy's action (every event of MODEL.md 3 and 8), restricted to
the committed states whose task part the task book can produce (`pomdp.solver.task_closure`:
a state such as ty = 3 with tp = 0 is no task at all), at every h, d and queue level: 1,080
states (3,240 with a queue of 2), which is why it is quick. The person does their part as the
model says (their counter runs down every epoch).

`best_completion` is the same question maximised over every policy (value iteration on the
reach probability, with the model's availability): the bound no policy of the model can pass,
which tells a policy's shortfall from one the model itself imposes (at d = 0 only dn is planned
with the fail-safe, and an aggressive person stays there with probability 0.95 an epoch).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import ACTIONS, N_DISTANCE, N_HIDDEN, HRCModel

HORIZON = 50          # epochs (issue 34: P(complete within 50 epochs) >= 0.95)
TARGET = 0.95
SLACK = 1e-9          # rounding between two computations of one probability


def committed_states(model: HRCModel) -> np.ndarray:
    """The flat states with a committed task (ty != 0) whose task part the task book can
    produce, at every h, d and queue level, ascending."""
    from ..pomdp.solver import task_closure
    y = np.zeros(model.n_task, dtype=bool)
    y[task_closure(model)] = True
    y &= model.task_grid['ty'] != 0
    mask = np.broadcast_to(y[None, None, :, None], (model.n_levels, N_HIDDEN, model.n_task,
                                                    N_DISTANCE))
    return np.flatnonzero(mask.reshape(-1))


class CommittedChain:
    """The transition rows of the committed states (`committed_states`) by action: for action
    a, `inside[a]` (n, n) sparse, P(s' | s, a) among the committed states, and `done[a]` (n,),
    P(the task completes | s, a); `available[a]` (n,) whether a may be planned at s."""

    def __init__(self, model: HRCModel, actions=range(len(ACTIONS))):
        from scipy import sparse
        self.model = model
        self.states = committed_states(model)
        n = len(self.states)
        position = np.full(model.n_states, -1, dtype=np.int64)
        position[self.states] = np.arange(n)
        ty = model.task_grid['ty']
        d = self.states % N_DISTANCE
        self.inside, self.done, self.available = {}, {}, {}
        for a in actions:
            t = model.transition(self.states, a)
            target_y = (model.split(t.target)[1] // N_DISTANCE) % model.n_task
            finished = ty[target_y] == 0
            rows, cols = t.source[~finished], position[t.target[~finished]]
            if np.any(cols < 0):
                raise AssertionError('a committed task left the task book\'s states without '
                                     'completing: the chain is not closed')
            self.inside[a] = sparse.csr_matrix((t.probability[~finished], (rows, cols)),
                                               shape=(n, n))
            self.done[a] = np.bincount(t.source[finished], weights=t.probability[finished],
                                       minlength=n)
            self.available[a] = model.availability[a, d]

    def policy_step(self, policy: np.ndarray):
        """(P, done) of the policy's action at every committed state."""
        from scipy import sparse
        action = np.asarray(policy)[self.states]
        n = len(self.states)
        p, done = sparse.csr_matrix((n, n)), np.zeros(n)
        for a in np.unique(action):
            pick = sparse.diags((action == a).astype(float))
            p = p + pick @ self.inside[int(a)]
            done += np.where(action == a, self.done[int(a)], 0.0)
        return p.tocsr(), done


@dataclass
class Liveness:
    """Completion probabilities (`completion_probability`, `best_completion`)."""

    states: np.ndarray          # the committed states (flat indices)
    probability: np.ndarray     # P(complete within horizon) at each
    horizon: int

    @property
    def minimum(self) -> float:
        return float(self.probability.min())

    @property
    def worst(self) -> int:
        """The flat state of the smallest probability (the first of them)."""
        return int(self.states[np.argmin(self.probability)])


def completion_probability(model: HRCModel, policy, horizon: int = HORIZON,
                           chain: CommittedChain | None = None) -> Liveness:
    """P(the committed task completes within `horizon` epochs | pi) at every state with a
    committed task (module docstring); `policy` an (N,) action array or a loaded policy."""
    policy = np.asarray(getattr(policy, 'policy', policy))
    if policy.shape != (model.n_states,):
        raise ValueError(f'the policy has {policy.size} states, the model {model.n_states}')
    chain = chain or CommittedChain(model, np.unique(policy[committed_states(model)]))
    p, done = chain.policy_step(policy)
    u = np.zeros(len(chain.states))
    for _ in range(int(horizon)):
        u = p @ u + done
    return Liveness(chain.states, u, int(horizon))


def best_completion(model: HRCModel, horizon: int = HORIZON,
                    chain: CommittedChain | None = None) -> Liveness:
    """The largest P(the committed task completes within `horizon` epochs) any policy of the
    model reaches (with its availability: only dn at d = 0 with the fail-safe), per state."""
    chain = chain or CommittedChain(model)
    u = np.zeros(len(chain.states))
    for _ in range(int(horizon)):
        u = np.max([np.where(chain.available[a], chain.inside[a] @ u + chain.done[a], -np.inf)
                    for a in chain.inside], axis=0)
    return Liveness(chain.states, u, int(horizon))


@dataclass
class LivenessCheck:
    """A policy's completion probabilities beside the model's bound (`check_liveness`)."""

    policy: Liveness
    bound: Liveness
    target: float = TARGET

    @property
    def short(self) -> np.ndarray:
        """(n,) bool over the committed states: the policy below min(target, the bound),
        below the target where some policy of the model reaches it, below the bound where
        none does."""
        return self.policy.probability < np.minimum(self.target, self.bound.probability) - SLACK

    @property
    def passed(self) -> bool:
        return not self.short.any()

    def lines(self, model: HRCModel) -> list[str]:
        p, b = self.policy, self.bound
        near = p.states % N_DISTANCE > 0
        at = np.flatnonzero(near)[np.argmin(p.probability[near])]
        out = [f'liveness: P(a committed task completes within {p.horizon} epochs) over the '
               f'{len(p.states):,} states with a committed task (every h, d and task state the '
               f'task book produces): min {p.minimum:.4f} at {describe_state(model, p.worst)}, '
               f'min at d >= 1 {p.probability[at]:.4f} at '
               f'{describe_state(model, int(p.states[at]))}',
               f'liveness: the model\'s bound (the best any policy reaches) min '
               f'{b.minimum:.4f} at {describe_state(model, b.worst)}']
        short = self.short
        if short.any():
            first = int(np.flatnonzero(short)[0])
            out.append(f'liveness: FAILED: {int(short.sum()):,} states below min({self.target}, '
                       f'the bound), e.g. {describe_state(model, int(p.states[first]))}: '
                       f'{p.probability[first]:.4f} (bound {b.probability[first]:.4f})')
        else:
            out.append(f'liveness: met: no state below min({self.target}, the bound)')
        return out


def check_liveness(model: HRCModel, policy, horizon: int = HORIZON,
                   target: float = TARGET) -> LivenessCheck:
    """The policy's completion probabilities and the model's bound (module docstring)."""
    chain = CommittedChain(model)
    return LivenessCheck(completion_probability(model, policy, horizon, chain),
                         best_completion(model, horizon, chain), target)


def describe_state(model: HRCModel, index: int) -> str:
    """'[em,ea,tp,tc,tx,ty,hp,hc,bp,bc,d]' of a flat state (with l = ... under a queue)."""
    level, base = model.split(index)
    state = '[' + ','.join(str(v) for v in model.state(int(base))) + ']'
    return state if model.queue is None else f'{state} l={int(level)}'
