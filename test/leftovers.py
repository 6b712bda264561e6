"""The node processes a test module left running in the run's DDS domain (conftest.py's
`_no_node_left_behind`): a node of one module that outlives it is a second writer on every
topic of the next module's graph (a second arm's joint states, a second clock), and that
module then fails far from the cause. ROS-free: read from /proc."""

from __future__ import annotations

import os
import signal
import time
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path


def console_scripts() -> frozenset[str]:
    """hrc_ros's node and tool commands (its console_scripts entry points)."""
    try:
        return frozenset(e.name for e in distribution('hrc_ros').entry_points
                         if e.group == 'console_scripts')
    except PackageNotFoundError:
        return frozenset()


SCRIPTS = console_scripts()
# the variable that names one test run (conftest.py sets it; every process started inherits it)
RUN_VARIABLE = 'HRC_TEST_RUN'


def is_ours(argv: list[str]) -> bool:
    """A command line of one of hrc_ros's commands: a console script among its words, or
    `-m hrc_ros...` (a path that merely contains "hrc_ros", a clone's folder, is not)."""
    for i, word in enumerate(argv):
        if os.path.basename(word) in SCRIPTS:
            return True
        if word == '-m' and i + 1 < len(argv) and argv[i + 1].split('.')[0] == 'hrc_ros':
            return True
    return False


def ancestors(pid: int) -> set[int]:
    """`pid` and the processes above it."""
    found = set()
    while pid > 1 and pid not in found:
        found.add(pid)
        try:
            pid = int(Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            break
    return found


def graph_processes(domain: int, exclude: set[int], run: str | None = None,
                    worker: str | None = None) -> list[tuple[int, str]]:
    """(pid, command line) of every live process of hrc_ros's commands whose environment says
    ROS_DOMAIN_ID=`domain`, and, given `run`, HRC_TEST_RUN=`run` (one test run's, never
    another run's that happens to share the domain), and, given `worker`,
    PYTEST_XDIST_WORKER=`worker` (this worker's, never another worker's that started a process
    in a domain of its own choosing, test_bag's), but those in `exclude`."""
    wanted = f'ROS_DOMAIN_ID={domain}'.encode()
    of_run = None if run is None else f'{RUN_VARIABLE}={run}'.encode()
    of_worker = None if worker is None else f'PYTEST_XDIST_WORKER={worker}'.encode()
    found = []
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit() or int(entry.name) in exclude:
            continue
        try:
            environ = (entry / 'environ').read_bytes().split(b'\0')
            argv = (entry / 'cmdline').read_bytes().decode(errors='replace').split('\0')
        except OSError:           # gone, or not ours to read
            continue
        if wanted in environ and (of_run is None or of_run in environ) \
                and (of_worker is None or of_worker in environ) \
                and is_ours([a for a in argv if a]):
            found.append((int(entry.name), ' '.join(a for a in argv if a)))
    return found


def left_behind(domain: int, grace: float, exclude: set[int], run: str | None = None,
                worker: str | None = None) -> list[tuple[int, str]]:
    """`graph_processes` still there after `grace` seconds (a stop in progress may finish);
    the ones found are killed (SIGKILL) and returned."""
    deadline = time.monotonic() + grace
    left = graph_processes(domain, exclude, run, worker)
    while left and time.monotonic() < deadline:
        time.sleep(0.1)
        left = graph_processes(domain, exclude, run, worker)
    for pid, _ in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    return left
