"""Node processes started as a user would start them: their console scripts, in process groups.

Used by `hrc-case-study`, `bench/stop_bench.py` and the tests that run the suite as separate
processes. Each node runs `<console script> --ros-args --params-file ...` in its own session (so
SIGINT reaches the whole group, as Ctrl-C in a terminal would), logging to
`<log_dir>/<executable>.log`.

Stopping (stop.py has the nodes' side). `stop()` sends SIGINT to one node at a time, the last
started first, and waits until it has exited before it signals the next (`STOP_ORDER`,
'sequential'): Fast DDS 2.14 can deadlock when several participants are destroyed at once (a
participant's `destroy_participant` waiting in `set_listener` for its listener's callbacks, while
its discovery thread waits in `onReaderDiscovery` for the listener's mutex, called as another
participant's readers go; bench/README.md, "Stopping"), and with one node leaving at a time no
other participant is leaving while one is destroyed. `order='together'` signals every node at once
(the old way; bench/stop_bench.py compares the two). Each node has the whole `timeout` of its own.
A node is started with SIGINT and SIGTERM blocked, which survives exec: a signal sent before the
interpreter has run the first line of the console script stays pending until `stop.install()`
unblocks it, and is then a clean stop like any other. A node still running after the timeout is
stuck somewhere: before it is killed its native and Python stacks go into its log (`py-spy dump
--native`, and gdb's backtraces when gdb is installed; without either, the SIGABRT that Python's
faulthandler answers with the Python stacks), then SIGABRT, then SIGKILL.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable

from . import stop as stop_regime

STACK_DUMP_TIMEOUT = 20.0     # seconds for py-spy or gdb to write a hung node's stacks
STOP_ORDERS = ('sequential', 'together')
STOP_ORDER = 'sequential'     # the default of `NodeProcesses.stop` (module docstring)


class NodeProcessError(RuntimeError):
    """A node process exited while it should be running."""


def node_command(executable: str) -> list[str]:
    """The console script: next to this interpreter, on PATH, or in <prefix>/lib/hrc_ros
    (a colcon install); `python -m hrc_ros.ros.entry <name>` as the last resort."""
    candidates = [Path(sys.executable).parent / executable, shutil.which(executable),
                  Path(sys.prefix) / 'lib' / 'hrc_ros' / executable]
    for candidate in candidates:
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            return [str(candidate)]
    return [sys.executable, '-m', 'hrc_ros.ros.entry', executable]


def stack_dumpers() -> list[list[str]]:
    """Commands (pid appended) that write a process's stacks: py-spy for the Python frames with
    the native ones, and gdb, whose unwinder also walks stripped C++ libraries (the ROS
    wheels'), when they are installed."""
    dumpers = []
    for candidate in (Path(sys.executable).parent / 'py-spy', shutil.which('py-spy')):
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            dumpers.append([str(candidate), 'dump', '--native', '--pid'])
            break
    gdb = shutil.which('gdb')
    if gdb:
        dumpers.append([gdb, '-batch', '-nx', '-ex', 'thread apply all bt', '-p'])
    return dumpers


def dump_stacks(pid: int, log_path: Path) -> bool:
    """Append the stacks of process `pid` to `log_path`; False if no tool could."""
    written = False
    for dumper in stack_dumpers():
        with open(log_path, 'a') as log:
            log.write(f'\n--- {os.path.basename(dumper[0])}: stacks of pid {pid}, still '
                      'running after the stop timeout ---\n')
            log.flush()
            try:
                result = subprocess.run(dumper + [str(pid)], stdout=log,
                                        stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                        timeout=STACK_DUMP_TIMEOUT)
            except (OSError, subprocess.TimeoutExpired) as exc:
                log.write(f'--- the stack dump failed: {exc} ---\n')
                continue
            log.write(f'--- end of stacks (exit {result.returncode}) ---\n')
            written = written or result.returncode == 0
    return written


@contextmanager
def _blocked_stop_signals():
    """Around Popen: the child starts with SIGINT and SIGTERM blocked (see the module
    docstring); the calling thread's mask is restored at once."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, stop_regime.STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class NodeProcesses:
    """Start, watch and stop node processes; `params` are passed as --params-file in order."""

    def __init__(self, log_dir: str | Path, params: Iterable[str | Path],
                 env: dict | None = None):
        self.log_dir = Path(log_dir)
        self.params = [str(p) for p in params]
        # the launcher's pid: a node whose launcher dies without stopping it stops itself
        # (stop.py, point 7)
        self.env = {**(os.environ if env is None else env), 'PYTHONFAULTHANDLER': '1',
                    'PYTHONUNBUFFERED': '1', stop_regime.PARENT_ENV: str(os.getpid())}
        self.processes: dict[str, subprocess.Popen] = {}
        self.stacks_dumped: list[str] = []
        self.stop_seconds: dict[str, float] = {}    # signal (or the stop call) to exit, per node
        stop_regime.on_force(self.kill)     # a forced exit of this process leaves no node behind

    def start(self, executable: str, remappings: Iterable[tuple[str, str]] = (), *,
              ros_args: list[str] | None = None, name: str | None = None) -> None:
        """Start `executable` with the params files and `remappings`, or with `ros_args`
        (everything after `--ros-args`, as a launch file passes it) instead; `name` keys the
        process and its log (default: the executable)."""
        name = name or executable
        cmd = node_command(executable) + ['--ros-args']
        if ros_args is None:
            for path in self.params:
                cmd += ['--params-file', path]
            for old, new in remappings:
                cmd += ['-r', f'{old}:={new}']
        else:
            cmd += list(ros_args)
        # appended to (O_APPEND): the node's own writes and the stacks `stop()` adds later
        # must not overwrite each other
        self.log_path(name).write_text('')
        with open(self.log_path(name), 'a') as log, _blocked_stop_signals():
            self.processes[name] = subprocess.Popen(
                cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=self.env, start_new_session=True)

    def log_path(self, name: str) -> Path:
        return self.log_dir / f'{name}.log'

    def log(self, name: str, tail: int = 6000) -> str:
        return self.log_path(name).read_text()[-tail:]

    def logs(self) -> str:
        return '\n'.join(f'--- {name} (exit {p.poll()}) ---\n{self.log(name)}'
                         for name, p in self.processes.items())

    def dead(self) -> list[str]:
        return [name for name, p in self.processes.items() if p.poll() is not None]

    def check_alive(self) -> None:
        for name in self.dead():
            tail = self.log(name).strip().splitlines()[-5:]
            raise NodeProcessError(f'{name} exited with code {self.processes[name].returncode}'
                                   ':\n  ' + '\n  '.join(tail))

    def send_signal(self, name: str, signum: int) -> None:
        """Send `signum` to the process group of `name` (what Ctrl-C in its terminal does)."""
        try:
            os.killpg(self.processes[name].pid, signum)
        except ProcessLookupError:
            pass

    def stop(self, timeout: float = 10.0, signum: int | None = signal.SIGINT,
             order: str = STOP_ORDER) -> dict[str, int]:
        """`signum` (SIGINT; None: already sent) to the process groups, then the exit codes
        (in start order).

        'sequential' (module docstring): the last started first, each signalled once the one
        before it has exited, with `timeout` s of its own; 'together': all at once, `timeout`
        for all. A process still running after its timeout gets its stacks written to its
        log (`dump_stacks`, named in `stacks_dumped`), then SIGABRT (Python's faulthandler,
        PYTHONFAULTHANDLER=1, adds the Python stacks), then SIGKILL; the next is signalled
        after that. `stop_seconds` holds each one's time from its signal to its exit.
        """
        if order not in STOP_ORDERS:
            raise ValueError(f'order must be one of {", ".join(STOP_ORDERS)}, got {order!r}')
        codes = {}
        running = {name for name, process in self.processes.items() if process.poll() is None}
        if order == 'together':
            sent = time.monotonic()
            for name, process in self.processes.items():
                if process.poll() is None and signum is not None:
                    self.send_signal(name, signum)
            for name, process in self.processes.items():
                codes[name] = self._wait_or_kill(name, process, sent + timeout, sent,
                                                  name in running)
        else:
            for name, process in reversed(self.processes.items()):
                sent = time.monotonic()
                if process.poll() is None and signum is not None:
                    self.send_signal(name, signum)
                codes[name] = self._wait_or_kill(name, process, sent + timeout, sent,
                                                 name in running)
        return {name: codes[name] for name in self.processes}

    def _wait_or_kill(self, name: str, process: subprocess.Popen, deadline: float,
                      sent: float, running: bool) -> int:
        """The exit code of `process` by `deadline`, or its stacks, SIGABRT and SIGKILL;
        `running`: it ran when `stop` was called (its stop time is then recorded)."""
        try:
            code = process.wait(timeout=max(0.1, deadline - time.monotonic()))
            if running:
                self.stop_seconds[name] = time.monotonic() - sent
            return code
        except subprocess.TimeoutExpired:
            pass
        if dump_stacks(process.pid, self.log_path(name)):
            self.stacks_dumped.append(name)
        self.send_signal(name, signal.SIGABRT)
        try:
            return process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self.send_signal(name, signal.SIGKILL)
            return process.wait()

    def kill(self) -> None:
        """SIGKILL every process group still running (a forced exit of the caller)."""
        for name, process in self.processes.items():
            if process.poll() is None:
                self.send_signal(name, signal.SIGKILL)
