"""The person's side of the cell, without ROS and without a web framework: the rules of the HMI.

What the worker and the operator see, and what their taps may do, as a sans-IO state machine
(the `h11` pattern): the HMI node feeds it the cell's messages (epoch, action, task state,
belief, distance level, diagnostics, the robot arm's speed override and separation) with their
source timestamps and its clock, and the pages' commands (an answer to a request, a task
order) with the client that sent them; the machine says what to publish on the graph, what to
answer the page and what the pages show, in words.

- `machine`: `HmiMachine`: when a request is open (`model.request_eligible` on the epoch's task
  state, until the task manager's next task state closes it), one answer per request, the
  outcome of each request and each order, the cell's liveness;
- `orders`: the task form (`tasks.check_task`, the task book's own rule) and the outcome of
  each order, matched to the task manager's `hrc/task_request_result` reports;
- `words`: the actions, tasks, distance bands and fail-safes in the worker's words, and the two
  views (`worker_view`, `operator_view`) as plain dicts;
- `access`: the security rules of the web server (loopback binding, the access token, the
  Origin and Host checks), as pure functions;
- `limits`: token-bucket rate limits.
"""

from .access import AccessError, AccessPolicy, is_loopback
from .limits import TokenBucket
from .machine import AnswerResult, HmiMachine, Request
from .orders import Order, OrderStep, Orders

__all__ = ['AccessError', 'AccessPolicy', 'AnswerResult', 'HmiMachine', 'Order', 'OrderStep',
           'Orders', 'Request', 'TokenBucket', 'is_loopback']
