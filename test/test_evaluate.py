"""hrc-evaluate: the batched episodes reproduce `simulate`; the table, bound and outputs."""

import csv
import json

import numpy as np
import pytest
from reference import rule_q

from hrc_ros.core.study.evaluation import (METRICS, BatchSimulator, evaluate, human_seed,
                                           paired_difference, random_scenarios, summarize)
from hrc_ros.core.model import ACTIONS
from hrc_ros.core.mdp.policy import default_policy_path
from hrc_ros.core.study.simulation import simulate
from hrc_ros.tools.evaluate import main

SELECTORS = ('paper', 'qmdp', 'mls', 'mdp')


def test_random_scenarios_are_seeded_and_valid(model):
    a = random_scenarios(model, 30, 40, seed=5, task_rate=0.3)
    assert a == random_scenarios(model, 30, 40, seed=5, task_rate=0.3)
    assert a != random_scenarios(model, 30, 40, seed=6, task_rate=0.3)
    for s in a:
        em, ea, *task, d = s.initial_state
        assert em in range(3) and ea in range(3) and d in (1, 2, 3) and not any(task)
        assert s.schedule[0][0] == 1 and s.epochs == 40
        for k, (tp, tc, tx) in s.schedule:
            assert 1 <= k <= 40 and 1 <= tp <= model.rho and 1 <= tc <= model.sigma
            assert 0 <= tx <= 3
    releases = sum(len(s.schedule) - 1 for s in a) / (30 * 39)
    assert 0.2 < releases < 0.4



def test_random_scenarios_kept_for_the_next_call_are_the_fresh_draw_and_a_list_of_its_own(
        model, monkeypatch):
    """The episodes kept for the next call with the same arguments (the plant's check draws
    the same ones four times a refit) are the ones a fresh draw makes, whatever the caller did
    to the list it got; a set beyond KEPT_EPISODE_EPOCHS is drawn anew and not kept."""
    from hrc_ros.core.study import evaluation
    evaluation._kept_scenarios.cache_clear()
    prior = [0.3, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.05, 0.05]
    first = random_scenarios(model, 20, 30, seed=8, prior=np.array(prior))
    fresh = list(evaluation._scenarios(model.rho, model.sigma, 20, 30, 8, 0.2, tuple(prior)))
    assert first == fresh
    first.clear()                                      # the caller's list, not the kept one
    again = random_scenarios(model, 20, 30, seed=8, prior=prior)
    assert again == fresh and evaluation._kept_scenarios.cache_info().hits == 1
    assert random_scenarios(model, 20, 30, seed=8) != fresh         # the prior is in the key
    monkeypatch.setattr(evaluation, 'KEPT_EPISODE_EPOCHS', 20 * 30 - 1)
    assert random_scenarios(model, 20, 30, seed=8, prior=prior) == fresh
    assert evaluation._kept_scenarios.cache_info().hits == 1

@pytest.mark.parametrize('mode', ['bayes', 'table', 'posterior'])
@pytest.mark.parametrize('selector', SELECTORS + ('pomdp', 'fib'))
def test_batch_reproduces_simulate_episode_by_episode(model, policy, mode, selector):
    scenarios = random_scenarios(model, 12, 30, seed=3, task_rate=0.35)
    seeds = [human_seed(3, e) for e in range(12)]
    batch = BatchSimulator(model, policy, mode=mode).run(scenarios, seeds, selector,
                                                         keep_actions=True)
    for e, scenario in enumerate(scenarios):
        t = simulate(model, policy, scenario, selector=selector, mode=mode, seed=seeds[e])
        assert [ACTIONS[a] for a in batch.actions[e]] == t.actions
        assert batch.discounted_cost[e] == pytest.approx(t.discounted_cost, rel=1e-12)
        assert batch.collision_epochs[e] == np.sum(t.column('d') == 0)
        answers = list(t.column('accepted'))
        assert batch.refused_requests[e] == sum(a is False for a in answers)
        assert batch.requests[e] == sum(a is not None for a in answers)
        done = [r.epochs_to_complete for r in t.tasks if r.complete_epoch is not None]
        assert batch.tasks_completed[e] == len(done)
        assert batch.tasks_released[e] == len(t.tasks)
        if done:
            assert batch.epochs_to_complete[e] == pytest.approx(np.mean(done))
        else:
            assert np.isnan(batch.epochs_to_complete[e])


def test_batch_handles_an_initial_task_and_the_fail_safe_switch(model, policy):
    from hrc_ros.core.study.simulation import case_study
    scenario = case_study()
    for fail_safe in (True, False):
        batch = BatchSimulator(model, policy, fail_safe=fail_safe).run(
            [scenario] * 3, [0, 4, 8], 'paper', keep_actions=True)
        for e, seed in enumerate((0, 4, 8)):
            t = simulate(model, policy, scenario, seed=seed, fail_safe=fail_safe)
            assert [ACTIONS[a] for a in batch.actions[e]] == t.actions


def test_q_table_is_the_models_q(model, policy):
    sim = BatchSimulator(model, policy)
    states = np.random.default_rng(0).integers(0, model.n_states, 40)
    assert np.allclose(sim.q_table[states], rule_q(model, policy.value, states), atol=1e-9)


@pytest.fixture(scope='module')
def small_run(model, policy):
    return evaluate(model, policy, episodes=300, epochs=40, seed=1)


def test_summary_structure_and_the_mdp_bound(small_run):
    assert list(small_run) == list(SELECTORS)
    summaries = {s: summarize(r) for s, r in small_run.items()}
    for summary in summaries.values():
        assert list(summary) == [m for m, _ in METRICS]
        for metric, stats in summary.items():
            assert stats['low'] <= stats['mean'] <= stats['high']
            assert stats['n'] == 300 or metric == 'epochs_to_complete'
    bound = summaries['mdp']['discounted_cost']['mean']
    for s in ('paper', 'qmdp', 'mls'):
        cost = summaries[s]['discounted_cost']
        assert bound <= cost['mean'] + cost['half_width'], s
        diff = paired_difference(small_run[s], small_run['mdp'])
        assert diff['high'] > 0, s      # the paired interval does not lie below the bound


def test_results_are_reproducible_for_a_seed(model, policy, small_run):
    again = evaluate(model, policy, episodes=300, epochs=40, seed=1, selectors=('paper',))
    other = evaluate(model, policy, episodes=300, epochs=40, seed=2, selectors=('paper',))
    assert np.array_equal(again['paper'].discounted_cost, small_run['paper'].discounted_cost)
    assert not np.array_equal(other['paper'].discounted_cost,
                              small_run['paper'].discounted_cost)
    chunked = evaluate(model, policy, episodes=300, epochs=40, seed=1, selectors=('paper',),
                       chunk=7)
    assert np.allclose(chunked['paper'].discounted_cost, small_run['paper'].discounted_cost)


def test_cli_table_and_files(tmp_path, capsys):
    assert main(['--episodes', '40', '--epochs', '20', '--out', str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert '40 episodes x 20 epochs' in out and 'paper: 40/40 episodes' in out
    table = [line.split()[0] for line in out.splitlines()
             if line.split() and line.split()[0] in SELECTORS and '±' in line]
    assert table == list(SELECTORS)
    with (tmp_path / 'summary.csv').open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(SELECTORS) * len(METRICS)
    assert {r['selector'] for r in rows} == set(SELECTORS)
    summary = json.loads((tmp_path / 'summary.json').read_text())
    assert summary['settings']['episodes'] == 40
    assert set(summary['selectors']) == set(SELECTORS)
    assert summary['cost_minus_mdp_cost']['mdp']['mean'] == 0.0
    with (tmp_path / 'episodes.csv').open() as f:
        assert sum(1 for _ in f) == 1 + 40 * len(SELECTORS)
    assert (tmp_path / 'summary.png').read_bytes()[:4] == b'\x89PNG'


def test_cli_refuses_bad_inputs(tmp_path, capsys):
    for argv in (['--selectors', 'paper,best'], ['--episodes', '0'], ['--seed', '-1'],
                 ['--task-rate', '1.5']):
        with pytest.raises(SystemExit):
            main(argv + ['--out', str(tmp_path)])
    paper_policy = default_policy_path().with_name('paper.npz')    # shipped: it is tracked
    assert main(['--policy', str(paper_policy), '--out', str(tmp_path)]) == 2
    assert 'was solved for configuration' in capsys.readouterr().err


def test_bad_api_inputs_raise(model, policy):
    scenarios = random_scenarios(model, 2, 5)
    sim = BatchSimulator(model, policy)
    with pytest.raises(ValueError, match='unknown selector'):
        sim.run(scenarios, [0, 1], 'greedy')
    with pytest.raises(ValueError, match='one seed per scenario'):
        sim.run(scenarios, [0], 'paper')
    with pytest.raises(ValueError, match='same number of epochs'):
        sim.run([scenarios[0], random_scenarios(model, 1, 6)[0]], [0, 1], 'paper')
    with pytest.raises(ValueError, match='needs the solved value'):
        BatchSimulator(model, policy.policy).run(scenarios, [0, 1], 'qmdp')
    with pytest.raises(ValueError, match='policy has 5 states'):
        BatchSimulator(model, np.zeros(5, dtype=np.int8))
    with pytest.raises(ValueError, match='episodes must be an integer >= 1'):
        random_scenarios(model, 0, 5)
    with pytest.raises(ValueError, match='task_rate'):
        random_scenarios(model, 1, 5, task_rate=2.0)
    with pytest.raises(ValueError, match='unknown selector'):
        evaluate(model, policy, episodes=2, epochs=2, selectors=('paper', 'best'))


# -- model mismatch: --true-config ------------------------------------------------------------
def reluctant(default_config):
    """A world whose human refuses more and steps closer than the default assumes."""
    return default_config.with_overrides({'model': {
        'p_accept': [0.05, 0.35, 0.7],
        'p_delta': [[0.05, 0.65, 0.30], [0.05, 0.55, 0.40], [0.02, 0.38, 0.60]]}})


def test_the_world_is_drawn_from_the_true_model_and_the_robot_plans_with_its_own(
        model, policy, default_config):
    from hrc_ros.core.model import HRCModel
    world = HRCModel(reluctant(default_config))
    scenarios = random_scenarios(model, 200, 30, seed=4)
    seeds = [human_seed(4, e) for e in range(200)]
    mismatched = BatchSimulator(model, policy, world=world).run(scenarios, seeds, record=True)
    matched = BatchSimulator(model, policy).run(scenarios, seeds, record=True)
    # the same decisions at epoch 1 (same policy, filter, initial observation), other answers
    np.testing.assert_array_equal(mismatched.trajectory['action'][:, 0],
                                  matched.trajectory['action'][:, 0])
    t = mismatched.trajectory
    answered = t['accepted'] >= 0
    rate = t['accepted'][answered].mean()
    expected = np.asarray(world.config.p_accept)[t['em'][answered]].mean()
    assert abs(rate - expected) < 0.08            # the world's p_accept, not the plan's
    assert mismatched.refused_requests.sum() > matched.refused_requests.sum()


def test_planning_with_the_true_model_has_no_regret_and_the_default_has_some(
        model, policy, default_config):
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.mdp.solver import solve
    world = HRCModel(reluctant(default_config))
    true_policy = solve(world)
    true = evaluate(world, true_policy, 300, 40, 3, selectors=('paper',), world=world)
    same = evaluate(world, true_policy, 300, 40, 3, selectors=('paper',), world=world)
    assert paired_difference(same['paper'], true['paper'])['mean'] == 0.0
    wrong = evaluate(model, policy, 300, 40, 3, selectors=('paper',), world=world)
    regret = paired_difference(wrong['paper'], true['paper'])
    assert regret['low'] > 0                      # planning with the wrong model costs


def test_cli_true_config_prints_and_writes_the_regret(tmp_path, capsys, default_config):
    import yaml
    path = tmp_path / 'true.yaml'
    path.write_text(yaml.safe_dump(reluctant(default_config).data))
    assert main(['--episodes', '30', '--epochs', '20', '--selectors', 'paper,mdp',
                 '--true-config', str(path), '--out', str(tmp_path / 'out')]) == 0
    out = capsys.readouterr().out
    assert f'the world is {path}' in out and 'solving' in out and 'regret (paired)' in out
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['settings']['true_config'] == str(path)
    assert set(summary['regret']) == {'paper', 'mdp'}
    assert set(summary['true_model']) == {'paper', 'mdp'}


def test_cli_true_config_must_describe_the_same_cell(tmp_path, capsys, default_config):
    import yaml
    path = tmp_path / 'small.yaml'
    path.write_text(yaml.safe_dump(default_config.with_overrides(
        {'model': {'rho': 1, 'sigma': 1}}).data))
    assert main(['--true-config', str(path), '--out', str(tmp_path)]) == 2
    assert 'they must describe the same cell' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(['--true-policy', 'x.npz', '--out', str(tmp_path)])


def test_random_people_come_from_the_worlds_person_prior_and_never_from_the_plans(
        model, policy, default_config):
    """A world with a person prior (observation.prior) draws the random episodes' people from
    it: evaluate's run is the batch run of `random_scenarios(..., prior=)` episode by episode,
    and not the uniform people's. A world without one, and a planning model with one, keep
    the uniform people (a plan's prior changes only what the robot believes)."""
    from hrc_ros.core.model import HRCModel
    at_zero = {'observation': {'prior': [1.0] + [0.0] * 8}}
    plain = evaluate(model, policy, 300, 30, 5, selectors=('paper',))['paper']
    same = evaluate(model, policy, 300, 30, 5, selectors=('paper',),
                    world=HRCModel(default_config))['paper']
    np.testing.assert_array_equal(same.discounted_cost, plain.discounted_cost)
    world = HRCModel(default_config.with_overrides(at_zero))
    drawn = evaluate(model, policy, 300, 30, 5, selectors=('paper',), world=world)['paper']
    people = random_scenarios(model, 300, 30, seed=5, prior=world.config.observation_prior)
    assert all(tuple(s.initial_state[:2]) == (0, 0) for s in people)
    direct = BatchSimulator(model, policy, world=world).run(
        people, [human_seed(5, e) for e in range(300)], 'paper')
    np.testing.assert_array_equal(drawn.discounted_cost, direct.discounted_cost)
    assert not np.array_equal(drawn.discounted_cost, plain.discounted_cost)
    believing = HRCModel(default_config.with_overrides(at_zero))
    believed = evaluate(believing, policy, 300, 30, 5, selectors=('paper',))['paper']
    np.testing.assert_array_equal(believed.tasks_released, plain.tasks_released)
