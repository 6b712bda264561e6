"""Value iteration on the factored HRC model (MODEL.md section 5), with no N x N matrix.

The Bellman operator is

    (T V)(s) = max_a { -J(s, a) + gamma * sum_s' P(s' | s, a) V(s') }.

With the flat layout V[h, y, d] (hidden emotions h, task/activity part y, distance d), one
transition is: an emotion step h -> h' (9x9 matrix E_g of the action's group g), a distance step
d -> d' (4x4 matrix D_a[ea] chosen by the action and the *current* aggression), and a
deterministic task step y -> y' = T_a(y, accepted). These commute in the right order:

    E[V(s') | s, a] = sum_acc P(acc | em, y, a) * U_a[h, T_a(y, acc), d],
    U_a[h, y', d]   = sum_d' D_a[ea(h)][d, d'] * sum_h' E_g[h, h'] V[h', y', d'].

So a sweep is one 27x9 matrix product (the three emotion groups), a few batched 4x4 distance
products, and gathers along y. Further savings, all exact:

- nw, dp, dm, mh and the refused branch of rh1/rh2 share the default task step T0, and a max
  commutes with a gather by the same index, so their best value is taken *before* gathering;
- ct differs from nw only where it is effective, and requests matter only where eligible;
  those subsets (about 1/12 and 1/8 of y) are handled separately;
- dn differs from nw only by the paused robot counter, a gather of one array.

`bellman_q` gives the full Q (8 x N) for policy extraction and tests; `bellman_max` is the fast
sweep. With `solver.fail_safe_aware` only dn is available at d = 0 (the other actions' Q there
is -inf), so the policy plans with the decision node's fail-safe instead of against it. The policy is the greedy argmax of the final sweep's Q with the safety tie order
(MODEL.md 5): actions within ``1e-9 * max(1, |V|)`` of the best go to the first of
``dn, dp, nw, ct, rh1, rh2, mh, dm``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import _kernels
from .model import (ACTIONS, CT, DM, DN, DP, MH, N_DISTANCE, N_HIDDEN, NW, RH1, RH2,
                    SAFETY_ORDER, HRCModel, step_task)

SOLVER_VERSION = '1.0'
TIE_TOLERANCE = 1e-9


@dataclass
class SolveResult:
    """What `solve` returns (the shape of QuantEcon's DPSolveResult)."""

    value: np.ndarray           # V, shape (N,)
    policy: np.ndarray          # action index per state, int8, shape (N,)
    sweeps: int                 # Bellman sweeps run
    residual: float             # max |V_t - V_{t-1}| of the last sweep
    converged: bool             # residual < eta (always False-free for a fixed sweep count)
    method: str
    timings: dict = field(default_factory=dict)  # seconds: build, sweeps, policy, total


class FactoredBellman:
    """Precomputed pieces of the factored Bellman operator for one model."""

    def __init__(self, model: HRCModel):
        self.model = model
        self.gamma = model.gamma
        n_y = self.n_y = model.n_task
        grid = model.task_grid
        self.shape = (N_HIDDEN, n_y, N_DISTANCE)

        def task_map(action, accepted):
            return model.task_index(step_task(grid, action, accepted)).astype(np.intp)

        # Deterministic task steps y -> y'.
        self.t_default = task_map(NW, False)        # nw dp dm mh, refused requests, idle ct
        self.t_pause = task_map(DN, False)          # dn: the robot's counter is paused
        tp, tx, ty = grid['tp'], grid['tx'], grid['ty']
        open_task = (tp > 0) & (ty == 0)
        self.ct_effective = np.flatnonzero(open_task & ((tx == 0) | (tx == 2)))
        t_ct = task_map(CT, False)                  # equals t_default where ct is ineffective
        self.t_commit = t_ct[self.ct_effective]
        # Where a request is eligible: rh1 for tx in {1, 2}, rh2 for tx = 3 (disjoint).
        self.request_y = np.flatnonzero(open_task & (tx != 0))
        self.request_is_rh2 = tx[self.request_y] == 3
        rh1_accept = task_map(RH1, True)
        rh2_accept = task_map(RH2, True)
        self.t_accept = np.where(self.request_is_rh2, rh2_accept[self.request_y],
                                 rh1_accept[self.request_y])
        # For the request subset: whether ct is effective there too (tx = 2).
        self.request_ct = np.isin(self.request_y, self.ct_effective)
        self.t_commit_on_request = t_ct[self.request_y]

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
        # mix[group, ea, d', d] = P(d' | d, ea) for the groups (other, dp, dm)
        self.mix = np.ascontiguousarray(np.stack(
            [model.distance_matrix(a).transpose(0, 2, 1) for a in (NW, DP, DM)])
            .reshape(3, 3, 16))
        self._w = None

    # -- building blocks ---------------------------------------------------------------
    def _continuations(self, value: np.ndarray):
        """gamma * U for (nw, dp, dm) [base], mh [motivate], requests [request]."""
        v = value.reshape(N_HIDDEN, -1)
        w = (self.emotion @ v).reshape(3, N_HIDDEN, self.n_y, N_DISTANCE)
        w *= self.gamma
        base = np.matmul(w[0], self.dist_base)          # (9, n_y, 12): nw | dp | dm
        motivate = np.matmul(w[1], self.dist_other)
        request = np.matmul(w[2], self.dist_other)
        return base, motivate, request

    def bellman_q(self, value: np.ndarray) -> np.ndarray:
        """Full Q(s, a), shape (8, N): the reference form of one Bellman step."""
        base, motivate, request = self._continuations(value)
        nw = base[..., 0:4]
        q = np.empty((len(ACTIONS),) + self.shape)
        q[NW] = nw[:, self.t_default]
        q[DP] = base[:, self.t_default, 4:8]
        q[DM] = base[:, self.t_default, 8:12]
        q[MH] = motivate[:, self.t_default]
        q[DN] = nw[:, self.t_pause]
        q[CT] = q[NW]
        q[CT][:, self.ct_effective] = nw[:, self.t_commit]
        refused = request[:, self.t_default]
        q[RH1] = refused
        q[RH2] = refused
        ry = self.request_y
        accepted = request[:, self.t_accept]
        mixed = refused[:, ry] + self.p_accept_h * (accepted - refused[:, ry])
        rh2 = self.request_is_rh2
        q[RH1][:, ry[~rh2]] = mixed[:, ~rh2]
        q[RH2][:, ry[rh2]] = mixed[:, rh2]
        q -= self.cost
        q -= self.g[:, None, None, None]
        if self.fail_safe_aware:  # at d = 0 only dn is available
            q[np.arange(len(ACTIONS)) != DN, :, :, 0] = -np.inf
        return q.reshape(len(ACTIONS), -1)

    def sweep(self, value: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                                float]:
        """One sweep: (T V, max |T V - V|), with the fused kernel where numba is present."""
        if not _kernels.AVAILABLE:
            new = self.bellman_max(value)
            return new, float(np.max(np.abs(new - value)))
        if self._w is None:
            self._w = np.empty((3,) + self.shape)
        if out is None:
            out = np.empty(self.model.n_states)
        residual = np.empty(self.n_y)
        _kernels.sweep(self.gamma_emotion, self.t_default, self.t_pause, self.t_commit_full,
                       self.t_accept_full, self.p_accept_vector, self.mix, self.g, self.cost,
                       self.fail_safe_aware, value.reshape(self.shape), self._w,
                       out.reshape(self.shape), residual)
        return out, float(residual.max())

    def bellman_max(self, value: np.ndarray) -> np.ndarray:
        """(T V), shape (N,): the max of `bellman_q` without forming it (numpy form)."""
        base, motivate, request = self._continuations(value)
        g = self.g
        nw = base[..., 0:4]
        # Best of the actions that use the default task step, before the gather.
        pre = np.maximum(nw, base[..., 4:8] - g[DP])
        np.maximum(pre, base[..., 8:12] - g[DM], out=pre)
        np.maximum(pre, motivate - g[MH], out=pre)
        refused = request - g[RH1]
        with_refused = np.maximum(pre, refused)
        best = np.take(with_refused, self.t_default, axis=1)
        np.maximum(best, np.take(nw, self.t_pause, axis=1), out=best)
        ce = self.ct_effective
        best[:, ce] = np.maximum(best[:, ce], nw[:, self.t_commit])
        # Where a request is eligible, "certainly refused" is not an option: redo those y.
        ry = self.request_y
        t0 = self.t_default[ry]
        exact = np.maximum(pre[:, t0], np.take(nw, self.t_pause[ry], axis=1))
        rc = self.request_ct
        exact[:, rc] = np.maximum(exact[:, rc], nw[:, self.t_commit_on_request[rc]])
        ref = refused[:, t0]
        np.maximum(exact, ref, out=exact)  # the ineligible one of rh1/rh2
        acc = refused[:, self.t_accept]
        np.maximum(exact, ref + self.p_accept_h * (acc - ref), out=exact)
        best[:, ry] = exact
        if self.fail_safe_aware:  # at d = 0 only dn is available
            best[..., 0] = np.take(nw[..., 0], self.t_pause, axis=1)
        best -= self.cost
        return best.reshape(-1)


def greedy_policy(q: np.ndarray) -> np.ndarray:
    """Argmax over actions (axis 0) with the safety tie order of MODEL.md 5."""
    best = q.max(axis=0)
    tol = TIE_TOLERANCE * np.maximum(1.0, np.abs(best))
    policy = np.full(q.shape[1:], -1, dtype=np.int8)
    for a in reversed(SAFETY_ORDER):
        policy[q[a] >= best - tol] = a
    return policy


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
        cost[sources] = model.cost(model.state(sources), a)
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


def solve(model: HRCModel, method: str = 'value_iteration', eta: float | None = None,
          sweeps: int | None = None, progress: Callable[[int, float, float], None] | None
          = None, operator: FactoredBellman | None = None) -> SolveResult:
    """Solve the model; defaults for eta and sweeps come from the configuration.

    `method` is `value_iteration` (MODEL.md 5, the default) or `policy_iteration` (Howard's:
    exact evaluation by a sparse linear solve, greedy improvement with the safety tie order,
    until the policy is stable). Policy iteration is kept as an independent check: on this
    model it is slower than the fused value iteration, so the shipped policies use VI.
    `progress(sweep, residual, elapsed_seconds)` is called after every sweep (or improvement).
    """
    if method == 'policy_iteration':
        return _policy_iteration(model, progress, operator)
    if method != 'value_iteration':
        raise ValueError(f'unknown method {method!r}; available: value_iteration, '
                         'policy_iteration')
    cfg = model.config
    eta = cfg.eta if eta is None else float(eta)
    sweeps = cfg.sweeps if sweeps is None else sweeps
    if sweeps is not None and sweeps < 1:
        raise ValueError(f'sweeps must be >= 1, got {sweeps}')
    t0 = time.perf_counter()
    op = operator or FactoredBellman(model)
    t_built = time.perf_counter()
    value = np.zeros(model.n_states)
    spare = np.empty(model.n_states)
    n = 0
    while True:
        new_value, residual = op.sweep(value, out=spare)
        n += 1
        if progress is not None:
            progress(n, residual, time.perf_counter() - t0)
        if (sweeps is None and residual < eta) or (sweeps is not None and n >= sweeps):
            break
        value, spare = new_value, value
    t_sweeps = time.perf_counter()
    # The policy is the argmax of the last sweep's Q (formed from V_{t}, whose image is the
    # returned V_{t+1}), exactly as a textbook value iteration reports it.
    q = op.bellman_q(value)
    policy = greedy_policy(q)
    t_end = time.perf_counter()
    return SolveResult(
        value=new_value, policy=policy, sweeps=n, residual=residual,
        converged=residual < eta, method=method,
        timings={'build': t_built - t0, 'sweeps': t_sweeps - t_built,
                 'policy': t_end - t_sweeps, 'total': t_end - t0})


def _policy_iteration(model: HRCModel, progress, operator) -> SolveResult:
    t0 = time.perf_counter()
    op = operator or FactoredBellman(model)
    t_built = time.perf_counter()
    policy = greedy_policy(op.bellman_q(np.zeros(model.n_states)))
    rounds = 0
    while True:
        value = evaluate_policy(model, policy)
        q = op.bellman_q(value)
        rounds += 1
        improved = greedy_policy(q)
        # Keep the current action where it is still (within the tie tolerance) the best, so
        # ties cannot make the iteration cycle.
        best = q.max(axis=0)
        current = q[policy.astype(np.intp), np.arange(model.n_states)]
        keep = current >= best - TIE_TOLERANCE * np.maximum(1.0, np.abs(best))
        improved[keep] = policy[keep]
        residual = float(np.max(best - current))
        if progress is not None:
            progress(rounds, residual, time.perf_counter() - t0)
        if np.array_equal(improved, policy):
            break
        policy = improved
    t_end = time.perf_counter()
    return SolveResult(value=value, policy=policy, sweeps=rounds, residual=residual,
                       converged=True, method='policy_iteration',
                       timings={'build': t_built - t0, 'sweeps': t_end - t_built,
                                'policy': 0.0, 'total': t_end - t0})
