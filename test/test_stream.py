"""The task stream in the model (MODEL.md 8): configuration, rule-by-rule arrivals, the factored
MDP solver against them, and the paper's model left exactly as it was."""

import numpy as np
import pytest
from reference import (assert_shipped_policy_solves_todays_model, read_only, rule_q,
                       solved_successors)

from hrc_ros.core.config import ConfigError, load_config
from hrc_ros.core.mdp.policy import PolicyError, load_policy, save_policy
from hrc_ros.core.mdp.solver import FactoredBellman, solve
from hrc_ros.core.model import CT, DN, NW, RH2, HRCModel
from hrc_ros.core.paths import default_config_path, share_dir, shipped_config_path

CONFIG = default_config_path()
STREAM = {'arrival_idle': 0.3, 'arrival_complete': 0.6,
          'q': [[1, 1, 0, 0.5], [1, 1, 3, 0.2], [1, 1, 2, 0.3]]}
SMALL = {'model': {'rho': 1, 'sigma': 1}}


@pytest.fixture(scope='module')
def small_stream():
    return HRCModel(load_config(CONFIG, overrides={**SMALL, 'stream': STREAM}))


def _frozen(result):
    """A solve shared by several tests, read-only so that none can change it for the next."""
    read_only(result.value, result.policy)
    return result


@pytest.fixture(scope='module')
def small_stream_mdp(small_stream):
    """The MDP solve of `small_stream`, once for the tests that read it."""
    return _frozen(solve(small_stream))


@pytest.fixture(scope='module')
def small_plain_mdp():
    """The MDP solve of the small paper's model (no stream), once for the tests that read
    it."""
    return _frozen(solve(HRCModel(load_config(CONFIG, overrides=SMALL))))


def test_no_stream_section_is_the_papers_model_with_its_hash():
    plain = load_config(CONFIG)
    assert not plain.has_stream and plain.stream is None
    assert HRCModel(plain).arrivals is None
    # the hash of a configuration without a stream is the one the shipped policies carry
    meta = load_policy(share_dir() / 'policies' / 'default.npz', plain).meta
    assert meta['config_sha256'] == plain.policy_hash
    streamed = load_config(CONFIG, overrides={'stream': STREAM | {'q': None}})
    assert streamed.policy_hash != plain.policy_hash
    p_idle, p_complete, tasks, q = streamed.stream
    assert (p_idle, p_complete) == (0.3, 0.6)
    assert len(tasks) == 16 and np.allclose(q, 1 / 16)     # q null: the model's tasks, uniform


@pytest.mark.parametrize('stream, message', [
    ({'arrival_idle': 1.5, 'arrival_complete': 0.5}, 'stream.arrival_idle'),
    ({'arrival_idle': 0.5}, 'missing key stream.arrival_complete'),
    ({'arrival_idle': 0.5, 'arrival_complete': 0.5, 'rate': 1}, 'unknown key stream.rate'),
    ({'arrival_idle': 0.5, 'arrival_complete': 0.5, 'q': [[1, 1, 0, 0.5]]}, 'sum to 0.5'),
    ({'arrival_idle': 0.5, 'arrival_complete': 0.5, 'q': [[3, 1, 0, 1.0]]}, 'not a task'),
    ({'arrival_idle': 0.5, 'arrival_complete': 0.5, 'q': [[1, 1, 0, 0.5], [1, 1, 0, 0.5]]},
     'listed twice'),
    ({'arrival_idle': 0.5, 'arrival_complete': 0.5, 'q': [[1, 1.5, 0, 1.0]]}, 'integer'),
])
def test_a_bad_stream_section_is_refused_naming_the_field(stream, message):
    with pytest.raises(ConfigError, match=message):
        load_config(CONFIG, overrides={'stream': stream})


@pytest.mark.parametrize('stream', [[0.3, 0.6], 'yes', 5])
def test_a_stream_section_that_is_not_a_mapping_is_named_so_not_missing(stream):
    with pytest.raises(ConfigError, match="section 'stream' must be a mapping") as caught:
        load_config(CONFIG, overrides={'stream': stream})
    assert 'missing' not in str(caught.value) and '\n' not in str(caught.value)


def test_a_task_outside_the_model_is_quoted_within_the_cap():
    """A 4,000-digit tp (as a 64 KiB configuration or a live `config` may hold) is refused in
    a line of bounded size, not echoed whole."""
    with pytest.raises(ConfigError, match='not a task of the model') as caught:
        load_config(CONFIG, overrides={'stream': {
            'arrival_idle': 0.5, 'arrival_complete': 0.5, 'q': [[10 ** 4000, 1, 0, 1.0]]}})
    assert len(str(caught.value)) < 600


def test_arrivals_rule_by_rule(small_stream):
    """From an idle cell a task of q arrives with arrival_idle; right after a task completes,
    with arrival_complete; a busy cell gets none."""
    m = small_stream
    idle = m.index((1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 2))
    completing = m.index((1, 1, 1, 1, 0, 2, 0, 0, 1, 1, 2))   # the robot's last epoch of it
    waiting = m.index((1, 1, 1, 1, 3, 0, 0, 0, 0, 0, 2))      # a joint task, uncommitted
    for source, p_arrive in ((idle, 0.3), (completing, 0.6), (waiting, 0.0)):
        t = m.transition(np.array([source]), NW)
        nxt = m.state(t.target)
        got = {}
        for row, p in zip(nxt, t.probability):
            key = tuple(row[2:5]) if row[2] else None
            got[key] = got.get(key, 0.0) + p
        if p_arrive == 0.0:
            assert set(got) == {(1, 1, 3)}
            continue
        assert got[None] == pytest.approx(1 - p_arrive)
        for (tp, tc, tx, q) in STREAM['q']:
            assert got[(tp, tc, tx)] == pytest.approx(p_arrive * q)
        # an arrived task is uncommitted and the emotions move as without the stream
        assert np.all(nxt[nxt[:, 2] > 0, 5] == 0)
    # every row of ct's explicit transition matrix sums to 1: the row sums of
    # `sparse_matrices()[CT]` (its CSR of these same rows; test_solver checks the assembly),
    # summed from the rows themselves without building the other seven actions' matrices
    t = m.transition(np.arange(m.n_states), CT)
    assert np.allclose(np.bincount(t.source, weights=t.probability, minlength=m.n_states), 1.0)


@pytest.mark.parametrize('aware', [True, False])
def test_factored_q_and_the_fused_sweep_equal_the_rule_by_rule_stream(small_stream, aware):
    model = HRCModel(load_config(CONFIG, overrides={**SMALL, 'stream': STREAM,
                                                     'solver': {'fail_safe_aware': aware}}))
    op = FactoredBellman(model)
    value = np.random.default_rng(5).normal(size=model.n_states) * 20
    q = op.q(value)
    sources = np.arange(model.n_states)
    np.testing.assert_allclose(q.T, rule_q(model, value, sources), atol=1e-10)
    new, residual = op.apply(value)
    np.testing.assert_allclose(new, q.max(axis=0), atol=1e-10)
    assert residual == pytest.approx(np.max(np.abs(q.max(axis=0) - value)), abs=1e-10)


def test_factored_q_equals_rule_by_rule_on_sampled_full_stream_states():
    model = HRCModel(load_config(shipped_config_path('stream')))
    rng = np.random.default_rng(13)
    value = rng.normal(size=model.n_states) * 20
    sample = rng.choice(model.n_states, size=1500, replace=False)
    q = FactoredBellman(model).q(value)
    np.testing.assert_allclose(q[:, sample].T, rule_q(model, value, sample), atol=1e-10)


def test_the_stream_changes_what_an_idle_cell_expects(small_stream, small_stream_mdp,
                                                     small_plain_mdp):
    """Tasks that will come cost: every idle state is worth less with the stream, and the
    same state without one is the paper's value."""
    v_plain, v_stream = small_plain_mdp.value, small_stream_mdp.value
    idle = small_stream.state(np.arange(small_stream.n_states))[:, 2] == 0
    assert np.all(v_stream[idle] < v_plain[idle] - 1e-6)


def test_shipped_policies_of_the_paper_model_are_unchanged_by_the_stream_code():
    """The operator with the stream code keeps every shipped configuration without a stream
    at its shipped policy, action for action (at the fixed point:
    reference.assert_shipped_policy_solves_todays_model); the fail-safe-unaware one, the only
    shipped model of that branch (test_config_policy solves the default afresh), is also
    solved from zero and held to its file value for value."""
    for name in ('default', 'paper', 'fail_safe_unaware'):
        assert_shipped_policy_solves_todays_model(name)
    config = load_config(shipped_config_path('fail_safe_unaware'))
    shipped = load_policy(share_dir() / 'policies' / 'fail_safe_unaware.npz', config)
    fresh = solve(HRCModel(config))
    np.testing.assert_array_equal(fresh.policy, shipped.policy)
    np.testing.assert_allclose(fresh.value, shipped.value, atol=1e-9)


@pytest.mark.parametrize('name', ['stream', 'case_study_stream', 'case_study_stream150'])
def test_shipped_stream_policies_load_and_solve_todays_model(name):
    config, shipped = assert_shipped_policy_solves_todays_model(name)
    assert shipped.meta['config']['stream'] == config.data['stream']


def test_a_stream_policy_is_refused_against_the_papers_model_saying_which_is_which(
        tmp_path, small_stream_mdp, small_plain_mdp):
    stream = load_config(CONFIG, overrides={**SMALL, 'stream': STREAM})
    plain = load_config(CONFIG, overrides=SMALL)
    path = save_policy(tmp_path / 'stream.npz', small_stream_mdp, stream)   # solved for stream
    with pytest.raises(PolicyError, match=r'plans a task stream .* describes no task stream'):
        load_policy(path, plain)
    path = save_policy(tmp_path / 'plain.npz', small_plain_mdp, plain)      # solved for plain
    with pytest.raises(PolicyError, match=r'plans no task stream .* describes a task stream.*'
                       r'hrc-solve --config'):
        load_policy(path, stream)


def test_the_stream_policy_waits_for_nothing_when_no_task_can_come(small_plain_mdp):
    """arrival 0: the stream model is the paper's model (same values, same policy)."""
    zero = HRCModel(load_config(CONFIG, overrides={**SMALL, 'stream': {
        'arrival_idle': 0.0, 'arrival_complete': 0.0, 'q': None}}))
    a, b = solve(zero), small_plain_mdp
    np.testing.assert_allclose(a.value, b.value, atol=1e-9)
    np.testing.assert_array_equal(a.policy, b.policy)
    assert {DN, RH2} <= set(np.unique(a.policy))


# -- the POMDP of the stream model -------------------------------------------------------------
@pytest.fixture(scope='module')
def small_stream_hrc(small_stream):
    from hrc_ros.core.pomdp.solver import hrc_pomdp
    return hrc_pomdp(small_stream)


def test_pomdp_successors_are_the_rule_by_rule_stream_transition(small_stream, small_stream_hrc):
    """P(x' | x, h, a) of the POMDP, arrivals included, equals the model's explicit transition
    summed over h', at every solved state."""
    hrc, pomdp, m = small_stream_hrc, small_stream_hrc.pomdp, small_stream
    n_columns = m.n_task * 4
    for h in (0, 4, 8):
        for a in range(8):
            # every solved state at once: row i of `expected` / `got` is state i's P(x' | .)
            t = m.transition(h * n_columns + hrc.columns, a)
            expected = np.zeros((pomdp.n_x, n_columns))
            np.add.at(expected, (t.source, t.target % n_columns), t.probability)
            got = solved_successors(pomdp, hrc.columns, a, h, n_columns)
            np.testing.assert_allclose(got, expected, atol=1e-12)
    # some successors are arrivals: more than the 2 x 3 of no stream
    arrived = np.count_nonzero(np.count_nonzero(pomdp.succ_x >= 0, axis=2) > 6)
    assert arrived > 0


def test_pomdp_mdp_over_the_solved_states_is_the_stream_factored_q(small_stream,
                                                                    small_stream_hrc):
    hrc, pomdp = small_stream_hrc, small_stream_hrc.pomdp
    value = np.random.default_rng(2).normal(size=small_stream.n_states) * 20
    q = FactoredBellman(small_stream).q(value).reshape(8, 9, -1)[:, :, hrc.columns]
    v = value.reshape(9, -1)[:, hrc.columns].T
    mine = pomdp.reward + pomdp.gamma * pomdp.expected_next(v)
    available = pomdp.available[..., None]
    np.testing.assert_allclose(np.where(available, mine, 0.0),
                               np.where(available, q.transpose(2, 0, 1), 0.0), atol=1e-10)


def test_the_stream_pomdp_bounds_bracket_and_sit_below_the_mdp(small_stream, small_stream_mdp):
    from hrc_ros.core.pomdp.solver import solve_pomdp
    result = solve_pomdp(small_stream, episodes=100, per_state=15, rounds=0, seed=2,
                         tol=1e-2)
    for target in result.report['targets']:
        assert target['lower'] <= target['upper'] + 1e-9
        assert target['relative_gap'] < 0.05
    # the POMDP's lower bound is no better than the fully informed MDP at any point
    mdp = small_stream_mdp.value.reshape(9, -1)[:, result.hrc.columns].T   # (x, h)
    alphas = result.alphas
    for x, b in zip(result.points_x[:400], result.points[:400]):
        lower = (alphas.alpha[alphas.offsets[x]:alphas.offsets[x + 1]] @ b).max()
        assert lower <= b @ mdp[x] + 1e-9


def test_the_shipped_stream_pomdp_policy_is_found_and_refused_for_the_papers_model():
    from hrc_ros.core.pomdp.policy import default_pomdp_policy_path, load_pomdp_policy
    config = load_config(shipped_config_path('case_study_stream'))
    path = default_pomdp_policy_path(config)
    assert path.name == 'case_study_stream.npz'
    loaded = load_pomdp_policy(path, config)
    assert loaded.meta['report']['case_study_relative_gap'] < 0.02
    assert loaded.meta['config']['stream'] == config.data['stream']
    plain = load_config(default_config_path())
    with pytest.raises(PolicyError, match='plans a task stream .* describes no task stream'):
        load_pomdp_policy(path, plain)


@pytest.mark.parametrize('name', ['stream', 'case_study_stream150'])
def test_every_stream_configuration_ships_its_pomdp_policy(name):
    from hrc_ros.core.pomdp.policy import default_pomdp_policy_path, load_pomdp_policy
    config = load_config(shipped_config_path(name))
    path = default_pomdp_policy_path(config)
    assert path.name == f'{name}.npz'
    assert load_pomdp_policy(path, config).meta['report']['case_study_relative_gap'] < 0.02


def test_the_live_swap_never_takes_a_policy_of_the_other_model():
    """The parameter service's rule (core.swap.check_swap) between the paper's model and the
    stream's, both ways: a policy of the other model set with a configuration is refused,
    saying which model each is; a configuration set alone beside the policy of the other
    model is staged (the old pair decides); '' finds the policy solved for it."""
    from hrc_ros.core.swap import ACCEPTED, REFUSED, STAGED, check_swap
    paper_cfg, stream_cfg = str(CONFIG), str(shipped_config_path('stream'))
    paper_pol = str(share_dir() / 'policies' / 'default.npz')
    stream_pol = str(share_dir() / 'policies' / 'stream.npz')
    for (run_cfg, run_pol), (cfg, pol) in (((paper_cfg, paper_pol), (stream_cfg, paper_pol)),
                                           ((stream_cfg, stream_pol), (paper_cfg, stream_pol))):
        staged = check_swap(2, 2, run_cfg, cfg, run_pol, run_pol)
        assert staged.verdict == STAGED and 'task stream' in staged.reason
        refused = check_swap(2, 2, run_cfg, cfg, '', pol)
        assert refused.verdict == REFUSED and 'task stream' in refused.reason
        assert check_swap(2, 2, run_cfg, cfg, run_pol, '').verdict == ACCEPTED


def test_a_stream_without_its_optional_q_is_the_same_model_as_q_null(tmp_path):
    """`q` may be left out (it then reads as null, MODEL.md 8): the configuration is the same
    model, so it has the same hash and finds the policy shipped for `q: null`."""
    from hrc_ros.core.mdp.policy import default_policy_path
    shipped = shipped_config_path('stream')
    text = shipped.read_text()
    assert '\n  q: null' in text
    left_out = tmp_path / 'stream.yaml'
    left_out.write_text(text.replace('\n  q: null', '\n'))
    config = load_config(left_out)
    assert config.stream[2].shape == (16, 3)
    assert config.policy_hash == load_config(shipped).policy_hash
    assert default_policy_path(config) == share_dir() / 'policies' / 'stream.npz'
