"""Fused sweep kernels of the factored Bellman operator (numba).

The fast path of `solver.FactoredBellman`: one sweep ``T V`` (the max over actions of
`FactoredBellman.q`, which the tests hold it equal to), fused into two parallel passes over the
task part y, so a sweep reads and writes each array once:

1. the emotion step W[g, h, y, d] = sum_h' gammaE_g[h, h'] V[h', y, d] for the three emotion
   groups g (base, motivate, request), i.e. the 27x9 product of the numpy form, done here so
   that numba's and BLAS's thread pools never fight over the two cores;
2. for every (y, h) the distance step (4x4 matrices by action group and ea) on the
   rows W[g, h, y'] at the successors y' of y, the max over the eight actions, the cost and the
   residual.

The four distance values of a row are contiguous and handled as one 4-wide vector (the loops
over d are unrolled by hand so LLVM vectorises them); h is the outer loop so the distance
coefficients of its ea are loop invariants. Both passes are numba-parallel over y; the kernel is
compiled parallel and serial (`core.parallel`), and each sweep runs the variant that is faster
on the machine as it is, with the same result bit for bit (each output element is computed
the same way by either). numba is a dependency of the package.

Arguments of `sweep` (N = 9 * n_y * 4, 9 = `model.N_HIDDEN`, 4 = `model.N_DISTANCE`, the
width the distance loops are unrolled to): `gamma_e` (3, 9, 9) the gamma-scaled emotion matrices;
task maps
`t_default`, `t_pause`, `t_commit` (-1 where ct is not effective), `t_accept` (-1 where no
request is eligible); `p_accept_h` (9,) by h; `mix` (3, 3, 16) the distance matrices
[group (other, dp, dm), ea, 4 d' + d] = P(d' | d, ea); `g` (8,) action costs; `cost`
(9, n_y, 4); `fail_safe_aware` (only dn at d = 0); `dp_paused`, `dm_paused` (dp, dm step
the task as dn does, `t_pause`, instead of as nw, `t_default`: `model.robot_paused_by`);
`rated`, `rate` (n_y, 4; any values without a rate), `t_accept_pause` (model.robot_rate,
MODEL.md 3.2: every action under which the robot works mixes its successor with the paused
one, `t_pause` or, for an accepted request, `t_accept_pause`, by rate[y, d]; without a rate
nothing of it runs and the
sweep is what it was, bit for bit); the
stream (MODEL.md 8; empty
`arrive_y` without one): `arrive_y` the idle y, `arrive_enter` (len(arrive_y), K) the task
states a task k makes of them, `arrive_q` (K,), `p_idle`, `p_complete`; `value` V (9, n_y, 4);
`w` (3, 9, n_w, 4) scratch for the emotion step (n_w = n_y, or 2 n_y with a stream: rows
n_y + y hold the arrival_idle mix, and the task maps of idle sources point there); `out`
receives T V; `residual` (n_y,) receives max over h, d of |T V - V| per y; `w_given`: skip
steps 1 and 1b, w holds the continuations already (the queue's, below).

1b. (a stream only) at the idle y: W[y] <- (1 - p_complete) W[y] + p_complete sum_k q_k
W[enter(y, k)], and W[n_y + y] the same with p_idle; the entered rows are busy, so never
written in this pass.

`queue_continuations` (the queue, MODEL.md 8.1): the emotion step of every queue level into
`z` (L+1, 3, 9, n_y, 4), then per source level l the release-and-entry mix along (l, y') into
`w` (L+1, 3, 9, 2 n_y, 4) (rows y: busy sources, p = arrival_busy; rows n_y + y: idle sources,
p = arrival_idle); `sweep` then runs its step 2 on each level's w (``w_given``).
"""

from __future__ import annotations

import numba

from ..model import N_HIDDEN
from ..parallel import parallel_kernel


def _mix(c, x0, x1, x2, x3):
    """The distance step of one row: out_d = sum_k c[4k + d] x_k (c = P(d' = k | d))."""
    return (c[0] * x0 + c[4] * x1 + c[8] * x2 + c[12] * x3,
            c[1] * x0 + c[5] * x1 + c[9] * x2 + c[13] * x3,
            c[2] * x0 + c[6] * x1 + c[10] * x2 + c[14] * x3,
            c[3] * x0 + c[7] * x1 + c[11] * x2 + c[15] * x3)


def _emotion(e, value, y):
    """The emotion step of one row: out_d = sum_k e[k] value[k, y, d] (e = gammaE_g[h]), the
    four d at once, k in order (the same sums bit for bit wherever it is used)."""
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    a3 = 0.0
    for k in range(N_HIDDEN):
        ek = e[k]
        a0 += ek * value[k, y, 0]
        a1 += ek * value[k, y, 1]
        a2 += ek * value[k, y, 2]
        a3 += ek * value[k, y, 3]
    return a0, a1, a2, a3


def _rated(rate, run, pause):
    """The working action's value with model.robot_rate (MODEL.md 3.2): the paused branch
    plus the rate times the run's gain, per start band d."""
    return (pause[0] + rate[0] * (run[0] - pause[0]), pause[1] + rate[1] * (run[1] - pause[1]),
            pause[2] + rate[2] * (run[2] - pause[2]), pause[3] + rate[3] * (run[3] - pause[3]))


def _sweep(gamma_e, t_default, t_pause, t_commit, t_accept, p_accept_h, mix, g, cost,
           fail_safe_aware, dp_paused, dm_paused, arrive_y, arrive_enter, arrive_q, p_idle,
           p_complete, value, w, out, residual, w_given, rated, rate, t_accept_pause):
    n_y = value.shape[1]
    if not w_given:   # the queue (MODEL.md 8.1) forms w itself (`queue_continuations`)
        # 1. emotion step for the three groups (one parallel region)
        for y in numba.prange(n_y):
            for grp in range(3):
                for h in range(N_HIDDEN):
                    a0, a1, a2, a3 = _emotion_inline(gamma_e[grp, h], value, y)
                    w[grp, h, y, 0] = a0
                    w[grp, h, y, 1] = a1
                    w[grp, h, y, 2] = a2
                    w[grp, h, y, 3] = a3
        # 1b. the stream's arrivals at the idle y (nothing without a stream)
        n_k = arrive_q.shape[0]
        for j in numba.prange(arrive_y.shape[0]):
            y = arrive_y[j]
            for grp in range(3):
                for h in range(N_HIDDEN):
                    for d in range(4):
                        mixed = 0.0
                        for k in range(n_k):
                            mixed += arrive_q[k] * w[grp, h, arrive_enter[j, k], d]
                        stay = w[grp, h, y, d]
                        w[grp, h, n_y + y, d] = (1.0 - p_idle) * stay + p_idle * mixed
                        w[grp, h, y, d] = (1.0 - p_complete) * stay + p_complete * mixed
    # 2. distance step at the successors, max over actions, cost, residual
    g_rh = g[1]
    g_dp = g[4]
    g_dm = g[5]
    g_mh = g[6]
    residual[:] = 0.0
    for h in range(N_HIDDEN):
        ea = h % 3
        pa = p_accept_h[h]
        cn = mix[0, ea]  # nw, dn, ct, mh, requests
        cp = mix[1, ea]  # dp
        cm = mix[2, ea]  # dm
        wb = w[0, h]
        wm = w[1, h]
        wr = w[2, h]
        cost_h = cost[h]
        value_h = value[h]
        out_h = out[h]
        for y in numba.prange(n_y):
            y0 = t_default[y]
            yq = t_pause[y]
            yc = t_commit[y]
            ya = t_accept[y]
            ry = rate[y]  # model.robot_rate at (tx(y), d), read only when rated
            x0 = wb[y0, 0]
            x1 = wb[y0, 1]
            x2 = wb[y0, 2]
            x3 = wb[y0, 3]
            p0 = wb[yq, 0]  # the paused successor: dn's, and dp's, dm's where they pause
            p1 = wb[yq, 1]
            p2 = wb[yq, 2]
            p3 = wb[yq, 3]
            b0, b1, b2, b3 = _mix_inline(cn, x0, x1, x2, x3)  # nw
            if rated:   # a working robot's counter runs with the rate, else stays
                b0, b1, b2, b3 = _rated_inline(ry, (b0, b1, b2, b3),
                                               _mix_inline(cn, p0, p1, p2, p3))
            if dp_paused:
                q0, q1, q2, q3 = _mix_inline(cp, p0, p1, p2, p3)  # dp
            else:
                q0, q1, q2, q3 = _mix_inline(cp, x0, x1, x2, x3)  # dp
                if rated:
                    q0, q1, q2, q3 = _rated_inline(ry, (q0, q1, q2, q3),
                                                   _mix_inline(cp, p0, p1, p2, p3))
            b0 = max(b0, q0 - g_dp)
            b1 = max(b1, q1 - g_dp)
            b2 = max(b2, q2 - g_dp)
            b3 = max(b3, q3 - g_dp)
            if dm_paused:
                q0, q1, q2, q3 = _mix_inline(cm, p0, p1, p2, p3)  # dm
            else:
                q0, q1, q2, q3 = _mix_inline(cm, x0, x1, x2, x3)  # dm
                if rated:
                    q0, q1, q2, q3 = _rated_inline(ry, (q0, q1, q2, q3),
                                                   _mix_inline(cm, p0, p1, p2, p3))
            b0 = max(b0, q0 - g_dm)
            b1 = max(b1, q1 - g_dm)
            b2 = max(b2, q2 - g_dm)
            b3 = max(b3, q3 - g_dm)
            q0, q1, q2, q3 = _mix_inline(cn, wm[y0, 0], wm[y0, 1], wm[y0, 2], wm[y0, 3])  # mh
            if rated:
                q0, q1, q2, q3 = _rated_inline(ry, (q0, q1, q2, q3), _mix_inline(
                    cn, wm[yq, 0], wm[yq, 1], wm[yq, 2], wm[yq, 3]))
            b0 = max(b0, q0 - g_mh)
            b1 = max(b1, q1 - g_mh)
            b2 = max(b2, q2 - g_mh)
            b3 = max(b3, q3 - g_mh)
            q0, q1, q2, q3 = _mix_inline(cn, p0, p1, p2, p3)  # dn
            dn0 = q0
            b0 = max(b0, q0)
            b1 = max(b1, q1)
            b2 = max(b2, q2)
            b3 = max(b3, q3)
            if yc >= 0:  # ct, where effective
                q0, q1, q2, q3 = _mix_inline(cn, wb[yc, 0], wb[yc, 1], wb[yc, 2], wb[yc, 3])
                b0 = max(b0, q0)
                b1 = max(b1, q1)
                b2 = max(b2, q2)
                b3 = max(b3, q3)
            # requests: the refused branch (all a request can do where it is not eligible)
            r0, r1, r2, r3 = _mix_inline(cn, wr[y0, 0], wr[y0, 1], wr[y0, 2], wr[y0, 3])
            if rated:
                r0, r1, r2, r3 = _rated_inline(ry, (r0, r1, r2, r3), _mix_inline(
                    cn, wr[yq, 0], wr[yq, 1], wr[yq, 2], wr[yq, 3]))
            r0 -= g_rh
            r1 -= g_rh
            r2 -= g_rh
            r3 -= g_rh
            b0 = max(b0, r0)
            b1 = max(b1, r1)
            b2 = max(b2, r2)
            b3 = max(b3, r3)
            if ya >= 0:  # the eligible request: accepted with p_accept[em]
                q0, q1, q2, q3 = _mix_inline(cn, wr[ya, 0], wr[ya, 1], wr[ya, 2], wr[ya, 3])
                if rated:
                    yp = t_accept_pause[y]
                    q0, q1, q2, q3 = _rated_inline(ry, (q0, q1, q2, q3), _mix_inline(
                        cn, wr[yp, 0], wr[yp, 1], wr[yp, 2], wr[yp, 3]))
                b0 = max(b0, r0 + pa * (q0 - g_rh - r0))
                b1 = max(b1, r1 + pa * (q1 - g_rh - r1))
                b2 = max(b2, r2 + pa * (q2 - g_rh - r2))
                b3 = max(b3, r3 + pa * (q3 - g_rh - r3))
            if fail_safe_aware:  # at d = 0 only dn is available
                b0 = dn0
            b0 -= cost_h[y, 0]
            b1 -= cost_h[y, 1]
            b2 -= cost_h[y, 2]
            b3 -= cost_h[y, 3]
            worst = max(abs(b0 - value_h[y, 0]), abs(b1 - value_h[y, 1]),
                        abs(b2 - value_h[y, 2]), abs(b3 - value_h[y, 3]))
            if worst > residual[y]:
                residual[y] = worst
            out_h[y, 0] = b0
            out_h[y, 1] = b1
            out_h[y, 2] = b2
            out_h[y, 3] = b3


def _queue_continuations(gamma_e, busy_y, arrive_y, arrive_enter, arrive_q, p_idle, p_busy,
                         drop, value, z, w):
    """The queue's continuations (MODEL.md 8.1): z[l] the emotion step of V[l], then per
    source level l the busy-source (copy 0, rows y) and idle-source (copy 1, rows n_y + y)
    mixes of the release and the head's entry along (l, y')."""
    n_l = value.shape[0]
    n_y = value.shape[2]
    top = n_l - 1
    for y in numba.prange(n_y):
        for lv in range(n_l):
            for grp in range(3):
                for h in range(N_HIDDEN):
                    a0, a1, a2, a3 = _emotion_inline(gamma_e[grp, h], value[lv], y)
                    z[lv, grp, h, y, 0] = a0
                    z[lv, grp, h, y, 1] = a1
                    z[lv, grp, h, y, 2] = a2
                    z[lv, grp, h, y, 3] = a3
    # y' with a task: a release waits (l + 1), or is dropped at L (charged drop)
    for j in numba.prange(busy_y.shape[0]):
        y = busy_y[j]
        for lv in range(n_l):
            up = lv + 1 if lv < top else top
            charge = 0.0 if lv < top else drop
            for grp in range(3):
                for h in range(N_HIDDEN):
                    for d in range(4):
                        stay = z[lv, grp, h, y, d]
                        more = z[up, grp, h, y, d] - charge
                        w[lv, grp, h, y, d] = (1.0 - p_busy) * stay + p_busy * more
                        w[lv, grp, h, n_y + y, d] = (1.0 - p_idle) * stay + p_idle * more
    # y' idle: the head enters when a task waits (l - 1 without a release, l with one)
    n_k = arrive_q.shape[0]
    for j in numba.prange(arrive_y.shape[0]):
        y = arrive_y[j]
        for grp in range(3):
            for h in range(N_HIDDEN):
                for d in range(4):
                    below = z[0, grp, h, y, d]    # l = 0, no release: the cell stays idle
                    for lv in range(n_l):
                        mixed = 0.0
                        for k in range(n_k):
                            mixed += arrive_q[k] * z[lv, grp, h, arrive_enter[j, k], d]
                        w[lv, grp, h, y, d] = (1.0 - p_busy) * below + p_busy * mixed
                        w[lv, grp, h, n_y + y, d] = (1.0 - p_idle) * below + p_idle * mixed
                        below = mixed


_mix_inline = numba.njit(inline='always')(_mix)
_rated_inline = numba.njit(inline='always')(_rated)
_emotion_inline = numba.njit(inline='always')(_emotion)
sweep = parallel_kernel(_sweep, cache=True, nogil=True)
queue_continuations = parallel_kernel(_queue_continuations, cache=True, nogil=True)
