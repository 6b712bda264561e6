"""Parallel numba kernels that share the machine: each call runs serial or parallel, whichever
is faster on the machine as it is now (every parallel kernel of core/ goes through here).

Why. A numba ``parallel=True`` kernel splits each ``prange`` loop into one equal chunk per
thread (numba's gufunc scheduler, then OpenMP's static ``omp for``; the workqueue layer does the
same) and waits at the end of the loop for every chunk. When another process holds one of the
two cores, one of our threads is descheduled for a time slice (milliseconds) at some barrier,
and the loop waits for it, while the OpenMP thread that finished spins. With one busy process
beside it `hrc-solve` took 17-24 s instead of 2.6 s (3.6 s with one thread): the sweep has ten
barriers in 4 ms. No chunk size helps a chunk already taken by a descheduled thread, and TBB
is not installed. What does hold is measuring: the same kernel compiled without
``parallel`` (`numba.njit` reads ``prange`` as ``range``; it is also faster than the parallel
build on one thread, which loses vectorisation in numba's gufunc lowering) is never held up by
another thread, so each call runs the variant that has been faster lately.

How (`ParallelKernel`, mode ``auto``): each kernel is compiled twice, parallel and serial, from
one Python function (`parallel_kernel`). A call times itself (``time.perf_counter``) and keeps
the seconds per unit of `work` (the caller's size of the call, e.g. points backed up) of the
last `WINDOW` calls of each variant; it runs the variant whose median is lower. The other is
re-probed once the calls since its last run took `PROBE_RATIO` times its own expected cost, so
probing costs at most about 1 / PROBE_RATIO of the run time and a load that comes or goes is
seen within that. Before its first call each variant is compiled for the call's types (or
loaded from numba's cache) without running, so that loading is not counted as its cost.
A machine (or an affinity mask, or ``NUMBA_NUM_THREADS``) with one core runs serial only.
Both variants compute each output element with the same operations in the same order (the
kernels' loops are independent per element and every reduction is in a fixed order), so the
results do not depend on the variant: the tests hold them equal.

Override: the environment variable ``HRC_KERNEL_THREADS`` = ``auto`` (default), ``serial``
(or ``1``: never parallel) or a number of threads N >= 2 (always parallel with N threads,
at most numba's pool, ``NUMBA_NUM_THREADS``); in code `set_mode` (the same values) or the
context manager `mode`. An unknown value is refused with a one-line error when the first
kernel runs. docs/DESIGN.md ("Parallel kernels on a shared machine") says the same for users;
bench/kernel_bench.py measures it.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
import types
from collections import deque

import numba

ENV = 'HRC_KERNEL_THREADS'
AUTO, SERIAL = 'auto', 'serial'
WINDOW = 3          # calls of each variant whose median decides
PROBE_RATIO = 20.0  # re-probe the other variant after this many times its expected cost

_lock = threading.Lock()
_override: str | int | None = None   # set_mode's value; None: the environment's
_limit: int | None = None            # limit_threads's value; None: no limit


def machine_threads() -> int:
    """Threads a parallel call can use: the cores this process may run on (its affinity mask),
    at most numba's pool (``NUMBA_NUM_THREADS``)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, min(cores, numba.config.NUMBA_NUM_THREADS, _limit or cores))


def limit_threads(threads: int | None) -> None:
    """At most `threads` threads for every kernel of this process (None: no limit), e.g. the
    CPUs a scheduler gave a task; the mode (auto, serial, N) stays, and one thread means
    serial. Sets numba's thread count to match: the kernels reset it on a parallel call, so
    `numba.set_num_threads` alone does not hold."""
    global _limit
    _limit = None if threads is None else max(1, int(threads))
    numba.set_num_threads(machine_threads())


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable), or None."""
    try:
        with open('/proc/meminfo') as meminfo:
            for line in meminfo:
                if line.startswith('MemAvailable:'):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


class KernelSettingError(ValueError):
    """``HRC_KERNEL_THREADS`` (or a `set_mode` value) is not one this module accepts."""


def descendants(pid: int) -> set[int]:
    """Every live process below pid (children, their children, ...), read from /proc; empty
    where /proc is missing. For measuring what a pool of workers holds (memory, stray
    processes)."""
    from pathlib import Path
    children: dict[int, set[int]] = {}
    try:
        entries = list(Path('/proc').iterdir())
    except OSError:
        return set()
    for entry in entries:
        if entry.name.isdigit():
            try:
                ppid = int((entry / 'stat').read_text().rsplit(')', 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, set()).add(int(entry.name))
    out, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), ()):
            if child not in out:
                out.add(child)
                todo.append(child)
    return out


def parse_mode(value) -> str | int:
    """`AUTO`, `SERIAL` or a thread count >= 2 from a `set_mode` / ``HRC_KERNEL_THREADS``
    value; KernelSettingError (a ValueError) saying what is accepted."""
    text = str(value).strip().lower()
    if text in ('', AUTO):
        return AUTO
    if text in (SERIAL, '1'):
        return SERIAL
    if text.isdigit() and int(text) >= 2:
        return int(text)
    raise KernelSettingError(f'{ENV} (or parallel.set_mode) must be auto, serial or a number of '
                     f'threads >= 1, got {value!r}')


_parsed: dict = {}


def current_mode() -> str | int:
    """The mode in force: `set_mode`'s, else ``HRC_KERNEL_THREADS``'s, else auto."""
    if _override is not None:
        return _override
    text = os.environ.get(ENV, AUTO)
    if text not in _parsed:
        _parsed[text] = parse_mode(text)
    return _parsed[text]


def set_mode(value) -> None:
    """Set the mode for every kernel of this process (None: back to the environment's)."""
    global _override
    _override = None if value is None else parse_mode(value)


@contextlib.contextmanager
def mode(value):
    """``with parallel.mode('serial'): ...``: the mode for the block, then the previous one."""
    global _override
    previous = _override
    set_mode(value)
    try:
        yield
    finally:
        _override = previous


class ParallelKernel:
    """A kernel with a parallel and a serial variant of one function; calling it runs one of
    them (module docstring) and returns what it returns."""

    def __init__(self, name: str, parallel, serial, clock=time.perf_counter):
        self.name = name
        self.parallel = parallel
        self.serial = serial
        self.clock = clock
        self.reset()

    def reset(self) -> None:
        """Forget the timings (the next calls warm up and measure both variants again)."""
        self._seconds = {SERIAL: deque(maxlen=WINDOW), 'parallel': deque(maxlen=WINDOW)}
        self._warm = {SERIAL: False, 'parallel': False}
        self._since = {SERIAL: 0.0, 'parallel': 0.0}   # run time since the variant last ran
        self.calls = {SERIAL: 0, 'parallel': 0}

    def _expected(self, variant: str) -> float:
        """The median of the variant's last WINDOW timings (the upper one of an even count)."""
        values = sorted(self._seconds[variant])
        return values[len(values) // 2]

    def choose(self, work: float) -> str:
        """The variant the next call of size `work` runs under the current mode."""
        wanted = current_mode()
        if wanted == SERIAL or machine_threads() == 1:
            return SERIAL
        if wanted != AUTO:
            return 'parallel'
        for variant in (SERIAL, 'parallel'):        # time each once, serial first
            if not self._seconds[variant]:
                return variant
        best, other = sorted((SERIAL, 'parallel'), key=self._expected)
        if self._since[other] >= PROBE_RATIO * self._expected(other) * work:
            return other
        return best

    def __call__(self, *args, work: float = 1.0):
        work = max(float(work), 1e-12)
        variant = self.choose(work)
        if variant == 'parallel':
            wanted = current_mode()
            threads = machine_threads() if wanted == AUTO else min(wanted, machine_threads())
            if numba.get_num_threads() != threads:
                numba.set_num_threads(threads)
            kernel = self.parallel
        else:
            kernel = self.serial
        if not self._warm[variant]:
            _load(kernel, args)
            self._warm[variant] = True
        start = self.clock()
        out = kernel(*args)
        seconds = self.clock() - start
        with _lock:
            self.calls[variant] += 1
            self._seconds[variant].append(seconds / work)
            self._since[variant] = 0.0
            for other in self._since:
                if other != variant:
                    self._since[other] += seconds
        return out

    def stats(self) -> dict:
        """Calls per variant and the current seconds per unit of work (for benchmarks)."""
        return {'calls': dict(self.calls),
                'seconds_per_work': {v: (self._expected(v) if s else None)
                                     for v, s in self._seconds.items()}}


def _load(kernel, args) -> None:
    """Compile `kernel` for the types of `args`, or load it from numba's cache, without
    running it, so that its first timed call is a call like the others."""
    compile_ = getattr(kernel, 'compile', None)
    if compile_ is None:        # not a numba dispatcher (the tests' stand-ins)
        return
    try:
        compile_(tuple(numba.typeof(a) for a in args))
    except Exception:           # a type numba.typeof reads otherwise: the call compiles it
        pass


def _renamed(fn, suffix: str):
    """A copy of `fn` under another qualified name: numba's cache keys its files by the name
    and not by the compile options, so the two variants need two names."""
    copy = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + suffix,
                              fn.__defaults__, fn.__closure__)
    copy.__qualname__ = fn.__qualname__ + suffix
    copy.__kwdefaults__ = fn.__kwdefaults__
    copy.__module__ = fn.__module__
    return copy


def parallel_kernel(fn, **options) -> ParallelKernel:
    """`fn` (plain Python with ``numba.prange`` loops) compiled twice with numba.njit's
    `options` (cache, nogil, fastmath, ...): with ``parallel=True`` and without."""
    kernel = ParallelKernel(f'{fn.__module__}.{fn.__qualname__.lstrip("_")}',
                            numba.njit(parallel=True, **options)(fn),
                            numba.njit(**options)(_renamed(fn, '_serial')))
    KERNELS.append(kernel)
    return kernel


KERNELS: list[ParallelKernel] = []   # every kernel made by parallel_kernel, for benchmarks
