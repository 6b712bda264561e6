"""hrc-hmi-shots: screenshots of the HMI's pages at phone, tablet and desktop sizes.

    hrc-hmi-shots [--out out/hmi_shots] [--scene request] [--colours 128]
                  [--chromium /usr/bin/chromium]
    hrc-hmi-shots --url http://127.0.0.1:8080/ [--token OPERATOR_TOKEN]

Without --url it serves the pages itself, on a free loopback port, from a scripted cell: the
HMI's own machine (`core.hmi.HmiMachine`) fed with the messages of an eleven-minute shift (a
stream of tasks through the task manager's rules, the robot asking for joint work and the
worker declining now and then, the arm with its separation and protective stops, a fail-safe,
a refused order, a policy swap) and then a joint task with the robot asking for it, or a
collision stop, so each picture shows a state a person meets, with the console's figures,
timeline and event log filled; no ROS is needed. With --url it takes the pages of a
running HMI as they are. The pictures are PNG files named `<page>_<state>_<size>.png`; the
browser is Debian's Chromium driven by Playwright (`ros.hmi.browser`).
"""

from __future__ import annotations

import json
import os
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import numpy as np

from ...core.hmi import AccessPolicy, HmiMachine
from ...core.quoting import cap
from ...core.model import ACTIONS, DN, RH2, TASK_VARIABLES
from ...tools.common import Parser, command, fail, output_folder, path_text
from .browser import SIZES, BrowserError, launch
from .server import HmiServer, ServerSettings

S = 1_000_000_000


def _task(*values) -> dict:
    return dict(zip(TASK_VARIABLES, values))


HISTORY_S = 11 * 60            # the scripted shift: eleven minutes of a cell at 1 s epochs
ARM_RATE = 10                  # Hz of its arm's separation samples
SCENES = {'request': 1, 'stopped': 0, 'working': 2, 'clear': 3}    # scene -> distance level


def _history(machine: HmiMachine, now: int, wall: int) -> tuple[int, int, int]:
    """Feed `machine` the scripted shift's epochs, ending 1 s before now: the task book of the
    default model runs a stream of tasks (`core.tasks.TaskBook`, the task manager's rules),
    the robot asks for joint work (declined every third time), the worker comes close now and
    then (a protective stop of the arm, once a fail-safe of the decision), an order is refused
    and the policy is swapped once. (epoch, monotonic, system) times of the last epoch."""
    from ...core.config import load_config
    from ...core.model import ACTION_INDEX, HRCModel, request_eligible
    from ...core.paths import default_config_path
    from ...core.tasks import TaskBook
    model = HRCModel(load_config(default_config_path()))
    stream = [(1, 2, 0), (2, 1, 3), (1, 2, 2), (2, 2, 0), (1, 1, 3), (2, 1, 1)]
    book = TaskBook(model, schedule=[(1 + 9 * i, stream[i % len(stream)])
                                     for i in range(HISTORY_S // 9)], max_queue=50)
    rng = np.random.default_rng(4)
    offset = now - wall                     # system -> monotonic
    t0 = wall - HISTORY_S * S
    asked = 0
    stopped = False
    for k in range(1, HISTORY_S):
        t = t0 + k * S
        book.begin_epoch(k)
        x = book.state
        phase = 2 * np.pi * k / 97
        near = k % 160 in range(60, 68)            # the worker steps close
        d = 0 if k % 160 == 64 else 1 if near else 2 + (k % 37 > 30)
        tp, tx, ty = int(x['tp']), int(x['tx']), int(x['ty'])
        if d == 0:
            action = ACTION_INDEX['dn']
        elif tp and ty == 0 and tx in (0, 2):
            action = ACTION_INDEX['ct']
        elif tp and request_eligible(ACTION_INDEX['rh2'], tp, tx, ty):
            action = ACTION_INDEX['rh2']
        elif tp and request_eligible(ACTION_INDEX['rh1'], tp, tx, ty):
            action = ACTION_INDEX['rh1']
        elif near:
            action = ACTION_INDEX['dp']
        elif k % 45 == 0:
            action = ACTION_INDEX['mh']
        else:
            action = ACTION_INDEX['nw']
        belief = np.outer([0.2 + 0.15 * np.sin(phase), 0.5, 0.3 - 0.15 * np.sin(phase)],
                          [0.6 - 0.3 * near, 0.3, 0.1 + 0.3 * near]).reshape(-1)
        machine.belief_message(belief / belief.sum())
        machine.distance_message(d)
        machine.epoch_signal(k, t, t + offset)
        machine.task_state_message(x, t + 1000, t + offset)
        machine.action_message(action, t + 2000, t + offset)
        faults = 'd = 0: the human is inside the collision circle' if d == 0 else 'none'
        machine.decision_report(k, ACTIONS[action], faults, 'WARN' if d == 0 else 'OK', t + 3000)
        accepted = None
        if request_eligible(action, tp, tx, ty):
            asked += 1
            accepted = asked % 3 != 0
            machine.response_message(accepted, t + 500_000_000, t + offset)
        if k == 200:
            machine.policy_report('OK', 'now deciding with policy policies/night-2.npz', {
                'epoch': k, 'policy_file': 'policies/night-2.npz',
                'previous_policy_file': 'policies/default.npz'}, t + 4000)
        if k == 420:
            machine.task_request_result({'accepted': False, 'task': (2, 2, 3),
                                         'published_ns': t, 'reason': 'task (2, 2, 3) '
                                         'refused: the queue is full (5 tasks waiting, '
                                         'max_queue 5)'}, t + 5000)
        for i in range(ARM_RATE):                       # the arm over the epoch
            ts = t + i * S // ARM_RATE
            separation = 0.35 + 0.1 * i / ARM_RATE if near else \
                1.1 + 0.3 * np.sin(phase + i / 7) + 0.02 * rng.standard_normal()
            protective = 0.45 if near else 0.6
            stop = separation < protective
            if stop != stopped:
                stopped = stop
                machine.protective_stop_message(stop, ts)
                if stop:
                    machine.stop_report(True, f'separation {separation:.3f} m below the '
                                        f'protective distance {protective:.3f} m at the '
                                        'slowest motion (0.05 m/s)', ts + 1000)
            override = 0.0 if stop else 0.4 if near else 0.8 + 0.2 * np.sin(phase / 2)
            speed = 0.0 if action in (ACTION_INDEX['dn'], ACTION_INDEX['mh']) else \
                0.5 * override
            machine.separation_message(separation, protective, speed, ts, ts + offset)
            machine.speed_override_message(override, ts + offset)
        robot_runs = action != ACTION_INDEX['dn']
        book.apply(action, accepted, robot_runs)
    return HISTORY_S - 1, t0 + (HISTORY_S - 1) * S + offset, t0 + (HISTORY_S - 1) * S


def scripted_cell(scene: str, now: int, wall: int | None = None) -> HmiMachine:
    """A machine in the state `scene` (a key of SCENES) at clock `now` (monotonic) and `wall`
    (system clock), after eleven minutes of a scripted shift."""
    wall = time.time_ns() if wall is None else wall
    machine = HmiMachine(2, 2, instance='demo', start_ns=wall - (HISTORY_S + 60) * S)
    k, t, t_wall = _history(machine, now - S, wall - S)
    joint = _task(2, 2, 3, 0, 0, 0, 0, 0)
    k, t, t_wall = k + 1, now, wall
    machine.epoch_signal(k, t_wall, t)
    machine.task_state_message(joint, t_wall + 1000, t)
    machine.task_manager_report({'queued_tasks': '1', 'next_queued': '[1, 1, 0]',
                                 'completed_tasks': str(sum(1 for x in machine.tasks
                                                            if x.done_epoch)),
                                 'waiting_for': 'none'})
    for fields, accepted in (({'priority': 1, 'duration': 1, 'nature': 0}, True),
                             ({'priority': 2, 'duration': 2, 'nature': 1}, False)):
        step = machine.order(fields, 'operator', now, listening=True)
        machine.order_sent(step.order, 10, 20)
        machine.task_request_result({'accepted': accepted, 'task': step.publish,
                                     'published_ns': 15, 'queued': 1,
                                     'reason': 'task (2, 2, 1) refused: the queue is full '
                                     '(1 tasks waiting, max_queue 1)'}, wall)
    d = SCENES[scene]
    machine.distance_message(d)
    if scene == 'request':
        machine.decision_report(k, 'rh2', 'none', 'OK', t_wall + 3000)
        machine.action_message(RH2, t_wall + 2000, t)
    elif scene == 'stopped':
        machine.decision_report(k, 'dn', 'd = 0: the human is inside the collision circle',
                                'WARN', t_wall + 3000)
        machine.action_message(DN, t_wall + 2000, t)
    else:
        machine.decision_report(k, 'nw', 'none', 'OK', t_wall + 3000)
        machine.action_message(0, t_wall + 2000, t)
    return machine


def _serve_scene(scene: str) -> tuple[HmiServer, str]:
    server = HmiServer(ServerSettings(port=0), AccessPolicy('127.0.0.1'), lambda c: True)
    port = server.start()
    now, wall = time.monotonic_ns(), time.time_ns()
    machine = scripted_cell(scene, now, wall)
    server.publish_views({'worker': _json(machine.worker_view(now)),
                          'operator': _json(machine.operator_view(now, wall))})
    server.append_feeds({'timeline': [json.dumps(machine.timeline.snapshot())],
                         'events': [json.dumps(e) for e in machine.events.entries]})
    return server, f'http://127.0.0.1:{port}/'


def _json(view: dict) -> str:
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
            # waits on selectors: wait_for_function polls with eval, which the pages'
            # Content-Security-Policy forbids
            page.locator('#connection:not([data-state="disconnected"])').wait_for(
                timeout=30_000)
            if path:                            # the console: its charts once it has data
                page.locator('#timeline canvas, #timeline[data-epochs="0"]').first.wait_for(
                    timeout=30_000)
            page.wait_for_timeout(300)          # the view is rendered after it arrives
            target = out / f'{page_name}_{state}_{size}.png'
            page.screenshot(path=str(target), full_page=True)
            written.append(target)
            context.close()
    return written


REACH_TIMEOUT_SEC = 5.0


def check_reachable(url: str) -> None:
    """ValueError in one line when `url` is not an http(s) address or nothing answers there
    (an HTTP error status is an answer: the HMI may ask for its token)."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ('http', 'https') or not parts.hostname:
        raise ValueError(f'--url {cap(url, 200)}: not an http(s) address, e.g. '
                         'http://127.0.0.1:8080/')
    try:
        with urllib.request.urlopen(url, timeout=REACH_TIMEOUT_SEC):
            pass
    except urllib.error.HTTPError:
        pass
    except (urllib.error.URLError, OSError, ValueError) as exc:
        reason = getattr(exc, 'reason', exc)
        raise ValueError(f'cannot reach {cap(url, 200)}: {reason}; is the HMI running '
                         '(hmi_node, or hrc-case-study --hmi)?') from None


@command('hrc-hmi-shots')
def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog='hrc-hmi-shots', description=__doc__.split('\n')[0])
    parser.add_argument('--out', default='out/hmi_shots', type=path_text,
                        help='folder for the PNG files')
    parser.add_argument('--url', default='', help='a running HMI (default: a scripted cell '
                        'served here)')
    parser.add_argument('--token', default=os.environ.get('HRC_HMI_OPERATOR_TOKEN', ''),
                        help="the running HMI's operator's access token (it opens both pages; "
                        'default: $HRC_HMI_OPERATOR_TOKEN, which unlike the option does not show '
                        'in the process list)')
    parser.add_argument('--scene', action='append', choices=tuple(SCENES),
                        help='the scripted cell\'s states to take (default: request and '
                        'stopped)')
    parser.add_argument('--colours', type=int, default=0, help='reduce each picture to this '
                        'many colours (2..256; 0: as taken), e.g. 128 for a repository')
    parser.add_argument('--chromium', default=None, help='the Chromium executable (default '
                        '/usr/bin/chromium)')
    args = parser.parse_args(argv)
    if args.colours and not 2 <= args.colours <= 256:
        return fail('hrc-hmi-shots', f'--colours must lie in 2..256, got {args.colours}')
    try:
        if args.url:            # before the folder is made: an HMI that is not there is one line
            check_reachable(args.url)
        out = output_folder(Path(args.out))
        from playwright.sync_api import Error as PlaywrightError
        from playwright.sync_api import sync_playwright
    except ImportError:
        return fail('hrc-hmi-shots', 'playwright is not installed: pip install playwright')
    except Exception as exc:  # noqa: BLE001 - a bad output folder or URL, said in one line
        return fail('hrc-hmi-shots', exc)
    written = []
    try:
        with sync_playwright() as playwright:
            browser = launch(playwright, args.chromium)
            try:
                if args.url:
                    written += shoot(browser, args.url, out, 'live', args.token)
                else:
                    for scene in args.scene or ('request', 'stopped'):
                        server, url = _serve_scene(scene)
                        try:
                            written += shoot(browser, url, out, scene)
                        finally:
                            server.stop()
            finally:
                browser.close()
    except BrowserError as exc:
        return fail('hrc-hmi-shots', exc)
    except PlaywrightError as exc:      # the HMI went away, a page that never loaded
        return fail('hrc-hmi-shots', f'the browser failed: {str(exc).splitlines()[0]}')
    for path in written:
        if args.colours:
            reduce_colours(path, args.colours)
        print(f'wrote {path}')
    return 0


def reduce_colours(path: Path, colours: int) -> None:
    """The picture with at most `colours` colours (no dithering: flat areas stay flat), in
    place: a console's page falls from about 400 kB to 150 kB at 128."""
    from PIL import Image
    with Image.open(path) as image:
        reduced = image.convert('RGB').quantize(colors=colours, method=Image.Quantize.MEDIANCUT,
                                                dither=Image.Dither.NONE)
    reduced.save(path, optimize=True)


if __name__ == '__main__':
    sys.exit(main())
