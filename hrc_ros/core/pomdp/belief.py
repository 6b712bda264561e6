"""The belief over the hidden emotions h = 3*em + ea (MODEL.md section 6).

The belief b is a probability vector over h = 0..8 (the paper's Table 5 "State 1..9").
Table 5 gives, for each velocity level O, a distribution T[O, h] over h. Two modes:

- ``table`` (the paper's case study): after an observation O the belief *is* row T[O]; the
  previous belief and the action are ignored.
- ``bayes`` (the default): a discrete Bayes filter. Table 5 is read as P(h | O) under a uniform
  prior on O, so by Bayes' rule the likelihood is each column normalised over O, mixed with
  epsilon of uniform so that no observation has probability zero:

      L[O, h] = (1 - epsilon) * T[O, h] / sum_O' T[O', h] + epsilon / 3,      sum_O L[O, h] = 1.

  One epoch under action a with emotion matrix E_a[h, h'] = P(h' | h, a) (MODEL.md 3.4):

      predict   b_pred(h') = sum_h b(h) E_a[h, h']          (b_pred = b @ E_a)
      correct   b'(h')    ∝ L[O, h'] * b_pred(h').

  Both steps are one product with the precomputed 9x9 matrix M[a, O] = E_a * L[O] (columns
  scaled), so `update` is a vector-matrix product and a normalisation.

A configuration may instead give P(O | h) itself (`observation.likelihood`, for example fitted
from recordings by `hrc-fit`): then L is that matrix as it is (no epsilon mix: a fitted matrix
is already the estimate), unless a `table` or `epsilon` is passed explicitly, which asks for
the Table 5 form. Table mode always reads Table 5.

Evidence other than one velocity level: `observation` may be a likelihood vector l (9,),
l(h) = P(evidence | h) (all ones: no evidence, the prediction alone); bayes mode corrects with l
instead of L[O]. In table mode a vector yields the posterior under the prior that Table 5
implies: T[O, h] = L0[O, h] * c(h) / 3 with c(h) = sum_O T[O, h] and L0 the epsilon-free
likelihood, so the table mode of a vector l is b'(h) ∝ l(h) c(h); for l = L0[O] that is row O
exactly.

Underflow. With epsilon > 0 the normaliser is at least epsilon/3 and never vanishes. With
epsilon = 0 an observation that the predicted belief calls impossible (for example O = 3 when
all the mass sits on calm states) gives a zero posterior; the filter then restarts from the
evidence alone, b' = l / sum(l) (the belief `initial` would give under a uniform prior), rather
than return NaN. The same fallback applies whenever the normaliser is below the smallest normal
float, where the quotient would lose precision.

The first belief. Without a person prior b_1 = L[O_1] / sum (uniform before the first
observation). A configuration may give `observation.prior`, the distribution of h when the
filter starts (the cell's people, fitted by `hrc-fit`: MODEL.md 6.1); then b_1 ∝ prior * L[O_1]
(bayes and posterior mode; table mode reads Table 5 as always), and `initial()` without an
observation is the prior.

Evidence of the observable transition (mode ``posterior``). Acting reveals more than O': the
human's answer to an eligible request depends on em and the distance move on ea, both at the
epoch's start (MODEL.md 3). With their likelihood e(h) = P(x' | x, h, a)
(`HRCModel.transition_likelihood`) the exact posterior is

    b'(h') ∝ L[O, h'] sum_h b(h) e(h) E_a[h, h'],

which is what the POMDP policy plans with (`pomdp`). In ``posterior`` mode `update` and
`update_many` take e as `evidence`; ``bayes`` and ``table`` ignore it (MODEL.md 6 as
written), and ``posterior`` without evidence is ``bayes``.

`update_many` is the same update for a batch of beliefs (the batch evaluator's episodes).

All functions are pure: they return new arrays and never modify their inputs.
"""

from __future__ import annotations

import numpy as np

from ..config import BELIEF_MODES
from ..model import ACTIONS, N_HIDDEN, N_OBSERVATIONS, OBSERVATION_LEVELS, action_index

BELIEF_TOLERANCE = 1e-6  # |sum(b) - 1| allowed in an input belief
_TINY = np.finfo(float).tiny


def validate_belief(belief, name: str = 'belief') -> np.ndarray:
    """`belief` as a float array (9,) if it is a probability vector; ValueError naming it.

    Cheap (it runs every epoch): a NaN or inf makes the sum non-finite, which fails the check.
    """
    try:
        b = np.asarray(belief, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be {N_HIDDEN} probabilities over h = 3*em + ea, '
                         f'got {belief!r}') from None
    if b.shape != (N_HIDDEN,):
        raise ValueError(f'{name} must have shape ({N_HIDDEN},) (h = 3*em + ea), got {b.shape}')
    values = b.tolist()   # nine Python floats: faster to reduce than numpy calls
    total = sum(values)
    low = min(values)
    if not (low >= 0.0 and abs(total - 1.0) <= BELIEF_TOLERANCE):
        if not np.all(np.isfinite(b)):
            raise ValueError(f'{name} holds NaN or inf: {b.tolist()}')
        if low < 0.0:
            raise ValueError(f'{name} holds a negative probability: {b.tolist()}')
        raise ValueError(f'{name} sums to {total:.9g}, not 1 (tolerance {BELIEF_TOLERANCE})')
    return b


def _check_table(table) -> np.ndarray:
    try:
        t = np.array(table, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'table must be 3 rows of {N_HIDDEN} probabilities, got '
                         f'{table!r}') from None
    if t.shape != (N_OBSERVATIONS, N_HIDDEN):
        raise ValueError(f'table must have shape (3, {N_HIDDEN}) (row O-1, column h), got '
                         f'{t.shape}')
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValueError('table must hold finite non-negative probabilities')
    rows = t.sum(axis=1)
    if np.any(np.abs(rows - 1.0) > BELIEF_TOLERANCE):
        o = int(np.argmax(np.abs(rows - 1.0))) + 1
        raise ValueError(f'table row O={o} sums to {rows[o - 1]:.9g}, not 1')
    if np.any(t.sum(axis=0) <= 0):
        h = int(np.argmin(t.sum(axis=0)))
        raise ValueError(f'table column h={h} is zero under every O: the bayes likelihood '
                         'is undefined')
    return t


def _checked_evidence(evidence) -> np.ndarray:
    e = np.asarray(evidence, dtype=float)
    if e.shape != (N_HIDDEN,) or not np.all(np.isfinite(e)) or e.min() < 0.0:
        raise ValueError(f'evidence must be {N_HIDDEN} finite non-negative likelihoods '
                         f"P(x' | x, h, a), got {evidence!r}")
    return e


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


class BeliefFilter:
    """Belief over h for one model; defaults from `model.config` (observation section)."""

    def __init__(self, model, table=None, epsilon=None, mode=None):
        cfg = model.config
        self.model = model
        self.table = _read_only(_check_table(cfg.observation_table if table is None
                                             else table))
        explicit_epsilon = epsilon
        epsilon = cfg.epsilon if epsilon is None else epsilon
        if isinstance(epsilon, bool) or not isinstance(epsilon, (int, float, np.floating)) \
                or not 0.0 <= float(epsilon) <= 1.0:
            raise ValueError(f'epsilon must be a probability in [0, 1], got {epsilon!r}')
        self.epsilon = float(epsilon)
        mode = cfg.belief_mode if mode is None else mode
        if mode not in BELIEF_MODES:
            raise ValueError(f'mode must be one of {", ".join(BELIEF_MODES)}, got {mode!r}')
        self.mode = mode

        column_mass = self.table.sum(axis=0)           # c(h) = sum_O T[O, h]
        self.table_prior = _read_only(column_mass / column_mass.sum())
        given = cfg.observation_likelihood
        if given is not None and table is None and explicit_epsilon is None:
            self.likelihood = _read_only(np.array(given, dtype=float))
        else:
            exact = self.table / column_mass            # L0[O, h], columns sum to 1
            self.likelihood = _read_only((1.0 - self.epsilon) * exact
                                         + self.epsilon / N_OBSERVATIONS)
        # The restart from the evidence alone: uniform prior corrected by L[O].
        self._evidence_only = _read_only(self.likelihood
                                         / self.likelihood.sum(axis=1, keepdims=True))
        # initial(O) in bayes and posterior mode: the prior (the configuration's person prior,
        # else uniform) corrected by L[O]; where the prior gives O no mass, the evidence alone.
        prior = cfg.observation_prior
        self.prior = _read_only(np.full(N_HIDDEN, 1.0 / N_HIDDEN) if prior is None
                                else prior / prior.sum())
        first = self.likelihood * self.prior
        mass = first.sum(axis=1, keepdims=True)
        self._first = _read_only(np.where(mass >= _TINY, first / np.maximum(mass, _TINY),
                                          self._evidence_only))
        self.emotion = _read_only(np.stack([model.action_emotion_matrix(a)
                                            for a in range(len(ACTIONS))]))
        # M[a, O-1] = E_a with column h' scaled by L[O, h']: b' ∝ b @ M[a, O-1].
        self._predict_correct = _read_only(self.emotion[:, None, :, :]
                                           * self.likelihood[None, :, None, :])

    # -- inputs ------------------------------------------------------------------------
    def _observation(self, observation):
        """(O-1, None) for an integer level, (None, l) for a likelihood vector."""
        if isinstance(observation, (int, np.integer)) and not isinstance(observation, bool):
            if 1 <= observation <= N_OBSERVATIONS:
                return int(observation) - 1, None
            raise ValueError(f'observation must be a velocity level in {OBSERVATION_LEVELS} '
                             f'or a likelihood vector (9,), got {observation!r}')
        try:
            lik = np.asarray(observation, dtype=float)
        except (TypeError, ValueError):
            lik = None
        if lik is None or lik.shape != (N_HIDDEN,):
            raise ValueError(f'observation must be a velocity level in {OBSERVATION_LEVELS} '
                             f'or a likelihood vector (9,), got {observation!r}')
        if not np.all(np.isfinite(lik)) or lik.min() < 0.0 or not lik.max() > 0.0:
            raise ValueError('observation likelihood must be finite, non-negative and not all '
                             f'zero, got {lik.tolist()}')
        # Only ratios matter; scaling to max 1 keeps products of many features from underflow.
        return None, lik / lik.max()

    # -- the filter --------------------------------------------------------------------
    def initial(self, observation=None) -> np.ndarray:
        """b_1: the prior without an observation (`observation.prior`, else uniform); else row O
        (table) or the prior times L[O], normalised (bayes, posterior)."""
        if observation is None:
            return self.prior.copy()
        o, lik = self._observation(observation)
        if self.mode == 'table':
            return self.table[o].copy() if lik is None else self._table_vector(lik)
        if lik is None:
            return self._first[o].copy()
        post = lik * self.prior
        total = post.sum()
        return post / total if total >= _TINY else lik / lik.sum()

    def update(self, belief, action, observation, evidence=None) -> np.ndarray:
        """b' after taking `action` (name or index) and then observing `observation`;
        `evidence` (9,): P(x' | x, h, a), used in ``posterior`` mode."""
        b = validate_belief(belief)
        a = action_index(action)
        o, lik = self._observation(observation)
        if self.mode == 'table':
            return self.table[o].copy() if lik is None else self._table_vector(lik)
        if evidence is not None and self.mode == 'posterior':
            b = b * _checked_evidence(evidence)
        if lik is None:
            post = b @ self._predict_correct[a, o]
        else:
            post = (b @ self.emotion[a]) * lik
        total = post.sum()
        if not total >= _TINY:
            # Evidence the prediction calls impossible (epsilon = 0): restart from it alone.
            return self._evidence_only[o].copy() if lik is None else lik / lik.sum()
        post /= total
        return post

    def update_many(self, beliefs, actions, observations, evidence=None) -> np.ndarray:
        """`update` of a batch: beliefs (E, 9), action indices (E,), observations O (E,) in
        1..3, `evidence` (E, 9) or None; the same arithmetic, and the same restart from the
        evidence where the normaliser vanishes. Inputs are trusted (no per-row validation: a
        hot path)."""
        o = np.asarray(observations, dtype=np.intp) - 1
        if self.mode == 'table':
            return self.table[o].copy()
        beliefs = np.asarray(beliefs, dtype=float)
        if evidence is not None and self.mode == 'posterior':
            beliefs = beliefs * evidence
        post = np.einsum('eh,ehk->ek', beliefs,
                         self._predict_correct[np.asarray(actions, dtype=np.intp), o])
        total = post.sum(axis=1, keepdims=True)
        lost = total[:, 0] < _TINY
        if lost.any():
            post[lost] = self._evidence_only[o[lost]]
            total[lost] = 1.0
        return post / total

    def initial_many(self, observations) -> np.ndarray:
        """`initial` of a batch of observations O (E,) in 1..3."""
        o = np.asarray(observations, dtype=np.intp) - 1
        return (self.table if self.mode == 'table' else self._first)[o].copy()

    def _table_vector(self, lik: np.ndarray) -> np.ndarray:
        post = lik * self.table_prior
        total = post.sum()
        if not total >= _TINY:
            return lik / lik.sum()
        return post / total
