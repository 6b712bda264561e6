"""Policy files (`policies/*.npz`, MODEL.md section 5).

A policy file holds ``policy`` (int8, (N,)), ``value`` (float64, (N,)) and ``meta`` (a JSON
string: the full configuration, gamma, eta, sweeps, final residual, solver version, creation
time and ``config_sha256``, the SHA-256 of the model/cost/solver sections). `load_policy`
refuses a file that is not such an archive, whose arrays have the wrong shape or dtype, or that
was solved for another configuration, with a message that says what to do.

A policy file may come from anywhere (a colleague, a download, a fitted model), so it is read
as untrusted input: it must be a regular file of at most the 'policy' cap (`paths.open_input`:
a FIFO or /dev/zero is refused before it is opened), opened once and read only through that
handle; the zip's central directory is bounded before `zipfile` parses it (at most
`MAX_MEMBERS` members in `MAX_DIRECTORY_BYTES`); the members and their `.npy` headers are
checked (names, dtypes, shapes against the configuration's state count when one is given,
and each member's declared size against its header's) before any array is read, so a header
that claims 2^40 elements is refused instead of allocated and no member inflates past what its
header says; `meta` is bounded in size and nesting and its fields are type-checked. Anything
else is a `PolicyError`, and what it quotes of the file is capped (`quoting`).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..config import Config
from ..model import ACTIONS, HRCModel
from ..paths import PATH_QUOTE, open_input, replace_file, share_dir
from ..quoting import QUOTE_LIMIT, cap, quote
from .solver import SOLVER_VERSION, SolveResult


class PolicyError(RuntimeError):
    """A policy file is missing, corrupt, or solved for another configuration."""


MAX_META_CHARS = 1 << 20          # meta JSON: a configuration and a few numbers, far below
MAX_META_DEPTH = 32               # nesting of the meta JSON (the configuration is 4 deep)
MAX_STATES = 200_000_000          # without a configuration to compare: 1.4 GB of value alone
MAX_MEMBERS = 16                  # members of a policy archive (MDP: 3, POMDP: 6)
MAX_DIRECTORY_BYTES = 64 * 1024   # its zip central directory (the shipped ones: 165-346 bytes)
SHA256_HEX = frozenset('0123456789abcdef')
_END_OF_DIRECTORY = b'PK\x05\x06'
_ZIP64_LOCATOR = b'PK\x06\x07'


def solve_again(path: Path) -> str:
    """What to do about a policy file that cannot be used: solve it again in its place when
    it is named like one (.npz); a README or a folder named by mistake is not overwritten."""
    target = cap(path, PATH_QUOTE) if path.suffix == '.npz' and not path.is_dir() else \
        '<file>.npz'
    return f'Solve it again: hrc-solve --config <your config.yaml> -o {target}'


def open_policy(path: Path, resolve: str, what: str = 'policy') -> BinaryIO:
    """A policy file opened for reading (`paths.open_input`: a regular file of at most the
    'policy' cap), or PolicyError saying what is wrong and `resolve` (what to do). `what`
    names the kind ('policy', 'POMDP policy'): the messages add 'file'."""
    if not os.path.lexists(path):
        raise PolicyError(f'{what} file {cap(path, PATH_QUOTE)} does not exist. {resolve}')
    return open_input(path, lambda message: PolicyError(f'{message}. {resolve}'), 'policy', what)


def _check_directory(stream: BinaryIO, path: Path, resolve: str) -> None:
    """Bound the zip's central directory before zipfile parses it whole: zipfile reads as many
    entries as the end record's directory size says, so a 1 GB directory of empty entries
    would become gigabytes of ZipInfo objects."""
    size = stream.seek(0, os.SEEK_END)
    tail_size = min(size, 22 + 0xFFFF)          # the end record, and a comment of up to 64 KiB
    stream.seek(size - tail_size)
    tail = stream.read(tail_size)
    at = tail.rfind(_END_OF_DIRECTORY)
    if at < 0 or len(tail) - at < 22:
        return                                  # not a zip: zipfile says so below
    entries, directory_bytes = struct.unpack('<xxxxxxxxxxHI', tail[at:at + 16])
    if tail[max(0, at - 20):at - 16] == _ZIP64_LOCATOR or entries > MAX_MEMBERS \
            or directory_bytes > MAX_DIRECTORY_BYTES:
        raise PolicyError(f'{path} is not a policy file: its zip directory lists {entries} '
                          f'members in {directory_bytes:,} bytes (a policy has at most '
                          f'{MAX_MEMBERS} in {MAX_DIRECTORY_BYTES:,}). {resolve}')


def _headers(stream: BinaryIO, path: Path, resolve: str) -> dict:
    """name -> (shape, dtype, declared bytes, bytes its header implies) of an .npz's members,
    from their .npy headers only (`_read_members` refuses a member whose two sizes differ)."""
    out = {}
    try:
        _check_directory(stream, path, resolve)
        stream.seek(0)
        with zipfile.ZipFile(stream) as archive:
            for info in archive.infolist():
                name = info.filename[:-4] if info.filename.endswith('.npy') else info.filename
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                              else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = reader(member)
                    header_bytes = member.tell()
                out[name] = (shape, dtype, info.file_size,
                             header_bytes + math.prod(shape) * dtype.itemsize)
    except PolicyError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError, TypeError,
            SyntaxError, OverflowError, NotImplementedError, RuntimeError) as exc:
        raise PolicyError(f'{path} is corrupt or not a policy file ({type(exc).__name__}: '
                          f'{cap(exc, 200)}). {resolve}') from None
    return out


def _read_members(stream: BinaryIO, path: Path, headers: dict, names, resolve: str,
                  what: str = 'a policy file') -> dict:
    """The arrays `names` of an archive whose `headers` were checked, read through `stream`.
    A member whose declared size is not its header's plus its elements' is refused first, so
    np.load reads exactly what the checked header says (and inflates no more)."""
    for name in names:
        shape, dtype, declared, expected = headers[name]
        if declared != expected:
            raise PolicyError(f'{path} is corrupt: member {cap(name, 80)} holds {declared:,} '
                              f'bytes, its header says {expected:,} ({dtype} '
                              f'{cap(shape, 80)}). {resolve}')
    try:
        stream.seek(0)
        with np.load(stream, allow_pickle=False) as archive:
            return {name: archive[name] for name in names}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError, RuntimeError,
            NotImplementedError) as exc:
        raise PolicyError(f'{path} is corrupt or not {what} ({type(exc).__name__}: '
                          f'{cap(exc, 200)}). {resolve}') from None


def write_npz(path: Path, **arrays) -> None:
    """np.savez_compressed into exactly `path` (through a file object: given a name without
    .npz, numpy would write to another name, with .npz appended)."""
    with open(path, 'wb') as stream:
        np.savez_compressed(stream, **arrays)


def _check_headers(path: Path, headers: dict, n_states: int | None, resolve: str) -> None:
    missing = {'policy', 'value', 'meta'} - set(headers)
    if missing:
        raise PolicyError(f'{path} is not an hrc_ros policy file (missing '
                          f'{", ".join(sorted(missing))}). {resolve}')
    limit = MAX_STATES if n_states is None else n_states
    for name, dtype in (('policy', np.dtype(np.int8)), ('value', np.dtype(np.float64))):
        shape, got = headers[name][:2]
        if got != dtype or len(shape) != 1:
            raise PolicyError(f'{path}: {name} must be a 1-D {dtype} array, got {got} '
                              f'{shape}. {resolve}')
        if shape[0] > limit:   # larger than the configuration: it cannot be its policy
            what = f'the configuration has {n_states}' if n_states else f'at most {limit}'
            raise PolicyError(f'{path}: {name} holds {shape[0]} states, {what}. {resolve}')
    if headers['value'][0] != headers['policy'][0]:
        raise PolicyError(f'{path}: value must have the shape of policy. {resolve}')
    shape, dtype = headers['meta'][:2]
    if shape != () or dtype.kind != 'U' or dtype.itemsize // 4 > MAX_META_CHARS:
        raise PolicyError(f'{path}: meta must be one JSON string of at most {MAX_META_CHARS} '
                          f'characters, got {dtype} {shape}. {resolve}')


def _depth(value, limit: int) -> int:
    """Nesting depth of a parsed JSON value, stopping past `limit` (no deep recursion)."""
    depth, level = 0, [value]
    while level and depth <= limit:
        depth += 1
        level = [v for item in level if isinstance(item, (dict, list))
                 for v in (item.values() if isinstance(item, dict) else item)]
    return depth


def _parse_meta(path: Path, text: str, resolve: str) -> dict:
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise PolicyError(f'{path}: meta is not JSON ({type(exc).__name__}: '
                          f'{cap(exc, 200)}). {resolve}') from None
    if not isinstance(meta, dict) or _depth(meta, MAX_META_DEPTH) > MAX_META_DEPTH:
        raise PolicyError(f'{path}: meta must be a JSON object of depth at most '
                          f'{MAX_META_DEPTH}. {resolve}')
    sha = meta.get('config_sha256')
    if not (isinstance(sha, str) and len(sha) == 64 and set(sha) <= SHA256_HEX):
        raise PolicyError(f'{path} has no valid configuration hash in its meta (config_sha256 '
                          f'must be 64 hex digits, got {quote(sha, 80)}). {resolve}')
    source = meta.get('config_source', '')
    if not isinstance(source, str):
        meta['config_source'] = cap(source, 200)
    return meta


@dataclass
class Policy:
    policy: np.ndarray   # int8 action index per flat state
    value: np.ndarray    # float64 V per flat state
    meta: dict
    path: str

    @property
    def config_sha256(self) -> str:
        return self.meta['config_sha256']


def default_policy_path(config: Config | None = None) -> Path:
    """The shipped policy to use when none is named: with `config`, the shipped policy solved
    for it (so `config:=.../paper.yaml` alone finds `policies/paper.npz`); otherwise, or when
    none matches, `policies/default.npz` (whose check then says what to solve)."""
    default = share_dir() / 'policies' / 'default.npz'
    if config is None:
        return default
    for path in sorted(default.parent.glob('*.npz'), key=lambda p: (p != default, p)):
        try:
            if _check_meta_only(path)['config_sha256'] == config.policy_hash:
                return path
        except PolicyError:   # a damaged shipped file is reported when it is loaded
            continue
    return default


def _check_meta_only(path: Path) -> dict:
    """The checked meta of a policy file, reading no other array."""
    with open_policy(path, '') as stream:
        headers = _headers(stream, path, '')
        if 'meta' not in headers:
            raise PolicyError(f'{path} has no meta')
        shape, dtype = headers['meta'][:2]
        if shape != () or dtype.kind != 'U' or dtype.itemsize // 4 > MAX_META_CHARS:
            raise PolicyError(f'{path}: meta is not a bounded JSON string')
        text = str(_read_members(stream, path, headers, ['meta'], '')['meta'])
    return _parse_meta(path, text, '')


def policy_arrays(policy, value=None) -> tuple[np.ndarray, np.ndarray | None]:
    """(action array, value array or None) of a `Policy`, a `SolveResult` or a plain (N,)
    action array; an explicit `value` wins over the object's own."""
    if hasattr(policy, 'policy'):
        if value is None:
            value = getattr(policy, 'value', None)
        policy = policy.policy
    return np.asarray(policy), (None if value is None else np.asarray(value, dtype=float))


def policy_meta(config: Config, **fields) -> dict:
    """The meta every policy file carries (the configuration, its hash, gamma, eta, the solver
    version, the creation time, the actions) and `fields`."""
    return {
        'config': config.data,
        'config_source': config.source,
        'config_sha256': config.policy_hash,
        'gamma': config.gamma,
        'eta': config.eta,
        **fields,
        'solver_version': SOLVER_VERSION,
        'created': _dt.datetime.now(_dt.timezone.utc).isoformat(timespec='seconds'),
        'actions': list(ACTIONS),
    }


def save_policy(path: str | Path, result: SolveResult, config: Config) -> Path:
    path = Path(path)
    meta = policy_meta(
        config, method=result.method, iterations=result.iterations,
        sweeps=result.iterations if result.method == 'value_iteration' else None,
        residual=result.residual, converged=result.converged,
        n_states=int(result.policy.size))
    path.parent.mkdir(parents=True, exist_ok=True)
    return replace_file(path, lambda tmp: write_npz(
        tmp, policy=result.policy.astype(np.int8), value=result.value.astype(np.float64),
        meta=np.array(json.dumps(meta))))


def load_policy(path: str | Path, config: Config | None = None) -> Policy:
    """Load and check a policy file; with `config`, also check it was solved for it."""
    path = Path(path)
    resolve = solve_again(path)
    n_states = None if config is None else HRCModel(config).n_states
    with open_policy(path, resolve) as stream:
        headers = _headers(stream, path, resolve)
        _check_headers(path, headers, n_states, resolve)
        arrays = _read_members(stream, path, headers, ('policy', 'value', 'meta'), resolve)
    policy, value = arrays['policy'], arrays['value']
    meta = _parse_meta(path, str(arrays['meta']), resolve)
    if policy.size and (policy.min() < 0 or policy.max() >= len(ACTIONS)):
        raise PolicyError(f'{path}: policy holds action indices outside 0..7. {resolve}')
    if not np.all(np.isfinite(value)):
        raise PolicyError(f'{path}: value holds NaN or inf. {resolve}')
    loaded = Policy(policy=policy, value=value, meta=meta, path=str(path))
    if config is not None:
        check_policy(loaded, config)
    return loaded


def peek_policy(path: str | Path, config: Config) -> dict:
    """The quick half of `load_policy`, for a check that must not stall its caller (a node's
    parameter callback): the file exists, its members' headers are a policy's for `config`'s
    state count, and its meta says it was solved for `config`. Reads the headers and the meta
    only (milliseconds); `load_policy` then reads and checks the arrays. PolicyError as there."""
    path = Path(path)
    resolve = solve_again(path)
    with open_policy(path, resolve) as stream:
        headers = _headers(stream, path, resolve)
        _check_headers(path, headers, HRCModel(config).n_states, resolve)
        text = str(_read_members(stream, path, headers, ['meta'], resolve)['meta'])
    meta = _parse_meta(path, text, resolve)
    check_policy(Policy(np.zeros(0, dtype=np.int8), np.zeros(0), meta, str(path)), config,
                 states=headers['policy'][0][0])
    return meta


def check_policy(policy: Policy, config: Config, states: int | None = None) -> None:
    """Refuse a policy solved for another configuration."""
    check_config_hash(policy.path, policy.meta, config)
    n = HRCModel(config).n_states
    size = policy.policy.size if states is None else states
    if size != n:
        raise PolicyError(f'policy {policy.path} has {size} states, the '
                          f'configuration has {n}. Solve it again with hrc-solve.')


def _stream_kind(stream: bool) -> str:
    return ('a task stream (MODEL.md 8: tasks keep arriving)' if stream
            else 'no task stream (the paper\'s model: no task arrives)')


def check_config_hash(path, meta: dict, config: Config, solve: str = '') -> None:
    """Refuse a policy file (its `meta`) solved for another configuration than `config`."""
    expected = config.policy_hash
    found = meta['config_sha256']
    if found != expected:
        raw = meta.get('config')
        planned = isinstance(raw, dict) and isinstance(raw.get('stream'), dict)
        kinds = ''
        if planned != config.has_stream:
            kinds = (f' The policy plans {_stream_kind(planned)}; the configuration describes '
                     f'{_stream_kind(config.has_stream)}.')
        raise PolicyError(
            f'policy {path} was solved for configuration {str(found)[:12]} '
            f'({cap(meta.get("config_source", "unknown source"), QUOTE_LIMIT)}), but the '
            f'configuration in use ({config.source}) is {expected[:12]}.{kinds} '
            'Solve a policy for it: '
            f'hrc-solve --config {config.source}{solve} -o <policy.npz>, or pass the matching '
            'configuration.')
