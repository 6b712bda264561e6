"""Who publishes on an input: the graph's publishers of a topic, named, and the epoch input.

rclpy (Jazzy) gives a message's writer sequence number and source timestamp, but no publisher
id, so the protocol machines tell writers apart by their sequence numbers
(`core.protocol.EpochFollower`, `StreamLock`); naming the writer is the graph's part, here.

`TopicPublishers` remembers the publishers of one topic by GID, as the graph shows them: a
publisher's endpoint is discovered before its node's name (the graph says
``_NODE_NAMESPACE_UNKNOWN_/_NODE_NAME_UNKNOWN_`` meanwhile), so a publisher is named by its node
only once the graph knows it, and by its GID until then. It is refreshed whenever a publisher
matches or leaves the node's subscription (the `matched` event) and before it names anyone, so
a short-lived publisher (`ros2 topic pub --once`, gone a fraction of a second after its
message) is still named: by its node while the graph knows it, afterwards by its GID and the
name last known. `followed` narrows down which publisher the follower follows: one of those
present each time it takes a message.

`subscribe_epochs` is every follower's `hrc/epoch` input: the conversion's refusals (an epoch
of 0) are noted by the `EpochFollower` too (`refused`: they can show a second writer), and
an epoch refused as another source's names the publishers other than the one followed, on
/diagnostics (WARN `<node>: epoch source`), at once for a publisher not named before and at
most once per `WARNING_THROTTLE_SEC` otherwise.

`EpochReady` is a listener's ready mark on `hrc/_epoch_ready` (`ready_topic`: beside the
resolved epoch topic; `core.protocol.EpochListeners`): the node that holds its `hrc/epoch`
readers and the GIDs of the reliable epoch writers they have matched, said again whenever they
change (a matched event, or the check every `READY_CHECK_SEC`), so that the decision node
starts its clock only once those readers have discovered the clock, not only once the clock
has discovered them. `subscribe_epochs` gives every follower one; the view and
`hrc-case-study`'s observer (its watcher and its bag recorder) make their own. A recorder that
says nothing (`ros2 bag record`) is not covered: `min_epoch_subscribers` counts it, from the
clock's side only.
"""

from __future__ import annotations

import time
from typing import Callable

from rclpy.clock import Clock, ClockType
from rclpy.qos import ReliabilityPolicy
from std_msgs.msg import String, UInt32

from ..core.protocol import (UNKNOWN_NODE_NAME, WARN, Endpoint, EpochFollower, InputError,
                             ReadyMark, Report, Stamp, ready_writers)
from . import conversions as conv
from . import qos

UNKNOWN_NODE_NAMESPACE = '_NODE_NAMESPACE_UNKNOWN_'
GID_BYTES = 16           # a Fast DDS GUID: 12 bytes of participant prefix, 4 of entity id
PUBLISHERS_KEPT = 32     # publishers remembered per topic, present or gone
NAMING_THROTTLE_SEC = 5.0
READY_NAME = '_epoch_ready'   # hidden: not recorded by a bag of every topic, not replayed
READY_CHECK_SEC = 0.25


def gid_text(gid) -> str:
    """An endpoint GID as hex (the GUID part: prefix and entity id)."""
    return ''.join(f'{b:02x}' for b in list(gid)[:GID_BYTES])


def endpoint_node(info) -> str | None:
    """The fully qualified node name of a graph endpoint; None while the graph does not know it
    (its endpoint discovered before its node's name)."""
    if not info.node_name or info.node_name == UNKNOWN_NODE_NAME \
            or info.node_namespace == UNKNOWN_NODE_NAMESPACE:
        return None
    return f'{info.node_namespace.rstrip("/")}/{info.node_name}'


def endpoints(node, topic: str, skip_own: bool = True) -> list[Endpoint]:
    """The publishers of `topic` as `Endpoint`s; with `skip_own`, one publisher of `node`'s own
    name is left out (its own: two nodes of one name are still told apart by count)."""
    me = node.get_fully_qualified_name()
    found, own = [], skip_own
    resolved = node.resolve_topic_name(topic)
    for info in node.get_publishers_info_by_topic(resolved):
        name = endpoint_node(info)
        if own and name == me:
            own = False
            continue
        found.append(Endpoint(resolved, name, gid_text(info.endpoint_gid)))
    return found


class TopicPublishers:
    """The publishers of one topic the graph has shown, by GID (module docstring)."""

    def __init__(self, node, topic: str):
        self.node = node
        self.topic = node.resolve_topic_name(topic)
        self.known: dict[str, dict] = {}        # gid -> {'node': name | None, 'present': bool}
        self.followed: set[str] | None = None   # the GIDs the followed writer may have

    def refresh(self, *_event) -> set[str]:
        """Read the graph; the GIDs present now."""
        present = set()
        for info in self.node.get_publishers_info_by_topic(self.topic):
            gid = gid_text(info.endpoint_gid)
            present.add(gid)
            entry = self.known.pop(gid, {'node': None})
            entry['node'] = endpoint_node(info) or entry['node']
            entry['present'] = True
            self.known[gid] = entry
        for gid, entry in self.known.items():
            entry['present'] = gid in present
        while len(self.known) > PUBLISHERS_KEPT:
            gone = next((g for g, e in self.known.items() if not e['present']),
                        next(iter(self.known)))
            del self.known[gone]
        return present

    def taken(self) -> None:
        """A message of the followed writer was taken: it is one of the publishers present."""
        present = self.refresh()
        narrowed = present if self.followed is None else self.followed & present
        self.followed = narrowed or present

    def new_line(self) -> None:
        """The follower follows a new writer: any present publisher may be it."""
        self.followed = None

    def names(self, others_only: bool = True) -> list[str]:
        """Each publisher known (refreshed first): its node once the graph names it, its GID,
        and whether it has left the graph; with `others_only`, not the followed writer (when
        it is known to be one publisher)."""
        self.refresh()
        followed = self.followed if self.followed is not None and len(self.followed) == 1 \
            else set()
        out = []
        for gid, entry in self.known.items():
            if others_only and gid in followed:
                continue
            who = entry['node'] or 'a node the graph does not name'
            gone = '' if entry['present'] else '; no longer on the graph'
            out.append(f'{who} (gid {gid}{gone})')
        return out


class _Naming:
    """When to name the other publishers: at once for a new set, else throttled."""

    def __init__(self):
        self.last: tuple[float, tuple] | None = None

    def due(self, names: list[str]) -> bool:
        now = time.monotonic()
        key = tuple(sorted(names))
        if self.last is not None and self.last[1] == key \
                and now - self.last[0] < NAMING_THROTTLE_SEC:
            return False
        self.last = (now, key)
        return True


def ready_topic(epoch_topic: str) -> str:
    """The ready marks' topic beside the resolved epoch topic (`/hrc/epoch` ->
    `/hrc/_epoch_ready`), so that a remapped or namespaced clock has its own."""
    return f'{epoch_topic.rsplit("/", 1)[0]}/{READY_NAME}'


class EpochReady:
    """A listener's ready mark for `hrc/epoch` (module docstring). `readers` are the node's
    readers of the topic (subscriptions, or callables giving one or None while it does not
    exist yet), held by `reader_node` (the node by default; the view's sampled inputs live on a
    helper node); `update` reads their matched counts and the graph and publishes the mark when
    it changes (`core.protocol.ready_writers`). A listener says it has matched nothing as soon
    as it starts: a restarted one replaces the mark its previous run left at the clock."""

    def __init__(self, node, reader_node=None, check_sec: float = READY_CHECK_SEC):
        self.node = node
        self.reader_node = reader_node or node
        self.topic = node.resolve_topic_name('hrc/epoch')
        self.readers: list = []
        self.publisher = node.create_publisher(String, ready_topic(self.topic), qos.LATCHED)
        self.said: ReadyMark | None = None
        self._say(frozenset())
        self.timer = node.create_timer(check_sec, self.update,
                                       clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _say(self, writers: frozenset[str]) -> None:
        mark = ReadyMark(self.reader_node.get_fully_qualified_name(), writers)
        if mark != self.said:
            self.publisher.publish(conv.epoch_ready_to_msg(mark))
            self.said = mark

    def update(self, *_event) -> None:
        # read each time, not skipped for unchanged counts: a writer replaced keeps them
        readers = [reader() if callable(reader) else reader for reader in self.readers]
        writers = {gid_text(info.endpoint_gid)
                   for info in self.node.get_publishers_info_by_topic(self.topic)
                   if info.qos_profile.reliability == ReliabilityPolicy.RELIABLE}
        said = ready_writers([None if r is None else r.get_publisher_count() for r in readers],
                             set(sorted(writers)[:conv.READY_WRITERS_MAX]))
        if said is not None:
            self._say(said)


def subscribe_epochs(inputs, follower: Callable[[], EpochFollower],
                     handle: Callable[[int, Stamp], None],
                     ready_mark: bool = True) -> TopicPublishers:
    """Subscribe `hrc/epoch` for a follower (module docstring): `handle(k, stamp)` feeds the
    follower's machine (which raises `InputError` for another source's epoch). With
    `ready_mark`, the follower says on `hrc/_epoch_ready` which epoch clocks its reader has
    matched (`EpochReady`)."""
    node = inputs.node
    publishers = TopicPublishers(node, 'hrc/epoch')
    ready = EpochReady(node) if ready_mark else None

    def on_matched(*event) -> None:
        publishers.refresh()
        if ready is not None:
            ready.update()
    naming = _Naming()

    def name_others(what: str) -> None:
        names = publishers.names()
        if names and naming.due(names):
            inputs.report(Report(
                WARN, 'epoch source', f'{what} came from another publisher than the epoch '
                f'source followed: hrc/epoch publishers {", ".join(names)}',
                {'publishers': ', '.join(names)}, kind='stray_epoch'))

    def on_epoch(msg, stamp: Stamp) -> None:
        epochs = follower()
        try:
            k = conv.epoch_from_msg(msg)
        except conv.MessageError:
            epochs.refused(stamp)
            if epochs.foreign_in_evidence(stamp.published_ns):
                name_others(f'a refused hrc/epoch {int(msg.data)}')
            raise
        ignored, lines = epochs.ignored, epochs.lines
        try:
            handle(k, stamp)
        except InputError:
            if epochs.ignored > ignored:
                name_others(f'hrc/epoch {k}')
            raise
        if epochs.lines != lines:
            publishers.new_line()
        publishers.taken()

    reader = inputs.subscribe(UInt32, 'hrc/epoch', qos.RELIABLE, lambda msg: msg, on_epoch,
                              with_stamp=True, on_matched=on_matched)
    if ready is not None:
        ready.readers.append(reader)
        ready.update()
    return publishers
