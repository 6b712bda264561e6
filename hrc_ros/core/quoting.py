"""Quoting what a user or a peer handed in, in an error, a log line or a diagnostic: capped.

A message field, a YAML value, a CSV field, a policy file's meta or a bag's topic name can be
megabytes long; quoted whole, one refusal becomes a megabyte log line, a parameter service
reason that `ros2 param set` prints page after page, or a diagnostic that floods the graph.
So every quote of such data goes through one of these two (docs/ROBUSTNESS.md):

- `quote(value)`: a value's repr, cut to `QUOTE_LIMIT` characters (a sequence to its first
  values) with its original size;
- `cap(text)`: a whole error text cut to `4 * QUOTE_LIMIT` characters with its length, for
  texts that carry quotes of their own (an exception's message, a traceback's last line).

The ROS ring (`hrc_ros.ros.conversions`) uses the same two for message content.
"""

from __future__ import annotations

import reprlib

import numpy as np

QUOTE_LIMIT = 200   # characters of user data quoted in an error (logs, diagnostics, reasons)


def _short_repr(limit: int) -> reprlib.Repr:
    """A repr that never builds more than about `limit` characters of any one part, however
    large or deep the value (a list of 1 MB strings, a dict nested 1,000 deep)."""
    short = reprlib.Repr()
    short.maxlevel = 4
    short.maxstring = short.maxother = short.maxlong = limit
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = short.maxarray = limit // 4
    return short


def quote(value, limit: int = QUOTE_LIMIT) -> str:
    """A value for an error text: its repr, cut to `limit` characters with the original size,
    so a 10 MB string or 20,000 NaNs never become a 10 MB log line."""
    shown = limit // 4                     # values shown of a sequence (each >= 3 characters)
    short = _short_repr(limit).repr
    if isinstance(value, np.ndarray):
        size, cut = f'{value.size} values', value.size > shown
        text = short(value.reshape(-1)[:shown].tolist())
    elif isinstance(value, (list, tuple)):
        size, cut, text = f'{len(value)} values', len(value) > shown, short(list(value[:shown]))
    elif isinstance(value, (str, bytes)):
        size, cut, text = f'{len(value)} characters', len(value) > limit, repr(value[:limit])
    elif isinstance(value, dict):
        size, cut, text = f'{len(value)} entries', len(value) > shown, short(value)
    else:
        text = short(value)
        size, cut = f'{len(text)} characters', False
    if len(text) <= limit and not cut:
        return text
    return f'{text[:limit]}... ({size})'


def cap(text, limit: int = 4 * QUOTE_LIMIT) -> str:
    """An error text cut to `limit` characters, with its original length."""
    text = str(text)
    return text if len(text) <= limit else f'{text[:limit]}... ({len(text)} characters)'
