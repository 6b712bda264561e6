"""The operator's console's three targets (issue 36): a topic message to the page, the node's
CPU with ten pages open, and the browser's memory over an hour of timeline.

    .venv/bin/python bench/console_bench.py                  # latency and CPU (~6 min)
    .venv/bin/python bench/console_bench.py --phase memory --memory-minutes 60   # the hour
    .venv/bin/python bench/console_bench.py --phase latency --samples 400

Phase `latency` (target p99 < 100 ms at 10 open pages): `hmi_node` as a process; this bench
plays the cell (it publishes `hrc/epoch`, an idle task state and an action each sample, a new
distance level every other one, and the arm's `hrc/separation` at 125 Hz and the speed
override all the while, as cobot_sim and the bridge would); ten console pages are open: two
in headless Chromium (Debian's, through Playwright), eight aiohttp clients speaking the page's
protocol. A sample's latency is from the bench's system clock just before `publish` to the
moment the page shows it: in Chromium a MutationObserver's time (`performance.timeOrigin +
performance.now()`, the same system clock) when `#action` (a control input, taken at once) or
`#distance` (a sampled input, read `refresh_rate` times a second) changes to the new text; for
the clients the arrival of the first view that carries it. Printed per input and page kind.

Phase `cpu` (target < 5% of one core at 10 pages and 1 s epochs): the cell with the arm as
processes (task manager, belief estimator, the simulated person walking in 3D, the decision
node at its 1 s epoch, cobot_sim and robot_bridge, as `hrc-case-study --robot sim` runs them,
with a task stream and nobody answering, so requests lapse), and `hmi_node`. First
`--baseline` s with no page, then the ten pages (two Chromium consoles, eight clients: six
consoles, two workers' pages) for `--soak` s; `hmi_node`'s CPU (utime + stime of
/proc/<pid>/stat) per `--sample` s window. Printed: the mean and the windows' max with no page
and with the pages, and the difference, the pages' own cost.

Phase `memory` (target: flat): the same cell and one Chromium console for `--memory-minutes`;
every `--memory-sample` s after a garbage collection (CDP `HeapProfiler.collectGarbage`) its
JS heap in use, DOM nodes and event listeners (CDP `Performance.getMetrics`) and the timeline's
points. The timeline fills for its first ten minutes, then holds ten minutes: printed are the
values at 10 minutes and at the end and the slope over everything after 10 minutes (a leak
grows linearly; a page that holds its window does not).

Each run uses a private DDS domain (HRC_BENCH_DOMAIN_ID, else random 100..199, localhost
discovery) and loopback ports chosen free. Run it under `nice -n 10` on a shared machine and
give the load (`uptime`) with its figures.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import shlex
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from private_domain import use_private_domain

if __name__ == '__main__':
    use_private_domain()

import yaml  # noqa: E402
from std_msgs.msg import Float64, Float64MultiArray, UInt8  # noqa: E402

from hmi_bench import (BenchNode, PlayedCell, cpu_seconds, cpu_windows, free_port,  # noqa: E402
                       wait)
from hrc_ros.core.model import TASK_VARIABLES  # noqa: E402
from hrc_ros.core.paths import arm_config_path  # noqa: E402
from hrc_ros.ros import conversions as conv  # noqa: E402
from hrc_ros.ros import qos  # noqa: E402
from hrc_ros.ros.hmi.server import FEEDS  # noqa: E402
from hrc_ros.ros.launch_plan import ROBOT_OVERRIDES  # noqa: E402
from hrc_ros.ros.processes import NodeProcesses  # noqa: E402

IDLE = dict.fromkeys(TASK_VARIABLES, 0)
# idle task, so each action reads the same whatever the task: the console's words for them
ACTIONS = {'nw': 'carrying on', 'dp': 'moving away to give the worker room',
           'dm': 'coming closer to work with the worker', 'mh': 'cheering the worker on'}
DISTANCES = {1: 'close to the robot', 2: 'middle distance', 3: 'at a safe distance'}
WATCH = """() => {
  window.__changes = [];
  for (const id of ['action', 'distance']) {
    new MutationObserver(() => window.__changes.push(
        [id, document.getElementById(id).textContent,
         performance.timeOrigin + performance.now()])).observe(
        document.getElementById(id), {childList: true, characterData: true, subtree: true});
  }
}"""


def percentiles(values) -> str:
    v = np.asarray(values)
    return (f'p50 {np.percentile(v, 50):.1f} ms, p90 {np.percentile(v, 90):.1f} ms, '
            f'p99 {np.percentile(v, 99):.1f} ms, max {v.max():.1f} ms (n = {v.size})')


# -- phase latency -----------------------------------------------------------------------------
class Client:
    """A console page over aiohttp: the arrival time of every view, with its action and
    distance texts (parsed only to find the texts; the clock is taken first)."""

    def __init__(self):
        self.seen: list[tuple[float, str, str]] = []

    async def run(self, session, url: str, stop: asyncio.Event, view: str = 'operator'):
        async with session.ws_connect(f'{url}ws?view={view}') as ws:
            while not stop.is_set():
                try:
                    message = await asyncio.wait_for(ws.receive(), 0.5)
                except asyncio.TimeoutError:
                    continue
                arrived = time.time()
                if message.type != 1:
                    return
                if message.data.startswith('{"type":"view"'):
                    data = json.loads(message.data)
                    self.seen.append((arrived, data.get('action'),
                                      (data.get('distance') or {}).get('text')))


def run_clients(url: str, count: int, done, results) -> None:
    """In a process of its own (the bench's publishing and Playwright would otherwise delay
    the clients' reading): `count` console clients until `done` is set; their views'
    arrivals."""
    import aiohttp

    async def main():
        stop = asyncio.Event()
        clients = [Client() for _ in range(count)]
        async with aiohttp.ClientSession() as session:
            tasks = [asyncio.ensure_future(c.run(session, url, stop)) for c in clients]
            while not all(c.seen for c in clients):
                await asyncio.sleep(0.05)
            results.put('ready')                 # every client has its first view
            while not done.is_set():
                await asyncio.sleep(0.1)
            stop.set()
            await asyncio.gather(*tasks, return_exceptions=True)
        return [c.seen for c in clients]

    results.put(asyncio.run(main()))


class ArmStream(threading.Thread):
    """hrc/separation at 125 Hz and the speed override, as the robot side publishes them."""

    def __init__(self, node, rate: float = 125.0):
        super().__init__(daemon=True)
        self.separation = node.create_publisher(Float64MultiArray, 'hrc/separation',
                                                qos.SENSOR_DATA)
        self.override = node.create_publisher(Float64, 'hrc/speed_override', qos.RELIABLE)
        self.period = 1.0 / rate
        self.running = True

    def run(self):
        k = 0
        next_at = time.monotonic()
        while self.running:
            k += 1
            s = 0.9 + 0.3 * np.sin(k / 200)
            self.separation.publish(conv.separation_to_msg(s, [0.3, 0, 0.5], [0.3 + s, 0, 0.5],
                                                           0.6, 0.2 + 0.1 * np.sin(k / 50)))
            self.override.publish(Float64(data=0.5))
            next_at += self.period
            time.sleep(max(0.0, next_at - time.monotonic()))


def latency(args, work: Path) -> None:
    from playwright.sync_api import sync_playwright

    from hrc_ros.ros.hmi.browser import launch
    cell = PlayedCell(work, [(UInt8, 'hrc/distance_level', qos.LATCHED)])
    epoch, task, action, (level,) = cell.epoch, cell.task, cell.action, cell.more
    arm = ArmStream(cell.bench.node)
    url = cell.url
    count = args.pages - args.browsers
    context = multiprocessing.get_context('spawn')
    results = context.Queue()
    try:
        cell.start()
        arm.start()
        done = context.Event()
        clients = context.Process(target=run_clients, args=(url, count, done, results))
        clients.start()
        if results.get(timeout=60) != 'ready':
            raise RuntimeError('the clients did not connect')
        sent: list[tuple[str, str, float]] = []        # (element, text, publish time)
        with sync_playwright() as playwright:
            browser = launch(playwright, args.chromium)
            pages = []
            for _ in range(args.browsers):
                page = browser.new_page(viewport={'width': 1440, 'height': 900})
                page.goto(url + 'operator')
                page.locator('#connection:not([data-state="disconnected"])').wait_for(
                    timeout=30_000)
                page.evaluate(WATCH)
                pages.append(page)
            names = list(ACTIONS)
            for k in range(1, args.samples + 1):
                epoch.publish(conv.epoch_to_msg(k))
                task.publish(conv.task_state_to_msg(IDLE))
                code = names[k % len(names)]
                sent.append(('action', ACTIONS[code], time.time()))
                action.publish(conv.action_to_msg(code))
                if k % 2 == 0:
                    d = 1 + (k // 2) % 3
                    sent.append(('distance', DISTANCES[d], time.time()))
                    level.publish(conv.distance_level_to_msg(d))
                time.sleep(args.interval)
            time.sleep(1.0)
            changes = [page.evaluate('window.__changes') for page in pages]
            browser.close()
        done.set()
        seen = results.get(timeout=120)
        clients.join(30)
    finally:
        arm.running = False
        cell.close()
    # each sample: the first change to its text after its publication, before the next sample
    # of the same element (a text repeats every few samples)
    for element in ('action', 'distance'):
        mine = [(text, t) for e, text, t in sent if e == element]
        browser_ms, client_ms = [], []
        for i, (text, t) in enumerate(mine):
            until = mine[i + 1][1] if i + 1 < len(mine) else float('inf')
            for page_changes in changes:
                hit = [c[2] / 1e3 for c in page_changes
                       if c[0] == element and c[1] == text and t <= c[2] / 1e3 < until]
                if hit:
                    browser_ms.append((hit[0] - t) * 1e3)
            for client_seen in seen:
                hit = [arrived for arrived, shown_action, shown_distance in client_seen
                       if (shown_action if element == 'action' else shown_distance) == text
                       and t <= arrived < until]
                if hit:
                    client_ms.append((hit[0] - t) * 1e3)
        kind = 'control input, taken at once' if element == 'action' else \
            'sampled input, read 20 times a second'
        print(f'hrc/{"action" if element == "action" else "distance_level"} -> #{element} '
              f'({kind}), {args.pages} pages open:')
        print(f'  in Chromium ({args.browsers} pages): {percentiles(browser_ms)}')
        print(f'  aiohttp clients ({count} pages, a process of their own): '
              f'{percentiles(client_ms)}')
        print(f'  all: {percentiles(browser_ms + client_ms)}; missed '
              f'{len(mine) * args.pages - len(browser_ms) - len(client_ms)} of '
              f'{len(mine) * args.pages}')


# -- the cell with the arm (phases cpu and memory) -----------------------------------------------
def cell_params(port: int) -> dict:
    params = {
        '/**': {'ros__parameters': {'config': str(arm_config_path())}},
        '/**/decision': {'ros__parameters': {'epoch_period': 1.0, 'input_timeout': 0.8,
                                             'min_epoch_subscribers': 3}},
        '/**/task_manager': {'ros__parameters': {
            'initial_task': [1, 1, 0], 'max_queue': 3,
            'schedule': [f'{k}:{1 + k % 2},{1 + k % 2},{k % 4}' for k in range(3, 4000, 4)]}},
        '/**/cell_sim': {'ros__parameters': {'seed': 0, 'answer_requests': False}},
        '/**/hmi': {'ros__parameters': {'port': port}},
    }
    for name, values in ROBOT_OVERRIDES.items():
        params.setdefault(f'/**/{name}', {'ros__parameters': {}})['ros__parameters'].update(
            values)
    return params


def start_cell(work: Path):
    port = free_port()
    path = work / 'cell.yaml'
    path.write_text(yaml.safe_dump(cell_params(port), sort_keys=False))
    run = NodeProcesses(work, [path])
    bench = BenchNode()
    names = ('hmi', 'task_manager', 'belief_estimator', 'cell_sim', 'cobot_sim', 'robot_bridge')
    for name in names:
        run.start(f'{name}_node')
    wait(lambda: set(names) <= set(bench.node.get_node_names()) or run.dead(), 60,
         'the nodes')
    run.check_alive()
    run.start('decision_node')
    wait(lambda: 'decision' in bench.node.get_node_names() or run.dead(), 60, 'the decision')
    run.check_alive()
    return run, bench, f'http://127.0.0.1:{port}/'


def measure(pid: int, seconds: float, every: float) -> list[float]:
    samples = [(time.monotonic(), cpu_seconds(pid), 0.0)]
    end = samples[0][0] + seconds
    while time.monotonic() < end:
        time.sleep(min(every, max(0.0, end - time.monotonic())))
        samples.append((time.monotonic(), cpu_seconds(pid), 0.0))
    return cpu_windows(samples)


def cpu(args, work: Path) -> None:
    from playwright.sync_api import sync_playwright

    from hrc_ros.ros.hmi.browser import launch
    run, bench, url = start_cell(work)
    pid = run.processes['hmi_node'].pid
    stop = asyncio.Event()
    loop = asyncio.new_event_loop()
    threading.Thread(target=loop.run_forever, daemon=True).start()
    clients = args.pages - args.browsers
    views = ['operator'] * (clients - clients // 4) + ['worker'] * (clients // 4)

    async def open_clients():
        import aiohttp
        session = aiohttp.ClientSession()
        return session, [asyncio.ensure_future(Client().run(session, url, stop, view))
                         for view in views]

    try:
        time.sleep(args.warmup)
        base = measure(pid, args.baseline, args.sample)
        print(f'no page open ({args.baseline:g} s): hmi_node CPU {np.mean(base):.2f}% of a core '
              f'(windows max {max(base):.2f}%)', flush=True)
        with sync_playwright() as playwright:
            browser = launch(playwright, args.chromium)
            for _ in range(args.browsers):
                page = browser.new_page(viewport={'width': 1440, 'height': 900})
                page.goto(url + 'operator')
            session, _ = asyncio.run_coroutine_threadsafe(open_clients(), loop).result(30)
            time.sleep(args.warmup)
            opened = measure(pid, args.soak, args.sample)
            browser.close()
        loop.call_soon_threadsafe(stop.set)
        time.sleep(1.0)
        asyncio.run_coroutine_threadsafe(session.close(), loop).result(10)
        run.check_alive()
    finally:
        codes = run.stop()
        bench.close()
    print(f'{args.pages} pages open ({args.browsers} in Chromium, {len(views)} clients: '
          f'{views.count("operator")} consoles, {views.count("worker")} workers\' pages), '
          f'{args.soak:g} s: hmi_node CPU {np.mean(opened):.2f}% of a core (per '
          f'{args.sample:g} s window: median {np.median(opened):.2f}%, max {max(opened):.2f}%)')
    print(f'  the pages\' own cost: {np.mean(opened) - np.mean(base):+.2f} points of a core')
    print('nodes stopped: ' + ', '.join(f'{n} exit {c}' for n, c in codes.items()))


# -- phase memory ------------------------------------------------------------------------------
def memory(args, work: Path) -> None:
    from playwright.sync_api import sync_playwright

    from hrc_ros.ros.hmi.browser import launch
    run, bench, url = start_cell(work)
    rows = []
    try:
        with sync_playwright() as playwright:
            browser = launch(playwright, args.chromium)
            page = browser.new_page(viewport={'width': 1440, 'height': 900})
            page.goto(url + 'operator')
            cdp = page.context.new_cdp_session(page)
            cdp.send('Performance.enable')
            start = time.monotonic()
            end = start + args.memory_minutes * 60
            while True:
                cdp.send('HeapProfiler.collectGarbage')
                metrics = {m['name']: m['value']
                           for m in cdp.send('Performance.getMetrics')['metrics']}
                timeline = page.evaluate("""() => { const t = document.getElementById(
                    'timeline'); return [Number(t.dataset.epochs), Number(t.dataset.robot),
                    document.getElementById('events').children.length]; }""")
                minute = (time.monotonic() - start) / 60
                rows.append((minute, metrics['JSHeapUsedSize'] / 2**20, metrics['Nodes'],
                             metrics['JSEventListeners'], *timeline))
                print(f'{minute:6.1f} min: JS heap {rows[-1][1]:.2f} MiB, {int(rows[-1][2])} '
                      f'DOM nodes, {int(rows[-1][3])} listeners; timeline {timeline[0]} '
                      f'epochs, {timeline[1]} arm points; {timeline[2]} events', flush=True)
                if time.monotonic() >= end:
                    break
                time.sleep(min(args.memory_sample, max(0.0, end - time.monotonic())))
                run.check_alive()
            browser.close()
    finally:
        codes = run.stop()
        bench.close()
    data = np.array(rows)
    # the timeline holds its ten minutes from 10 min on; the event log its 200 entries once
    # that many happened (each entry a few DOM nodes): after both, nothing may grow
    full = data[data[:, 6] >= FEEDS['events'], 0]
    for since in (10.0, full[0] if full.size else None):
        later = data[:, 0] >= since if since is not None else np.zeros(len(data), bool)
        if later.sum() < 3:
            continue
        for column, name, unit in ((1, 'JS heap', 'MiB'), (2, 'DOM nodes', ''),
                                   (3, 'event listeners', '')):
            values = data[later, column]
            slope = np.polyfit(data[later, 0], values, 1)[0] * 60
            print(f'{name}: {values[0]:.2f} {unit} at {since:.0f} min, {values[-1]:.2f} {unit} '
                  f'at {data[-1, 0]:.0f} min (min {values.min():.2f}, max {values.max():.2f}); '
                  f'slope after {since:.0f} min {slope:+.3f} {unit}/hour')
    print('nodes stopped: ' + ', '.join(f'{n} exit {c}' for n, c in codes.items()))


def main() -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--phase', action='append', choices=('latency', 'cpu', 'memory'),
                        help='the phases to run (default: latency and cpu)')
    parser.add_argument('--pages', type=int, default=10)
    parser.add_argument('--browsers', type=int, default=2, help='pages in Chromium')
    parser.add_argument('--samples', type=int, default=200)
    parser.add_argument('--interval', type=float, default=0.5, help='s between samples')
    parser.add_argument('--soak', type=float, default=120.0)
    parser.add_argument('--baseline', type=float, default=60.0)
    parser.add_argument('--warmup', type=float, default=15.0)
    parser.add_argument('--sample', type=float, default=10.0)
    parser.add_argument('--memory-minutes', type=float, default=60.0)
    parser.add_argument('--memory-sample', type=float, default=60.0)
    parser.add_argument('--chromium', default=None)
    args = parser.parse_args()
    phases = args.phase or ['latency', 'cpu']
    print('command: ' + shlex.join([sys.executable, *sys.argv]) + f'  (ROS_DOMAIN_ID '
          f'{os.environ["ROS_DOMAIN_ID"]}, {os.cpu_count()} cores, load '
          f'{" ".join(f"{x:.1f}" for x in os.getloadavg())})', flush=True)
    with tempfile.TemporaryDirectory(prefix='console_bench_') as folder:
        for phase in phases:
            {'latency': latency, 'cpu': cpu, 'memory': memory}[phase](args, Path(folder))
            print(f'load after {phase}: {" ".join(f"{x:.1f}" for x in os.getloadavg())}',
                  flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
