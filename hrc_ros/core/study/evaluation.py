"""Compare the action selectors over many seeded episodes (`hrc-evaluate`).

The paper shows one 20-epoch run. To say whether its vote heuristic is any good, this runs many
episodes with random task streams and random initial humans, once per selector, on common
random numbers: episode e of every selector sees the same scenario (initial (em, ea, d), task
releases) and the same uniform stream of its simulated human (`cell.SimulatedHuman` with seed
``(seed, e)``), so differences between selectors come from their decisions, not from luck.

Selectors: ``paper`` (the weighted vote), ``qmdp``, ``mls``, ``pomdp`` and ``fib`` (the solved
POMDP's alpha vectors and fast informed bound, `pomdp.AlphaPolicy`'s batch forms) and ``mdp``,
the policy action of the *true* state: a full-information bound that no belief-based selector
should beat on average. Every selector is subject to the fail-safe (d = 0 -> dn) unless
`--no-fail-safe`.

Metrics per episode (then mean and a 95% normal confidence interval over episodes):

- discounted cost  sum_k gamma^(k-1) J(s_k, a_k), J of MODEL.md 4 on the true state;
- epochs to complete a task, release to completion, both counted (mean over the episode's
  completed tasks; episodes that complete none are left out);
- epochs in collision (d_k = 0), requests refused (eligible rh1/rh2 answered no), tasks
  completed.

The queue (MODEL.md 8.1): with a configuration whose stream has a queue, the robot observes
l = min(tasks waiting in the task book, L) (released, not yet in the cell) and every selector
reads the policy / Q at that l; the discounted cost then includes w * (every waiting task, not
capped at L) per epoch, for every selector alike, and the table gains the waiting task-epochs
(`QUEUE_METRICS`). `waiting_cost=` charges a w in any configuration (so that a run planning
without a queue is scored the same way, `hrc-evaluate --waiting-cost`); without a queue and
without it nothing is charged and the output is what it always was.

For speed the episodes run side by side: `BatchSimulator` is the epoch protocol of
`simulator.simulate` written over arrays of episodes (task steps as lookup tables, the human's
draws by inverse CDF from the same uniforms, belief and selection as array arithmetic with the
same tie rules as `selection.ActionSelector`, the belief by `BeliefFilter.update_many`, given the
epoch's observable transition as evidence in ``posterior`` mode). The
test suite checks that it reproduces `simulate` episode by episode. qmdp uses the full Q table
of one Bellman step on the solved value (`FactoredBellman.q`), computed once.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, fields

import numpy as np

from ..pomdp.belief import BeliefFilter
from ..cell.human import UNIFORMS_PER_EPOCH, sample_index
from ..model import (ACTION_EMOTION_GROUP, ACTIONS, DELTAS, DN, N_DISTANCE, N_HIDDEN,
                     TASK_VARIABLES, HRCModel, first_in_safety_order,
                     request_eligible, safest_best)
from ..mdp.policy import policy_arrays
from ..decision.selection import POMDP_SELECTORS, VOTE_TOLERANCE, check_alpha_columns
from .simulation import SIMULATION_SELECTORS, Scenario, case_study, check_model_cell

METRICS = (
    ('discounted_cost', 'discounted cost'),
    ('epochs_to_complete', 'epochs to complete a task'),
    ('collision_epochs', 'epochs in collision'),
    ('collision_stuck', 'share with > 3 epochs in a row at d = 0'),
    ('refused_requests', 'requests refused'),
    ('tasks_completed', 'tasks completed'),
)
# where waiting tasks are charged (MODEL.md 8.1): also the waiting task-epochs
QUEUE_METRICS = METRICS + (('waiting_epochs', 'waiting task-epochs'),)
STUCK_EPOCHS = 3    # more epochs than this in a row at d = 0: the cell is stuck in collision
SCENARIOS = ('random', 'case-study')
Z95 = 1.959963984540054


def human_seed(seed: int, episode: int) -> list:
    """Seed of episode `episode`'s simulated human (the same for every selector)."""
    return [seed, episode]


def random_scenarios(model: HRCModel, episodes: int, epochs: int, seed: int = 0,
                     task_rate: float = 0.2, prior=None) -> list:
    """Seeded episodes: random (em, ea) in 0..2, d in 1..3, an idle cell, a task at epoch 1
    and then a new random task (tp 1..rho, tc 1..sigma, tx 0..3) with probability
    `task_rate` per epoch; released tasks queue until the cell is idle.

    (em, ea) are uniform, or with `prior` (9 probabilities of h = 3*em + ea, a
    configuration's `observation_prior`: the cell's people, MODEL.md 6.1) h is drawn from it
    (one draw of the episode's generator in place of the two uniform integers, so the rest of
    the episode differs from the uniform one's). Without it, the episodes are as always."""
    for name, v, lo in (('episodes', episodes, 1), ('epochs', epochs, 1), ('seed', seed, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f'{name} must be an integer >= {lo}, got {v!r}')
    if not 0.0 <= task_rate <= 1.0:
        raise ValueError(f'task_rate must be a probability in [0, 1], got {task_rate!r}')
    if prior is not None:
        prior = np.asarray(prior, dtype=float)
        if (prior.shape != (N_HIDDEN,) or not np.all(prior >= 0)
                or not abs(prior.sum() - 1.0) < 1e-9):
            raise ValueError(f'prior must be {N_HIDDEN} probabilities of h = 3*em + ea summing '
                             f'to 1, got {prior.tolist()!r}')
        prior = tuple(float(p) for p in prior)
    args = (int(model.rho), int(model.sigma), int(episodes), int(epochs), int(seed),
            float(task_rate), prior)
    if episodes * epochs <= KEPT_EPISODE_EPOCHS:
        return list(_kept_scenarios(*args))
    return list(_scenarios(*args))


# `random_scenarios` keeps the last few sets of episodes up to this size (episodes x epochs;
# a plant check's 1000 x 50 is 50,000): the plant's check evaluates the running and the new
# policy on the same seeded episodes, each refit twice, and drew them anew every time (a
# seventh of a check's time). Larger sets are drawn every time, not held in memory.
KEPT_EPISODE_EPOCHS = 200_000


def _scenarios(rho: int, sigma: int, episodes: int, epochs: int, seed: int, task_rate: float,
               prior: tuple | None) -> tuple:
    """`random_scenarios`' episodes (its arguments checked), as a tuple."""
    scenarios = []
    for e in range(episodes):
        rng = np.random.default_rng([seed, e, 1])
        if prior is None:
            em, ea = (int(v) for v in rng.integers(0, 3, size=2))
        else:
            em, ea = divmod(int(rng.choice(N_HIDDEN, p=prior)), 3)
        d = int(rng.integers(1, 4))
        release = rng.random(epochs) < task_rate
        release[0] = True
        tp = rng.integers(1, rho + 1, size=epochs)
        tc = rng.integers(1, sigma + 1, size=epochs)
        tx = rng.integers(0, 4, size=epochs)
        schedule = tuple((k + 1, (int(tp[k]), int(tc[k]), int(tx[k])))
                         for k in np.flatnonzero(release))
        scenarios.append(Scenario((em, ea, 0, 0, 0, 0, 0, 0, 0, 0, d), schedule, epochs,
                                  name=f'episode {e}'))
    return tuple(scenarios)


# the same episodes for the same arguments (Scenario is frozen: sharing them is safe)
_kept_scenarios = functools.lru_cache(maxsize=8)(_scenarios)


def episodes_of(model: HRCModel, scenario: str, episodes: int, epochs: int, seed: int = 0,
                task_rate: float = 0.2, prior=None) -> tuple[list, list]:
    """(scenarios, human seeds) of `episodes` episodes.

    ``random``: `random_scenarios` (its people drawn from `prior` if given), human seed
    ``(seed, e)``. ``case-study``: the paper's case
    study (MODEL.md 7) every time, with `epochs` epochs and human seed ``seed + e``, so that
    episode e is ``hrc-simulate --seed <seed + e>``.
    """
    if scenario == 'random':
        return (random_scenarios(model, episodes, epochs, seed, task_rate, prior),
                [human_seed(seed, e) for e in range(episodes)])
    if scenario == 'case-study':
        base = case_study()
        one = Scenario(base.initial_state, base.schedule, epochs, base.name)
        return [one] * episodes, [seed + e for e in range(episodes)]
    raise ValueError(f'unknown scenario {scenario!r}; expected one of {", ".join(SCENARIOS)}')


@dataclass
class BatchResult:
    """Per-episode metrics of one selector (arrays of length E) and, if kept, the actions."""

    selector: str
    discounted_cost: np.ndarray
    epochs_to_complete: np.ndarray    # NaN where the episode completed no task
    collision_epochs: np.ndarray
    longest_collision_run: np.ndarray  # most consecutive epochs at d = 0
    refused_requests: np.ndarray
    requests: np.ndarray
    tasks_completed: np.ndarray
    tasks_released: np.ndarray
    waiting_epochs: np.ndarray        # sum over the epochs of the tasks waiting (uncapped)
    discounted_waiting: np.ndarray    # sum_k gamma^(k-1) (tasks waiting at epoch k)
    actions: np.ndarray | None = None   # (E, K) action indices
    trajectory: dict | None = None      # with run(record=True): (E, K) arrays, see `run`

    def recordings(self, model: HRCModel) -> list:
        """The recorded episodes as `recordings.Recording`s (what a robot sees: no em, ea),
        with `queued` the tasks waiting per epoch (MODEL.md 8.1; the task book's, uncapped)."""
        from ..learning.recordings import Recording
        t = self.trajectory
        if t is None:
            raise ValueError('run the batch with record=True to keep its trajectories')
        grid = model.task_grid
        epochs = np.arange(1, t['action'].shape[1] + 1)
        out = []
        for e in range(t['action'].shape[0]):
            task = np.stack([grid[n][t['y'][e]] for n in TASK_VARIABLES], axis=1)
            out.append(Recording('simulation', str(e), epochs, task, t['d'][e],
                                 t['observation'][e], t['action'][e], t['accepted'][e], epochs,
                                 queued=t['waiting'][e].copy()))
        return out

    @property
    def collision_stuck(self) -> np.ndarray:
        """1 where an episode spent more than STUCK_EPOCHS epochs in a row at d = 0."""
        return (self.longest_collision_run > STUCK_EPOCHS).astype(float)


class BatchSimulator:
    """`simulator.simulate` over an array of episodes (see the module docstring)."""

    def __init__(self, model: HRCModel, policy, value=None, mode: str | None = None,
                 fail_safe: bool = True, pomdp=None, world: HRCModel | None = None,
                 waiting_cost: float | None = None):
        self.policy, value = policy_arrays(policy, value)
        self.model = model
        world = model if world is None else world
        check_model_cell(world)
        self.world = world
        if self.policy.shape != (model.n_states,):
            raise ValueError(f'the policy has {self.policy.size} states, the model '
                             f'{model.n_states}')
        if world.dims != model.dims:
            raise ValueError(f'the world (rho {world.rho}, sigma {world.sigma}) and the planning '
                             f'model (rho {model.rho}, sigma {model.sigma}) differ in size')
        self.value = value
        self.fail_safe = fail_safe
        self.filter = BeliefFilter(model, mode=mode)
        self.mode = self.filter.mode
        n_y = model.n_task
        self.columns = n_y * N_DISTANCE
        # the queue (MODEL.md 8.1): the policy's rows per level l, as columns l * columns + c
        self.levels, self.top, self.n_base = model.n_levels, model.queue_length or 0, model.n_base
        if self.levels == 1:
            self.by_h = self.policy.reshape(N_HIDDEN, self.columns)
        else:
            self.by_h = np.ascontiguousarray(self.policy.reshape(
                self.levels, N_HIDDEN, self.columns).transpose(1, 0, 2).reshape(N_HIDDEN, -1))
        # what waiting costs is the world's (the costs are drawn from it), not the plan's
        self.waiting_cost = charged_waiting_cost(world, waiting_cost)
        self.state_cost = world.state_cost_vector
        self.action_cost = world.action_cost
        grid = model.task_grid
        self.grid = grid
        # y' = task_step[a, accepted, y]; eligible[a, y]: an eligible request.
        self.task_step = np.stack([
            np.stack([model.task_index(world.step_task(grid, a, acc)) for acc in (False, True)])
            for a in range(len(ACTIONS))]).astype(np.intp)
        self.eligible = np.stack([request_eligible(a, grid['tp'], grid['tx'], grid['ty'])
                                  for a in range(len(ACTIONS))])
        cfg = world.config        # the human's side: the world's
        self.p_accept = cfg.p_accept
        self.delta_cdf = np.cumsum(cfg.p_delta, axis=1)
        self.next_d = np.array([[[world.next_distance(d, a, delta) for delta in DELTAS]
                                 for d in range(N_DISTANCE)] for a in range(len(ACTIONS))])
        chains = world.emotion_chains
        self.em_cdf = np.stack([np.cumsum(chains[ACTION_EMOTION_GROUP[a]][0], axis=1)
                                for a in range(len(ACTIONS))])
        self.ea_cdf = np.stack([np.cumsum(chains[ACTION_EMOTION_GROUP[a]][1], axis=1)
                                for a in range(len(ACTIONS))])
        likelihood = (self.filter if world is model else BeliefFilter(world)).likelihood
        self.observation_cdf = np.cumsum(likelihood, axis=0).T
        self._q = None
        self.pomdp = pomdp

    @property
    def q_table(self) -> np.ndarray:
        """Q(s, a) for every state, (N, 8): one Bellman step on the solved value."""
        if self._q is None:
            if self.value is None:
                raise ValueError("selector 'qmdp' needs the solved value function")
            from ..mdp.solver import FactoredBellman
            self._q = np.ascontiguousarray(FactoredBellman(self.model).q(self.value).T)
        return self._q

    @property
    def alphas(self):
        """The POMDP policy's `AlphaPolicy` (pomdp and fib; the shipped one for the
        configuration when none was given)."""
        if self.pomdp is None:
            from ..pomdp.policy import load_shipped_pomdp_policy
            self.pomdp = load_shipped_pomdp_policy(self.model.config)
        alphas = getattr(self.pomdp, 'policy', self.pomdp)
        check_alpha_columns(alphas, self.model)
        return alphas

    # -- selection, vectorised with ActionSelector's tie rules ---------------------------
    def _paper(self, belief, column):
        actions = self.by_h[:, column].T                              # (E, 9)
        weights = belief[:, :, None] * (actions[:, :, None] == np.arange(len(ACTIONS)))
        scores = weights.sum(axis=1)
        single = weights.max(axis=1)
        tied = scores >= scores.max(axis=1, keepdims=True) - VOTE_TOLERANCE
        top = np.where(tied, single, -np.inf).max(axis=1, keepdims=True)
        several = tied.sum(axis=1) > 1
        tied[several] &= single[several] >= top[several] - VOTE_TOLERANCE
        return first_in_safety_order(tied)

    def _mls(self, belief, column):
        h = np.argmax(belief >= belief.max(axis=1, keepdims=True) - VOTE_TOLERANCE, axis=1)
        return self.by_h[h, column]

    def _qmdp(self, belief, column, level):
        candidates = (np.arange(N_HIDDEN)[None, :] * self.columns + column[:, None]
                      + (level * self.n_base)[:, None])
        scores = np.einsum('eh,eha->ea', belief, self.q_table[candidates])
        return safest_best(scores)

    # -- the episodes --------------------------------------------------------------------
    def run(self, scenarios, seeds, selector: str = 'paper', keep_actions: bool = False,
            explore: float = 0.0, record: bool = False) -> BatchResult:
        """Run the scenarios side by side; `seeds[e]` seeds episode e's human.

        `explore`: each epoch, with this probability, the robot takes an action drawn
        uniformly from the eight instead of the selector's (before the fail-safe), from a
        stream of its own per episode (spawned from the human's seed), so the human's draws
        stay common to every run. `record`: keep per epoch the task index `y`, `d`,
        `observation` O_k, `action`, `accepted` (1 / 0 for an eligible request, else -1),
        the tasks `waiting` in the task book (MODEL.md 8.1) and the hidden `em`, `ea` in
        `BatchResult.trajectory` ((E, K) arrays)."""
        if not 0.0 <= explore <= 1.0:
            raise ValueError(f'explore must be a probability in [0, 1], got {explore!r}')
        if selector not in SIMULATION_SELECTORS:
            raise ValueError(f'unknown selector {selector!r}; expected one of '
                             f'{", ".join(SIMULATION_SELECTORS)}')
        if len(scenarios) != len(seeds) or not scenarios:
            raise ValueError('give one seed per scenario, and at least one scenario')
        epochs = scenarios[0].epochs
        if any(s.epochs != epochs for s in scenarios):
            raise ValueError('the scenarios of one batch must have the same number of epochs')
        if selector == 'qmdp' and self.value is None:     # fail early, before any work
            raise ValueError("selector 'qmdp' needs the solved value function")
        if selector in POMDP_SELECTORS:
            self.alphas                                    # noqa: B018 - load it now
        model, n = self.model, len(scenarios)
        rows = np.arange(n)
        initial = np.array([s.initial_state for s in scenarios], dtype=np.int64)
        model.index(initial)                               # range check
        em, ea, d = initial[:, 0].copy(), initial[:, 1].copy(), initial[:, 10].copy()
        y = model.task_index({v: initial[:, 2 + i] for i, v in enumerate(TASK_VARIABLES)})
        y = np.asarray(y, dtype=np.intp)

        # Tasks per episode: an initial task (if any, started at epoch 1), then the schedule.
        lists = []
        for s, first in zip(scenarios, initial):
            own = [(1, int(first[2]), int(first[3]), int(first[4]))] if first[2] > 0 else []
            own += [(int(k), int(tp), int(tc), int(tx)) for k, (tp, tc, tx) in
                    sorted(s.schedule, key=lambda entry: entry[0])]
            lists.append(own)
        width = max(1, max(len(t) for t in lists))
        task = np.zeros((n, width, 4), dtype=np.int64)
        task[:, :, 0] = epochs + 1                         # padding: never released
        for e, own in enumerate(lists):
            if own:
                task[e, :len(own)] = own
        for name, col, lo, hi in (('tp', 1, 1, model.rho), ('tc', 2, 1, model.sigma),
                                  ('tx', 3, 0, 3)):
            real = task[:, :, 0] <= epochs
            bad = real & ((task[:, :, col] < lo) | (task[:, :, col] > hi))
            if bad.any():
                raise ValueError(f'bad task in a schedule: {name} must lie in {lo}..{hi}')
        n_tasks = np.array([len(t) for t in lists])
        released = np.array([sum(1 for t in own if t[0] <= epochs) for own in lists])
        current = np.where(initial[:, 2] > 0, 0, -1)
        next_task = (initial[:, 2] > 0).astype(np.int64)
        complete = np.zeros((n, width), dtype=np.int64)

        uniforms = np.stack([np.random.default_rng(seed).random(1 + UNIFORMS_PER_EPOCH * epochs)
                             for seed in seeds])
        observation = sample_index(self.observation_cdf[3 * em + ea], uniforms[:, 0]) + 1
        belief = self.filter.initial_many(observation)
        exploring = None
        if explore > 0.0:
            exploring = np.stack([np.random.default_rng(np.random.SeedSequence(
                seed).spawn(1)[0]).random(2 * epochs) for seed in seeds]).reshape(n, epochs, 2)
        kept = ({name: np.zeros((n, epochs), dtype=np.int64) for name in
                 ('y', 'd', 'observation', 'action', 'accepted', 'em', 'ea', 'waiting')} if record
                else None)

        cost = np.zeros(n)
        waiting_epochs = np.zeros(n, dtype=np.int64)
        discounted_waiting = np.zeros(n)
        collisions = np.zeros(n, dtype=np.int64)
        run = np.zeros(n, dtype=np.int64)
        longest_run = np.zeros(n, dtype=np.int64)
        requests = np.zeros(n, dtype=np.int64)
        refused = np.zeros(n, dtype=np.int64)
        actions_kept = np.zeros((n, epochs), dtype=np.int8) if keep_actions else None
        grid_tp = self.grid['tp']
        for k in range(1, epochs + 1):
            # 1. begin_epoch(k): an idle cell takes the next released task.
            slot = np.minimum(next_task, width - 1)
            take = ((grid_tp[y] == 0) & (next_task < n_tasks)
                    & (task[rows, slot, 0] <= k))
            if take.any():
                t = task[rows[take], slot[take]]
                parts = [t[:, 1], t[:, 2], t[:, 3], np.zeros(len(t), dtype=np.int64)]
                parts += [self.grid[v][y[take]] for v in ('hp', 'hc', 'bp', 'bc')]
                y[take] = np.ravel_multi_index(tuple(parts), model.task_dims)
                current[take] = slot[take]
                next_task[take] += 1
            # the tasks released and waiting (not the current one); l = min(waiting, L)
            waiting = (task[:, :, 0] <= k).sum(axis=1) - next_task
            level = np.minimum(waiting, self.top)
            # 2-3. decide from (belief, observable); fail-safe at d = 0.
            column = y * N_DISTANCE + d
            h = 3 * em + ea
            if selector == 'mdp':
                action = self.policy[level * self.n_base + h * self.columns
                                     + column].astype(np.intp)
            elif selector == 'paper':
                action = self._paper(belief, level * self.columns + column)
            elif selector == 'mls':
                action = self._mls(belief, level * self.columns + column).astype(np.intp)
            elif selector == 'pomdp':     # the policy's columns carry l (MODEL.md 8.1)
                action = self.alphas.pomdp_many(belief, level * self.columns + column)
            elif selector == 'fib':
                action = self.alphas.fib_many(belief, level * self.columns + column)
            else:
                action = self._qmdp(belief, column, level)
            if exploring is not None:
                other = exploring[:, k - 1, 0] < explore
                action = np.where(other, (exploring[:, k - 1, 1] * len(ACTIONS)).astype(np.intp),
                                  action)
            if self.fail_safe:
                action = np.where(d == 0, DN, action)
            if keep_actions:
                actions_kept[:, k - 1] = action
            cost += self.world.gamma ** (k - 1) * (self.state_cost[h * self.columns + column]
                                              + self.action_cost[action])
            waiting_epochs += waiting
            discounted_waiting += self.world.gamma ** (k - 1) * waiting
            if self.waiting_cost is not None:
                cost += self.world.gamma ** (k - 1) * self.waiting_cost * waiting
            collisions += d == 0
            run = np.where(d == 0, run + 1, 0)
            np.maximum(longest_run, run, out=longest_run)
            # 4. the human reacts: acceptance, Delta, em', ea', O' (cell.SimulatedHuman order).
            u = uniforms[:, 1 + UNIFORMS_PER_EPOCH * (k - 1):1 + UNIFORMS_PER_EPOCH * k]
            eligible = self.eligible[action, y]
            accepted = eligible & (u[:, 0] < self.p_accept[em])
            requests += eligible
            refused += eligible & ~accepted
            if kept is not None:
                for name, value in (('y', y), ('d', d), ('observation', observation),
                                    ('waiting', waiting),
                                    ('action', action), ('em', em), ('ea', ea),
                                    ('accepted', np.where(eligible, accepted, -1))):
                    kept[name][:, k - 1] = value
            delta = sample_index(self.delta_cdf[ea], u[:, 1])
            d_start = d
            d = self.next_d[action, d, delta]
            em = sample_index(self.em_cdf[action, em], u[:, 2])
            ea = sample_index(self.ea_cdf[action, ea], u[:, 3])
            observation = sample_index(self.observation_cdf[3 * em + ea], u[:, 4]) + 1
            # 5. the task book applies (a, accepted); the belief is updated.
            y_next = self.task_step[action, accepted.astype(np.intp), y]
            done = (grid_tp[y] > 0) & (grid_tp[y_next] == 0)
            complete[rows[done], current[done]] = k
            current[done] = -1
            y = y_next
            evidence = (model.transition_likelihood(action, eligible, accepted, d_start, d)
                        if self.mode == 'posterior' else None)
            belief = self.filter.update_many(belief, action, observation, evidence)

        completed = complete > 0
        latency = np.where(completed, complete - task[:, :, 0] + 1, 0)
        n_done = completed.sum(axis=1)
        with np.errstate(invalid='ignore', divide='ignore'):
            mean_latency = np.where(n_done > 0, latency.sum(axis=1) / n_done, np.nan)
        return BatchResult(selector, cost, mean_latency, collisions, longest_run, refused,
                           requests, n_done, released, waiting_epochs, discounted_waiting,
                           actions_kept, kept)


def charged_waiting_cost(model: HRCModel, waiting_cost: float | None = None) -> float | None:
    """w charged per waiting task per epoch: `waiting_cost` when given, else the
    configuration's stream.waiting_cost with a queue (MODEL.md 8.1), else None (not charged)."""
    if waiting_cost is not None:
        w = float(waiting_cost)
        if not (w >= 0 and np.isfinite(w)):
            raise ValueError(f'waiting_cost must be a finite number >= 0, got {waiting_cost!r}')
        return w
    return model.config.waiting_cost if model.queue is not None else None


# -- statistics and outputs ------------------------------------------------------------------
def summarize(result: BatchResult, metrics=METRICS) -> dict:
    """metric -> {n, mean, half_width, low, high} (95% normal interval over episodes)."""
    out = {}
    for metric, _ in metrics:
        x = np.asarray(getattr(result, metric), dtype=float)
        x = x[np.isfinite(x)]
        mean = float(x.mean()) if x.size else float('nan')
        half = float(Z95 * x.std(ddof=1) / np.sqrt(x.size)) if x.size > 1 else float('nan')
        out[metric] = {'n': int(x.size), 'mean': mean, 'half_width': half,
                       'low': mean - half, 'high': mean + half}
    return out


def paired_difference(result: BatchResult, reference: BatchResult) -> dict:
    """Mean and 95% interval of the per-episode cost difference (common random numbers)."""
    diff = result.discounted_cost - reference.discounted_cost
    mean = float(diff.mean())
    half = float(Z95 * diff.std(ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else float('nan')
    return {'mean': mean, 'half_width': half, 'low': mean - half, 'high': mean + half}


TABLE_LABELS = ('discounted cost', 'epochs per task', 'collision epochs', 'stuck > 3 at d=0',
                'refused requests', 'tasks completed', 'cost - mdp cost')
QUEUE_TABLE_LABELS = TABLE_LABELS[:-1] + ('waiting epochs',) + TABLE_LABELS[-1:]


def format_regret(planned: dict, true: dict) -> str:
    """Per selector: the cost planning with the configuration, with the true one, and the
    regret (their paired difference, 95% interval), over the same episodes of the true world."""
    head = (f'{"selector":<9}{"cost, planned model":>22}{"cost, true model":>22}'
            f'{"regret (paired)":>22}')
    lines = [head, '-' * len(head)]
    for selector, result in planned.items():
        a = summarize(result)['discounted_cost']
        b = summarize(true[selector])['discounted_cost']
        r = paired_difference(result, true[selector])
        lines.append(f'{selector:<9}{a["mean"]:>13.3f} ± {a["half_width"]:<6.3f}'
                     f'{b["mean"]:>13.3f} ± {b["half_width"]:<6.3f}'
                     f'{r["mean"]:>+13.3f} ± {r["half_width"]:<6.3f}')
    return '\n'.join(lines)


def format_table(summaries: dict, differences: dict, metrics=METRICS) -> str:
    """Mean ± 95% half-width per selector and metric; the last column is paired (CRN)."""
    width = 19
    labels = TABLE_LABELS if metrics is METRICS else QUEUE_TABLE_LABELS
    head = f'{"selector":<9}' + ''.join(f'{n:>{width}}' for n in labels)
    lines = [head, '-' * len(head)]
    for selector, summary in summaries.items():
        cells = []
        for metric, _ in metrics:
            s = summary[metric]
            cells.append(f'{s["mean"]:.3f} ± {s["half_width"]:.3f}')
        diff = differences.get(selector)
        cells.append('' if diff is None else f'{diff["mean"]:+.3f} ± {diff["half_width"]:.3f}')
        lines.append(f'{selector:<9}' + ''.join(f'{c:>{width}}' for c in cells))
    return '\n'.join(lines)


def format_paired(results: dict, baseline: str) -> str:
    """Per selector, the paired (same episodes) discounted-cost difference to `baseline`:
    mean, 95% interval, and whether the interval excludes zero."""
    reference = results[baseline]
    lines = [f'paired differences of the discounted cost to {baseline} (same episodes, 95%):']
    for selector, result in results.items():
        if selector == baseline:
            continue
        d = paired_difference(result, reference)
        verdict = ('higher' if d['low'] > 0 else 'lower' if d['high'] < 0
                   else 'not distinguishable')
        lines.append(f'  {selector:<9} - {baseline:<9} {d["mean"]:+8.3f} ± {d["half_width"]:.3f}'
                     f'  [{d["low"]:+.3f}, {d["high"]:+.3f}]  {verdict}')
    return '\n'.join(lines)


def evaluate(model: HRCModel, policy, episodes: int = 1000, epochs: int = 50, seed: int = 0,
             task_rate: float = 0.2, selectors=('paper', 'qmdp', 'mls', 'mdp'),
             mode: str | None = None, fail_safe: bool = True, chunk: int = 250,
             progress=None, scenario: str = 'random', pomdp=None,
             world: HRCModel | None = None, waiting_cost: float | None = None) -> dict:
    """selector -> BatchResult over the same seeded episodes (common random numbers).

    `world`: the model the human and the costs are drawn from when it is not the one the
    robot plans with (`model`: its policy and belief filter); the episodes and the human's
    uniforms do not depend on either, so runs with different planning models are paired. The
    random scenario's people are uniform, or drawn from the world's person prior when a
    `world` with one is given (`observation.prior`, MODEL.md 6.1); the planning model's prior
    never changes who the people are, only what the robot believes of them."""
    for s in selectors:
        if s not in SIMULATION_SELECTORS:
            raise ValueError(f'unknown selector {s!r}; expected some of '
                             f'{", ".join(SIMULATION_SELECTORS)}')
    people = None if world is None else world.config.observation_prior
    scenarios, seeds = episodes_of(model, scenario, episodes, epochs, seed, task_rate, people)
    sim = BatchSimulator(model, policy, mode=mode, fail_safe=fail_safe, pomdp=pomdp,
                         world=world, waiting_cost=waiting_cost)
    results = {}
    for selector in selectors:
        t0 = time.perf_counter()
        parts = []
        for start in range(0, episodes, chunk):
            stop = min(start + chunk, episodes)
            parts.append(sim.run(scenarios[start:stop], seeds[start:stop], selector))
            if progress:
                progress(f'{selector}: {stop}/{episodes} episodes '
                         f'({time.perf_counter() - t0:.1f} s)')
        results[selector] = BatchResult(selector, *(
            np.concatenate([getattr(p, f.name) for p in parts])
            for f in fields(BatchResult)[1:-2]))
    return results
