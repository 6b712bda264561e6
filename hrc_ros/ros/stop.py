"""How every process of the suite stops: the nodes, `hrc-bag` and `hrc-case-study`'s observer.

Why one regime. rclpy's default signal handling shuts every context down from a thread of its
own, while Python's KeyboardInterrupt lands at whatever bytecode the main thread is running:
inside a conversion in `take_message`, between `Context.ok()` and `shutdown()`, inside a
`with handle:` block whose use count then never drops, in a `Future.__del__`. Each landing
spot was a different symptom (exit 1 with an RCLError, a node hung in `destroy_node` until it
was killed, "Exception ignored in Future.__del__"). The regime below removes the class: no
signal interrupts anything, and nothing but the main thread ever shuts a context down.

1. The console scripts enter through `entry.py`, which calls `install()` before it imports
   rclpy, numpy or the node's module (about a second of imports, several on a loaded
   machine): a stop signal during the imports ends the process at once with 0 (`importing`),
   since nothing exists yet to tear down.
2. SIGINT and SIGTERM only record the signal (`requested()`). A helper thread reads the
   interpreter's signal wake-up pipe and calls the registered wakers (the node's spin loop
   registers a guard condition), so a loop blocked in `rcl_wait` wakes at once; the Python
   handler itself only runs once the main thread is back in Python.
3. rclpy is initialised with `SignalHandlerOptions.NO` (`init_options()`): rclpy installs no
   handler and no thread of its own shuts the context down.
4. The spin loop checks `requested()`; then the process destroys its nodes and executor while
   the context is still valid, and only then calls `rclpy.try_shutdown()`.
5. A second stop signal forces the exit: the `on_force` hooks run (hrc-case-study kills its
   node processes), one line goes to stderr, and the process ends with `os._exit(FORCED_EXIT)`
   (3), whatever the main thread is doing, as long as some thread can take the interpreter
   lock (the helper thread does it too, for a main thread waiting in C++).
6. Once the command's `main()` has returned (its node destroyed, its context shut down, which
   flushes and closes the ROS log file; its bag closed), `entry` ends the process with
   `leave(code)`: the atexit hooks, Python's logging and the standard streams are flushed, then
   `os._exit(code)`. What it skips is the interpreter's finalization: the teardown of every
   module and the final garbage collection of the ROS, numpy and numba objects, ~1.8 s of CPU
   under load in native stacks (issue 37), with the signal handlers already reset to the
   default, so that `ros2 launch`'s SIGTERM after its 5 s grace killed a node there (exit -15)
   after it had stopped cleanly. Nothing is lost: everything the process writes is written and
   closed before `main()` returns, and a command that left work in a thread of its own must
   join it first.

7. A node started by `processes.NodeProcesses` (hrc-case-study, the benches) is told its
   launcher's pid (`PARENT_ENV`). If the launcher dies without stopping it (SIGKILL, a crash:
   its own stop never runs), the node sees its parent change (polled every `ORPHAN_POLL` s by
   a daemon thread) and stops itself the clean way, as if it had got SIGINT: before, it ran on
   as an orphan, its motion and its topics with it. Under `ros2 launch` (no variable) nothing
   is watched: launch's own shutdown covers its children.

Exit codes: 0 for a stop by signal (also during start-up, before the node exists), 1 for a
node that cannot start, FORCED_EXIT for a second signal. What this cannot cover is the first
~50 ms after exec, before the interpreter has run a line of the script (twice that when the ROS
wheels' bootstrapper re-executes the interpreter): a signal then ends the process the default
way. `processes.NodeProcesses` starts its nodes with SIGINT and SIGTERM blocked, so such a
signal stays pending until `install()` unblocks it and is then a clean stop too.

This module imports only the standard library: it must be cheap before the heavy imports.
"""

from __future__ import annotations

import atexit
import os
import select
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator, NoReturn

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
FORCED_EXIT = 3      # exit code of a process whose stop a second signal forced
PARENT_ENV = 'HRC_PARENT_PID'   # the launcher's pid, set by processes.NodeProcesses (point 7)
ORPHAN_POLL = 0.5    # s between the orphan watch's looks at the parent pid


class _Regime:
    """The process's stop state; one instance, `_regime`, touched only through the functions
    below. The signal handler only appends to `signals` (atomic under the GIL): it never takes
    a lock, since it may run in the main thread while that thread holds one."""

    def __init__(self):
        self.signals: list[int] = []
        self.lock = threading.Lock()
        self.wakers: list[Callable[[], None]] = []
        self.force_hooks: list[Callable[[], None]] = []
        self.installed = False
        self.exit_at_once = False       # nothing exists yet to tear down (`importing`)
        self.previous: dict = {}
        self.previous_wakeup_fd = -1
        self.pipe: tuple[int, int] | None = None
        self.reader: threading.Thread | None = None


_regime = _Regime()


def install() -> bool:
    """Make SIGINT and SIGTERM stop requests for this process; True if this call did it
    (False: already installed). Must run in the main thread. Also unblocks the two signals,
    so one that arrived while they were blocked (see `NodeProcesses`) is taken now."""
    if _regime.installed:
        return False
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError('stop.install() must run in the main thread')
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    _regime.signals.clear()
    _regime.pipe = (read_end, write_end)
    _regime.previous_wakeup_fd = signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)
    for signum in STOP_SIGNALS:
        _regime.previous[signum] = signal.signal(signum, _on_signal)
    _regime.reader = threading.Thread(target=_read_wakeups, args=(read_end,),
                                      name='stop signals', daemon=True)
    _regime.reader.start()
    _regime.installed = True
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    _watch_parent()
    return True


def _watch_parent() -> None:
    """Point 7 of the module docstring: when `PARENT_ENV` names this process's parent, a
    daemon thread sends this process SIGINT once the parent is gone. The variable is taken out
    of the environment (a process this one starts has another parent); a parent that is gone
    already at the start stops the process at once."""
    value = os.environ.pop(PARENT_ENV, None)
    try:
        parent = int(value)
    except (TypeError, ValueError):
        return
    if parent <= 1:
        return
    if os.getppid() != parent:
        try:
            os.kill(parent, 0)
            return          # alive: not our parent (a grandchild that inherited the variable)
        except ProcessLookupError:
            pass            # gone during the imports: the watch below stops this at once
        except OSError:
            return

    def watch():
        while os.getppid() == parent:
            time.sleep(ORPHAN_POLL)
        print(f'the launching process {parent} is gone: stopping', file=sys.stderr, flush=True)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=watch, name='orphan watch', daemon=True).start()


def uninstall() -> None:
    """Give the signals back to their previous handlers and forget any request (for a caller
    that installed the regime in a process that goes on, such as a test)."""
    if not _regime.installed:
        return
    for signum, handler in _regime.previous.items():
        signal.signal(signum, handler)
    signal.set_wakeup_fd(_regime.previous_wakeup_fd)
    read_end, write_end = _regime.pipe
    os.close(write_end)                 # the reader sees the end of the pipe and returns
    _regime.reader.join(timeout=5.0)
    os.close(read_end)
    _regime.previous.clear()
    _regime.signals.clear()
    with _regime.lock:
        _regime.wakers.clear()
        _regime.force_hooks.clear()
    _regime.pipe = _regime.reader = None
    _regime.installed = False


@contextmanager
def regime() -> Iterator[None]:
    """`install()` for the duration of a command's main(), and `uninstall()` after it if this
    call installed it (a main() called inside a process that goes on, such as a test)."""
    owned = install()
    try:
        yield
    finally:
        if owned:
            uninstall()


@contextmanager
def importing() -> Iterator[None]:
    """While the command's modules import, a stop signal ends the process at once with 0:
    nothing exists yet to tear down (no context, no file written), and on a loaded machine
    the imports take seconds, past ros2 launch's 5 s before it escalates to SIGTERM."""
    _regime.exit_at_once = True
    try:
        if requested():
            os._exit(0)
        yield
    finally:
        _regime.exit_at_once = False


def requested() -> bool:
    """A stop signal was received."""
    return bool(_regime.signals)


def signal_name() -> str:
    """The first stop signal received ('' if none), e.g. 'SIGINT'."""
    return signal.Signals(_regime.signals[0]).name if _regime.signals else ''


def add_waker(wake: Callable[[], None]) -> None:
    """Call `wake()` (from the helper thread) when a stop signal arrives."""
    with _regime.lock:
        _regime.wakers.append(wake)
    if requested():
        wake()


def remove_waker(wake: Callable[[], None]) -> None:
    """Forget `wake`; once this returns it is not called again (so its guard condition can
    be destroyed)."""
    with _regime.lock:
        if wake in _regime.wakers:
            _regime.wakers.remove(wake)


def on_force(hook: Callable[[], None]) -> None:
    """Run `hook()` before a forced exit (second signal), e.g. to kill child processes."""
    with _regime.lock:
        _regime.force_hooks.append(hook)


def init_options() -> dict:
    """The keyword arguments of every `rclpy.init` of the suite: rclpy installs no signal
    handler of its own (point 3 of the module docstring)."""
    from rclpy.signals import SignalHandlerOptions
    return {'signal_handler_options': SignalHandlerOptions.NO}


def _on_signal(signum, frame) -> None:
    _regime.signals.append(signum)
    if _regime.exit_at_once:
        os._exit(0)
    if len(_regime.signals) >= 2:
        force()


def _read_wakeups(read_end: int) -> None:
    """The helper thread: one byte per signal the interpreter caught arrives on the pipe."""
    seen = 0
    while True:
        try:
            select.select([read_end], [], [])
            data = os.read(read_end, 64)
        except InterruptedError:
            continue
        except OSError:
            return
        if not data:
            return
        stops = sum(byte in STOP_SIGNALS for byte in data)
        if not stops:
            continue
        seen += stops
        if _regime.exit_at_once:        # the imports hold the main thread in C for a while
            os._exit(0)
        with _regime.lock:      # held while waking: `remove_waker` returns after, never during
            for wake in _regime.wakers:
                try:
                    wake()
                except Exception:  # noqa: BLE001 - the flag is set whatever a waker does
                    pass
        if seen >= 2:
            force()


def leave(code: int | None) -> NoReturn:
    """End the process with `code` (None: 0) now that the command's own stop is done (point 6
    of the module docstring): the atexit hooks, Python's logging and the standard streams
    flushed, then `os._exit`, skipping the interpreter's finalization."""
    if code is None:
        code = 0
    elif not isinstance(code, int):      # what sys.exit would do with it
        print(code, file=sys.stderr)
        code = 1
    try:
        atexit._run_exitfuncs()
    except Exception:  # noqa: BLE001 - exiting anyway; the hooks print their own errors
        pass
    logging = sys.modules.get('logging')
    if logging is not None:
        logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass
    os._exit(code)


def force() -> None:
    """The forced exit: the hooks, one line on stderr, os._exit(FORCED_EXIT)."""
    with _regime.lock:
        hooks = list(_regime.force_hooks)
    for hook in hooks:
        try:
            hook()
        except Exception:  # noqa: BLE001 - exiting anyway
            pass
    try:
        name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else 'python'
        os.write(2, f'{name}: second stop signal: exiting at once ({FORCED_EXIT})\n'.encode())
    except OSError:
        pass
    os._exit(FORCED_EXIT)
