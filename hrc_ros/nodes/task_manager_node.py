"""task_manager: the cell's task and activity bookkeeping (MODEL.md 3.2) on the ROS graph.

It holds a `TaskBook` and drives it by the epoch protocol of docs/DESIGN.md. On `hrc/epoch` k:

1. finalise a_{k-1}: ``book.apply(a_{k-1}, accepted)``, where a_{k-1} is the last `hrc/action`
   received since epoch k-1 and `accepted` is whether the last `hrc/human_response` received
   since epoch k-1 was true (the step ignores it unless a_{k-1} was an eligible request);
2. ``book.begin_epoch(k)``: scheduled tasks due at k are released, an idle cell takes the head
   of the queue;
3. publish `hrc/task_state` ``[tp, tc, tx, ty, hp, hc, bp, bc]`` (latched) and a status.

The response window opens at the epoch rather than at the action, so that a response that
overtakes the action on the way here still counts.

Step 1 waits for what it needs. `hrc/epoch` k, a_{k-1} and the answer to it come from three
writers: DDS does not order them, and rclpy's executor runs the callbacks of messages that are
ready together in subscription order (the epoch first), not in arrival order. So when epoch k
arrives before a_{k-1}, or before the human's answer to an eligible request a_{k-1}, the
finalisation is held until it arrives, at most `input_timeout`; then a missing a_{k-1} counts as
dn and a missing answer as a refusal, with a warning and a diagnostic. Keep `input_timeout`
below the decision node's, which waits for this node's task state. (Finalising at once made a
loaded machine record an accepted request as refused.) A response that arrives after its
epoch was finalised falls into the next window, where it answers the next request ("the
robot's last request"), except in the window right after a request was refused for want of
an answer: there every response published before that window's action is ignored (with a
warning and a diagnostic), since it answers the refused request. So an answer sent before the
next request is never taken as consent to it; one sent after it is its answer. Of several
responses in a window the latest published counts. (Publication times are the writers' source
timestamps: the hosts' clocks must agree, as for tf.)

A restarted epoch count (hrc/epoch 1 after a higher one: the decision node restarted, or a
replay began again) is followed, not refused: the old count's last action is finalised like
any other (held for it and its answer, else dn), the task state and queue are kept, and the
numbering starts again. Requests on `hrc/task_request` beyond `max_queue` waiting tasks are
refused with a warning and a diagnostic (scheduled releases are not limited).

Tasks enter through the `initial_task` (tp, tc, tx) present at epoch 1, the `schedule`
(``"epoch:tp,tc,tx"`` releases) and `hrc/task_request` ``[tp, tc, tx]`` (validated against the
model's rho and sigma, then queued; a bad request is dropped with a warning and a diagnostic).
"""

from __future__ import annotations

from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Bool, String, UInt8MultiArray, UInt32

from .. import conversions as conv
from .. import qos
from ..model import ACTIONS, DN, HRCModel, request_eligible
from ..tasks import TaskBook, parse_schedule
from .common import (STATUS_PERIOD_SEC, WARN, Deadline, Inputs, NodeParameters, ParamSpec, StartupError,
                     check_array, load_node_config, run)

T = Parameter.Type
PARAMETERS = (
    ParamSpec('config', T.STRING, '', "model configuration YAML ('' = the shipped "
              'default.yaml)', read_only=True),
    ParamSpec('initial_task', T.INTEGER_ARRAY, [], '(tp, tc, tx) of the task present at epoch '
              '1; [] = an idle cell', read_only=True,
              constraints='[] or 3 integers: tp in 1..rho, tc in 1..sigma, tx in 0..3'),
    ParamSpec('schedule', T.STRING_ARRAY, [], 'scripted task releases "epoch:tp,tc,tx"',
              read_only=True, constraints='each entry "epoch:tp,tc,tx", epoch >= 1'),
    ParamSpec('max_queue', T.INTEGER, 100, 'tasks that may wait in the queue; a request '
              'beyond them is refused (dropped with a diagnostic)', read_only=True,
              range=(1, 1000000)),
    ParamSpec('input_timeout', T.DOUBLE, 0.25, 'seconds after hrc/epoch k to wait for a_{k-1} '
              'and, for an eligible request, the human response; then dn / refused. Keep it '
              "below the decision node's input_timeout", range=(0.0, 3600.0)),
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
        self.params = NodeParameters(self, PARAMETERS, check_parameters,
                                     self._apply_parameters)
        values = self.params.values()
        self.config = load_node_config(values['config'])
        self.model = HRCModel(self.config)
        initial = tuple(int(v) for v in values['initial_task']) or None
        try:
            self.book = TaskBook(self.model, initial_task=initial,
                                 schedule=list(values['schedule']),
                                 max_queue=values['max_queue'])
        except ValueError as exc:
            raise StartupError(f'task parameters: {exc}') from None
        self._action: int | None = None     # a_{k-1}
        self._action_ns: int | None = None  # its publication time
        self._response: tuple[bool, int] | None = None  # last response since epoch k-1, (value,
        #                                                 publication time)
        self._screening = False             # the last request was refused for want of an
        #                                     answer: screen out answers sent before a_k
        self._next_epoch: int | None = None  # epoch k, received, waiting for step 1
        self._renumber = False              # epoch k restarts the count
        self.last_finalised: tuple | None = None
        self.late_inputs = 0                # finalisations that timed out
        self.late_answers = 0               # responses ignored as answers to a refused request

        self.task_state_pub = self.create_publisher(UInt8MultiArray, 'hrc/task_state',
                                                    qos.LATCHED)
        self.inputs = Inputs(self)
        self.inputs.subscribe(UInt32, 'hrc/epoch', qos.RELIABLE, conv.epoch_from_msg,
                              self._on_epoch)
        self.inputs.subscribe(String, 'hrc/action', qos.RELIABLE, conv.action_from_msg,
                              self._on_action, with_published=True)
        self.inputs.subscribe(Bool, 'hrc/human_response', qos.RELIABLE,
                              conv.human_response_from_msg, self._on_human_response,
                              with_published=True)
        self.inputs.subscribe(UInt8MultiArray, 'hrc/task_request', qos.RELIABLE,
                              self._task_request_from_msg, self._on_task_request)
        self.status_timer = self.create_timer(STATUS_PERIOD_SEC, self._publish_status)
        self.hold = Deadline(self, values['input_timeout'], self._on_hold_timeout)

    def _apply_parameters(self, values) -> None:
        self.hold.set_period(values['input_timeout'])

    def _task_request_from_msg(self, msg):
        return conv.task_request_from_msg(msg, self.model.rho, self.model.sigma)

    # -- inputs ----------------------------------------------------------------------------
    def _on_action(self, action: int, published_ns: int) -> None:
        self._action, self._action_ns = action, published_ns
        self._screen_response()
        self._try_finalise()

    def _on_human_response(self, accepted: bool, published_ns: int) -> None:
        if self._response is None or published_ns >= self._response[1]:
            self._response = (accepted, published_ns)     # the latest word of the human
        self._screen_response()
        self._try_finalise()

    def _screen_response(self) -> None:
        """In the window after a request was refused for want of an answer, ignore a response
        published before this window's action: it is the late answer to the refused request.
        Every such response is screened (a double press, two answering writers)."""
        if not (self._screening and self._response is not None
                and self._action_ns is not None and self._response[1] < self._action_ns):
            return
        self.late_answers += 1
        message = (f'ignored a late human response ({self._response[0]}): it was sent before '
                   f'{ACTIONS[self._action]} of epoch {self.book.epoch}, so it answers the '
                   'request refused earlier for want of an answer')
        self._response = None
        self.get_logger().warning(message, throttle_duration_sec=5.0)
        self.inputs.publish(self.inputs.status('tasks', WARN, message,
                                               {'epoch': self.book.epoch}))

    def _on_task_request(self, task: tuple) -> None:
        try:
            self.book.request(*task)
        except ValueError as exc:
            raise conv.MessageError(str(exc)) from None
        self.get_logger().info(f'task {task} queued; {len(self.book.queue)} waiting')

    def _on_epoch(self, k: int) -> None:
        last = self.book.epoch if self._next_epoch is None else self._next_epoch
        restarted = self.inputs.epoch_order(k, last)
        if self._next_epoch is not None:        # epoch k came before k-1 was finalised
            self._try_finalise(timed_out=True)
        self._next_epoch = k
        self._renumber = restarted              # the old count's last action is finalised
        if self.book.epoch < 1:                 # as any other (held for it, else dn)
            self._begin(k)
        else:
            self._try_finalise()

    def _accepted(self) -> bool:
        return self._response is not None and self._response[0]

    def _awaited(self) -> str | None:
        """What step 1 still waits for, or None."""
        if self._action is None:
            return f'hrc/action of epoch {self.book.epoch}'
        task = self.book.state
        if self._response is None and request_eligible(self._action, task['tp'], task['tx'],
                                                       task['ty']):
            return (f'hrc/human_response to {ACTIONS[self._action]} of epoch '
                    f'{self.book.epoch}')
        return None

    def _try_finalise(self, timed_out: bool = False) -> None:
        if self._next_epoch is None:
            return
        awaited = self._awaited()
        if awaited is not None and not timed_out:
            if not self.hold.armed:
                self.hold.start()
            return
        unanswered = awaited is not None and self._action is not None
        if awaited is not None:
            self.late_inputs += 1
            message = (f'no {awaited} within input_timeout; taking '
                       + ('dn' if self._action is None else 'the request as refused'))
            self.get_logger().warning(message, throttle_duration_sec=5.0)
            self.inputs.publish(self.inputs.status('tasks', WARN, message,
                                                   {'epoch': self.book.epoch}))
        action = DN if self._action is None else self._action
        accepted = self._accepted()
        self.book.apply(action, accepted)
        self.last_finalised = (self.book.epoch, ACTIONS[action], accepted)
        if self._renumber:
            self.book.renumber(self._next_epoch)
        self._begin(self._next_epoch)
        self._screening = unanswered            # for the window that begins now

    def _on_hold_timeout(self) -> None:
        self._try_finalise(timed_out=True)

    def _begin(self, k: int) -> None:
        self.hold.cancel()
        self.book.begin_epoch(k)
        self._next_epoch, self._renumber, self._screening = None, False, False
        self._action, self._action_ns, self._response = None, None, None
        self.task_state_pub.publish(conv.task_state_to_msg(self.book.state))
        self._publish_status()

    # -- health ----------------------------------------------------------------------------
    def _publish_status(self) -> None:
        head = self.book.queue[0] if self.book.queue else None
        values = {'epoch': self.book.epoch, 'task_state': list(self.book.state.values()),
                  'queued_tasks': len(self.book.queue),
                  'next_queued': None if head is None else (head.tp, head.tc, head.tx),
                  'last_finalised': self.last_finalised,
                  'waiting_for': None if self._next_epoch is None else self._awaited(),
                  'late_inputs': self.late_inputs,
                  'late_answers_ignored': self.late_answers,
                  'completed_tasks': len(self.book.completed)}
        self.inputs.publish_health('tasks', values)


def main(args=None):
    return run(TaskManagerNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
