"""The promotion check: how much cheaper the new policy truly is, with an interval that holds,
and the promotion rule on it (docs/FLEET.md "The promotion rule").

What is estimated. The new policy pi^ is solved from theta^, the model fitted from the cell's
recordings; the cell's people are theta, unknown. The question is

    Delta = C(pi^; theta) - C(pi_run; theta)

(C: the mean per-episode discounted cost, or collision epochs, ... of a policy run with the
cell's selector against people theta; pi_run the running pair). The plant can compute C in any
world it has a model of, never in theta.

In-sample. Delta_in = C(pi^; theta^) - C(pi_run; theta^) (the shadow stage: both policies in the
world fitted from all the recordings, paired episodes) is biased toward the new policy: pi^ is
optimal for theta^, so wherever theta^ is off by fitting noise the new policy wins there
(measured: -1.17 per episode in unchanged cells whose truth is -0.14), and its interval over
the episodes leaves the fitting error out altogether.

Refits (the bootstrap of the whole procedure). The error e = Delta_in - Delta is what fitting
does; the bootstrap repeats the procedure in a world whose truth is known, theta^: R
resamples of the recordings' episodes (with replacement, `stages.refit_data`) are each
fitted as the cell's fit fits (from the base, the same starts, tolerances, held families)
into theta*_b and solved into pi*_b, and

    e*_b = [C(pi*_b; theta*_b) - C(pi_run; theta*_b)] - [C(pi*_b; theta^) - C(pi_run; theta^)]

is that refit's in-sample figure minus its truth. The estimate is Delta_in minus their mean.
Its interval is a prediction interval for the cell's own error e = Delta_in - Delta: that
error is the fitting error f (distributed as the refits' f*_b, the bootstrap's principle) plus
the episodes' noise of Delta_in (variance v_in, from its paired episodes); each e*_b is f*_b
plus its own episodes' noise (variance v_b, known from its paired episodes: the two figures
of a refit are over the same seeded episodes, so it is the variance of the per-episode
differences over n). So the fitting error's variance is s_f^2 = max(var(e*) - mean(v_b), 0)
and

    Delta_in - mean(e*)  +-  t(0.975, R - 1) sqrt(s_f^2 (1 + 1/R) + v_in + mean(v_b) / R),

the fitting error's spread, the uncertainty of its mean from R refits and the episodes' noise
of both sides; never narrower than the in-sample interval over the episodes alone. (Taking
sd(e*) for the fitting error would count the refits' episodes' noise as fitting error: in
pilot cells at 500 episodes a refit, that noise was 10-65% of e*'s variance.)

Why whole refits from the base and not hrc-fit's bootstrap (each resample refitted from the
estimate): those stay in the estimate's basin and leave out EM's other maxima, which the
cell's own fit meets; their errors' spread was too small (a cell whose new policy was truly
3.2 worse got an interval 4.2 of its sd from the truth). Why resampled episodes and not
recordings simulated from theta^ with the recorded actions: the recorded actions answer what
the policy saw of the real person, not of a simulated one, and fits of such recordings erred
far more than the cell's own fit does (measured, docs/FLEET.md). A bootstrap over episodes
needs episodes: with fewer than `stages.MIN_EPISODES` the cell is kept, saying so.

The rule (`decide`), on the corrected figures:

- promote when the cost's interval is below zero (the new policy is cheaper in the cost the
  policy minimises, which already prices requests, refusals and the person's emotions), and
- the safety guard holds: the collision epochs per episode are not higher with 95%
  confidence (their interval, corrected alike, does not lie above zero);
- a further guard is a plant-file setting (`promote.guards`, none by default): the metric not
  worse with 95% confidence; when a guard keeps a cell that the cost alone would promote, the
  report shows the cost it gave up.
"""

from __future__ import annotations

import math

import numpy as np

PROMOTE, KEEP = 'promote', 'keep'
Z95 = 1.959963984540054
COST = 'discounted_cost'
SAFETY = 'collision_epochs'
# metric -> (its words, +1 when more is worse, -1 when less is worse)
METRICS = {
    'discounted_cost': ('discounted cost', +1),
    'collision_epochs': ('collision epochs', +1),
    'refused_requests': ('refused requests', +1),
    'tasks_completed': ('tasks completed', -1),
    'collision_stuck': ('episodes stuck more than 3 epochs at d = 0', +1),
}
GUARDS = ('refused_requests', 'tasks_completed', 'collision_stuck')    # promote.guards
WORLD = ('the world fitted from all the recordings (in-sample), corrected for the fit\'s '
         'optimism by refits of resampled episodes (each fitted from the base and solved as '
         'the cell was); the interval carries the fitting error and the episodes\' noise')
# the same without refits (too few episodes to resample): nothing corrects the figures
WORLD_UNCORRECTED = ('the world fitted from all the recordings (in-sample), not corrected: too '
                     'few episodes for refits, so the interval is the episodes\' alone and leaves '
                     'the fitting error out; the cell is kept')


def t_quantile(dof: int) -> float:
    from scipy.stats import t as student
    return float(student.ppf(0.975, dof))


def corrected(in_sample: dict, errors, noise=None) -> dict:
    """One metric: the in-sample paired figures (`stages.paired`: mean, half_width, new,
    running) and the refits' errors e*_b with the episodes' variance of each (`noise`, known
    from its paired episodes) -> the estimate of Delta with its 95% interval (module
    docstring); with fewer than 2 refits the in-sample figures as they are."""
    errors = np.asarray(errors, dtype=float)
    noise = np.zeros(errors.size) if noise is None else np.asarray(noise, dtype=float)
    keep = np.isfinite(errors) & np.isfinite(noise)
    errors, noise = errors[keep], noise[keep]
    episodes_half = float(in_sample['half_width'])
    out = {'in_sample': float(in_sample['mean']), 'in_sample_half_width': episodes_half,
           'new': float(in_sample['new']), 'running': float(in_sample['running']),
           'refits': int(errors.size)}
    if errors.size < 2:
        return {**out, 'mean': out['in_sample'], 'half_width': episodes_half,
                'low': out['in_sample'] - episodes_half, 'high': out['in_sample'] + episodes_half,
                'optimism': None, 'optimism_sd': None, 'fitting_sd': None}
    r = errors.size
    optimism, spread = float(errors.mean()), float(errors.std(ddof=1))
    episodes_noise = float(noise.mean())
    fitting = max(spread ** 2 - episodes_noise, 0.0)
    own = (episodes_half / Z95) ** 2
    half = max(t_quantile(r - 1) * math.sqrt(fitting * (1 + 1 / r) + own + episodes_noise / r),
               episodes_half)
    mean = out['in_sample'] - optimism
    return {**out, 'mean': mean, 'half_width': half, 'low': mean - half, 'high': mean + half,
            'optimism': optimism, 'optimism_sd': spread, 'fitting_sd': math.sqrt(fitting)}


def combine(in_sample: dict, refits: list[dict]) -> dict:
    """Every metric of the in-sample figures (`stages.shadow`'s facts) corrected by the
    refits' errors (`stages.refits`' rows: metric -> [in-sample in the refit's world, the
    same in theta^, the episodes' variance of their difference])."""
    return {metric: corrected(in_sample[metric],
                              [row[metric][0] - row[metric][1] for row in refits],
                              [row[metric][2] if len(row[metric]) > 2 else 0.0
                               for row in refits])
            for metric in METRICS if metric in in_sample}


def _figure(m: dict) -> str:
    return f'{m["mean"]:+.3f} [{m["low"]:+.3f}, {m["high"]:+.3f}]'


def worse(metric: str, m: dict) -> bool:
    """The new policy worse on `metric` with 95% confidence: its interval wholly on the worse
    side of zero."""
    sign = METRICS[metric][1]
    return m['low'] > 0 if sign > 0 else m['high'] < 0


def decide(figures: dict, guards=(), where: str = 'corrected for the fit\'s optimism',
           unchecked: str = 'fewer than 2 refits') -> tuple[str, str, list[dict]]:
    """The promotion rule (module docstring) on `combine`'s figures: (decision, reason, the
    guards that kept a cell the cost alone would promote, each with the cost it gave up).
    Without two refits there is no interval that carries the fitting error: keep, saying
    why (`unchecked`)."""
    cost = figures[COST]
    refits = cost['refits']
    if refits < 2:
        safety = figures[SAFETY]
        more = (f'; and in-sample more collision epochs: {_figure(safety)} per episode'
                if worse(SAFETY, safety) else '')
        return KEEP, (f'the fitting error could not be bounded ({unchecked}), so nothing is '
                      f'promoted: in-sample cost new - running {_figure(cost)} per episode '
                      f'over the episodes alone, optimistic for the new policy{more}'), []
    said = (f'cost new - running {_figure(cost)} per episode (95%, {where}, {refits} '
            f'refit{"s" if refits != 1 else ""}; in-sample {cost["in_sample"]:+.3f})')
    safety = figures[SAFETY]
    safety_words = (f'collision epochs new - running {_figure(safety)} per episode (95%)')
    cheaper = math.isfinite(cost['high']) and cost['high'] < 0
    blocked = []
    if cheaper and worse(SAFETY, safety):
        return KEEP, (f'more collision epochs with 95% confidence, the safety guard: '
                      f'{safety_words}; although cheaper: {said}'), blocked
    if not cheaper:
        note = (f'; {safety_words}, more with 95% confidence' if worse(SAFETY, safety)
                else '')
        return KEEP, f'not cheaper with 95% confidence: {said}{note}', blocked
    for metric in guards:
        m = figures[metric]
        if worse(metric, m):
            blocked.append({'guard': metric, 'figure': m, 'cost_given_up': cost})
    if blocked:
        words = '; '.join(f'{METRICS[b["guard"]][0]} new - running {_figure(b["figure"])} '
                          f'(worse with 95% confidence)' for b in blocked)
        return KEEP, (f'kept by the plant\'s guard{"s" if len(blocked) > 1 else ""} '
                      f'({", ".join(b["guard"] for b in blocked)}): {words}; cost given up: '
                      f'{said}; {safety_words}'), blocked
    return PROMOTE, f'cheaper: {said}; {safety_words}, not more with 95% confidence', blocked
