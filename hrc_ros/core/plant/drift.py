"""Drift: are a cell's recent recordings explained worse by the running model than by a refit?

The recent recordings W are the last `window` epochs of the cell's recordings (an episode that
straddles the window's start is kept from there; every segment starts from the fitted initial
distribution, as in the fit). Under the running configuration theta_0 the fit's likelihood
(core.learning.fit: the input-output HMM over h = 3*em + ea, the actions as inputs) gives

    Lambda = 2 [ max_{theta, pi} l(theta, pi; W) - max_pi l(theta_0, pi; W) ]  >= 0,

the likelihood ratio of "some model of the same form" against "the running model", with the
initial distribution pi a nuisance fitted under both (the configuration has none). The first
maximum is `fit` from theta_0 (one start, no bootstrap), the second EM over pi alone (every
family held); Lambda is floored at 0, as theta_0 lies inside the alternative.

Calibration by simulation. The chi-square reference (39 free parameters) does not hold for an
HMM: parameters on the boundary, hidden states that are hard to tell apart and EM's local
maxima all move the distribution, and how much depends on the design. So the null
distribution is simulated under the running model itself: `simulations` recordings with W's
design (the same segments, the same actions, the same epochs carrying an observation, an
answer and a known move; the distance d_k as recorded) and the human drawn from
(theta_0, pi_0): h at each segment start from pi_0 (the fitted nuisance), h_{k+1} from the
emotion chain of a_k's group, O_k from P(O | h_k), the answer from p_accept[em_k], the move
from p_delta[ea_k] (its evidence is which Deltas give the same next d as the drawn one). Each
simulated recording gets the same statistic, computed the same way (the same EM tolerances and
caps, so what they do to Lambda is in the reference too), and

    p = (1 + #{b: Lambda_b >= Lambda}) / (1 + simulations),

the Monte Carlo p-value, exact in level for any number of simulations (a test at alpha rejects
with probability at most alpha under theta_0, when the design is held as given). Drift is
p < alpha. Recordings that are impossible under theta_0 (a move, an answer or an observation to
which it gives probability 0) have Lambda = inf and p = 0. The simulation holds the recorded
actions fixed although the policy chose them from what it saw: the test conditions on them,
which is the usual treatment of the inputs of an input-output model; the false-alarm rate on
recordings made by the running policy in closed loop is measured in bench/fleet_bench.py and
written in docs/FLEET.md.

Drift alone never changes a policy: it starts the cell's fit, solve and shadow check
(core.plant.pipeline), and the promotion rule decides.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..config import Config
from ..learning.fit import EM, FAMILIES, FitData, FitError, Params, fit, run_em
from ..model import N_HIDDEN, N_OBSERVATIONS

NO_OBSERVATION = N_OBSERVATIONS          # FitData.observation's "none"
NO_ANSWER, ACCEPTED, REFUSED = 0, 1, 2   # FitData.answer


@dataclasses.dataclass(frozen=True)
class Statistic:
    """The likelihood ratio of one recording and what it took."""

    lr: float                  # Lambda (inf when W is impossible under theta_0)
    loglik_running: float      # max over pi of l(theta_0, pi)
    loglik_refit: float        # max of l(theta, pi)
    pi_running: np.ndarray     # pi_0, the initial distribution fitted under theta_0
    impossible: str = ''       # why W is impossible under theta_0, if it is


def statistic(data: FitData, running: Config, tol: float = 1e-6, max_iter: int = 200,
              params: Params | None = None) -> Statistic:
    """Lambda of `data` against the configuration `running` (module docstring)."""
    theta0 = params if params is not None else Params.from_config(running)
    start = theta0.copy()
    start.pi = np.full(N_HIDDEN, 1.0 / N_HIDDEN)
    try:
        null = run_em(data, start, FAMILIES, tol, max_iter, method=EM)
    except FitError as exc:
        return Statistic(math.inf, -math.inf, math.nan, start.pi, str(exc))
    loglik0 = null.trace[-1]
    refit = fit(data, running, (), n_init=1, tol=tol, max_iter=max_iter, bootstrap=0)
    loglik1 = max(refit.loglik, loglik0)
    return Statistic(2.0 * (loglik1 - loglik0), loglik0, loglik1, null.params.pi.copy())


def simulate(data: FitData, params: Params, pi: np.ndarray, rng: np.random.Generator,
             pi_cut: np.ndarray | None = None) -> FitData:
    """A recording with the design of `data` and the human drawn from (params, pi); with
    `pi_cut` (a fit with a person prior) the segments that do not start an episode
    (`FitData.true_starts`) start from it instead."""
    emotion = params.emotion_matrices()                      # (3, 9, 9)
    emotion_cdf = np.cumsum(emotion, axis=2)
    observation_cdf = np.cumsum(params.likelihood, axis=0)   # (3, 9) over O
    delta_cdf = np.cumsum(params.p_delta, axis=1)
    pi_cdfs = [np.cumsum(pi), np.cumsum(pi if pi_cut is None else pi_cut)]
    epochs = data.epochs
    starts = np.zeros(epochs, dtype=bool)
    starts[data.seg_start[:-1]] = True
    kind = np.zeros(epochs, dtype=np.int64)     # which start distribution each segment has
    if pi_cut is not None:
        kind[data.seg_start[:-1]] = np.where(data.true_starts, 0, 1)
    u = rng.random((epochs, 5))
    h = np.empty(epochs, dtype=np.int64)
    for t in range(epochs):
        if starts[t]:
            pi_cdf = pi_cdfs[kind[t]]
            h[t] = min(int(np.searchsorted(pi_cdf, u[t, 0] * pi_cdf[-1], side='right')),
                       N_HIDDEN - 1)
        else:
            row = emotion_cdf[data.group[t - 1], h[t - 1]]
            h[t] = min(int(np.searchsorted(row, u[t, 0] * row[-1], side='right')),
                       N_HIDDEN - 1)
    em, ea = h // 3, h % 3
    column = observation_cdf[:, h]                           # (3, T)
    drawn_o = np.minimum((u[:, 1][None, :] * column[-1] > column).sum(axis=0),
                         N_OBSERVATIONS - 1)
    observation = np.where(data.observation < NO_OBSERVATION, drawn_o, NO_OBSERVATION)
    accepted = u[:, 2] < params.p_accept[em]
    answer = np.where(data.answer != NO_ANSWER, np.where(accepted, ACCEPTED, REFUSED),
                      NO_ANSWER)
    cdf = delta_cdf[ea]                                      # (T, 3)
    delta = np.minimum((u[:, 3][:, None] * cdf[:, -1:] > cdf).sum(axis=1), 2)
    unique = data.unique_delta.astype(bool)
    # the Deltas that give the drawn one's next d: itself if it is told apart from both
    # others, else every Delta that is not (the classes a move of d splits the three into)
    drawn_unique = unique[np.arange(epochs), delta]
    same_class = np.where(drawn_unique[:, None], np.arange(3)[None, :] == delta[:, None],
                          ~unique)
    move = np.where(data.has_move[:, None], same_class, True).astype(data.move.dtype)
    return dataclasses.replace(
        data, observation=np.ascontiguousarray(observation.astype(data.observation.dtype)),
        answer=np.ascontiguousarray(answer.astype(data.answer.dtype)),
        move=np.ascontiguousarray(move))


def null_statistics(data: FitData, running: Config, pi: np.ndarray, seeds,
                    tol: float = 1e-6, max_iter: int = 200) -> list[float]:
    """Lambda of one simulated recording per seed (module docstring)."""
    theta0 = Params.from_config(running)
    out = []
    for seed in seeds:
        simulated = simulate(data, theta0, pi, np.random.default_rng(seed))
        out.append(statistic(simulated, running, tol, max_iter, params=theta0).lr)
    return out


def p_value(observed: float, null) -> float:
    """The Monte Carlo p-value (1 + #{null >= observed}) / (1 + len(null))."""
    null = np.asarray(null, dtype=float)
    if math.isinf(observed) and observed > 0:
        return 0.0
    return float((1 + np.count_nonzero(null >= observed)) / (1 + null.size))


def describe(d: dict) -> str:
    """The drift test's result in words, as the report states it: the epochs it tested
    against the window asked for (a cell with fewer recorded epochs is tested on all of
    them), and p as the fraction it is, with where it stands against alpha (p equal to alpha
    is no drift: the test calls drift for p < alpha only)."""
    n = d['simulations']
    if d.get('impossible'):
        return (f'the recordings\' last {d["window_epochs"]} epochs are impossible under the '
                f'running model ({d["impossible"]}): p = 0, drift')
    above = round(d['p'] * (n + 1)) - 1          # simulations at or above the statistic
    p = f'p = {d["p"]:.3f} (= {above + 1}/{n + 1}: {above} of {n} simulations at or above it)'
    if d['p'] < d['alpha']:
        verdict = f'below alpha {d["alpha"]:g}: drift'
    elif math.isclose(d['p'], d['alpha'], rel_tol=1e-9, abs_tol=1e-12):
        verdict = (f'exactly alpha {d["alpha"]:g}, not below it: no drift (drift is p < alpha; '
                   f'p moves in steps of {1 / (n + 1):.3g})')
    else:
        verdict = f'not below alpha {d["alpha"]:g}: no drift'
    window = d.get('window')
    epochs = (f'the last {d["window_epochs"]} epochs' if window is None
              or d['window_epochs'] >= window else
              f'all {d["window_epochs"]} recorded epochs (fewer than the window of {window})')
    median = '' if d.get('null_median') is None else f', their median {d["null_median"]:.2f}'
    return (f'likelihood ratio {d["statistic"]:.2f} over {epochs}, {p}, {verdict} '
            f'({n} simulations under the running model{median})')
