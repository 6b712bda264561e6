"""The operator's task form, and what became of each order.

An order is the form's three fields: ``priority``, ``duration``, ``nature`` (tp, tc, tx).
Each is a whole number (a JSON integer, or a string of ASCII digits, as a form sends it) in its
range (priority 1..rho, duration 1..sigma, nature 0..3 of the model's configuration), refused
in words that name the field, state the range and show what was given ("priority must be a
whole number from 1 to 2, got 'abc'"); the task book's own rule (`tasks.check_task`) has the
last word, so the form accepts exactly what the task manager would queue. A
valid order is published on `hrc/task_request` (the path every order takes) only while a task
manager listens there, at most `rate` orders a second per page (after a `burst`), and at most
`max_pending` orders wait for their outcome at once.

The outcome comes from the task manager: for every request it handles it publishes a report on
`hrc/task_request_result` (accepted and queued, or refused and why; docs/INTERFACES.md) with
the request's content and its source timestamp. The HMI publishes its orders from one thread
and notes the system-clock window around each publish call; a report with the same content
whose source timestamp lies in an order's window is that order's (two of its orders never
share a window). An order with no report after `timeout_ns` is `unknown`: the task manager
may be down or too old to report, and the operator is told so rather than left waiting.
Reports of other publishers' requests (a MES, `ros2 topic pub`) join the operator's list too.
"""

from __future__ import annotations

import re
from collections import OrderedDict, deque
from dataclasses import dataclass

from ..tasks import check_task
from .limits import TokenBucket
from .words import FIELD_WORDS, OPERATOR_NATURES

FIELDS = ('priority', 'duration', 'nature')
CHECKING, SENT, ACCEPTED, REFUSED, UNKNOWN = 'checking', 'sent', 'accepted', 'refused', 'unknown'
MAX_CLIENTS = 1024     # rate-limit buckets kept (least recently used dropped first)


@dataclass
class Order:
    number: int
    client: str
    task: tuple
    created_ns: int
    status: str = CHECKING
    text: str = ''
    window: tuple | None = None      # system clock (ns) before and after the publish call
    queued: int | None = None        # tasks waiting after it was queued


@dataclass(frozen=True)
class OrderStep:
    """The answer to a submitted form: the task to publish on hrc/task_request (None: nothing
    is sent), the order (None when the form was refused before it became one), its status and
    the words for the operator."""

    publish: tuple | None
    order: Order | None
    status: str
    text: str


TASK_PREFIX = re.compile(r'^task \(\d+, \d+, \d+\) refused: ')   # the task book's
DIGITS = re.compile(r'[+-]?[0-9]{1,6}')    # ASCII digits only: '²' and '٣' are not numbers here


def _limits(rho: int, sigma: int) -> dict:
    return {'priority': (1, rho), 'duration': (1, sigma), 'nature': (0, 3)}


def _whole_number(name: str, value, low: int, high: int) -> int:
    """`value` as a whole number in low..high, or `ValueError` that names the field, states
    the range and shows what was given (a person typed it: no Python in the words)."""
    words = FIELD_WORDS[name]
    if name == 'nature':
        expected = (f'{words} must be one of ' + ', '.join(
            f'{k} ({v})' for k, v in OPERATOR_NATURES.items()))
    else:
        expected = f'{words} must be a whole number from {low} to {high}'
    number = None
    if isinstance(value, int) and not isinstance(value, bool):
        number = value
    elif isinstance(value, str) and DIGITS.fullmatch(value.strip()):
        number = int(value.strip())
    if number is not None and low <= number <= high:
        return number
    if number is not None:
        shown = str(number)
    elif isinstance(value, str) and not value.strip():
        shown = 'nothing'
    elif isinstance(value, (list, dict)):    # no repr: a page's JSON may nest a thousand deep
        shown = 'a list' if isinstance(value, list) else 'a set of fields'
    else:
        shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:40] + '...'
    raise ValueError(f'{expected}, got {shown}')


def parse_order(fields, rho: int, sigma: int) -> tuple[int, int, int]:
    """(tp, tc, tx) of a task form, or `ValueError` saying which field is wrong and its range.
    The task book's rule (`tasks.check_task`) has the last word."""
    if not isinstance(fields, dict):
        raise ValueError('a task order has the fields priority, duration and nature')
    missing = [FIELD_WORDS[name] for name in FIELDS if name not in fields]
    if missing:
        raise ValueError(f'{", ".join(missing)} missing: a task order has a priority, a '
                         'duration and who does it')
    limits = _limits(rho, sigma)
    task = tuple(_whole_number(name, fields[name], *limits[name]) for name in FIELDS)
    return check_task(task, rho, sigma)


class Orders:
    def __init__(self, rho: int, sigma: int, timeout_ns: int, rate: float = 1.0,
                 burst: int = 3, max_pending: int = 16, history: int = 20):
        self.rho, self.sigma = rho, sigma
        self.timeout_ns = int(timeout_ns)
        self.rate, self.burst = rate, burst
        self.max_pending = max_pending
        self.pending: OrderedDict[int, Order] = OrderedDict()   # sent, awaiting a report
        self.history: deque = deque(maxlen=history)            # orders and others' reports
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()
        self._count = 0
        self.counts = {ACCEPTED: 0, REFUSED: 0, UNKNOWN: 0, 'invalid': 0, 'limited': 0}

    def _bucket(self, client: str, now: int) -> TokenBucket:
        bucket = self._buckets.pop(client, None) or TokenBucket(self.rate, self.burst, now)
        self._buckets[client] = bucket
        while len(self._buckets) > MAX_CLIENTS:
            self._buckets.popitem(last=False)
        return bucket

    def forget(self, client: str) -> None:
        """A page went away: its rate-limit state goes too."""
        self._buckets.pop(client, None)

    def submit(self, fields, client: str, now: int, listening: bool) -> OrderStep:
        try:
            task = parse_order(fields, self.rho, self.sigma)
        except ValueError as exc:
            self.counts['invalid'] += 1
            return OrderStep(None, None, REFUSED, f'refused: {exc}')
        if not self._bucket(client, now).take(now):
            self.counts['limited'] += 1
            return OrderStep(None, None, REFUSED, 'refused: too many orders from this page; '
                             f'at most {self.rate:g} a second')
        if not listening:
            return OrderStep(None, None, REFUSED, 'not sent: no task manager listens on '
                             'hrc/task_request (is the cell running?)')
        if len(self.pending) >= self.max_pending:
            return OrderStep(None, None, REFUSED, f'not sent: {len(self.pending)} orders still '
                             'wait for the task manager; try again in a moment')
        self._count += 1
        order = Order(self._count, client, task, now, CHECKING, 'sending...')
        self.history.append(order)
        return OrderStep(task, order, CHECKING, order.text)

    def sent(self, order: Order, before_ns: int, after_ns: int) -> None:
        """The ring published `order` between these system-clock times."""
        order.window = (int(before_ns), int(after_ns))
        order.status, order.text = SENT, 'sent: waiting for the task manager'
        self.pending[order.number] = order

    def report(self, result: dict) -> Order | None:
        """A task manager's report on one request (`conversions.task_request_result_from_msg`);
        the order it answers, now decided, or None (another publisher's request)."""
        stamp, task = result.get('published_ns'), result.get('task')
        for number, order in self.pending.items():
            if task == order.task and stamp is not None \
                    and order.window[0] <= stamp <= order.window[1]:
                del self.pending[number]
                self._decide(order, result)
                return order
        self.history.append(Order(0, '', task if task is not None else (), 0,
                                  ACCEPTED if result.get('accepted') else REFUSED,
                                  self.words(result), None, result.get('queued')))
        return None

    def words(self, result: dict) -> str:
        """A report in words: "accepted: queued, 2 waiting" or "refused: <reason>"."""
        if result.get('accepted'):
            queued = result.get('queued')
            return 'accepted: queued' + (f', {queued} waiting' if queued is not None else '')
        reason = TASK_PREFIX.sub('', result.get('reason') or '') or 'no reason given'
        return f'refused: {reason}'

    def _decide(self, order: Order, result: dict) -> None:
        order.status = ACCEPTED if result.get('accepted') else REFUSED
        order.queued = result.get('queued')
        order.text = self.words(result)
        self.counts[order.status] += 1

    def expire(self, now: int) -> list[Order]:
        """Orders whose report did not come within the timeout, now `unknown`."""
        lapsed = [o for o in self.pending.values() if now - o.created_ns >= self.timeout_ns]
        for order in lapsed:
            del self.pending[order.number]
            order.status = UNKNOWN
            order.text = (f'no report from the task manager within {self.timeout_ns * 1e-9:g} s: '
                          'it may not have been queued (check hrc/task_state)')
            self.counts[UNKNOWN] += 1
        return lapsed
