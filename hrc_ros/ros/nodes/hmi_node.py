"""hmi: the person's side of the cell, a web page for the worker and one for the operator.

Contract (docs/HMI.md): serves ``http://<host>:<port>/`` (the worker's page) and ``/operator``
(the operator's console) and keeps them live over a WebSocket; the worker's access token opens
the worker's page only. It listens to `hrc/epoch`, `hrc/action`, `hrc/task_state`,
`hrc/belief`, `hrc/distance_level`, `hrc/human_response`, `hrc/task_request_result`, the
decision node's, the task manager's and the robot bridge's statuses on /diagnostics, and the
robot side's speed override, separation and protective stop when they are published; it
publishes the worker's answers on `hrc/human_response` (std_msgs/Bool, reliable) and the
operator's orders on `hrc/task_request` (std_msgs/UInt8MultiArray, `qos.ORDERS`, the path every
order takes), and its health on /diagnostics. The rules (when a request is open, one answer per
request, the task form, what the pages say) are `core.hmi.HmiMachine`; the web server is
`ros.hmi.server` (aiohttp, on a loop in its own thread); this node owns the topics, the
parameters, the timers and the bridge between the two threads.

The four inputs that decide a request (`hrc/epoch`, `hrc/action`, `hrc/task_state`,
`hrc/human_response`, a few messages an epoch) are ordinary subscriptions: the machine takes
each at once, in whatever order DDS delivers them (it pairs them by source timestamp), and the
pages follow. Everything else (the belief, the distance, /diagnostics, the reports, the robot
side) is `SampledInputs`, taken `refresh_rate` times a second and before each control message
(so an epoch's row of the timeline has the belief published before its action), so the node
never wakes for those and its share of the CPU hardly grows with their rates. A page's command
wakes it at
once through a guard condition (the web thread never waits for the executor, nor the executor
for the web thread: a bounded queue between them); the executor runs the control messages
ready with it first, so the machine decides on the latest state, then publishes and replies.
"""

from __future__ import annotations

import json
import os
import queue
import resource
import time
import traceback

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, Float64, Float64MultiArray, String, UInt8, UInt8MultiArray, UInt32

from ...core.hmi import AccessError, AccessPolicy, HmiMachine, is_loopback
from ...core.hmi.access import OPERATOR, TOKEN_ENV, WORKER
from ...core.hmi.orders import REFUSED
from ...core.protocol import InputError
from .. import conversions as conv
from .. import qos
from ..hmi.server import Command, HmiServer, ServerSettings
from ..node_support import (CONFIG, STATUS_PERIOD_SEC, Inputs, ParamSpec, SampledInputs,
                            StartupError, control_clock, node_setup, run)
from .cell_view_node import SAMPLED

T = Parameter.Type
LEGACY_TOKEN_ENV = 'HRC_HMI_TOKEN'
COMMAND_QUEUE = 256        # page commands waiting for the executor; beyond: "busy"
ORDER_REFS_KEPT = 256
# hrc/separation at the arm's joint-state rate (125 Hz) between two reads (20 Hz by default):
# deep enough that a read late by a second loses no sample of the smallest separation
SEPARATION_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=256,
                            reliability=ReliabilityPolicy.BEST_EFFORT)
# hrc/protective_stop is latched (published on change): a late HMI gets the stop in force
STOP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
PARAMETERS = (
    CONFIG,
    ParamSpec('host', T.STRING, '127.0.0.1', 'address the web server binds (loopback by '
              'default: this machine only); any other address needs an access token',
              read_only=True),
    ParamSpec('port', T.INTEGER, 8080, 'TCP port of the pages; 0 = a free port (logged and on '
              '/diagnostics)', read_only=True, range=(0, 65535)),
    ParamSpec('worker_token', T.STRING, '', f"the worker's access token ('' = the "
              f'{TOKEN_ENV[WORKER]} environment variable, else none), at least 16 characters: '
              "it opens the worker's page only; required off loopback. Prefer the environment "
              'variable: a parameter can be read with ros2 param get', read_only=True),
    ParamSpec('operator_token', T.STRING, '', f"the operator's access token ('' = the "
              f'{TOKEN_ENV[OPERATOR]} environment variable, else none), at least 16 '
              "characters, not the worker's: it opens both pages and queues tasks; required "
              'off loopback (and whenever the worker has one)', read_only=True),
    ParamSpec('token', T.STRING, '', "replaced by worker_token and operator_token: a "
              'value here refuses to start rather than guess its role', read_only=True),
    ParamSpec('allowed_origins', T.STRING_ARRAY, [], 'origins besides the page itself whose '
              'pages may open the WebSocket (a reverse proxy\'s public origin, e.g. '
              'https://hmi.plant.example)', read_only=True),
    ParamSpec('allowed_hosts', T.STRING_ARRAY, [], 'Host names the pages may be asked by on '
              'loopback without a token, besides localhost and 127.0.0.1 (a reverse proxy that '
              'passes its Host on)', read_only=True),
    ParamSpec('worker_answers', T.BOOL, True, "Accept and Decline answer the robot's requests "
              'on hrc/human_response; false: the page only shows the answers another source '
              'gives (the simulated person of cell_sim)'),
    ParamSpec('cell_timeout', T.DOUBLE, 0.0, 'seconds without hrc/epoch or hrc/action after '
              'which the pages say "no connection to the cell" and an open request lapses; '
              '0 = 3 x the epoch period seen, at least 3 s', range=(0.0, 3600.0)),
    ParamSpec('refresh_rate', T.DOUBLE, 20.0, 'Hz: how often the inputs are read and the pages '
              'updated (only when something changed)', range=(1.0, 100.0)),
    ParamSpec('order_timeout', T.DOUBLE, 3.0, "seconds an order waits for the task manager's "
              'report on hrc/task_request_result before the operator is told it is unknown',
              range=(0.1, 60.0)),
    ParamSpec('max_connections', T.INTEGER, 1000, 'pages served at once; more get 503',
              read_only=True, range=(1, 100000)),
    ParamSpec('max_frame_bytes', T.INTEGER, 4096, 'largest WebSocket message a page may send; '
              'a larger frame closes its connection (1009)', read_only=True,
              range=(256, 1048576)),
    ParamSpec('message_rate', T.DOUBLE, 10.0, 'messages a second a page may send after '
              'message_burst (more are refused; a page that keeps flooding is closed)',
              read_only=True, range=(0.1, 10000.0)),
    ParamSpec('message_burst', T.INTEGER, 20, 'messages a page may send at once',
              read_only=True, range=(1, 100000)),
    ParamSpec('decision_node', T.STRING, 'decision', 'the decision node whose /diagnostics '
              'status gives the fail-safe reasons', read_only=True),
    ParamSpec('task_manager_node', T.STRING, 'task_manager', 'the task manager whose '
              '/diagnostics status gives the queue', read_only=True),
    ParamSpec('robot_bridge_node', T.STRING, 'robot_bridge', 'the robot bridge whose '
              '/diagnostics status gives the reason of each protective stop', read_only=True),
    ParamSpec('speed_override_topic', T.STRING, 'hrc/speed_override', "the robot side's speed "
              'override (std_msgs/Float64, 0..1), shown on /operator while published',
              read_only=True),
    ParamSpec('separation_topic', T.STRING, 'hrc/separation', "the robot side's separation of "
              'the person from the arm (std_msgs/Float64MultiArray of cobot_sim_node, its S in '
              'metres), shown on /operator while published', read_only=True),
)


def check_parameters(values) -> str | None:
    if 'host' in values and not values['host'].strip():
        return "host must be an address to bind, e.g. 127.0.0.1 (loopback) or 0.0.0.0"
    return None


def _separation(msg: Float64MultiArray) -> tuple[float, float, float]:
    """(S, S_p, speed bound) of the robot side's hrc/separation
    (`conversions.separation_from_msg`): metres, metres, m/s."""
    values = conv.separation_from_msg(msg)
    return values['S'], values['S_p'], values['speed']


def _stopped(msg: Bool) -> bool:
    return bool(msg.data)


def _tokens(values) -> dict:
    """Each role's token: its parameter, else its environment variable. The one token of
    before (the `token` parameter, HRC_HMI_TOKEN) is refused: its role cannot be guessed, and
    dropping it silently would open a page it protected."""
    if values['token'] or os.environ.get(LEGACY_TOKEN_ENV):
        raise StartupError(f'the single access token (token, {LEGACY_TOKEN_ENV}) is replaced by '
                           f"two: the worker's (worker_token, {TOKEN_ENV[WORKER]}) opens the "
                           "worker's page only, the operator's (operator_token, "
                           f'{TOKEN_ENV[OPERATOR]}) the console too; set those and unset it '
                           '(docs/HMI.md, "Roles")')
    return {role: values[f'{role}_token'] or os.environ.get(TOKEN_ENV[role], '')
            for role in (WORKER, OPERATOR)}


class HmiInputs:
    """What the HMI reads and how each message enters its machine, for the node and for a
    replay of recorded messages alike (`replay`: the console's figures of a recorded run).

    `topics`: input name -> (message type, topic); `convert(name, msg)` the value (MessageError
    for a bad message); `feed(machine, name, value, published_ns, now)` hands it to the
    machine and returns the HMI's order a task manager's report decided, if any."""

    CONTROL = ('epoch', 'task_state', 'action', 'human_response')

    def __init__(self, rho: int, sigma: int, namespace: str = '', decision_node='decision',
                 task_manager_node='task_manager', robot_bridge_node='robot_bridge',
                 speed_override_topic='hrc/speed_override', separation_topic='hrc/separation'):
        self.rho, self.sigma = rho, sigma
        prefix = f'{namespace.strip("/")}/' if namespace.strip('/') else ''
        self.statuses = {f'{prefix}{decision_node}: decision': 'decision',
                         f'{prefix}{decision_node}: policy': 'policy',
                         f'{prefix}{task_manager_node}: tasks': 'task_manager',
                         f'{prefix}{robot_bridge_node}: ssm': 'stop',
                         f'{prefix}{robot_bridge_node}: bridge': 'bridge'}
        self.topics = {
            'epoch': (UInt32, 'hrc/epoch'), 'task_state': (UInt8MultiArray, 'hrc/task_state'),
            'action': (String, 'hrc/action'), 'human_response': (Bool, 'hrc/human_response'),
            'belief': (Float64MultiArray, 'hrc/belief'),
            'distance_level': (UInt8, 'hrc/distance_level'),
            'task_request_result': (DiagnosticStatus, 'hrc/task_request_result'),
            'diagnostics': (DiagnosticArray, '/diagnostics'),
            'speed_override': (Float64, speed_override_topic),
            'separation': (Float64MultiArray, separation_topic),
            'protective_stop': (Bool, 'hrc/protective_stop')}
        self._convert = {
            'epoch': conv.epoch_from_msg,
            'task_state': lambda m: conv.task_state_from_msg(m, rho, sigma),
            'action': conv.action_from_msg, 'human_response': conv.human_response_from_msg,
            'belief': conv.belief_from_msg, 'distance_level': conv.distance_level_from_msg,
            'task_request_result': conv.task_request_result_from_msg,
            'diagnostics': self.read_statuses, 'speed_override': conv.speed_override_from_msg,
            'separation': _separation, 'protective_stop': _stopped}

    def convert(self, name: str, msg):
        return self._convert[name](msg)

    def read_statuses(self, msg: DiagnosticArray):
        """The statuses the HMI reads in `msg` (None: none): the decision node's epoch report
        and policy swaps, the task manager's queue, the robot bridge's protective stop (its
        `ssm` report of each stop, and its health every second, which also has the stop in
        force: a stop reported before the HMI listened gets its reason from there)."""
        found = []
        for status in msg.status:
            kind = self.statuses.get(status.name)
            if kind is None:
                continue
            values = conv.diagnostic_values(status)
            level = conv.LEVEL_NAMES.get(status.level, '?')
            if kind == 'decision':
                epoch = values.get('epoch', '')
                if epoch.isdigit() and int(epoch) > 0:
                    found.append((kind, int(epoch), values.get('action', ''),
                                  values.get('faults', ''), level))
            elif kind == 'task_manager':
                found.append((kind, values))
            elif kind == 'stop':
                found.append((kind, status.level != DiagnosticStatus.OK,
                              values.get('reason', '')))
            elif kind == 'bridge':          # its health, every second: the stop in force
                found.append(('stop', values.get('protective_stop') == 'True',
                              values.get('stop_reason', '')))
            else:
                found.append((kind, level, status.message, values))
        return found or None

    @staticmethod
    def feed(machine: HmiMachine, name: str, value, published: int, now: int):
        if name == 'epoch':
            machine.epoch_signal(value, published, now)
        elif name == 'task_state':
            machine.task_state_message(value, published, now)
        elif name == 'action':
            machine.action_message(value, published, now)
        elif name == 'human_response':
            machine.response_message(value, published, now)
        elif name == 'belief':
            machine.belief_message(value)
        elif name == 'distance_level':
            machine.distance_message(value)
        elif name == 'task_request_result':
            return machine.task_request_result(value, published)
        elif name == 'diagnostics' and value is not None:
            for status in value:
                if status[0] == 'decision':
                    machine.decision_report(*status[1:], published)
                elif status[0] == 'task_manager':
                    machine.task_manager_report(status[1])
                elif status[0] == 'stop':
                    machine.stop_report(*status[1:], published)
                else:
                    machine.policy_report(*status[1:], published)
        elif name == 'speed_override':
            machine.speed_override_message(value, now)
        elif name == 'separation':
            machine.separation_message(*value, published, now)
        elif name == 'protective_stop':
            machine.protective_stop_message(value, published)
        return None

    def replay(self, machine: HmiMachine, records) -> None:
        """Recorded messages `(published_ns, input name, message)` into `machine`, in
        publication order (the source timestamps: the clock the machine counts with); a bad
        message is left out, as the node drops it."""
        for published, name, msg in sorted(records, key=lambda r: r[0]):
            try:
                value = self.convert(name, msg)
            except InputError:
                continue
            self.feed(machine, name, value, published, published)


class HmiNode(Node):
    NODE_NAME = 'hmi'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.params, values, self.config, self.model = node_setup(
            self, PARAMETERS, check_parameters, self._apply)
        tokens = _tokens(values)
        self.policy = AccessPolicy(values['host'], tokens[WORKER], tokens[OPERATOR],
                                   values['allowed_origins'], values['allowed_hosts'])
        try:
            self.policy.check_start()
        except AccessError as exc:
            raise StartupError(str(exc)) from None
        self.clock = control_clock(self)
        self.machine = HmiMachine(self.model.rho, self.model.sigma, values['worker_answers'],
                                  values['cell_timeout'], values['order_timeout'])
        self.response_pub = self.create_publisher(Bool, 'hrc/human_response', qos.RELIABLE)
        self.request_pub = self.create_publisher(UInt8MultiArray, 'hrc/task_request',
                                                 qos.ORDERS)
        self.inputs = Inputs(self)
        self.sampled = SampledInputs(self, self.inputs)
        self.reads = HmiInputs(self.model.rho, self.model.sigma, self.get_namespace(),
                               values['decision_node'], values['task_manager_node'],
                               values['robot_bridge_node'], values['speed_override_topic'],
                               values['separation_topic'])
        # In causal order: rclpy runs the messages ready in one wait in subscription order
        for name in HmiInputs.CONTROL:
            msg_type, topic = self.reads.topics[name]
            self.inputs.subscribe(msg_type, topic, SAMPLED, self._converter(name),
                                  self._control(name), name=name, with_published=True)
        for name, profile, latest_only in (
                ('belief', SAMPLED, True), ('distance_level', SAMPLED, True),
                ('task_request_result', qos.REPORTS, False), ('diagnostics', SAMPLED, False),
                ('speed_override', qos.SENSOR_DATA, True), ('separation', SEPARATION_QOS, False),
                ('protective_stop', STOP_QOS, False)):
            msg_type, topic = self.reads.topics[name]
            self.sampled.subscribe(msg_type, topic, profile, self._converter(name), name=name,
                                   latest_only=latest_only)
        self.commands: queue.Queue = queue.Queue(maxsize=COMMAND_QUEUE)
        self.order_refs: dict[int, tuple] = {}
        self.published = {'answers': 0, 'orders': 0}
        self._views: tuple | None = None
        self.wake = self.create_guard_condition(self._on_commands)
        self.push_soon = self.create_guard_condition(lambda: self._push(self._now()))
        self.refresh = self.create_timer(1.0 / values['refresh_rate'], self._refresh)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        settings = ServerSettings(values['host'], values['port'], values['max_connections'],
                                  values['max_frame_bytes'], values['message_rate'],
                                  values['message_burst'])
        self._raise_file_limit(settings.max_connections)
        self.server = HmiServer(settings, self.policy, self._submit)
        try:
            port = self.server.start()
        except OSError as exc:
            raise StartupError(f'cannot serve the pages on {values["host"]}:{values["port"]}: '
                               f'{exc}') from None
        host = values['host']
        shown = f'[{host}]' if ':' in host else host
        self.url = f'http://{shown}:{port}/'
        self.get_logger().info(
            f'worker page {self.url}, operator page {self.url}operator'
            + ('' if is_loopback(host) else ' (access token required)')
            + ('' if values['worker_answers'] else '; the page only shows the answers'))

    def _apply(self, values) -> None:
        if hasattr(self, 'machine'):
            self.machine.worker_answers = values['worker_answers']
            self.machine.cell_timeout_s = values['cell_timeout']
            self.machine.orders.timeout_ns = int(values['order_timeout'] * 1e9)
            self.refresh.timer_period_ns = int(1e9 / values['refresh_rate'])

    def _raise_file_limit(self, connections: int) -> None:
        """Each page is a socket: raise the soft open-files limit towards the hard one."""
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        wanted = connections + 256
        if soft != resource.RLIM_INFINITY and soft < wanted:
            target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            if target < wanted:
                self.get_logger().warning(
                    f'open files limited to {target}: fewer than max_connections '
                    f'({connections}) pages can be served (raise ulimit -n)')

    def _now(self) -> int:
        return self.clock.now().nanoseconds

    # -- inputs ----------------------------------------------------------------------------
    def _converter(self, name: str):
        return lambda msg: self.reads.convert(name, msg)

    def _control(self, name: str):
        """A handler of a control input: the machine takes it at once (after the sampled
        inputs waiting, so it sees the belief and the distance published before it) and the
        pages follow once the control messages ready with it are taken too (an epoch's signal,
        task state and action come together: one view for the three, not three in a row)."""
        def handle(value, published_ns: int) -> None:
            now = self._now()
            self._take(now)
            HmiInputs.feed(self.machine, name, value, published_ns, now)
            self.push_soon.trigger()
        return handle

    def _take(self, now: int) -> None:
        for published, name, value in self.sampled.take():
            self._order_done(HmiInputs.feed(self.machine, name, value, published, now))

    def _refresh(self) -> None:
        now = self._now()
        self._take(now)
        for order in self.machine.expire(now):
            self._order_done(order)
        self.machine.expire_events(time.time_ns())
        self._push(now)

    def _push(self, now: int) -> None:
        machine, wall = self.machine, time.time_ns()
        views = tuple(json.dumps({'type': 'view', **view}, separators=(',', ':'), default=str)
                      for view in (machine.worker_view(now), machine.operator_view(now, wall)))
        if views != self._views:
            self._views = views
            self.server.publish_views({'worker': views[0], 'operator': views[1]})
        feeds = {}
        rows = machine.timeline.take(wall)
        if rows is not None:
            feeds['timeline'] = [json.dumps(rows, separators=(',', ':'))]
        events = machine.events.take()
        if events:
            feeds['events'] = [json.dumps(e, separators=(',', ':')) for e in events]
        if feeds:
            self.server.append_feeds(feeds)

    # -- the pages' commands (web thread -> executor) --------------------------------------
    def _submit(self, command: Command) -> bool:
        """From the web thread: queue a command and wake the executor; False when full."""
        try:
            self.commands.put_nowait(command)
        except queue.Full:
            return False
        self.wake.trigger()
        return True

    def _on_commands(self) -> None:
        now = self._now()
        for _ in range(COMMAND_QUEUE):
            try:
                command = self.commands.get_nowait()
            except queue.Empty:
                break
            try:
                if command.kind == 'answer':
                    self._answer(command, now)
                elif command.kind == 'order':
                    self._order(command, now)
                else:
                    self.machine.forget_client(command.client)
            except Exception:  # noqa: BLE001 - a page's command must not end the node
                self.inputs.internal_error(f'page {command.kind}', 'a page',
                                           traceback.format_exc())
                self._failed(command)
        self._push(now)

    def _failed(self, command: Command) -> None:
        """The reply to a command that failed, shaped as its normal one so that the page
        leaves its waiting state (the worker's buttons, the console's 'sending...')."""
        text = 'the HMI could not handle this (logged); try again'
        payload = command.payload
        if command.kind == 'answer':
            request, accept = payload.get('request'), payload.get('accept')
            self.server.reply(command.client, {
                'type': 'answer_result', 'request': request if isinstance(request, str) else None,
                'accept': accept if isinstance(accept, bool) else None, 'ok': False,
                'code': 'error', 'text': text})
        elif command.kind == 'order':
            self.server.reply(command.client, {'type': 'order_result', 'ref': payload.get('ref'),
                                               'order': None, 'status': REFUSED, 'text': text})

    def _answer(self, command: Command, now: int) -> None:
        request, accept = command.payload['request'], command.payload['accept']
        result = self.machine.answer(request, accept, command.client, now)
        if result.publish is not None:
            self.response_pub.publish(conv.human_response_to_msg(result.publish))
            self.published['answers'] += 1
        self.server.reply(command.client, {
            'type': 'answer_result', 'request': request if isinstance(request, str) else None,
            'accept': accept if isinstance(accept, bool) else None,
            'ok': result.publish is not None, 'code': result.code, 'text': result.text})

    def _order(self, command: Command, now: int) -> None:
        listening = self.request_pub.get_subscription_count() > 0
        step = self.machine.order(command.payload['fields'], command.client, now, listening)
        ref = command.payload.get('ref')
        if step.publish is not None:
            before = time.time_ns()
            self.request_pub.publish(conv.task_request_to_msg(*step.publish))
            self.machine.order_sent(step.order, before, time.time_ns())
            self.published['orders'] += 1
            self.order_refs[step.order.number] = (command.client, ref)
            while len(self.order_refs) > ORDER_REFS_KEPT:
                self.order_refs.pop(next(iter(self.order_refs)))
        order = step.order
        self.server.reply(command.client, {
            'type': 'order_result', 'ref': ref, 'order': None if order is None else order.number,
            'status': order.status if order is not None else step.status,
            'text': order.text if order is not None else step.text})

    def _order_done(self, order) -> None:
        """An order's outcome: tell the page that sent it (if it is still open)."""
        if order is None or order.number not in self.order_refs:
            return
        client, ref = self.order_refs.pop(order.number)
        self.server.reply(client, {'type': 'order_result', 'ref': ref, 'order': order.number,
                                   'status': order.status, 'text': order.text})

    # -- health ----------------------------------------------------------------------------
    def _publish_status(self) -> None:
        machine = self.machine
        request = machine.request
        self.inputs.publish_health('hmi', {
            'url': self.url, 'epoch': machine.epoch,
            'cell_connected': machine.cell_alive(self._now()),
            'worker_answers': machine.worker_answers,
            'request_open': None if request is None else request.text,
            'answers_published': self.published['answers'],
            'orders_published': self.published['orders'],
            **machine.counts,
            **{f'orders_{k}': v for k, v in machine.orders.counts.items()},
            **self.server.stats()})

    def destroy_node(self):
        self.server.stop()
        self.sampled.destroy()
        return super().destroy_node()


def main(args=None):
    return run(HmiNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
