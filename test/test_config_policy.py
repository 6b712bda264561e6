"""Configuration validation, policy files and the hrc-solve command."""

import io
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import yaml
from reference import assert_shipped_policy_solves_todays_model

from hrc_ros.core.config import ConfigError, load_config
from hrc_ros.core.model import HRCModel
from hrc_ros.core.paths import default_config_path, share_dir, shipped_config_path
from hrc_ros.core.mdp.policy import PolicyError, default_policy_path, load_policy, save_policy
from hrc_ros.core.mdp.solver import solve

DEFAULT = default_config_path()


def write_config(tmp_path, mutate):
    data = yaml.safe_load(open(DEFAULT))
    mutate(data)
    path = tmp_path / 'config.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_arm_config_is_the_default_with_the_cell_keys_of_the_arm():
    """config/arm.yaml (docs/ROBOT.md 4): model keys more than the default (the robot paused
    under dp and dm, a retreat and a move closer that gain no band) and a queue (issue 34's
    liveness) and the arm's measured progress (model.robot_rate, MODEL.md 3.2); each key's
    default and the key left out are one model, one hash."""
    default, arm = load_config(DEFAULT), load_config(shipped_config_path('arm'))
    assert default.robot_paused_by == ('dn',) and arm.robot_paused_by == ('dn', 'dp', 'dm')
    assert default.retreat_reach is None and arm.retreat_reach == 1
    assert default.approach_reach is None and arm.approach_reach == 3
    assert default.robot_rate is None                                # optional: the paper's rule
    # the arm works least at the shared station and near the person (bench/progress_bench.py)
    assert arm.robot_rate[3, 1] < arm.robot_rate[0, 1] < arm.robot_rate[0, 3] < 1
    assert arm.robot_rate[[0, 2, 3], 0].max() == 0 and arm.robot_rate[1].min() == 1   # SSM stops
    cell_keys = ('robot_paused_by', 'retreat_reach', 'approach_reach', 'robot_rate')
    assert {k: v for k, v in arm.data['model'].items()
            if k not in cell_keys} == default.data['model']
    assert arm.queue == 2 and 'stream' not in default.data
    assert {k: arm.data[k] for k in arm.data if k not in ('model', 'stream')} == \
        {k: default.data[k] for k in default.data if k != 'model'}
    assert arm.policy_hash != default.policy_hash
    explicit = load_config(DEFAULT, {'model': {'robot_paused_by': ['dn'], 'retreat_reach': None,
                                               'approach_reach': None, 'robot_rate': None}})
    assert explicit.policy_hash == default.policy_hash
    rated = load_config(DEFAULT, {'model': {'robot_rate': {3: [0, 0.1, 0.5, 1]}}})
    assert rated.policy_hash != default.policy_hash           # the counter's rule: the policy's
    assert rated.belief_hash == default.belief_hash           # no evidence about the person
    assert rated.robot_rate[3].tolist() == [0, 0.1, 0.5, 1] and rated.robot_rate[1].min() == 1
    as_json = load_config(DEFAULT, {'model': {'robot_rate': {'3': [0, 0.1, 0.5, 1]}}})
    assert as_json.policy_hash == rated.policy_hash           # a policy meta's JSON keys
    approach = load_config(DEFAULT, {'model': {'approach_reach': 3}})
    assert approach.policy_hash != default.policy_hash
    assert approach.belief_hash != default.belief_hash     # the posterior reads the move
    null = load_config(DEFAULT, {'model': {'robot_paused_by': None}})
    assert null.robot_paused_by == ('dn',) and null.policy_hash == default.policy_hash
    reach = load_config(DEFAULT, {'model': {'retreat_reach': 2}})
    assert reach.policy_hash not in (default.policy_hash, arm.policy_hash)
    reordered = load_config(shipped_config_path('arm'),
                            {'model': {'robot_paused_by': ['dm', 'dn', 'dp']}})
    assert reordered.policy_hash == arm.policy_hash


def test_the_belief_hash_tells_apart_what_the_posterior_filter_reads_of_the_arms_keys():
    """The exact posterior (mode posterior, MODEL.md 6) reads the distance move through the
    distance matrices, which model.retreat_reach changes: after dp from d = 2 to d = 3 the arm's
    model (reach 1: no band gained) and the default (a band gained) update the belief apart, so
    their belief hashes must differ, or the decision node calls an estimator on the other model
    a match. What pauses the robot's counter is no part of the filter: one belief hash."""
    from hrc_ros.core.model import DP
    from hrc_ros.core.pomdp.belief import BeliefFilter
    default = load_config(DEFAULT)
    reach = load_config(DEFAULT, {'model': {'retreat_reach': 1}})
    beliefs = []
    for config in (default, reach):
        model = HRCModel(config)
        belief_filter = BeliefFilter(model, mode='posterior')
        evidence = model.transition_likelihood(DP, False, False, 2, 3)
        beliefs.append(belief_filter.update(np.full(9, 1 / 9), DP, 2, evidence))
    assert np.abs(beliefs[0] - beliefs[1]).max() > 0.01
    assert reach.belief_hash != default.belief_hash
    assert load_config(shipped_config_path('arm')).belief_hash == load_config(
        DEFAULT, {'model': {'retreat_reach': 1, 'approach_reach': 3}}).belief_hash
    assert load_config(DEFAULT, {'model': {'retreat_reach': None}}).belief_hash == \
        default.belief_hash
    paused = load_config(DEFAULT, {'model': {'robot_paused_by': ['dn', 'dp', 'dm']}})
    assert paused.belief_hash == default.belief_hash


def test_shipped_configs_load_and_differ_only_in_alpha10():
    default, paper = load_config(DEFAULT), load_config(shipped_config_path('paper'))
    assert default.cost['alpha10'] == 10 and paper.cost['alpha10'] == 1
    assert {k: v for k, v in paper.cost.items() if k != 'alpha10'} == \
        {k: v for k, v in default.cost.items() if k != 'alpha10'}
    assert all(v == 1 for k, v in paper.cost.items())
    assert default.policy_hash != paper.policy_hash
    # observation settings do not change the policy hash
    assert load_config(DEFAULT, {'observation': {'epsilon': 0.05}}).policy_hash == \
        default.policy_hash


@pytest.mark.parametrize('mutate, field', [
    (lambda d: d['model']['p_delta'].__setitem__(1, [0.1, 0.7, 0.3]), r'model\.p_delta\[1\]'),
    (lambda d: d['model']['emotion']['motivate'].__setitem__('em', [0.1, 0.4, 0.6]),
     r'model\.emotion\.motivate\.em'),
    (lambda d: d['model']['p_accept'].__setitem__(0, 1.3), r'model\.p_accept\[0\]'),
    (lambda d: d['cost'].__setitem__('alpha3', -1.0), r'cost\.alpha3'),
    (lambda d: d['solver'].__setitem__('gamma', 1.0), r'solver\.gamma'),
    (lambda d: d['solver'].__setitem__('gamma', 0.0), r'solver\.gamma'),
    (lambda d: d['model'].__setitem__('rho', 0), r'model\.rho'),
    (lambda d: d['model'].__setitem__('sigma', 0), r'model\.sigma'),
    (lambda d: d['model'].__setitem__('sigma', 1.5), r'model\.sigma'),
    (lambda d: d['cost'].__setitem__('alpha14', 1.0), r'cost\.alpha14'),
    (lambda d: d.__setitem__('extras', {}), r'extras'),
    (lambda d: d['model']['emotion'].__setitem__('shout', {}), r'model\.emotion\.shout'),
    (lambda d: d['cost'].pop('beta4'), r'cost\.beta4'),
    (lambda d: d['observation'].__setitem__('mode', 'magic'), r'observation\.mode'),
    (lambda d: d['solver'].__setitem__('eta', 'small'), r'solver\.eta'),
    (lambda d: d['solver'].__setitem__('fail_safe_aware', 'yes'), r'solver\.fail_safe_aware'),
    (lambda d: d['model'].__setitem__('robot_paused_by', ['dp']), r'robot_paused_by must hold dn'),
    (lambda d: d['model'].__setitem__('robot_paused_by', ['dn', 'ct']),
     r"robot_paused_by: 'ct' cannot pause"),
    (lambda d: d['model'].__setitem__('robot_paused_by', ['dn', 'dn']),
     r'robot_paused_by lists an action twice'),
    (lambda d: d['model'].__setitem__('robot_paused_by', 'dn'), r'robot_paused_by must be a list'),
    (lambda d: d['model'].__setitem__('retreat_reach', 3), r'model\.retreat_reach must be null'),
    (lambda d: d['model'].__setitem__('retreat_reach', True), r'model\.retreat_reach must be'),
    # an integer key, as rho and sigma: 1.0 is not one
    (lambda d: d['model'].__setitem__('retreat_reach', 1.0), r'model\.retreat_reach must be'),
    (lambda d: d['model'].__setitem__('approach_reach', 0), r'model\.approach_reach must be'),
    (lambda d: d['model'].__setitem__('approach_reach', 4), r'model\.approach_reach must be'),
    (lambda d: d['model'].__setitem__('robot_rate', {1: [1, 1, 1, 1]}),
     r'model\.robot_rate: 1 is no task nature with a robot share'),
    (lambda d: d['model'].__setitem__('robot_rate', {0: [1, 1, 1]}), r'model\.robot_rate\[0\]'),
    (lambda d: d['model'].__setitem__('robot_rate', {0: [1, 1, 1.5, 1]}),
     r'model\.robot_rate\[0\]\[2\]'),
    (lambda d: d['model'].__setitem__('robot_rate', [1, 1, 1, 1]), r'model\.robot_rate must be'),
])
def test_bad_configs_fail_naming_the_field(tmp_path, mutate, field):
    with pytest.raises(ConfigError, match=field):
        load_config(write_config(tmp_path, mutate))


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match='cannot read'):
        load_config(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('model: [unclosed\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load_config(bad)
    binary = tmp_path / 'policy_by_mistake.yaml'
    binary.write_bytes(b'PK\x03\x04\xff\xfe\x00')
    with pytest.raises(ConfigError, match='not a text'):
        load_config(binary)


def test_a_key_given_twice_is_refused_naming_it_and_its_line(tmp_path):
    """YAML's loaders keep a repeated key's second value without a word: a configuration with
    `k1` twice under cost was solved with the second (a review, 2026-12-06). Lists of mappings
    with the same keys, the same key in two mappings and merge keys stay valid."""
    lines = DEFAULT.read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith('cost:'))
    twice = tmp_path / 'twice.yaml'
    twice.write_text('\n'.join(lines[:at + 1] + ['  k1: 5.0'] + lines[at + 1:]) + '\n')
    second = [i + 1 for i, line in enumerate(twice.read_text().splitlines())
              if line.strip().startswith('k1:')][1]
    with pytest.raises(ConfigError) as error:
        load_config(twice)
    message = str(error.value)
    assert f'line {second}: the key cost.k1 is given twice' in message, message
    assert '\n' not in message
    from hrc_ros.core.paths import parse_yaml
    assert parse_yaml('a: [{x: 1}, {x: 2}]\nb: {x: 1}\nc: {x: 2}\n', ValueError, 's') == {
        'a': [{'x': 1}, {'x': 2}], 'b': {'x': 1}, 'c': {'x': 2}}
    assert parse_yaml('base: &b {x: 1}\nother: {<<: *b, y: 2}\n', ValueError, 's')[
        'other'] == {'x': 1, 'y': 2}


def test_shipped_policies_load_and_match_their_configs():
    for name in ('default', 'paper', 'fail_safe_unaware', 'arm'):
        config = load_config(shipped_config_path(name))
        policy = load_policy(share_dir() / 'policies' / f'{name}.npz', config)
        states = 419_904 * (1 if config.queue is None else config.queue + 1)   # arm: a queue
        assert policy.policy.shape == (states,) and policy.policy.dtype == np.int8
        assert policy.meta['config_sha256'] == config.policy_hash
        assert policy.meta['converged'] and policy.meta['residual'] < 1e-6
    with pytest.raises(PolicyError, match='solved for configuration'):
        load_policy(share_dir() / 'policies' / 'paper.npz', load_config(DEFAULT))


def test_the_shipped_policy_is_found_for_its_configuration():
    """No policy named: the shipped one solved for the configuration, else default.npz (whose
    check then says what to solve)."""
    from hrc_ros.core.mdp.policy import default_policy_path
    for name in ('default', 'paper', 'fail_safe_unaware', 'arm'):
        path = default_policy_path(load_config(shipped_config_path(name)))
        assert path.name == f'{name}.npz'
        load_policy(path, load_config(shipped_config_path(name)))
    other = load_config(DEFAULT, overrides={'solver': {'gamma': 0.9}})
    assert default_policy_path(other).name == 'default.npz'
    with pytest.raises(PolicyError, match='solved for configuration'):
        load_policy(default_policy_path(other), other)


def test_shipped_default_policy_is_a_fresh_solve():
    """policies/default.npz: action for action, and value for value, what a solve from zero
    gives today."""
    config = load_config(shipped_config_path('default'))
    fresh = solve(HRCModel(config))
    shipped = load_policy(default_policy_path(config), config)
    np.testing.assert_array_equal(shipped.policy, fresh.policy)
    np.testing.assert_allclose(shipped.value, fresh.value, atol=1e-9)


@pytest.mark.parametrize('name', ['default', 'arm'])
def test_shipped_policy_is_the_solution_of_todays_model(name):
    """policies/default.npz and, with the arm's keys (the kernel's dp_paused and dm_paused),
    policies/arm.npz: today's Bellman update leaves their values within eta and their
    policies greedy (reference.assert_shipped_policy_solves_todays_model; for the default
    this holds alongside the fresh solve above)."""
    assert_shipped_policy_solves_todays_model(name)


@pytest.fixture(scope='module')
def small(tmp_path_factory):
    config = load_config(DEFAULT, overrides={'model': {'rho': 1, 'sigma': 1}})
    path = tmp_path_factory.mktemp('pol') / 'small.npz'
    save_policy(path, solve(HRCModel(config), sweeps=5), config)
    return config, path


def test_corrupt_and_foreign_policy_files_are_refused(tmp_path, small):
    config, good = small
    assert load_policy(good, config).policy.size == HRCModel(config).n_states
    with pytest.raises(PolicyError, match='does not exist'):
        load_policy(tmp_path / 'nope.npz', config)
    junk = tmp_path / 'junk.npz'
    junk.write_bytes(b'not a zip at all' * 10)
    with pytest.raises(PolicyError, match='corrupt'):
        load_policy(junk, config)
    truncated = tmp_path / 'truncated.npz'
    truncated.write_bytes(good.read_bytes()[:2000])
    with pytest.raises(PolicyError, match='hrc-solve'):
        load_policy(truncated, config)
    partial = tmp_path / 'partial.npz'
    np.savez(partial, policy=np.zeros(3, np.int8))
    with pytest.raises(PolicyError, match='missing meta, value'):
        load_policy(partial, config)
    wrong_dtype = tmp_path / 'dtype.npz'
    with np.load(good) as a:
        np.savez(wrong_dtype, policy=a['policy'].astype(np.int64), value=a['value'],
                 meta=a['meta'])
    with pytest.raises(PolicyError, match='int8'):
        load_policy(wrong_dtype, config)
    with pytest.raises(PolicyError, match=str(good.name)):
        load_policy(good, load_config(DEFAULT))  # solved for rho = sigma = 1
    assert zipfile.is_zipfile(good)


def crafted_policy(path, good, meta=None, policy=None, raw_member=None):
    """A policy file built from `good` with parts replaced (a crafted, untrusted file)."""
    with np.load(good) as archive:
        arrays = {name: archive[name] for name in archive.files}
    if meta is not None:
        arrays['meta'] = np.array(meta)
    if policy is not None:
        arrays['policy'] = policy
    np.savez(path, **arrays)
    if raw_member is not None:      # replace one member with raw .npy bytes
        name, data = raw_member
        rebuilt = path.with_suffix('.tmp')
        with zipfile.ZipFile(path) as old, zipfile.ZipFile(rebuilt, 'w') as new:
            for info in old.infolist():
                new.writestr(info.filename, data if info.filename == name + '.npy'
                             else old.read(info))
        rebuilt.replace(path)
    return path


def huge_header(elements: int) -> bytes:
    """An .npy whose header claims `elements` int8 values, with almost no data after it."""
    header = {'descr': '|i1', 'fortran_order': False, 'shape': (elements,)}
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(out, header)
    return out.getvalue() + b'\0' * 64


def test_crafted_policy_files_are_refused_before_they_are_read(tmp_path, small):
    """Issue 13: each of these gave a traceback (or a 1 TiB allocation) instead of a refusal."""
    config, good = small
    meta = json.loads(str(np.load(good)['meta']))
    deep = '[' * 100_000 + ']' * 100_000
    cases = {
        'deep': crafted_policy(tmp_path / 'deep.npz', good, meta=deep),
        'sha_type': crafted_policy(tmp_path / 'sha.npz', good,
                                   meta=json.dumps({**meta, 'config_sha256': 12345})),
        'not_object': crafted_policy(tmp_path / 'list.npz', good, meta='[1, 2, 3]'),
        'huge': crafted_policy(tmp_path / 'huge.npz', good,
                               raw_member=('policy', huge_header(2 ** 40))),
        'long_meta': crafted_policy(tmp_path / 'long.npz', good, meta=' ' * (2 << 20)),
    }
    reasons = {'deep': 'meta', 'sha_type': 'config_sha256 must be 64 hex digits',
               'not_object': 'JSON object', 'huge': 'holds 1099511627776 states',
               'long_meta': 'at most'}
    for name, path in cases.items():
        for checked_against in (config, None):
            with pytest.raises(PolicyError, match=reasons[name]):
                load_policy(path, checked_against)
    # the command line says it in one line and exits 2, as for any refused file
    proc = subprocess.run([sys.executable, '-m', 'hrc_ros.tools.simulate', '--policy',
                           str(cases['huge']), '--out', str(tmp_path / 'sim')],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert 'holds 1099511627776 states' in proc.stderr


def test_hrc_solve_cli(tmp_path):
    config = write_config(tmp_path, lambda d: d['model'].update(rho=1, sigma=1))
    out = tmp_path / 'p.npz'
    proc = subprocess.run([sys.executable, '-m', 'hrc_ros.tools.solve', '--config', str(config),
                           '-o', str(out), '--every', '50'], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert 'sweep   50  residual' in proc.stdout and 'converged after 280 sweeps' in proc.stdout
    meta = json.loads(str(np.load(out)['meta']))
    assert meta['sweeps'] == 280 and meta['config']['model']['rho'] == 1
    bad = write_config(tmp_path, lambda d: d['solver'].update(gamma=2))
    proc = subprocess.run([sys.executable, '-m', 'hrc_ros.tools.solve', '--config', str(bad),
                           '-o', str(out)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and 'solver.gamma' in proc.stderr
    assert 'Traceback' not in proc.stderr
