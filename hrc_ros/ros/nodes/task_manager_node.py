"""task_manager: the cell's task and activity bookkeeping (MODEL.md 3.2) on the ROS graph.

Contract (docs/DESIGN.md, "ROS epoch protocol"): on `hrc/epoch` k it finalises a_{k-1}
(`hrc/action`, and the `hrc/human_response` to an eligible request), begins epoch k and
publishes `hrc/task_state` ``[tp, tc, tx, ty, hp, hc, bp, bc]`` (latched). With
`robot_progress` true it also subscribes the robot bridge's `hrc/robot_progress` ``[nature,
cycles, cycles_done]`` and the robot's counter bc runs down only when the arm has completed a
cycle of its program (`core.tasks.robot_cycle_done`, the batch cell's rule; docs/ROBOT.md).
Tasks come from the
`initial_task`, the scripted `schedule` and `hrc/task_request` ``[tp, tc, tx]``. The rules
(holds, timeouts, late answers, restarts) are `core.protocol.TaskEpochs`; this node owns the
topics, the parameters and the timer. Every task request is counted once, as accepted, refused
(malformed, out of its domain, the queue full) or lost (`core.protocol.RequestCounts`), and
every request it handles, valid or not, gets one report on `hrc/task_request_result`
(accepted and queued, or refused and why: docs/INTERFACES.md), so whoever ordered it (the HMI's
operator page, a MES) learns its fate.
"""

from __future__ import annotations

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Bool, String, UInt8MultiArray

from ...core.protocol import (ERROR, TASK_HOLD, WARN, InputError, Report, RequestCounts, Stamp,
                              TaskEpochs, check_timeout_order)
from ...core.study.simulation import check_model_cell
from ...core.tasks import TaskBook, parse_schedule
from .. import conversions as conv
from .. import qos
from ..node_support import (CONFIG, STATUS_PERIOD_SEC, DeadlineTimer, Inputs, ParamSpec,
                            StartupError, check_array, control_clock, node_setup, run)
from ..sources import subscribe_epochs

T = Parameter.Type
PARAMETERS = (
    CONFIG,
    ParamSpec('initial_task', T.INTEGER_ARRAY, [], '(tp, tc, tx) of the task present at epoch '
              '1; [] = an idle cell', read_only=True,
              constraints='[] or 3 integers: tp in 1..rho, tc in 1..sigma, tx in 0..3'),
    ParamSpec('schedule', T.STRING_ARRAY, [], 'scripted task releases "epoch:tp,tc,tx"',
              read_only=True, constraints='each entry "epoch:tp,tc,tx", epoch >= 1'),
    ParamSpec('max_queue', T.INTEGER, 100, 'tasks that may wait in the queue; a request '
              'beyond them is refused (dropped with a diagnostic)', read_only=True,
              range=(1, 1000000)),
    ParamSpec('input_timeout', T.DOUBLE, 0.0, 'seconds after hrc/epoch k to wait for a_{k-1} '
              'and, for an eligible request, the human response; then dn / refused. 0 = '
              f'{TASK_HOLD.fraction:g} x the epoch period seen on hrc/epoch '
              f'({TASK_HOLD.fallback_s:g} s before two epochs); an explicit value must be '
              "shorter than the belief estimator's task_state_timeout and the decision node's "
              'input_timeout', range=(0.0, 3600.0)),
    ParamSpec('robot_progress', T.BOOL, False, "the robot's counter bc follows the arm's "
              'physical work: it runs down in an epoch only if the robot bridge reported a '
              'completed program cycle on hrc/robot_progress by its end (the cell with the '
              "arm, docs/ROBOT.md); false: the model's rule (every action but dn)",
              read_only=True),
)


def check_parameters(values) -> str | None:
    task = values.get('initial_task', [])
    if task:
        reason = check_array(values, 'initial_task', 3, low=0)
        if reason:
            return reason
    try:
        parse_schedule(list(values.get('schedule', [])))
    except ValueError as exc:
        return f'schedule: {exc}'
    return None


class TaskManagerNode(Node):
    NODE_NAME = 'task_manager'

    def __init__(self, **kwargs):
        super().__init__(self.NODE_NAME, **kwargs)
        self.tasks: TaskEpochs | None = None
        self.params, values, self.config, self.model = node_setup(
            self, PARAMETERS, self._check_parameters, self._apply_parameters)
        if not values['robot_progress']:
            # without the arm's progress this node runs the model's own cell (the paper's
            # counter, one an epoch): refuse a model that cell cannot run (MODEL.md 3.2)
            try:
                check_model_cell(self.model)
            except ValueError as exc:
                raise StartupError(f'{exc}; this node needs robot_progress: true with it (the '
                                   'cell with the arm, robot:=sim)') from None
        initial = tuple(int(v) for v in values['initial_task']) or None
        try:
            book = TaskBook(self.model, initial_task=initial, schedule=list(values['schedule']),
                            max_queue=values['max_queue'])
        except ValueError as exc:
            raise StartupError(f'task parameters: {exc}') from None
        self.clock = control_clock(self)
        self.input_timeout = values['input_timeout']
        self.tasks = TaskEpochs(book, TASK_HOLD.ns(self.input_timeout, None),
                                robot_progress=values['robot_progress'])
        self._order_reported: str | None = None

        self.task_state_pub = self.create_publisher(UInt8MultiArray, 'hrc/task_state',
                                                    qos.LATCHED)
        self.request_result_pub = self.create_publisher(DiagnosticStatus,
                                                        'hrc/task_request_result', qos.REPORTS)
        self.inputs = Inputs(self)
        self.epoch_publishers = subscribe_epochs(self.inputs, lambda: self.tasks.epochs,
                                                 self._on_epoch)
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              lambda a, t: self._step(self.tasks.action(a, t, self._now())),
                              with_published=True)
        self.inputs.subscribe(Bool, 'hrc/human_response', qos.RELIABLE,
                              conv.human_response_from_msg,
                              lambda yes, t: self._step(self.tasks.answer(yes, t, self._now())),
                              with_published=True)
        self.inputs.subscribe(UInt8MultiArray, 'hrc/task_request', qos.ORDERS,
                              lambda msg: msg, self._on_task_request, with_stamp=True)
        if values['robot_progress']:
            self.inputs.subscribe(UInt8MultiArray, 'hrc/robot_progress', qos.RELIABLE,
                                  conv.robot_progress_from_msg,
                                  lambda p, t: self.tasks.robot_progress_received(
                                      p['nature'], p['cycles'], p['cycles_done'], t),
                                  with_published=True)
        self.requests = RequestCounts()
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        self.hold = DeadlineTimer(self, lambda now: self._step(self.tasks.expire(now)))

    @property
    def book(self) -> TaskBook:
        return self.tasks.book

    def _now(self) -> int:
        return self.clock.now().nanoseconds

    def _period_s(self) -> float | None:
        period = None if self.tasks is None else self.tasks.epochs.period.period_ns
        return None if period is None else period * 1e-9

    def _hold_ns(self) -> int:
        """input_timeout, or a fraction of the epoch period the follower sees."""
        return TASK_HOLD.ns(self.input_timeout, self.tasks.epochs.period.period_ns)

    def _check_parameters(self, values) -> str | None:
        return check_parameters(values) or check_timeout_order(
            self._period_s(), {TASK_HOLD: values.get('input_timeout', 0.0)})

    def _apply_parameters(self, values) -> None:
        self.input_timeout = values['input_timeout']
        self.tasks.input_timeout_ns = self._hold_ns()

    def _check_timeout_order(self) -> None:
        """An explicit input_timeout that the period learnt since makes too long: WARN once
        (the value was accepted before the period was known)."""
        reason = check_timeout_order(self._period_s(), {TASK_HOLD: self.input_timeout}) \
            if self.input_timeout > 0 else None
        if reason and reason != self._order_reported:
            self.inputs.report(Report(WARN, 'timeouts', f'{reason} (epoch period seen on '
                                      f'hrc/epoch: {self._period_s():g} s)',
                                      {'input_timeout': self.input_timeout}, kind='order'))
        self._order_reported = reason

    def _on_epoch(self, k: int, stamp: Stamp) -> None:
        step = self.tasks.epoch(k, stamp, self._now())   # InputError: another epoch source
        self.tasks.input_timeout_ns = self._hold_ns()
        self._check_timeout_order()
        self._step(step)

    def _on_task_request(self, msg, stamp: Stamp) -> None:
        """Every request in one count: lost before it (its writer's numbers skip), then this
        one accepted or refused, for whatever reason (the conversion or the task book), and
        one report of its fate on hrc/task_request_result."""
        self._report_lost_requests(stamp)
        task, error = None, None
        try:
            task = conv.task_request_from_msg(msg, self.model.rho, self.model.sigma)
            self.tasks.request(*task)
        except InputError as exc:
            error = exc
            if task is None and len(msg.data) == 3:     # reported with its content
                task = tuple(int(v) for v in msg.data)
        if error is None:
            self.requests.accept()
        else:
            self.requests.refuse()
        node = self.get_fully_qualified_name()
        self.request_result_pub.publish(conv.task_request_result_to_msg(
            f'{node.lstrip("/")}: task_request', node, error is None, str(error or ''), task,
            np.asarray(msg.data), stamp.published_ns, stamp.sequence, len(self.book.queue)))
        if error is not None:
            raise error          # dropped with a warning and a diagnostic, as any bad input
        self.get_logger().info(f'task {task} queued; {len(self.book.queue)} waiting')

    def _report_lost_requests(self, stamp: Stamp) -> None:
        """Report requests a writer sent that never arrived (a writer's own keep-last history
        can overwrite a burst before it is sent): with one publisher on the topic, its
        sequence numbers must not skip."""
        last = self.requests.gaps.last
        lost = self.requests.arrived(stamp.sequence,
                                     self.count_publishers('hrc/task_request') == 1)
        if lost:
            self.inputs.report(Report(
                ERROR, 'task_request input', f'{lost} task request(s) sent on hrc/task_request '
                "never arrived (the publisher's sequence numbers skip from "
                f'{last} to {stamp.sequence}): publish orders with a deeper history or '
                'KEEP_ALL', {'lost': lost, 'lost_total': self.requests.lost},
                kind='lost_requests'))

    def _step(self, step) -> None:
        for report in step.reports:
            self.inputs.report(report)
        if step.task_state is not None:
            self.task_state_pub.publish(conv.task_state_to_msg(step.task_state))
            self._publish_status()
        self.hold.sync(self.tasks.deadline)

    def _publish_status(self) -> None:
        timeout_s = self.tasks.input_timeout_ns * 1e-9
        self.inputs.publish_health('tasks', {
            **self.tasks.status(), 'input_timeout_s': timeout_s, **self.requests.counts()})


def main(args=None):
    return run(TaskManagerNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
