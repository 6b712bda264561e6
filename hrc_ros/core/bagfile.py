"""rosbag2-compatible MCAP bags without ROS: the file format (write, read, check).

Recording from and playing onto the graph (rclpy serialization, QoS objects, `hrc-bag`) is the
ring's half, `hrc_ros.ros.bag`; this half handles CDR bytes and plain QoS dicts only.

Why: rosbag2 (`ros2 bag`) is not installable on the project's machines, yet the suite is tested
"as a user starts it, fed from a recorded bag", and bags recorded here must play in a real ROS
install (and the other way round). So this module writes exactly the layout rosbag2 jazzy's
`rosbag2_storage_mcap` plugin writes and reads, using the `mcap` library for the container.
Checked against rosbag2's sources (`rosbag2_storage_mcap` `mcap_storage.cpp` and
`message_definition_cache.cpp`, `rosbag2_storage` `qos.cpp` and `yaml.hpp`, pull request
ros2/rosbag2#1476 that made metadata version 9).

Format notes (an MCAP file):

- Header profile ``ros2``. A ``rosbag2`` Metadata record (key ``serialized_metadata``: the YAML
  of rosbag2's BagMetadata, every field of metadata.yaml's ``rosbag2_bagfile_information``), as
  rosbag2_storage_mcap writes it, so ``ros2 bag info file.mcap`` on the file alone knows the
  distribution; `bag_info` reads it back (`BagInfo.ros_distro`).
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

A bag is untrusted input (`paths`): the file must be a regular file within the 'bag' cap, its
summary section within 'bag_metadata', and before any chunk is inflated (`_check_chunks`) each
chunk's record is read from the file and compared with its index, and what it can inflate to
is bounded by its compression's own frame header: the content size a zstd or lz4 frame
declares must be the chunk's declared uncompressed size (the `mcap` reader hands that size to
zstandard as the output bound, but zstandard allocates what the frame says, so an 88 KB file
would inflate to 1 GiB), an lz4 frame without one is bounded by its block count times its
block size. Each chunk may inflate to at most the 'bag_chunk' cap and all of them together to
'bag_inflated'. A bag without a chunk index, which the `mcap` reader reads linearly, has every
record checked the same way. What the errors quote of a bag (topic names, encodings, the
parser's messages) is capped.
"""

from __future__ import annotations

import json
import os
import struct
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import yaml
from mcap.reader import SeekingReader
from mcap.writer import CompressionType, Writer

from .paths import (MIB, ament_share_dir, file_limit, folder_target, input_stat, open_input,
                    output_target, parse_yaml, read_yaml, write_text)
from .quoting import QUOTE_LIMIT, cap, quote

PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
METADATA_VERSION = 9          # rosbag2 jazzy's BagMetadata::version
ROS_DISTRO = 'jazzy'
METADATA_FILE = 'metadata.yaml'
ROSBAG2_METADATA = 'rosbag2'    # the MCAP metadata record rosbag2_storage_mcap reads and writes
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
_CHUNK_OPCODE = 0x06
_DATA_END_OPCODE = 0x0F
_CHUNK_HEAD = 1 + 8 + 8 + 8 + 8 + 4 + 4   # opcode, length, start, end, size, crc, name length
_ZSTD_MAGIC = 0xFD2FB528
_LZ4_MAGIC = 0x184D2204
_LZ4_BLOCK_BYTES = {4: 64 << 10, 5: 256 << 10, 6: 1 << 20, 7: 4 << 20}   # by BD's block id


class BagError(RuntimeError):
    """A bag cannot be read or written: missing, not MCAP, truncated, corrupt or not ROS 2."""


# --------------------------------------------------------------------------------------------
# Message types: names, .msg definitions, type hashes

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
    """Where a message package's .msg files may be: its ament share folder, then the
    interpreter prefix's share folder (the pip wheels put them there)."""
    indexed = ament_share_dir(package)
    return ([indexed] if indexed is not None else []) + [Path(sys.prefix) / 'share' / package]


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


# --------------------------------------------------------------------------------------------
# QoS profiles <-> rosbag2's YAML

def duration_fields(nanoseconds: int) -> dict:
    return {'sec': int(nanoseconds) // 10 ** 9, 'nsec': int(nanoseconds) % 10 ** 9}


def qos_dict(profile: Mapping) -> dict:
    """A QoS profile mapping completed with rosbag2's defaults, keys in rosbag2's order."""
    return {key: profile.get(key, DEFAULT_QOS[key]) for key in QOS_KEYS}


class _RosbagDumper(yaml.SafeDumper):
    """yaml-cpp's block style: a sequence under a key is indented, keys keep their order."""

    def increase_indent(self, flow=False, indentless=False):
        return super().increase_indent(flow, False)


def _dump_yaml(data: Any) -> str:
    return yaml.dump(data, Dumper=_RosbagDumper, sort_keys=False, default_flow_style=False,
                     allow_unicode=True)


def qos_profiles_yaml(profiles: Sequence[Mapping]) -> str:
    """The ``offered_qos_profiles`` channel metadata string (YAML::Dump form, no final newline).

    An empty list is written as ``''``, as rosbag2 reads an empty string as no profiles.
    """
    if not profiles:
        return ''
    return _dump_yaml([qos_dict(p) for p in profiles]).rstrip('\n')


def policy_name(key: str, value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return 'unknown'
    if isinstance(value, int):
        names = _LEGACY_POLICY_NAMES[key]
        return names[value] if 0 <= value < len(names) else 'unknown'
    return str(value)


def duration_ns(value: Any) -> int:
    if isinstance(value, Mapping):
        return int(value.get('sec', 0)) * 10 ** 9 + int(value.get('nsec', 0))
    return 0


def parse_qos_profiles(text: str | None) -> list[dict]:
    """The profiles of an ``offered_qos_profiles`` string (metadata version 9 or older)."""
    if not text:
        return []
    if len(text) > file_limit('bag_metadata', BagError):
        raise BagError(f'offered_qos_profiles holds {len(text):,} characters, more than a '
                       'bag\'s metadata may have here (HRC_ROS_LIMIT_BAG_METADATA)')
    loaded = parse_yaml(text, BagError, 'offered_qos_profiles')
    if loaded is None:
        return []
    if not isinstance(loaded, list) or not all(isinstance(p, Mapping) for p in loaded):
        raise BagError('offered_qos_profiles is not a YAML list of QoS profiles')
    profiles = []
    for raw in loaded:
        profile = {key: raw.get(key, DEFAULT_QOS[key]) for key in QOS_KEYS}
        for key in _LEGACY_POLICY_NAMES:
            profile[key] = policy_name(key, profile[key])
        profiles.append(profile)
    return profiles


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
            try:
                self.path = output_target(target)   # a link only to a regular file
            except OSError as exc:
                raise BagError(f'cannot write {target}: {exc.strerror}') from None
        else:
            try:
                target = folder_target(target, empty=True)
            except OSError as exc:
                raise BagError(f'cannot record into {target}: {exc.strerror}') from None
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

    @property
    def message_counts(self) -> dict[str, int]:
        """topic -> messages written on it so far (0 for a topic added and never written)."""
        return {name: record.message_count for name, record in self._topics.items()}

    def add_topic(self, topic: str, type_name: str, qos: Sequence[Mapping] | None = None, *,
                  topic_type_hash: str | None = None) -> None:
        """Declare a topic (a channel, with its type's schema the first time it is seen).

        ``qos``: a list of QoS profile mappings (one per recorded publisher, rosbag2's keys),
        or None for reliable / volatile / keep last 10. ``topic_type_hash`` defaults to the
        installed hash.
        """
        self._check_open()
        name = full_type_name(type_name)
        if topic in self._topics:
            if self._topics[topic].type_name != name:
                raise BagError(f'topic {topic} was added as {self._topics[topic].type_name}, '
                               f'not {name}')
            return
        profiles = [dict(DEFAULT_QOS)] if qos is None else [qos_dict(p) for p in qos]
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

    def topic_type(self, topic: str) -> str:
        """The type name of an added topic; BagError if it was not added."""
        record = self._topics.get(topic)
        if record is None:
            raise BagError(f'topic {topic} was not added to the bag (call add_topic first)')
        return record.type_name

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Write one message, its CDR bytes, received at ``log_time_ns``."""
        self._check_open()
        self.topic_type(topic)
        record = self._topics[topic]
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise BagError(f'a message on {topic} must be written as its CDR bytes, not a '
                           f'{type(data).__name__} (hrc_ros.ros.bag.BagWriter serializes)')
        data = bytes(data)
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
        """Write the `rosbag2` metadata record, the summary section and footer (and
        metadata.yaml for a directory)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.add_metadata(ROSBAG2_METADATA, {
                'serialized_metadata': _dump_yaml(self.bag_information())})
            self._writer.finish()
        finally:
            self._stream.close()
        if self.directory is not None:
            write_text(self.directory / METADATA_FILE, self.metadata_yaml())

    def metadata_yaml(self) -> str:
        """rosbag2 jazzy's ``metadata.yaml`` for this bag (metadata version 9)."""
        return _dump_yaml({'rosbag2_bagfile_information': self.bag_information()})

    def bag_information(self) -> dict:
        """rosbag2's BagMetadata of this bag: metadata.yaml's `rosbag2_bagfile_information`,
        which is also the `serialized_metadata` of the MCAP's `rosbag2` metadata record."""
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
        return information

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
    decoded: Any = field(default=None, compare=False)   # with read_bag(decode=True)
    decode_error: str = field(default='', compare=False)   # why `decoded` is None, if it is


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
    metadata: dict = field(default_factory=dict)   # the rosbag2 record's BagMetadata, if any

    @property
    def ros_distro(self) -> str:
        return str(self.metadata.get('ros_distro') or 'unknown')

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
            f'ROS Distro:        {self.ros_distro}',
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
                info = read_yaml(metadata, BagError, 'bag metadata', kind='bag_metadata')
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
    if os.path.lexists(target):   # a loop of links, a FIFO, a device: say which
        input_stat(target, BagError, 'bag')
    raise BagError(f'{cap(target, 300)}: no such file or directory')


def _open_bag(path: Path):
    """The bag file opened for reading (`paths.open_input`, the 'bag' cap)."""
    return open_input(path, BagError, 'bag', 'MCAP bag')


def _check_container(path: Path) -> None:
    """Magic bytes at both ends, a footer with a summary, and the summary's size and CRC."""
    try:
        with _open_bag(path) as stream:
            size = os.fstat(stream.fileno()).st_size
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
            summary_limit = file_limit('bag_metadata', BagError)
            if crc_end - summary_start > summary_limit:
                raise BagError(f'{path}: its summary section holds {crc_end - summary_start:,} '
                               f'bytes, more than the {summary_limit:,} a bag\'s metadata may '
                               'have here (HRC_ROS_LIMIT_BAG_METADATA)')
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
    record_limit = max(file_limit('bag_chunk', BagError), file_limit('bag_metadata', BagError))
    try:
        reader = SeekingReader(stream, validate_crcs=True, record_size_limit=record_limit + MIB)
        header = reader.get_header()
        summary = reader.get_summary()
    except BagError:
        raise
    except Exception as exc:  # noqa: BLE001 - the mcap parser raises many types on bad bytes
        raise BagError(f'{path}: corrupt MCAP file ({type(exc).__name__}: {cap(exc)})') from None
    if header.profile != PROFILE:
        raise BagError(f'{path}: MCAP profile is {quote(header.profile)}, not {PROFILE!r} '
                       '(not a ROS 2 bag)')
    if summary is None or summary.statistics is None:
        raise BagError(f'{path}: the MCAP file has no Statistics record')
    topic_types: dict[int, str] = {}
    qos: dict[int, list] = {}
    for channel_id, channel in summary.channels.items():
        topic = quote(channel.topic)
        if channel.message_encoding != MESSAGE_ENCODING:
            raise BagError(f'{path}: topic {topic} is encoded as '
                           f'{quote(channel.message_encoding)}, not {MESSAGE_ENCODING!r}')
        schema = summary.schemas.get(channel.schema_id)
        if schema is None:
            raise BagError(f'{path}: topic {topic} has no schema (message type)')
        if schema.encoding not in (SCHEMA_ENCODING, 'ros2idl'):
            raise BagError(f'{path}: topic {topic} has a {quote(schema.encoding)} schema, '
                           f'not {SCHEMA_ENCODING!r}')
        try:
            topic_types[channel_id] = full_type_name(schema.name)
            qos[channel_id] = parse_qos_profiles(channel.metadata.get('offered_qos_profiles'))
        except BagError as exc:
            raise BagError(f'{path}: topic {topic}: {exc}') from None
    _check_chunks(path, stream, summary)
    return _Contents(reader, summary, topic_types, qos)


def _check_chunks(path: Path, stream, summary) -> None:
    """Bound what inflating the chunks can cost, before any is inflated (module docstring):
    each chunk record against its index and its frame header, at most the 'bag_chunk' cap
    each and 'bag_inflated' together; without a chunk index, every record of the data
    section, as the `mcap` reader will then read them all."""
    per_chunk = file_limit('bag_chunk', BagError)
    total_limit = file_limit('bag_inflated', BagError)
    size = os.fstat(stream.fileno()).st_size
    if summary.chunk_indexes:
        chunks = ((index.chunk_start_offset, index) for index in summary.chunk_indexes)
    else:
        chunks = ((offset, None) for offset in _chunk_offsets(path, stream, size, per_chunk))
    total = 0
    try:
        for offset, index in chunks:
            total += _chunk_inflated(path, stream, size, offset, index, per_chunk)
            if total > total_limit:
                raise BagError(f'{path}: its chunks inflate to more than {total_limit:,} bytes '
                               'together, the most a bag may hold here (a site that needs more '
                               'sets HRC_ROS_LIMIT_BAG_INFLATED)')
    except (OSError, struct.error) as exc:
        raise BagError(f'{path}: corrupt MCAP file ({type(exc).__name__}: {cap(exc)})') from None


def _chunk_offsets(path: Path, stream, size: int, per_record: int):
    """The offsets of the Chunk records of a file without a chunk index: its records walked
    from the magic to the Data End record, each bounded like a chunk."""
    offset = len(_MAGIC)
    while offset + 9 <= size:
        stream.seek(offset)
        opcode, length = struct.unpack('<BQ', stream.read(9))
        if opcode == _DATA_END_OPCODE or opcode == _FOOTER_OPCODE:
            return
        if length > per_record + per_record // 64 + 4096:
            raise BagError(f'{path}: a record at byte {offset:,} holds {length:,} bytes, more '
                           f'than the {per_record:,} a bag chunk may have here '
                           '(HRC_ROS_LIMIT_BAG_CHUNK)')
        if opcode == _CHUNK_OPCODE:
            yield offset
        offset += 9 + length


def _corrupt_chunk(path: Path, offset: int, what: str) -> BagError:
    return BagError(f'{path}: corrupt MCAP file (the chunk at byte {offset:,} {what})')


def _chunk_inflated(path: Path, stream, size: int, offset: int, index, per_chunk: int) -> int:
    """The most bytes the chunk record at `offset` can inflate to, read from its record and
    its frame header (its index, if any, must agree); BagError past `per_chunk`."""
    stream.seek(offset)
    head = stream.read(_CHUNK_HEAD)
    if len(head) < _CHUNK_HEAD or head[0] != _CHUNK_OPCODE:
        raise _corrupt_chunk(path, offset, 'is not a chunk record')
    _, _, _, declared, _, name_length = struct.unpack('<QQQQII', head[1:])
    if name_length > 16:
        raise _corrupt_chunk(path, offset, f'names a compression of {name_length:,} bytes')
    compression = stream.read(name_length).decode('utf-8', 'replace')
    (data_length,) = struct.unpack('<Q', stream.read(8))
    data_start = stream.tell()
    if data_start + data_length > size:
        raise _corrupt_chunk(path, offset, 'runs past the end of the file')
    if index is not None and (index.compression, index.uncompressed_size,
                              index.compressed_size) != (compression, declared, data_length):
        raise _corrupt_chunk(path, offset, 'is not what its index says')
    if compression == '':
        inflated = data_length
    elif compression == 'zstd':
        framed = _zstd_content_size(stream.read(18))
        if framed is False:
            raise _corrupt_chunk(path, offset, 'does not begin with a zstd frame')
        if framed is not None and framed != declared:
            raise _corrupt_chunk(path, offset, f'declares {declared:,} bytes, its zstd frame '
                                 f'{framed:,}')
        inflated = declared      # mcap hands it to zstandard as the bound without a frame size
    elif compression == 'lz4':
        inflated = _lz4_inflated(path, stream, offset, data_start, data_length, declared,
                                 per_chunk)
    else:
        inflated = declared      # the mcap reader refuses an unknown compression itself
    if inflated > per_chunk or data_length > per_chunk + per_chunk // 64 + 4096:
        raise BagError(f'{path}: the chunk at byte {offset:,} inflates to {inflated:,} bytes, '
                       f'more than the {per_chunk:,} a bag chunk may have here (a site that '
                       'needs more sets HRC_ROS_LIMIT_BAG_CHUNK)')
    return inflated


def _zstd_content_size(head: bytes):
    """The content size a zstd frame header declares (RFC 8878 3.1.1.1), None when it declares
    none, False when `head` is not the start of a zstd frame."""
    if len(head) < 6 or int.from_bytes(head[:4], 'little') != _ZSTD_MAGIC:
        return False
    descriptor = head[4]
    size_flag, single_segment, dictionary_flag = descriptor >> 6, descriptor >> 5 & 1, \
        descriptor & 3
    at = 5 + (0 if single_segment else 1) + (0, 1, 2, 4)[dictionary_flag]
    width = (single_segment, 2, 4, 8)[size_flag]
    if width == 0:
        return None
    if len(head) < at + width:
        return False
    value = int.from_bytes(head[at:at + width], 'little')
    return value + 256 if width == 2 else value


def _lz4_inflated(path: Path, stream, offset: int, start: int, length: int, declared: int,
                  limit: int) -> int:
    """The most bytes the lz4 frame of a chunk inflates to (the lz4 frame format): the content
    size its header declares (which must be `declared`; lz4 stops there), else its blocks
    times their maximum size, counted until past `limit`."""
    stream.seek(start)
    head = stream.read(min(length, 15))
    if len(head) < 7 or int.from_bytes(head[:4], 'little') != _LZ4_MAGIC or head[4] >> 6 != 1:
        raise _corrupt_chunk(path, offset, 'does not begin with an lz4 frame')
    flags, block_id = head[4], head[5] >> 4 & 7
    if flags & 0x08:
        framed = int.from_bytes(head[6:14], 'little')
        if framed != declared:
            raise _corrupt_chunk(path, offset, f'declares {declared:,} bytes, its lz4 frame '
                                 f'{framed:,}')
        return framed
    if block_id not in _LZ4_BLOCK_BYTES:
        raise _corrupt_chunk(path, offset, 'has an lz4 frame of an unknown block size')
    block_bytes = _LZ4_BLOCK_BYTES[block_id]
    checksum = 4 if flags & 0x10 else 0
    at, end, inflated = start + 7 + (4 if flags & 0x01 else 0), start + length, 0
    while at + 4 <= end and inflated <= limit:
        stream.seek(at)
        (block,) = struct.unpack('<I', stream.read(4))
        if block == 0:           # the end mark: mcap's lz4 reads this one frame only
            break
        inflated += block_bytes
        at += 4 + (block & 0x7FFFFFFF) + checksum
    return inflated


def _decoder_factory():
    """mcap_ros2's CDR decoder, which builds each message type from the schema text stored in
    the bag (no ROS needed)."""
    try:
        from mcap_ros2.decoder import DecoderFactory
    except ImportError:
        raise BagError('decoding bag messages without ROS needs mcap_ros2: pip install '
                       'mcap-ros2-support') from None
    return DecoderFactory()


def read_bag(path: str | os.PathLike, topics: Iterable[str] | None = None,
             decode: bool = False) -> Iterator[BagMessage]:
    """Yield the messages of a bag (a .mcap file or a bag directory) in log-time order.

    ``topics``: only these topics. ``decode``: also decode each message from its schema text
    (`BagMessage.decoded`, mcap_ros2's dynamic message: fields as attributes); a message whose
    bytes its schema cannot decode comes with ``decoded`` None and `BagMessage.decode_error`
    saying why, so that one bad message does not cost the rest of the bag: the caller reports
    and skips it. Raises `BagError` for a bag that is missing, not MCAP, truncated or corrupt
    (also part way through: chunk CRCs are checked as chunks are read), and for a topic whose
    schema gives no decoder.
    """
    bag_file = resolve_bag_file(path)
    _check_container(bag_file)
    wanted = None if topics is None else set(topics)
    factory = _decoder_factory() if decode else None
    with _open_bag(bag_file) as stream:
        contents = _open_contents(bag_file, stream)
        try:
            for schema, channel, message in contents.reader.iter_messages(
                    topics=None if wanted is None else sorted(wanted), log_time_order=True):
                decoded, decode_error = None, ''
                if factory is not None:
                    decoder = factory.decoder_for(channel.message_encoding, schema)
                    if decoder is None:
                        raise BagError(f'{bag_file}: topic {quote(channel.topic)} has no '
                                       'ros2msg schema to decode it with')
                    try:
                        decoded = decoder(message.data)
                    except Exception as exc:  # noqa: BLE001 - bad CDR: struct.error, ValueError..
                        decode_error = (f'its {len(message.data)} CDR bytes do not decode as '
                                        f'{cap(schema.name, QUOTE_LIMIT)}: '
                                        f'{type(exc).__name__}: {cap(exc)}')
                yield BagMessage(channel.topic, contents.topic_types[channel.id],
                                 message.log_time, message.publish_time, bytes(message.data),
                                 contents.qos[channel.id], decoded, decode_error)
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 - the mcap parser raises many types on bad bytes
            raise BagError(f'{bag_file}: corrupt MCAP data ({type(exc).__name__}: '
                           f'{cap(exc)})') from None


def bag_info(path: str | os.PathLike, verify: bool = True) -> BagInfo:
    """The summary of a bag: topics, types, counts, start, end, duration.

    ``verify`` also reads every chunk (checking CRCs) and compares the message counts with the
    Statistics record, so a damaged bag is refused here and not half way through a replay.
    """
    bag_file = resolve_bag_file(path)
    _check_container(bag_file)
    with _open_bag(bag_file) as stream:
        contents = _open_contents(bag_file, stream)
        metadata = _rosbag2_metadata(bag_file, contents.reader)
    statistics = contents.summary.statistics
    counts = dict(statistics.channel_message_counts)
    if verify:
        seen: dict[str, int] = {}
        for bag_message in read_bag(bag_file):
            seen[bag_message.topic] = seen.get(bag_message.topic, 0) + 1
        for channel_id, channel in contents.summary.channels.items():
            if seen.get(channel.topic, 0) != counts.get(channel_id, 0):
                raise BagError(f'{bag_file}: corrupt MCAP file ({quote(channel.topic)}: '
                               f'{seen.get(channel.topic, 0)} messages, the summary says '
                               f'{counts.get(channel_id, 0)})')
    topics = [TopicInfo(channel.topic, contents.topic_types[channel_id],
                        int(counts.get(channel_id, 0)), contents.qos[channel_id],
                        channel.metadata.get('topic_type_hash', ''))
              for channel_id, channel in sorted(contents.summary.channels.items())]
    return BagInfo(bag_file, bag_file.stat().st_size, topics, int(statistics.message_count),
                   int(statistics.message_start_time), int(statistics.message_end_time),
                   metadata)


def _rosbag2_metadata(bag_file: Path, reader) -> dict:
    """The BagMetadata of the last `rosbag2` Metadata record ({} without one); BagError for a
    record rosbag2 could not read either."""
    found: dict = {}
    try:
        for record in reader.iter_metadata():
            if record.name == ROSBAG2_METADATA:
                text = record.metadata.get('serialized_metadata', '')
                if len(text) > file_limit('bag_metadata', BagError):
                    raise BagError(f'{bag_file}: its rosbag2 metadata record holds '
                                   f'{len(text):,} characters, more than a bag\'s metadata may '
                                   'have here (HRC_ROS_LIMIT_BAG_METADATA)')
                found = parse_yaml(text, BagError,
                                   f'{bag_file}: its rosbag2 metadata record') or {}
    except BagError:
        raise
    except Exception as exc:  # noqa: BLE001 - the mcap parser raises many types on bad bytes
        raise BagError(f'{bag_file}: corrupt MCAP metadata ({type(exc).__name__})') from None
    if not isinstance(found, dict):
        raise BagError(f'{bag_file}: its rosbag2 metadata record is not a mapping')
    return found
