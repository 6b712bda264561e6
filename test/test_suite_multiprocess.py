"""The four nodes as four processes, started as a user starts them, talking over real DDS.

Each node runs from its console script with ``--ros-args --params-file <yaml>`` holding the
paper's case study (MODEL.md 7, `core.study.simulation.case_study()` as node parameters): task 1
(1, 1, 3) at epoch 1, task 2 (2, 2, 1) released at 9, task 3 (2, 2, 2) at 16, a calm unmotivated
human (em = ea = 0) at the inner circle; seed 8 (the simulator's reference seed), a 0.5 s
epoch. The test process only listens: `hrc/action`,
`hrc/task_state`, the decision node's per-epoch /diagnostics (for d and the faults) and the
simulator's `hrc/sim/true_state` (for the hidden motivation). After 20 epochs it checks the
behaviours MODEL.md 7 asks for, and that the distributed loop took exactly the decisions of
the ROS-free simulator (`simulate`, same seed): the epoch protocol makes the loop's decisions
depend on the messages' content, not on their timing.

The processes run in their own process groups and are stopped by SIGINT to the group (what
Ctrl-C does), then SIGKILL if they linger, whatever the test's outcome.
"""

from __future__ import annotations

import time

import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String, UInt8MultiArray, UInt32

from hrc_ros.core.model import HRCModel
from hrc_ros.core.mdp.policy import load_policy
from hrc_ros.core.study.simulation import case_study, simulate
from hrc_ros.ros import conversions as conv
from hrc_ros.ros import qos
from hrc_ros.ros.launch_plan import scenario_parameters
from hrc_ros.ros.processes import NodeProcesses

EPOCHS = 20
EPOCH_PERIOD = 0.5       # with 0.4 s for an epoch's inputs: room for a scheduling stall
SEED = 8
DEADLINE = 90.0          # seconds for start-up plus 20 epochs (10 s of them)
STOP_TIMEOUT = 10.0
NODES = ('task_manager', 'belief_estimator', 'cell_sim')
OBSERVED = ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc', 'd')

PARAMS = """\
/**:
  ros__parameters:
    config: ''
    velocity_thresholds: [0.3, 0.8]
    safety_radii: [0.2, 0.6, 1.2]
    robot_reference_point: [0.0, 0.0, 0.0]
decision:
  ros__parameters:
    policy: '{policy}'
    selector: paper
    epoch_period: {period}
    input_timeout: 0.4
    stale_timeout: 3.0
    epoch_source: timer
cell_sim:
  ros__parameters:
    seed: {seed}
    sensor_rate: 50.0
"""


class Listener:
    """The test's own node: what the suite publishes, in arrival order."""

    def __init__(self):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('suite_listener', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.actions: list[str] = []
        self.task_states: list[dict] = []
        self.true_states: list[dict] = []
        self.decisions: dict[int, dict] = {}
        self.node.create_subscription(String, 'hrc/action',
                                      lambda m: self.actions.append(m.data), qos.RELIABLE)
        self.node.create_subscription(
            UInt8MultiArray, 'hrc/task_state',
            lambda m: self.task_states.append(conv.task_state_from_msg(m)), qos.RELIABLE)
        # Latched like the publisher, but a deep queue: a listener that wakes up late must not
        # lose a state to the next one (their count is the epoch).
        self.node.create_subscription(
            UInt8MultiArray, 'hrc/sim/true_state',
            lambda m: self.true_states.append(conv.true_state_from_msg(m)),
            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics,
                                      qos.RELIABLE)

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if status.name == 'decision: decision':
                values = conv.diagnostic_values(status)
                if values.get('epoch', '0') != '0':
                    self.decisions[int(values['epoch'])] = {'level': status.level, **values}

    def spin_until(self, predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def nodes_up(self, names) -> bool:
        return set(names) <= set(self.node.get_node_names())

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def processes(tmp_path, policy_path, ros_domain_id):
    """The (not yet started) node processes and the listener; always stopped at the end."""
    params = tmp_path / 'case_study.yaml'
    params.write_text(PARAMS.format(policy=policy_path, period=EPOCH_PERIOD, seed=SEED))
    scenario = tmp_path / 'scenario.yaml'       # the case study's one definition, the core's
    scenario.write_text(yaml.safe_dump(scenario_parameters(case_study())))
    suite = NodeProcesses(tmp_path, [scenario, params])
    listener = Listener()
    try:
        yield suite, listener
    finally:
        suite.stop(STOP_TIMEOUT)
        listener.close()


def observed_rows(listener):
    """Per epoch k = 1..EPOCHS: task state, d, action, and the human's em before the action."""
    rows = []
    for k in range(1, EPOCHS + 1):
        decision = listener.decisions[k]
        assert decision['observable'] != 'none', (
            f'epoch {k}: the decision node had no complete input set: {decision["faults"]}')
        observable = [int(v) for v in decision['observable'].strip('[]').split(',')]
        rows.append({**listener.task_states[k - 1], 'd': observable[-1],
                     'action': listener.actions[k - 1], 'fail_safe': decision['faults'],
                     # true_states[0] is the initial state; [k] follows the k-th reaction
                     'em': listener.true_states[k - 1]['em']})
    return rows


@pytest.mark.parametrize('stray_epoch', [False, True], ids=['clean', 'stray_epoch'])
def test_four_processes_run_the_case_study(processes, default_config, policy_path,
                                           stray_epoch):
    """With `stray_epoch`, a second writer puts one hrc/epoch of 4294967295 on the running cell
    at epoch 5 (issue 13: the followers then refused every real epoch and the robot sat in dn
    for good); the run must stay the simulator's, decision for decision."""
    suite, listener = processes
    deadline = time.monotonic() + DEADLINE
    # The decision node owns the clock: start it once the others are on the graph. A node
    # already running discovers a new one at once; the new decision node discovers them in
    # turn and holds epoch 1 until it has (see conftest.py on discovery speed).
    for node in NODES:
        suite.start(f'{node}_node')
    up = listener.spin_until(lambda: listener.nodes_up(NODES) or suite.dead(),
                             deadline - time.monotonic())
    assert up and not suite.dead(), suite.logs()
    suite.start('decision_node')
    if stray_epoch:
        assert listener.spin_until(lambda: len(listener.actions) >= 5 or suite.dead(),
                                   deadline - time.monotonic()), suite.logs()
        stray = listener.node.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
        assert listener.spin_until(lambda: stray.get_subscription_count() >= 2,
                                   deadline - time.monotonic())
        stray.publish(UInt32(data=4294967295))
    done = listener.spin_until(
        lambda: (len(listener.actions) >= EPOCHS and len(listener.task_states) >= EPOCHS
                 and len(listener.true_states) > EPOCHS
                 and all(k in listener.decisions for k in range(1, EPOCHS + 1)))
        or suite.dead(), deadline - time.monotonic())
    assert done and not suite.dead(), (
        f'{len(listener.actions)} actions, {len(listener.task_states)} task states, '
        f'{len(listener.true_states)} true states, {len(listener.decisions)} decisions '
        f'(from epoch {min(listener.decisions, default=None)}) after '
        f'{DEADLINE} s\n{suite.logs()}')

    rows = observed_rows(listener)
    actions = [row['action'] for row in rows]
    table = '\n'.join(f'{k:>2} {[row[n] for n in OBSERVED]} em={row["em"]} {row["action"]} '
                      f'{row["fail_safe"]}' for k, row in enumerate(rows, start=1))
    assert all(row['fail_safe'] == 'none' for row in rows if row['d'] > 0), table

    # Task 1 (joint, epochs from 1): mh before rh2 while motivation is low, no robot-alone
    # commitment, and it runs with ty = 3 until done.
    task1 = [i for i, row in enumerate(rows) if (row['tp'], row['tx']) == (1, 3)]
    a1 = [actions[i] for i in task1]
    assert task1[0] == 0 and 'rh2' in a1, table
    assert 'mh' in a1[:a1.index('rh2')], table
    assert 'ct' not in a1 and any(rows[i]['ty'] == 3 for i in task1), table
    assert all(rows[i]['ty'] in (0, 3) for i in task1), table

    # Between tasks the robot moves away (dp while d < 3) and stops (dn at d = 3).
    idle = [i for i, row in enumerate(rows) if row['tp'] == 0]
    assert idle, table
    assert all(actions[i] == ('dp' if rows[i]['d'] < 3 else 'dn') for i in idle), table
    assert any(actions[i] == 'dn' for i in idle), table

    # Task 2 (human only), released at 9: mh while the human is unmotivated, then rh1; the
    # robot never commits to it.
    task2 = [i for i, row in enumerate(rows) if (row['tp'], row['tx']) == (2, 1)]
    assert task2 and task2[0] >= 8, table
    open2 = [i for i in task2 if rows[i]['ty'] == 0]
    a2 = [actions[i] for i in open2]
    assert a2[-1] == 'rh1' and set(a2) <= {'mh', 'rh1', 'dp'}, table
    assert all(actions[i] == 'mh' for i in open2 if rows[i]['em'] == 0) or \
        rows[open2[0]]['em'] > 0, table
    assert all(rows[i]['ty'] in (0, 1) for i in task2), table

    # Task 3 (either), released at 16: the robot commits (ct) and works (nw) until done.
    task3 = [i for i, row in enumerate(rows) if (row['tp'], row['tx']) == (2, 2)]
    assert task3 and task3[0] >= 15, table
    a3 = [actions[i] for i in task3]
    assert a3[0] == 'ct' and 'nw' in a3 and set(a3[1:]) <= {'nw', 'dp'}, table
    assert all(rows[i]['ty'] == 2 for i in task3[1:]), table
    assert task3[-1] < EPOCHS - 1 and rows[task3[-1] + 1]['tp'] == 0, table   # done

    # The distributed loop decided exactly as the ROS-free simulator on the same seed.
    model = HRCModel(default_config)
    expected = simulate(model, load_policy(policy_path, default_config), case_study(),
                        seed=SEED).actions
    assert actions == expected, f'{table}\nsimulator: {expected}'

    # Ctrl-C (SIGINT to each process group) stops every node cleanly.
    codes = suite.stop(STOP_TIMEOUT)
    assert codes == {node: 0 for node in codes}, f'{codes}\n{suite.logs()}'
