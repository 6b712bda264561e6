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

Live swap (`ros2 param set /decision policy <file>`, and `config`; docs/LEARNING.md): the
parameter callback checks the pair (the configuration loads and describes the same cell; the
policy file exists, is a policy and was solved for that configuration: its meta only, a few
ms) and refuses a bad one with the reason, keeping the old. A policy solved for another
configuration than `config` is refused; a `config` set alone while `policy` is not solved for
it is accepted but staged (reported; the old pair keeps running) until a `policy` solved for
it is set, so that `ros2 param set`, one parameter at a time, can change both. An accepted pair
is loaded and fully checked in a background thread (`BackgroundLoad`) and swapped in at the
next epoch boundary (`DecisionGate.begin(select=...)`), so no epoch waits for the file; if the
full check still fails (damaged arrays) the parameters return to the pair in use, with an
ERROR status. The estimator announces its configuration on `hrc/estimator_config`; every
decision status names the policy and configuration in use and whether the estimator's belief
sections match, and a mismatch is a WARN status. The swap rule is `core.swap.check_swap`, the
belief estimator's too.

One decider per cell (`core.protocol.ClockOwner`): every decision node, in either mode,
claims the cell on the hidden latched topic `hrc/_clock_claim` (its start time, a random id,
its name; repeated every second) and only the owner, the oldest claim, publishes epochs and
actions: a newer one stays silent (or stops a clock it started before it heard the older),
with an ERROR status naming the owner, and so does a follower (`epoch_source: topic`), which
is an action source too. Other publishers of `hrc/epoch` or `hrc/action` are named from the
graph, by node once the graph knows it, by GID until then.

Epoch 1 (timer mode) waits for the graph (`ClockStart`): a publisher of every input,
`min_epoch_subscribers` readers of `hrc/epoch` counted by this node's writer, and
`min_epoch_ready` listeners whose own reader has matched this writer, as they say on the hidden
latched topic `hrc/_epoch_ready` (`core.protocol.EpochListeners`, `sources.EpochReady`): a
reader that matches the writer after epoch 1 was sent never gets it (issue 37).
"""

from __future__ import annotations

import secrets
import time
from dataclasses import dataclass

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32

from ...core.config import Config
from ...core.model import HRCModel
from ...core.mdp.policy import Policy, PolicyError, load_policy
from ...core.protocol import (CLAIM_PERIOD_S, DECISION_WAIT, ERROR, OK, STALE, WARN, Claim,
                              ClockOwner, ClockStart, DecisionGate, EpochFollower, EpochListeners,
                              Report, Stamp, check_timeout_order)
from ...core.decision.selection import POMDP_SELECTORS, SELECTORS, ActionSelector
from ...core.swap import SAME, STAGED, check_swap, policy_path
from .. import conversions as conv
from .. import qos
from ..node_support import (LIVE_CONFIG, BackgroundLoad, DeadlineTimer, Inputs, ParamSpec,
                            StartupError, config_path, control_clock, load_node_config, node_setup,
                            run)
from ..sources import endpoint_node, endpoints, ready_topic, subscribe_epochs

EPOCH_SOURCES = ('timer', 'topic')
INPUT_FRACTION = DECISION_WAIT.fraction   # input_timeout 0: this fraction of the epoch period
STALE_PERIODS = STALE.fraction            # stale_timeout 0: this many epoch periods
GRAPH_WAIT_MIN = 10.0  # stale_timeout 0: seconds the clock may wait for DDS discovery at least
CLAIM_TOPIC = 'hrc/_clock_claim'   # hidden: not recorded by a bag of every topic, not replayed
T = Parameter.Type
PARAMETERS = (
    LIVE_CONFIG,
    ParamSpec('policy', T.STRING, '', "policy file solved for the configuration ('' = the "
              'shipped policy solved for config, e.g. policies/paper.npz for paper.yaml; else '
              'default.npz); settable at run time: swapped in at the next epoch boundary'),
    ParamSpec('selector', T.STRING, 'paper', 'action selection from the belief: '
              + ', '.join(SELECTORS), constraints=' or '.join(SELECTORS)),
    ParamSpec('pomdp_policy', T.STRING, '', "POMDP policy file the pomdp and fib selectors "
              "read, solved for the configuration ('' = the shipped one in policies/pomdp/ "
              'solved for config); settable at run time with config and policy: swapped in '
              'at the next epoch boundary'),
    ParamSpec('policy_in_use', T.STRING, '', 'the policy file deciding now, resolved (read-only: '
              'set policy; it follows each swap at its epoch boundary)', read_only=True),
    ParamSpec('pomdp_policy_in_use', T.STRING, '', 'the POMDP policy file the pomdp and fib '
              "selectors read now, resolved ('' while the selector reads none; read-only: set "
              'pomdp_policy)', read_only=True),
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
    ParamSpec('min_epoch_ready', T.INTEGER, 2, 'timer mode: listeners of hrc/epoch (task '
              'manager, belief estimator, view, hrc-case-study) whose reader must have matched '
              'this clock, as they say on hrc/_epoch_ready, before epoch 1 (a reader that matches '
              'later misses it; 0: none); the clock starts anyway after stale_timeout',
              read_only=True, range=(0, 1000)),
)


def check_parameters(values) -> str | None:
    if 'selector' in values and values['selector'] not in SELECTORS:
        return f'selector must be one of {", ".join(SELECTORS)}, got {values["selector"]!r}'
    if 'epoch_source' in values and values['epoch_source'] not in EPOCH_SOURCES:
        return (f'epoch_source must be one of {", ".join(EPOCH_SOURCES)}, got '
                f'{values["epoch_source"]!r}')
    return check_timeout_order(values.get('epoch_period'),
                               {DECISION_WAIT: values.get('input_timeout', 0.0),
                                STALE: values.get('stale_timeout', 0.0)})


@dataclass(frozen=True)
class Running:
    """A (configuration, policy) pair, loaded and checked: what decides, or is about to."""

    config_value: str        # the parameters as set
    policy_value: str
    config: Config
    model: HRCModel
    policy: Policy
    selector: ActionSelector
    pomdp_value: str = ''    # pomdp_policy as set


@dataclass(frozen=True)
class Staged:
    """A configuration set without a policy solved for it yet."""

    config_value: str
    policy_value: str
    reason: str
    pomdp_value: str = ''


def load_pair(config_value: str, policy_value: str, method: str, pomdp_value: str = ''
              ) -> Running:
    """Load and fully check a (configuration, policy) pair the swap rule accepted
    (`core.swap.check_swap`), and for the pomdp and fib selectors the POMDP policy
    `pomdp_value` names; StartupError / PolicyError when a file turns out bad."""
    config = load_node_config(config_value)
    model = HRCModel(config)
    policy = load_policy(policy_path(policy_value, config), config)
    return Running(config_value, policy_value, config, model, policy,
                   ActionSelector(model, policy, method=method, pomdp_path=pomdp_value),
                   pomdp_value)


def timeouts_ns(values) -> tuple[int, int]:
    """(input_timeout, stale_timeout) in ns: the explicit values, or fractions of the period."""
    period_ns = int(values['epoch_period'] * 1e9)
    return (DECISION_WAIT.ns(values['input_timeout'], period_ns),
            STALE.ns(values['stale_timeout'], period_ns))


class DecisionNode(Node):
    NODE_NAME = 'decision'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.running: Running | None = None      # set below: swaps are checked from then on
        self._checked: tuple | None = None        # the last swap verdict, by its values
        self._shown_method: str | None = None     # the selector `_show_in_use` showed
        self.params, values, config, model = node_setup(
            self, PARAMETERS, self._check_parameters, self._apply_parameters)
        try:
            policy = load_policy(policy_path(values['policy'], config), config)
        except PolicyError as exc:
            raise StartupError(
                f'{exc} (expected a policy for configuration {config_path(values["config"])}, '
                f'sha256 {config.policy_hash})') from None
        try:   # pomdp and fib read the POMDP policy (pomdp_policy; '': the shipped one)
            selector = ActionSelector(model, policy, method=values['selector'],
                                      pomdp_path=values['pomdp_policy'])
        except PolicyError as exc:
            raise StartupError(f'selector {values["selector"]}: {exc}') from None
        if values['pomdp_policy'] and values['selector'] not in POMDP_SELECTORS:
            from ...core.pomdp.policy import peek_pomdp_policy
            try:   # not read yet, but named: it must be one for config, as when set live
                peek_pomdp_policy(values['pomdp_policy'], config)
            except Exception as exc:  # noqa: BLE001 - PolicyError, or what a damaged file raises
                raise StartupError(f'pomdp_policy: {exc}') from None
        self.loader = BackgroundLoad('decision')
        self.staged: Staged | None = None
        self.estimator_config: tuple[str, str] | None = None   # (belief sha256, source)
        self.epoch_source = values['epoch_source']
        self.min_epoch_subscribers = values['min_epoch_subscribers']
        self.min_epoch_ready = values['min_epoch_ready']
        self.epoch_listeners = EpochListeners()
        self.clock = control_clock(self)   # epochs, waits and input ages
        self.running = Running(values['config'], values['policy'], config, model, policy,
                               selector, values['pomdp_policy'])
        input_ns, stale_ns = timeouts_ns(values)
        self.gate = DecisionGate(self.selector.select, stale_ns, input_ns,
                                 fresh_at_epoch=self.epoch_source == 'timer')
        self.stale_timeout = values['stale_timeout']
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)   # claims age on it, always
        self.claim = Claim(time.time_ns(), secrets.randbits(63),
                           self.get_fully_qualified_name(), self.epoch_source)
        self.owner = ClockOwner(self.claim)
        self.clock_start = ClockStart(self.steady.now().nanoseconds, self._graph_wait_ns(),
                                      running=self.epoch_source == 'topic', owner=self.owner)
        self.epochs = EpochFollower()
        self.last_action: int | None = None

        self.action_pub = self.create_publisher(String, 'hrc/action', qos.RELIABLE)
        self.claim_pub = self.create_publisher(String, CLAIM_TOPIC, qos.CLAIMS)
        self.inputs = Inputs(self)
        self.claim_sub = self.inputs.subscribe(String, CLAIM_TOPIC, qos.CLAIMS,
                                               conv.claim_from_msg, self._on_claim,
                                               name='clock_claim')
        self._publish_claim()
        self.claim_timer = self.create_timer(CLAIM_PERIOD_S, self._publish_claim,
                                             clock=self.steady)
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
        self.epoch_gid: str | None = None      # this node's epoch writer, as the graph has it
        if self.epoch_source == 'timer':
            before = self._own_writers()
            self.epoch_pub = self.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
            # a local writer enters the graph at once: the one new GID of this node's name is
            # it (not one of a stopped node of the same name the graph still shows)
            new = self._own_writers() - before
            self.epoch_gid = new.pop() if len(new) == 1 else None
            self.inputs.subscribe(String, ready_topic(self.resolve_topic_name('hrc/epoch')),
                                  qos.READY_MARKS,
                                  conv.epoch_ready_from_msg, self.epoch_listeners.heard,
                                  name='epoch_ready')
            self.epoch_timer = self.create_timer(values['epoch_period'], self._on_tick,
                                                 clock=self.clock)
        else:
            self.epoch_pub = None
            self.epoch_timer = None
            subscribe_epochs(self.inputs, lambda: self.epochs, self._on_epoch,
                             ready_mark=False)
        self.inputs.subscribe(String, 'hrc/estimator_config', qos.STATE_INPUT,
                              conv.config_identity_from_msg, self._on_estimator_config)
        self._show_in_use()
        pomdp = getattr(self.selector.pomdp, 'path', None)
        self.get_logger().info(
            f'policy {self.policy.path} (configuration {self.config.source}, sha256 '
            f'{self.config.policy_hash[:12]}), selector {values["selector"]}'
            + (f' (POMDP policy {pomdp})' if pomdp else '') + f', epochs from '
            f'{self.epoch_source}')

    @property
    def epoch(self) -> int:
        return self.gate.epoch

    def _show_in_use(self) -> None:
        """The files deciding now as the read-only parameters `policy_in_use` and
        `pomdp_policy_in_use` (issue 37: `ros2 param get /decision pomdp_policy` showed '',
        the shipped one's path was only in the log)."""
        pomdp = (getattr(self.selector.pomdp, 'path', '') or ''
                 if self.selector.method in POMDP_SELECTORS else '')
        self._shown_method = self.selector.method
        self.params.show({'policy_in_use': str(self.policy.path),
                          'pomdp_policy_in_use': str(pomdp)})

    # the pair in use
    config = property(lambda self: self.running.config)
    model = property(lambda self: self.running.model)
    policy = property(lambda self: self.running.policy)
    selector = property(lambda self: self.running.selector)

    def _graph_wait_ns(self) -> int:
        """The longest wait for the graph: an explicit stale_timeout, else 3 periods but at
        least GRAPH_WAIT_MIN (DDS discovery does not follow the epoch period)."""
        if self.stale_timeout > 0:
            return self.gate.stale_timeout_ns
        return max(self.gate.stale_timeout_ns, int(GRAPH_WAIT_MIN * 1e9))

    def _now(self) -> int:
        return self.clock.now().nanoseconds

    # -- parameters ------------------------------------------------------------------------
    def _check_parameters(self, values) -> str | None:
        reason = check_parameters(values)
        if reason is None and self.running is not None \
                and values.get('selector') in POMDP_SELECTORS \
                and not self._pomdp_changed(values):    # else the swap rule checks the new one
            try:
                self.selector.prepare(values['selector'])    # loads the POMDP policy
            except PolicyError as exc:
                return f'selector {values["selector"]}: {exc}'
        return reason or self._check_swap(values)

    def _pomdp_changed(self, values) -> bool:
        return values.get('pomdp_policy', self.running.pomdp_value) != self.running.pomdp_value

    def _verdict(self, values, checked: bool = False):
        """The swap rule's verdict on the (config, policy) in `values` (`core.swap`). With
        `checked` (the post-set callback), the verdict the parameter callback just reached on
        the same values, so the files are read once per change."""
        running = self.running
        key = (running.config_value, running.policy_value, running.pomdp_value,
               values['config'], values['policy'], values['pomdp_policy'],
               values['selector'] in POMDP_SELECTORS)
        done, self._checked = self._checked, None
        if checked and done is not None and done[0] == key:
            return done[1]
        verdict = check_swap(running.model.rho, running.model.sigma, running.config_value,
                             values['config'], running.policy_value, values['policy'],
                             paused=running.model.config.robot_paused_by,
                             queue=running.model.config.queue,
                             rated=running.model.config.robot_rate is not None,
                             running_pomdp=running.pomdp_value,
                             pomdp_value=values['pomdp_policy'],
                             pomdp_needed=values['selector'] in POMDP_SELECTORS)
        self._checked = None if checked else (key, verdict)
        return verdict

    def _check_swap(self, values) -> str | None:
        """The quick check of a new (config, policy) pair, in the parameter callback."""
        if self.running is None or any(name not in values
                                       for name in ('config', 'policy', 'pomdp_policy')):
            return None            # start-up: __init__ loads and checks the pair itself
        verdict = self._verdict(values)
        return verdict.reason if verdict.refused else None

    def _apply_parameters(self, values) -> None:
        if self.running is not None:
            verdict = self._verdict(values, checked=True)
            method = values['selector']
            if verdict.verdict == STAGED:    # config set alone: until a policy for it is set
                staged = Staged(values['config'], values['policy'], verdict.reason,
                                values['pomdp_policy'])
                self.loader.start(lambda: staged)
            elif verdict.verdict == SAME:    # back to the pair in use: nothing pending
                self.loader.start(lambda: None)
            elif not verdict.refused:
                self.loader.start(lambda: load_pair(values['config'], values['policy'], method,
                                                    values['pomdp_policy']))
        if values['selector'] not in POMDP_SELECTORS or not self._pomdp_changed(values):
            self.selector.set_method(values['selector'])   # qmdp's Q table is built here
            if values['selector'] != self._shown_method:
                self._show_in_use()
        # else the pair loading meanwhile reads the new POMDP policy and takes the method
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
                'epoch_ready': ', '.join(self._ready_listeners()) or 'none',
                **{f'{name}_publishers': sub.get_publisher_count()
                   for name, sub in zip(self.gate.slots, self.input_subscriptions)}}

    def _graph_ready(self) -> bool:
        return (self.epoch_pub.get_subscription_count() >= self.min_epoch_subscribers
                and all(sub.get_publisher_count() > 0 for sub in self.input_subscriptions)
                and (self.min_epoch_ready == 0
                     or len(self._ready_listeners()) >= self.min_epoch_ready))

    def _own_writers(self) -> set[str]:
        """The GIDs of the hrc/epoch publishers of this node's name the graph shows."""
        me = self.get_fully_qualified_name()
        return {e.gid for e in endpoints(self, 'hrc/epoch', skip_own=False) if e.node == me}

    def _ready_listeners(self) -> list[str]:
        """The listeners ready for this clock (`EpochListeners.ready`): their marks name this
        node's epoch writer and the graph shows their readers."""
        topic = self.resolve_topic_name('hrc/epoch')
        readers = {endpoint_node(info) for info in self.get_subscriptions_info_by_topic(topic)}
        return self.epoch_listeners.ready(self.epoch_gid, readers - {None})

    def _other_sources(self) -> list:
        """Other publishers of hrc/epoch or hrc/action (`Endpoint`s): a second decision node,
        say (also one with this node's name: one publisher per topic of this name is this
        node's own). Following hrc/epoch (topic mode), its one publisher is the source this
        node follows (a bag's player, a clock of the cell), not another: only a second one
        is (a replay used to report its player as 'another epoch source ... Stop one')."""
        epoch = endpoints(self, 'hrc/epoch', skip_own=self.epoch_pub is not None)
        if self.epoch_pub is None and len(epoch) == 1:
            epoch = []
        return epoch + endpoints(self, 'hrc/action')

    def _publish_claim(self) -> None:
        self.claim_pub.publish(conv.claim_to_msg(self.claim))

    def _on_claim(self, claim: Claim) -> None:
        self.owner.heard(claim, self.steady.now().nanoseconds)

    def _tick(self, graph_ready) -> bool:
        """The clock's, or (topic mode) the follower's, say in this epoch (`ClockStart`)."""
        tick = self.clock_start.tick(self.steady.now().nanoseconds, graph_ready, self._graph,
                                     self._other_sources, self.get_fully_qualified_name(),
                                     self.claim_sub.get_publisher_count)
        if tick.report is not None:
            self.inputs.report(tick.report)
        return tick.start_epoch

    def _on_tick(self) -> None:
        if self._tick(self._graph_ready):
            k = self.epoch + 1
            self._act(self.gate.begin(k, self._now(), select=self._swap(k)))
            self.epoch_pub.publish(conv.epoch_to_msg(k))

    def _on_epoch(self, k: int, stamp: Stamp) -> None:
        restart = self.epochs.check(k, stamp)     # another source: InputError, dropped
        if restart is not None:
            self.inputs.report(restart)
        self.epochs.take(k, stamp)
        if self._tick(lambda: True):            # not the cell's decider: no action
            self._act(self.gate.begin(k, self._now(), select=self._swap(k)))

    def _swap(self, k: int):
        """At the boundary of epoch k: a pair loaded meanwhile takes over (its `select`)."""
        done = self.loader.take()
        if done is None:
            return None
        loaded, error = done
        old = self.running
        if loaded is None and error is None:      # the parameters went back to the pair in use
            return None
        if isinstance(loaded, Running):
            if loaded.selector.method != self.params.value('selector'):
                loaded.selector.set_method(self.params.value('selector'))
            self.running, self.staged = loaded, None
            self._show_in_use()
            pomdp = getattr(loaded.selector.pomdp, 'path', None)
            before = getattr(old.selector.pomdp, 'path', None)
            self.inputs.report(Report(
                OK, 'policy', f'epoch {k}: now deciding with policy {loaded.policy.path}'
                + (f' and POMDP policy {pomdp}' if pomdp else '')
                + f' (configuration {loaded.config.source}, sha256 '
                f'{loaded.config.policy_hash[:12]}); before: {old.policy.path}'
                + (f' and POMDP policy {before}' if before else ''),
                {'epoch': k, 'policy_file': loaded.policy.path, 'config': loaded.config.source,
                 'previous_policy_file': old.policy.path,
                 **({'pomdp_policy_file': pomdp} if pomdp else {})}, kind='swap'))
            return loaded.selector.select
        if isinstance(loaded, Staged):
            self.staged = loaded
            self.inputs.report(Report(
                WARN, 'policy', f'configuration {config_path(loaded.config_value)} is set but '
                f'not in use: {loaded.reason}; still deciding with {old.policy.path} '
                f'({old.config.source}). Set policy (and for the pomdp and fib selectors '
                'pomdp_policy) to files solved for it.',
                {'config_staged': config_path(loaded.config_value),
                 'policy_file': old.policy.path}, kind='staged'))
            return None
        self.inputs.report(Report(
            ERROR, 'policy', f'refused the new configuration / policy: {error}; still deciding '
            f'with {old.policy.path} ({old.config.source})',
            {'policy_file': old.policy.path, 'error': str(error)}, kind='refused'))
        # back to the set in use, in one atomic set (one at a time, each would be checked
        # against the others not yet back), with the selector it decides with
        result = self.set_parameters_atomically([
            Parameter('config', value=old.config_value),
            Parameter('policy', value=old.policy_value),
            Parameter('pomdp_policy', value=old.pomdp_value),
            Parameter('selector', value=old.selector.method)])
        if not result.successful:
            self.get_logger().error(f'could not set the parameters back to the set in use: '
                                    f'{result.reason}')
        return None

    def _on_estimator_config(self, identity: tuple[str, str]) -> None:
        self.estimator_config = identity

    # -- the decision ----------------------------------------------------------------------
    def _act(self, decisions) -> None:
        for decision in decisions:
            start = time.perf_counter()
            self.action_pub.publish(conv.action_to_msg(decision.action))
            publish_ms = (time.perf_counter() - start) * 1e3
            self.last_action = decision.action
            estimator = self.estimator_config
            matches = None if estimator is None else estimator[0] == self.config.belief_hash
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
                      'config_staged': (None if self.staged is None
                                        else config_path(self.staged.config_value)),
                      'estimator_config': None if estimator is None else estimator[1],
                      'estimator_config_matches': matches,
                      **self.inputs.counts()}
            self.inputs.report(Report(decision.level, 'decision', decision.message, values,
                                      log=bool(decision.faults), kind='fail_safe'))
            if matches is False:
                self.inputs.report(Report(
                    WARN, 'configuration', f'epoch {decision.epoch}: the belief estimator runs '
                    f'{estimator[1]} (belief sections sha256 {estimator[0][:12]}), this node '
                    f'{self.config.source} ({self.config.belief_hash[:12]}): its belief is not '
                    "the one the policy's model would give; set the estimator's config too",
                    {'epoch': decision.epoch, 'estimator_config': estimator[1],
                     'config': self.config.source}, kind='estimator_config'))
        self.deadline.sync(self.gate.deadline)


def main(args=None):
    return run(DecisionNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
