"""Configuration of the HRC decision model: load, validate, hash.

Every number of the model (MODEL.md) comes from a YAML file; `config/default.yaml` holds the
defaults of MODEL.md and `config/paper.yaml` the paper's own values. A configuration file is
complete: a missing or unknown key is an error naming the field, so a typo never silently falls
back to a default. Programmatic variants (for example the reduced rho = sigma = 1 model of the
tests) are made with `load_config(path, overrides={...})`.

Sections:

- `model`: rho, sigma, p_accept (per em), p_delta (per ea, Delta = -1, 0, +1), emotion chains
  (down, stay, up) per action group and emotion variable, and optionally `robot_paused_by`: the
  actions under which the robot's counter bc does not run down (MODEL.md 3.2; absent: [dn], the
  paper's model; [dn, dp, dm]: the cell with an arm, where a retreat or a move to the
  collaboration pose stops the task's program, docs/ROBOT.md), and optionally `retreat_reach`:
  the band below which a retreat (dp) gains one (MODEL.md 3.3; absent or null: every band; 1:
  the cell with an arm, where a retreat gains none, config/arm.yaml), and optionally
  `approach_reach`: the band above which a move closer (dm) gains one, without the paper's
  floor at band 1 (MODEL.md 3.3; absent or null: the paper's rule; 3: the cell with an arm,
  where a move to the collaboration pose gains none, config/arm.yaml), and optionally
  `robot_rate`: per task nature with a robot share (0, 2, 3: the station its program runs at)
  the probability, by the band d = 0..3 at the epoch's start, that the robot's counter runs
  down in an epoch it works (MODEL.md 3.2; absent or null: 1, the paper's rule; the cell with
  an arm: measured, SSM slows the arm near the person, config/arm.yaml);
- `cost`: k1, k2, alpha1..alpha13, beta1..beta6 (MODEL.md section 4);
- `solver`: gamma, eta, sweeps (null = run to eta, at most MAX_SWEEPS; an integer = the paper's
  fixed sweep count, at most MAX_SWEEPS),
  fail_safe_aware (false = MODEL.md: every action at every state; true = only dn at d = 0, the
  action the decision node's fail-safe enforces there, so the policy plans around it);
- `observation`: the Table 5 rows, the bayes-mode epsilon and the belief mode (MODEL.md 6), and
  optionally `likelihood`: P(O | h) as 3 rows (O = 1, 2, 3) of 9 columns (h = 3*em + ea), each
  column a distribution over O. Absent or null: the bayes filter derives P(O | h) from Table 5
  and epsilon (MODEL.md 6); given (for example fitted from recordings by `hrc-fit`), the filter
  and the simulated cell use it as it is, and epsilon applies to the Table 5 form only. It is
  the one optional key: a file written before it existed stays valid.

- `stream` (optional, MODEL.md 8): arrival_idle, arrival_complete, q; with `queue` (L, 1..4,
  MODEL.md 8.1) instead arrival_idle, arrival_busy, waiting_cost, q (arrival_complete refused).

The configuration hash (`Config.policy_hash`) is the SHA-256 of the canonical JSON of the
sections that determine the policy (`model`, `cost`, `solver`, and `stream` when present, so
the hash of a configuration without a stream is what it always was). Observation settings do not
change the policy, so editing them does not invalidate a solved policy file.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .paths import parse_yaml, read_text
from .quoting import QUOTE_LIMIT, cap, quote

EMOTION_GROUPS = ('base', 'motivate', 'request')
ALPHAS = tuple(f'alpha{i}' for i in range(1, 14))
BETAS = tuple(f'beta{i}' for i in range(1, 7))
BELIEF_MODES = ('table', 'bayes', 'posterior')

# The schema: section -> key -> kind. Kinds are checked by _check_* below.
_SCHEMA: dict[str, dict[str, str]] = {
    'model': {'rho': 'int>=1', 'sigma': 'int>=1', 'p_accept': 'prob[3]',
              'p_delta': 'rows[3x3]', 'emotion': 'chains', 'robot_paused_by': 'paused',
              'retreat_reach': 'reach|null', 'approach_reach': 'approach|null',
              'robot_rate': 'rate|null'},
    'cost': {'k1': 'weight', 'k2': 'weight', **{k: 'weight' for k in ALPHAS + BETAS}},
    'solver': {'gamma': 'open01', 'eta': 'positive', 'sweeps': 'sweeps',
               'fail_safe_aware': 'bool'},
    'observation': {'table': 'rows[3x9]', 'epsilon': 'prob', 'mode': 'belief_mode',
                    'likelihood': 'columns[3x9]|null', 'prior': 'prior[9]|null'},
    'stream': {'arrival_idle': 'prob', 'arrival_complete': 'prob', 'q': 'tasks|null',
               'queue': 'queue', 'arrival_busy': 'prob', 'waiting_cost': 'weight'},
}
# stream keys of the two forms (MODEL.md 8 and 8.1): without `queue`, arrival_complete; with it,
# arrival_busy and waiting_cost (arrival_complete belongs to the queue-less form)
STREAM_PLAIN_KEYS = ('arrival_complete',)
STREAM_QUEUE_KEYS = ('arrival_busy', 'waiting_cost')
MAX_QUEUE = 4
# Keys that may be left out (they then read as null).
_OPTIONAL = {('observation', 'likelihood'), ('observation', 'prior'), ('stream', 'q'),
             ('model', 'robot_paused_by'), ('model', 'retreat_reach'), ('stream', 'queue'),
             ('model', 'approach_reach'), ('model', 'robot_rate'),
             # required by one form of the stream, refused by the other (`_check_stream_form`)
             *(('stream', k) for k in STREAM_PLAIN_KEYS + STREAM_QUEUE_KEYS)}
# model.robot_paused_by: dn always pauses the robot (it stops); dp and dm may (MODEL.md 3.2)
PAUSED_ALWAYS = ('dn',)
PAUSED_MAY = ('dp', 'dm')
# the optional model keys of the cell with an arm (docs/ROBOT.md 4); belief_hash keeps only
# retreat_reach and approach_reach (the posterior filter's distance move), and only when set
CELL_KEYS = ('robot_paused_by', 'retreat_reach', 'approach_reach', 'robot_rate')
# model.robot_rate: the natures whose task the robot has a share of (its program's station)
RATE_NATURES = (0, 2, 3)
# Sections that may be left out (then absent from the validated data).
_OPTIONAL_SECTIONS = {'stream'}

PROBABILITY_TOLERANCE = 1e-9
MAX_SWEEPS = 100_000   # value iteration's bound: a fixed count, or the cap of a run to eta
# YAML values a configuration file may hold (the schema has about 150): a node parses a live
# `config` in its parameter callback, and 5,000 values parse in well under a second, where the
# 64 KiB the file may have (paths.FILE_LIMITS) could hold 30,000
MAX_VALUES = 5_000


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the field."""


@dataclass(frozen=True)
class Config:
    """A validated configuration. `data` is the plain nested dict (YAML-shaped)."""

    data: dict
    source: str = '<memory>'

    # -- sections as numpy ---------------------------------------------------------------
    @property
    def rho(self) -> int:
        return int(self.data['model']['rho'])

    @property
    def sigma(self) -> int:
        return int(self.data['model']['sigma'])

    @property
    def p_accept(self) -> np.ndarray:
        return np.asarray(self.data['model']['p_accept'], dtype=float)

    @property
    def p_delta(self) -> np.ndarray:
        """Shape (3, 3): row ea, columns Delta = -1, 0, +1."""
        return np.asarray(self.data['model']['p_delta'], dtype=float)

    def emotion_chain(self, group: str, variable: str) -> np.ndarray:
        """(down, stay, up) of `variable` ('em' or 'ea') under action group `group`."""
        return np.asarray(self.data['model']['emotion'][group][variable], dtype=float)

    @property
    def robot_paused_by(self) -> tuple[str, ...]:
        """The actions under which the robot's counter bc is paused (MODEL.md 3.2), in the
        order dn, dp, dm; ('dn',) unless the configuration says more."""
        given = self.data['model'].get('robot_paused_by') or PAUSED_ALWAYS
        return tuple(a for a in PAUSED_ALWAYS + PAUSED_MAY if a in given)

    @property
    def retreat_reach(self) -> int | None:
        """The band below which dp gains one band (MODEL.md 3.3); None: every band."""
        value = self.data['model'].get('retreat_reach')
        return None if value is None else int(value)

    @property
    def approach_reach(self) -> int | None:
        """The band above which dm gains one band, without the paper's floor at band 1
        (MODEL.md 3.3); None: the paper's rule d' = max(1, d - 1 - Delta)."""
        value = self.data['model'].get('approach_reach')
        return None if value is None else int(value)

    @property
    def robot_rate(self) -> np.ndarray | None:
        """(4, 4): P(the robot's counter runs down in an epoch it works | the task's nature tx
        (row), the band d at the epoch's start (column)) (MODEL.md 3.2); a nature the
        configuration leaves out (and tx 1, no robot share) runs at 1. None: the paper's rule
        (1 everywhere, deterministic)."""
        value = self.data['model'].get('robot_rate')
        if value is None:
            return None
        out = np.ones((4, 4))
        for tx, row in value.items():
            out[int(tx)] = row
        return out

    @property
    def cost(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.data['cost'].items()}

    @property
    def gamma(self) -> float:
        return float(self.data['solver']['gamma'])

    @property
    def eta(self) -> float:
        return float(self.data['solver']['eta'])

    @property
    def sweeps(self) -> int | None:
        s = self.data['solver']['sweeps']
        return None if s is None else int(s)

    @property
    def fail_safe_aware(self) -> bool:
        """Plan with only dn available at d = 0, as the decision node's fail-safe enforces."""
        return bool(self.data['solver']['fail_safe_aware'])

    @property
    def observation_table(self) -> np.ndarray:
        """Shape (3, 9): Table 5, row O-1, column h = 3*em + ea."""
        return np.asarray(self.data['observation']['table'], dtype=float)

    @property
    def observation_likelihood(self) -> np.ndarray | None:
        """P(O | h), shape (3, 9) (row O-1, column h), if the configuration gives one; else None
        (the bayes filter then derives it from Table 5 and epsilon)."""
        value = self.data['observation'].get('likelihood')
        return None if value is None else np.asarray(value, dtype=float)

    @property
    def observation_prior(self) -> np.ndarray | None:
        """The person's emotions h when the belief filter starts, shape (9,), if the
        configuration gives them; else None (uniform, MODEL.md 6)."""
        value = self.data['observation'].get('prior')
        return None if value is None else np.asarray(value, dtype=float)

    @property
    def epsilon(self) -> float:
        return float(self.data['observation']['epsilon'])

    @property
    def belief_mode(self) -> str:
        return str(self.data['observation']['mode'])

    @property
    def has_stream(self) -> bool:
        """Whether the configuration describes a task stream (MODEL.md 8)."""
        return 'stream' in self.data

    @property
    def queue(self) -> int | None:
        """L, the most tasks that wait in the stream's queue (MODEL.md 8.1); None without a
        queue (no stream, or the queue-less stream of MODEL.md 8)."""
        body = self.data.get('stream')
        return None if body is None or 'queue' not in body else int(body['queue'])

    @property
    def waiting_cost(self) -> float:
        """w, the cost per waiting task per epoch (MODEL.md 8.1); 0 without a queue."""
        return float(self.data['stream']['waiting_cost']) if self.queue else 0.0

    @property
    def stream(self) -> tuple[float, float, np.ndarray, np.ndarray] | None:
        """(arrival_idle, arrival_complete, tasks (K, 3) int (tp, tc, tx), q (K,)) of the
        stream section, None without one. q null: every task of the model equally likely.
        With a queue (MODEL.md 8.1) the second number is arrival_busy (P(a task is released
        in an epoch that started with a task))."""
        body = self.data.get('stream')
        if body is None:
            return None
        rows = body.get('q')
        if rows is None:
            tasks = np.array([(tp, tc, tx) for tp in range(1, self.rho + 1)
                              for tc in range(1, self.sigma + 1) for tx in range(4)])
            q = np.full(len(tasks), 1.0 / len(tasks))
        else:
            tasks = np.array([row[:3] for row in rows], dtype=np.int64)
            q = np.array([row[3] for row in rows], dtype=float)
        second = body['arrival_busy'] if 'queue' in body else body['arrival_complete']
        return float(body['arrival_idle']), float(second), tasks, q

    # -- identity ------------------------------------------------------------------------
    @property
    def policy_sections(self) -> dict:
        sections = {k: self.data[k] for k in ('model', 'cost', 'solver')}
        sections['model'] = self._model_identity(with_paused=True)
        if self.has_stream:   # q left out reads as null: one model, one hash
            sections['stream'] = {'q': None, **self.data['stream']}
        return sections

    @property
    def policy_hash(self) -> str:
        """SHA-256 of the sections that determine the policy (model, cost, solver; stream
        when the configuration has one)."""
        return config_hash(self.policy_sections)

    @property
    def belief_hash(self) -> str:
        """SHA-256 of the sections the belief filter reads (model: its emotion chains;
        observation), so two nodes can tell whether they track the human with one model."""
        observation = dict(self.data['observation'])
        observation.setdefault('likelihood', None)
        if observation.get('prior') is None:   # left out or null: uniform, one hash
            observation.pop('prior', None)
        # what pauses the robot's counter, and how fast it runs, is not the filter's (one hash
        # with and without them: the run is no evidence about the person);
        # what a retreat gains is: the posterior mode reads the distance move after dp
        # (HRCModel.transition_likelihood)
        return config_hash({'model': self._model_identity(with_paused=False),
                            'observation': observation})

    def _model_identity(self, with_paused: bool) -> dict:
        """The model section as the hashes read it: the cell keys (CELL_KEYS) only where they
        differ from the paper's model (robot_paused_by left out or [dn], retreat_reach left out
        or null: one model, one hash), robot_paused_by and robot_rate only `with_paused`."""
        model = {k: v for k, v in self.data['model'].items() if k not in CELL_KEYS}
        if with_paused and self.robot_paused_by != PAUSED_ALWAYS:
            model['robot_paused_by'] = list(self.robot_paused_by)
        if with_paused and self.robot_rate is not None:   # the counter's rule, as the pauses
            model['robot_rate'] = {str(k): list(v) for k, v in
                                   sorted(self.data['model']['robot_rate'].items())}
        if self.retreat_reach is not None:
            model['retreat_reach'] = self.retreat_reach
        if self.approach_reach is not None:
            model['approach_reach'] = self.approach_reach
        return model

    def with_overrides(self, overrides: Mapping[str, Any]) -> 'Config':
        data = copy.deepcopy(self.data)
        _merge(data, overrides, '')
        return Config(validate(data), source=f'{self.source} (with overrides)')


def config_hash(sections: Mapping[str, Any]) -> str:
    canonical = json.dumps(_canonical(sections), sort_keys=True, separators=(',', ':'))
    return hashlib.sha256(canonical.encode('utf-8')).hexdigest()


def _canonical(value: Any) -> Any:
    """Numbers as floats (so 1 and 1.0 hash alike), except the integer sizes."""
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    return value


def _merge(base: dict, overrides: Mapping[str, Any], prefix: str) -> None:
    for key, value in overrides.items():
        name = f'{prefix}{key}'
        if key not in base and tuple(name.split('.')) not in _OPTIONAL \
                and name not in _OPTIONAL_SECTIONS:
            raise ConfigError(f'unknown configuration key {quote(name)}')
        if key not in base:
            base[key] = None
        if isinstance(value, Mapping) and isinstance(base[key], dict):
            _merge(base[key], value, name + '.')
        else:
            base[key] = copy.deepcopy(value)


def load_config(path: str | Path, overrides: Mapping[str, Any] | None = None) -> Config:
    """Load and validate a configuration YAML file (complete; see module docstring)."""
    path = Path(path)
    data = parse_yaml(read_text(path, ConfigError, 'YAML configuration', kind='config'),
                      ConfigError, str(path), max_nodes=MAX_VALUES)
    if overrides:
        if not isinstance(data, dict):
            raise ConfigError(f'{path}: the top level must be a mapping of sections')
        _merge(data, overrides, '')
    try:
        return Config(validate(data), source=str(path))
    except ConfigError as exc:
        raise ConfigError(f'{path}: {exc}') from None


def validate(data: Any) -> dict:
    """Check a YAML-shaped configuration; return it with plain Python numbers."""
    if not isinstance(data, dict):
        raise ConfigError('the top level must be a mapping with sections '
                          + ', '.join(_SCHEMA))
    for section in data:
        if section not in _SCHEMA:
            raise ConfigError(f'unknown section {quote(section)} (known: '
                              f'{", ".join(_SCHEMA)})')
    out: dict = {}
    for section, keys in _SCHEMA.items():
        body = data.get(section)
        if body is None and section in _OPTIONAL_SECTIONS:
            continue
        if body is None:
            raise ConfigError(f'missing section {section!r}')
        if not isinstance(body, dict):
            raise ConfigError(f'section {section!r} must be a mapping of keys, got '
                              f'{quote(body)}')
        for key in body:
            if key not in keys:
                raise ConfigError(f'unknown key {section}.{cap(key, QUOTE_LIMIT)}')
        out[section] = {}
        for key, kind in keys.items():
            name = f'{section}.{key}'
            if key not in body:
                if (section, key) in _OPTIONAL:
                    continue
                raise ConfigError(f'missing key {name}')
            if section == 'stream' and key in STREAM_PLAIN_KEYS + STREAM_QUEUE_KEYS:
                _check_stream_form(body, key)
            out[section][key] = _check(name, kind, body[key])
        if section == 'stream':
            for key in STREAM_PLAIN_KEYS + STREAM_QUEUE_KEYS:
                if key not in body:
                    _check_stream_form(body, key, missing=True)
    if 'stream' in out:
        _check_stream_tasks(out['stream'].get('q'), out['model']['rho'], out['model']['sigma'])
    return out


def _check_stream_form(body: dict, key: str, missing: bool = False) -> None:
    """A stream with `queue` (MODEL.md 8.1) takes arrival_busy and waiting_cost, one without
    it (MODEL.md 8) arrival_complete: a key of the other form is refused, one of its own form
    that is missing is named."""
    queued = 'queue' in body
    own = key in (STREAM_QUEUE_KEYS if queued else STREAM_PLAIN_KEYS)
    if missing and own:
        raise ConfigError(f'missing key stream.{key}'
                          + (' (a stream with a queue needs it, MODEL.md 8.1)' if queued else ''))
    if not missing and not own:
        if queued:
            raise ConfigError(f'stream.{key} belongs to the stream without a queue (MODEL.md 8); '
                              'with stream.queue give arrival_busy (P(a task is released in an '
                              'epoch that started with a task)) instead')
        raise ConfigError(f'stream.{key} needs stream.queue (the queue of waiting tasks, '
                          'MODEL.md 8.1); without a queue the stream takes arrival_complete')


def _check_stream_tasks(rows, rho: int, sigma: int) -> None:
    """The stream's tasks must be tasks of the model: tp 1..rho, tc 1..sigma, tx 0..3."""
    for i, (tp, tc, tx, _) in enumerate(rows or ()):
        if not (1 <= tp <= rho and 1 <= tc <= sigma and 0 <= tx <= 3):
            raise ConfigError(f'stream.q[{i}] = {quote([tp, tc, tx])} is not a task of the '
                              f'model (tp 1..{rho}, tc 1..{sigma}, tx 0..3)')


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f'{name} must be a number, got {quote(value)}')
    if not math.isfinite(value):
        raise ConfigError(f'{name} must be finite, got {quote(value)}')
    return float(value)


def _prob_vector(name: str, value: Any, length: int) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != length:
        raise ConfigError(f'{name} must be a list of {length} probabilities, got '
                          f'{quote(value)}')
    row = [_number(f'{name}[{i}]', v) for i, v in enumerate(value)]
    for i, p in enumerate(row):
        if not 0.0 <= p <= 1.0:
            raise ConfigError(f'{name}[{i}] = {p} is not a probability in [0, 1]')
    return row


def _prob_rows(name: str, value: Any, rows: int, cols: int) -> list[list[float]]:
    if not isinstance(value, (list, tuple)) or len(value) != rows:
        raise ConfigError(f'{name} must be {rows} rows of {cols} probabilities')
    out = []
    for r, row in enumerate(value):
        checked = _prob_vector(f'{name}[{r}]', row, cols)
        total = sum(checked)
        if abs(total - 1.0) > PROBABILITY_TOLERANCE:
            raise ConfigError(f'{name}[{r}] sums to {total:.12g}, not 1')
        out.append(checked)
    return out


def _band_or_null(name: str, value: Any, bands: tuple, what: str) -> int | None:
    """A band among `bands`, or None; ConfigError '<name> must be <what>, got ...'."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value not in bands:
        raise ConfigError(f'{name} must be {what}, got {quote(value)}')
    return int(value)


def _check(name: str, kind: str, value: Any) -> Any:
    if kind == 'int>=1':
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f'{name} must be an integer >= 1, got {quote(value)}')
        return int(value)
    if kind == 'sweeps':
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_SWEEPS:
            raise ConfigError(f'{name} must be null (run to eta) or an integer in '
                              f'1..{MAX_SWEEPS}, got {quote(value)}')
        return int(value)
    if kind == 'bool':
        if not isinstance(value, bool):
            raise ConfigError(f'{name} must be true or false, got {quote(value)}')
        return value
    if kind == 'weight':
        v = _number(name, value)
        if v < 0:
            raise ConfigError(f'{name} is a cost weight and must be >= 0, got {v}')
        return v
    if kind == 'positive':
        v = _number(name, value)
        if v <= 0:
            raise ConfigError(f'{name} must be > 0, got {v}')
        return v
    if kind == 'open01':
        v = _number(name, value)
        if not 0.0 < v < 1.0:
            raise ConfigError(f'{name} must lie in the open interval (0, 1), got {v}')
        return v
    if kind == 'prob':
        v = _number(name, value)
        if not 0.0 <= v <= 1.0:
            raise ConfigError(f'{name} must be a probability in [0, 1], got {v}')
        return v
    if kind == 'prob[3]':
        return _prob_vector(name, value, 3)
    if kind == 'rows[3x3]':
        return _prob_rows(name, value, 3, 3)
    if kind == 'rows[3x9]':
        rows = _prob_rows(name, value, 3, 9)
        column_mass = np.asarray(rows).sum(axis=0)
        if np.any(column_mass <= 0):
            h = int(np.argmin(column_mass))
            raise ConfigError(f'{name}: hidden state h={h} has zero probability under every '
                              'observation, so the bayes likelihood is undefined')
        return rows
    if kind == 'columns[3x9]|null':
        if value is None:
            return None
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise ConfigError(f'{name} must be 3 rows (O = 1, 2, 3) of 9 probabilities '
                              '(h = 0..8), or null')
        rows = [_prob_vector(f'{name}[{r}]', row, 9) for r, row in enumerate(value)]
        column_mass = np.asarray(rows).sum(axis=0)
        for h, total in enumerate(column_mass):
            if abs(total - 1.0) > PROBABILITY_TOLERANCE:
                raise ConfigError(f'{name}: column h={h} (P(O | h) over O = 1, 2, 3) sums to '
                                  f'{total:.12g}, not 1')
        for r, row in enumerate(rows):
            if not any(row):
                raise ConfigError(f'{name}: observation O={r + 1} has probability 0 under every '
                                  'hidden state, so the filter could not take it')
        return rows
    if kind == 'prior[9]|null':
        if value is None:
            return None
        row = _prob_vector(name, value, 9)
        total = sum(row)
        if abs(total - 1.0) > PROBABILITY_TOLERANCE:
            raise ConfigError(f'{name} (P(h) over h = 3*em + ea) sums to {total:.12g}, not 1')
        return row
    if kind == 'queue':
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_QUEUE:
            raise ConfigError(f'{name} (the most tasks that wait) must be an integer in '
                              f'1..{MAX_QUEUE}, got {quote(value)}')
        return int(value)
    if kind == 'tasks|null':
        if value is None:
            return None
        if not isinstance(value, (list, tuple)) or not value:
            raise ConfigError(f'{name} must be null or a non-empty list of [tp, tc, tx, '
                              f'probability] rows, got {quote(value)}')
        rows, seen = [], set()
        for i, row in enumerate(value):
            if not isinstance(row, (list, tuple)) or len(row) != 4 or any(
                    isinstance(v, bool) or not isinstance(v, int) for v in row[:3]):
                raise ConfigError(f'{name}[{i}] must be [tp, tc, tx, probability] with integer '
                                  f'tp, tc, tx, got {quote(row)}')
            if tuple(row[:3]) in seen:
                raise ConfigError(f'{name}[{i}]: task {list(row[:3])} is listed twice')
            seen.add(tuple(row[:3]))
            rows.append([int(v) for v in row[:3]] + [_check(f'{name}[{i}][3]', 'prob', row[3])])
        total = sum(r[3] for r in rows)
        if abs(total - 1.0) > PROBABILITY_TOLERANCE:
            raise ConfigError(f'{name}: the probabilities sum to {total:.12g}, not 1')
        return rows
    if kind == 'chains':
        if not isinstance(value, dict):
            raise ConfigError(f'{name} must map the groups {", ".join(EMOTION_GROUPS)}')
        for group in value:
            if group not in EMOTION_GROUPS:
                raise ConfigError(f'unknown key {name}.{cap(group, QUOTE_LIMIT)}')
        out = {}
        for group in EMOTION_GROUPS:
            body = value.get(group)
            if not isinstance(body, dict):
                raise ConfigError(f'missing key {name}.{group}')
            for var in body:
                if var not in ('em', 'ea'):
                    raise ConfigError(f'unknown key {name}.{group}.{cap(var, QUOTE_LIMIT)}')
            out[group] = {}
            for var in ('em', 'ea'):
                if var not in body:
                    raise ConfigError(f'missing key {name}.{group}.{var}')
                out[group][var] = _prob_rows(f'{name}.{group}.{var}', [body[var]], 1, 3)[0]
        return out
    if kind == 'reach|null':
        return _band_or_null(name, value, (1, 2), 'null (a retreat gains a band from every '
                             'band) or 1 or 2 (the band it cannot retreat beyond)')
    if kind == 'approach|null':
        return _band_or_null(name, value, (1, 2, 3), "null (the paper's rule: dm gains a band, "
                             'never below band 1) or 1, 2 or 3 (the band above which dm gains '
                             'one; 3: none)')
    if kind == 'rate|null':
        if value is None:
            return None
        if not isinstance(value, dict) or not value:
            raise ConfigError(f'{name} must be null or map task natures with a robot share '
                              f'({", ".join(map(str, RATE_NATURES))}) to 4 probabilities (d = '
                              f'0..3), got {quote(value)}')
        out = {}
        for tx, row in value.items():
            if isinstance(tx, str) and tx.isdigit() and len(tx) == 1:
                tx = int(tx)        # as JSON writes the keys (a policy's meta)
            if isinstance(tx, bool) or not isinstance(tx, int) or tx not in RATE_NATURES:
                natures = ', '.join(map(str, RATE_NATURES))
                raise ConfigError(f'{name}: {quote(tx)} is no task nature with a robot share '
                                  f'(the robot works on natures {natures})')
            out[tx] = _prob_vector(f'{name}[{tx}]', row, 4)
        return out
    if kind == 'paused':
        if value is None:      # as left out: [dn], the paper's model (as retreat_reach: null)
            return None
        allowed = PAUSED_ALWAYS + PAUSED_MAY
        if not isinstance(value, (list, tuple)) or not all(isinstance(a, str) for a in value):
            raise ConfigError(f'{name} must be a list of action names from '
                              f'{", ".join(allowed)}, got {quote(value)}')
        for a in value:
            if a not in allowed:
                raise ConfigError(f'{name}: {quote(a)} cannot pause the robot\'s counter '
                                  f'(only {", ".join(allowed)})')
        if len(set(value)) != len(value):
            raise ConfigError(f'{name} lists an action twice: {quote(value)}')
        if 'dn' not in value:
            raise ConfigError(f'{name} must hold dn (the robot stops under dn), got '
                              f'{quote(value)}')
        return [a for a in allowed if a in value]
    if kind == 'belief_mode':
        if value not in BELIEF_MODES:
            raise ConfigError(f'{name} must be one of {", ".join(BELIEF_MODES)}, '
                              f'got {quote(value)}')
        return value
    raise AssertionError(f'unknown schema kind {kind}')
