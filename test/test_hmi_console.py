"""The operator's console in a real browser: headless Chromium (Debian's, driven by Playwright)
against `hmi_node` and the cell with the arm as processes (the suite's nodes, `cobot_sim_node`
and `robot_bridge_node`, real DDS), with the worker's and the operator's tokens set.

First, without ROS, the scripted cell of `hrc-hmi-shots` (eleven minutes of a shift) in each
of its states: the accessibility checks in the browser (every text's WCAG AA contrast on both
pages, the accessible names of Accept and Decline, the connection announced, a focus ring of
3 px or more that contrasts with the page and with both buttons).

Then, on one running cell, in order:

1. the console fills as the cell runs: the timeline has the epochs and the arm's samples, the
   figures have values;
2. a person's body at the arm (this test publishes it, as a second body tracker would): the
   bridge stops the arm, and the stop is in the event log with the bridge's reason and on the
   timeline; the log downloads as CSV with it;
3. the worker's token opens the worker's page only: no link to the console, 403 on /operator,
   and an order sent from the worker's page is refused (403);
4. the figures on the page are the core's computation on the recorded run: this test records
   every message the HMI reads (with its source timestamp), and once the cell has stopped the
   same `HmiMachine`, fed the recording through the node's own input path
   (`hmi_node.HmiInputs.replay`), gives the page's figures at the page's time.

Waits are on conditions with bounded timeouts, never fixed sleeps.
"""

from __future__ import annotations

import os
import re
import signal
import time

import pytest
from geometry_msgs.msg import PoseArray
from playwright.sync_api import expect
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from a11y import CONTRAST, FOCUS, contrast
from hrc_ros.core.cell.tracking import K4ABT_JOINTS
from hrc_ros.core.config import load_config
from hrc_ros.core.hmi import HmiMachine
from hrc_ros.core.hmi.shift import DECIMALS
from hrc_ros.core.model import HRCModel
from hrc_ros.core.paths import arm_config_path
from hrc_ros.ros import conversions as conv
from hrc_ros.ros import qos
from hrc_ros.ros.hmi import shots
from hrc_ros.ros.launch_plan import ROBOT_OVERRIDES
from hrc_ros.ros.nodes.hmi_node import HmiInputs
from hrc_ros.ros.processes import NodeProcesses
from spun import SpunNode
from test_hmi_browser import logged_port, serving

START_TIMEOUT = 60.0      # seconds for the processes to start (a loaded machine)
BODY_S = 2.5              # seconds the body at the arm stays (the stop, and d = 0 epochs)
MS = 1000
WORKER = 'worker-token-for-the-tablet-1'
OPERATOR = 'operator-token-for-the-console'
CELL = ('hmi', 'task_manager', 'belief_estimator', 'cell_sim', 'cobot_sim', 'robot_bridge')
PARAMS = {
    '/**': {'ros__parameters': {'config': str(arm_config_path())}},
    '/**/decision': {'ros__parameters': {'epoch_period': 1.0, 'input_timeout': 0.8,
                                         'min_epoch_subscribers': 3}},
    '/**/task_manager': {'ros__parameters': {
        'initial_task': [1, 1, 0],
        'schedule': [f'{k}:{tp},1,{tx}' for k, tp, tx in
                     ((3, 2, 3), (5, 1, 0), (8, 2, 2), (11, 1, 3), (14, 2, 0), (17, 1, 2),
                      (20, 2, 3), (23, 1, 0), (26, 2, 2))]}},
    # nobody answers the robot's requests (the worker's page could; this test does not):
    # each is refused, taken as declined when the task manager's hold is over
    '/**/cell_sim': {'ros__parameters': {'seed': 3, 'initial_emotions': [1, 0],
                                         'initial_distance': 2, 'answer_requests': False}},
}
DEEP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10000,
                  reliability=ReliabilityPolicy.RELIABLE)


def params_file(folder, port) -> str:
    import yaml
    params = {key: {'ros__parameters': dict(value['ros__parameters'])}
              for key, value in PARAMS.items()}
    for name, values in ROBOT_OVERRIDES.items():
        params.setdefault(f'/**/{name}', {'ros__parameters': {}})['ros__parameters'].update(
            values)
    params['/**/hmi'] = {'ros__parameters': {'port': port,
                                             'worker_token': WORKER,
                                             'operator_token': OPERATOR}}
    path = folder / 'params.yaml'
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    return str(path)


class Recorder(SpunNode):
    """Every message the HMI reads, as (source timestamp, input name, message), and a
    publisher of a person's body at the arm."""

    def __init__(self, reads: HmiInputs):
        super().__init__('hmi_console_recorder')
        self.records: list[tuple] = []
        for name, (msg_type, topic) in reads.topics.items():
            profile = DEEP
            if name in ('separation', 'speed_override'):
                profile = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10000,
                                     reliability=ReliabilityPolicy.BEST_EFFORT)
            elif name == 'protective_stop':
                profile = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                     reliability=ReliabilityPolicy.RELIABLE,
                                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.node.create_subscription(msg_type, topic, self._record(name), profile)
        self.skeleton = self.node.create_publisher(PoseArray, 'human/skeleton', qos.SENSOR_DATA)
        self.start()

    def _record(self, name):
        def on_message(msg, info):
            published = info.get('source_timestamp') if isinstance(info, dict) else None
            self.records.append((int(published or time.time_ns()), name, msg))
        return on_message

    def nodes_up(self, names) -> bool:
        return set(names) <= set(self.node.get_node_names())


@pytest.fixture(scope='module')
def cell(tmp_path_factory, ros_domain_id):
    """The HMI, then the cell with the arm (all but the decision node), the recorder and the
    HMI's URL; the decision node starts when the HMI and the recorder hear the rest, so the
    shift (its first epoch) begins with both hearing everything. Always stopped at the end."""
    folder = tmp_path_factory.mktemp('hmi_console')
    suite = NodeProcesses(folder, [params_file(folder, 0)])     # port 0: the OS chooses
    model = HRCModel(load_config(arm_config_path()))
    reads = HmiInputs(model.rho, model.sigma)
    recorder = Recorder(reads)
    try:
        for node in CELL:
            suite.start(f'{node}_node')
        recorder.wait(lambda: (recorder.nodes_up(CELL) and serving(logged_port(suite)))
                      or suite.dead(), 'the nodes to start', START_TIMEOUT)
        assert not suite.dead(), suite.logs()
        recorder.wait(lambda: any(name == 'separation' for _, name, _ in recorder.records),
                      'the arm to publish', START_TIMEOUT)
        suite.start('decision_node')
        yield suite, recorder, reads, model, f'http://127.0.0.1:{logged_port(suite)}/'
    finally:
        suite.stop(10.0)
        recorder.close()


@pytest.fixture(scope='module')
def console(browser, cell):
    """The operator's console, opened with the operator's token (one browser context)."""
    context = browser.new_context(viewport={'width': 1440, 'height': 900},
                                  accept_downloads=True)
    context.set_default_timeout(START_TIMEOUT * MS)
    page = context.new_page()
    page.goto(cell[-1] + f'operator?token={OPERATOR}')
    yield page
    context.close()


def stop_node(suite, name: str) -> None:
    process = suite.processes.pop(f'{name}_node')
    os.killpg(process.pid, signal.SIGINT)
    assert process.wait(15) == 0, suite.log(f'{name}_node')


def number(page, selector: str, attribute: str) -> int:
    return int(page.locator(selector).get_attribute(attribute) or 0)


# -- accessibility, on the scripted cell -------------------------------------------------------
@pytest.fixture(scope='module')
def scenes():
    served = {scene: shots._serve_scene(scene) for scene in shots.SCENES}
    yield {scene: url for scene, (_, url) in served.items()}
    for server, _ in served.values():
        server.stop()


def check_contrast(page, what: str) -> int:
    result = page.evaluate(CONTRAST)
    assert not result['failures'], f'{what}: ' + '; '.join(result['failures'])
    return result['checked']


def test_every_text_passes_wcag_aa_contrast_on_both_pages(browser, scenes):
    context = browser.new_context(viewport={'width': 1280, 'height': 800})
    page = context.new_page()
    checked = 0
    for scene, url in scenes.items():        # the distance bands of every level, both pages
        for path in ('', 'operator'):
            page.goto(url + path)
            expect(page.locator('#connection')).to_have_text('connected')
            expect(page.locator('#distance-band')).to_have_attribute(
                'data-level', str(shots.SCENES[scene]))
            if path:
                expect(page.locator('#timeline canvas').first).to_be_visible()
                expect(page.locator('#events li').first).to_be_visible()
            checked += check_contrast(page, f'{path or "worker"} page, {scene}')
    page.goto(scenes['request'])             # an answered request: the chosen button
    page.locator('#accept').click()
    checked += check_contrast(page, 'worker page, a refused tap')
    context.close()
    server, url = shots._serve_scene('request')     # its server stops: no connection
    pages = [browser.new_page() for _ in range(2)]
    for page, path in zip(pages, ('', 'operator')):
        page.goto(url + path)
        expect(page.locator('#connection')).to_have_text('connected')
    server.stop()
    for page, path in zip(pages, ('', 'operator')):
        expect(page.locator('#connection')).to_have_text('no connection to the cell')
        checked += check_contrast(page, f'{path or "worker"} page, no connection')
        page.close()
    assert checked > 300


def test_accept_and_decline_say_what_they_answer_and_the_connection_is_announced(
        browser, scenes):
    page = browser.new_page(viewport={'width': 390, 'height': 844})
    page.goto(scenes['request'])
    expect(page.get_by_role('button', name="Accept: Let's do task 74 together")).to_be_enabled()
    expect(page.get_by_role('button', name="Decline: Let's do task 74 together")).to_be_enabled()
    status = page.get_by_role('status')
    expect(status).to_have_text('connected')
    expect(status).to_have_attribute('aria-live', 'polite')
    expect(page.locator('a[href="/operator"]')).to_have_count(0)
    page.goto(scenes['stopped'])
    expect(page.get_by_role('button', name='Accept (no request open)')).to_be_disabled()
    page.close()


def test_focus_is_a_ring_of_3_px_that_contrasts_with_the_page_and_both_buttons(
        browser, scenes):
    page = browser.new_page(viewport={'width': 1280, 'height': 800})
    page.goto(scenes['request'])
    expect(page.locator('#accept')).to_be_enabled()
    rings = {}
    for button in ('accept', 'decline'):
        page.keyboard.press('Tab')
        ring = page.evaluate(FOCUS)
        assert ring['id'] == button and ring['focusVisible'], ring
        rings[button] = ring
    green, red = rings['accept']['background'], rings['decline']['background']
    for ring in rings.values():
        assert ring['outlineStyle'] == 'solid' and ring['outlineWidth'] >= 3, ring
        assert contrast(ring['outlineColor'], ring['page']) >= 3, ring
        assert ring['ringWidth'] >= 3, ring             # inside the outline, on the button
        assert contrast(ring['ringColor'], ring['background']) >= 3, ring
        assert contrast(ring['ringColor'], ring['outlineColor']) >= 3, ring
    assert contrast(rings['accept']['ringColor'], red) >= 3     # and against the other one
    assert contrast(rings['decline']['ringColor'], green) >= 3
    page.goto(scenes['request'] + 'operator')        # the console's controls too
    for _ in range(4):
        page.keyboard.press('Tab')
        ring = page.evaluate(FOCUS)
        assert ring['focusVisible'] and ring['outlineWidth'] >= 3, ring
        assert contrast(ring['outlineColor'], ring['page']) >= 3, ring
    page.close()


# -- the console on a running cell -------------------------------------------------------------
def test_the_console_fills_as_the_cell_runs(cell, console):
    suite, recorder, reads, model, url = cell
    page = console
    expect(page.locator('#connection')).to_have_text('connected', timeout=START_TIMEOUT * MS)
    recorder.wait(lambda: number(page, '#timeline', 'data-epochs') >= 3
                  and number(page, '#timeline', 'data-robot') >= 4, 'the timeline to fill', 30)
    expect(page.locator('#timeline canvas')).to_have_count(3)
    expect(page.locator('#action-legend li')).to_have_count(8)
    expect(page.locator('[data-kpi=tasks_per_hour]')).not_to_have_attribute('data-value', '')
    expect(page.locator('[data-kpi=min_separation] dd')).to_have_text(re.compile(r'^-?\d\.\d\d m'))
    expect(page.locator('#robot')).to_contain_text('from the arm')
    assert not suite.dead(), suite.logs()


def test_a_protective_stop_is_in_the_log_with_its_reason_and_on_the_timeline(cell, console):
    suite, recorder, reads, model, url = cell
    page = console
    logged = page.locator('#events li[data-kind="protective stop"]',
                          has_text='below the protective distance')
    before = logged.count()                                   # the 3D person's, if any
    start, frame = time.monotonic(), 0
    while logged.count() <= before or time.monotonic() < start + BODY_S:
        assert time.monotonic() < start + 20, 'no protective stop in the log'
        frame += 1                  # a body at the arm's base, breathing (a tracker's noise:
        wobble = 0.002 * (frame % 5)        # the bridge takes a still skeleton for a frozen one)
        recorder.skeleton.publish(conv.keypoints_to_msg(
            [[0.05 + wobble, 0.0, 0.15]] * len(K4ABT_JOINTS),
            conv.seconds_to_stamp(time.time())))
        time.sleep(1 / 30)
    expect(logged.first).to_contain_text(re.compile(r'the arm (stopped|stays stopped) for '
                                                    r'safety: separation'))
    expect(logged.first.locator('time')).to_have_attribute('datetime', re.compile(r'^\d{4}-'))
    recorder.wait(lambda: number(page, '#timeline', 'data-stops') >= 1, 'the stop on the timeline')
    with page.expect_download() as download:
        page.locator('#events-csv').click()
    lines = open(download.value.path(), encoding='utf-8').read().splitlines()
    assert lines[0] == 'time,kind,what happened,detail'
    assert any(re.search(r',protective stop,the arm (stopped|stays stopped) for safety: '
                         r'separation', line) for line in lines[1:]), lines[:5]
    assert download.value.suggested_filename.startswith('cell-events-')


def test_the_workers_token_opens_the_workers_page_only_and_cannot_queue(browser, cell):
    suite, recorder, reads, model, url = cell
    context = browser.new_context()
    page = context.new_page()
    page.goto(url + f'?token={WORKER}')
    assert page.url == url                             # the token left the address bar
    expect(page.locator('#connection')).to_have_text('connected')
    expect(page.locator('a[href="/operator"]')).to_have_count(0)
    refused = page.goto(url + 'operator')
    assert refused.status == 403
    assert "needs the operator's access token" in page.content()
    page.goto(url)
    # an order crafted on the worker's tablet, on its own WebSocket: refused
    reply = page.evaluate("""() => new Promise((resolve) => {
      const ws = new WebSocket(`ws://${location.host}/ws?view=worker`);
      ws.onopen = () => ws.send(JSON.stringify({type: 'order', ref: 1, priority: 1,
                                                duration: 1, nature: 0}));
      ws.onmessage = (e) => { const m = JSON.parse(e.data);
                              if (m.type === 'order_result') { ws.close(); resolve(m); } };
      setTimeout(() => resolve(null), 10000);
    })""")
    assert reply is not None and reply['code'] == 403 and reply['status'] == 'refused'
    opened = page.evaluate("""() => new Promise((resolve) => {
      const ws = new WebSocket(`ws://${location.host}/ws?view=operator`);
      ws.onopen = () => { ws.close(); resolve('open'); };
      ws.onerror = () => resolve('refused');
    })""")
    assert opened == 'refused'
    context.close()


def quiet(recorder, seconds: float = 0.6) -> bool:
    """No message of the cell recorded for `seconds` (the nodes still running publish their
    health on /diagnostics every second: not the cell's)."""
    def count():
        return sum(name != 'diagnostics' for _, name, _ in recorder.records)
    before = count()
    time.sleep(seconds)
    return count() == before


def test_the_figures_are_the_cores_computation_on_the_recorded_run(cell, console):
    suite, recorder, reads, model, url = cell
    page = console
    recorder.wait(lambda: sum(name == 'epoch' for _, name, _ in recorder.records) >= EPOCHS,
                  f'{EPOCHS} epochs', 2 * EPOCHS + 30)
    for name in ('decision', 'robot_bridge', 'cobot_sim', 'cell_sim'):     # the cell stops
        stop_node(suite, name)
    recorder.wait(lambda: quiet(recorder), 'the recording to end', 20)
    # the page's figures once the arm's hold is over (its measured time no longer grows)
    before, deadline = page.evaluate(SNAPSHOT), time.monotonic() + 20
    while True:               # the figures are counted again every second
        time.sleep(1.1)
        shown = page.evaluate(SNAPSHOT)
        if shown['arm_seconds'] == before['arm_seconds'] and shown['as_of'] > before['as_of']:
            break
        assert time.monotonic() < deadline, ('the figures did not settle', before, shown)
        before = shown
    machine = HmiMachine(model.rho, model.sigma)
    reads.replay(machine, recorder.records)
    core = machine.shift.all_windows(shown['as_of'] * 1_000_000)
    counted = core[shown['window']]
    assert counted['since_ns'] // 1_000_000 == shown['since']
    assert counted['arm_seconds'] > 10 and counted['protective_stop_share'] > 0   # the body
    assert counted['fail_safe_epochs'] is not None   # the decision node's reports were read
    for name, value in shown['values'].items():
        expected = counted[name]
        if expected is not None and name in DECIMALS:
            expected = round(expected, DECIMALS[name])
        if name in ('idle_share', 'protective_stop_share'):
            # the node counts messages in the order they reach it, the replay in publication
            # order: a stop edge overtaken by a separation sample of another process moves a
            # few ms of arm time (a tenth of a per cent shows it only at a rounding edge)
            assert abs(value - expected) <= 0.15, (name, value, expected)
        else:
            assert value == expected, (name, value, expected)


EPOCHS = 12               # the run's length before it stops (the first tests take some of it)
SNAPSHOT = """() => {
  const box = document.getElementById('figures');
  const values = {};
  for (const e of box.querySelectorAll('[data-kpi]')) {
    values[e.dataset.kpi] = e.dataset.value === '' ? null : Number(e.dataset.value);
  }
  return {window: box.dataset.window, as_of: Number(box.dataset.asOf),
          since: Number(box.dataset.since), arm_seconds: Number(box.dataset.armSeconds),
          values};
}"""
