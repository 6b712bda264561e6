"""conversions: message <-> numpy round trips, and every refusal with its reason."""

import math

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import Pose, PoseArray
from sensor_msgs.msg import JointState
from std_msgs.msg import (Bool, Float64MultiArray, MultiArrayDimension, String, UInt8,
                          UInt8MultiArray, UInt32)

from hrc_ros.core.decision.observation import (MAX_JOINT_SPEED, MAX_JOINTS, MAX_KEYPOINT_RANGE,
                                               MAX_KEYPOINTS, distance_level, velocity_level)
from hrc_ros.core.model import ACTIONS, STATE_VARIABLES, TASK_VARIABLES
from hrc_ros.core.protocol import ReadyMark
from hrc_ros.ros import conversions as conv
from hrc_ros.ros.conversions import MessageError


def joint_state(names=('a', 'b'), velocity=(0.1, -0.2), position=(), stamp=0.0):
    msg = JointState()
    msg.header.stamp = conv.seconds_to_stamp(stamp)
    msg.name = list(names)
    msg.velocity = [float(v) for v in velocity]
    msg.position = [float(q) for q in position]
    return msg


# -- joint states -----------------------------------------------------------------------------
def test_joint_state_velocities_pass_through():
    sample = conv.joint_sample_from_msg(joint_state(stamp=12.5))
    assert sample.names == ('a', 'b')
    assert sample.stamp == pytest.approx(12.5)
    np.testing.assert_allclose(conv.joint_velocities(sample), [0.1, -0.2])


def test_joint_velocities_derived_from_positions_and_stamps():
    first = conv.joint_sample_from_msg(joint_state(velocity=(), position=(0.0, 1.0), stamp=1.0))
    second = conv.joint_sample_from_msg(joint_state(velocity=(), position=(0.5, 0.0),
                                                    stamp=1.25))
    assert conv.joint_velocities(first, None) is None          # nothing to difference yet
    np.testing.assert_allclose(conv.joint_velocities(second, first), [2.0, -4.0])


def test_joint_velocities_need_the_same_joints_to_derive():
    first = conv.joint_sample_from_msg(joint_state(velocity=(), position=(0, 1), stamp=1.0))
    other = conv.joint_sample_from_msg(joint_state(names=('a', 'c'), velocity=(),
                                                   position=(0, 1), stamp=2.0))
    assert conv.joint_velocities(other, first) is None


@pytest.mark.parametrize('kwargs, reason', [
    ({'names': (), 'velocity': ()}, 'empty'),
    ({'names': ('a', 'b'), 'velocity': (0.1,)}, '2 names but 1 velocity'),
    ({'names': ('a',), 'velocity': (0.1,), 'position': (0.0, 1.0)}, '1 names but 2 position'),
    ({'velocity': (math.nan, 0.0)}, 'NaN or inf'),
    ({'velocity': (0.0, math.inf)}, 'NaN or inf'),
    ({'velocity': (), 'position': (0.0, -math.inf)}, 'NaN or inf'),
    ({'velocity': (), 'position': ()}, 'neither velocities nor positions'),
    ({'names': ('a', 'a')}, 'not unique'),
])
def test_joint_state_refusals(kwargs, reason):
    with pytest.raises(MessageError, match=reason):
        conv.joint_sample_from_msg(joint_state(**kwargs))


def test_derivation_refuses_stamps_that_do_not_increase():
    first = conv.joint_sample_from_msg(joint_state(velocity=(), position=(0, 1), stamp=2.0))
    same = conv.joint_sample_from_msg(joint_state(velocity=(), position=(1, 1), stamp=2.0))
    with pytest.raises(MessageError, match='not after the previous'):
        conv.joint_velocities(same, first)


def test_message_error_is_a_value_error():
    assert issubclass(MessageError, ValueError)


def test_derived_velocities_that_overflow_are_a_malformed_message():
    names = ('a', 'b')
    first = conv.JointSample(names, np.array([1e308, -1e308]), None, 1.0)
    second = conv.JointSample(names, np.array([-1e308, 1e308]), None, 1.0 + 1e-9)
    with pytest.raises(MessageError, match='not finite'):
        conv.joint_velocities(second, first)


def test_errors_quote_a_capped_part_of_the_content():
    with pytest.raises(MessageError) as caught:
        conv.action_from_msg(String(data='y' * 10_000_000))
    assert len(str(caught.value)) < 500 and '(10000000 characters)' in str(caught.value)
    with pytest.raises(MessageError) as caught:          # 9 values, each 20 k characters
        conv.task_request_from_msg(UInt8MultiArray(data=[1] * 20_000))
    assert len(str(caught.value)) < 500 and '(20000 values)' in str(caught.value)
    with pytest.raises(MessageError) as caught:       # as many joints as a sample may hold
        conv.joint_sample_from_msg(JointState(name=[f'j{i}' for i in range(MAX_JOINTS)],
                                              velocity=[float('nan')] * MAX_JOINTS))
    assert len(str(caught.value)) < 500 and f'({MAX_JOINTS} values)' in str(caught.value)
    assert conv.cap('z' * 5000, 100) == 'z' * 100 + '... (5000 characters)'


def test_joint_state_round_trip():
    stamp = conv.seconds_to_stamp(3.000000250)
    msg = conv.joint_state_to_msg(conv.HUMAN_JOINTS, np.arange(6) * 0.1, np.ones(6), stamp)
    sample = conv.joint_sample_from_msg(msg)
    assert sample.names == conv.HUMAN_JOINTS
    np.testing.assert_allclose(sample.velocity, np.arange(6) * 0.1)
    assert sample.stamp == pytest.approx(3.00000025, abs=1e-9)


# -- skeleton ---------------------------------------------------------------------------------
def test_keypoints_round_trip():
    points = np.array([[0.1, 0.2, 0.3], [1.0, -1.0, 2.0]])
    msg = conv.keypoints_to_msg(points)
    assert msg.header.frame_id == 'base_link'
    np.testing.assert_allclose(conv.keypoints_from_msg(msg), points)


def test_keypoints_refusals():
    msg = conv.keypoints_to_msg(np.zeros((2, 3)), frame_id='camera')
    with pytest.raises(MessageError, match="frame 'camera'"):
        conv.keypoints_from_msg(msg)
    with pytest.raises(MessageError, match='no keypoints'):
        conv.keypoints_from_msg(PoseArray(header=conv.keypoints_to_msg([]).header))
    bad = conv.keypoints_to_msg(np.zeros((2, 3)))
    bad.poses[1].position.y = math.nan
    with pytest.raises(MessageError, match='NaN or inf'):
        conv.keypoints_from_msg(bad)


# -- finite but overflowing input (issue 17) --------------------------------------------------
def test_a_keypoint_beyond_the_cell_is_malformed_never_far():
    """A keypoint at 1e308 made the closest distance inf (sum of squares overflowing), read as
    d = 3, the unsafe side, even beside a keypoint at 0.1 m; now the skeleton is refused."""
    for far in (1e308, -1e200, MAX_KEYPOINT_RANGE + 0.5):
        points = np.array([[0.1, 0.0, 0.0], [far, 0.0, 0.0]])
        with pytest.raises(MessageError, match=f'farther than {MAX_KEYPOINT_RANGE:g} m'):
            conv.keypoints_from_msg(conv.keypoints_to_msg(points))
        with pytest.raises(ValueError, match='farther than'):
            distance_level(points[1:])                         # the core refuses it too
    diagonal = np.full((1, 3), 0.9 * MAX_KEYPOINT_RANGE)       # each coordinate in range
    with pytest.raises(MessageError, match='from the frame origin'):
        conv.keypoints_from_msg(conv.keypoints_to_msg(diagonal))
    near = np.array([[0.1, 0.0, 0.0], [MAX_KEYPOINT_RANGE - 0.5, 0.0, 0.0]])
    assert distance_level(conv.keypoints_from_msg(conv.keypoints_to_msg(near))) == 0
    with pytest.raises(MessageError, match=f'more than {MAX_KEYPOINTS}'):
        conv.keypoints_from_msg(conv.keypoints_to_msg(np.zeros((MAX_KEYPOINTS + 1, 3))))


def test_a_joint_speed_beyond_any_human_is_malformed_and_a_sample_has_a_joint_cap():
    """A velocity of 1e308 gave O = 3 (its mean overflows to inf); 100,000 joints were taken."""
    with pytest.raises(MessageError, match=f'above {MAX_JOINT_SPEED:g} rad/s'):
        conv.joint_sample_from_msg(JointState(name=list(conv.HUMAN_JOINTS),
                                              velocity=[1e308] * 6))
    with pytest.raises(ValueError, match='no human joint'):
        velocity_level([1e308] * 6)
    with pytest.raises(MessageError, match=f'more than {MAX_JOINTS}'):
        conv.joint_sample_from_msg(JointState(name=[f'j{i}' for i in range(100_000)],
                                              velocity=[0.1] * 100_000))
    ok = conv.joint_sample_from_msg(JointState(name=[f'j{i}' for i in range(MAX_JOINTS)],
                                               velocity=[MAX_JOINT_SPEED] * MAX_JOINTS))
    assert velocity_level(ok.velocity) == 3
    # positions 1 rad apart in 1 ms: 1000 rad/s derived, no human
    first, second = (JointState(name=list(conv.HUMAN_JOINTS), position=[q] * 6)
                     for q in (0.0, 1.0))
    second.header.stamp = conv.seconds_to_stamp(0.001)
    with pytest.raises(MessageError, match='derived from positions'):
        conv.joint_velocities(conv.joint_sample_from_msg(second),
                              conv.joint_sample_from_msg(first))


# -- task state, requests, true state ---------------------------------------------------------
def test_task_state_round_trip_with_labels():
    state = dict(zip(TASK_VARIABLES, (2, 1, 3, 3, 2, 1, 2, 1)))
    msg = conv.task_state_to_msg(state)
    assert [d.label for d in msg.layout.dim] == list(TASK_VARIABLES)
    assert conv.task_state_from_msg(msg, rho=2, sigma=2) == state


def test_task_state_without_layout_is_accepted():
    msg = UInt8MultiArray(data=[1, 1, 3, 0, 0, 0, 0, 0])
    assert conv.task_state_from_msg(msg)['tx'] == 3


def test_task_state_with_the_queue_length_round_trips():
    """MODEL.md 8.1: a ninth labelled value `queued` (the tasks waiting), capped at 255; read
    back with the eight, labelled or hand-typed; eight values read as before (no queued)."""
    state = {'tp': 1, 'tc': 2, 'tx': 3, 'ty': 0, 'hp': 0, 'hc': 0, 'bp': 1, 'bc': 1}
    msg = conv.task_state_to_msg({**state, 'queued': 3})
    assert [d.label for d in msg.layout.dim] == list(TASK_VARIABLES) + ['queued']
    assert conv.task_state_from_msg(msg, rho=2, sigma=2) == {**state, 'queued': 3}
    assert conv.task_state_to_msg({**state, 'queued': 1000}).data[-1] == 255
    assert conv.task_state_from_msg(UInt8MultiArray(data=[1, 2, 3, 0, 0, 0, 1, 1, 4])) == \
        {**state, 'queued': 4}
    plain = conv.task_state_to_msg({**state, 'queued': None})
    assert len(plain.data) == 8 and 'queued' not in conv.task_state_from_msg(plain)


@pytest.mark.parametrize('data, labels, reason', [
    ([1, 1, 3, 0, 0, 0, 0], None, 'must hold 8 values'),
    ([1, 1, 3, 0, 0, 0, 0, 0, 0, 0], None, 'must hold 8 values'),
    ([1, 1, 3, 0, 0, 0, 0, 0, 2], list('tp tc tx ty hp hc bp bc waiting'.split()),
     'layout labels'),
    ([3, 1, 3, 0, 0, 0, 0, 0], None, r'tp = 3 is out of its domain 0..2'),
    ([1, 1, 4, 0, 0, 0, 0, 0], None, r'tx = 4 is out of its domain 0..3'),
    ([1, 1, 3, 0, 0, 0, 0, 9], None, r'bc = 9'),
    ([1, 1, 3, 0, 0, 0, 0, 0], list('abcdefgh'), 'layout labels'),
])
def test_task_state_refusals(data, labels, reason):
    msg = UInt8MultiArray(data=data)
    if labels:
        msg.layout.dim = [MultiArrayDimension(label=label, size=1, stride=1) for label in labels]
    with pytest.raises(MessageError, match=reason):
        conv.task_state_from_msg(msg, rho=2, sigma=2)


def test_task_request_round_trip_and_refusals():
    assert conv.task_request_from_msg(conv.task_request_to_msg(2, 2, 1), 2, 2) == (2, 2, 1)
    for data, reason in (([2, 2], 'priority, duration, nature'), ([0, 1, 1], 'tp'),
                         ([3, 1, 1], 'tp'), ([1, 0, 1], 'tc'), ([1, 3, 1], 'tc'),
                         ([1, 1, 4], 'tx')):
        with pytest.raises(MessageError, match=reason):
            conv.task_request_from_msg(UInt8MultiArray(data=data), rho=2, sigma=2)


def test_true_state_round_trip():
    state = dict(zip(STATE_VARIABLES, range(11)))
    msg = conv.true_state_to_msg(state)
    assert [d.label for d in msg.layout.dim] == list(STATE_VARIABLES)
    assert conv.true_state_from_msg(msg) == state


# -- belief -----------------------------------------------------------------------------------
def test_belief_round_trip_with_layout():
    belief = np.arange(1, 10) / 45.0
    msg = conv.belief_to_msg(belief)
    assert [(d.label, d.size, d.stride) for d in msg.layout.dim] == [
        ('motivation', 3, 9), ('aggression', 3, 3)]
    np.testing.assert_array_equal(conv.belief_from_msg(msg), belief)


@pytest.mark.parametrize('data, reason', [
    ([1 / 8] * 8, 'must hold 9'),
    ([1 / 10] * 10, 'must hold 9'),
    ([math.nan] + [1 / 8] * 8, 'NaN or inf'),
    ([math.inf] + [0.0] * 8, 'NaN or inf'),
    ([-0.1, 0.2] + [0.9 / 7] * 7, 'negative'),
    ([0.2] * 9, 'sums to 1.8'),
])
def test_belief_refusals(data, reason):
    with pytest.raises(MessageError, match=reason):
        conv.belief_from_msg(Float64MultiArray(data=data))


def test_belief_refuses_a_foreign_layout():
    msg = conv.belief_to_msg(np.full(9, 1 / 9))
    msg.layout.dim[0].label = 'em'
    with pytest.raises(MessageError, match='layout'):
        conv.belief_from_msg(msg)


def test_belief_without_layout_is_accepted():
    np.testing.assert_allclose(conv.belief_from_msg(Float64MultiArray(data=[1 / 9] * 9)),
                               np.full(9, 1 / 9))


# -- actions, levels, epochs, responses -------------------------------------------------------
@pytest.mark.parametrize('index, name', list(enumerate(ACTIONS)))
def test_action_round_trip(index, name):
    assert conv.action_to_msg(index).data == name
    assert conv.action_to_msg(name).data == name
    assert conv.action_from_msg(String(data=name)) == index


@pytest.mark.parametrize('text', ['', 'stop', 'DN', ' dn', 'rh3'])
def test_unknown_action_refused(text):
    with pytest.raises(MessageError, match='unknown action'):
        conv.action_from_msg(String(data=text))


def test_levels_epochs_responses():
    assert conv.observation_from_msg(conv.observation_to_msg(3)) == 3
    assert conv.distance_level_from_msg(conv.distance_level_to_msg(0)) == 0
    with pytest.raises(MessageError, match='observation level 0'):
        conv.observation_from_msg(UInt8(data=0))
    with pytest.raises(MessageError, match='distance level 4'):
        conv.distance_level_from_msg(UInt8(data=4))
    assert conv.epoch_from_msg(conv.epoch_to_msg(7)) == 7
    with pytest.raises(MessageError, match='numbered from 1'):
        conv.epoch_from_msg(UInt32(data=0))
    assert conv.human_response_from_msg(conv.human_response_to_msg(True)) is True
    assert conv.human_response_from_msg(Bool(data=False)) is False


def test_stamps():
    assert conv.stamp_to_seconds(Time(sec=3, nanosec=500_000_000)) == 3.5
    stamp = conv.seconds_to_stamp(1.9999999999)
    assert stamp.nanosec <= 999_999_999


# -- diagnostics ------------------------------------------------------------------------------
def test_diagnostic_builders_format_values():
    status = conv.diagnostic_status('decision: decision', DiagnosticStatus.WARN, 'dn', {
        'belief': np.array([0.5, 0.25]), 'ok': True, 'age': 0.1234567, 'none': None,
        'epoch': 3, 'scores': (1.0, 2.0)})
    values = conv.diagnostic_values(status)
    assert values == {'belief': '[0.5, 0.25]', 'ok': 'true', 'age': '0.123457',
                      'none': 'none', 'epoch': '3', 'scores': '[1, 2]'}
    array = conv.diagnostic_array([status], conv.seconds_to_stamp(2.0))
    assert array.status[0].level == DiagnosticStatus.WARN and array.header.stamp.sec == 2
    with pytest.raises(ValueError, match='diagnostic level'):
        conv.diagnostic_status('x', b'\x07', 'bad level')


def test_pose_array_uses_identity_orientation():
    msg = conv.keypoints_to_msg([[1, 2, 3]])
    assert isinstance(msg.poses[0], Pose) and msg.poses[0].orientation.w == 1.0


def test_an_epoch_ready_mark_round_trips_and_a_bad_one_is_refused_quoted():
    gids = frozenset({'010f78fd5937b7010000010000002d03', 'ab' * 16})
    mark = ReadyMark('/ns/task_manager', gids)
    assert conv.epoch_ready_from_msg(conv.epoch_ready_to_msg(mark)) == mark
    assert conv.epoch_ready_from_msg(String(data='/view')) == ReadyMark('/view', frozenset())
    for data in ('task_manager ' + 'ab' * 16,          # not a fully qualified node name
                 '/tm ' + 'AB' * 16, '/tm ' + 'ab' * 15, '/tm  ' + 'ab' * 16, '',
                 '/tm' + (' ' + 'ab' * 16) * (conv.READY_WRITERS_MAX + 1),
                 '/' + 'x' * 300, '/x\n[ERROR] [decision]: forged\x1b[2J', '/a//b', '/9a'):
        with pytest.raises(MessageError, match='epoch ready mark'):
            conv.epoch_ready_from_msg(String(data=data))
    with pytest.raises(MessageError, match='too long'):
        conv.epoch_ready_from_msg(String(data='/' + 'x' * 100_000))
