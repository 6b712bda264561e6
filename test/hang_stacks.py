"""A hang's stacks in the log when the test ran on a pytest-xdist worker.

pytest-timeout's thread method (pytest.ini) dumps every thread's stack and ends the process
with ``os._exit``. In a single process the dump reaches the terminal; on an xdist worker it
goes to the worker's own output, which the controller never shows, so CI read only "[gw1] node
down: Not properly terminated" and "worker 'gw1' crashed while running ...": a hang without
its stacks. This plugin arms faulthandler on each worker to write every thread's stack to a
file of that worker `MARGIN` seconds before the test's timeout (as pytest-timeout reads it:
the marker's, else --timeout, PYTEST_TIMEOUT or pytest.ini's), and the controller adds that
file to the report of a test whose worker crashed. The file is emptied as each test starts,
so what it holds is of the test that hung. Without xdist it does nothing (pytest-timeout's
own dump is in the log).

A hang that holds the GIL. pytest-timeout's timer is a Python thread: it needs the GIL to dump
and end the process. A worker stuck in native code that holds it never ends: on 2026-12-07 a
worker of a fresh clone's suite spun for over 30 minutes in Fast DDS 2.14 (the main thread in
`rcl_node_fini` -> `destroy_participant` -> `DomainParticipant::set_listener`, waiting on a
listener while the participant's async flow-controller thread looped, the livelock of
eProsima/Fast-DDS#6513 and ros2/rmw_fastrtps#666; it started when the garbage collector freed
a node whose construction had failed in test_nodes), and CI would have sat until its own limit.
faulthandler's watchdog is a C thread that needs no GIL, so on a worker it both writes the
stacks and ends the process (``exit=True``), `MARGIN` s before pytest-timeout would; in a
single process, where pytest-timeout's dump is the one the log shows, it ends the process
`BACKSTOP` s after the timeout in case pytest-timeout could not (not under a debugger, as
pytest-timeout). After a failed setup or call, when pytest and pytest-timeout stop their
timers, the watchdog is armed again for the teardown. Arming it replaces pytest's own
`faulthandler_timeout` dump, which this suite does not set.
"""

from __future__ import annotations

import faulthandler
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import pytest

ENV = 'HRC_TEST_STACKS_DIR'
MARGIN = 2.0            # s before pytest-timeout ends the worker
BACKSTOP = 10.0         # s after the timeout: a single process that pytest-timeout could not end
LIMIT = 30_000          # characters of stacks at most in a report


def timeout_of(item) -> float:
    """The test's timeout in seconds as pytest-timeout takes it: its timeout marker's, else
    --timeout, PYTEST_TIMEOUT or the ini's (pytest_timeout.get_env_settings); 0: none."""
    if not item.config.pluginmanager.has_plugin('timeout'):      # -p no:timeout: no limit
        return 0.0
    from pytest_timeout import get_env_settings
    marker = item.get_closest_marker('timeout')
    value = None
    if marker is not None:
        value = marker.args[0] if marker.args else marker.kwargs.get('timeout')
    if value is None:
        value = get_env_settings(item.config).timeout
    try:
        return max(float(value or 0), 0.0)
    except (TypeError, ValueError):
        return 0.0


class HangStacks:
    """Registered by conftest.py (and by test_layout's check of it)."""

    def __init__(self, config):
        self.file = None
        self.deadline = None        # monotonic time the watchdog ends this test's process
        self.created = None
        worker = getattr(config, 'workerinput', None)
        uses_workers = worker is not None or bool(getattr(config.option, 'numprocesses', 0))
        if worker is None and uses_workers:
            # the controller, before its workers start (they inherit the environment): a
            # folder of its own even when it inherited one, as a pytest run inside a test of
            # the suite does, whose worker gw0 would share the suite's gw0's file (CI,
            # 2026-12-06: the suite's gw0 emptied it as its next test started)
            self.created = os.environ[ENV] = tempfile.mkdtemp(prefix='hrc_test_stacks_')
        folder = os.environ.get(ENV)
        self.folder = Path(folder) if folder and uses_workers else None
        if worker is not None and self.folder is not None:
            self.file = open(self.folder / f'{worker["workerid"]}.txt', 'w')
        # the backstop's output: the real stderr (pytest_configure runs with pytest's capture
        # suspended; during a test fd 2 is pytest's capture file, lost when the process ends)
        self.stderr = None
        if self.file is None and self.folder is None:
            try:
                self.stderr = os.fdopen(os.dup(sys.__stderr__.fileno()), 'w')
            except (AttributeError, OSError, ValueError):
                pass

    def _arm(self, seconds: float) -> None:
        """faulthandler's watchdog: the stacks and the end of the process in `seconds`."""
        sink = self.file if self.file is not None else self.stderr
        if sink is not None and seconds > 0:
            faulthandler.dump_traceback_later(seconds, exit=True, file=sink)

    def pytest_runtest_protocol(self, item, nextitem):
        seconds = timeout_of(item)
        self.deadline = None
        if self.file is not None:
            self.file.seek(0)
            self.file.truncate()
            after = max(seconds - MARGIN, seconds / 2)
        else:                               # a single process: the backstop
            from pytest_timeout import is_debugging
            if is_debugging():              # pytest-timeout holds off under a debugger too
                return None
            after = seconds + BACKSTOP
        if seconds > 0 and (self.file is not None or self.stderr is not None):
            self.deadline = time.monotonic() + after
            self._arm(after)
        return None

    @pytest.hookimpl(trylast=True)
    def pytest_exception_interact(self, node, call, report):
        """A setup or a call that failed: pytest's faulthandler plugin and pytest-timeout
        both stop their timers then, so the watchdog is armed again for the time left, for
        the teardown (a node's destruction hung there, holding the GIL)."""
        if self.deadline is None or node.config.option.usepdb:
            return
        self._arm(max(self.deadline - time.monotonic(), 0.1))

    def pytest_runtest_logfinish(self, nodeid, location):
        self.deadline = None
        faulthandler.cancel_dump_traceback_later()

    def pytest_runtest_logreport(self, report):
        node = getattr(report, 'node', None)
        if (self.file is not None or self.folder is None or not report.failed
                or node is None or 'crashed while running' not in str(report.longrepr)):
            return
        path = self.folder / f'{node.gateway.id}.txt'
        text = path.read_text(errors='replace') if path.exists() else ''
        if text.strip():
            report.longrepr = (f'{report.longrepr}\n\nits threads {MARGIN:.0f} s before the '
                               f'test\'s timeout, when faulthandler ended the worker '
                               f'({path.name}):\n{text[-LIMIT:]}')

    def pytest_unconfigure(self, config):
        faulthandler.cancel_dump_traceback_later()
        for handle in (self.file, self.stderr):
            if handle is not None:
                handle.close()
        if self.created is not None:
            shutil.rmtree(self.created, ignore_errors=True)
            os.environ.pop(ENV, None)
