"""Replay the recorded bags of bags/ into freshly started nodes; check the format independently.

Each bag folder holds the MCAP file of a live run of the suite (`hrc-case-study`), its
`metadata.yaml` and, in `params/`, the parameter files the run's nodes were started with. The
replay starts `belief_estimator_node`, `task_manager_node` and `decision_node` as processes
with those parameters (the decision node with `epoch_source: topic`, so it follows the
recorded `hrc/epoch` instead of its own clock), plays the bag's inputs with `hrc-bag play
--order publish`, which starts once every subscriber of the played topics has matched (joint
states, skeletons, human responses, task requests and the epoch
signals, in the order their writers sent them, which is the order the live nodes' windows
were cut by; the recorder may have taken two of them the other way round) and compares
the actions the fresh nodes publish with the recorded ones, epoch by epoch (DESIGN.md explains
why decisions are deterministic given the inputs). A bag of a body-tracker run (it holds
`body_tracking_data`) is replayed through a fresh `body_tracking_node` instead: the tracker's
frames are played, not the `human/*` the adapter made of them.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from hrc_ros.ros.bag import BagError, bag_info, deserialize, read_bag
from hrc_ros.ros.processes import NodeProcesses

REPO = Path(__file__).resolve().parents[1]
BAGS = sorted(p for p in (REPO / 'bags').iterdir() if p.is_dir() and any(p.glob('*.mcap')))
INPUTS = ['/human/joint_states', '/human/skeleton', '/hrc/human_response', '/hrc/task_request',
          '/hrc/epoch']
REPLAYED_NODES = ('belief_estimator_node', 'task_manager_node', 'decision_node')
TRACKER_INPUT = '/body_tracking_data'


def actions_by_epoch(events) -> dict[int, str]:
    """Epoch -> the first action published after that epoch's signal, from
    ``(publication time, 'epoch' | 'action', value)`` events.

    Publication (source) timestamps, not the order messages reached a subscriber: the signal
    and the action come from two writers, and a subscriber that wakes up late takes them in
    subscription order, not in the order they were sent."""
    actions, epoch = {}, None
    for _, kind, value in sorted(events):
        if kind == 'epoch':
            epoch = int(value)
        elif epoch is not None:
            actions.setdefault(epoch, value)
    return actions


def recorded_actions(bag: Path) -> dict[int, str]:
    return actions_by_epoch(
        (m.publish_time_ns, m.topic.rsplit('/', 1)[-1], deserialize(m).data)
        for m in read_bag(bag, topics=['/hrc/epoch', '/hrc/action']))


def decision_reports(bag: Path) -> dict[int, dict]:
    """Epoch -> the decision node's per-epoch /diagnostics values, as recorded."""
    from hrc_ros.ros.conversions import diagnostic_values
    reports = {}
    for m in read_bag(bag, topics=['/diagnostics']):
        for status in deserialize(m).status:
            if status.name.endswith('decision: decision'):
                values = diagnostic_values(status)
                if values.get('epoch', '0') != '0':
                    reports[int(values['epoch'])] = values
    return reports


def test_bags_exist_and_are_small():
    names = {bag.name for bag in BAGS}
    assert 'case_study' in names and any(n.startswith('fault') for n in names), names
    for bag in BAGS:
        size = sum(f.stat().st_size for f in bag.glob('*.mcap'))
        assert size < 5 * 1024 * 1024, f'{bag.name}: {size} bytes'
        assert sorted((bag / 'params').glob('*.yaml')), f'{bag.name} has no params/'


@pytest.mark.parametrize('bag', BAGS, ids=[b.name for b in BAGS])
def test_every_message_decodes_without_rclpy(bag, tmp_path):
    """mcap_ros2 decodes each message from the schema text alone, in a process with no ROS."""
    script = tmp_path / 'decode.py'
    script.write_text(
        'import sys, json, collections\n'
        'for blocked in ("rclpy", "std_msgs", "sensor_msgs", "geometry_msgs",\n'
        '                "diagnostic_msgs", "builtin_interfaces", "visualization_msgs"):\n'
        '    sys.modules[blocked] = None\n'
        'from mcap_ros2.reader import read_ros2_messages\n'
        'counts = collections.Counter()\n'
        'for m in read_ros2_messages(sys.argv[1]):\n'
        '    assert m.ros_msg is not None\n'
        '    counts[m.channel.topic] += 1\n'
        'print(json.dumps(counts))\n')
    mcap_file = next(bag.glob('*.mcap'))
    proc = subprocess.run([sys.executable, str(script), str(mcap_file)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    counts = yaml.safe_load(proc.stdout)
    info = bag_info(bag)
    assert counts == {t.topic: t.message_count for t in info.topics}
    assert sum(counts.values()) == info.message_count > 0


def test_a_damaged_bag_is_refused_clearly(tmp_path):
    source = next(BAGS[0].glob('*.mcap')).read_bytes()
    truncated = tmp_path / 'truncated.mcap'
    truncated.write_bytes(source[: len(source) // 2])
    with pytest.raises(BagError):
        bag_info(truncated)
    proc = subprocess.run([sys.executable, '-m', 'hrc_ros.ros.bag', 'play', str(truncated)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.startswith('hrc-bag: ') and 'Traceback' not in proc.stderr


@pytest.mark.parametrize('bag', BAGS, ids=[b.name for b in BAGS])
def test_replay_reproduces_the_recorded_actions(bag, tmp_path, ros_domain_id):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String, UInt32

    from hrc_ros.ros.conversions import diagnostic_values

    expected = recorded_actions(bag)
    assert len(expected) >= 10, f'{bag.name} holds only {len(expected)} decisions'
    replay = tmp_path / 'replay.yaml'
    replay.write_text(yaml.safe_dump({'/**/decision': {'ros__parameters': {
        'epoch_source': 'topic'}}}))
    nodes = NodeProcesses(tmp_path, sorted((bag / 'params').glob('*.yaml')) + [replay])
    context = rclpy.context.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('replay_observer', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    events, reports = [], {}

    def listen(kind):
        def on_message(msg, info):
            events.append((info['source_timestamp'], kind, msg.data))
        return on_message

    def on_diagnostics(msg):
        for status in msg.status:
            if status.name == 'decision: decision':
                values = diagnostic_values(status)
                if values.get('epoch', '0') != '0':
                    reports[int(values['epoch'])] = values

    deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(UInt32, 'hrc/epoch', listen('epoch'), deep)
    node.create_subscription(String, 'hrc/action', listen('action'), deep)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, deep)

    def spin_until(predicate, timeout, what):
        deadline = time.monotonic() + timeout
        while not predicate():
            assert time.monotonic() < deadline, f'timed out waiting for {what}'
            assert not nodes.dead(), nodes.logs()
            executor.spin_once(timeout_sec=0.05)

    recorded = {t.topic for t in bag_info(bag).topics}
    tracked = TRACKER_INPUT in recorded
    inputs = [TRACKER_INPUT] + INPUTS[2:] if tracked else INPUTS
    try:
        for name in REPLAYED_NODES + ('body_tracking_node',) * tracked:
            nodes.start(name)
        wanted = {'belief_estimator', 'task_manager', 'decision'} \
            | ({'body_tracking'} if tracked else set())
        spin_until(lambda: wanted <= {n for n, _ in node.get_node_names_and_namespaces()},
                   30, 'the replayed nodes to start')
        spin_until(lambda: node.count_subscribers('hrc/epoch') >= 4, 30,
                   'the nodes to subscribe hrc/epoch')
        spin_until(lambda: not tracked or node.count_subscribers('human/joint_states') >= 1, 30,
                   'the estimator to subscribe the adapter')
        player = subprocess.Popen(
            [sys.executable, '-m', 'hrc_ros.ros.bag', 'play', str(bag), '--topics',
             *[t for t in inputs if t in recorded],
             '--wait-for-subscribers', '10', '--order', 'publish'],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True)
        last = max(expected)

        def decided_last():
            return last in actions_by_epoch(events) and last in reports

        duration = bag_info(bag).duration_ns / 1e9
        spin_until(lambda: player.poll() is not None or decided_last(), duration + 30,
                   'the replay')
        spin_until(decided_last, 10, f'the action of epoch {last} (seen: {events[-12:]}; '
                   f'decision log: {nodes.log("decision_node", 1500)})')
        code, output = player.wait(30), player.stdout.read()
        assert code == 0, output
        # the first message went out once every running subscriber had matched (issue 17)
        assert 'not matched' not in output, output
    finally:
        if 'player' in locals() and player.poll() is None:
            os.killpg(player.pid, signal.SIGKILL)
        nodes.stop()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    replayed = actions_by_epoch(events)
    # The decision node's own per-epoch reports name the epoch explicitly: they must agree.
    assert {k: v['action'] for k, v in reports.items() if k in expected} == replayed
    mismatches = {k: (expected[k], replayed.get(k)) for k in expected
                  if replayed.get(k) != expected[k]}
    if mismatches:
        recorded_reports = decision_reports(bag)
        keys = ('action', 'faults', 'observable', 'belief', 'input_wait_ms')
        detail = '\n'.join(
            f'epoch {k}: recorded {[recorded_reports.get(k, {}).get(n) for n in keys]}\n'
            f'{"":9}replayed {[reports.get(k, {}).get(n) for n in keys]}' for k in mismatches)
        pytest.fail(f'epoch: (recorded, replayed) {mismatches}; ({", ".join(keys)}):\n{detail}')
