"""Policy files (`policies/*.npz`, MODEL.md section 5) and where shipped data lives.

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
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import Config
from .model import ACTIONS, HRCModel
from .solver import SOLVER_VERSION, SolveResult

PACKAGE = 'hrc_ros'


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


def share_dir() -> Path:
    """The package's data folder (holding config/ and policies/).

    In order: $HRC_ROS_SHARE; the ament index (a colcon/ROS install); <sys.prefix>/share/hrc_ros
    (a pip install); the source checkout this module lives in.
    """
    env = os.environ.get('HRC_ROS_SHARE')
    if env:
        return Path(env)
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory(PACKAGE))
    except Exception:  # noqa: BLE001 - not a ROS install, or the package is not indexed
        pass
    here = Path(__file__).resolve().parent.parent
    if (here / 'config' / 'default.yaml').is_file():
        return here
    return Path(sys.prefix) / 'share' / PACKAGE


def default_config_path() -> Path:
    return share_dir() / 'config' / 'default.yaml'


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


def save_policy(path: str | Path, result: SolveResult, config: Config) -> Path:
    path = Path(path)
    meta = {
        'config': config.data,
        'config_source': config.source,
        'config_sha256': config.policy_hash,
        'gamma': config.gamma,
        'eta': config.eta,
        'sweeps': result.sweeps,
        'residual': result.residual,
        'converged': result.converged,
        'method': result.method,
        'solver_version': SOLVER_VERSION,
        'created': _dt.datetime.now(_dt.timezone.utc).isoformat(timespec='seconds'),
        'n_states': int(result.policy.size),
        'actions': list(ACTIONS),
    }
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
    expected = config.policy_hash
    if policy.config_sha256 != expected:
        raise PolicyError(
            f'policy {policy.path} was solved for configuration {policy.config_sha256[:12]} '
            f'({policy.meta.get("config_source", "unknown source")}), but the configuration '
            f'in use ({config.source}) is {expected[:12]}. Solve a policy for it: '
            f'hrc-solve --config {config.source} -o <policy.npz>, or pass the matching '
            'configuration.')
    n = HRCModel(config).n_states
    if policy.policy.size != n:
        raise PolicyError(f'policy {policy.path} has {policy.policy.size} states, the '
                          f'configuration has {n}. Solve it again with hrc-solve.')
