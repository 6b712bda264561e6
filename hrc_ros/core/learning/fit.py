"""Learning the cell's model from its recordings: an input-output HMM fitted by EM (`hrc-fit`).

The robot never sees the human's motivation em and aggression ea; it sees, per epoch k, the
observable state x_k (task part and distance d_k), the velocity level O_k, its own action a_k
and, for an eligible request, the answer. With h = 3*em + ea the recordings are an
input-output hidden Markov model whose inputs are the actions (MODEL.md 3 and 6):

    h_1 ~ pi,     h_{k+1} | h_k, a_k ~ E_{g(a_k)}[h_k, .]   (g: the action's emotion group,
                                                             E = kron(em chain, ea chain))
    evidence of epoch k given h_k:
        e_k(h) = L[O_k, h]                                  (no factor when O_k is missing)
               * p_accept[em]^acc (1 - p_accept[em])^(1-acc) (eligible requests with an answer)
               * sum_{Delta: next_distance(d_k, a_k, Delta) = d_{k+1}} p_delta[ea, Delta]
                                                            (when d_{k+1} is known)

so an observed move of d may be explained by several Delta values (MODEL.md 3.3's clipping),
and a (down, stay, up) chain by several moves at its bounds. Every factor of e_k depends on
h_k only, so the forward-backward recursions (`_fit_kernels.e_step_batch`, scaled) give
the posteriors gamma_k(h) and the expected transition counts xi_g(h, h') per action group.

EM. The complete data add the hidden h_k, the Delta of every move and the move of each emotion
chain; their log likelihood is a sum of multinomial terms, so every M-step is closed form:

    p_accept[em]   = sum_k gamma_k(em) [accepted] / sum_k gamma_k(em)      (answered requests)
    p_delta[ea, D] = sum_k gamma_k(ea) r_k(D | ea) / sum_k gamma_k(ea),
                     r_k(D | ea) = p_delta[ea, D] [D fits the move] / sum_D' (the same)
    chain (g, var) = expected moves: the counts C[i, j] of var going i -> j under group g
                     (summed from xi_g), each split over the moves m with clip(i + m) = j in
                     proportion to the current chain, normalised
    L[O, h]        = sum_k gamma_k(h) [O_k = O] / sum_k gamma_k(h)          (epochs with an O)
    pi             = sum over segments of gamma at the segment's first epoch, normalised

(pi is a nuisance parameter unless the person prior is fitted, below.) Each family can be held
fixed at the base configuration's value.

The person prior (`prior=True`, hrc-fit --prior; MODEL.md 6.1). pi is then the distribution of
h where a person starts, written as `observation.prior`, and only the segments that start an
episode at its first epoch (`FIRST_EPOCH`, epoch 1: an epoch count restarting, a new
recording; `FitData.true_starts`) start from it; the pieces cut from an episode (a gap, a
transition the model cannot produce) and recordings that begin mid-run are not new people,
so they start from a separate nuisance distribution pi_cut (`Params.pi_cut`, the packed rows'
last 9 entries, its M-step the same sum over those segments). Without `prior` every segment
starts from pi and the packed rows are as they always were, so the fit's numbers are too.
Its bootstrap interval is that of pi over the resamples; its support is the number of episode
starts (each informs the whole distribution). The log likelihood never decreases; the fit
stops when it rises by less than `tol` per epoch in an iteration, or after `max_iter`. Where
the hidden state is hard to tell EM crawls (its rate is the share of missing information), so
an iteration is a SQUAREM cycle (`run_em`): two EM steps and a checked extrapolation; and
then, with `method=NEWTON` (`fit`'s default), a trust-region quasi-Newton step with the
curvature of the full-data fit, checked (`run_em_batch`): for the estimate's last iterations
and for every bootstrap resample, which it takes to its maximum in a third of SQUAREM's
E-steps where SQUAREM stops short along flat directions (bench/README.md, "hrc-fit's
bootstrap, side by side").

Initialisations. EM finds a local maximum. The first start is the base configuration (mixed
with `INIT_FLOOR` of uniform, because EM can never move a probability away from exactly 0 or
1); the others draw each free family around it (Dirichlet with `INIT_CONCENTRATION`). Each start
runs `SHORT_RUN` iterations; the best continues to convergence (the short-run strategy of
Biernacki, Celeux and Govaert, 2003). The likelihood does not change when em is relabelled
2 - em (reversing p_accept and swapping every em chain's down and up) or ea 2 - ea; the cost
(MODEL.md 4) does, so among the relabellings that leave the held families unchanged the fit
keeps the one nearest the base configuration: the base's labels say which end is "low".

Uncertainty. A nonparametric bootstrap over episodes: `bootstrap` resamples of the episodes
with replacement (as multiplicities, so the data are not copied), each fitted by EM from the
estimate (all of them side by side, `run_em_batch`: one E-step kernel call and one numpy
M-step per iteration for every resample still running, each resample following exactly its
own EM); the 95% interval of a parameter is the 2.5 and 97.5 percentiles of its resampled
values. Support: the posterior-expected number of epochs that inform a parameter (answered
requests by em; moves that tell this Delta apart from both others, by ea; chain moves whose
outcome is unique, from the level they start at; epochs with an observation, by h). Effective
support: p (1 - p) / bootstrap variance, the number of directly observed events that would
pin it down as well; where h is hard to tell it is far below the support. A parameter below
`min_support` in either gets a warning, as does a family never exercised (a chain of an action
never taken keeps its start value).

Data preparation (`prepare`): rows come from `recordings` and never include em or ea. A row
whose answer contradicts the model (an ineligible request accepted) is reported and left out;
a transition the model cannot produce (d moving where no Delta leads, a task state that is not
the rules' successor, MODEL.md 3.2, nor a new task entering an idle cell) is reported and the
episode is cut there; a gap in the epoch numbers cuts it too. An eligible request without an
answer takes the answer its successor's task state shows (accepted requests commit the task);
with no successor it adds no acceptance evidence. The segments of one episode are resampled
together.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime as _dt
import math
import time
from dataclasses import dataclass, field, fields

import numpy as np
import yaml

from . import _kernels as _fit_kernels
from ..config import EMOTION_GROUPS, Config, validate
from ..model import (ACTION_EMOTION_GROUP, ACTIONS, DELTAS, N_HIDDEN, N_OBSERVATIONS,
                     HRCModel, next_distance, request_eligible)
from .rate import successor_ok, working
from .recordings import NO_OBSERVATION, UNANSWERED, UNKNOWN_DISTANCE, Recording

EMOTION_VARIABLES = ('em', 'ea')
MOVES = ('down', 'stay', 'up')
CHAIN_FAMILIES = tuple(f'emotion.{g}.{v}' for g in EMOTION_GROUPS for v in EMOTION_VARIABLES)
FAMILIES = ('p_accept', 'p_delta') + CHAIN_FAMILIES + ('likelihood',)
GROUP_INDEX = {g: i for i, g in enumerate(EMOTION_GROUPS)}
ACTION_GROUP = np.array([GROUP_INDEX[ACTION_EMOTION_GROUP[a]] for a in range(len(ACTIONS))])

INIT_FLOOR = 0.02          # share of uniform mixed into the starting values
INIT_CONCENTRATION = 10.0  # Dirichlet concentration of the random starts around the base
SHORT_RUN = 10             # EM iterations of every start before the best one continues
TOL = 1e-8                 # stop when the log likelihood rises by less than this per epoch
MAX_ITER = 1000
EM, SQUAREM, NEWTON = 'em', 'squarem', 'newton'   # run_em_batch's methods
METHODS = (EM, SQUAREM, NEWTON)
DEFAULT_METHOD = NEWTON    # hrc-fit's (bench/README.md "hrc-fit's bootstrap, side by side")
BOOTSTRAP = 200
MIN_SUPPORT = 100.0        # expected informative epochs below which a parameter is flagged
UNSEEN_FLOOR = 1e-6        # P(O | h) written for a level O that no epoch observed
FIRST_EPOCH = 1            # the epoch count's first value: where a person's run starts
_ACCEPTED, _REFUSED = 1, 2


class FitError(ValueError):
    """The fit cannot run on what it was given; the one-line message says why."""


def expand_hold(names) -> tuple[str, ...]:
    """Families named by `names`: a family, `emotion` (all six chains) or `emotion.<group>`."""
    out: list[str] = []
    for name in names:
        name = name.strip()
        if not name:
            continue
        matched = [f for f in FAMILIES if f == name or f.startswith(name + '.')]
        if not matched:
            raise FitError(f'unknown parameter family {name!r} to hold; families: '
                           f'{", ".join(FAMILIES)} (or emotion, emotion.<group>)')
        out += [f for f in matched if f not in out]
    return tuple(out)


# -- parameters -------------------------------------------------------------------------------
@dataclass
class Params:
    """The fitted quantities: pi (9,), p_accept (3,), p_delta (3, 3) [ea, Delta], chains
    (3, 2, 3) [group, variable, move], likelihood (3, 9) [O - 1, h]."""

    pi: np.ndarray
    p_accept: np.ndarray
    p_delta: np.ndarray
    chains: np.ndarray
    likelihood: np.ndarray
    pi_cut: np.ndarray | None = None   # (9,) with a person prior: where cut pieces start

    @property
    def split_start(self) -> bool:
        """Whether the episodes' starts (pi, the person prior) and the pieces cut from them
        (pi_cut) start from separate distributions (`fit(prior=True)`)."""
        return self.pi_cut is not None

    @classmethod
    def from_config(cls, config: Config) -> 'Params':
        from ..pomdp.belief import BeliefFilter
        from ..model import HRCModel
        chains = np.array([[config.emotion_chain(g, v) for v in EMOTION_VARIABLES]
                           for g in EMOTION_GROUPS])
        likelihood = BeliefFilter(HRCModel(config)).likelihood
        return cls(np.full(N_HIDDEN, 1.0 / N_HIDDEN), config.p_accept.copy(),
                   config.p_delta.copy(), chains, np.array(likelihood))

    def copy(self) -> 'Params':
        return Params(*(np.array(getattr(self, f)) for f in _PARAM_FIELDS),
                      pi_cut=None if self.pi_cut is None else np.array(self.pi_cut))

    def family(self, name: str) -> np.ndarray:
        """The array of one family (a view)."""
        if name in ('p_accept', 'p_delta', 'likelihood'):
            return getattr(self, name)
        _, group, variable = name.split('.')
        return self.chains[GROUP_INDEX[group], EMOTION_VARIABLES.index(variable)]

    def vector(self) -> np.ndarray:
        """The 57 configuration parameters in `PARAMETER_NAMES` order."""
        return np.concatenate([self.p_accept, self.p_delta.ravel(), self.chains.ravel(),
                               self.likelihood.ravel()])

    def emotion_matrices(self) -> np.ndarray:
        """(3, 9, 9): kron(em chain, ea chain) per group."""
        from ..model import chain_matrix
        return np.stack([np.kron(chain_matrix(*self.chains[g, 0]),
                                 chain_matrix(*self.chains[g, 1]))
                         for g in range(len(EMOTION_GROUPS))])


_PARAM_FIELDS = ('pi', 'p_accept', 'p_delta', 'chains', 'likelihood')


def _parameter_names() -> tuple[list[str], list[str]]:
    names, families = [], []
    for em in range(3):
        names.append(f'p_accept[em={em}]')
        families.append('p_accept')
    for ea in range(3):
        for delta in DELTAS:
            names.append(f'p_delta[ea={ea}][Delta={delta:+d}]')
            families.append('p_delta')
    for g in EMOTION_GROUPS:
        for v in EMOTION_VARIABLES:
            for m in MOVES:
                names.append(f'emotion.{g}.{v}.{m}')
                families.append(f'emotion.{g}.{v}')
    for o in range(N_OBSERVATIONS):
        for h in range(N_HIDDEN):
            names.append(f'likelihood[O={o + 1}][h={h}]')
            families.append('likelihood')
    return names, families


PARAMETER_NAMES, PARAMETER_FAMILIES = _parameter_names()
# the person prior's entries (`fit(prior=True)`), reported after the 57
PRIOR_NAMES = tuple(f'prior[h={h}]' for h in range(N_HIDDEN))


# -- data -------------------------------------------------------------------------------------
@dataclass
class FitData:
    """Flat per-epoch arrays over every kept epoch (T), in segments (see `prepare`)."""

    group: np.ndarray          # (T,) emotion group of a_t (moves h_t to h_{t+1})
    observation: np.ndarray    # (T,) O_t - 1, or 3 when there is none
    answer: np.ndarray         # (T,) 0 no acceptance evidence, 1 accepted, 2 refused
    move: np.ndarray           # (T, 3) 1 where Delta fits the move d_t -> d_{t+1}, else 0
    has_move: np.ndarray       # (T,) whether d_t -> d_{t+1} is known
    unique_delta: np.ndarray   # (T, 3) the move tells this Delta apart from both others
    seg_start: np.ndarray      # (S + 1,)
    seg_episode: np.ndarray    # (S,) episode index of each segment
    episodes: list             # episode names
    issues: list               # what was left out or cut, and why
    rows_read: int = 0
    seg_true_start: np.ndarray | None = None   # (S,) the segment starts its episode at epoch 1

    @property
    def true_starts(self) -> np.ndarray:
        """(S,) bool: the segments that start where a person starts, an episode's first
        recorded epoch when that is epoch `FIRST_EPOCH` (not a piece cut from an episode, nor
        a recording that began mid-run); all False when `prepare` did not say."""
        if self.seg_true_start is None:
            return np.zeros(self.segments, dtype=bool)
        return np.asarray(self.seg_true_start, dtype=bool)

    @property
    def epochs(self) -> int:
        return int(self.group.size)

    @property
    def segments(self) -> int:
        return int(self.seg_episode.size)

    @property
    def seg_of_epoch(self) -> np.ndarray:
        return np.repeat(np.arange(self.segments), np.diff(self.seg_start))



def _successor_ok(task, action, accepted, nxt, model: HRCModel | None = None,
                  counter_may_stay: bool = False) -> np.ndarray:
    """Whether each next task state follows from (task, action, accepted) by MODEL.md 3.2 with
    `model`'s rules (the paper's without one), or is a new task entering the cell that the step
    left idle (the task book's rule); with `counter_may_stay` a working robot's counter may
    also have stayed (model.robot_rate: the cell with the arm's progress)."""
    ok = successor_ok(model, task, action, accepted, nxt)
    if counter_may_stay:
        works = working(model, task, action)
        ok |= works & successor_ok(model, task, action, accepted, nxt, False)
    return ok


def _delta_outcomes(d: np.ndarray, action: np.ndarray,
                    model: HRCModel | None = None) -> np.ndarray:
    """(n, 3): next_distance of each Delta (with `model`'s retreat and approach rules, the
    paper's without one)."""
    out = np.empty((len(d), len(DELTAS)), dtype=np.int64)
    move = next_distance if model is None else model.next_distance
    for a in np.unique(action):
        rows = np.flatnonzero(action == a)
        for k, delta in enumerate(DELTAS):
            out[rows, k] = move(d[rows], int(a), delta)
    return out


def prepare(recordings: list[Recording], model: HRCModel | None = None,
            counter_may_stay: bool = False) -> FitData:
    """The fit's arrays from recorded episodes (rules in the module docstring), vectorised
    over the concatenated episodes. `model`: whose rules read the moves and the task steps
    (the base configuration's: robot_paused_by, retreat_reach, approach_reach; None: the
    paper's); `counter_may_stay` (a model with robot_rate, or one being fitted, `hrc-fit
    --rate`): a working robot's counter may stay, as in the cell with the arm."""
    if model is not None and model.robot_rate is not None:
        counter_may_stay = True
    if counter_may_stay and model is None:
        raise ValueError('counter_may_stay needs the model whose pauses say when the robot works')
    issues: list[str] = []
    for r in recordings:
        for message in r.issues:
            if message not in issues:
                issues.append(message)
    recordings = [r for r in recordings if len(r)]
    if not recordings:
        raise FitError('no usable epoch in the recordings')
    episode = np.repeat(np.arange(len(recordings)), [len(r) for r in recordings])
    task = np.concatenate([r.task for r in recordings])
    action, d, epoch, observation, accepted, line = (
        np.concatenate([getattr(r, f) for r in recordings]).astype(np.int64)
        for f in ('action', 'd', 'epoch', 'observation', 'accepted', 'line'))
    n = len(action)

    def where(i: int) -> str:
        return f'{recordings[episode[i]].source}:{line[i]}'

    eligible = np.zeros(n, dtype=bool)
    for a in np.unique(action):
        rows = action == a
        eligible[rows] = request_eligible(int(a), task[rows, 0], task[rows, 2], task[rows, 3])
    keep = ~((accepted == 1) & ~eligible)
    for i in np.flatnonzero(~keep):
        issues.append(f'{where(i)}: {ACTIONS[action[i]]} was accepted, but it was not an '
                      'eligible request (MODEL.md 3.1); row left out')
    accepted = np.where(eligible, accepted, UNANSWERED)   # an ineligible request's "no" is no news
    # link[i]: the transition from row i to row i + 1 (same episode) is usable
    same = np.zeros(n, dtype=bool)
    same[:-1] = episode[1:] == episode[:-1]
    step = np.zeros(n, dtype=np.int64)
    step[:-1] = np.diff(epoch)
    both = same & keep & np.append(keep[1:], False)
    for i in np.flatnonzero(both & (step != 1)):
        issues.append(f'{where(i + 1)}: epoch {epoch[i + 1]} follows epoch {epoch[i]}: the '
                      'episode is cut at the gap')
    link = both & (step == 1)
    outcomes = _delta_outcomes(np.maximum(d, 0), action, model)
    d_next = np.append(d[1:], UNKNOWN_DISTANCE)
    known = link & (d >= 0) & (d_next >= 0)
    fits = outcomes == d_next[:, None]
    bad_move = known & ~fits.any(axis=1)
    for i in np.flatnonzero(bad_move):
        issues.append(f'{where(i + 1)}: d goes from {d[i]} to {d[i + 1]} under '
                      f'{ACTIONS[action[i]]}, which no Delta gives (MODEL.md 3.3); the episode '
                      'is cut there')
    follows = {}
    for value in (False, True):
        follows[value] = np.zeros(n, dtype=bool)
        follows[value][:-1] = _successor_ok(task[:-1], action[:-1], np.full(n - 1, value),
                                            task[1:], model, counter_may_stay)
    # an unanswered eligible request: its successor's task state tells the answer
    infer = link & eligible & (accepted == UNANSWERED)
    accepted[infer & follows[True] & ~follows[False]] = 1
    accepted[infer & follows[False] & ~follows[True]] = 0
    answer_ok = np.where(accepted == 1, follows[True],
                         np.where(accepted == 0, follows[False], follows[False] | follows[True]))
    bad_task = link & ~answer_ok
    for i in np.flatnonzero(bad_task):
        issues.append(f'{where(i + 1)}: the task state does not follow from epoch {epoch[i]} '
                      f'under {ACTIONS[action[i]]} (MODEL.md 3.2); the episode is cut there')
    link &= ~bad_move & ~bad_task
    kept = np.flatnonzero(keep)
    if not kept.size:
        raise FitError('no usable epoch in the recordings')
    has_move = (known & link)[kept]
    distinct = (outcomes[kept][:, :, None] != outcomes[kept][:, None, :]).sum(axis=2) == 2
    obs = observation[kept]
    acc = accepted[kept]
    ends = np.flatnonzero(~link[kept]) + 1          # every segment ends at an unusable link
    starts = np.concatenate([[0], ends[:-1]])
    used = np.unique(episode[kept])
    opens = np.ones(n, dtype=bool)                   # the first row of its recording
    opens[1:] = episode[1:] != episode[:-1]
    first_row = kept[starts]
    renumber = np.full(len(recordings), -1)
    renumber[used] = np.arange(len(used))
    return FitData(
        group=np.ascontiguousarray(ACTION_GROUP[action[kept]]),
        observation=np.where(obs == NO_OBSERVATION, N_OBSERVATIONS, obs - 1),
        answer=np.where(acc == 1, _ACCEPTED, np.where(acc == 0, _REFUSED, 0)),
        move=np.ascontiguousarray(np.where(has_move[:, None], fits[kept], True), dtype=float),
        has_move=has_move, unique_delta=np.ascontiguousarray(distinct & has_move[:, None]),
        seg_start=np.concatenate([[0], ends]).astype(np.int64),
        seg_episode=renumber[episode[kept][starts]],
        episodes=[recordings[e].name for e in used], issues=issues, rows_read=n,
        seg_true_start=opens[first_row] & (epoch[first_row] == FIRST_EPOCH))


# -- E-step and M-step ------------------------------------------------------------------------
# Both work on a batch of parameter sets at once (the lanes: EM starts, bootstrap resamples),
# the parameters packed as rows of X (B, 66) in `_PARAM_FIELDS` order; a single fit is a batch
# of one. The E-step is one numba kernel over all lanes (`_fit_kernels`), the M-step numpy
# over the lane axis, so an EM iteration of 200 resamples costs one Python step, not 200.
@dataclass
class Expected:
    """Expected complete-data counts of one E-step (weighted by segment multiplicity); with
    a leading lane axis on every field in a batch (`e_step_batch`)."""

    loglik: float
    first: np.ndarray          # (9,) posterior of each segment's first hidden state, summed
    accept: np.ndarray         # (2, 3) [accepted, refused] by em
    delta: np.ndarray          # (3, 3) [ea, Delta]
    transitions: np.ndarray    # (3, 2, 3, 3) [group, variable, level i, level j]
    observed: np.ndarray       # (3, 9) [O - 1, h]
    unique_moves: np.ndarray   # (3, 3) [ea, Delta]: moves telling Delta apart from the others
    first_cut: np.ndarray      # (9,) the same of the pieces cut from episodes, with a split
                               # start (`Params.split_start`); else 0 (they are in `first`)

    def lane(self, i) -> 'Expected':
        """Lane(s) `i` of a batch (an int: one lane's counts; an index array: a batch)."""
        return Expected(*(getattr(self, f.name)[i] for f in fields(self)))


_SIZES = {'pi': (N_HIDDEN,), 'p_accept': (3,), 'p_delta': (3, 3),
          'chains': (len(EMOTION_GROUPS), len(EMOTION_VARIABLES), 3),
          'likelihood': (N_OBSERVATIONS, N_HIDDEN)}
_SLICES, _at = {}, 0
for _f in ('pi', 'p_accept', 'p_delta', 'chains', 'likelihood'):
    _n = int(np.prod(_SIZES[_f]))
    _SLICES[_f] = slice(_at, _at + _n)
    _at += _n
N_PACKED = _at
# With a person prior (`Params.split_start`) the cut pieces' start distribution follows, so
# the rows of a fit without one are as they always were.
_SIZES['pi_cut'] = (N_HIDDEN,)
_SLICES['pi_cut'] = slice(N_PACKED, N_PACKED + N_HIDDEN)
N_PACKED_SPLIT = N_PACKED + N_HIDDEN
SPLIT = 2    # a batch of fewer lanes runs each lane as this many halves of the segments
SPLIT_EPOCHS = 10_000   # ... when the data have at least this many epochs (else the overhead wins)


def _field(x: np.ndarray, name: str) -> np.ndarray:
    """The view of one field in packed rows x (B, N_PACKED or N_PACKED_SPLIT): (B,) + its
    shape."""
    return x[:, _SLICES[name]].reshape((len(x),) + _SIZES[name])


def _chain_matrices(chains: np.ndarray) -> np.ndarray:
    """(B, G, V, 3, 3) bounded chain matrices (`model.chain_matrix`) of chains (B, G, V, 3)."""
    m = np.zeros(chains.shape[:-1] + (3, 3))
    for i in range(3):
        m[..., i, max(i - 1, 0)] += chains[..., 0]
        m[..., i, i] += chains[..., 1]
        m[..., i, min(i + 1, 2)] += chains[..., 2]
    return m


def epoch_kinds(data: FitData) -> tuple:
    """The epochs grouped by their evidence: (kind (T,), then per kind its observation,
    answer, move (K, 3), has_move and unique_delta (K, 3)). Epochs of one kind have the same
    evidence e_t(h) under any parameters, so the kernel computes it once per kind and lane,
    and sums the posteriors of a kind before it makes the counts. Kept on `data` (keyed by the
    arrays it was made from)."""
    key = tuple(id(a) for a in (data.observation, data.answer, data.move, data.has_move,
                                data.unique_delta))
    cached = data.__dict__.get('_kinds')
    if cached is not None and cached[0] == key:
        return cached[1]
    move = np.asarray(data.move) > 0
    unique = np.asarray(data.unique_delta, dtype=bool)
    bits = np.array([1, 2, 4])
    label = (np.asarray(data.observation, dtype=np.int64)
             + 4 * (np.asarray(data.answer, dtype=np.int64)
                    + 3 * ((move @ bits) + 8 * (np.asarray(data.has_move, dtype=np.int64)
                                                + 2 * (unique @ bits)))))
    labels, kind = np.unique(label, return_inverse=True)
    at = np.zeros(len(labels), dtype=np.int64)
    at[kind] = np.arange(len(kind))                     # an epoch of each kind
    kinds = (np.ascontiguousarray(kind, dtype=np.int64),
             np.ascontiguousarray(data.observation[at], dtype=np.int64),
             np.ascontiguousarray(data.answer[at], dtype=np.int64),
             np.ascontiguousarray(move[at], dtype=float),
             np.ascontiguousarray(data.has_move[at], dtype=np.bool_),
             np.ascontiguousarray(unique[at]))
    data.__dict__['_kinds'] = (key, kinds)
    return kinds


def _lane_last(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(a, 0, -1))


def e_step_batch(x: np.ndarray, data: FitData, seg_weight: np.ndarray | None = None
                 ) -> tuple[Expected, np.ndarray]:
    """The E-step (`_fit_kernels.e_step_batch`) at each packed row of `x` (B, N_PACKED), with
    segment weights (B, S) (None: all 1). Returns the batch's counts and, per lane, the first
    segment whose evidence is impossible under its parameters (-1 for none; that lane's
    counts and log likelihood are then not to be used). Rows of `N_PACKED_SPLIT` entries have
    a split start: the segments that start an episode (`FitData.true_starts`) from pi, the
    others from pi_cut; rows of `N_PACKED`, every segment from pi."""
    x = np.atleast_2d(x)
    used = len(x)
    split_start = x.shape[1] == N_PACKED_SPLIT
    pi = _field(x, 'pi')
    pi = np.stack([pi, _field(x, 'pi_cut') if split_start else pi], axis=1)   # (B, 2, 9)
    seg_kind = (np.where(data.true_starts, 0, 1) if split_start
                else np.zeros(data.segments)).astype(np.int64)
    weight = np.broadcast_to(1.0 if seg_weight is None else np.asarray(seg_weight, dtype=float),
                             (used, data.segments))
    # Fewer lanes than SPLIT (a single fit of SPLIT_EPOCHS epochs or more): each lane is run
    # as SPLIT lanes over disjoint
    # halves of the segments (weight 0 elsewhere, which the kernel skips) and summed, so the
    # parallel loop over lanes has work for both cores. Always split the same way, serial or
    # parallel, so the result does not depend on the variant.
    split = SPLIT if used < SPLIT and data.epochs >= SPLIT_EPOCHS else 1
    if split > 1:
        part = np.minimum(np.arange(data.segments) * split // data.segments, split - 1)
        weight = np.concatenate([np.where(part == k, weight, 0.0) for k in range(split)])
        x = np.concatenate([x] * split)
        pi = np.concatenate([pi] * split)
    weight = np.ascontiguousarray(weight)
    n_lanes = len(x)
    loglik = np.empty((n_lanes, data.segments))
    first = np.empty((n_lanes, 2, N_HIDDEN))
    accept = np.empty((n_lanes, 2, 3))
    delta = np.empty((n_lanes, 3, 3))
    transitions = np.empty((n_lanes, len(EMOTION_GROUPS), len(EMOTION_VARIABLES), 3, 3))
    observed = np.empty((n_lanes, N_OBSERVATIONS, N_HIDDEN))
    unique = np.empty((n_lanes, 3, 3))
    _fit_kernels.e_step_batch(
        np.ascontiguousarray(_field(x, 'likelihood')),
        np.ascontiguousarray(_field(x, 'p_accept')),
        np.ascontiguousarray(_field(x, 'p_delta')), np.ascontiguousarray(pi),
        np.ascontiguousarray(_chain_matrices(_field(x, 'chains'))), data.group,
        *epoch_kinds(data), data.seg_start, seg_kind, weight, loglik, first, accept, delta,
        transitions, observed, unique,
        work=max(1.0, float(((weight > 0) @ np.diff(data.seg_start)).sum())))
    if split > 1:
        def joined(a):
            return a.reshape((split, used) + a.shape[1:]).sum(axis=0)
        loglik, weight = joined(loglik), joined(weight)
        first, accept, delta, transitions, observed, unique = (
            joined(a) for a in (first, accept, delta, transitions, observed, unique))
    finite = np.isfinite(loglik)
    impossible = np.where(finite.all(axis=1), -1, np.argmax(~finite, axis=1))
    ll = np.einsum('ls,ls->l', np.where(finite, loglik, 0.0), weight)
    return Expected(np.where(impossible < 0, ll, -np.inf), first[:, 0], accept, delta,
                    transitions, observed, unique, first[:, 1]), impossible


def _impossible(data: FitData, segment: int) -> FitError:
    return FitError(f'{data.episodes[data.seg_episode[segment]]} is impossible under the '
                    'parameters held fixed: hold fewer families')


def e_step(params: Params, data: FitData, seg_weight: np.ndarray | None = None) -> Expected:
    """The E-step at `params` (a batch of one); FitError if the data are impossible."""
    stats, impossible = e_step_batch(_pack(params)[None], data, seg_weight)
    if impossible[0] >= 0:
        raise _impossible(data, int(impossible[0]))
    out = stats.lane(0)
    out.loglik = float(out.loglik)
    return out


def emission(params: Params, data: FitData) -> np.ndarray:
    """(T, 9): e_t(h), the evidence of each epoch given h_t (module docstring): the reference
    form of what the kernel computes inline, and with the answer and the move the model's own
    `HRCModel.transition_likelihood` (the tests hold all three equal)."""
    observation = np.vstack([params.likelihood, np.ones(N_HIDDEN)])[data.observation]
    answer = np.stack([np.ones(3), params.p_accept, 1.0 - params.p_accept])[data.answer]
    distance = data.move @ params.p_delta.T                       # (T, ea)
    return observation * (answer[:, :, None] * distance[:, None, :]).reshape(-1, N_HIDDEN)


_TARGET = np.array([[max(i + m - 1, 0) if m < 2 else min(i + 1, 2) for m in range(3)]
                    for i in range(3)])                   # [level i, move m] -> level j
_SAME_TARGET = (_TARGET[:, :, None] == _TARGET[:, None, :]).astype(float)   # [i, m, m']


def _chain_moves(counts: np.ndarray, chain: np.ndarray) -> np.ndarray:
    """Expected (down, stay, up) moves (..., 3) from the level counts C[..., i, j] of a
    bounded chain (..., 3): each count split over the moves that lead i -> j in proportion to
    the chain's current moves."""
    share = np.einsum('imn,...n->...im', _SAME_TARGET, chain)    # moves ending where m does
    counted = counts[..., np.arange(3)[:, None], _TARGET]        # C[i, target(i, m)]
    split = np.where(share > 0, counted * chain[..., None, :] / np.where(share > 0, share, 1.0),
                     0.0)
    return split.sum(axis=-2)


def _normalised(counts: np.ndarray, old: np.ndarray) -> np.ndarray:
    """counts / sum over the last axis; rows without counts keep their old values."""
    total = counts.sum(axis=-1, keepdims=True)
    return np.where(total > 0, counts / np.where(total > 0, total, 1.0), old)


def m_step_batch(stats: Expected, x: np.ndarray, hold: tuple = ()) -> np.ndarray:
    """The closed-form M-step (module docstring) of every lane: packed rows (B, N_PACKED)."""
    new = x.copy()
    _field(new, 'pi')[:] = _normalised(stats.first, _field(x, 'pi'))
    if x.shape[1] == N_PACKED_SPLIT:
        _field(new, 'pi_cut')[:] = _normalised(stats.first_cut, _field(x, 'pi_cut'))
    if 'p_accept' not in hold:
        answered = stats.accept.sum(axis=1)
        _field(new, 'p_accept')[:] = np.where(
            answered > 0, stats.accept[:, 0] / np.where(answered > 0, answered, 1.0),
            _field(x, 'p_accept'))
    if 'p_delta' not in hold:
        _field(new, 'p_delta')[:] = _normalised(stats.delta, _field(x, 'p_delta'))
    chains, new_chains = _field(x, 'chains'), _field(new, 'chains')
    for g in range(len(EMOTION_GROUPS)):
        for v in range(len(EMOTION_VARIABLES)):
            if f'emotion.{EMOTION_GROUPS[g]}.{EMOTION_VARIABLES[v]}' in hold:
                continue
            moves = _chain_moves(stats.transitions[:, g, v], chains[:, g, v])
            new_chains[:, g, v] = _normalised(moves, chains[:, g, v])
    if 'likelihood' not in hold:
        likelihood = _field(x, 'likelihood').swapaxes(1, 2)
        _field(new, 'likelihood')[:] = _normalised(stats.observed.swapaxes(1, 2),
                                                   likelihood).swapaxes(1, 2)
    return new


def m_step(stats: Expected, params: Params, hold: tuple = ()) -> Params:
    """The M-step of one lane (`m_step_batch` on a batch of one)."""
    batch = Expected(*(np.asarray(getattr(stats, f.name))[None] for f in fields(stats)))
    return _unpack(m_step_batch(batch, _pack(params)[None], hold)[0], params)


@dataclass
class EMRun:
    params: Params
    trace: list                 # log likelihood after each iteration (the start's first)
    converged: bool
    stats: Expected | None = None
    e_steps: int = 0

    @property
    def iterations(self) -> int:
        return max(0, len(self.trace) - 1)


def _pack(params: Params) -> np.ndarray:
    """The packed row: `_PARAM_FIELDS` in order, then pi_cut with a split start."""
    names = _PARAM_FIELDS + (('pi_cut',) if params.split_start else ())
    return np.concatenate([np.ravel(getattr(params, f)) for f in names])


def _unpack(vector: np.ndarray, like: Params) -> Params:
    out, at = like.copy(), 0
    for f in _PARAM_FIELDS + (('pi_cut',) if like.split_start else ()):
        shape = getattr(like, f).shape
        size = int(np.prod(shape))
        setattr(out, f, vector[at:at + size].reshape(shape).copy())
        at += size
    return out


def run_em(data: FitData, start: Params, hold: tuple = (), tol: float = TOL,
           max_iter: int = MAX_ITER, seg_weight=None, run: EMRun | None = None,
           method: str = SQUAREM, curvature: 'Curvature | None' = None) -> EMRun:
    """EM from `start` (or continuing `run`) until the log likelihood rises by less than
    `tol` per epoch in an iteration, or after `max_iter` iterations in all: `run_em_batch`
    with one lane."""
    weights = None if seg_weight is None else np.asarray(seg_weight, dtype=float)[None]
    return run_em_batch(data, [start], hold, tol, max_iter, weights,
                        None if run is None else [run], method, curvature=curvature)[0]


def run_em_batch(data: FitData, starts: list, hold: tuple = (), tol: float = TOL,
                 max_iter: int = MAX_ITER, seg_weight=None, runs: list | None = None,
                 method: str = SQUAREM, progress=None, curvature: 'Curvature | None' = None
                 ) -> list:
    """EM for each lane: from `starts[l]` (or continuing `runs[l]`) with segment weights
    `seg_weight[l]` (None: all 1), until its log likelihood rises by less than `tol` per
    epoch in an iteration, or after `max_iter` iterations in all. Returns an `EMRun` per lane.

    The lanes are independent: each follows exactly the steps it would alone; they only share
    the E-step calls (the lanes still running, in one batch).

    `method` `SQUAREM` (the default): an iteration is one SQUAREM cycle (Varadhan and Roland
    2008, scheme S3, with the step control of their SQUAREM package): two EM steps theta1 =
    M(theta0), theta2 = M(theta1); the extrapolation x = theta0 - 2 alpha r + alpha^2 v (r =
    theta1 - theta0, v = theta2 - 2 theta1 + theta0, alpha = -|r| / |v|, at most `step_max`
    in size, halved towards -1 while x leaves the probabilities' domain; alpha = -1 is theta2);
    one EM step from x, kept if its likelihood is not below theta0's, else theta2. `step_max`
    starts at 1, grows 4-fold when alpha reaches it and shrinks 4-fold when an extrapolation
    is refused. So the likelihood never decreases from cycle to cycle, and EM's crawl along flat
    directions (its rate is the share of missing information) is cut several times over.
    `EM`: an iteration is one EM step.

    `NEWTON`: an iteration is one quasi-Newton step on the log likelihood in the log-ratio
    coordinates of `curvature` (a `Curvature`, by default `curvature_at` the first lane's
    start): the gradient from the lane's own E-step counts (Fisher's identity), the inverse
    Hessian starting from `curvature.inverse` (minus the Hessian at the full-data fit: each
    bootstrap resample's is near it) and improved by BFGS updates from the lane's own steps;
    the step maximises the quadratic model within the lane's trust radius (`_trust_steps`:
    Newton's step where it is shorter, else damped Levenberg-Marquardt style, so a flat
    direction whose Newton step is long is cut and the well-curved ones keep theirs; the old
    rule shrank the whole step, and one flat direction held every other to its pace). The
    radius starts at `NEWTON_RADIUS`, is cut to a quarter of the step where the likelihood rose
    by less than a quarter of the model's promise and doubled where the model held
    (`NEWTON_GROW`) at the radius's edge. A step that lowers the likelihood (or makes the
    evidence impossible) is retried with the smaller radius, at most `NEWTON_RETRIES` times;
    then the lane takes EM's step (which never lowers it) and starts again from
    `curvature.inverse`. So the likelihood never decreases, and the fixed points are EM's:
    the points where the gradient is 0. The stopping rule is the same, with one addition: an
    iteration whose step was shorter than the full quasi-Newton step (cut to the radius, or
    EM's) ends the run only if that full step also predicted a rise below `tol` per epoch, or
    after `NEWTON_PATIENCE` iterations in a row below it (a rise that is small only because
    the step was cut is not convergence: it stopped a resample 4.8 log likelihood units below
    its maximum, test_fit).

    The returned parameters' E-step is `stats` (the trace's last entry). `progress(lanes
    done)` is called after every iteration."""
    if method not in METHODS:
        raise ValueError(f'unknown EM method {method!r}; known: {", ".join(METHODS)}')
    n_lanes = len(starts) if runs is None else len(runs)
    weights = None if seg_weight is None else np.asarray(seg_weight, dtype=float)
    lengths = np.diff(data.seg_start)
    n = (np.full(n_lanes, max(1.0, data.epochs)) if weights is None
         else np.maximum(1.0, weights @ lengths))
    like = starts[0] if runs is None else runs[0].params
    x = np.stack([_pack(s) for s in starts] if runs is None
                 else [_pack(r.params) for r in runs])
    traces = [[] for _ in range(n_lanes)] if runs is None else [list(r.trace) for r in runs]
    e_steps = np.zeros(n_lanes, dtype=int) if runs is None else np.array(
        [r.e_steps for r in runs])

    def expect(rows, lanes, guarded=False):
        """The E-step of packed `rows` for `lanes`; impossible evidence is a FitError unless
        `guarded` (then those lanes' log likelihoods are -inf)."""
        e_steps[lanes] += 1
        w = None if weights is None else weights[lanes]
        stats, impossible = e_step_batch(rows, data, w)
        if not guarded and np.any(impossible >= 0):
            raise _impossible(data, int(impossible[impossible >= 0][0]))
        return stats

    if runs is None:
        stats = expect(x, np.arange(n_lanes))
        for lane in range(n_lanes):
            traces[lane].append(float(stats.loglik[lane]))
    else:
        stats = Expected(*(np.stack([np.asarray(getattr(r.stats, f.name)) for r in runs])
                           for f in fields(Expected)))
    converged = np.zeros(n_lanes, dtype=bool)
    stalled = np.zeros(n_lanes, dtype=int)     # iterations in a row that rose by < tol
    step_max = np.ones(n_lanes)
    if method == NEWTON:
        if curvature is None:
            curvature = curvature_at(data, _unpack(x[0], like), hold)
        inverse = np.repeat(curvature.inverse[None], n_lanes, axis=0)
        radius = np.full(n_lanes, NEWTON_RADIUS)
    while True:
        lanes = np.flatnonzero(~converged & (np.array([len(t) for t in traces]) <= max_iter))
        if lanes.size == 0:
            break
        x0, s0 = x[lanes], stats.lane(lanes)
        ahead = np.zeros(len(lanes))
        if method == NEWTON:
            x_new, s_new, ahead = _quasi_newton_step(curvature, inverse, radius, lanes, x0,
                                                     s0, hold, expect)
        else:
            x1 = m_step_batch(s0, x0, hold)
            s1 = expect(x1, lanes)
            x_new, s_new = x1, s1
        if method == SQUAREM:
            x2 = m_step_batch(s1, x1, hold)
            r, v = x1 - x0, x2 - 2 * x1 + x0
            x_new = x2
            # x2's E-step is needed only where x2 is the iteration's end (no extrapolation,
            # or one refused): run after the extrapolations, for those lanes only
            plain = np.ones(len(lanes), dtype=bool)
            ends = None
            norm_r, norm_v = np.linalg.norm(r, axis=1), np.linalg.norm(v, axis=1)
            moving = norm_v > 0
            alpha = np.full(len(lanes), -1.0)
            ratio = -norm_r[moving] / norm_v[moving]
            alpha[moving] = np.maximum(-step_max[lanes][moving], np.minimum(-1.0, ratio))
            grow = moving & (alpha == -step_max[lanes])
            step_max[lanes[grow]] *= 4.0
            xe = x0 - 2 * alpha[:, None] * r + alpha[:, None] ** 2 * v
            while True:
                out = (alpha < -1.0) & ~(np.all(xe >= 0, axis=1) & np.all(xe <= 1, axis=1))
                if not out.any():
                    break
                alpha[out] = np.where(alpha[out] < -1.01,
                                      np.minimum(-1.0, (alpha[out] - 1.0) / 2 + 1e-12), -1.0)
                xe[out] = (x0[out] - 2 * alpha[out, None] * r[out]
                           + alpha[out, None] ** 2 * v[out])
            tried = np.flatnonzero(alpha < -1.0)
            if tried.size:
                se = expect(xe[tried], lanes[tried], guarded=True)
                ok = np.isfinite(se.loglik)
                accepted = np.zeros(tried.size, dtype=bool)
                if ok.any():
                    x3 = m_step_batch(se.lane(np.flatnonzero(ok)), xe[tried[ok]], hold)
                    s3 = expect(x3, lanes[tried[ok]], guarded=True)
                    better = np.isfinite(s3.loglik) & (s3.loglik >= s0.loglik[tried[ok]])
                    accepted[np.flatnonzero(ok)[better]] = True
                    keep = tried[ok][better]
                    x_new = x_new.copy()
                    x_new[keep] = x3[better]
                    plain[keep] = False
                    ends = (keep, s3.lane(np.flatnonzero(better)))
                refused = lanes[tried[~accepted]]
                step_max[refused] = np.maximum(1.0, step_max[refused] / 4.0)
            if plain.all():
                s_new = expect(x2, lanes)
            else:
                s_new = _merged(s0, *ends)
                if plain.any():
                    need = np.flatnonzero(plain)
                    s_new = _merged(s_new, need, expect(x2[need], lanes[need]))
        x[lanes] = x_new
        stats = _merged(stats, lanes, s_new)
        for i, lane in enumerate(lanes):
            traces[lane].append(float(s_new.loglik[i]))
            small = abs(traces[lane][-1] - traces[lane][-2]) < tol * n[lane]
            stalled[lane] = stalled[lane] + 1 if small else 0
            if small and (ahead[i] < tol * n[lane] or stalled[lane] >= NEWTON_PATIENCE):
                converged[lane] = True
        if progress is not None:
            progress(int(np.sum(converged | (np.array([len(t) for t in traces]) > max_iter))))
    return [EMRun(_unpack(x[lane], like), traces[lane], bool(converged[lane]),
                  _single(stats.lane(lane)), int(e_steps[lane])) for lane in range(n_lanes)]


# -- quasi-Newton EM --------------------------------------------------------------------------
@dataclass
class Curvature:
    """The log likelihood's curvature at a fit in the coordinates `NEWTON` moves in: each
    free probability as its log ratio to a reference entry of its distribution (the largest
    at the fit; p_accept: to its complement), entries that are exactly 0 left out (EM keeps
    them 0). `inverse` is the pseudo-inverse of minus the Hessian in those coordinates."""

    index: np.ndarray       # (d,) packed position of each coordinate
    reference: np.ndarray   # (d,) packed position of its reference entry; -1: 1 - x (p_accept)
    rows: list              # per distribution: the packed positions of its entries
    inverse: np.ndarray     # (d, d)

    def coordinates(self, x: np.ndarray) -> np.ndarray:
        """(B, d) log ratios of packed rows x (B, N_PACKED)."""
        ref = np.where(self.reference >= 0, x[:, np.maximum(self.reference, 0)],
                       1.0 - x[:, self.index])
        with np.errstate(divide='ignore'):
            return np.log(x[:, self.index]) - np.log(ref)

    def packed(self, eta: np.ndarray, like: np.ndarray) -> np.ndarray:
        """Packed rows with the coordinates `eta` (B, d) in place of `like`'s free entries."""
        out = like.copy()
        binary = self.reference < 0
        with np.errstate(over='ignore'):    # a far step: exp -> inf, the entry 0, as it should
            out[:, self.index[binary]] = 1.0 / (1.0 + np.exp(-eta[:, binary]))
        for row, members in self.rows:
            top = np.maximum(0.0, eta[:, members].max(axis=1, initial=0.0))
            weight = np.exp(eta[:, members] - top[:, None])
            total = weight.sum(axis=1) + np.exp(-top)
            out[:, row] = 0.0
            out[:, self.reference[members[0]]] = np.exp(-top) / total
            out[:, self.index[members]] = weight / total[:, None]
        return out

    def gradient(self, stats: Expected, x: np.ndarray) -> np.ndarray:
        """(B, d) the log likelihood's gradient in the coordinates at packed rows x, from
        their E-step's counts (Fisher's identity: n_i - N x_i per distribution)."""
        counts = np.zeros_like(x)
        _field(counts, 'pi')[:] = stats.first
        if x.shape[1] == N_PACKED_SPLIT:
            _field(counts, 'pi_cut')[:] = stats.first_cut
        _field(counts, 'p_accept')[:] = stats.accept[:, 0]
        _field(counts, 'p_delta')[:] = stats.delta
        chains = _field(x, 'chains')
        _field(counts, 'chains')[:] = _chain_moves(stats.transitions, chains)
        _field(counts, 'likelihood')[:] = stats.observed
        total = np.zeros_like(x)
        for row, _ in self.rows:
            total[:, row] = counts[:, row].sum(axis=1, keepdims=True)
        accept = _SLICES['p_accept']
        total[:, accept] = stats.accept.sum(axis=1)
        return counts[:, self.index] - total[:, self.index] * x[:, self.index]


CURVATURE_STEP = 1e-4     # central differences of the gradient, in log ratio
CURVATURE_FLOOR = 1e-6    # eigenvalues of -H are raised to at least this share of the largest
NEWTON_RADIUS = 1.0       # a lane's first trust radius (length of a step in log ratios)
NEWTON_RETRIES = 2        # a step that lowers the likelihood is retried this often, then EM
NEWTON_GROW = 0.75        # a step at the radius rising by this share of the model's doubles it
NEWTON_PATIENCE = 3       # iterations in a row below tol that end a run whose model promised more


def curvature_at(data: FitData, params: Params, hold: tuple = ()) -> Curvature:
    """The log likelihood's `Curvature` at `params` (on all of `data`, weights 1): central
    differences of its gradient, every coordinate's two lanes in one batched E-step."""
    x = _pack(params)
    index, reference, rows = [], [], []
    accept = _SLICES['p_accept']
    if 'p_accept' not in hold:
        for i in range(accept.start, accept.stop):
            if 0.0 < x[i] < 1.0:
                index.append(i)
                reference.append(-1)
    distributions = [np.arange(_SLICES['pi'].start, _SLICES['pi'].stop)]
    if params.split_start and not data.true_starts.all():   # pieces cut from episodes
        distributions.append(np.arange(_SLICES['pi_cut'].start, _SLICES['pi_cut'].stop))
    offsets = {name: _SLICES[name].start for name in ('p_delta', 'chains', 'likelihood')}
    if 'p_delta' not in hold:
        distributions += [offsets['p_delta'] + 3 * ea + np.arange(3) for ea in range(3)]
    for g, group in enumerate(EMOTION_GROUPS):
        for v, variable in enumerate(EMOTION_VARIABLES):
            if f'emotion.{group}.{variable}' not in hold:
                distributions.append(offsets['chains'] + 3 * (2 * g + v) + np.arange(3))
    if 'likelihood' not in hold:
        distributions += [offsets['likelihood'] + N_HIDDEN * np.arange(N_OBSERVATIONS) + h
                          for h in range(N_HIDDEN)]
    for row in distributions:
        positive = row[x[row] > 0]
        top = positive[np.argmax(x[positive])]
        members = [i for i in positive if i != top]
        if members:
            rows.append((row, np.arange(len(index), len(index) + len(members))))
            index += members
            reference += [top] * len(members)
    curvature = Curvature(np.array(index, dtype=int), np.array(reference, dtype=int), rows,
                          np.zeros((len(index), len(index))))
    d = len(index)
    if d == 0:
        return curvature
    eta = curvature.coordinates(x[None])[0]
    shifted = eta + CURVATURE_STEP * np.concatenate([np.eye(d), -np.eye(d)])
    lanes = curvature.packed(shifted, np.repeat(x[None], 2 * d, axis=0))
    stats, impossible = e_step_batch(lanes, data)
    if np.any(impossible >= 0):
        raise _impossible(data, int(impossible[impossible >= 0][0]))
    g = curvature.gradient(stats, lanes)
    hessian = (g[:d] - g[d:]).T / (2 * CURVATURE_STEP)
    values, vectors = np.linalg.eigh(-(hessian + hessian.T) / 2)
    values = np.maximum(values, CURVATURE_FLOOR * max(values.max(), 1.0))
    curvature.inverse = (vectors / values) @ vectors.T
    return curvature


def _trust_steps(values: np.ndarray, along: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """The steps (in the eigenbasis of each lane's inverse Hessian: `values` its eigenvalues,
    `along` the gradient's components) that maximise the quadratic model within `radius`:
    the Newton step values * along where it is shorter, else the damped step values / (1 +
    mu values) * along with mu > 0 such that its length is the radius (Levenberg-Marquardt:
    the flat directions, whose Newton step is long, are cut the most; the well-curved ones
    keep their full step)."""
    step = values * along
    over = np.linalg.norm(step, axis=1) > radius
    if not over.any():
        return step
    v, g, r = values[over], along[over], radius[over]

    def length(mu):
        return np.linalg.norm(v / (1.0 + mu[:, None] * v) * g, axis=1)

    low, high = np.zeros(len(r)), np.ones(len(r))
    for _ in range(60):                       # bracket: the length falls towards 0 in mu
        long = length(high) > r
        if not long.any():
            break
        high[long] *= 10.0
    for _ in range(50):                       # bisection to a relative 1e-15 of the bracket
        mid = (low + high) / 2
        long = length(mid) > r
        low, high = np.where(long, mid, low), np.where(long, high, mid)
    step[over] = v / (1.0 + high[:, None] * v) * g
    return step


def _quasi_newton_step(curvature: Curvature, inverse: np.ndarray, radius: np.ndarray,
                       lanes: np.ndarray, x0: np.ndarray, s0: Expected, hold: tuple, expect):
    """One `NEWTON` iteration of `lanes` (see `run_em_batch`); updates `inverse` (the
    lanes' inverse Hessian estimates) and `radius` (their trust radii) in place. Returns the
    new packed rows, their E-steps and, per lane, the rise its full quasi-Newton step
    predicted where the step taken was shorter (cut to the trust radius, or EM's), else 0."""
    n = len(lanes)
    eta0 = curvature.coordinates(x0)
    g0 = curvature.gradient(s0, x0)
    values, vectors = np.linalg.eigh(inverse[lanes])
    values = np.maximum(values, 1e-12 * np.maximum(values.max(axis=1, keepdims=True), 1e-300))
    along = np.einsum('lji,lj->li', vectors, g0)

    predicted = np.einsum('li,li->l', along, values * along) / 2   # the full step's rise
    r = radius[lanes].copy()
    x_new, s_new = x0.copy(), s0
    cut = np.zeros(n, dtype=bool)
    taken = np.zeros(n, dtype=bool)
    pending = np.flatnonzero(predicted > 0)
    for _ in range(NEWTON_RETRIES + 1):
        if pending.size == 0:
            break
        limit = r[pending]
        step = _trust_steps(values[pending], along[pending], limit)
        length = np.linalg.norm(step, axis=1)
        cut[pending] = length < np.linalg.norm(values[pending] * along[pending], axis=1)
        expected = (np.einsum('li,li->l', along[pending], step)
                    - np.einsum('li,li->l', step, step / values[pending]) / 2)
        xt = curvature.packed(eta0[pending] + np.einsum('lij,lj->li', vectors[pending], step),
                              x0[pending])
        st = expect(xt, lanes[pending], guarded=True)
        rise = np.where(np.isfinite(st.loglik), st.loglik - s0.loglik[pending], -np.inf)
        better = rise >= 0
        ratio = np.where(expected > 0, rise / np.maximum(expected, 1e-300), 0.0)
        # the trust radius: cut to a quarter of the step where the model overpromised,
        # doubled where it held at the radius's edge
        r[pending] = np.where(better & (ratio >= 0.25), r[pending], length / 4)
        grow = better & (ratio > NEWTON_GROW) & (length >= 0.99 * limit)
        r[pending[grow]] = 2 * length[grow]
        x_new[pending[better]] = xt[better]
        s_new = _merged(s_new, pending[better], st.lane(np.flatnonzero(better)))
        taken[pending[better]] = True
        pending = pending[~better]
    radius[lanes] = np.maximum(r, NEWTON_RADIUS * 1e-9)
    fallback = np.flatnonzero(~taken)
    if fallback.size:            # EM's step never lowers the likelihood
        xf = m_step_batch(s0.lane(fallback), x0[fallback], hold)
        x_new[fallback] = xf
        s_new = _merged(s_new, fallback, expect(xf, lanes[fallback]))
        inverse[lanes[fallback]] = curvature.inverse
        radius[lanes[fallback]] = NEWTON_RADIUS
    moved = np.flatnonzero(taken)
    if moved.size:               # BFGS on minus the log likelihood
        with np.errstate(invalid='ignore'):   # a probability at 0: -inf - -inf, skipped below
            s = curvature.coordinates(x_new[moved]) - eta0[moved]
            y = g0[moved] - curvature.gradient(s_new.lane(moved), x_new[moved])
            sy = np.einsum('li,li->l', s, y)
        ok = np.isfinite(sy) & (sy > 1e-12 * np.linalg.norm(s, axis=1)
                                * np.linalg.norm(y, axis=1))
        for i in np.flatnonzero(ok):
            h = inverse[lanes[moved[i]]]
            rho = 1.0 / sy[i]
            hy = h @ y[i]
            inverse[lanes[moved[i]]] = (h - rho * (np.outer(s[i], hy) + np.outer(hy, s[i]))
                                        + (rho ** 2 * (y[i] @ hy) + rho)
                                        * np.outer(s[i], s[i]))
    unsettled = cut | ~taken
    return x_new, s_new, np.where(unsettled, np.maximum(predicted, 0.0), 0.0)


def _merged(stats: Expected, lanes: np.ndarray, new: Expected) -> Expected:
    """`stats` with the rows `lanes` replaced by `new`'s."""
    out = []
    for f in fields(Expected):
        values = np.array(getattr(stats, f.name), copy=True)
        values[lanes] = getattr(new, f.name)
        out.append(values)
    return Expected(*out)


def _single(stats: Expected) -> Expected:
    stats.loglik = float(stats.loglik)
    return stats


# -- starts and labels ------------------------------------------------------------------------
def _free(hold: tuple) -> list[str]:
    return [f for f in FAMILIES if f not in hold]


def _smoothed(params: Params, hold: tuple) -> Params:
    """`params` with INIT_FLOOR of uniform mixed into every free family (EM cannot move a
    probability off exactly 0 or 1)."""
    out = params.copy()
    for name in _free(hold):
        values = out.family(name)
        if name == 'p_accept':
            values[:] = (1 - INIT_FLOOR) * values + INIT_FLOOR * 0.5
        elif name == 'likelihood':
            values[:] = (1 - INIT_FLOOR) * values + INIT_FLOOR / N_OBSERVATIONS
        else:
            values[...] = (1 - INIT_FLOOR) * values + INIT_FLOOR / values.shape[-1]
    return out


def _random_start(base: Params, hold: tuple, rng: np.random.Generator) -> Params:
    """Each free family drawn around the (smoothed) base: Dirichlet(c * base + 0.5)."""
    out = _smoothed(base, hold)
    for name in _free(hold):
        values = out.family(name)
        if name == 'p_accept':
            values[:] = rng.beta(INIT_CONCENTRATION * values + 0.5,
                                 INIT_CONCENTRATION * (1 - values) + 0.5)
        elif name == 'likelihood':
            values[:] = np.stack([rng.dirichlet(INIT_CONCENTRATION * values[:, h] + 0.5)
                                  for h in range(N_HIDDEN)], axis=1)
        else:
            rows = values.reshape(-1, 3)
            values[...] = np.stack([rng.dirichlet(INIT_CONCENTRATION * row + 0.5)
                                    for row in rows]).reshape(values.shape)
    return out


def relabel(params: Params, flip_em: bool, flip_ea: bool) -> Params:
    """The same model with em read as 2 - em and/or ea as 2 - ea (the likelihood is equal)."""
    out = params.copy()
    em = np.arange(3)[::-1] if flip_em else np.arange(3)
    ea = np.arange(3)[::-1] if flip_ea else np.arange(3)
    h = (3 * em[:, None] + ea[None, :]).ravel()        # new h -> old h
    out.pi = params.pi[h]
    if params.split_start:
        out.pi_cut = params.pi_cut[h]
    out.likelihood = params.likelihood[:, h]
    if flip_em:
        out.p_accept = params.p_accept[::-1].copy()
        out.chains[:, 0] = params.chains[:, 0, ::-1]
    if flip_ea:
        out.p_delta = params.p_delta[::-1].copy()
        out.chains[:, 1] = params.chains[:, 1, ::-1]
    return out


def canonical_labels(params: Params, base: Params, hold: tuple) -> tuple[Params, str]:
    """Of the relabellings that leave every held family unchanged, the nearest to `base`."""
    best, best_name, best_distance = params, '', math.inf
    for flip_em in (False, True):
        for flip_ea in (False, True):
            candidate = relabel(params, flip_em, flip_ea)
            if any(not np.allclose(candidate.family(f), params.family(f)) for f in hold):
                continue
            distance = float(np.sum((candidate.vector() - base.vector()) ** 2))
            if distance < best_distance - 1e-12:
                name = '+'.join(v for v, f in (('em', flip_em), ('ea', flip_ea)) if f)
                best, best_name, best_distance = candidate, name, distance
    return best, best_name


# -- the fit ----------------------------------------------------------------------------------
@dataclass
class FitResult:
    params: Params
    base: Params
    hold: tuple
    trace: list                    # log likelihood per iteration of the chosen start
    start_logliks: list            # each start's log likelihood after its short run
    chosen_start: int              # 0: the base configuration
    converged: bool
    relabelled: str                # '' or the variables read reversed ('em', 'ea', 'em+ea')
    support: np.ndarray            # (57,) expected informative epochs
    interval: np.ndarray | None    # (2, 57) bootstrap 2.5 and 97.5 percentiles
    samples: np.ndarray | None     # (B, 57) bootstrap estimates
    effective: np.ndarray | None   # (57,) p (1 - p) / bootstrap variance (module docstring)
    warnings: list
    epochs: int
    segments: int
    episodes: int
    rows_read: int
    issues: list
    seconds: dict = field(default_factory=dict)
    min_support: float = MIN_SUPPORT
    sample_logliks: np.ndarray | None = None   # (B,) the log likelihood of each resample's fit
    resample_counts: np.ndarray | None = None  # (B, episodes) how often each resample drew each
    resample_points: np.ndarray | None = None  # (B, N_PACKED) each resample's fit, packed (pi too)
    # with a person prior (`fit(prior=True)`): params.pi is it, written as observation.prior
    prior: bool = False
    prior_base: np.ndarray | None = None       # (9,) the base's prior (uniform if it has none)
    prior_starts: int = 0                      # segments that start an episode at epoch 1
    prior_interval: np.ndarray | None = None   # (2, 9) bootstrap 2.5 and 97.5 percentiles
    prior_samples: np.ndarray | None = None    # (B, 9)
    prior_effective: np.ndarray | None = None  # (9,) p (1 - p) / bootstrap variance
    # NEWTON: the curvature at the estimate that its resamples start from (core.plant reuses it)
    curvature: 'Curvature | None' = None

    @property
    def iterations(self) -> int:
        return max(0, len(self.trace) - 1)

    @property
    def weak(self) -> np.ndarray:
        """(57,) bool: a free parameter below `min_support` in support or effective support."""
        free = ~np.isin(PARAMETER_FAMILIES, self.hold)
        low = self.support < self.min_support
        if self.effective is not None:
            low |= self.effective < self.min_support
        return free & low

    @property
    def loglik(self) -> float:
        return self.trace[-1]

    @property
    def free(self) -> list[str]:
        return _free(self.hold)

    @property
    def prior_weak(self) -> np.ndarray:
        """(9,) bool: a prior entry below `min_support` episode starts or effective events."""
        low = np.full(N_HIDDEN, self.prior_starts < self.min_support)
        if self.prior_effective is not None:
            low |= self.prior_effective < self.min_support
        return low & self.prior


NO_SPREAD_VARIANCE = 1e-18


def effective_support(estimate: np.ndarray, samples: np.ndarray,
                      at_bounds: bool = False) -> np.ndarray:
    """p (1 - p) / var: how many fully observed events would pin each parameter down as well
    as the data do (the bootstrap variance of a binomial share is p (1 - p) / n). With
    `at_bounds`, an estimate at 0 or 1 (p (1 - p) below 1e-12: a person prior's h that no
    episode starts in) reads p as the resamples' mean, so that a share pinned at the bound by
    every resample counts as well determined rather than as 0 events."""
    variance = samples.var(axis=0, ddof=1) if len(samples) > 1 else np.full(samples.shape[1],
                                                                             np.inf)
    share = np.clip(estimate, 0.0, 1.0)
    if at_bounds and len(samples):
        share = np.where(share * (1 - share) < 1e-12,
                         np.clip(samples.mean(axis=0), 0.0, 1.0), share)
    with np.errstate(divide='ignore', invalid='ignore'):
        # a spread at rounding level (sd < 1e-9: the EM's fixed point, not the data) is none
        return np.where(variance > NO_SPREAD_VARIANCE, share * (1 - share) / variance, np.inf)


def support_of(stats: Expected) -> np.ndarray:
    """(57,) expected informative epochs per parameter (module docstring)."""
    out = [stats.accept.sum(axis=0), stats.unique_moves.ravel()]
    leaving = stats.transitions.sum(axis=3)                  # [g, v, level i]
    chain = np.stack([leaving[..., 1] + leaving[..., 2], leaving[..., 1],
                      leaving[..., 0] + leaving[..., 1]], axis=-1)
    out.append(chain.ravel())
    out.append(np.tile(stats.observed.sum(axis=0), N_OBSERVATIONS))
    return np.concatenate(out)


def _listed(names, values, which, family) -> str:
    """'name (value), ...', or 'all N (from a to b)' when the whole family is listed."""
    if np.array_equal(which, family) and which.sum() > 3:
        return (f'all {int(which.sum())} (from {values[which].min():.0f} to '
                f'{values[which].max():.0f})')
    return ', '.join(f'{n} ({v:.0f})' for n, v in zip(names[which], values[which]))


def _warnings(support: np.ndarray, effective: np.ndarray | None, hold: tuple,
              min_support: float, episodes: int, bootstrap: int) -> list[str]:
    """A warning per family with parameters below `min_support` informative epochs, or, with
    a bootstrap, below `min_support` effective events (the data may hold many epochs that say
    little about a parameter when the hidden state is hard to tell)."""
    out = []
    if bootstrap and episodes < 10:
        out.append(f'only {episodes} episode{"s" if episodes != 1 else ""}: bootstrap '
                   'intervals over episodes need more to mean much')
    names = np.array(PARAMETER_NAMES)
    families = np.array(PARAMETER_FAMILIES)
    for family in FAMILIES:
        if family in hold:
            continue
        rows = families == family
        if not np.any(support[rows] > 0):
            out.append(f'{family}: no epoch informs it (for a chain: its actions were never '
                       'taken, or never from a level where a move shows); it keeps its start '
                       'value')
            continue
        weak = rows & (support < min_support)
        if weak.any():
            out.append(f'{family}: poorly supported, fewer than {min_support:g} informative '
                       f'epochs: {_listed(names, support, weak, rows)}')
        if effective is not None:
            vague = rows & (support >= min_support) & (effective < min_support)
            if vague.any():
                out.append(f'{family}: poorly determined, the data weigh less than '
                           f'{min_support:g} observed events (bootstrap): '
                           f'{_listed(names, effective, vague, rows)}')
    return out


def fit(data: FitData, base: Config, hold=(), n_init: int = 4, seed: int = 0,
        tol: float = TOL, max_iter: int = MAX_ITER, bootstrap: int = BOOTSTRAP,
        min_support: float = MIN_SUPPORT, progress=None, method: str = DEFAULT_METHOD,
        prior: bool = False) -> FitResult:
    """EM from `n_init` starts (the base first), then the bootstrap (module docstring).
    `method` `SQUAREM`: the chosen start and every resample by SQUAREM; `NEWTON`: the chosen
    start by SQUAREM, then (if it left any of `max_iter`) the quasi-Newton EM
    (`run_em_batch`) from there with the `curvature_at` the estimate, and every resample by
    the quasi-Newton EM with that curvature. `prior`: fit the person prior (module
    docstring, "The person prior"): pi from the segments that start an episode at epoch 1
    only, starting from the base's `observation.prior` (or uniform), the pieces cut from
    episodes from a nuisance pi_cut; FitError when no segment starts an episode."""
    hold = expand_hold(hold)
    if prior and not data.true_starts.any():
        raise FitError('--prior: no episode in the recordings starts at epoch '
                       f'{FIRST_EPOCH} (each begins mid-run, or its first epoch was left out), '
                       'so nothing shows how a person starts; record from the start of a run, '
                       'or fit without --prior')
    if n_init < 1:
        raise FitError(f'n_init must be >= 1, got {n_init}')
    if bootstrap < 0:
        raise FitError(f'bootstrap must be >= 0, got {bootstrap}')
    if method not in (SQUAREM, NEWTON):
        raise FitError(f'method must be {SQUAREM} or {NEWTON}, got {method!r}')
    say = progress or (lambda message: None)
    t0, cpu0 = time.perf_counter(), time.process_time()
    base_params = Params.from_config(base)
    if prior:
        given = base.observation_prior
        base_params.pi = (np.full(N_HIDDEN, 1.0 / N_HIDDEN) if given is None
                          else given / given.sum())
        base_params.pi_cut = np.full(N_HIDDEN, 1.0 / N_HIDDEN)
    rng = np.random.default_rng(seed)
    starts = [_smoothed(base_params, hold)]
    starts += [_random_start(base_params, hold, rng) for _ in range(n_init - 1)]
    if prior:    # EM cannot move a probability off 0: the base prior mixed with uniform too
        for start in starts:
            start.pi = (1 - INIT_FLOOR) * start.pi + INIT_FLOOR / N_HIDDEN
    runs = run_em_batch(data, starts, hold, tol, min(SHORT_RUN, max_iter), method=EM)
    start_logliks = [r.trace[-1] for r in runs]
    chosen = int(np.argmax(start_logliks))
    say(f'{n_init} start{"s" if n_init > 1 else ""}, log likelihood after {SHORT_RUN} '
        'iterations: ' + ', '.join(f'{v:.3f}' for v in start_logliks)
        + f'; continuing start {chosen}')
    best = runs[chosen]
    if not best.converged:
        best = run_em(data, best.params, hold, tol, max_iter, run=best)
    params, relabelled = canonical_labels(best.params, base_params, hold)
    stats = e_step(params, data)
    curvature = None
    if method == NEWTON:
        curvature = curvature_at(data, params, hold)
        if len(best.trace) <= max_iter:   # else SQUAREM used every iteration: its fit stands
            best = run_em(data, params, hold, tol, max_iter, method=NEWTON,
                          curvature=curvature,
                          run=dataclasses.replace(best, params=params, stats=stats))
            params, stats = best.params, best.stats
    support = support_of(stats)
    seconds = {'fit': time.perf_counter() - t0, 'fit_cpu': time.process_time() - cpu0}
    say(f'EM: {best.iterations} iterations, log likelihood {best.trace[-1]:.4f}'
        f'{"" if best.converged else " (not converged)"}; {seconds["fit"]:.2f} s')
    interval = samples = effective = sample_logliks = counts = points = None
    prior_samples = prior_interval = prior_effective = None
    if bootstrap:
        t1 = time.perf_counter()
        n_episodes = len(data.episodes)
        counts = np.stack([rng.multinomial(n_episodes, np.full(n_episodes, 1.0 / n_episodes))
                           for _ in range(bootstrap)]).astype(np.int32)
        weights = counts[:, data.seg_episode].astype(float)
        step = max(1, bootstrap // 10)
        shown = [0]
        say(f'bootstrap: {bootstrap} resamples of the {n_episodes} episodes from the estimate, '
            f'side by side ({method}); each line: resamples done')

        def show(done):
            if done // step > shown[0] // step:
                shown[0] = done
                say(f'bootstrap {done}/{bootstrap} ({time.perf_counter() - t1:.1f} s)')
        runs = run_em_batch(data, [params] * bootstrap, hold, tol, max_iter, weights,
                            method=method, progress=show,
                            curvature=curvature)
        samples = np.stack([run.params.vector() for run in runs])
        sample_logliks = np.array([run.trace[-1] for run in runs])
        points = np.stack([_pack(run.params) for run in runs])
        interval = np.percentile(samples, [2.5, 97.5], axis=0)
        effective = effective_support(params.vector(), samples)
        if prior:
            prior_samples = np.stack([run.params.pi for run in runs])
            prior_interval = np.percentile(prior_samples, [2.5, 97.5], axis=0)
            prior_effective = effective_support(params.pi, prior_samples, at_bounds=True)
        seconds['bootstrap'] = time.perf_counter() - t1
    warnings = _warnings(support, effective, hold, min_support, len(data.episodes), bootstrap)
    prior_starts = int(data.true_starts.sum())
    if prior:
        warnings += _prior_warnings(prior_starts, prior_effective, min_support)
    if 'likelihood' not in hold:
        warnings += [f'no epoch observed O={o + 1}: the configuration gives it P(O | h) = '
                     f'{UNSEEN_FLOOR:g} for every h so that a filter can take it'
                     for o in np.flatnonzero(stats.observed.sum(axis=1) == 0)]
    return FitResult(params, base_params, hold, best.trace, start_logliks, chosen,
                     best.converged, relabelled, support, interval, samples, effective,
                     warnings,
                     data.epochs, data.segments, len(data.episodes), data.rows_read,
                     data.issues, seconds, min_support, sample_logliks, counts, points,
                     prior, base_params.pi.copy() if prior else None, prior_starts,
                     prior_interval, prior_samples, prior_effective, curvature)


def _prior_warnings(starts: int, effective, min_support: float) -> list[str]:
    """The person prior's warnings: few episode starts, entries the bootstrap says little
    about."""
    out = []
    if starts < min_support:
        out.append(f'observation.prior: poorly supported, only {starts} episode'
                   f'{"s" if starts != 1 else ""} start at epoch {FIRST_EPOCH} (fewer than '
                   f'{min_support:g})')
    if effective is not None:
        vague = (effective < min_support) & (starts >= min_support)
        if vague.any():
            names = np.array([f'prior[h={h}]' for h in range(N_HIDDEN)])
            out.append(f'observation.prior: poorly determined, the data weigh less than '
                       f'{min_support:g} observed events (bootstrap): '
                       f'{_listed(names, effective, vague, np.ones(N_HIDDEN, dtype=bool))}')
    return out


def with_bootstrap(result: FitResult, samples: np.ndarray,
                   prior_samples: np.ndarray | None = None) -> FitResult:
    """`result` (a fit without the bootstrap) with the intervals, effective support and
    warnings of bootstrap estimates `samples` (B, 57) made elsewhere, by `fit`'s rules: for
    a scheduler that runs the resamples as separate tasks (core.plant). With a person prior
    (`result.prior`), `prior_samples` (B, 9) are the resamples' priors (their `pi`): its
    interval, effective support and warnings likewise."""
    samples = np.asarray(samples, dtype=float)
    interval = np.percentile(samples, [2.5, 97.5], axis=0)
    effective = effective_support(result.params.vector(), samples)
    unseen = [w for w in result.warnings if w.startswith('no epoch observed O=')]
    warnings = _warnings(result.support, effective, result.hold, result.min_support,
                         result.episodes, len(samples))
    prior = {}
    if result.prior:
        if prior_samples is None:
            raise ValueError('a fit with a person prior needs the resamples\' priors')
        prior_samples = np.asarray(prior_samples, dtype=float)
        prior_effective = effective_support(result.params.pi, prior_samples, at_bounds=True)
        prior = dict(prior_samples=prior_samples, prior_effective=prior_effective,
                     prior_interval=np.percentile(prior_samples, [2.5, 97.5], axis=0))
        warnings += _prior_warnings(result.prior_starts, prior_effective, result.min_support)
    return dataclasses.replace(result, interval=interval, samples=samples, effective=effective,
                               warnings=warnings + unseen, **prior)


# -- outputs ----------------------------------------------------------------------------------
def _row(values, digits: int = 6) -> list[float]:
    """Rounded for a readable file, still a distribution (the largest entry takes the rest)."""
    r = np.round(np.asarray(values, dtype=float), digits)
    r[int(np.argmax(r))] += 1.0 - r.sum()
    return [float(round(v, 12)) for v in r]


def fitted_data(result: FitResult, base: Config) -> dict:
    """The base configuration's data with the fitted families in place."""
    data = copy.deepcopy(base.data)
    p = result.params
    model = data['model']
    if 'p_accept' in result.free:
        model['p_accept'] = [float(round(v, 6)) for v in p.p_accept]
    if 'p_delta' in result.free:
        model['p_delta'] = [_row(row) for row in p.p_delta]
    for g, group in enumerate(EMOTION_GROUPS):
        for v, variable in enumerate(EMOTION_VARIABLES):
            if f'emotion.{group}.{variable}' in result.free:
                model['emotion'][group][variable] = _row(p.chains[g, v])
    if 'likelihood' in result.free:
        likelihood = p.likelihood.copy()
        unseen = ~np.any(likelihood > 0, axis=1)
        if unseen.any():    # a filter must be able to take every level: a floor, renormalised
            likelihood[unseen] = UNSEEN_FLOOR
            likelihood /= likelihood.sum(axis=0, keepdims=True)
        columns = [_row(likelihood[:, h], digits=7) for h in range(N_HIDDEN)]
        data['observation']['likelihood'] = [[columns[h][o] for h in range(N_HIDDEN)]
                                             for o in range(N_OBSERVATIONS)]
    if result.prior:
        data['observation']['prior'] = _row(p.pi)
    return validate(data)


def _yaml_lines(value, indent: int = 0) -> list[str]:
    """A configuration mapping as block YAML with each list of numbers on one line."""
    def scalar(v) -> str:
        return yaml.safe_dump(v, default_flow_style=True, width=10 ** 6).strip().removesuffix(
            '\n...').removesuffix('...').strip()
    pad = ' ' * indent
    lines = []
    for key, v in value.items():
        if isinstance(v, dict):
            lines.append(f'{pad}{key}:')
            lines += _yaml_lines(v, indent + 2)
        elif isinstance(v, list) and v and isinstance(v[0], list):
            lines.append(f'{pad}{key}:')
            lines += [f'{pad}  - {scalar(row)}' for row in v]
        else:
            lines.append(f'{pad}{key}: {scalar(v)}')
    return lines


def config_yaml(result: FitResult, base: Config, sources, stream=None, rate=None) -> str:
    """The fitted configuration as a complete YAML file with a header saying what it is;
    with `stream` (a `stream.StreamFit` or `QueueStreamFit`) its `stream` section is the
    fitted one, with `rate` (a `rate.RateFit`) its model.robot_rate."""
    import textwrap
    data = fitted_data(result, base)
    if stream is not None:
        data['stream'] = stream.section()
    if rate is not None:
        data['model']['robot_rate'] = rate.section()
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec='seconds')
    sources = [str(s) for s in sources]
    header = [
        f'hrc_ros model configuration fitted by hrc-fit on {now} (docs/LEARNING.md) from '
        f'{len(sources)} input(s): {", ".join(sources)}.',
        f'{result.epochs} epochs in {result.episodes} episode(s) ({result.segments} segment(s); '
        f'{len(result.issues)} rows or transitions left out, see the report).',
        f'Base configuration: {base.source}. Fitted: '
        f'{", ".join(result.free + (["observation.prior"] if result.prior else [])) or "none"}. '
        f'Held at the base values: {", ".join(result.hold) or "none"}.',
        f'EM: {result.iterations} iterations, log likelihood {result.loglik:.4f}'
        f'{"" if result.converged else " (NOT converged)"}, start {result.chosen_start} of '
        f'{len(result.start_logliks)} (0 = the base); {len(result.warnings)} warning(s) in the '
        'report.',
        "Everything else (rho, sigma, cost, solver, observation table, epsilon, mode) is the "
        "base's. Solve it before use: hrc-solve --config <this file> -o <policy.npz>",
    ]
    for counted in (stream, rate):
        if counted is not None:
            header.insert(-1, counted.header())
    lines = [f'# {line}' for paragraph in header
             for line in textwrap.wrap(paragraph, 97, break_on_hyphens=False)]
    return '\n'.join(lines + [''] + _yaml_lines(data)) + '\n'


def _fmt(v: float) -> str:
    return f'{v:.4f}'


def report_text(result: FitResult, trace_every: int = 10) -> str:
    p = result.params.vector()
    b = result.base.vector()
    lines = [f'{"parameter":<30}{"fitted":>9}{"base":>9}{"95% interval":>20}{"support":>10}'
             f'{"effective":>11}']
    lines.append('-' * len(lines[0]))
    families = PARAMETER_FAMILIES
    weak = result.weak
    for i, name in enumerate(PARAMETER_NAMES):
        if families[i] in result.hold:
            interval = 'held'
        elif result.interval is None:
            interval = '-'
        else:
            interval = f'[{_fmt(result.interval[0, i])}, {_fmt(result.interval[1, i])}]'
        flag = '  !' if weak[i] else ''
        effective = ('' if result.effective is None or families[i] in result.hold
                     else 'no spread' if not np.isfinite(result.effective[i])
                     else f'{result.effective[i]:.0f}')
        lines.append(f'{name:<30}{_fmt(p[i]):>9}{_fmt(b[i]):>9}{interval:>20}'
                     f'{result.support[i]:>10.0f}{effective:>11}{flag}')
    if result.prior:
        for h, name in enumerate(PRIOR_NAMES):
            interval = ('-' if result.prior_interval is None else
                        f'[{_fmt(result.prior_interval[0, h])}, '
                        f'{_fmt(result.prior_interval[1, h])}]')
            effective = ('' if result.prior_effective is None
                         else 'no spread' if not np.isfinite(result.prior_effective[h])
                         else f'{result.prior_effective[h]:.0f}')
            flag = '  !' if result.prior_weak[h] else ''
            lines.append(f'{name:<30}{_fmt(result.params.pi[h]):>9}'
                         f'{_fmt(result.prior_base[h]):>9}{interval:>20}'
                         f'{result.prior_starts:>10}{effective:>11}{flag}')
    trace = result.trace
    shown = [(i, v) for i, v in enumerate(trace) if i % trace_every == 0 or i == len(trace) - 1]
    if result.prior:
        cut = result.segments - result.prior_starts
        start = [f'observation.prior (the person prior, h = 3*em + ea) from the '
                 f'{result.prior_starts} episode starts at epoch {FIRST_EPOCH}; '
                 + (f'the {cut} pieces cut from episodes or recorded from mid-run start from '
                    'their own distribution (nuisance, not in the configuration): '
                    + ' '.join(f'{v:.3f}' for v in result.params.pi_cut) if cut else
                    'no piece cut from an episode')]
    else:
        start = ['initial hidden state (nuisance, not in the configuration): '
                 + ' '.join(f'{v:.3f}' for v in result.params.pi)]
    lines += [''] + start + [
              'log likelihood by iteration: '
              + ', '.join(f'{i}: {v:.4f}' for i, v in shown),
              f'{result.iterations} EM iterations '
              f'({"converged" if result.converged else "NOT converged"}), '
              f'start {result.chosen_start} of {len(result.start_logliks)} '
              f'(0 = the base; after the short runs: '
              + ', '.join(f'{v:.3f}' for v in result.start_logliks) + ')'
              + (f'; labels read reversed for {result.relabelled} to match the base'
                 if result.relabelled else ''),
              f'epochs used {result.epochs} of {result.rows_read} read, {result.episodes} '
              f'episodes, {result.segments} segments']
    if result.interval is not None:
        lines.append(f'bootstrap: {len(result.samples)} resamples of the episodes')
    if result.issues:
        lines.append(f'left out or cut ({len(result.issues)}):')
        lines += [f'  {m}' for m in result.issues[:20]]
        if len(result.issues) > 20:
            lines.append(f'  ... and {len(result.issues) - 20} more (all in the JSON report)')
    for w in result.warnings:
        lines.append(f'warning: {w}')
    return '\n'.join(lines)


def report_dict(result: FitResult) -> dict:
    p = result.params.vector()
    b = result.base.vector()
    parameters = []
    for i, name in enumerate(PARAMETER_NAMES):
        held = PARAMETER_FAMILIES[i] in result.hold
        parameters.append({
            'name': name, 'family': PARAMETER_FAMILIES[i], 'fitted': float(p[i]),
            'base': float(b[i]), 'held': held, 'support': float(result.support[i]),
            'effective_support': None if held or result.effective is None
            else float(min(result.effective[i], 1e12)),
            'ci95': None if held or result.interval is None
            else [float(result.interval[0, i]), float(result.interval[1, i])]})
    extra = {}
    if result.prior:
        for h, name in enumerate(PRIOR_NAMES):
            parameters.append({
                'name': name, 'family': 'observation.prior',
                'fitted': float(result.params.pi[h]), 'base': float(result.prior_base[h]),
                'held': False, 'support': float(result.prior_starts),
                'effective_support': None if result.prior_effective is None
                else float(min(result.prior_effective[h], 1e12)),
                'ci95': None if result.prior_interval is None
                else [float(result.prior_interval[0, h]), float(result.prior_interval[1, h])]})
        extra = {'prior': _row(result.params.pi), 'prior_episode_starts': result.prior_starts,
                 'cut_initial_state': result.params.pi_cut.tolist()}
    return {'parameters': parameters, 'initial_hidden_state': result.params.pi.tolist(),
            **extra, 'loglik_trace': list(result.trace), 'iterations': result.iterations,
            'converged': result.converged, 'start_logliks': result.start_logliks,
            'chosen_start': result.chosen_start, 'relabelled': result.relabelled,
            'hold': list(result.hold), 'epochs': result.epochs,
            'rows_read': result.rows_read, 'episodes': result.episodes,
            'segments': result.segments, 'bootstrap': 0 if result.samples is None
            else len(result.samples), 'issues': result.issues, 'warnings': result.warnings,
            'seconds': result.seconds}
