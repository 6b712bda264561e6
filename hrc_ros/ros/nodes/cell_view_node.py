"""cell_view: the cell as markers for RViz and Foxglove, on `hrc/markers`.

Contract: reads `hrc/epoch`, `hrc/action`, `hrc/belief`, `hrc/distance_level`,
`hrc/task_state`, `human/skeleton` and the decision node's per-epoch status on /diagnostics (for
the reasons of a fail-safe dn); publishes `visualization_msgs/MarkerArray` on `hrc/markers` in
`robot_frame`: the whole picture of `core.cell.view.scene` (the three safety circles, the human's
keypoints coloured by their distance level, the closest keypoint and its distance, a text panel
with the epoch, the action, the top beliefs over (em, ea) and the task state) after a DELETEALL,
so every message replaces the last. `hrc/markers` is reliable and transient local (depth 1): a
viewer that connects late gets the current picture at once. On SIGINT or SIGTERM it publishes a
lone DELETEALL, waits (at most `STOP_ACK_SEC`) until the subscribers have it, and stops, leaving
the viewers empty.

It only listens, and at its own pace: its inputs are `SampledInputs`, taken `refresh_rate` times
a second in publication order (`core.cell.view.CellView` pairs each action with its epoch's
inputs),
and a picture is drawn at a tick when something changed. So it never wakes for a message, its
share of the CPU does not grow with the rate of the epochs or of the tracker, nothing of the
decision loop waits for it, and bench/loop_latency.py --view-pairs measures the loop with and
without it.

With `robot` true (the cell with the arm, docs/ROBOT.md) it also reads the arm's `joint_states`
and `hrc/separation` and draws the arm's link capsules at the latest joint state, S_p as a
translucent shell around them, the person's body capsules (`keypoint_joints`) and the
separation segment between the two closest points (`core.cell.view.arm_scene`).
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from sensor_msgs.msg import JointState
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32
from visualization_msgs.msg import MarkerArray

from ...core.model import ACTIONS
from ...core.cell.view import CellView, scene
from .. import conversions as conv
from .. import qos
from ..node_support import (STATUS_PERIOD_SEC, Inputs, NodeParameters, ParamSpec, SampledInputs,
                            run)
from ..sources import EpochReady
from .belief_estimator_node import (ROBOT_FRAME, ROBOT_REFERENCE_POINT, SAFETY_RADII,
                                    check_motion_parameters)
from .robot_bridge_node import KEYPOINT_JOINTS, ROBOT_DESCRIPTION, check_names, load_description

T = Parameter.Type
STOP_ACK_SEC = 1.0
# Reader histories deep enough for the messages of several epochs between two ticks; volatile,
# so that any publisher of the state topics matches (qos.STATE_INPUT's reasoning).
SAMPLED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
PARAMETERS = (
    SAFETY_RADII, ROBOT_REFERENCE_POINT, ROBOT_FRAME,
    ParamSpec('refresh_rate', T.DOUBLE, 5.0, 'Hz: how often the inputs are read and, if '
              'anything changed, the picture drawn', range=(0.1, 100.0)),
    ParamSpec('decision_node', T.STRING, 'decision', 'name of the decision node whose '
              '/diagnostics status gives the reasons of a fail-safe dn', read_only=True),
    ParamSpec('robot', T.BOOL, False, "draw the cell with the arm: the arm's capsules at its "
              'joint_states, the S_p shell and the separation of hrc/separation, the '
              "person's body capsules (docs/ROBOT.md)", read_only=True),
    KEYPOINT_JOINTS, ROBOT_DESCRIPTION,
)


def check_parameters(values) -> str | None:
    return check_motion_parameters(values) or check_names(values)


class CellViewNode(Node):
    NODE_NAME = 'cell_view'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_parameters, self._apply)
        self._apply(self.params.values())
        self.view = CellView()
        self.pictures = 0
        namespace = self.get_namespace().strip('/')
        self.decision_status = (f'{namespace}/' if namespace else '') \
            + f'{self.params.value("decision_node")}: decision'
        self.markers_pub = self.create_publisher(MarkerArray, 'hrc/markers', qos.LATCHED)
        self.inputs = Inputs(self)
        self.sampled = SampledInputs(self, self.inputs)
        subscribe = self.sampled.subscribe
        # a listener that must not miss epoch 1 says when its reader has matched the clock
        self.epoch_ready = EpochReady(self, reader_node=self.sampled.helper)
        self.epoch_ready.readers.append(subscribe(UInt32, 'hrc/epoch', SAMPLED,
                                                  conv.epoch_from_msg))
        subscribe(String, 'hrc/action', SAMPLED,
                  lambda msg: ACTIONS[conv.action_from_msg(msg)])
        subscribe(Float64MultiArray, 'hrc/belief', SAMPLED, conv.belief_from_msg)
        subscribe(UInt8, 'hrc/distance_level', SAMPLED, conv.distance_level_from_msg)
        subscribe(UInt8MultiArray, 'hrc/task_state', SAMPLED, conv.task_state_from_msg)
        subscribe(PoseArray, 'human/skeleton', qos.SENSOR_DATA,
                  lambda msg: conv.keypoints_from_msg(msg, self.robot_frame), latest_only=True)
        subscribe(DiagnosticArray, '/diagnostics', SAMPLED, self._decision_report,
                  name='decision')
        self.arm = None
        if self.params.value('robot'):
            self._robot_inputs(subscribe)
        self.refresh = self.create_timer(1.0 / self.params.value('refresh_rate'), self._refresh)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)

    def _robot_inputs(self, subscribe) -> None:
        from ...core.robot.arm import Arm, body_capsules
        from ...core.robot.bridge import JointStateReader
        values = self.params.values()
        reader = JointStateReader(load_description(values['robot_description']))
        self.arm = Arm()
        joints = tuple(values['keypoint_joints']) or None

        def arm_capsules(msg: JointState):
            q, _ = reader.read(msg.name, msg.position)
            return self.arm.segments(q), self.arm.radii

        def body(msg: PoseArray):
            try:
                caps = body_capsules(conv.keypoints_from_msg(msg, self.robot_frame), joints)
            except ValueError as exc:
                raise conv.MessageError(f'skeleton: {exc}') from None
            return caps.segments, caps.radii
        subscribe(JointState, 'joint_states', qos.SENSOR_DATA, arm_capsules, name='arm',
                  latest_only=True)
        subscribe(PoseArray, 'human/skeleton', qos.SENSOR_DATA, body, name='body',
                  latest_only=True)
        subscribe(Float64MultiArray, 'hrc/separation', qos.SENSOR_DATA, conv.separation_from_msg,
                  name='separation', latest_only=True)

    def _apply(self, values) -> None:
        self.safety_radii = tuple(values['safety_radii'])
        self.robot_reference_point = tuple(values['robot_reference_point'])
        self.robot_frame = values['robot_frame']
        if hasattr(self, 'refresh'):
            self.refresh.timer_period_ns = int(1e9 / values['refresh_rate'])

    def _decision_report(self, msg: DiagnosticArray):
        """(epoch, action, faults) of the decision node's per-epoch status in `msg`; None for
        the other statuses (dropped by `CellView`'s caller below)."""
        for status in msg.status:
            if status.name == self.decision_status:
                values = conv.diagnostic_values(status)
                epoch = values.get('epoch', '')
                if epoch.isdigit() and int(epoch) > 0:
                    return int(epoch), values.get('action', ''), values.get('faults', '')
        return None

    # -- the picture -----------------------------------------------------------------------
    def _refresh(self) -> None:
        now = time.monotonic()          # ages are the viewer's: wall time since arrival
        for _, name, value in self.sampled.take():
            if value is not None:
                self.view.feed(name, value, now)
        self.view.age(now)
        if self.view.changed:
            self.draw()

    def draw(self) -> None:
        shapes = scene(self.view.state, self.safety_radii, self.robot_reference_point)
        self.markers_pub.publish(conv.markers_to_msg(shapes, self.robot_frame,
                                                     self.get_clock().now().to_msg()))
        self.view.drawn()
        self.pictures += 1

    def on_stop(self) -> None:
        """The last word (node_support.run): leave the viewers empty."""
        self.markers_pub.publish(conv.delete_all_markers_msg())
        self.markers_pub.wait_for_all_acked(Duration(seconds=STOP_ACK_SEC))

    def destroy_node(self):
        self.sampled.destroy()
        return super().destroy_node()

    def _publish_status(self) -> None:
        state = self.view.state
        self.inputs.publish_health('view', {
            'epoch': state.epoch, 'action': state.action, 'pictures': self.pictures,
            'subscribers': self.markers_pub.get_subscription_count()})


def main(args=None):
    return run(CellViewNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
