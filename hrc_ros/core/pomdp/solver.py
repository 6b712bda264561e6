"""Planning over the belief: a point-based solver for the mixed-observability HRC POMDP.

The cell's state is s = (h, x): the hidden emotions h = 3*em + ea (9 values) and the observable
part x = (y, d) (task/activity part y, distance d). Only h is hidden, so the belief is a vector
over 9 values for the observed x, and the value function is one convex piecewise-linear function
per x: V(x, b) = max_{alpha in Gamma(x)} alpha . b (a mixed-observability MDP, Ong et al. 2010).

One epoch under action a (MODEL.md 3), as the POMDP sees it:

- the observable part moves x -> x' with P(x' | x, h, a): acceptance of an eligible request
  with p_accept[em], the distance step with p_delta[ea], the task step deterministic given
  those. So x' is evidence about h *before* the emotion step: l_{x'}(h) = P(x' | x, h, a);
- h moves by the emotion chain of the action's group g, E_g[h, h'], and O' is drawn from
  P(O' | h') = L[O', h'] (the belief filter's `likelihood`, Table 5 read by Bayes' rule).

The exact posterior after (a, x', O') is therefore

    b'(h') ∝ L[O', h'] sum_h b(h) l_{x'}(h) E_g[h, h'],

which uses the acceptance and the distance move as well as O'. `BeliefFilter` computes exactly
this when it is given the observable transition (`BeliefFilter.update(..., evidence=...)` with
`transition_evidence`; docs/POMDP.md says where the running system does so).

Solver family: **point-based value iteration with Perseus's improvement rule over a gathered
belief set, bracketed by an upper bound** (`solve_pomdp`). Why this family: the observable part
the task book can produce is small (149 task states x 4 distances at full size, `hrc_pomdp`
computes the closure) while the evaluation visits beliefs all over it, so a fixed, broad belief
set backed up in full sweeps (PBVI) serves the whole policy rather than one start (HSVI and
SARSOP spend their effort on the beliefs reachable from one initial belief); every point is
backed up in each sweep, in parallel (numba), and a point keeps its old vector when the new one
is worse (Perseus), so the lower bound never decreases at any point. The belief set is gathered
where the cell goes: simulated episodes (the case study's start and random task streams with
new tasks entering an idle cell, as `hrc-evaluate` runs them) with the exact posterior, acting
by the current bound's policy with some random actions, plus the 9 corners, the Table 5 rows
and the filter's first beliefs at every x; then more points from episodes run with the solved
policy (PBVI's belief expansion), and solved again from the current vectors.

Bounds. The lower bound starts from the blind policies (always a, dn where a is not
available) and only ever holds vectors that are values of executable conditional plans, so
max alpha.b <= V*(x, b). The upper bound is the fast informed bound (Hauskrecht 2000),

    Q_fib(x, a, h) = r(x, a, h) + gamma sum_{x', O'} max_a' sum_h' P(x', h', O' | x, h, a)
                     Q_fib(x', a', h'),

iterated from the MDP's Q (each iterate is an upper bound), tightened at the belief points by
sawtooth interpolation (Hauskrecht 2000; Smith and Simmons 2005) of point-wise backed-up
values, U(x, b) = min(FIB(x, b), sawtooth(x, b)). The solve reports U - L at the case study's
first beliefs and over the belief set.

Vectorised numpy builds the structure; the backups are numba kernels (`_pomdp_kernels`).
The transition pieces come from `solver.FactoredBellman` (task maps, acceptance, costs) and
`HRCModel` (distance matrices, availability), so the POMDP and the MDP are one model: over the
solved x the MDP Q of this module equals `FactoredBellman.q` (a test holds them equal).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import _kernels as kernels
from .belief import BeliefFilter
from ..config import EMOTION_GROUPS
from ..model import (ACTION_EMOTION_GROUP, ACTIONS, CT, DM, DN, DP, N_DISTANCE, N_HIDDEN, RH1, RH2,
                     SAFETY_ORDER, TASK_VARIABLES, HRCModel, entering_task, safest_best,
                     safest_best_one, tie_floor)
from ..mdp.solver import FactoredBellman


@dataclass(frozen=True)
class MixedPOMDP:
    """A POMDP over (x observed, h hidden), in arrays.

    X observable states, A actions, H hidden values, K successors at most, G action groups,
    O observations. `succ_x[x, a, k]` is the k-th possible x' (-1 pads) and
    `succ_l[x, a, k, h] = P(x'_k | x, h, a)` (sums to 1 over k); `kernel[g, o, h, h'] =
    P(h', o | h)` under group g; `reward[x, a, h]` = -cost; `available[x, a]`; `group[a]`;
    `order`: the actions in tie order (the first wins a tie).
    """

    succ_x: np.ndarray
    succ_l: np.ndarray
    reward: np.ndarray
    available: np.ndarray
    group: np.ndarray
    kernel: np.ndarray
    gamma: float
    order: np.ndarray

    def __post_init__(self):
        n_x, n_a, n_k = self.succ_x.shape
        if self.succ_l.shape[:3] != (n_x, n_a, n_k) or self.reward.shape != (
                n_x, n_a, self.n_hidden):
            raise ValueError('succ_x, succ_l and reward disagree in shape')
        if not np.all(self.available.any(axis=1)):
            raise ValueError('every observable state needs an available action')
        total = np.where(self.succ_x >= 0, 1, 0)[..., None] * self.succ_l
        ok = np.abs(total.sum(axis=2) - 1.0) < 1e-9
        if not np.all(ok | ~self.available[..., None]):
            raise ValueError('P(x\' | x, h, a) must sum to 1 over the successors')
        if not np.allclose(self.kernel.sum(axis=(1, 3)), 1.0, atol=1e-9):
            raise ValueError('kernel[g] must be a distribution over (o, h\') for every h')

    @property
    def n_x(self) -> int:
        return self.succ_x.shape[0]

    @property
    def n_actions(self) -> int:
        return self.succ_x.shape[1]

    @property
    def n_hidden(self) -> int:
        return self.succ_l.shape[3]

    @property
    def hidden_transition(self) -> np.ndarray:
        """E_g[h, h'] = sum_o kernel[g, o, h, h'], shape (G, H, H)."""
        return self.kernel.sum(axis=1)

    def expected_next(self, value: np.ndarray) -> np.ndarray:
        """sum_k l_k(h) sum_h' E_g[h, h'] value[x'_k, h'] for every (x, a, h): (X, A, H)."""
        e = self.hidden_transition[self.group]                     # (A, H, H)
        stepped = np.einsum('ahk,xk->xah', e, value)                # value after the h step
        nxt = np.maximum(self.succ_x, 0)
        a_index = np.arange(self.n_actions)[None, :, None]
        gathered = stepped[nxt, a_index, :]                         # (X, A, K, H)
        gathered = np.where((self.succ_x >= 0)[..., None], gathered, 0.0)
        return np.einsum('xakh,xakh->xah', self.succ_l, gathered)

    def successor_belief(self, x: int, b: np.ndarray, a: int):
        """[(x'_k, o, P(x'_k, o | b), b')] after action a from (x, b): the exact posterior."""
        out = []
        g = self.group[a]
        for k in range(self.succ_x.shape[2]):
            xn = int(self.succ_x[x, a, k])
            if xn < 0:
                break
            bl = b * self.succ_l[x, a, k]
            for o in range(self.kernel.shape[1]):
                nb = bl @ self.kernel[g, o]
                p = float(nb.sum())
                if p > 0.0:
                    out.append((xn, o, p, nb / p))
        return out


# -- the HRC cell as a MixedPOMDP ---------------------------------------------------------------
@dataclass(frozen=True)
class HRCPomdp:
    """The HRC POMDP over the observable states the task book can produce.

    `columns[i]` is the observable column l * n_task * 4 + y * 4 + d of solved state i (the
    column of `ActionSelector`; l the queue length of MODEL.md 8.1, outermost as in the flat
    index, 0 without a queue); `column_index[c]` the solved state of column c, -1 outside the
    set. Solved state i = l * n_y * 4 + i_y * 4 + d (n_y task states of the closure, every l).
    `enter[i, j]` is the solved state after task j of `tasks` enters the idle cell of state i,
    at the same l (-1 where the cell is busy); `likelihood` is P(O | h), (3, 9).
    """

    model: HRCModel
    pomdp: MixedPOMDP
    columns: np.ndarray
    column_index: np.ndarray
    tasks: np.ndarray
    enter: np.ndarray
    likelihood: np.ndarray

    def state(self, observable, level: int = 0) -> int:
        """The solved state of observable x = (tp, tc, tx, ty, hp, hc, bp, bc, d) with `level`
        tasks waiting (the queue length l of MODEL.md 8.1; 0 without a queue)."""
        *task, d = (int(v) for v in observable)
        y = self.model.task_index({n: np.asarray(v) for n, v in zip(TASK_VARIABLES, task)})
        if not 0 <= int(level) < self.model.n_levels:
            raise ValueError(f'queue length {level} outside 0..{self.model.n_levels - 1}')
        column = int(level) * self.model.n_task * N_DISTANCE + int(y) * N_DISTANCE + d
        i = int(self.column_index[column])
        if i < 0:
            raise ValueError(f'observable state {tuple(observable)} is not one the task book '
                             'can produce; the POMDP policy does not cover it')
        return i


def _task_outcomes(op: FactoredBellman):
    """Per action: (y' when refused or not a request, y' when accepted or -1, eligible)."""
    rh1 = np.zeros(op.n_y, dtype=bool)
    rh2 = np.zeros(op.n_y, dtype=bool)
    rh1[op.request_y[~op.request_is_rh2]] = True
    rh2[op.request_y[op.request_is_rh2]] = True
    commit = np.where(op.t_commit_full >= 0, op.t_commit_full, op.t_default)
    out = []
    for a in range(len(ACTIONS)):
        refused = {DN: op.t_pause, CT: commit, DP: op.t_dp, DM: op.t_dm}.get(a, op.t_default)
        eligible = {RH1: rh1, RH2: rh2}.get(a, np.zeros(op.n_y, dtype=bool))
        out.append((refused, np.where(eligible, op.t_accept_full, -1), eligible))
    return out


def _arrival_branches(arrivals, ys: np.ndarray, branches: list) -> list:
    """The stream's arrivals (MODEL.md 8) on the task branches [(y' per source, P by h)]: a
    branch that leaves the cell idle splits into 'no task arrives' and one branch per task of
    the stream, entered (`model.Arrivals`); the arrival is independent of h, so it scales the
    branch's likelihood. -1 (no branch) stays -1."""
    p_arrive = arrivals.probability(ys)[:, None]                    # (n_y, 1), by the source
    out = []
    for y_next, p_y in branches:
        ends_idle = (y_next >= 0) & arrivals.idle[np.maximum(y_next, 0)]
        out.append((y_next, p_y * np.where(ends_idle[:, None], 1.0 - p_arrive, 1.0)))
        for j, q_j in enumerate(arrivals.q):
            entered = np.where(ends_idle, arrivals.enter[np.maximum(y_next, 0), j], -1)
            out.append((entered, p_y * p_arrive * q_j))
    return out


def _queue_branches(queue, ys: np.ndarray, level: int, branches: list) -> tuple[list, list]:
    """The queue's epoch (MODEL.md 8.1, as `HRCModel._queue_steps`) on the task branches
    [(y' per source, P by h)] of the sources `ys` with `level` tasks waiting: a task is
    released with arrival_busy or arrival_idle by the source's tp (a Bernoulli of its own);
    where the step left the cell idle and a task waits, the head (task k of q) enters and the
    queue shortens by one; l' = min(l + released - entered, L). The release and the entry are
    independent of h, so they scale the branch's likelihood. Returns (l' per branch, the
    branches); branches with the same l' and the same y' everywhere are merged (at l = L a
    busy cell's release is dropped: the same successor as no release). -1 stays -1."""
    arr, top = queue.arrivals, queue.levels
    p_release = np.where(arr.idle[ys], arr.p_idle, arr.p_complete)[:, None]   # by the source
    levels, out = [], []

    def add(l_next, y_next, p):
        for i, (l_old, (y_old, p_old)) in enumerate(zip(levels, out)):
            if l_old == l_next and np.array_equal(y_old, y_next):
                out[i] = (y_old, p_old + p)
                return
        levels.append(l_next)
        out.append((y_next, p))

    for y_next, p_y in branches:
        ends_idle = (y_next >= 0) & arr.idle[np.maximum(y_next, 0)]
        for released, p_r in ((1, p_release), (0, 1.0 - p_release)):
            waiting = level + released
            enters = ends_idle & (waiting > 0)
            add(min(waiting, top), np.where(enters, -1, y_next), p_y * p_r)
            if waiting > 0:
                for j, q_j in enumerate(arr.q):
                    entered = np.where(enters, arr.enter[np.maximum(y_next, 0), j], -1)
                    add(min(waiting - 1, top), entered, p_y * p_r * q_j)
    return levels, out


def model_tasks(model: HRCModel) -> np.ndarray:
    """Every task (tp, tc, tx) of the model, (K, 3)."""
    return np.array([(tp, tc, tx) for tp in range(1, model.rho + 1)
                     for tc in range(1, model.sigma + 1) for tx in range(4)])


def task_closure(model: HRCModel, operator: FactoredBellman | None = None) -> np.ndarray:
    """The task states y the task book can produce, ascending: the idle cell, every task
    entering an idle cell, and the closure under every action and answer (149 of the 11,664
    at full size). The POMDP's solved states and the liveness check (`mdp.liveness`) read
    them."""
    op = operator or FactoredBellman(model)
    outcomes = _task_outcomes(op)
    grid = model.task_grid
    tasks = model_tasks(model)
    idle_y = entering_task(model, np.array([0]), 0, 0, 0)[0]    # tp = 0 everywhere: y = 0
    reach = np.zeros(model.n_task, dtype=bool)
    reach[idle_y] = True
    while True:
        ys = np.flatnonzero(reach)
        nxt = [refused[ys] for refused, _, _ in outcomes]
        nxt += [accepted[ys][accepted[ys] >= 0] for _, accepted, _ in outcomes]
        idle = ys[grid['tp'][ys] == 0]
        nxt += [entering_task(model, idle, *t) for t in tasks]
        before = int(reach.sum())
        reach[np.concatenate(nxt)] = True
        if int(reach.sum()) == before:
            break
    return np.flatnonzero(reach)


def _paused_outcomes(op: FactoredBellman, outcomes: list) -> list:
    """Per action, with model.robot_rate: (y' when refused or not a request, y' when accepted
    or -1) with the robot's counter staying (the run's failure, MODEL.md 3.2); the same as
    `_task_outcomes` where the step sets the counter (an effective ct, an accepted rh2)."""
    commit = np.where(op.t_commit_full >= 0, op.t_commit_full, op.t_pause)
    return [({CT: commit}.get(a, op.t_pause), np.where(eligible, op.t_accept_pause_full, -1))
            for a, (_, _, eligible) in enumerate(outcomes)]


def _run_branches(op: FactoredBellman, ys: np.ndarray, d: int, runs, stays, p) -> list:
    """The task branches [(y', P by h)] of the sources `ys` at band d of an action under which
    the robot works: each of (refused, accepted) splits into the counter running (rate[tx, d])
    and staying; where both give one y' (no robot work) the one branch keeps its weight."""
    rate = op.rate_yd[ys, d][:, None]
    out = []
    for run, stay, p_branch in zip(runs, stays, p):
        run, stay = run[ys], stay[ys]
        same = (run == stay)[:, None]
        out.append((run, np.where(same, p_branch, p_branch * rate)))
        out.append((np.where(same[:, 0], -1, stay), np.where(same, 0.0, p_branch * (1 - rate))))
    return out


def _add_successors(succ_x, succ_l, k, first, a, dist, d_of_x, y_index, n_y, levels, branches,
                    source_d) -> None:
    """Write the branches [(y' per source, P by h)] at queue levels `levels` through the
    distance step into the successor lists of action a (rows first + (i_y, d); only the rows
    at band `source_d` unless it is None), counting in k."""
    for l_next, (y_next, p_y) in zip(levels, branches):
        has = y_next >= 0
        for d_next in range(N_DISTANCE):
            p_d = dist[:, :, d_next].T                      # (d, 9)
            lik = np.repeat(p_y, N_DISTANCE, axis=0) * p_d[d_of_x]   # (n_y * 4, 9)
            use = np.repeat(has, N_DISTANCE) & (lik.max(axis=1) > 0)
            if source_d is not None:
                use &= d_of_x == source_d
            rows = np.flatnonzero(use)
            target = y_index[np.repeat(np.where(has, y_next, 0), N_DISTANCE)[rows]]
            succ_x[first + rows, a, k[rows]] = (l_next * n_y + target) * N_DISTANCE + d_next
            succ_l[first + rows, a, k[rows]] = lik[rows]
            k[rows] += 1


def hrc_pomdp(model: HRCModel, operator: FactoredBellman | None = None) -> HRCPomdp:
    """The MixedPOMDP of `model` over the closure of the task states the task book produces:
    the idle cell, every task (tp, tc, tx) entering an idle cell, and all that the dynamics
    reach from them, at every distance, and with a queue (MODEL.md 8.1) at every queue length
    l = 0..L: (L + 1) times the states, the successors split by the release and the head's
    entry (`_queue_branches`), the reward the MDP's (`HRCModel.flat_cost`: J + w l + the
    expected drop charge)."""
    op = operator or FactoredBellman(model)
    outcomes = _task_outcomes(op)
    grid = model.task_grid
    tasks = model_tasks(model)
    ys = task_closure(model, op)
    n_y = ys.size
    y_index = np.full(model.n_task, -1, dtype=np.intp)
    y_index[ys] = np.arange(n_y)
    # x = (l * n_y + i_y) * 4 + d: every l of the queue (MODEL.md 8.1; one level without one)
    # holds the same closure, l outermost as in the flat index
    n_levels, n_cols = model.n_levels, model.n_task * N_DISTANCE
    n_base_x = n_y * N_DISTANCE
    base_columns = (ys[:, None] * N_DISTANCE + np.arange(N_DISTANCE)[None, :]).ravel()
    columns = (np.arange(n_levels)[:, None] * n_cols + base_columns[None, :]).ravel()
    n_x = columns.size
    column_index = np.full(n_levels * n_cols, -1, dtype=np.intp)
    column_index[columns] = np.arange(n_x)

    ea = np.arange(N_HIDDEN) % 3
    p_accept = op.p_accept_vector                                   # by h
    n_a = len(ACTIONS)
    arrivals, queue = model.arrivals, model.queue
    if queue is None:
        n_k = 2 * 3 * (1 if arrivals is None else 1 + len(arrivals.q))
    else:                     # (accepted, released) x (stays, or the head's K kinds) x 3 d'
        n_k = 2 * 2 * 3 * (1 + len(queue.arrivals.q))
    if op.rated:              # model.robot_rate: the counter runs or stays (MODEL.md 3.2)
        n_k *= 2
    paused = _paused_outcomes(op, outcomes) if op.rated else None
    succ_x = np.full((n_x, n_a, n_k), -1, dtype=np.intp)
    succ_l = np.zeros((n_x, n_a, n_k, N_HIDDEN))
    d_of_x = np.tile(np.arange(N_DISTANCE), n_y)
    for level in range(n_levels):
        first = level * n_base_x                                    # this level's rows
        for a, (refused, accepted, eligible) in enumerate(outcomes):
            dist = model.distance_matrix(a)[ea]                     # (9, d, d')
            p_refused = np.where(eligible[ys][:, None], 1.0 - p_accept, 1.0)
            p_accepted = np.where(eligible[ys][:, None], p_accept, 0.0)
            # (the source band the branches hold for, None: every one; the task branches)
            groups = [(None, [(refused[ys], p_refused), (accepted[ys], p_accepted)])]
            if paused is not None and a not in model.paused:
                groups = [(d, _run_branches(op, ys, d, (refused, accepted),
                                            paused[a], (p_refused, p_accepted)))
                          for d in range(N_DISTANCE)]
            k = np.zeros(n_base_x, dtype=np.intp)
            for source_d, branches in groups:
                if arrivals is not None:
                    branches = _arrival_branches(arrivals, ys, branches)
                levels = [0] * len(branches)
                if queue is not None:
                    levels, branches = _queue_branches(queue, ys, level, branches)
                _add_successors(succ_x, succ_l, k, first, a, dist, d_of_x, y_index, n_y,
                                levels, branches, source_d)
    d_of_x = np.tile(np.arange(N_DISTANCE), n_y * n_levels)
    if queue is None:
        cost = op.cost[:, ys, :].transpose(1, 2, 0).reshape(n_x, N_HIDDEN)   # (x, h)
        reward = -(cost[:, None, :] + op.g[None, :, None])
    else:
        # the MDP's cost of the queue (J + w l + the expected drop charge), by (x, h)
        used = int((succ_x >= 0).sum(axis=2).max())
        succ_x, succ_l = succ_x[:, :, :used].copy(), succ_l[:, :, :used].copy()
        flat = (np.repeat(np.arange(n_levels), n_base_x)[:, None] * model.n_base
                + np.arange(N_HIDDEN)[None, :] * n_cols
                + np.tile(base_columns, n_levels)[:, None])                  # (x, h)
        reward = -np.stack([model.flat_cost(flat.ravel(), a).reshape(n_x, N_HIDDEN)
                            for a in range(n_a)], axis=1)
    available = model.availability[:, d_of_x].T.copy()             # (x, a)
    likelihood = BeliefFilter(model).likelihood
    emotion = np.stack([model.emotion_matrices[g] for g in EMOTION_GROUPS])
    kernel = emotion[:, None, :, :] * likelihood[None, :, None, :]  # (g, o, h, h')
    group = np.array([EMOTION_GROUPS.index(ACTION_EMOTION_GROUP[a]) for a in range(n_a)])
    pomdp = MixedPOMDP(succ_x=succ_x, succ_l=succ_l, reward=reward, available=available,
                       group=group, kernel=np.ascontiguousarray(kernel), gamma=model.gamma,
                       order=np.array(SAFETY_ORDER))
    idle_x = np.tile(np.repeat(grid['tp'][ys] == 0, N_DISTANCE), n_levels)
    level_of_x = np.repeat(np.arange(n_levels), n_base_x)
    enter = np.full((n_x, len(tasks)), -1, dtype=np.intp)
    for j, t in enumerate(tasks):                   # the task enters, the queue stays
        entered = np.tile(np.repeat(y_index[entering_task(model, ys, *t)], N_DISTANCE),
                          n_levels)
        enter[:, j] = np.where(idle_x, (level_of_x * n_y + entered) * N_DISTANCE + d_of_x, -1)
    return HRCPomdp(model, pomdp, columns, column_index, tasks, enter, likelihood)


# -- the MDP and the fast informed bound over the solved states -------------------------------
def _greedy_value(pomdp: MixedPOMDP, q: np.ndarray) -> np.ndarray:
    return np.where(pomdp.available[..., None], q, -np.inf).max(axis=1)


def _successor_sums(pomdp: MixedPOMDP, table: np.ndarray, pick: np.ndarray,
                    rows: np.ndarray | None = None) -> np.ndarray:
    """(X, M, H): sum_k l_k(h) table[pick[x, m], x'_k, h] over the successors of (x, rows[x, m])
    (rows: every action, M = A, by default), by the sparse kernel (`_kernels.successor_sums`)."""
    n_x, n_a = pomdp.n_x, pomdp.n_actions
    if rows is None:
        rows = np.broadcast_to(np.arange(n_a), (n_x, n_a))
    rows = np.ascontiguousarray(rows, dtype=np.intp)
    out = np.empty(rows.shape + (pomdp.n_hidden,))
    kernels.successor_sums(np.ascontiguousarray(pomdp.succ_x, dtype=np.intp), pomdp.succ_l,
                           rows, np.ascontiguousarray(table, dtype=float),
                           np.ascontiguousarray(pick, dtype=np.intp), out, work=rows.size)
    return out


def _expected_next(pomdp: MixedPOMDP, value: np.ndarray, fast: bool) -> np.ndarray:
    """`MixedPOMDP.expected_next`, or with `fast` its sparse form (the same sums, another order
    of adding them up: equal to rounding, a test holds them so)."""
    if not fast:
        return pomdp.expected_next(value)
    stepped = np.einsum('ghk,xk->gxh', pomdp.hidden_transition, value)   # (G, X', H)
    return _successor_sums(pomdp, stepped, np.broadcast_to(pomdp.group, (pomdp.n_x,
                                                                        pomdp.n_actions)))


def mdp_q(pomdp: MixedPOMDP, tol: float = 1e-9, max_sweeps: int = 100_000,
          fast: bool = False) -> np.ndarray:
    """Q of the fully observed MDP over (x, h), (X, A, H), by value iteration to `tol`.
    `fast`: the successors' sums by the sparse kernel (`solve_pomdp` uses it for a queue)."""
    value = np.zeros((pomdp.n_x, pomdp.n_hidden))
    for _ in range(max_sweeps):
        q = pomdp.reward + pomdp.gamma * _expected_next(pomdp, value, fast)
        new = _greedy_value(pomdp, q)
        change = np.max(np.abs(new - value))
        value = new
        if change < tol:
            break
    return pomdp.reward + pomdp.gamma * _expected_next(pomdp, value, fast)


def fib_step(pomdp: MixedPOMDP, q: np.ndarray, fast: bool = False) -> np.ndarray:
    """One fast-informed-bound backup of Q (X, A, H) (`fast`: the gather by the sparse
    kernel)."""
    masked = np.where(pomdp.available[..., None], q, -np.inf)       # (X, A', H')
    # w[x', g, o, h] = max_a' sum_h' kernel[g, o, h, h'] q[x', a', h']
    proj = np.einsum('gohk,xak->xgoha', pomdp.kernel, np.where(np.isfinite(masked), q, 0.0))
    proj = np.where(pomdp.available[:, None, None, None, :], proj, -np.inf)
    w = proj.max(axis=4).sum(axis=2)                                 # (X, G, H)
    if fast:
        table = w.transpose(1, 0, 2)                                 # (G, X', H)
        pick = np.broadcast_to(pomdp.group, (pomdp.n_x, pomdp.n_actions))
        return pomdp.reward + pomdp.gamma * _successor_sums(pomdp, table, pick)
    nxt = np.maximum(pomdp.succ_x, 0)
    gathered = w[nxt, pomdp.group[None, :, None], :]                # (X, A, K, H)
    gathered = np.where((pomdp.succ_x >= 0)[..., None], gathered, 0.0)
    return pomdp.reward + pomdp.gamma * np.einsum('xakh,xakh->xah', pomdp.succ_l, gathered)


def fib_q(pomdp: MixedPOMDP, tol: float = 1e-9, start: np.ndarray | None = None,
          max_sweeps: int = 100_000, fast: bool = False) -> tuple[np.ndarray, int]:
    """The fast informed bound's Q, (X, A, H), iterated from the MDP's Q (an upper bound, so
    every iterate is one); returns (Q, sweeps)."""
    q = mdp_q(pomdp, tol, fast=fast) if start is None else start
    for n in range(1, max_sweeps + 1):
        new = fib_step(pomdp, q, fast)
        change = np.max(np.abs(np.where(pomdp.available[..., None], new - q, 0.0)))
        q = np.minimum(q, new)     # a valid upper bound stays one; guards rounding drift
        if change < tol:
            return q, n
    return q, max_sweeps


def blind_alphas(pomdp: MixedPOMDP, tol: float = 1e-9, fast: bool = False) -> np.ndarray:
    """Values (A, X, H) of the blind policies 'always a (where a is unavailable, the first
    available action of the tie order)': executable whatever the belief, so lower bounds.
    `fast`: the successors' sums by the sparse kernel."""
    n_a, n_x = pomdp.n_actions, pomdp.n_x
    first = pomdp.order[np.argmax(pomdp.available[:, pomdp.order], axis=1)]   # (X,)
    act = np.where(pomdp.available.T, np.arange(n_a)[:, None], first[None, :])  # (A, X)
    rows = np.arange(n_x)[None, :]
    reward = pomdp.reward[rows, act]                                # (A, X, H)
    if fast:
        n_g = pomdp.hidden_transition.shape[0]
        # table[b * G + g, x'] = E_g applied to policy b's value at x'; policy b at x reads
        # its action's successors and group
        pick = (np.arange(n_a)[:, None] * n_g + pomdp.group[act]).T   # (X, A)
        value = np.zeros((n_a, n_x, pomdp.n_hidden))
        while True:
            table = np.einsum('ghj,bxj->bgxh', pomdp.hidden_transition, value)
            future = _successor_sums(pomdp, table.reshape(n_a * n_g, n_x, -1), pick, act.T)
            new = reward + pomdp.gamma * future.transpose(1, 0, 2)
            change = np.max(np.abs(new - value))
            value = new
            if change < tol:
                return value
    e = pomdp.hidden_transition[pomdp.group[act]]                   # (A, X, H, H')
    succ_x = pomdp.succ_x[rows, act]                                # (A, X, K)
    succ_l = pomdp.succ_l[rows, act]                                # (A, X, K, H)
    exists = (succ_x >= 0)[..., None]
    nxt = np.maximum(succ_x, 0)
    blind = np.arange(n_a)[:, None, None]
    value = np.zeros((n_a, n_x, pomdp.n_hidden))
    while True:
        gathered = np.where(exists, value[blind, nxt], 0.0)         # (A, X, K, H')
        future = np.einsum('axkh,axhj,axkj->axh', succ_l, e, gathered)
        new = reward + pomdp.gamma * future
        change = np.max(np.abs(new - value))
        value = new
        if change < tol:
            return value


# -- belief points ------------------------------------------------------------------------------
def q_policy(pomdp: MixedPOMDP, q: np.ndarray):
    """(x array, b array) -> argmax_a sum_h b(h) q[x, a, h] over available a, tie order."""
    def act(x, b):
        scores = np.einsum('eah,eh->ea', q[x], b)
        return first_of_best(np.where(pomdp.available[x], scores, -np.inf), pomdp.order)
    return act


def first_of_best(scores: np.ndarray, order=SAFETY_ORDER) -> np.ndarray:
    """Per row of scores (E, A), the first action of `order` tied with the row's best (the
    model's tie rule, `model.safest_best`)."""
    return safest_best(scores, order)


@dataclass
class Starts:
    """Where sampled episodes begin: observable states, the true h's distribution and the
    prior the belief starts from (b_1 ∝ prior * L[O_1], O_1 drawn from the true h)."""

    x: np.ndarray
    truth: np.ndarray     # (S, H)
    prior: np.ndarray     # (S, H)


def sample_beliefs(pomdp: MixedPOMDP, likelihood: np.ndarray, starts: Starts, policy,
                   episodes: int, epochs: int, seed: int = 0, explore: float = 0.2,
                   enter: np.ndarray | None = None, task_rate: float = 0.2):
    """Beliefs (x, b) met in `episodes` simulated episodes of `epochs` epochs, with the exact
    posterior. Actions: `policy(x, b)`, or with probability `explore` a random available one.
    With `enter` (X, T), a task enters an idle cell with probability `task_rate` per epoch
    (as in `hrc-evaluate`'s random task streams). Returns (x (E*K,), b (E*K, H))."""
    rng = np.random.default_rng(seed)
    n_h = pomdp.n_hidden
    s = rng.integers(0, len(starts.x), size=episodes)
    x = starts.x[s].astype(np.intp)
    h = _draw(rng, starts.truth[s])
    o = _draw(rng, likelihood.T[h])
    evidence = likelihood / likelihood.sum(axis=1, keepdims=True)    # L[o] alone, normalised
    b = _normalised(starts.prior[s] * likelihood[o], evidence[o])
    xs, bs = [], []
    for _ in range(epochs):
        xs.append(x.copy())
        bs.append(b.copy())
        a = policy(x, b)
        wild = rng.random(episodes) < explore
        if wild.any():
            avail = pomdp.available[x[wild]].astype(float)
            a[wild] = _draw(rng, avail / avail.sum(axis=1, keepdims=True))
        p_k = pomdp.succ_l[x, a, :, h]                               # (E, K)
        k = _draw(rng, p_k)
        lik = pomdp.succ_l[x, a, k]                                  # (E, H)
        x_next = pomdp.succ_x[x, a, k]
        g = pomdp.group[a]
        joint = pomdp.kernel[g, :, h, :].reshape(episodes, -1)       # (E, O*H')
        oh = _draw(rng, joint)
        o, h = oh // n_h, oh % n_h
        b = _normalised(np.einsum('eh,ehk->ek', b * lik, pomdp.kernel[g, o]), evidence[o])
        x = x_next
        if enter is not None:
            can = enter[x, 0] >= 0
            arrive = can & (rng.random(episodes) < task_rate)
            if arrive.any():
                j = rng.integers(0, enter.shape[1], size=int(arrive.sum()))
                x[arrive] = enter[x[arrive], j]
    return np.concatenate(xs), np.concatenate(bs)


def _normalised(b: np.ndarray, restart: np.ndarray) -> np.ndarray:
    """Rows of b normalised; a row whose mass is below the smallest normal float (evidence the
    belief called impossible: a person prior or epsilon 0 that rules it out) restarts from
    `restart`, the evidence alone, as `BeliefFilter` does."""
    total = b.sum(axis=1, keepdims=True)
    lost = total[:, 0] < np.finfo(float).tiny
    out = b / np.where(lost[:, None], 1.0, total)
    out[lost] = restart[lost]
    return out


def _draw(rng, p: np.ndarray) -> np.ndarray:
    """One index per row of p (rows are distributions), by inverse CDF."""
    c = np.cumsum(p, axis=1)
    u = rng.random(len(p)) * c[:, -1]
    return np.minimum((c <= u[:, None]).sum(axis=1), p.shape[1] - 1)


def thin_points(x: np.ndarray, b: np.ndarray, resolution: float = 0.01,
                per_state: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Distinct beliefs per x at `resolution` (rounded), at most `per_state` per x (random
    ones beyond), sorted by x."""
    key = np.round(b / resolution).astype(np.int64)
    _, first = np.unique(np.column_stack([x, key]), axis=0, return_index=True)
    x, b = x[first], b[first]
    rng = np.random.default_rng(seed)
    keep = np.ones(len(x), dtype=bool)
    order = np.argsort(x, kind='stable')
    x, b = x[order], b[order]
    starts = np.flatnonzero(np.r_[True, x[1:] != x[:-1]])
    ends = np.r_[starts[1:], len(x)]
    for lo, hi in zip(starts, ends):
        if hi - lo > per_state:
            drop = rng.choice(np.arange(lo, hi), size=hi - lo - per_state, replace=False)
            keep[drop] = False
    return x[keep], b[keep]


# -- the solver -----------------------------------------------------------------------------------
@dataclass
class AlphaSet:
    """Alpha vectors grouped by observable state: Gamma(x) = alpha[offsets[x]:offsets[x+1]]."""

    alpha: np.ndarray     # (n, H) float64
    action: np.ndarray    # (n,) int8
    offsets: np.ndarray   # (X + 1,) int64

    @classmethod
    def build(cls, x, alpha, action, n_x: int) -> 'AlphaSet':
        """From unsorted rows; exact duplicates (same x, action, vector) are merged."""
        rows = np.column_stack([x.astype(float), action.astype(float), alpha])
        _, first = np.unique(rows, axis=0, return_index=True)
        first = first[np.argsort(x[first], kind='stable')]
        x, alpha, action = x[first], alpha[first], action[first]
        offsets = np.searchsorted(x, np.arange(n_x + 1)).astype(np.int64)
        return cls(np.ascontiguousarray(alpha), action.astype(np.int8), offsets)

    @property
    def owner(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.offsets) - 1), np.diff(self.offsets))

    def __len__(self) -> int:
        return len(self.alpha)


@dataclass
class UpperBound:
    """FIB's Q, the corner values and the sawtooth points (sorted by x) with their values."""

    q_fib: np.ndarray     # (X, A, H)
    available: np.ndarray  # (X, A)
    corner: np.ndarray    # (X, H)
    points_x: np.ndarray  # (P,) sorted
    points: np.ndarray    # (P, H)
    values: np.ndarray    # (P,)

    @classmethod
    def from_fib(cls, q_fib, available, points_x, points) -> 'UpperBound':
        corner = np.where(available[..., None], q_fib, -np.inf).max(axis=1)
        ub = cls(q_fib, available, corner, points_x, points, np.full(len(points), np.inf))
        ub.values = ub.evaluate(points_x, points)
        return ub

    def sawtooth(self):
        """(1 / b_i, v_i - c.b_i, offsets) of the points that lower the bound (v_i < c.b_i)."""
        base = np.einsum('ph,ph->p', self.corner[self.points_x], self.points)
        slope = self.values - base
        use = slope < -1e-12
        with np.errstate(divide='ignore'):
            inverse = np.where(self.points[use] > 0, 1.0 / self.points[use], 0.0)
        offsets = np.searchsorted(self.points_x[use], np.arange(len(self.corner) + 1))
        return (np.ascontiguousarray(inverse), np.ascontiguousarray(slope[use]),
                offsets.astype(np.int64))

    def evaluate(self, x, b) -> np.ndarray:
        """U(x, b) = min(FIB, sawtooth) for rows (x, b)."""
        x = np.ascontiguousarray(x, dtype=np.intp)
        b = np.ascontiguousarray(b, dtype=float)
        out = np.empty(len(x))
        kernels.ub_values(b, x, self.q_fib, self.available, self.corner, *self.sawtooth(), out,
                          work=len(x))
        return out


def initial_bounds(pomdp: MixedPOMDP, points_x: np.ndarray, points: np.ndarray,
                   tol: float = 1e-9) -> tuple[AlphaSet, UpperBound]:
    """The blind policies' vectors (lower bound) and FIB with the points' values (upper)."""
    q_fib, _ = fib_q(pomdp, tol)
    return (blind_alpha_set(pomdp, blind_alphas(pomdp, tol)),
            UpperBound.from_fib(q_fib, pomdp.available, points_x, points))


def blind_alpha_set(pomdp: MixedPOMDP, blind: np.ndarray) -> AlphaSet:
    """The lower bound a solve starts from: `blind_alphas`' values (A, X, H), one vector per
    action at every observable state x."""
    n_x, n_a = pomdp.n_x, pomdp.n_actions
    return AlphaSet.build(np.tile(np.arange(n_x), n_a), blind.reshape(-1, pomdp.n_hidden),
                          np.repeat(np.arange(n_a), n_x), n_x)


def shared_actions(pomdp: MixedPOMDP, share: bool = True) -> np.ndarray:
    """(X, A) intp: for each (x, a) the first available a0 < a with the same successors,
    likelihoods and action group, whose backup differs from a's by the reward alone (nw and an
    ineffective ct, rh1 and rh2 where neither is eligible, dn where the robot has no work: a
    quarter of a queue's backup work), else -1; all -1 with `share` False (the kernels then
    back every action up in full)."""
    out = np.full((pomdp.n_x, pomdp.n_actions), -1, dtype=np.intp)
    if not share:
        return out
    for x in range(pomdp.n_x):
        seen = []
        for a in range(pomdp.n_actions):
            if not pomdp.available[x, a]:
                continue
            for a0 in seen:
                if (pomdp.group[a0] == pomdp.group[a]
                        and np.array_equal(pomdp.succ_x[x, a0], pomdp.succ_x[x, a])
                        and np.array_equal(pomdp.succ_l[x, a0], pomdp.succ_l[x, a])):
                    out[x, a] = a0
                    break
            else:
                seen.append(a)
    return out


def _perseus_lower(backup, points, points_x, old_val, n_x: int, rng, share: int = 16):
    """One Perseus sweep of the lower bound (Spaan and Vlassis 2005), in parallel batches:
    back up a random batch of the points not yet improved (about 1/`share` of them, at
    least 64), add the vectors, and drop from the rest every point the new vectors already
    lift to its old value; until none is left. Every point ends at least at its old value
    (`backup` keeps a point's old best vector where its backup is not better). Returns (x,
    vectors, actions) of the new set and its value at every point."""
    n_p = len(points)
    todo = np.ones(n_p, dtype=bool)
    value = np.full(n_p, -np.inf)
    xs, vecs, acts = [], [], []
    while True:
        rows = np.flatnonzero(todo)
        if rows.size == 0:
            break
        size = min(rows.size, max(64, -(-rows.size // share)))
        pick = np.sort(rng.choice(rows, size=size, replace=False))
        v, a, got = backup(pick)
        xs.append(points_x[pick])
        vecs.append(v)
        acts.append(a)
        value[pick] = np.maximum(value[pick], got)
        todo[pick] = False
        rows = np.flatnonzero(todo)
        if rows.size:          # what the batch's vectors give the points still to do
            batch = AlphaSet.build(points_x[pick], v, a, n_x)
            lifted = np.empty(rows.size)
            index = np.empty(rows.size, dtype=np.intp)
            kernels.lb_values(points[rows], points_x[rows], batch.alpha, batch.offsets, lifted,
                              index, work=rows.size)
            value[rows] = np.maximum(value[rows], lifted)
            todo[rows[value[rows] >= old_val[rows]]] = False
    return np.concatenate(xs), np.vstack(vecs), np.concatenate(acts), value


def backup_sweeps(pomdp: MixedPOMDP, points_x: np.ndarray, points: np.ndarray,
                  alphas: AlphaSet, upper: UpperBound, max_sweeps: int, tol: float,
                  targets=None, progress: Callable[[dict], None] | None = None,
                  time_limit: float | None = None, ub_every: int = 25,
                  share: bool = False, perseus: bool = False
                  ) -> tuple[AlphaSet, UpperBound, list]:
    """Full point-based sweeps of both bounds until neither moves by `tol` at any point.

    Lower bound: every point backed up from the current vectors (`lb_backup`); a point keeps
    its current best vector where the new one is worse (Perseus's rule), so the bound never
    decreases at a point; the new set is the vectors the points hold. Upper bound: every point
    backed up through min(FIB, sawtooth) (`ub_backup`), keeping the smaller value; the corners
    (points e_h) lower the corner values. `targets` = (x, b) rows whose gap is reported.
    `share`: an action with another's successors and group is backed up from that one's
    (`shared_actions`; the same values to rounding, a quarter less work for a queue).
    `perseus`: the lower bound's sweep is Perseus's randomised one (`_perseus_lower`): only
    the points no new vector has improved yet are backed up, so a sweep costs a fraction of
    a full one and the sets stay smaller (the queue's solve, 3 x the states); and once it
    moves by less than `tol` it is left as it is while the upper bound's sweeps go on.
    """
    n_x, n_h = pomdp.n_x, pomdp.n_hidden
    order = np.ascontiguousarray(pomdp.order, dtype=np.intp)
    group = np.ascontiguousarray(pomdp.group, dtype=np.intp)
    succ_x = np.ascontiguousarray(pomdp.succ_x, dtype=np.intp)
    same_as = shared_actions(pomdp, share)
    n_p = len(points)
    vec = np.empty((n_p, n_h))
    act = np.empty(n_p, dtype=np.intp)
    val = np.empty(n_p)
    old_val = np.empty(n_p)
    old_idx = np.empty(n_p, dtype=np.intp)
    ub_new = np.empty(n_p)
    ub_act = np.empty(n_p, dtype=np.intp)
    is_corner = points.max(axis=1) >= 1.0
    corner_h = points.argmax(axis=1)
    t0 = time.perf_counter()
    history = []
    ub_change = np.inf
    lower_done = False
    for sweep in range(1, max_sweeps + 1):
        kernels.lb_values(points, points_x, alphas.alpha, alphas.offsets, old_val, old_idx,
                          work=n_p)
        if lower_done:     # Perseus's runs: the lower bound has converged, the upper goes on
            lower_now, lb_change = old_val.copy(), 0.0
        else:
            proj = np.ascontiguousarray(np.einsum('gohk,ik->goih', pomdp.kernel, alphas.alpha))

            def backup(rows, proj=proj, alphas=alphas):
                """(vectors, actions, values) of the points `rows` backed up from the current
                set, each point's current best vector where the backup is not better (Perseus's
                rule)."""
                out_vec, out_act, out_val = vec[:len(rows)], act[:len(rows)], val[:len(rows)]
                kernels.lb_backup(points[rows], points_x[rows], succ_x, pomdp.succ_l,
                                  pomdp.reward, pomdp.available, group, order, proj,
                                  alphas.offsets, pomdp.gamma, same_as, out_vec, out_act, out_val,
                                  work=len(rows))
                better = out_val > old_val[rows]
                return (np.where(better[:, None], out_vec, alphas.alpha[old_idx[rows]]),
                        np.where(better, out_act, alphas.action[old_idx[rows]]),
                        np.maximum(out_val, old_val[rows]))

            if perseus:
                keep_x, keep_vec, keep_act, lower_now = _perseus_lower(
                    backup, points, points_x, old_val, n_x, np.random.default_rng(sweep))
            else:
                keep_vec, keep_act, lower_now = backup(np.arange(n_p))
                keep_x = points_x
            lb_change = float(np.max(lower_now - old_val))
            # states without points keep their vectors
            lonely = np.ones(n_x, dtype=bool)
            lonely[points_x] = False
            held = lonely[alphas.owner]
            alphas = AlphaSet.build(np.concatenate([keep_x, alphas.owner[held]]),
                                    np.vstack([keep_vec, alphas.alpha[held]]),
                                    np.concatenate([keep_act, alphas.action[held]]), n_x)
            lower_done = perseus and lb_change < tol

        last = lb_change < tol or sweep == max_sweeps or (
            time_limit is not None and time.perf_counter() - t0 > time_limit)
        if sweep == 1 or sweep % ub_every == 0 or last:
            kernels.ub_backup(points, points_x, succ_x, pomdp.succ_l, pomdp.reward,
                              pomdp.available, group, order, pomdp.kernel, pomdp.gamma,
                              upper.q_fib, upper.corner, *upper.sawtooth(), same_as, ub_new,
                              ub_act, work=n_p)
            ub_change = float(np.max(np.maximum(upper.values - ub_new, 0.0)))
            upper.values = np.minimum(upper.values, ub_new)
            c = upper.corner.copy()
            np.minimum.at(c, (points_x[is_corner], corner_h[is_corner]),
                          upper.values[is_corner])
            upper.corner = c
        gap = upper.values - lower_now
        row = {'sweep': sweep, 'vectors': len(alphas), 'lb_change': lb_change,
               'ub_change': ub_change, 'gap_max': float(gap.max()),
               'gap_mean': float(gap.mean()), 'elapsed': time.perf_counter() - t0}
        if targets is not None:
            tx, tb = targets
            lo = np.array([(alphas.alpha[alphas.offsets[x]:alphas.offsets[x + 1]] @ b).max()
                           for x, b in zip(tx, tb)])
            hi = upper.evaluate(tx, tb)
            row['target_lower'] = lo.tolist()
            row['target_upper'] = hi.tolist()
            row['target_gap'] = float(np.max((hi - lo) / np.maximum(1.0, np.abs(lo))))
        history.append(row)
        if progress is not None:
            progress(row)
        if lb_change < tol and ub_change < tol:
            break
        if time_limit is not None and time.perf_counter() - t0 > time_limit:
            break
    return alphas, upper, history


# -- the solve ---------------------------------------------------------------------------------
@dataclass
class PomdpResult:
    """What `solve_pomdp` returns: the policy's arrays, both bounds and the report."""

    hrc: HRCPomdp
    alphas: AlphaSet
    upper: UpperBound
    points_x: np.ndarray
    points: np.ndarray
    report: dict

    def policy(self) -> 'AlphaPolicy':
        pomdp = self.hrc.pomdp
        return AlphaPolicy(self.hrc.columns, self.alphas.alpha, self.alphas.action,
                           self.alphas.offsets, self.upper.q_fib, pomdp.available,
                           _n_columns(self.hrc.model))


def _n_columns(model: HRCModel) -> int:
    """The observable columns l * n_task * 4 + y * 4 + d of a model (l < 1 without a queue)."""
    return model.n_levels * model.n_task * N_DISTANCE


def case_study_targets(hrc: HRCPomdp) -> tuple[list, np.ndarray, np.ndarray]:
    """The case study's first beliefs (MODEL.md 7: task (1, 1, 3) at d = 1): b_1 after each
    O_1 (`BeliefFilter.initial`, bayes), as (names, x, b)."""
    model = hrc.model
    observable = (1, 1, 3, 0, 0, 0, 0, 0, 1)
    x1 = hrc.state(observable)
    filt = BeliefFilter(model, mode='bayes')
    names = [f'case study, b_1 after O_1 = {o}' for o in (1, 2, 3)]
    beliefs = np.array([filt.initial(o) for o in (1, 2, 3)])
    return names, np.full(3, x1), beliefs


def _starts(hrc: HRCPomdp) -> Starts:
    """The case study's start (true h = (0, 0)) and every task entering the idle cell at
    d = 1..3 with a human drawn from the person prior (`observation.prior`, else uniform: the
    humans of `hrc-evaluate`); every belief starts from that prior (b_1 ∝ prior * L[O_1], as
    `BeliefFilter.initial`). With a queue (MODEL.md 8.1) every start has none waiting (l = 0),
    as `hrc-evaluate`'s episodes; the queue fills by the model's releases."""
    prior = BeliefFilter(hrc.model, mode='bayes').prior
    _, tx, _ = case_study_targets(hrc)
    idle = hrc.column_index[np.arange(N_DISTANCE)]          # y = 0: the idle cell
    xs = [tx[0]] + [hrc.enter[idle[d], j] for d in (1, 2, 3) for j in range(len(hrc.tasks))]
    truth = np.vstack([np.eye(N_HIDDEN)[0]] + [prior] * (len(xs) - 1))
    return Starts(np.array(xs), truth, np.tile(prior, (len(xs), 1)))


def _fixed_points(hrc: HRCPomdp) -> tuple[np.ndarray, np.ndarray]:
    """At every x: the 9 corners, the filter's first beliefs under a uniform prior L[O] / sum
    L[O] and the Table 5 rows (with a person prior its first beliefs are among the case-study
    targets, which `_with_fixed` adds, and the sampled starts begin from it)."""
    n_x = hrc.pomdp.n_x
    lik = hrc.likelihood
    rows = np.vstack([np.eye(N_HIDDEN), lik / lik.sum(axis=1, keepdims=True),
                      hrc.model.config.observation_table])
    return np.repeat(np.arange(n_x), len(rows)), np.tile(rows, (n_x, 1))


def solve_pomdp(model: HRCModel, episodes: int = 2000, epochs: int = 50,
                per_state: int = 100, rounds: int = 1, tol: float = 1e-3,
                max_sweeps: int = 2000, seed: int = 0, explore: float = 0.2,
                resolution: float = 0.01, progress: Callable[[str], None] | None = None
                ) -> PomdpResult:
    """Solve the HRC POMDP of `model` (see the module docstring).

    Round 0 gathers beliefs from `episodes` simulated episodes of `epochs` epochs acting by
    the fast informed bound (with probability `explore` a random action), thins them to at
    most `per_state` distinct beliefs per x at `resolution`, adds the fixed points and sweeps
    both bounds until neither moves by `tol`; each further round gathers as many episodes
    acting by the current lower bound's policy, adds their beliefs and sweeps again.
    """
    say = progress or (lambda message: None)
    t0 = time.perf_counter()
    op = FactoredBellman(model)
    hrc = hrc_pomdp(model, op)
    pomdp = hrc.pomdp
    # A queue's successors are many (up to 96 per action where the cell goes idle, 12 on
    # average): the bounds' sums by the sparse kernels. Without a queue the arithmetic that
    # solved the shipped policies, bit for bit.
    fast = model.queue is not None
    q_mdp = mdp_q(pomdp, tol=1e-9, fast=fast)
    q_fib, fib_sweeps = fib_q(pomdp, tol=1e-9, start=q_mdp, fast=fast)
    alphas = blind_alpha_set(pomdp, blind_alphas(pomdp, tol=1e-9, fast=fast))
    n_x = pomdp.n_x
    t_bounds = time.perf_counter()
    levels = '' if model.queue is None else f' x {model.n_levels} queue lengths'
    say(f'{n_x} observable states ({n_x // N_DISTANCE // model.n_levels} task states x '
        f'{N_DISTANCE} distances{levels}), FIB {fib_sweeps} sweeps, {t_bounds - t0:.1f} s')
    names, tx, tb = case_study_targets(hrc)
    starts = _starts(hrc)
    fixed_x, fixed_b = _with_fixed(tx, tb, *_fixed_points(hrc))
    points_x, points = fixed_x, fixed_b
    upper = UpperBound.from_fib(q_fib, pomdp.available, points_x, points)
    sweeps = []

    def show(row, name):
        if row['sweep'] % 25 == 0 or row['sweep'] == 1:
            say(f'{name} sweep {row["sweep"]:4d}: {row["vectors"]} vectors, lower '
                f'+{row["lb_change"]:.2e}, upper -{row["ub_change"]:.2e}, gap at the case '
                f'study {100 * row["target_gap"]:.3f}%, {row["elapsed"]:.1f} s')
    # Warm start: the fixed points alone (corners, first beliefs, Table 5 rows at every x)
    # converge in a fraction of the time and lift the blind vectors for the sampled points.
    alphas, upper, history = backup_sweeps(pomdp, points_x, points, alphas, upper, max_sweeps,
                                           tol, (tx, tb), lambda row: show(row, 'fixed'),
                                           share=fast, perseus=fast)
    sweeps.append(len(history))
    say(f'fixed points: {len(points_x)} points, {len(history)} sweeps, {len(alphas)} vectors')
    for r in range(rounds + 1):
        policy = (q_policy(pomdp, q_fib) if r == 0
                  else AlphaPolicy.from_set(alphas, q_fib, pomdp.available, hrc).act)
        # A stream model's successors hold its arrivals (and its queue's); the paper's model
        # gets the hrc-evaluate task stream from outside.
        streamed = model.arrivals is not None or model.queue is not None
        enter = None if streamed else hrc.enter
        xs, bs = sample_beliefs(pomdp, hrc.likelihood, starts, policy, episodes, epochs,
                                seed=seed + r, explore=explore, enter=enter)
        points_x, points = thin_points(np.concatenate([points_x, xs]), np.vstack([points, bs]),
                                       resolution, per_state, seed=seed + r)
        points_x, points = _with_fixed(points_x, points, fixed_x, fixed_b)
        upper = UpperBound(q_fib, pomdp.available, upper.corner, points_x, points,
                           upper.evaluate(points_x, points))
        alphas, upper, history = backup_sweeps(pomdp, points_x, points, alphas, upper,
                                               max_sweeps, tol, (tx, tb),
                                               lambda row, r=r: show(row, f'round {r}'),
                                               share=fast, perseus=fast)
        sweeps.append(len(history))
        say(f'round {r}: {len(points_x)} points, {len(history)} sweeps, {len(alphas)} '
            f'vectors, gap at the case study {100 * history[-1]["target_gap"]:.3f}%')
    t_end = time.perf_counter()
    lower = np.array([(alphas.alpha[alphas.offsets[x]:alphas.offsets[x + 1]] @ b).max()
                      for x, b in zip(points_x, points)])
    upper_values = upper.evaluate(points_x, points)
    gap = upper_values - lower
    target_lower = np.array([(alphas.alpha[alphas.offsets[x]:alphas.offsets[x + 1]] @ b).max()
                             for x, b in zip(tx, tb)])
    target_upper = upper.evaluate(tx, tb)
    relative = (target_upper - target_lower) / np.abs(target_lower)
    report = {
        'family': 'point-based value iteration (PBVI sweeps, Perseus improvement rule) with '
                  'fast-informed-bound and sawtooth upper bound',
        'observable_states': int(n_x), 'points': int(len(points_x)),
        'fixed_points': int(len(fixed_x)),
        'vectors': int(len(alphas)), 'rounds': rounds, 'sweeps': sweeps,
        'episodes': episodes, 'epochs': epochs, 'per_state': per_state, 'tol': tol,
        'explore': explore, 'resolution': resolution, 'seed': seed,
        'fib_sweeps': int(fib_sweeps),
        'targets': [{'name': n, 'lower': float(lo), 'upper': float(hi),
                     'gap': float(hi - lo), 'relative_gap': float(rel)}
                    for n, lo, hi, rel in zip(names, target_lower, target_upper, relative)],
        'case_study_relative_gap': float(relative.max()),
        'points_gap': {'mean': float(gap.mean()), 'median': float(np.median(gap)),
                       'p95': float(np.quantile(gap, 0.95)), 'max': float(gap.max()),
                       'mean_relative': float(np.mean(gap / np.maximum(1.0, np.abs(lower))))},
        'seconds': {'bounds': t_bounds - t0, 'total': t_end - t0},
    }
    return PomdpResult(hrc, alphas, upper, points_x, points, report)


def report_lines(report: dict) -> list[str]:
    """The bounds of a solve's report as lines: the gap at each case-study target and over
    the belief points (hrc-solve and bench/pomdp_bench.py print them)."""
    lines = [f'{t["name"]}: lower {t["lower"]:.4f}, upper {t["upper"]:.4f}, gap {t["gap"]:.4f} '
             f'({100 * t["relative_gap"]:.3f}%)' for t in report['targets']]
    g = report['points_gap']
    lines.append(f'{report["points"]} belief points: gap mean {g["mean"]:.4f}, median '
                 f'{g["median"]:.4f}, p95 {g["p95"]:.4f}, max {g["max"]:.4f}; '
                 f'{report["vectors"]} vectors over {report["observable_states"]} observable '
                 f'states; sweeps {report["sweeps"]}; {report["seconds"]["total"]:.1f} s')
    return lines


def _with_fixed(points_x, points, fixed_x, fixed_b):
    """The points with the fixed ones always present (thinning may have dropped some)."""
    x = np.concatenate([points_x, fixed_x])
    b = np.vstack([points, fixed_b])
    key = np.round(b * 1e9).astype(np.int64)
    _, first = np.unique(np.column_stack([x, key]), axis=0, return_index=True)
    first = first[np.argsort(x[first], kind='stable')]
    return x[first], np.ascontiguousarray(b[first])


# -- the policy online ---------------------------------------------------------------------------
class AlphaPolicy:
    """The solved POMDP over its observable states, for selection (pomdp and fib).

    `columns[i]` is the observable column (l * n_task * 4 + y * 4 + d, l the queue length of
    MODEL.md 8.1, 0 without a queue: `ActionSelector`'s column offset by l times the columns of
    a level, as the flat index is) of solved state i; Gamma(i) =
    `alpha[offsets[i]:offsets[i+1]]` with `action`; `q_fib[i]` (A, H) the fast informed
    bound's Q. pomdp: the action of the best vector for (x, b), vectors within the tie
    tolerance of the best go to the first action of the safety order; scores[a] = the best
    value of a's vectors (-inf where a has none). fib: argmax_a b . Q_fib(x, a) over the
    available actions, ties likewise; scores = b . Q_fib(x, a) (-inf where unavailable).
    """

    def __init__(self, columns, alpha, action, offsets, q_fib, available, n_columns: int):
        self.columns = np.asarray(columns, dtype=np.int64)
        self.alpha = np.ascontiguousarray(alpha, dtype=float)
        self.action = np.asarray(action, dtype=np.intp)
        self._actions = self.action.tolist()
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.q_fib = np.asarray(q_fib, dtype=float)
        self.available = np.asarray(available, dtype=bool)
        self.column_index = np.full(int(n_columns), -1, dtype=np.intp)
        self.column_index[self.columns] = np.arange(len(self.columns))
        rank = np.empty(len(SAFETY_ORDER), dtype=np.intp)      # position in the safety order
        rank[np.array(SAFETY_ORDER)] = np.arange(len(SAFETY_ORDER))
        # dense (X, M, H) copy for selecting many at once; padding never wins
        counts = np.diff(self.offsets)
        width = int(counts.max())
        owner = np.repeat(np.arange(len(counts)), counts)
        slot = np.arange(len(self.alpha)) - self.offsets[owner]
        self.dense = np.zeros((len(counts), width, self.alpha.shape[1]))
        self.dense[owner, slot] = self.alpha
        self.dense_valid = np.zeros((len(counts), width), dtype=bool)
        self.dense_valid[owner, slot] = True
        self.dense_rank = np.full((len(counts), width), len(SAFETY_ORDER), dtype=np.intp)
        self.dense_rank[owner, slot] = rank[self.action]

    @classmethod
    def from_set(cls, alphas: AlphaSet, q_fib, available, hrc: HRCPomdp) -> 'AlphaPolicy':
        return cls(hrc.columns, alphas.alpha, alphas.action, alphas.offsets, q_fib, available,
                   _n_columns(hrc.model))

    def state(self, column: int) -> int:
        i = int(self.column_index[column])
        if i < 0:
            raise ValueError('the observable state is not one the task book can produce, so '
                             'the POMDP policy does not cover it (solved: the task states '
                             'reachable from an idle cell with tasks entering it)')
        return i

    def states(self, columns) -> np.ndarray:
        i = self.column_index[np.asarray(columns, dtype=np.intp)]
        if np.any(i < 0):
            self.state(int(np.asarray(columns)[np.argmax(i < 0)]))
        return i

    def pomdp(self, b: np.ndarray, column: int) -> tuple[int, np.ndarray]:
        """(action, scores (A,)) of the best vector at (x, b). An action is tied when its best
        vector is within the tolerance of the best, so the tie rule works on the scores."""
        i = self.state(column)
        lo, hi = int(self.offsets[i]), int(self.offsets[i + 1])
        scores = [-np.inf] * self.q_fib.shape[1]
        for v, a in zip((self.alpha[lo:hi] @ b).tolist(), self._actions[lo:hi]):
            if v > scores[a]:
                scores[a] = v
        return safest_best_one(scores, SAFETY_ORDER), np.array(scores)

    def fib(self, b: np.ndarray, column: int) -> tuple[int, np.ndarray]:
        i = self.state(column)
        # -inf after the product: -inf * b(h) = nan where b(h) = 0
        scores = np.where(self.available[i], self.q_fib[i] @ b, -np.inf)
        return int(first_of_best(scores[None, :])[0]), scores

    def pomdp_many(self, b: np.ndarray, columns) -> np.ndarray:
        i = self.states(columns)
        values = np.einsum('emh,eh->em', self.dense[i], b)
        values = np.where(self.dense_valid[i], values, -np.inf)
        best = values.max(axis=1, keepdims=True)
        tied = values >= tie_floor(best)
        rank = np.where(tied, self.dense_rank[i], len(SAFETY_ORDER))
        return np.array(SAFETY_ORDER)[rank.min(axis=1)]

    def fib_many(self, b: np.ndarray, columns) -> np.ndarray:
        i = self.states(columns)
        return first_of_best(np.where(self.available[i],
                                      np.einsum('eah,eh->ea', self.q_fib[i], b), -np.inf))

    def act(self, x: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The pomdp action for solved-state indices x (the sampler's policy)."""
        return self.pomdp_many(b, self.columns[x])
