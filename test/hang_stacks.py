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
"""

from __future__ import annotations

import faulthandler
import os
import shutil
import tempfile
from pathlib import Path

ENV = 'HRC_TEST_STACKS_DIR'
MARGIN = 2.0            # s before pytest-timeout ends the worker
LIMIT = 30_000          # characters of stacks at most in a report


def timeout_of(item) -> float:
    """The test's timeout in seconds as pytest-timeout takes it: its timeout marker's, else
    --timeout, PYTEST_TIMEOUT or the ini's (pytest_timeout.get_env_settings); 0: none."""
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

    def pytest_runtest_protocol(self, item, nextitem):
        if self.file is None:
            return None
        self.file.seek(0)
        self.file.truncate()
        seconds = timeout_of(item)
        if seconds > 0:
            faulthandler.dump_traceback_later(max(seconds - MARGIN, seconds / 2),
                                              file=self.file)
        return None

    def pytest_runtest_logfinish(self, nodeid, location):
        if self.file is not None:
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
                               f'test\'s timeout (faulthandler, {path.name}):\n'
                               f'{text[-LIMIT:]}')

    def pytest_unconfigure(self, config):
        if self.file is not None:
            faulthandler.cancel_dump_traceback_later()
            self.file.close()
        if self.created is not None:
            shutil.rmtree(self.created, ignore_errors=True)
            os.environ.pop(ENV, None)
