"""hrc-fleet's Ray session: joining a cluster, where Ray's output goes, what a run's retries
and lost nodes were, and stopping an embedded cluster whole (docs/FLEET.md "Engine").

- `check_address`: a cluster that cannot be joined is one line naming the address and the
  cause, in seconds, before anything is started or written. `ray.init` itself retries an
  unreachable GCS for minutes (824 s measured, with 60 warnings naming the address Ray
  resolved to) and says only "Failed to connect" when the cluster refuses the driver's token;
  so the address is resolved as Ray resolves it, its port tried over TCP, a GCS address
  asked for its cluster id with the driver's credentials (Ray's own client, a 5 s timeout),
  and a Ray Client address (ray://) pinged once as Ray's client pings it (its own retries
  take 30 s and end in "ray client connection timeout").
- `RayLog`: file descriptors 1 and 2 go to OUT/ray.log while Ray runs in this process, so
  that Ray's warnings, its workers' forwarded output and its raylet's messages (the memory
  monitor's dumps) land there and not between the decision lines; the progress bar writes to
  the terminal's stderr, kept aside.
- `Attempts`: every stage task puts one key into the GCS's key-value store when it starts
  (run, cell, stage key, task id, worker pid), so a task Ray ran twice (its worker died, its
  node was lost) is seen in the report; `LostNodes` notes the nodes the cluster lost during
  the run.
- `EmbeddedProcesses`: the processes an embedded `ray.init` started, stopped by their ids
  after `ray.shutdown` if they outlive it (Ray's dashboard and runtime-env agents stayed
  30-90 s after a Ctrl-C).
"""

from __future__ import annotations

import os
import signal
import socket
import sys
import tempfile
import time
from pathlib import Path

from .common import ToolError

PROBE_TIMEOUT = 5.0          # seconds for the TCP connection and for the GCS's answer
NAMESPACE = 'hrc_fleet'      # the GCS key-value namespace of the attempts
NODE_POLL = 5.0              # seconds between two looks at the cluster's nodes
STOP_GRACE = 2.0             # seconds an embedded process has to exit after ray.shutdown


# -- joining ----------------------------------------------------------------------------------
def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(':')
    if not host or not port.isdigit():
        raise ValueError(f'not HOST:PORT: {text!r}')
    return host.strip('[]'), int(port)


class _Quiet:
    """File descriptor 2 into a temporary file while Ray's C++ client complains (its warnings
    would be the lines before ours); what it wrote is kept in `text`."""

    def __enter__(self):
        sys.stderr.flush()
        self._file = tempfile.TemporaryFile()
        self._saved = os.dup(2)
        os.dup2(self._file.fileno(), 2)
        return self

    def __exit__(self, *exc):
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read().decode(errors='replace')
        self._file.close()
        return False


def check_address(address: str, timeout: float = PROBE_TIMEOUT) -> str:
    """The cluster at `address` ('auto', HOST:PORT or ray://HOST:PORT) resolved as Ray
    resolves it and checked: its port answers, and a GCS accepts this driver (its token). The
    address Ray will connect to; ToolError with one line naming `address`, what it resolved
    to and the cause otherwise."""
    client = address.startswith('ray://')
    try:
        if client:
            target = address[len('ray://'):]
        else:
            from ray._private.services import canonicalize_bootstrap_address_or_die
            target = canonicalize_bootstrap_address_or_die(address)
        host, port = _host_port(target)
    except (ConnectionError, ValueError) as exc:
        raise ToolError(f'cannot join the Ray cluster at {address}: '
                        f'{" ".join(str(exc).split())[:300]}') from None
    where = address if target == address else f'{address} ({target})'
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except socket.timeout:
        cause = (f'no answer within {timeout:g} s (the host is down, or a firewall drops the '
                 'connection)')
    except ConnectionRefusedError:
        cause = ('connection refused: nothing listens on that port (is the cluster running, '
                 'and is this its GCS port, 6379 by default, or for ray:// its client port?)')
    except OSError as exc:
        cause = exc.strerror or str(exc)
    else:
        cause = (_client_refusal(target, timeout) if client
                 else _gcs_refusal(target, timeout, address == 'auto'))
    if cause:
        raise ToolError(f'cannot join the Ray cluster at {where}: {cause}')
    return target


TOKEN_REFUSED = ("the cluster refused this driver's authentication token (Ray's token "
                 "authentication: give hrc-fleet the cluster's token in RAY_AUTH_TOKEN, in a "
                 'file named by RAY_AUTH_TOKEN_PATH or in ~/.ray/auth_token, with '
                 'RAY_AUTH_MODE=token)')


def _gcs_refusal(target: str, timeout: float, auto: bool) -> str | None:
    """Why the GCS at `target` does not take this driver (None when it does): asked for its
    cluster id with the credentials `ray.init` would use (for `auto`, a local cluster found,
    the token it finds, as ray.init enables it)."""
    from ray._private.authentication.authentication_token_setup import (
        maybe_enable_token_auth_if_token_available)
    from ray._raylet import InnerGcsClient
    from ray.exceptions import AuthenticationError, RpcError
    try:
        with _Quiet():
            if auto:
                maybe_enable_token_auth_if_token_available(warn_if_disabled=False)
            InnerGcsClient.standalone(target, None, int(timeout * 1000))
    except AuthenticationError:
        return TOKEN_REFUSED
    except RpcError as exc:
        return (f'no Ray GCS answers there ({" ".join(str(exc).split())[:200]}; is this the '
                'GCS port?)')
    return None


def _client_refusal(target: str, timeout: float) -> str | None:
    """Why the Ray Client server at `target` does not answer this driver (None when it does):
    pinged as `ray.init('ray://...')` pings it before connecting (the same channel, with Ray's
    TLS and token settings), but once and within `timeout`: Ray's own client retries for 30 s
    (5 + 10 + 15) and then says only 'ray client connection timeout'."""
    import grpc
    from ray._private.grpc_utils import init_grpc_channel
    from ray.core.generated import ray_client_pb2, ray_client_pb2_grpc
    from ray.util.client.common import GRPC_OPTIONS
    with _Quiet():
        channel = init_grpc_channel(target, options=GRPC_OPTIONS)
        try:
            grpc.channel_ready_future(channel).result(timeout=timeout)
            ray_client_pb2_grpc.RayletDriverStub(channel).ClusterInfo(
                ray_client_pb2.ClusterInfoRequest(type=ray_client_pb2.ClusterInfoType.PING),
                timeout=timeout, metadata=[('client_id', 'hrc-fleet-probe')])
        except grpc.FutureTimeoutError:
            return (f'the port answers but no gRPC server within {timeout:g} s: is this the '
                    "cluster's Ray Client port (10001 by default), and TLS set as the server "
                    'wants it (RAY_USE_TLS)?')
        except grpc.RpcError as exc:
            if exc.code() == grpc.StatusCode.UNAUTHENTICATED:
                return TOKEN_REFUSED
            return (f'no Ray Client server answers there ({exc.code().name}: '
                    f'{" ".join(str(exc.details()).split())[:200]}; is this the Ray Client '
                    'port?)')
        finally:
            channel.close()
    return None


# -- Ray's output -----------------------------------------------------------------------------
class RayLog:
    """File descriptors 1 and 2 into `path` (appended) while Ray runs (module docstring);
    `terminal` is the stderr they had, for the progress bar."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def __enter__(self):
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        self._file = open(self.path, 'ab')
        self._saved = {fd: os.dup(fd) for fd in (1, 2)}
        self.terminal = os.fdopen(os.dup(self._saved[2]), 'w', buffering=1)
        for fd in (1, 2):
            os.dup2(self._file.fileno(), fd)
        return self

    def __exit__(self, *exc):
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        for fd, saved in self._saved.items():
            os.dup2(saved, fd)
            os.close(saved)
        self.terminal.close()
        self._file.close()
        return False


# -- retries and lost nodes -------------------------------------------------------------------
def record_attempt(ray, run: str, cell: str, key: str) -> None:
    """In a stage task: one key per attempt (module docstring). Never fails the stage."""
    try:
        from ray.experimental.internal_kv import _internal_kv_put
        context = ray.get_runtime_context()
        _internal_kv_put(f'{run}|{cell}|{key}|{context.get_task_id()}|{os.getpid()}',
                         context.get_node_id(), namespace=NAMESPACE)
    except Exception:   # noqa: BLE001 - bookkeeping only: the stage's work comes first
        pass


def attempts(run: str) -> dict:
    """(cell, key) -> [{'pid', 'node'}, ...] for every stage task Ray started more than
    once in run `run`; the run's keys are deleted."""
    from ray.experimental.internal_kv import (_internal_kv_del, _internal_kv_get,
                                              _internal_kv_list)
    runs: dict = {}
    try:
        keys = _internal_kv_list(f'{run}|', namespace=NAMESPACE)
        for raw in keys:
            _, cell, key, task, pid = raw.decode().split('|')
            node = _internal_kv_get(raw, namespace=NAMESPACE)
            runs.setdefault((cell, key, task), []).append(
                {'pid': int(pid), 'node': node.decode() if node else None})
        _internal_kv_del(f'{run}|', del_by_prefix=True, namespace=NAMESPACE)
    except Exception:   # noqa: BLE001 - a report without them rather than none
        return {}
    return {(cell, key): sorted(seen, key=lambda s: s['pid'])
            for (cell, key, _), seen in runs.items() if len(seen) > 1}


class LostNodes:
    """The cluster's nodes at the start, and those it lost since (`poll`, at most once per
    `NODE_POLL` seconds)."""

    def __init__(self, ray):
        self.ray, self.t0, self.lost, self._next = ray, time.monotonic(), [], 0.0
        self.nodes = {n['NodeID']: n for n in self._nodes()}
        self.alive = {k for k, n in self.nodes.items() if n['Alive']}

    def _nodes(self) -> list:
        try:
            return self.ray.nodes()
        except Exception:   # noqa: BLE001 - the GCS busy: the next poll
            return []

    def poll(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now < self._next:
            return
        self._next = now + NODE_POLL
        for node in self._nodes():
            key = node['NodeID']
            self.nodes.setdefault(key, node)
            if node['Alive']:
                self.alive.add(key)
            elif key in self.alive:
                self.alive.discard(key)
                self.lost.append({'node': key, 'address': node.get('NodeManagerAddress'),
                                  'after_seconds': round(now - self.t0, 1),
                                  'reason': ' '.join(str(node.get('DeathReasonMessage')
                                                         or '').split())[:200]})

    def address(self, node: str | None) -> str:
        known = self.nodes.get(node) or {}
        return f'{(node or "?")[:12]} ({known.get("NodeManagerAddress", "?")})'


# -- stopping an embedded cluster -------------------------------------------------------------
def _start_time(pid: int) -> str | None:
    """A process's start time (clock ticks since boot), None when it is gone or a zombie: with
    the pid it names the process, so a pid reused since is never signalled."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except (OSError, IndexError):
        return None
    return None if fields[0] in ('Z', 'X') else fields[19]


class EmbeddedProcesses:
    """The processes below this one that an embedded Ray started (`add` after ray.init and
    again before the shutdown, for the workers), and `stop`: whatever of them outlives
    ray.shutdown by `STOP_GRACE` seconds gets SIGTERM, then SIGKILL."""

    def __init__(self):
        from ..core.parallel import descendants
        self._descendants = descendants
        self.before = descendants(os.getpid())
        self.started: dict[int, str] = {}

    def add(self) -> None:
        for pid in self._descendants(os.getpid()) - self.before:
            start = _start_time(pid)
            if start is not None:
                self.started.setdefault(pid, start)

    def alive(self) -> list[int]:
        return [pid for pid, start in self.started.items() if _start_time(pid) == start]

    def stop(self, grace: float = STOP_GRACE) -> list[int]:
        """Wait for them, then end the ones left; the pids that had to be ended."""
        deadline = time.monotonic() + grace
        while self.alive() and time.monotonic() < deadline:
            time.sleep(0.1)
        ended = self.alive()
        for sig, wait in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 2.0)):
            left = self.alive()
            if not left:
                break
            for pid in left:
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            while self.alive() and time.monotonic() < deadline:
                time.sleep(0.05)
        return ended
