"""belief_estimator: human motion -> velocity level O, distance level d and the belief b.

Contract (docs/DESIGN.md): subscribes `human/joint_states` and `human/skeleton` (sensor data
QoS), `hrc/action` and `hrc/epoch`; on epoch k publishes `hrc/distance_level` d_k (latched),
`hrc/observation` O_k and `hrc/belief` b_k (latched) of the window that epoch k closes, and a
per-second status (rates, lag = receive time - header stamp of the joint states, drops). Each
joint state gets its velocity level at once (`core.decision.observation.velocity_level`; velocities
derived from positions and stamps where the message has none) and each skeleton its distance
level (closest keypoint, `robot_frame`); the windows, O_k and the belief update are
`core.protocol.EstimatorEpochs`. A malformed message is dropped with a diagnostic; a window
without enough joint states or without a skeleton publishes nothing for that input, so the
decision node fails safe.

`distance_source` says what d is the band of. `reference_point` (the default): the closest
keypoint's distance to `robot_reference_point`. `arm_links` (the cell with the arm,
docs/ROBOT.md): the separation between the arm's link capsules, at its latest `joint_states`
(sensor_msgs/JointState, the arm's, as `robot_bridge_node` reads them), and the person's body
capsules of each skeleton (`keypoint_joints`: K4ABT names, bones between them; []: a sphere
around each keypoint), the batch cell's rule (`core.robot.links.LinkDistance`). Without a fresh
arm state (none, or older than the skeleton by more than the robot description's
`joint_state_timeout`, both by their header stamps) d is 0, the
collision level, so the decision node fails safe, with a WARN on /diagnostics when that
begins and an OK when the arm's state is back.

It announces the configuration its filter runs on `hrc/estimator_config` (latched:
`Config.belief_hash` and the file), so the decision node can flag a mismatch. A new `config`
(`ros2 param set /belief_estimator config <file>`) is checked in the parameter callback by the
decision node's rule (`core.swap.check_swap`: it must load and describe the same cell size,
rho and sigma; and its belief filter must build), its filter (observation likelihood, emotion
chains) is built off the epoch path (`BackgroundLoad`) and takes over at the next epoch
signal, from the belief it has reached.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray, String, UInt8, UInt8MultiArray

from ...core.pomdp.belief import BeliefFilter
from ...core.config import BELIEF_MODES
from ...core.model import HRCModel
from ...core.decision.observation import (DEFAULT_SAFETY_RADII, DEFAULT_VELOCITY_THRESHOLDS,
                                          check_keypoint_range, distance_level, velocity_level)
from ...core.protocol import (ERROR, ESTIMATOR_HOLD, OK, WARN, EstimatorEpochs, Report, Stamp,
                              check_timeout_order)
from ...core.swap import ACCEPTED, check_swap
from .. import conversions as conv
from .. import qos
from ..node_support import (LIVE_CONFIG, STATUS_PERIOD_SEC, BackgroundLoad, DeadlineTimer, Inputs,
                            ParamSpec, StartupError, check_array, check_core, load_node_config,
                            node_setup, run)
from ..sources import subscribe_epochs
from .robot_bridge_node import (KEYPOINT_JOINTS, ROBOT_DESCRIPTION, check_names, load_description,
                                stamp_ns)

T = Parameter.Type
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
MOTION_PARAMETERS = (VELOCITY_THRESHOLDS, SAFETY_RADII, ROBOT_REFERENCE_POINT, ROBOT_FRAME)
DISTANCE_SOURCES = ('reference_point', 'arm_links')
ARM_PARAMETERS = (
    ParamSpec('distance_source', T.STRING, 'reference_point', 'what the distance level d is '
              'the band of: reference_point (the closest keypoint to robot_reference_point) or '
              "arm_links (the separation between the arm's links at its latest joint_states "
              "and the person's body capsules; no fresh arm state: d = 0)", read_only=True,
              constraints="'reference_point' or 'arm_links'"),
    KEYPOINT_JOINTS,
    ROBOT_DESCRIPTION,
)
PARAMETERS = (
    LIVE_CONFIG,
    ParamSpec('belief_mode', T.STRING, '', "belief filter: 'bayes', 'table' or 'posterior' "
              "(bayes and the human's answers and distance moves: the exact posterior the "
              "pomdp selector plans with; '' = the configuration's observation.mode)",
              constraints="'', 'bayes', 'table' or 'posterior'"),
    ParamSpec('min_window_samples', T.INTEGER, 3, 'joint-state samples an epoch window needs '
              'for an observation; fewer count as a sensor dropout (no observation)',
              range=(1, 100000)),
    ParamSpec('task_state_timeout', T.DOUBLE, 0.0, 'posterior mode: seconds after hrc/epoch '
              'k that b_k waits for the task state x_k (then the answer is left out). 0 = '
              f'{ESTIMATOR_HOLD.fraction:g} x the epoch period seen on hrc/epoch '
              f'({ESTIMATOR_HOLD.fallback_s:g} s before two epochs); an explicit value must be '
              "longer than the task manager's input_timeout and shorter than the decision "
              "node's", range=(0.0, 3600.0)),
) + MOTION_PARAMETERS + ARM_PARAMETERS


def check_motion_parameters(values) -> str | None:
    """Thresholds, radii and reference point (shared with cell_sim, which must match)."""
    return (check_core(values, 'velocity_thresholds', lambda t: velocity_level([0.0], t))
            or check_core(values, 'safety_radii',
                          lambda r: distance_level(np.zeros((1, 3)), (0.0, 0.0, 0.0), r))
            or check_array(values, 'robot_reference_point', 3)
            or check_core(values, 'robot_reference_point',
                          lambda point: check_keypoint_range(np.array(point)[None],
                                                             'robot_reference_point'))
            or ('robot_frame must not be empty' if values.get('robot_frame', 'x') == ''
                else None))


def check_parameters(values) -> str | None:
    mode = values.get('belief_mode', '')
    if mode not in ('',) + BELIEF_MODES:
        return f"belief_mode must be '', {' or '.join(BELIEF_MODES)}, got {mode!r}"
    source = values.get('distance_source', DISTANCE_SOURCES[0])
    if source not in DISTANCE_SOURCES:
        return f"distance_source must be {' or '.join(DISTANCE_SOURCES)}, got {source!r}"
    return check_motion_parameters(values) or check_names(values)


def link_distance(values):
    """The arm_links machine for the node's parameters."""
    from ...core.robot.links import LinkDistance
    return LinkDistance(load_description(values['robot_description']),
                        values['safety_radii'], values['keypoint_joints'] or None)


class BeliefEstimatorNode(Node):
    NODE_NAME = 'belief_estimator'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.windows: EstimatorEpochs | None = None
        self.config_value: str | None = None      # set below: changes are checked from then on
        self.params, values, self.config, self.model = node_setup(
            self, PARAMETERS, self._check_parameters, self._apply_parameters)
        self.loader = BackgroundLoad('belief_estimator')
        self.config_pub = self.create_publisher(String, 'hrc/estimator_config', qos.LATCHED)
        self._apply_parameters(values)
        self.config_value = values['config']
        self._announce()
        self._previous_sample: conv.JointSample | None = None
        self._lag = LagStats()
        self.links = link_distance(values) if values['distance_source'] == 'arm_links' else None
        self._arm_reason: str | None = None       # why the arm's links cannot be used now
        self.separation: float | None = None      # S of the latest skeleton (arm_links)

        self.belief_pub = self.create_publisher(Float64MultiArray, 'hrc/belief', qos.LATCHED)
        self.distance_pub = self.create_publisher(UInt8, 'hrc/distance_level', qos.LATCHED)
        self.observation_pub = self.create_publisher(UInt8, 'hrc/observation', qos.RELIABLE)
        self.inputs = Inputs(self)
        self.inputs.subscribe(JointState, 'human/joint_states', qos.SENSOR_DATA,
                              conv.joint_sample_from_msg, self._on_joint_sample,
                              with_published=True)
        frame = self.params.value('robot_frame')
        self.inputs.subscribe(PoseArray, 'human/skeleton', qos.SENSOR_DATA,
                              lambda msg: (conv.keypoints_from_msg(msg, frame),
                                           stamp_ns(msg.header.stamp)),
                              self._on_keypoints, with_published=True)
        if self.links is not None:
            self.inputs.subscribe(JointState, 'joint_states', qos.SENSOR_DATA, lambda msg: msg,
                                  self._on_arm_state, name='arm_joint_states')
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              lambda action, published_ns: self.windows.action(action,
                                                                               published_ns),
                              with_published=True)
        self.epoch_publishers = subscribe_epochs(self.inputs, lambda: self.windows.epochs,
                                                 self._on_epoch)
        self._order_reported: str | None = None
        # posterior mode: x_k shows the human's answer to a_{k-1}, if one was published
        # (volatile: any publisher, as for the decision node; docs/ROBUSTNESS.md). The answer
        # is subscribed first: rclpy takes the messages ready at one wake in that order.
        self.inputs.subscribe(Bool, 'hrc/human_response', qos.RELIABLE,
                              conv.human_response_from_msg,
                              lambda _accepted, published_ns: self._publish(
                                  self.windows.response(published_ns)),
                              with_published=True)
        self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.RELIABLE,
                              self._task_state_from_msg, self._on_task_state,
                              with_published=True)
        self.hold = DeadlineTimer(self, lambda now: self._publish(self.windows.expire(now)))
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)

    def _period_s(self) -> float | None:
        period = None if self.windows is None else self.windows.epochs.period.period_ns
        return None if period is None else period * 1e-9

    def _check_parameters(self, values) -> str | None:
        reason = check_parameters(values) or check_timeout_order(
            self._period_s(), {ESTIMATOR_HOLD: values.get('task_state_timeout', 0.0)})
        if reason or self.config_value is None or 'config' not in values:
            return reason
        verdict = check_swap(self.model.rho, self.model.sigma, self.config_value,
                             values['config'])
        if verdict.verdict != ACCEPTED:
            return verdict.reason or None
        try:
            BeliefFilter(HRCModel(verdict.config), mode=values['belief_mode'] or None)
        except ValueError as exc:
            return f'config refused: {exc}'
        return None

    def _check_timeout_order(self) -> None:
        """An explicit task_state_timeout that the period learnt since makes too long or too
        short: WARN once (it was accepted before the period was known)."""
        explicit = self.windows.task_state_timeout_s
        reason = check_timeout_order(self._period_s(), {ESTIMATOR_HOLD: explicit}) \
            if explicit > 0 else None
        if reason and reason != self._order_reported:
            self.inputs.report(Report(WARN, 'timeouts', f'{reason} (epoch period seen on '
                                      f'hrc/epoch: {self._period_s():g} s)',
                                      {'task_state_timeout': explicit}, kind='order'))
        self._order_reported = reason

    def _announce(self) -> None:
        self.config_pub.publish(conv.config_identity_to_msg(self.config.belief_hash,
                                                            self.config.source))

    def _apply_parameters(self, values) -> None:
        if self.config_value is not None and values['config'] == self.config_value:
            self.loader.start(lambda: None)      # back to the one in use: nothing pending
        elif self.config_value is not None:
            value, mode = values['config'], values['belief_mode'] or None

            def load():
                config = load_node_config(value)
                model = HRCModel(config)
                return value, config, model, BeliefFilter(model, mode=mode)
            self.loader.start(load)
        try:
            belief_filter = BeliefFilter(self.model, mode=values['belief_mode'] or None)
        except ValueError as exc:
            raise StartupError(f'belief filter: {exc}') from None
        if self.windows is None:
            self.windows = EstimatorEpochs(belief_filter, values['min_window_samples'])
        self.windows.filter = belief_filter
        self.windows.task_state_timeout_s = values['task_state_timeout']
        self.windows.min_window_samples = values['min_window_samples']
        self.velocity_thresholds = tuple(values['velocity_thresholds'])
        self.safety_radii = tuple(values['safety_radii'])
        self.robot_reference_point = tuple(values['robot_reference_point'])
        if getattr(self, 'links', None) is not None:
            self.links.radii = self.safety_radii

    @property
    def belief(self):
        return self.windows.belief

    # -- inputs ----------------------------------------------------------------------------
    def _on_joint_sample(self, sample: conv.JointSample, published_ns: int) -> None:
        previous = self._previous_sample
        if sample.position is not None:
            self._previous_sample = sample
        velocities = conv.joint_velocities(sample, previous)
        if velocities is None:
            return
        self.windows.sample(velocity_level(velocities, self.velocity_thresholds), published_ns)
        if sample.stamp > 0.0:
            self._lag.add(self.get_clock().now().nanoseconds * 1e-9 - sample.stamp)

    def _on_keypoints(self, skeleton: tuple, published_ns: int) -> None:
        keypoints, stamp = skeleton
        if self.links is None:
            self.windows.skeleton(distance_level(keypoints, self.robot_reference_point,
                                                 self.safety_radii), published_ns)
            return
        level = self.links.level(keypoints, stamp)
        self.separation = None if level.separation is None else level.separation.distance
        self._arm_state(level.reason)
        self.windows.skeleton(level.d, published_ns)

    def _on_arm_state(self, msg: JointState) -> None:
        self.links.joint_state(msg.name, msg.position, stamp_ns(msg.header.stamp),
                               self.get_clock().now().nanoseconds)

    def _arm_state(self, reason: str) -> None:
        """Report when the arm's links stop (WARN) or start again (OK) to give d."""
        was_stale = bool(self._arm_reason)
        self._arm_reason = reason
        if reason and not was_stale:
            self.inputs.report(Report(WARN, 'arm links', f'{reason}: distance level 0 (the '
                                      "arm's links cannot be placed) until it is back",
                                      {'reason': reason}, kind='stale_arm'))
        elif was_stale and not reason:
            self.inputs.report(Report(OK, 'arm links', "the arm's joint states are back: d is "
                                      "the band of the separation to the arm's links",
                                      log=False, kind='stale_arm'))

    def _swap(self, k: int) -> None:
        """At epoch k's signal: a configuration loaded meanwhile takes over the filter."""
        done = self.loader.take()
        if done is None:
            return
        loaded, error = done
        if loaded is None and error is None:      # the parameter went back to the one in use
            return
        if error is not None:
            self.inputs.report(Report(ERROR, 'estimator', f'refused configuration: {error}; '
                                      f'still running {self.config.source}', {'epoch': k}))
            self.set_parameters([Parameter('config', value=self.config_value)])
            return
        old = self.config.source
        self.config_value, self.config, self.model, self.windows.filter = loaded
        self._announce()
        self.inputs.report(Report(OK, 'estimator', f'epoch {k}: belief filter now from '
                                  f'{self.config.source} (before: {old})',
                                  {'epoch': k, 'config': self.config.source}, kind='swap'))

    def _on_epoch(self, k: int, stamp: Stamp) -> None:
        self._swap(k)
        self._announce()        # again each epoch: state is republished (qos.STATE_INPUT)
        self._publish(self.windows.epoch_signal(k, stamp, self.hold.clock.now().nanoseconds))
        self._check_timeout_order()

    def _task_state_from_msg(self, msg):
        return conv.task_state_from_msg(msg, self.model.rho, self.model.sigma)

    def _on_task_state(self, state: dict, published_ns: int) -> None:
        self._publish(self.windows.task_state(state, published_ns))

    def _publish(self, step) -> None:
        if step is not None:
            if step.distance_level is not None:
                self.distance_pub.publish(conv.distance_level_to_msg(step.distance_level))
            if step.observation is not None:
                self.observation_pub.publish(conv.observation_to_msg(step.observation))
            if step.belief is not None:
                self.belief_pub.publish(conv.belief_to_msg(step.belief))
            for report in step.reports:
                self.inputs.report(report)
        self.hold.sync(self.windows.deadline)

    # -- health ----------------------------------------------------------------------------
    def _publish_status(self) -> None:
        lag = self._lag.take()
        w = self.windows
        values = {'epoch': w.epoch, 'observation': w.observation,
                  'distance_level': w.distance_level,
                  'belief': None if w.belief is None else np.round(w.belief, 4),
                  'belief_mode': w.filter.mode,
                  'config': self.config.source,
                  'config_belief_sha256': self.config.belief_hash,
                  'joint_states_in_period': lag['count'],
                  'joint_state_lag_ms_mean': lag['mean_ms'],
                  'joint_state_lag_ms_max': lag['max_ms']}
        if self.links is not None:
            values.update({'distance_source': 'arm_links', 'separation_m': self.separation,
                           'arm_state': self._arm_reason or 'fresh'})
        self.inputs.publish_health('estimator', values)


class LagStats:
    """Receive time - header stamp of the joint states, accumulated per status period."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.count, self.total, self.max = 0, 0.0, float('-inf')

    def add(self, lag: float) -> None:
        self.count += 1
        self.total += lag
        self.max = max(self.max, lag)

    def take(self) -> dict:
        """The period's count, mean and max (ms), and a fresh period."""
        out = {'count': self.count,
               'mean_ms': 1e3 * self.total / self.count if self.count else None,
               'max_ms': 1e3 * self.max if self.count else None}
        self.reset()
        return out


def main(args=None):
    return run(BeliefEstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
