"""The whole learning loop in processes, as a user runs it (docs/LEARNING.md):

1. `hrc-case-study` runs the four node processes and records a bag, with a simulated human
   who declines every request (`--faults decline:1-24`);
2. `hrc-fit` fits the bag into a configuration (it learns that requests are refused, so its
   policy stops asking where the default asks);
3. `hrc-solve` solves it;
4. the suite runs again (four processes, a stream of tasks); after a few epochs the test sets,
   through rclpy's parameter service client as `ros2 param set` does, the belief estimator's
   `config`, then the decision node's `config` and `policy`.

Checked from what the processes publish: every epoch has its signal and one action, none
decided late or without its inputs; before the swap the actions are the default policy's
choice for the belief and the state each epoch had, from the swap epoch on the fitted
policy's, and on at least one of those epochs the two differ (so the check can tell them
apart); the decision node flags the estimator while the two run different configurations and
stops when they agree.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray, UInt32
from test_suite_multiprocess import Listener

from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTIONS, HRCModel
from hrc_ros.core.mdp.policy import load_policy
from hrc_ros.core.learning.recordings import place_in_epochs
from hrc_ros.core.decision.selection import ActionSelector
from hrc_ros.ros import conversions as conv
from hrc_ros.ros.processes import NodeProcesses

EPOCH_PERIOD = 0.5
BEFORE = 5          # epochs with the default policy before the parameters are set
AFTER = 10          # epochs with the fitted policy before the test stops, at least
MAX_AFTER = 30      # ... and at most, while none of them tells the two policies apart
DEADLINE = 120.0
NODES = ('task_manager', 'belief_estimator', 'cell_sim')
PARAMS = """\
/**:
  ros__parameters:
    config: ''
decision:
  ros__parameters:
    policy: '{policy}'
    selector: paper
    epoch_period: {period}
    input_timeout: 0.4
    stale_timeout: 3.0
    min_epoch_subscribers: 3
task_manager:
  ros__parameters:
    initial_task: [1, 1, 3]
    schedule: [{schedule}]
cell_sim:
  ros__parameters:
    seed: 5
    initial_emotions: [1, 1]
    initial_distance: 2
"""


def tool(name: str, *args, timeout=180.0) -> str:
    script = Path(sys.executable).parent / name
    result = subprocess.run([str(script), *map(str, args)], capture_output=True, text=True,
                            timeout=timeout)
    assert result.returncode == 0, f'{name} failed:\n{result.stdout[-3000:]}{result.stderr}'
    return result.stdout


class Watcher(Listener):
    """The multi-process test's listener, plus: epoch signals and beliefs with their source
    timestamps, every status, and a parameter client per node."""

    def __init__(self):
        super().__init__()
        self.signals: list = []
        self.beliefs: list = []
        self.statuses: list = []
        deep = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)

        def stamped(store, convert):
            def on_message(msg, info):
                store.append((int(info['source_timestamp']), convert(msg)))
            return on_message

        self.node.create_subscription(UInt32, 'hrc/epoch',
                                      stamped(self.signals, conv.epoch_from_msg),
                                      QoSProfile(depth=100,
                                                 reliability=ReliabilityPolicy.RELIABLE))
        self.node.create_subscription(Float64MultiArray, 'hrc/belief',
                                      stamped(self.beliefs, conv.belief_from_msg), deep)
        self.clients = {name: AsyncParameterClient(self.node, name)
                        for name in ('decision', 'belief_estimator')}

    def _on_diagnostics(self, msg) -> None:
        super()._on_diagnostics(msg)
        for status in msg.status:
            self.statuses.append((status.name, status.level, status.message,
                                  conv.diagnostic_values(status)))

    def set(self, node: str, name: str, value: str):
        client = self.clients[node]
        assert client.wait_for_services(timeout_sec=10.0), f'{node} has no parameter services'
        future = client.set_parameters([Parameter(name, value=value)])
        assert self.spin_until(future.done, 10.0), f'setting {node}.{name} timed out'
        return future.result().results[0]


def belief_of(k: int, decision: dict, placed: dict) -> np.ndarray:
    """The belief epoch k was decided on: the one the listener placed in epoch k when it is
    exactly one and is the one the decision status reports (rounded to 1e-4 there), else the
    reported one. hrc/belief is latched with depth 1, so a listener that spins late under load
    loses a belief the next one overwrote before it was delivered: placed by timestamps, epoch
    k then had none (KeyError) or the neighbour's (issue 37)."""
    reported = np.array([float(v) for v in re.findall(r'[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?',
                                                      decision['belief'])])
    got = placed.get(('belief', k), [])
    if len(got) == 1 and np.allclose(got[0][1], reported, atol=1.5e-4):
        return got[0][1]
    return reported / reported.sum()       # the status's is rounded


def differing(watcher, old, new, first: int, last: int) -> int:
    """The epochs first..last (decided so far) whose state the fitted and the default policy
    would decide differently."""
    placed = place_in_epochs(watcher.signals, [('belief', b, t) for t, b in watcher.beliefs])
    count = 0
    for k in range(first, last + 1):
        decision = watcher.decisions.get(k)
        if decision is None or decision['observable'] == 'none':
            continue
        belief = belief_of(k, decision, placed)
        x = tuple(int(v) for v in decision['observable'].strip('[]()').split(','))
        count += old.select(belief, x).action != new.select(belief, x).action
    return count


def test_record_fit_solve_and_swap_the_running_suite(tmp_path, policy_path, ros_domain_id):
    # 1-3: record, fit, solve, each with its command line
    tool('hrc-case-study', '--out', tmp_path / 'run', '--epochs', 24, '--epoch-period', 0.25,
         '--seed', 3, '--policy', policy_path, '--faults', 'decline:1-24')
    fitted_config = tmp_path / 'fitted.yaml'
    tool('hrc-fit', tmp_path / 'run' / 'bag', '-o', fitted_config, '--bootstrap', 0, '-q')
    fitted_policy = tmp_path / 'fitted.npz'
    tool('hrc-solve', '--config', fitted_config, '-o', fitted_policy, '-q')
    default = load_config(Path(__file__).resolve().parent.parent / 'config' / 'default.yaml')
    fitted = load_config(fitted_config)
    old = ActionSelector(HRCModel(default), load_policy(policy_path, default))
    new = ActionSelector(HRCModel(fitted), load_policy(fitted_policy, fitted))

    # 4: the suite again, with a task every few epochs
    schedule = ', '.join(f'"{k}:{1 + k % 2},{1 + k % 2},{k % 4}"' for k in range(3, 40, 3))
    params = tmp_path / 'suite.yaml'
    params.write_text(PARAMS.format(policy=policy_path, period=EPOCH_PERIOD, schedule=schedule))
    (tmp_path / 'logs').mkdir()
    suite = NodeProcesses(tmp_path / 'logs', [params])
    watcher = Watcher()
    try:
        for node in NODES:
            suite.start(f'{node}_node')
        assert watcher.spin_until(lambda: watcher.nodes_up(NODES) or suite.dead(), 30), \
            suite.logs()
        suite.start('decision_node')
        assert watcher.spin_until(lambda: len(watcher.decisions) >= BEFORE or suite.dead(),
                                  DEADLINE), suite.logs()
        # the estimator first: until the decision node follows, it runs another configuration
        assert watcher.set('belief_estimator', 'config', str(fitted_config)).successful
        assert watcher.spin_until(lambda: any(
            d.get('estimator_config_matches') == 'false' for d in watcher.decisions.values())
            or suite.dead(), 30), suite.logs()
        # then the decision node, one parameter at a time as `ros2 param set` does
        result = watcher.set('decision', 'policy', str(fitted_policy))
        assert not result.successful and 'set config first' in result.reason
        assert watcher.set('decision', 'config', str(fitted_config)).successful
        assert watcher.set('decision', 'policy', str(fitted_policy)).successful
        swaps = [s for s in watcher.statuses if s[0] == 'decision: policy' and s[1] == b'\x00']

        def swapped():
            swaps[:] = [s for s in watcher.statuses
                        if s[0] == 'decision: policy' and s[1] == b'\x00']
            return bool(swaps) or bool(suite.dead())
        assert watcher.spin_until(swapped, 30) and swaps, suite.logs()
        first = int(swaps[0][3]['epoch'])

        def decided(last: int) -> bool:
            # the epoch signals (hrc/epoch), the decisions (diagnostics) and the actions
            # (hrc/action) come on three topics from two nodes, in no order between them at
            # the listener: wait for all three (a run stopped with the last action not yet
            # taken, 16 of 17; one with the last epoch's signal not yet taken, its decision
            # and action in, at load 6 with two test workers, 2026-12-07)
            signalled = {k for _, k in watcher.signals}
            return (all(k in watcher.decisions and k in signalled for k in range(1, last + 1))
                    and len(watcher.actions) >= last)
        # AFTER epochs with the fitted policy, and more (up to MAX_AFTER) until one of them is
        # an epoch where the two policies differ: when the swap lands depends on the load
        # (the parameter sets take longer), and a window of AFTER epochs from a late swap could
        # hold none (issue 37: "chose alike on every epoch" at load 21)
        last = first + AFTER
        assert watcher.spin_until(lambda: decided(last) or suite.dead(), DEADLINE), \
            suite.logs()
        while not differing(watcher, old, new, first, last) and last < first + MAX_AFTER:
            last += 1
            assert watcher.spin_until(lambda upto=last: decided(upto) or suite.dead(),
                                      DEADLINE), suite.logs()
        assert not suite.dead(), suite.logs()
    finally:
        suite.stop(10.0)
        watcher.close()

    # every epoch signalled once, in order, and decided on time with its inputs
    epochs = [k for _, k in sorted(watcher.signals)]
    assert epochs[:last] == list(range(1, last + 1))
    assert len(watcher.actions) >= last
    placed = place_in_epochs(watcher.signals, [('belief', b, t) for t, b in watcher.beliefs])
    differ = 0
    for k in range(1, last + 1):
        decision = watcher.decisions[k]
        assert decision['input_timed_out'] == 'false', (k, decision)
        assert decision['observable'] != 'none' and decision['selected'] != 'none', (k, decision)
        x = tuple(int(v) for v in decision['observable'].strip('[]()').split(','))
        belief = belief_of(k, decision, placed)
        want_old = ACTIONS[old.select(belief, x).action]
        want_new = ACTIONS[new.select(belief, x).action]
        chosen = decision['selected']
        if k < first:
            assert chosen == want_old and decision['policy_file'] == policy_path, (k, decision)
        else:
            assert chosen == want_new, (k, first, chosen, want_new, want_old, decision)
            assert decision['policy_file'] == str(fitted_policy)
            assert decision['config'] == str(fitted_config)
            differ += want_new != want_old
        assert watcher.actions[k - 1] == (chosen if x[-1] > 0 else 'dn')
    assert differ >= 1, 'the fitted and the default policy chose alike on every epoch'
    assert watcher.decisions[last]['estimator_config_matches'] == 'true'
    flagged = [s for s in watcher.statuses if s[0] == 'decision: configuration']
    assert flagged and all(int(s[3]['epoch']) < first for s in flagged)
    assert np.isfinite(first) and first > BEFORE
