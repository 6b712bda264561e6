"""A test's own rclpy node, in its own Context, spun in a daemon thread."""

import threading
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor


class SpunNode:
    """`self.node` in its own Context and executor; `start()` spins it in a daemon thread (call
    it once the subscriptions and timers exist). `close()` stops the spin, destroys the node
    while its context is still valid, then shuts the context down (the order of
    hrc_ros/ros/stop.py)."""

    wait_timeout = 30.0    # s, wait()'s default

    def __init__(self, name: str):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stopping = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _spin(self) -> None:
        while not self._stopping.is_set() and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - the context went down under it
                return

    def wait(self, predicate, what: str, timeout: float | None = None):
        """predicate()'s first true value, polled every 20 ms; an AssertionError naming `what`
        after `timeout` s (default `wait_timeout`), and what `context_now()` says then (a wait that
        fails under load must name the state it left the graph in)."""
        timeout = self.wait_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while True:
            value = predicate()
            if value:
                return value
            if time.monotonic() >= deadline:
                said = self.context_now()
                raise AssertionError(f'timed out after {timeout} s waiting for {what}'
                                     + (f'; {said}' if said else ''))
            time.sleep(0.02)

    def context_now(self) -> str:
        """What a timed-out `wait` adds to its message ('' here)."""
        return ''

    def call(self, service_type, name: str, request=None, timeout: float | None = None):
        """The answer of service `name` to `request` (default: an empty request), waiting
        for the service and the answer at most `timeout` s each (default `wait_timeout`)."""
        timeout = self.wait_timeout if timeout is None else timeout
        client = self.node.create_client(service_type, name)
        try:
            assert client.wait_for_service(timeout_sec=timeout), f'no service {name}'
            future = client.call_async(service_type.Request() if request is None else request)
            return self.wait(future.result, f'the answer of {name}', timeout)
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        self._stopping.set()
        self.thread.join(5)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def forger(name: str, msg_type, topic: str, matches: int = 0, timeout: float = 30.0):
    """Another node on the cell (a stray script, an attacker): a SpunNode, with a DDS
    participant of its own, and its reliable publisher of `topic`, returned once `matches`
    subscriptions have matched it (at most `timeout` s). `close()` it when it leaves: its
    participant leaves with it. (A publisher made on a test's own long-lived node and destroyed
    with destroy_publisher stayed in the bridge's graph twice in about ten suite runs,
    2026-12-06 and 07: "1 other publisher(s) of the goal topic" for the rest of the module,
    whose next ten tests timed out behind the arm's stop, the safe way, with nobody there.)"""
    from hrc_ros.ros import qos
    node = SpunNode(name)
    try:
        publisher = node.node.create_publisher(msg_type, topic, qos.RELIABLE)
        node.start()
        node.wait(lambda: publisher.get_subscription_count() >= matches,
                  f'{topic} to match the forger', timeout)
    except BaseException:
        node.close()
        raise
    return node, publisher


def last_statuses(statuses, parts=('robot_bridge', 'cobot_sim'), scan: int = 400) -> str:
    """The last /diagnostics status of every component whose name holds one of `parts`, among
    the last `scan` of `statuses`: level and message, for a timed-out wait's message."""
    last = {}
    for status in statuses[-scan:]:
        if any(part in status.name for part in parts):
            last[status.name] = f'{status.level!r} {status.message[:200]}'
    return '; '.join(f'{k}: {v}' for k, v in sorted(last.items()))
