"""speed_scaling_node: the bridge's speed override onto a joint trajectory controller's speed
scaling input (docs/ROBOT.md 3, "Speed override onto a real arm").

    ros2 run hrc_ros speed_scaling_node --ros-args \
        -r speed_scaling_input:=/joint_trajectory_controller/speed_scaling_input

Reads the override (std_msgs/Float64 on `override_topic`, `hrc/speed_override` by default, as
robot_bridge_node publishes it: reliable, volatile) and publishes control_msgs/msg/
SpeedScalingFactor (`factor`) on `scaling_topic`, reliable and transient local with depth 1, as
ros2_controllers' joint_trajectory_controller with speed scaling reads `~/speed_scaling_input`.
The rules are `core.robot.scaling.ScalingAdapter`'s: 0 at start and while no override has
come, 0 once the override is older than `override_timeout` (a watchdog timer), 0 for a value
that is no finite number or from a second writer, a finite value clamped to [0, 1]; the factor
goes out with every override and every watchdog tick (a value another node writes to the
controller's topic lasts until the next one).

It runs in a ROS install where control_msgs exists (`rosdep install` installs
ros-jazzy-control-msgs); the pip wheels here do not bring it, and without it the node stops at
start with one line that says so (exit 1). `/diagnostics`: `speed_scaling: scaling` once a
second, OK while the factor follows the override, WARN while it holds at 0 for a reason
(`held_because`), with the counts of refused, clamped and timed-out overrides.
"""

from __future__ import annotations

import time

from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64

from ...core.robot.scaling import DEFAULT_TIMEOUT, ScalingAdapter
from .. import qos
from ..node_support import (OK, STATUS_PERIOD_SEC, WARN, Inputs, NodeParameters, ParamSpec,
                            StartupError, run)

T = Parameter.Type
PARAMETERS = (
    ParamSpec('override_topic', T.STRING, 'hrc/speed_override', "the bridge's speed override "
              '(std_msgs/Float64, 0..1)', read_only=True),
    ParamSpec('scaling_topic', T.STRING, 'speed_scaling_input', 'where the scaling factor '
              'goes (control_msgs/msg/SpeedScalingFactor, reliable, transient local): remap it '
              "to the controller's <controller>/speed_scaling_input", read_only=True),
    ParamSpec('override_timeout', T.DOUBLE, DEFAULT_TIMEOUT, 'seconds without an override '
              'before the factor is 0 (the arm pauses on its path)', range=(0.005, 10.0),
              read_only=True),
)
MISSING_CONTROL_MSGS = ('control_msgs is not installed: this node publishes '
                        'control_msgs/msg/SpeedScalingFactor and runs in a ROS install '
                        '(rosdep install, or apt install ros-jazzy-control-msgs)')


def scaling_message_class():
    """control_msgs/msg/SpeedScalingFactor, or StartupError where control_msgs is missing."""
    try:
        from control_msgs.msg import SpeedScalingFactor
    except ImportError:
        raise StartupError(MISSING_CONTROL_MSGS) from None
    return SpeedScalingFactor


class SpeedScalingNode(Node):
    NODE_NAME = 'speed_scaling'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        message = scaling_message_class()
        self.params = NodeParameters(self, PARAMETERS, lambda values: None)
        values = self.params.values()
        self.message = message
        self.adapter = ScalingAdapter(values['override_timeout'],
                                      f'the speed override on {values["override_topic"]}')
        self.publisher = self.create_publisher(message, values['scaling_topic'], qos.LATCHED)
        self.inputs = Inputs(self)
        self.inputs.subscribe(Float64, values['override_topic'], qos.RELIABLE,
                              lambda msg: msg.data, self._on_override, name='override',
                              with_stamp=True)
        self._publish(self.adapter.start())
        self.create_timer(self.adapter.watchdog_period, self._on_watchdog)
        self.create_timer(STATUS_PERIOD_SEC, self._on_status)
        self.get_logger().info(
            f'{values["override_topic"]} -> {self.resolve_topic_name(values["scaling_topic"])} '
            f'(SpeedScalingFactor, 0 after {self.adapter.timeout:g} s without an override)')

    def _on_override(self, value, stamp) -> None:
        self._publish(self.adapter.override(value, time.monotonic(), stamp.sequence))

    def _on_watchdog(self) -> None:
        self._publish(self.adapter.tick(time.monotonic()))

    def _publish(self, factor: float) -> None:
        self.publisher.publish(self.message(factor=float(factor)))

    def _on_status(self) -> None:
        values = self.adapter.values(time.monotonic())
        held = self.adapter.reason
        self.inputs.publish(self.inputs.status(
            'scaling', WARN if held else OK,
            f'factor {self.adapter.factor:g}' + (f': held at 0, {held}' if held else ''),
            {**values, 'subscribers': self.publisher.get_subscription_count(),
             **self.inputs.counts()}))

    def on_stop(self) -> None:
        """The last word: 0, so that a controller still running pauses."""
        self._publish(0.0)


def main(args=None):
    return run(SpeedScalingNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
