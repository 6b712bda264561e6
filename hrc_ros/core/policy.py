"""Policy files (`policies/*.npz`, MODEL.md section 5).

A policy file holds ``policy`` (int8, (N,)), ``value`` (float64, (N,)) and ``meta`` (a JSON
string: the full configuration, gamma, eta, sweeps, final residual, solver version, creation
time and ``config_sha256``, the SHA-256 of the model/cost/solver sections). `load_policy`
refuses a file that is not such an archive, whose arrays have the wrong shape or dtype, or that
was solved for another configuration, with a message that says what to do.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import Config
from .model import ACTIONS, HRCModel
from .paths import share_dir
from .solver import SOLVER_VERSION, SolveResult


class PolicyError(RuntimeError):
    """A policy file is missing, corrupt, or solved for another configuration."""


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
            with np.load(path, allow_pickle=False) as archive:   # reads `meta` only
                if json.loads(str(archive['meta'])).get('config_sha256') == config.policy_hash:
                    return path
        except Exception:  # noqa: BLE001 - a damaged shipped file is reported when loaded
            continue
    return default


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
    tmp = path.with_name(path.name + '.tmp.npz')
    np.savez_compressed(tmp, policy=result.policy.astype(np.int8),
                        value=result.value.astype(np.float64), meta=np.array(json.dumps(meta)))
    os.replace(tmp, path)
    return path


def load_policy(path: str | Path, config: Config | None = None) -> Policy:
    """Load and check a policy file; with `config`, also check it was solved for it."""
    path = Path(path)
    resolve = (f'Solve it again: hrc-solve --config <your config.yaml> -o {path}')
    if not path.is_file():
        raise PolicyError(f'policy file {path} does not exist. {resolve}')
    try:
        with np.load(path, allow_pickle=False) as archive:
            missing = {'policy', 'value', 'meta'} - set(archive.files)
            if missing:
                raise PolicyError(f'{path} is not an hrc_ros policy file (missing '
                                  f'{", ".join(sorted(missing))}). {resolve}')
            policy = archive['policy']
            value = archive['value']
            meta = json.loads(str(archive['meta']))
    except PolicyError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
        raise PolicyError(f'{path} is corrupt or not a policy file ({exc}). {resolve}') from None
    if not isinstance(meta, dict) or 'config_sha256' not in meta:
        raise PolicyError(f'{path} has no configuration hash in its meta. {resolve}')
    if policy.dtype != np.int8 or policy.ndim != 1:
        raise PolicyError(f'{path}: policy must be a 1-D int8 array, got {policy.dtype} '
                          f'{policy.shape}. {resolve}')
    if value.dtype != np.float64 or value.shape != policy.shape:
        raise PolicyError(f'{path}: value must be float64 of shape {policy.shape}. {resolve}')
    if policy.size and (policy.min() < 0 or policy.max() >= len(ACTIONS)):
        raise PolicyError(f'{path}: policy holds action indices outside 0..7. {resolve}')
    if not np.all(np.isfinite(value)):
        raise PolicyError(f'{path}: value holds NaN or inf. {resolve}')
    loaded = Policy(policy=policy, value=value, meta=meta, path=str(path))
    if config is not None:
        check_policy(loaded, config)
    return loaded


def check_policy(policy: Policy, config: Config) -> None:
    """Refuse a policy solved for another configuration."""
    check_config_hash(policy.path, policy.meta, config)
    n = HRCModel(config).n_states
    if policy.policy.size != n:
        raise PolicyError(f'policy {policy.path} has {policy.policy.size} states, the '
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
