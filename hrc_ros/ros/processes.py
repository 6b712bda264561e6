"""Node processes started as a user would start them: their console scripts, in process groups.

Used by `hrc-case-study` and by the tests that run the suite as separate processes. Each node
runs `<console script> --ros-args --params-file ...` in its own session (so SIGINT reaches the
whole group, as Ctrl-C in a terminal would), logging to `<log_dir>/<executable>.log`.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterable


class NodeProcessError(RuntimeError):
    """A node process exited while it should be running."""


def node_command(executable: str) -> list[str]:
    """The console script: next to this interpreter, on PATH, or in <prefix>/lib/hrc_ros
    (a colcon install); `python -m hrc_ros.nodes.<name>` as the last resort."""
    candidates = [Path(sys.executable).parent / executable, shutil.which(executable),
                  Path(sys.prefix) / 'lib' / 'hrc_ros' / executable]
    for candidate in candidates:
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            return [str(candidate)]
    return [sys.executable, '-m', f'hrc_ros.ros.nodes.{executable}']


class NodeProcesses:
    """Start, watch and stop node processes; `params` are passed as --params-file in order."""

    def __init__(self, log_dir: str | Path, params: Iterable[str | Path],
                 env: dict | None = None):
        self.log_dir = Path(log_dir)
        self.params = [str(p) for p in params]
        self.env = {**(os.environ if env is None else env), 'PYTHONFAULTHANDLER': '1',
                    'PYTHONUNBUFFERED': '1'}
        self.processes: dict[str, subprocess.Popen] = {}

    def start(self, executable: str, remappings: Iterable[tuple[str, str]] = ()) -> None:
        cmd = node_command(executable) + ['--ros-args']
        for path in self.params:
            cmd += ['--params-file', path]
        for old, new in remappings:
            cmd += ['-r', f'{old}:={new}']
        with open(self.log_dir / f'{executable}.log', 'w') as log:
            self.processes[executable] = subprocess.Popen(
                cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=self.env, start_new_session=True)

    def log(self, executable: str, tail: int = 6000) -> str:
        return (self.log_dir / f'{executable}.log').read_text()[-tail:]

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

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        """SIGINT to every process group, then the exit codes.

        A process still running after `timeout` gets SIGABRT, which makes Python's faulthandler
        (PYTHONFAULTHANDLER=1) write every thread's stack to its log, then SIGKILL.
        """
        for process in self.processes.values():
            if process.poll() is None:
                try:
                    os.killpg(process.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        codes = {}
        deadline = time.monotonic() + timeout
        for name, process in self.processes.items():
            try:
                codes[name] = process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                for sig, wait in ((signal.SIGABRT, 2.0), (signal.SIGKILL, None)):
                    try:
                        os.killpg(process.pid, sig)
                    except ProcessLookupError:
                        pass
                    try:
                        codes[name] = process.wait(timeout=wait)
                        break
                    except subprocess.TimeoutExpired:
                        continue
        return codes
