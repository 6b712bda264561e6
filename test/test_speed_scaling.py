"""The speed override onto a controller's speed scaling (`core.robot.scaling`, the logic of
speed_scaling_node; docs/ROBOT.md 3). control_msgs has no wheel here, so the node itself runs
only in a ROS install: here it must stop at start with one line that says so."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from hrc_ros.core.robot.scaling import SECOND_WRITER_HOLD, ScalingAdapter, safe_factor


@pytest.mark.parametrize('value, factor', [
    (0.5, 0.5), (1.0, 1.0), (0.0, 0.0), (1.7, 1.0), (-0.2, 0.0), (math.nan, 0.0),
    (math.inf, 0.0), (-math.inf, 0.0), ('x', 0.0), (None, 0.0)])
def test_a_factor_is_a_finite_override_clamped_and_anything_else_a_pause(value, factor):
    assert safe_factor(value) == factor


def test_the_factor_follows_the_override_and_goes_out_every_time():
    """Unchanged factors go out again: the controller keeps the last factor anyone sent, and
    only changes went out before (a forged 1.0 while the arm was held at 0 ran the goal)."""
    adapter = ScalingAdapter(timeout=0.1)
    assert adapter.start() == 0.0                     # a controller that starts first holds
    assert adapter.override(0.4, 1.00, sequence=1) == 0.4
    assert adapter.override(0.4, 1.01, sequence=2) == 0.4     # unchanged: sent again
    assert adapter.override(2.0, 1.02, sequence=3) == 1.0     # never faster than planned
    assert adapter.override(math.nan, 1.03, sequence=4) == 0.0
    assert adapter.override(0.3, 1.04, sequence=5) == 0.3
    assert (adapter.refused, adapter.clamped) == (1, 1)
    assert adapter.reason == ''


def test_no_override_for_the_timeout_pauses_the_arm_until_one_comes():
    adapter = ScalingAdapter(timeout=0.1)
    adapter.start()
    assert adapter.tick(0.5) == 0.0 and adapter.factor == 0.0      # none yet: still 0
    assert adapter.override(0.8, 1.0, sequence=1) == 0.8
    assert adapter.tick(1.05) == 0.8                               # within the timeout: again
    assert adapter.tick(1.11) == 0.0 and adapter.timeouts == 1     # the bridge went quiet
    assert 'no override for' in adapter.reason
    assert adapter.tick(1.2) == 0.0 and adapter.timeouts == 1      # counted once
    assert adapter.override(0.8, 1.3, sequence=2) == 0.8           # back


def test_a_second_writer_holds_the_arm_whatever_either_says():
    adapter = ScalingAdapter(timeout=0.1)
    adapter.start()
    assert adapter.override(0.9, 1.0, sequence=100) == 0.9
    assert adapter.override(1.0, 1.01, sequence=5) == 0.0     # another writer's numbers
    assert adapter.second_writer == 1 and 'second writer' in adapter.reason
    assert adapter.override(0.9, 1.02, sequence=101) == 0.0   # the bridge's, but held: 0
    assert adapter.factor == 0.0
    assert adapter.override(0.9, 1.03 + SECOND_WRITER_HOLD, sequence=102) == 0.9


def test_the_default_timeout_is_no_longer_than_the_latency_ssm_plans_for():
    """The arm must not run on an override older than the bridge's SSM planned it for (its
    control period plus command_latency): the adapter's 0.1 s and its watchdog's 0.05 s let it
    run 0.11 s longer. The timeout and the watchdog's period together stay within it."""
    from hrc_ros.core.robot.bridge import load_robot_description
    from hrc_ros.ros.nodes.robot_bridge_node import PARAMETERS
    period = next(spec.default for spec in PARAMETERS if spec.name == 'control_period')
    adapter = ScalingAdapter()
    assert adapter.timeout + adapter.watchdog_period <= (
        period + load_robot_description().command_latency)


def test_a_gap_in_the_bridges_overrides_does_not_hand_the_line_to_another_writer():
    """The writer lock's silence is not the timeout: after a 40 ms gap (the factor is 0 for
    it) another writer's value is still a second writer's, flagged and held."""
    adapter = ScalingAdapter()
    assert adapter.override(0.9, 1.0, sequence=100) == 0.9
    assert adapter.tick(1.04) == 0.0                          # the gap: paused
    assert adapter.override(1.0, 1.041, sequence=5) == 0.0    # someone else's 1.0
    assert adapter.second_writer == 1 and 'second writer' in adapter.reason


@pytest.mark.parametrize('timeout', [0, -1, math.nan, math.inf])
def test_a_timeout_that_is_no_positive_number_is_refused(timeout):
    with pytest.raises(ValueError):
        ScalingAdapter(timeout)


def test_the_node_stops_at_start_in_one_line_where_control_msgs_is_missing(ros_domain_id):
    pytest.importorskip('rclpy')
    try:
        import control_msgs  # noqa: F401
        pytest.skip('control_msgs is installed: the node runs (the ROS install route)')
    except ImportError:
        pass
    script = Path(sys.executable).parent / 'speed_scaling_node'
    result = subprocess.run([str(script)], capture_output=True, text=True, timeout=120,
                            stdin=subprocess.DEVNULL)
    assert result.returncode == 1, (result.stdout, result.stderr)
    lines = (result.stdout + result.stderr).strip().splitlines()
    assert len(lines) == 1 and 'control_msgs is not installed' in lines[0], lines
