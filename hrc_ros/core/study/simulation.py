"""The closed loop without ROS: task book, simulated human, belief filter and action selector.

This is the paper's "online trajectory" (its Fig. 8 and Section 6) run with the exact model of
MODEL.md, so the behaviour of a solved policy can be checked and plotted before any node runs.
One decision epoch k = 1, 2, ... follows docs/DESIGN.md, the same protocol as the ROS graph:

1. ``book.begin_epoch(k)``: scheduled tasks due at k join the queue; an idle cell takes the
   head uncommitted;
2. the observable state x_k = (tp, tc, tx, ty, hp, hc, bp, bc, d_k) and the belief b_k, where
   b_1 = ``BeliefFilter.initial(O_1)`` and O_1 is drawn from the initial hidden state;
3. a_k from (b_k, x_k) by the selector; **fail-safe**: d_k = 0 (collision) -> dn;
4. the human reacts to a_k (acceptance, Delta, em', ea', O_{k+1}; see `cell.py`);
5. ``book.apply(a_k, accepted)`` and b_{k+1} = ``update(b_k, a_k, O_{k+1})``.

Selectors: ``paper`` (the paper's weighted vote), ``qmdp``, ``mls`` (MODEL.md 6), ``pomdp``
and ``fib`` (the solved POMDP's alpha vectors and its fast informed bound, `pomdp`), and ``mdp``:
the policy action of the *true* state, a full-information upper bound on what any belief-based
selector can achieve (the fail-safe applies to it too).

A row of the trajectory holds epoch k, the true state s_k (11 variables, the paper's Table 6
order), O_k, b_k (9 values over h = 3*em + ea), a_k, the human's answer, whether the fail-safe
fired, the selector's scores (8) and the cost J(s_k, a_k). `hrc-simulate` prints the rows as
the paper's Table 6 (`Trajectory.table`), writes them as CSV and plots them in the spirit of the
paper's Figs 9-12 (`plots.plot_trajectory`).

The queue (MODEL.md 8.1): with a configuration whose stream has a queue, the robot observes
l = min(tasks waiting in the task book, L) (released, not yet in the cell, after step 1), every
selector reads the policy / Q at that l, the epoch's cost adds w * (every waiting task, not
capped at L), and the rows gain the column `queued` (the tasks waiting): the rule of
`evaluation.BatchSimulator`, which the tests hold equal episode by episode. Without a queue
the rows, the CSV and the table are as they always were.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..pomdp.belief import BeliefFilter
from ..cell.human import SimulatedHuman
from ..model import ACTIONS, DN, N_HIDDEN, STATE_VARIABLES, TASK_VARIABLES, HRCModel
from ..mdp.policy import policy_arrays
from ..paths import written
from ..decision.selection import SELECTORS, ActionSelector
from ..tasks import TaskBook, TaskRecord

SIMULATION_SELECTORS = SELECTORS + ('mdp',)
BELIEF_COLUMNS = tuple(f'b{h}' for h in range(N_HIDDEN))
SCORE_COLUMNS = tuple(f'score_{a}' for a in ACTIONS)
COLUMNS = (('epoch',) + STATE_VARIABLES + ('O',) + BELIEF_COLUMNS
           + ('action', 'accepted', 'fail_safe') + SCORE_COLUMNS + ('cost',))
QUEUED = 'queued'    # the tasks waiting, a column only with a queue (MODEL.md 8.1)


@dataclass(frozen=True)
class Scenario:
    """Initial state s_1 (11 variables), task releases ``(epoch, (tp, tc, tx))``, horizon."""

    initial_state: tuple
    schedule: tuple = ()
    epochs: int = 20
    name: str = 'scenario'

    def __post_init__(self):
        if len(tuple(self.initial_state)) != len(STATE_VARIABLES):
            raise ValueError(f'initial_state has the 11 variables {STATE_VARIABLES}, got '
                             f'{self.initial_state!r}')
        if isinstance(self.epochs, bool) or not isinstance(self.epochs, (int, np.integer)) \
                or self.epochs < 1:
            raise ValueError(f'epochs must be an integer >= 1, got {self.epochs!r}')


def case_study() -> Scenario:
    """MODEL.md 7: task 1 (1, 1, 3) at the start, task 2 (2, 2, 1) at 9, task 3 (2, 2, 2) at 16."""
    return Scenario(initial_state=(0, 0, 1, 1, 3, 0, 0, 0, 0, 0, 1),
                    schedule=((9, (2, 2, 1)), (16, (2, 2, 2))), epochs=20, name='case study')


@dataclass
class Trajectory:
    """The rows of one closed-loop run (see the module docstring) and its task records."""

    rows: list
    scenario: Scenario
    selector: str
    mode: str
    seed: object
    gamma: float
    tasks: list[TaskRecord] = field(default_factory=list)

    def column(self, name: str) -> np.ndarray:
        if name not in self.columns:
            raise KeyError(f'no column {name!r}; columns: {", ".join(self.columns)}')
        return np.array([row[name] for row in self.rows])

    @property
    def columns(self) -> tuple:
        """The columns of the rows: `COLUMNS`, and with a queue (MODEL.md 8.1) `queued` (the
        tasks waiting) last."""
        if self.rows and QUEUED in self.rows[0]:
            return COLUMNS + (QUEUED,)
        return COLUMNS

    @property
    def actions(self) -> list:
        return [row['action'] for row in self.rows]

    @property
    def states(self) -> np.ndarray:
        return np.array([[row[n] for n in STATE_VARIABLES] for row in self.rows])

    @property
    def beliefs(self) -> np.ndarray:
        return np.array([[row[c] for c in BELIEF_COLUMNS] for row in self.rows])

    @property
    def discounted_cost(self) -> float:
        cost = self.column('cost')
        return float(np.sum(cost * self.gamma ** np.arange(len(cost))))

    def to_csv(self, path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with written(path) as f:
            writer = csv.DictWriter(f, fieldnames=self.columns)
            writer.writeheader()
            for row in self.rows:
                out = dict(row)
                out['accepted'] = '' if row['accepted'] is None else int(row['accepted'])
                out['fail_safe'] = int(row['fail_safe'])
                for c in BELIEF_COLUMNS + SCORE_COLUMNS + ('cost',):
                    out[c] = f'{row[c]:.6g}'
                writer.writerow(out)
        return path

    def table(self) -> str:
        """The paper's Table 6: epoch, state vector, O, belief (top hidden states), action."""
        queued = QUEUED in self.columns
        head = (f'{"epoch":>5}  {"state [em,ea,tp,tc,tx,ty,hp,hc,bp,bc,d]":<40} {"O":>1}  '
                + (f'{"queued":>6}  ' if queued else '')
                + f'{"belief, top (em,ea):p":<30} action')
        lines = [f'{self.scenario.name}: selector {self.selector}, belief {self.mode}, '
                 f'seed {self.seed}', head, '-' * len(head)]
        for row in self.rows:
            state = '[' + ','.join(str(row[n]) for n in STATE_VARIABLES) + ']'
            b = np.array([row[c] for c in BELIEF_COLUMNS])
            top = [h for h in np.argsort(-b, kind='stable')[:3] if b[h] >= 0.005]
            belief = ' '.join(f'({h // 3},{h % 3}):{b[h]:.2f}' for h in top)
            action = row['action']
            if row['fail_safe']:
                action += ' (fail-safe)'
            elif row['accepted'] is not None:
                action += ' (accepted)' if row['accepted'] else ' (refused)'
            waiting = f'{row[QUEUED]:>6}  ' if queued else ''
            lines.append(f'{row["epoch"]:>5}  {state:<40} {row["O"]:>1}  {waiting}'
                         f'{belief:<30} {action}')
        lines.append(f'discounted cost {self.discounted_cost:.3f} (gamma {self.gamma}); tasks '
                     f'completed {sum(r.complete_epoch is not None for r in self.tasks)}'
                     f'/{len(self.tasks)}')
        return '\n'.join(lines)


def check_model_cell(world: HRCModel) -> None:
    """ValueError for a world the model's cell cannot run: `model.robot_rate` is the cell with
    the arm's physics (its program's cycles under SSM, MODEL.md 3.2), which the model's cell,
    without an arm, does not simulate (its robot's counter is the paper's)."""
    if world.robot_rate is not None:
        raise ValueError(f'{world.config.source} has model.robot_rate, the arm\'s progress under '
                         'SSM, which the model\'s cell does not simulate: run it in the cell with '
                         'the arm (hrc-evaluate --cell arm, hrc-case-study --robot sim)')


def simulate(model: HRCModel, policy, scenario: Scenario, selector: str = 'paper',
             mode: str | None = None, seed=0, value=None, fail_safe: bool = True,
             pomdp=None) -> Trajectory:
    """Run `scenario` in closed loop; `seed` seeds the simulated human (cell.SimulatedHuman).

    `policy`: a loaded `Policy`, a `SolveResult` or the (N,) action array; `value` (for qmdp)
    defaults to its `.value`. `mode`: belief mode `bayes` or `table` (None: the config's).
    `fail_safe=False` lets the selector act at d = 0 too (for studying the fail-safe only).
    `pomdp`: the POMDP policy for the pomdp and fib selectors (default: the shipped one).
    The belief update is given the epoch's observable transition (the human's answer and the
    distance move) as evidence; only the ``posterior`` mode uses it (`belief`). With a queue
    (MODEL.md 8.1) the selector reads l = min(tasks waiting, L) and the cost charges every
    waiting task (module docstring).
    """
    from .evaluation import charged_waiting_cost      # evaluation imports this module
    if selector not in SIMULATION_SELECTORS:
        raise ValueError(f'unknown selector {selector!r}; expected one of '
                         f'{", ".join(SIMULATION_SELECTORS)}')
    check_model_cell(model)
    pi, value = policy_arrays(policy, value)
    waiting_cost = charged_waiting_cost(model)
    top = model.queue_length
    if pi.shape != (model.n_states,):
        raise ValueError(f'the policy has {pi.size} states, the model {model.n_states}')
    model.index(scenario.initial_state)            # range check, names the variable
    em, ea, *task_values, d = (int(v) for v in scenario.initial_state)
    book = TaskBook(model, initial_task=dict(zip(TASK_VARIABLES, task_values)),
                    schedule=scenario.schedule)
    human = SimulatedHuman(model, seed=seed, em=em, ea=ea, d=d)
    belief_filter = BeliefFilter(model, mode=mode)
    chooser = (None if selector == 'mdp'
               else ActionSelector(model, pi, value, method=selector, pomdp=pomdp))
    belief = belief_filter.initial(human.observation)
    observation = human.observation
    rows = []
    for k in range(1, scenario.epochs + 1):
        book.begin_epoch(k)
        x = book.observable(human.d)
        state = (human.em, human.ea) + x
        waiting = len(book.queue)      # released, not yet in the cell
        level = 0 if top is None else min(waiting, top)
        if chooser is None:
            action = int(pi[level * model.n_base + model.index(state)])
            scores = np.zeros(len(ACTIONS))
            scores[action] = 1.0
        else:
            selection = chooser.select(belief, x if top is None else x + (level,))
            action, scores = selection.action, selection.scores
        stopped = fail_safe and human.d == 0
        if stopped:
            action = DN
        cost = float(model.state_cost_vector[model.index(state)] + model.action_cost[action])
        if waiting_cost is not None:
            cost += waiting_cost * waiting
        reaction = human.react(action, book.state)
        row = {'epoch': k, **dict(zip(STATE_VARIABLES, state)), 'O': observation}
        if top is not None:
            row[QUEUED] = waiting
        row.update(zip(BELIEF_COLUMNS, (float(p) for p in belief)))
        row.update(action=ACTIONS[action], accepted=reaction.accepted, fail_safe=stopped)
        row.update(zip(SCORE_COLUMNS, (float(s) for s in scores)))
        row['cost'] = cost
        rows.append(row)
        book.apply(action, reaction.accepted)
        evidence = model.transition_likelihood(action, reaction.accepted is not None,
                                               bool(reaction.accepted), x[-1], reaction.d)
        belief = belief_filter.update(belief, action, reaction.observation, evidence)
        observation = reaction.observation
    return Trajectory(rows, scenario, selector, belief_filter.mode, seed, model.gamma,
                      tasks=list(book.records))
