"""decision: the robot's decision maker; owns the epoch clock (docs/DESIGN.md).

Contract: every `epoch_period` it publishes `hrc/epoch` k (`epoch_source: timer`; with `topic`
it follows a replay's `hrc/epoch`), takes this epoch's `hrc/belief`, `hrc/task_state` and
`hrc/distance_level`, and publishes a_k on `hrc/action`: the policy's action for (belief, x_k)
by the `selector`, or `dn` when an input is missing, stale, malformed or late, or d = 0. One
/diagnostics status per epoch says which and why, with the policy identity and the timings
(`compute_ms`: fault checks and selection; `publish_ms`). The rules are
`core.protocol.DecisionGate` and `ClockStart`; this node owns the topics, the policy file,
the parameters and the timers. It refuses to start (exit 1, one line) on a missing policy or
one solved for another configuration.
"""

from __future__ import annotations

import time

from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32

from ...core.policy import PolicyError, default_policy_path, load_policy
from ...core.protocol import ClockStart, DecisionGate, EpochFollower, Report
from ...core.selection import POMDP_SELECTORS, SELECTORS, ActionSelector
from .. import conversions as conv
from .. import qos
from ..node_support import (CONFIG, DeadlineTimer, Inputs, ParamSpec, StartupError, config_path,
                            control_clock, node_setup, run)

EPOCH_SOURCES = ('timer', 'topic')
T = Parameter.Type
PARAMETERS = (
    CONFIG,
    ParamSpec('policy', T.STRING, '', "policy file solved for the configuration ('' = the "
              'shipped policy solved for config, e.g. policies/paper.npz for paper.yaml; else '
              'default.npz)', read_only=True),
    ParamSpec('selector', T.STRING, 'paper', 'action selection from the belief: '
              + ', '.join(SELECTORS), constraints=' or '.join(SELECTORS)),
    ParamSpec('epoch_period', T.DOUBLE, 1.0, 'seconds between decision epochs',
              range=(0.01, 3600.0)),
    ParamSpec('input_timeout', T.DOUBLE, 0.5, "seconds to wait for an epoch's inputs; below "
              'epoch_period', range=(0.001, 3600.0), constraints='< epoch_period'),
    ParamSpec('stale_timeout', T.DOUBLE, 3.0, 'seconds after which an input is stale',
              range=(0.001, 86400.0)),
    ParamSpec('epoch_source', T.STRING, 'timer', "'timer': publish hrc/epoch; 'topic': follow "
              'hrc/epoch (replay)', read_only=True, constraints=' or '.join(EPOCH_SOURCES)),
    ParamSpec('min_epoch_subscribers', T.INTEGER, 1, 'timer mode: subscribers of hrc/epoch '
              'to discover before epoch 1 (e.g. 3 with a recorder besides the task manager and '
              'the belief estimator); the clock starts anyway after stale_timeout',
              read_only=True, range=(1, 1000)),
)


def check_parameters(values) -> str | None:
    if 'selector' in values and values['selector'] not in SELECTORS:
        return f'selector must be one of {", ".join(SELECTORS)}, got {values["selector"]!r}'
    if 'epoch_source' in values and values['epoch_source'] not in EPOCH_SOURCES:
        return (f'epoch_source must be one of {", ".join(EPOCH_SOURCES)}, got '
                f'{values["epoch_source"]!r}')
    period, timeout = values.get('epoch_period'), values.get('input_timeout')
    if period is not None and timeout is not None and not timeout < period:
        return f'input_timeout ({timeout} s) must be shorter than epoch_period ({period} s)'
    return None


class DecisionNode(Node):
    NODE_NAME = 'decision'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.selector = None
        self.params, values, self.config, self.model = node_setup(
            self, PARAMETERS, self._check_parameters, self._apply_parameters)
        policy_path = values['policy'] or str(default_policy_path(self.config))
        try:
            self.policy = load_policy(policy_path, self.config)
        except PolicyError as exc:
            raise StartupError(
                f'{exc} (expected a policy for configuration {config_path(values["config"])}, '
                f'sha256 {self.config.policy_hash})') from None
        try:   # pomdp and fib read the shipped POMDP policy solved for the configuration
            self.selector = ActionSelector(self.model, self.policy, method=values['selector'])
        except PolicyError as exc:
            raise StartupError(f'selector {values["selector"]}: {exc}') from None
        self.epoch_source = values['epoch_source']
        self.min_epoch_subscribers = values['min_epoch_subscribers']
        self.clock = control_clock(self)   # epochs, waits and input ages
        self.gate = DecisionGate(self.selector.select, int(values['stale_timeout'] * 1e9),
                                 int(values['input_timeout'] * 1e9),
                                 fresh_at_epoch=self.epoch_source == 'timer')
        self.clock_start = ClockStart(self._now(), self.gate.stale_timeout_ns,
                                      running=self.epoch_source == 'topic')
        self.epochs = EpochFollower()
        self.last_action: int | None = None

        self.action_pub = self.create_publisher(String, 'hrc/action', qos.RELIABLE)
        self.inputs = Inputs(self)
        self.input_subscriptions = [
            self.inputs.subscribe(Float64MultiArray, 'hrc/belief', qos.LATCHED,
                                  self._guard('belief', conv.belief_from_msg),
                                  self._input('belief')),
            self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.LATCHED,
                                  self._guard('task_state', self._task_state_from_msg),
                                  self._input('task_state')),
            self.inputs.subscribe(UInt8, 'hrc/distance_level', qos.LATCHED,
                                  self._guard('distance_level', conv.distance_level_from_msg),
                                  self._input('distance_level')),
        ]
        self.deadline = DeadlineTimer(self, lambda now: self._act(self.gate.expire(now)))
        if self.epoch_source == 'timer':
            self.epoch_pub = self.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
            self.epoch_timer = self.create_timer(values['epoch_period'], self._on_tick,
                                                 clock=self.clock)
        else:
            self.epoch_pub = None
            self.epoch_timer = None
            self.inputs.subscribe(UInt32, 'hrc/epoch', qos.RELIABLE, conv.epoch_from_msg,
                                  self._on_epoch)
        self.get_logger().info(
            f'policy {self.policy.path} (configuration {self.config.source}, sha256 '
            f'{self.config.policy_hash[:12]}), selector {values["selector"]}, epochs from '
            f'{self.epoch_source}')

    @property
    def epoch(self) -> int:
        return self.gate.epoch

    def _now(self) -> int:
        return self.clock.now().nanoseconds

    def _check_parameters(self, values) -> str | None:
        reason = check_parameters(values)
        if reason is None and self.selector is not None \
                and values.get('selector') in POMDP_SELECTORS:
            try:
                self.selector.prepare(values['selector'])    # loads the POMDP policy
            except PolicyError as exc:
                return f'selector {values["selector"]}: {exc}'
        return reason

    def _apply_parameters(self, values) -> None:
        self.selector.set_method(values['selector'])   # qmdp's Q table is built here
        self.gate.stale_timeout_ns = int(values['stale_timeout'] * 1e9)
        self.gate.input_timeout_ns = int(values['input_timeout'] * 1e9)
        self.clock_start.stale_timeout_ns = self.gate.stale_timeout_ns
        if self.epoch_timer is not None:
            self.epoch_timer.timer_period_ns = int(values['epoch_period'] * 1e9)
        self.deadline.sync(self.gate.deadline)

    def _task_state_from_msg(self, msg):
        return conv.task_state_from_msg(msg, self.model.rho, self.model.sigma)

    # -- inputs ----------------------------------------------------------------------------
    def _guard(self, name: str, convert):
        """A conversion that also tells the gate when the input is malformed."""
        def convert_or_mark(msg):
            try:
                return convert(msg)
            except conv.MessageError as exc:
                self._act(self.gate.malformed(name, str(exc), self._now()))
                raise
        return convert_or_mark

    def _input(self, name: str):
        def store(value):
            self._act(self.gate.received(name, value, self._now()))
        return store

    # -- the epoch clock -------------------------------------------------------------------
    def _graph(self) -> dict:
        return {'epoch_subscribers': self.epoch_pub.get_subscription_count(),
                **{f'{name}_publishers': sub.get_publisher_count()
                   for name, sub in zip(self.gate.slots, self.input_subscriptions)}}

    def _graph_ready(self) -> bool:
        return (self.epoch_pub.get_subscription_count() >= self.min_epoch_subscribers
                and all(sub.get_publisher_count() > 0 for sub in self.input_subscriptions))

    def _on_tick(self) -> None:
        tick = self.clock_start.tick(self._now(), self._graph_ready, self._graph)
        if tick.report is not None:
            self.inputs.report(tick.report)
        if tick.start_epoch:
            k = self.epoch + 1
            self._act(self.gate.begin(k, self._now()))
            self.epoch_pub.publish(conv.epoch_to_msg(k))

    def _on_epoch(self, k: int) -> None:
        restart = self.epochs.check(k)     # a restarted replay is followed
        if restart is not None:
            self.inputs.report(restart)
        self.epochs.take(k)
        self._act(self.gate.begin(k, self._now()))

    # -- the decision ----------------------------------------------------------------------
    def _act(self, decisions) -> None:
        for decision in decisions:
            start = time.perf_counter()
            self.action_pub.publish(conv.action_to_msg(decision.action))
            publish_ms = (time.perf_counter() - start) * 1e3
            self.last_action = decision.action
            values = {**decision.values(), 'selector': self.selector.method,
                      'publish_ms': publish_ms,
                      'policy_file': self.policy.path,
                      **({'pomdp_policy_file': getattr(self.selector.pomdp, 'path', '')}
                         if self.selector.method in POMDP_SELECTORS else {}),
                      'policy_config_sha256': self.policy.config_sha256,
                      'config': self.config.source,
                      'config_sha256': self.config.policy_hash,
                      **self.inputs.counts()}
            self.inputs.report(Report(decision.level, 'decision', decision.message, values,
                                      log=bool(decision.faults), kind='fail_safe'))
        self.deadline.sync(self.gate.deadline)


def main(args=None):
    return run(DecisionNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
