"""Solving the HRC MDP (MODEL.md section 5) with the factored Bellman operator: no N x N matrix.

The Bellman operator is

    (T V)(s) = max_a { -J(s, a) + gamma * sum_s' P(s' | s, a) V(s') }.

With the flat layout V[h, y, d] (hidden emotions h, task/activity part y, distance d), one
transition is: an emotion step h -> h' (9x9 matrix E_g of the action's group g), a distance step
d -> d' (4x4 matrix D_a[ea] chosen by the action and the *current* aggression), and a
deterministic task step y -> y' = T_a(y, accepted). These commute in the right order:

    E[V(s') | s, a] = sum_acc P(acc | em, y, a) * U_a[h, T_a(y, acc), d],
    U_a[h, y', d]   = sum_d' D_a[ea(h)][d, d'] * sum_h' E_g[h, h'] V[h', y', d'].

So a sweep is one 27x9 matrix product (the three emotion groups), a few batched 4x4 distance
products, and gathers along y. ct differs from nw only where it is effective
(`model.commit_effective`), requests only where eligible (`model.request_eligible`), dn only by
the paused robot counter; dp and dm step the task as nw does, or as dn does where the
configuration pauses the robot under them (`model.robot_paused_by`, the cell with an arm). With
`model.robot_rate` (MODEL.md 3.2) every action under which the robot works has two task
successors, its own (the counter runs) and the paused one, mixed by the rate at (tx(y), d)
after the distance step (the run is independent of the person and of Delta).

`FactoredBellman` is the operator, in two forms of one definition:

- `q(V)`: the full Q (8, N), numpy: the reference form, used for the greedy policy, QMDP and
  the tests (which hold it equal to `HRCModel.transition`, the rule-by-rule model);
- `apply(V)`: (T V, max|T V - V|), the fused numba kernel of `_kernels`: the fast path of a
  value-iteration sweep (the tests hold it equal to ``q(V).max(axis=0)``).

With `solver.fail_safe_aware` only dn is available at d = 0 (the other actions' Q there is
-inf), so the policy plans with the decision node's fail-safe instead of against it.

With a task stream (MODEL.md 8, `HRCModel.arrivals`) a step that leaves the cell idle is
followed by an arrival: U is mixed along y' before the gather, U'[y'] = (1 - p) U[y'] + p sum_k
q_k U[enter(y', k)] at the idle y', once with p = arrival_complete (read by the sources with a
task) and once with p = arrival_idle (read by the idle sources, through task maps offset by
n_y into the second copy). The arrival is independent of h and d, so it commutes with the
emotion and distance steps. Without a stream nothing of this runs and the sweep is the one it
always was, bit for bit.

With a queue (MODEL.md 8.1, `HRCModel.queue`) V is (L + 1) copies of the paper's layout, the
queue length l outermost. The release and the head's entry act on (l, y') only, so they too
commute with the emotion and distance steps: the continuation of every level is mixed
(`_queue_arrive`, `_kernels.queue_continuations`) into a busy-source and an idle-source copy
per source level (the offsets above), the drop charge subtracted where a release meets a full
queue, and the gather and max run per level with the cost J + w l.

Solvers, in the shape of QuantEcon's ``ddp.py``: `value_iteration` (MODEL.md 5: from V_0 = 0
until ``max|V_{t+1} - V_t| < eta``, or a fixed number of sweeps) and `policy_iteration`
(Howard's: exact evaluation by a sparse linear solve, greedy improvement, until the policy is
stable; an independent check, slower here than the fused sweeps). `solve(model, method=...)`
dispatches to them. Each returns a `SolveResult` whose fields mean the same for every method.
The policy is greedy with the safety tie order (MODEL.md 5, `model.safest_best`): actions
within ``TIE_TOLERANCE * max(1, |V|)`` of the best go to the first of ``dn, dp, nw, ct, rh1,
rh2, mh, dm``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..config import MAX_SWEEPS
from ..model import (ACTIONS, CT, DM, DN, DP, MH, N_DISTANCE, N_HIDDEN, NW, RH1, RH2, HRCModel,
                     commit_effective, request_eligible, safest_best, tie_floor)

SOLVER_VERSION = '2.0'
METHODS = ('value_iteration', 'policy_iteration')


@dataclass
class SolveResult:
    """What every solver returns (the shape of QuantEcon's DPSolveResult).

    The fields mean the same for every method: `iterations` counts the method's own steps
    (value iteration: Bellman sweeps; policy iteration: evaluate-and-improve rounds),
    `converged` says whether its stopping rule was met (rather than an iteration limit), and
    `residual` is the Bellman residual ``max_s |(T V)(s) - V(s)|`` of the returned value,
    computed the same way after any method (so ``residual * gamma / (1 - gamma)`` bounds the
    distance of V to the optimum).
    """

    value: np.ndarray           # V, shape (N,)
    policy: np.ndarray          # action index per state, int8, shape (N,)
    method: str
    iterations: int
    converged: bool
    residual: float
    timings: dict = field(default_factory=dict)  # seconds: build, iterate, policy, total


class FactoredBellman:
    """Precomputed pieces of the factored Bellman operator for one model."""

    def __init__(self, model: HRCModel):
        self.model = model
        self.gamma = model.gamma
        n_y = self.n_y = model.n_task
        grid = model.task_grid
        self.shape = (N_HIDDEN, n_y, N_DISTANCE)

        def task_map(action, accepted):
            return model.task_index(model.step_task(grid, action, accepted)).astype(np.intp)

        # Deterministic task steps y -> y'.
        self.t_default = task_map(NW, False)        # nw mh, refused requests, idle ct
        self.t_pause = task_map(DN, False)          # dn: the robot's counter is paused
        # dp, dm: t_default, or t_pause where the configuration pauses the robot under them
        self.dp_paused, self.dm_paused = DP in model.paused, DM in model.paused
        self.t_dp = self.t_pause if self.dp_paused else self.t_default
        self.t_dm = self.t_pause if self.dm_paused else self.t_default
        tp, tx, ty = grid['tp'], grid['tx'], grid['ty']
        self.ct_effective = np.flatnonzero(commit_effective(tp, tx, ty))
        t_ct = task_map(CT, False)                  # equals t_default where ct is ineffective
        self.t_commit = t_ct[self.ct_effective]
        # Where a request is eligible: rh1 or rh2, never both (the subsets are disjoint).
        rh1_eligible = request_eligible(RH1, tp, tx, ty)
        rh2_eligible = request_eligible(RH2, tp, tx, ty)
        self.request_y = np.flatnonzero(rh1_eligible | rh2_eligible)
        self.request_is_rh2 = rh2_eligible[self.request_y]
        rh1_accept = task_map(RH1, True)
        rh2_accept = task_map(RH2, True)
        self.t_accept = np.where(self.request_is_rh2, rh2_accept[self.request_y],
                                 rh1_accept[self.request_y])
        # model.robot_rate (MODEL.md 3.2): where the robot works its counter runs down with
        # probability rate[tx, d], else it stays as under a pause: every working action's
        # successor mixes its own task map (run) with the paused one, per y and d
        self.rated = model.robot_rate is not None
        self.rate_yd = np.ascontiguousarray(model.robot_rate[grid['tx']] if self.rated
                                            else np.ones((n_y, N_DISTANCE)))
        paused = {a: model.task_index(model.step_task(grid, a, True, False)).astype(np.intp)
                  for a in (RH1, RH2)}
        self.t_accept_pause = np.where(self.request_is_rh2, paused[RH2][self.request_y],
                                       paused[RH1][self.request_y])

        self.p_accept_vector = np.repeat(model.config.p_accept, 3)   # by h = 3*em + ea
        self.p_accept_h = self.p_accept_vector[:, None, None]

        # Emotion step, stacked: rows 0-8 base, 9-17 motivate, 18-26 request.
        e = model.emotion_matrices
        self.emotion = np.vstack([e['base'], e['motivate'], e['request']])
        # Distance step by h (through ea), transposed for right-multiplication:
        # U[h] = W[h] @ D[ea(h)].T.
        ea_of_h = np.arange(N_HIDDEN) % 3

        def dist(action):
            return np.ascontiguousarray(model.distance_matrix(action)[ea_of_h]
                                        .transpose(0, 2, 1))

        self.dist_base = np.concatenate([dist(NW), dist(DP), dist(DM)], axis=2)  # (9,4,12)
        self.dist_other = dist(NW)
        self.cost = model.state_cost_vector.reshape(self.shape)  # k1*f1 + k2*f2
        self.g = model.action_cost
        self.fail_safe_aware = model.config.fail_safe_aware

        # Inputs of the fused kernels (_kernels): the same pieces, indexed per y.
        self.gamma_emotion = (self.gamma * self.emotion).reshape(3, N_HIDDEN, N_HIDDEN)
        self.t_commit_full = np.full(n_y, -1, dtype=np.intp)
        self.t_commit_full[self.ct_effective] = self.t_commit
        self.t_accept_full = np.full(n_y, -1, dtype=np.intp)
        self.t_accept_full[self.request_y] = self.t_accept
        self.t_accept_pause_full = np.full(n_y, -1, dtype=np.intp)
        self.t_accept_pause_full[self.request_y] = self.t_accept_pause
        # mix[group, ea, d', d] = P(d' | d, ea) for the groups (other, dp, dm)
        self.mix = np.ascontiguousarray(np.stack(
            [model.distance_matrix(a).transpose(0, 2, 1) for a in (NW, DP, DM)])
            .reshape(3, 3, 16))
        # The stream (MODEL.md 8): the continuation is mixed over the arrivals at the idle y'
        # (`_arrive`); the idle sources read the arrival_idle copy, offset by n_y.
        arrivals = self.arrivals = model.arrivals
        queue = self.queue = model.queue
        if queue is not None:   # MODEL.md 8.1: the same two copies, per queue level
            arrivals = queue.arrivals
        if arrivals is None:
            offset = np.zeros(n_y, dtype=np.intp)
            self.arrive_y = np.zeros(0, dtype=np.intp)
            self.arrive_enter = np.zeros((0, 1), dtype=np.intp)
            self.arrive_q = np.zeros(1)
            self.arrive_p = (0.0, 0.0)
        else:
            offset = np.where(arrivals.idle, n_y, 0).astype(np.intp)
            self.arrive_y = np.flatnonzero(arrivals.idle).astype(np.intp)
            self.arrive_enter = np.ascontiguousarray(arrivals.enter[self.arrive_y])
            self.arrive_q = np.asarray(arrivals.q, dtype=float)
            self.arrive_p = (arrivals.p_idle, arrivals.p_complete)
        self.n_w = n_y if arrivals is None else 2 * n_y
        self.n_levels = model.n_levels
        if queue is not None:
            self.busy_y = np.flatnonzero(~arrivals.idle).astype(np.intp)
            w_wait = queue.waiting_cost
            self.level_cost = np.stack([self.cost + w_wait * lv for lv in range(self.n_levels)])
            self._z = None
        self.g_default = self.t_default + offset
        self.g_pause = self.t_pause + offset
        self.g_dp = self.t_dp + offset
        self.g_dm = self.t_dm + offset
        self.g_commit_full = np.where(self.t_commit_full >= 0, self.t_commit_full + offset, -1)
        self.g_accept_full = np.where(self.t_accept_full >= 0, self.t_accept_full + offset, -1)
        self.g_accept_pause_full = np.where(self.t_accept_pause_full >= 0,
                                            self.t_accept_pause_full + offset, -1)
        self._w = None
        self._residual = np.empty(n_y)

    # -- building blocks ---------------------------------------------------------------
    def _continuations(self, value: np.ndarray):
        """gamma * U for (nw, dp, dm) [base], mh [motivate], requests [request]."""
        v = value.reshape(N_HIDDEN, -1)
        w = (self.emotion @ v).reshape(3, N_HIDDEN, self.n_y, N_DISTANCE)
        w *= self.gamma
        base = np.matmul(w[0], self.dist_base)          # (9, n_y, 12): nw | dp | dm
        motivate = np.matmul(w[1], self.dist_other)
        request = np.matmul(w[2], self.dist_other)
        return self._arrive(base), self._arrive(motivate), self._arrive(request)

    def _queue_arrive(self, units: list) -> list:
        """The queue's mix (MODEL.md 8.1) of the continuations U[l'] (9, n_y, m), one per queue
        level l': per source level l the [busy-source, idle-source] copies along y (9, 2 n_y,
        m). A release has probability p (arrival_busy, arrival_idle by the copy); at y' with a
        task it waits (l + 1; at L it is dropped and charged drop_cost); at an idle y' the head
        enters (sum_k q_k U[enter(y', k)] at l - 1 without a release, at l with one) or, with no
        task waiting, the cell stays idle."""
        queue, top = self.queue, self.n_levels - 1
        rows, busy = self.arrive_y, self.busy_y
        p_idle, p_busy = self.arrive_p
        entered = [np.einsum('hykm,k->hym', u[:, self.arrive_enter], self.arrive_q) for u in units]
        out = []
        for lv in range(self.n_levels):
            copies = []
            for p in (p_busy, p_idle):
                c = np.empty_like(units[lv])
                more = (units[lv + 1][:, busy] if lv < top
                        else units[top][:, busy] - queue.drop_cost)
                c[:, busy] = (1.0 - p) * units[lv][:, busy] + p * more
                below = entered[lv - 1] if lv > 0 else units[0][:, rows]
                c[:, rows] = (1.0 - p) * below + p * entered[lv]
                copies.append(c)
            out.append(np.concatenate(copies, axis=1))
        return out

    def _arrive(self, u: np.ndarray) -> np.ndarray:
        """U (9, n_y, m) with the stream's arrival at the idle y': [arrival_complete form,
        arrival_idle form] along y (9, 2 n_y, m); U itself without a stream."""
        if self.arrivals is None:
            return u
        rows = self.arrive_y
        mixed = np.einsum('hykm,k->hym', u[:, self.arrive_enter], self.arrive_q)
        p_idle, p_complete = self.arrive_p
        busy, idle = u.copy(), u.copy()
        busy[:, rows] = (1.0 - p_complete) * u[:, rows] + p_complete * mixed
        idle[:, rows] = (1.0 - p_idle) * u[:, rows] + p_idle * mixed
        return np.concatenate([busy, idle], axis=1)

    def q(self, value: np.ndarray) -> np.ndarray:
        """Full Q(s, a) = -J(s, a) + gamma E[V(s') | s, a], shape (8, N): the reference form."""
        if self.queue is not None:
            return self._queue_q(value)
        base, motivate, request = self._continuations(value)
        return self._gather(base, motivate, request, self.cost).reshape(len(ACTIONS), -1)

    def _queue_q(self, value: np.ndarray) -> np.ndarray:
        """`q` with the queue (MODEL.md 8.1): the continuations of every level, mixed along
        (l, y') by `_queue_arrive`, then the gather of each source level with its cost."""
        value = np.asarray(value).reshape(self.n_levels, -1)
        parts = [self._continuations(v) for v in value]   # unmixed (self.arrivals is None)
        mixed = [self._queue_arrive([p[i] for p in parts]) for i in range(3)]
        q = [self._gather(mixed[0][lv], mixed[1][lv], mixed[2][lv], self.level_cost[lv])
             for lv in range(self.n_levels)]
        return np.concatenate([x.reshape(len(ACTIONS), -1) for x in q], axis=1)

    def _gather(self, base, motivate, request, cost) -> np.ndarray:
        """Q (8, 9, n_y, 4) from the continuations along y' (the task maps, per action) and
        the state cost."""
        nw = base[..., 0:4]
        work = self._working
        q = np.empty((len(ACTIONS),) + self.shape)
        q[NW] = work(nw, self.g_default)
        q[DP] = work(base[..., 4:8], self.g_dp, works=not self.dp_paused)
        q[DM] = work(base[..., 8:12], self.g_dm, works=not self.dm_paused)
        q[MH] = work(motivate, self.g_default)
        q[DN] = nw[:, self.g_pause]
        q[CT] = q[NW]
        q[CT][:, self.ct_effective] = nw[:, self.g_commit_full[self.ct_effective]]
        refused = work(request, self.g_default)
        q[RH1] = refused
        q[RH2] = refused
        ry = self.request_y
        accepted = work(request, self.g_accept_full[ry], self.g_accept_pause_full[ry], ry)
        mixed = refused[:, ry] + self.p_accept_h * (accepted - refused[:, ry])
        rh2 = self.request_is_rh2
        q[RH1][:, ry[~rh2]] = mixed[:, ~rh2]
        q[RH2][:, ry[rh2]] = mixed[:, rh2]
        q -= cost
        q -= self.g[:, None, None, None]
        unavailable = ~self.model.availability                     # (8, 4): by action and d
        q[np.broadcast_to(unavailable[:, None, None, :], q.shape)] = -np.inf
        return q

    def _working(self, continuation, rows, paused_rows=None, ys=None,
                 works: bool = True) -> np.ndarray:
        """The continuation (9, n_w, 4) of an action read at its successor `rows` (one per y
        of `ys`, every y by default): with model.robot_rate, where the robot `works` under
        it, mixed per (y, d) with the paused successors `paused_rows` (the pause's, g_pause,
        by default) by the rate; as it is without a rate or for an action that pauses."""
        if not self.rated or not works:
            return continuation[:, rows]
        paused_rows = self.g_pause if paused_rows is None else paused_rows
        rate = self.rate_yd if ys is None else self.rate_yd[ys]
        pause = continuation[:, paused_rows]
        return pause + rate * (continuation[:, rows] - pause)

    def apply(self, value: np.ndarray, out: np.ndarray | None = None
              ) -> tuple[np.ndarray, float]:
        """(T V, max |T V - V|): one sweep by the fused kernel (`_kernels.sweep`)."""
        from . import _kernels   # numba: imported where a sweep runs, not by the nodes
        if out is None:
            out = np.empty(self.model.n_states)
        if self.queue is not None:
            return self._queue_apply(value, out)
        if self._w is None:
            self._w = np.empty((3, N_HIDDEN, self.n_w, N_DISTANCE))
        _kernels.sweep(self.gamma_emotion, self.g_default, self.g_pause, self.g_commit_full,
                       self.g_accept_full, self.p_accept_vector, self.mix, self.g, self.cost,
                       self.fail_safe_aware, self.dp_paused, self.dm_paused,
                       self.arrive_y, self.arrive_enter, self.arrive_q,
                       self.arrive_p[0], self.arrive_p[1],
                       np.ascontiguousarray(value).reshape(self.shape),
                       self._w, out.reshape(self.shape), self._residual, False,
                       self.rated, self.rate_yd, self.g_accept_pause_full)
        return out, float(self._residual.max())

    def _queue_apply(self, value: np.ndarray, out: np.ndarray) -> tuple[np.ndarray, float]:
        """`apply` with the queue (MODEL.md 8.1): `_kernels.queue_continuations` forms the
        mixed continuations of every source level, then the sweep's action pass runs per level
        on them (its emotion and arrival steps skipped)."""
        from . import _kernels
        n_l = self.n_levels
        if self._z is None:
            self._z = np.empty((n_l, 3, N_HIDDEN, self.n_y, N_DISTANCE))
            self._w = np.empty((n_l, 3, N_HIDDEN, self.n_w, N_DISTANCE))
            self._level_residual = np.empty((n_l, self.n_y))
        levels = (n_l,) + self.shape
        value = np.ascontiguousarray(value).reshape(levels)
        result = out.reshape(levels)
        p_idle, p_busy = self.arrive_p
        _kernels.queue_continuations(self.gamma_emotion, self.busy_y, self.arrive_y,
                                     self.arrive_enter, self.arrive_q, p_idle, p_busy,
                                     self.queue.drop_cost, value, self._z, self._w)
        for lv in range(n_l):
            _kernels.sweep(self.gamma_emotion, self.g_default, self.g_pause, self.g_commit_full,
                           self.g_accept_full, self.p_accept_vector, self.mix, self.g,
                           self.level_cost[lv], self.fail_safe_aware, self.dp_paused,
                           self.dm_paused, self.arrive_y, self.arrive_enter, self.arrive_q,
                           p_idle, p_busy, value[lv], self._w[lv], result[lv],
                           self._level_residual[lv], True, self.rated, self.rate_yd,
                           self.g_accept_pause_full)
        return out, float(self._level_residual.max())

    def residual(self, value: np.ndarray) -> float:
        """The Bellman residual max |T V - V| of a value function."""
        return self.apply(value)[1]


BYTES_PER_STATE = 180        # value, spare, cost, kernel scratch, the policy step's Q and masks
STREAM_BYTES_PER_STATE = 180  # with a stream: the second scratch copy and q's arrival copies
RUNTIME_BYTES = 150 * 2**20  # python, numpy, scipy, numba


def memory_estimate(model: HRCModel) -> int:
    """Peak bytes of a value-iteration solve of `model`: about BYTES_PER_STATE per state plus
    the runtime (bench/solve_bench.py measures 227 MB at 0.42 M states, 1.6 GB at 9 M)."""
    streamed = model.arrivals is not None or model.queue is not None
    per_state = BYTES_PER_STATE + (STREAM_BYTES_PER_STATE if streamed else 0)
    return per_state * model.n_states + RUNTIME_BYTES


def greedy_policy(q: np.ndarray) -> np.ndarray:
    """Argmax over actions (axis 0) with the safety tie order of MODEL.md 5."""
    return safest_best(q, axis=0).astype(np.int8)


def policy_matrix(model: HRCModel, policy: np.ndarray):
    """P_pi (N x N, scipy.sparse CSR) and the cost vector c_pi of a fixed policy."""
    from scipy import sparse

    rows, cols, vals = [], [], []
    cost = np.empty(model.n_states)
    for a in range(len(ACTIONS)):
        sources = np.flatnonzero(policy == a)
        if sources.size == 0:
            continue
        t = model.transition(sources, a)
        rows.append(sources[t.source])
        cols.append(t.target)
        vals.append(t.probability)
        cost[sources] = model.flat_cost(sources, a)
    p = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(model.n_states, model.n_states))
    p.sum_duplicates()
    return p, cost


def evaluate_policy(model: HRCModel, policy: np.ndarray, tol: float = 1e-12) -> np.ndarray:
    """V_pi: the solution of (I - gamma P_pi) V = -c_pi (BiCGSTAB, warm-started by sweeps)."""
    from scipy import sparse
    from scipy.sparse.linalg import bicgstab

    p, cost = policy_matrix(model, policy)
    a = sparse.identity(model.n_states, format='csr') - model.gamma * p
    value, info = bicgstab(a, -cost, rtol=tol, atol=0.0, maxiter=10_000)
    if info != 0:
        raise RuntimeError(f'policy evaluation did not converge (bicgstab info={info})')
    return value


def value_iteration(model: HRCModel, eta: float | None = None, sweeps: int | None = None,
                    progress: Callable[[int, float, float], None] | None = None,
                    operator: FactoredBellman | None = None,
                    start: np.ndarray | None = None) -> SolveResult:
    """Value iteration from V_0 = 0 (MODEL.md 5), or from `start` (a nearby model's values:
    the same fixed point, in fewer sweeps; the plant's refits start from the fit's).

    Stops when ``max|V_{t+1} - V_t| < eta`` or, with `sweeps`, after exactly that many sweeps
    (the paper's fixed count); both default to the configuration's. A run to eta stops after
    `MAX_SWEEPS` sweeps at the latest (`converged` False then: gamma too close to 1). The policy
    is the greedy argmax of the last sweep's Q, as a textbook value iteration reports it.
    `progress(sweep, max|V_{t+1} - V_t|, elapsed_seconds)` is called after every sweep.
    """
    cfg = model.config
    eta = cfg.eta if eta is None else float(eta)
    sweeps = cfg.sweeps if sweeps is None else sweeps
    if sweeps is not None and (isinstance(sweeps, bool) or int(sweeps) != sweeps
                               or not 1 <= sweeps <= MAX_SWEEPS):
        raise ValueError(f'sweeps must be an integer in 1..{MAX_SWEEPS}, got {sweeps!r}')
    if not eta > 0:
        raise ValueError(f'eta must be > 0, got {eta!r}')
    t0 = time.perf_counter()
    op = operator or FactoredBellman(model)
    t_built = time.perf_counter()
    value = np.zeros(model.n_states) if start is None else np.array(start, dtype=float)
    if value.shape != (model.n_states,):
        raise ValueError(f'start has shape {value.shape}; the model has {model.n_states} states')
    spare = np.empty(model.n_states)
    n = 0
    while True:
        new_value, change = op.apply(value, out=spare)
        n += 1
        if progress is not None:
            progress(n, change, time.perf_counter() - t0)
        if (sweeps is None and change < eta) or n >= (sweeps or MAX_SWEEPS):
            break
        value, spare = new_value, value
    t_iterated = time.perf_counter()
    policy = greedy_policy(op.q(value))
    residual = op.residual(new_value)
    t_end = time.perf_counter()
    return SolveResult(
        value=new_value, policy=policy, method='value_iteration', iterations=n,
        converged=change < eta, residual=residual,
        timings={'build': t_built - t0, 'iterate': t_iterated - t_built,
                 'policy': t_end - t_iterated, 'total': t_end - t0})


def policy_iteration(model: HRCModel, max_iterations: int = 100,
                     progress: Callable[[int, float, float], None] | None = None,
                     operator: FactoredBellman | None = None) -> SolveResult:
    """Howard's policy iteration: evaluate the policy exactly (`evaluate_policy`), improve it
    greedily (keeping the current action where it is still within the tie tolerance of the
    best, so ties cannot make it cycle), until it is stable or `max_iterations` rounds ran.
    `progress(round, max|T V - V|, elapsed_seconds)` is called after every round."""
    if isinstance(max_iterations, bool) or int(max_iterations) != max_iterations \
            or max_iterations < 1:
        raise ValueError(f'max_iterations must be an integer >= 1, got {max_iterations!r}')
    t0 = time.perf_counter()
    op = operator or FactoredBellman(model)
    t_built = time.perf_counter()
    policy = greedy_policy(op.q(np.zeros(model.n_states)))
    rounds, stable = 0, False
    while rounds < max_iterations:
        value = evaluate_policy(model, policy)
        q = op.q(value)
        rounds += 1
        best = q.max(axis=0)
        residual = float(np.max(np.abs(best - value)))
        if progress is not None:
            progress(rounds, residual, time.perf_counter() - t0)
        improved = greedy_policy(q)
        current = q[policy.astype(np.intp), np.arange(model.n_states)]
        keep = current >= tie_floor(best)
        improved[keep] = policy[keep]
        if np.array_equal(improved, policy):
            stable = True
            break
        policy = improved
    t_end = time.perf_counter()
    return SolveResult(value=value, policy=policy, method='policy_iteration',
                       iterations=rounds, converged=stable, residual=residual,
                       timings={'build': t_built - t0, 'iterate': t_end - t_built,
                                'policy': 0.0, 'total': t_end - t0})


def solve(model: HRCModel, method: str = 'value_iteration', **options) -> SolveResult:
    """Solve the model with `method` (one of `METHODS`); `options` go to that solver."""
    solvers = {'value_iteration': value_iteration, 'policy_iteration': policy_iteration}
    if method not in solvers:
        raise ValueError(f'unknown method {method!r}; available: {", ".join(METHODS)}')
    return solvers[method](model, **options)
