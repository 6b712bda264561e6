"""cell_view: the cell as markers for RViz and Foxglove, on `hrc/markers`.

Contract: subscribes `hrc/epoch`, `hrc/action`, `hrc/belief`, `hrc/distance_level`,
`hrc/task_state`, `human/skeleton` and the decision node's per-epoch status on /diagnostics
(for the reasons of a fail-safe dn); publishes `visualization_msgs/MarkerArray` on `hrc/markers`
in `robot_frame`: the whole picture of `core.view.scene` (the three safety circles, the human's
keypoints coloured by their distance level, the closest keypoint and its distance, a text panel
with the epoch, the action, the top beliefs over (em, ea) and the task state) after a DELETEALL,
so every message replaces the last. It draws at each action, when the decision node's report of
that epoch says it failed safe, and after a new skeleton at most `refresh_rate` times a second.
`hrc/markers` is reliable and transient local (depth 1): a viewer that connects late gets the
current picture at once. On SIGINT or SIGTERM it publishes a lone DELETEALL, waits (at most
`STOP_ACK_SEC`) until the subscribers have it, and stops, leaving the viewers empty.

It only listens: nothing of the decision loop waits for it or reads what it publishes
(bench/loop_latency.py --view measures the loop with it running).
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32
from visualization_msgs.msg import MarkerArray

from ...core.model import ACTIONS
from ...core.view import CellView, scene
from .. import conversions as conv
from .. import qos
from ..node_support import STATUS_PERIOD_SEC, Inputs, NodeParameters, ParamSpec, run
from .belief_estimator_node import (ROBOT_FRAME, ROBOT_REFERENCE_POINT, SAFETY_RADII,
                                    check_motion_parameters)

T = Parameter.Type
STOP_ACK_SEC = 1.0
PARAMETERS = (
    SAFETY_RADII, ROBOT_REFERENCE_POINT, ROBOT_FRAME,
    ParamSpec('refresh_rate', T.DOUBLE, 5.0, 'Hz: the most pictures a second drawn for new '
              'skeletons (each action is drawn at once)', range=(0.1, 100.0)),
    ParamSpec('decision_node', T.STRING, 'decision', 'name of the decision node whose '
              '/diagnostics status gives the reasons of a fail-safe dn', read_only=True),
)


class CellViewNode(Node):
    NODE_NAME = 'cell_view'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_motion_parameters, self._apply)
        self._apply(self.params.values())
        self.view = CellView()
        self.pictures = 0
        namespace = self.get_namespace().strip('/')
        self.decision_status = (f'{namespace}/' if namespace else '') \
            + f'{self.params.value("decision_node")}: decision'
        self.markers_pub = self.create_publisher(MarkerArray, 'hrc/markers', qos.LATCHED)
        self.inputs = Inputs(self)
        self.inputs.subscribe(UInt32, 'hrc/epoch', qos.RELIABLE, conv.epoch_from_msg,
                              self.view.epoch)
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              self._on_action)
        self.inputs.subscribe(Float64MultiArray, 'hrc/belief', qos.LATCHED, conv.belief_from_msg,
                              self._store('belief'))
        self.inputs.subscribe(UInt8, 'hrc/distance_level', qos.LATCHED,
                              conv.distance_level_from_msg, self._store('distance_level'))
        self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.LATCHED,
                              conv.task_state_from_msg, self._store('task_state'))
        self.inputs.subscribe(PoseArray, 'human/skeleton', qos.SENSOR_DATA,
                              lambda msg: conv.keypoints_from_msg(msg, self.robot_frame),
                              self.view.skeleton)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics,
                                 qos.RELIABLE)
        self.refresh = self.create_timer(1.0 / self.params.value('refresh_rate'), self._refresh)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        self.view.changed = True    # the first picture at the first refresh, once spinning

    def _apply(self, values) -> None:
        self.safety_radii = tuple(values['safety_radii'])
        self.robot_reference_point = tuple(values['robot_reference_point'])
        self.robot_frame = values['robot_frame']
        if hasattr(self, 'refresh'):
            self.refresh.timer_period_ns = int(1e9 / values['refresh_rate'])

    def _store(self, name: str):
        def store(value):
            setattr(self.view.state, name, value)
        return store

    # -- inputs ----------------------------------------------------------------------------
    def _on_action(self, action: int) -> None:
        if self.view.action(ACTIONS[action]):
            self.draw()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name != self.decision_status:
                continue
            values = conv.diagnostic_values(status)
            try:
                epoch = int(values.get('epoch', '0'))
            except ValueError:
                continue
            if self.view.decision_report(epoch, values.get('action', ''),
                                         values.get('faults', '')):
                self.draw()

    def _refresh(self) -> None:
        if self.view.due():
            self.draw()

    # -- output ----------------------------------------------------------------------------
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

    def _publish_status(self) -> None:
        state = self.view.state
        self.inputs.publish_health('view', {
            'epoch': state.epoch, 'action': state.action, 'pictures': self.pictures,
            'subscribers': self.markers_pub.get_subscription_count()})


def main(args=None):
    return run(CellViewNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
