"""Headless Chromium for the HMI's screenshots and browser tests: Debian's package, driven by
Playwright's Python API (`executable_path`); Playwright's own browser download is not used.

`FLAGS` are what a machine without a network and without a screen needs (no sandbox as root,
no GPU, no QUIC, no first-run, background networking, component updates or sync, which would
try to reach the internet). Playwright gives every `launch` a fresh, empty profile directory
of its own (it refuses a --user-data-dir flag), so nothing carries over between runs.
"""

from __future__ import annotations

import os
import shutil

CHROMIUM = '/usr/bin/chromium'
FLAGS = ('--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
         '--disable-background-networking', '--disable-component-update', '--disable-sync',
         '--disable-dev-shm-usage')
SIZES = {'phone': (390, 844), 'tablet': (1280, 800), 'desktop': (1440, 900)}


class BrowserError(RuntimeError):
    """No browser to drive; the text says what to install."""


def chromium_path(path: str | None = None) -> str:
    """The Chromium executable (`path`, $HRC_CHROMIUM, /usr/bin/chromium), or BrowserError."""
    path = path or os.environ.get('HRC_CHROMIUM') or CHROMIUM
    found = path if os.path.isfile(path) and os.access(path, os.X_OK) else shutil.which(path)
    if not found:
        raise BrowserError(f'no Chromium at {path}: install Debian\'s package (apt-get install '
                           'chromium) or pass its path')
    return found


def launch(playwright, executable: str | None = None):
    """A headless Chromium browser (Playwright `Browser`) with `FLAGS`."""
    try:
        import playwright as _  # noqa: F401
    except ImportError:
        raise BrowserError('playwright is not installed: pip install playwright') from None
    return playwright.chromium.launch(executable_path=chromium_path(executable), headless=True,
                                      args=list(FLAGS))
