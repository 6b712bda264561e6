"""cobot_sim_node's motion thread (its module docstring): the schedule that decides when a step
publishes, and joint states that do not wait for the node's executor."""

from __future__ import annotations

import numpy as np
import pytest
import rclpy
from sensor_msgs.msg import JointState

from hrc_ros.ros import qos
from hrc_ros.ros.nodes.cobot_sim_node import CobotSimNode, MotionSchedule, next_tick
from spun import SpunNode

STEP, PUBLISH = 1 / 250, 1 / 125      # the shipped rate and joint_state_rate


def publishes(times) -> int:
    schedule = MotionSchedule(0.0, STEP, PUBLISH)
    count = 0
    for now in times:
        count += schedule.step(now)
        assert now < schedule.next_step <= now + STEP + 1e-12
    return count


def test_steps_on_time_publish_every_second_one():
    assert publishes([k * STEP + 1e-4 for k in range(250)]) == 125


def test_steps_at_half_the_rate_still_publish_once_a_publish_period():
    # a loaded machine: every other step tick lost and each step 3 ms late. Publishing every
    # 2nd step (the timer design) gave 62 joint states here
    assert publishes([k * 2 * STEP + 3e-3 for k in range(125)]) == 125


def test_a_pause_is_skipped_not_caught_up_in_a_burst():
    schedule = MotionSchedule(0.0, STEP, PUBLISH)
    assert schedule.step(1e-4)
    assert schedule.step(0.5001)                  # the first step after the pause publishes
    assert schedule.next_publish == pytest.approx(0.504)
    assert schedule.next_step == pytest.approx(0.504)
    assert not schedule.step(0.5021)              # the missed periods are not made up
    assert schedule.step(0.5041)


@pytest.mark.parametrize('tick, now, expected', [(0.0, 0.0, 0.004), (0.0, 0.0039, 0.004),
                                                 (0.0, 0.004, 0.008), (0.0, 0.0101, 0.012),
                                                 (0.5, 0.1, 0.504)])
def test_next_tick_is_the_first_grid_tick_after_now(tick, now, expected):
    assert next_tick(tick, now, STEP) == pytest.approx(expected)


def test_joint_states_do_not_wait_for_the_nodes_executor(ros_domain_id):
    """The node built but its executor never spun (as when it is busy with its inputs): the
    joint states still come, the arm's state (at home, at rest); destroying the node ends the
    motion thread first."""
    listener = SpunNode('motion_listener')
    received = []
    listener.node.create_subscription(JointState, 'joint_states', received.append,
                                      qos.SENSOR_DATA)
    listener.start()
    context = rclpy.Context()
    rclpy.init(context=context)
    node = CobotSimNode(context=context)
    try:
        listener.wait(lambda: len(received) >= 25, '25 joint states with no executor spinning')
        home = node.description.poses['home']
        for msg in received[:25]:
            assert list(msg.name) == list(node.description.joint_names)
            np.testing.assert_allclose(msg.position, home, atol=1e-12)
            np.testing.assert_allclose(msg.velocity, 0.0, atol=1e-12)
        stamps = [m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec for m in received[:25]]
        assert all(b > a for a, b in zip(stamps, stamps[1:]))
        assert node.steps >= 25
    finally:
        thread = node._motion_thread
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        listener.close()
    assert not thread.is_alive()


def test_an_override_older_than_the_watchdog_is_taken_as_0(ros_domain_id):
    """The controller's watchdog (OVERRIDE_TIMEOUT): the bridge plans each override for its
    control period, so one held back longer (the node's executor late on a loaded host) must
    not keep the arm at its speed; 3 control periods, then 0."""
    from hrc_ros.ros.nodes.cobot_sim_node import OVERRIDE_TIMEOUT
    from hrc_ros.ros.nodes.robot_bridge_node import PARAMETERS as BRIDGE_PARAMETERS
    period = next(p.default for p in BRIDGE_PARAMETERS if p.name == 'control_period')
    assert OVERRIDE_TIMEOUT <= 3 * period + 1e-12
    context = rclpy.Context()
    rclpy.init(context=context)
    node = CobotSimNode(context=context)
    try:
        assert node.override_timeout == OVERRIDE_TIMEOUT
        node.held = ''
        node.override, node._override_at = 0.8, 100.0
        assert node._commanded(100.0 + OVERRIDE_TIMEOUT - 1e-3) == 0.8
        assert node._commanded(100.0 + OVERRIDE_TIMEOUT + 1e-3) == 0.0
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
