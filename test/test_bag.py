"""hrc_ros.ros.bag: rosbag2-compatible MCAP bags, checked against independent readers and live DDS.

Independent references: the installed .msg files and rosidl_adapter's .msg parser (schema
text), mcap_ros2 decoding from the schema text alone in a process where rclpy and the message
packages cannot be imported (CDR), the raw mcap reader (profile, encodings, channel metadata)
and real processes on a private DDS domain (record -> play).
"""

from __future__ import annotations

import json
import os
import random
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import rclpy
import yaml
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseArray, Quaternion
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import (QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy,
                       qos_profile_sensor_data)
from rosidl_adapter.parser import parse_message_string
from sensor_msgs.msg import JointState
from std_msgs.msg import (Bool, Float64MultiArray, Header, MultiArrayDimension, MultiArrayLayout,
                          String, UInt8, UInt8MultiArray, UInt32)

from hrc_ros.core import bagfile
from hrc_ros.ros import bag
from hrc_ros.ros.bag import BagError, BagWriter

SEPARATOR = '=' * 80
SHARE = Path(sys.prefix) / 'share'
QOS_KEYS = ['history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan',
            'liveliness', 'liveliness_lease_duration', 'avoid_ros_namespace_conventions']
MARKER = 'payload-marker-0123456789'


# --------------------------------------------------------------------------------------------
# fixtures: a private DDS domain, an rclpy context of our own


@pytest.fixture(scope='module', autouse=True)
def ros_env():
    """A random domain in 101..199 on localhost (above the test workers' 1..100, conftest), so
    concurrent DDS tests do not meet ours."""
    saved = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
    os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(101, 199))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    yield dict(os.environ)
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture(scope='module')
def ros_context(ros_env):
    context = Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


@pytest.fixture
def node(ros_context):
    test_node = rclpy.create_node(f'test_bag_{os.getpid()}', context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(test_node)
    test_node.executor_for_test = executor
    yield test_node
    executor.shutdown()
    test_node.destroy_node()


def spin_until(node, condition, timeout: float, what: str) -> None:
    """Spin ``node`` in 50 ms steps until ``condition()`` or fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f'timed out after {timeout} s waiting for {what}')
        node.executor_for_test.spin_once(timeout_sec=0.05)


def hrc_bag_command() -> list[str]:
    script = Path(sys.executable).parent / 'hrc-bag'
    return [str(script)] if script.is_file() else [sys.executable, '-m', 'hrc_ros.ros.bag']


# --------------------------------------------------------------------------------------------
# the project's message types, with content in every field that matters


def project_messages() -> list[tuple[str, str, object]]:
    stamp = Time(sec=1_700_000_000, nanosec=123_456_789)
    joints = JointState(
        header=Header(stamp=stamp, frame_id='human_base'),
        name=['l_shoulder', 'l_elbow', 'r_shoulder', 'r_elbow'],
        position=[0.1, -0.2, 0.3, -0.4], velocity=[0.05, 0.9, -1.25, 0.0], effort=[])
    skeleton = PoseArray(
        header=Header(stamp=stamp, frame_id='robot_base'),
        poses=[Pose(position=Point(x=0.5 + i, y=-0.25 * i, z=1.5),
                    orientation=Quaternion(x=0.0, y=0.0, z=0.7071067811865476,
                                           w=0.7071067811865476)) for i in range(3)])
    task_state = UInt8MultiArray(
        layout=MultiArrayLayout(
            dim=[MultiArrayDimension(label=name, size=1, stride=1)
                 for name in ('tp', 'tc', 'tx', 'ty', 'hp', 'hc', 'bp', 'bc')],
            data_offset=0),
        data=[2, 3, 1, 0, 1, 2, 0, 255])
    belief = Float64MultiArray(
        layout=MultiArrayLayout(dim=[MultiArrayDimension(label='motivation', size=3, stride=9),
                                     MultiArrayDimension(label='aggression', size=3, stride=3)],
                                data_offset=0),
        data=[0.5, 0.1, 0.05, 0.1, 0.05, 0.05, 0.1, 0.025, 0.025])
    diagnostics = DiagnosticArray(
        header=Header(stamp=stamp, frame_id=''),
        status=[DiagnosticStatus(level=DiagnosticStatus.WARN, name='decision_node: inputs',
                                 message='belief stale', hardware_id='cell1',
                                 values=[KeyValue(key='belief_age', value='3.2'),
                                         KeyValue(key='action', value='dn')]),
                DiagnosticStatus(level=DiagnosticStatus.OK, name='policy', message='ok',
                                 hardware_id='', values=[])])
    return [
        ('/human/joint_states', 'sensor_msgs/msg/JointState', joints),
        ('/human/skeleton', 'geometry_msgs/msg/PoseArray', skeleton),
        ('/hrc/task_state', 'std_msgs/msg/UInt8MultiArray', task_state),
        ('/hrc/belief', 'std_msgs/msg/Float64MultiArray', belief),
        ('/hrc/action', 'std_msgs/msg/String', String(data=MARKER)),
        ('/hrc/human_response', 'std_msgs/msg/Bool', Bool(data=True)),
        ('/hrc/distance_level', 'std_msgs/msg/UInt8', UInt8(data=3)),
        ('/hrc/epoch', 'std_msgs/msg/UInt32', UInt32(data=4_000_000_000)),
        ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', diagnostics),
    ]


def to_plain(value):
    """A message (rclpy or mcap_ros2's dynamic one) as plain lists, dicts and numbers."""
    if hasattr(value, 'get_fields_and_field_types'):
        fields = value.get_fields_and_field_types()   # a 'byte' (octet) is bytes of length 1
        return {name: ord(getattr(value, name)) if kind == 'octet'
                else to_plain(getattr(value, name)) for name, kind in fields.items()}
    if isinstance(value, dict):
        return {name: to_plain(item) for name, item in value.items()}
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    if hasattr(value, '__slots__') and not isinstance(value, (list, tuple)):
        return {name: to_plain(getattr(value, name)) for name in value.__slots__}
    return [to_plain(item) for item in value]


def assert_same_message(expected, actual, where: str) -> None:
    """Field by field, naming the first field that differs."""
    def walk(a, b, path):
        if isinstance(a, dict):
            assert isinstance(b, dict) and sorted(a) == sorted(b), f'{path}: fields differ'
            for key in a:
                walk(a[key], b[key], f'{path}.{key}')
        elif isinstance(a, list):
            assert isinstance(b, list) and len(a) == len(b), f'{path}: {a!r} != {b!r}'
            for i, (x, y) in enumerate(zip(a, b)):
                walk(x, y, f'{path}[{i}]')
        else:
            assert a == b and type(a) is type(b), f'{path}: {a!r} != {b!r}'
    walk(to_plain(expected), to_plain(actual), where)


@pytest.fixture
def project_bag(tmp_path) -> Path:
    """A bag directory holding every project message type, two messages per topic."""
    directory = tmp_path / 'project'
    with BagWriter(directory) as writer:
        for topic, type_name, _message in project_messages():
            qos = qos_profile_sensor_data if topic.startswith('/human/') else None
            writer.add_topic(topic, type_name, qos)
        for rep in range(2):
            for i, (topic, _type, message) in enumerate(project_messages()):
                log_ns = 1_700_000_000_000_000_000 + rep * 10 ** 9 + i * 1000
                writer.write(topic, message, log_ns, publish_time_ns=log_ns - 500)
    return directory


# --------------------------------------------------------------------------------------------
# writing and reading


def test_round_trip_of_every_project_type(project_bag):
    expected = project_messages()
    messages = list(bag.read_bag(project_bag))
    assert len(messages) == 2 * len(expected)
    assert [m.log_time_ns for m in messages] == sorted(m.log_time_ns for m in messages)
    for i, bag_message in enumerate(messages):
        topic, type_name, original = expected[i % len(expected)]
        assert (bag_message.topic, bag_message.type_name) == (topic, type_name)
        assert bag_message.publish_time_ns == bag_message.log_time_ns - 500
        decoded = bag.deserialize(bag_message)
        assert decoded == original
        assert_same_message(original, decoded, topic)
    only = list(bag.read_bag(project_bag / 'project_0.mcap', topics=['/hrc/epoch']))
    assert [bag.deserialize(m).data for m in only] == [4_000_000_000] * 2


def test_writer_accepts_serialized_bytes_and_refuses_wrong_types(tmp_path):
    from rclpy.serialization import serialize_message
    with BagWriter(tmp_path / 'raw.mcap') as writer:
        writer.add_topic('/hrc/action', 'std_msgs/String')
        writer.write('/hrc/action', serialize_message(String(data='ct')), 5)
        with pytest.raises(BagError, match='std_msgs/msg/Bool message cannot be written'):
            writer.write('/hrc/action', Bool(data=True), 6)
        with pytest.raises(BagError, match='not added'):
            writer.write('/nowhere', String(), 7)
        with pytest.raises(BagError, match='no definition'):
            writer.add_topic('/x', 'std_msgs/msg/NoSuchType')
    assert [bag.deserialize(m).data for m in bag.read_bag(tmp_path / 'raw.mcap')] == ['ct']
    (tmp_path / 'taken').mkdir()
    (tmp_path / 'taken' / 'old.txt').write_text('x')
    with pytest.raises(BagError, match='already exists'):
        BagWriter(tmp_path / 'taken')


def independent_schema(type_name: str) -> str:
    """The expected schema text: .msg files joined depth first, dependencies found by rosidl."""
    root = type_name
    seen = {root}

    def section(name):
        package, _, short = name.split('/')
        text = (SHARE / package / 'msg' / f'{short}.msg').read_text()
        spec = parse_message_string(package, short, text)
        dependencies = sorted({f'{f.type.pkg_name}/msg/{f.type.type}' for f in spec.fields
                               if not f.type.is_primitive_type()})
        for dependency in dependencies:
            if dependency not in seen:
                seen.add(dependency)
                text += f'\n{SEPARATOR}\nMSG: {dependency}\n' + section(dependency)
        return text
    return section(root)


@pytest.mark.parametrize('type_name', sorted({t for _, t, _ in project_messages()}))
def test_schema_text_is_the_msg_files_depth_first(type_name):
    schema = bagfile.message_definition(type_name)
    assert schema == independent_schema(type_name)
    sections = schema.split(f'\n{SEPARATOR}\n')
    package, _, short = type_name.split('/')
    assert sections[0] == (SHARE / package / 'msg' / f'{short}.msg').read_text()
    names = []
    for text in sections[1:]:
        header, _, body = text.partition('\n')
        match = re.fullmatch(r'MSG: (\w+)/msg/(\w+)', header)
        assert match, header
        names.append(f'{match[1]}/msg/{match[2]}')
        assert body == (SHARE / match[1] / 'msg' / f'{match[2]}.msg').read_text()
    assert len(names) == len(set(names))
    assert all(len(line) == 80 for line in schema.splitlines() if set(line) == {'='})


def test_schema_of_pose_array_lists_its_types_depth_first():
    schema = bagfile.message_definition('geometry_msgs/msg/PoseArray')
    assert re.findall(r'^MSG: (\S+)$', schema, flags=re.M) == [
        'geometry_msgs/msg/Pose', 'geometry_msgs/msg/Point', 'geometry_msgs/msg/Quaternion',
        'std_msgs/msg/Header', 'builtin_interfaces/msg/Time']


def test_field_dependencies_parse_every_field_form():
    text = '\n'.join([
        '# comment with Fake/Type inside', 'Header header', 'builtin_interfaces/Time stamp',
        'geometry_msgs/msg/Point[] points  # trailing comment', 'Pose[3] fixed',
        'Pose[<=4] bounded', 'string<=10 short_name', 'string<=5[<=2] names',
        'uint8 LEVEL=2', 'int32[] values', 'float64 x 0.5', '', 'Quaternion orientation'])
    assert bagfile.field_dependencies(text, 'geometry_msgs') == [
        'std_msgs/msg/Header', 'builtin_interfaces/msg/Time', 'geometry_msgs/msg/Point',
        'geometry_msgs/msg/Pose', 'geometry_msgs/msg/Quaternion']


DECODE_WITHOUT_ROS = r'''
import json, sys
for blocked in ('rclpy', 'std_msgs', 'sensor_msgs', 'geometry_msgs', 'diagnostic_msgs',
                'builtin_interfaces', 'rosidl_runtime_py', 'hrc_ros'):
    sys.modules[blocked] = None
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

def plain(value):
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    if hasattr(value, '__slots__') and not isinstance(value, (list, tuple)):
        return {name: plain(getattr(value, name)) for name in value.__slots__}
    return [plain(item) for item in value]

out = []
with open(sys.argv[1], 'rb') as stream:
    reader = make_reader(stream, decoder_factories=[DecoderFactory()])
    for schema, channel, message, decoded in reader.iter_decoded_messages():
        out.append([channel.topic, schema.name, message.log_time, plain(decoded)])
print(json.dumps(out))
'''


def test_mcap_ros2_decodes_every_message_without_rclpy(project_bag, ros_env):
    result = subprocess.run(
        [sys.executable, '-c', DECODE_WITHOUT_ROS, str(project_bag / 'project_0.mcap')],
        capture_output=True, text=True, timeout=60, env=ros_env)
    assert result.returncode == 0, result.stderr
    decoded = json.loads(result.stdout)
    expected = project_messages() * 2
    assert len(decoded) == len(expected)
    for (topic, schema_name, _log, fields), (e_topic, e_type, original) in zip(decoded, expected):
        assert (topic, schema_name) == (e_topic, e_type)
        assert_same_message(original, fields, f'mcap_ros2 {topic}')


def test_profile_encodings_and_qos_metadata(project_bag):
    with open(project_bag / 'project_0.mcap', 'rb') as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        # issue 13: rosbag2's metadata record, as rosbag2_storage_mcap writes it (see below)
        assert [m.name for m in reader.iter_metadata()] == ['rosbag2']
    assert summary.statistics.message_count == 2 * len(project_messages())
    assert {s.name for s in summary.schemas.values()} == {t for _, t, _ in project_messages()}
    assert {s.encoding for s in summary.schemas.values()} == {'ros2msg'}
    channels = {c.topic: c for c in summary.channels.values()}
    assert sorted(channels) == sorted(t for t, _, _ in project_messages())
    for topic, type_name, _message in project_messages():
        channel = channels[topic]
        assert channel.message_encoding == 'cdr'
        assert set(channel.metadata) == {'offered_qos_profiles', 'topic_type_hash'}
        package, _, short = type_name.split('/')
        description = json.loads((SHARE / package / 'msg' / f'{short}.json').read_text())
        assert channel.metadata['topic_type_hash'] == description['type_hashes'][0]['hash_string']
        assert re.fullmatch(r'RIHS01_[0-9a-f]{64}', channel.metadata['topic_type_hash'])
        profiles = yaml.safe_load(channel.metadata['offered_qos_profiles'])
        assert len(profiles) == 1 and list(profiles[0]) == QOS_KEYS
        sensor = topic.startswith('/human/')
        assert profiles[0]['reliability'] == ('best_effort' if sensor else 'reliable')
        assert profiles[0]['durability'] == 'volatile'
        assert profiles[0]['history'] == 'keep_last'
        assert profiles[0]['depth'] == (5 if sensor else 10)
        assert profiles[0]['deadline'] == {'sec': 0, 'nsec': 0}
        assert profiles[0]['avoid_ros_namespace_conventions'] is False


def test_metadata_yaml_is_rosbag2_jazzy_form(project_bag):
    information = yaml.safe_load((project_bag / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']
    assert information['version'] == 9 and information['ros_distro'] == 'jazzy'
    assert information['storage_identifier'] == 'mcap'
    assert information['relative_file_paths'] == ['project_0.mcap']
    count = 2 * len(project_messages())
    assert information['message_count'] == count
    assert information['files'][0]['message_count'] == count
    assert information['duration']['nanoseconds'] == 10 ** 9 + 8000
    assert information['starting_time']['nanoseconds_since_epoch'] == 1_700_000_000 * 10 ** 9
    for entry in information['topics_with_message_count']:
        metadata = entry['topic_metadata']
        assert entry['message_count'] == 2
        assert metadata['serialization_format'] == 'cdr'
        assert list(metadata['offered_qos_profiles'][0]) == QOS_KEYS
        assert metadata['type_description_hash'].startswith('RIHS01_')
    for key in ('compression_format', 'compression_mode', 'custom_data'):
        assert key in information


def test_bag_info_summarises(project_bag):
    info = bag.bag_info(project_bag)
    assert info.message_count == 18 and info.duration_ns == 10 ** 9 + 8000
    assert {t.topic: t.message_count for t in info.topics} == {
        t: 2 for t, _, _ in project_messages()}
    text = info.format()
    assert 'Messages:          18' in text and 'sensor_msgs/msg/JointState' in text


def test_qos_reconstruction_follows_rosbag2():
    sensor = bag.qos_from_offers(bagfile.parse_qos_profiles(bagfile.qos_profiles_yaml(
        [bag.qos_to_dict(qos_profile_sensor_data)])))
    assert sensor.reliability == QoSReliabilityPolicy.BEST_EFFORT and sensor.depth == 5
    latched = QoSProfile(depth=1, durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)
    assert bag.qos_from_offers([bag.qos_to_dict(latched)]).durability == \
        QoSDurabilityPolicy.TRANSIENT_LOCAL
    mixed = bag.qos_from_offers([bag.qos_to_dict(qos_profile_sensor_data),
                                 bag.qos_to_dict(QoSProfile(depth=3))])
    assert (mixed.reliability, mixed.durability, mixed.depth) == (
        QoSReliabilityPolicy.RELIABLE, QoSDurabilityPolicy.VOLATILE, 10)
    assert bag.qos_from_offers([]).reliability == QoSReliabilityPolicy.RELIABLE
    legacy = bagfile.parse_qos_profiles('- history: 3\n  depth: 0\n  reliability: 2\n'
                                    '  durability: 1\n')   # metadata version <= 8: ints
    assert (legacy[0]['history'], legacy[0]['reliability'], legacy[0]['durability']) == (
        'unknown', 'best_effort', 'transient_local')
    offers = [qos_profile_sensor_data, QoSProfile(depth=10)]
    assert bag.qos_for_recording(offers).reliability == QoSReliabilityPolicy.BEST_EFFORT
    assert bag.qos_for_recording([QoSProfile(depth=1)]).reliability == \
        QoSReliabilityPolicy.RELIABLE
    assert bag.qos_for_recording([latched]).durability == QoSDurabilityPolicy.TRANSIENT_LOCAL
    assert bag.qos_for_recording([]).history == QoSHistoryPolicy.KEEP_LAST


# --------------------------------------------------------------------------------------------
# damaged and foreign files


def flip_byte(data: bytes, offset: int) -> bytes:
    return data[:offset] + bytes([data[offset] ^ 0xFF]) + data[offset + 1:]


def damaged_files(project_bag: Path, tmp_path: Path) -> dict[str, Path]:
    good = (project_bag / 'project_0.mcap').read_bytes()
    summary_start = struct.unpack('<Q', good[-8 - 20:-8 - 12])[0]
    variants = {
        'truncated_half': good[:len(good) // 2],
        'truncated_by_one_byte': good[:-1],
        'header_only': good[:64],
        'flipped_payload_byte': flip_byte(good, good.index(MARKER.encode()) + 3),
        'flipped_summary_byte': flip_byte(good, summary_start + 17),
        'text_file': b'rosbag2_bagfile_information:\n  version: 9\n',
        'empty': b'',
    }
    paths = {}
    for name, data in variants.items():
        paths[name] = tmp_path / f'{name}.mcap'
        paths[name].write_bytes(data)
    return paths


def foreign_mcap(path: Path, profile: str, message_encoding: str) -> Path:
    with open(path, 'wb') as stream:
        writer = Writer(stream, compression=CompressionType.NONE)
        writer.start(profile=profile, library='test')
        schema_id = writer.register_schema('std_msgs/msg/String', 'ros2msg', b'string data\n')
        channel_id = writer.register_channel('/chatter', message_encoding, schema_id)
        writer.add_message(channel_id, log_time=1, data=b'{"data": "x"}', publish_time=1)
        writer.finish()
    return path


def test_damaged_or_foreign_files_raise_bag_error(project_bag, tmp_path):
    cases = damaged_files(project_bag, tmp_path)
    cases['missing'] = tmp_path / 'missing.mcap'
    cases['foreign_profile'] = foreign_mcap(tmp_path / 'ros1.mcap', 'ros1', 'cdr')
    cases['json_channel'] = foreign_mcap(tmp_path / 'json.mcap', 'ros2', 'json')
    cases['empty_dir'] = tmp_path / 'empty_dir'
    cases['empty_dir'].mkdir()
    expected = {
        'truncated_half': 'truncated', 'truncated_by_one_byte': 'truncated',
        'header_only': 'truncated', 'flipped_payload_byte': 'corrupt',
        'flipped_summary_byte': 'CRC', 'text_file': 'not an MCAP file',
        'empty': 'not an MCAP file', 'missing': 'no such file',
        'foreign_profile': "profile is 'ros1'", 'json_channel': "'json', not 'cdr'",
        'empty_dir': 'no .mcap file'}
    for name, path in cases.items():
        with pytest.raises(BagError, match=re.escape(expected[name])):
            list(bag.read_bag(path))
        with pytest.raises(BagError):
            bag.bag_info(path)


def test_cli_refuses_damaged_files_with_one_line(project_bag, tmp_path, ros_env):
    cases = damaged_files(project_bag, tmp_path)
    for name in ('truncated_half', 'flipped_payload_byte', 'text_file'):
        result = subprocess.run(hrc_bag_command() + ['info', str(cases[name])],
                                capture_output=True, text=True, timeout=60, env=ros_env)
        assert result.returncode == 2, (name, result.stdout, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith('hrc-bag: '), (name, result.stderr)
        assert 'Traceback' not in result.stderr
    ok = subprocess.run(hrc_bag_command() + ['info', str(project_bag)], capture_output=True,
                        text=True, timeout=60, env=ros_env)
    assert ok.returncode == 0 and 'Messages:          18' in ok.stdout, ok.stderr


# --------------------------------------------------------------------------------------------
# live: in-process recorder, then record -> play across processes


def test_recorder_receives_best_effort_publishers(node, tmp_path):
    from hrc_ros.ros.bag import Recorder
    publisher = node.create_publisher(JointState, 'hrc_bag_test/joint_states',
                                      qos_profile_sensor_data)
    with BagWriter(tmp_path / 'sensor.mcap') as writer:
        recorder = Recorder(node, {'hrc_bag_test/joint_states': None}, writer)
        spin_until(node, lambda: publisher.get_subscription_count() >= 1, 15,
                   'the recorder to subscribe')
        for i in range(5):
            publisher.publish(JointState(name=['l_elbow'], velocity=[0.1 * i]))
            spin_until(node, lambda n=i + 1: writer.message_count == n, 5, f'message {i}')
        recorder.close()
    messages = list(bag.read_bag(tmp_path / 'sensor.mcap'))
    assert [bag.deserialize(m).velocity[0] for m in messages] == [0.1 * i for i in range(5)]
    assert messages[0].topic == '/hrc_bag_test/joint_states'
    assert messages[0].qos_profiles[0]['reliability'] == 'best_effort'
    assert all(m.publish_time_ns <= m.log_time_ns for m in messages)


class OutputLines:
    """Collect a subprocess's stdout lines in a thread (no blocking reads in the test)."""

    def __init__(self, process: subprocess.Popen):
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(process.stdout,), daemon=True)
        self._thread.start()

    def _read(self, stream):
        for line in stream:
            self.lines.append(line.rstrip('\n'))

    def seen(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))


def test_record_then_play_across_processes(node, tmp_path, ros_env):
    topic, count, period = '/hrc_bag_test/chatter', 20, 0.1
    silent = '/hrc_bag_test/silent'      # a publisher that sends nothing: named at the end
    output = tmp_path / 'live'
    recorder = subprocess.Popen(
        hrc_bag_command() + ['record', '-o', str(output), '--wait-timeout', '30', topic,
                             silent],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ros_env)
    try:
        recorder_output = OutputLines(recorder)
        publisher = node.create_publisher(String, topic, QoSProfile(depth=50))
        quiet = node.create_publisher(String, silent, QoSProfile(depth=50))
        spin_until(node, lambda: (publisher.get_subscription_count() >= 1
                                  and quiet.get_subscription_count() >= 1)
                   or recorder.poll() is not None, 30, 'the recorder to subscribe')
        assert recorder.poll() is None, recorder.stderr.read()
        start = time.monotonic()
        for i in range(count):
            due = start + i * period
            spin_until(node, lambda due=due: time.monotonic() >= due, 5, 'publish time')
            publisher.publish(String(data=f'message {i:02d}'))
        spin_until(node, lambda: recorder_output.seen(f'recorded {count} messages'), 15,
                   f'the recorder to report {count} messages')
        recorder.send_signal(signal.SIGINT)
        code = recorder.wait(timeout=20)
        errors = recorder.stderr.read()
        assert code == 0, errors
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait()
    node.destroy_publisher(publisher)
    node.destroy_publisher(quiet)
    assert recorder_output.seen(str(output / 'live_0.mcap'))
    # a topic that recorded nothing is named (a bag without its epochs went unremarked)
    assert f'warning: no message on {silent}:' in errors and topic not in errors, errors

    info = bag.bag_info(output)
    assert info.message_count == count
    messages = list(bag.read_bag(output))
    assert [bag.deserialize(m).data for m in messages] == [f'message {i:02d}'
                                                            for i in range(count)]
    assert messages[0].qos_profiles[0]['reliability'] == 'reliable'
    assert info.topics[0].type_hash.startswith('RIHS01_')
    metadata = yaml.safe_load((output / 'metadata.yaml').read_text())
    assert metadata['rosbag2_bagfile_information']['message_count'] == count
    recorded_s = info.duration_ns / 1e9
    assert recorded_s == pytest.approx((count - 1) * period, abs=1.0)

    received: list[tuple[float, str]] = []
    node.create_subscription(String, topic, lambda m: received.append((time.monotonic(),
                                                                       m.data)),
                             QoSProfile(depth=100))
    player = subprocess.Popen(
        hrc_bag_command() + ['play', str(output), '--rate', '2', '--wait-for-subscribers', '30'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ros_env)
    try:
        spin_until(node, lambda: len(received) >= count or player.poll() not in (None, 0), 40,
                   f'{count} played messages')
        code = player.wait(timeout=20)
        played_errors = player.stderr.read()
        assert code == 0, played_errors
    finally:
        if player.poll() is None:
            player.kill()
            player.wait()
    # the empty topic has nothing to deliver: the player neither waits the 30 s for a
    # subscriber of it nor reports it unmatched
    assert silent not in played_errors, played_errors
    assert [data for _, data in received] == [f'message {i:02d}' for i in range(count)]
    played_s = received[-1][0] - received[0][0]
    expected_s = recorded_s / 2
    assert 0.5 * expected_s <= played_s <= 1.5 * expected_s + 0.25, (played_s, expected_s)


def test_play_by_publish_time_restores_the_send_order(node, tmp_path):
    """The recorder took /b before /a (log order) although /a was sent first (publish order):
    `order='publish'` plays /a first, with the publish-time spacing; 'log' keeps ros2 bag
    play's receive order."""
    with BagWriter(tmp_path / 'order.mcap') as writer:
        for topic in ('/a', '/b'):
            writer.add_topic(topic, 'std_msgs/msg/String')
        ms = 1_000_000
        writer.write('/b', String(data='b'), 100 * ms, publish_time_ns=100 * ms)
        writer.write('/a', String(data='a'), 101 * ms, publish_time_ns=99 * ms)
        writer.write('/b', String(data='c'), 400 * ms, publish_time_ns=399 * ms)
    for order, expected in (('log', ['b', 'a', 'c']), ('publish', ['a', 'b', 'c'])):
        played = []
        result = bag.play(tmp_path / 'order.mcap', node=node, order=order,
                          on_publish=lambda m, played=played: played.append(
                              (time.monotonic(), bag.deserialize(m).data)))
        assert [data for _, data in played] == expected, order
        assert result.message_count == 3
        assert played[-1][0] - played[0][0] >= 0.29, order        # recorded spacing kept
    with pytest.raises(BagError, match='order must be one of log, publish'):
        bag.play(tmp_path / 'order.mcap', node=node, order='sent')


# --------------------------------------------------------------------------------------------
# bags of other recorders, and the rosbag2 metadata record


def ros2_record_all_like(path: Path) -> Path:
    """A bag as `ros2 bag record -a` writes one: with rosbag2's own /events/write_split topic,
    of a type (rosbag2_interfaces/msg/WriteSplitEvent) not installed here, holding nothing."""
    from rclpy.serialization import serialize_message
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='ros2', library='rosbag2')
        unknown = writer.register_schema('rosbag2_interfaces/msg/WriteSplitEvent', 'ros2msg',
                                         b'string closed_file\nstring opened_file\n'
                                         b'string node_name\n')
        writer.register_channel('/events/write_split', 'cdr', unknown,
                                {'offered_qos_profiles': '', 'topic_type_hash': ''})
        known = writer.register_schema('std_msgs/msg/String', 'ros2msg',
                                       bagfile.message_definition('std_msgs/msg/String').encode())
        chatter = writer.register_channel('/hrc_bag_test/chatter', 'cdr', known,
                                          {'offered_qos_profiles': '', 'topic_type_hash': ''})
        for i in range(3):
            writer.add_message(chatter, log_time=(i + 1) * 10_000_000, publish_time=0,
                               data=serialize_message(String(data=f'm{i}')), sequence=i)
        writer.finish()
    return path


def test_play_skips_a_topic_whose_type_is_not_installed(tmp_path, ros_env):
    """Issue 13: hrc-bag play of a `ros2 bag record -a` bag exited 2 ('message type
    rosbag2_interfaces/msg/WriteSplitEvent is not installed'). Like rosbag2's player it now
    warns, skips that topic and plays the rest; info still lists it."""
    path = ros2_record_all_like(tmp_path / 'record_all.mcap')
    info = subprocess.run(hrc_bag_command() + ['info', str(path)], capture_output=True,
                          text=True, timeout=60, env=ros_env)
    assert info.returncode == 0 and '/events/write_split' in info.stdout, info.stderr
    played = subprocess.run(hrc_bag_command() + ['play', str(path)], capture_output=True,
                            text=True, timeout=60, env=ros_env)
    assert played.returncode == 0, played.stderr
    assert 'not playing /events/write_split' in played.stderr
    assert 'played 3 messages' in played.stdout


def test_the_rosbag2_metadata_record_round_trips(project_bag):
    """The MCAP carries rosbag2's metadata record (so `ros2 bag info file.mcap` knows the
    distribution without metadata.yaml), with every field of metadata.yaml."""
    bag_file = next(project_bag.glob('*.mcap'))
    with open(bag_file, 'rb') as stream:     # read by the mcap library, not ours
        records = [r for r in make_reader(stream).iter_metadata() if r.name == 'rosbag2']
    assert len(records) == 1 and set(records[0].metadata) == {'serialized_metadata'}
    record = yaml.safe_load(records[0].metadata['serialized_metadata'])
    on_disk = yaml.safe_load((project_bag / 'metadata.yaml').read_text())
    assert record == on_disk['rosbag2_bagfile_information']
    assert record['version'] == 9 and record['ros_distro'] == 'jazzy'
    info = bag.bag_info(bag_file)
    assert info.ros_distro == 'jazzy' and info.metadata == record
    assert 'ROS Distro:        jazzy' in info.format()


# --------------------------------------------------------------------------------------------
# issue 17: the first messages of a replay, and refusals before any waiting


def test_play_starts_only_once_the_running_subscribers_are_matched(tmp_path, ros_env):
    """`ros2 bag play` of a bag into fresh nodes lost epoch 1: the player's new publisher was
    not yet discovered when it sent the first message (volatile: lost for good). The player
    here is a fresh participant (its own context, as `hrc-bag play` is) and the subscriber
    runs already, in a participant of its own: every message arrives, the first too."""
    path = tmp_path / 'three.mcap'
    with BagWriter(path) as writer:
        writer.add_topic('/hrc_bag_test/match', 'std_msgs/msg/UInt32', qos=QoSProfile(depth=10))
        for i in range(3):
            writer.write('/hrc_bag_test/match', UInt32(data=i), 1_000_000_000 + i * 50_000_000)
    context = Context()
    rclpy.init(context=context)
    listener = rclpy.create_node('match_listener', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(listener)
    received: list[int] = []
    listener.create_subscription(UInt32, '/hrc_bag_test/match', lambda m: received.append(m.data),
                                 QoSProfile(depth=10))
    results = []
    player = threading.Thread(target=lambda: results.append(bag.play(path, match_timeout=15)))
    try:
        player.start()
        deadline = time.monotonic() + 30
        while (player.is_alive() or len(received) < 3) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
        player.join(timeout=5)
    finally:
        executor.shutdown()
        listener.destroy_node()
        rclpy.try_shutdown(context=context)
    assert results and results[0].message_count == 3 and results[0].unmatched == {}, results
    assert received == [0, 1, 2]


def test_record_refuses_a_bad_topic_name_at_once(tmp_path, ros_env):
    """'hrc/ep och!!' ended in an RCLError traceback; now one line, before any waiting."""
    started = time.monotonic()
    result = subprocess.run(hrc_bag_command() + ['record', '-o', str(tmp_path / 'out'),
                                                 '--wait-timeout', '30', 'hrc/ep och!!'],
                            capture_output=True, text=True, timeout=60, env=ros_env)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        "hrc-bag: invalid topic name 'hrc/ep och!!': topic name must not contain characters "
        "other than alphanumerics, '_', '~', '{', or '}':"], result.stderr
    assert time.monotonic() - started < 30 and not (tmp_path / 'out').exists()


@pytest.mark.parametrize('existing', ['bag.mcap', 'folder'])
def test_record_refuses_an_existing_output_before_waiting(existing, tmp_path, ros_env):
    """-o to an existing file was refused only after the wait for publishers (10 s by
    default), and an existing .mcap was overwritten: refused at once, untouched."""
    target = tmp_path / existing
    if existing.endswith('.mcap'):
        target.write_bytes(b'a recording')
    else:
        target.mkdir()
        (target / 'kept.txt').write_text('kept')
    started = time.monotonic()
    result = subprocess.run(hrc_bag_command() + ['record', '-o', str(target), '--wait-timeout',
                                                 '30', '/hrc_bag_test/nobody'],
                            capture_output=True, text=True, timeout=60, env=ros_env)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and 'it already exists' in lines[0], result.stderr
    assert time.monotonic() - started < 30
    assert (target.read_bytes() == b'a recording' if existing.endswith('.mcap')
            else (target / 'kept.txt').read_text() == 'kept')
