"""Point backups of the mixed-observability POMDP solver (numba; see `pomdp`).

The state is (x, h): x observed, h hidden (H values). From x under action a the observed part
moves to one of at most K successors x'_k with probability l_k(h) = P(x'_k | x, h, a) (the
acceptance and the distance step of the HRC cell depend on h), the hidden part moves and is
observed through the action group's kernel Z_g[o, h, h'] = P(h', o | h) = E_g[h, h'] L[o, h'].
For a belief b over h at x, the successor after (a, x'_k, o) is

    b'(h') ∝ sum_h b(h) l_k(h) Z_g[o, h, h'],      with probability  sum of the same.

Lower bound (alpha vectors, `lb_backup`): the point-based backup

    alpha_a(h) = r(x, a, h) + gamma sum_{k, o} l_k(h) [Z_g[o] alpha*_{k,o}](h),
    alpha*_{k,o} = argmax_{alpha in Gamma(x'_k)} sum_h b(h) l_k(h) [Z_g[o] alpha](h),

with the projections ``proj[g, o, i] = Z_g[o] @ alpha_i`` formed once per sweep; the vector
of the action the model's tie rule picks is kept (`model.safest_best_one`, compiled here:
actions within the tie tolerance of the best go to the first of `order`, the safety order).

Upper bound (`ub_backup`): the same one-step lookahead on the upper bound U(x', b') =
min(FIB(x', b'), sawtooth(x', b')), where FIB(x, b) = max_a sum_h b(h) Q_fib(x, a, h) and the
sawtooth interpolates the corner values c(x, h) and the point values (b_i, v_i) of x:

    sawtooth(x, b) = min( c.b,  min_i c.b + kappa_i (v_i - c.b_i) ),
    kappa_i = min_{h : b_i(h) > 0} b(h) / b_i(h).

Both are parallel over the points (numba prange, through `core.parallel`, which runs each
call serial or parallel by what the machine gives) and never allocate per successor. The
upper bound's value at a point is the largest action's (a valid bound); its action is the one
the tie rule picks.
"""

from __future__ import annotations

import numba
import numpy as np

from ..model import safest_best_one
from ..parallel import parallel_kernel

_safest_best = numba.njit(inline='always')(safest_best_one)


def _ub_value(x, b, q_fib, available, corner, ub_inverse, ub_slope, ub_offsets):
    """min(FIB, sawtooth) at (x, b); b is normalised. The sawtooth points of x are given by
    `ub_inverse[i, h]` = 1 / b_i(h) (0 where b_i(h) = 0) and `ub_slope[i]` = v_i - c.b_i < 0
    (points with v_i >= c.b_i cannot lower the bound and are left out)."""
    n_a = q_fib.shape[1]
    n_h = b.shape[0]
    fib = -np.inf
    for a in range(n_a):
        if not available[x, a]:
            continue
        s = 0.0
        for h in range(n_h):
            s += q_fib[x, a, h] * b[h]
        if s > fib:
            fib = s
    base = 0.0
    for h in range(n_h):
        base += corner[x, h] * b[h]
    best = min(fib, base)
    for i in range(ub_offsets[x], ub_offsets[x + 1]):
        kappa = np.inf
        for h in range(n_h):
            inv = ub_inverse[i, h]
            if inv > 0.0:
                r = b[h] * inv
                if r < kappa:
                    kappa = r
        v = base + kappa * ub_slope[i]
        if v < best:
            best = v
    return best


_ub_value_inline = numba.njit(inline='always')(_ub_value)
ub_value = numba.njit(cache=True)(_ub_value)


def _lb_backup(points, point_x, succ_x, succ_l, reward, available, group, order, proj,
               offsets, gamma, same_as, out_vec, out_act, out_val):
    n_points, n_h = points.shape
    n_a = reward.shape[1]
    n_k = succ_x.shape[2]
    n_o = proj.shape[1]
    for p in numba.prange(n_points):
        x = point_x[p]
        b = points[p]
        vec = np.empty((n_a, n_h))
        val = np.full(n_a, -np.inf)
        bl = np.empty(n_h)
        for a in range(n_a):
            if not available[x, a]:
                continue
            g = group[a]
            a0 = same_as[x, a]
            if a0 >= 0:     # the successors and group of the earlier a0: only r differs
                v = 0.0
                for h in range(n_h):
                    vec[a, h] = reward[x, a, h] + (vec[a0, h] - reward[x, a0, h])
                    v += vec[a, h] * b[h]
                val[a] = v
                continue
            for h in range(n_h):
                vec[a, h] = reward[x, a, h]
            for k in range(n_k):
                xn = succ_x[x, a, k]
                if xn < 0:
                    break
                for h in range(n_h):
                    bl[h] = b[h] * succ_l[x, a, k, h]
                lo = offsets[xn]
                hi = offsets[xn + 1]
                for o in range(n_o):
                    best_i = lo
                    best_s = -np.inf
                    for i in range(lo, hi):
                        s = 0.0
                        for h in range(n_h):
                            s += bl[h] * proj[g, o, i, h]
                        if s > best_s:
                            best_s = s
                            best_i = i
                    for h in range(n_h):
                        vec[a, h] += gamma * succ_l[x, a, k, h] * proj[g, o, best_i, h]
            v = 0.0
            for h in range(n_h):
                v += vec[a, h] * b[h]
            val[a] = v
        a = _safest_best(val, order)
        out_act[p] = a
        out_val[p] = val[a]
        for h in range(n_h):
            out_vec[p, h] = vec[a, h]


lb_backup = parallel_kernel(_lb_backup, cache=True, nogil=True)


def _ub_backup(points, point_x, succ_x, succ_l, reward, available, group, order, kernel,
               gamma, q_fib, corner, ub_inverse, ub_slope, ub_offsets, same_as, out_val,
               out_act):
    n_points, n_h = points.shape
    n_a = reward.shape[1]
    n_k = succ_x.shape[2]
    n_o = kernel.shape[1]
    for p in numba.prange(n_points):
        x = point_x[p]
        b = points[p]
        bl = np.empty(n_h)
        nb = np.empty(n_h)
        val = np.full(n_a, -np.inf)
        future = np.zeros(n_a)
        for a in range(n_a):
            if not available[x, a]:
                continue
            g = group[a]
            q = 0.0
            for h in range(n_h):
                q += b[h] * reward[x, a, h]
            a0 = same_as[x, a]
            if a0 >= 0:     # the successors and group of the earlier a0: only r differs
                future[a] = future[a0]
                val[a] = q + future[a0]
                continue
            r = q
            for k in range(n_k):
                xn = succ_x[x, a, k]
                if xn < 0:
                    break
                for h in range(n_h):
                    bl[h] = b[h] * succ_l[x, a, k, h]
                for o in range(n_o):
                    total = 0.0
                    for h2 in range(n_h):
                        s = 0.0
                        for h in range(n_h):
                            s += bl[h] * kernel[g, o, h, h2]
                        nb[h2] = s
                        total += s
                    if total <= 0.0:
                        continue
                    for h2 in range(n_h):
                        nb[h2] /= total
                    q += gamma * total * _ub_value_inline(
                        xn, nb, q_fib, available, corner, ub_inverse, ub_slope, ub_offsets)
            future[a] = q - r
            val[a] = q
        out_act[p] = _safest_best(val, order)
        out_val[p] = val.max()


ub_backup = parallel_kernel(_ub_backup, cache=True, nogil=True)


def _lb_values(points, point_x, alpha, offsets, out_val, out_index):
    """max_{alpha in Gamma(x)} alpha . b per point, and the index of the maximiser."""
    n_points, n_h = points.shape
    for p in numba.prange(n_points):
        x = point_x[p]
        best = -np.inf
        best_i = -1
        for i in range(offsets[x], offsets[x + 1]):
            s = 0.0
            for h in range(n_h):
                s += alpha[i, h] * points[p, h]
            if s > best:
                best = s
                best_i = i
        out_val[p] = best
        out_index[p] = best_i


lb_values = parallel_kernel(_lb_values, cache=True, nogil=True)


def _ub_values(points, point_x, q_fib, available, corner, ub_inverse, ub_slope, ub_offsets,
               out_val):
    for p in numba.prange(points.shape[0]):
        out_val[p] = _ub_value_inline(point_x[p], points[p], q_fib, available, corner,
                                      ub_inverse, ub_slope, ub_offsets)


ub_values = parallel_kernel(_ub_values, cache=True, nogil=True)


def _successor_sums(succ_x, succ_l, rows, table, pick, out):
    """out[x, m, h] = sum_k succ_l[x, a, k, h] table[pick[x, m], succ_x[x, a, k], h] with
    a = rows[x, m], over the successors of (x, a) up to the first -1 (the padding is never
    read): the expectation over x' of a table of values by successor, in the sparse form (a
    queue's (x, a) has 12 successors on average and up to 96). The fast form of
    `MixedPOMDP.expected_next`, of the FIB's gather and of the blind policies' evaluation."""
    n_x, n_m = rows.shape
    n_k = succ_x.shape[2]
    n_h = succ_l.shape[3]
    for x in numba.prange(n_x):
        for m in range(n_m):
            a = rows[x, m]
            t = pick[x, m]
            for h in range(n_h):
                out[x, m, h] = 0.0
            for k in range(n_k):
                xn = succ_x[x, a, k]
                if xn < 0:
                    break
                for h in range(n_h):
                    out[x, m, h] += succ_l[x, a, k, h] * table[t, xn, h]


successor_sums = parallel_kernel(_successor_sums, cache=True, nogil=True)
