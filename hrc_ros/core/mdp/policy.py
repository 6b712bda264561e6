"""Policy files (`policies/*.npz`, MODEL.md section 5).

A policy file holds ``policy`` (int8, (N,)), ``value`` (float64, (N,)) and ``meta`` (a JSON
string: the full configuration, gamma, eta, sweeps, final residual, solver version, creation
time and ``config_sha256``, the SHA-256 of the model/cost/solver sections). `load_policy`
refuses a file that is not such an archive, whose arrays have the wrong shape or dtype, or that
was solved for another configuration, with a message that says what to do.

A policy file may come from anywhere (a colleague, a download, a fitted model), so it is read
as untrusted input: the archive's members and their `.npy` headers are checked (names, dtypes,
shapes, sizes, against the configuration's state count when one is given) before any array is
read, so a header that claims 2^40 elements is refused instead of allocated; `meta` is bounded
in size and nesting and its fields are type-checked. Anything else is a `PolicyError`.
"""

from __future__ import annotations

import datetime as _dt
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config
from ..model import ACTIONS, HRCModel
from ..paths import replace_file, share_dir
from .solver import SOLVER_VERSION, SolveResult


class PolicyError(RuntimeError):
    """A policy file is missing, corrupt, or solved for another configuration."""


MAX_META_CHARS = 1 << 20          # meta JSON: a configuration and a few numbers, far below
MAX_META_DEPTH = 32               # nesting of the meta JSON (the configuration is 4 deep)
MAX_STATES = 200_000_000          # without a configuration to compare: 1.4 GB of value alone
SHA256_HEX = frozenset('0123456789abcdef')


def _headers(path: Path, resolve: str) -> dict:
    """name -> (shape, dtype) of an .npz's members, from their .npy headers only."""
    out = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                name = info.filename[:-4] if info.filename.endswith('.npy') else info.filename
                with archive.open(info) as stream:
                    version = np.lib.format.read_magic(stream)
                    reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                              else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = reader(stream)
                out[name] = (shape, dtype, info.file_size)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError, TypeError,
            SyntaxError) as exc:
        raise PolicyError(f'{path} is corrupt or not a policy file ({type(exc).__name__}: '
                          f'{str(exc)[:200]}). {resolve}') from None
    return out


def _check_headers(path: Path, headers: dict, n_states: int | None, resolve: str) -> None:
    missing = {'policy', 'value', 'meta'} - set(headers)
    if missing:
        raise PolicyError(f'{path} is not an hrc_ros policy file (missing '
                          f'{", ".join(sorted(missing))}). {resolve}')
    limit = MAX_STATES if n_states is None else n_states
    for name, dtype in (('policy', np.dtype(np.int8)), ('value', np.dtype(np.float64))):
        shape, got, _ = headers[name]
        if got != dtype or len(shape) != 1:
            raise PolicyError(f'{path}: {name} must be a 1-D {dtype} array, got {got} '
                              f'{shape}. {resolve}')
        if shape[0] > limit:   # larger than the configuration: it cannot be its policy
            what = f'the configuration has {n_states}' if n_states else f'at most {limit}'
            raise PolicyError(f'{path}: {name} holds {shape[0]} states, {what}. {resolve}')
    if headers['value'][0] != headers['policy'][0]:
        raise PolicyError(f'{path}: value must have the shape of policy. {resolve}')
    shape, dtype, _ = headers['meta']
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
                          f'{str(exc)[:200]}). {resolve}') from None
    if not isinstance(meta, dict) or _depth(meta, MAX_META_DEPTH) > MAX_META_DEPTH:
        raise PolicyError(f'{path}: meta must be a JSON object of depth at most '
                          f'{MAX_META_DEPTH}. {resolve}')
    sha = meta.get('config_sha256')
    if not (isinstance(sha, str) and len(sha) == 64 and set(sha) <= SHA256_HEX):
        raise PolicyError(f'{path} has no valid configuration hash in its meta (config_sha256 '
                          f'must be 64 hex digits, got {str(sha)[:80]!r}). {resolve}')
    source = meta.get('config_source', '')
    if not isinstance(source, str):
        meta['config_source'] = str(source)[:200]
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
    headers = _headers(path, '')
    if 'meta' not in headers:
        raise PolicyError(f'{path} has no meta')
    shape, dtype, _ = headers['meta']
    if shape != () or dtype.kind != 'U' or dtype.itemsize // 4 > MAX_META_CHARS:
        raise PolicyError(f'{path}: meta is not a bounded JSON string')
    with np.load(path, allow_pickle=False) as archive:
        return _parse_meta(path, str(archive['meta']), '')


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
    return replace_file(path, lambda tmp: np.savez_compressed(
        tmp, policy=result.policy.astype(np.int8), value=result.value.astype(np.float64),
        meta=np.array(json.dumps(meta))))


def load_policy(path: str | Path, config: Config | None = None) -> Policy:
    """Load and check a policy file; with `config`, also check it was solved for it."""
    path = Path(path)
    resolve = (f'Solve it again: hrc-solve --config <your config.yaml> -o {path}')
    if not path.is_file():
        raise PolicyError(f'policy file {path} does not exist. {resolve}')
    n_states = None if config is None else HRCModel(config).n_states
    _check_headers(path, _headers(path, resolve), n_states, resolve)
    try:
        with np.load(path, allow_pickle=False) as archive:
            policy = archive['policy']
            value = archive['value']
            text = str(archive['meta'])
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
        raise PolicyError(f'{path} is corrupt or not a policy file ({type(exc).__name__}: '
                          f'{str(exc)[:200]}). {resolve}') from None
    meta = _parse_meta(path, text, resolve)
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
    resolve = f'Solve it again: hrc-solve --config <your config.yaml> -o {path}'
    if not path.is_file():
        raise PolicyError(f'policy file {path} does not exist. {resolve}')
    headers = _headers(path, resolve)
    _check_headers(path, headers, HRCModel(config).n_states, resolve)
    try:
        with np.load(path, allow_pickle=False) as archive:
            text = str(archive['meta'])
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
        raise PolicyError(f'{path} is corrupt or not a policy file ({type(exc).__name__}: '
                          f'{str(exc)[:200]}). {resolve}') from None
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


def check_config_hash(path, meta: dict, config: Config, solve: str = '') -> None:
    """Refuse a policy file (its `meta`) solved for another configuration than `config`."""
    expected = config.policy_hash
    found = meta['config_sha256']
    if found != expected:
        raise PolicyError(
            f'policy {path} was solved for configuration {str(found)[:12]} '
            f'({meta.get("config_source", "unknown source")}), but the configuration '
            f'in use ({config.source}) is {expected[:12]}. Solve a policy for it: '
            f'hrc-solve --config {config.source}{solve} -o <policy.npz>, or pass the matching '
            'configuration.')
