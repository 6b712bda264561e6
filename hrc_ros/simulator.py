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

Selectors: ``paper`` (the paper's weighted vote), ``qmdp``, ``mls`` (MODEL.md 6), and ``mdp``:
the policy action of the *true* state, a full-information upper bound on what any belief-based
selector can achieve (the fail-safe applies to it too).

A row of the trajectory holds epoch k, the true state s_k (11 variables, the paper's Table 6
order), O_k, b_k (9 values over h = 3*em + ea), a_k, the human's answer, whether the fail-safe
fired, the selector's scores (8) and the cost J(s_k, a_k). `hrc-simulate` prints the rows as
the paper's Table 6, writes them as CSV and plots them in the spirit of the paper's Figs 9-12
(task status, human and robot activity, distance, action sequence) plus the belief over time.
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .belief import BeliefFilter
from .cell import SimulatedHuman
from .config import ConfigError, load_config
from .model import ACTIONS, DN, STATE_VARIABLES, TASK_VARIABLES, HRCModel
from .policy import PolicyError, default_config_path, default_policy_path, load_policy
from .selection import SELECTORS, ActionSelector
from .tasks import TaskBook, TaskRecord

SIMULATION_SELECTORS = SELECTORS + ('mdp',)
BELIEF_COLUMNS = tuple(f'b{h}' for h in range(9))
SCORE_COLUMNS = tuple(f'score_{a}' for a in ACTIONS)
COLUMNS = (('epoch',) + STATE_VARIABLES + ('O',) + BELIEF_COLUMNS
           + ('action', 'accepted', 'fail_safe') + SCORE_COLUMNS + ('cost',))


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
        if name not in COLUMNS:
            raise KeyError(f'no column {name!r}; columns: {", ".join(COLUMNS)}')
        return np.array([row[name] for row in self.rows])

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
        with path.open('w', newline='') as f:
            writer = csv.DictWriter(f, fieldnames=COLUMNS)
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
        head = (f'{"epoch":>5}  {"state [em,ea,tp,tc,tx,ty,hp,hc,bp,bc,d]":<40} {"O":>1}  '
                f'{"belief, top (em,ea):p":<30} action')
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
            lines.append(f'{row["epoch"]:>5}  {state:<40} {row["O"]:>1}  {belief:<30} {action}')
        lines.append(f'discounted cost {self.discounted_cost:.3f} (gamma {self.gamma}); tasks '
                     f'completed {sum(r.complete_epoch is not None for r in self.tasks)}'
                     f'/{len(self.tasks)}')
        return '\n'.join(lines)


def _policy_arrays(policy, value):
    """(policy array, value or None) from a Policy, a SolveResult or plain arrays."""
    if hasattr(policy, 'policy'):
        if value is None:
            value = getattr(policy, 'value', None)
        policy = policy.policy
    return np.asarray(policy), value


def simulate(model: HRCModel, policy, scenario: Scenario, selector: str = 'paper',
             mode: str | None = None, seed=0, value=None, fail_safe: bool = True
             ) -> Trajectory:
    """Run `scenario` in closed loop; `seed` seeds the simulated human (cell.SimulatedHuman).

    `policy`: a loaded `Policy`, a `SolveResult` or the (N,) action array; `value` (for qmdp)
    defaults to its `.value`. `mode`: belief mode `bayes` or `table` (None: the config's).
    `fail_safe=False` lets the selector act at d = 0 too (for studying the fail-safe only).
    """
    if selector not in SIMULATION_SELECTORS:
        raise ValueError(f'unknown selector {selector!r}; expected one of '
                         f'{", ".join(SIMULATION_SELECTORS)}')
    pi, value = _policy_arrays(policy, value)
    if pi.shape != (model.n_states,):
        raise ValueError(f'the policy has {pi.size} states, the model {model.n_states}')
    model.index(scenario.initial_state)            # range check, names the variable
    em, ea, *task_values, d = (int(v) for v in scenario.initial_state)
    book = TaskBook(model, initial_task=dict(zip(TASK_VARIABLES, task_values)),
                    schedule=scenario.schedule)
    human = SimulatedHuman(model, seed=seed, em=em, ea=ea, d=d)
    belief_filter = BeliefFilter(model, mode=mode)
    chooser = None if selector == 'mdp' else ActionSelector(model, pi, value, method=selector)
    belief = belief_filter.initial(human.observation)
    observation = human.observation
    rows = []
    for k in range(1, scenario.epochs + 1):
        book.begin_epoch(k)
        x = book.observable(human.d)
        state = (human.em, human.ea) + x
        if chooser is None:
            action = int(pi[model.index(state)])
            scores = np.zeros(len(ACTIONS))
            scores[action] = 1.0
        else:
            selection = chooser.select(belief, x)
            action, scores = selection.action, selection.scores
        stopped = fail_safe and human.d == 0
        if stopped:
            action = DN
        cost = float(model.state_cost_vector[model.index(state)] + model.action_cost[action])
        reaction = human.react(action, book.state)
        row = {'epoch': k, **dict(zip(STATE_VARIABLES, state)), 'O': observation}
        row.update(zip(BELIEF_COLUMNS, (float(p) for p in belief)))
        row.update(action=ACTIONS[action], accepted=reaction.accepted, fail_safe=stopped)
        row.update(zip(SCORE_COLUMNS, (float(s) for s in scores)))
        row['cost'] = cost
        rows.append(row)
        book.apply(action, reaction.accepted)
        belief = belief_filter.update(belief, action, reaction.observation)
        observation = reaction.observation
    return Trajectory(rows, scenario, selector, belief_filter.mode, seed, model.gamma,
                      tasks=list(book.records))


# -- plots -----------------------------------------------------------------------------------
def _save_figure(plt, fig, path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _step_panels(plt, trajectory, names, labels, title, path):
    epochs = trajectory.column('epoch')
    fig, axes = plt.subplots(len(names), 1, sharex=True, figsize=(9, 1.7 * len(names) + 0.8))
    for ax, name in zip(axes, names):
        values = trajectory.column(name)
        ax.step(epochs, values, where='post', color='tab:blue', lw=2)
        ax.plot(epochs, values, 'o', color='tab:blue', ms=3)
        top = max(3, int(values.max()))
        ax.set_ylim(-0.3, top + 0.3)
        ax.set_yticks(range(top + 1))
        ax.set_ylabel(labels.get(name, name), rotation=0, ha='right', va='center')
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel('epoch')
    axes[-1].set_xticks(epochs)
    fig.suptitle(title)
    return _save_figure(plt, fig, path)


def plot_trajectory(trajectory: Trajectory, out_dir) -> list:
    """PNG plots of a trajectory (paper Figs 9-12 and the belief); returns the paths."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    subtitle = f'({trajectory.scenario.name}, selector {trajectory.selector})'
    labels = {'tp': 'tp\npriority', 'tc': 'tc\nremaining', 'tx': 'tx\nnature',
              'ty': 'ty\ncommitment', 'hp': 'hp\nhuman prio.', 'hc': 'hc\nhuman rem.',
              'bp': 'bp\nrobot prio.', 'bc': 'bc\nrobot rem.'}
    paths = [
        _step_panels(plt, trajectory, ('tp', 'tc', 'tx', 'ty'), labels,
                     f'Status of the active task {subtitle}', out / 'task_status.png'),
        _step_panels(plt, trajectory, ('hp', 'hc', 'bp', 'bc'), labels,
                     f'Human and robot activity {subtitle}', out / 'activity.png'),
    ]
    epochs = trajectory.column('epoch')

    fig, ax = plt.subplots(figsize=(9, 3.2))
    ax.step(epochs, trajectory.column('d'), where='post', lw=2, color='tab:red')
    ax.plot(epochs, trajectory.column('d'), 'o', color='tab:red', ms=4)
    ax.set_yticks(range(4), ['0 collision', '1 inner', '2 middle', '3 outer'])
    ax.set_ylim(-0.3, 3.3)
    ax.set_xticks(epochs)
    ax.set_xlabel('epoch')
    ax.grid(alpha=0.3)
    ax.set_title(f'Distance level d {subtitle}')
    paths.append(_save_figure(plt, fig, out / 'distance.png'))

    fig, ax = plt.subplots(figsize=(9, 3.8))
    index = np.array([ACTIONS.index(a) for a in trajectory.actions])
    ax.step(epochs, index, where='mid', color='0.7', lw=1)
    accepted = np.array([row['accepted'] for row in trajectory.rows], dtype=object)
    fail = trajectory.column('fail_safe').astype(bool)
    plain = np.array([a is None for a in accepted]) & ~fail
    ax.plot(epochs[plain], index[plain], 'o', color='tab:blue', ms=7, label='action')
    yes = np.array([a is True for a in accepted])
    no = np.array([a is False for a in accepted])
    ax.plot(epochs[yes], index[yes], 's', color='tab:green', ms=8, label='request accepted')
    ax.plot(epochs[no], index[no], 's', mfc='none', color='tab:orange', ms=8,
            label='request refused')
    ax.plot(epochs[fail], index[fail], 'X', color='tab:red', ms=9, label='fail-safe dn')
    ax.set_yticks(range(len(ACTIONS)), ACTIONS)
    ax.set_ylim(-0.5, len(ACTIONS) - 0.5)
    ax.set_xticks(epochs)
    ax.set_xlabel('epoch')
    ax.grid(alpha=0.3)
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.set_title(f'Sequence of the actions {subtitle}')
    paths.append(_save_figure(plt, fig, out / 'actions.png'))

    fig, ax = plt.subplots(figsize=(10, 4.5))
    image = ax.imshow(trajectory.beliefs.T, aspect='auto', origin='lower', cmap='viridis',
                      vmin=0.0, vmax=1.0, extent=(epochs[0] - 0.5, epochs[-1] + 0.5, -0.5, 8.5))
    true_h = 3 * trajectory.column('em') + trajectory.column('ea')
    ax.plot(epochs, true_h, 'o', mfc='none', mec='red', ms=9, mew=1.5, label='true (em, ea)')
    ax.set_yticks(range(9), [f'h={h} ({h // 3},{h % 3})' for h in range(9)])
    ax.set_xticks(epochs)
    ax.set_xlabel('epoch')
    ax.set_ylabel('hidden state (em, ea)')
    ax.legend(loc='upper left', bbox_to_anchor=(1.15, 1.0), fontsize=8)
    fig.colorbar(image, ax=ax, label='belief b(h)')
    ax.set_title(f'Belief over the hidden emotions ({trajectory.mode} filter)\n{subtitle}',
                 fontsize=11)
    paths.append(_save_figure(plt, fig, out / 'belief.png'))
    return paths


# -- command line ----------------------------------------------------------------------------
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='hrc-simulate',
        description='Run the case study (MODEL.md 7) in closed loop; print it as the paper\'s '
                    'Table 6, write a CSV and PNG plots.')
    parser.add_argument('--config', default=None,
                        help='configuration YAML (default: the shipped default.yaml)')
    parser.add_argument('--policy', default=None,
                        help='policy file solved for that configuration (default: the shipped '
                             'policy solved for it, e.g. paper.npz for paper.yaml)')
    parser.add_argument('--selector', default='paper', choices=SIMULATION_SELECTORS,
                        help='action selection (mdp = the true state, an upper bound)')
    parser.add_argument('--mode', default=None, choices=('bayes', 'table'),
                        help='belief mode (default: the configuration\'s)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the simulated human')
    parser.add_argument('--epochs', type=int, default=None,
                        help='number of epochs (default: the case study\'s 20)')
    parser.add_argument('--out', default='out/simulate', help='output folder')
    args = parser.parse_args(argv)
    if args.epochs is not None and args.epochs < 1:
        parser.error(f'--epochs must be >= 1, got {args.epochs}')
    try:
        config = load_config(args.config or default_config_path())
        policy = load_policy(args.policy or default_policy_path(config), config)
    except (ConfigError, PolicyError) as exc:
        print(f'hrc-simulate: error: {exc}', file=sys.stderr)
        return 2
    model = HRCModel(config)
    scenario = case_study()
    if args.epochs is not None:
        scenario = Scenario(scenario.initial_state, scenario.schedule, args.epochs,
                            scenario.name)
    trajectory = simulate(model, policy, scenario, selector=args.selector, mode=args.mode,
                          seed=args.seed)
    print(trajectory.table())
    out = Path(args.out)
    written = [trajectory.to_csv(out / 'trajectory.csv')] + plot_trajectory(trajectory, out)
    for path in written:
        print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
