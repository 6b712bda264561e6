"""Hostile files (issue 17): what a user hands in is refused in one line and at once when it
never ends, explodes or lies, and an output never goes through a link onto a special file.

- Files that never end: every reader (configuration, policy, POMDP policy, CSV, bag) refuses
  /dev/zero, a FIFO, a folder, a socket, a loop of links and a link to /dev/zero before it
  reads a byte, and a file over the cap of its kind before it reads it (paths.FILE_LIMITS,
  HRC_ROS_LIMIT_<KIND> raises one); the commands say so in one line, exit 2.
- YAML that explodes (1,500 levels, alias bombs, a recursive alias, a 5,000-digit integer):
  one line; anchors that repeat a few values are fine.
- Outputs: `paths.replace_file` writes through a link only onto a regular file;
  `hrc-solve -o mypolicy` is refused before it solves; nothing leaves a temporary file.
- Quotes of user data in errors are capped (a 5 MB value, a 900 KB config_source, a 5,095
  character CSV field, a 100 KB topic name).
- Counts are checked against the model and a cap before anything is allocated (a POMDP file
  of 2,000,001 zero vectors, an archive of many members, a member longer than its header).
- An MCAP zstd bomb (33 KB, a chunk that inflates to 1 GiB), a chunk whose frame says more
  than its record, chunks that inflate past the cap together, an lz4 frame without a size,
  the same without a chunk index: refused before anything is inflated.
- The decision node, set live to any of these through its parameter service, refuses at
  once with the reason and keeps deciding with the old configuration.

The commands run as processes under an address-space limit (CHILD_MEMORY), so a reader that
regresses fails the test instead of filling the machine.
"""

from __future__ import annotations

import io
import json
import os
import re
import resource
import socket
import stat
import subprocess
import sys
import time
import tracemalloc
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from mcap.data_stream import RecordBuilder
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, Schema,
                          Statistics)

from hrc_ros.core import bagfile, paths
from hrc_ros.core.bagfile import BagError, BagWriter
from hrc_ros.core.config import ConfigError, load_config
from hrc_ros.core.learning.recordings import RecordingError, read_csv, read_recordings
from hrc_ros.core.mdp.policy import PolicyError, load_policy, peek_policy, save_policy
from hrc_ros.core.mdp.solver import solve
from hrc_ros.core.model import HRCModel
from hrc_ros.core.paths import default_config_path, share_dir
from hrc_ros.core.pomdp.policy import load_pomdp_policy

DEFAULT = default_config_path()
CHILD_MEMORY = 3 << 30      # address space of a command under test (they need under 2 GiB)
CHILD_TIMEOUT = 60.0        # a command that does not answer by then hangs
SERVICE_TIMEOUT = 20.0      # a parameter service that does not answer by then hangs
GIB = 1 << 30
BAG_TOPICS = {'/hrc/epoch': 'std_msgs/msg/UInt32',
              '/hrc/task_state': 'std_msgs/msg/UInt8MultiArray',
              '/hrc/distance_level': 'std_msgs/msg/UInt8',
              '/hrc/observation': 'std_msgs/msg/UInt8', '/hrc/action': 'std_msgs/msg/String'}
CSV_HEADER = 'epoch,tp,tc,tx,ty,hp,hc,bp,bc,d,O,action,accepted'
CSV_ROWS = ['1,1,1,3,0,0,0,0,0,1,1,mh,', '2,1,1,3,0,0,0,0,0,1,2,rh2,1']


# -- the hostile files -----------------------------------------------------------------------
def mcap_with_chunks(path: Path, chunks, indexed: bool = True) -> Path:
    """An MCAP file of the hrc topics (no messages indexed) whose chunks are `chunks`:
    (compression, declared uncompressed size, compressed records), as a crafted file would
    have them; `indexed` False leaves out the chunk indexes, so readers go through it
    linearly."""
    build = RecordBuilder()
    out = bytearray(b'\x89MCAP0\r\n')

    def meta_records():
        for i, (topic, type_name) in enumerate(BAG_TOPICS.items(), start=1):
            Schema(id=i, name=type_name, encoding='ros2msg', data=b'').write(build)
            Channel(id=i, schema_id=i, topic=topic, message_encoding='cdr',
                    metadata={}).write(build)
    Header(profile='ros2', library='hostile').write(build)
    meta_records()
    out += build.end()
    indexes = []
    for compression, declared, data in chunks:
        offset = len(out)
        Chunk(compression=compression, data=data, message_start_time=0, message_end_time=0,
              uncompressed_crc=0, uncompressed_size=declared).write(build)
        record = build.end()
        out += record
        indexes.append(ChunkIndex(
            message_start_time=0, message_end_time=0, chunk_start_offset=offset,
            chunk_length=len(record), message_index_offsets={}, message_index_length=0,
            compression=compression, compressed_size=len(data), uncompressed_size=declared))
    DataEnd(data_section_crc=0).write(build)
    out += build.end()
    summary_start = len(out)
    meta_records()
    Statistics(attachment_count=0, channel_count=len(BAG_TOPICS),
               channel_message_counts={1: 1}, chunk_count=len(chunks), message_count=1,
               message_end_time=0, message_start_time=0, metadata_count=0,
               schema_count=len(BAG_TOPICS)).write(build)
    for index in indexes if indexed else ():
        index.write(build)
    out += build.end()
    Footer(summary_start=summary_start, summary_offset_start=0, summary_crc=0).write(build)
    out += build.end() + b'\x89MCAP0\r\n'
    path.write_bytes(bytes(out))
    return path


def zstd_zeros(size: int) -> bytes:
    """A zstd frame of `size` zero bytes that says its size in its header, as zstd writes it."""
    import zstandard
    compressor = zstandard.ZstdCompressor(level=1).compressobj(size=size)
    piece = bytes(min(size, 1 << 20))
    return b''.join(compressor.compress(piece) for _ in range(size // len(piece))) + \
        compressor.flush()


def lz4_records(records: bytes, store_size: bool) -> bytes:
    import lz4.frame
    return lz4.frame.compress(records, store_size=store_size)


def epoch_messages(count: int) -> bytes:
    """`count` hrc/epoch Message records (CDR UInt32), the records of a chunk."""
    build = RecordBuilder()
    for k in range(count):
        Message(channel_id=1, sequence=k, log_time=k, publish_time=k,
                data=b'\x00\x01\x00\x00' + int(k).to_bytes(4, 'little')).write(build)
    return build.end()


def one_line(error: Exception | str) -> str:
    text = str(error)
    assert '\n' not in text and len(text) < 1200, text[:2000]
    return text


def run_limited(args, **kwargs) -> subprocess.Popen:
    """A command as a process with at most CHILD_MEMORY of address space."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (CHILD_MEMORY, CHILD_MEMORY))
    return subprocess.Popen([sys.executable, '-m', *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=limit, **kwargs)


@pytest.fixture(scope='module')
def hostile(tmp_path_factory):
    """Every hostile input of this module, made once (a short folder: a socket's name is at
    most 107 bytes)."""
    folder = Path(tmp_path_factory.mktemp('h'))
    h = SimpleNamespace(folder=folder, specials={})
    os.mkfifo(folder / 'fifo')
    listener = socket.socket(socket.AF_UNIX)
    listener.bind(str(folder / 'socket'))
    h.listener = listener
    (folder / 'folder').mkdir()
    os.symlink(folder / 'loop_b', folder / 'loop_a')
    os.symlink(folder / 'loop_a', folder / 'loop_b')
    os.symlink('/dev/zero', folder / 'zero_link')
    sources = {'dev_zero': Path('/dev/zero'), 'fifo': folder / 'fifo',
               'folder': folder / 'folder', 'socket': folder / 'socket',
               'loop': folder / 'loop_a', 'link_to_dev_zero': folder / 'zero_link'}
    for kind, source in sources.items():     # each also under the names the readers expect
        h.specials[kind] = {'': source}
        for suffix in ('.yaml', '.npz', '.csv', '.mcap'):
            os.symlink(source, folder / f'{kind}{suffix}')
            h.specials[kind][suffix] = folder / f'{kind}{suffix}'
    h.csv = folder / 'run.csv'
    h.csv.write_text('\n'.join([CSV_HEADER] + CSV_ROWS) + '\n')
    small = load_config(DEFAULT, overrides={'model': {'rho': 1, 'sigma': 1}})
    h.small_config = folder / 'small.yaml'
    h.small_config.write_text(yaml.safe_dump(small.data))
    h.bomb = mcap_with_chunks(folder / 'zstd_bomb.mcap', [('zstd', GIB, zstd_zeros(GIB))])
    yield h
    listener.close()


# -- the commands ----------------------------------------------------------------------------
PROCESS_CASES = {
    # name: (arguments, what the one line says); run as processes, all at once
    'solve_config_dev_zero': (['hrc_ros.tools.solve', '--config', '/dev/zero', '-o',
                               '{out}/p.npz'], 'it is a character device, not a regular file'),
    'simulate_config_fifo': (['hrc_ros.tools.simulate', '--config', '{fifo}', '--out',
                              '{out}/sim'], 'it is a FIFO (named pipe), not a regular file'),
    'fit_csv_link_to_dev_zero': (['hrc_ros.tools.fit', '{zero_csv}', '-o', '{out}/fit.yaml'],
                                 'it is a character device, not a regular file'),
    'bag_info_zstd_bomb': (['hrc_ros.ros.bag', 'info', '{bomb}'],
                           'inflates to 1,073,741,824 bytes, more than the 67,108,864'),
}
MAIN_CASES = {
    # name: (arguments of the command's main, what the one line says); run in this process
    'fit_bag_link_to_dev_zero': (['fit', '{zero_mcap}', '-o', '{out}/fit.yaml'],
                                 'it is a character device, not a regular file'),
    'fit_symlink_loop': (['fit', '{loop}', '-o', '{out}/fit.yaml'],
                         'Too many levels of symbolic links'),
    'fit_zstd_bomb': (['fit', '{bomb}', '-o', '{out}/fit.yaml'],
                      'inflates to 1,073,741,824 bytes'),
    'solve_output_without_npz': (['solve', '--config', '{small_config}', '-o',
                                  '{out}/mypolicy'], 'must end in .npz'),
    'fit_output_link_to_fifo': (['fit', '{csv}', '-o', '{out}/fifo_link.yaml'],
                                'a symbolic link to'),
}


def case_folder(hostile, folder: Path, args) -> list[str]:
    """An output folder holding only a link to the FIFO, and `args` filled in."""
    os.symlink(hostile.specials['fifo'][''], folder / 'fifo_link.yaml')
    fields = {'out': folder, 'fifo': hostile.specials['fifo'][''],
              'zero_csv': hostile.specials['link_to_dev_zero']['.csv'],
              'zero_mcap': hostile.specials['link_to_dev_zero']['.mcap'],
              'loop': hostile.specials['loop'][''], 'bomb': hostile.bomb,
              'small_config': hostile.small_config, 'csv': hostile.csv}
    return [str(a).format(**fields) for a in args]


@pytest.fixture(scope='module')
def process_runs(hostile, tmp_path_factory):
    """name -> (return code, stdout, stderr, output folder) of every PROCESS_CASES command."""
    running = {}
    for name, (args, _) in PROCESS_CASES.items():
        out = Path(tmp_path_factory.mktemp(name))
        running[name] = (run_limited(case_folder(hostile, out, args), cwd=out), out)
    results = {}
    deadline = time.monotonic() + CHILD_TIMEOUT      # for all of them together
    for name, (process, out) in running.items():
        try:
            stdout, stderr = process.communicate(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            process.kill()
            stdout, stderr = process.communicate()
            stderr = f'(still running after {CHILD_TIMEOUT} s) {stderr[-2000:]}'
        results[name] = (process.returncode, stdout, stderr, out)
    return results


def assert_refused(hostile, code, stdout, stderr, out, reason):
    """Exit 2, one line on stderr that says `reason`, nothing written, the FIFO a FIFO."""
    assert code == 2, (code, stdout[-1000:], stderr[-3000:])
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and (': error: ' in lines[0] or lines[0].startswith('hrc-bag: ')), \
        stderr[-3000:]
    assert reason in lines[0] and len(lines[0]) < 1200, lines[0][:2000]
    left = sorted(p.name for p in out.iterdir())
    assert left == ['fifo_link.yaml'], f'the refused command left {left}'
    assert stat.S_ISFIFO(os.stat(hostile.specials['fifo']['']).st_mode)


@pytest.mark.parametrize('name', PROCESS_CASES)
def test_each_command_refuses_a_hostile_input_in_one_line(process_runs, hostile, name):
    assert_refused(hostile, *process_runs[name], PROCESS_CASES[name][1])


@pytest.mark.parametrize('name', MAIN_CASES)
def test_each_command_refuses_a_hostile_input_or_output_before_work(hostile, tmp_path, capsys,
                                                                    name):
    from hrc_ros.tools import fit, solve
    command, *args = MAIN_CASES[name][0]
    code = {'fit': fit, 'solve': solve}[command].main(case_folder(hostile, tmp_path, args))
    captured = capsys.readouterr()
    assert_refused(hostile, code, captured.out, captured.err, tmp_path, MAIN_CASES[name][1])


# -- readers ---------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def small(hostile):
    config = load_config(hostile.small_config)
    path = hostile.folder / 'small.npz'
    save_policy(path, solve(HRCModel(config), sweeps=3), config)
    return config, path


READERS = {
    'read_text': (lambda p, c: paths.read_text(p, ConfigError, 'text'), '', ConfigError),
    'load_config': (lambda p, c: load_config(p), '.yaml', ConfigError),
    'load_policy': (lambda p, c: load_policy(p, c), '.npz', PolicyError),
    'peek_policy': (lambda p, c: peek_policy(p, c), '.npz', PolicyError),
    'load_pomdp_policy': (lambda p, c: load_pomdp_policy(p, c), '.npz', PolicyError),
    'read_csv': (lambda p, c: read_csv(p, 1, 1), '.csv', RecordingError),
    'read_recordings': (lambda p, c: read_recordings([p], 1, 1), '.mcap', RecordingError),
    'bag_info': (lambda p, c: bagfile.bag_info(p), '.mcap', BagError),
    'read_bag': (lambda p, c: list(bagfile.read_bag(p)), '.mcap', BagError),
}
SPECIALS = {'dev_zero': 'it is a character device', 'fifo': 'it is a FIFO (named pipe)',
            'folder': 'it is a folder', 'socket': 'it is a socket',
            'loop': 'Too many levels of symbolic links',
            'link_to_dev_zero': 'it is a character device'}


@pytest.mark.parametrize('reader', READERS)
def test_every_reader_refuses_what_is_not_a_regular_file_before_reading(hostile, small, reader):
    read, suffix, error = READERS[reader]
    for kind, reason in SPECIALS.items():
        if kind == 'folder' and suffix == '.mcap':
            continue          # a folder is what a bag can be: test_bag covers an empty one
        with pytest.raises(error) as caught:
            read(hostile.specials[kind][suffix], small[0])
        assert reason in one_line(caught.value), (kind, str(caught.value))


def test_a_file_over_the_cap_of_its_kind_is_refused_unread_and_the_cap_can_be_raised(
        tmp_path, monkeypatch):
    padded = tmp_path / 'padded.yaml'
    padded.write_text(DEFAULT.read_text() + '#' * (64 * 1024) + '\n')
    with pytest.raises(ConfigError) as caught:
        load_config(padded)
    line = one_line(caught.value)
    assert f'{padded.stat().st_size:,} bytes, more than the 65,536' in line
    assert 'HRC_ROS_LIMIT_CONFIG' in line
    monkeypatch.setenv('HRC_ROS_LIMIT_CONFIG', '1 MiB')
    assert load_config(padded).policy_hash == load_config(DEFAULT).policy_hash
    monkeypatch.setenv('HRC_ROS_LIMIT_CONFIG', 'lots')
    with pytest.raises(ConfigError, match="HRC_ROS_LIMIT_CONFIG='lots' is not a size"):
        load_config(padded)
    # a file whose size says 0 and that goes on (as /proc's do): read to the cap, no further
    monkeypatch.setenv('HRC_ROS_LIMIT_TEXT', '64')
    assert os.stat('/proc/self/status').st_size == 0
    with pytest.raises(ConfigError, match='grew past the 64 bytes'):
        paths.read_text('/proc/self/status', ConfigError, 'status')


# -- YAML ------------------------------------------------------------------------------------
def bomb_anchors(levels: int) -> str:
    """The billion laughs as flow items: `levels` anchored lists of 9, each of 9 aliases of the
    one before (9 levels: 450 bytes that expand to 9^9 values)."""
    return ', '.join(['&l0 [' + ', '.join(['lol'] * 9) + ']'] + [
        f'&l{i} [' + ', '.join([f'*l{i - 1}'] * 9) + ']' for i in range(1, levels)])


def default_with(tmp_path, name, replace=None, prefix='') -> Path:
    """The default configuration's text with `replace` = (old, new) done once, `prefix`
    before it."""
    text = DEFAULT.read_text()
    if replace is not None:
        old, new = replace
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / name
    path.write_text(prefix + text)
    return path


def hostile_configs(folder: Path) -> dict:
    """name -> (a configuration file built to explode, a regex of what its one line says)."""
    lines = DEFAULT.read_text().splitlines(keepends=True)
    start = next(i for i, line in enumerate(lines) if line.startswith('  table:'))
    table = ''.join(lines[start:start + 4])
    row = '[' + ', '.join(['*l7'] * 9) + ']'
    return {
        'nested_1500': (default_with(folder, 'deep.yaml', ('  rho: 2', '  rho: ' + '[' * 1500
                                                           + ']' * 1500)),
                        # libyaml's parser stops at 1,000 levels itself, PyYAML's at 33 (ours)
                        'maximum nesting depth|nested deeper than 32 levels'),
        'nested_40': (default_with(folder, 'deep40.yaml', ('  rho: 2', '  rho: ' + '[' * 40
                                                          + ']' * 40)),
                      'line 7: nested deeper than 32 levels'),
        'alias_bomb_in_a_key': (default_with(folder, 'bomb.yaml', (
            '  rho: 2', f'  rho: [{bomb_anchors(9)}]')), 'more than 5,000 values'),
        'alias_bomb_in_observation_table': (default_with(folder, 'table_bomb.yaml', (
            table, f'  table: [[[{bomb_anchors(8)}]' + ', *l7' * 8 + f'], {row}, {row}]\n')),
            'more than 5,000 values'),
        'recursive_alias': (default_with(folder, 'recursive.yaml', prefix='loop: &me [*me]\n'),
                            'inside the node it names'),
        'integer_of_5000_digits': (default_with(folder, 'digits.yaml', ('  rho: 2', '  rho: '
                                                                        + '9' * 5000)),
                                   r'Exceeds the limit \(4300 digits\)'),
        'not_a_date': (default_with(folder, 'date.yaml', prefix='when: 2024-13-45\n'),
                       r'month must be in 1\.\.12'),
    }


def test_yaml_that_explodes_is_refused_in_one_line(tmp_path):
    for name, (path, reason) in hostile_configs(tmp_path).items():
        assert path.stat().st_size < 64 * 1024, name
        with pytest.raises(ConfigError) as caught:
            load_config(path)
        assert re.search(reason, one_line(caught.value)), (name, str(caught.value)[:500])
    # an anchor that repeats a few values is YAML as usual
    data = yaml.safe_load(DEFAULT.read_text())
    chain = data['model']['emotion']['base']['em']
    shared = default_with(tmp_path, 'shared.yaml', prefix=f'x-chain: &chain {chain}\n')
    with pytest.raises(ConfigError, match="unknown section 'x-chain'"):
        load_config(shared)          # parsed (aliases are fine), then the schema speaks
    # the same loader reads a bag's metadata
    with pytest.raises(BagError, match='more than 100,000 values'):
        bagfile.parse_qos_profiles(f'[{bomb_anchors(9)}]')


# -- outputs ---------------------------------------------------------------------------------
def test_replace_file_writes_through_a_link_only_to_a_regular_file(tmp_path):
    os.mkfifo(tmp_path / 'fifo')
    listener = socket.socket(socket.AF_UNIX)
    listener.bind(str(tmp_path / 'socket'))
    (tmp_path / 'folder').mkdir()
    targets = {'fifo': tmp_path / 'fifo', 'socket': tmp_path / 'socket',
               'folder': tmp_path / 'folder', 'dangling': tmp_path / 'nowhere' / 'x',
               'dev_null': Path('/dev/null')}
    for name, target in targets.items():
        link = tmp_path / f'{name}.yaml'
        os.symlink(target, link)
        with pytest.raises(OSError) as caught:
            paths.replace_file(link, lambda temporary: temporary.write_text('written\n'))
        assert 'only a link to a regular file is written through' in caught.value.strerror
        assert link.is_symlink()
    for name in ('fifo', 'socket', 'folder'):          # the special file itself, not a link
        with pytest.raises(OSError, match='not a regular file'):
            paths.replace_file(targets[name], lambda temporary: temporary.write_text('x'))
    os.symlink(tmp_path / 'loop_b', tmp_path / 'loop_a')
    os.symlink(tmp_path / 'loop_a', tmp_path / 'loop_b')
    with pytest.raises(OSError, match='leads to no file'):
        paths.replace_file(tmp_path / 'loop_a', lambda temporary: temporary.write_text('x'))
    assert stat.S_ISFIFO(os.stat(tmp_path / 'fifo').st_mode)
    assert stat.S_ISSOCK(os.stat(tmp_path / 'socket').st_mode)
    assert stat.S_ISCHR(os.stat('/dev/null').st_mode)
    listener.close()
    # a link to a regular file: the file is replaced whole, its mode kept, the link kept
    real = tmp_path / 'real.yaml'
    real.write_text('old\n')
    real.chmod(0o640)
    os.symlink(real, tmp_path / 'link.yaml')
    paths.replace_file(tmp_path / 'link.yaml', lambda temporary: temporary.write_text('new\n'))
    assert (tmp_path / 'link.yaml').is_symlink() and real.read_text() == 'new\n'
    assert stat.S_IMODE(real.stat().st_mode) == 0o640
    assert not [p for p in tmp_path.iterdir() if '.tmp' in p.name]


def test_a_policy_is_written_to_exactly_its_name_and_a_failed_write_leaves_nothing(tmp_path,
                                                                                  small):
    config, good = small
    result = solve(HRCModel(config), sweeps=2)
    written = save_policy(tmp_path / 'mypolicy', result, config)   # no .npz: numpy adds none
    assert written == tmp_path / 'mypolicy' and sorted(os.listdir(tmp_path)) == ['mypolicy']
    assert load_policy(written, config).policy.size == HRCModel(config).n_states
    before = written.read_bytes()

    def interrupted(temporary):
        temporary.write_bytes(b'half a policy')
        raise KeyboardInterrupt     # Ctrl-C while writing
    with pytest.raises(KeyboardInterrupt):
        paths.replace_file(written, interrupted)
    assert sorted(os.listdir(tmp_path)) == ['mypolicy'] and written.read_bytes() == before


# -- quotes ----------------------------------------------------------------------------------
def test_what_an_error_quotes_of_a_file_is_capped(tmp_path, small):
    config, good = small
    with pytest.raises(ConfigError) as caught:
        load_config(DEFAULT, overrides={'model': {'rho': 'A' * 5_000_000}})
    assert '(5000000 characters)' in one_line(caught.value)
    big_quote = default_with(tmp_path, 'quote.yaml', ('  rho: 2', '  rho: ' + 'A' * 60_000))
    with pytest.raises(ConfigError) as caught:
        load_config(big_quote)
    assert '(60000 characters)' in one_line(caught.value)
    field = tmp_path / 'field.csv'
    field.write_text(f'{CSV_HEADER}\n1,1,1,3,0,0,0,0,0,1,1,{"x" * 5095},\n')
    with pytest.raises(RecordingError) as caught:
        read_csv(field, 1, 1)
    assert '(5095 characters)' in one_line(caught.value)
    # a 900 KB config_source in a policy, quoted when the policy is refused
    with np.load(good) as archive:
        arrays = {name: archive[name] for name in archive.files}
    meta = json.loads(str(arrays['meta']))
    meta['config_source'] = 'S' * 900_000
    arrays['meta'] = np.array(json.dumps(meta))
    np.savez(tmp_path / 'source.npz', **arrays)
    with pytest.raises(PolicyError) as caught:
        load_policy(tmp_path / 'source.npz', load_config(DEFAULT))
    assert 'was solved for configuration' in one_line(caught.value)
    # a 100 KB topic name in a bag
    topic = '/' + 't' * 100_000
    named = tmp_path / 'named.mcap'
    with open(named, 'wb') as stream:
        from mcap.writer import Writer
        writer = Writer(stream)
        writer.start(profile='ros2', library='hostile')
        schema = writer.register_schema('std_msgs/msg/String', 'ros2msg', b'string data\n')
        writer.register_channel(topic, 'json', schema)
        writer.finish()
    with pytest.raises(BagError) as caught:
        bagfile.bag_info(named)
    assert '(100001 characters)' in one_line(caught.value)
    # one home for capping: the ring's conversions use the core's
    from hrc_ros.core import quoting
    from hrc_ros.ros import conversions
    assert conversions.cap is quoting.cap and conversions.quote is quoting.quote


# -- counts before allocation ----------------------------------------------------------------
def pomdp_with_vectors(path: Path, n_vectors: int) -> Path:
    """The shipped default POMDP file with `n_vectors` zero alpha vectors spread over its
    states, consistent in every other respect (a crafted 0.5 MB file of 144 MB of vectors)."""
    with np.load(share_dir() / 'policies' / 'pomdp' / 'default.npz') as archive:
        arrays = {name: archive[name] for name in archive.files}
    n_x = len(arrays['columns'])
    arrays['alpha_offsets'] = np.linspace(0, n_vectors, n_x + 1).astype(np.int64)
    arrays['alpha_action'] = np.zeros(n_vectors, np.int8)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {'descr': '<f8', 'fortran_order': False,
                                                  'shape': (n_vectors, 9)})
    with zipfile.ZipFile(path, 'w', zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for name, array in arrays.items():
            if name != 'alpha':
                with archive.open(f'{name}.npy', 'w') as member:
                    np.lib.format.write_array(member, np.asanyarray(array))
        with archive.open('alpha.npy', 'w', force_zip64=True) as member:
            member.write(header.getvalue())
            zeros, left = bytes(8 << 20), n_vectors * 9 * 8
            while left:
                member.write(zeros[:min(left, len(zeros))])
                left -= min(left, len(zeros))
    return path


def test_a_pomdp_file_with_more_vectors_than_allowed_is_refused_before_allocating(tmp_path,
                                                                                 default_config):
    crafted = pomdp_with_vectors(tmp_path / 'vectors.npz', 2_000_001)
    assert crafted.stat().st_size < 2_000_000
    tracemalloc.start()
    try:
        with pytest.raises(PolicyError) as caught:
            load_pomdp_policy(crafted, default_config)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert 'vectors a state, 2,000,000 in all' in one_line(caught.value)
    assert peak < 50 << 20, f'{peak / 2**20:.0f} MiB allocated before the refusal'
    # per state: the shipped file's states times 4096 bound the vectors too
    with np.load(share_dir() / 'policies' / 'pomdp' / 'default.npz') as archive:
        n_x = len(archive['columns'])
    assert n_x * 4096 > 2_000_000


def test_policy_archives_are_bounded_before_their_members_are_read(tmp_path, small):
    config, good = small
    with np.load(good) as archive:
        arrays = {name: archive[name] for name in archive.files}
    many = tmp_path / 'many.npz'
    np.savez(many, **arrays, **{f'extra{i}': np.zeros(1) for i in range(20)})
    with pytest.raises(PolicyError, match='its zip directory lists 23 members'):
        load_policy(many, config)
    longer = tmp_path / 'longer.npz'        # a member that goes on past what its header says
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(longer, 'w') as target:
        for info in source.infolist():
            data = source.read(info)
            target.writestr(info.filename, data + bytes(1 << 20) if info.filename ==
                            'value.npy' else data)
    with pytest.raises(PolicyError, match='member value holds .* bytes, its header says'):
        load_policy(longer, config)


# -- bags ------------------------------------------------------------------------------------
def test_a_chunk_whose_frame_says_more_than_its_record_is_refused_uninflated(hostile):
    lying = mcap_with_chunks(hostile.folder / 'lying.mcap', [('zstd', 1024, zstd_zeros(GIB))])
    with pytest.raises(BagError, match='declares 1,024 bytes, its zstd frame 1,073,741,824'):
        list(bagfile.read_bag(lying))
    unindexed = mcap_with_chunks(hostile.folder / 'unindexed.mcap',
                                 [('zstd', GIB, zstd_zeros(GIB))], indexed=False)
    with pytest.raises(BagError, match='inflates to 1,073,741,824 bytes'):
        bagfile.bag_info(unindexed)


def test_chunks_that_inflate_past_the_cap_together_are_refused(hostile):
    chunk = zstd_zeros(60 << 20)
    many = mcap_with_chunks(hostile.folder / 'many.mcap', [('zstd', 60 << 20, chunk)] * 70)
    assert many.stat().st_size < 1 << 20
    with pytest.raises(BagError, match='inflate to more than 4,294,967,296 bytes together'):
        bagfile.bag_info(many, verify=False)


def test_lz4_and_zstd_chunks_within_the_caps_read_and_an_lz4_frame_is_bounded(
        hostile, monkeypatch):
    records = epoch_messages(5000)
    plain = mcap_with_chunks(hostile.folder / 'lz4.mcap', [
        ('lz4', len(records), lz4_records(records, store_size=False)),
        ('lz4', len(records), lz4_records(records, store_size=True))])
    assert [m.data[4:] for m in bagfile.read_bag(plain)] == \
        [int(k).to_bytes(4, 'little') for k in range(5000) for _ in range(2)]
    for compression in ('zstd', 'lz4'):
        written = hostile.folder / f'written_{compression}.mcap'
        with BagWriter(written, compression=compression, chunk_size=4096) as writer:
            writer.add_topic('/hrc/epoch', 'std_msgs/msg/UInt32')
            for k in range(2000):
                writer.write('/hrc/epoch', b'\x00\x01\x00\x00' + k.to_bytes(4, 'little'), k)
        assert bagfile.bag_info(written).message_count == 2000
    monkeypatch.setenv('HRC_ROS_LIMIT_BAG_CHUNK', '64KiB')   # the lz4 frame: 2 blocks of 64 KiB
    with pytest.raises(BagError, match='inflates to 131,072 bytes, more than the 65,536'):
        list(bagfile.read_bag(plain))


# -- the decision node, live -----------------------------------------------------------------
def set_parameter(graph, name: str, value: str):
    """Set a parameter of /decision through its parameter service (as `ros2 param set`)."""
    from rcl_interfaces.msg import Parameter as ParameterMsg, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    client = graph.probe.create_client(SetParameters, '/decision/set_parameters')
    assert graph.spin_until(client.service_is_ready, SERVICE_TIMEOUT)
    request = SetParameters.Request(parameters=[ParameterMsg(name=name, value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=value))])
    future = client.call_async(request)
    assert graph.spin_until(future.done, SERVICE_TIMEOUT), f'{name}:={value}: no answer'
    graph.probe.destroy_client(client)
    return future.result().results[0]


def test_the_decision_node_refuses_hostile_files_at_once_and_keeps_deciding(
        graph, hostile, policy_path, tmp_path):
    from hrc_ros.ros import conversions as conv
    from test_nodes import Decision
    dec = Decision(graph, policy_path)
    dec.run(1)
    node = dec.node
    configs = {'/dev/zero': 'it is a character device', str(hostile.specials['fifo']['']):
               'it is a FIFO', str(hostile.specials['link_to_dev_zero']['.yaml']):
               'it is a character device', str(hostile.specials['loop']['.yaml']):
               'Too many levels of symbolic links'}
    configs = {path: re.escape(reason) for path, reason in configs.items()}
    configs.update({str(path): reason for path, reason in hostile_configs(tmp_path).values()})
    quoted = default_with(tmp_path, 'quote.yaml', ('  rho: 2', '  rho: ' + 'A' * 60_000))
    configs[str(quoted)] = re.escape('(60000 characters)')
    for value, reason in configs.items():
        result = set_parameter(graph, 'config', value)
        assert not result.successful and result.reason.startswith('config refused: ')
        assert re.search(reason, one_line(result.reason)), (value, result.reason[:500])
    for value, reason in (('/dev/zero', 'it is a character device'),
                          (str(hostile.specials['fifo']['']), 'it is a FIFO')):
        result = set_parameter(graph, 'policy', value)
        assert not result.successful and result.reason.startswith('policy refused: ')
        assert reason in one_line(result.reason)
    assert node.get_parameter('config').value == '' and node.config.source == str(DEFAULT)
    epoch = node.epoch
    assert graph.spin_until(lambda: node.epoch >= epoch + 3 and len(dec.actions) >= epoch + 3)
    for k in range(epoch + 1, epoch + 3):      # decided, with the configuration it had
        values = conv.diagnostic_values(dec.status(k))
        assert (values['config'], values['policy_file']) == (str(DEFAULT), policy_path)


@pytest.mark.parametrize('command, output, args', [
    ('hrc_ros.tools.simulate', 'trajectory.csv', []),
    ('hrc_ros.tools.evaluate', 'summary.csv', ['--episodes', '2', '--epochs', '3',
                                               '--selectors', 'paper']),
])
def test_a_link_planted_in_an_output_folder_is_not_followed(tmp_path, command, output, args):
    """The commands' CSV, JSON and plot outputs used to be written with open('w'), which
    follows a link planted in the output folder onto whatever it names (a FIFO here: the
    command would block on it; a device would be clobbered). Now they are written through
    paths.replace_file: the command stops in one line, exit 1, and the FIFO is untouched."""
    out = tmp_path / 'out'
    out.mkdir()
    fifo = tmp_path / 'fifo'
    os.mkfifo(fifo)
    (out / output).symlink_to(fifo)
    result = subprocess.run([sys.executable, '-m', command, '--out', str(out), *args],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 1, (result.returncode, result.stderr[-2000:])
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and 'cannot write' in lines[0] and 'FIFO' in lines[0], lines
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and (out / output).is_symlink()
