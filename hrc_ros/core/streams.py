"""A standard output that outlives its reader (standard library only).

`hrc-fit ... | head -1`: `head` exits after its line and every later write to the pipe raises
BrokenPipeError. Unhandled, that ended the fit before it wrote its files (the work the user
ordered lost, for a report they had stopped reading), and `hrc-bag info | head` with a
traceback. Decision (docs/ROBUSTNESS.md): what a command prints is its report, its files are
its work; once nobody reads the report, the rest of it goes to /dev/null and the work goes on
to its normal end and exit status. `outliving_stdout()` arranges that for the duration of a
command: the console scripts of `tools.common.command` and `ros.entry` run inside it.
"""

from __future__ import annotations

import contextlib
import os
import sys


class OutlivingStdout:
    """`stream` with writes and flushes that, once its reader has gone (BrokenPipeError),
    point its file descriptor at /dev/null and carry on: the interpreter's last flush too."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._drop()
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._drop()

    def _drop(self) -> None:
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
        except OSError:
            return
        try:
            os.dup2(devnull, self._stream.fileno())
        except (OSError, ValueError):   # no descriptor (a test's capture): writes still fail
            pass
        finally:
            os.close(devnull)

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def outliving_stdout():
    """sys.stdout as an `OutlivingStdout` while the block runs (not wrapped twice)."""
    before = sys.stdout
    if before is None or isinstance(before, OutlivingStdout):
        yield
        return
    sys.stdout = OutlivingStdout(before)
    try:
        yield
    finally:
        try:
            sys.stdout.flush()
        finally:
            sys.stdout = before
