"""The live view: the picture of a known cell state (core.cell.view), its markers, cell_view_node
on the graph and its shutdown, and the Foxglove layout.

- Core: circle radii and centre, the keypoints' colour at each distance level, the panel's text
  (epoch, action, FAIL-SAFE and why, top beliefs, task state), when the view draws.
- Messages: every MarkerArray starts with a DELETEALL and names each (ns, id) once, so a
  viewer never accumulates markers.
- Node (in-process, real DDS): the picture follows the epoch's inputs and the decision node's
  fail-safe report; as a process, SIGINT and SIGTERM leave a lone DELETEALL and exit 0.
- config/foxglove_layout.json: Foxglove's layout format (configById, a mosaic of those panels),
  and every topic it names is in docs/INTERFACES.md and in every shipped bag, with the fields
  its message paths read.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32
from test_nodes import console_script, spin_until
from visualization_msgs.msg import Marker, MarkerArray

from hrc_ros.core.model import TASK_VARIABLES
from hrc_ros.core.decision.observation import closest_distance, synthesize_skeleton
from hrc_ros.core.cell.view import (DISC_THICKNESS, GREY, LEVEL_COLORS, CellState, CellView,
                                    action_line, scene, state_text, top_beliefs, with_alpha)
from hrc_ros.ros import conversions as conv
from hrc_ros.ros import qos
from hrc_ros.ros.nodes.cell_view_node import CellViewNode

REPO = Path(__file__).resolve().parents[1]
RADII = (0.3, 0.7, 1.5)
REFERENCE = (1.0, 2.0, 0.0)
BELIEF = np.array([0.05, 0.0, 0.0, 0.1, 0.6, 0.0, 0.0, 0.25, 0.0])   # (1,1) (2,1) (1,0)
TASK = dict(zip(TASK_VARIABLES, (1, 1, 3, 0, 0, 0, 1, 1)))


def by_id(shapes):
    return {(s.ns, s.id): s for s in shapes}


# -- the picture (core) -----------------------------------------------------------------------
def test_the_three_safety_circles_surround_the_reference_point_with_the_radii():
    shapes = by_id(scene(CellState(), RADII, REFERENCE))
    for i, radius in enumerate(RADII):
        disc = shapes[('safety', i)]
        assert disc.kind == 'disc'
        assert disc.scale == pytest.approx((2 * radius, 2 * radius, DISC_THICKNESS))
        np.testing.assert_allclose(disc.points[0][:2], REFERENCE[:2])
        assert disc.color == with_alpha(LEVEL_COLORS[i], disc.color[3])
    # the smaller circle is drawn above the larger one
    assert shapes[('safety', 0)].points[0][2] > shapes[('safety', 1)].points[0][2] \
        > shapes[('safety', 2)].points[0][2]
    np.testing.assert_allclose(shapes[('robot', 0)].points[0], REFERENCE)
    assert ('human', 0) not in shapes and ('closest', 0) not in shapes   # no skeleton yet


@pytest.mark.parametrize('d', [0, 1, 2, 3])
def test_keypoints_are_coloured_by_their_distance_level(d):
    keypoints = synthesize_skeleton(d, RADII, REFERENCE, np.random.default_rng(d))
    shapes = by_id(scene(CellState(keypoints=keypoints), RADII, REFERENCE))
    human = shapes[('human', 0)]
    assert human.kind == 'spheres' and human.color == with_alpha(LEVEL_COLORS[d])
    np.testing.assert_allclose(human.points, keypoints)
    distance = closest_distance(keypoints, REFERENCE)
    closest = shapes[('closest', 0)]
    assert np.linalg.norm(closest.points[0] - REFERENCE) == pytest.approx(distance)
    np.testing.assert_allclose(shapes[('closest', 1)].points, [REFERENCE, closest.points[0]])
    name = ('collision', 'inner', 'middle', 'outer')[d]
    assert shapes[('closest', 2)].text == f'{distance:.2f} m ({name})'


def test_the_view_never_draws_beyond_the_cell():
    """Issue 17: a keypoint at 1e308 was drawn at 1e308 (and its distance read inf)."""
    keypoints = np.array([[1.2, 2.0, 0.5], [1e308, 0.0, 0.0], [0.0, -30.0, 0.0],
                          [np.nan, 0.0, 0.0]])
    for shown in (3, 4):
        shapes = by_id(scene(CellState(keypoints=keypoints[:shown]), RADII, REFERENCE))
        np.testing.assert_allclose(shapes[('human', 0)].points, keypoints[:1])
        assert all(np.all(np.abs(np.asarray(s.points)) < 100) for s in shapes.values())
    nothing = by_id(scene(CellState(keypoints=keypoints[1:]), RADII, REFERENCE))
    assert ('human', 0) not in nothing and ('closest', 0) not in nothing


def test_the_panel_says_epoch_action_fail_safe_beliefs_and_task():
    state = CellState(epoch=7, action='rh2', belief=BELIEF, distance_level=1, task_state=TASK)
    assert action_line(state) == 'epoch 7: rh2'
    assert state_text(state).splitlines() == [
        'd_k 1 (inner)',
        'belief (em, ea): (1, 1) 0.60  (2, 1) 0.25  (1, 0) 0.10',
        'tp 1 tc 1 tx 3 ty 0 | hp 0 hc 0 bp 1 bc 1']
    panel = by_id(scene(state, RADII, REFERENCE))
    assert panel[('panel', 0)].text == 'epoch 7: rh2'
    assert panel[('panel', 0)].color == (1.0, 1.0, 1.0, 1.0)
    assert panel[('panel', 1)].text == state_text(state)
    # dn forced by the collision circle, and dn with the decision node's reasons: red, marked
    collision = CellState(epoch=8, action='dn', distance_level=0)
    assert action_line(collision) == 'epoch 8: dn  FAIL-SAFE: d = 0 (collision)'
    late = CellState(epoch=9, action='dn', distance_level=2, faults='belief missing')
    assert action_line(late) == 'epoch 9: dn  FAIL-SAFE: belief missing'
    assert by_id(scene(late, RADII, REFERENCE))[('panel', 0)].color == with_alpha(LEVEL_COLORS[0])
    # dn chosen by the policy is not a fail-safe
    assert action_line(CellState(epoch=3, action='dn', distance_level=2)) == 'epoch 3: dn'
    assert state_text(CellState()).splitlines() == ['d_k none yet', 'belief: none yet',
                                                    'task: none yet']
    assert top_beliefs(np.full(9, 1 / 9), 2) == [(0, 0, pytest.approx(1 / 9)),
                                                 (0, 1, pytest.approx(1 / 9))]


def test_the_view_pairs_each_action_with_its_epochs_inputs():
    view = CellView()
    assert view.changed                      # the first picture
    view.drawn()
    view.feed('epoch', 4)
    view.feed('belief', BELIEF)
    view.feed('distance_level', 2)
    view.feed('task_state', TASK)
    assert not view.changed and view.state.epoch == 0 and view.state.belief is None
    view.feed('action', 'dn')                # epoch 4 is complete: shown with its inputs
    assert view.changed
    assert (view.state.epoch, view.state.action, view.state.distance_level) == (4, 'dn', 2)
    assert view.state.task_state == TASK and view.state.belief is BELIEF
    view.drawn()
    view.feed('epoch', 5)                    # epoch 5's inputs wait for its action
    view.feed('distance_level', 0)
    view.feed('decision', (3, 'dn', 'stale task state'))    # another epoch: ignored
    view.feed('decision', (4, 'dn', 'none'))                # nothing to add
    assert not view.changed and view.state.distance_level == 2
    view.feed('decision', (4, 'dn', 'belief missing'))
    assert view.changed and view.state.faults == 'belief missing'
    view.drawn()
    view.feed('decision', (4, 'dn', 'belief missing'))      # said already
    assert not view.changed
    view.feed('action', 'nw')
    assert (view.state.epoch, view.state.action, view.state.faults) == (5, 'nw', '')
    assert view.state.distance_level == 0 and view.state.belief is BELIEF   # kept
    view.drawn()
    view.feed('skeleton', np.zeros((1, 3)))
    assert view.changed
    with pytest.raises(ValueError, match='unknown view input'):
        view.feed('joint_states', None)


def test_nothing_old_is_shown_as_current():
    """The view once drew the last skeleton forever: with nobody in view (the adapter then
    publishes nothing) a person stood in the inner circle at "0.45 m", and a dead decision
    node's last action stayed white. A stale skeleton is no longer drawn, a stale action is
    greyed with its age, and fresh input clears both."""
    view = CellView()
    view.feed('epoch', 1, now=0.0)
    view.feed('action', 'nw', now=0.1)
    view.feed('skeleton', synthesize_skeleton(1, RADII, REFERENCE), now=0.2)
    view.drawn()
    view.age(1.2)                                   # 1.0 s: still current
    assert not view.changed and view.state.keypoints is not None
    view.age(1.3)
    assert view.changed and view.state.keypoints is None and view.state.skeleton_age == 1
    shapes = by_id(scene(view.state, RADII, REFERENCE))
    assert not any(ns in ('human', 'closest') for ns, _ in shapes)
    assert 'skeleton: none for 1 s' in shapes[('panel', 1)].text
    view.drawn()
    view.age(1.9)                                   # the same second: nothing new to draw
    assert not view.changed
    view.age(3.05)                                  # the skeleton's age moved on, not the action's
    assert view.changed and view.state.skeleton_age == 2 and view.state.action_age is None
    view.drawn()
    view.age(4.2)
    assert view.changed and view.state.action_age == 4
    panel = by_id(scene(view.state, RADII, REFERENCE))[('panel', 0)]
    assert panel.text == 'epoch 1: nw  (no action for 4 s)' and panel.color == GREY
    view.feed('skeleton', synthesize_skeleton(2, RADII, REFERENCE), now=4.3)
    view.feed('epoch', 2, now=4.3)
    view.feed('action', 'dn', now=4.4)
    view.age(4.5)
    assert view.state.keypoints is not None and view.state.skeleton_age is None
    assert view.state.action_age is None and action_line(view.state) == 'epoch 2: dn'


# -- the messages -----------------------------------------------------------------------------
def assert_whole_picture(msg: MarkerArray) -> dict:
    """A DELETEALL first, then each (ns, id) once: the previous picture is replaced."""
    assert msg.markers[0].action == Marker.DELETEALL
    keys = [(m.ns, m.id) for m in msg.markers[1:]]
    assert len(keys) == len(set(keys)) and all(m.action == Marker.ADD for m in msg.markers[1:])
    return {(m.ns, m.id): m for m in msg.markers[1:]}


def test_markers_replace_the_picture_and_carry_the_shapes():
    keypoints = synthesize_skeleton(1, RADII, REFERENCE, np.random.default_rng(1))
    state = CellState(epoch=2, action='dm', keypoints=keypoints)
    stamp = conv.seconds_to_stamp(12.5)
    markers = assert_whole_picture(conv.markers_to_msg(scene(state, RADII, REFERENCE),
                                                       'cell1/base_link', stamp))
    assert {m.header.frame_id for m in markers.values()} == {'cell1/base_link'}
    assert all(m.header.stamp == stamp for m in markers.values())
    disc = markers[('safety', 2)]
    assert disc.type == Marker.CYLINDER and disc.scale.x == pytest.approx(2 * RADII[2])
    assert (disc.pose.position.x, disc.pose.position.y) == REFERENCE[:2]
    human = markers[('human', 0)]
    assert human.type == Marker.SPHERE_LIST
    np.testing.assert_allclose([(p.x, p.y, p.z) for p in human.points], keypoints)
    assert (human.color.r, human.color.g, human.color.b) == pytest.approx(LEVEL_COLORS[1])
    assert markers[('closest', 1)].type == Marker.LINE_LIST
    assert markers[('panel', 0)].type == Marker.TEXT_VIEW_FACING
    assert markers[('panel', 0)].text == 'epoch 2: dm'
    cleanup = conv.delete_all_markers_msg()
    assert [m.action for m in cleanup.markers] == [Marker.DELETEALL]


# -- cell_view_node in-process ----------------------------------------------------------------
def decision_status(epoch: int, action: str, faults: str) -> DiagnosticArray:
    return conv.diagnostic_array([conv.diagnostic_status(
        'decision: decision', DiagnosticStatus.ERROR, 'fail-safe',
        {'epoch': epoch, 'action': action, 'faults': faults})])


def test_cell_view_draws_the_epoch_and_marks_a_fail_safe(graph):
    node = graph.start(CellViewNode, safety_radii=list(RADII),
                       robot_reference_point=list(REFERENCE), refresh_rate=20.0)
    pictures = graph.collect(MarkerArray, 'hrc/markers', qos.LATCHED)
    assert graph.spin_until(lambda: pictures), 'no first picture'
    first = assert_whole_picture(pictures[-1])
    assert first[('panel', 0)].text == 'waiting for epoch 1'
    epoch = graph.publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
    action = graph.publisher(String, 'hrc/action', qos.RELIABLE)
    belief = graph.publisher(Float64MultiArray, 'hrc/belief', qos.LATCHED)
    distance = graph.publisher(UInt8, 'hrc/distance_level', qos.LATCHED)
    task = graph.publisher(UInt8MultiArray, 'hrc/task_state', qos.LATCHED)
    skeleton = graph.publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
    diagnostics = graph.publisher(DiagnosticArray, '/diagnostics', qos.RELIABLE)

    def panel(index=0):
        return assert_whole_picture(pictures[-1])[('panel', index)]

    keypoints = synthesize_skeleton(2, RADII, REFERENCE, np.random.default_rng(5))
    skeleton.publish(conv.keypoints_to_msg(keypoints))
    assert graph.spin_until(lambda: ('human', 0) in assert_whole_picture(pictures[-1]))
    epoch.publish(conv.epoch_to_msg(3))
    belief.publish(conv.belief_to_msg(BELIEF))
    distance.publish(conv.distance_level_to_msg(2))
    task.publish(conv.task_state_to_msg(TASK))
    action.publish(conv.action_to_msg('dn'))
    assert graph.spin_until(lambda: panel().text == 'epoch 3: dn')   # the policy's dn, so far
    drawn = assert_whole_picture(pictures[-1])
    assert drawn[('panel', 1)].text == state_text(CellState(belief=BELIEF, distance_level=2,
                                                            task_state=TASK))
    np.testing.assert_allclose([(p.x, p.y, p.z) for p in drawn[('human', 0)].points], keypoints)
    assert (drawn[('human', 0)].color.r, drawn[('human', 0)].color.g) == \
        pytest.approx(LEVEL_COLORS[2][:2])
    # the decision node's periodic health status has the same name and no epoch: not a report
    diagnostics.publish(conv.diagnostic_array([conv.diagnostic_status(
        'decision: decision', DiagnosticStatus.OK, 'ok', {'policy': 'default.npz'})]))
    # the decision node says it failed safe: the panel says so, in red
    diagnostics.publish(decision_status(3, 'dn', 'task state stale'))
    assert graph.spin_until(lambda: 'FAIL-SAFE' in panel().text)
    assert panel().text == 'epoch 3: dn  FAIL-SAFE: task state stale'
    assert (panel().color.r, panel().color.g) == pytest.approx(LEVEL_COLORS[0][:2])
    # epoch 4's inputs wait for its action; a report of another epoch changes nothing
    epoch.publish(conv.epoch_to_msg(4))
    distance.publish(conv.distance_level_to_msg(0))
    diagnostics.publish(decision_status(2, 'dn', 'belief missing'))
    assert graph.spin_until(lambda: node.inputs.received['decision'] >= 2
                            and node.inputs.received['distance_level'] >= 2)
    graph.spin_until(lambda: False, timeout=0.2)
    assert panel().text == 'epoch 3: dn  FAIL-SAFE: task state stale'
    assert panel(1).text.startswith('d_k 2 (middle)')
    action.publish(conv.action_to_msg('dn'))
    assert graph.spin_until(lambda: panel().text.startswith('epoch 4: dn'))
    assert panel().text == 'epoch 4: dn  FAIL-SAFE: d = 0 (collision)'
    assert all(p.markers[0].action == Marker.DELETEALL for p in pictures)
    assert all('belief missing' not in m.text for p in pictures for m in p.markers)
    assert not node.inputs.dropped                  # nothing refused, no internal error


# -- shutdown ---------------------------------------------------------------------------------
@pytest.mark.parametrize('stop', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_cell_view_leaves_the_viewers_empty_when_it_stops(stop, tmp_path):
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('viewer', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    pictures: list[MarkerArray] = []
    node.create_subscription(MarkerArray, 'hrc/markers', pictures.append, qos.LATCHED)
    log = tmp_path / 'cell_view.log'
    with open(log, 'w') as output:
        process = subprocess.Popen([console_script('cell_view_node')], stdout=output,
                                   stderr=subprocess.STDOUT, start_new_session=True)
    try:
        assert spin_until(executor, lambda: pictures, 30), log.read_text()
        assert len(pictures[-1].markers) > 1          # a picture: circles, robot, panel
        os.killpg(process.pid, stop)
        assert process.wait(timeout=15) == 0, log.read_text()
        assert spin_until(executor, lambda: len(pictures[-1].markers) == 1, 5), \
            [len(p.markers) for p in pictures]
        assert pictures[-1].markers[0].action == Marker.DELETEALL
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


# -- the Foxglove layout ----------------------------------------------------------------------
LAYOUT = REPO / 'config' / 'foxglove_layout.json'
PANEL_TYPES = {'3D', 'Plot', 'StateTransitions', 'DiagnosticSummary', 'DiagnosticStatusPanel'}


def mosaic_leaves(node) -> list[str]:
    if isinstance(node, str):
        return [node]
    assert set(node) <= {'first', 'second', 'direction', 'splitPercentage'}, node
    assert node['direction'] in ('row', 'column')
    return mosaic_leaves(node['first']) + mosaic_leaves(node['second'])


def layout_topics(layout: dict) -> dict[str, set]:
    """topic -> the message paths the layout reads from it ('' for a whole message)."""
    topics: dict[str, set] = {}
    for panel_id, config in layout['configById'].items():
        kind = panel_id.split('!')[0]
        paths = [p['value'] for p in config.get('paths', [])]
        for path in paths:
            topic, _, field = path.partition('.')
            topics.setdefault(topic, set()).add(field)
        for topic in config.get('topics', {}):
            topics.setdefault(topic, set()).add('')
        if 'topicToRender' in config:
            topics.setdefault(config['topicToRender'], set()).add('')
        assert kind != 'Plot' or paths, panel_id
    return topics


def interface_topics() -> set[str]:
    text = (REPO / 'docs' / 'INTERFACES.md').read_text()
    return {'/' + t.lstrip('/') for t in re.findall(r'^\| `([^`]+)` \|', text, re.M)}


def test_the_foxglove_layout_is_a_layout_of_the_suites_topics():
    layout = json.loads(LAYOUT.read_text())
    assert set(layout) == {'configById', 'globalVariables', 'userNodes', 'playbackConfig',
                           'layout'}
    panels = layout['configById']
    assert sorted(mosaic_leaves(layout['layout'])) == sorted(panels)   # each panel shown once
    assert {p.split('!')[0] for p in panels} == PANEL_TYPES
    three_d = next(c for p, c in panels.items() if p.startswith('3D!'))
    assert three_d['topics'] == {'/hrc/markers': {'visible': True}}
    assert three_d['followTf'] == conv.ROBOT_BASE_FRAME
    topics = layout_topics(layout)
    plotted = {path for t in topics for path in (f'{t}.{f}' for f in topics[t] if f)}
    assert {f'/hrc/belief.data[{h}]' for h in range(9)} <= plotted
    assert {'/hrc/distance_level.data', '/hrc/action.data'} <= plotted
    assert '/diagnostics' in topics
    # every topic is one the suite publishes: in the contract, and in every shipped bag
    assert set(topics) <= interface_topics(), set(topics) - interface_topics()
    from hrc_ros.ros.bag import bag_info, message_class
    bags = [p for p in (REPO / 'bags').iterdir() if any(p.glob('*.mcap'))]
    assert bags
    for bag in bags:
        recorded = {t.topic: t.type_name for t in bag_info(bag).topics}
        assert set(topics) <= set(recorded), (bag.name, set(topics) - set(recorded))
        for topic, fields in topics.items():
            message = message_class(recorded[topic])
            for field in fields - {''}:
                name, _, index = field.partition('[')
                assert name in message.get_fields_and_field_types(), (topic, field)
                if index:      # the belief's components: h = 3 em + ea < 9
                    assert int(index.rstrip(']')) < 9
