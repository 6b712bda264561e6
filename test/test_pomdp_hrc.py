"""The HRC POMDP: its structure against the model, the exact posterior, the reduced model's
bounds and the pomdp selector's achieved cost against them, the policy files and the CLI."""

import json

import numpy as np
import pytest
import yaml
from reference import solved_successors

from hrc_ros.core.pomdp.belief import BeliefFilter
from hrc_ros.core.config import load_config
from hrc_ros.core.study.evaluation import BatchSimulator, human_seed, random_scenarios
from hrc_ros.core.model import ACTIONS, DN, N_DISTANCE, NW, RH2, HRCModel, step_task
from hrc_ros.core.paths import default_config_path, shipped_config_path
from hrc_ros.core.mdp.policy import PolicyError, save_policy
from hrc_ros.core.pomdp.solver import AlphaPolicy, case_study_targets, hrc_pomdp, solve_pomdp
from hrc_ros.core.pomdp.policy import (default_pomdp_policy_path, load_pomdp_policy,
                                       save_pomdp_policy)
from hrc_ros.core.decision.selection import ActionSelector
from hrc_ros.core.study.simulation import Scenario
from hrc_ros.core.mdp.solver import FactoredBellman, solve
from hrc_ros.core.tasks import TaskBook

REDUCED = {'model': {'rho': 1, 'sigma': 1}}
CASE_TASK = (1, 1, 3, 0, 0, 0, 0, 0)
# The reduced solve's gap at the case study's first beliefs stays below this share of |V|.
STATED_GAP = 0.01


@pytest.fixture(scope='module')
def reduced():
    return HRCModel(load_config(default_config_path(), overrides=REDUCED))


@pytest.fixture(scope='module')
def reduced_hrc(reduced):
    return hrc_pomdp(reduced)


@pytest.fixture(scope='module')
def reduced_mdp(reduced):
    """The reduced model's MDP solve, once for the tests that read it (none changes it)."""
    return solve(reduced)


@pytest.fixture(scope='module')
def reduced_solution(reduced):
    return solve_pomdp(reduced, episodes=400, per_state=40, rounds=1, seed=3)


@pytest.mark.parametrize('config', ['default', 'arm', 'rated'])
def test_successors_are_the_rule_by_rule_transition(config, reduced, reduced_hrc):
    """P(x' | x, h, a) of the POMDP equals the model's explicit transition summed over h';
    with the arm's model too (dp, dm pause the robot's counter, a retreat and a move closer
    gain no band, the queue of MODEL.md 8.1: columns l * n_task * 4 + y * 4 + d)."""
    if config == 'arm':       # the arm's rules without its measured progress ('rated' has it)
        reduced = HRCModel(load_config(shipped_config_path(config), overrides={
            'model': {**REDUCED['model'], 'robot_rate': None}}))
        reduced_hrc = hrc_pomdp(reduced)
    if config == 'rated':     # model.robot_rate: the counter's run is a branch of its own
        rate = {0: [0.0, 0.1, 0.5, 0.9], 2: [0.2, 0.3, 0.6, 1.0], 3: [0.0, 0.05, 0.4, 0.7]}
        reduced = HRCModel(load_config(shipped_config_path('arm'), overrides={
            'model': {**REDUCED['model'], 'robot_rate': rate}}))
        reduced_hrc = hrc_pomdp(reduced)
    hrc, pomdp = reduced_hrc, reduced_hrc.pomdp
    rng = np.random.default_rng(4)
    n_columns = reduced.n_task * N_DISTANCE
    all_columns = reduced.n_levels * n_columns
    # (the queue's rule-by-rule transitions are slow: fewer states with it)
    xs = rng.choice(pomdp.n_x, size=60 if reduced.queue is None else 24, replace=False)
    hs = (0, 4, 8)
    level, within = np.divmod(hrc.columns[xs].astype(np.int64), n_columns)
    # every (x, h) source of an action in one call: `transition` enumerates each source's row
    # on its own (rows indexed by t.source), so this is the per-source transition, batched
    sources = (level[:, None] * reduced.n_base + np.array(hs)[None, :] * n_columns
               + within[:, None]).reshape(-1)
    for a in range(len(ACTIONS)):
        t = reduced.transition(sources, a)
        level_next, base = divmod(t.target, reduced.n_base)
        columns_next = level_next * n_columns + base % n_columns
        got = {h: solved_successors(pomdp, hrc.columns, a, h, all_columns) for h in hs}
        for j, (i, h) in enumerate((int(i), h) for i in xs for h in hs):
            row = t.source == j
            expected = np.bincount(columns_next[row], weights=t.probability[row],
                                   minlength=all_columns)
            np.testing.assert_allclose(got[h][i], expected, atol=1e-12)


def test_the_mdp_over_the_solved_states_is_the_factored_bellman_q(reduced, reduced_hrc):
    hrc, pomdp = reduced_hrc, reduced_hrc.pomdp
    value = np.random.default_rng(2).normal(size=reduced.n_states) * 20
    q = FactoredBellman(reduced).q(value).reshape(len(ACTIONS), 9, -1)[:, :, hrc.columns]
    v = value.reshape(9, -1)[:, hrc.columns].T                        # (x, h)
    mine = pomdp.reward + pomdp.gamma * pomdp.expected_next(v)
    available = pomdp.available[..., None]
    np.testing.assert_allclose(np.where(available, mine, 0.0),
                               np.where(available, q.transpose(2, 0, 1), 0.0), atol=1e-10)


def test_the_task_book_never_leaves_the_solved_states(reduced, reduced_hrc):
    rng = np.random.default_rng(9)
    for _ in range(40):
        book = TaskBook(reduced, schedule=[(k, (1, 1, int(rng.integers(0, 4))))
                                           for k in range(1, 60, 3)])
        for k in range(1, 60):
            book.begin_epoch(k)
            reduced_hrc.state(book.observable(int(rng.integers(0, 4))))   # raises if outside
            a = int(rng.integers(0, len(ACTIONS)))
            book.apply(a, bool(rng.random() < 0.5))
    with pytest.raises(ValueError, match='does not cover'):
        reduced_hrc.state((0, 1, 0, 0, 0, 0, 0, 0, 1))     # no task but time left: unreachable


def test_posterior_is_bayes_rule_on_the_joint(reduced):
    """The posterior mode's update equals Bayes' rule on P(h, x', h', O') enumerated from the
    rule-by-rule transition; bayes mode ignores the evidence (MODEL.md 6 as written)."""
    model = reduced
    posterior = BeliefFilter(model, mode='posterior')
    bayes = BeliefFilter(model, mode='bayes')
    lik = posterior.likelihood
    rng = np.random.default_rng(1)
    y = model.task_index({n: np.asarray(v) for n, v in zip(
        ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc'), CASE_TASK)})
    n_columns = model.n_task * N_DISTANCE
    for a, accepted, d in ((RH2, True, 1), (RH2, False, 2), (NW, False, 1), (DN, False, 3)):
        b = rng.dirichlet(np.ones(9))
        grid = {n: np.asarray(v) for n, v in zip(
            ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc'), CASE_TASK)}
        y_next = int(model.task_index(step_task(grid, a, accepted)))
        for d_next in range(4):
            joint = np.zeros(9)          # P(h', x' = (y', d')) summed over h
            for h in range(9):
                t = model.transition([h * n_columns + int(y) * 4 + d], a)
                hit = (t.target % n_columns) == y_next * 4 + d_next
                np.add.at(joint, t.target[hit] // n_columns, b[h] * t.probability[hit])
            if joint.sum() == 0:
                continue
            eligible = a == RH2
            evidence = model.transition_likelihood(a, eligible, accepted, d, d_next)
            for o in (1, 2, 3):
                expected = joint * lik[o - 1]
                expected /= expected.sum()
                got = posterior.update(b, a, o, evidence)
                np.testing.assert_allclose(got, expected, atol=1e-12)
                many = posterior.update_many(b[None], [a], [o], evidence[None])[0]
                np.testing.assert_allclose(many, expected, atol=1e-12)
                np.testing.assert_allclose(bayes.update(b, a, o, evidence),
                                           bayes.update(b, a, o), atol=0)


def test_reduced_bounds_meet_within_the_stated_gap(reduced_solution):
    r = reduced_solution.report
    assert r['case_study_relative_gap'] < STATED_GAP
    for target in r['targets']:
        assert target['lower'] <= target['upper']
        assert target['gap'] < STATED_GAP * abs(target['lower'])
    assert r['points_gap']['mean'] < 0.05 and r['points_gap']['max'] >= 0.0


def test_the_lower_bound_is_below_fib_and_the_mdp_everywhere(reduced, reduced_solution):
    s = reduced_solution
    lower = np.array([(s.alphas.alpha[s.alphas.offsets[x]:s.alphas.offsets[x + 1]] @ b).max()
                      for x, b in zip(s.points_x, s.points)])
    assert np.all(lower <= s.upper.evaluate(s.points_x, s.points) + 1e-9)
    q_fib = s.upper.q_fib
    fib = np.where(s.hrc.pomdp.available[s.points_x], np.einsum(
        'pah,ph->pa', q_fib[s.points_x], s.points), -np.inf).max(axis=1)
    assert np.all(lower <= fib + 1e-9)


def test_pomdp_selector_achieves_the_lower_bound_from_the_case_study_start(
        reduced, reduced_solution, reduced_mdp, tmp_path):
    """Episodes from the case study's task at d = 1 with the hidden state uniform, so that
    P(h | O_1) is exactly b_1 = initial(O_1); no further tasks, as the POMDP models; the exact
    posterior. The mean discounted cost agrees with -E[lower bound at b_1] (and lies above
    -E[upper bound]) within its 95% interval and the 150-epoch truncation."""
    s = reduced_solution
    names, tx, tb = case_study_targets(s.hrc)
    p_o = BeliefFilter(reduced).likelihood.sum(axis=1) / 9.0           # P(O_1)
    lower = sum(p * t['lower'] for p, t in zip(p_o, s.report['targets']))
    upper = sum(p * t['upper'] for p, t in zip(p_o, s.report['targets']))
    epochs, per_h = 150, 400
    scenarios = [Scenario((h // 3, h % 3) + CASE_TASK + (1,), (), epochs)
                 for h in range(9) for _ in range(per_h)]
    seeds = [human_seed(11, e) for e in range(len(scenarios))]
    sim = BatchSimulator(reduced, reduced_mdp, mode='posterior', pomdp=s.policy())
    cost = np.concatenate([sim.run(scenarios[i:i + 900], seeds[i:i + 900], 'pomdp')
                           .discounted_cost for i in range(0, len(scenarios), 900)])
    half = 1.96 * cost.std(ddof=1) / np.sqrt(cost.size)
    tail = 0.95 ** epochs * 200.0                    # what 150 epochs leave out, at most
    assert cost.mean() - half <= -lower + tail
    assert cost.mean() + half >= -upper - tail
    assert abs(cost.mean() + lower) < half + (upper - lower) + tail


PERSON_PRIOR = [0.45, 0.2, 0.0, 0.15, 0.1, 0.0, 0.05, 0.05, 0.0]


def test_sampled_starts_come_from_the_person_prior(reduced):
    """observation.prior: every sampled episode's belief starts from it and the humans of the
    random starts are drawn from it (the case study's start keeps its own h = (0, 0))."""
    from hrc_ros.core.pomdp.solver import _starts
    model = HRCModel(reduced.config.with_overrides({'observation': {'prior': PERSON_PRIOR}}))
    starts = _starts(hrc_pomdp(model))
    np.testing.assert_allclose(starts.prior, np.tile(PERSON_PRIOR, (len(starts.x), 1)))
    np.testing.assert_array_equal(starts.truth[0], np.eye(9)[0])
    np.testing.assert_allclose(starts.truth[1:], np.tile(PERSON_PRIOR, (len(starts.x) - 1, 1)))
    uniform = _starts(hrc_pomdp(reduced))
    np.testing.assert_array_equal(uniform.prior, np.full((len(uniform.x), 9), 1 / 9))


def test_pomdp_selector_achieves_the_lower_bound_with_a_person_prior(reduced, reduced_mdp):
    """The reduced model with a non-uniform person prior: the solve's bounds at the case
    study's first beliefs (b_1 ∝ prior * L[O_1]) bracket the pomdp selector's mean cost over
    humans drawn from that prior, as they do for the uniform one above."""
    model = HRCModel(reduced.config.with_overrides({'observation': {'prior': PERSON_PRIOR}}))
    s = solve_pomdp(model, episodes=400, per_state=40, rounds=1, seed=3)
    prior = np.array(PERSON_PRIOR)
    lik = BeliefFilter(model).likelihood
    p_o = lik @ prior                                                 # P(O_1)
    names, tx, tb = case_study_targets(s.hrc)
    for o in (1, 2, 3):
        np.testing.assert_allclose(tb[o - 1], lik[o - 1] * prior / p_o[o - 1])
    lower = sum(p * t['lower'] for p, t in zip(p_o, s.report['targets']))
    upper = sum(p * t['upper'] for p, t in zip(p_o, s.report['targets']))
    epochs, n = 150, 3600
    hs = np.random.default_rng(5).choice(9, size=n, p=prior)
    scenarios = [Scenario((h // 3, h % 3) + CASE_TASK + (1,), (), epochs) for h in hs]
    seeds = [human_seed(12, e) for e in range(n)]
    # the prior is not part of the MDP (its configuration hash is the reduced model's): the
    # reduced model's MDP solve is this model's
    assert model.config.policy_hash == reduced.config.policy_hash
    sim = BatchSimulator(model, reduced_mdp, mode='posterior', pomdp=s.policy())
    cost = np.concatenate([sim.run(scenarios[i:i + 900], seeds[i:i + 900], 'pomdp')
                           .discounted_cost for i in range(0, n, 900)])
    half = 1.96 * cost.std(ddof=1) / np.sqrt(cost.size)
    tail = 0.95 ** epochs * 200.0
    assert cost.mean() - half <= -lower + tail
    assert cost.mean() + half >= -upper - tail
    assert abs(cost.mean() + lower) < half + (upper - lower) + tail


def test_pomdp_and_fib_ties_go_to_the_safety_order():
    alpha = np.array([[1.0] * 9, [1.0] * 9, [0.0] * 9])
    policy = AlphaPolicy(columns=[5], alpha=alpha, action=[NW, DN, RH2], offsets=[0, 3],
                         q_fib=np.ones((1, 8, 9)), available=np.ones((1, 8), dtype=bool),
                         n_columns=8)
    b = np.full(9, 1 / 9)
    action, scores = policy.pomdp(b, 5)
    assert action == DN and scores[NW] == scores[DN] == pytest.approx(1.0)
    assert scores[RH2] == pytest.approx(0.0) and np.isneginf(scores[1])
    assert policy.fib(b, 5)[0] == DN                    # all eight tied
    assert list(policy.pomdp_many(b[None], [5])) == [DN]
    assert list(policy.fib_many(b[None], [5])) == [DN]
    with pytest.raises(ValueError, match='does not cover'):
        policy.pomdp(b, 4)


def test_fib_with_a_belief_that_rules_states_out_picks_the_best_available_action():
    """An unavailable action's score was -inf * b(h): nan wherever b(h) = 0 (a sure belief),
    and a nan best made every action untied, so fib fell to dn whatever Q said (and published
    nan scores). The mask now applies after the product."""
    q_fib = np.zeros((1, 8, 9))
    q_fib[0, NW] = 5.0
    available = np.ones((1, 8), dtype=bool)
    available[0, RH2] = False
    policy = AlphaPolicy(columns=[5], alpha=np.zeros((1, 9)), action=[DN], offsets=[0, 1],
                         q_fib=q_fib, available=available, n_columns=8)
    sure = np.eye(9)[4]
    action, scores = policy.fib(sure, 5)
    assert action == NW and not np.isnan(scores).any() and np.isneginf(scores[RH2])
    assert list(policy.fib_many(sure[None], [5])) == [NW]


def test_selector_and_batch_agree_with_the_alpha_policy(reduced, reduced_solution, reduced_mdp):
    """ActionSelector's pomdp and fib are the AlphaPolicy's; BatchSimulator reproduces
    `simulate` action for action with them (posterior and bayes)."""
    from hrc_ros.core.study.simulation import simulate
    policy = reduced_solution.policy()
    mdp = reduced_mdp
    rng = np.random.default_rng(5)
    selector = ActionSelector(reduced, mdp, method='pomdp', pomdp=policy)
    for i in rng.choice(len(policy.columns), size=30, replace=False):
        column = int(policy.columns[i])
        y, d = divmod(column, N_DISTANCE)
        observable = tuple(int(reduced.task_grid[n][y]) for n in
                           ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc')) + (d,)
        b = rng.dirichlet(np.ones(9) * 0.3)
        for method in ('pomdp', 'fib'):
            got = selector.select(b, observable, method)
            action, scores = getattr(policy, method)(b, column)
            assert got.action == action and got.method == method
            np.testing.assert_array_equal(got.scores, scores)
    scenarios = random_scenarios(reduced, 10, 30, seed=2, task_rate=0.3)
    seeds = [human_seed(2, e) for e in range(10)]
    for mode in ('posterior', 'bayes'):
        for method in ('pomdp', 'fib'):
            batch = BatchSimulator(reduced, mdp, mode=mode, pomdp=policy).run(
                scenarios, seeds, method, keep_actions=True)
            for e, scenario in enumerate(scenarios):
                t = simulate(reduced, mdp, scenario, selector=method, mode=mode, seed=seeds[e],
                             pomdp=policy)
                assert [ACTIONS[a] for a in batch.actions[e]] == t.actions
                assert batch.discounted_cost[e] == pytest.approx(t.discounted_cost, rel=1e-12)


# -- policy files ------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def reduced_file(reduced, reduced_solution, tmp_path_factory):
    path = tmp_path_factory.mktemp('pomdp') / 'reduced.npz'
    return save_pomdp_policy(path, reduced_solution, reduced.config)


def test_policy_file_round_trip(reduced, reduced_solution, reduced_file):
    loaded = load_pomdp_policy(reduced_file, reduced.config)
    s = reduced_solution
    np.testing.assert_array_equal(loaded.policy.alpha, s.alphas.alpha)
    np.testing.assert_array_equal(loaded.policy.action, s.alphas.action)
    np.testing.assert_array_equal(loaded.policy.columns, s.hrc.columns)
    assert loaded.meta['kind'] == 'pomdp'
    assert loaded.config_sha256 == reduced.config.policy_hash
    assert loaded.meta['report']['case_study_relative_gap'] < STATED_GAP
    b = np.full(9, 1 / 9)
    for column in loaded.policy.columns[:50]:
        assert loaded.policy.pomdp(b, column)[0] == s.policy().pomdp(b, column)[0]


def test_policy_file_refuses_another_configuration(reduced, reduced_file, default_config):
    with pytest.raises(PolicyError, match='hrc-solve --config .* --method pomdp'):
        load_pomdp_policy(reduced_file, default_config)
    table = np.array(reduced.config.observation_table)
    table[0] = [0.7, 0.2, 0, 0.1, 0, 0, 0, 0, 0]
    other = reduced.config.with_overrides({'observation': {'table': table.tolist()}})
    assert other.policy_hash == reduced.config.policy_hash      # the MDP would not notice
    with pytest.raises(PolicyError, match='another observation model'):
        load_pomdp_policy(reduced_file, other)


def test_policy_file_refuses_damage(reduced, reduced_mdp, reduced_file, tmp_path):
    with pytest.raises(PolicyError, match='does not exist'):
        load_pomdp_policy(tmp_path / 'none.npz', reduced.config)
    junk = tmp_path / 'junk.npz'
    junk.write_bytes(b'not a zip')
    with pytest.raises(PolicyError, match='corrupt'):
        load_pomdp_policy(junk, reduced.config)
    with np.load(reduced_file) as archive:
        arrays = {k: archive[k] for k in archive.files}

    def broken(**changes):
        path = tmp_path / f'broken_{len(list(tmp_path.glob("broken_*")))}.npz'
        np.savez(path, **{**arrays, **changes})
        return path
    mdp_file = save_policy(tmp_path / 'mdp.npz', reduced_mdp, reduced.config)
    for path, message in (
            (mdp_file, 'not an hrc_ros POMDP policy file'),
            (broken(alpha_action=arrays['alpha_action'] + 20), 'outside 0..7'),
            (broken(alpha_offsets=arrays['alpha_offsets'][:-1]), 'alpha_offsets'),
            (broken(alpha=arrays['alpha'] * np.nan), 'NaN'),
            (broken(columns=arrays['columns'][::-1].copy()), 'increasing'),
            (broken(meta=np.array(json.dumps({'kind': 'mdp'}))), 'configuration hash'),
            (broken(meta=np.array(json.dumps({'config_sha256': 'a' * 64}))), 'no POMDP meta'),
            (broken(alpha=np.zeros((3, 4))), 'alpha must be float64'),
            (broken(q_fib=arrays['q_fib'][:, :3]), 'q_fib')):
        with pytest.raises(PolicyError, match=message):
            load_pomdp_policy(path, reduced.config)


def test_policy_file_refuses_a_wide_state_before_the_dense_copy(default_config, tmp_path):
    """A small file whose one state holds 4,096 vectors (within the per-state and total caps)
    among 596 states: its dense copy (states x widest x 9) would take 2.4 M slots, more than
    MAX_VECTORS; refused before it is allocated (with 46,656 states such a 200 kB file asked
    for 13 GiB and ended the node that loaded it)."""
    from hrc_ros.core.pomdp import policy as pomdp_policy
    shipped = pomdp_policy.default_pomdp_policy_path(default_config)
    with np.load(shipped) as archive:
        arrays = {k: archive[k] for k in archive.files}
    offsets = arrays['alpha_offsets']
    extra = 4096 - int(offsets[1] - offsets[0])
    arrays['alpha'] = np.concatenate([np.repeat(arrays['alpha'][:1], extra, axis=0),
                                      arrays['alpha']])
    arrays['alpha_action'] = np.concatenate([np.repeat(arrays['alpha_action'][:1], extra),
                                             arrays['alpha_action']])
    arrays['alpha_offsets'] = np.concatenate([[0], offsets[1:] + extra])
    assert len(arrays['alpha']) < pomdp_policy.MAX_VECTORS
    assert len(offsets) - 1 == 596 and 596 * 4096 > pomdp_policy.MAX_VECTORS
    wide = tmp_path / 'wide.npz'
    np.savez(wide, **arrays)
    with pytest.raises(PolicyError, match='slots the loaded policy may take'):
        load_pomdp_policy(wide, default_config)


def test_shipped_pomdp_policies_are_found_by_configuration():
    for name in ('default', 'fail_safe_unaware'):
        config = load_config(shipped_config_path(name))
        path = default_pomdp_policy_path(config)
        assert path.name == f'{name}.npz' and path.parent.name == 'pomdp'
        loaded = load_pomdp_policy(path, config)
        assert loaded.meta['report']['case_study_relative_gap'] < 0.01
        assert path.stat().st_size < 20e6
    # the arm's model (docs/ROBOT.md 4): shipped, its gap stated there (0.39% at the study)
    arm = load_config(shipped_config_path('arm'))
    path = default_pomdp_policy_path(arm)
    assert path.name == 'arm.npz' and path.parent.name == 'pomdp'
    assert load_pomdp_policy(path, arm).meta['report']['case_study_relative_gap'] < 0.01
    paper = load_config(shipped_config_path('paper'))
    with pytest.raises(PolicyError, match='hrc-solve --config .* --method pomdp'):
        load_pomdp_policy(default_pomdp_policy_path(paper), paper)
    with pytest.raises(PolicyError):
        ActionSelector(HRCModel(paper), np.zeros(HRCModel(paper).n_states, dtype=np.int8),
                       method='pomdp')


# -- command lines -----------------------------------------------------------------------------
def test_cli_solves_a_pomdp_and_evaluates_it_paired(reduced, tmp_path, capsys):
    from hrc_ros.tools.evaluate import main as evaluate_main
    from hrc_ros.tools.solve import main as solve_main
    config = tmp_path / 'reduced.yaml'
    data = yaml.safe_load(default_config_path().read_text())
    data['model'].update(REDUCED['model'])
    config.write_text(yaml.safe_dump(data))
    mdp, pomdp = tmp_path / 'mdp.npz', tmp_path / 'pomdp.npz'
    assert solve_main(['--config', str(config), '-o', str(mdp), '-q']) == 0
    # few gathering episodes: the command line's path is the claim here, not the bounds'
    # quality (the round-0 gathering is what costs: 150 episodes took 7 of its 9 CPU s)
    assert solve_main(['--method', 'pomdp', '--config', str(config), '-o', str(pomdp),
                       '--episodes', '10', '--rounds', '0', '-q']) == 0
    out = capsys.readouterr().out
    assert 'case study, b_1 after O_1 = 1: lower' in out and f'wrote {pomdp}' in out
    assert load_pomdp_policy(pomdp, load_config(config)).meta['report']['rounds'] == 0
    code = evaluate_main(['--config', str(config), '--policy', str(mdp), '--pomdp-policy',
                          str(pomdp), '--episodes', '60', '--epochs', '20',
                          '--selectors', 'paper,qmdp,fib,pomdp,mdp', '--baseline', 'pomdp',
                          '--mode', 'posterior', '--out', str(tmp_path / 'ev')])
    assert code == 0
    out = capsys.readouterr().out
    assert 'paired differences of the discounted cost to pomdp' in out
    for name in ('paper', 'qmdp', 'fib', 'mdp'):
        assert f'  {name:<9} - pomdp' in out
    summary = json.loads((tmp_path / 'ev' / 'summary.json').read_text())
    assert summary['baseline'] == 'pomdp' and set(summary['cost_minus_baseline_cost']) == {
        'paper', 'qmdp', 'fib', 'mdp'}
    assert (tmp_path / 'ev' / 'paired.csv').read_text().startswith('selector,baseline')


def test_cli_refuses_a_baseline_not_evaluated_and_a_missing_pomdp_policy(tmp_path, capsys):
    from hrc_ros.tools.evaluate import main as evaluate_main
    with pytest.raises(SystemExit) as exc:
        evaluate_main(['--selectors', 'paper,mls', '--baseline', 'pomdp'])
    assert exc.value.code == 2
    assert '--baseline' in capsys.readouterr().err
    code = evaluate_main(['--selectors', 'paper,pomdp', '--pomdp-policy',
                          str(tmp_path / 'none.npz'), '--out', str(tmp_path)])
    assert code == 2
    assert 'does not exist' in capsys.readouterr().err


def test_sampled_beliefs_stay_probabilities_when_the_prior_rules_the_evidence_out(reduced):
    """epsilon 0 and a person prior all on h = 4 (review): the case study's start keeps its
    true h = 0, whose first observation the prior calls impossible; the gathered beliefs
    restart from the evidence alone (as BeliefFilter does) instead of becoming NaN."""
    from hrc_ros.core.pomdp.solver import _starts, q_policy, fib_q, sample_beliefs
    model = HRCModel(reduced.config.with_overrides({'observation': {
        'epsilon': 0.0, 'prior': [0, 0, 0, 0, 1, 0, 0, 0, 0]}}))
    hrc = hrc_pomdp(model)
    q_fib, _ = fib_q(hrc.pomdp, tol=1e-6)
    xs, bs = sample_beliefs(hrc.pomdp, hrc.likelihood, _starts(hrc), q_policy(hrc.pomdp, q_fib),
                            episodes=400, epochs=20, seed=1, enter=hrc.enter)
    assert np.all(np.isfinite(bs))
    np.testing.assert_allclose(bs.sum(axis=1), 1.0)
