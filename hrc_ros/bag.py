"""rosbag2-compatible MCAP bags: write, read, record from and play onto the ROS graph (`hrc-bag`).

Why: rosbag2 (`ros2 bag`) is not installable on the project's machines, yet the suite is tested
"as a user starts it, fed from a recorded bag", and bags recorded here must play in a real ROS
install (and the other way round). So this module writes exactly the layout rosbag2 jazzy's
`rosbag2_storage_mcap` plugin writes and reads, using the `mcap` library for the container and
rclpy for CDR serialization. Checked against rosbag2's sources (`rosbag2_storage_mcap`
`mcap_storage.cpp` and `message_definition_cache.cpp`, `rosbag2_storage` `qos.cpp` and
`yaml.hpp`, pull request ros2/rosbag2#1476 that made metadata version 9).

Format notes (an MCAP file):

- Header profile ``ros2``. No ``rosbag2`` metadata record: it is optional, and a reader that
  finds one must decode it fully, so leaving it out is the safe choice.
- One schema per message type: name ``pkg/msg/Type``, encoding ``ros2msg``, data = the type's
  ``.msg`` text, then for every dependency, depth first and each type once, ``"\\n"``, a line of
  80 ``=``, a line ``MSG: pkg/msg/Type`` and that type's ``.msg`` text. Dependencies of one type
  are visited in sorted order, as rosbag2's MessageDefinitionCache does (a std::set); rosbag2
  writes the name as spelled in the field (``MSG: std_msgs/Header``), we write the full
  ``pkg/msg/Type`` name: mcap_ros2 registers both spellings, and rosbag2's player does not
  parse schemas at all (it publishes the CDR bytes with the installed type support).
- One channel per topic: message encoding ``cdr``, metadata ``offered_qos_profiles`` (a YAML
  list, one profile per publisher, in metadata-version-9 form: policies as rmw's short names
  such as ``reliable``, durations as ``{sec, nsec}``; infinite is sec 9223372036
  nsec 854775807) and ``topic_type_hash`` (the ``RIHS01_...`` hash of the type description,
  from the publisher's endpoint info or from ``share/<pkg>/msg/<Type>.json``; empty if unknown).
- Chunked, uncompressed (rosbag2's default), with chunk CRCs, message indexes and the summary
  section with the Statistics record, which rosbag2's reader needs.
- A recording into a directory ``DIR`` writes ``DIR/<basename(DIR)>_0.mcap`` and, on close,
  ``DIR/metadata.yaml`` in rosbag2 jazzy's form (``rosbag2_bagfile_information``, version 9).
  A path ending in ``.mcap`` writes that file alone (``ros2 bag play file.mcap`` works since
  Humble).

Reading refuses, with `BagError`, a missing file, a file that is not MCAP, a truncated one (no
footer: a recorder killed before it closed the file), one without a summary or Statistics, a
summary or chunk whose CRC does not match, a profile other than ``ros2`` and non-``cdr``
channels. Times are integer nanoseconds: log time = receive time, as rosbag2 records it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import struct
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import yaml
from mcap.reader import SeekingReader
from mcap.writer import CompressionType, Writer

PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
METADATA_VERSION = 9          # rosbag2 jazzy's BagMetadata::version
ROS_DISTRO = 'jazzy'
METADATA_FILE = 'metadata.yaml'
DEFINITION_SEPARATOR = '=' * 80
LIBRARY = 'hrc_ros.bag'

PRIMITIVE_TYPES = frozenset((
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'))

INFINITE_NS = 2 ** 63 - 1     # RMW_DURATION_INFINITE = {9223372036 s, 854775807 ns}
QOS_KEYS = ('history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan',
            'liveliness', 'liveliness_lease_duration', 'avoid_ros_namespace_conventions')
DEFAULT_QOS = {  # rosbag2's Rosbag2QoS{} = rclcpp::QoS(10): reliable, volatile, keep last 10
    'history': 'keep_last', 'depth': 10, 'reliability': 'reliable', 'durability': 'volatile',
    'deadline': {'sec': 0, 'nsec': 0}, 'lifespan': {'sec': 0, 'nsec': 0},
    'liveliness': 'system_default', 'liveliness_lease_duration': {'sec': 0, 'nsec': 0},
    'avoid_ros_namespace_conventions': False,
}
# Policy enum values of metadata version <= 8, which wrote ints (rmw's enum order).
_LEGACY_POLICY_NAMES = {
    'history': ('system_default', 'keep_last', 'keep_all', 'unknown'),
    'reliability': ('system_default', 'reliable', 'best_effort', 'unknown', 'best_available'),
    'durability': ('system_default', 'transient_local', 'volatile', 'unknown', 'best_available'),
    'liveliness': ('system_default', 'automatic', 'manual_by_node', 'manual_by_topic', 'unknown',
                   'best_available'),
}

_MAGIC = b'\x89MCAP0\r\n'
_FOOTER_OPCODE = 0x02
_FOOTER_RECORD = 1 + 8 + 8 + 8 + 4   # opcode, length, summary_start, summary_offset_start, crc


class BagError(RuntimeError):
    """A bag cannot be read or written: missing, not MCAP, truncated, corrupt or not ROS 2."""


# --------------------------------------------------------------------------------------------
# Message types: names, .msg definitions, type hashes, Python classes


def split_type_name(type_name: str) -> tuple[str, str]:
    """``'std_msgs/msg/String'`` or ``'std_msgs/String'`` -> ``('std_msgs', 'String')``."""
    parts = str(type_name).split('/')
    if len(parts) == 3 and parts[1] == 'msg' and all(parts):
        return parts[0], parts[2]
    if len(parts) == 2 and all(parts):
        return parts[0], parts[1]
    raise BagError(f'message type {type_name!r} is not of the form pkg/msg/Type')


def full_type_name(type_name: str) -> str:
    package, name = split_type_name(type_name)
    return f'{package}/msg/{name}'


def _share_dirs(package: str) -> list[Path]:
    dirs = []
    try:
        from ament_index_python.packages import get_package_share_directory
        dirs.append(Path(get_package_share_directory(package)))
    except Exception:  # noqa: BLE001 - no ament index (a pip install): use the prefix below
        pass
    dirs.append(Path(sys.prefix) / 'share' / package)
    return dirs


def _interface_file(type_name: str, suffix: str) -> Path | None:
    package, name = split_type_name(type_name)
    for share in _share_dirs(package):
        candidate = share / 'msg' / f'{name}{suffix}'
        if candidate.is_file():
            return candidate
    return None


def msg_text(type_name: str) -> str:
    """The installed ``.msg`` text of a type, verbatim."""
    path = _interface_file(type_name, '.msg')
    if path is None:
        package, name = split_type_name(type_name)
        places = ', '.join(str(d / 'msg') for d in _share_dirs(package))
        raise BagError(f'no definition {name}.msg of {full_type_name(type_name)} in {places}')
    return path.read_text(encoding='utf-8')


def field_dependencies(text: str, package: str) -> list[str]:
    """Full names of the message types the fields of a ``.msg`` text use, each once.

    A field line is ``TYPE NAME [DEFAULT]`` or a constant ``TYPE NAME=VALUE``; TYPE may carry an
    array suffix (``[]``, ``[N]``, ``[<=N]``) or a string bound (``string<=N``). A bare ``Header``
    is std_msgs/Header; another bare name is a type of the same package.
    """
    dependencies: list[str] = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        field_type = line.split()[0].split('[', 1)[0].split('<=', 1)[0]
        if field_type in PRIMITIVE_TYPES:
            continue
        if '/' in field_type:
            dependency = full_type_name(field_type)
        elif field_type == 'Header':
            dependency = 'std_msgs/msg/Header'
        else:
            dependency = f'{package}/msg/{field_type}'
        if dependency not in dependencies:
            dependencies.append(dependency)
    return dependencies


def message_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of a type: its .msg text and every dependency's, once each."""
    root = full_type_name(type_name)
    seen = {root}

    def append(name: str, depth: int) -> str:
        if depth > 50:
            raise BagError(f'message definition of {root} nests deeper than 50 types')
        text = msg_text(name)
        for dependency in sorted(field_dependencies(text, split_type_name(name)[0])):
            if dependency not in seen:
                seen.add(dependency)
                text += f'\n{DEFINITION_SEPARATOR}\nMSG: {dependency}\n'
                text += append(dependency, depth + 1)
        return text

    return append(root, 0)


def type_hash(type_name: str) -> str:
    """The ``RIHS01_...`` type-description hash from ``share/<pkg>/msg/<Type>.json``, or ''."""
    path = _interface_file(type_name, '.json')
    if path is None:
        return ''
    try:
        hashes = json.loads(path.read_text(encoding='utf-8'))['type_hashes']
    except (OSError, ValueError, KeyError, TypeError):
        return ''
    name = full_type_name(type_name)
    for entry in hashes:
        if isinstance(entry, dict) and entry.get('type_name') == name:
            return str(entry.get('hash_string', ''))
    return ''


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


# --------------------------------------------------------------------------------------------
# QoS profiles <-> rosbag2's YAML


def _duration_fields(nanoseconds: int) -> dict:
    return {'sec': int(nanoseconds) // 10 ** 9, 'nsec': int(nanoseconds) % 10 ** 9}


def qos_to_dict(profile: Any) -> dict:
    """An rclpy QoSProfile as rosbag2 writes it (metadata version 9), keys in rosbag2's order."""
    if isinstance(profile, Mapping):
        return {key: profile.get(key, DEFAULT_QOS[key]) for key in QOS_KEYS}
    from rclpy.qos import (QoSDurabilityPolicy, QoSHistoryPolicy, QoSLivelinessPolicy,
                           QoSReliabilityPolicy)
    return {
        'history': QoSHistoryPolicy(profile.history).short_key,
        'depth': int(profile.depth),
        'reliability': QoSReliabilityPolicy(profile.reliability).short_key,
        'durability': QoSDurabilityPolicy(profile.durability).short_key,
        'deadline': _duration_fields(profile.deadline.nanoseconds),
        'lifespan': _duration_fields(profile.lifespan.nanoseconds),
        'liveliness': QoSLivelinessPolicy(profile.liveliness).short_key,
        'liveliness_lease_duration': _duration_fields(
            profile.liveliness_lease_duration.nanoseconds),
        'avoid_ros_namespace_conventions': bool(profile.avoid_ros_namespace_conventions),
    }


class _RosbagDumper(yaml.SafeDumper):
    """yaml-cpp's block style: a sequence under a key is indented, keys keep their order."""

    def increase_indent(self, flow=False, indentless=False):
        return super().increase_indent(flow, False)


def _dump_yaml(data: Any) -> str:
    return yaml.dump(data, Dumper=_RosbagDumper, sort_keys=False, default_flow_style=False,
                     allow_unicode=True)


def qos_profiles_yaml(profiles: Sequence[Any]) -> str:
    """The ``offered_qos_profiles`` channel metadata string (YAML::Dump form, no final newline).

    An empty list is written as ``''``, as rosbag2 reads an empty string as no profiles.
    """
    if not profiles:
        return ''
    return _dump_yaml([qos_to_dict(p) for p in profiles]).rstrip('\n')


def _policy_name(key: str, value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return 'unknown'
    if isinstance(value, int):
        names = _LEGACY_POLICY_NAMES[key]
        return names[value] if 0 <= value < len(names) else 'unknown'
    return str(value)


def _duration_ns(value: Any) -> int:
    if isinstance(value, Mapping):
        return int(value.get('sec', 0)) * 10 ** 9 + int(value.get('nsec', 0))
    return 0


def parse_qos_profiles(text: str | None) -> list[dict]:
    """The profiles of an ``offered_qos_profiles`` string (metadata version 9 or older)."""
    if not text:
        return []
    try:
        loaded = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise BagError(f'offered_qos_profiles is not YAML: {exc}') from None
    if loaded is None:
        return []
    if not isinstance(loaded, list) or not all(isinstance(p, Mapping) for p in loaded):
        raise BagError('offered_qos_profiles is not a YAML list of QoS profiles')
    profiles = []
    for raw in loaded:
        profile = {key: raw.get(key, DEFAULT_QOS[key]) for key in QOS_KEYS}
        for key in _LEGACY_POLICY_NAMES:
            profile[key] = _policy_name(key, profile[key])
        profiles.append(profile)
    return profiles


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
    from rclpy.qos import (QoSDurabilityPolicy, QoSHistoryPolicy, QoSLivelinessPolicy,
                           QoSProfile, QoSReliabilityPolicy)
    default = QoSProfile(depth=10)
    if not profiles:
        return default
    compat_keys = ('reliability', 'durability', 'deadline', 'liveliness',
                   'liveliness_lease_duration')
    first = profiles[0]
    if any(any(p.get(k) != first.get(k) for k in compat_keys) for p in profiles[1:]):
        return default

    def policy(enum, key, fallback):
        name = _policy_name(key, first.get(key))
        if name in ('unknown', 'system_default'):
            return fallback
        try:
            return enum.get_from_short_key(name)
        except Exception:  # noqa: BLE001 - a name this rmw does not know
            return fallback

    depth = int(first.get('depth') or 0)
    keep_all = _policy_name('history', first.get('history')) == 'keep_all'
    return QoSProfile(
        history=QoSHistoryPolicy.KEEP_ALL if keep_all else QoSHistoryPolicy.KEEP_LAST,
        depth=depth if depth > 0 else 10,
        reliability=policy(QoSReliabilityPolicy, 'reliability', QoSReliabilityPolicy.RELIABLE),
        durability=policy(QoSDurabilityPolicy, 'durability', QoSDurabilityPolicy.VOLATILE),
        deadline=_duration_or_default(_duration_ns(first.get('deadline'))),
        lifespan=_duration_or_default(_duration_ns(first.get('lifespan'))),
        liveliness=policy(QoSLivelinessPolicy, 'liveliness', QoSLivelinessPolicy.SYSTEM_DEFAULT),
        liveliness_lease_duration=_duration_or_default(
            _duration_ns(first.get('liveliness_lease_duration'))),
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
# Writing


@dataclass
class _TopicRecord:
    topic: str
    type_name: str
    channel_id: int
    qos_profiles: list[dict]
    type_hash: str
    message_count: int = 0
    sequence: int = 0


class BagWriter:
    """Write a rosbag2-compatible MCAP bag.

    ``BagWriter('runs/demo')`` writes ``runs/demo/demo_0.mcap`` and ``runs/demo/metadata.yaml``
    (the directory must not exist or be empty); ``BagWriter('demo.mcap')`` writes that file only.
    Use it as a context manager: closing writes the summary (and metadata.yaml), also when the
    block raises.
    """

    def __init__(self, path: str | os.PathLike, *, compression: str = 'none',
                 chunk_size: int = 1024 * 1024):
        target = Path(path)
        if target.suffix == '.mcap':
            self.directory: Path | None = None
            self.path = target
            if not target.parent.is_dir():
                raise BagError(f'cannot write {target}: folder {target.parent} does not exist')
        else:
            if target.exists() and (not target.is_dir() or any(target.iterdir())):
                raise BagError(f'cannot record into {target}: it already exists '
                               '(choose a new folder)')
            target.mkdir(parents=True, exist_ok=True)
            self.directory = target
            self.path = target / f'{target.resolve().name}_0.mcap'
        compressions = {'none': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                        'lz4': CompressionType.LZ4}
        if compression not in compressions:
            raise BagError(f'compression {compression!r} is not one of {sorted(compressions)}')
        try:
            self._stream = open(self.path, 'wb')
        except OSError as exc:
            raise BagError(f'cannot write {self.path}: {exc.strerror}') from None
        self._writer = Writer(self._stream, chunk_size=chunk_size,
                              compression=compressions[compression])
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _TopicRecord] = {}
        self.message_count = 0
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.closed = False

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    @property
    def topics(self) -> dict[str, str]:
        """topic -> type name of the topics added so far."""
        return {name: record.type_name for name, record in self._topics.items()}

    def add_topic(self, topic: str, type_name: str, qos: Any = None, *,
                  topic_type_hash: str | None = None) -> None:
        """Declare a topic (a channel, with its type's schema the first time it is seen).

        ``qos``: an rclpy QoSProfile, a list of them (one per recorded publisher), or None for
        reliable / volatile / keep last 10. ``topic_type_hash`` defaults to the installed hash.
        """
        self._check_open()
        name = full_type_name(type_name)
        if topic in self._topics:
            if self._topics[topic].type_name != name:
                raise BagError(f'topic {topic} was added as {self._topics[topic].type_name}, '
                               f'not {name}')
            return
        if qos is None:
            profiles = [dict(DEFAULT_QOS)]
        elif isinstance(qos, (list, tuple)):
            profiles = [qos_to_dict(p) for p in qos]
        else:
            profiles = [qos_to_dict(qos)]
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(
                name=name, encoding=SCHEMA_ENCODING,
                data=message_definition(name).encode('utf-8'))
        hash_string = type_hash(name) if topic_type_hash is None else str(topic_type_hash)
        channel_id = self._writer.register_channel(
            topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=self._schemas[name],
            metadata={'offered_qos_profiles': qos_profiles_yaml(profiles),
                      'topic_type_hash': hash_string})
        self._topics[topic] = _TopicRecord(topic, name, channel_id, profiles, hash_string)

    def write(self, topic: str, message: Any, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Write one message (an rclpy message or its CDR bytes) received at ``log_time_ns``."""
        self._check_open()
        record = self._topics.get(topic)
        if record is None:
            raise BagError(f'topic {topic} was not added to the bag (call add_topic first)')
        if isinstance(message, (bytes, bytearray, memoryview)):
            data = bytes(message)
        else:
            if type_name_of(message) != record.type_name:
                raise BagError(f'a {type_name_of(message)} message cannot be written on '
                               f'{topic}, a {record.type_name} topic')
            from rclpy.serialization import serialize_message
            data = serialize_message(message)
        log_time_ns = int(log_time_ns)
        if log_time_ns < 0:
            raise BagError(f'log time {log_time_ns} ns on {topic} is negative')
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        self._writer.add_message(channel_id=record.channel_id, log_time=log_time_ns,
                                 data=data, publish_time=publish_time_ns,
                                 sequence=record.sequence)
        record.sequence = (record.sequence + 1) % 2 ** 32
        record.message_count += 1
        self.message_count += 1
        self.start_ns = log_time_ns if self.start_ns is None else min(self.start_ns, log_time_ns)
        self.end_ns = log_time_ns if self.end_ns is None else max(self.end_ns, log_time_ns)

    def close(self) -> None:
        """Write the summary section and footer (and metadata.yaml for a directory)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
        finally:
            self._stream.close()
        if self.directory is not None:
            (self.directory / METADATA_FILE).write_text(self.metadata_yaml(), encoding='utf-8')

    def metadata_yaml(self) -> str:
        """rosbag2 jazzy's ``metadata.yaml`` for this bag (metadata version 9)."""
        start = self.start_ns or 0
        duration = (self.end_ns - self.start_ns) if self.start_ns is not None else 0
        relative = self.path.name
        information = {
            'version': METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': self.message_count,
            'topics_with_message_count': [
                {'topic_metadata': {
                    'name': record.topic,
                    'type': record.type_name,
                    'serialization_format': MESSAGE_ENCODING,
                    'offered_qos_profiles': record.qos_profiles,
                    'type_description_hash': record.type_hash},
                 'message_count': record.message_count}
                for record in self._topics.values()],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [relative],
            'files': [{'path': relative,
                       'starting_time': {'nanoseconds_since_epoch': start},
                       'duration': {'nanoseconds': duration},
                       'message_count': self.message_count}],
            'custom_data': None,
            'ros_distro': ROS_DISTRO,
        }
        return _dump_yaml({'rosbag2_bagfile_information': information})

    def _check_open(self) -> None:
        if self.closed:
            raise BagError(f'bag {self.path} is closed')


# --------------------------------------------------------------------------------------------
# Reading


@dataclass(frozen=True)
class BagMessage:
    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    qos_profiles: list = field(default_factory=list, compare=False)


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    type_name: str
    message_count: int
    qos_profiles: list
    type_hash: str


@dataclass(frozen=True)
class BagInfo:
    path: Path
    size_bytes: int
    topics: list[TopicInfo]
    message_count: int
    start_ns: int
    end_ns: int

    @property
    def duration_ns(self) -> int:
        return max(0, self.end_ns - self.start_ns) if self.message_count else 0

    def format(self) -> str:
        """A ``ros2 bag info``-like text."""
        def stamp(ns: int) -> str:
            utc = time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime(ns // 10 ** 9))
            return f'{utc}.{ns % 10 ** 9:09d} UTC ({ns // 10 ** 9}.{ns % 10 ** 9:09d})'
        lines = [
            f'Files:             {self.path}',
            f'Bag size:          {format_size(self.size_bytes)}',
            'Storage id:        mcap',
            f'Duration:          {self.duration_ns / 1e9:.9f}s',
            f'Start:             {stamp(self.start_ns)}',
            f'End:               {stamp(self.end_ns)}',
            f'Messages:          {self.message_count}',
        ]
        for i, topic in enumerate(self.topics):
            label = 'Topic information: ' if i == 0 else ' ' * 19
            lines.append(f'{label}Topic: {topic.topic} | Type: {topic.type_name} | '
                         f'Count: {topic.message_count} | Serialization Format: cdr')
        if not self.topics:
            lines.append('Topic information: (none)')
        return '\n'.join(lines)


def format_size(size_bytes: int) -> str:
    size = float(size_bytes)
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if size < 1024 or unit == 'GiB':
            return f'{size:.0f} {unit}' if unit == 'B' else f'{size:.1f} {unit}'
        size /= 1024
    return f'{size_bytes} B'


def resolve_bag_file(path: str | os.PathLike) -> Path:
    """The .mcap file of a bag: the file itself, or the one in a bag directory."""
    target = Path(path)
    if target.is_file():
        return target
    if target.is_dir():
        listed: list[str] = []
        metadata = target / METADATA_FILE
        if metadata.is_file():
            try:
                info = yaml.safe_load(metadata.read_text(encoding='utf-8'))
                listed = list(info['rosbag2_bagfile_information']['relative_file_paths'])
            except Exception:  # noqa: BLE001 - fall back to looking at the folder
                listed = []
        candidates = [target / Path(name).name for name in listed] or sorted(target.glob('*.mcap'))
        candidates = [c for c in candidates if c.is_file()]
        if not candidates:
            raise BagError(f'{target} holds no .mcap file')
        if len(candidates) > 1:
            raise BagError(f'{target} holds {len(candidates)} .mcap files (split bags are not '
                           'supported): name one of them')
        return candidates[0]
    raise BagError(f'{target}: no such file or directory')


def _check_container(path: Path) -> None:
    """Magic bytes at both ends, a footer with a summary, and the summary's CRC."""
    try:
        size = path.stat().st_size
        with open(path, 'rb') as stream:
            head = stream.read(len(_MAGIC))
            if head != _MAGIC:
                raise BagError(f'{path}: not an MCAP file (no MCAP magic bytes at the start)')
            if size < 2 * len(_MAGIC) + _FOOTER_RECORD:
                raise BagError(f'{path}: truncated MCAP file ({size} bytes, no footer)')
            stream.seek(size - len(_MAGIC) - _FOOTER_RECORD)
            tail = stream.read()
            if tail[0] != _FOOTER_OPCODE or tail[-len(_MAGIC):] != _MAGIC:
                raise BagError(f'{path}: truncated MCAP file (no footer: the writer did not '
                               'close it)')
            summary_start, _, summary_crc = struct.unpack('<QQI', tail[9:29])
            if summary_start == 0:
                raise BagError(f'{path}: the MCAP file has no summary section (rosbag2 needs '
                               'its Statistics record)')
            crc_end = size - len(_MAGIC) - 4
            if not len(_MAGIC) <= summary_start < crc_end:
                raise BagError(f'{path}: corrupt MCAP footer (summary offset {summary_start} '
                               f'outside the file)')
            if summary_crc:
                stream.seek(summary_start)
                if zlib.crc32(stream.read(crc_end - summary_start)) != summary_crc:
                    raise BagError(f'{path}: corrupt MCAP file (summary section CRC mismatch)')
    except OSError as exc:
        raise BagError(f'{path}: cannot read: {exc.strerror}') from None


@dataclass
class _Contents:
    reader: SeekingReader
    summary: Any
    topic_types: dict[int, str]            # channel id -> type name
    qos: dict[int, list]                   # channel id -> offered profiles


def _open_contents(path: Path, stream) -> _Contents:
    """Check the header, summary and channels; BagError for anything rosbag2 would not play."""
    try:
        reader = SeekingReader(stream, validate_crcs=True)
        header = reader.get_header()
        summary = reader.get_summary()
    except BagError:
        raise
    except Exception as exc:  # noqa: BLE001 - the mcap parser raises many types on bad bytes
        raise BagError(f'{path}: corrupt MCAP file ({type(exc).__name__}: {exc})') from None
    if header.profile != PROFILE:
        raise BagError(f'{path}: MCAP profile is {header.profile!r}, not {PROFILE!r} '
                       '(not a ROS 2 bag)')
    if summary is None or summary.statistics is None:
        raise BagError(f'{path}: the MCAP file has no Statistics record')
    topic_types: dict[int, str] = {}
    qos: dict[int, list] = {}
    for channel_id, channel in summary.channels.items():
        if channel.message_encoding != MESSAGE_ENCODING:
            raise BagError(f'{path}: topic {channel.topic} is encoded as '
                           f'{channel.message_encoding!r}, not {MESSAGE_ENCODING!r}')
        schema = summary.schemas.get(channel.schema_id)
        if schema is None:
            raise BagError(f'{path}: topic {channel.topic} has no schema (message type)')
        if schema.encoding not in (SCHEMA_ENCODING, 'ros2idl'):
            raise BagError(f'{path}: topic {channel.topic} has a {schema.encoding!r} schema, '
                           f'not {SCHEMA_ENCODING!r}')
        topic_types[channel_id] = full_type_name(schema.name)
        qos[channel_id] = parse_qos_profiles(channel.metadata.get('offered_qos_profiles'))
    return _Contents(reader, summary, topic_types, qos)


def read_bag(path: str | os.PathLike,
             topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Yield the messages of a bag (a .mcap file or a bag directory) in log-time order.

    ``topics``: only these topics. Raises `BagError` for a bag that is missing, not MCAP,
    truncated or corrupt (also part way through: chunk CRCs are checked as chunks are read).
    """
    bag_file = resolve_bag_file(path)
    _check_container(bag_file)
    wanted = None if topics is None else set(topics)
    with open(bag_file, 'rb') as stream:
        contents = _open_contents(bag_file, stream)
        try:
            for _schema, channel, message in contents.reader.iter_messages(
                    topics=None if wanted is None else sorted(wanted), log_time_order=True):
                yield BagMessage(channel.topic, contents.topic_types[channel.id],
                                 message.log_time, message.publish_time, bytes(message.data),
                                 contents.qos[channel.id])
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 - the mcap parser raises many types on bad bytes
            raise BagError(f'{bag_file}: corrupt MCAP data ({type(exc).__name__}: '
                           f'{exc})') from None


def bag_info(path: str | os.PathLike, verify: bool = True) -> BagInfo:
    """The summary of a bag: topics, types, counts, start, end, duration.

    ``verify`` also reads every chunk (checking CRCs) and compares the message counts with the
    Statistics record, so a damaged bag is refused here and not half way through a replay.
    """
    bag_file = resolve_bag_file(path)
    _check_container(bag_file)
    with open(bag_file, 'rb') as stream:
        contents = _open_contents(bag_file, stream)
    statistics = contents.summary.statistics
    counts = dict(statistics.channel_message_counts)
    if verify:
        seen: dict[str, int] = {}
        for bag_message in read_bag(bag_file):
            seen[bag_message.topic] = seen.get(bag_message.topic, 0) + 1
        for channel_id, channel in contents.summary.channels.items():
            if seen.get(channel.topic, 0) != counts.get(channel_id, 0):
                raise BagError(f'{bag_file}: corrupt MCAP file ({channel.topic}: '
                               f'{seen.get(channel.topic, 0)} messages, the summary says '
                               f'{counts.get(channel_id, 0)})')
    topics = [TopicInfo(channel.topic, contents.topic_types[channel_id],
                        int(counts.get(channel_id, 0)), contents.qos[channel_id],
                        channel.metadata.get('topic_type_hash', ''))
              for channel_id, channel in sorted(contents.summary.channels.items())]
    return BagInfo(bag_file, bag_file.stat().st_size, topics, int(statistics.message_count),
                   int(statistics.message_start_time), int(statistics.message_end_time))


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
        self.message_count = 0
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
            self.message_count += 1
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
    interrupted: bool        # the context shut down (Ctrl-C) before the last message


PLAY_ORDERS = ('log', 'publish')


def play(path: str | os.PathLike, node: Any = None, rate: float = 1.0,
         topics: Iterable[str] | None = None, start_delay: float = 0.0,
         wait_for_subscribers: float = 0.0, ack_timeout: float = 2.0,
         on_publish: Callable[[BagMessage], None] | None = None,
         order: str = 'log') -> PlayResult:
    """Publish a bag's messages (serialized, as recorded) with the recorded timing / ``rate``.

    Message i goes out at t0 + (time_i - time_0) / rate on the monotonic clock (no
    accumulated sleep drift), t0 = start + ``start_delay``, where time is the log (receive)
    time with ``order='log'``, as `ros2 bag play` does, or the publish time (the writers'
    source timestamps) with ``order='publish'``: the order the messages were sent in, which on
    one host is their causal order, while the recorder may have taken two messages of
    different writers in the other order. 'publish' sorts the bag in memory. Each topic's
    publisher uses
    `qos_from_offers` of the recorded profiles. ``wait_for_subscribers``: wait up to that many
    seconds for every publisher to match a subscription first. At the end, reliable
    publishers wait up to ``ack_timeout`` s for their messages to be acknowledged. Without a
    ``node`` a private rclpy context and node are made and torn down. Stops early (returning
    what was played) when the node's context shuts down, e.g. on Ctrl-C.
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
    import rclpy
    import rclpy.context
    from rclpy.duration import Duration
    from rclpy.qos import QoSReliabilityPolicy
    own_context = None
    if node is None:
        own_context = rclpy.context.Context()
        rclpy.init(context=own_context)
        node = rclpy.create_node('hrc_bag_player', context=own_context)
    context = node.context
    publishers = {}
    try:
        for topic in info.topics:
            if topic.topic in wanted:
                publishers[topic.topic] = node.create_publisher(
                    message_class(topic.type_name), topic.topic,
                    qos_from_offers(topic.qos_profiles))
        deadline = time.monotonic() + max(0.0, wait_for_subscribers)
        while (wait_for_subscribers > 0 and context.ok() and time.monotonic() < deadline
               and any(p.get_subscription_count() < 1 for p in publishers.values())):
            time.sleep(0.02)
        count, first_ns, start, last_wall = 0, None, 0.0, 0.0
        messages = read_bag(info.path, topics=wanted)
        if order == 'publish':
            messages = sorted(messages, key=lambda m: m.publish_time_ns)

        def timestamp(m: BagMessage) -> int:
            return m.publish_time_ns if order == 'publish' else m.log_time_ns

        for bag_message in messages:
            if first_ns is None:
                first_ns = timestamp(bag_message)
                start = time.monotonic() + max(0.0, start_delay)
            due = start + (timestamp(bag_message) - first_ns) / 1e9 / rate
            while context.ok() and (remaining := due - time.monotonic()) > 0:
                time.sleep(min(remaining, 0.05))
            if not context.ok():
                break
            publishers[bag_message.topic].publish(bag_message.data)
            last_wall = time.monotonic()
            count += 1
            if on_publish is not None:
                on_publish(bag_message)
        for topic in info.topics:
            if (topic.topic in publishers and context.ok()
                    and qos_from_offers(topic.qos_profiles).reliability
                    == QoSReliabilityPolicy.RELIABLE):
                publishers[topic.topic].wait_for_all_acked(Duration(seconds=ack_timeout))
        return PlayResult(count, max(0.0, last_wall - start) if count else 0.0,
                          interrupted=not context.ok())
    finally:
        if context.ok():
            for publisher in publishers.values():
                node.destroy_publisher(publisher)
        if own_context is not None:
            node.destroy_node()
            rclpy.try_shutdown(context=own_context)


# --------------------------------------------------------------------------------------------
# hrc-bag


def _wait_for_topics(node: Any, topics: list[str], timeout: float) -> dict[str, str]:
    """topic -> type once every topic has a publisher; BagError after ``timeout`` seconds."""
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
        now = time.monotonic()
        if now >= deadline:
            raise BagError(f'no publisher appeared within {timeout:g} s on '
                           f'{", ".join(missing)}')
        if now >= next_notice:
            print(f'hrc-bag: waiting for {", ".join(missing)}', flush=True)
            next_notice = now + 2.0
        rclpy.spin_once(node, timeout_sec=0.05)


def _record_command(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    writer = recorder = node = None
    started = time.monotonic()
    try:
        rclpy.init()
        node = rclpy.create_node('hrc_bag_recorder')
        topics = [node.resolve_topic_name(t) for t in args.topics]
        types = _wait_for_topics(node, topics, args.wait_timeout)
        writer = BagWriter(args.output)
        recorder = Recorder(node, types, writer)
        print(f'hrc-bag: recording {", ".join(topics)} to {writer.path}', flush=True)
        started = time.monotonic()
        reported = -1
        next_status = 0.0
        while True:
            rclpy.spin_once(node, timeout_sec=0.05)
            now = time.monotonic()
            if recorder.message_count != reported and now >= next_status:
                reported = recorder.message_count
                print(f'hrc-bag: recorded {reported} messages', flush=True)
                next_status = now + 1.0
            if args.duration is not None and now - started >= args.duration:
                break
            if args.max_messages is not None and recorder.message_count >= args.max_messages:
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if recorder is not None:
            try:
                recorder.close()
            except Exception:  # noqa: BLE001 - the context may already be shut down
                pass
        if writer is not None:
            writer.close()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if writer is None:
        return 130
    print(f'hrc-bag: recorded {writer.message_count} messages on {len(writer.topics)} '
          f'topic(s) in {time.monotonic() - started:.1f} s to {writer.path} '
          f'({format_size(writer.path.stat().st_size)})', flush=True)
    return 0


def _play_command(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    info = bag_info(args.bag)
    print(f'hrc-bag: playing {info.path}: {info.message_count} messages, '
          f'{info.duration_ns / 1e9:.3f} s at rate {args.rate:g}', flush=True)
    rclpy.init()
    node = rclpy.create_node('hrc_bag_player')
    try:
        result = play(info.path, node=node, rate=args.rate, topics=args.topics,
                      start_delay=args.start_delay,
                      wait_for_subscribers=args.wait_for_subscribers, order=args.order)
    except (KeyboardInterrupt, ExternalShutdownException):
        print('hrc-bag: playback interrupted', flush=True)
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'hrc-bag: {"interrupted after" if result.interrupted else "played"} '
          f'{result.message_count} messages in {result.duration_s:.3f} s', flush=True)
    return 0


def _info_command(args: argparse.Namespace) -> int:
    print(bag_info(args.bag, verify=not args.quick).format())
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='hrc-bag', description='Record, play and inspect rosbag2-compatible MCAP bags.')
    commands = parser.add_subparsers(dest='command', required=True)
    record = commands.add_parser('record', help='record topics into a bag directory')
    record.add_argument('-o', '--output', required=True,
                        help='bag directory to create (or a file name ending in .mcap)')
    record.add_argument('--duration', type=float, default=None, help='stop after S seconds')
    record.add_argument('--max-messages', type=int, default=None,
                        help='stop after N messages')
    record.add_argument('--wait-timeout', type=float, default=10.0,
                        help='seconds to wait for every topic to have a publisher (default 10)')
    record.add_argument('topics', nargs='+', metavar='TOPIC')
    player = commands.add_parser('play', help='publish a bag with its recorded timing')
    player.add_argument('bag', metavar='FILE_OR_DIR')
    player.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    player.add_argument('--topics', nargs='+', default=None, metavar='T',
                        help='play only these topics')
    player.add_argument('--start-delay', type=float, default=0.0,
                        help='seconds to wait before the first message')
    player.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='S',
                        help='wait up to S s for every topic to have a subscriber')
    player.add_argument('--order', choices=PLAY_ORDERS, default='log',
                        help="timing and order by 'log' (receive) time, as ros2 bag play, or "
                        "by 'publish' time, the order the writers sent them in (default log)")
    info = commands.add_parser('info', help='print a bag summary')
    info.add_argument('bag', metavar='FILE_OR_DIR')
    info.add_argument('--quick', action='store_true',
                      help='read the summary only (do not check every chunk)')
    args = parser.parse_args(argv)
    handlers = {'record': _record_command, 'play': _play_command, 'info': _info_command}
    try:
        return handlers[args.command](args)
    except BagError as exc:
        print(f'hrc-bag: {" ".join(str(exc).split())}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
