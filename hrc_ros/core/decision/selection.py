"""Action selection from a belief over h and the observable state (MODEL.md section 6).

The policy pi was solved for the fully observed MDP (MODEL.md 5). Online the robot knows the
observable part x = (tp, tc, tx, ty, hp, hc, bp, bc, d) and a belief b over the hidden part
h = 3*em + ea. Each candidate full state s_h = (em, ea, x), h = 0..8, has flat index

    index(s_h) = (h * n_task + y) * 4 + d,    y = ravel_multi_index((tp, ..., bc), task_dims),

so the nine candidates are one column of the policy reshaped to (9, n_task * 4).

Selectors (`SELECTORS`):

- ``paper`` (the paper's "Action Selection Heuristic"): a vote. Action a scores
  V(a) = sum_{h : pi(s_h) = a} b(h); the largest V wins. Ties (within 1e-12) go to the tied
  action holding the largest single weight max_{h : pi(s_h) = a} b(h); a remaining tie (again
  within 1e-12) goes to the first action of the safety order dn, dp, nw, ct, rh1, rh2, mh, dm.
  scores = V (8,).
- ``qmdp``: a* = argmax_a sum_h b(h) Q(s_h, a), with Q(s, a) = -J(s, a) + gamma E[V(s')] of the
  solved value V (one factored Bellman step, `FactoredBellman.q`, formed once). Ties within
  model.TIE_TOLERANCE * max(1, |best|) (the solver's own rule, `model.safest_best`) go to
  the safety order. scores = the
  expected Q (8,). Needs `value`.
- ``mls`` (most likely state): the policy action of h* = argmax_h b(h); ties in h (within 1e-12)
  go to the lowest h, i.e. the calmer, less motivated human. scores = one-hot of the action.
- ``pomdp``: the action of the best alpha vector of the solved POMDP (`pomdp`,
  docs/POMDP.md) for (x, b); vectors within the tie tolerance of the best go to the first
  action of the safety order. scores[a] = the best value of a's vectors (-inf where a has
  none). Needs a POMDP policy (`pomdp=`, else the shipped one solved for the configuration).
- ``fib``: a* = argmax_a sum_h b(h) Q_fib(s_h, a), the fast informed bound's Q (a step past
  QMDP: it averages over the next observation before maximising); ties as qmdp. scores = the
  expected Q_fib (-inf where unavailable). From the same POMDP policy file.

The selectors are pure and do not apply the epoch's fail-safe (d = 0 -> dn); the caller does
(DESIGN.md, one decision epoch, step 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..pomdp.belief import validate_belief
from ..model import (ACTIONS, N_DISTANCE, N_HIDDEN, OBSERVABLE_VARIABLES, first_in_safety_order,
                     safest_best)
from ..mdp.policy import policy_arrays

SELECTORS = ('paper', 'qmdp', 'mls', 'pomdp', 'fib')
POMDP_SELECTORS = ('pomdp', 'fib')   # read the POMDP policy file
VOTE_TOLERANCE = 1e-12
N_ACTIONS = len(ACTIONS)


def check_alpha_columns(alphas, model) -> None:
    """A POMDP policy must cover the model's columns, l * n_task * 4 + y * 4 + d for every
    queue length l (MODEL.md 8.1): ValueError for one solved for another state space."""
    want = model.n_levels * model.n_task * N_DISTANCE
    have = getattr(alphas, 'column_index', None)
    if have is not None and len(have) != want:
        raise ValueError(f'the POMDP policy covers {len(have)} observable columns, the model '
                         f'{model.config.source} has {want} (queue length L = '
                         f'{model.queue_length}): solve it for this configuration '
                         '(hrc-solve --method pomdp)')


@dataclass(frozen=True)
class Selection:
    action: int          # action index (ACTIONS order)
    scores: np.ndarray   # (8,): vote sums (paper), expected Q (qmdp), one-hot (mls)
    method: str

    @property
    def name(self) -> str:
        return ACTIONS[self.action]


class ActionSelector:
    """Select an action from (belief, observable state) with a solved policy.

    `policy` is the (N,) array of action indices, or an object with `.policy` (a loaded
    `Policy` or a `SolveResult`); then its `.value` serves qmdp when `value` is not given.
    `pomdp` is a loaded `PomdpPolicy` (or its `AlphaPolicy`) for pomdp and fib; without it
    the file `pomdp_path` names (a node's `pomdp_policy` parameter: '' or None is the shipped
    one solved for the configuration) is loaded when such a method is chosen.
    """

    def __init__(self, model, policy, value=None, method: str = 'paper', pomdp=None,
                 pomdp_path: str | None = None):
        policy, value = policy_arrays(policy, value)
        self.model = model
        n = model.n_states
        pi = np.ascontiguousarray(policy)
        if pi.shape != (n,) or not np.issubdtype(pi.dtype, np.integer):
            raise ValueError(f'policy must be an integer array of shape ({n},), got '
                             f'{pi.dtype} {pi.shape}')
        if pi.min() < 0 or pi.max() >= N_ACTIONS:
            raise ValueError(f'policy holds action indices outside 0..{N_ACTIONS - 1}')
        self.policy = pi
        # the queue (MODEL.md 8.1): one block of N0 states per queue length l, outermost
        self.levels, self.n_base = model.n_levels, model.n_base
        self.n_columns = self.n_base // N_HIDDEN             # (y, d) per level
        # row h, column l * n_columns + (y, d)
        self._by_h = np.ascontiguousarray(pi.reshape(self.levels, N_HIDDEN, self.n_columns)
                                          .transpose(1, 0, 2).reshape(N_HIDDEN, -1))
        if value is not None:
            if value.shape != (n,) or not np.all(np.isfinite(value)):
                raise ValueError(f'value must be a finite float array of shape ({n},), got '
                                 f'{value.shape}')
        self.value = value
        self._q = None   # Q (8, N) for qmdp, formed once from value (27 MB at full size)
        self.pomdp = pomdp
        self.pomdp_path = pomdp_path
        self.set_method(method)
        self._h_offsets = np.arange(N_HIDDEN) * self.n_columns
        dims = model.dims[2:]
        strides = np.cumprod((1,) + tuple(dims[:0:-1]))[::-1]
        self._observable = tuple(zip(OBSERVABLE_VARIABLES, (int(v) for v in dims),
                                     (int(s) for s in strides)))
        assert self._observable[-1][1] == N_DISTANCE

    def set_method(self, method: str) -> None:
        """Change the default method (validated); qmdp's Q table is formed now, not in the
        next `select`."""
        self.method = self.prepare(method)

    def prepare(self, method: str) -> str:
        """Validate `method` and load what it needs (qmdp's Q table, the POMDP policy for
        pomdp and fib: `PolicyError` when there is none); the default method is unchanged."""
        method = self._check_method(method)
        if method == 'qmdp':
            self._q_table()
        if method in POMDP_SELECTORS:
            self._alphas()
        return method

    def _check_method(self, method: str) -> str:
        if method not in SELECTORS:
            raise ValueError(f'unknown selector method {method!r}; expected one of '
                             f'{", ".join(SELECTORS)}')
        if method == 'qmdp' and self.value is None:
            raise ValueError("method 'qmdp' needs the solved value function: pass value= "
                             '(or a Policy/SolveResult that has .value)')
        return method

    # -- inputs ------------------------------------------------------------------------
    def column(self, observable) -> int:
        """Column of the candidates: y * 4 + d, and with a queue (MODEL.md 8.1) l * n_task * 4
        + y * 4 + d for l = min(the observable's tenth value, L), the tasks waiting as the
        robot observes them (the task manager's `queued`); a candidate's index is
        l * N0 + h * n_task * 4 + y * 4 + d (`candidate_indices`). Without a queue a tenth
        value (a cell that publishes its queue to a policy without one) is not read."""
        nine = 'the 9 integers (tp, tc, tx, ty, hp, hc, bp, bc, d)'
        want = nine + (' and the tasks waiting l >= 0 (the model has a queue, MODEL.md 8.1)'
                       if self.levels > 1 else ', optionally the tasks waiting')
        try:
            values = tuple(observable)
        except TypeError:
            raise ValueError(f'observable must be {want}, got {observable!r}') from None
        n = len(self._observable)
        if len(values) not in ((n + 1,) if self.levels > 1 else (n, n + 1)):
            raise ValueError(f'observable must be {want}, got {len(values)} values')
        column = 0
        if len(values) > n:
            level, values = values[-1], values[:-1]
            if isinstance(level, bool) or not isinstance(level, (int, np.integer)) \
                    or level < 0:
                raise ValueError('observable l (tasks waiting, MODEL.md 8.1) must be an '
                                 f'integer >= 0, got {level!r}')
            column = min(int(level), self.levels - 1) * self.n_columns
        for v, (name, size, stride) in zip(values, self._observable):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ValueError(f'observable {name} must be an integer, got {v!r}')
            if not 0 <= v < size:
                raise ValueError(f'observable {name} must lie in 0..{size - 1}, got {v}')
            column += int(v) * stride
        return column

    def candidate_indices(self, observable) -> np.ndarray:
        """Flat indices of the nine full states (h, x), h = 0..8."""
        return self._indices(self.column(observable))

    def _indices(self, column: int) -> np.ndarray:
        level, within = divmod(column, self.n_columns)
        return level * self.n_base + self._h_offsets + within

    # -- selection ---------------------------------------------------------------------
    def select(self, belief, observable, method: str | None = None) -> Selection:
        """The action for belief b (9,) and observable x; `method` overrides the default."""
        method = self.method if method is None else self._check_method(method)
        b = validate_belief(belief)
        column = self.column(observable)
        if method == 'paper':
            return self._paper(b, self._by_h[:, column])
        if method == 'qmdp':
            return self._qmdp(b, self._indices(column))
        if method in POMDP_SELECTORS:
            action, scores = getattr(self._alphas(), method)(b, column)
            return Selection(action, scores, method)
        return self._mls(b, self._by_h[:, column])

    def _alphas(self):
        """The POMDP policy's `AlphaPolicy` (when none was given, the file `pomdp_path` names,
        loaded once and checked against the configuration); `PolicyError` when there is
        none."""
        if self.pomdp is None:
            from ..pomdp.policy import load_pomdp_policy, pomdp_policy_path
            self.pomdp = load_pomdp_policy(pomdp_policy_path(self.pomdp_path, self.model.config),
                                           self.model.config)
        alphas = getattr(self.pomdp, 'policy', self.pomdp)
        check_alpha_columns(alphas, self.model)
        return alphas

    def _paper(self, b: np.ndarray, actions: np.ndarray) -> Selection:
        scores = np.bincount(actions, weights=b, minlength=N_ACTIONS)
        votes = scores.tolist()
        best = max(votes)
        tied = [v >= best - VOTE_TOLERANCE for v in votes]
        if sum(tied) == 1:
            return Selection(tied.index(True), scores, 'paper')
        single = [0.0] * N_ACTIONS
        for a, w in zip(actions.tolist(), b.tolist()):
            if w > single[a]:
                single[a] = w
        top = max(single[a] for a in range(N_ACTIONS) if tied[a])
        tied = [tied[a] and single[a] >= top - VOTE_TOLERANCE for a in range(N_ACTIONS)]
        return Selection(int(first_in_safety_order(tied)), scores, 'paper')

    def _q_table(self) -> np.ndarray:
        """Q(s, a) for every state, from one factored Bellman step on `value` (~50 ms)."""
        if self._q is None:
            from ..mdp.solver import FactoredBellman
            self._q = FactoredBellman(self.model).q(self.value)
        return self._q

    def _qmdp(self, b: np.ndarray, indices: np.ndarray) -> Selection:
        support = np.flatnonzero(b > 0.0)   # terms with b(h) = 0 add exactly nothing
        q = self._q_table()[:, indices[support]].T
        scores = b[support] @ q
        return Selection(int(safest_best(scores)), scores, 'qmdp')

    def _mls(self, b: np.ndarray, actions: np.ndarray) -> Selection:
        h = int(np.flatnonzero(b >= b.max() - VOTE_TOLERANCE)[0])
        action = int(actions[h])
        scores = np.zeros(N_ACTIONS)
        scores[action] = 1.0
        return Selection(action, scores, 'mls')
