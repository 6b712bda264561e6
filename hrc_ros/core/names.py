"""What the command lines and the plant file take as a ROS namespace and as a list, checked
before any work starts (issue 37: `hrc-fit --namespace ///` was the root namespace,
`hrc-evaluate --selectors paper,,paper` and `hrc-fit --hold ,,,` were taken, and a plant cell's
namespace of 5,001 characters was accepted).

A namespace is ``/`` or ``/name/name...`` (each name a letter, then letters, digits or ``_``;
one leading slash optional, one trailing slash dropped; an empty name, ``//``, is refused),
at most `MAX_NAMESPACE` characters: ROS refuses a topic or service name longer than 247, and
the longest name a cell's node uses under its namespace, `LONGEST_CELL_NAME`, must still fit.
A list is comma-separated items, each stripped; an empty list, an empty item and an item given
twice are refused: each is a typo that would otherwise run something else than was asked.
"""

from __future__ import annotations

import re

from .quoting import quote

ROS_NAME_LIMIT = 247                 # rmw: a topic or service name's longest (255 - 8)
LONGEST_CELL_NAME = '/belief_estimator/set_parameters_atomically'
MAX_NAMESPACE = ROS_NAME_LIMIT - len(LONGEST_CELL_NAME)
_NAME = re.compile(r'[A-Za-z][A-Za-z0-9_]*')


class BadName(ValueError):
    """A namespace or a list the command cannot take; the text says why, in one line."""


def namespace(text: str, what: str = 'namespace') -> str:
    """`text` as a ROS namespace, '/' or '/a/b'; BadName for anything else."""
    if not isinstance(text, str):
        raise BadName(f'{what} must be a ROS namespace such as /line1, got {quote(text)}')
    if len(text) > MAX_NAMESPACE + 1:    # (one trailing slash is dropped below)
        raise BadName(too_long(what, len(text)))
    inner = text[1:] if text.startswith('/') else text
    inner = inner[:-1] if inner.endswith('/') else inner
    if inner == '':
        if text in ('/', ''):
            return '/'
        raise BadName(f'{what} {quote(text)} has an empty name between slashes; the root '
                         'namespace is /')
    names = inner.split('/')
    for name in names:
        if not _NAME.fullmatch(name):
            reason = ('an empty name between slashes' if name == '' else
                      f'the name {quote(name)}, which must start with a letter and hold only '
                      'letters, digits and _')
            raise BadName(f'{what} {quote(text)} has {reason}')
    shown = '/' + '/'.join(names)
    if len(shown) > MAX_NAMESPACE:
        raise BadName(too_long(what, len(shown)))
    return shown


def too_long(what: str, length: int) -> str:
    return (f'{what} has {length:,} characters; a namespace holds at most {MAX_NAMESPACE} '
            f'(ROS names end at {ROS_NAME_LIMIT}, and the cell adds up to '
            f'{len(LONGEST_CELL_NAME)})')


def items(text: str, what: str) -> tuple[str, ...]:
    """The comma-separated items of `text`, stripped; BadName for no item, an empty item
    (``a,,b``, a trailing comma) or an item given twice."""
    parts = [part.strip() for part in text.split(',')]
    if not any(parts):
        raise BadName(f'{what} names nothing ({quote(text)})')
    if '' in parts:
        raise BadName(f'{what} {quote(text)} has an empty item (two commas, or one at an '
                         'end)')
    twice = sorted({part for part in parts if parts.count(part) > 1})
    if twice:
        raise BadName(f'{what} {quote(text)} names {", ".join(twice)} twice')
    return tuple(parts)
