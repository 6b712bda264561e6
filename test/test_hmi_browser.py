"""The HMI in a real browser on the real graph: headless Chromium (Debian's, driven by
Playwright) against `hmi_node` and the suite's nodes as processes, started as a user starts
them (their console scripts, real DDS), like test/test_suite_multiprocess.py.

The cell is the case study's first task (1, 1, 3): a joint task, so the decision node asks
`rh2`; the simulated person does not answer (`cell_sim` `answer_requests: false`): the page
does. In order, on one running cell:

1. the worker's page, opened before the decision node runs, says "no connection to the cell",
   and "connected" by itself once the cell runs;
2. the robot asks; the test taps Decline (a double tap): one `false` on hrc/human_response, the
   task manager leaves the task uncommitted, the page says "declined";
3. the robot asks again; the test taps Accept: one `true`, the task manager commits the task
   (ty = 3 in hrc/task_state), the page says "accepted", and so does a second tab, with its
   buttons disabled (the server's refusal of a second tab's answer is test_hmi_node.py's);
4. the operator queues a task from the form: the page shows the task manager's "accepted:
   queued" and the task appears in hrc/task_state; an out-of-range one and one with letters
   are refused with the field's range; the console's timeline has the epochs;
5. the HMI process is stopped: the page says "no connection to the cell"; started again on the
   same port with tokens the page lacks, it says its access is refused; started again without
   them, the page reconnects by itself.

Before them, `hrc-hmi-shots`' screenshots of its scripted cell at the three sizes.

Waits are on conditions with bounded timeouts (Playwright's expect, the listener's
predicates), never fixed sleeps.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from playwright.sync_api import expect
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, String, UInt8MultiArray

from hrc_ros.ros import conversions as conv
from hrc_ros.ros.processes import NodeProcesses
from spun import SpunNode

EPOCH_PERIOD = 1.0        # a person's window: the epoch and the task manager's 0.6 s hold
START_TIMEOUT = 40.0      # seconds for the processes to start (a loaded machine)
REQUEST_TIMEOUT = 30.0    # seconds for the robot to ask
MS = 1000

PARAMS = """\
/**:
  ros__parameters:
    config: ''
decision:
  ros__parameters:
    policy: '{policy}'
    epoch_period: {period}
    input_timeout: 0.8
    min_epoch_subscribers: 2
task_manager:
  ros__parameters:
    initial_task: [1, 1, 3]
    input_timeout: 0.6
cell_sim:
  ros__parameters:
    seed: 8
    initial_emotions: [0, 0]
    initial_distance: 1
    answer_requests: false
hmi:
  ros__parameters:
    port: {port}
"""
DEEP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                  reliability=ReliabilityPolicy.RELIABLE)


class Listener(SpunNode):
    """The test's own node, spun in a thread: what the cell publishes, in arrival order."""

    def __init__(self):
        super().__init__('hmi_browser_listener')
        self.task_states: list[dict] = []
        self.responses: list[bool] = []
        self.actions: list[str] = []
        self.hmi: dict = {}
        self.node.create_subscription(
            UInt8MultiArray, 'hrc/task_state',
            lambda m: self.task_states.append(conv.task_state_from_msg(m)), DEEP)
        self.node.create_subscription(Bool, 'hrc/human_response',
                                      lambda m: self.responses.append(m.data), DEEP)
        self.node.create_subscription(String, 'hrc/action',
                                      lambda m: self.actions.append(m.data), DEEP)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._status, DEEP)
        self.start()

    def _status(self, msg):
        for status in msg.status:
            if status.name == 'hmi: hmi':
                self.hmi = conv.diagnostic_values(status)

    def wait(self, predicate, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while not predicate():
            assert time.monotonic() < deadline, f'timed out after {timeout} s waiting for {what}'
            time.sleep(0.02)

    def nodes_up(self, names) -> bool:
        return set(names) <= set(self.node.get_node_names())



LOGGED_URL = re.compile(r'worker page (http://127\.0\.0\.1:(\d+)/),')


def logged_port(suite: NodeProcesses, name: str = 'hmi_node') -> int | None:
    """The port the HMI bound, from its log line (port 0: the OS chose it, so no other
    process can hold it, as it could a number picked here and bound later); None until the
    line is there."""
    found = LOGGED_URL.search(suite.log(name, 10 ** 6))
    return None if found is None else int(found.group(2))


def serving(port: int | None) -> bool:
    """The HMI's web server accepts connections (its node joins the graph before it binds)."""
    if port is None:
        return False
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(('127.0.0.1', port)) == 0


@pytest.fixture(scope='module')
def cell(tmp_path_factory, policy_path, ros_domain_id):
    """The suite's processes (all but the decision node, which the first test starts), the
    listener and the HMI's URL; always stopped at the end."""
    folder = tmp_path_factory.mktemp('hmi_cell')
    params = folder / 'params.yaml'
    params.write_text(PARAMS.format(policy=policy_path, period=EPOCH_PERIOD, port=0))
    suite = NodeProcesses(folder, [params])
    listener = Listener()
    try:
        for node in ('hmi', 'task_manager', 'belief_estimator', 'cell_sim'):
            suite.start(f'{node}_node')
        listener.wait(lambda: (listener.nodes_up(('hmi', 'task_manager', 'belief_estimator',
                                                  'cell_sim')) and serving(logged_port(suite)))
                      or suite.dead(), START_TIMEOUT, 'the nodes to start')
        assert not suite.dead(), suite.logs()
        port = logged_port(suite)
        # a restart (test_the_page_recovers_when_the_hmi_restarts) binds the same port
        params.write_text(PARAMS.format(policy=policy_path, period=EPOCH_PERIOD, port=port))
        yield suite, listener, f'http://127.0.0.1:{port}/'
    finally:
        suite.stop(10.0)
        listener.close()


@pytest.fixture(scope='module')
def pages(browser, cell):
    """The worker's page, a second tab, and the operator's page, in one browser context."""
    context = browser.new_context(viewport={'width': 1280, 'height': 800})
    context.set_default_timeout(REQUEST_TIMEOUT * MS)
    yield context
    context.close()


# every text an element shows from now on, into window[name]: page.evaluate(WATCH_TEXT,
# [element id, name])
WATCH_TEXT = """([id, name]) => {
  window[name] = [];
  const element = document.getElementById(id);
  new MutationObserver(() => window[name].push(element.textContent)).observe(
      element, {childList: true, characterData: true, subtree: true});
}"""
WATCH_OUTCOMES = ['request-outcome', '__outcomes']
# how many times the page asked for itself (hmi.js, after a handshake that never opened)
COUNT_ASKING = """() => {
  window.__asked = 0;
  const fetch = window.fetch;
  window.fetch = (...args) => { window.__asked += 1; return fetch(...args); };
}"""


def wait_for_outcome(page, words: str, timeout=REQUEST_TIMEOUT) -> None:
    """The page showed `words` as a request's outcome (it may show the next request at once:
    the robot can ask again in the next epoch, so every text it showed is recorded)."""
    deadline = time.monotonic() + timeout      # (wait_for_function would need eval, which
    while not page.evaluate('(w) => window.__outcomes.some(t => t.includes(w))', words):
        assert time.monotonic() < deadline, (   # the pages' Content-Security-Policy forbids)
            f'the page did not show {words!r}; it showed {page.evaluate("window.__outcomes")}')
        time.sleep(0.02)


MISSED = ('too late', 'closed: the robot moved on', 'no answer in time',
          'the accept reached the robot after it moved on')


def tap_the_next_request(page, listener, button: str, double: bool = False,
                         attempts: int = 3) -> tuple[str, int]:
    """Tap `button` as soon as the robot asks (one Playwright call: the click waits until the
    button is enabled, checked every animation frame) and wait for the request to close: (the
    outcome the page showed, the answers on hrc/human_response before the tap). A person's
    window is the epoch and the task manager's hold (1.6 s here); on a loaded machine a tap
    can miss it, and the page then says so (too late, no answer in time): then the robot's
    next request is tapped, at most `attempts` requests."""
    seen = []
    for _ in range(attempts):
        page.evaluate(WATCH_TEXT, WATCH_OUTCOMES)
        answers = len(listener.responses)
        shown = page.evaluate('window.__outcomes.length')
        target = page.locator(f'#{button}')
        (target.dblclick if double else target.click)(timeout=REQUEST_TIMEOUT * MS)
        deadline = time.monotonic() + 10
        while not (after := [t for t in page.evaluate('window.__outcomes')[shown:] if t]):
            assert time.monotonic() < deadline, 'the request did not close within 10 s'
            time.sleep(0.02)
        seen.append(after[0])
        if not any(words in after[0] for words in MISSED):
            return after[0], answers
    pytest.fail(f'{attempts} requests in a row closed before the tap reached the robot: {seen}')


def test_hrc_hmi_shots_saves_both_pages(browser, tmp_path):
    """hrc-hmi-shots' scripted cell (a request open), its pages at the phone's size (the
    others differ by the viewport only)."""
    from hrc_ros.ros.hmi import shots
    from hrc_ros.ros.hmi.browser import SIZES
    server, url = shots._serve_scene('request')
    try:
        page = browser.new_page()
        page.goto(url)
        expect(page.locator('#request')).to_have_text("Let's do task 74 together")
        expect(page.locator('#accept')).to_be_enabled()
        page.close()
        written = shots.shoot(browser, url, tmp_path, 'request', sizes=('phone',))
    finally:
        server.stop()
    expected = {f'{view}_request_phone.png': SIZES['phone'][0] for view in ('worker', 'operator')}
    assert sorted(p.name for p in written) == sorted(expected)
    for path in written:
        data = path.read_bytes()
        assert data[:8] == b'\x89PNG\r\n\x1a\n'
        assert int.from_bytes(data[16:20], 'big') == expected[path.name], path.name


def test_the_page_says_no_connection_until_the_cell_runs_then_connects(cell, pages):
    suite, listener, url = cell
    page = pages.new_page()
    page.goto(url)
    connection = page.locator('#connection')
    expect(connection).to_have_text('no connection to the cell')
    expect(page.locator('#action-label')).to_be_hidden()     # not "The robot is / no connection"
    expect(page.locator('#request')).to_have_text('')
    expect(page.locator('#accept')).to_be_disabled()
    suite.start('decision_node')
    expect(connection).to_have_text('connected', timeout=START_TIMEOUT * MS)
    expect(page.locator('#action')).not_to_have_text('no connection to the cell')
    expect(page.locator('#action-label')).to_have_text('The robot is')


def test_the_worker_declines_and_the_task_manager_keeps_the_task_open(cell, pages):
    suite, listener, url = cell
    page = pages.pages[0]
    states = len(listener.task_states)
    outcome, answers = tap_the_next_request(page, listener, 'decline', double=True)
    assert outcome == "Let's do task 1 together: declined: the robot carries on"
    listener.wait(lambda: len(listener.responses) > answers, 5, 'the answer on the graph')
    assert listener.responses[answers:] == [False]          # one answer for a double tap
    listener.wait(lambda: len(listener.task_states) > states, 5, 'the next task state')
    after = listener.task_states[-1]
    assert (after['tp'], after['tx'], after['ty']) == (1, 3, 0), after
    assert not suite.dead(), suite.logs()


def test_the_worker_accepts_and_the_task_manager_commits_the_task(cell, pages):
    suite, listener, url = cell
    page = pages.pages[0]
    second_tab = pages.new_page()
    second_tab.goto(url)
    second_tab.evaluate(WATCH_TEXT, WATCH_OUTCOMES)
    outcome, answers = tap_the_next_request(page, listener, 'accept')
    assert outcome == "Let's do task 1 together: accepted: we do task 1 together"
    listener.wait(lambda: any(s['ty'] == 3 for s in listener.task_states), 5,
                  'the task manager to commit the task (ty = 3)')
    listener.wait(lambda: len(listener.responses) > answers, 5, 'the answer on the graph')
    assert listener.responses[answers:] == [True]
    # the second tab saw the same request, and now its outcome, with nothing left to tap
    wait_for_outcome(second_tab, 'accepted: we do task 1 together')
    expect(second_tab.locator('#accept')).to_be_disabled()
    second_tab.close()


def test_the_operator_queues_a_task_and_it_enters_the_cell(cell, pages):
    suite, listener, url = cell
    page = pages.new_page()
    page.goto(url + 'operator')
    expect(page.locator('#connection')).to_have_text('connected')
    form = page.locator('#task-form')
    result = page.locator('#task-result')
    for typed, shown in (('9', '9'), ('abc', "'abc'"), ('', 'nothing')):
        form.get_by_label('Priority').fill(typed)
        form.locator('button[type=submit]').click()
        expect(result).to_have_text(f'refused: priority must be a whole number from 1 to 2, '
                                    f'got {shown}')
    form.get_by_label('Priority').fill('2')
    form.get_by_label('Duration').fill('1')
    form.get_by_label('Who does it').select_option(label="the robot's job")
    form.locator('button[type=submit]').click()
    expect(result).to_have_text(re.compile(r'^accepted: queued, \d+ waiting$'))
    expect(result).to_have_attribute('data-status', 'accepted')
    listener.wait(lambda: any((s['tp'], s['tc'], s['tx']) == (2, 1, 0)
                              for s in listener.task_states), 20,
                  'the ordered task (2, 1, 0) in hrc/task_state')
    expect(page.locator('#history')).to_contain_text("priority 2, 1 step, the robot's job")
    timeline = page.locator('#timeline')
    listener.wait(lambda: int(timeline.get_attribute('data-epochs')) >= 3, 10,
                  'the timeline to have the epochs')
    expect(timeline.locator('canvas')).to_have_count(3)
    assert timeline.get_attribute('data-robot') == '0'           # no arm in this cell
    expect(page.locator('[data-kpi=idle_share] dd')).to_have_text('no arm')
    page.close()


def test_the_page_recovers_when_the_hmi_restarts(cell, pages):
    suite, listener, url = cell
    page = pages.pages[0]
    expect(page.locator('#connection')).to_have_text('connected')
    process = suite.processes.pop('hmi_node')
    os.killpg(process.pid, signal.SIGINT)
    assert process.wait(10) == 0
    expect(page.locator('#connection')).to_have_text('no connection to the cell')
    expect(page.locator('#accept')).to_be_disabled()
    # started again with tokens this page does not carry: it says its access is refused,
    # where it said "no connection" for as long as anyone waited
    tokens = ['-p', 'worker_token:=worker-token-000000000', '-p',
              'operator_token:=operator-token-00000000']
    params = [arg for path in suite.params for arg in ('--params-file', path)]
    suite.start('hmi_node', ros_args=params + tokens)
    expect(page.locator('#connection')).to_have_text(re.compile('^access refused: open this '),
                                                     timeout=START_TIMEOUT * MS)
    expect(page.locator('#accept')).to_be_disabled()
    # ... and keeps saying so through its retries (each asks for the page itself), where it
    # said "no connection" for a moment at every retry
    page.evaluate(WATCH_TEXT, ['connection', '__connection'])
    page.evaluate(COUNT_ASKING)
    deadline = time.monotonic() + REQUEST_TIMEOUT
    while page.evaluate('window.__asked') < 2:
        assert time.monotonic() < deadline, 'the page did not try again'
        time.sleep(0.05)
    assert page.evaluate('window.__connection') == [], page.evaluate('window.__connection')
    process = suite.processes.pop('hmi_node')
    os.killpg(process.pid, signal.SIGINT)
    assert process.wait(10) == 0
    suite.start('hmi_node')                       # without tokens: the page connects by itself
    expect(page.locator('#connection')).to_have_text('connected', timeout=START_TIMEOUT * MS)
