"""What the nodes share: parameter declaration and validation, input guarding, dropped message
accounting and protocol reports on /diagnostics, deadlines, and the `main()` wrapper.

Parameters. A node lists its parameters as `ParamSpec`s; `NodeParameters` declares them with a
`ParameterDescriptor` (description, type, range, read-only) and registers one
`add_on_set_parameters_callback` that runs the node's `check(values) -> reason | None` on the
merged proposed values. The callback is registered before the declarations, so values from a
`--params-file` are validated by the same code at start-up (a bad value stops the node with
the reason). Changes accepted at run time reach the node through
`add_post_set_parameters_callback`. An array parameter whose default is empty is declared with
that typed empty value (`NodeParameters._declare_empty_array`), so every parameter has a value
that `ros2 param get` and `ros2 param dump` show.

Inputs. `Inputs.subscribe` wraps a subscription: the callback converts the message (a
`conversions` function) and hands the value to the node; a `MessageError`, raised by the
conversion or by the handler (any `core.protocol.InputError`), drops the message with a
throttled warning (one throttle per input, through a child logger) and a WARN status on
/diagnostics (at most one per input per `WARNING_THROTTLE_SEC`; the count of dropped messages
is in every status). Any other exception
is a bug: it is logged with its traceback and reported as ERROR, and the node keeps spinning,
so that no input can stop a node. `Inputs.report` publishes (and logs, throttled) a
`core.protocol.Report` of the node's protocol machine.

Deadlines. `Deadline` is a one-shot timeout that gives way to messages already waiting;
`DeadlineTimer` keeps one armed at a protocol machine's `deadline` (an absolute control-clock
time), so the machines decide what a timeout means and the nodes only keep time.
"""

from __future__ import annotations

import os
import re
import sys
import textwrap
import threading
import time
import traceback
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import qos_policy_name_from_kind
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args

from ..core import protocol
from ..core.config import ConfigError, load_config
from ..core.paths import input_stat
from ..core.swap import config_path
from ..core.protocol import InputError, Report, Stamp
from . import qos, stop
from .conversions import cap, diagnostic_array, diagnostic_status

WARNING_THROTTLE_SEC = 5.0   # one warning (and one drop diagnostic) per input per this period
STATUS_PERIOD_SEC = 1.0      # periodic health status of the nodes
DIAGNOSTICS_TOPIC = '/diagnostics'
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
LEVELS = {protocol.OK: OK, protocol.WARN: WARN, protocol.ERROR: ERROR}


class StartupError(RuntimeError):
    """The node cannot start (bad configuration, policy or parameters); the text says why."""


# -- parameters -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ParamSpec:
    name: str
    type: Parameter.Type
    default: Any
    description: str
    read_only: bool = False
    range: tuple | None = None     # (low, high), inclusive, for scalar numbers
    constraints: str = ''          # additional_constraints text (array shapes, orders)

    def descriptor(self) -> ParameterDescriptor:
        desc = ParameterDescriptor(name=self.name, type=self.type.value,
                                   description=self.description, read_only=self.read_only,
                                   additional_constraints=self.constraints)
        if self.range is not None and self.type == Parameter.Type.DOUBLE:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(self.range[0]), to_value=float(self.range[1]), step=0.0)]
        elif self.range is not None and self.type == Parameter.Type.INTEGER:
            desc.integer_range = [IntegerRange(
                from_value=int(self.range[0]), to_value=int(self.range[1]), step=1)]
        return desc


Check = Callable[[Mapping[str, Any]], 'str | None']

CONFIG = ParamSpec('config', Parameter.Type.STRING, '', "model configuration YAML ('' = the "
                   'shipped default.yaml)', read_only=True)
# The decision node and the belief estimator take a new configuration while they run.
LIVE_CONFIG = ParamSpec('config', Parameter.Type.STRING, '', "model configuration YAML ('' = "
                        'the shipped default.yaml); settable at run time: checked at once, '
                        'loaded off the epoch path and used from the next epoch on')


class NodeParameters:
    """Declare `specs` on `node`; validate every change with `check`; apply with `apply`."""

    def __init__(self, node: Node, specs: Sequence[ParamSpec], check: Check,
                 apply: Callable[[Mapping[str, Any]], None] | None = None):
        self.node = node
        self.specs = {spec.name: spec for spec in specs}
        self._check = check
        self._apply = apply
        self._showing = False
        node.add_on_set_parameters_callback(self._on_set)
        for spec in specs:
            empty_array = isinstance(spec.default, (list, tuple)) and not spec.default
            if empty_array and not node.has_parameter(spec.name):
                self._declare_empty_array(spec)
            else:
                node.declare_parameter(spec.name, spec.default, spec.descriptor())
        node.add_post_set_parameters_callback(self._post_set)

    def _declare_empty_array(self, spec: ParamSpec) -> None:
        """Declare an array parameter whose default is empty with that typed empty value.

        rclpy infers a byte array from ``[]``, and a parameter declared by type alone reads as
        "not set": `ros2 param get` then says so and the get-parameters service answers
        nothing for a request that names it (so `ros2 param dump` printed ``{}``). rclpy's
        public API cannot declare a typed empty array (its value is inferred), so the typed
        value goes through the declaration step rclpy uses itself; a value from a params
        file (an override, typed by rcl) still wins. test_nodes checks that every parameter
        of every node has a value."""
        descriptor = spec.descriptor()
        override = self.node._parameter_overrides.get(spec.name)    # typed by rcl
        value = (override if override is not None and override.type_ == spec.type
                 else Parameter(spec.name, spec.type, []))
        self.node._declare_parameter_common([Parameter(spec.name, spec.type, value.value)],
                                            {spec.name: descriptor})

    def value(self, name: str) -> Any:
        try:
            value = self.node.get_parameter(name).value
        except ParameterUninitializedException:
            return self.specs[name].default
        return list(value) if isinstance(value, (list, tuple)) or hasattr(value, 'tolist') \
            else value

    def values(self) -> dict:
        return {name: self.value(name) for name in self.specs
                if self.node.has_parameter(name)}

    def show(self, values: Mapping[str, Any]) -> None:
        """Set read-only parameters that show what the node uses now (the decision node's
        `policy_in_use`): `ros2 param get` reads them, nobody else sets them (read-only), and
        the node's check and apply callbacks do not see them (nothing to check or apply)."""
        parameters = [Parameter(name, self.specs[name].type, value)
                      for name, value in values.items()]
        self._showing = True
        try:
            result = self.node._set_parameters_atomically_common(   # rclpy: read-only ones too
                parameters, {p.name: self.specs[p.name].descriptor() for p in parameters})
        finally:
            self._showing = False
        if not result.successful:
            raise RuntimeError(f'could not show {", ".join(values)}: {result.reason}')

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        if self._showing:
            return SetParametersResult(successful=True)
        proposed = {p.name: (list(p.value) if isinstance(p.value, (list, tuple))
                             or hasattr(p.value, 'tolist') else p.value)
                    for p in parameters
                    if p.name in self.specs and p.type_ != Parameter.Type.NOT_SET}
        if not proposed:
            return SetParametersResult(successful=True)
        merged = self.values()
        merged.update(proposed)
        try:
            reason = self._check(merged)
        except (TypeError, ValueError) as exc:
            reason = cap(str(exc))
        except Exception as exc:  # noqa: BLE001 - a check that fails (a file too large to load:
            # MemoryError) refuses the change; raised out of this callback it ends the node
            reason = cap(f'{type(exc).__name__}: {exc}')
        if reason:
            return SetParametersResult(successful=False, reason=cap(reason))
        return SetParametersResult(successful=True)

    def _post_set(self, parameters: list[Parameter]) -> None:
        if self._showing:
            return
        if self._apply is not None and any(p.name in self.specs for p in parameters):
            self._apply(self.values())


def node_setup(node: Node, specs: Sequence[ParamSpec], check: Check,
               apply: Callable[[Mapping[str, Any]], None] | None = None):
    """Declare a node's parameters and load the model configuration its `config` names:
    (NodeParameters, their values, the Config, its HRCModel). StartupError on a bad config."""
    from ..core.model import HRCModel
    params = NodeParameters(node, specs, check, apply)
    values = params.values()
    config = load_node_config(values['config'])
    return params, values, config, HRCModel(config)


def load_node_config(value: str):
    """The model configuration named by a node's `config` parameter ('' = shipped default)."""
    path = config_path(value)
    try:
        return load_config(path)
    except ConfigError as exc:
        raise StartupError(f'bad model configuration: {exc}') from None


def check_array(values: Mapping[str, Any], name: str, length: int | None = None,
                low=None, high=None) -> str | None:
    """A reason if array parameter `name` (when present) has the wrong length or range."""
    if name not in values:
        return None
    array = list(values[name])
    if length is not None and len(array) != length:
        return f'{name} must hold {length} values, got {len(array)}'
    for v in array:
        if v != v or v in (float('inf'), float('-inf')):
            return f'{name} must be finite, got {array}'
        if (low is not None and v < low) or (high is not None and v > high):
            span = (f'in [{low}, {high}]' if low is not None and high is not None
                    else f'>= {low}' if low is not None else f'<= {high}')
            return f'{name} values must be {span}, got {array}'
    return None


def check_core(values: Mapping[str, Any], name: str, probe: Callable[[Any], Any]) -> str | None:
    """Validate parameter `name` by calling the core with it (its checks live there)."""
    if name not in values:
        return None
    try:
        probe(values[name])
    except ValueError as exc:
        return f'{name}: {exc}'
    return None


class BackgroundLoad:
    """Load files off the executor thread; the node takes the result at an epoch boundary.

    `start(load)` runs `load()` in a daemon thread (reading and checking a policy takes
    ~0.1 s: inside a callback it would delay the epoch that falls due meanwhile). `take()`
    returns what the latest start produced, once: its value or the exception it raised, or None
    while it runs (a newer start supersedes an older one that has not finished)."""

    def __init__(self, name: str):
        self.name = name
        self._lock = threading.Lock()
        self._generation = 0
        self._done: tuple | None = None

    def start(self, load: Callable[[], Any]) -> None:
        with self._lock:
            self._generation += 1
            generation = self._generation
            self._done = None

        def work():
            try:
                done = (load(), None)
            except Exception as exc:  # noqa: BLE001 - handed to the node, which reports it
                done = (None, exc)
            with self._lock:
                if generation == self._generation:
                    self._done = done

        threading.Thread(target=work, name=f'{self.name} load', daemon=True).start()

    def take(self) -> tuple | None:
        """(value, None) or (None, exception) of the latest load, once; None until it ends."""
        with self._lock:
            done, self._done = self._done, None
        return done


# -- inputs and diagnostics -------------------------------------------------------------------
def control_clock(node: Node) -> Clock:
    """The clock of a node's epochs, deadlines and input ages: the ROS clock under
    `use_sim_time` (a replay with /clock), else the monotonic (steady) clock, so that a step of
    the system clock (NTP, a manual date) neither stalls the epoch clock nor makes old inputs
    look fresh. `use_sim_time` is read once: set it at start-up."""
    if node.get_parameter('use_sim_time').value:
        return node.get_clock()
    return Clock(clock_type=ClockType.STEADY_TIME)


class Deadline:
    """A one-shot timeout that gives way to the messages already waiting.

    rclpy's executor runs a ready timer before the subscriptions that are ready in the same
    wait, so a node that wakes up late would time out on a message that arrived in time and is
    waiting to be taken. `Deadline` fires `callback()` through a guard condition instead,
    which the executor runs after the subscriptions ready with it; `callback` must therefore
    check that what it waited for is still missing. `start()` arms it (again), `cancel()`
    disarms it."""

    def __init__(self, node: Node, seconds: float, callback: Callable[[], None]):
        self._callback = callback
        self._generation = 0        # start() and cancel() make a fired deadline obsolete
        self._fired: int | None = None
        self._guard = node.create_guard_condition(self._expired)
        self.timer = node.create_timer(seconds, self._fire, clock=control_clock(node),
                                       autostart=False)

    def set_period_ns(self, nanoseconds: int) -> None:
        self.timer.timer_period_ns = int(nanoseconds)

    def start(self) -> None:
        self._generation += 1
        self.timer.reset()

    def cancel(self) -> None:
        self._generation += 1
        self.timer.cancel()

    @property
    def armed(self) -> bool:
        """Started and neither cancelled nor expired (an expiry waiting to run counts)."""
        return not self.timer.is_canceled() or self._fired == self._generation

    def _fire(self) -> None:
        self.timer.cancel()
        self._fired = self._generation
        self._guard.trigger()

    def _expired(self) -> None:
        if self._fired == self._generation:
            self._fired = None
            self._callback()


class DeadlineTimer:
    """Keeps a `Deadline` armed at a protocol machine's `deadline` (absolute control-clock ns,
    or None). Call `sync(machine.deadline)` after feeding the machine; `callback(now_ns)` runs
    when the time comes and must call the machine's `expire(now)` (which re-checks the time),
    then `sync` again."""

    MIN_PERIOD_NS = 1000

    def __init__(self, node: Node, callback: Callable[[int], None]):
        self.clock = control_clock(node)
        self._callback = callback
        self._armed_for: int | None = None
        self._deadline = Deadline(node, 1.0, self._fire)

    def sync(self, deadline_ns: int | None) -> None:
        if deadline_ns == self._armed_for:
            return
        self._armed_for = deadline_ns
        if deadline_ns is None:
            self._deadline.cancel()
            return
        remaining = deadline_ns - self.clock.now().nanoseconds
        self._deadline.set_period_ns(max(remaining, self.MIN_PERIOD_NS))
        self._deadline.start()

    def _fire(self) -> None:
        self._armed_for = None
        self._callback(self.clock.now().nanoseconds)


class Inputs:
    """Guarded subscriptions of a node, its /diagnostics publisher and its dropped-message counts.
    """

    def __init__(self, node: Node):
        self.node = node
        self.publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, qos.RELIABLE)
        self.received: Counter = Counter()
        self.dropped: Counter = Counter()
        self.last_drop_reason: dict[str, str] = {}
        self._loggers: dict[str, Any] = {}
        self._last_drop_report: dict[str, float] = {}
        self._last_error_report: dict[str, float] = {}
        self._last_log: dict[tuple, float] = {}
        self._unreported: Counter = Counter()

    # -- subscriptions -----------------------------------------------------------------------
    def subscribe(self, msg_type, topic: str, profile, convert: Callable[[Any], Any],
                  handle: Callable[..., None], name: str | None = None,
                  with_published: bool = False, with_stamp: bool = False,
                  on_matched: Callable[..., None] | None = None):
        """Subscribe; `handle(convert(msg))` runs for valid messages, drops are reported.

        With `with_published`, `handle(value, published_ns)` also gets the message's
        publication time: the writer's source timestamp (system clock, ns), or the system time
        of its receipt where the middleware gives none. With `with_stamp`, `handle(value,
        stamp)` gets a `core.protocol.Stamp` (that time and the writer's sequence number).
        A publisher whose QoS cannot match the subscription's (`incompatible_qos` event) is
        reported as ERROR on /diagnostics, naming the topic and the policy. `on_matched(event)`
        runs when a publisher matches the subscription or leaves it."""
        name = name or topic.rsplit('/', 1)[-1]

        def guarded(msg, *extra):
            self.received[name] += 1
            try:
                handle(convert(msg), *extra)
            except InputError as exc:
                self.drop(name, topic, str(exc))
            except Exception:  # noqa: BLE001 - a bug must not stop the node; it is reported
                self.internal_error(name, topic, traceback.format_exc())

        if not (with_published or with_stamp):
            def callback(msg):
                guarded(msg)
        else:
            def callback(msg, info):
                info = info if isinstance(info, dict) else {}
                published = int(info.get('source_timestamp') or time.time_ns())
                guarded(msg, Stamp(published, info.get('publication_sequence_number'))
                        if with_stamp else published)

        events = SubscriptionEventCallbacks(
            incompatible_qos=lambda event: self.incompatible_qos(name, topic, event),
            matched=on_matched)
        return self.node.create_subscription(msg_type, topic, callback, profile,
                                             event_callbacks=events)

    def incompatible_qos(self, name: str, topic: str, event) -> None:
        """A publisher offers a QoS this subscription cannot match: its messages never arrive.
        Reported as ERROR (throttled per input), with the policy that failed."""
        try:
            policy = qos_policy_name_from_kind(event.last_policy_kind)
        except (AttributeError, ValueError):
            policy = 'unknown policy'

        message = (f'a publisher of {topic} offers a QoS this subscription cannot match '
                   f'({policy}); its messages are not received (total '
                   f'{getattr(event, "total_count", "?")})')
        self.report(Report(protocol.ERROR, f'{name} input', message,
                           {'topic': topic, 'policy': policy}, kind='incompatible_qos'))

    def _logger(self, name: str):
        if name not in self._loggers:
            self._loggers[name] = self.node.get_logger().get_child(name)
        return self._loggers[name]

    def drop(self, name: str, topic: str, reason: str) -> None:
        """Count a dropped message, warn (throttled) and report it on /diagnostics; the reason
        is capped (`conversions.cap`), whatever a conversion quoted."""
        reason = cap(reason)
        self.dropped[name] += 1
        self._unreported[name] += 1
        self.last_drop_reason[name] = reason
        self._logger(name).warning(f'dropped a message on {topic}: {reason}',
                                   throttle_duration_sec=WARNING_THROTTLE_SEC)
        if self._report_due(self._last_drop_report, name):
            self.publish(self.status(
                f'{name} input', WARN, f'dropped a message on {topic}: {reason}',
                {'topic': topic, 'reason': reason, 'dropped': self.dropped[name],
                 'dropped_since_last_report': self._unreported[name]}))
            self._unreported[name] = 0

    @staticmethod
    def _report_due(last_report: dict, name) -> bool:
        """True (and the time noted) at most once per input per WARNING_THROTTLE_SEC."""
        now = time.monotonic()
        if now - last_report.get(name, -float('inf')) < WARNING_THROTTLE_SEC:
            return False
        last_report[name] = now
        return True

    def internal_error(self, name: str, topic: str, trace: str) -> None:
        """A bug met while handling an input: logged with its traceback and reported as ERROR
        (both throttled per input, like drops, so a bug hit at 1 kHz cannot flood)."""
        self.dropped[name] += 1
        self._unreported[name] += 1
        self._logger(name).error(f'internal error while handling {topic}:\n{cap(trace, 8000)}',
                                 throttle_duration_sec=WARNING_THROTTLE_SEC)
        if self._report_due(self._last_error_report, name):
            self.publish(self.status(f'{name} input', ERROR, f'internal error handling {topic}',
                                     {'topic': topic,
                                      'error': cap(trace.strip().splitlines()[-1]),
                                      'dropped': self.dropped[name]}))

    def report(self, report: Report) -> None:
        """Publish a protocol machine's report; log it too if it asks, at most once per
        (part, kind) per WARNING_THROTTLE_SEC."""
        if report.log and self._report_due(self._last_log, (report.what, report.kind)):
            if report.level == protocol.ERROR:
                self._logger(report.what).error(report.message)
            else:
                self._logger(report.what).warning(report.message)
        self.publish(self.status(report.what, LEVELS[report.level], report.message,
                                 report.values))

    # -- diagnostics -------------------------------------------------------------------------
    def status(self, what: str, level: bytes, message: str,
               values: Mapping[str, object] | None = None) -> DiagnosticStatus:
        """A status named like diagnostic_updater's, `<node>: <what>`; a namespaced node
        (a second cell) is named `<namespace>/<node>: <what>` so that two cells' reports stay
        apart on the global /diagnostics, and hardware_id is the fully qualified node name."""
        full = self.node.get_fully_qualified_name()
        return diagnostic_status(f'{full.lstrip("/")}: {what}', level, message, values,
                                 hardware_id=full)

    def publish(self, *statuses: DiagnosticStatus) -> None:
        self.publisher.publish(diagnostic_array(statuses, self.node.get_clock().now().to_msg()))

    def publish_health(self, what: str, values: Mapping[str, object]) -> None:
        """The node's periodic status: `values` plus the input counts; WARN once any message
        was dropped."""
        dropped = sum(self.dropped.values())
        message = f'{dropped} messages dropped so far' if dropped else 'ok'
        self.publish(self.status(what, WARN if dropped else OK, message,
                                 {**values, **self.counts()}))

    def counts(self) -> dict:
        """received_<input> and dropped_<input> for every input seen so far."""
        out = {}
        for name in sorted(set(self.received) | set(self.dropped)):
            out[f'received_{name}'] = self.received[name]
            out[f'dropped_{name}'] = self.dropped[name]
        return out


class SampledInputs:
    """Subscriptions a node reads when it chooses (`take`), not as messages arrive.

    rclpy rebuilds its wait set each time a message wakes the executor (about a millisecond of
    Python for a node with a dozen entities), so a node that only needs its inputs at its own
    rate, like the view, should not wake for each of them. These subscriptions live on a helper
    node (`<node>_inputs`, same namespace and context, no parameter services) that no executor
    spins; messages wait in the DDS reader's history (keep last `depth`) until `take()` drains
    them. Conversion errors are dropped and reported through the owner's `Inputs`, and any other
    exception is reported as an internal error, as `Inputs.subscribe` does.

    Names under remapping. The process's ROS arguments are meant for the owner: ros2 launch
    passes `-r __node:=<name>` to every process, and a helper that took the global arguments
    would be renamed to the owner's name (two nodes of one fully qualified name, and `ros2
    node info` or `ros2 param` talking to the wrong one). So the helper ignores the global
    arguments (`use_global_arguments=False`), is named after the owner's final name and
    namespace, and subscribes each topic by the name the owner resolves it to, so the owner's
    topic remappings and namespace still apply to it."""

    def __init__(self, node: Node, inputs: Inputs):
        self.inputs = inputs
        self.node = node
        self.helper = rclpy.create_node(f'{node.get_name()}_inputs',
                                        namespace=node.get_namespace(), context=node.context,
                                        use_global_arguments=False,
                                        start_parameter_services=False, enable_rosout=False)
        self._topics: list[tuple] = []

    def subscribe(self, msg_type, topic: str, profile, convert: Callable[[Any], Any],
                  name: str | None = None, latest_only: bool = False):
        """`convert(msg)` each message; with `latest_only`, only the last one of each `take`
        (the others are taken as bytes and never deserialised)."""
        name = name or topic.rsplit('/', 1)[-1]
        subscription = self.helper.create_subscription(
            msg_type, self.node.resolve_topic_name(topic), lambda *_: None, profile,
            raw=latest_only)
        self._topics.append((name, topic, subscription, convert, latest_only))
        return subscription

    def take(self) -> list[tuple[int, str, Any]]:
        """Everything received since the last call as (published ns, input name, value), in
        publication order (the writers' source timestamps)."""
        from rclpy.serialization import deserialize_message
        events = []
        for name, topic, subscription, convert, latest_only in self._topics:
            taken = []
            with subscription.handle:
                while True:
                    message = subscription.handle.take_message(subscription.msg_type,
                                                               subscription.raw)
                    if message is None:
                        break
                    taken.append(message)
            self.inputs.received[name] += len(taken)
            if latest_only:
                taken = [(deserialize_message(taken[-1][0], subscription.msg_type),
                          taken[-1][1])] if taken else []
            for msg, info in taken:
                try:
                    value = convert(msg)
                except InputError as exc:
                    self.inputs.drop(name, topic, str(exc))
                    continue
                except Exception:  # noqa: BLE001 - a bug must not stop the node; it is reported
                    self.inputs.internal_error(name, topic, traceback.format_exc())
                    continue
                published = info.get('source_timestamp') if isinstance(info, dict) else None
                events.append((int(published or time.time_ns()), name, value))
        events.sort(key=lambda event: event[0])
        return events

    def destroy(self) -> None:
        self.helper.destroy_node()


def warm_up_before_the_node(*arms) -> None:
    """The arms' numba kernels compiled (or loaded from numba's cache) before the node that
    uses them exists: about 9 s on a fresh install, during which a stop signal ends the process
    at once with 0, as during the imports (`stop.importing`): no node and so no DDS participant
    yet (rmw_fastrtps creates it with a context's first node), nothing written. Built after it,
    the node starts with warm kernels and stops as any other. (Warmed up after the node joined
    the graph, robot_bridge_node's first start in a colcon install ignored a SIGINT for 10 s.)"""
    from ..core.robot.arm import warm_up
    with stop.importing():
        warm_up(*arms)


# -- main -------------------------------------------------------------------------------------
STARTUP_ERRORS = (StartupError, ParameterException)
STOP_BACKSTOP_SEC = 1.0   # the longest a spin waits; a stop signal wakes it at once (stop.py)


RCL_SOURCE = re.compile(r',? at /\S+:\d+')      # rcl's "at /project/src/x.c:N" trail
USAGE = ('usage: {prog} [--help] [--ros-args [-p NAME:=VALUE] [--params-file FILE] '
         '[-r FROM:=TO] ...]')
SHOWN_ARGUMENTS = 200     # characters of refused arguments a one-line error quotes


def command_line(node_class, argv: Sequence[str]) -> int | None:
    """What the command line asks before any ROS work: None to start the node (ROS arguments
    only); else the exit code, after the usage and parameters on stdout (--help, 0) or one
    line on stderr (2): an argument that is not a ROS argument, or ROS arguments rcl refuses
    (a --params-file missing or not YAML, a malformed -p). A node used to start on either,
    robot-side ones included, and rcl's refusal was a traceback."""
    prog = os.path.basename(argv[0]) if argv else node_class.NODE_NAME

    def refuse(why: str) -> int:
        print(f'{prog}: error: {why}', file=sys.stderr)
        return 2
    for flag, value in zip(argv, argv[1:]):
        if flag == '--params-file':   # rcl would block on a FIFO and trace back on the rest
            try:
                input_stat(value, ValueError, 'parameters')
            except ValueError as exc:
                return refuse(f'--params-file {exc}')
    try:
        rest = remove_ros_args(list(argv))[1:]
    except _rclpy.UnknownROSArgsError as exc:     # its text: the list's repr
        unknown = ' '.join(re.findall(r"'((?:[^'\\]|\\.)*)'", str(exc))) or str(exc)
        return refuse(f'unknown ROS arguments: {cap(unknown, SHOWN_ARGUMENTS)} (after '
                      f'--ros-args; {prog} --help shows the usage)')
    except _rclpy.RCLError as exc:
        why = RCL_SOURCE.sub('', ' '.join(str(exc).split()))
        return refuse(f'the ROS arguments are refused: {cap(why, SHOWN_ARGUMENTS)}')
    if '-h' in rest or '--help' in rest:
        print(node_help(node_class, prog))
        return 0
    if rest:
        return refuse(f'unrecognized arguments: {cap(" ".join(rest), SHOWN_ARGUMENTS)} (a node '
                      f'takes ROS arguments only: {prog} --ros-args -p NAME:=VALUE; {prog} '
                      '--help lists its parameters)')
    return None


def node_help(node_class, prog: str) -> str:
    """The usage, the node's module docstring's first paragraph and its parameters (their
    ParamSpecs: what `ros2 param describe` shows once it runs)."""
    module = sys.modules[node_class.__module__]
    lines = [USAGE.format(prog=prog), '']
    summary = ' '.join((module.__doc__ or '').split('\n\n')[0].split())
    if summary:
        lines += textwrap.wrap(summary, 96) + ['']
    lines.append(f'parameters of node {node_class.NODE_NAME!r} (set with -p NAME:=VALUE or '
                 'a --params-file):')
    for spec in getattr(module, 'PARAMETERS', ()):
        kind = spec.type.name.lower().replace('_array', '[]')
        extra = ''.join([f', {spec.range[0]}..{spec.range[1]}' if spec.range else '',
                         ', read-only' if spec.read_only else ''])
        lines += textwrap.wrap(f'{spec.name} ({kind}, default {spec.default!r}{extra}): '
                               f'{spec.description}', 96, initial_indent='  ',
                               subsequent_indent='      ')
    return '\n'.join(lines)


def run(node_class, args=None) -> int:
    """The `main()` of a node (ros2/demos talker pattern, with the suite's stop regime of
    `stop.py`); returns the process exit code.

    SIGINT or SIGTERM, at any moment (also while the node is still being built), only notes
    the request; the spin loop sees it and returns, the node's last word (`on_stop()`, if the
    class has one: cell_view's DELETEALL) goes out while the context is up, the node and its
    executor are destroyed while the context is still valid, then the context is shut down:
    exit 0. A second signal forces the exit (`stop.FORCED_EXIT`). A context shut down from
    elsewhere (ExternalShutdownException) also ends the loop. A node that cannot start
    (`StartupError`, a rejected parameter) logs why and returns 1, with no traceback; any
    other error is a bug and propagates. Before any of it, `command_line`: --help, and
    arguments that are not ROS arguments or that rcl refuses (exit 2, one line).
    """
    refused = command_line(node_class, sys.argv if args is None else args)
    if refused is not None:
        return refused
    with stop.regime():
        if stop.requested():
            return 0
        rclpy.init(args=args, **stop.init_options())
        try:
            return _run_node(node_class)
        finally:
            rclpy.try_shutdown()


WRONG_TYPE = re.compile(r"to '([^']*)' of type 'INTEGER', expecting type 'DOUBLE'")


def type_hint(message: str) -> str:
    """What to do about rclpy's refusal of an integer where a parameter is a double (YAML's
    `1` is an integer): write it with a decimal point."""
    found = WRONG_TYPE.search(message)
    return '' if found is None else f' (write {found.group(1)}.0: a number with a decimal point)'


def _run_node(node_class) -> int:
    if stop.requested():
        return 0
    try:
        node = node_class()
    except STARTUP_ERRORS as exc:
        rclpy.logging.get_logger(node_class.NODE_NAME).error(
            f'cannot start: {exc}{type_hint(str(exc))}')
        return 1
    executor = SingleThreadedExecutor()
    try:
        executor.add_node(node)
        wake = node.create_guard_condition(lambda: None)   # a stop signal wakes the spin
        stop.add_waker(wake.trigger)
        try:
            # the context is only ever shut down by this thread (a callback calling
            # rclpy.shutdown(), as in-process composition may): then the loop ends too
            while not stop.requested() and node.context.ok():
                executor.spin_once(timeout_sec=STOP_BACKSTOP_SEC)
        except ExternalShutdownException:
            pass
        finally:
            stop.remove_waker(wake.trigger)
        if hasattr(node, 'on_stop') and node.context.ok():
            try:
                node.on_stop()
            except Exception:  # noqa: BLE001 - the node stops anyway; say why its last word failed
                node.get_logger().error(f'on_stop failed:\n{traceback.format_exc()}')
    finally:
        executor.shutdown(timeout_sec=0)
        node.destroy_node()
    return 0
