"""The suite's time per test file, printed at the end of every run (the CI log), so that a file
whose time grows is seen in the next run and not when CI reaches its limit.

conftest.py feeds every test report (setup, call and teardown: a module fixture's start-up is
in its first test's setup, its stop in its last test's teardown) to `FileTimes.add` and prints
`FileTimes.table()` in pytest's terminal summary. Besides the wall time, the CPU time: the test
process's own and that of the child processes it waited for (node processes, commands), from
`getrusage` around each test (`cpu_now`), which says what a file costs whatever the load; with
pytest-xdist it is measured in the worker and travels in the teardown report's
user_properties (`CPU_PROPERTY`). With HRC_TEST_TIMES=PATH the same figures go
to PATH as JSON ({"wall": s, "collect": s, "files": {file: {"seconds": s, "tests": n}}});
bench/ci_bench.py reads them. A session-scoped fixture counts in the file that first uses it.
"""

from __future__ import annotations

import json
import resource
import time
from collections import Counter, defaultdict
from pathlib import Path


CPU_PROPERTY = 'hrc_cpu_seconds'


def cpu_now() -> float:
    """CPU seconds (user + system) of this process and of its children waited for."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class FileTimes:
    def __init__(self):
        self.started = time.monotonic()
        self.collected: float | None = None
        self.seconds: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.tests: Counter = Counter()

    def collection_done(self) -> None:
        self.collected = time.monotonic() - self.started

    def add(self, nodeid: str, when: str, duration: float, cpu: float = 0.0) -> None:
        name = nodeid.split('::', 1)[0]
        self.seconds[name] += duration
        self.cpu[name] += cpu
        if when == 'call':
            self.tests[name] += 1

    def figures(self) -> dict:
        return {'wall': time.monotonic() - self.started, 'collect': self.collected,
                'files': {name: {'seconds': round(seconds, 3), 'cpu': round(self.cpu[name], 3),
                                 'tests': self.tests[name]}
                          for name, seconds in self.seconds.items()}}

    def table(self) -> str:
        """The files, slowest first, with their share of the tests' total; the wall time and
        the collection (imports) last."""
        figures = self.figures()
        total = sum(self.seconds.values())
        lines = [f'{"seconds":>9} {"share":>6} {"cpu s":>8} {"tests":>6}  file']
        for name, seconds in sorted(self.seconds.items(), key=lambda item: -item[1]):
            share = 100.0 * seconds / total if total else 0.0
            lines.append(f'{seconds:9.1f} {share:5.1f}% {self.cpu[name]:8.1f} '
                         f'{self.tests[name]:6d}  {name}')
        collect = figures['collect']
        lines.append(f'{total:9.1f} {100.0 if total else 0.0:5.1f}% '
                     f'{sum(self.cpu.values()):8.1f} {sum(self.tests.values()):6d}  all files '
                     f'(wall {figures["wall"]:.1f} s'
                     + (f', collection {collect:.1f} s' if collect is not None else '') + ')')
        return '\n'.join(lines)

    def write(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.figures(), indent=1, sort_keys=True) + '\n')
