"""The closed-loop simulator: the epoch protocol, outputs, and MODEL.md 7's case study.

The case-study checks run the default configuration with the shipped policy (or a freshly
solved one when no matching file is shipped). The behaviours MODEL.md 7 demands are checked
three ways: as facts of the solved policy (no simulation), literally on reference seeds, and
as rates over 50 seeds, where the belief (an ambiguous velocity observation) and the fail-safe
(d = 0 -> dn) legitimately cause some runs to deviate.
"""

import csv

import numpy as np
import pytest

from hrc_ros.core.pomdp.belief import BeliefFilter
from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTIONS, DN, HRCModel, request_eligible
from hrc_ros.core.study.plots import plot_trajectory
from hrc_ros.core.paths import shipped_config_path
from hrc_ros.core.mdp.policy import default_policy_path, load_policy
from hrc_ros.core.study.simulation import COLUMNS, STATE_VARIABLES, Scenario, case_study, simulate
from hrc_ros.tools.simulate import main


def pi(model, policy, state):
    return ACTIONS[policy.policy[model.index(state)]]


# -- the solved policy (no simulation) ---------------------------------------------------------
def test_policy_facts_behind_the_case_study(model, policy):
    task1 = (1, 1, 3, 0, 0, 0, 0, 0)     # joint task, uncommitted
    task2 = (2, 2, 1, 0, 0, 0, 0, 0)     # human only
    task3 = (2, 2, 2, 0, 0, 0, 0, 0)     # either
    idle = (0,) * 8
    for d in (2, 3):                      # 1. motivate a low-motivation human first ...
        for ea in (0, 1, 2):
            # (issue 14) planning with the fail-safe, the default first steps back from an
            # aggressive human at the middle circle: d = 0 would stop the robot for good
            expected = 'dp' if (ea, d) == (2, 2) else 'mh'
            assert pi(model, policy, (0, ea) + task1 + (d,)) == expected
    for em in (1, 2):                     # ... then ask for joint work, never in the inner
        for ea in (0, 1, 2):              # circle (issue 14: joint work at d = 1 risks d = 0,
            assert pi(model, policy, (em, ea) + task1 + (1,)) == 'dp'   # where dn stops it)
            for d in (2, 3):
                assert pi(model, policy, (em, ea) + task1 + (d,)) == 'rh2'
    for em in range(3):                   # 2. an idle robot moves away, then stops
        for ea in range(3):
            for d in (1, 2):
                assert pi(model, policy, (em, ea) + idle + (d,)) == 'dp'
            if (em, ea) != (0, 2):        # (0, 2): mh, see test below
                assert pi(model, policy, (em, ea) + idle + (3,)) == 'dn'
    for ea in (0, 1):                     # 3. human-only task: motivate, then request
        for d in (2, 3):
            assert pi(model, policy, (0, ea) + task2 + (d,)) == 'mh'
    for em in (1, 2):
        for ea in range(3):
            assert pi(model, policy, (em, ea) + task2 + (3,)) == 'rh1'
    for ea in range(3):                   # 4. task for either: the robot commits and works
        assert pi(model, policy, (1, ea) + task3 + (1,)) == 'dp'   # after stepping back
        for d in (2, 3):
            assert pi(model, policy, (1, ea) + task3 + (d,)) == 'ct'
        for bc in (2, 1):
            assert pi(model, policy, (1, ea, 2, bc, 2, 2, 0, 0, 2, bc, 3)) == 'nw'


def test_policy_motivates_a_calm_but_aggressive_idle_human(model, policy):
    """Recorded quirk: at (em, ea) = (0, 2) an idle robot at d = 3 motivates (not dn)."""
    assert pi(model, policy, (0, 2) + (0,) * 8 + (3,)) == 'mh'


# -- helpers for trajectories ----------------------------------------------------------------
def task_epochs(trajectory, task_id):
    """0-based row positions of the epochs a task spends in the cell (start..completion)."""
    record = trajectory.tasks[task_id]
    if record.start_epoch is None:
        return []
    end = record.complete_epoch or len(trajectory.rows)
    return list(range(record.start_epoch - 1, end))


def behaviours(trajectory):
    """MODEL.md 7's four behaviours, each True/False, for a case-study trajectory."""
    rows, actions = trajectory.rows, trajectory.actions
    out = {}
    tasks = trajectory.tasks
    e1 = task_epochs(trajectory, 0)
    a1 = [actions[i] for i in e1]
    out['1 task 1: mh before rh2, ty = 3, done'] = (
        'rh2' in a1 and 'mh' in a1[:a1.index('rh2')] and 'ct' not in a1
        and any(rows[i]['ty'] == 3 for i in e1) and tasks[0].complete_epoch is not None)
    idle = [i for i, row in enumerate(rows) if row['tp'] == 0]
    out['2 idle: dp while d < 3, dn at d = 3'] = bool(idle) and all(
        actions[i] == ('dp' if rows[i]['d'] < 3 else 'dn') for i in idle)
    e2 = task_epochs(trajectory, 1)
    open2 = [i for i in e2 if rows[i]['ty'] == 0]
    a2 = [actions[i] for i in open2]
    out['3 task 2: mh while em low, then rh1, no robot'] = (
        bool(e2) and tasks[1].complete_epoch is not None
        and all(rows[i]['ty'] in (0, 1) for i in e2) and 'ct' not in a2
        and set(a2) <= {'mh', 'rh1', 'dp'} and a2[-1] == 'rh1'
        and (rows[e2[0]]['em'] > 0 or a2[0] == 'mh'))
    e3 = task_epochs(trajectory, 2)
    a3 = [actions[i] for i in e3]
    out['4 task 3: ct, then works (nw/dp) until done'] = (
        bool(e3) and tasks[2].complete_epoch is not None and a3[0] == 'ct'
        and set(a3[1:]) <= {'nw', 'dp'})
    return out


# -- the case study ----------------------------------------------------------------------------
@pytest.mark.parametrize('mode, seed', [('bayes', 8), ('table', 24)])
def test_case_study_reference_seeds_show_the_papers_behaviour(model, policy, mode, seed):
    t = simulate(model, policy, case_study(), selector='paper', mode=mode, seed=seed)
    assert all(behaviours(t).values()), (behaviours(t), t.table())
    # The literal shape of the paper's Fig. 12 on these seeds: task 2 starts with an
    # unmotivated human and is motivated before the request; task 3 is ct, nw, nw.
    e2 = task_epochs(t, 1)
    assert t.rows[e2[0]]['em'] == 0 and t.actions[e2[0]] == 'mh'
    assert [t.actions[i] for i in task_epochs(t, 2)] == ['ct', 'nw', 'nw']
    assert [r.complete_epoch is not None for r in t.tasks] == [True, True, True]


def test_case_study_behaviour_rates_over_seeds(model, policy):
    """Rates over seeds 0..49 (paper selector, bayes belief); deviations have known causes:

    1: the first velocity level is ambiguous (O = 2 fits (0,1) and (1,0) alike), so a calm
       human is sometimes asked before being motivated; a collision under joint work freezes
       the robot (fail-safe dn pauses bc) past the horizon.
    3: the belief takes a calm human for a motivated one and asks at once.
    4: rarely, the task starts only near the horizon after delays.
    """
    counts = {}
    for seed in range(50):
        for name, ok in behaviours(simulate(model, policy, case_study(), seed=seed)).items():
            counts[name] = counts.get(name, 0) + int(ok)
    print(counts)
    assert counts['1 task 1: mh before rh2, ty = 3, done'] >= 40
    assert counts['2 idle: dp while d < 3, dn at d = 3'] >= 45
    assert counts['3 task 2: mh while em low, then rh1, no robot'] >= 40
    assert counts['4 task 3: ct, then works (nw/dp) until done'] >= 45


def test_task_two_is_never_taken_by_the_robot(model, policy):
    for seed in range(20):
        for selector in ('paper', 'qmdp', 'mls', 'mdp'):
            t = simulate(model, policy, case_study(), selector=selector, seed=seed)
            assert all(t.rows[i]['ty'] in (0, 1) for i in task_epochs(t, 1))


# -- the epoch protocol ------------------------------------------------------------------------
@pytest.mark.parametrize('selector', ['paper', 'qmdp', 'mls', 'mdp'])
@pytest.mark.parametrize('mode', ['bayes', 'table'])
def test_rows_follow_the_epoch_protocol(model, policy, selector, mode):
    scenario = Scenario((2, 2, 1, 1, 3, 0, 0, 0, 0, 0, 0), ((3, (2, 2, 2)), (4, (1, 1, 1))),
                        epochs=25, name='protocol')
    t = simulate(model, policy, scenario, selector=selector, mode=mode, seed=5)
    filt = BeliefFilter(model, mode=mode)
    rows = t.rows
    assert [r['epoch'] for r in rows] == list(range(1, 26))
    assert np.allclose(t.beliefs[0], filt.initial(rows[0]['O']))
    for k in range(len(rows) - 1):
        expected = filt.update(t.beliefs[k], rows[k]['action'], rows[k + 1]['O'])
        assert np.allclose(t.beliefs[k + 1], expected)
    for row, state in zip(rows, t.states):
        assert row['fail_safe'] == (row['d'] == 0)
        if row['d'] == 0:
            assert row['action'] == 'dn'
        elif selector == 'mdp':
            assert row['action'] == pi(model, policy, tuple(state))
        a = ACTIONS.index(row['action'])
        assert row['cost'] == pytest.approx(model.cost(state[None], a)[0])
        eligible = request_eligible(a, row['tp'], row['tx'], row['ty'])
        assert (row['accepted'] is None) == (not eligible)
    assert rows[0]['action'] == 'dn'      # starts in collision: fail-safe
    assert t.discounted_cost == pytest.approx(
        sum(r['cost'] * model.gamma ** k for k, r in enumerate(rows)))


def test_same_seed_same_trajectory(model, policy):
    a = simulate(model, policy, case_study(), seed=11)
    b = simulate(model, policy, case_study(), seed=11)
    c = simulate(model, policy, case_study(), seed=12)
    assert a.rows == b.rows
    assert a.rows != c.rows


def test_fail_safe_can_be_switched_off_for_study():
    # the policy planned through collision (the default plans dn there itself)
    config = load_config(shipped_config_path('fail_safe_unaware'))
    model, policy = HRCModel(config), load_policy(default_policy_path(config), config)
    scenario = Scenario((1, 1, 1, 1, 3, 0, 0, 0, 0, 0, 0), epochs=1)
    on = simulate(model, policy, scenario, selector='mdp')
    off = simulate(model, policy, scenario, selector='mdp', fail_safe=False)
    assert on.actions == ['dn'] and on.rows[0]['fail_safe']
    assert off.actions == [pi(model, policy, scenario.initial_state)] != ['dn']


# -- outputs -----------------------------------------------------------------------------------
def test_table_csv_and_plots(model, policy, tmp_path):
    t = simulate(model, policy, case_study(), seed=8)
    table = t.table()
    lines = table.splitlines()
    assert lines[3].split()[:2] == ['1', '[0,0,1,1,3,0,0,0,0,0,1]']
    assert len(lines) == 3 + 20 + 1
    path = t.to_csv(tmp_path / 'trajectory.csv')
    with path.open() as f:
        read = list(csv.DictReader(f))
    assert tuple(read[0]) == COLUMNS and len(read) == 20
    assert [int(r['d']) for r in read] == [row['d'] for row in t.rows]
    assert [r['action'] for r in read] == t.actions
    pngs = plot_trajectory(t, tmp_path / 'plots')
    assert [p.name for p in pngs] == ['task_status.png', 'activity.png', 'distance.png',
                                      'actions.png', 'belief.png']
    for p in pngs:
        assert p.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and p.stat().st_size > 10_000


def test_cli_writes_outputs_and_refuses_a_mismatched_policy(tmp_path, capsys):
    shipped = default_policy_path()       # tracked files: a missing one fails the test
    assert main(['--seed', '8', '--out', str(tmp_path), '--epochs', '12']) == 0
    out = capsys.readouterr().out
    assert 'case study: selector paper' in out and 'wrote' in out
    assert (tmp_path / 'trajectory.csv').is_file() and (tmp_path / 'belief.png').is_file()
    paper_policy = shipped.with_name('paper.npz')
    assert main(['--policy', str(paper_policy), '--out', str(tmp_path)]) == 2
    assert 'was solved for configuration' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(['--selector', 'best'])


# -- bad inputs --------------------------------------------------------------------------------
def test_bad_inputs_raise(model, policy):
    with pytest.raises(ValueError, match='unknown selector'):
        simulate(model, policy, case_study(), selector='greedy')
    with pytest.raises(ValueError, match='11 variables'):
        Scenario((0, 0, 1))
    with pytest.raises(ValueError, match='epochs must be an integer >= 1'):
        Scenario(case_study().initial_state, epochs=0)
    with pytest.raises(ValueError, match='state variable d must lie in 0..3'):
        simulate(model, policy, Scenario((0, 0, 1, 1, 3, 0, 0, 0, 0, 0, 5)))
    with pytest.raises(ValueError, match='policy has 3 states'):
        simulate(model, np.zeros(3, dtype=np.int8), case_study())
    with pytest.raises(ValueError, match='bad task'):
        simulate(model, policy, Scenario(case_study().initial_state, ((2, (9, 1, 1)),)))
    with pytest.raises(KeyError, match='no column'):
        simulate(model, policy, Scenario(case_study().initial_state, epochs=1)).column('x')
    assert STATE_VARIABLES[0] == 'em' and DN == ACTIONS.index('dn')


def test_the_models_cell_refuses_the_arms_progress_rate(model, policy):
    """model.robot_rate (MODEL.md 3.2) is the arm's physics, which the model's cell does not
    simulate: the simulator and the batch evaluator refuse it in one line instead of running
    the paper's counter under a plan that expects another."""
    from hrc_ros.core.study.evaluation import BatchSimulator
    rated = HRCModel(load_config(shipped_config_path('default'), overrides={
        'model': {'robot_rate': {0: [0.0, 0.1, 0.5, 0.9]}}}))
    with pytest.raises(ValueError, match=r'model\.robot_rate.*hrc-evaluate --cell arm'):
        simulate(rated, policy, case_study())
    with pytest.raises(ValueError, match=r'model\.robot_rate'):
        BatchSimulator(model, policy, world=rated)


def test_the_default_never_freezes_in_the_collision_circle(model, policy):
    """Issue 14: the shipped default plans with the fail-safe. Planned with every action at
    d = 0, the case study with seed 4 asked for joint work at d = 1, the human stepped into the
    collision circle, and the forced dn held it there for the remaining 14 epochs (0 of 3
    tasks); 4 of seeds 0-99 spent more than 3 epochs in a row at d = 0 and 7 missed a task."""
    from hrc_ros.core.study.evaluation import STUCK_EPOCHS, BatchSimulator, episodes_of
    assert model.config.fail_safe_aware
    trajectory = simulate(model, policy, case_study(), seed=4)
    assert sum(r.complete_epoch is not None for r in trajectory.tasks) == 3
    scenarios, seeds = episodes_of(model, 'case-study', 100, 20, seed=0)
    result = BatchSimulator(model, policy).run(scenarios, seeds, 'paper')
    assert result.longest_collision_run.max() <= STUCK_EPOCHS
    assert np.count_nonzero(result.tasks_completed == 3) >= 95
