"""Where the package's data lives, and how a user's file is read and written.

`share_dir()`, the folder holding `config/` and `policies/`, looks, in order, at

1. ``$HRC_ROS_SHARE`` (a folder holding ``config/`` and ``policies/``);
2. the ament index: the first prefix of ``$AMENT_PREFIX_PATH`` that holds the marker
   ``share/ament_index/resource_index/packages/hrc_ros`` (a colcon build or a ROS install),
   read here as plain files, as `ament_index_python` does, so the core imports nothing of ROS;
3. the source checkout this module lives in (a clone, or ``pip install -e .``);
4. ``<sys.prefix>/share/hrc_ros`` (a ``pip install .``).

A user's file (a configuration, a policy, a recording, a bag: anything named on a command line
or in a node parameter) is untrusted input. It may be a FIFO that never ends, ``/dev/zero``, a
folder, a loop of symbolic links, gigabytes, or YAML built to explode. So every reader of one
goes through this module (docs/ROBUSTNESS.md, "Files"):

- `open_input` checks the file type first (`os.stat`, before anything is opened: a regular
  file, after symbolic links; a FIFO, a device, a folder or a socket is refused in one line
  that says what it is), then its size against the cap of its kind (`FILE_LIMITS`), then opens
  it without blocking and checks that what it opened is the file it looked at;
- `read_bytes` / `read_text` read at most the cap, so a file that grows while it is read is
  still bounded;
- `parse_yaml` / `read_yaml` are the one YAML loader for what users hand in (configurations,
  bag metadata; later the robot's and the plant's files): safe tags only, at most
  `YAML_MAX_DEPTH` levels and `YAML_MAX_NODES` values, checked on the parser's events before
  anything is composed or built, with every alias counted as the values it repeats (a 3.5 KB
  alias bomb would expand into gigabytes; anchors and aliases themselves are fine, our own bag
  metadata has them) and an alias inside the node it names refused; every loader error
  (yaml's own, RecursionError, MemoryError, the ValueError of a 5,000-digit integer) becomes
  one line.

A writer (`replace_file`) writes a file whole or not at all, and through a symbolic link only
onto a regular file (`output_target`): ``ln -s /dev/null out.yaml`` never replaces the device.

The caps are per kind, in bytes, far above what the suite itself writes and below what would
stall a node or fill the memory. A site that really needs more sets ``HRC_ROS_LIMIT_<KIND>``
(``HRC_ROS_LIMIT_BAG=16GiB``: bytes, or with a KiB, MiB, GiB or TiB suffix) in the environment
of the commands and nodes.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import re
import stat
import sys
from pathlib import Path
from typing import BinaryIO, Callable

import yaml

from .quoting import cap

PACKAGE = 'hrc_ros'


def ament_share_dir(package: str = PACKAGE) -> Path | None:
    """``<prefix>/share/<package>`` of the first AMENT_PREFIX_PATH prefix that indexes it."""
    marker = Path('share') / 'ament_index' / 'resource_index' / 'packages' / package
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix and (Path(prefix) / marker).is_file():
            return Path(prefix) / 'share' / package
    return None


def share_dir() -> Path:
    """The package's data folder (holding config/ and policies/); see the module docstring."""
    env = os.environ.get('HRC_ROS_SHARE')
    if env:
        return Path(env)
    indexed = ament_share_dir()
    if indexed is not None:
        return indexed
    checkout = Path(__file__).resolve().parents[2]
    if (checkout / 'config' / 'default.yaml').is_file():
        return checkout
    return Path(sys.prefix) / 'share' / PACKAGE


def default_config_path() -> Path:
    """The shipped default configuration, `config/default.yaml`."""
    return share_dir() / 'config' / 'default.yaml'


ARM_CONFIG = 'arm'   # config/arm.yaml: the model of the cell with an arm (docs/ROBOT.md 4)


def arm_config_path() -> Path:
    """The shipped configuration of the cell with an arm, `config/arm.yaml` (the default's
    model with the robot's counter paused under dp and dm, docs/ROBOT.md): what `--robot sim`,
    `robot:=sim` and `hrc-evaluate --cell arm` plan with unless a configuration is named."""
    return shipped_config_path(ARM_CONFIG)


def shipped_config_path(name: str) -> Path:
    """A shipped configuration by name: ``shipped_config_path('paper')`` is
    `config/paper.yaml` of the share folder."""
    return share_dir() / 'config' / f'{name}.yaml'


KIB, MIB, GIB = 1 << 10, 1 << 20, 1 << 30

# kind -> the most bytes read of a user's file of that kind (see the module docstring)
FILE_LIMITS = {
    'config': 64 * KIB,         # a model configuration (the shipped ones: 3 KB)
    'yaml': 1 * MIB,            # any other YAML a user hands in (`read_yaml`'s default)
    'text': 16 * MIB,           # `read_text`'s default
    'csv': 64 * MIB,            # a trajectory CSV for hrc-fit (about a million epochs)
    'policy': 1 * GIB,          # an MDP or POMDP policy file (the shipped ones: 0.15-0.55 MB)
    'bag': 4 * GIB,             # an MCAP bag file
    'bag_chunk': 64 * MIB,      # one chunk of a bag, inflated (rosbag2 writes 768 KiB)
    'bag_inflated': 4 * GIB,    # all the chunks of one bag together, inflated
    'bag_metadata': 16 * MIB,   # a bag folder's metadata.yaml, a bag's rosbag2 record
}
YAML_MAX_DEPTH = 32        # nesting of a YAML document (a configuration is 5 deep)
YAML_MAX_NODES = 100_000   # values in one YAML document (a configuration has about 150)
PATH_QUOTE = 300           # characters of a path quoted in an error when it cannot be opened

_SIZE = re.compile(r'(\d+)\s*(b|k|kb|kib|m|mb|mib|g|gb|gib|t|tb|tib)?', re.IGNORECASE)
_UNITS = {'': 1, 'b': 1, 'k': KIB, 'm': MIB, 'g': GIB, 't': GIB * KIB}

Error = Callable[[str], Exception]   # an exception class, or anything that makes one of a text


def limit_variable(kind: str) -> str:
    """The environment variable that raises (or lowers) the cap of `kind`."""
    return f'HRC_ROS_LIMIT_{kind.upper()}'


def file_limit(kind: str, error: Error = ValueError) -> int:
    """The cap of `kind` in bytes: ``$HRC_ROS_LIMIT_<KIND>`` if set, else `FILE_LIMITS`."""
    text = os.environ.get(limit_variable(kind), '').strip()
    if not text:
        return FILE_LIMITS[kind]
    match = _SIZE.fullmatch(text)
    if match is None:
        raise error(f'{limit_variable(kind)}={cap(text, 40)!r} is not a size (bytes, or with '
                    'a KiB, MiB, GiB or TiB suffix)')
    return int(match.group(1)) * _UNITS[(match.group(2) or '').lower()[:1]]


def file_type(mode: int) -> str:
    """What a file of `mode` (st_mode) is, in words."""
    for test, name in ((stat.S_ISREG, 'a regular file'), (stat.S_ISDIR, 'a folder'),
                       (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device'),
                       (stat.S_ISFIFO, 'a FIFO (named pipe)'), (stat.S_ISSOCK, 'a socket'),
                       (stat.S_ISLNK, 'a symbolic link')):
        if test(mode):
            return name
    return 'not a regular file'


def _shown(path) -> str:
    return cap(str(path), PATH_QUOTE)


def input_stat(path: str | Path, error: Error, what: str) -> os.stat_result:
    """`os.stat` of a user's input file (symbolic links followed), opening nothing; `error`
    with one line when it is missing, unreadable, a loop of links or not a regular file."""
    try:
        status = os.stat(path)
    except (OSError, ValueError) as exc:     # ValueError: a NUL byte in the name
        reason = exc.strerror if isinstance(exc, OSError) else 'not a file name'
        raise error(f'{_shown(path)}: cannot read: {reason}') from None
    if not stat.S_ISREG(status.st_mode):
        raise error(f'{_shown(path)}: cannot read: it is {file_type(status.st_mode)}, not a '
                    f'regular file (name the {what} file itself)')
    return status


def open_input(path: str | Path, error: Error, kind: str, what: str | None = None) -> BinaryIO:
    """A user's file of `kind` (a key of FILE_LIMITS) opened for reading in binary, after the
    checks of the module docstring (type, size, the file opened is the one checked); `error`
    with one line otherwise. `what` names the kind in the messages (default: `kind`)."""
    what = what or kind
    limit = file_limit(kind, error)
    checked = input_stat(path, error, what)
    if checked.st_size > limit:
        raise error(f'{_shown(path)}: cannot read: {checked.st_size:,} bytes, more than the '
                    f'{limit:,} a {what} file may have here (a site that needs more sets '
                    f'{limit_variable(kind)})')
    try:   # O_NONBLOCK: a FIFO put in its place meanwhile does not block the open
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise error(f'{_shown(path)}: cannot read: {exc.strerror}') from None
    try:
        opened = os.fstat(fd)
        if (not stat.S_ISREG(opened.st_mode)
                or (opened.st_dev, opened.st_ino) != (checked.st_dev, checked.st_ino)):
            raise error(f'{_shown(path)}: cannot read: it was replaced while it was opened')
        os.set_blocking(fd, True)
        return os.fdopen(fd, 'rb')
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | Path, error: Error, kind: str, what: str | None = None) -> bytes:
    """The bytes of a user's file of `kind`, at most its cap (`open_input`)."""
    what = what or kind
    limit = file_limit(kind, error)
    with open_input(path, error, kind, what) as stream:
        try:
            data = stream.read(limit + 1)
        except OSError as exc:
            raise error(f'{_shown(path)}: cannot read: {exc.strerror}') from None
    if len(data) > limit:
        raise error(f'{_shown(path)}: cannot read: it grew past the {limit:,} bytes a {what} '
                    f'file may have here while it was read ({limit_variable(kind)})')
    return data


def read_text(path: str | Path, error: Error, what: str, kind: str = 'text') -> str:
    """The text of a user's file, or `error` with one line that names it: cannot read (and
    why: missing, not a regular file, larger than the cap of `kind`) or not UTF-8 text (`what`:
    what the file should be, e.g. 'YAML'). A UTF-8 byte order mark, as Excel and Notepad write
    one, is dropped: it is not part of the text."""
    data = read_bytes(path, error, kind, what)
    try:
        return data.decode('utf-8-sig')
    except UnicodeDecodeError:
        raise error(f'{path}: not a text (UTF-8) {what} file') from None


class _Refused(Exception):
    """What the bounded YAML loader does not take (too deep, too many values, a recursive
    alias)."""


# libyaml's parser when PyYAML has it (4 times faster on a 64 KB file), else PyYAML's own
_YAML_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)


def _check_yaml_events(text: str, max_depth: int, max_nodes: int) -> None:
    """Walk a YAML text's events (the parser's, nothing built yet) and refuse it when it nests
    deeper than `max_depth` or holds more than `max_nodes` values, every alias counted as the
    values and levels of the node it names (so neither an alias bomb nor 1,500 nested brackets
    ever reach the composer, the constructor or Python's recursion limit), or when an alias
    sits inside the node it names (a structure that contains itself), or when a mapping gives
    one key twice (YAML's loaders keep the second silently: a cost given twice in a
    configuration was solved with the second value, without a word)."""
    nodes = depth = reach = 0
    anchored: dict[str, tuple[int, int]] = {}    # anchor -> (values, levels) of its node
    open_nodes: list[tuple] = []                 # per open collection: anchor, values, reach
    mappings: list[list | None] = []             # per open collection: [keys, key next, key]

    def done() -> None:
        """A whole node ended inside the innermost collection: in a mapping, the key's or
        the value's turn follows."""
        if mappings and mappings[-1] is not None:
            mappings[-1][1] = not mappings[-1][1]

    def check_key(event) -> None:
        frame = mappings[-1] if mappings else None
        if frame is None or not frame[1]:
            return
        key = event.value
        if key in frame[0] and key != '<<':
            line = event.start_mark.line + 1 if event.start_mark is not None else '?'
            where = '.'.join(str(f[2]) for f in mappings[:-1] if f is not None and f[2])
            name = f'{where}.{key}' if where else key
            raise _Refused(f'line {line}: the key {cap(name, 80)} is given twice (the second '
                           'would silently replace the first); keep one')
        frame[0].add(key)
        frame[2] = key

    def grow(count: int, level: int, event) -> None:
        nonlocal nodes, reach
        nodes += count
        reach = max(reach, level)
        line = event.start_mark.line + 1 if event.start_mark is not None else '?'
        if nodes > max_nodes:
            raise _Refused(f'line {line}: more than {max_nodes:,} values (an alias counts as '
                           'the values it repeats)')
        if level > max_depth:
            raise _Refused(f'line {line}: nested deeper than {max_depth} levels')
    for event in yaml.parse(text, Loader=_YAML_LOADER):
        if isinstance(event, yaml.AliasEvent):
            if event.anchor in anchored:
                count, levels = anchored[event.anchor]
                grow(count, depth + levels, event)
            elif any(entry[0] == event.anchor for entry in open_nodes):
                line = event.start_mark.line + 1 if event.start_mark is not None else '?'
                raise _Refused(f'line {line}: the alias *{cap(event.anchor, 40)} is inside the '
                               'node it names (a structure that contains itself)')
            done()
        elif isinstance(event, yaml.ScalarEvent):
            grow(1, depth + 1, event)
            if event.anchor is not None:
                anchored[event.anchor] = (1, 1)
            check_key(event)
            done()
        elif isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            grow(1, depth + 1, event)
            depth += 1
            open_nodes.append((event.anchor, nodes, reach))
            mappings.append([set(), True, None] if isinstance(event, yaml.MappingStartEvent)
                            else None)
            reach = depth
        elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            anchor, count_before, reach_before = open_nodes.pop()
            mappings.pop()
            if anchor is not None:
                anchored[anchor] = (nodes - count_before + 1, reach - depth + 1)
            reach = max(reach, reach_before)
            depth -= 1
            done()


def parse_yaml(text: str, error: Error, source: str, max_depth: int = YAML_MAX_DEPTH,
               max_nodes: int = YAML_MAX_NODES):
    """The data of a YAML text a user handed in (safe tags only; see the module docstring),
    or `error` with one line naming `source`."""
    try:
        _check_yaml_events(text, max_depth, max_nodes)
        return yaml.load(text, Loader=_YAML_LOADER)
    except _Refused as exc:
        raise error(f'{source}: not accepted as YAML: {exc}') from None
    except yaml.YAMLError as exc:
        raise error(f'{source} is not valid YAML: {cap(" ".join(str(exc).split()))}') from None
    except (RecursionError, MemoryError, ValueError, TypeError, OverflowError) as exc:
        raise error(f'{source} cannot be read as YAML ({type(exc).__name__}: '
                    f'{cap(" ".join(str(exc).split()))})') from None


def read_yaml(path: str | Path, error: Error, what: str = 'YAML', kind: str = 'yaml'):
    """The data of a user's YAML file: `read_text` with the cap of `kind`, then
    `parse_yaml`."""
    return parse_yaml(read_text(path, error, what, kind), error, str(path))


def _refusal(path: Path, reason: str) -> OSError:
    return OSError(errno.EINVAL, reason, str(path))


def _output_stat(path: Path, leads_to: str) -> tuple[Path, os.stat_result | None]:
    """(where `path` leads, its status): `path` and None for a new name, the target of a
    symbolic link and its status; the one-line OSError of `output_target` and `folder_target`
    for a name that cannot be looked up or a link that leads nowhere (dangling, a loop)."""
    try:
        status = os.lstat(path)
    except FileNotFoundError:
        return path, None
    except (OSError, ValueError) as exc:
        raise _refusal(path, exc.strerror if isinstance(exc, OSError)
                       else 'not a file name') from None
    if not stat.S_ISLNK(status.st_mode):
        return path, status
    try:
        target = Path(os.path.realpath(path, strict=True))
        return target, os.stat(target)
    except OSError as exc:
        raise _refusal(path, f'it is a symbolic link that leads to {leads_to} '
                             f'({exc.strerror})') from None


def output_target(path: str | Path) -> Path:
    """The file `replace_file(path)` replaces: `path` itself, a new file, or the regular file
    its symbolic link leads to. OSError, whose strerror says why in one line, for anything else:
    a folder, a device, a FIFO, a socket, a link to one of these, a dangling link or a loop."""
    path = Path(path)
    target, status = _output_stat(path, 'no file; only a link to a regular file is written '
                                        'through')
    if status is None or stat.S_ISREG(status.st_mode):
        return target
    if target == path:
        raise _refusal(path, f'it is {file_type(status.st_mode)}, not a regular file; name a '
                             'file')
    raise _refusal(path, f'it is a symbolic link to {target}, {file_type(status.st_mode)}; '
                         'only a link to a regular file is written through')


def folder_target(path: str | Path, empty: bool = False) -> Path:
    """The folder `path` names for output: `path` itself when it is a new name or a folder, or
    the folder its symbolic link leads to; with `empty`, only a new name or an empty folder (a
    bag's). OSError (EINVAL), whose strerror says why in one line, for anything else: a file,
    a device, a FIFO, a socket, a link that leads to none of these or to nothing (dangling, a
    loop), a folder that is not empty. Nothing is created: the caller checks before it waits
    or works."""
    path = Path(path)
    target, status = _output_stat(path, 'nothing; name a folder')
    if status is None:
        return target
    if not stat.S_ISDIR(status.st_mode):
        kind = 'a file' if stat.S_ISREG(status.st_mode) else file_type(status.st_mode)
        link = f'a symbolic link to {_shown(target)}, ' if target != path else ''
        raise _refusal(path, f'it is {link}{kind}, not a folder; name a folder')
    if empty:
        try:
            full = any(os.scandir(target))
        except OSError as exc:
            raise _refusal(path, f'its entries cannot be read ({exc.strerror})') from None
        if full:
            raise _refusal(path, 'it already exists and is not empty (choose a new folder)')
    return target


def replace_file(path: str | Path, write, check=None) -> Path:
    """Write a file whole or not at all: `write(temporary)` a file beside it (same suffix; the
    temporary exists, empty, when `write` is called), `check(temporary)` it if given, then
    rename it over `path` (os.replace). A `path` that is a symbolic link to a regular file is
    written through (its target replaced, its mode kept, the link kept); anything else that is
    not a regular file or a new name is refused (`output_target`). The temporary file is
    removed in any case (an exception, Ctrl-C), so a run that fails on the way leaves `path` as
    it was. OSError and the check's errors propagate."""
    target = output_target(path)
    temporary = target.with_name(f'{target.name}.{os.getpid()}.tmp{target.suffix}')
    try:
        temporary.unlink(missing_ok=True)    # a stale one, or a link put there: never followed
        os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666))
        write(temporary)
        if check is not None:
            check(temporary)
        if output_target(path) != target:
            raise OSError(errno.EAGAIN, 'it was replaced while it was written', str(path))
        if target.exists():
            os.chmod(temporary, stat.S_IMODE(os.stat(target).st_mode))
        os.replace(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)
    return Path(path)


@contextlib.contextmanager
def written(path: str | Path):
    """``with written(path) as f:`` a text file (UTF-8, newlines as written: csv's too) that
    appears whole when the block ends without an exception, or not at all (`replace_file`: a
    link is written through only to a regular file). For the commands' outputs (CSV, JSON,
    YAML) a user may have pointed anywhere."""
    buffer = io.StringIO(newline='')
    yield buffer

    def write(temporary):
        with open(temporary, 'w', newline='', encoding='utf-8') as handle:
            handle.write(buffer.getvalue())
    replace_file(path, write)


def write_text(path: str | Path, text: str) -> Path:
    """`text` written to `path` whole or not at all (`written`)."""
    with written(path) as handle:
        handle.write(text)
    return Path(path)


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """A matplotlib figure saved whole or not at all (`replace_file`: the temporary keeps the
    suffix, which tells matplotlib the format)."""
    return replace_file(path, lambda temporary: fig.savefig(temporary, dpi=dpi))
