"""The HRC decision model of MODEL.md: state space, transition rules and cost.

Symbols follow the paper (MODEL.md section 1): the state is the 11-tuple
``(em, ea, tp, tc, tx, ty, hp, hc, bp, bc, d)``:

- em, ea: the human's hidden motivation and aggression (0 low .. 2 high); h = 3*em + ea;
- tp, tc, tx, ty: task priority (0 = no task), remaining epochs, nature (0 robot, 1 human,
  2 either, 3 both), commitment (0 none, 1 human, 2 robot, 3 joint);
- hp, hc / bp, bc: human / robot activity priority and remaining epochs;
- d: distance level (0 collision, 1 inner, 2 middle, 3 outer circle or beyond).

The flat index is row-major over these variables with dims
``[3, 3, rho+1, sigma+1, 4, 4, rho+1, sigma+1, rho+1, sigma+1, 4]``, so a value vector of
length N reshapes to ``(9, n_task, 4)``: hidden part h, the task/activity part
``y = (tp, tc, tx, ty, hp, hc, bp, bc)`` and the distance d. The solver exploits that split.

One decision epoch (MODEL.md 3): three independent random events, then deterministic rules.

1. Acceptance: rh1 is eligible when ``tp > 0, ty = 0, tx in {1, 2}``, rh2 when
   ``tp > 0, ty = 0, tx = 3``; an eligible request is accepted with ``p_accept[em]``.
2. Commitment and activities (`step_task`): an accepted rh1 gives ``ty'=1, hp'=tp, hc'=tc``;
   an accepted rh2 ``ty'=3`` and both agents take (tp, tc); an effective ct
   (``tp > 0, ty = 0, tx in {0, 2}``) ``ty'=2, bp'=tp, bc'=tc``. Otherwise counters count
   down (``hc' = max(0, hc-1)``, ``hp' = hp if hc != 0 else 0``, the same for the robot),
   except that under dn the robot is paused (``bc' = bc``), and under dp and dm too where
   the configuration's ``model.robot_paused_by`` says so (the cell with an arm, MODEL.md 3.2);
   with its ``model.robot_rate`` the counter of a robot that works runs down only with
   probability rate[tx, d] (an event of its own, `task_steps`).
   A committed task whose committed agents' counters are all 0 is complete and resets
   ``tp = tc = tx = ty = 0``; otherwise ``tc'`` is the largest committed counter.
   An uncommitted task waits unchanged.
3. Distance: Delta in {-1, 0, +1} drawn from ``p_delta[ea]``; dp: ``min(3, d+1-Delta)``,
   dm: ``max(1, d-1-Delta)``, otherwise ``min(3, max(0, d-Delta))``. With the configuration's
   ``model.retreat_reach`` r, dp gains the band only from d < r: ``min(3, d+[d<r]-Delta)``;
   with its ``model.approach_reach`` c, dm gains the band only from d > c and has no floor:
   ``min(3, max(0, d-[d>c]-Delta))`` (c = 3: dm moves the distance as nw does).
4. Emotions: em and ea each follow a bounded (down, stay, up) chain chosen by the action's
   group (base, motivate = mh, request = rh1/rh2); the 9x9 matrix is their Kronecker product.

5. Arrivals (MODEL.md 8, only with a configuration's `stream` section): when the step
   leaves the cell without a task (tp' = 0), a task (tp, tc, tx) ~ q enters it, uncommitted,
   with probability ``arrival_complete`` if the epoch started with a task (it just completed)
   and ``arrival_idle`` if it started idle (`arrivals`). Without a stream no task arrives.
6. The queue (MODEL.md 8.1, only with ``stream.queue: L``): the state gets the number l = 0..L
   of released tasks waiting (not the current one) as its outermost index, s = l * N0 + s0
   (N0 = 9 * n_task * 4, `n_base`). After the task step a task is released with probability
   ``arrival_busy`` (the epoch started with a task) or ``arrival_idle``; l_tmp = l + a; if the
   step left the cell idle and l_tmp > 0 the head of the queue enters (as in 5) and l_tmp -= 1;
   l' = min(l_tmp, L), a task beyond L is dropped and charged ``drop_cost`` = w / (1 - gamma).
   The cost is J + w * l plus the expected drop charge (`flat_cost`). `queue` holds the pieces;
   `arrivals` is None for such a configuration (it is the queue-less stream's).

Cost (MODEL.md 4): ``J(s, a) = k1*f1(s) + k2*f2(s) + g(a)``; see `state_cost`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .config import EMOTION_GROUPS, Config

ACTIONS = ('nw', 'rh1', 'rh2', 'ct', 'dp', 'dm', 'mh', 'dn')
ACTION_INDEX = {name: i for i, name in enumerate(ACTIONS)}
NW, RH1, RH2, CT, DP, DM, MH, DN = range(8)
# Ties go to the first action of this order: an idle robot stops rather than "works".
SAFETY_ORDER = (DN, DP, NW, CT, RH1, RH2, MH, DM)
# Two action values are tied when within TIE_TOLERANCE * max(1, |best|) of the best (MODEL.md
# 5): `tie_floor`, `safest_best` and `first_in_safety_order` below are the one home of that
# rule (the solver's greedy policy and policy iteration, the qmdp, pomdp and fib selectors,
# the POMDP backups).
TIE_TOLERANCE = 1e-9
# Which emotion chain each action uses (MODEL.md 3.4).
ACTION_EMOTION_GROUP = {NW: 'base', CT: 'base', DP: 'base', DM: 'base', DN: 'base',
                        MH: 'motivate', RH1: 'request', RH2: 'request'}

STATE_VARIABLES = ('em', 'ea', 'tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc', 'd')
TASK_VARIABLES = ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc')
OBSERVABLE_VARIABLES = STATE_VARIABLES[2:]   # tp tc tx ty hp hc bp bc d
N_HIDDEN = 9                      # h = 3*em + ea
N_DISTANCE = 4
DISTANCE_LEVELS = tuple(range(N_DISTANCE))   # d: 0 collision, 1 inner, 2 middle, 3 outer
OBSERVATION_LEVELS = (1, 2, 3)    # O: the human velocity level (MODEL.md 6)
N_OBSERVATIONS = len(OBSERVATION_LEVELS)
DELTAS = (-1, 0, 1)


def tie_floor(best):
    """Scores at or above ``tie_floor(best)`` are tied with the best score `best` (a float or
    an array of them): ``best - TIE_TOLERANCE * max(1, |best|)``."""
    return best - TIE_TOLERANCE * np.maximum(1.0, np.abs(best))


def first_in_safety_order(tied, order=SAFETY_ORDER, axis: int = -1):
    """Per row of the bool mask `tied` (actions along `axis`, at least one True per row), the
    first action of `order` that is tied; an int array of the other axes' shape."""
    order = np.asarray(order)
    tied = np.moveaxis(np.asarray(tied, dtype=bool), axis, -1)
    return order[np.argmax(tied[..., order], axis=-1)]


def safest_best(scores, order=SAFETY_ORDER, axis: int = -1):
    """The tie rule on arrays: per row of `scores` (actions along `axis`, -inf for an action
    that is not available), the first action of `order` tied with the row's best."""
    scores = np.asarray(scores, dtype=float)
    best = np.max(scores, axis=axis, keepdims=True)
    return first_in_safety_order(scores >= tie_floor(best), order, axis)


def safest_best_one(scores, order) -> int:
    """The tie rule for one row of scores (a sequence over the actions, -inf where one is not
    available), in plain loops: the numba kernels compile this same function, the decision's
    scalar paths call it as it is. Equal to `safest_best` (the tests hold it so)."""
    best = -np.inf
    for a in order:
        if scores[a] > best:
            best = scores[a]
    floor = best - TIE_TOLERANCE * max(1.0, abs(best))
    for a in order:
        if scores[a] >= floor:
            return a
    return order[0]


def action_index(action: str | int) -> int:
    """Index of an action given by name (`'ct'`) or index; a clear error otherwise."""
    if isinstance(action, (int, np.integer)) and not isinstance(action, bool):
        if 0 <= int(action) < len(ACTIONS):
            return int(action)
        raise ValueError(f'action index {action} is out of range 0..{len(ACTIONS) - 1}')
    if isinstance(action, str) and action in ACTION_INDEX:
        return ACTION_INDEX[action]
    raise ValueError(f'unknown action {action!r}; expected one of {" ".join(ACTIONS)}')


def chain_matrix(down: float, stay: float, up: float) -> np.ndarray:
    """3x3 bounded chain: mass that would leave [0, 2] stays at the boundary."""
    m = np.zeros((3, 3))
    for i in range(3):
        m[i, max(i - 1, 0)] += down
        m[i, i] += stay
        m[i, min(i + 1, 2)] += up
    return m


def next_distance(d, action: int, delta, reach=None, approach=None):
    """MODEL.md 3.3 (works on scalars and arrays). `reach` (the configuration's
    ``model.retreat_reach``, `HRCModel.retreat_reach`): a retreat gains a band only from a
    band below it; None, the model's rule, from every band. `approach` (``model.approach_reach``,
    `HRCModel.approach_reach`): a move closer gains a band only from a band above it, and the
    paper's floor at band 1 goes (what keeps the person out of band 0 is not the robot's
    move: docs/ROBOT.md 4); None, the model's rule ``max(1, d - 1 - Delta)``."""
    if action == DP:
        gain = 1 if reach is None else (np.asarray(d) < reach).astype(np.int64)
        return np.minimum(3, d + gain - delta)
    if action == DM:
        if approach is None:
            return np.maximum(1, d - 1 - delta)
        gain = (np.asarray(d) > approach).astype(np.int64)
        return np.minimum(3, np.maximum(0, d - gain - delta))
    return np.minimum(3, np.maximum(0, d - delta))


def request_eligible(action: int, tp, tx, ty):
    """Whether `action` is an eligible request (MODEL.md 3.1); False for non-requests.

    The one home of the rule: the task book, the solver, the simulated cell and the batch
    evaluator all call it (on scalars or on arrays of task variables)."""
    open_task = (tp > 0) & (ty == 0)
    if action == RH1:
        return open_task & ((tx == 1) | (tx == 2))
    if action == RH2:
        return open_task & (tx == 3)
    return np.zeros(np.shape(tp), dtype=bool) if np.ndim(tp) else False


def commit_effective(tp, tx, ty):
    """Whether ct commits the robot (MODEL.md 3.2): an open task the robot may take alone."""
    return (tp > 0) & (ty == 0) & ((tx == 0) | (tx == 2))


def step_task(task: dict, action: int, accepted, robot_runs=None, paused=(DN,)) -> dict:
    """MODEL.md 3.2: the next (tp, tc, tx, ty, hp, hc, bp, bc), vectorised.

    `task` maps the variable names to equal-shape integer arrays (the epoch's start values);
    `accepted` is whether the human accepted (ignored unless the request is eligible).
    `robot_runs`: whether the robot's counter bc runs down this epoch; None is the model's
    rule: every action but those in `paused` (the configuration's ``robot_paused_by``,
    `HRCModel.paused`; dn alone in the paper's model). The cell with an arm (`robot.cell`,
    docs/ROBOT.md) passes whether the arm completed a cycle of its program, so bc follows the
    physical work.
    """
    tp, tc, tx, ty = task['tp'], task['tc'], task['tx'], task['ty']
    hp, hc, bp, bc = task['hp'], task['hc'], task['bp'], task['bc']
    accepted = np.asarray(accepted, dtype=bool)
    human_takes = request_eligible(action, tp, tx, ty) & accepted & (action == RH1)
    joint = request_eligible(action, tp, tx, ty) & accepted & (action == RH2)
    robot_commits = (action == CT) & commit_effective(tp, tx, ty)
    human_new = human_takes | joint
    robot_new = joint | robot_commits

    hc_n = np.where(human_new, tc, np.maximum(0, hc - 1))
    hp_n = np.where(human_new, tp, np.where(hc != 0, hp, 0))
    runs = (action not in paused) if robot_runs is None else np.asarray(robot_runs, dtype=bool)
    bc_run = np.where(runs, np.maximum(0, bc - 1), bc)
    bc_n = np.where(robot_new, tc, bc_run)
    bp_n = np.where(robot_new, tp, np.where(bc != 0, bp, 0))
    ty_n = np.where(human_takes, 1, np.where(joint, 3, np.where(robot_commits, 2, ty)))

    human_in = (ty_n == 1) | (ty_n == 3)
    robot_in = (ty_n == 2) | (ty_n == 3)
    remaining = np.maximum(np.where(human_in, hc_n, 0), np.where(robot_in, bc_n, 0))
    committed = ty_n != 0
    complete = committed & (remaining == 0)
    tc_n = np.where(committed, remaining, tc)
    return {
        'tp': np.where(complete, 0, tp), 'tc': np.where(complete, 0, tc_n),
        'tx': np.where(complete, 0, tx), 'ty': np.where(complete, 0, ty_n),
        'hp': hp_n, 'hc': hc_n, 'bp': bp_n, 'bc': bc_n,
    }


def entering_task(model: 'HRCModel', y: np.ndarray, tp, tc, tx) -> np.ndarray:
    """The task state after task (tp, tc, tx) enters an idle cell in task state y: the task
    uncommitted (ty = 0), the activities as they were (`TaskBook.begin_epoch`)."""
    grid = model.task_grid
    task = {n: grid[n][y] for n in TASK_VARIABLES}
    shape = np.shape(y)
    task.update(tp=np.broadcast_to(tp, shape), tc=np.broadcast_to(tc, shape),
                tx=np.broadcast_to(tx, shape), ty=np.zeros(shape, dtype=np.int64))
    return np.asarray(model.task_index(task), dtype=np.intp)


@dataclass(frozen=True)
class Arrivals:
    """The stream's arrivals on the task part (MODEL.md 8), as arrays over y.

    `idle[y]`: the cell of task state y has no task (tp = 0); `enter[y, k]`: the task state
    after task k of the stream enters the idle cell y (-1 where y is busy); `q` (K,) the
    tasks' probabilities; `p_idle`, `p_complete` the arrival probabilities after an epoch that
    started idle, and after one that started with a task."""

    idle: np.ndarray
    enter: np.ndarray
    q: np.ndarray
    p_idle: float
    p_complete: float

    def probability(self, source_y):
        """P(a task arrives | the step ends idle), by the epoch-start task state(s)."""
        return np.where(self.idle[source_y], self.p_idle, self.p_complete)


@dataclass(frozen=True)
class Queue:
    """The stream with a queue (MODEL.md 8.1). `levels` = L (l = 0..L); `arrivals` the task
    part's pieces (its `p_idle` = arrival_idle, `p_complete` = arrival_busy: P(a task is
    released | the epoch started with a task)); `waiting_cost` w per waiting task per epoch;
    `drop_cost` = w / (1 - gamma), the charge of a task released into a full queue."""

    levels: int
    arrivals: Arrivals
    waiting_cost: float
    drop_cost: float


@dataclass(frozen=True)
class Transition:
    """Sparse rows of P(. | s, a) for a batch of source states (flat indices)."""

    source: np.ndarray  # position of the source state in the batch, per entry
    target: np.ndarray  # flat index of s', per entry
    probability: np.ndarray


class HRCModel:
    """The exact model of MODEL.md for one configuration."""

    def __init__(self, config: Config):
        self.config = config
        self.rho = config.rho
        self.sigma = config.sigma
        p, c = self.rho + 1, self.sigma + 1
        self.dims = (3, 3, p, c, 4, 4, p, c, p, c, N_DISTANCE)
        self.task_dims = (p, c, 4, 4, p, c, p, c)
        self.n_task = int(np.prod(self.task_dims))
        # the paper's states N0; with a queue (MODEL.md 8.1) one copy per queue length l = 0..L,
        # l outermost: s = l * N0 + s0
        self.n_base = N_HIDDEN * self.n_task * N_DISTANCE
        self.queue_length = config.queue
        self.n_levels = 1 if self.queue_length is None else self.queue_length + 1
        self.n_states = self.n_levels * self.n_base
        self.gamma = config.gamma
        # the actions under which the robot's counter is paused (MODEL.md 3.2)
        self.paused = tuple(ACTION_INDEX[a] for a in config.robot_paused_by)
        # the band below which a retreat gains one (MODEL.md 3.3; None: every band)
        self.retreat_reach = config.retreat_reach
        # the band above which a move closer gains one (MODEL.md 3.3; None: the paper's rule)
        self.approach_reach = config.approach_reach
        # P(the robot's counter runs down in an epoch it works) by (tx, d) (MODEL.md 3.2;
        # None: 1, the paper's deterministic rule)
        self.robot_rate = config.robot_rate

    def next_distance(self, d, action: int, delta):
        """`next_distance` with this model's retreat and approach (`retreat_reach`,
        `approach_reach`)."""
        return next_distance(d, action, delta, self.retreat_reach, self.approach_reach)

    def step_task(self, task: dict, action: int, accepted, robot_runs=None) -> dict:
        """`step_task` with this model's rule for the robot's counter (`paused`)."""
        return step_task(task, action, accepted, robot_runs, self.paused)

    def run_probability(self, action: int, tx, d):
        """P(the robot's counter runs down this epoch | it works) of `action` at the tasks'
        natures `tx` and bands `d` (MODEL.md 3.2, `robot_rate`); None where the step has no
        such event: no rate, or an action that pauses the robot."""
        if self.robot_rate is None or action in self.paused:
            return None
        return self.robot_rate[np.asarray(tx), np.asarray(d)]

    def task_steps(self, task: dict, action: int, accepted, d) -> list:
        """[(the next task variables, their probability)] of one acceptance branch: the task
        step, split by whether the robot's counter runs (`run_probability`; one step of
        probability 1 without that event)."""
        rate = self.run_probability(action, task['tx'], d)
        if rate is None:
            return [(self.step_task(task, action, accepted), 1.0)]
        return [(self.step_task(task, action, accepted, True), rate),
                (self.step_task(task, action, accepted, False), 1.0 - rate)]

    # -- indexing ------------------------------------------------------------------------
    def index(self, state) -> int | np.ndarray:
        """Flat index of an 11-tuple (or of an (..., 11) array of states)."""
        state = np.asarray(state)
        if state.shape[-1:] != (11,):
            raise ValueError(f'a state has 11 variables {STATE_VARIABLES}, got shape '
                             f'{state.shape}')
        for k, (name, size) in enumerate(zip(STATE_VARIABLES, self.dims)):
            v = state[..., k]
            if np.any((v < 0) | (v >= size)):
                raise ValueError(f'state variable {name} must lie in 0..{size - 1}, got {v}')
        idx = np.ravel_multi_index(tuple(state[..., k] for k in range(11)), self.dims)
        return int(idx) if np.ndim(idx) == 0 else idx

    def state(self, index) -> tuple | np.ndarray:
        """The 11-tuple of a flat index (or an (n, 11) array for an array of indices)."""
        parts = np.unravel_index(index, self.dims)
        if np.ndim(index) == 0:
            return tuple(int(v) for v in parts)
        return np.stack(parts, axis=-1)

    def split(self, index):
        """(l, s0) of flat indices: the queue length and the index of the paper's state
        (l = 0, s0 = index without a queue)."""
        index = np.asarray(index, dtype=np.int64)
        if np.any((index < 0) | (index >= self.n_states)):
            raise ValueError(f'state index must lie in 0..{self.n_states - 1}')
        return index // self.n_base, index % self.n_base

    @cached_property
    def arrivals(self) -> Arrivals | None:
        """The configuration's task stream on the task part, None without one (and None for
        a stream with a queue: `queue`)."""
        if self.queue_length is not None:
            return None
        return self._arrivals()

    @cached_property
    def queue(self) -> Queue | None:
        """The stream with a queue (MODEL.md 8.1), None without one."""
        if self.queue_length is None:
            return None
        w = self.config.waiting_cost
        return Queue(self.queue_length, self._arrivals(), w, w / (1.0 - self.gamma))

    def _arrivals(self) -> Arrivals | None:
        stream = self.config.stream
        if stream is None:
            return None
        p_idle, p_complete, tasks, q = stream
        idle = self.task_grid['tp'] == 0
        y = np.arange(self.n_task)
        enter = np.stack([np.where(idle, entering_task(self, y, *t), -1) for t in tasks], axis=1)
        for a in (idle, enter, q):
            a.flags.writeable = False
        return Arrivals(idle, enter.astype(np.intp), q, p_idle, p_complete)

    @cached_property
    def task_grid(self) -> dict:
        """Task/activity variables of every y = 0..n_task-1 (int64 arrays)."""
        grid = np.unravel_index(np.arange(self.n_task), self.task_dims)
        return {name: g.astype(np.int64) for name, g in zip(TASK_VARIABLES, grid)}

    def task_index(self, task: dict) -> np.ndarray:
        return np.ravel_multi_index(tuple(task[n] for n in TASK_VARIABLES), self.task_dims)

    # -- dynamics pieces -----------------------------------------------------------------
    @cached_property
    def emotion_chains(self) -> dict:
        """Group -> (em chain, ea chain), the 3x3 bounded chains of MODEL.md 3.4."""
        return {group: tuple(chain_matrix(*self.config.emotion_chain(group, variable))
                             for variable in ('em', 'ea'))
                for group in EMOTION_GROUPS}

    @cached_property
    def emotion_matrices(self) -> dict:
        """Group -> 9x9 matrix P(h' | h) = kron(em chain, ea chain)."""
        return {group: np.kron(em, ea) for group, (em, ea) in self.emotion_chains.items()}

    def action_emotion_matrix(self, action: int) -> np.ndarray:
        return self.emotion_matrices[ACTION_EMOTION_GROUP[action]]

    def distance_matrix(self, action: int) -> np.ndarray:
        """Shape (3, 4, 4): P(d' | d, ea) under `action`."""
        p_delta = self.config.p_delta
        out = np.zeros((3, N_DISTANCE, N_DISTANCE))
        for ea in range(3):
            for d in range(N_DISTANCE):
                for k, delta in enumerate(DELTAS):
                    out[ea, d, self.next_distance(d, action, delta)] += p_delta[ea, k]
        return out

    def acceptance_probability(self, action: int, em, tp, tx, ty):
        """P(accepted | s, a): p_accept[em] for an eligible request, else 0."""
        return np.where(request_eligible(action, tp, tx, ty), self.config.p_accept[em], 0.0)

    @cached_property
    def distance_matrices(self) -> np.ndarray:
        """(8, 3, 4, 4): `distance_matrix` of every action."""
        out = np.stack([self.distance_matrix(a) for a in range(len(ACTIONS))])
        out.flags.writeable = False
        return out

    def transition_likelihood(self, action, eligible, accepted, d, d_next) -> np.ndarray:
        """P(the epoch's observable outcome | h, x, a) as a function of the epoch-start h,
        shape (..., 9): the human's answer to an eligible request (p_accept[em] or its
        complement; 1 for anything else) times the distance move P(d' | d, ea, a). Given
        those two the task step is deterministic (MODEL.md 3), so this is P(x' | x, h, a):
        the evidence about h that acting reveals besides O' (the exact posterior's factor,
        `BeliefFilter.update(..., evidence=)`). Broadcasts over its array arguments. `d` or
        `d_next` None (a window without a skeleton on the ROS graph): the move is unknown and
        left out, only the answer counts."""
        h = np.arange(N_HIDDEN)
        p = self.config.p_accept[h // 3]
        eligible = np.asarray(eligible, dtype=bool)[..., None]
        accepted = np.asarray(accepted, dtype=bool)[..., None]
        answer = np.where(eligible, np.where(accepted, p, 1.0 - p), 1.0)
        if d is None or d_next is None:
            return answer * np.ones(np.shape(action) + (N_HIDDEN,))
        move = self.distance_matrices[np.asarray(action)[..., None], h % 3,
                                      np.asarray(d)[..., None], np.asarray(d_next)[..., None]]
        return answer * move

    # -- actions -------------------------------------------------------------------------
    @cached_property
    def availability(self) -> np.ndarray:
        """(8, 4) bool: whether action a may be planned at distance level d. Every action
        everywhere, except that with `solver.fail_safe_aware` (the default) only dn is
        available at d = 0, the action the decision node's fail-safe enforces (MODEL.md 5)."""
        out = np.ones((len(ACTIONS), N_DISTANCE), dtype=bool)
        if self.config.fail_safe_aware:
            out[np.arange(len(ACTIONS)) != DN, 0] = False
        out.flags.writeable = False
        return out

    # -- cost ----------------------------------------------------------------------------
    @cached_property
    def action_cost(self) -> np.ndarray:
        """g(a) for the 8 actions (MODEL.md 4)."""
        c = self.config.cost
        g = np.zeros(len(ACTIONS))
        g[MH] = c['alpha11']
        g[[RH1, RH2]] = c['alpha12']
        g[[DP, DM]] = c['alpha13']
        return g

    def state_cost(self, states: np.ndarray) -> np.ndarray:
        """k1*f1 + k2*f2 of an (n, 11) array of states (the action-free part of J)."""
        s = np.asarray(states, dtype=float)
        return self._state_cost_terms(*(s[..., k] for k in range(11)))

    def _state_cost_terms(self, em, ea, tp, tc, tx, ty, hp, hc, bp, bc, d):
        """MODEL.md 4's f1 and f2 on (broadcastable) arrays of the 11 variables."""
        c = self.config.cost
        f1 = (c['alpha1'] * (ty == 3) * d * hc * bc
              + (c['alpha2'] + c['alpha3'] * (bp == 0) + c['alpha4'] * (hp == 0))
              * (ty == 0) * (tp != 0)
              + c['alpha5'] * (2 - em) * (tx == 2) * (ty == 0)
              + c['alpha6'] * (tx == 3) * (ty != 3)
              + c['alpha7'] * (tp > bp) * (ty == 0)
              + c['alpha8'] * bc + c['alpha9'] * hc
              + c['alpha10'] * (d == 0))
        f2 = (c['beta1'] * (3 - d)
              + (ty != 3) * (c['beta2'] * np.exp(c['beta3'] * (ea - 3) * d)
                             + c['beta4'] * np.exp(-c['beta5'] * (em + 1) * d)
                             + ea * c['beta6'] * np.exp(-d)))
        return c['k1'] * f1 + c['k2'] * f2

    @cached_property
    def state_cost_vector(self) -> np.ndarray:
        """k1*f1 + k2*f2 for every flat state, shape (N,), from broadcast parts (no (N, 11))."""
        grid = self.task_grid
        h = np.arange(N_HIDDEN)
        em = (h // 3)[:, None, None].astype(float)
        ea = (h % 3)[:, None, None].astype(float)
        task = (grid[n][None, :, None].astype(float) for n in TASK_VARIABLES)
        d = np.arange(N_DISTANCE, dtype=float)[None, None, :]
        cost = self._state_cost_terms(em, ea, *task, d)
        return np.broadcast_to(cost, (N_HIDDEN, self.n_task, N_DISTANCE)).reshape(-1)

    def cost(self, states: np.ndarray, action: int) -> np.ndarray:
        """J(s, a) for an (n, 11) array of states."""
        return self.state_cost(states) + self.action_cost[action]

    # -- explicit transition rows --------------------------------------------------------
    def transition(self, sources: np.ndarray, action: int) -> Transition:
        """P(. | s, a) for the flat states `sources`, enumerated explicitly.

        Every combination of acceptance, Delta and (em', ea') is one entry (duplicates of a
        target are kept; sum them, as scipy.sparse does). This is the rule-by-rule form of
        the model: the independent formulation that the tests and the benchmark hold the
        factored solver against, and the rows of a fixed policy's matrix (policy iteration).
        """
        action = action_index(action)
        sources = np.atleast_1d(np.asarray(sources, dtype=np.int64))
        if self.queue is not None:
            return self._queue_transition(sources, action)
        s = self.state(sources)
        em = s[:, 0]
        task = {name: s[:, 2 + k] for k, name in enumerate(TASK_VARIABLES)}
        p_acc = self.acceptance_probability(action, em, task['tp'], task['tx'], task['ty'])
        out = []
        arrivals = self.arrivals
        steps = [(nxt, p_a * p_run) for accepted, p_a in ((True, p_acc), (False, 1.0 - p_acc))
                 for nxt, p_run in self.task_steps(task, action, accepted, s[:, 10])]
        for nxt, p_a in steps:
            y_step = self.task_index(nxt)
            branches = [(y_step, p_a)]
            if arrivals is not None:    # MODEL.md 8: a task may enter the cell left idle
                p_arrive = np.where(nxt['tp'] == 0,
                                    arrivals.probability(self.task_index(task)), 0.0)
                branches = [(y_step, p_a * (1.0 - p_arrive))]
                for j, q_j in enumerate(arrivals.q):
                    entered = np.where(nxt['tp'] == 0, arrivals.enter[y_step, j], y_step)
                    branches.append((entered, p_a * p_arrive * q_j))
            out += [(0, y_next, p_y) for y_next, p_y in branches]
        return self._spread(out, s, action)

    def _spread(self, branches, s: np.ndarray, action: int) -> Transition:
        """The task branches [(l', y', P)] of sources with states `s` (l' 0 without a queue)
        through the distance and emotion steps, as sparse rows."""
        em, ea, d = s[:, 0], s[:, 1], s[:, 10]
        emotion = self.action_emotion_matrix(action)
        p_delta = self.config.p_delta
        batch = np.arange(len(s))
        src, tgt, prob = [], [], []
        for l_next, y_next, p_y in branches:
            for k, delta in enumerate(DELTAS):
                d_next = self.next_distance(d, action, delta)
                p_ad = p_y * p_delta[ea, k]
                for h_next in range(N_HIDDEN):
                    p = p_ad * emotion[3 * em + ea, h_next]
                    keep = p > 0
                    flat = (np.asarray(l_next)[keep] * self.n_base if np.ndim(l_next) else 0) \
                        + (h_next * self.n_task + y_next[keep]) * N_DISTANCE + d_next[keep]
                    src.append(batch[keep])
                    tgt.append(flat)
                    prob.append(p[keep])
        return Transition(np.concatenate(src), np.concatenate(tgt), np.concatenate(prob))

    def _queue_steps(self, sources: np.ndarray, action: int):
        """The queue's epoch (MODEL.md 8.1) rule by rule: per source (flat indices) the
        branches [(l', y', P(l', y' | s, a) without the emotion and distance steps)], and the
        probability that a task is dropped; plus the source states."""
        queue = self.queue
        arr, top = queue.arrivals, queue.levels
        level, base = self.split(sources)
        s = self.state(base)
        em = s[:, 0]
        task = {name: s[:, 2 + k] for k, name in enumerate(TASK_VARIABLES)}
        p_acc = self.acceptance_probability(action, em, task['tp'], task['tx'], task['ty'])
        p_release = np.where(task['tp'] > 0, arr.p_complete, arr.p_idle)
        branches, dropped = [], np.zeros(len(sources))
        steps = [(nxt, p_a * p_run) for accepted, p_a in ((True, p_acc), (False, 1.0 - p_acc))
                 for nxt, p_run in self.task_steps(task, action, accepted, s[:, 10])]
        for nxt, p_a in steps:
            y_step = np.asarray(self.task_index(nxt), dtype=np.intp)
            idle = nxt['tp'] == 0
            for released, p_r in ((1, p_release), (0, 1.0 - p_release)):
                waiting = level + released
                enters = idle & (waiting > 0)
                stays = p_a * p_r * ~enters
                branches.append((np.minimum(waiting, top), y_step, stays))
                dropped += stays * (waiting > top)
                for j, q_j in enumerate(arr.q):
                    entered = np.where(enters, arr.enter[y_step, j], y_step)
                    branches.append((np.minimum(waiting - 1, top), entered,
                                     p_a * p_r * enters * q_j))
        return branches, dropped, s

    def _queue_transition(self, sources: np.ndarray, action: int) -> Transition:
        branches, _, s = self._queue_steps(sources, action)
        return self._spread(branches, s, action)

    def flat_cost(self, sources, action: int) -> np.ndarray:
        """The expected cost of action `action` at the flat states `sources`: J(s, a), and with
        a queue (MODEL.md 8.1) w * l plus drop_cost * P(a task is dropped | s, a)."""
        action = action_index(action)
        sources = np.atleast_1d(np.asarray(sources, dtype=np.int64))
        if self.queue is None:
            return self.cost(self.state(sources), action)
        level, base = self.split(sources)
        _, dropped, s = self._queue_steps(sources, action)
        return (self.cost(s, action) + self.queue.waiting_cost * level
                + self.queue.drop_cost * dropped)

    def sparse_matrices(self, chunk: int = 1 << 16):
        """The 8 explicit N x N transition matrices (scipy.sparse CSR), rows = s."""
        from scipy import sparse

        matrices = []
        for a in range(len(ACTIONS)):
            rows, cols, vals = [], [], []
            for start in range(0, self.n_states, chunk):
                sources = np.arange(start, min(start + chunk, self.n_states))
                t = self.transition(sources, a)
                rows.append(sources[t.source].astype(np.int32))
                cols.append(t.target.astype(np.int32))
                vals.append(t.probability)
            m = sparse.csr_matrix(
                (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                shape=(self.n_states, self.n_states))
            m.sum_duplicates()
            matrices.append(m)
        return matrices
