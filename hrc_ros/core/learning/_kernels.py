"""The E-step of `fit` (numba): evidence, scaled forward-backward and expected counts, fused,
for a batch of parameter sets (lanes: the EM starts, the bootstrap resamples) at once.

One pass per segment (a run of epochs whose transitions are all usable), t = a .. b-1, with
h = 3*em + ea:

    e_t(h)   = L[O_t, h] * acc_t(em) * sum_D move[t, D] p_delta[ea, D]     (module `fit`)
    alpha_a  = pi_k * e_a / c_a,        alpha_t = (alpha_{t-1} E_{g(t-1)}) * e_t / c_t
    beta_{b-1} = 1,                     beta_t  = E_{g(t)} (e_{t+1} * beta_{t+1}) / c_{t+1}
    gamma_t  = alpha_t * beta_t,        xi_t(h, h') = alpha_t(h) E(h, h') e_{t+1}(h')
                                                      beta_{t+1}(h') / c_{t+1}
    log P(segment) = sum_t log c_t      (Rabiner's scaling: no underflow at any length)

where pi_k is the start distribution of the segment's kind k = `seg_kind[s]`: 0 for every
segment unless the fit has a person prior (`fit --prior`), then 0 for the segments that start
an episode (the prior) and 1 for the pieces cut from one (a nuisance distribution).

Two things make it cheaper than the formulas read (docs/LEARNING.md, "Time"):

- E = kron(A_em, A_ea): alpha E is two 3 x 3 products, P_t(j, a) = sum_i A_em(i, j)
  alpha_t(i, a) (kept from the forward pass) then sum_a P(j, a) A_ea(a, b); E n likewise
  through M(j, a) = sum_b A_ea(a, b) n(j, b). The M-step reads only xi summed over the other
  variable, and those sums are A_em(i, j) sum_t sum_a alpha_t(i, a) M_t(j, a) and A_ea(a, b)
  sum_t sum_j P_t(j, a) n_t(j, b): the 9 x 9 xi is never formed.
- Epochs of one kind (the same observation, answer, fitting Deltas, has_move and unique
  Deltas: `fit.epoch_kinds`, a few dozen kinds in 100k epochs) have the same evidence under
  any parameters: it is computed once per kind and lane, and the posteriors gamma_t of each
  kind are summed in the pass; the counts below are made from those sums at the end.

The counts the M-step needs, each weighted by the segment's multiplicity `seg_weight`
(1, or how often a bootstrap resample drew its episode; 0 skips the segment):

    first[k, h]       sum of gamma at the first epochs of the segments of kind k
    accept[0|1, em]   sum of gamma_t(em) over accepted | refused eligible requests
    delta[ea, D]      sum of gamma_t(ea) r_t(D | ea) over known moves, r the posterior of D
    moves[g, v, i, j] expected moves of variable v (em, ea) from level i to j under group g
    observed[O, h]    sum of gamma_t(h) over epochs that observed O
    unique[ea, D]     sum of gamma_t(ea) over moves that tell D apart from both others

`e_step_batch` runs the lanes as a parallel loop (`core.parallel`: serial or parallel,
whichever the machine gives); each lane is computed by the same sequential code whatever the
variant, so its counts do not depend on it. (A layout with the lanes innermost, vectorised
across lanes, was tried: numba's code for it was no faster per lane on this machine and took
several times longer to compile.)

Arguments (T epochs, K kinds of epoch, S segments, B lanes, 9 = `model.N_HIDDEN`): per lane
`likelihood` (B, 3, 9), `p_accept` (B, 3), `p_delta` (B, 3, 3), `pi` (B, 2, 9), `chain`
(B, 3, 2, 3, 3) the bounded chain matrices [group, variable, i, j]; per epoch `group` (T,)
the emotion group of a_t and `code` (T,) its kind; per kind `code_observation` (K,) O - 1 or 3
for none, `code_answer` (K,) 0 none, 1 accepted, 2 refused, `code_move` (K, 3) 1 where Delta
fits the move (all 1 when it is unknown), `code_has_move` (K,), `code_unique` (K, 3);
`seg_start` (S + 1,), `seg_kind` (S,), `seg_weight` (B, S); outputs (overwritten) `loglik` (B, S)
(unweighted, -inf for evidence impossible under the parameters, 0 where the weight is 0) and
the counts above with a leading lane axis.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..model import N_HIDDEN
from ..parallel import parallel_kernel


def _segments(first_segment, last_segment, likelihood, p_accept, p_delta, pi, chain,
              group, code, code_observation, code_answer, code_move, code_has_move,
              code_unique, seg_start, seg_kind, seg_weight, alpha, pushed, scale, evidence,
              posterior, loglik, first, accept, delta, moves, observed, unique):
    """The segments first_segment .. last_segment - 1, counts added into the given arrays.
    `evidence` (C, 9) and `posterior` (C, 9) are scratch: the evidence of each epoch kind and
    the posterior summed over the epochs of each kind."""
    n_h = N_HIDDEN
    n_g = chain.shape[0]
    n_codes = code_observation.shape[0]
    nxt = np.empty(n_h)
    through = np.empty(n_h)
    beta = np.empty(n_h)
    gamma = np.empty(n_h)
    dist = np.empty(3)
    joint_em = np.zeros((n_g, 3, 3))     # sum_t w sum_a alpha_t(i, a) M_t(j, a), per group
    joint_ea = np.zeros((n_g, 3, 3))     # sum_t w sum_j P_t(j, a) nxt_t(j, b), per group
    # evidence of each kind of epoch: e(h) = L[O, h] acc(em) sum_D move[D] p_delta[ea, D]
    for c in range(n_codes):
        o = code_observation[c]
        for ea in range(3):
            dist[ea] = (code_move[c, 0] * p_delta[ea, 0] + code_move[c, 1] * p_delta[ea, 1]
                        + code_move[c, 2] * p_delta[ea, 2])
        for em in range(3):
            acc = 1.0
            if code_answer[c] == 1:
                acc = p_accept[em]
            elif code_answer[c] == 2:
                acc = 1.0 - p_accept[em]
            for ea in range(3):
                h = 3 * em + ea
                v = acc * dist[ea]
                if o < 3:
                    v *= likelihood[o, h]
                evidence[c, h] = v
                posterior[c, h] = 0.0
    for s in range(first_segment, last_segment):
        a = seg_start[s]
        b = seg_start[s + 1]
        w = seg_weight[s]
        kind_s = seg_kind[s]
        if w == 0.0:
            loglik[s] = 0.0
            continue
        # forward: alpha_t = (P_{t-1} A_ea) * e_t / c_t, P_{t-1}(j, a) = sum_i A_em(i, j)
        # alpha_{t-1}(i, a): the kron(em, ea) transition as two 3 x 3 products
        total = 0.0
        possible = True
        for t in range(a, b):
            e = evidence[code[t]]
            c = 0.0
            if t == a:
                for j in range(n_h):
                    v = pi[kind_s, j] * e[j]
                    alpha[0, j] = v
                    c += v
            else:
                m_ea = chain[group[t - 1], 1]
                for j in range(3):
                    p0 = pushed[t - 1 - a, 3 * j]
                    p1 = pushed[t - 1 - a, 3 * j + 1]
                    p2 = pushed[t - 1 - a, 3 * j + 2]
                    for k in range(3):
                        v = (p0 * m_ea[0, k] + p1 * m_ea[1, k] + p2 * m_ea[2, k]) * e[3 * j + k]
                        alpha[t - a, 3 * j + k] = v
                        c += v
            if not c > 0.0:
                possible = False
                break
            inverse = 1.0 / c
            for j in range(n_h):
                alpha[t - a, j] *= inverse
            scale[t - a] = c
            total += math.log(c)
            if t < b - 1:
                m_em = chain[group[t], 0]
                for j in range(3):
                    for k in range(3):
                        pushed[t - a, 3 * j + k] = (m_em[0, j] * alpha[t - a, k]
                                                    + m_em[1, j] * alpha[t - a, 3 + k]
                                                    + m_em[2, j] * alpha[t - a, 6 + k])
        if not possible:
            loglik[s] = -math.inf
            continue
        loglik[s] = total
        # backward, with the counts of epoch t once beta_t is known
        for j in range(n_h):
            beta[j] = 1.0
        for t in range(b - 1, a - 1, -1):
            if t < b - 1:
                g = group[t]
                m_em = chain[g, 0]
                m_ea = chain[g, 1]
                e = evidence[code[t + 1]]
                inverse = 1.0 / scale[t + 1 - a]
                for j in range(n_h):
                    nxt[j] = e[j] * beta[j] * inverse
                # through(j, a) = sum_b A_ea(a, b) nxt(j, b)
                for j in range(3):
                    n0 = nxt[3 * j]
                    n1 = nxt[3 * j + 1]
                    n2 = nxt[3 * j + 2]
                    for k in range(3):
                        through[3 * j + k] = m_ea[k, 0] * n0 + m_ea[k, 1] * n1 + m_ea[k, 2] * n2
                # beta_t(i, a) = sum_j A_em(i, j) through(j, a)
                for i in range(3):
                    for k in range(3):
                        beta[3 * i + k] = (m_em[i, 0] * through[k] + m_em[i, 1] * through[3 + k]
                                           + m_em[i, 2] * through[6 + k])
                for i in range(3):
                    for j in range(3):
                        joint_em[g, i, j] += w * (alpha[t - a, 3 * i] * through[3 * j]
                                                  + alpha[t - a, 3 * i + 1] * through[3 * j + 1]
                                                  + alpha[t - a, 3 * i + 2] * through[3 * j + 2])
                for k in range(3):
                    for m in range(3):
                        joint_ea[g, k, m] += w * (pushed[t - a, k] * nxt[m]
                                                  + pushed[t - a, 3 + k] * nxt[3 + m]
                                                  + pushed[t - a, 6 + k] * nxt[6 + m])
            z = 0.0
            for h in range(n_h):
                gamma[h] = alpha[t - a, h] * beta[h]
                z += gamma[h]
            z = w / z
            for h in range(n_h):
                gamma[h] *= z
            if t == a:
                for h in range(n_h):
                    first[kind_s, h] += gamma[h]
            kind = posterior[code[t]]
            for h in range(n_h):
                kind[h] += gamma[h]
    # the counts of each kind of epoch
    for c in range(n_codes):
        o = code_observation[c]
        kind = posterior[c]
        if o < 3:
            for h in range(n_h):
                observed[o, h] += kind[h]
        if code_answer[c] > 0:
            for em in range(3):
                accept[code_answer[c] - 1, em] += kind[3 * em] + kind[3 * em + 1] \
                    + kind[3 * em + 2]
        if code_has_move[c]:
            for ea in range(3):
                g_ea = kind[ea] + kind[3 + ea] + kind[6 + ea]
                norm = (code_move[c, 0] * p_delta[ea, 0] + code_move[c, 1] * p_delta[ea, 1]
                        + code_move[c, 2] * p_delta[ea, 2])
                for k in range(3):
                    if norm > 0.0:
                        delta[ea, k] += g_ea * code_move[c, k] * p_delta[ea, k] / norm
                    if code_unique[c, k]:
                        unique[ea, k] += g_ea
    # the expected moves: xi summed over the other variable is A (elementwise) joint
    for g in range(n_g):
        for i in range(3):
            for j in range(3):
                moves[g, 0, i, j] += chain[g, 0, i, j] * joint_em[g, i, j]
                moves[g, 1, i, j] += chain[g, 1, i, j] * joint_ea[g, i, j]


def _e_step_batch(likelihood, p_accept, p_delta, pi, chain, group, code, code_observation,
                  code_answer, code_move, code_has_move, code_unique, seg_start, seg_kind,
                  seg_weight, loglik, first, accept, delta, moves, observed, unique):
    longest = 1
    for s in range(seg_start.shape[0] - 1):
        longest = max(longest, seg_start[s + 1] - seg_start[s])
    n_codes = code_observation.shape[0]
    for lane in numba.prange(pi.shape[0]):
        alpha = np.empty((longest, N_HIDDEN))
        pushed = np.empty((longest, N_HIDDEN))
        scale = np.empty(longest)
        evidence = np.empty((n_codes, N_HIDDEN))
        posterior = np.empty((n_codes, N_HIDDEN))
        first[lane] = 0.0
        accept[lane] = 0.0
        delta[lane] = 0.0
        moves[lane] = 0.0
        observed[lane] = 0.0
        unique[lane] = 0.0
        _segments_jit(0, seg_start.shape[0] - 1, likelihood[lane], p_accept[lane],
                      p_delta[lane], pi[lane], chain[lane], group, code, code_observation,
                      code_answer, code_move, code_has_move, code_unique, seg_start, seg_kind,
                      seg_weight[lane], alpha, pushed, scale, evidence, posterior,
                      loglik[lane], first[lane], accept[lane], delta[lane], moves[lane],
                      observed[lane], unique[lane])


# fastmath without assuming finite values (an impossible segment's -inf must survive).
_FLAGS = {'reassoc', 'contract', 'arcp', 'nsz'}
_segments_jit = numba.njit(cache=True, nogil=True, fastmath=_FLAGS)(_segments)
e_step_batch = parallel_kernel(_e_step_batch, cache=True, nogil=True, fastmath=_FLAGS)
