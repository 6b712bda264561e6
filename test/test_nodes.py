"""The four nodes in-process with the real rclpy: one Context per test, a bounded spin loop.

Each test starts the node under test and a probe node in a fresh `rclpy.Context` (its own DDS
participant, in the session's private domain, see conftest.py) and spins one executor with
`spin_until(executor, predicate, timeout)`: no fixed sleeps. Before a message whose effect
depends on earlier ones (an epoch after joint states), the test spins until the node has
counted the earlier ones, because an executor does not order callbacks across topics.

Covered: the epoch protocol of each node against the ROS-free core; every fail-safe of the
decision node (missing, stale, malformed and late inputs, d = 0 -> dn with a /diagnostics
report); every malformed input of every node (dropped, a diagnostic, the node keeps working);
parameter validation at run time and at start-up; and, as a subprocess, the decision node's
refusal of a policy solved for another configuration.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import (Bool, Float64MultiArray, MultiArrayDimension, String, UInt8,
                          UInt8MultiArray, UInt32)

from hrc_ros.core.pomdp.belief import BeliefFilter
from hrc_ros.core.model import ACTIONS, DN, MH, TASK_VARIABLES, HRCModel
from hrc_ros.core.decision.observation import (distance_level, synthesize_joint_velocities,
                                               synthesize_skeleton, velocity_level)
from hrc_ros.core.mdp.policy import load_policy
from hrc_ros.core.decision.selection import ActionSelector
from hrc_ros.core.tasks import TaskBook
from hrc_ros.core.protocol import ReadyMark
from hrc_ros.ros import conversions as conv
from hrc_ros.ros import qos
from hrc_ros.ros.nodes.belief_estimator_node import BeliefEstimatorNode
from hrc_ros.ros.nodes.cell_sim_node import CellSimNode
from hrc_ros.ros.nodes.cell_view_node import CellViewNode
from hrc_ros.ros.nodes.decision_node import DecisionNode
from hrc_ros.ros.nodes.task_manager_node import TaskManagerNode
from hrc_ros.ros.sources import endpoint_node, gid_text, ready_topic

TIMEOUT = 5.0
EPOCH_PERIOD = 0.2
INPUT_TIMEOUT = 0.12
MS = 1_000_000


def spin_until(executor, predicate, timeout: float = TIMEOUT) -> bool:
    """Spin `executor` until `predicate()` holds or `timeout` seconds pass; its last value."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return bool(predicate())
        executor.spin_once(timeout_sec=0.01)
    return True


class Graph:
    """A Context with an executor, the nodes under test and a probe node."""

    def __init__(self):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.probe = rclpy.create_node('probe', context=self.context)
        self.executor.add_node(self.probe)
        self.nodes = []
        self.statuses: list[DiagnosticStatus] = []
        self.collect(DiagnosticArray, '/diagnostics', qos.RELIABLE,
                     lambda msg: self.statuses.extend(msg.status))

    def start(self, node_class, **parameters):
        overrides = [Parameter(name, value=value) for name, value in parameters.items()]
        node = node_class(context=self.context, parameter_overrides=overrides)
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def publisher(self, msg_type, topic, profile):
        publisher = self.probe.create_publisher(msg_type, topic, profile)
        assert self.spin_until(lambda: publisher.get_subscription_count() > 0), topic
        return publisher

    def collect(self, msg_type, topic, profile, callback=None) -> list:
        messages = []

        def receive(msg):
            messages.append(msg)
            if callback is not None:
                callback(msg)

        self.probe.create_subscription(msg_type, topic, receive, profile)
        return messages

    def spin_until(self, predicate, timeout: float = TIMEOUT) -> bool:
        return spin_until(self.executor, predicate, timeout)

    def diagnostics(self, name: str, level=None) -> list[DiagnosticStatus]:
        return [s for s in self.statuses if s.name == name
                and (level is None or s.level == level)]

    def close(self):
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        self.probe.destroy_node()
        rclpy.try_shutdown(context=self.context)


def new_epoch_source(graph, follower):
    """A new writer of hrc/epoch (a restarted decision node), once the source the node follows
    has been silent long enough to be taken for gone (`EpochFollower.silence_ns`)."""
    gone = follower.last_published_ns + follower.silence_ns
    assert graph.spin_until(lambda: time.time_ns() > gone)
    return graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)


@pytest.fixture(scope='module')
def model(default_config):
    return HRCModel(default_config)


WARN, ERROR, OK = DiagnosticStatus.WARN, DiagnosticStatus.ERROR, DiagnosticStatus.OK


def assert_dropped(graph, node, input_name, reason_part):
    """The node dropped a message on `input_name` and reported it on /diagnostics."""
    name = f'{node.get_name()}: {input_name} input'
    assert graph.spin_until(lambda: graph.diagnostics(name, WARN)), \
        f'no drop diagnostic {name!r}; statuses: {[s.name for s in graph.statuses]}'
    status = graph.diagnostics(name, WARN)[0]
    assert reason_part in status.message, status.message
    assert node.inputs.dropped[input_name] >= 1


# =============================================================================================
# belief_estimator
# =============================================================================================
def test_a_deadline_gives_way_to_a_message_waiting_with_it(graph):
    """A node that wakes up late finds its timeout and the awaited message ready together;
    rclpy runs timers first. `Deadline` must let the waiting message be handled first."""
    from hrc_ros.ros.node_support import Deadline
    order = []
    node = rclpy.create_node('deadline_probe', context=graph.context)
    graph.executor.add_node(node)
    graph.nodes.append(node)
    node.create_subscription(String, 'deadline_probe', lambda m: order.append('message'),
                             qos.RELIABLE)
    deadline = Deadline(node, 0.05, lambda: order.append('deadline'))
    publisher = graph.publisher(String, 'deadline_probe', qos.RELIABLE)
    for _ in range(2):                               # reusable: start() re-arms it
        order.clear()
        deadline.start()
        assert deadline.armed
        publisher.publish(String(data='x'))
        # Do not spin until the message is in the reader's queue (acknowledged) and the timer
        # is due: both are then ready in the same wait.
        assert publisher.wait_for_all_acked(Duration(seconds=5.0))
        end = time.monotonic() + 5.0
        while not deadline.timer.is_ready() and time.monotonic() < end:
            time.sleep(0.01)
        assert deadline.timer.is_ready()
        assert graph.spin_until(lambda: len(order) == 2)
        assert order == ['message', 'deadline']
        assert not deadline.armed
    # cancel() makes a started deadline silent, even one whose timer already fired.
    order.clear()
    deadline.start()
    end = time.monotonic() + 5.0
    while not deadline.timer.is_ready() and time.monotonic() < end:
        time.sleep(0.01)
    graph.executor.spin_once(timeout_sec=0.1)        # the timer fires, the guard is triggered
    deadline.cancel()
    # a later deadline fires after the cancelled one's guard had its chance to run
    sentinel = Deadline(node, 0.05, lambda: order.append('sentinel'))
    sentinel.start()
    assert graph.spin_until(lambda: 'sentinel' in order)
    assert order == ['sentinel']


class Estimator:
    """Drive a belief estimator: joint states, skeletons, actions and epochs."""

    def __init__(self, graph, **parameters):
        self.graph = graph
        self.node = graph.start(BeliefEstimatorNode, **parameters)
        self.joints = graph.publisher(JointState, 'human/joint_states', qos.SENSOR_DATA)
        self.skeleton = graph.publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
        self.action = graph.publisher(String, 'hrc/action', qos.RELIABLE)
        self.epoch_pub = graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
        self.beliefs = graph.collect(Float64MultiArray, 'hrc/belief', qos.LATCHED)
        self.observations = graph.collect(UInt8, 'hrc/observation', qos.RELIABLE)
        self.distances = graph.collect(UInt8, 'hrc/distance_level', qos.LATCHED)
        self.rng = np.random.default_rng(7)
        self.stamp = 100.0

    def wait_received(self, name, count):
        assert self.graph.spin_until(lambda: self.node.inputs.received[name] >= count), name

    def send(self, name, publisher, msg):
        before = self.node.inputs.received[name]
        publisher.publish(msg)
        self.wait_received(name, before + 1)

    def motion(self, level, samples=5):
        for _ in range(samples):
            self.stamp += 0.02
            velocity = synthesize_joint_velocities(level, 6, rng=self.rng)
            self.send('joint_states', self.joints, conv.joint_state_to_msg(
                conv.HUMAN_JOINTS, velocity, stamp=conv.seconds_to_stamp(self.stamp)))

    def body(self, d):
        self.send('skeleton', self.skeleton, conv.keypoints_to_msg(
            synthesize_skeleton(d, rng=self.rng)))

    def act(self, action):
        self.send('action', self.action, String(data=action))

    def epoch(self, k, expect_belief=True):
        """Publish epoch k; wait for the belief, observation and distance level it brings."""
        outputs = [self.distances] + ([self.beliefs, self.observations] if expect_belief
                                      else [])
        counts = [len(messages) for messages in outputs]
        self.send('epoch', self.epoch_pub, conv.epoch_to_msg(k))
        assert self.graph.spin_until(lambda: all(
            len(messages) > count for messages, count in zip(outputs, counts)))
        return conv.belief_from_msg(self.beliefs[-1]) if expect_belief else None


def test_estimator_epochs_follow_the_belief_filter(graph, model):
    est = Estimator(graph)
    belief_filter = BeliefFilter(model)
    est.motion(2, samples=6)
    est.body(2)
    b1 = est.epoch(1)
    np.testing.assert_allclose(b1, belief_filter.initial(2))
    assert graph.spin_until(lambda: est.observations and est.distances)
    assert est.observations[-1].data == 2 and est.distances[-1].data == 2
    est.motion(3, samples=3)
    est.motion(1, samples=2)       # a minority of another level does not change O
    est.body(3)
    est.act('mh')
    b2 = est.epoch(2)
    np.testing.assert_allclose(b2, belief_filter.update(b1, MH, 3))
    assert graph.spin_until(lambda: len(est.observations) == 2 and len(est.distances) == 2)
    assert est.observations[-1].data == 3 and est.distances[-1].data == 3


def test_estimator_counts_a_sample_published_after_the_signal_in_the_next_window(graph):
    """Epoch k's signal, then the cell's first samples after its reaction, all taken in one
    executor pass: rclpy runs them in subscription order (samples first). Window k must still
    end at the signal (by publication time), and the samples open window k+1."""
    est = Estimator(graph)
    est.body(2)
    est.motion(1, samples=4)
    est.epoch(1)
    assert (est.observations[-1].data, est.distances[-1].data) == (1, 2)
    est.motion(1, samples=4)
    est.body(2)
    outputs = (len(est.observations), len(est.distances))
    received = dict(est.node.inputs.received)
    # Published in this order, but not taken until all of them are waiting.
    est.epoch_pub.publish(conv.epoch_to_msg(2))
    for _ in range(4):
        est.joints.publish(conv.joint_state_to_msg(
            conv.HUMAN_JOINTS, synthesize_joint_velocities(3, 6, rng=est.rng)))
    est.skeleton.publish(conv.keypoints_to_msg(synthesize_skeleton(3, rng=est.rng)))
    assert graph.spin_until(lambda: len(est.observations) > outputs[0]
                            and len(est.distances) > outputs[1])
    assert est.node.inputs.received['joint_states'] - received['joint_states'] >= 1
    assert (est.observations[-1].data, est.distances[-1].data) == (1, 2)
    est.wait_received('joint_states', received['joint_states'] + 4)
    est.wait_received('skeleton', received['skeleton'] + 1)
    est.epoch(3)
    assert (est.observations[-1].data, est.distances[-1].data) == (3, 3)


def test_estimator_without_action_predicts_with_dn(graph, model):
    est = Estimator(graph)
    belief_filter = BeliefFilter(model)
    est.motion(1)
    est.body(1)
    b1 = est.epoch(1)
    est.motion(2)
    est.body(1)
    np.testing.assert_allclose(est.epoch(2), belief_filter.update(b1, DN, 2))


def test_estimator_table_mode_and_run_time_parameters(graph, model):
    est = Estimator(graph, belief_mode='table')
    est.motion(3)
    est.body(1)
    np.testing.assert_allclose(est.epoch(1), model.config.observation_table[2])
    # Faster thresholds at run time: the same level-3 motion now reads as level 1.
    result = est.node.set_parameters([Parameter('velocity_thresholds', value=[5.0, 10.0])])
    assert result[0].successful, result[0].reason
    est.motion(3)
    est.body(1)
    np.testing.assert_allclose(est.epoch(2), model.config.observation_table[0])


def test_estimator_derives_velocities_from_positions(graph, model):
    est = Estimator(graph)
    for i in range(5):              # 1.0 rad/s on every joint: level 3 with [0.3, 0.8]
        msg = JointState(name=list(conv.HUMAN_JOINTS), position=[0.1 * i] * 6)
        msg.header.stamp = conv.seconds_to_stamp(10.0 + 0.1 * i)
        est.send('joint_states', est.joints, msg)
    est.body(1)
    est.epoch(1)
    assert graph.spin_until(lambda: est.observations)
    assert est.observations[-1].data == 3


def test_estimator_drops_positions_whose_derived_velocity_overflows(graph):
    """Issue 13: two position-only samples of +-1e308, 1 ns apart, made the velocity infinite
    and took the internal-error path with a traceback; they are a malformed message."""
    est = Estimator(graph)
    for i, q in enumerate((1e308, -1e308)):
        msg = JointState(name=list(conv.HUMAN_JOINTS), position=[q] * 6)
        msg.header.stamp = conv.seconds_to_stamp(10.0 + 1e-9 * i)
        est.send('joint_states', est.joints, msg)
    assert_dropped(graph, est.node, 'joint_states', 'not finite')
    assert not graph.diagnostics('belief_estimator: joint_states input', ERROR)


def test_estimator_window_without_motion_publishes_no_belief(graph):
    est = Estimator(graph)
    est.body(1)
    est.epoch(1, expect_belief=False)
    assert graph.spin_until(lambda: graph.diagnostics('belief_estimator: epoch', WARN))
    assert 'no joint states' in graph.diagnostics('belief_estimator: epoch')[0].message
    assert est.beliefs == [] and len(est.distances) == 1
    est.motion(2)                   # the next window with motion starts the belief
    est.body(1)
    assert est.epoch(2) is not None


def _joint_state(names=conv.HUMAN_JOINTS, velocity=(0.1,) * 6, position=(), stamp=1.0):
    msg = JointState(name=list(names), velocity=[float(v) for v in velocity],
                     position=[float(q) for q in position])
    msg.header.stamp = conv.seconds_to_stamp(stamp)
    return msg


BAD_JOINT_STATES = {
    'empty': (JointState(), 'empty'),
    'length mismatch': (_joint_state(velocity=(0.1, 0.2)), '6 names but 2 velocity'),
    'nan velocity': (_joint_state(velocity=(math.nan,) * 6), 'NaN or inf'),
    'inf velocity': (_joint_state(velocity=(0.1,) * 5 + (math.inf,)), 'NaN or inf'),
    'no velocity nor position': (_joint_state(velocity=()), 'neither'),
}


@pytest.mark.parametrize('case', sorted(BAD_JOINT_STATES))
def test_estimator_drops_malformed_joint_states(graph, case):
    est = Estimator(graph)
    msg, reason = BAD_JOINT_STATES[case]
    est.send('joint_states', est.joints, msg)
    assert_dropped(graph, est.node, 'joint_states', reason)
    est.motion(2)                   # and keeps working
    est.body(1)
    assert est.epoch(1) is not None
    assert est.observations[-1].data == 2


def test_estimator_drops_positions_whose_stamps_do_not_increase(graph):
    est = Estimator(graph)
    est.send('joint_states', est.joints, _joint_state(velocity=(), position=(0.0,) * 6))
    est.send('joint_states', est.joints, _joint_state(velocity=(), position=(1.0,) * 6))
    assert_dropped(graph, est.node, 'joint_states', 'not after the previous')


BAD_SKELETONS = {
    'wrong frame': (conv.keypoints_to_msg(np.ones((3, 3)), frame_id='camera_link'), 'frame'),
    'empty': (conv.keypoints_to_msg(np.zeros((0, 3))), 'no keypoints'),
    'nan': (conv.keypoints_to_msg([[math.nan, 0.0, 0.0]]), 'NaN or inf'),
}


def test_estimator_takes_skeletons_in_its_robot_frame(graph):
    """A robot whose base frame is not base_link (here a namespaced cell's) sets robot_frame;
    then skeletons in that frame count and base_link ones are dropped."""
    est = Estimator(graph, robot_frame='cell1/base_link')
    est.send('skeleton', est.skeleton, conv.keypoints_to_msg(np.ones((3, 3))))
    assert_dropped(graph, est.node, 'skeleton', "expected 'cell1/base_link'")
    est.motion(1)
    est.send('skeleton', est.skeleton, conv.keypoints_to_msg(
        synthesize_skeleton(2, rng=est.rng), frame_id='cell1/base_link'))
    assert est.epoch(1) is not None and est.distances[-1].data == 2


def test_namespaced_nodes_report_under_their_namespace(graph):
    """/diagnostics is global: two cells' reports must not share a status name."""
    node = BeliefEstimatorNode(context=graph.context, namespace='cell2')
    graph.nodes.append(node)
    graph.executor.add_node(node)
    assert graph.spin_until(lambda: graph.diagnostics('cell2/belief_estimator: estimator'))
    status = graph.diagnostics('cell2/belief_estimator: estimator')[0]
    assert status.hardware_id == '/cell2/belief_estimator'


@pytest.mark.parametrize('case', sorted(BAD_SKELETONS))
def test_estimator_drops_malformed_skeletons(graph, case):
    est = Estimator(graph)
    msg, reason = BAD_SKELETONS[case]
    est.send('skeleton', est.skeleton, msg)
    assert_dropped(graph, est.node, 'skeleton', reason)
    est.motion(1)
    est.body(2)
    assert est.epoch(1) is not None
    assert est.distances[-1].data == 2


def test_estimator_drops_unknown_actions_and_repeated_epochs(graph):
    est = Estimator(graph)
    est.send('action', est.action, String(data='jump'))
    assert_dropped(graph, est.node, 'action', 'unknown action')
    est.motion(1)
    est.body(1)
    est.epoch(3)
    est.send('epoch', est.epoch_pub, conv.epoch_to_msg(3))
    assert_dropped(graph, est.node, 'epoch', 'does not continue the epoch source')
    est.send('epoch', est.epoch_pub, UInt32(data=0))
    assert est.node.inputs.dropped['epoch'] == 2


def test_estimator_follows_a_restarted_epoch_count(graph, model):
    """A restarted decision node counts from 1 again: refusing the lower numbers would leave
    the suite without belief (dn) until the count passed the old one."""
    est = Estimator(graph)
    belief_filter = BeliefFilter(model)
    est.motion(2)
    est.body(2)
    est.epoch(40)
    est.motion(2)
    est.body(2)
    b1 = est.epoch(41)
    est.act('mh')
    est.motion(3)
    est.body(3)
    est.epoch_pub = new_epoch_source(graph, est.node.windows.epochs)
    b2 = est.epoch(1)
    np.testing.assert_allclose(b2, belief_filter.update(b1, MH, 3))
    assert est.distances[-1].data == 3 and est.node.windows.epoch == 1
    assert graph.spin_until(lambda: any('restarted at 1 after 41' in s.message for s in
                                        graph.diagnostics('belief_estimator: epoch', WARN)))
    assert est.node.inputs.dropped['epoch'] == 0
    est.motion(1)
    est.body(1)
    assert est.epoch(2) is not None


@pytest.mark.parametrize('name, value, reason', [
    ('velocity_thresholds', [0.8, 0.3], 'increasing'),
    ('velocity_thresholds', [0.3], '2 numbers'),
    ('velocity_thresholds', [-0.1, 0.3], 'positive'),
    ('safety_radii', [0.2, 0.6], '3 numbers'),
    ('safety_radii', [0.6, 0.2, 1.2], 'increasing'),
    ('robot_reference_point', [0.0, 0.0], '3 values'),
    ('robot_reference_point', [0.0, math.nan, 0.0], 'finite'),
    ('belief_mode', 'kalman', 'belief_mode'),
    ('config', '/tmp/no-such-config.yaml', 'config refused: bad model configuration: '
     '/tmp/no-such-config.yaml: cannot read: No such file'),
])
def test_estimator_rejects_bad_parameters(graph, name, value, reason):
    node = graph.start(BeliefEstimatorNode)
    before = node.get_parameter(name).value
    result = node.set_parameters([Parameter(name, value=value)])[0]
    assert not result.successful
    assert reason in result.reason, result.reason
    assert node.get_parameter(name).value == before


def test_estimator_refuses_bad_parameters_at_start_up(graph):
    with pytest.raises(InvalidParameterValueException, match='increasing'):
        graph.start(BeliefEstimatorNode, safety_radii=[1.0, 0.5, 2.0])


# =============================================================================================
# decision
# =============================================================================================
TASK_1 = dict(zip(TASK_VARIABLES, (1, 1, 3, 0, 0, 0, 0, 0)))
LOW_MOTIVATION = np.array([0.8, 0.1, 0, 0.1, 0, 0, 0, 0, 0])


class Decision:
    """A decision node whose inputs are answered by `respond(k)` on each hrc/epoch k."""

    def __init__(self, graph, policy_path, respond=None, **parameters):
        self.graph = graph
        # the probe answers for the task manager and the belief estimator and says no ready
        # mark (hrc/_epoch_ready): epoch 1 waits for its reader as the writer counts it only
        parameters = {'policy': policy_path, 'epoch_period': EPOCH_PERIOD,
                      'input_timeout': INPUT_TIMEOUT, 'stale_timeout': 2.0,
                      'min_epoch_ready': 0, **parameters}
        self.belief = graph.probe.create_publisher(Float64MultiArray, 'hrc/belief',
                                                   qos.LATCHED)
        self.task = graph.probe.create_publisher(UInt8MultiArray, 'hrc/task_state',
                                                 qos.LATCHED)
        self.distance = graph.probe.create_publisher(UInt8, 'hrc/distance_level', qos.LATCHED)
        self.respond = respond or (lambda k: self.inputs())
        self.epochs = graph.collect(UInt32, 'hrc/epoch', qos.RELIABLE,
                                    lambda msg: self.respond(msg.data))
        self.actions = graph.collect(String, 'hrc/action', qos.RELIABLE)
        self.node = graph.start(DecisionNode, **parameters)

    def inputs(self, task=TASK_1, d=1, belief=LOW_MOTIVATION):
        if task is not None:
            self.task.publish(task if isinstance(task, UInt8MultiArray)
                              else conv.task_state_to_msg(task))
        if d is not None:
            self.distance.publish(d if isinstance(d, UInt8) else conv.distance_level_to_msg(d))
        if belief is not None:
            self.belief.publish(belief if isinstance(belief, Float64MultiArray)
                                else conv.belief_to_msg(belief))

    def run(self, epochs):
        assert self.graph.spin_until(lambda: len(self.actions) >= epochs), \
            f'{len(self.actions)} actions after {TIMEOUT} s'
        return [m.data for m in self.actions]

    def status(self, epoch):
        for status in self.graph.statuses:
            if status.name == 'decision: decision' and \
                    conv.diagnostic_values(status).get('epoch') == str(epoch):
                return status
        raise AssertionError(f'no decision status for epoch {epoch}')


def expected_action(model, policy_path, belief=LOW_MOTIVATION, task=TASK_1, d=1):
    selector = ActionSelector(model, load_policy(policy_path, model.config))
    observable = tuple(task[n] for n in TASK_VARIABLES) + (d,)
    return ACTIONS[selector.select(belief, observable).action]


def test_decision_selects_with_the_policy_and_reports(graph, model, policy_path):
    expected = expected_action(model, policy_path)
    assert expected != 'dn'        # so that the test tells a decision from the fail-safe
    dec = Decision(graph, policy_path)
    assert dec.run(2)[:2] == [expected, expected]
    assert [m.data for m in dec.epochs[:2]] == [1, 2]
    status = dec.status(1)
    values = conv.diagnostic_values(status)
    assert status.level == OK and values['faults'] == 'none'
    assert values['policy_file'] == policy_path
    assert values['policy_config_sha256'] == model.config.policy_hash
    assert values['config_sha256'] == model.config.policy_hash
    assert values['input_timed_out'] == 'false'
    assert f'{expected}=' in values['action_scores']
    for key in ('belief_age_s', 'task_state_age_s', 'distance_level_age_s', 'compute_ms',
                'belief', 'observable'):
        assert key in values
    assert float(values['compute_ms']) < 50.0


def test_decision_other_selectors(graph, model, policy_path):
    dec = Decision(graph, policy_path, selector='mls')
    selector = ActionSelector(model, load_policy(policy_path, model.config), method='mls')
    observable = tuple(TASK_1[n] for n in TASK_VARIABLES) + (1,)
    assert dec.run(1)[0] == ACTIONS[selector.select(LOW_MOTIVATION, observable).action]


@pytest.mark.parametrize('method', ['pomdp', 'fib'])
def test_decision_runs_the_shipped_pomdp_policy(graph, model, policy_path, method):
    """selector:=pomdp (or fib) takes the shipped POMDP policy of the configuration and
    decides as ActionSelector does; its diagnostics name that file."""
    dec = Decision(graph, policy_path, selector=method)
    selector = ActionSelector(model, load_policy(policy_path, model.config), method=method)
    observable = tuple(TASK_1[n] for n in TASK_VARIABLES) + (1,)
    expected = ACTIONS[selector.select(LOW_MOTIVATION, observable).action]
    assert dec.run(2)[:2] == [expected, expected]
    values = conv.diagnostic_values(dec.status(1))
    assert values['selector'] == method and values['faults'] == 'none'
    assert Path(values['pomdp_policy_file']).parent.name == 'pomdp'
    assert float(values['compute_ms']) < 50.0


def test_decision_refuses_pomdp_without_a_pomdp_policy(graph, other_config_policy_path,
                                                       default_config, tmp_path):
    """No POMDP policy solved for the configuration: selector:=pomdp is refused at start-up
    and at run time, with the command that solves one."""
    from hrc_ros.ros.node_support import StartupError
    other = tmp_path / 'reduced.yaml'
    data = default_config.data
    other.write_text(yaml.safe_dump({**data, 'model': {**data['model'], 'rho': 1, 'sigma': 1}}))
    with pytest.raises(StartupError, match='--method pomdp'):
        graph.start(DecisionNode, config=str(other), policy=other_config_policy_path,
                    selector='pomdp')
    node = graph.start(DecisionNode, config=str(other), policy=other_config_policy_path)
    result = node.set_parameters([Parameter('selector', value='fib')])[0]
    assert not result.successful and '--method pomdp' in result.reason
    assert node.selector.method == 'paper'


def _bad_belief(data, labels=None):
    msg = Float64MultiArray(data=[float(v) for v in data])
    if labels:
        msg.layout.dim = [MultiArrayDimension(label=label, size=3, stride=3) for label in labels]
    return msg


def _bad_task(data):
    return UInt8MultiArray(data=list(data))


MALFORMED_INPUTS = {
    # case: (inputs of the first epoch, dropped input, reason part)
    'belief of 8': ({'belief': _bad_belief([1 / 8] * 8)}, 'belief', 'must hold 9'),
    'belief with nan': ({'belief': _bad_belief([math.nan] + [1 / 8] * 8)}, 'belief', 'NaN'),
    'belief with inf': ({'belief': _bad_belief([math.inf] + [0.0] * 8)}, 'belief', 'NaN'),
    'belief summing to 2': ({'belief': _bad_belief([2 / 9] * 9)}, 'belief', 'sums to 2'),
    'negative belief': ({'belief': _bad_belief([-0.2, 0.4] + [0.8 / 7] * 7)}, 'belief',
                        'negative'),
    'belief layout': ({'belief': _bad_belief([1 / 9] * 9, ['em', 'ea'])}, 'belief', 'layout'),
    'task state of 7': ({'task': _bad_task([1, 1, 3, 0, 0, 0, 0])}, 'task_state',
                        'must hold 8'),
    'task priority out of domain': ({'task': _bad_task([5, 1, 3, 0, 0, 0, 0, 0])},
                                    'task_state', 'tp = 5'),
    'task nature out of domain': ({'task': _bad_task([1, 1, 7, 0, 0, 0, 0, 0])},
                                  'task_state', 'tx = 7'),
    'distance level 4': ({'d': UInt8(data=4)}, 'distance_level', 'distance level 4'),
}


@pytest.mark.parametrize('case', sorted(MALFORMED_INPUTS))
def test_decision_fails_safe_on_malformed_input(graph, model, policy_path, case):
    bad, input_name, reason = MALFORMED_INPUTS[case]
    expected = expected_action(model, policy_path)

    def respond(k):
        dec.inputs(**(bad if k == 1 else {}))

    dec = Decision(graph, policy_path, respond=respond)
    actions = dec.run(2)
    assert actions[:2] == ['dn', expected]        # fail-safe, then it carries on
    assert_dropped(graph, dec.node, input_name, reason)
    status = dec.status(1)
    values = conv.diagnostic_values(status)
    assert status.level == ERROR
    assert 'malformed' in values['faults'] and reason in values['faults']
    assert values['input_timed_out'] == 'false'   # decided at once, not at the timeout
    assert dec.status(2).level == OK


def test_decision_with_a_queue_policy_reads_the_tasks_waiting(graph):
    """MODEL.md 8.1 on the graph: config/stream_queue.yaml's policy commits (ct) an
    uncommitted 'either' task at d = 1 with a calm unmotivated person once two tasks wait,
    and moves away (dp) while fewer do; the task state's ninth value `queued` decides which,
    more than L = 2 reads as 2, and a task state without it is a fault (dn, named)."""
    from hrc_ros.core.paths import share_dir, shipped_config_path
    task = dict(zip(TASK_VARIABLES, (1, 2, 2, 0, 0, 0, 0, 0)))
    calm = np.eye(9)[0]
    queued = {1: 0, 2: 2, 3: 5, 4: None, 5: 1}

    def respond(k):
        dec.inputs(task={**task, 'queued': queued.get(k, 0)}, d=1, belief=calm)

    dec = Decision(graph, str(share_dir() / 'policies' / 'stream_queue.npz'), respond=respond,
                   config=str(shipped_config_path('stream_queue')))
    assert dec.run(5)[:5] == ['dp', 'ct', 'ct', 'dn', 'dp']
    values = conv.diagnostic_values(dec.status(4))
    assert 'tasks waiting' in values['faults'] and dec.status(4).level == ERROR
    assert dec.status(5).level == OK


def test_decision_fails_safe_on_a_missing_input(graph, policy_path):
    dec = Decision(graph, policy_path, respond=lambda k: dec.inputs(belief=None))
    assert dec.run(2)[:2] == ['dn', 'dn']
    values = conv.diagnostic_values(dec.status(1))
    assert 'hrc/belief missing' in values['faults']
    assert values['input_timed_out'] == 'true'
    assert float(values['input_wait_ms']) >= INPUT_TIMEOUT * 1e3 * 0.9
    assert dec.status(1).level == ERROR
    assert values['belief_age_s'] == 'none'


def test_decision_fails_safe_when_the_epoch_inputs_are_late(graph, model, policy_path):
    expected = expected_action(model, policy_path)
    # Epoch 1 answered in full; from epoch 2 on the belief estimator stays silent.
    dec = Decision(graph, policy_path,
                   respond=lambda k: dec.inputs(belief=LOW_MOTIVATION if k == 1 else None))
    assert dec.run(2)[:2] == [expected, 'dn']
    faults = conv.diagnostic_values(dec.status(2))['faults']
    assert 'hrc/belief not received for epoch 2 within input_timeout' in faults


def test_decision_fails_safe_on_a_stale_distance(graph, model, policy_path):
    expected = expected_action(model, policy_path)
    stale_timeout = 3 * EPOCH_PERIOD
    dec = Decision(graph, policy_path, stale_timeout=stale_timeout,
                   respond=lambda k: dec.inputs(d=1 if k == 1 else None))
    actions = dec.run(6)
    assert actions[0] == expected
    assert actions[5] == 'dn'
    stale = [k for k in range(1, 7)
             if 'hrc/distance_level stale' in conv.diagnostic_values(dec.status(k))['faults']]
    assert stale and all(actions[k - 1] == 'dn' for k in stale)
    assert all(actions[k - 1] == expected for k in range(1, 7) if k not in stale)


def test_decision_stops_at_collision_distance(graph, model, policy_path):
    dec = Decision(graph, policy_path, respond=lambda k: dec.inputs(d=0))
    assert dec.run(1)[0] == 'dn'
    status = dec.status(1)
    values = conv.diagnostic_values(status)
    assert status.level == WARN
    assert 'd = 0' in values['faults']
    assert values['selected'] in ACTIONS    # the policy was consulted, then overridden


def test_decision_follows_the_epoch_topic(graph, model, policy_path):
    expected = expected_action(model, policy_path)
    dec = Decision(graph, policy_path, epoch_source='topic')
    epoch = graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
    dec.inputs()
    epoch.publish(UInt32(data=1))
    assert dec.run(1) == [expected]
    assert graph.probe.count_publishers('hrc/epoch') == 1   # the probe's, not the node's
    epoch.publish(UInt32(data=1))                            # a repeat: dropped
    assert_dropped(graph, dec.node, 'epoch', 'does not continue the epoch source')
    dec.inputs()
    epoch.publish(UInt32(data=2))
    assert dec.run(2) == [expected] * 2
    # the one writer of hrc/epoch is the source it follows, not 'another epoch source' (a
    # replay's player was reported so, with 'Stop one'); a second writer is
    assert graph.spin_until(lambda: dec.node.count_publishers('hrc/epoch') == 1)
    assert dec.node._other_sources() == []
    second = graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
    assert graph.spin_until(lambda: len(dec.node._other_sources()) == 2)
    graph.probe.destroy_publisher(second)
    assert graph.spin_until(lambda: dec.node._other_sources() == [])
    dec.inputs()
    epoch = new_epoch_source(graph, dec.node.epochs)
    epoch.publish(UInt32(data=1))                            # the replay started again
    assert dec.run(3) == [expected] * 3 and dec.node.epoch == 1
    assert graph.spin_until(lambda: any('restarted at 1 after 2' in s.message
                                        for s in graph.diagnostics('decision: epoch', WARN)))


def test_decision_waits_for_the_graph_then_fails_safe(graph, policy_path):
    actions = graph.collect(String, 'hrc/action', qos.RELIABLE)
    epochs = graph.collect(UInt32, 'hrc/epoch', qos.RELIABLE)
    graph.start(DecisionNode, policy=policy_path, epoch_period=0.1, input_timeout=0.05,
                stale_timeout=0.5)       # no belief estimator, no task manager
    assert graph.spin_until(lambda: actions)
    waiting = graph.diagnostics('decision: decision', WARN)
    assert waiting and 'waiting for the graph' in waiting[0].message
    assert float(conv.diagnostic_values(waiting[-1])['waited_s']) < 0.5
    assert [m.data for m in epochs[:1]] == [1] and actions[0].data == 'dn'
    assert 'hrc/task_state missing' in graph.diagnostics('decision: decision', ERROR)[0].message


def _waiting(graph) -> list[dict]:
    return [conv.diagnostic_values(s) for s in graph.diagnostics('decision: decision', WARN)
            if 'waiting for the graph' in s.message]


def _clock_gid(graph, node='/decision') -> str:
    gids = [gid_text(info.endpoint_gid)
            for info in graph.probe.get_publishers_info_by_topic('/hrc/epoch')
            if endpoint_node(info) == node]
    assert len(gids) == 1, gids
    return gids[0]


def test_decision_waits_for_its_listeners_readers_to_match_its_clock(graph, policy_path):
    """Issue 37 (the main job at load 9: epoch 1 lost to the task manager): the clock's writer
    counted the task manager's reader before that reader had matched the writer, and a reader
    that matches after the sample was sent never gets it. With min_epoch_ready, epoch 1 waits
    for a listener's own mark naming this clock; a mark for another clock, or from a node the
    clock's graph shows no reader of, does not count."""
    dec = Decision(graph, policy_path, min_epoch_ready=1, stale_timeout=60.0)
    inputs = ('belief', 'task_state', 'distance_level')
    # every input has a publisher and the probe's reader of hrc/epoch is counted: only the
    # listener's mark is missing
    assert graph.spin_until(lambda: any(
        v['epoch_subscribers'] != '0' and all(v[f'{n}_publishers'] != '0' for n in inputs)
        for v in _waiting(graph)))
    clock = _clock_gid(graph)
    marks = graph.probe.create_publisher(String, ready_topic('/hrc/epoch'), qos.LATCHED)
    ghost = graph.probe.create_publisher(String, ready_topic('/hrc/epoch'), qos.LATCHED)
    marks.publish(conv.epoch_ready_to_msg(ReadyMark('/probe', frozenset({'0' * 32}))))
    ghost.publish(conv.epoch_ready_to_msg(ReadyMark('/no_reader', frozenset({clock}))))
    assert graph.spin_until(lambda: set(dec.node.epoch_listeners.marks)
                            == {'/probe', '/no_reader'})
    seen = len(_waiting(graph))
    assert graph.spin_until(lambda: len(_waiting(graph)) >= seen + 3)   # three ticks later
    assert dec.epochs == [] and dec.actions == []
    assert _waiting(graph)[-1]['epoch_ready'] == 'none'
    marks.publish(conv.epoch_ready_to_msg(ReadyMark('/probe', frozenset({clock}))))
    assert dec.run(1)
    assert [m.data for m in dec.epochs[:1]] == [1]
    assert dec.node._ready_listeners() == ['/probe']


@pytest.mark.parametrize('node_class, reader', [
    (TaskManagerNode, '/task_manager'), (BeliefEstimatorNode, '/belief_estimator'),
    (CellViewNode, '/cell_view_inputs')], ids=['task_manager', 'belief_estimator', 'view'])
def test_listeners_say_which_epoch_clocks_their_reader_has_matched(graph, node_class, reader):
    """The other half: each listener says on hrc/_epoch_ready which epoch writers its own
    reader has matched (the view's reader is on its sampled-inputs node), nothing at its start,
    and says it again for a second writer (a restarted clock)."""
    marks = graph.collect(String, '/hrc/_epoch_ready', qos.READY_MARKS)
    first = graph.probe.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)   # the clock first
    one = _clock_gid(graph, '/probe')
    graph.start(node_class)

    def said(writers):
        return any(conv.epoch_ready_from_msg(m) == ReadyMark(reader, frozenset(writers))
                   for m in marks)
    assert graph.spin_until(lambda: said({one})), [m.data for m in marks]
    # its first word is that it has matched nothing, even with the clock already on the graph:
    # a restarted listener replaces the mark its previous run left at the clock at once
    assert conv.epoch_ready_from_msg(marks[0]) == ReadyMark(reader, frozenset())
    graph.probe.destroy_publisher(first)
    graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
    two = _clock_gid(graph, '/probe')
    assert two != one and graph.spin_until(lambda: said({two})), [m.data for m in marks]


@pytest.mark.parametrize('name, value, reason', [
    ('selector', 'greedy', 'selector must be one of'),
    ('input_timeout', 0.5, 'shorter than epoch_period'),
    ('epoch_period', 0.1, 'shorter than epoch_period'),
    ('epoch_period', -1.0, 'range'),
    ('stale_timeout', -1.0, 'range'),
    ('stale_timeout', 0.1, 'longer than epoch_period'),
    ('policy', '/tmp/no-such-policy.npz', 'policy refused: policy file '
     '/tmp/no-such-policy.npz does not exist'),
    ('config', '/tmp/no-such-config.yaml', 'config refused: bad model configuration: '
     '/tmp/no-such-config.yaml: cannot read: No such file'),
    ('epoch_source', 'topic', 'read-only'),
])
def test_decision_rejects_bad_parameters(graph, policy_path, name, value, reason):
    node = Decision(graph, policy_path).node
    before = node.get_parameter(name).value
    result = node.set_parameters([Parameter(name, value=value)])[0]
    assert not result.successful
    assert reason in result.reason, result.reason
    assert node.get_parameter(name).value == before


def test_decision_applies_parameters_at_run_time(graph, policy_path):
    node = Decision(graph, policy_path).node
    results = node.set_parameters([Parameter('selector', value='qmdp'),
                                   Parameter('epoch_period', value=0.25)])
    assert all(r.successful for r in results)
    assert node.selector.method == 'qmdp'
    assert node.selector._q is not None          # formed now, not in the next decision
    assert node.epoch_timer.timer_period_ns == 250_000_000


def test_decision_clock_is_steady_unless_sim_time(graph, policy_path):
    """Epochs run on the monotonic clock (a system clock step cannot stall them); under
    use_sim_time they follow /clock instead, so a replay with a clock drives them."""
    from rclpy.clock import ClockType
    from rosgraph_msgs.msg import Clock as ClockMsg
    steady = Decision(graph, policy_path, epoch_source='topic').node   # publishes no epochs
    assert steady.clock.clock_type == ClockType.STEADY_TIME
    graph.executor.remove_node(steady)           # one decision node per graph (a second one
    graph.nodes.remove(steady)                   # does not start its clock)
    steady.destroy_node()
    assert graph.spin_until(lambda: graph.probe.count_publishers('hrc/action') == 0)
    sim = Decision(graph, policy_path, use_sim_time=True, epoch_period=1.0,
                   input_timeout=0.6, stale_timeout=1.5)
    assert sim.node.clock.clock_type == ClockType.ROS_TIME
    clock = graph.publisher(ClockMsg, '/clock', qos.RELIABLE)
    before = len(sim.epochs)
    graph.executor.spin_once(timeout_sec=0.3)       # no /clock yet: sim time stands still
    assert len(sim.epochs) == before
    for second in range(1, 6):
        clock.publish(ClockMsg(clock=conv.seconds_to_stamp(float(second))))
        target = second * 10**9
        assert graph.spin_until(lambda t=target: sim.node.get_clock().now().nanoseconds >= t)
    assert graph.spin_until(lambda: len(sim.epochs) >= before + 2)


def test_decision_finds_the_shipped_policy_of_its_configuration(graph):
    """config:=paper.yaml alone is enough: the node takes the shipped paper.npz."""
    repo = Path(__file__).resolve().parent.parent
    node = graph.start(DecisionNode, config=str(repo / 'config' / 'paper.yaml'))
    assert Path(node.policy.path).name == 'paper.npz'


def test_timeouts_follow_the_epoch_period(graph, policy_path):
    """Issue 13: -p epoch_period:=0.2 alone refused to start (input_timeout 0.5 s was not below
    it); the timeouts left at 0 now follow the period, also when it changes at run time."""
    node = graph.start(DecisionNode, policy=policy_path, epoch_period=0.2)
    assert (node.gate.input_timeout_ns, node.gate.stale_timeout_ns) == (100 * MS, 600 * MS)
    assert node.set_parameters([Parameter('epoch_period', value=2.0)])[0].successful
    assert (node.gate.input_timeout_ns, node.gate.stale_timeout_ns) == (1000 * MS, 6000 * MS)
    assert node.set_parameters([Parameter('input_timeout', value=1.0)])[0].successful
    result = node.set_parameters([Parameter('epoch_period', value=0.25)])[0]
    assert not result.successful and 'shorter than epoch_period' in result.reason


def test_decision_refuses_bad_parameters_at_start_up(graph, policy_path):
    with pytest.raises(InvalidParameterValueException, match='shorter than epoch_period'):
        graph.start(DecisionNode, policy=policy_path, epoch_period=0.2, input_timeout=0.5)
    with pytest.raises(InvalidParameterValueException, match='selector'):
        graph.start(DecisionNode, policy=policy_path, selector='vote')


def console_script(name: str) -> str:
    """A console script of this environment (beside the interpreter), else from PATH."""
    beside = Path(sys.executable).parent / name
    return str(beside) if beside.is_file() else (shutil.which(name) or name)


def _run_decision_node(*ros_args):
    result = subprocess.run([console_script('decision_node'), '--ros-args', *ros_args],
                            capture_output=True,
                            text=True, timeout=60, env=dict(os.environ),
                            start_new_session=True)
    return result.returncode, result.stdout + result.stderr


def test_decision_node_refuses_a_policy_of_another_configuration(other_config_policy_path,
                                                                  default_config):
    code, output = _run_decision_node('-p', f'policy:={other_config_policy_path}')
    assert code == 1, output
    assert other_config_policy_path in output                    # names the file
    assert default_config.source in output                       # and the expected config
    assert default_config.policy_hash[:12] in output
    assert 'Traceback' not in output


def test_decision_node_refuses_a_missing_policy(tmp_path):
    missing = str(tmp_path / 'nowhere.npz')
    code, output = _run_decision_node('-p', f'policy:={missing}')
    assert code == 1, output
    assert missing in output and 'does not exist' in output
    assert 'Traceback' not in output


# =============================================================================================
# task_manager
# =============================================================================================
class Tasks:
    def __init__(self, graph, **parameters):
        self.graph = graph
        self.node = graph.start(TaskManagerNode, **parameters)
        self.epoch_pub = graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
        self.action = graph.publisher(String, 'hrc/action', qos.RELIABLE)
        self.response = graph.publisher(Bool, 'hrc/human_response', qos.RELIABLE)
        self.request = graph.publisher(UInt8MultiArray, 'hrc/task_request', qos.RELIABLE)
        self.states = graph.collect(UInt8MultiArray, 'hrc/task_state', qos.LATCHED)

    def send(self, name, publisher, msg):
        before = self.node.inputs.received[name]
        publisher.publish(msg)
        assert self.graph.spin_until(lambda: self.node.inputs.received[name] > before), name

    def epoch(self, k, action=None, accepted=None):
        if action is not None:
            self.send('action', self.action, String(data=action))
        if accepted is not None:
            self.send('human_response', self.response, Bool(data=accepted))
        count = len(self.states)
        self.send('epoch', self.epoch_pub, conv.epoch_to_msg(k))
        assert self.graph.spin_until(lambda: len(self.states) > count)
        return conv.task_state_from_msg(self.states[-1])


def test_task_manager_follows_the_task_book(graph, model):
    tasks = Tasks(graph, initial_task=[1, 1, 3], schedule=['3:2,2,1'])
    book = TaskBook(model, initial_task=(1, 1, 3), schedule=['3:2,2,1'])
    script = [(None, None), ('rh2', False), ('rh2', True), ('nw', None), ('mh', None),
              ('rh1', True), ('nw', None)]
    for k, (action, accepted) in enumerate(script, start=1):
        if k > 1:
            book.apply(action, bool(accepted))
        book.begin_epoch(k)
        assert tasks.epoch(k, action, accepted) == book.state, f'epoch {k}'
    assert tasks.states[0].layout.dim[0].label == 'tp'
    assert len(book.completed) == 1


def test_task_manager_with_a_queue_publishes_the_tasks_waiting(graph):
    """A configuration with a queue (MODEL.md 8.1): hrc/task_state carries `queued`, the
    released tasks waiting behind the current one, as the task book counts them; without a
    queue it stays the eight values (the test above)."""
    from hrc_ros.core.config import load_config
    from hrc_ros.core.paths import shipped_config_path
    config = str(shipped_config_path('stream_queue'))
    schedule = ['2:2,2,1', '2:1,1,3', '3:2,1,0']
    tasks = Tasks(graph, config=config, initial_task=[1, 1, 3], schedule=schedule)
    book = TaskBook(HRCModel(load_config(config)), initial_task=(1, 1, 3), schedule=schedule)
    for k, action in enumerate([None, 'dn', 'dn', 'ct', 'nw'], start=1):
        if k > 1:
            book.apply(action, False)
        book.begin_epoch(k)
        assert tasks.epoch(k, action) == {**book.state, 'queued': len(book.queue)}, k
    assert [d.label for d in tasks.states[-1].layout.dim][-1] == 'queued'
    assert [conv.task_state_from_msg(m)['queued'] for m in tasks.states[:3]] == [0, 2, 3]


def test_task_manager_takes_a_missing_action_as_dn(graph, model):
    tasks = Tasks(graph, initial_task=[2, 2, 2])
    tasks.epoch(1)
    assert tasks.epoch(2, 'ct')['ty'] == 2
    state = tasks.epoch(3)           # no action: dn, the robot's counter is paused
    assert state['bc'] == 2 and state['tc'] == 2


def test_task_manager_holds_an_epoch_that_overtakes_the_action_and_the_answer(graph, model):
    """Epoch k+1, a_k and the answer come from three writers; rclpy runs ready callbacks in
    subscription order (the epoch first). An accepted request must still count as accepted."""
    tasks = Tasks(graph, initial_task=[1, 1, 3], input_timeout=30.0)
    tasks.epoch(1)
    count = len(tasks.states)
    tasks.send('epoch', tasks.epoch_pub, conv.epoch_to_msg(2))
    tasks.send('action', tasks.action, String(data='rh2'))    # eligible: waits for the answer
    graph.executor.spin_once(timeout_sec=0.05)
    assert len(tasks.states) == count
    tasks.send('human_response', tasks.response, Bool(data=True))
    assert graph.spin_until(lambda: len(tasks.states) > count)
    book = TaskBook(model, initial_task=(1, 1, 3))
    book.begin_epoch(1)
    book.apply('rh2', True)
    book.begin_epoch(2)
    assert conv.task_state_from_msg(tasks.states[-1]) == book.state
    assert book.state['ty'] != 0                             # accepted: committed
    assert not graph.diagnostics('task_manager: tasks', WARN)


def test_task_manager_takes_an_unanswered_request_as_refused_after_input_timeout(graph):
    tasks = Tasks(graph, initial_task=[1, 1, 3], input_timeout=0.2)
    tasks.epoch(1)
    start = time.monotonic()
    state = tasks.epoch(2, 'rh2')
    assert time.monotonic() - start >= 0.2                     # it waited for the answer
    assert state['ty'] == 0 and state['tp'] == 1               # refused: nothing changed
    assert graph.spin_until(lambda: any('as refused' in s.message for s in
                                        graph.diagnostics('task_manager: tasks', WARN)))
    assert tasks.node.tasks.late_inputs == 1
    assert tasks.epoch(3, 'nw')['tp'] == 1                      # a non-request: no wait


def test_task_manager_ignores_a_late_answer_to_a_refused_request(graph, model):
    """A yes that comes after its request was refused (input_timeout) must not be taken as
    consent to the next request; an answer sent after that request still counts."""
    tasks = Tasks(graph, initial_task=[1, 1, 3], input_timeout=0.2)
    tasks.epoch(1)
    assert tasks.epoch(2, 'rh2')['ty'] == 0                    # unanswered: refused
    for _ in range(2):                                         # the late yes, pressed twice
        tasks.send('human_response', tasks.response, Bool(data=True))
    tasks.send('action', tasks.action, String(data='rh2'))     # asked again
    state = tasks.epoch(3)                                     # no answer to the new rh2
    assert state['ty'] == 0, 'the late answer was taken as consent to the next request'
    assert tasks.node.tasks.late_answers == 1      # the two held as one (the latest)
    assert graph.spin_until(lambda: any('late human response' in s.message for s in
                                        graph.diagnostics('task_manager: tasks', WARN)))
    book = TaskBook(model, initial_task=(1, 1, 3))
    book.begin_epoch(1)
    book.apply('rh2', True)
    book.begin_epoch(2)
    assert tasks.epoch(4, 'rh2', accepted=True) == book.state  # answered after the request
    assert book.state['ty'] == 3


def test_task_manager_follows_a_restarted_epoch_count(graph, model):
    """The decision node restarted (epoch 1 again): the old count's last action is applied,
    the task carries on, and the new epochs are followed instead of dropped."""
    tasks = Tasks(graph, initial_task=[2, 2, 2])
    book = TaskBook(model, initial_task=(2, 2, 2))
    book.begin_epoch(1)
    tasks.epoch(1)
    for k, action in ((2, 'ct'), (1, 'nw')):
        book.apply(action, False)
        book.renumber(k) if k == 1 else None
        book.begin_epoch(k)
        if k == 1:
            tasks.epoch_pub = new_epoch_source(graph, tasks.node.tasks.epochs)
        assert tasks.epoch(k, action) == book.state, f'epoch {k} ({action})'
    assert tasks.node.book.epoch == 1 and tasks.node.inputs.dropped['epoch'] == 0
    assert graph.spin_until(lambda: any('restarted at 1 after 2' in s.message for s in
                                        graph.diagnostics('task_manager: epoch', WARN)))
    book.apply('nw', False)
    book.begin_epoch(2)
    assert tasks.epoch(2, 'nw') == book.state
    assert book.state['tp'] == 0                   # the task finished across the restart


def test_task_manager_restart_finalises_the_old_count_like_any_epoch(graph, model):
    """A restart while a request waits for its answer holds for it, refuses it at the
    timeout and screens the late answer."""
    tasks = Tasks(graph, initial_task=[1, 1, 3], input_timeout=0.2)
    tasks.epoch(1)
    tasks.epoch(2, 'nw')
    tasks.send('action', tasks.action, String(data='rh2'))     # the old node's last action
    tasks.epoch_pub = new_epoch_source(graph, tasks.node.tasks.epochs)
    assert tasks.epoch(1)['ty'] == 0                           # restart: held, then refused
    assert tasks.node.tasks.late_inputs == 1 and tasks.node.book.epoch == 1
    tasks.send('human_response', tasks.response, Bool(data=True))   # the late yes
    assert tasks.epoch(2, 'rh2')['ty'] == 0                    # not consent to the new rh2
    assert tasks.node.tasks.late_answers == 1


def test_task_manager_restart_takes_a_missing_last_action_as_dn(graph, model):
    human = Tasks(graph, initial_task=[1, 2, 1], input_timeout=0.2)
    book = TaskBook(model, initial_task=(1, 2, 1))
    book.begin_epoch(1)
    human.epoch(1)
    book.apply('rh1', True)
    book.begin_epoch(2)
    assert human.epoch(2, 'rh1', accepted=True) == book.state  # the human works
    book.apply('dn', False)                                    # the old node died before a_2
    book.renumber(1)
    book.begin_epoch(1)
    human.epoch_pub = new_epoch_source(graph, human.node.tasks.epochs)
    assert human.epoch(1) == book.state
    assert book.state['hc'] == 1                               # dn still counts the human


def test_task_manager_drops_a_second_epoch_source(graph):
    """Issue 13: a stray hrc/epoch of 4294967295 from another writer (ros2 topic pub --once)
    made every real epoch 'not follow' and ran begin_epoch(4294967295); an interleaved
    second count is dropped too. The followed source goes on."""
    tasks = Tasks(graph, initial_task=[1, 1, 0], schedule=['5:2,2,1'])
    stray = graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
    for k in (1, 2, 3):
        tasks.epoch(k, 'dn')
    tasks.send('epoch', stray, conv.epoch_to_msg(4294967295))   # while the source is alive
    assert_dropped(graph, tasks.node, 'epoch', 'does not continue the epoch source')
    tasks.send('epoch', stray, conv.epoch_to_msg(2))
    assert tasks.node.book.epoch == 3 and tasks.node.book.pending == []
    assert tasks.epoch(4, 'dn')['tp'] == 1 and tasks.node.inputs.dropped['epoch'] == 2


def test_task_manager_stays_with_the_epoch_source_against_a_forger(graph):
    """Issue 17: 1,000 refused epochs of value 0 from a second writer, then k+1 right after
    the decision node's k: the task manager followed the forger (its numbers had passed the
    real writer's) and refused the real epochs. It stays with the real source, the schedule
    is not released early, and the forger is named on /diagnostics."""
    tasks = Tasks(graph, initial_task=[1, 1, 0], schedule=['5:2,2,1'])
    forger_node = rclpy.create_node('forger', context=graph.context)
    graph.executor.add_node(forger_node)
    graph.nodes.append(forger_node)
    forger = forger_node.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
    assert graph.spin_until(lambda: forger.get_subscription_count() > 0)
    for k in (1, 2, 3):
        tasks.epoch(k, 'dn')
    for _ in range(1000):                 # its writer numbers them 1..1000, past the source's
        forger.publish(UInt32(data=0))
    assert forger.wait_for_all_acked(Duration(seconds=10.0))
    assert graph.spin_until(lambda: tasks.node.inputs.dropped['epoch'] >= 10, timeout=10.0)
    tasks.epoch(4, 'dn')                                      # the decision node's k
    follower = tasks.node.tasks.epochs
    forger.publish(conv.epoch_to_msg(5))                      # k + 1, right after it
    forger.publish(conv.epoch_to_msg(6))
    assert graph.spin_until(lambda: follower.ignored == 2)   # both refused as another's
    assert tasks.node.book.epoch == 4 and tasks.node.book.pending == []
    state = tasks.epoch(5, 'dn')                              # the real k + 1
    assert tasks.node.book.epoch == 5 and state['tp'] == 1
    assert tasks.node.tasks.epochs.last == 5
    name = 'task_manager: epoch source'
    assert graph.spin_until(lambda: any('/forger (gid' in s.message
                                        for s in graph.diagnostics(name, WARN)))


def test_a_short_lived_stray_epoch_publisher_is_named(graph):
    """Issue 17: `ros2 topic pub --once hrc/epoch ...` was never named: its node is gone a
    moment after its message. It is named by node while the graph knows it, else by GID."""
    tasks = Tasks(graph, initial_task=[1, 1, 0])
    for k in (1, 2):
        tasks.epoch(k, 'dn')
    names = []
    for gone in (False, True):
        stray_node = rclpy.create_node(f'stray_once_{int(gone)}', context=graph.context)
        graph.executor.add_node(stray_node)
        stray = stray_node.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
        assert graph.spin_until(lambda p=stray: p.get_subscription_count() > 0)
        gid = next(''.join(f'{b:02x}' for b in list(info.endpoint_gid)[:16])
                   for info in graph.probe.get_publishers_info_by_topic('/hrc/epoch')
                   if info.node_name == stray_node.get_name())
        names.append((stray_node.get_name(), gid))
        # the task manager has seen it match (its `matched` event), as it sees any publisher
        # that lives long enough to deliver a message
        assert graph.spin_until(lambda g=gid: g in tasks.node.epoch_publishers.known)
        stray.publish(conv.epoch_to_msg(4294967295))
        if gone:
            assert stray.wait_for_all_acked(Duration(seconds=5.0))
            graph.executor.remove_node(stray_node)
            stray_node.destroy_node()                       # gone before it is handled
        else:
            graph.nodes.append(stray_node)
        dropped = tasks.node.inputs.dropped['epoch']
        assert graph.spin_until(lambda d=dropped: tasks.node.inputs.dropped['epoch'] > d)
    def reports():
        return [s.message for s in graph.diagnostics('task_manager: epoch source', WARN)]
    assert graph.spin_until(lambda: any(f'gid {names[1][1]}; no longer on the graph' in m
                                        for m in reports())), reports()
    assert any(f'/{names[0][0]} (gid {names[0][1]})' in m for m in reports()), reports()
    assert not any('UNKNOWN' in m for m in reports())
    assert tasks.epoch(3, 'dn')['tp'] == 1                   # the source goes on


def test_refused_requests_are_not_counted_as_lost(graph):
    """Issue 17: 10 invalid task requests among 30 gave 9 'never arrived' errors and one
    request in no count: a request refused by its conversion never reached the gap count,
    so the next one's sequence number skipped it. Each is in exactly one count now."""
    tasks = Tasks(graph)
    for i in range(30):
        msg = UInt8MultiArray(data=[1, 0, 1]) if i % 3 == 2 else \
            conv.task_request_to_msg(1 + i % 2, 1, i % 4)
        tasks.send('task_request', tasks.request, msg)
    def counts():
        statuses = [conv.diagnostic_values(s) for s in graph.diagnostics('task_manager: tasks')]
        return {key: statuses[-1][key] for key in ('requests_accepted', 'requests_refused',
                                                   'requests_lost')} if statuses else {}
    assert graph.spin_until(lambda: counts().get('requests_accepted') == '20')
    assert counts() == {'requests_accepted': '20', 'requests_refused': '10',
                        'requests_lost': '0'}
    assert len(tasks.node.book.queue) == 20
    assert not graph.diagnostics('task_manager: task_request input', ERROR)


def test_task_manager_refuses_requests_beyond_max_queue(graph):
    tasks = Tasks(graph, initial_task=[1, 1, 3], max_queue=2)
    for task in ((1, 1, 0), (2, 1, 0), (2, 2, 1)):
        tasks.send('task_request', tasks.request, conv.task_request_to_msg(*task))
    assert_dropped(graph, tasks.node, 'task_request', 'queue is full')
    assert tasks.node.book.pending == [(1, 1, 0), (2, 1, 0)]


def test_task_manager_queues_requests_and_drops_bad_ones(graph):
    tasks = Tasks(graph)
    assert tasks.epoch(1)['tp'] == 0
    tasks.send('task_request', tasks.request, conv.task_request_to_msg(2, 1, 0))
    assert tasks.epoch(2, 'dn') == dict(zip(TASK_VARIABLES, (2, 1, 0, 0, 0, 0, 0, 0)))
    tasks.send('task_request', tasks.request, UInt8MultiArray(data=[1, 1]))
    assert_dropped(graph, tasks.node, 'task_request', 'priority, duration, nature')
    tasks.send('task_request', tasks.request, UInt8MultiArray(data=[3, 1, 1]))
    tasks.send('task_request', tasks.request, UInt8MultiArray(data=[1, 0, 1]))
    assert tasks.node.inputs.dropped['task_request'] == 3
    assert tasks.node.book.pending == []


def test_bad_input_is_quoted_capped_never_whole(graph):
    """Issue 13: a 10 MB invalid action made a 10 MB log line and a ~20 MB status."""
    tasks = Tasks(graph, initial_task=[1, 1, 0])
    tasks.send('action', tasks.action, String(data='x' * 10_000_000))
    assert_dropped(graph, tasks.node, 'action', '(10000000 characters)')
    status = graph.diagnostics('task_manager: action input', WARN)[0]
    assert len(status.message) < 1000 and all(len(kv.value) < 1000 for kv in status.values)


def test_task_manager_drops_bad_actions_and_epochs(graph):
    tasks = Tasks(graph, initial_task=[1, 1, 0])
    tasks.epoch(1)
    tasks.send('action', tasks.action, String(data='commit'))
    assert_dropped(graph, tasks.node, 'action', 'unknown action')
    tasks.send('epoch', tasks.epoch_pub, conv.epoch_to_msg(1))
    assert_dropped(graph, tasks.node, 'epoch', 'does not continue the epoch source')
    assert tasks.epoch(2, 'ct')['ty'] == 2          # still working


@pytest.mark.parametrize('parameters, reason', [
    ({'initial_task': [1, 1]}, '3 values'),
    ({'initial_task': [1, 1, -3]}, 'initial_task'),
    ({'schedule': ['9:2,2']}, 'bad schedule entry'),
    ({'schedule': ['0:1,1,1']}, 'numbered from 1'),
])
def test_task_manager_refuses_bad_parameters_at_start_up(graph, parameters, reason):
    with pytest.raises(InvalidParameterValueException, match=reason):
        graph.start(TaskManagerNode, **parameters)


def test_task_manager_refuses_out_of_domain_initial_task(graph):
    from hrc_ros.ros.node_support import StartupError
    with pytest.raises(StartupError, match='tp'):
        graph.start(TaskManagerNode, initial_task=[9, 1, 1])


def test_task_manager_refuses_the_arms_rate_without_the_arms_progress(graph):
    """config/arm.yaml plans with the arm's measured progress (model.robot_rate): a task
    manager that counts the robot's share down one an epoch (no robot_progress, no arm) would
    run another cell than the plan's, so it refuses at start in one line; with the arm's
    progress it starts."""
    from hrc_ros.core.paths import arm_config_path
    from hrc_ros.ros.node_support import StartupError
    with pytest.raises(StartupError, match='robot_rate.*needs robot_progress: true'):
        graph.start(TaskManagerNode, config=str(arm_config_path()))
    node = graph.start(TaskManagerNode, config=str(arm_config_path()), robot_progress=True)
    assert node.model.robot_rate is not None


def test_task_manager_parameters_are_read_only(graph):
    node = Tasks(graph, initial_task=[1, 1, 3]).node
    result = node.set_parameters([Parameter('schedule', value=['2:1,1,1'])])[0]
    assert not result.successful and 'read-only' in result.reason


# =============================================================================================
# cell_sim
# =============================================================================================
class Cell:
    def __init__(self, graph, **parameters):
        self.graph = graph
        self.joints = graph.collect(JointState, 'human/joint_states', qos.SENSOR_DATA)
        self.skeletons = graph.collect(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
        self.responses = graph.collect(Bool, 'hrc/human_response', qos.RELIABLE)
        self.true_states = graph.collect(UInt8MultiArray, 'hrc/sim/true_state', qos.LATCHED)
        self.node = graph.start(CellSimNode, **{'sensor_rate': 100.0, **parameters})
        self.action = graph.publisher(String, 'hrc/action', qos.RELIABLE)
        self.task = graph.publisher(UInt8MultiArray, 'hrc/task_state', qos.LATCHED)

    def send(self, name, publisher, msg):
        before = self.node.inputs.received[name]
        publisher.publish(msg)
        assert self.graph.spin_until(lambda: self.node.inputs.received[name] > before), name


def test_cell_streams_the_initial_observation_and_distance(graph):
    cell = Cell(graph, seed=3, initial_emotions=[2, 1], initial_distance=2)
    assert graph.spin_until(lambda: len(cell.joints) >= 10 and len(cell.skeletons) >= 10)
    human = cell.node.human
    for msg in cell.joints:
        assert tuple(msg.name) == conv.HUMAN_JOINTS and len(msg.velocity) == 6
        assert len(msg.position) == 6
        assert velocity_level(msg.velocity) == human.observation
    for msg in cell.skeletons:
        assert msg.header.frame_id == 'base_link'
        assert distance_level(conv.keypoints_from_msg(msg)) == 2
    assert graph.spin_until(lambda: cell.true_states)
    state = conv.true_state_from_msg(cell.true_states[-1])
    assert (state['em'], state['ea'], state['d']) == (2, 1, 2)


def test_cell_reacts_to_actions_like_the_simulated_human(graph, model):
    from hrc_ros.core.cell.human import SimulatedHuman
    cell = Cell(graph, seed=11)
    twin = SimulatedHuman(model, seed=11, em=0, ea=0, d=1)
    task = dict(TASK_1)
    for action in ('mh', 'mh', 'rh2', 'nw'):
        # As the task manager does: x_k each epoch, then a_k.
        cell.send('task_state', cell.task, conv.task_state_to_msg(task))
        reaction = twin.react(action, task)
        if action == 'rh2':
            accepted = reaction.accepted
        count = cell.node.reactions
        cell.send('action', cell.action, String(data=action))
        assert cell.node.reactions == count + 1      # x_k was in: no wait
        assert graph.spin_until(lambda: conv.true_state_from_msg(cell.true_states[-1])
                                == cell.node.true_state())
        state = conv.true_state_from_msg(cell.true_states[-1])
        assert (state['em'], state['ea'], state['d']) == (reaction.em, reaction.ea, reaction.d)
        assert cell.node.human.observation == reaction.observation
    assert graph.spin_until(lambda: len(cell.responses) == 1)   # one request, one response
    assert cell.responses[0].data is accepted
    # After the last reaction every new sample is in the band of the new observation.
    count = len(cell.joints)
    assert graph.spin_until(lambda: len(cell.joints) >= count + 5)
    assert all(velocity_level(m.velocity) == twin.observation for m in cell.joints[count + 1:])


def test_cell_answers_an_ineligible_request_with_false(graph):
    cell = Cell(graph)
    cell.send('task_state', cell.task, conv.task_state_to_msg(
        dict(zip(TASK_VARIABLES, (0,) * 8))))
    cell.send('action', cell.action, String(data='rh1'))
    assert graph.spin_until(lambda: cell.responses)
    assert cell.responses[0].data is False


def test_cell_drops_malformed_inputs(graph):
    cell = Cell(graph)
    cell.send('action', cell.action, String(data='wave'))
    assert_dropped(graph, cell.node, 'action', 'unknown action')
    cell.send('task_state', cell.task, UInt8MultiArray(data=[1, 2, 3]))
    assert_dropped(graph, cell.node, 'task_state', 'must hold 8')
    assert cell.node.reactions == 0
    cell.send('action', cell.action, String(data='dn'))
    # No good task state was received: the action waits task_state_timeout, then the cell
    # reacts as in an idle cell.
    assert cell.node.reactions == 0
    assert graph.spin_until(lambda: cell.node.reactions == 1, timeout=5.0)


def test_cell_holds_an_action_that_overtakes_its_task_state(graph, model):
    """a_k and x_k come from two writers; a_k may be processed first. The cell must answer
    the request with x_k (eligible), not with x_{k-1} (idle: ineligible, so false)."""
    from hrc_ros.core.cell.human import SimulatedHuman
    idle = dict(zip(TASK_VARIABLES, (0,) * 8))
    task = {**idle, 'tp': 2, 'tc': 2, 'tx': 1}
    twin = SimulatedHuman(model, seed=2, em=0, ea=0, d=1)
    twin.react('dn', idle)
    assert twin.react('rh1', task).accepted is True       # this seed's human accepts
    cell = Cell(graph, seed=2, task_state_timeout=30.0)
    cell.send('task_state', cell.task, conv.task_state_to_msg(idle))
    cell.send('action', cell.action, String(data='dn'))       # epoch 1, x_1 idle
    assert cell.node.reactions == 1
    cell.send('action', cell.action, String(data='rh1'))      # a_2 before x_2
    assert cell.node.reactions == 1
    cell.send('task_state', cell.task, conv.task_state_to_msg(task))
    assert cell.node.reactions == 2
    assert graph.spin_until(lambda: cell.responses)
    assert [m.data for m in cell.responses] == [True]



@pytest.mark.parametrize('name, value, reason', [
    ('sensor_rate', 0.0, 'range'),
    ('sensor_rate', 5000.0, 'range'),
    ('velocity_thresholds', [0.5, 0.5], 'increasing'),
    ('safety_radii', [0.2, 0.6, 1.2, 2.0], '3 numbers'),
    ('seed', 4, 'read-only'),
])
def test_cell_rejects_bad_parameters(graph, name, value, reason):
    node = graph.start(CellSimNode)
    result = node.set_parameters([Parameter(name, value=value)])[0]
    assert not result.successful and reason in result.reason, result.reason


def test_cell_applies_the_sensor_rate_at_run_time(graph):
    node = graph.start(CellSimNode)
    assert node.set_parameters([Parameter('sensor_rate', value=20.0)])[0].successful
    assert node.sensor_timer.timer_period_ns == 50_000_000


@pytest.mark.parametrize('parameters, reason', [
    ({'initial_emotions': [3, 0]}, 'initial_emotions'),
    ({'initial_emotions': [0]}, '2 values'),
    ({'initial_distance': 4}, 'range'),
])
def test_cell_refuses_bad_parameters_at_start_up(graph, parameters, reason):
    with pytest.raises(InvalidParameterValueException, match=reason):
        graph.start(CellSimNode, **parameters)


def test_every_parameter_of_every_node_has_a_value(graph, policy_path):
    """Issue 13: `ros2 param dump /task_manager` printed `ros__parameters: {}` and `ros2 param
    get /cell_sim faults` said "Parameter not set": parameters whose default is an empty array
    were declared by type alone, and the get-parameters service answered nothing for a request
    that named one. Here through the same services `ros2 param` uses."""
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import GetParameters, ListParameters
    nodes = [graph.start(TaskManagerNode), graph.start(CellSimNode),
             graph.start(BeliefEstimatorNode),
             graph.start(DecisionNode, policy=policy_path, epoch_source='topic')]
    client_node = rclpy.create_node('param_dump_probe', context=graph.context)
    graph.executor.add_node(client_node)
    graph.nodes.append(client_node)
    def call(service_type, service, request):
        client = client_node.create_client(service_type, service)
        assert graph.spin_until(client.service_is_ready), f'{service} not ready'
        future = client.call_async(request)
        assert graph.spin_until(future.done), f'{service} did not answer'
        return future.result()

    for node in nodes:
        name = node.get_fully_qualified_name()
        names = call(ListParameters, f'{name}/list_parameters',
                     ListParameters.Request()).result.names
        assert 'config' in names
        values = call(GetParameters, f'{name}/get_parameters',
                      GetParameters.Request(names=names)).values
        assert len(values) == len(names), f'{name}: get_parameters answered {len(values)}'
        unset = [n for n, v in zip(names, values) if v.type == ParameterType.PARAMETER_NOT_SET]
        assert unset == [], f'{name}: parameters without a value: {unset}'
    faults = nodes[1].get_parameter('faults')
    assert faults.type_ == Parameter.Type.STRING_ARRAY and list(faults.value) == []
    assert nodes[0].get_parameter('initial_task').type_ == Parameter.Type.INTEGER_ARRAY


def test_a_second_decision_node_does_not_start_its_clock(graph, policy_path):
    """Issue 13: two decision nodes on one domain interleaved their epochs (7, 8, 9, 1, 10, 2,
    ...) and put two commands per period on hrc/action, and nothing named the fault. The newer
    one now refuses to start its clock while the other publishes; both report ERROR naming the
    other; the followers stay on the first."""
    tasks = graph.start(TaskManagerNode, initial_task=[1, 1, 0])
    epochs = graph.collect(UInt32, 'hrc/epoch', qos.RELIABLE)
    actions = graph.collect(String, 'hrc/action', qos.RELIABLE)
    first = graph.start(DecisionNode, policy=policy_path, epoch_period=0.1, stale_timeout=0.3)
    assert graph.spin_until(lambda: len(epochs) >= 3)
    second = graph.start(DecisionNode, policy=policy_path, epoch_period=0.1, stale_timeout=0.3)

    def errors():
        return graph.diagnostics('decision: clock', ERROR)

    assert graph.spin_until(lambda: any('does not start its clock' in s.message
                                        for s in errors()))
    assert graph.spin_until(lambda: any('keeps its clock' in s.message for s in errors()))
    assert not second.clock_start.running and second.epoch == 0
    count = len(epochs)
    assert graph.spin_until(lambda: len(epochs) >= count + 5)
    numbers = [m.data for m in epochs]
    assert numbers == list(range(numbers[0], numbers[0] + len(numbers)))   # one count
    assert len(actions) <= len(epochs) and first.clock_start.running
    assert tasks.inputs.dropped['epoch'] == 0
    values = conv.diagnostic_values(next(s for s in errors()
                                         if 'does not start' in s.message))
    assert 'on /hrc/epoch' in values['other_sources'] and values['this_node'] == '/decision'


def _decision_pair(graph, policy_path, running_first=False, **second):
    """A task manager, input publishers, and two decision nodes started back to back (with
    `running_first`, the second once the first's clock runs)."""
    graph.start(TaskManagerNode, initial_task=[1, 1, 0])
    belief = graph.probe.create_publisher(Float64MultiArray, 'hrc/belief', qos.LATCHED)
    task = graph.probe.create_publisher(UInt8MultiArray, 'hrc/task_state', qos.LATCHED)
    distance = graph.probe.create_publisher(UInt8, 'hrc/distance_level', qos.LATCHED)

    def answer(_epoch):
        task.publish(conv.task_state_to_msg(TASK_1))
        distance.publish(conv.distance_level_to_msg(1))
        belief.publish(conv.belief_to_msg(LOW_MOTIVATION))
    epochs = graph.collect(UInt32, 'hrc/epoch', qos.RELIABLE, answer)
    actions = graph.collect(String, 'hrc/action', qos.RELIABLE)
    parameters = {'policy': policy_path, 'epoch_period': 0.1, 'input_timeout': 0.06,
                  'stale_timeout': 0.3}
    nodes = [graph.start(DecisionNode, **parameters)]
    if running_first:
        assert graph.spin_until(lambda: len(epochs) >= 3)
    nodes.append(graph.start(DecisionNode, **{**parameters, **second}))
    return nodes, epochs, actions


def test_two_decision_nodes_started_at_the_same_moment_agree_on_one(graph, policy_path):
    """Issue 17: two decision nodes started together each saw the other publish and neither
    started its clock: 0 actions. The older claim decides; exactly one publishes epochs."""
    nodes, epochs, actions = _decision_pair(graph, policy_path)
    assert graph.spin_until(lambda: len(epochs) >= 8, timeout=10.0), 'deadlock: no epochs'
    running = [n for n in nodes if n.clock_start.running]
    assert len(running) == 1 and running[0].owner.owns(running[0].steady.now().nanoseconds)
    numbers = [m.data for m in epochs]
    assert numbers == list(range(1, len(numbers) + 1))      # one count
    assert len(actions) <= len(epochs) + 1
    silent = next(n for n in nodes if n is not running[0])
    assert silent.epoch == 0
    errors = graph.diagnostics('decision: clock', ERROR)
    assert any(f'decides for the cell: {running[0].claim.node}' in s.message
               and 'does not start its clock' in s.message for s in errors)


def test_a_following_decision_node_is_a_second_action_source(graph, policy_path):
    """Issue 17: a decision node with epoch_source topic beside a running cell was never
    refused and published an action every epoch (two per epoch). It publishes none."""
    nodes, epochs, actions = _decision_pair(graph, policy_path, running_first=True,
                                            epoch_source='topic')
    timer, follower = nodes
    start = len(epochs)
    assert graph.spin_until(lambda: len(epochs) >= start + 8)
    assert follower.gate.epoch == 0 and follower.epochs.last >= start
    assert len(actions) <= len(epochs) + 1                   # one action per epoch
    errors = graph.diagnostics('decision: clock', ERROR)
    assert any('publishes no action' in s.message for s in errors)


def test_timeouts_that_break_the_nesting_are_refused_with_the_reason(graph, policy_path):
    """The holds nest (task manager < belief estimator < decision node < period); it was a
    comment. The decision node knows its period; the task manager learns it from the epochs,
    then refuses a value that breaks the order, and reports one accepted before it knew."""
    node = Decision(graph, policy_path).node      # epoch_period 0.2
    result = node.set_parameters([Parameter('input_timeout', value=0.07)])[0]
    assert not result.successful
    assert "belief_estimator's task_state_timeout (0.4 x the period = 0.08 s) must be " \
        "shorter than decision's input_timeout (0.07 s)" in result.reason
    # The period the task manager learns is the median gap between the epochs' source stamps:
    # at least the 0.45 s the test waits, more on a loaded machine (at load 9 the 0.2 s gaps
    # this test had read longer, and 0.1 s no longer broke the order, 2026-12-07). 0.4 s
    # breaks the nesting (>= 0.4 x the period) but not the period (< it) for any period in
    # (0.4, 1.0] s: gaps up to 0.55 s longer than asked still give the warning
    tasks = Tasks(graph, input_timeout=0.4)       # accepted: no period known yet
    for k in (1, 2, 3):
        start = time.monotonic()
        assert graph.spin_until(lambda t=start: time.monotonic() > t + 0.45)  # >= 0.45 s apart
        tasks.epoch(k, 'dn' if k > 1 else None)
    period = tasks.node.tasks.epochs.period.period_ns * 1e-9     # learnt by now (epoch waits)
    assert 0.4 < period <= 1.0, period
    assert graph.spin_until(lambda: graph.diagnostics('task_manager: timeouts', WARN))
    warning = graph.diagnostics('task_manager: timeouts', WARN)[0].message
    assert "task_manager's input_timeout (0.4 s) must be shorter than belief_estimator's" \
        in warning
    # refused: 0.42 s is >= 0.4 x a period up to 1.05 s and < any period from 0.45 s
    result = tasks.node.set_parameters([Parameter('input_timeout', value=0.42)])[0]
    assert not result.successful and 'the holds nest' in result.reason
    assert tasks.node.set_parameters([Parameter('input_timeout', value=0.04)])[0].successful


def test_a_burst_of_task_requests_is_queued_whole(graph):
    """Issue 13: hrc/task_request kept the last 10 messages: 30 valid requests published back
    to back gave 11 received and 0 reported dropped. Reliable delivery is now sized to the
    queue, and a request beyond it is refused with a report."""
    tasks = graph.start(TaskManagerNode, max_queue=40)
    requests = graph.publisher(UInt8MultiArray, 'hrc/task_request', qos.RELIABLE)
    for i in range(45):                              # no spinning in between: one burst
        requests.publish(conv.task_request_to_msg(1 + i % 2, 1, i % 4))
    assert graph.spin_until(lambda: tasks.inputs.received['task_request'] == 45)
    assert len(tasks.book.queue) == 40 and tasks.inputs.dropped['task_request'] == 5
    assert graph.spin_until(lambda: graph.diagnostics('task_manager: task_request input', WARN))
    assert 'queue is full' in graph.diagnostics('task_manager: task_request input')[0].message


def test_state_inputs_take_ordinary_publishers_and_name_an_incompatible_one(graph,
                                                                          policy_path):
    """Issue 13: `ros2 topic pub --once hrc/distance_level std_msgs/msg/UInt8 '{data: 2}'` was
    never received: the subscription asked for transient-local durability, which a default
    (volatile) publisher does not offer. A publisher that cannot match (best effort against a
    reliable input) is now named on /diagnostics with the policy."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    node = graph.start(DecisionNode, policy=policy_path, epoch_source='topic')
    plain = graph.publisher(UInt8, 'hrc/distance_level', QoSProfile(depth=10))  # ros2 topic pub
    plain.publish(UInt8(data=2))
    assert graph.spin_until(lambda: node.inputs.received['distance_level'] == 1)
    assert node.gate.slots['distance_level'].value == 2
    tasks = graph.start(TaskManagerNode)
    best_effort = tasks.create_publisher(   # any node will do: the graph matches endpoints
        Bool, 'hrc/human_response', QoSProfile(depth=10,
                                                reliability=ReliabilityPolicy.BEST_EFFORT))
    assert best_effort is not None
    assert graph.spin_until(lambda: graph.diagnostics('task_manager: human_response input',
                                                      ERROR))
    status = graph.diagnostics('task_manager: human_response input', ERROR)[0]
    assert 'RELIABILITY' in status.message and 'hrc/human_response' in status.message


def test_a_parameter_check_that_fails_refuses_the_change_and_the_node_lives_on(graph):
    """A node's check that raises something other than TypeError / ValueError (MemoryError:
    loading a file too large) refuses the set with the error as its reason; it was raised out
    of rclpy's parameter callback, which ended the node."""
    from rclpy.parameter import Parameter as RclParameter
    from hrc_ros.ros.node_support import NodeParameters, ParamSpec

    def check(values):
        if values['size'] > 10:
            raise MemoryError(f'cannot allocate {values["size"]} GiB')
        return None
    node = rclpy.create_node('checked', context=graph.context)
    try:
        NodeParameters(node, [ParamSpec('size', RclParameter.Type.INTEGER, 1, 'a size')], check)
        result = node.set_parameters([RclParameter('size', value=20)])[0]
        assert not result.successful
        assert result.reason == 'MemoryError: cannot allocate 20 GiB'
        assert node.get_parameter('size').value == 1
        assert node.set_parameters([RclParameter('size', value=5)])[0].successful
        assert node.get_parameter('size').value == 5
    finally:
        node.destroy_node()
