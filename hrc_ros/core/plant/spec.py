"""The plant file: which cells a plant has and how each one is learned (docs/FLEET.md).

    plant: example                 # a name for the report
    defaults:                      # optional: any cell setting below, for every cell
      drift: {window: 1000}
    cells:
      - name: line1                # letters, digits, '_' and '-'; unique; the output folder
        namespace: /line1          # the cell's ROS namespace (default: /<name>)
        recordings: bags/line1     # a bag folder, .mcap or .csv file, or a folder of them,
                                   # or a list of those; relative to the plant file
        base: default              # the configuration the cell runs now: a shipped name or
                                   # a path (the fit's start, the drift test's null model,
                                   # the running side of the shadow check)
        policy: null               # the policy it runs now (default: the shipped one solved
                                   # for base, else solved by the plant)
        pomdp_policy: null         # the POMDP policy it runs now, for the pomdp and fib
                                   # selectors (default: the shipped one solved for base)
        solver: mdp                # mdp, pomdp or both: which policies are solved
        selector: paper            # the cell's selector (pomdp, fib need solver pomdp/both)
        run: on_drift              # on_drift: fit, solve and check only when drift is found;
                                   # always: every run
        drift: {window: 1000, alpha: 0.05, simulations: 199}
        fit: {bootstrap: 50, starts: 2, tol: 1.0e-7, max_iter: 1000, hold: [], window: null,
              prior: false, stream: false}
        evaluate: {episodes: 1000, epochs: 50, task_rate: 0.2, refits: 10}   # the check
        promote: {guards: []}      # further guards (refused_requests, tasks_completed,
                                   # collision_stuck), none by default; collision epochs
                                   # are always guarded
        pomdp: {episodes: 2000, rounds: 1}
        max_memory_mb: null        # a solve whose memory estimate is above this fails
        retries: 3                 # Ray's retries of a task whose worker died
        seed: 0

`fit` is hrc-fit's: `prior: true` also fits the person prior (hrc-fit --prior, written as
observation.prior), `stream: true` also fits the task stream from the recordings (hrc-fit
--stream, written as the `stream` section; with a base that has stream.queue, recordings
without the tasks waiting fail the cell when they are read); both in the promotion check's
refits too, so that every fit of the cell fits the same model.

A generated cell has `generate:` instead of `recordings:`: the batch simulator records
`episodes` x `epochs` of the running policy in a world whose people differ from the base
(`world`: overrides of the base configuration, or a configuration path), with `explore` of
uniformly drawn actions, from `seed`; the people (em, ea at each episode's start) are drawn
from the world's person prior (`observation.prior`) when it has one, uniform otherwise; the
recordings go to the output folder's cache, named by a hash of the settings and of the base,
world and policy files' contents.

The file is read with the project's safe YAML loader (`paths.read_yaml`: a regular file of at
most 1 MiB, nesting and expansion bounded, one line for any loader error); a schema
error is one line naming the cell and the key (`PlantError`) and refuses the whole plant
before any work. What a cell's files hold (a base configuration that does not load, a missing
recording) is that cell's failure, reported with the others' results.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path


from ..names import BadName
from ..names import namespace as ros_namespace
from ..paths import read_yaml, shipped_config_path

MAX_CELLS = 10_000
# The version of what `stages.generate` records for the same settings (part of the cache's
# key): 2 draws the people from the world's person prior (observation.prior) when it has one.
GENERATOR = 2
REFITS = 10    # the promotion check's refits per cell (docs/FLEET.md: chosen by coverage)
SOLVERS = ('mdp', 'pomdp', 'both')
RUNS = ('on_drift', 'always')
MDP_SELECTORS = ('paper', 'qmdp', 'mls')
POMDP_SELECTORS = ('pomdp', 'fib')
NAME = re.compile(r'^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$')

# section -> key -> (kind, default); kinds are checked by _value below
SECTIONS = {
    'drift': {'window': ('int:20:10000000', 1000), 'alpha': ('prob_open', 0.05),
              'simulations': ('int:9:100000', 199), 'tol': ('float:1e-12:1', 1e-6),
              'max_iter': ('int:1:100000', 200)},
    'fit': {'bootstrap': ('int:0:10000', 50), 'starts': ('int:1:100', 2),
            'tol': ('float:1e-15:1', 1e-7), 'max_iter': ('int:1:100000', 1000),
            'hold': ('families', ()), 'window': ('int_or_null:20:1000000000', None),
            'prior': ('bool', False), 'stream': ('bool', False)},
    'evaluate': {'episodes': ('int:10:1000000', 1000), 'epochs': ('int:1:100000', 50),
                 'task_rate': ('prob', 0.2), 'refits': ('int:2:1000', REFITS)},
    'promote': {'guards': ('guards', ())},
    'pomdp': {'episodes': ('int:1:100000', 2000), 'rounds': ('int:0:20', 1)},
    'generate': {'world': ('world', None), 'episodes': ('int:1:1000000', 40),
                 'epochs': ('int:1:100000', 50), 'explore': ('prob', 0.2),
                 'seed': ('int:0:2147483647', 0)},
}
SCALARS = {'base': ('text', 'default'), 'policy': ('text_or_null', None),
           'pomdp_policy': ('text_or_null', None),
           'solver': (SOLVERS, 'mdp'), 'selector': ('selector', None), 'run': (RUNS, 'on_drift'),
           'max_memory_mb': ('int_or_null:1:100000000', None), 'retries': ('int:0:100', 3),
           'seed': ('int:0:2147483647', 0)}
CELL_ONLY = ('name', 'namespace', 'recordings', 'generate')
CHUNK = 10     # bootstrap resamples and drift simulations per task
# keys a plant file may no longer have, and what to do instead
RETIRED = {'evaluate.worlds': 'the held-out check and its bootstrap worlds are gone: the '
                              'interval carries the fitting error through refits '
                              '(evaluate.refits; docs/FLEET.md); remove evaluate.worlds'}


class PlantError(ValueError):
    """The plant file cannot be used; the one-line message names the cell and the key."""


@dataclass(frozen=True)
class CellSpec:
    """One cell as the plant file gives it, defaults applied and paths resolved."""

    name: str
    namespace: str
    recordings: tuple          # resolved paths (empty for a generated cell)
    generate: dict | None      # the generate section, with `world` as given
    base: str                  # resolved configuration path
    policy: str | None
    pomdp_policy: str | None
    solver: str
    selector: str
    run: str
    drift: dict
    fit: dict
    evaluate: dict
    pomdp: dict
    promote: dict
    max_memory_mb: int | None
    retries: int
    seed: int
    index: int = 0

    @property
    def solves_pomdp(self) -> bool:
        return self.solver in ('pomdp', 'both')

    def generate_key(self) -> str:
        """A hash of what the generated recordings depend on (the cache's name): the
        generator's version, the `generate` settings, and the base, world and policy files by
        their contents (the policy: the cell's, or with `policy: null` the shipped one its
        base runs), so that an edited file or a changed generator is not served from an old
        cache."""
        world = (self.generate or {}).get('world')
        files = {name: _file_digest(path) for name, path in
                 (('base', self.base), ('policy', self.policy or _shipped_policy(self.base)),
                  ('world', world if isinstance(world, str) else None))}
        blob = json.dumps({'generator': GENERATOR, 'generate': self.generate, 'base': self.base,
                           'policy': self.policy, 'files': files},
                          sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _shipped_policy(base: str) -> str | None:
    """The policy a cell with `policy: null` runs (the shipped one for its base, by the base's
    hash), None when the base does not load (the cell's stages report that)."""
    from ..config import ConfigError, load_config
    from ..mdp.policy import default_policy_path
    try:
        return str(default_policy_path(load_config(base)))
    except (ConfigError, OSError, ValueError):
        return None


def _file_digest(path: str | None) -> str | None:
    """The sha256 of a regular file's bytes, read in chunks; None for no path, or a path that
    is not a regular file or cannot be read (the stage that loads it reports that; a FIFO or a
    device is never opened here)."""
    if path is None or not Path(path).is_file():
        return None
    digest = hashlib.sha256()
    try:
        with open(path, 'rb') as f:
            for chunk in iter(lambda: f.read(1 << 20), b''):
                digest.update(chunk)
    except OSError:
        return None
    return digest.hexdigest()


@dataclass(frozen=True)
class Plant:
    name: str
    source: str
    cells: tuple = field(default_factory=tuple)


def _where(index: int | None, name: str | None) -> str:
    if index is None:
        return 'defaults'
    return f'cells[{index}]' + (f' ({name})' if name else '')


def _value(where: str, key: str, kind, value):
    """`value` checked against `kind`; PlantError naming `where` and `key` otherwise."""
    def bad(expected: str):
        return PlantError(f'{where}: {key} must be {expected}, got {value!r}')
    if isinstance(kind, tuple):
        if value not in kind:
            raise bad(' or '.join(kind))
        return value
    if kind == 'bool':
        if not isinstance(value, bool):
            raise bad('true or false')
        return value
    if kind == 'text':
        if not isinstance(value, str) or not value.strip():
            raise bad('a non-empty text')
        return value
    if kind == 'text_or_null':
        return None if value is None else _value(where, key, 'text', value)
    if kind == 'selector':
        if value not in MDP_SELECTORS + POMDP_SELECTORS:
            raise bad(' or '.join(MDP_SELECTORS + POMDP_SELECTORS))
        return value
    if kind.startswith('int_or_null:'):
        return None if value is None else _value(where, key, 'int:' + kind.split(':', 1)[1],
                                                 value)
    if kind.startswith('int:'):
        low, high = (int(float(v)) for v in kind.split(':')[1:])
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise bad(f'an integer in {low}..{high}')
        return value
    if kind.startswith('float:'):
        low, high = (float(v) for v in kind.split(':')[1:])
        if (isinstance(value, bool) or not isinstance(value, (int, float))
                or not math.isfinite(value) or not low <= value <= high):
            raise bad(f'a number in [{low:g}, {high:g}]')
        return float(value)
    if kind in ('prob', 'prob_open'):
        ok = (not isinstance(value, bool) and isinstance(value, (int, float))
              and (0 <= value <= 1 if kind == 'prob' else 0 < value < 1))
        if not ok:
            raise bad('a probability in [0, 1]' if kind == 'prob' else 'a number in (0, 1)')
        return float(value)
    if kind == 'guards':        # promote.guards: further guards, none by default
        from .check import GUARDS
        if isinstance(value, str):
            value = [v for v in value.split(',') if v.strip()]
        if not isinstance(value, (list, tuple)) or not all(v in GUARDS for v in value):
            raise bad(f'a list of guards among {", ".join(GUARDS)}')
        return tuple(dict.fromkeys(value))
    if kind == 'families':
        from ..learning.fit import FitError, expand_hold
        if isinstance(value, str):
            value = [v for v in value.split(',') if v.strip()]
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise bad('a list of parameter families')
        try:
            return expand_hold(value)
        except FitError as exc:
            raise PlantError(f'{where}: {key}: {exc}') from None
    if kind == 'world':
        if not isinstance(value, (dict, str)):
            raise bad('overrides of the base configuration (a mapping) or a configuration '
                      'path')
        return copy.deepcopy(value)
    raise AssertionError(kind)


def _settings(where: str, given: dict, into: dict, allowed=None) -> dict:
    """Cell settings of `given` merged over `into` (a copy), each checked."""
    out = copy.deepcopy(into)
    for key, value in given.items():
        if allowed is not None and key not in allowed:
            raise PlantError(f'{where}: unknown key {key!r} (known: {", ".join(allowed)})')
        if key in SECTIONS:
            if not isinstance(value, dict):
                raise PlantError(f'{where}: {key} must be a mapping of '
                                 f'{", ".join(SECTIONS[key])}')
            section = dict(out.get(key) or {})
            for sub, v in value.items():
                if f'{key}.{sub}' in RETIRED:
                    raise PlantError(f'{where}: {key}.{sub}: {RETIRED[f"{key}.{sub}"]}')
                if sub not in SECTIONS[key]:
                    raise PlantError(f'{where}: unknown key {key}.{sub!s} (known: '
                                     f'{", ".join(SECTIONS[key])})')
                section[sub] = _value(where, f'{key}.{sub}', SECTIONS[key][sub][0], v)
            out[key] = section
        elif key in SCALARS:
            out[key] = _value(where, key, SCALARS[key][0], value)
    return out


def _section(settings: dict, name: str) -> dict:
    values = {k: default for k, (_, default) in SECTIONS[name].items()}
    values.update(settings.get(name) or {})
    return values


def _resolve(folder: Path, text: str) -> str:
    path = Path(text).expanduser()
    return str(path if path.is_absolute() else (folder / path))


def _base_path(folder: Path, text: str) -> str:
    """A shipped configuration by name (`default`, `paper`), else a path."""
    if '/' not in text and not text.endswith(('.yaml', '.yml')):
        return str(shipped_config_path(text))
    return _resolve(folder, text)


def check_world(where: str, base: str, world: dict, loaded: dict) -> None:
    """PlantError when a generated cell's world (overrides written in the plant file) does not
    make a configuration of its base: a typo there is the plant file's, refused before any
    work (it failed the cell after the others had run). A base that does not load is left to
    the cell (its read stage fails it alone, as a broken file of its own). `loaded`: base ->
    its configuration (None: it does not load), so that a base many cells share (up to
    MAX_CELLS) is read once."""
    from ..config import ConfigError, load_config
    if base not in loaded:
        try:
            loaded[base] = load_config(base)
        except ConfigError:
            loaded[base] = None
    config = loaded[base]
    if config is None:
        return
    try:
        config.with_overrides(world)
    except ConfigError as exc:
        raise PlantError(f'{where}: generate.world: {exc}') from None


def load_plant(path: str | Path) -> Plant:
    """The plant file, checked (module docstring); PlantError with one line otherwise."""
    path = Path(path)
    data = read_yaml(path, PlantError, 'YAML plant')
    if not isinstance(data, dict):
        raise PlantError(f'{path}: the top level must be a mapping with plant, defaults, cells')
    unknown = set(data) - {'plant', 'defaults', 'cells'}
    if unknown:
        raise PlantError(f'{path}: unknown top-level key {sorted(map(str, unknown))[0]!r} '
                         '(known: plant, defaults, cells)')
    name = data.get('plant', path.stem)
    if not isinstance(name, str) or not name.strip():
        raise PlantError(f'{path}: plant must be a name, got {name!r}')
    defaults = data.get('defaults') or {}
    if not isinstance(defaults, dict):
        raise PlantError(f'{path}: defaults must be a mapping of cell settings')
    for key in defaults:
        if key in CELL_ONLY:
            raise PlantError(f'{path}: defaults: {key} is set per cell, not in defaults')
    shared = _settings(f'{path}: defaults', defaults, {},
                       allowed=tuple(SCALARS) + tuple(s for s in SECTIONS if s != 'generate'))
    cells = data.get('cells')
    if not isinstance(cells, list) or not cells:
        raise PlantError(f'{path}: cells must be a non-empty list of cells')
    if len(cells) > MAX_CELLS:
        raise PlantError(f'{path}: {len(cells)} cells; a plant file holds at most {MAX_CELLS}')
    folder = path.resolve().parent
    out, names, namespaces, bases = [], set(), {}, {}
    for i, cell in enumerate(cells):
        label = cell.get('name') if isinstance(cell, dict) else None
        where = f'{path}: {_where(i, label if isinstance(label, str) else None)}'
        if not isinstance(cell, dict):
            raise PlantError(f'{where}: a cell must be a mapping with name, recordings, ...')
        if not isinstance(label, str) or not NAME.match(label):
            raise PlantError(f'{where}: name must be letters, digits, _ or - (at most 64, '
                             f'starting with a letter or digit), got {label!r}')
        if label in names:
            raise PlantError(f'{where}: the name {label!r} is used by another cell')
        names.add(label)
        settings = _settings(where, cell, shared,
                             allowed=CELL_ONLY + tuple(SCALARS) + tuple(SECTIONS))
        try:
            namespace = ros_namespace(cell.get('namespace', f'/{label}'))
        except BadName as exc:
            raise PlantError(f'{where}: {exc}') from None
        if namespace in namespaces:
            raise PlantError(f'{where}: namespace {namespace} is also the namespace of cell '
                             f'{namespaces[namespace]}')
        namespaces[namespace] = label
        has_recordings, has_generate = 'recordings' in cell, 'generate' in cell
        if has_recordings == has_generate:
            raise PlantError(f'{where}: give either recordings (where its bags are) or '
                             'generate (recordings made by the batch simulator)')
        recordings: tuple = ()
        generate = None
        if has_recordings:
            given = cell['recordings']
            given = [given] if isinstance(given, str) else given
            if (not isinstance(given, list) or not given
                    or not all(isinstance(g, str) and g.strip() for g in given)):
                raise PlantError(f'{where}: recordings must be a path or a list of paths, got '
                                 f'{cell["recordings"]!r}')
            recordings = tuple(_resolve(folder, g) for g in given)
        else:
            generate = _section(settings, 'generate')
            if generate['world'] is None:
                raise PlantError(f'{where}: generate.world is needed: overrides of the base '
                                 'configuration, or a configuration path')
            if isinstance(generate['world'], str):
                generate['world'] = _base_path(folder, generate['world'])
        solver = settings.get('solver', SCALARS['solver'][1])
        selector = settings.get('selector') or ('pomdp' if solver == 'pomdp' else 'paper')
        if selector in POMDP_SELECTORS and solver == 'mdp':
            raise PlantError(f'{where}: selector {selector} plans with a POMDP policy: set '
                             'solver: pomdp or both')
        if selector in MDP_SELECTORS and solver == 'pomdp':
            raise PlantError(f'{where}: selector {selector} reads the MDP policy; with solver: '
                             'pomdp the cell runs pomdp or fib (or set solver: both)')
        policy, pomdp_policy = settings.get('policy'), settings.get('pomdp_policy')
        if pomdp_policy is not None and selector not in POMDP_SELECTORS:
            raise PlantError(f'{where}: pomdp_policy is the running POMDP policy of a cell '
                             f'whose selector is pomdp or fib; this one runs {selector}')
        base = _base_path(folder, settings.get('base', SCALARS['base'][1]))
        if generate is not None and isinstance(generate['world'], dict):
            check_world(where, base, generate['world'], bases)
        out.append(CellSpec(
            name=label, namespace=namespace, recordings=recordings, generate=generate,
            base=base,
            policy=None if policy is None else _resolve(folder, policy),
            pomdp_policy=None if pomdp_policy is None else _resolve(folder, pomdp_policy),
            solver=solver, selector=selector, run=settings.get('run', SCALARS['run'][1]),
            drift=_section(settings, 'drift'), fit=_section(settings, 'fit'),
            evaluate=_section(settings, 'evaluate'), pomdp=_section(settings, 'pomdp'),
            promote=_section(settings, 'promote'),
            max_memory_mb=settings.get('max_memory_mb'),
            retries=settings.get('retries', SCALARS['retries'][1]),
            seed=settings.get('seed', SCALARS['seed'][1]), index=i))
    return Plant(name.strip(), str(path), tuple(out))


RECORDING_SUFFIXES = ('.csv', '.mcap')


def recording_files(paths) -> list[Path]:
    """The recordings a cell's `recordings` name, oldest first: a bag folder (one holding
    metadata.yaml or .mcap files directly) is one recording; any other folder contributes
    its .csv files, .mcap files and bag folders, in name order (name them by date)."""
    out: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir() and not (path / 'metadata.yaml').is_file() and not any(
                path.glob('*.mcap')):
            for entry in sorted(path.iterdir()):
                if entry.suffix.lower() in RECORDING_SUFFIXES or (
                        entry.is_dir() and ((entry / 'metadata.yaml').is_file()
                                            or any(entry.glob('*.mcap')))):
                    out.append(entry)
        else:
            out.append(path)
    return out
