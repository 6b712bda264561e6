"""A simulated human worker and the human-robot distance, sampled from MODEL.md's dynamics.

The decision maker never sees the human's motivation em and aggression ea; it sees the
distance level d and a velocity level O. This module plays the other side: it holds the hidden
(em, ea) and d and, for each robot action a_k, draws one epoch of MODEL.md 3 from the *same*
probabilities the planner uses, so a simulation tests the decision making, not a model mismatch.

One reaction (`SimulatedHuman.react`), with every random number drawn in this fixed order from
one `numpy.random.default_rng(seed)` stream, one uniform u per event, sampled by inverse CDF:

1. acceptance (always drawn, so the stream does not depend on the action):
   ``accepted = u < p_accept[em]`` for an eligible request (MODEL.md 3.1), None otherwise;
2. Delta in (-1, 0, +1) from ``p_delta[ea]``, then ``d' = next_distance(d, a, Delta)`` (3.3);
3. em' from the em chain of the action's group, row em (3.4);
4. ea' from the ea chain of the action's group, row ea;
5. the observation O' in {1, 2, 3} from P(O | h') with h' = 3*em' + ea', the belief filter's
   likelihood (MODEL.md 6), so the evidence is generated the way the filter reads it.

em' and ea' are drawn separately because the 9x9 emotion matrix is their Kronecker product.
The constructor draws O_1 from the initial (em, ea). Acceptance and Delta read the epoch's
start values of em and ea, as the transition equations do. A fixed count of five uniforms per
epoch keeps runs with different selectors on common random numbers and lets the vectorised
evaluator (`evaluate.py`) replay the same stream.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import (ACTION_EMOTION_GROUP, DELTAS, HRCModel, action_index, request_eligible)

UNIFORMS_PER_EPOCH = 5


@dataclass(frozen=True)
class Reaction:
    """The cell's answer to one action: acceptance, the new hidden state, d' and O'."""

    accepted: bool | None   # None: the action was not an eligible request
    em: int
    ea: int
    d: int
    observation: int        # O' in {1, 2, 3}, drawn from the new (em, ea)
    delta: int              # the human's step (-1 away, 0, +1 closer)


def sample_index(cumulative: np.ndarray, u):
    """Inverse-CDF draw: the first index whose cumulative probability exceeds u."""
    index = np.sum(np.asarray(cumulative)[..., :-1] <= np.asarray(u)[..., None], axis=-1)
    return index


def _check_level(name: str, value, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or not 0 <= value <= high:
        raise ValueError(f'{name} must be an integer in 0..{high}, got {value!r}')
    return int(value)


class SimulatedHuman:
    """The hidden human (em, ea) and the distance level d of one simulated cell.

    `seed` is anything `numpy.random.default_rng` accepts (an int, a sequence of ints, a
    SeedSequence). `likelihood` (3, 9) = P(O | h) defaults to `BeliefFilter(model).likelihood`.
    """

    def __init__(self, model: HRCModel, seed=0, em: int = 0, ea: int = 0, d: int = 1,
                 likelihood=None):
        self.model = model
        self.em = _check_level('em', em, 2)
        self.ea = _check_level('ea', ea, 2)
        self.d = _check_level('d', d, 3)
        if likelihood is None:
            from ..pomdp.belief import BeliefFilter
            likelihood = BeliefFilter(model).likelihood
        likelihood = np.asarray(likelihood, dtype=float)
        if likelihood.shape != (3, 9):
            raise ValueError(f'likelihood must have shape (3, 9) (O, h), got '
                             f'{likelihood.shape}')
        self.likelihood = likelihood
        self.rng = np.random.default_rng(seed)
        cfg = model.config
        self._accept = cfg.p_accept
        self._delta_cdf = np.cumsum(cfg.p_delta, axis=1)
        self._chain_cdf = {g: tuple(np.cumsum(m, axis=1) for m in chains)
                           for g, chains in model.emotion_chains.items()}
        self._observation_cdf = np.cumsum(likelihood, axis=0).T   # row h: CDF over O
        self.observation = self._draw_observation(self.rng.random())

    @property
    def h(self) -> int:
        """The hidden state index h = 3*em + ea."""
        return 3 * self.em + self.ea

    def _draw_observation(self, u: float) -> int:
        return int(sample_index(self._observation_cdf[self.h], u)) + 1

    def react(self, action, task_state) -> Reaction:
        """One epoch's answer to `action`, given the epoch's start task state (tp, tx, ty)."""
        a = action_index(action)
        try:
            tp, tx, ty = (int(task_state[n]) for n in ('tp', 'tx', 'ty'))
        except (KeyError, TypeError, ValueError):
            raise ValueError('task_state must map tp, tx and ty to integers, got '
                             f'{task_state!r}') from None
        u_accept, u_delta, u_em, u_ea, u_obs = self.rng.random(UNIFORMS_PER_EPOCH)
        accepted = None
        if request_eligible(a, tp, tx, ty):
            accepted = bool(u_accept < self._accept[self.em])
        delta = DELTAS[int(sample_index(self._delta_cdf[self.ea], u_delta))]
        self.d = int(self.model.next_distance(self.d, a, delta))
        em_cdf, ea_cdf = self._chain_cdf[ACTION_EMOTION_GROUP[a]]
        self.em = int(sample_index(em_cdf[self.em], u_em))
        self.ea = int(sample_index(ea_cdf[self.ea], u_ea))
        self.observation = self._draw_observation(u_obs)
        return Reaction(accepted, self.em, self.ea, self.d, self.observation, delta)
