"""belief_estimator: human motion -> velocity level O, distance level d and the belief b.

Per epoch k (docs/DESIGN.md, ROS epoch protocol), on `hrc/epoch` k:

    O_k = window_level(levels of the joint-state samples of window k)
    b_k = initial(O_k)                         at the first epoch
    b_k = update(b_{k-1}, a_{k-1}, O_k)        afterwards (a_{k-1}: the last `hrc/action`)
    d_k = distance_level(latest skeleton of window k)

Window k holds the samples received since epoch k-1's signal that were published before
epoch k's signal (publication = the writer's source timestamp). A sample published after the
signal belongs to window k+1 even if it is taken first: rclpy runs callbacks that are ready
together in subscription order, so a node that wakes up late would otherwise count the cell's
first sample after its reaction (or, in a replay, the next played sample) in the closing window.

and publishes `hrc/distance_level` d_k, `hrc/observation` O_k and `hrc/belief` b_k. Each joint
state sample gets its level at once (`velocity_level` of its velocities), so the node keeps
three counters per window and the last `RECENT` (publication time, level) pairs, not the
samples, so its memory is bounded whatever the rate.

Degraded inputs, never fatal: a malformed message is dropped (warning + diagnostic). A window
with fewer than `min_window_samples` valid joint states (a sensor dropout; the threshold also
keeps the one or two samples streamed just before the cell reacted to the last action from
deciding an observation alone) publishes no observation and no belief (the decision node then falls back
to dn); the belief is carried forward by the prediction step alone (an uninformative
observation), so the next epoch's update stays consistent with the actions taken. A window with
no skeleton publishes no distance level (the decision node's copy ages and goes stale). A
missing a_{k-1} is taken as dn, the robot controller's safe default.

Topics: subscribes `human/joint_states`, `human/skeleton` (sensor data QoS), `hrc/action`,
`hrc/epoch`; publishes `hrc/belief`, `hrc/distance_level` (latched), `hrc/observation`,
`/diagnostics` (per-second status: rates, lag = receive time - header stamp of the joint
states, drops).
"""

from __future__ import annotations

from collections import deque

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt32

from .. import conversions as conv
from .. import qos
from ..belief import BELIEF_MODES, BeliefFilter
from ..model import DN, HRCModel
from ..observation import (DEFAULT_SAFETY_RADII, DEFAULT_VELOCITY_THRESHOLDS, distance_level,
                           velocity_level, window_level)
from .common import (STATUS_PERIOD_SEC, WARN, Inputs, NodeParameters, ParamSpec, StartupError,
                     check_array, check_core, load_node_config, run)

LEVELS = np.array([1, 2, 3])
RECENT = 2048   # samples per stream remembered with their publication time, to split a
#                window: 2 s of joint states at 1 kHz, a minute of skeletons at 30 Hz
NO_EVIDENCE = np.ones(9)   # the likelihood of an epoch without observation: predict only

T = Parameter.Type
CONFIG = ParamSpec('config', T.STRING, '', "model configuration YAML ('' = the shipped "
                   'default.yaml)', read_only=True)
VELOCITY_THRESHOLDS = ParamSpec(
    'velocity_thresholds', T.DOUBLE_ARRAY, list(DEFAULT_VELOCITY_THRESHOLDS),
    'rad/s, mean |joint velocity| of a sample: O=1 below the first, O=2 below the second, '
    'else O=3', constraints='2 values, positive, strictly increasing')
SAFETY_RADII = ParamSpec(
    'safety_radii', T.DOUBLE_ARRAY, list(DEFAULT_SAFETY_RADII),
    'metres: collision / inner / middle circle radii around the robot reference point',
    constraints='3 values, positive, strictly increasing')
ROBOT_REFERENCE_POINT = ParamSpec(
    'robot_reference_point', T.DOUBLE_ARRAY, [0.0, 0.0, 0.0],
    'metres, robot base frame: centre of the safety circles', constraints='3 finite values')
ROBOT_FRAME = ParamSpec(
    'robot_frame', T.STRING, conv.ROBOT_BASE_FRAME, 'frame_id of human/skeleton: the robot '
    'base frame the keypoints and robot_reference_point are in (e.g. cell1/base_link)',
    read_only=True, constraints='non-empty')
PARAMETERS = (
    CONFIG,
    ParamSpec('belief_mode', T.STRING, '', "belief filter: 'bayes' or 'table' ('' = the "
              "configuration's observation.mode)", constraints="'', 'bayes' or 'table'"),
    ParamSpec('min_window_samples', T.INTEGER, 3, 'joint-state samples an epoch window needs '
              'for an observation; fewer count as a sensor dropout (no observation)',
              range=(1, 100000)),
    VELOCITY_THRESHOLDS, SAFETY_RADII, ROBOT_REFERENCE_POINT, ROBOT_FRAME,
)


def check_motion_parameters(values) -> str | None:
    """Thresholds, radii and reference point (shared with cell_sim, which must match)."""
    return (check_core(values, 'velocity_thresholds', lambda t: velocity_level([0.0], t))
            or check_core(values, 'safety_radii',
                          lambda r: distance_level(np.zeros((1, 3)), (0.0, 0.0, 0.0), r))
            or check_array(values, 'robot_reference_point', 3)
            or ('robot_frame must not be empty' if values.get('robot_frame', 'x') == ''
                else None))


def check_parameters(values) -> str | None:
    mode = values.get('belief_mode', '')
    if mode not in ('',) + BELIEF_MODES:
        return f"belief_mode must be '', {' or '.join(BELIEF_MODES)}, got {mode!r}"
    return check_motion_parameters(values)


class BeliefEstimatorNode(Node):
    NODE_NAME = 'belief_estimator'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_parameters, self._apply_parameters)
        self.config = load_node_config(self.params.value('config'))
        self.model = HRCModel(self.config)
        self._apply_parameters(self.params.values())

        self.epoch = 0
        self.belief: np.ndarray | None = None
        self.observation: int | None = None
        self.distance_level: int | None = None
        self._level_counts = np.zeros(3, dtype=np.int64)   # samples of O = 1, 2, 3 in the window
        self._recent_levels: deque = deque(maxlen=RECENT)  # (published_ns, level), this window
        self._recent_distances: deque = deque(maxlen=RECENT)  # (published_ns, d), this window
        self._action: int | None = None                    # a_{k-1}: last action of the window
        self._previous_sample: conv.JointSample | None = None
        self._lag = LagStats()

        self.belief_pub = self.create_publisher(Float64MultiArray, 'hrc/belief', qos.LATCHED)
        self.distance_pub = self.create_publisher(UInt8, 'hrc/distance_level', qos.LATCHED)
        self.observation_pub = self.create_publisher(UInt8, 'hrc/observation', qos.RELIABLE)
        self.inputs = Inputs(self)
        self.inputs.subscribe(JointState, 'human/joint_states', qos.SENSOR_DATA,
                              conv.joint_sample_from_msg, self._on_joint_sample,
                              with_published=True)
        frame = self.params.value('robot_frame')
        self.inputs.subscribe(PoseArray, 'human/skeleton', qos.SENSOR_DATA,
                              lambda msg: conv.keypoints_from_msg(msg, frame),
                              self._on_keypoints, with_published=True)
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              self._on_action)
        self.inputs.subscribe(UInt32, 'hrc/epoch', qos.RELIABLE, conv.epoch_from_msg,
                              self._on_epoch, with_published=True)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)

    def _apply_parameters(self, values) -> None:
        mode = values['belief_mode'] or None
        try:
            self.filter = BeliefFilter(self.model, mode=mode)
        except ValueError as exc:
            raise StartupError(f'belief filter: {exc}') from None
        self.min_window_samples = values['min_window_samples']
        self.velocity_thresholds = tuple(values['velocity_thresholds'])
        self.safety_radii = tuple(values['safety_radii'])
        self.robot_reference_point = tuple(values['robot_reference_point'])

    # -- inputs ----------------------------------------------------------------------------
    def _on_joint_sample(self, sample: conv.JointSample, published_ns: int) -> None:
        previous = self._previous_sample
        if sample.position is not None:
            self._previous_sample = sample
        velocities = conv.joint_velocities(sample, previous)
        if velocities is None:
            return
        level = velocity_level(velocities, self.velocity_thresholds)
        self._level_counts[level - 1] += 1
        self._recent_levels.append((published_ns, level))
        if sample.stamp > 0.0:
            self._lag.add(self.get_clock().now().nanoseconds * 1e-9 - sample.stamp)

    def _on_keypoints(self, keypoints: np.ndarray, published_ns: int) -> None:
        self._recent_distances.append((published_ns, distance_level(
            keypoints, self.robot_reference_point, self.safety_radii)))

    def _close_window(self, signal_ns: int) -> int | None:
        """Split off the samples published after epoch k's signal (they open window k+1);
        return d_k (None without a skeleton in window k)."""
        later = [(t, level) for t, level in self._recent_levels if t >= signal_ns]
        self._level_counts[:] = 0
        for _, level in later:
            self._level_counts[level - 1] += 1
        self._recent_levels = deque(later, maxlen=RECENT)
        window = [(t, d) for t, d in self._recent_distances if t < signal_ns]
        self._recent_distances = deque(((t, d) for t, d in self._recent_distances
                                        if t >= signal_ns), maxlen=RECENT)
        return max(window)[1] if window else None

    def _on_action(self, action: int) -> None:
        self._action = action

    def _on_epoch(self, k: int, signal_ns: int) -> None:
        self.inputs.epoch_order(k, self.epoch)    # a restarted count is followed
        self.epoch = k
        action = DN if self._action is None else self._action
        statuses = []
        # The window's counts, less the samples published after the signal.
        counts = self._level_counts.copy()
        window_distance = self._close_window(signal_ns)
        counts -= self._level_counts
        if window_distance is not None:
            self.distance_level = window_distance
            self.distance_pub.publish(conv.distance_level_to_msg(self.distance_level))
        else:
            statuses.append(self.inputs.status(
                'epoch', WARN, f'epoch {k}: no skeleton since the last epoch; distance level '
                'not published', {'epoch': k}))
        if counts.sum() >= self.min_window_samples:
            self.observation = window_level(np.repeat(LEVELS, counts))
            self.belief = (self.filter.initial(self.observation) if self.belief is None
                           else self.filter.update(self.belief, action, self.observation))
            self.observation_pub.publish(conv.observation_to_msg(self.observation))
            self.belief_pub.publish(conv.belief_to_msg(self.belief))
        else:
            self.observation = None
            if self.belief is not None:
                self.belief = self.filter.update(self.belief, action, NO_EVIDENCE)
            statuses.append(self.inputs.status(
                'epoch', WARN, f'epoch {k}: no joint states to observe ('
                f'{int(counts.sum())} valid samples in its window, fewer than '
                f'{self.min_window_samples}); belief not published (predicted only)',
                {'epoch': k}))
        if statuses:
            self.get_logger().warning(statuses[0].message, throttle_duration_sec=5.0)
            self.inputs.publish(*statuses)
        self._action = None

    # -- health ----------------------------------------------------------------------------
    def _publish_status(self) -> None:
        lag = self._lag.take()
        values = {'epoch': self.epoch, 'observation': self.observation,
                  'distance_level': self.distance_level,
                  'belief': None if self.belief is None else np.round(self.belief, 4),
                  'belief_mode': self.filter.mode,
                  'joint_states_in_period': lag['count'],
                  'joint_state_lag_ms_mean': lag['mean_ms'],
                  'joint_state_lag_ms_max': lag['max_ms']}
        self.inputs.publish_health('estimator', values)


class LagStats:
    """Receive time - header stamp of the joint states, accumulated per status period."""

    def __init__(self):
        self.count, self.total, self.max = 0, 0.0, float('-inf')

    def add(self, lag: float) -> None:
        self.count += 1
        self.total += lag
        self.max = max(self.max, lag)

    def take(self) -> dict:
        out = {'count': self.count,
               'mean_ms': 1e3 * self.total / self.count if self.count else None,
               'max_ms': 1e3 * self.max if self.count else None}
        self.__init__()
        return out


def main(args=None):
    return run(BeliefEstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
