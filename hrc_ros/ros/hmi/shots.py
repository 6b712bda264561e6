"""hrc-hmi-shots: screenshots of the HMI's pages at phone, tablet and desktop sizes.

    hrc-hmi-shots [--out out/hmi_shots] [--chromium /usr/bin/chromium]
    hrc-hmi-shots --url http://127.0.0.1:8080/ [--token TOKEN]

Without --url it serves the pages itself, on a free loopback port, from a scripted cell: the
HMI's own machine (`core.hmi.HmiMachine`) fed with the messages of a few epochs (a joint task
with the robot asking for it, a belief, a decision report, two orders, a collision stop), so
each picture shows a state a person meets; no ROS is needed. With --url it takes the pages of a
running HMI as they are. The pictures are PNG files named `<page>_<state>_<size>.png`; the
browser is Debian's Chromium driven by Playwright (`ros.hmi.browser`).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ...core.hmi import AccessPolicy, HmiMachine
from ...core.model import DN, RH2, TASK_VARIABLES
from ...tools.common import Parser, fail, output_folder
from .browser import SIZES, BrowserError, launch
from .server import HmiServer, ServerSettings

S = 1_000_000_000


def _task(*values) -> dict:
    return dict(zip(TASK_VARIABLES, values))


def scripted_cell(scene: str, now: int) -> HmiMachine:
    """A machine in the state `scene` ('request' or 'stopped') at clock `now`."""
    machine = HmiMachine(2, 2, instance='demo')
    t = now - 6 * S
    states = [_task(1, 1, 0, 2, 0, 0, 1, 1), _task(0, 0, 0, 0, 0, 0, 0, 0),
              _task(2, 2, 3, 0, 0, 0, 0, 0), _task(2, 2, 3, 0, 0, 0, 0, 0)]
    for k, state in enumerate(states, start=1):
        t += S
        machine.epoch_signal(k, t, t)
        machine.task_state_message(state, t + 1000, t)
        machine.action_message(0 if k == 1 else 4 if k == 2 else 6, t + 2000, t)
        machine.decision_report(k, 'nw', 'none', 'OK')
    t += S
    machine.epoch_signal(5, t, t)
    machine.task_state_message(states[-1], t + 1000, t)
    machine.belief_message([0.02, 0.01, 0.0, 0.30, 0.12, 0.02, 0.40, 0.10, 0.03])
    machine.task_manager_report({'queued_tasks': '1', 'next_queued': '[1, 1, 0]',
                                 'completed_tasks': '1', 'waiting_for': 'none'})
    machine.speed_override_message(0.35, now)
    machine.separation_message(0.82, now)
    for fields, accepted in (({'priority': 1, 'duration': 1, 'nature': 0}, True),
                             ({'priority': 2, 'duration': 2, 'nature': 1}, False)):
        step = machine.order(fields, 'operator', now, listening=True)
        machine.order_sent(step.order, 10, 20)
        machine.task_request_result({'accepted': accepted, 'task': step.publish,
                                     'published_ns': 15, 'queued': 1,
                                     'reason': 'the queue is full (1 task waiting, max_queue '
                                     '1)'})
    if scene == 'request':
        machine.distance_message(1)
        machine.decision_report(5, 'rh2', 'none', 'OK')
        machine.action_message(RH2, t + 2000, t)
    else:
        machine.distance_message(0)
        machine.decision_report(5, 'dn', 'd = 0: the human is inside the collision circle',
                                'WARN')
        machine.action_message(DN, t + 2000, t)
    return machine


def _serve_scene(scene: str) -> tuple[HmiServer, str]:
    server = HmiServer(ServerSettings(port=0), AccessPolicy('127.0.0.1'), lambda c: True)
    port = server.start()
    now = time.monotonic_ns()
    machine = scripted_cell(scene, now)
    server.publish_views({'worker': _json(machine.worker_view(now)),
                          'operator': _json(machine.operator_view(now))})
    return server, f'http://127.0.0.1:{port}/'


def _json(view: dict) -> str:
    import json
    return json.dumps({'type': 'view', **view}, default=str)


def shoot(browser, url: str, out: Path, state: str, token: str = '',
          sizes=tuple(SIZES)) -> list[Path]:
    """The worker and operator pages at each of `sizes` (SIZES' names); the files written."""
    written = []
    for page_name, path in (('worker', ''), ('operator', 'operator')):
        for size in sizes:
            width, height = SIZES[size]
            context = browser.new_context(viewport={'width': width, 'height': height},
                                          device_scale_factor=1)
            page = context.new_page()
            query = f'?token={token}' if token else ''
            page.goto(url.rstrip('/') + '/' + path + query)
            page.wait_for_function(
                "document.getElementById('connection').dataset.state !== 'disconnected'",
                timeout=10_000)
            page.wait_for_timeout(300)          # the view is rendered after it arrives
            target = out / f'{page_name}_{state}_{size}.png'
            page.screenshot(path=str(target), full_page=True)
            written.append(target)
            context.close()
    return written


def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog='hrc-hmi-shots', description=__doc__.split('\n')[0])
    parser.add_argument('--out', default='out/hmi_shots', help='folder for the PNG files')
    parser.add_argument('--url', default='', help='a running HMI (default: a scripted cell '
                        'served here)')
    parser.add_argument('--token', default='', help="the running HMI's access token")
    parser.add_argument('--chromium', default=None, help='the Chromium executable (default '
                        '/usr/bin/chromium)')
    args = parser.parse_args(argv)
    try:
        out = output_folder(Path(args.out))
        from playwright.sync_api import sync_playwright
    except ImportError:
        return fail('hrc-hmi-shots', 'playwright is not installed: pip install playwright')
    except Exception as exc:  # noqa: BLE001 - a bad output folder, said in one line
        return fail('hrc-hmi-shots', exc)
    written = []
    try:
        with sync_playwright() as playwright:
            browser = launch(playwright, args.chromium)
            try:
                if args.url:
                    written += shoot(browser, args.url, out, 'live', args.token)
                else:
                    for scene in ('request', 'stopped'):
                        server, url = _serve_scene(scene)
                        try:
                            written += shoot(browser, url, out, scene)
                        finally:
                            server.stop()
            finally:
                browser.close()
    except BrowserError as exc:
        return fail('hrc-hmi-shots', exc)
    for path in written:
        print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
