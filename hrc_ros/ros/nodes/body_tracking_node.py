"""body_tracking: a body tracker's stream -> `human/joint_states` + `human/skeleton`.

Contract: subscribes `input_topic` (default `body_tracking_data`), a
`visualization_msgs/MarkerArray` per body frame as the Azure Kinect and Orbbec (Femto Bolt /
Mega, through Orbbec's K4A wrapper) body-tracking ROS drivers publish it (one marker per joint,
id = body id * 100 + joint index, positions in `camera_frame`; `core.cell.tracking`). For each
frame it publishes, in `robot_frame`, with the frame's capture stamp:

- `human/skeleton` (geometry_msgs/PoseArray): the `keypoint_joints` of every body in view, the
  followed body's first (the distance level counts everyone near the robot);
- `human/joint_states` (sensor_msgs/JointState): the followed body's six arm angles
  (`HUMAN_JOINTS`, rad) as positions and their velocities from successive frames (rad/s); not
  on a followed body's first frame (no velocity yet), never without the skeleton.

The camera's pose in `robot_frame` is the static transform `camera_translation` +
`camera_rotation` (x, y, z, w): there is no tf2 in the pip wheels. On a full ROS install it is
`ros2 run tf2_ros tf2_echo <robot_frame> <camera_frame>`, and a tf2 buffer lookup would belong
here (`conversions.body_frame_from_msg` then the transform). Both have no default: the node
refuses to start without them, since a wrong pose would give wrong distances.

The input is read as any external stream: best effort, volatile, so that a reliable publisher
(the Azure Kinect driver's QoS(1)) and a best-effort one both connect. A frame that gives the
estimator nothing (no body in view, NaN or missing joints, a foreign frame, a jump of metres in
one frame, a stamp that goes back) is dropped with a throttled warning and a /diagnostics
status; the estimator then lacks joint states, so the decision node fails safe (dn).

One tracker per cell: the node follows one publisher of `input_topic` (its writer's sequence
numbers, `core.protocol.StreamLock`); a second publisher's frames never make joint states nor
move the followed stream's stamps, and are reported as ERROR (`body_tracking: tracking`, kind
`second_stream`) naming the topic's publishers from the graph. When the two disagree about
where a person is, the nearer wins: a second stream's frame nearer to the robot than the
skeleton published is published at once (`core.cell.tracking`).

Why a node in front of the estimator and not inside it: the estimator keeps one input contract
(`human/*`, which bags, replays and the simulated cell use), the adapter can run next to the
camera driver, and a cell with another tracker swaps this node only. It costs one hop of the
middleware (well under a millisecond here, against 1/30 s between frames).
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker, MarkerArray

from ...core.decision.observation import HUMAN_JOINTS, check_keypoint_range
from ...core.cell.tracking import (DEFAULT_CONFIRM_FRAMES, DEFAULT_MAX_GAP, DEFAULT_MAX_SPEED,
                                   DEFAULT_SWITCH_MARGIN, K4ABT_JOINTS, BodyTracking,
                                   RigidTransform, joint_indices)
from ...core.protocol import ERROR, Report, Stamp
from .. import conversions as conv
from .. import qos
from ..node_support import (STATUS_PERIOD_SEC, WARNING_THROTTLE_SEC, Inputs, NodeParameters,
                            ParamSpec, StartupError, check_array, check_core, run)
from ..sources import TopicPublishers
from .belief_estimator_node import ROBOT_FRAME, ROBOT_REFERENCE_POINT

T = Parameter.Type
DEFAULT_CAMERA_FRAME = 'depth_camera_link'     # the Azure Kinect driver's, without tf_prefix
CAMERA_PARAMETERS = (
    ParamSpec('camera_frame', T.STRING, DEFAULT_CAMERA_FRAME, 'frame_id of the body-tracking '
              "markers: the driver's depth camera frame (tf_prefix + depth_camera_link)",
              read_only=True, constraints='non-empty'),
    ParamSpec('camera_translation', T.DOUBLE_ARRAY, [], "metres: the camera frame's origin in "
              'robot_frame (tf2_echo <robot_frame> <camera_frame>: Translation)', read_only=True,
              constraints='3 finite values; required'),
    ParamSpec('camera_rotation', T.DOUBLE_ARRAY, [], "the camera frame's orientation in "
              'robot_frame, a unit quaternion x, y, z, w (tf2_echo: Rotation in Quaternion)',
              read_only=True, constraints='4 finite values of norm 1; required'),
)
PARAMETERS = CAMERA_PARAMETERS + (
    ROBOT_REFERENCE_POINT, ROBOT_FRAME,
    ParamSpec('input_topic', T.STRING, 'body_tracking_data', 'the body tracker\'s MarkerArray '
              'topic', read_only=True, constraints='non-empty'),
    ParamSpec('follow_body', T.INTEGER, -1, 'body whose arm angles feed the belief: -1 the '
              'nearest to the robot (with switch_margin hysteresis), else that body id',
              range=(-1, 2**31 - 1)),
    ParamSpec('switch_margin', T.DOUBLE, DEFAULT_SWITCH_MARGIN, 'metres another body must be '
              'nearer than the followed one before the nearest rule switches to it',
              range=(0.0, 10.0)),
    # The robot side's safety reads these (the bridge's capsules, the jump gate): fixed while
    # the node runs (a runtime set of keypoint_joints: [PELVIS] hid every hand from SSM)
    ParamSpec('keypoint_joints', T.STRING_ARRAY, [], 'joints of each body that make up '
              f"human/skeleton (names of {', '.join(K4ABT_JOINTS[:3])}, ...; [] = all 32)",
              read_only=True),
    ParamSpec('max_speed', T.DOUBLE, DEFAULT_MAX_SPEED, 'm/s a body centroid may move; a '
              'faster move is a tracking jump (frame dropped until it holds confirm_frames '
              'frames)', range=(0.1, 100.0), read_only=True),
    ParamSpec('max_gap', T.DOUBLE, DEFAULT_MAX_GAP, 'seconds between frames beyond which '
              'velocities restart and the followed body is chosen again; also how long the '
              'followed stream may be silent before another publisher is followed, and how '
              'long a frame not taken counts for the nearer person', range=(0.001, 60.0),
              read_only=True),
    ParamSpec('confirm_frames', T.INTEGER, DEFAULT_CONFIRM_FRAMES, 'frames a relocated body '
              'must hold before it is taken as its new place', range=(1, 1000),
              read_only=True),
)


def check_camera(values) -> str | None:
    for name in ('camera_translation', 'camera_rotation'):
        if name in values and len(values[name]) == 0:
            return (f'{name} must be set: the pose of camera_frame in robot_frame (on a ROS '
                    'install: ros2 run tf2_ros tf2_echo <robot_frame> <camera_frame>)')
    if 'camera_translation' in values and 'camera_rotation' in values:
        return check_core(values, 'camera_rotation', lambda q: RigidTransform.from_parameters(
            values['camera_translation'], q))
    return ('camera_frame must not be empty' if values.get('camera_frame', 'x') == '' else None)


def check_parameters(values) -> str | None:
    return (check_camera(values) or check_array(values, 'robot_reference_point', 3)
            or check_core(values, 'robot_reference_point',
                          lambda point: check_keypoint_range(np.array(point)[None],
                                                             'robot_reference_point'))
            or check_core(values, 'keypoint_joints',
                          lambda names: joint_indices(names or K4ABT_JOINTS))
            or ('input_topic must not be empty' if values.get('input_topic', 'x') == '' else None)
            or ('robot_frame must not be empty' if values.get('robot_frame', 'x') == ''
                else None))


def camera_transform(params: NodeParameters) -> RigidTransform:
    """The camera's pose from the parameters; StartupError when they are missing or bad."""
    values = {name: params.value(name) for name in ('camera_translation', 'camera_rotation')}
    reason = check_camera(values)
    if reason:
        raise StartupError(reason)
    return RigidTransform.from_parameters(values['camera_translation'],
                                          values['camera_rotation'])


class BodyTrackingNode(Node):
    NODE_NAME = 'body_tracking'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_parameters, self._apply)
        values = self.params.values()
        self.camera_frame = values['camera_frame']
        self.robot_frame = values['robot_frame']
        self.tracking = BodyTracking(
            camera_transform(self.params), values['robot_reference_point'],
            values['keypoint_joints'] or K4ABT_JOINTS)
        self._apply(values)
        self.published = {'skeleton': 0, 'joint_states': 0}
        self.skeleton_pub = self.create_publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
        self.joint_pub = self.create_publisher(JointState, 'human/joint_states', qos.SENSOR_DATA)
        self.inputs = Inputs(self)
        self.input_topic = values['input_topic']
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.input_publishers = TopicPublishers(self, self.input_topic)
        self._second_reported: float | None = None
        self.inputs.subscribe(MarkerArray, self.input_topic, qos.SENSOR_DATA, self._convert,
                              self._on_frame, name='body_tracking', with_stamp=True,
                              on_matched=self.input_publishers.refresh)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)

    def _apply(self, values) -> None:
        machine = self.tracking
        machine.follow_body = int(values['follow_body'])
        machine.switch_margin = float(values['switch_margin'])
        machine.max_speed = float(values['max_speed'])
        machine.max_gap = float(values['max_gap'])
        machine.confirm_frames = int(values['confirm_frames'])
        machine.keypoints = joint_indices(values['keypoint_joints'] or K4ABT_JOINTS)

    def _convert(self, msg: MarkerArray):
        frame = conv.body_frame_from_msg(msg, self.camera_frame)
        stamp = next((m.header.stamp for m in msg.markers if m.action == Marker.ADD), None)
        return frame, stamp

    def _on_frame(self, converted, source: Stamp) -> None:
        frame, stamp = converted
        others = self.tracking.lock.others
        try:
            step = self.tracking.frame(frame, source, self.steady.now().nanoseconds * 1e-9)
        finally:
            if self.tracking.lock.others > others:
                self._second_stream()
        if stamp is None:                  # a second stream's person while nobody is followed
            stamp = conv.seconds_to_stamp(step.stamp)
        for report in step.reports:
            self.inputs.report(report)
        self.skeleton_pub.publish(conv.keypoints_to_msg(step.keypoints, stamp, self.robot_frame))
        self.published['skeleton'] += 1
        if step.velocities is not None:
            self.joint_pub.publish(conv.joint_state_to_msg(HUMAN_JOINTS, step.velocities,
                                                           step.angles, stamp))
            self.published['joint_states'] += 1

    def _second_stream(self) -> None:
        """A frame of another publisher than the one followed: ERROR naming the topic's
        publishers, at most once per WARNING_THROTTLE_SEC."""
        now = time.monotonic()
        if self._second_reported is not None \
                and now - self._second_reported < WARNING_THROTTLE_SEC:
            return
        self._second_reported = now
        names = self.input_publishers.names(others_only=False)
        self.inputs.report(Report(
            ERROR, 'tracking', f'a second body-tracking stream publishes on {self.input_topic} '
            f'(publishers: {", ".join(names) or "none left on the graph"}); following one (one '
            'tracker per cell): the other makes no joint states and counts for the distance '
            'only where it sees a person nearer. Stop one.',
            {'input_topic': self.input_topic, 'publishers': ', '.join(names),
             'frames_of_other_streams': self.tracking.lock.others}, kind='second_stream'))

    def _publish_status(self) -> None:
        machine = self.tracking
        self.inputs.publish_health('tracking', {
            'input_topic': self.input_topic, 'followed': machine.followed,
            'published_skeletons': self.published['skeleton'],
            'published_joint_states': self.published['joint_states'],
            'frames_of_other_streams': machine.lock.others})


def main(args=None):
    return run(BodyTrackingNode, args)


if __name__ == '__main__':
    raise SystemExit(main())

