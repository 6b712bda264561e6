"""The HMI's two targets: a click in the page to `hrc/human_response` on the graph, and 200 open
pages on a running cell.

    .venv/bin/python bench/hmi_bench.py                      # ~2.5 min: 200 clicks, 60 s soak
    .venv/bin/python bench/hmi_bench.py --full               # the 10-minute soak
    .venv/bin/python bench/hmi_bench.py --skip-latency --soak 120 --pages 500

Phase 1, click -> graph (target p99 < 50 ms): `hmi_node` as a process; this bench plays the
cell (it publishes `hrc/epoch`, the task state x_k of a joint task and `rh2`, so a request is
open) and listens to `hrc/human_response`; headless Chromium (Debian's, through Playwright)
shows the worker's page and clicks Accept. The click's time is taken inside the page (a
capture-phase listener on #accept: `performance.timeOrigin + performance.now()`, the system
clock in ms) and the answer's arrival on the bench's subscription on the same clock, so the
figure is the whole path: the page's handler, the WebSocket, the web thread, the bounded queue
and the guard condition into the executor, the machine's checks, the publish, DDS to another
process. Each sample then closes the request with the next epoch and opens a new one.

Phase 2, 200 open pages (targets: CPU < 20% of a core at the default 1 s epoch, memory growth
bounded): the real suite as processes (task manager, belief estimator, simulated cell,
decision node at its default period, `hmi_node` with its default parameters), the case study's
tasks and an operator client that orders a task every `--order-period` s so the cell keeps
working and the views keep changing. First `--baseline` s with no page, then `--pages`
WebSocket pages (aiohttp clients speaking the page's protocol; 5% of them the operator's view)
open for `--soak` s. The node's CPU (utime + stime from /proc/<pid>/stat) and RSS are sampled
every `--sample` s; printed: CPU per window (mean, max), RSS at the start and end of the soak
and its growth per minute over the second half (a leak grows linearly; a heap that has settled
does not), the views each page received, pages closed by the server.

The bench runs in a private DDS domain (HRC_BENCH_DOMAIN_ID, else random 100..199, localhost
discovery) and on loopback ports chosen free.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import shlex
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from private_domain import use_private_domain

if __name__ == '__main__':
    use_private_domain()

import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Bool, String, UInt8MultiArray, UInt32  # noqa: E402

from hrc_ros.core.model import TASK_VARIABLES  # noqa: E402
from hrc_ros.ros import conversions as conv  # noqa: E402
from hrc_ros.ros import qos  # noqa: E402
from hrc_ros.ros.processes import NodeProcesses  # noqa: E402

JOINT = dict(zip(TASK_VARIABLES, (1, 1, 3, 0, 0, 0, 0, 0)))
TICKS = os.sysconf('SC_CLK_TCK')
DEEP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                  reliability=ReliabilityPolicy.RELIABLE)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def cpu_seconds(pid: int) -> float:
    with open(f'/proc/{pid}/stat') as stat:
        fields = stat.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS       # utime + stime


def rss_mib(pid: int) -> float:
    with open(f'/proc/{pid}/status') as status:
        kib = int(next(line for line in status if line.startswith('VmRSS:')).split()[1])
    return kib / 1024


def percentiles(values) -> str:
    v = np.asarray(values)
    return (f'p50 {np.percentile(v, 50):.1f} ms, p90 {np.percentile(v, 90):.1f} ms, '
            f'p99 {np.percentile(v, 99):.1f} ms, max {v.max():.1f} ms (n = {v.size})')


class BenchNode:
    """The bench's own rclpy node, spun in a thread."""

    def __init__(self):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('hmi_bench', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.answers: list[tuple[float, bool]] = []
        self.node.create_subscription(Bool, 'hrc/human_response',
                                      lambda m: self.answers.append((time.time(), m.data)),
                                      DEEP)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.02)
            except Exception:  # noqa: BLE001 - the context went down under it
                return

    def close(self):
        rclpy.try_shutdown(context=self.context)
        self.thread.join(5)
        self.node.destroy_node()


def wait(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise RuntimeError(f'timed out after {timeout} s waiting for {what}')
        time.sleep(0.005)


class PlayedCell:
    """`hmi_node` as a process, and this bench playing the decision node and the task
    manager: publishers of hrc/epoch, hrc/task_state and hrc/action, and `more` ((type, topic,
    QoS) each); `start()` waits until the node listens on all of them."""

    def __init__(self, work: Path, more=()):
        port = free_port()
        params = work / 'played_cell.yaml'
        params.write_text(f'hmi:\n  ros__parameters:\n    port: {port}\n'
                          '    cell_timeout: 30.0\n')
        self.url = f'http://127.0.0.1:{port}/'
        self.run = NodeProcesses(work, [params])
        self.bench = BenchNode()
        node = self.bench.node
        self.epoch = node.create_publisher(UInt32, 'hrc/epoch', qos.RELIABLE)
        self.task = node.create_publisher(UInt8MultiArray, 'hrc/task_state', qos.LATCHED)
        self.action = node.create_publisher(String, 'hrc/action', qos.RELIABLE)
        self.more = [node.create_publisher(*spec) for spec in more]

    def start(self) -> None:
        self.run.start('hmi_node')
        publishers = [self.epoch, self.task, self.action, *self.more]
        wait(lambda: all(p.get_subscription_count() for p in publishers) or self.run.dead(),
             30, 'hmi_node to subscribe')
        self.run.check_alive()

    def close(self) -> None:
        self.run.stop()
        self.bench.close()


# -- phase 1 -----------------------------------------------------------------------------------
CLICK_PROBE = """() => {
  window.__clicks = [];
  document.getElementById('accept').addEventListener(
      'click', () => window.__clicks.push(performance.timeOrigin + performance.now()), true);
}"""


def latency(args, work: Path) -> None:
    from playwright.sync_api import expect, sync_playwright

    from hrc_ros.ros.hmi.browser import launch
    cell = PlayedCell(work)
    bench, epoch, task, action = cell.bench, cell.epoch, cell.task, cell.action
    try:
        cell.start()
        with sync_playwright() as playwright:
            browser = launch(playwright, args.chromium)
            page = browser.new_page(viewport={'width': 1280, 'height': 800})
            page.goto(cell.url)
            page.evaluate(CLICK_PROBE)
            accept = page.locator('#accept')
            in_page, with_driver = [], []
            for k in range(1, args.clicks + 1):
                epoch.publish(conv.epoch_to_msg(k))
                task.publish(conv.task_state_to_msg(JOINT))
                action.publish(conv.action_to_msg('rh2'))
                expect(accept).to_be_enabled(timeout=10_000)
                count = len(bench.answers)
                start = time.time()
                accept.click()
                wait(lambda n=count: len(bench.answers) > n, 5, f'answer {k}')
                arrived = bench.answers[-1][0]
                clicked = page.evaluate('window.__clicks[window.__clicks.length - 1]') / 1e3
                in_page.append((arrived - clicked) * 1e3)
                with_driver.append((arrived - start) * 1e3)
            browser.close()
        print(f'click in the page -> hrc/human_response on the graph: {percentiles(in_page)}')
        print(f'  (from the bench\'s click() call, Playwright included: '
              f'{percentiles(with_driver)})')
    finally:
        cell.close()


# -- phase 2 -----------------------------------------------------------------------------------
SOAK_PARAMS = """\
/**:
  ros__parameters:
    config: ''
decision:
  ros__parameters:
    min_epoch_subscribers: 2
task_manager:
  ros__parameters:
    initial_task: [1, 1, 3]
    schedule: ["9:2,2,1", "16:2,2,2"]
cell_sim:
  ros__parameters:
    seed: 0
hmi:
  ros__parameters:
    port: {port}
"""


async def page_client(session, url: str, view: str, stats: dict, stop: asyncio.Event):
    async with session.ws_connect(f'{url}ws?view={view}') as ws:
        stats['open'] += 1
        try:
            while not stop.is_set():
                try:
                    message = await asyncio.wait_for(ws.receive(), 1.0)
                except asyncio.TimeoutError:
                    continue
                if message.type != 1:          # aiohttp.WSMsgType.TEXT
                    stats['closed_by_server'] += 1
                    return
                if '"type":"view"' in message.data:
                    stats['views'] += 1
        finally:
            stats['open'] -= 1


async def operator_client(session, url: str, period: float, stats: dict, stop: asyncio.Event):
    rng = random.Random(1)
    async with session.ws_connect(f'{url}ws?view=operator') as ws:
        ref = 0
        while not stop.is_set():
            ref += 1
            await ws.send_str(json.dumps({'type': 'order', 'ref': ref,
                                          'priority': rng.randint(1, 2),
                                          'duration': rng.randint(1, 2),
                                          'nature': rng.randint(0, 3)}))
            deadline = time.monotonic() + period
            while time.monotonic() < deadline and not stop.is_set():
                try:
                    message = await asyncio.wait_for(ws.receive(), 0.5)
                except asyncio.TimeoutError:
                    continue
                if message.type == 1 and '"order_result"' in message.data:
                    status = json.loads(message.data)['status']
                    stats[f'orders_{status}'] = stats.get(f'orders_{status}', 0) + 1


async def measure(pid: int, seconds: float, every: float) -> list[tuple[float, float, float]]:
    """(time, cpu seconds, rss MiB) every `every` seconds for `seconds`."""
    samples = [(time.monotonic(), cpu_seconds(pid), rss_mib(pid))]
    end = samples[0][0] + seconds
    while time.monotonic() < end:
        await asyncio.sleep(min(every, max(0.0, end - time.monotonic())))
        samples.append((time.monotonic(), cpu_seconds(pid), rss_mib(pid)))
    return samples


def cpu_windows(samples) -> list[float]:
    return [100 * (c1 - c0) / (t1 - t0)
            for (t0, c0, _), (t1, c1, _) in zip(samples, samples[1:])]


async def soak_run(args, url: str, pid: int) -> None:
    import aiohttp
    stats = {'open': 0, 'views': 0, 'closed_by_server': 0}
    stop = asyncio.Event()
    connector = aiohttp.TCPConnector(limit=0)
    async with aiohttp.ClientSession(connector=connector) as session:
        ordering = asyncio.ensure_future(operator_client(session, url, args.order_period,
                                                         stats, stop))
        await asyncio.sleep(args.warmup)
        if args.baseline > 0:
            base = await measure(pid, args.baseline, args.sample)
            windows = cpu_windows(base)
            print(f'no page open ({args.baseline:g} s): hmi_node CPU {np.mean(windows):.1f}% '
                  f'of a core (windows max {max(windows):.1f}%), RSS {base[-1][2]:.1f} MiB')
        operators = max(1, args.pages // 20)
        clients = [asyncio.ensure_future(page_client(session, url, 'operator' if i < operators
                                                     else 'worker', stats, stop))
                   for i in range(args.pages)]
        opened = time.monotonic()
        while stats['open'] < args.pages:
            assert time.monotonic() - opened < 60, f'only {stats["open"]} pages opened'
            await asyncio.sleep(0.05)
        print(f'{args.pages} pages open after {time.monotonic() - opened:.1f} s '
              f'({operators} operator)')
        await asyncio.sleep(args.warmup)
        views_before = stats['views']
        samples = await measure(pid, args.soak, args.sample)
        views = stats['views'] - views_before
        stop.set()
        await asyncio.gather(*clients, ordering, return_exceptions=True)
    windows = cpu_windows(samples)
    rss = np.array([s[2] for s in samples])
    times = np.array([s[0] for s in samples]) - samples[0][0]
    half = times >= times[-1] / 2
    slope = np.polyfit(times[half], rss[half], 1)[0] * 60 if half.sum() >= 2 else float('nan')
    print(f'{args.pages} pages, {args.soak:g} s: hmi_node CPU {np.mean(windows):.1f}% of a core '
          f'(per {args.sample:g} s window: median {np.median(windows):.1f}%, max '
          f'{max(windows):.1f}%)')
    print(f'  RSS {rss[0]:.1f} MiB at the start, {rss[-1]:.1f} MiB at the end, max '
          f'{rss.max():.1f} MiB; growth over the second half {slope:+.2f} MiB/min')
    print(f'  views received: {views / args.pages / args.soak:.2f} per page per second; pages '
          f'closed by the server: {stats["closed_by_server"]}; orders: '
          + ', '.join(f'{k[7:]} {v}' for k, v in sorted(stats.items())
                      if k.startswith('orders_')))


def soak(args, work: Path) -> None:
    port = free_port()
    params = work / 'soak.yaml'
    params.write_text(SOAK_PARAMS.format(port=port))
    run = NodeProcesses(work, [params])
    bench = BenchNode()
    try:
        for name in ('task_manager', 'belief_estimator', 'cell_sim', 'hmi'):
            run.start(f'{name}_node')
        wait(lambda: {'task_manager', 'belief_estimator', 'cell_sim', 'hmi'}
             <= set(bench.node.get_node_names()) or run.dead(), 30, 'the nodes')
        run.check_alive()
        run.start('decision_node')
        wait(lambda: 'decision' in bench.node.get_node_names() or run.dead(), 30,
             'the decision node')
        asyncio.run(soak_run(args, f'http://127.0.0.1:{port}/', run.processes['hmi_node'].pid))
        run.check_alive()
    finally:
        codes = run.stop()
        bench.close()
    print('nodes stopped: ' + ', '.join(f'{n} exit {c}' for n, c in codes.items()))


def main() -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--clicks', type=int, default=200)
    parser.add_argument('--pages', type=int, default=200)
    parser.add_argument('--soak', type=float, default=60.0, help='seconds with the pages open')
    parser.add_argument('--full', action='store_true', help='the 10-minute soak (--soak 600)')
    parser.add_argument('--baseline', type=float, default=20.0,
                        help='seconds measured with no page first (0: none)')
    parser.add_argument('--warmup', type=float, default=5.0)
    parser.add_argument('--sample', type=float, default=5.0)
    parser.add_argument('--order-period', type=float, default=5.0)
    parser.add_argument('--skip-latency', action='store_true')
    parser.add_argument('--skip-soak', action='store_true')
    parser.add_argument('--chromium', default=None)
    args = parser.parse_args()
    if args.full:
        args.soak = 600.0
    print('command: ' + shlex.join([sys.executable, *sys.argv]) + f'  (ROS_DOMAIN_ID '
          f'{os.environ["ROS_DOMAIN_ID"]}, {os.cpu_count()} cores)', flush=True)
    with tempfile.TemporaryDirectory(prefix='hmi_bench_') as folder:
        if not args.skip_latency:
            latency(args, Path(folder))
        if not args.skip_soak:
            soak(args, Path(folder))
    return 0


if __name__ == '__main__':
    sys.exit(main())
