"""The POMDP of the stream with a queue (MODEL.md 8.1, docs/POMDP.md): the solved states carry
the queue length l, the successors split by the release and the head's entry as the rule-by-
rule model does, the MDP over the solved states is the factored MDP's, the bounds bracket and
stay below the MDP, the policy file finds (l, x); and without a queue the POMDP is exactly
what it was (the shipped policies' fast informed bound recomputed to the bit)."""

import numpy as np
import pytest
from reference import read_only, solved_successors

from hrc_ros.core.config import load_config
from hrc_ros.core.mdp.policy import PolicyError
from hrc_ros.core.mdp.solver import FactoredBellman, solve
from hrc_ros.core.model import N_HIDDEN, HRCModel
from hrc_ros.core.paths import default_config_path, share_dir, shipped_config_path
from hrc_ros.core.pomdp.solver import fib_q, hrc_pomdp, mdp_q, solve_pomdp

CONFIG = default_config_path()
SMALL = {'model': {'rho': 1, 'sigma': 1}}
QUEUE = {'arrival_idle': 0.3, 'arrival_busy': 0.25, 'waiting_cost': 2.0,
         'q': [[1, 1, 0, 0.5], [1, 1, 3, 0.2], [1, 1, 2, 0.3]]}


def queue_model(levels, **solver):
    overrides = {**SMALL, 'stream': {**QUEUE, 'queue': levels}}
    if solver:
        overrides['solver'] = solver
    return HRCModel(load_config(CONFIG, overrides=overrides))


@pytest.fixture(scope='module', params=[1, 2])
def small(request):
    model = queue_model(request.param)
    return model, hrc_pomdp(model)


@pytest.fixture(scope='module')
def queue_mdp():
    """levels -> the MDP solve of `queue_model(levels)`, each solved once for the module (the
    tests below compared with, or selected by, four solves of these two models)."""
    solved = {}

    def get(levels):
        if levels not in solved:
            result = solve(queue_model(levels))
            read_only(result.value, result.policy)
            solved[levels] = result
        return solved[levels]
    return get


@pytest.fixture(scope='module')
def small_mdp(small, queue_mdp):
    """The MDP's value of `small`'s model at its solved states (x, h): one solve for the
    tests that compare with it."""
    model, hrc = small
    return queue_mdp(model.queue_length).value[flat_states(model, hrc)]


@pytest.fixture(scope='module')
def small_reference(small):
    """The reference (dense) forms' MDP Q, blind vectors and FIB Q of `small`'s POMDP, all to
    the default tol 1e-9, once: the sparse kernels' test holds the first two against the
    sparse forms, and `small_start` builds the initial bounds from the last two."""
    from hrc_ros.core.pomdp.solver import blind_alphas
    pomdp = small[1].pomdp
    q_mdp = mdp_q(pomdp)
    q_fib, _ = fib_q(pomdp, start=q_mdp)    # = fib_q(pomdp): it starts from mdp_q(pomdp)
    return read_only(q_mdp, blind_alphas(pomdp), q_fib)


@pytest.fixture(scope='module')
def small_start(small, small_reference):
    """The fixed points of `small`'s POMDP and the bounds a solve starts from there (blind
    vectors and FIB), built once: the sweep tests deep-copy them before they move them.
    `initial_bounds(hrc.pomdp, points_x, points)` to the bit, from `small_reference`'s
    arrays (the same calls `initial_bounds` makes) instead of solving them a second time."""
    from hrc_ros.core.pomdp.solver import UpperBound, _fixed_points, blind_alpha_set
    _, hrc = small
    pomdp = hrc.pomdp
    points_x, points = _fixed_points(hrc)
    _, blind, q_fib = small_reference
    return points_x, points, (blind_alpha_set(pomdp, blind),
                              UpperBound.from_fib(q_fib, pomdp.available, points_x, points))


@pytest.fixture(scope='module')
def queue2_solved():
    """A quick POMDP solve of the L = 2 queue model (its quality does not matter, only how
    its file and the selectors read it), shared by the tests that read it."""
    model = queue_model(2)
    return model, solve_pomdp(model, episodes=60, per_state=8, rounds=0, seed=4, tol=5e-2)


def flat_states(model, hrc):
    """(x, h) -> the flat index l * N0 + (h * n_task + y) * 4 + d of the model."""
    n_cols = model.n_task * 4
    level, column = np.divmod(hrc.columns, n_cols)
    return (level[:, None] * model.n_base + np.arange(N_HIDDEN)[None, :] * n_cols
            + column[:, None])


def test_the_solved_states_are_every_queue_length_of_the_closure(small):
    model, hrc = small
    plain = hrc_pomdp(HRCModel(load_config(CONFIG, overrides=SMALL)))
    n_cols = model.n_task * 4
    assert len(hrc.columns) == model.n_levels * len(plain.columns)
    for level in range(model.n_levels):
        block = hrc.columns[level * len(plain.columns):(level + 1) * len(plain.columns)]
        np.testing.assert_array_equal(block, level * n_cols + plain.columns)
    # the observable state with l tasks waiting is found there, and l outside 0..L is refused
    observable = (1, 1, 3, 0, 0, 0, 0, 0, 1)
    for level in range(model.n_levels):
        i = hrc.state(observable, level)
        assert hrc.columns[i] == level * n_cols + plain.columns[plain.state(observable)]
    with pytest.raises(ValueError, match='queue length'):
        hrc.state(observable, model.n_levels)


def test_queue_pomdp_successors_are_the_rule_by_rule_transition(small):
    """P((l', x') | (l, x), h, a) of the POMDP equals the model's explicit transition summed
    over h', at every solved state, every action, h = 0, 4, 8."""
    model, hrc = small
    pomdp = hrc.pomdp
    n_cols = model.n_task * 4
    n_keys = model.n_levels * n_cols
    flat = flat_states(model, hrc)
    queued = 0
    for h in (0, 4, 8):
        for a in range(8):
            t = model.transition(flat[:, h], a)
            level, base = model.split(t.target)
            expected = np.zeros((pomdp.n_x, n_keys))
            np.add.at(expected, (t.source, level * n_cols + base % n_cols), t.probability)
            got = solved_successors(pomdp, hrc.columns, a, h, n_keys)
            np.testing.assert_allclose(got, expected, atol=1e-12)
            queued += int(np.count_nonzero(got[:, n_cols:] > 0))
    assert queued > 0          # some successors have tasks waiting


def test_queue_pomdp_successors_are_distinct(small):
    """No two successors of one (x, a) are the same observed state (the top level's dropped
    release is merged into its 'no release'), so a backup does no work twice."""
    _, hrc = small
    succ = hrc.pomdp.succ_x
    for i in range(succ.shape[0]):
        for a in range(succ.shape[1]):
            row = succ[i, a][succ[i, a] >= 0]
            assert len(np.unique(row)) == len(row)


@pytest.mark.parametrize('aware', [True, False])
def test_queue_pomdp_mdp_is_the_factored_queue_q(aware):
    """reward + gamma E[V] over the solved states equals `FactoredBellman.q` of the queue model
    (its own mix along (l, y') and its waiting and drop charges), for a random V."""
    for levels in (1, 2):
        model = queue_model(levels, fail_safe_aware=aware)
        hrc = hrc_pomdp(model)
        pomdp = hrc.pomdp
        value = np.random.default_rng(levels).normal(size=model.n_states) * 20
        flat = flat_states(model, hrc)
        q = FactoredBellman(model).q(value)[:, flat]             # (8, x, h)
        mine = pomdp.reward + pomdp.gamma * pomdp.expected_next(value[flat])
        available = pomdp.available[..., None]
        np.testing.assert_allclose(np.where(available, mine, 0.0),
                                   np.where(available, q.transpose(1, 0, 2), 0.0), atol=1e-10)
    # the waiting charge is in: below the top level (L = 2, where nothing is dropped) the same
    # x and h cost w more per waiting task
    n_base_x = pomdp.n_x // model.n_levels
    np.testing.assert_allclose(pomdp.reward[n_base_x:2 * n_base_x],
                               pomdp.reward[:n_base_x] - QUEUE['waiting_cost'], atol=1e-12)


def test_the_queue_pomdp_mdp_value_is_the_mdp_solve(small, small_mdp):
    """The POMDP's fully observed MDP over the solved states converges to the MDP's value."""
    _, hrc = small
    value = small_mdp
    q = mdp_q(hrc.pomdp, tol=1e-10)
    best = np.where(hrc.pomdp.available[..., None], q, -np.inf).max(axis=1)
    np.testing.assert_allclose(best, value, atol=1e-4)   # the solve stops at eta = 1e-6


def test_the_queue_pomdp_bounds_bracket_and_sit_below_the_mdp(queue_mdp):
    model = queue_model(1)
    result = solve_pomdp(model, episodes=100, per_state=12, rounds=0, seed=3, tol=1e-2)
    assert result.report['observable_states'] == 2 * 4 * 27 == len(result.hrc.columns)
    for target in result.report['targets']:
        assert target['lower'] <= target['upper'] + 1e-9
        assert target['relative_gap'] < 0.05
    mdp = queue_mdp(1).value[flat_states(model, result.hrc)]           # (x, h)
    alphas = result.alphas
    levels = result.points_x // (len(result.hrc.columns) // model.n_levels)
    assert set(np.unique(levels)) == {0, 1}       # points were gathered with tasks waiting
    lower = np.array([(alphas.alpha[alphas.offsets[x]:alphas.offsets[x + 1]] @ b).max()
                      for x, b in zip(result.points_x, result.points)])
    upper = result.upper.evaluate(result.points_x, result.points)
    assert np.all(lower <= upper + 1e-9)
    assert np.all(lower <= np.einsum('ph,ph->p', mdp[result.points_x], result.points) + 1e-9)


def test_the_queue_pomdp_policy_file_finds_the_queue_length(tmp_path, queue2_solved):
    from hrc_ros.core.pomdp.policy import load_pomdp_policy, save_pomdp_policy
    model, result = queue2_solved
    config = model.config
    path = save_pomdp_policy(tmp_path / 'queue.npz', result, config)
    loaded = load_pomdp_policy(path, config).policy
    mine = result.policy()
    hrc = result.hrc
    np.testing.assert_array_equal(loaded.columns, hrc.columns)
    n_cols = model.n_task * 4
    b = np.full(N_HIDDEN, 1 / N_HIDDEN)
    observable = (1, 1, 3, 0, 0, 0, 0, 0, 1)
    column = hrc.columns[hrc.state(observable)]
    values = []
    for level in range(3):
        i = hrc.state(observable, level)
        assert loaded.state(level * n_cols + column) == i
        assert loaded.pomdp(b, level * n_cols + column)[0] == mine.pomdp(b, hrc.columns[i])[0]
        values.append(loaded.pomdp(b, level * n_cols + column)[1].max())
    assert values[0] > values[1] > values[2]    # tasks waiting cost
    many = loaded.pomdp_many(np.tile(b, (3, 1)), np.arange(3) * n_cols + column)
    assert list(many) == [loaded.pomdp(b, lv * n_cols + column)[0] for lv in range(3)]
    with pytest.raises(ValueError, match='does not cover it'):
        loaded.state(int(np.setdiff1d(np.arange(3 * n_cols), hrc.columns)[-1]))
    # the queue's policy is refused for the same model without the queue
    plain = load_config(CONFIG, overrides={**SMALL, 'stream': {
        'arrival_idle': 0.3, 'arrival_complete': 0.25, 'q': QUEUE['q']}})
    with pytest.raises(PolicyError, match='solved for configuration'):
        load_pomdp_policy(path, plain)


@pytest.mark.parametrize('name', ['default', 'case_study_stream'])
def test_without_a_queue_the_pomdp_is_the_shipped_one_to_the_bit(name):
    """The queue code leaves a configuration without a queue exactly as it was: its solved
    states are the shipped policy's, and the fast informed bound recomputed from its successors
    and rewards is the shipped file's q_fib, bit for bit (paper's model and queue-less
    stream)."""
    from hrc_ros.core.pomdp.policy import load_pomdp_policy
    config = load_config(shipped_config_path(name))
    shipped = load_pomdp_policy(share_dir() / 'policies' / 'pomdp' / f'{name}.npz', config)
    hrc = hrc_pomdp(HRCModel(config))
    np.testing.assert_array_equal(hrc.columns, shipped.policy.columns)
    q_fib, _ = fib_q(hrc.pomdp, tol=1e-9, start=mdp_q(hrc.pomdp, tol=1e-9))
    assert np.array_equal(q_fib, shipped.policy.q_fib)


def test_the_sparse_bounds_equal_the_reference_forms(small, small_reference):
    """The sparse kernels the queue's solve uses give the reference forms on the queue model
    (the reference MDP Q and blind vectors: `small_reference`'s, computed once)."""
    q_mdp, blind, _ = small_reference
    assert_sparse_bounds_are_the_reference_forms(small[1].pomdp, q_mdp, blind)


def test_the_sparse_bounds_equal_the_reference_forms_without_a_queue():
    """... and on a queue-less stream (one model: it does not depend on `small`'s L)."""
    assert_sparse_bounds_are_the_reference_forms(hrc_pomdp(HRCModel(load_config(
        CONFIG, overrides={**SMALL, 'stream': {'arrival_idle': 0.3, 'arrival_complete': 0.25,
                                               'q': QUEUE['q']}}))).pomdp)


def assert_sparse_bounds_are_the_reference_forms(pomdp, q_mdp=None, blind=None):
    """The sparse kernels (`fast`) give the reference forms' MDP Q, FIB step and blind
    vectors (`q_mdp`, `blind`: the reference forms `mdp_q(pomdp)` and `blind_alphas(pomdp)`
    if the caller has them already, else computed here)."""
    from hrc_ros.core.pomdp.solver import blind_alphas, fib_step
    q_mdp = mdp_q(pomdp) if q_mdp is None else q_mdp
    np.testing.assert_allclose(mdp_q(pomdp, fast=True), q_mdp, atol=1e-9)
    q = pomdp.reward + np.random.default_rng(7).normal(size=pomdp.reward.shape)
    np.testing.assert_allclose(fib_step(pomdp, q, fast=True), fib_step(pomdp, q), atol=1e-12)
    blind = blind_alphas(pomdp) if blind is None else blind
    np.testing.assert_allclose(blind_alphas(pomdp, fast=True), blind, atol=1e-9)


def test_shared_backups_equal_the_full_ones(small, small_start):
    """Backing up an action from another with the same successors and group (`share`, the
    queue's solve) moves both bounds as backing every action up in full does."""
    import copy

    from hrc_ros.core.pomdp.solver import backup_sweeps, shared_actions
    _, hrc = small
    pomdp = hrc.pomdp
    same_as = shared_actions(pomdp)
    assert np.count_nonzero(same_as >= 0) > pomdp.n_x           # there is work to share
    assert np.all(same_as < np.arange(pomdp.n_actions)[None, :])
    points_x, points, start = small_start
    runs = []
    for share in (False, True):
        alphas, upper = copy.deepcopy(start)
        alphas, upper, _ = backup_sweeps(pomdp, points_x, points, alphas, upper, 8, 0.0,
                                         ub_every=4, share=share)
        lower = [(alphas.alpha[alphas.offsets[x]:alphas.offsets[x + 1]] @ b).max()
                 for x, b in zip(points_x, points)]
        runs.append((np.array(lower), upper.values.copy()))
    np.testing.assert_allclose(runs[1][0], runs[0][0], atol=1e-9)
    np.testing.assert_allclose(runs[1][1], runs[0][1], atol=1e-9)


@pytest.mark.parametrize('small', [1], indirect=True)
def test_perseus_sweeps_keep_the_bounds_and_lift_every_point(small, small_start, small_mdp):
    """The randomised sweep of the queue's solve (`perseus`): the lower bound never falls at a
    point, stays below the upper bound and the MDP, and reaches the full sweeps' values within
    a small margin, with fewer vectors. On the L = 1 queue only: both runs go to convergence
    (about 250 sweeps each), 58 of the suite's CPU seconds at L = 2 against 38 at L = 1 for
    the same check of the sweep, which does not depend on L (the solved states' levels are
    checked at L = 2 by the tests above)."""
    import copy

    from hrc_ros.core.pomdp.solver import backup_sweeps
    _, hrc = small
    pomdp = hrc.pomdp
    points_x, points, start = small_start
    mdp = small_mdp
    results = {}
    for perseus in (False, True):
        alphas, upper = copy.deepcopy(start)
        alphas, upper, history = backup_sweeps(pomdp, points_x, points, alphas, upper, 400,
                                               1e-4, share=True, perseus=perseus)
        lower = np.array([(alphas.alpha[alphas.offsets[x]:alphas.offsets[x + 1]] @ b).max()
                          for x, b in zip(points_x, points)])
        assert all(row['lb_change'] >= 0 for row in history)
        assert history[-1]['lb_change'] < 1e-4
        assert np.all(lower <= upper.values + 1e-9)
        assert np.all(lower <= np.einsum('ph,ph->p', mdp[points_x], points) + 1e-6)
        results[perseus] = (lower, len(alphas))
    # the same bound as the full sweeps' within 0.05 (of values 50-300) at every point and no
    # lower on average, with fewer vectors
    shortfall = results[False][0] - results[True][0]
    assert shortfall.max() < 0.05 and shortfall.mean() <= 0.0
    assert results[True][1] < results[False][1]


def test_the_selector_and_the_evaluation_read_the_queue_pomdp_at_the_queue_length(
        queue2_solved, queue_mdp):
    """The pomdp and fib selectors at l: ActionSelector (the decision node's) and the batch
    evaluation ask the alpha policy for the column l * n_task * 4 + y * 4 + d (the episodes'
    actions reproduce the selector's), and a POMDP policy of another state space is refused."""
    from hrc_ros.core.decision.selection import ActionSelector
    from hrc_ros.core.model import TASK_VARIABLES
    from hrc_ros.core.study.evaluation import BatchSimulator, human_seed
    model, result = queue2_solved
    alphas = result.policy()
    mdp = queue_mdp(2)                  # the MDP solve of queue_model(2), `model`'s config
    selector = ActionSelector(model, mdp, pomdp=alphas)
    hrc, n_cols, grid = result.hrc, model.n_task * 4, model.task_grid
    rng = np.random.default_rng(6)
    for i in rng.choice(len(hrc.columns), size=40, replace=False):
        level, column = divmod(int(hrc.columns[i]), n_cols)
        y, d = divmod(column, 4)
        observable = tuple(int(grid[n][y]) for n in TASK_VARIABLES) + (d, level)
        b = rng.dirichlet(np.ones(N_HIDDEN))
        for method in ('pomdp', 'fib'):
            want = getattr(alphas, method)(b, int(hrc.columns[i]))[0]
            assert selector.select(b, observable, method).action == want
    # the batch at epoch 1, where the belief is the filter's first one: one task, or three
    # released at once (two waiting), at every distance and nature
    from hrc_ros.core.pomdp.belief import BeliefFilter
    from hrc_ros.core.study.simulation import Scenario
    scenarios = [Scenario((0, 0, 0, 0, 0, 0, 0, 0, 0, 0, d),
                          tuple((1, (1, 1, tx)) for _ in range(n)), 3, name='start')
                 for d in (1, 2, 3) for tx in range(4) for n in (1, 3) for _ in range(5)]
    seeds = [human_seed(9, e) for e in range(len(scenarios))]
    first = BeliefFilter(model, mode='posterior')
    differs = 0
    for method in ('pomdp', 'fib'):
        run = BatchSimulator(model, mdp, mode='posterior', pomdp=alphas).run(
            scenarios, seeds, method, keep_actions=True, record=True)
        t = run.trajectory
        for e in range(len(scenarios)):
            y, d, level = int(t['y'][e, 0]), int(t['d'][e, 0]), int(t['waiting'][e, 0])
            observable = tuple(int(grid[n][y]) for n in TASK_VARIABLES) + (d,)
            b = first.initial(int(t['observation'][e, 0]))
            assert run.actions[e, 0] == selector.select(b, observable + (level,), method).action
            differs += selector.select(b, observable + (0,), method).action != \
                selector.select(b, observable + (2,), method).action
    assert differs > 0                  # the check tells l = 2 from l = 0
    plain = queue_model(1)
    with pytest.raises(ValueError, match='observable columns'):
        ActionSelector(plain, queue_mdp(1), method='pomdp', pomdp=alphas)
