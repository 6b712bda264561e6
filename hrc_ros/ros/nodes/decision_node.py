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
from ...core.protocol import (ClockStart, DecisionGate, EpochFollower, Report, Stamp,
                              timeout_ns)
from ...core.selection import POMDP_SELECTORS, SELECTORS, ActionSelector
from .. import conversions as conv
from .. import qos
from ..node_support import (CONFIG, DeadlineTimer, Inputs, ParamSpec, StartupError, config_path,
                            control_clock, node_setup, run)

EPOCH_SOURCES = ('timer', 'topic')
INPUT_FRACTION = 0.5   # input_timeout 0: this fraction of the epoch period
STALE_PERIODS = 3.0    # stale_timeout 0: this many epoch periods
GRAPH_WAIT_MIN = 3.0   # stale_timeout 0: seconds the clock may wait for DDS discovery at least
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
    ParamSpec('input_timeout', T.DOUBLE, 0.0, "seconds to wait for an epoch's inputs; 0 = "
              f'{INPUT_FRACTION:g} x epoch_period', range=(0.0, 3600.0),
              constraints='0 (follow the period) or < epoch_period'),
    ParamSpec('stale_timeout', T.DOUBLE, 0.0, 'seconds after which an input is stale, and the '
              'longest wait for the graph before epoch 1; 0 = '
              f'{STALE_PERIODS:g} x epoch_period (and a graph wait of at least '
              f'{GRAPH_WAIT_MIN:g} s)', range=(0.0, 86400.0),
              constraints='0 (follow the period) or > epoch_period'),
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
    period = values.get('epoch_period')
    timeout, stale = values.get('input_timeout', 0.0), values.get('stale_timeout', 0.0)
    if period is not None and timeout and not timeout < period:
        return (f'input_timeout ({timeout} s) must be shorter than epoch_period ({period} s); '
                f'0 follows the period ({INPUT_FRACTION:g} x)')
    if period is not None and stale and not stale > period:
        return (f'stale_timeout ({stale} s) must be longer than epoch_period ({period} s), or '
                'every input would be stale at every epoch; 0 follows the period '
                f'({STALE_PERIODS:g} x)')
    return None


def timeouts_ns(values) -> tuple[int, int]:
    """(input_timeout, stale_timeout) in ns: the explicit values, or fractions of the period."""
    period_ns = int(values['epoch_period'] * 1e9)
    return (timeout_ns(values['input_timeout'], INPUT_FRACTION, period_ns, 0.0),
            timeout_ns(values['stale_timeout'], STALE_PERIODS, period_ns, 0.0))


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
        input_ns, stale_ns = timeouts_ns(values)
        self.gate = DecisionGate(self.selector.select, stale_ns, input_ns,
                                 fresh_at_epoch=self.epoch_source == 'timer')
        self.stale_timeout = values['stale_timeout']
        self.clock_start = ClockStart(self._now(), self._graph_wait_ns(),
                                      running=self.epoch_source == 'topic')
        self.epochs = EpochFollower()
        self.last_action: int | None = None

        self.action_pub = self.create_publisher(String, 'hrc/action', qos.RELIABLE)
        self.inputs = Inputs(self)
        self.input_subscriptions = [
            self.inputs.subscribe(Float64MultiArray, 'hrc/belief', qos.STATE_INPUT,
                                  self._guard('belief', conv.belief_from_msg),
                                  self._input('belief')),
            self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.STATE_INPUT,
                                  self._guard('task_state', self._task_state_from_msg),
                                  self._input('task_state')),
            self.inputs.subscribe(UInt8, 'hrc/distance_level', qos.STATE_INPUT,
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
                                  self._on_epoch, with_stamp=True)
        self.get_logger().info(
            f'policy {self.policy.path} (configuration {self.config.source}, sha256 '
            f'{self.config.policy_hash[:12]}), selector {values["selector"]}, epochs from '
            f'{self.epoch_source}')

    @property
    def epoch(self) -> int:
        return self.gate.epoch

    def _graph_wait_ns(self) -> int:
        """The longest wait for the graph: an explicit stale_timeout, else 3 periods but at
        least GRAPH_WAIT_MIN (DDS discovery does not follow the epoch period)."""
        if self.stale_timeout > 0:
            return self.gate.stale_timeout_ns
        return max(self.gate.stale_timeout_ns, int(GRAPH_WAIT_MIN * 1e9))

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
        self.gate.input_timeout_ns, self.gate.stale_timeout_ns = timeouts_ns(values)
        self.stale_timeout = values['stale_timeout']
        self.clock_start.stale_timeout_ns = self._graph_wait_ns()
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
                self._act(self.gate.malformed(name, conv.cap(str(exc)), self._now()))
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

    def _other_sources(self) -> list[str]:
        """Other publishers of hrc/epoch or hrc/action: a second decision node, say (also one
        with this node's name: one publisher per topic of this name is this node's own)."""
        me = (self.get_namespace(), self.get_name())
        found = []
        for topic in (self.epoch_pub.topic_name, self.action_pub.topic_name):
            own = 1
            for info in self.get_publishers_info_by_topic(topic):
                if own and (info.node_namespace, info.node_name) == me:
                    own = 0
                    continue
                name = f'{info.node_namespace.rstrip("/")}/{info.node_name}'
                gid = '.'.join(f'{b:02x}' for b in list(info.endpoint_gid)[:12])
                found.append(f'{name} on {topic} (gid {gid})')
        return found

    def _on_tick(self) -> None:
        tick = self.clock_start.tick(self._now(), self._graph_ready, self._graph,
                                     self._other_sources, self.get_fully_qualified_name())
        if tick.report is not None:
            self.inputs.report(tick.report)
        if tick.start_epoch:
            k = self.epoch + 1
            self._act(self.gate.begin(k, self._now()))
            self.epoch_pub.publish(conv.epoch_to_msg(k))

    def _on_epoch(self, k: int, stamp: Stamp) -> None:
        restart = self.epochs.check(k, stamp)     # another source: InputError, dropped
        if restart is not None:
            self.inputs.report(restart)
        self.epochs.take(k, stamp)
        self._act(self.gate.begin(k, self._now()))

    # -- the decision ----------------------------------------------------------------------
    def _act(self, decisions) -> None:
        for decision in decisions:
            start = time.perf_counter()
            self.action_pub.publish(conv.action_to_msg(decision.action))
            publish_ms = (time.perf_counter() - start) * 1e3
            self.last_action = decision.action
            values = {**decision.values(), 'selector': self.selector.method,
                      'input_timeout_s': self.gate.input_timeout_ns * 1e-9,
                      'stale_timeout_s': self.gate.stale_timeout_ns * 1e-9,
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
