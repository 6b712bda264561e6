"""Bags on the ROS graph: record topics into, and play them from, rosbag2-compatible MCAP bags
(`hrc-bag record | play | info`).

The file format is `hrc_ros.core.bagfile` (ROS-free); this is its rclpy half: message classes
and CDR serialization, QoS profiles as rclpy objects, a `Recorder` on a node, `play`, and the
`hrc-bag` command line. Recording subscribes with rosbag2's adapted QoS (`qos_for_recording`)
and writes the publishers' offered profiles; playing publishes each topic with
`qos_from_offers` of what was recorded, as `ros2 bag play` does.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from ..core import bagfile
from ..core.paths import folder_target
from ..core.quoting import cap
from ..tools.common import Parser, bounded_float, bounded_int, path_text
from ..core.bagfile import (BagError, BagMessage, bag_info, duration_fields, duration_ns,
                            format_size, full_type_name, policy_name, read_bag, split_type_name)

INFINITE_NS = bagfile.INFINITE_NS


def qos_to_dict(profile: Any) -> dict:
    """An rclpy QoSProfile (or a mapping) as rosbag2 writes it, keys in rosbag2's order."""
    if isinstance(profile, Mapping):
        return bagfile.qos_dict(profile)
    from rclpy.qos import (
        QoSDurabilityPolicy,
        QoSHistoryPolicy,
        QoSLivelinessPolicy,
        QoSReliabilityPolicy,
    )
    return {
        'history': QoSHistoryPolicy(profile.history).short_key,
        'depth': int(profile.depth),
        'reliability': QoSReliabilityPolicy(profile.reliability).short_key,
        'durability': QoSDurabilityPolicy(profile.durability).short_key,
        'deadline': duration_fields(profile.deadline.nanoseconds),
        'lifespan': duration_fields(profile.lifespan.nanoseconds),
        'liveliness': QoSLivelinessPolicy(profile.liveliness).short_key,
        'liveliness_lease_duration': duration_fields(
            profile.liveliness_lease_duration.nanoseconds),
        'avoid_ros_namespace_conventions': bool(profile.avoid_ros_namespace_conventions),
    }


class BagWriter(bagfile.BagWriter):
    """`bagfile.BagWriter` that also takes rclpy messages and rclpy QoS profiles."""

    def add_topic(self, topic: str, type_name: str, qos: Any = None, *,
                  topic_type_hash: str | None = None) -> None:
        """``qos``: an rclpy QoSProfile or mapping, a list of them (one per recorded
        publisher), or None for reliable / volatile / keep last 10."""
        if qos is not None:
            qos = [qos_to_dict(p) for p in (qos if isinstance(qos, (list, tuple)) else [qos])]
        super().add_topic(topic, type_name, qos, topic_type_hash=topic_type_hash)

    def write(self, topic: str, message: Any, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Write one message (an rclpy message or its CDR bytes) received at ``log_time_ns``."""
        if not isinstance(message, (bytes, bytearray, memoryview)):
            expected = self.topic_type(topic)
            if type_name_of(message) != expected:
                raise BagError(f'a {type_name_of(message)} message cannot be written on '
                               f'{topic}, a {expected} topic')
            from rclpy.serialization import serialize_message
            message = serialize_message(message)
        super().write(topic, message, log_time_ns, publish_time_ns)


def message_class(type_name: str) -> type:
    """The rclpy message class of ``pkg/msg/Type`` (``pkg.msg.Type``)."""
    package, name = split_type_name(type_name)
    try:
        return getattr(importlib.import_module(f'{package}.msg'), name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f'message type {full_type_name(type_name)} is not installed '
                       f'(import {package}.msg.{name} failed: {exc})') from None


def type_name_of(message: Any) -> str:
    """``pkg/msg/Type`` of an rclpy message instance."""
    cls = type(message)
    return f'{cls.__module__.split(".")[0]}/msg/{cls.__name__}'


def deserialize(bag_message: 'BagMessage', message_type: type | None = None) -> Any:
    """The rclpy message of a `BagMessage` (its CDR bytes deserialized)."""
    from rclpy.serialization import deserialize_message
    cls = message_type or message_class(bag_message.type_name)
    try:
        return deserialize_message(bag_message.data, cls)
    except Exception as exc:  # noqa: BLE001 - rclpy raises several types for bad CDR
        raise BagError(f'cannot deserialize a {bag_message.type_name} message on '
                       f'{bag_message.topic} at {bag_message.log_time_ns} ns: {exc}') from None


def _duration_or_default(nanoseconds: int):
    from rclpy.duration import Duration
    if nanoseconds <= 0 or nanoseconds >= INFINITE_NS:
        return Duration()   # 0 = the rmw default, which DDS takes as infinite
    return Duration(nanoseconds=nanoseconds)


def qos_from_offers(profiles: Sequence[Mapping]) -> Any:
    """The QoSProfile to publish a recorded topic with (rosbag2's adapt_offer_to_recorded_offers).

    The recorded publishers' profile if they all agree on the policies that decide
    compatibility (reliability, durability, deadline, liveliness and its lease), with keep-last
    history (depth as recorded, or 10 when the publisher did not report it); else, and when
    nothing was recorded, reliable / volatile / keep last 10.
    """
    from rclpy.qos import (
        QoSDurabilityPolicy,
        QoSHistoryPolicy,
        QoSLivelinessPolicy,
        QoSProfile,
        QoSReliabilityPolicy,
    )
    default = QoSProfile(depth=10)
    if not profiles:
        return default
    compat_keys = ('reliability', 'durability', 'deadline', 'liveliness',
                   'liveliness_lease_duration')
    first = profiles[0]
    if any(any(p.get(k) != first.get(k) for k in compat_keys) for p in profiles[1:]):
        return default

    def policy(enum, key, fallback):
        name = policy_name(key, first.get(key))
        if name in ('unknown', 'system_default'):
            return fallback
        try:
            return enum.get_from_short_key(name)
        except Exception:  # noqa: BLE001 - a name this rmw does not know
            return fallback

    depth = int(first.get('depth') or 0)
    keep_all = policy_name('history', first.get('history')) == 'keep_all'
    return QoSProfile(
        history=QoSHistoryPolicy.KEEP_ALL if keep_all else QoSHistoryPolicy.KEEP_LAST,
        depth=depth if depth > 0 else 10,
        reliability=policy(QoSReliabilityPolicy, 'reliability', QoSReliabilityPolicy.RELIABLE),
        durability=policy(QoSDurabilityPolicy, 'durability', QoSDurabilityPolicy.VOLATILE),
        deadline=_duration_or_default(duration_ns(first.get('deadline'))),
        lifespan=_duration_or_default(duration_ns(first.get('lifespan'))),
        liveliness=policy(QoSLivelinessPolicy, 'liveliness', QoSLivelinessPolicy.SYSTEM_DEFAULT),
        liveliness_lease_duration=_duration_or_default(
            duration_ns(first.get('liveliness_lease_duration'))),
    )


def qos_for_recording(offered: Sequence[Any], depth: int = 100) -> Any:
    """The subscription QoS that receives from every publisher (rosbag2's adapt_request_to_offers).

    Reliable only if every publisher is reliable, else best effort (a best-effort subscription
    matches reliable and best-effort publishers alike); transient local only if every publisher
    is, so latched state is received without refusing volatile publishers.
    """
    from rclpy.qos import QoSDurabilityPolicy, QoSProfile, QoSReliabilityPolicy
    profile = QoSProfile(depth=depth)
    if offered and not all(
            QoSReliabilityPolicy(p.reliability) == QoSReliabilityPolicy.RELIABLE
            for p in offered):
        profile.reliability = QoSReliabilityPolicy.BEST_EFFORT
    if offered and all(
            QoSDurabilityPolicy(p.durability) == QoSDurabilityPolicy.TRANSIENT_LOCAL
            for p in offered):
        profile.durability = QoSDurabilityPolicy.TRANSIENT_LOCAL
    return profile


# --------------------------------------------------------------------------------------------
# Recording from and playing onto the ROS graph


class Recorder:
    """Record topics of the ROS graph through an existing rclpy node into a `BagWriter`.

    ``topics``: topic -> type name (None: the type the graph reports); None records every
    topic that appears. A topic is subscribed (``raw=True``: CDR bytes, never deserialized) once
    it has publishers, with `qos_for_recording` of their offers, and the publishers' offered
    profiles are stored with the topic. Log time is the node clock's receive time; publish time
    is the publisher's source timestamp. Topics without publishers yet are retried every
    ``poll_period`` seconds by a timer on the node, so the node must be spun.
    """

    def __init__(self, node: Any, topics: Mapping[str, str | None] | None, writer: BagWriter,
                 *, poll_period: float = 0.1, depth: int = 100):
        self.node = node
        self.writer = writer
        self.depth = depth
        self.record_all = topics is None
        self.pending: dict[str, str | None] = {
            node.resolve_topic_name(t): (None if ty is None else full_type_name(ty))
            for t, ty in (topics or {}).items()}
        self.subscriptions: dict[str, Any] = {}
        self._timer = node.create_timer(poll_period, self.poll)
        self.poll()

    @property
    def recorded_topics(self) -> dict[str, str]:
        return self.writer.topics

    def poll(self) -> None:
        """Subscribe the topics that have publishers now."""
        graph = dict(self.node.get_topic_names_and_types())
        if self.record_all:
            for name in graph:
                hidden = any(part.startswith('_') for part in name.split('/'))
                if name not in self.subscriptions and name not in self.pending and not hidden:
                    self.pending[name] = None
        for topic, wanted_type in list(self.pending.items()):
            publishers = self.node.get_publishers_info_by_topic(topic)
            if not publishers:
                continue
            types = sorted({full_type_name(p.topic_type) for p in publishers})
            type_name = wanted_type or (types[0] if len(types) == 1 else None)
            if type_name is None or type_name not in types:
                self.node.get_logger().warning(
                    f'not recording {topic}: its publishers offer {", ".join(types)}'
                    + (f', not {wanted_type}' if wanted_type else ''), once=True)
                continue
            offers = [p.qos_profile for p in publishers if full_type_name(p.topic_type)
                      == type_name]
            hashes = {str(p.topic_type_hash) for p in publishers
                      if str(p.topic_type_hash).startswith('RIHS')}
            self.writer.add_topic(topic, type_name, qos=offers,
                                  topic_type_hash=hashes.pop() if len(hashes) == 1 else None)
            self.subscriptions[topic] = self.node.create_subscription(
                message_class(type_name), topic, self._make_callback(topic),
                qos_for_recording(offers, self.depth), raw=True)
            del self.pending[topic]

    def _make_callback(self, topic: str) -> Callable[[bytes, Any], None]:
        clock = self.node.get_clock()

        def on_message(data: bytes, info: Any) -> None:
            receive_ns = clock.now().nanoseconds
            source_ns = info.get('source_timestamp') if isinstance(info, dict) else None
            self.writer.write(topic, data, receive_ns, source_ns or receive_ns)
        return on_message

    def close(self) -> None:
        """Stop recording (the writer stays open: the caller closes it)."""
        self.node.destroy_timer(self._timer)
        for subscription in self.subscriptions.values():
            self.node.destroy_subscription(subscription)
        self.subscriptions.clear()


@dataclass(frozen=True)
class PlayResult:
    message_count: int
    duration_s: float        # wall time from the first to the last publication
    interrupted: bool        # a stop signal (Ctrl-C) or a shut-down context ended it early
    skipped: dict = field(default_factory=dict)   # topic -> why it was not played
    unmatched: dict = field(default_factory=dict)  # topic -> subscribers not matched at start


PLAY_ORDERS = ('log', 'publish')
MATCH_POLL_SEC = 0.02


def _stopped(context) -> bool:
    from . import stop
    return stop.requested() or not context.ok()


def unmatched_subscribers(node: Any, publishers: Mapping[str, Any]) -> dict[str, int]:
    """topic -> how many subscriptions the graph shows on it (of its type, with a QoS that can
    match the publisher's) that the publisher has not matched yet; topics with none are left
    out. The graph and the matches both come from discovery, without spinning."""
    from rclpy.qos import QoSCompatibility, qos_check_compatible
    missing = {}
    for topic, publisher in publishers.items():
        cls = publisher.msg_type
        type_name = f'{cls.__module__.split(".")[0]}/msg/{cls.__name__}'
        wanted = 0
        for info in node.get_subscriptions_info_by_topic(topic):
            if full_type_name(info.topic_type) != type_name:
                continue
            compatibility, _ = qos_check_compatible(publisher.qos_profile, info.qos_profile)
            wanted += compatibility != QoSCompatibility.ERROR
        count = wanted - publisher.get_subscription_count()
        if count > 0:
            missing[topic] = count
    return missing


def wait_until_matched(node: Any, publishers: Mapping[str, Any], timeout: float,
                       every_topic: bool = False,
                       notice: Callable[[str], None] | None = None) -> dict[str, int]:
    """Before the first message: wait up to `timeout` s until every subscription the graph
    shows on the played topics is matched by its publisher and at least one is (with
    `every_topic`, at least one on every topic). A fresh publisher is discovered by the
    subscribers already running some milliseconds after it appears, and a volatile message
    published before that is lost to them: `ros2 bag play` of a bag into fresh nodes lost
    epoch 1 that way. Returns what is still unmatched (topic -> count; a topic without any
    subscription counts 1 under `every_topic`); {} when ready. Stops early on a stop signal."""
    deadline = time.monotonic() + max(0.0, timeout)
    next_notice = time.monotonic() + 1.0
    while True:
        missing = unmatched_subscribers(node, publishers)
        matched = {t: p.get_subscription_count() for t, p in publishers.items()}
        if every_topic:
            missing.update({t: 1 for t, n in matched.items() if n == 0 and t not in missing})
        if not missing and any(matched.values()):
            return {}
        if time.monotonic() >= deadline or _stopped(node.context):
            if notice is not None and not missing and not any(matched.values()):
                notice(f'no subscriber of the played topics appeared within {timeout:g} s')
            return missing
        if notice is not None and time.monotonic() >= next_notice:
            waiting = ', '.join(f'{t} ({n})' for t, n in sorted(missing.items()))
            notice(f'waiting for subscribers to match: {waiting or "none found yet"}')
            next_notice = time.monotonic() + 2.0
        time.sleep(MATCH_POLL_SEC)


def play(path: str | os.PathLike, node: Any = None, rate: float = 1.0,
         topics: Iterable[str] | None = None, start_delay: float = 0.0,
         wait_for_subscribers: float = 0.0, match_timeout: float = 5.0,
         ack_timeout: float = 2.0, on_publish: Callable[[BagMessage], None] | None = None,
         order: str = 'log', notice: Callable[[str], None] | None = None) -> PlayResult:
    """Publish a bag's messages (serialized, as recorded) with the recorded timing / ``rate``.

    Message i goes out at t0 + (time_i - time_0) / rate on the monotonic clock (no
    accumulated sleep drift), t0 = start + ``start_delay``, where time is the log (receive)
    time with ``order='log'``, as `ros2 bag play` does, or the publish time (the writers'
    source timestamps) with ``order='publish'``: the order the messages were sent in, which on
    one host is their causal order, while the recorder may have taken two messages of
    different writers in the other order. 'publish' sorts the bag in memory. Each topic's
    publisher uses `qos_from_offers` of the recorded profiles.

    Before the first message the player waits (`wait_until_matched`) up to ``match_timeout``
    s until every subscriber the graph shows on the played topics has matched its publisher,
    or, with ``wait_for_subscribers`` > 0, up to that long until every topic has one; what is
    still unmatched then is in the result's `unmatched` (and the play goes on). At the end,
    reliable publishers wait up to ``ack_timeout`` s for their messages to be acknowledged.
    Without a ``node`` a private rclpy context and node are made and torn down. Stops early
    (returning what was played) on a stop signal (`stop.requested`) or when the node's context
    shuts down.
    """
    if not rate > 0:
        raise BagError(f'rate must be positive, not {rate}')
    if order not in PLAY_ORDERS:
        raise BagError(f'order must be one of {", ".join(PLAY_ORDERS)}, not {order!r}')
    info = bag_info(path)
    wanted = {t.topic for t in info.topics} if topics is None else set(topics)
    unknown = wanted - {t.topic for t in info.topics}
    if unknown:
        raise BagError(f'{info.path} has no topic {", ".join(sorted(unknown))} '
                       f'(it has {", ".join(t.topic for t in info.topics) or "none"})')
    counts = {t.topic: t.message_count for t in info.topics}
    import rclpy
    import rclpy.context
    from rclpy.duration import Duration
    from rclpy.qos import QoSReliabilityPolicy

    from . import stop
    own_context = None
    if node is None:
        own_context = rclpy.context.Context()
        rclpy.init(context=own_context, **stop.init_options())
        node = rclpy.create_node('hrc_bag_player', context=own_context)
    context = node.context
    publishers = {}
    try:
        skipped = {}
        for topic in info.topics:
            if topic.topic not in wanted:
                continue
            try:
                cls = message_class(topic.type_name)
            except BagError as exc:   # as rosbag2's player: warn, and play the other topics
                skipped[topic.topic] = str(exc)
                continue
            publishers[topic.topic] = node.create_publisher(
                cls, topic.topic, qos_from_offers(topic.qos_profiles))
        wanted = set(publishers)
        every_topic = wait_for_subscribers > 0
        # a topic without messages has nothing to deliver: nobody need listen to it (a bag
        # with an empty topic waited the whole --wait-for-subscribers for it)
        played = {topic: publisher for topic, publisher in publishers.items()
                  if counts.get(topic, 0) > 0}
        unmatched = wait_until_matched(
            node, played, wait_for_subscribers if every_topic else match_timeout,
            every_topic=every_topic, notice=notice) if played else {}
        count, first_ns, start, last_wall = 0, None, 0.0, 0.0
        messages = read_bag(info.path, topics=wanted) if wanted else iter(())
        if order == 'publish':
            messages = sorted(messages, key=lambda m: m.publish_time_ns)

        def timestamp(m: BagMessage) -> int:
            return m.publish_time_ns if order == 'publish' else m.log_time_ns

        for bag_message in messages:
            if first_ns is None:
                first_ns = timestamp(bag_message)
                start = time.monotonic() + max(0.0, start_delay)
            due = start + (timestamp(bag_message) - first_ns) / 1e9 / rate
            while not _stopped(context) and (remaining := due - time.monotonic()) > 0:
                time.sleep(min(remaining, 0.05))
            if _stopped(context):
                break
            publishers[bag_message.topic].publish(bag_message.data)
            last_wall = time.monotonic()
            count += 1
            if on_publish is not None:
                on_publish(bag_message)
        for topic in info.topics:
            if (topic.topic in publishers and not _stopped(context)
                    and qos_from_offers(topic.qos_profiles).reliability
                    == QoSReliabilityPolicy.RELIABLE):
                publishers[topic.topic].wait_for_all_acked(Duration(seconds=ack_timeout))
        return PlayResult(count, max(0.0, last_wall - start) if count else 0.0,
                          interrupted=_stopped(context), skipped=skipped, unmatched=unmatched)
    finally:
        if context.ok():
            for publisher in publishers.values():
                node.destroy_publisher(publisher)
        if own_context is not None:
            node.destroy_node()
            rclpy.try_shutdown(context=own_context)


# --------------------------------------------------------------------------------------------
# hrc-bag


def _wait_for_topics(node: Any, topics: list[str], timeout: float) -> dict[str, str] | None:
    """topic -> type once every topic has a publisher; None on a stop signal; BagError after
    ``timeout`` seconds."""
    import rclpy
    found: dict[str, str] = {}
    deadline = time.monotonic() + timeout
    next_notice = 0.0
    while True:
        for topic in topics:
            if topic in found:
                continue
            types = {full_type_name(p.topic_type)
                     for p in node.get_publishers_info_by_topic(topic)}
            if len(types) == 1:
                found[topic] = types.pop()
            elif len(types) > 1:
                raise BagError(f'topic {topic} has publishers of several types: '
                               f'{", ".join(sorted(types))}')
        missing = [t for t in topics if t not in found]
        if not missing:
            return found
        if _stopped(node.context):
            return None
        now = time.monotonic()
        if now >= deadline:
            raise BagError(f'no publisher appeared within {timeout:g} s on '
                           f'{", ".join(missing)}')
        if now >= next_notice:
            print(f'hrc-bag: waiting for {", ".join(missing)}', flush=True)
            next_notice = now + 2.0
        rclpy.spin_once(node, timeout_sec=0.05)


def check_topic_names(topics: Iterable[str]) -> None:
    """BagError (one line) for a topic name ROS refuses, before anything waits on it."""
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.validate_topic_name import validate_topic_name
    for topic in topics:
        try:
            validate_topic_name(topic)
        except InvalidTopicNameException as exc:
            reason = str(exc).splitlines()[0].removeprefix('Invalid topic name: ')
            raise BagError(f'invalid topic name {topic!r}: {reason}') from None


def check_output(path: str | os.PathLike) -> None:
    """BagError (one line) if `hrc-bag record -o PATH` cannot write there, before any waiting:
    an existing .mcap file (or a link by that name) is never overwritten, and its folder must
    exist; a bag folder must be new or empty (`paths.folder_target`: not a file, a device, a
    FIFO, a dangling link or a loop of links)."""
    target = Path(path)
    if target.suffix == '.mcap':
        if target.exists() or target.is_symlink():
            raise BagError(f'cannot record into {target}: it already exists (choose a new name)')
        if not target.parent.is_dir():
            raise BagError(f'cannot write {target}: folder {target.parent} does not exist')
        return
    try:
        folder_target(target, empty=True)
    except OSError as exc:
        raise BagError(f'cannot record into {target}: {exc.strerror}') from None


def _resolved(node: Any, topics: Iterable[str]) -> list[str]:
    resolved = []
    for topic in topics:
        try:
            resolved.append(node.resolve_topic_name(topic))
        except Exception as exc:  # noqa: BLE001 - rcl refuses a name the expansion made bad
            raise BagError(f'invalid topic name {topic!r}: '
                           f'{str(exc).splitlines()[0]}') from None
    return resolved


def _record_command(args: argparse.Namespace) -> int:
    """Record until --duration, --max-messages or a stop signal (Ctrl-C: exit 0 with the bag
    closed). A stop signal while waiting for the publishers records nothing: exit 130."""
    import rclpy

    from . import stop
    check_topic_names(args.topics)
    check_output(args.output)
    rclpy.init(**stop.init_options())
    try:
        node = rclpy.create_node('hrc_bag_recorder')
        try:
            return _record(node, args)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


def _record(node: Any, args: argparse.Namespace) -> int:
    import rclpy
    topics = _resolved(node, args.topics)
    types = _wait_for_topics(node, topics, args.wait_timeout)
    if types is None:
        print('hrc-bag: interrupted before recording; nothing written', flush=True)
        return 130
    with BagWriter(args.output) as writer:
        recorder = Recorder(node, types, writer)
        print(f'hrc-bag: recording {", ".join(topics)} to {writer.path}', flush=True)
        started = time.monotonic()
        reported = -1
        next_status = 0.0
        try:
            while not _stopped(node.context):
                rclpy.spin_once(node, timeout_sec=0.05)
                now = time.monotonic()
                if writer.message_count != reported and now >= next_status:
                    reported = writer.message_count
                    print(f'hrc-bag: recorded {reported} messages', flush=True)
                    next_status = now + 1.0
                if args.duration is not None and now - started >= args.duration:
                    break
                if args.max_messages is not None and \
                        writer.message_count >= args.max_messages:
                    break
        finally:
            if node.context.ok():
                recorder.close()
    print(f'hrc-bag: recorded {writer.message_count} messages on {len(writer.topics)} '
          f'topic(s) in {time.monotonic() - started:.1f} s to {writer.path} '
          f'({format_size(writer.path.stat().st_size)})', flush=True)
    written = writer.message_counts
    empty = [topic for topic in topics if written.get(topic, 0) == 0]
    if empty:      # a bag that lacks a topic's messages cannot be replayed or fitted as one
        print(f'hrc-bag: warning: no message on {cap(", ".join(empty), 400)}: they had '
              'publishers but sent nothing while recording (start the recorder before the '
              'run, or record longer)', file=sys.stderr, flush=True)
    return 0


def _play_command(args: argparse.Namespace) -> int:
    """Play the bag; a stop signal ends it early (exit 130)."""
    import rclpy

    from . import stop
    info = bag_info(args.bag)
    print(f'hrc-bag: playing {info.path}: {info.message_count} messages, '
          f'{info.duration_ns / 1e9:.3f} s at rate {args.rate:g}', flush=True)
    for topic in info.topics:
        if args.topics is None or topic.topic in args.topics:
            try:
                message_class(topic.type_name)
            except BagError as exc:
                print(f'hrc-bag: warning: not playing {topic.topic} ({topic.message_count} '
                      f'messages): {exc}', file=sys.stderr, flush=True)
    rclpy.init(**stop.init_options())
    try:
        node = rclpy.create_node('hrc_bag_player')
        try:
            result = play(info.path, node=node, rate=args.rate, topics=args.topics,
                          start_delay=args.start_delay,
                          wait_for_subscribers=args.wait_for_subscribers,
                          match_timeout=args.match_timeout, order=args.order,
                          notice=lambda text: print(f'hrc-bag: {text}', flush=True))
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    if result.unmatched:
        print('hrc-bag: warning: started with subscribers not matched yet (they may miss the '
              'first messages): ' + ', '.join(f'{t} ({n})' for t, n in
                                              sorted(result.unmatched.items())),
              file=sys.stderr, flush=True)
    print(f'hrc-bag: {"interrupted after" if result.interrupted else "played"} '
          f'{result.message_count} messages in {result.duration_s:.3f} s', flush=True)
    return 130 if result.interrupted else 0


def _info_command(args: argparse.Namespace) -> int:
    print(bag_info(args.bag, verify=not args.quick).format())
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = Parser(
        prog='hrc-bag', description='Record, play and inspect rosbag2-compatible MCAP bags.')
    commands = parser.add_subparsers(dest='command', required=True)
    record = commands.add_parser('record', help='record topics into a bag directory')
    record.add_argument('-o', '--output', required=True, type=path_text,
                        help='bag directory to create (or a file name ending in .mcap)')
    record.add_argument('--duration', type=bounded_float(0.0, 1e7), default=None,
                        help='stop after S seconds')
    record.add_argument('--max-messages', type=bounded_int(1, 2 ** 62), default=None,
                        help='stop after N messages')
    record.add_argument('--wait-timeout', type=bounded_float(0.0, 86400.0), default=10.0,
                        help='seconds to wait for every topic to have a publisher (default 10)')
    record.add_argument('topics', nargs='+', metavar='TOPIC')
    player = commands.add_parser('play', help='publish a bag with its recorded timing')
    player.add_argument('bag', metavar='FILE_OR_DIR')
    player.add_argument('--rate', type=bounded_float(1e-3, 1e3), default=1.0,
                        help='playback speed factor')
    player.add_argument('--topics', nargs='+', default=None, metavar='T',
                        help='play only these topics')
    player.add_argument('--start-delay', type=bounded_float(0.0, 86400.0), default=0.0,
                        help='seconds to wait before the first message')
    player.add_argument('--wait-for-subscribers', type=bounded_float(0.0, 86400.0), default=0.0,
                        metavar='S',
                        help='wait up to S s for every topic to have a subscriber (and every '
                        'subscriber to match) before the first message')
    player.add_argument('--match-timeout', type=bounded_float(0.0, 86400.0), default=5.0,
                        metavar='S',
                        help='wait up to S s (default 5) for the subscribers the graph shows on '
                        'the played topics to match before the first message; 0: do not wait')
    player.add_argument('--order', choices=PLAY_ORDERS, default='log',
                        help="timing and order by 'log' (receive) time, as ros2 bag play, or "
                        "by 'publish' time, the order the writers sent them in (default log)")
    info = commands.add_parser('info', help='print a bag summary')
    info.add_argument('bag', metavar='FILE_OR_DIR')
    info.add_argument('--quick', action='store_true',
                      help='read the summary only (do not check every chunk)')
    from . import stop
    with stop.regime():
        args = parser.parse_args(argv)
        handlers = {'record': _record_command, 'play': _play_command, 'info': _info_command}
        try:
            return handlers[args.command](args)
        except BagError as exc:
            print(f'hrc-bag: {" ".join(str(exc).split())}', file=sys.stderr)
            return 2


if __name__ == '__main__':
    sys.exit(main())
