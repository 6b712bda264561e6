"""POMDP policy files (`policies/pomdp/*.npz`, written by `hrc-solve --method pomdp`).

A POMDP policy file holds the solved alpha vectors and the fast informed bound over the
observable states the task book can produce (`pomdp.hrc_pomdp`):

- ``columns`` int64 (X,): the observable column l * n_task * 4 + y * 4 + d of each solved
  state, increasing (l the queue length of MODEL.md 8.1, outermost; l = 0 and so y * 4 + d,
  as before, without a queue);
- ``alpha`` float64 (n, 9), ``alpha_action`` int8 (n,), ``alpha_offsets`` int64 (X + 1,):
  Gamma(x_i) = alpha[offsets[i]:offsets[i + 1]], every set non-empty;
- ``q_fib`` float64 (X, 8, 9): the fast informed bound's Q (the `fib` selector);
- ``meta``: JSON, the meta of every policy file (`policy.policy_meta`: the configuration, its
  SHA-256 over the model, cost and solver sections, gamma, eta, solver version, creation time)
  with ``kind: pomdp``, ``observation_sha256`` and the solve's report (bounds, gap, points).

The POMDP also depends on the observation model (Table 5 and epsilon, which the MDP does not
use and which the configuration hash leaves out), so a POMDP file records
``observation_sha256`` over those two, and `load_pomdp_policy` refuses a file whose
configuration hash *or* observation hash differs from the configuration in use, with the
command that solves the right one. The belief mode is not part of either: the policy is solved
for the exact posterior (`BeliefFilter` in bayes mode with the observable transition as
evidence) and runs on whatever belief it is given.

Shipped files live in `policies/pomdp/` (a folder of their own, so the MDP's lookup never
meets them); `default_pomdp_policy_path(config)` finds the one solved for a configuration.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config, config_hash
from ..model import ACTIONS, N_DISTANCE, N_HIDDEN, HRCModel
from ..paths import PATH_QUOTE, replace_file, share_dir
from ..quoting import cap, quote
from ..mdp.policy import (MAX_META_CHARS, MAX_STATES, PolicyError, _check_meta_only, _headers,
                          _parse_meta, _read_members, check_config_hash, open_policy,
                          policy_meta, write_npz)
from .solver import AlphaPolicy, PomdpResult

KIND = 'pomdp'
ARRAYS = ('columns', 'alpha', 'alpha_action', 'alpha_offsets', 'q_fib', 'meta')
# Alpha vectors a file may hold, checked on the headers before anything is allocated: at most
# MAX_VECTORS_PER_STATE per observable state it solves (the solver keeps one per belief point,
# at most 100 a round per state and 21 rounds; the shipped files hold at most 107) and at most
# MAX_VECTORS in all (144 MB; the shipped files hold about 11,000). The loaded policy also
# keeps a dense (states x most vectors of a state x 9) copy (AlphaPolicy.dense): its slots are
# bounded by MAX_VECTORS too (the shipped files need at most 202,044), else a 200 kB file
# with one wide state among 46,656 asks for 13 GiB.
MAX_VECTORS_PER_STATE = 4096
MAX_VECTORS = 2_000_000


def observation_hash(config: Config) -> str:
    """SHA-256 of what the POMDP takes from the observation section: Table 5 and epsilon, and
    the person prior where the configuration gives one (its belief points start from it)."""
    obs = config.data['observation']
    sections = {'table': obs['table'], 'epsilon': obs['epsilon']}
    if obs.get('prior') is not None:
        sections['prior'] = obs['prior']
    return config_hash(sections)


@dataclass
class PomdpPolicy:
    policy: AlphaPolicy
    meta: dict
    path: str

    @property
    def config_sha256(self) -> str:
        return self.meta['config_sha256']


def pomdp_folder() -> Path:
    return share_dir() / 'policies' / KIND


def shipped_pomdp_policy_path(config: Config) -> Path | None:
    """The shipped POMDP policy solved for `config` (by both hashes), or None."""
    want = (config.policy_hash, observation_hash(config))
    for path in sorted(pomdp_folder().glob('*.npz')):
        try:
            meta = _check_meta_only(path)                # reads and bounds `meta` only
        except PolicyError:   # a damaged shipped file is reported when it is loaded
            continue
        if (meta.get('config_sha256'), meta.get('observation_sha256')) == want:
            return path
    return None


def default_pomdp_policy_path(config: Config) -> Path:
    """The shipped POMDP policy solved for `config` (by both hashes); when none matches,
    `policies/pomdp/default.npz`, whose check then says what to solve."""
    return shipped_pomdp_policy_path(config) or pomdp_folder() / 'default.npz'


def pomdp_policy_path(value: str | None, config: Config) -> Path:
    """The file a `pomdp_policy` value names for `config`: the path itself, or for '' (and
    None) the shipped POMDP policy solved for it; PolicyError, saying what to do, when no
    shipped one is."""
    if value:
        return Path(value)
    path = shipped_pomdp_policy_path(config)
    if path is None:
        raise PolicyError(
            f'no POMDP policy in {pomdp_folder()} is solved for {quote(str(config.source))} '
            f'(configuration sha256 {config.policy_hash[:12]}, observation sha256 '
            f'{observation_hash(config)[:12]}): solve one (hrc-solve --method pomdp --config '
            '<that configuration> -o <file>) and name it in pomdp_policy')
    return path


def peek_pomdp_policy(path: str | Path, config: Config) -> dict:
    """The quick half of `load_pomdp_policy`, for a check that must not stall its caller (a
    node's parameter callback): the file exists, is a POMDP policy file and its meta says it
    was solved for `config` (both hashes). Reads the meta only (milliseconds); the loader then
    reads and checks the arrays. PolicyError, saying what to solve, as the loader's."""
    path = Path(path)
    shown = quote(str(path))
    how = 'Solve one: hrc-solve --method pomdp --config <the configuration> -o <file>'
    if not os.path.lexists(path):
        raise PolicyError(f'POMDP policy file {shown} does not exist. {how}')
    meta = _check_meta_only(path)
    _check_pomdp_meta(shown, meta, config, how)
    return meta


def _check_pomdp_meta(shown: str, meta: dict, config: Config | None, how: str) -> None:
    """A POMDP policy file's meta (parsed): its kind and observation hash, and with `config`
    that it was solved for it (both hashes); PolicyError ending with `how` to solve one. The
    peek and the loader alike."""
    if meta.get('kind') != KIND or not isinstance(meta.get('observation_sha256'), str):
        raise PolicyError(f'{shown} is not a POMDP policy file (no POMDP meta: kind, '
                          f'configuration and observation hashes). {how}')
    if config is None:
        return
    check_config_hash(shown, meta, config, solve=' --method pomdp')
    if meta['observation_sha256'] != observation_hash(config):
        raise PolicyError(f'POMDP policy {shown} was solved for another observation model '
                          '(Table 5, epsilon or the person prior) than the configuration in '
                          f'use ({config.source}). {how}')


def load_shipped_pomdp_policy(config: Config) -> PomdpPolicy:
    """The shipped POMDP policy solved for `config` (`PolicyError`, saying what to solve,
    when there is none)."""
    return load_pomdp_policy(default_pomdp_policy_path(config), config)


def save_pomdp_policy(path: str | Path, result: PomdpResult, config: Config) -> Path:
    path = Path(path)
    alphas, hrc = result.alphas, result.hrc
    meta = policy_meta(config, kind=KIND, method='pomdp',
                       observation_sha256=observation_hash(config),
                       observable_states=int(len(hrc.columns)), vectors=int(len(alphas)),
                       n_states=int(hrc.model.n_states), report=result.report)
    path.parent.mkdir(parents=True, exist_ok=True)
    return replace_file(path, lambda tmp: write_npz(
        tmp, columns=hrc.columns.astype(np.int64), alpha=alphas.alpha.astype(np.float64),
        alpha_action=alphas.action.astype(np.int8),
        alpha_offsets=alphas.offsets.astype(np.int64),
        q_fib=result.upper.q_fib.astype(np.float64), meta=np.array(json.dumps(meta))))


def load_pomdp_policy(path: str | Path, config: Config | None = None) -> PomdpPolicy:
    """Load and check a POMDP policy file; with `config`, also check it was solved for it."""
    path = Path(path)
    # the shipped folder's own file may be solved again in place; any other path may be
    # something else (an MDP policy named by mistake) that this advice must not overwrite
    target = cap(path, PATH_QUOTE) if path.parent == pomdp_folder() else '<file>'
    how = f'Solve it: hrc-solve --method pomdp --config <your config.yaml> -o {target}'
    n_columns = None
    if config is not None:
        model = HRCModel(config)
        n_columns = model.n_levels * model.n_task * N_DISTANCE   # l outermost (MODEL.md 8.1)
    with open_policy(path, how, 'POMDP policy') as stream:
        headers = _headers(stream, path, how)
        _check_headers(path, headers, n_columns, how)   # before any array is read
        arrays = _read_members(stream, path, headers, ARRAYS, how, 'a POMDP policy file')
    meta = _parse_meta(path, str(arrays.pop('meta')), how)
    _check_pomdp_meta(str(path), meta, config, how)
    _check_arrays(path, arrays, how)
    columns = arrays['columns']
    if config is not None:
        if int(columns.max()) >= n_columns:
            raise PolicyError(f'{path}: observable columns beyond the configuration\'s '
                              f'{n_columns}. {how}')
        available = model.availability[:, columns % N_DISTANCE].T
    else:
        n_columns = int(columns.max()) + 1
        available = np.ones((len(columns), len(ACTIONS)), dtype=bool)
    policy = AlphaPolicy(columns, arrays['alpha'], arrays['alpha_action'],
                         arrays['alpha_offsets'], arrays['q_fib'], available, n_columns)
    return PomdpPolicy(policy, meta, str(path))


def _check_headers(path: Path, headers: dict, n_columns: int | None, how: str) -> None:
    """Names, dtypes and bounded shapes of the members, from their .npy headers only."""
    missing = set(ARRAYS) - set(headers)
    if missing:
        raise PolicyError(f'{path} is not an hrc_ros POMDP policy file (missing '
                          f'{", ".join(sorted(missing))}). {how}')
    n_x = headers['columns'][0][:1]
    n_alpha = headers['alpha'][0][:1]
    limit_x = MAX_STATES if n_columns is None else n_columns
    limit_alpha = min(MAX_VECTORS, MAX_VECTORS_PER_STATE * (n_x[0] if n_x else 0))
    expected = {
        'columns': (np.int64, n_x, n_x and n_x[0] <= limit_x),
        'alpha': (np.float64, n_alpha + (N_HIDDEN,), n_alpha and n_alpha[0] <= limit_alpha),
        'alpha_action': (np.int8, n_alpha, True),
        'alpha_offsets': (np.int64, tuple(n + 1 for n in n_x), True),
        'q_fib': (np.float64, n_x + (len(ACTIONS), N_HIDDEN), True),
    }
    for name, (dtype, shape, bounded) in expected.items():
        got_shape, got_dtype = headers[name][:2]
        if got_dtype != np.dtype(dtype) or got_shape != shape or not bounded:
            raise PolicyError(f'{path}: {name} must be {np.dtype(dtype)} of shape '
                              f'{cap(shape, 80)} (at most {limit_x:,} states and '
                              f'{MAX_VECTORS_PER_STATE:,} vectors a state, {MAX_VECTORS:,} in '
                              f'all: {limit_alpha:,} here), got {got_dtype} '
                              f'{cap(got_shape, 80)}. {how}')
    shape, dtype = headers['meta'][:2]
    if shape != () or dtype.kind != 'U' or dtype.itemsize // 4 > MAX_META_CHARS:
        raise PolicyError(f'{path}: meta must be one JSON string of at most {MAX_META_CHARS} '
                          f'characters. {how}')


def _check_arrays(path: Path, a: dict, how: str) -> None:
    def bad(what: str):
        raise PolicyError(f'{path}: {what}. {how}')
    columns, alpha, action = a['columns'], a['alpha'], a['alpha_action']
    offsets, q_fib = a['alpha_offsets'], a['q_fib']
    if columns.dtype != np.int64 or columns.ndim != 1 or columns.size == 0:
        bad('columns must be a non-empty 1-D int64 array')
    if columns.min() < 0 or np.any(np.diff(columns) <= 0):
        bad('columns must be non-negative and increasing')
    n_x = columns.size
    if alpha.dtype != np.float64 or alpha.ndim != 2 or alpha.shape[1] != N_HIDDEN:
        bad(f'alpha must be float64 of shape (n, {N_HIDDEN})')
    if action.dtype != np.int8 or action.shape != (alpha.shape[0],):
        bad('alpha_action must be int8, one per vector')
    if action.size and (action.min() < 0 or action.max() >= len(ACTIONS)):
        bad(f'alpha_action holds action indices outside 0..{len(ACTIONS) - 1}')
    if offsets.dtype != np.int64 or offsets.shape != (n_x + 1,):
        bad(f'alpha_offsets must be int64 of shape ({n_x + 1},)')
    if offsets[0] != 0 or offsets[-1] != alpha.shape[0] or np.any(np.diff(offsets) < 1):
        bad('alpha_offsets must run from 0 to the number of vectors, every state holding one '
            'or more')
    if n_x * int(np.diff(offsets).max()) > MAX_VECTORS:
        bad(f'{n_x:,} states by {int(np.diff(offsets).max()):,} vectors in the widest is more '
            f'than the {MAX_VECTORS:,} slots the loaded policy may take')
    if q_fib.dtype != np.float64 or q_fib.shape != (n_x, len(ACTIONS), N_HIDDEN):
        bad(f'q_fib must be float64 of shape ({n_x}, {len(ACTIONS)}, {N_HIDDEN})')
    if not (np.all(np.isfinite(alpha)) and np.all(np.isfinite(q_fib))):
        bad('alpha or q_fib holds NaN or inf')
