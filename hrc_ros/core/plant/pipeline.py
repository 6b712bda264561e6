"""A cell's pipeline as a state machine, and the promotion rule (docs/FLEET.md).

`CellPipeline` never runs anything: it is fed the facts of each finished stage (or its
failure) and answers with the stages that may run now, as `Job`s whose arguments are plain
values or `Ref`s to earlier stages' payloads (or to plant objects: the running
configurations and policies the driver loaded once). A scheduler runs them: `run_serially`
here, one after the other in this process (the benchmark's baseline), or `hrc_ros.tools.fleet`
as Ray tasks. So the order of stages, the fan-out of the drift simulations, bootstrap
resamples and refits, what a failure stops and the decision are unit tests, whatever runs them.

    [generate -> save]  ->  read  ->  drift_observed  ->  drift_null x K  ->  p
        run on_drift and p >= alpha: keep (no drift), nothing fitted
        otherwise: fit_point -> bootstrap x M -> fit_summary -> solve_mdp [-> solve_pomdp]
                   -> shadow (the in-sample figures) and refits x R (the fit's error)
                   -> decide (check.py) -> outputs -> write
    (run always: the fit starts beside the drift test instead of after it.)

The promotion rule (`check.decide`): promote when the new policy's discounted cost minus the
running one's, in-sample and corrected for the fit's optimism by R refits (the recorded
episodes resampled with replacement, each fitted and solved as the cell was), has a 95%
interval below zero (an interval that carries the fitting error as well as the episodes'
noise), unless its collision epochs are higher with 95% confidence (the safety guard) or a
guard the plant file sets (`promote.guards`, none by default) finds the new policy worse;
otherwise keep, with the figures (a cell of too few episodes for refits: keep, its interval
the episodes' alone). A failed stage fails the cell with its reason (decision `failed`); the
other cells go on.
"""

from __future__ import annotations

import json
import traceback
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from . import check, drift
from .check import KEEP, PROMOTE  # noqa: F401 - the decisions, named here too
from .spec import CHUNK, POMDP_SELECTORS, CellSpec
from .stages import MIN_EPISODES, SHADOW_METRICS, STAGES, CellError

FAILED = 'failed'
ANY, DRIVER_NODE, DRIVER = 'any', 'driver_node', 'driver'


@dataclass(frozen=True)
class Ref:
    """An earlier stage's payload (`key` of the same cell) or a plant object ('@...')."""

    key: str


@dataclass(frozen=True)
class Job:
    cell: str
    key: str            # names its payload for later jobs
    stage: str          # a name in STAGES or DRIVER_STAGES
    args: tuple
    where: str = ANY    # any node; the driver's node (the recordings are there); the driver
    retries: int = 3
    label: str = ''     # for the progress bar


REFIT_CHUNK = 1      # refits per task: each is a fit and a solve, seconds of work


def refit_draws(count: int) -> list[list[int]]:
    """The refits' draws 0..count - 1 in tasks of REFIT_CHUNK (their seeds come from the
    draw: the same whatever the scheduling)."""
    return [list(range(i, min(i + REFIT_CHUNK, count))) for i in range(0, count, REFIT_CHUNK)]


def seeds(seed: int, stream: int, count: int) -> list[list[list[int]]]:
    """Seeds of `count` draws in chunks of CHUNK: [seed, stream, b] (the same whatever the
    scheduling, so a plant run is reproducible)."""
    every = [[seed, stream, b] for b in range(count)]
    return [every[i:i + CHUNK] for i in range(0, count, CHUNK)]


@dataclass
class CellPipeline:
    """One cell's stages (module docstring). `folder`: where its files go (the driver writes
    them); `cache`: the generated recordings' file, `cached` when it is already there."""

    spec: CellSpec
    folder: str
    cache: str | None = None
    cached: bool = False
    error: str | None = None           # set before the start: the cell fails at once
    rho: int = 0
    sigma: int = 0
    entry: dict = field(default_factory=dict)
    stage: str = 'waiting'
    finished: bool = False
    _waiting: set = field(default_factory=set)
    _null: list = field(default_factory=list)
    _drift: dict | None = None
    _fitting: bool = False
    _summarised: bool = False
    _solves: set = field(default_factory=set)
    _started: bool = False                          # the shadow check
    _shadow: dict | None = None                     # its in-sample facts
    _refits: list = field(default_factory=list)     # the refits' rows

    def __post_init__(self):
        s = self.spec
        self.entry = {'cell': s.name, 'namespace': s.namespace, 'decision': None,
                      'reason': None, 'drift_p': None, 'drift': None, 'cost_difference': None,
                      'collision_epochs': None, 'refused_requests': None, 'moved': [],
                      'solver': s.solver, 'selector': s.selector, 'run': s.run,
                      'base': s.base, 'recordings': list(s.recordings) or [self.cache],
                      'folder': self.folder, 'files': [], 'stages': {}, 'seconds': {}}

    # -- jobs ----------------------------------------------------------------------------
    def _job(self, key: str, stage: str, *args, where: str = ANY, label: str = '') -> Job:
        self._waiting.add(key)
        return Job(self.spec.name, key, stage, args, where, self.spec.retries, label or stage)

    def _object(self, what: str) -> Ref:
        return Ref(f'@{what}:{self.spec.name}')

    def start(self) -> list[Job]:
        if self.error is not None:
            return self._fail('start', self.error)
        if self.spec.generate is not None and not self.cached:
            self.stage = 'generate'
            return [self._job('generate', 'generate', self._object('base'),
                              self._object('policy'), self.spec.generate, self.spec.selector)]
        return [self._read()]

    def _read(self) -> Job:
        self.stage = 'read'
        paths = list(self.spec.recordings) or [self.cache]
        stream = self._object('base') if self.spec.fit['stream'] else None
        return self._job('read', 'read', paths, self.rho, self.sigma, self.spec.namespace,
                         self.spec.drift['window'], self.spec.fit['window'], stream,
                         self.spec.fit['prior'], where=DRIVER_NODE)

    def _fit(self) -> list[Job]:
        """The fit of the recordings."""
        s = self.spec
        self._fitting = True
        return [self._job('fit', 'fit_point', Ref('read'), self._object('base'), s.fit, s.seed)]

    def done(self, key: str, facts: dict) -> list[Job]:
        """The stage `key` finished with `facts` ({'error': ...} when it failed)."""
        if self.finished or key not in self._waiting:
            return []
        self._waiting.discard(key)
        if 'error' in facts:
            return self._fail(key, facts['error'])
        if 'seconds' in facts:
            name = key.split('.')[0]
            self.entry['seconds'][name] = round(self.entry['seconds'].get(name, 0.0)
                                                + facts['seconds'], 3)
        s = self.spec
        if key == 'generate':
            self.stage = 'save recordings'
            return [self._job('save', 'write_text', self.cache, Ref('generate'),
                              where=DRIVER, label='save recordings')]
        if key == 'save':
            return [self._read()]
        if key == 'read':
            self.entry['read'] = {k: facts[k] for k in ('epochs', 'episodes', 'window_epochs',
                                                        'issues', 'first_issues', 'files')}
            self.stage = 'drift'
            jobs = [self._job('drift', 'drift_observed', Ref('read'), self._object('base'),
                              s.drift)]
            if s.run == 'always':
                jobs += self._fit()
            return jobs
        if key == 'drift':
            self._drift = facts
            self.stage = 'drift simulations'
            if facts['impossible']:
                return self._drifted()
            return [self._job(f'null.{i}', 'drift_null', Ref('read'), self._object('base'),
                              Ref('drift'), s.drift, chunk, label='drift simulations')
                    for i, chunk in enumerate(seeds(s.seed, 1, s.drift['simulations']))]
        if key.startswith('null.'):
            self._null += facts['statistics']
            if any(k.startswith('null.') for k in self._waiting):
                return []
            return self._drifted()
        if key == 'fit':
            self.entry['fit'] = {'iterations': facts['iterations'], 'loglik': facts['loglik']}
            self.stage = 'bootstrap'
            chunks = seeds(s.seed, 2, s.fit['bootstrap'])
            if not chunks:
                return [self._summary()]
            return [self._job(f'boot.{i}', 'bootstrap', Ref('read'), Ref('fit'), s.fit, chunk,
                              label='bootstrap')
                    for i, chunk in enumerate(chunks)]
        if key.startswith('boot.'):
            if any(k.startswith('boot.') for k in self._waiting):
                return []
            return [self._summary()]
        if key == 'summary':
            self._summarised = True
            self.entry['moved'] = facts['moved']
            self.entry['fit'].update(bootstrap=facts['bootstrap'], warnings=facts['warnings'],
                                     config_sha256=facts['config_sha256'])
            if 'stream' in facts:
                self.entry['fit']['stream'] = facts['stream']
            return self._after_fit()
        if key in ('mdp', 'pomdp'):
            self.entry.setdefault('solve', {})[key] = {
                k: v for k, v in facts.items() if k != 'seconds'}
            self._solves.discard(key)
            if self._solves:
                return []
            return self._after_fit()
        if key == 'shadow':
            self._shadow = facts
        if key.startswith('refit.'):
            self._refits += facts['rows']
        if key == 'shadow' or key.startswith('refit.'):
            if any(k == 'shadow' or k.startswith('refit.') for k in self._waiting):
                return []
            return self._decided()
        if key == 'outputs':
            self.entry['files'] = facts['files']
            self.stage = 'write'
            return [self._job('write', 'write_files', self.folder, Ref('outputs'),
                              where=DRIVER, label='write')]
        if key == 'write':
            self.stage = self.entry['decision']
            self.finished = True
            return []
        raise AssertionError(key)

    def _summary(self) -> Job:
        self.stage = 'fit summary'
        s = self.spec
        chunks = len(seeds(s.seed, 2, s.fit['bootstrap']))
        return self._job('summary', 'fit_summary', Ref('fit'), self._object('base'),
                         self.entry['recordings'], Ref('read') if s.fit['stream'] else None,
                         s.fit, s.seed, *(Ref(f'boot.{i}') for i in range(chunks)))

    def _after_fit(self) -> list[Job]:
        """Solve once the fit is summarised; once the drift test says so (or run: always) and
        the solves are done, the shadow check: the in-sample figures and the refits
        (check.py), side by side."""
        s = self.spec
        jobs: list[Job] = []
        if (self._summarised and 'mdp' not in self.entry.get('solve', {})
                and 'mdp' not in self._solves):
            self.stage = 'solve'
            self._solves = {'mdp'} | ({'pomdp'} if s.solves_pomdp else set())
            jobs.append(self._job('mdp', 'solve_mdp', Ref('summary'), s.max_memory_mb,
                                  label='solve'))
            if s.solves_pomdp:
                jobs.append(self._job('pomdp', 'solve_pomdp', Ref('summary'), s.pomdp, s.seed,
                                      s.max_memory_mb, label='solve pomdp'))
        if self._drift_p() is None or self._started or self._solves or \
                'mdp' not in self.entry.get('solve', {}):
            return jobs
        self._started = True
        self.stage = 'shadow check'
        pomdp = Ref('pomdp') if s.solves_pomdp else None
        jobs.append(self._job('shadow', 'shadow', self._object('running'), Ref('summary'),
                              Ref('mdp'), pomdp, s.selector, s.evaluate, s.seed,
                              label='shadow check'))
        refit_pomdp = s.pomdp if s.selector in POMDP_SELECTORS else None
        count = s.evaluate['refits'] if self._episodes() >= MIN_EPISODES else 0
        for i, draws in enumerate(refit_draws(count)):
            jobs.append(self._job(f'refit.{i}', 'refits', self._object('running'), Ref('read'),
                                  Ref('fit'), Ref('summary'), Ref('mdp'), self._object('base'),
                                  s.selector, s.fit, refit_pomdp, s.evaluate, s.seed,
                                  s.max_memory_mb, draws, label='refits'))
        return jobs

    def _decided(self) -> list[Job]:
        """The rule (check.decide) on the in-sample figures corrected by the refits."""
        inside, rows = self._shadow, sorted(self._refits, key=lambda r: r['draw'])
        figures = check.combine(inside, rows)
        decision, reason, blocked = check.decide(
            figures, self.spec.promote['guards'],
            unchecked=f'the refits resample episodes, and the recordings hold '
                      f'{self._episodes()}; at least {MIN_EPISODES} are needed')
        self.entry['cost_difference'] = figures[check.COST]
        for metric in check.METRICS:
            if metric != check.COST and metric in figures:
                self.entry[metric] = figures[metric]
        self.entry['guards'] = {'safety': check.SAFETY,
                                'plant': list(self.spec.promote['guards']),
                                'kept_by': [{'guard': b['guard'],
                                             'figure': b['figure'],
                                             'cost_given_up': b['cost_given_up']}
                                            for b in blocked]}
        self.entry['shadow'] = {
            'world': check.WORLD if len(rows) >= 2 else check.WORLD_UNCORRECTED,
            'refits': len(rows),
            'refits_not_converged': sum(not r['converged'] for r in rows),
            'errors': {m: [r[m][0] - r[m][1] for r in rows] for m in check.METRICS},
            'in_sample': {**{k: inside[k] for k in ('world', 'episodes') + SHADOW_METRICS}},
            **{k: inside[k] for k in ('episodes', 'epochs', 'seed', 'selector')}}
        return self._outputs(decision, reason, shadow=True)

    def _episodes(self) -> int:
        return int(self.entry.get('read', {}).get('episodes', 0))

    def _drift_p(self) -> float | None:
        return self.entry['drift_p']

    def _drifted(self) -> list[Job]:
        s, facts = self.spec, self._drift
        p = drift.p_value(facts['statistic'], self._null)
        drifted = p < s.drift['alpha']
        self.entry['drift_p'] = p
        self.entry['drift'] = {
            'p': p, 'drifted': drifted, 'statistic': facts['statistic'],
            'simulations': len(self._null), 'alpha': s.drift['alpha'],
            'window_epochs': self.entry['read']['window_epochs'], 'window': s.drift['window'],
            'null_median': _median(self._null), 'impossible': facts['impossible'],
            'loglik_running': facts['loglik_running'], 'loglik_refit': facts['loglik_refit']}
        if not drifted and s.run == 'on_drift':
            return self._outputs(KEEP, f'no drift, nothing fitted (run: on_drift): '
                                 f'{drift.describe(self.entry["drift"])}', shadow=False)
        if not self._fitting:
            return self._fit()
        return self._after_fit()

    def _outputs(self, decision: str, reason: str, shadow: bool) -> list[Job]:
        self.entry['decision'], self.entry['reason'] = decision, reason
        self.stage = 'outputs'
        if not shadow:
            return [self._job('outputs', 'outputs', self._report(), None, None, None, None,
                              label='outputs')]
        s = self.spec
        return [self._job('outputs', 'outputs', self._report(), Ref('summary'), Ref('mdp'),
                          Ref('pomdp') if s.solves_pomdp else None, Ref('shadow'),
                          label='outputs')]

    def _report(self) -> dict:
        return json.loads(json.dumps(self.entry, default=float))

    def _fail(self, key: str, reason: str) -> list[Job]:
        if self.entry['decision'] == FAILED:
            self.finished = True
            return []
        stage = key.split('.')[0]
        self.entry['decision'] = FAILED
        self.entry['reason'] = f'{stage}: {reason}' if not reason.startswith(stage) else reason
        self.entry['failed_stage'] = stage
        self._waiting.clear()
        self.stage = 'failed'
        if key == 'write':           # nothing more to try: the report says so
            self.finished = True
            return []
        report = (json.dumps(self._report(), indent=2) + '\n').encode()
        return [self._job('write', 'write_files', self.folder, {'cell_report.json': report},
                          where=DRIVER, label='write')]


def _median(values) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    n = len(ordered)
    return float(ordered[n // 2] if n % 2 else (ordered[n // 2 - 1] + ordered[n // 2]) / 2)


# -- what only the driver does: write ------------------------------------------------------
def write_text(path: str, text: str) -> tuple[dict, None]:
    from ..paths import replace_file
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    replace_file(path, lambda temporary: temporary.write_text(text))
    return {'path': path}, None


def write_files(folder: str, files: dict) -> tuple[dict, None]:
    """Each file whole or not at all (`paths.replace_file`), cell_report.json last: it is
    there only once every other file of the run is."""
    from ..paths import replace_file
    target = Path(folder)
    target.mkdir(parents=True, exist_ok=True)
    names = sorted(files, key=lambda n: n == 'cell_report.json')
    for name in names:
        replace_file(target / name, lambda temporary, data=files[name]:
                     temporary.write_bytes(data))
    return {'files': names}, None


DRIVER_STAGES = {'write_text': write_text, 'write_files': write_files}


def run_stage(stage: str, *args) -> tuple[dict, object]:
    """Run one stage; its failure becomes facts {'error': one line} (a bug's too, with its
    type and place), so that one cell's failure is that cell's report, not the plant's."""
    function = STAGES.get(stage) or DRIVER_STAGES[stage]
    try:
        return function(*args)
    except CellError as exc:
        return {'error': ' '.join(str(exc).split())}, None
    except OSError as exc:
        return {'error': f'{stage}: {exc.strerror or exc} ({getattr(exc, "filename", "")})'}, None
    except Exception as exc:   # noqa: BLE001 - reported as the cell's failure, with its place
        where = traceback.extract_tb(exc.__traceback__)[-1]
        return {'error': f'{stage}: {type(exc).__name__}: {" ".join(str(exc).split())[:300]} '
                         f'({Path(where.filename).name}:{where.lineno})'}, None


def resolve(args: tuple, payloads: dict, cell: str):
    """`args` with every Ref replaced by its payload (cell-local keys or plant objects)."""
    def one(a):
        if isinstance(a, Ref):
            return payloads[a.key] if a.key.startswith('@') else payloads[(cell, a.key)]
        return a
    return tuple(one(a) for a in args)


def run_serially(pipelines: list[CellPipeline], objects: dict, progress=None) -> None:
    """Every cell's stages one after the other in this process: the same work as the Ray
    scheduler does, for comparison (bench/fleet_bench.py) and for a machine without Ray."""
    payloads: dict = dict(objects)
    queue = deque((p, job) for p in pipelines for job in p.start())
    while queue:
        pipeline, job = queue.popleft()
        facts, payload = run_stage(job.stage, *resolve(job.args, payloads, job.cell))
        payloads[(job.cell, job.key)] = payload
        queue.extend((pipeline, j) for j in pipeline.done(job.key, facts))
        if progress is not None:
            progress(pipelines)
