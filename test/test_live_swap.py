"""The live swap of a policy and a configuration in the running nodes (in-process, real rclpy).

`ros2 param set /decision policy <file>` and `config`: a missing, corrupt or mismatched file is
refused with the reason and the old policy keeps deciding; a configuration set alone waits,
staged, for a policy solved for it; an accepted pair is loaded off the epoch path and decides
from the next epoch boundary, without a missed or late epoch; a pair whose arrays turn out
damaged is refused at the boundary and the parameters return to the pair in use. The belief
estimator takes a new `config` the same way, announces it on `hrc/estimator_config`, and the
decision node flags an estimator running another configuration.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import String
from test_nodes import TASK_1, Decision, Estimator

from hrc_ros.core.pomdp.belief import BeliefFilter
from hrc_ros.core.model import ACTIONS, TASK_VARIABLES, HRCModel
from hrc_ros.core.mdp.policy import load_policy, save_policy
from hrc_ros.core.decision.selection import ActionSelector
from hrc_ros.core.mdp.solver import solve
from hrc_ros.ros import conversions as conv
from hrc_ros.ros import qos

OTHER_MODEL = {'model': {
    'p_accept': [0.05, 0.35, 0.7],
    'p_delta': [[0.05, 0.65, 0.30], [0.05, 0.55, 0.40], [0.02, 0.38, 0.60]],
    'emotion': {'motivate': {'em': [0.10, 0.60, 0.30], 'ea': [0.05, 0.80, 0.15]}}},
    'observation': {'likelihood': [[0.6] * 3 + [0.3] * 3 + [0.1] * 3,
                                   [0.3] * 3 + [0.4] * 3 + [0.3] * 3,
                                   [0.1] * 3 + [0.3] * 3 + [0.6] * 3]}}


@pytest.fixture(scope='module')
def other(default_config, tmp_path_factory):
    """Another configuration of the same cell, written to a file, and its policy."""
    import yaml
    folder = tmp_path_factory.mktemp('other')
    config_path = folder / 'other.yaml'
    config_path.write_text(yaml.safe_dump(default_config.with_overrides(OTHER_MODEL).data))
    from hrc_ros.core.config import load_config
    config = load_config(config_path)
    policy_path = save_policy(folder / 'other.npz', solve(HRCModel(config)), config)
    return config, str(config_path), str(policy_path)


def differing_inputs(default_config, policy_path, other):
    """(belief, task, d) on which the default policy and the other one choose differently."""
    config, _, other_policy = other
    old = ActionSelector(HRCModel(default_config), load_policy(policy_path, default_config))
    new = ActionSelector(HRCModel(config), load_policy(other_policy, config))
    for h in range(9):
        belief = np.eye(9)[h] * 0.91 + 0.01
        for tx in range(4):
            for d in (1, 2, 3):
                task = dict(TASK_1, tx=tx)
                x = tuple(task[n] for n in TASK_VARIABLES) + (d,)
                a, b = old.select(belief, x).action, new.select(belief, x).action
                if a != b and 'dn' not in (ACTIONS[a], ACTIONS[b]):
                    return belief, task, d, ACTIONS[a], ACTIONS[b]
    raise AssertionError('the two policies agree everywhere tried')


def statuses(graph, what, since=0):
    return [s for s in graph.statuses[since:] if s.name == f'decision: {what}']


def test_a_missing_corrupt_or_mismatched_policy_is_refused_and_the_old_one_decides(
        graph, policy_path, other_config_policy_path, tmp_path):
    dec = Decision(graph, policy_path)
    dec.run(1)
    node = dec.node
    corrupt = tmp_path / 'corrupt.npz'
    corrupt.write_bytes(b'PK\x03\x04 not really a zip archive')
    cases = [('/tmp/hrc-no-such-policy.npz', 'does not exist'),
             (str(corrupt), 'is corrupt or not a policy file'),
             (other_config_policy_path, 'was solved for configuration')]
    for path, reason in cases:
        result = node.set_parameters([Parameter('policy', value=path)])[0]
        assert not result.successful
        assert result.reason.startswith('policy refused: ') and reason in result.reason
        assert node.get_parameter('policy').value == policy_path
    before = len(dec.actions)
    dec.run(before + 2)
    assert node.policy.path == policy_path and node.loader.take() is None


def test_a_config_waits_for_its_policy_then_both_decide_from_an_epoch_boundary(
        graph, default_config, policy_path, other):
    config, config_path, other_policy = other
    belief, task, d, old_action, new_action = differing_inputs(default_config, policy_path,
                                                               other)
    dec = Decision(graph, policy_path, respond=lambda k: dec.inputs(task, d, belief))
    assert dec.run(2)[-1] == old_action
    node = dec.node
    # config alone: accepted, but staged (the policy in use was not solved for it)
    assert node.set_parameters([Parameter('config', value=config_path)])[0].successful
    assert graph.spin_until(lambda: statuses(graph, 'policy'))
    staged = statuses(graph, 'policy')[-1]
    assert staged.level == conv.DiagnosticStatus.WARN and 'is set but not in use' in \
        staged.message
    epoch = node.epoch
    assert graph.spin_until(lambda: node.epoch >= epoch + 2)
    assert dec.actions[-1].data == old_action and node.config.source != config_path
    assert conv.diagnostic_values(dec.status(node.epoch - 1))['config_staged'] == config_path
    # then the policy solved for it: swapped in at the next epoch boundary
    assert node.set_parameters([Parameter('policy', value=other_policy)])[0].successful

    def swapped():
        return [s for s in statuses(graph, 'policy') if s.level == conv.DiagnosticStatus.OK]
    assert graph.spin_until(swapped)
    swap = swapped()[-1]
    assert node.policy.path == other_policy and other_policy in swap.message
    first = int(conv.diagnostic_values(swap)['epoch'])
    assert graph.spin_until(lambda: node.epoch >= first + 2)
    epochs = [m.data for m in dec.epochs]
    actions = [m.data for m in dec.actions]
    assert epochs == list(range(1, len(epochs) + 1))
    assert len(actions) >= first + 1
    assert actions[first - 2] == old_action and actions[first - 1:first + 1] == [new_action] * 2
    for k in range(1, first + 2):                 # no epoch missed, none decided late
        values = conv.diagnostic_values(dec.status(k))
        assert values['faults'] == 'none' and values['input_timed_out'] == 'false'
    values = conv.diagnostic_values(dec.status(first))
    assert values['policy_file'] == other_policy and values['config'] == config_path
    assert values['config_staged'] == 'none'


def test_a_policy_whose_arrays_are_damaged_is_refused_at_the_boundary(graph, policy_path,
                                                                      default_config,
                                                                      tmp_path):
    with np.load(policy_path) as archive:
        meta = json.loads(str(archive['meta']))
        value = archive['value']
        actions = archive['policy']
    damaged = tmp_path / 'damaged.npz'
    actions = actions.copy()
    actions[123] = 9                        # no such action: only reading the array shows it
    np.savez_compressed(damaged, policy=actions, value=value, meta=np.array(json.dumps(meta)))
    dec = Decision(graph, policy_path)
    dec.run(1)
    node = dec.node
    since = len(graph.statuses)
    # its headers and meta are right, so the quick check passes; the full check does not
    assert node.set_parameters([Parameter('policy', value=str(damaged))])[0].successful
    assert graph.spin_until(lambda: any(s.level == conv.DiagnosticStatus.ERROR
                                        for s in statuses(graph, 'policy', since)))
    refused = [s for s in statuses(graph, 'policy', since)
               if s.level == conv.DiagnosticStatus.ERROR][-1]
    assert 'policy holds action indices outside 0..7' in refused.message
    assert node.get_parameter('policy').value == policy_path      # back to the pair in use
    assert node.policy.path == policy_path
    count = len(dec.actions)
    dec.run(count + 1)


def test_the_decision_node_flags_an_estimator_on_another_configuration(graph, policy_path,
                                                                       default_config, other):
    config = other[0]
    dec = Decision(graph, policy_path)
    announce = graph.probe.create_publisher(String, 'hrc/estimator_config', qos.LATCHED)
    announce.publish(conv.config_identity_to_msg(config.belief_hash, 'other.yaml'))
    assert graph.spin_until(lambda: statuses(graph, 'configuration'))
    flag = statuses(graph, 'configuration')[-1]
    assert flag.level == conv.DiagnosticStatus.WARN and 'runs other.yaml' in flag.message
    epoch = int(conv.diagnostic_values(flag)['epoch'])
    values = conv.diagnostic_values(dec.status(epoch))
    assert values['estimator_config_matches'] == 'false'
    announce.publish(conv.config_identity_to_msg(default_config.belief_hash, 'default.yaml'))
    assert graph.spin_until(lambda: dec.node.estimator_config[1] == 'default.yaml')
    since = len(graph.statuses)
    k = dec.node.epoch
    assert graph.spin_until(lambda: dec.node.epoch >= k + 3)
    assert conv.diagnostic_values(dec.status(k + 2))['estimator_config_matches'] == 'true'
    assert not statuses(graph, 'configuration', since)


def test_the_estimator_takes_a_new_config_at_the_next_epoch_and_announces_it(
        graph, default_config, other):
    config, config_path, _ = other
    est = Estimator(graph)
    announced = graph.collect(String, 'hrc/estimator_config', qos.LATCHED)
    assert graph.spin_until(lambda: announced)
    assert conv.config_identity_from_msg(announced[-1])[0] == default_config.belief_hash
    bad = est.node.set_parameters([Parameter('config', value='/tmp/hrc-none.yaml')])[0]
    assert not bad.successful and bad.reason.startswith('config refused: ')
    est.motion(1)
    est.body(2)
    belief = est.epoch(1)
    assert est.node.set_parameters([Parameter('config', value=config_path)])[0].successful
    assert graph.spin_until(lambda: est.node.loader._done is not None)   # loaded, not yet used
    assert est.node.config.source != config_path
    est.act('mh')
    est.motion(3)
    est.body(2)
    after = est.epoch(2)
    new_filter = BeliefFilter(HRCModel(config))
    np.testing.assert_allclose(after, new_filter.update(belief, 'mh', 3), atol=1e-12)
    assert graph.spin_until(lambda: conv.config_identity_from_msg(announced[-1])
                            == (config.belief_hash, config_path))
    assert est.node.config.source == config_path


def test_a_live_config_of_another_cell_size_is_refused(graph, policy_path, default_config,
                                                        tmp_path):
    import yaml
    small = tmp_path / 'small.yaml'
    small.write_text(yaml.safe_dump(default_config.with_overrides(
        {'model': {'rho': 1, 'sigma': 1}}).data))
    node = Decision(graph, policy_path).node
    result = node.set_parameters([Parameter('config', value=str(small))])[0]
    assert not result.successful and 'restart the nodes to change the state space' in \
        result.reason



def test_the_decision_node_and_the_estimator_agree_on_every_swap(graph, policy_path,
                                                                 default_config, other,
                                                                 tmp_path):
    """Issue 17: the decision node refused a configuration with another rho/sigma, the belief
    estimator took it and then checked task states against the new sizes. One rule
    (`core.swap.check_swap`) decides for both: the same verdict, the same reason."""
    import yaml
    small = tmp_path / 'small.yaml'
    small.write_text(yaml.safe_dump(default_config.with_overrides(
        {'model': {'rho': 1, 'sigma': 1}}).data))
    broken = tmp_path / 'broken.yaml'
    broken.write_text('model: [unclosed\n')
    cases = {'same cell, other model': other[1], 'another cell size': str(small),
             'missing': str(tmp_path / 'none.yaml'), 'not YAML': str(broken),
             'the one in use': ''}
    decision = Decision(graph, policy_path).node
    estimator = Estimator(graph).node
    for case, path in cases.items():
        verdicts = []
        for node in (decision, estimator):
            before = node.get_parameter('config').value
            result = node.set_parameters([Parameter('config', value=path)])[0]
            verdicts.append((result.successful, result.reason))
            if result.successful:
                node.set_parameters([Parameter('config', value=before)])
        assert verdicts[0] == verdicts[1], (case, verdicts)
        assert verdicts[0][0] == (case in ('same cell, other model', 'the one in use')), case
    assert estimator.model.rho == decision.model.rho == default_config.rho


def test_a_pomdp_selector_swaps_in_the_pomdp_policy_named_with_the_pair(graph, policy_path,
                                                                       tmp_path):
    """pomdp_policy: the POMDP policy of the pomdp and fib selectors, by path, set live with
    config and policy (hrc-fleet --apply's order: config, pomdp_policy, policy); staged until
    the set is whole, swapped in at an epoch boundary, and reported by the decision status;
    one solved for another configuration, or missing, is refused and the old one decides."""
    import shutil
    from hrc_ros.core.paths import share_dir, shipped_config_path
    config_path = str(shipped_config_path('fail_safe_unaware'))
    new_policy = str(share_dir() / 'policies' / 'fail_safe_unaware.npz')
    new_pomdp = tmp_path / 'fitted_pomdp.npz'     # a file of its own, not policies/pomdp/'s
    shutil.copyfile(share_dir() / 'policies' / 'pomdp' / 'fail_safe_unaware.npz', new_pomdp)
    new_pomdp = str(new_pomdp)
    default_pomdp = str(share_dir() / 'policies' / 'pomdp' / 'default.npz')
    dec = Decision(graph, policy_path, selector='pomdp')
    dec.run(1)
    node = dec.node
    assert node.selector.pomdp.path == default_pomdp       # '': the shipped one for config

    def in_use():
        return (node.get_parameter('policy_in_use').value,
                node.get_parameter('pomdp_policy_in_use').value)
    # what `ros2 param get` shows: pomdp_policy is '', the file in use is named (issue 37)
    assert node.get_parameter('pomdp_policy').value == ''
    assert in_use() == (str(Path(policy_path).resolve()), default_pomdp)
    refused = node.set_parameters([Parameter('pomdp_policy_in_use', value=new_pomdp)])[0]
    assert not refused.successful and 'read-only' in refused.reason
    for name, value in (('config', config_path), ('pomdp_policy', new_pomdp)):
        assert node.set_parameters([Parameter(name, value=value)])[0].successful, name
        assert node.config.source != config_path           # staged: not whole yet
    assert node.set_parameters([Parameter('policy', value=new_policy)])[0].successful

    def swapped():
        return [s for s in statuses(graph, 'policy') if s.level == conv.DiagnosticStatus.OK]
    assert graph.spin_until(swapped)
    values = conv.diagnostic_values(swapped()[-1])
    assert values['policy_file'] == new_policy and values['pomdp_policy_file'] == new_pomdp
    assert f'and POMDP policy {new_pomdp} (' in swapped()[-1].message      # the new one named
    assert swapped()[-1].message.endswith(f'and POMDP policy {default_pomdp}')
    assert node.selector.pomdp.path == new_pomdp and node.selector.method == 'pomdp'
    assert in_use() == (new_policy, new_pomdp)
    first = int(values['epoch'])
    assert graph.spin_until(lambda: node.epoch >= first + 2)
    decided = conv.diagnostic_values(dec.status(first + 1))
    assert decided['pomdp_policy_file'] == new_pomdp and decided['faults'] == 'none'
    # one solved for another configuration, or none at all: refused, the parameter kept
    for value, reason in ((default_pomdp, 'was solved for configuration'),
                          (str(tmp_path / 'none.npz'), 'does not exist')):
        result = node.set_parameters([Parameter('pomdp_policy', value=value)])[0]
        assert not result.successful and result.reason.startswith('pomdp_policy refused: ')
        assert reason in result.reason
        assert node.get_parameter('pomdp_policy').value == new_pomdp
    count = len(dec.actions)
    dec.run(count + 1)
    assert node.selector.pomdp.path == new_pomdp


def test_a_set_refused_at_the_boundary_goes_back_whole_with_the_selector(graph, policy_path,
                                                                         tmp_path):
    """selector pomdp and a pomdp_policy whose meta is right but whose arrays are damaged, in
    one set: accepted by the quick check, refused by the full load at the boundary; the
    parameters go back in one atomic set to the set in use and the selector it decides with
    (set back one at a time, each was checked against the others not yet back: the node
    restarted the failed load every epoch, an ERROR each time, and kept selector pomdp)."""
    from hrc_ros.core.paths import share_dir
    shipped = share_dir() / 'policies' / 'pomdp' / 'default.npz'
    with np.load(shipped) as archive:
        arrays = {name: archive[name] for name in archive.files}
    arrays['alpha_action'] = arrays['alpha_action'].copy()
    arrays['alpha_action'][5] = 9           # no such action: only reading the array shows it
    damaged = tmp_path / 'damaged_pomdp.npz'
    np.savez_compressed(damaged, **arrays)
    dec = Decision(graph, policy_path)
    dec.run(1)
    node = dec.node
    since = len(graph.statuses)
    result = node.set_parameters_atomically([Parameter('selector', value='pomdp'),
                                             Parameter('pomdp_policy', value=str(damaged))])
    assert result.successful, result.reason

    def errors():
        return [s for s in statuses(graph, 'policy', since)
                if s.level == conv.DiagnosticStatus.ERROR]
    assert graph.spin_until(errors)
    assert 'alpha_action holds action indices outside' in errors()[0].message
    epoch = node.epoch
    assert graph.spin_until(lambda: node.epoch >= epoch + 3)
    assert len(errors()) == 1                  # refused once, not again every epoch
    assert node.get_parameter('selector').value == 'paper'
    assert node.get_parameter('pomdp_policy').value == ''
    assert node.selector.method == 'paper' and node.selector.pomdp is None
    values = conv.diagnostic_values(dec.status(epoch + 2))
    assert values['selector'] == 'paper' and values['policy_file'] == policy_path


def test_a_pomdp_policy_named_at_start_up_is_checked_whatever_the_selector(graph, policy_path):
    """Set live, a pomdp_policy for another configuration (or not a POMDP policy at all) is
    refused with the selector paper too; at start-up it was taken silently and found wrong
    only when the selector was switched."""
    from hrc_ros.core.paths import share_dir
    from hrc_ros.ros.node_support import StartupError
    from hrc_ros.ros.nodes.decision_node import DecisionNode
    for value, reason in ((policy_path, 'is not a POMDP policy file'),
                          (str(share_dir() / 'policies' / 'pomdp' / 'fail_safe_unaware.npz'),
                           'was solved for configuration')):
        with pytest.raises(StartupError, match=f'pomdp_policy: .*{reason}'):
            graph.start(DecisionNode, policy=policy_path, pomdp_policy=value)
