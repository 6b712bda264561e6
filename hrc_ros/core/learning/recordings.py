"""Recorded runs of the cell as per-epoch records: what `hrc-fit` (core.learning.fit) learns from.

A record of epoch k is what the robot saw and did, never the hidden emotions:

    x_k = (tp, tc, tx, ty, hp, hc, bp, bc) and d_k    the observable state at the epoch's start
    O_k                                               the velocity level observed (0: none)
    a_k                                               the action taken (after the fail-safe)
    accepted_k                                        1 / 0 for an answered request, -1: none

Two sources give the same `Recording` (one per episode):

Trajectory CSV (`read_csv`; docs/LEARNING.md): one row per epoch with the columns `epoch`, `tp
tc tx ty hp hc bp bc d` (x_k), `O` (1..3; empty or 0 when the epoch had no observation),
`action` (a name, `nw` .. `dn`) and `accepted` (1 or 0, empty when a_k was not an answered
request; `true` / `false` are read too), and optionally `episode` (any text; without it the
file is one episode), and optionally `queued` (the tasks released and waiting behind the
current one at the epoch's start, MODEL.md 8.1; empty where unknown). Every other column is
ignored, in particular `em`, `ea` and the belief columns that `hrc-simulate` and
`hrc-case-study` write: real data has no hidden state. A missing column, an unreadable or
out-of-range value or epochs going backwards within an episode stop the reading with one line
naming the file, the line and what is wrong (`RecordingError`).

Bags (`read_bag_recording`): the topics `hrc/epoch`, `hrc/task_state`, `hrc/distance_level`,
`hrc/observation`, `hrc/action` and, if present, `hrc/human_response` of one cell (a namespace;
the only one in the bag unless named). Messages are decoded from the schemas stored in the bag
(mcap_ros2, no ROS needed) and placed in epochs the way the nodes and `hrc-case-study` do
(`place_in_epochs`): a message belongs to the last epoch whose `hrc/epoch` signal was published
before it, by the writers' source timestamps. The epoch signals follow the nodes' rule
(`protocol.EpochFollower`, by count and time: a bag keeps no writer sequence numbers): a new
count after the source fell silent (a restart) begins a new episode, a stray epoch that does
not continue the count is left out and reported. Of each epoch's task state, distance level,
observation and action the first one counts; the answer to a request is the latest
`hrc/human_response` published after the action in its window (the task manager's rule,
docs/DESIGN.md). The task state's optional ninth value, `queued` (a task manager with a queue,
MODEL.md 8.1), is kept as `Recording.queued`. A message that cannot be read (CDR bytes its
schema does not decode, a value out of range) is reported and left out (`Recording.issues`),
the rest of the bag is read; an epoch left without its task state or action goes too, reported.
A bag without one of the needed topics is refused.
"""

from __future__ import annotations

import bisect
import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..model import ACTIONS, DISTANCE_LEVELS, OBSERVATION_LEVELS, TASK_VARIABLES, action_index
from ..paths import input_stat, read_text
from ..protocol import EpochFollower, InputError, Stamp
from ..quoting import QUOTE_LIMIT, cap, quote

COLUMNS = ('epoch',) + TASK_VARIABLES + ('d', 'O', 'action', 'accepted')
OPTIONAL_COLUMNS = ('episode', 'queued')
NO_OBSERVATION = 0
UNANSWERED = -1
UNKNOWN_DISTANCE = -1
UNKNOWN_QUEUED = -1
MAX_QUEUED = 255        # the task state's ninth value is capped there (ros/conversions.py)
BAG_TOPICS = ('hrc/epoch', 'hrc/task_state', 'hrc/distance_level', 'hrc/observation',
              'hrc/action')
OPTIONAL_BAG_TOPICS = ('hrc/human_response',)
_TRUE = ('1', 'true', 'True', 'TRUE')
_FALSE = ('0', 'false', 'False', 'FALSE')


class RecordingError(ValueError):
    """A recording cannot be read; the one-line message names the file and what is wrong."""


@dataclass
class Recording:
    """One episode: per-epoch arrays of equal length T (see the module docstring).

    `task` is (T, 8) in TASK_VARIABLES order; `d` is -1 and `action` -1 where a bag had none
    for that epoch; `line` is the CSV line (or the epoch number for a bag) for reports.
    `queued` (T,) is the tasks waiting behind the current one at each epoch's start (MODEL.md
    8.1), -1 where an epoch's record has none; None when no epoch of the recording has it (a
    cell without a queue, a CSV without the column)."""

    source: str
    episode: str
    epoch: np.ndarray
    task: np.ndarray
    d: np.ndarray
    observation: np.ndarray
    action: np.ndarray
    accepted: np.ndarray
    line: np.ndarray
    issues: list = field(default_factory=list)
    queued: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.epoch.size)

    @property
    def name(self) -> str:
        return f'{self.source} episode {self.episode}'


def _recording(source: str, episode: str, rows: list, issues: list) -> Recording:
    """rows: (epoch, task (8), d, O, action, accepted, line[, queued or None]) tuples."""
    def column(i, dtype=np.int64):
        return np.array([r[i] for r in rows], dtype=dtype)
    task = np.array([r[1] for r in rows], dtype=np.int64).reshape(len(rows), len(TASK_VARIABLES))
    queued = [r[7] if len(r) > 7 else None for r in rows]
    kept = (None if all(v is None for v in queued) else
            np.array([UNKNOWN_QUEUED if v is None else v for v in queued], dtype=np.int64))
    return Recording(source, episode, column(0), task, column(2), column(3), column(4),
                     column(5), column(6), issues, kept)


# -- CSV --------------------------------------------------------------------------------------
def _integer(path, line: int, column: str, text: str, low: int, high: int) -> int:
    try:
        value = int(text.strip())
    except ValueError:
        raise RecordingError(f'{path}:{line}: column {column} must be an integer in '
                             f'{low}..{high}, got {quote(text)}') from None
    if not low <= value <= high:
        raise RecordingError(f'{path}:{line}: column {column} = {value} is out of range '
                             f'{low}..{high}')
    return value


def _records(path, text: str):
    """(line, fields) of every record of a CSV text but blank lines; `line` is the file line
    the record starts on, from csv's line_num, so blank lines and quoted fields that span lines
    are counted."""
    reader = csv.reader(io.StringIO(text, newline=''))
    while True:
        line = reader.line_num + 1
        try:
            fields = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise RecordingError(f'{path}:{line}: not a CSV record ({cap(exc)})') from None
        if fields:
            yield line, fields


def read_csv(path, rho: int, sigma: int) -> list[Recording]:
    """The episodes of a trajectory CSV file (format in the module docstring)."""
    path = Path(path)
    records = _records(path, read_text(path, RecordingError, 'CSV', kind='csv'))
    _, header = next(records, (None, []))
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise RecordingError(f'{path}: missing column{"s" if len(missing) > 1 else ""} '
                             f'{", ".join(missing)} (a trajectory CSV needs '
                             f'{", ".join(COLUMNS)})')
    tops = {'tp': rho, 'tc': sigma, 'tx': 3, 'ty': 3, 'hp': rho, 'hc': sigma, 'bp': rho,
            'bc': sigma}
    episodes: dict[str, list] = {}
    for line, fields in records:
        row = dict(zip(header, fields))
        if len(fields) > len(header) or any(c not in row for c in COLUMNS):
            raise RecordingError(f'{path}:{line}: the row has {len(header)} columns in the '
                                 'header but not in this line')
        episode = row['episode'].strip() if 'episode' in row and row['episode'] else '1'
        epoch = _integer(path, line, 'epoch', row['epoch'], 1, 2 ** 31)
        task = tuple(_integer(path, line, n, row[n], 0, tops[n]) for n in TASK_VARIABLES)
        d = _integer(path, line, 'd', row['d'], DISTANCE_LEVELS[0], DISTANCE_LEVELS[-1])
        o_text = row['O'].strip()
        observation = (NO_OBSERVATION if o_text in ('', '0') else
                       _integer(path, line, 'O', o_text, OBSERVATION_LEVELS[0],
                                OBSERVATION_LEVELS[-1]))
        name = row['action'].strip()
        if name not in ACTIONS:
            raise RecordingError(f'{path}:{line}: column action = {quote(name)} is not one of '
                                 f'{" ".join(ACTIONS)}')
        answer = row['accepted'].strip()
        if answer == '':
            accepted = UNANSWERED
        elif answer in _TRUE or answer in _FALSE:
            accepted = int(answer in _TRUE)
        else:
            raise RecordingError(f'{path}:{line}: column accepted must be 1, 0 or empty, got '
                                 f'{quote(answer)}')
        queued = None
        if 'queued' in header and row['queued'].strip() != '':
            queued = _integer(path, line, 'queued', row['queued'], 0, 2 ** 31)
        rows = episodes.setdefault(episode, [])
        if rows and epoch <= rows[-1][0]:
            raise RecordingError(f'{path}:{line}: epochs out of order in episode '
                                 f'{cap(episode, QUOTE_LIMIT)}: epoch {epoch} after epoch '
                                 f'{rows[-1][0]}')
        rows.append((epoch, task, d, observation, action_index(name), accepted, line, queued))
    if not episodes:
        raise RecordingError(f'{path}: no rows (a trajectory CSV has one row per epoch)')
    return [_recording(str(path), episode, rows, []) for episode, rows in episodes.items()]


# -- bags -------------------------------------------------------------------------------------
def place_in_epochs(signals: list, events: list) -> dict:
    """(topic, k) -> the values of `topic` in epoch k's window, in publication order.

    `signals`: (published_ns, k) of the epoch signals taken; `events`: (topic, value,
    published_ns). A message belongs to the last epoch whose signal was published before it
    (epoch 0: before the first signal). Source timestamps follow the causal order on one host,
    whatever order the messages reached a recorder in (docs/DESIGN.md)."""
    signals = sorted(signals)
    times = [t for t, _ in signals]
    placed: dict = {}
    for topic, value, t in sorted(events, key=lambda e: e[2]):
        i = bisect.bisect_right(times, t)
        k = signals[i - 1][1] if i else 0
        placed.setdefault((topic, k), []).append((t, value))
    return placed


def _bag_topics(path, topic_names, namespace: str | None) -> str:
    """The namespace prefix ('' or '/cell1') whose hrc topics the bag holds."""
    def prefix_of(topic: str, suffix: str):
        if topic.lstrip('/') == suffix:
            return ''
        return topic[:-len(suffix) - 1] if topic.endswith('/' + suffix) else None
    prefixes = {prefix_of(t, 'hrc/epoch') for t in topic_names} - {None}
    if namespace is not None:
        wanted = '/' + namespace.strip('/') if namespace.strip('/') else ''
        if wanted not in prefixes:
            raise RecordingError(f'{path}: no hrc/epoch topic in namespace {quote(namespace)} '
                                 f'(the bag has {_topic_list(topic_names)})')
        prefixes = {wanted}
    if not prefixes:
        raise RecordingError(f'{path}: the bag has no hrc/epoch topic (needed: '
                             f'{", ".join(BAG_TOPICS)})')
    if len(prefixes) > 1:
        raise RecordingError(f'{path}: the bag holds several cells ({_topic_list(prefixes)})'
                             ': name one with --namespace')
    prefix = prefixes.pop()
    missing = [s for s in BAG_TOPICS if f'{prefix}/{s}' not in topic_names
               and not (prefix == '' and s in topic_names)]
    if missing:
        raise RecordingError(f'{path}: the bag has no {", ".join(missing)} topic (needed: '
                             f'{", ".join(BAG_TOPICS)})')
    return prefix


def _topic_list(names) -> str:
    """Topic names (or namespaces) of a bag for an error: capped, however many and long."""
    return cap(', '.join(sorted(names)), 4 * QUOTE_LIMIT) or 'no topics'


def _decoders(rho: int, sigma: int) -> dict:
    """Suffix -> decoded message -> value (ValueError when the content is out of range)."""
    def level(values):
        def read(msg):
            v = int(msg.data)
            if v not in values:
                raise ValueError(f'{v} is not in {tuple(values)}')
            return v
        return read

    def task_state(msg):
        values = [int(v) for v in bytes(msg.data)] if isinstance(msg.data, (bytes, bytearray)) \
            else [int(v) for v in msg.data]
        queued = None
        if len(values) == len(TASK_VARIABLES) + 1:
            queued = values.pop()       # `queued` (MODEL.md 8.1): the tasks waiting
        if len(values) != len(TASK_VARIABLES):
            raise ValueError(f'{len(values)} values, not the 8 {" ".join(TASK_VARIABLES)} '
                             '(and optionally queued)')
        tops = (rho, sigma, 3, 3, rho, sigma, rho, sigma)
        for name, v, top in zip(TASK_VARIABLES, values, tops):
            if not 0 <= v <= top:
                raise ValueError(f'{name} = {v} is out of range 0..{top}')
        return tuple(values), queued

    def action(msg):
        return action_index(str(msg.data))

    return {'hrc/epoch': lambda msg: int(msg.data), 'hrc/task_state': task_state,
            'hrc/distance_level': level(DISTANCE_LEVELS),
            'hrc/observation': level(OBSERVATION_LEVELS), 'hrc/action': action,
            'hrc/human_response': lambda msg: bool(msg.data)}


def read_bag_recording(path, rho: int, sigma: int, namespace: str | None = None
                       ) -> list[Recording]:
    """The episodes of a bag (a folder or a .mcap file; see the module docstring)."""
    from ..bagfile import BagError, bag_info, read_bag

    try:
        info = bag_info(path, verify=False)
    except BagError as exc:
        raise RecordingError(str(exc)) from None
    source = str(info.path)
    prefix = _bag_topics(source, {t.topic for t in info.topics}, namespace)
    decoders = _decoders(rho, sigma)
    topics = {f'{prefix}/{s}' if prefix else f'/{s}': s
              for s in BAG_TOPICS + OPTIONAL_BAG_TOPICS}
    topics.update({s: s for s in BAG_TOPICS + OPTIONAL_BAG_TOPICS} if not prefix else {})
    issues: list[str] = []
    signals: list = []
    events: list = []
    try:
        for message in read_bag(info.path, topics=[t for t in topics
                                                   if t in {i.topic for i in info.topics}],
                                decode=True):
            suffix = topics[message.topic]
            try:
                if message.decode_error:
                    raise ValueError(message.decode_error)
                value = decoders[suffix](message.decoded)
            except (ValueError, TypeError, AttributeError) as exc:
                issues.append(f'{source}: a {suffix} message published at '
                              f'{message.publish_time_ns} ns cannot be read ({cap(exc)}); left '
                              'out')
                continue
            if suffix == 'hrc/epoch':
                signals.append((message.publish_time_ns, value))
            else:
                events.append((suffix, value, message.publish_time_ns))
    except BagError as exc:
        raise RecordingError(str(exc)) from None
    if not signals:
        raise RecordingError(f'{source}: the bag has no hrc/epoch message, so no epoch can be '
                             'told apart')
    # The epoch signals as a follower takes them: a restart begins an episode. Each signal
    # taken opens a window, numbered from 1 in publication order (0: before the first).
    follower = EpochFollower()
    episodes: list[list] = []           # per episode: (window, k)
    windows: list = []                  # (published_ns, window)
    for t, k in sorted(signals):
        stamp = Stamp(t)           # a bag keeps no writer sequence: the count and the time rule
        try:
            restart = follower.check(k, stamp)
        except InputError as exc:
            issues.append(f'{source}: {cap(exc)}; that hrc/epoch signal is left out')
            continue
        follower.take(k, stamp)
        if restart is not None or not episodes:
            episodes.append([])
        episodes[-1].append((len(windows) + 1, k))
        windows.append((t, len(windows) + 1))
    placed = place_in_epochs(windows, events)
    recordings = []
    for number, epochs in enumerate(episodes, start=1):
        rows = [row for w, k in epochs
                if (row := _bag_row(source, placed, w, k, issues)) is not None]
        if rows:
            recordings.append(_recording(source, str(number), rows, issues))
    if not recordings:
        raise RecordingError(f'{source}: no epoch has a task state and an action')
    return recordings


def _bag_row(source: str, placed: dict, w: int, k: int, issues: list):
    """The record of window w (epoch k), or None when it lacks the task state or the action."""
    def first(topic):
        values = placed.get((topic, w))
        return values[0] if values else (None, None)
    _, state = first('hrc/task_state')
    task, queued = (None, None) if state is None else state
    action_t, action = first('hrc/action')
    if task is None or action is None:
        what = ' and '.join(n for n, v in (('task state', task), ('action', action))
                            if v is None)
        issues.append(f'{source}: epoch {k} has no {what}; the epoch is left out')
        return None
    _, d = first('hrc/distance_level')
    _, observation = first('hrc/observation')
    answers = [v for t, v in placed.get(('hrc/human_response', w), []) if t > action_t]
    accepted = UNANSWERED if not answers else int(answers[-1])
    return (k, task, UNKNOWN_DISTANCE if d is None else d,
            NO_OBSERVATION if observation is None else observation, action, accepted, k, queued)


def read_recordings(paths, rho: int, sigma: int, namespace: str | None = None
                    ) -> list[Recording]:
    """Every episode of the given CSV files, bag folders and .mcap files, in order."""
    out: list[Recording] = []
    for path in paths:
        path = Path(path)
        if path.suffix.lower() == '.csv':
            out += read_csv(path, rho, sigma)
        elif path.is_dir():
            out += read_bag_recording(path, rho, sigma, namespace)
        else:   # missing, a loop of links, a FIFO or a device: refused before it is opened
            input_stat(path, RecordingError, 'recording')
            if path.suffix.lower() != '.mcap':
                raise RecordingError(f'{path}: not a .csv file, a .mcap file or a bag folder')
            out += read_bag_recording(path, rho, sigma, namespace)
    return out
