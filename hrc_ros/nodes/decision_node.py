"""decision: the robot's decision maker; owns the epoch clock (docs/DESIGN.md).

Each epoch k: publish `hrc/epoch` k (`epoch_source: timer`; with `topic` it follows the
`hrc/epoch` of a replay instead), wait up to `input_timeout` for this epoch's `hrc/belief`,
`hrc/task_state` and `hrc/distance_level`, then select

    a_k = ActionSelector(policy, selector).select(b_k, x_k),  x_k = (tp .. bc, d_k)

and publish it on `hrc/action`, with one /diagnostics status per epoch: the action, the
selector's scores, the belief, the observable state, input ages, the policy identity (file and
configuration SHA-256), the time from the epoch to the decision, the decision's compute time
(fault checks and selection, `compute_ms`) and the time to publish the action (`publish_ms`).

Fail-safe: a_k = dn, and the status is ERROR with the faults, when an input

- was never received (missing),
- is older than `stale_timeout` (stale),
- was malformed (its last message was dropped),
- did not arrive for this epoch within `input_timeout` (belief and task state must be fresh:
  received after epoch k was published; the distance level may be an older, not stale, one),

and a_k = dn with a WARN status when d = 0 (the human is inside the collision circle). The
epoch's decision is taken as soon as each input has answered (with a good or a malformed
message), or at `input_timeout` (a `Deadline`: inputs already waiting when it expires are taken
first).

Clock. Epochs, waits and input ages use `common.control_clock`: the monotonic clock, or the
ROS clock under `use_sim_time` (read at start-up).

Start-up. The policy file must exist and match the configuration; otherwise the node logs
which file and which configuration it expected and exits with status 1. In timer mode the clock
starts one `epoch_period` after the graph is ready (`min_epoch_subscribers` subscribers of
`hrc/epoch` and a publisher of each input are discovered) or after `stale_timeout`,
whichever comes first, so
that the first epochs are not lost to discovery; until then it publishes no action.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32

from .. import conversions as conv
from .. import qos
from ..model import ACTIONS, DN, TASK_VARIABLES, HRCModel
from ..policy import PolicyError, default_policy_path, load_policy
from ..selection import SELECTORS, ActionSelector
from .common import (ERROR, OK, WARN, Deadline, Inputs, NodeParameters, ParamSpec, StartupError,
                     config_path, control_clock, load_node_config, run)

EPOCH_SOURCES = ('timer', 'topic')
T = Parameter.Type
PARAMETERS = (
    ParamSpec('config', T.STRING, '', "model configuration YAML ('' = the shipped "
              'default.yaml)', read_only=True),
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


@dataclass
class InputSlot:
    """The latest good value of one input and the sequence numbers of its messages."""

    topic: str
    value: object = None
    received_ns: int | None = None   # node clock at the last good message
    seq: int = 0                     # event number of the last good message
    bad_seq: int = 0                 # event number of the last malformed message
    bad_reason: str = ''


class DecisionNode(Node):
    NODE_NAME = 'decision'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = NodeParameters(self, PARAMETERS, check_parameters, self._apply_parameters)
        values = self.params.values()
        self.config = load_node_config(values['config'])
        self.model = HRCModel(self.config)
        policy_path = values['policy'] or str(default_policy_path(self.config))
        try:
            self.policy = load_policy(policy_path, self.config)
        except PolicyError as exc:
            raise StartupError(
                f'{exc} (expected a policy for configuration {config_path(values["config"])}, '
                f'sha256 {self.config.policy_hash})') from None
        self.selector = ActionSelector(self.model, self.policy, method=values['selector'])
        self.epoch_source = values['epoch_source']
        self.stale_timeout = values['stale_timeout']
        self.min_epoch_subscribers = values['min_epoch_subscribers']

        self.epoch = 0
        self.pending = False           # waiting for the inputs of self.epoch
        self.last_action: int | None = None
        self._seq = 0
        self._fresh_since = 0          # inputs with seq > this belong to the pending epoch
        self._epoch_started_ns = 0
        self.clock = control_clock(self)   # epochs, waits and input ages
        self._started_ns = self.clock.now().nanoseconds
        self._clock_running = self.epoch_source == 'topic'
        self._graph_ready_tick = False
        self.slots = {'belief': InputSlot('hrc/belief'),
                      'task_state': InputSlot('hrc/task_state'),
                      'distance_level': InputSlot('hrc/distance_level')}

        self.action_pub = self.create_publisher(String, 'hrc/action', qos.RELIABLE)
        self.inputs = Inputs(self)
        self.input_subscriptions = [
            self.inputs.subscribe(Float64MultiArray, 'hrc/belief', qos.LATCHED, self._guard(
                'belief', conv.belief_from_msg), self._input('belief')),
            self.inputs.subscribe(UInt8MultiArray, 'hrc/task_state', qos.LATCHED, self._guard(
                'task_state', self._task_state_from_msg), self._input('task_state')),
            self.inputs.subscribe(UInt8, 'hrc/distance_level', qos.LATCHED, self._guard(
                'distance_level', conv.distance_level_from_msg), self._input('distance_level')),
        ]
        if self.epoch_source == 'timer':
            self.epoch_pub = self.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
            self.epoch_timer = self.create_timer(values['epoch_period'], self._on_tick,
                                                  clock=self.clock)
        else:
            self.epoch_pub = None
            self.epoch_timer = None
            self.inputs.subscribe(UInt32, 'hrc/epoch', qos.RELIABLE, conv.epoch_from_msg,
                                  self._on_epoch)
        self.input_deadline = Deadline(self, values['input_timeout'], self._on_input_timeout)
        self.get_logger().info(
            f'policy {self.policy.path} (configuration {self.config.source}, sha256 '
            f'{self.config.policy_hash[:12]}), selector {values["selector"]}, epochs from '
            f'{self.epoch_source}')

    def _apply_parameters(self, values) -> None:
        self.selector.set_method(values['selector'])   # qmdp's Q table is built here
        self.stale_timeout = values['stale_timeout']
        if self.epoch_timer is not None:
            self.epoch_timer.timer_period_ns = int(values['epoch_period'] * 1e9)
        self.input_deadline.set_period(values['input_timeout'])

    def _task_state_from_msg(self, msg):
        return conv.task_state_from_msg(msg, self.model.rho, self.model.sigma)

    # -- inputs ----------------------------------------------------------------------------
    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _guard(self, name: str, convert):
        """A conversion that also marks the input malformed when it fails."""
        def convert_or_mark(msg):
            try:
                return convert(msg)
            except conv.MessageError as exc:
                slot = self.slots[name]
                slot.bad_seq, slot.bad_reason = self._next_seq(), str(exc)
                self._maybe_decide()
                raise
        return convert_or_mark

    def _input(self, name: str):
        def store(value):
            slot = self.slots[name]
            slot.value, slot.seq = value, self._next_seq()
            slot.received_ns = self.clock.now().nanoseconds
            self._maybe_decide()
        return store

    def _answered(self, slot: InputSlot) -> bool:
        return max(slot.seq, slot.bad_seq) > self._fresh_since

    def _maybe_decide(self) -> None:
        if self.pending and all(self._answered(s) for s in self.slots.values()):
            self._decide(timed_out=False)

    # -- the epoch clock -------------------------------------------------------------------
    def _graph_ready(self) -> bool:
        return (self.epoch_pub.get_subscription_count() >= self.min_epoch_subscribers
                and all(sub.get_publisher_count() > 0 for sub in self.input_subscriptions))

    def _on_tick(self) -> None:
        if not self._clock_running:
            waited = (self.clock.now().nanoseconds - self._started_ns) * 1e-9
            if not (self._graph_ready_tick or waited >= self.stale_timeout):
                if self._graph_ready():
                    self._graph_ready_tick = True     # epoch 1 at the next tick
                else:
                    self.inputs.publish(self.inputs.status(
                        'decision', WARN, 'waiting for the graph: no hrc/epoch subscriber or '
                        'no input publisher discovered yet; no action published',
                        {'waited_s': waited,
                         'epoch_subscribers': self.epoch_pub.get_subscription_count(),
                         **{f'{name}_publishers': sub.get_publisher_count() for name, sub
                            in zip(self.slots, self.input_subscriptions)}}))
                return
            if not self._graph_ready_tick:
                self.get_logger().warning(f'starting the epoch clock after {waited:.1f} s '
                                          'without having discovered every input publisher')
            self._clock_running = True
        self._start_epoch(self.epoch + 1)
        self.epoch_pub.publish(conv.epoch_to_msg(self.epoch))

    def _on_epoch(self, k: int) -> None:
        self.inputs.epoch_order(k, self.epoch)    # a restarted replay is followed
        self._start_epoch(k)
        self._maybe_decide()

    def _start_epoch(self, k: int) -> None:
        if self.pending:
            self._decide(timed_out=True)
        self.epoch = k
        self.pending = True
        self._epoch_started_ns = self.clock.now().nanoseconds
        if self.epoch_source == 'timer':
            # Only what arrives after this epoch is published belongs to it.
            self._fresh_since = self._next_seq()
        self.input_deadline.start()

    def _on_input_timeout(self) -> None:
        if self.pending:
            self._decide(timed_out=True)

    # -- the decision ----------------------------------------------------------------------
    def _faults(self, now_ns: int) -> tuple[list[str], dict]:
        faults, ages = [], {}
        for name, slot in self.slots.items():
            age = None if slot.received_ns is None else (now_ns - slot.received_ns) * 1e-9
            ages[f'{name}_age_s'] = age
            if slot.bad_seq > slot.seq:
                faults.append(f'{slot.topic} malformed: {slot.bad_reason}')
            elif slot.value is None:
                faults.append(f'{slot.topic} missing (never received)')
            elif age > self.stale_timeout:
                faults.append(f'{slot.topic} stale ({age:.3f} s old > stale_timeout '
                              f'{self.stale_timeout} s)')
            elif name != 'distance_level' and slot.seq <= self._fresh_since:
                faults.append(f'{slot.topic} not received for epoch {self.epoch} within '
                              'input_timeout')
        return faults, ages

    def _decide(self, timed_out: bool) -> None:
        self.input_deadline.cancel()
        self.pending = False
        start = time.perf_counter()
        now_ns = self.clock.now().nanoseconds
        selection, observable, collision = None, None, False
        try:
            faults, ages = self._faults(now_ns)
            if not faults:
                task = self.slots['task_state'].value
                d = self.slots['distance_level'].value
                observable = tuple(task[n] for n in TASK_VARIABLES) + (d,)
                selection = self.selector.select(self.slots['belief'].value, observable)
                if d == 0:
                    collision = True
                    faults.append('d = 0: the human is inside the collision circle')
        except Exception as exc:  # noqa: BLE001 - whatever fails, the robot must stop
            faults, ages = [f'decision failed: {type(exc).__name__}: {exc}'], {}
            selection = None
        action = DN if faults else selection.action
        decided = time.perf_counter()
        self.action_pub.publish(conv.action_to_msg(action))
        published = time.perf_counter()
        self._fresh_since = self._next_seq()
        self.last_action = action
        self._report(action, faults, collision, ages, selection, observable, timed_out,
                     now_ns, {'compute_ms': (decided - start) * 1e3,
                              'publish_ms': (published - decided) * 1e3})

    def _report(self, action, faults, collision, ages, selection, observable, timed_out,
                now_ns, timings) -> None:
        belief = self.slots['belief'].value
        values = {
            'epoch': self.epoch, 'action': ACTIONS[action],
            'selector': self.selector.method,
            'faults': '; '.join(faults) if faults else 'none',
            **ages,
            'input_wait_ms': (now_ns - self._epoch_started_ns) * 1e-6,
            'input_timed_out': timed_out,
            **timings,
            'policy_file': self.policy.path,
            'policy_config_sha256': self.policy.config_sha256,
            'config': self.config.source,
            'config_sha256': self.config.policy_hash,
            'belief': None if belief is None else np.round(belief, 4),
            'observable': observable,
            'action_scores': (None if selection is None else ' '.join(
                f'{name}={score:.4g}' for name, score in zip(ACTIONS, selection.scores))),
            'selected': None if selection is None else selection.name,
            **self.inputs.counts(),
        }
        if not faults:
            level, message = OK, f'epoch {self.epoch}: {ACTIONS[action]}'
        else:
            level = WARN if collision and len(faults) == 1 else ERROR
            message = f'epoch {self.epoch}: dn (fail-safe): {"; ".join(faults)}'
            self.get_logger().warning(message, throttle_duration_sec=5.0)
        self.inputs.publish(self.inputs.status('decision', level, message, values))


def main(args=None):
    return run(DecisionNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
