"""tracker_sim: a synthetic body tracker, so the body-tracking input runs without a camera.

Contract: subscribes `sim/human/joint_states` and `sim/human/skeleton` (the simulated cell's
motion, `cell_sim_node` started with ``-r human/joint_states:=sim/human/joint_states -r
human/skeleton:=sim/human/skeleton``) and publishes `body_tracking_data` as the Azure Kinect
driver does (one body, id 1, 32 SPHERE markers, id = 100 + joint, `camera_frame`, reliable
depth 1): for each joint state, one body frame with that state's stamp, from
`core.cell.tracking.SyntheticBody`: its arm angles turn at exactly the joint state's speeds, and
its closest keypoint walks (at most `walk_speed`) into the band of the latest skeleton's distance
level, so `body_tracking_node` in front of the estimator hands it the same velocity levels and,
by each epoch's end, the same distance level as the simulated cell would directly. A joint state
with NaN velocities (the cell's `nan_velocity` fault) gives a frame whose arm joints are NaN, a
tracker glitch that `body_tracking_node` drops as the estimator drops NaN velocities.

The camera parameters are `body_tracking_node`'s and must be the same (the stream is placed in
the camera frame with the inverse of that transform); `config/body_tracking_sim_params.yaml`
sets both.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from visualization_msgs.msg import MarkerArray

from ...core.decision.observation import distance_level
from ...core.cell.tracking import ARM_ANGLES, DEFAULT_WALK_SPEED, JOINT_INDEX, SyntheticBody
from .. import conversions as conv
from .. import qos
from ..node_support import (STATUS_PERIOD_SEC, Inputs, NodeParameters, ParamSpec, StartupError,
                            check_array, run)
from .belief_estimator_node import ROBOT_FRAME, ROBOT_REFERENCE_POINT, SAFETY_RADII
from .body_tracking_node import CAMERA_PARAMETERS, camera_transform, check_camera

T = Parameter.Type
BODY_ID = 1
# The Azure Kinect driver's publisher: rclcpp's QoS(1), reliable and volatile.
DRIVER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
ARM_JOINTS = sorted({JOINT_INDEX[j] for _, a, b in ARM_ANGLES for j in a + b}
                    - {JOINT_INDEX['pelvis'], JOINT_INDEX['spine_chest']})
PARAMETERS = CAMERA_PARAMETERS + (
    SAFETY_RADII, ROBOT_REFERENCE_POINT, ROBOT_FRAME,
    ParamSpec('walk_speed', T.DOUBLE, DEFAULT_WALK_SPEED, 'm/s the body walks into a new '
              'distance band', range=(0.1, 20.0)),
    ParamSpec('direction', T.DOUBLE_ARRAY, [1.0, 0.0], 'horizontal direction (x, y) from the '
              'robot reference point to the body, robot_frame', read_only=True,
              constraints='2 finite values, not both 0'),
)


def check_parameters(values) -> str | None:
    reason = check_camera(values) or check_array(values, 'direction', 2)
    if reason is None and 'direction' in values and not any(values['direction']):
        reason = 'direction must not be [0, 0]'
    return reason


class TrackerSimNode(Node):
    NODE_NAME = 'tracker_sim'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_parameters, self._apply)
        values = self.params.values()
        self.to_camera = camera_transform(self.params).inverse()
        self.camera_frame = values['camera_frame']
        self.robot_frame = values['robot_frame']
        try:
            self.body = SyntheticBody(values['robot_reference_point'], values['safety_radii'],
                                      list(values['direction']) + [0.0], values['walk_speed'])
        except ValueError as exc:
            raise StartupError(f'synthetic body: {exc}') from None
        self.level: int | None = None
        self.frames = 0
        self.pub = self.create_publisher(MarkerArray, 'body_tracking_data', DRIVER_QOS)
        self.inputs = Inputs(self)
        self.inputs.subscribe(PoseArray, 'sim/human/skeleton', qos.SENSOR_DATA,
                              lambda msg: conv.keypoints_from_msg(msg, self.robot_frame),
                              self._on_skeleton, name='skeleton')
        self.inputs.subscribe(JointState, 'sim/human/joint_states', qos.SENSOR_DATA,
                              lambda msg: msg, self._on_joint_state, name='joint_states')
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)

    def _apply(self, values) -> None:
        if hasattr(self, 'body'):
            self.body.walk_speed = float(values['walk_speed'])

    def _on_skeleton(self, keypoints: np.ndarray) -> None:
        self.level = distance_level(keypoints, self.body.reference_point, self.body.radii)

    def _on_joint_state(self, msg: JointState) -> None:
        if self.level is None:
            return                  # no skeleton yet: nowhere to stand
        stamp = conv.stamp_to_seconds(msg.header.stamp)
        if self.body.stamp is not None and not stamp > self.body.stamp:
            raise conv.MessageError(f'joint state stamp {stamp:.9f} s is not after the previous '
                                    f'one ({self.body.stamp:.9f} s)')
        speeds = np.asarray(msg.velocity, dtype=float)
        if speeds.shape != (len(ARM_ANGLES),):
            raise conv.MessageError(f'joint state has {speeds.size} velocities, expected '
                                    f'{len(ARM_ANGLES)}')
        if np.all(np.isfinite(speeds)):
            joints = self.body.step(speeds, self.level, stamp)
        elif self.body.rho is None:
            return                  # a glitch before the first frame: nothing to show
        else:                       # a glitch: the arms at NaN, the body where it was
            joints = self.body.place(self.body.local_joints(self.body.angles), self.body.rho)
            joints[ARM_JOINTS] = np.nan
        self.pub.publish(conv.body_frame_to_msg({BODY_ID: self.to_camera.apply(joints)},
                                                msg.header.stamp, self.camera_frame))
        self.frames += 1

    def _publish_status(self) -> None:
        self.inputs.publish_health('tracker', {'frames': self.frames, 'level': self.level,
                                               'rho': self.body.rho})


def main(args=None):
    return run(TrackerSimNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
