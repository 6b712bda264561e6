"""The stages of a cell's pipeline as plain functions (docs/FLEET.md): what Ray schedules.

Every stage takes plain values (configurations, numpy arrays in dataclasses, settings) and
returns `(facts, payload)`: `facts` a small JSON-able dict the scheduler reads to decide what
runs next (and that goes into the report), `payload` what later stages take (arrays stay in
Ray's object store between them, never in files the workers would have to share). A stage
that cannot do its work raises `CellError` with one line; the cell is then reported failed
and the other cells go on. No stage touches the output folder: `outputs` returns the files'
bytes and the driver writes them (`paths.replace_file`), so workers need no shared disk.
The recordings are read where they are (`read` runs on the driver's node).

    generate       the batch simulator records the running policy in another world (CSV)
    read           recordings -> the fit's arrays, all of them and the drift window
    drift_observed the likelihood ratio of the window against the running model (drift.py)
    drift_null     the same statistic on recordings simulated under the running model
    fit_point      EM from the running configuration (core.learning.fit)
    bootstrap      resamples of the episodes, refitted (a chunk of them per call)
    fit_summary    intervals, the fitted configuration and what moved
    solve_mdp      value iteration of the fitted configuration
    solve_pomdp    the POMDP over the belief (solver pomdp or both)
    shadow         both policies in the cell as now fitted, paired episodes
    outputs        the files of the cell: fitted YAML and report, policies, report, plots
"""

from __future__ import annotations

import csv
import io
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import yaml

from .. import parallel
from ..config import Config, ConfigError, load_config, validate
from ..learning import fit as fitting
from ..learning.recordings import (NO_OBSERVATION, UNANSWERED, Recording, RecordingError,
                                   read_recordings)
from ..model import ACTIONS, TASK_VARIABLES, HRCModel
from . import drift

FIT_TASK_FIELDS = ('epoch', 'task', 'd', 'observation', 'action', 'accepted', 'line')


class CellError(RuntimeError):
    """A stage cannot do its work for this cell; the message says why in one line."""


def _seconds(t0: float) -> float:
    return round(time.perf_counter() - t0, 3)


# -- generate ---------------------------------------------------------------------------------
def world_config(base: Config, world) -> Config:
    """The world of a generated cell: overrides of `base`, or a configuration path."""
    try:
        if isinstance(world, str):
            return load_config(world)
        return base.with_overrides(world)
    except ConfigError as exc:
        raise CellError(f'generate.world: {exc}') from None


def recordings_csv(recordings: list[Recording]) -> str:
    """Recordings as a trajectory CSV (docs/LEARNING.md): what `read_csv` reads back."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator='\n')
    writer.writerow(('episode', 'epoch') + TASK_VARIABLES + ('d', 'O', 'action', 'accepted'))
    for r in recordings:
        for k in range(len(r)):
            o = int(r.observation[k])
            accepted = int(r.accepted[k])
            writer.writerow([r.episode, int(r.epoch[k]), *map(int, r.task[k]), int(r.d[k]),
                             '' if o == NO_OBSERVATION else o, ACTIONS[int(r.action[k])],
                             '' if accepted == UNANSWERED else accepted])
    return out.getvalue()


def generate(base: Config, policy, settings: dict, selector: str) -> tuple[dict, str]:
    """`settings['episodes']` x `settings['epochs']` of the running policy (and `selector`) in
    the world `settings['world']`, with `explore` of uniformly drawn actions: hrc-evaluate's
    random task streams and humans, recorded as a robot records them (no em, ea)."""
    from ..study.evaluation import BatchSimulator, episodes_of
    t0 = time.perf_counter()
    world = HRCModel(world_config(base, settings['world']))
    model = HRCModel(base)
    if world.dims != model.dims:
        raise CellError(f'generate.world has rho {world.rho}, sigma {world.sigma}; the base '
                        f'{model.rho}, {model.sigma}: they must describe the same cell')
    scenarios, seeds = episodes_of(model, 'random', settings['episodes'], settings['epochs'],
                                   settings['seed'])
    sim = BatchSimulator(model, policy, world=world)
    mdp_selector = selector if selector in ('paper', 'qmdp', 'mls') else 'paper'
    result = sim.run(scenarios, seeds, mdp_selector, explore=settings['explore'], record=True)
    text = recordings_csv(result.recordings(world))
    return {'epochs': settings['episodes'] * settings['epochs'], 'seconds': _seconds(t0)}, text


# -- read -------------------------------------------------------------------------------------
def tail(recordings: list[Recording], epochs: int) -> list[Recording]:
    """The last `epochs` epochs of the recordings, in order; the oldest episode kept is cut
    at the window's start."""
    out, left = [], epochs
    for r in reversed(recordings):
        if left <= 0:
            break
        if len(r) <= left:
            out.append(r)
            left -= len(r)
            continue
        cut = slice(len(r) - left, len(r))
        out.append(replace(r, **{f: getattr(r, f)[cut] for f in FIT_TASK_FIELDS}))
        left = 0
    return out[::-1]


def read(paths, rho: int, sigma: int, namespace: str, window: int,
         fit_window: int | None = None) -> tuple[dict, dict]:
    """The recordings as the fit's arrays: 'all' (or the last `fit_window` epochs) for the
    fit and 'window', the last `window` epochs, for the drift test. A bag holding several
    cells is read at the cell's namespace; a corrupt or unreadable recording fails the cell
    (a fit on what happened to be readable would hide it)."""
    from .spec import recording_files
    t0 = time.perf_counter()
    files = recording_files(paths)
    if not files:
        raise CellError(f'no recording in {", ".join(map(str, paths))}')
    try:
        try:
            recordings = read_recordings(files, rho, sigma)
        except RecordingError as exc:
            if 'holds several cells' not in str(exc):
                raise
            recordings = read_recordings(files, rho, sigma, namespace)
        used = recordings if fit_window is None else tail(recordings, fit_window)
        data = fitting.prepare(used)
        recent = fitting.prepare(tail(recordings, window))
    except (RecordingError, fitting.FitError) as exc:
        raise CellError(f'recordings: {" ".join(str(exc).split())}') from None
    facts = {'files': [str(f) for f in files], 'epochs': data.epochs,
             'episodes': len(data.episodes), 'window_epochs': recent.epochs,
             'issues': len(data.issues), 'first_issues': data.issues[:5],
             'seconds': _seconds(t0)}
    return facts, {'all': data, 'window': recent}


# -- drift ------------------------------------------------------------------------------------
def drift_observed(data: dict, running: Config, settings: dict) -> tuple[dict, np.ndarray]:
    t0 = time.perf_counter()
    s = drift.statistic(data['window'], running, settings['tol'], settings['max_iter'])
    facts = {'statistic': s.lr, 'loglik_running': s.loglik_running,
             'loglik_refit': s.loglik_refit, 'impossible': s.impossible,
             'seconds': _seconds(t0)}
    return facts, s.pi_running


def drift_null(data: dict, running: Config, pi: np.ndarray, settings: dict, seeds
               ) -> tuple[dict, None]:
    t0 = time.perf_counter()
    values = drift.null_statistics(data['window'], running, pi, seeds, settings['tol'],
                                   settings['max_iter'])
    return {'statistics': values, 'seconds': _seconds(t0)}, None


# -- fit --------------------------------------------------------------------------------------
def fit_point(data: dict, base: Config, settings: dict, seed: int
              ) -> tuple[dict, fitting.FitResult]:
    """EM as hrc-fit runs it, without the bootstrap (that is `bootstrap`, fanned out)."""
    t0 = time.perf_counter()
    try:
        result = fitting.fit(data['all'], base, settings['hold'], n_init=settings['starts'],
                             seed=seed, tol=settings['tol'], max_iter=settings['max_iter'],
                             bootstrap=0)
    except fitting.FitError as exc:
        raise CellError(f'fit: {exc}') from None
    if not result.converged:
        raise CellError(f'fit: EM did not converge in {result.iterations} iterations (log '
                        f'likelihood {result.loglik:.4f}, still rising by more than '
                        f'fit.tol = {settings["tol"]:g} per epoch); raise fit.max_iter or '
                        'record more')
    return {'iterations': result.iterations, 'loglik': result.loglik,
            'seconds': _seconds(t0)}, result


def bootstrap_counts(n_episodes: int, seed) -> np.ndarray:
    """Episode multiplicities of one resample (with replacement), from its own seed."""
    rng = np.random.default_rng(seed)
    return rng.multinomial(n_episodes, np.full(n_episodes, 1.0 / n_episodes))


def bootstrap(data: dict, point: fitting.FitResult, settings: dict, seeds
              ) -> tuple[dict, np.ndarray]:
    """The fit of one resample of the episodes per seed, by EM from the estimate: (n, 57)."""
    t0 = time.perf_counter()
    fit_data = data['all']
    out = np.empty((len(seeds), len(fitting.PARAMETER_NAMES)))
    for i, seed in enumerate(seeds):
        counts = bootstrap_counts(len(fit_data.episodes), seed)
        run = fitting.run_em(fit_data, point.params, point.hold, settings['tol'],
                             settings['max_iter'],
                             seg_weight=counts[fit_data.seg_episode].astype(float))
        out[i] = run.params.vector()
    return {'resamples': len(seeds), 'seconds': _seconds(t0)}, out


def moved_parameters(result: fitting.FitResult) -> list[dict]:
    """The free parameters whose 95% interval leaves out the base value: what moved."""
    if result.interval is None:
        return []
    fitted, base = result.params.vector(), result.base.vector()
    out = []
    for i, name in enumerate(fitting.PARAMETER_NAMES):
        if fitting.PARAMETER_FAMILIES[i] in result.hold:
            continue
        low, high = result.interval[:, i]
        if not low <= base[i] <= high:
            out.append({'name': name, 'base': float(base[i]), 'fitted': float(fitted[i]),
                        'ci95': [float(low), float(high)]})
    return out


def fit_summary(point: fitting.FitResult, base: Config, sources, *samples
                ) -> tuple[dict, dict]:
    """The bootstrap's intervals and effective support (hrc-fit's rules), the fitted
    configuration (as its YAML reads back) and the parameters that moved."""
    t0 = time.perf_counter()
    result = point
    if samples:
        draws = np.vstack(samples)
        result = fitting.with_bootstrap(point, draws)
    try:
        text = fitting.config_yaml(result, base, sources)
        config = Config(validate(yaml.safe_load(text)), source='fitted.yaml')
    except ConfigError as exc:
        raise CellError(f'the fitted configuration does not validate ({exc})') from None
    facts = {'moved': moved_parameters(result), 'warnings': result.warnings,
             'iterations': result.iterations, 'loglik': result.loglik,
             'epochs': result.epochs, 'episodes': result.episodes,
             'bootstrap': 0 if result.samples is None else len(result.samples),
             'config_sha256': config.policy_hash, 'seconds': _seconds(t0)}
    return facts, {'result': result, 'config': config, 'yaml': text}


# -- solve ------------------------------------------------------------------------------------
def check_memory(model: HRCModel, max_memory_mb: int | None, what: str) -> int:
    """The solve's memory estimate (bytes); CellError when it is above the cell's limit or
    above the memory available on this node."""
    from ..mdp.solver import memory_estimate
    needed = memory_estimate(model)
    limits = []
    if max_memory_mb is not None:
        limits.append((max_memory_mb * 2 ** 20, 'the cell\'s max_memory_mb'))
    available = parallel.available_memory()
    if available is not None:
        limits.append((available, 'the memory available on this node'))
    for limit, name in limits:
        if needed > limit:
            raise CellError(f'{what} of {model.n_states:,} states needs about '
                            f'{needed / 2 ** 20:,.0f} MiB, more than {name} '
                            f'({limit / 2 ** 20:,.0f} MiB); not solved')
    return needed


def _npz_bytes(save, *args) -> bytes:
    with tempfile.TemporaryDirectory(prefix='hrc_plant_') as folder:
        path = Path(folder) / 'policy.npz'
        save(path, *args)
        return path.read_bytes()


def load_npz(data: bytes, load, config: Config):
    """A policy file's bytes loaded (and checked against `config`) as its loader does."""
    with tempfile.TemporaryDirectory(prefix='hrc_plant_') as folder:
        path = Path(folder) / 'policy.npz'
        path.write_bytes(data)
        return load(path, config)


def solve_mdp(summary: dict, max_memory_mb: int | None) -> tuple[dict, dict]:
    from ..mdp.policy import save_policy
    from ..mdp.solver import solve
    t0 = time.perf_counter()
    config = summary['config']
    model = HRCModel(config)
    needed = check_memory(model, max_memory_mb, 'the MDP solve')
    result = solve(model)
    facts = {'iterations': result.iterations, 'converged': bool(result.converged),
             'residual': float(result.residual), 'memory_estimate_mb': needed / 2 ** 20,
             'seconds': _seconds(t0)}
    return facts, {'result': result, 'npz': _npz_bytes(save_policy, result, config)}


def solve_pomdp(summary: dict, settings: dict, seed: int, max_memory_mb: int | None
                ) -> tuple[dict, dict]:
    from ..pomdp.policy import load_pomdp_policy, save_pomdp_policy
    from ..pomdp.solver import solve_pomdp as solve
    t0 = time.perf_counter()
    config = summary['config']
    model = HRCModel(config)
    needed = check_memory(model, max_memory_mb, 'the POMDP solve')
    result = solve(model, episodes=settings['episodes'], rounds=settings['rounds'], seed=seed)
    data = _npz_bytes(save_pomdp_policy, result, config)
    facts = {'vectors': int(len(result.alphas)),
             'case_study_relative_gap': result.report['case_study_relative_gap'],
             'memory_estimate_mb': needed / 2 ** 20, 'seconds': _seconds(t0)}
    return facts, {'policy': load_npz(data, load_pomdp_policy, config), 'npz': data}


# -- the shadow check -------------------------------------------------------------------------
SHADOW_METRICS = ('discounted_cost', 'collision_epochs', 'refused_requests')


def paired(new: np.ndarray, running: np.ndarray) -> dict:
    """Mean of new - running over the same episodes with its 95% interval (the rule of
    `evaluation.paired_difference`, applied to any per-episode metric)."""
    from ..study.evaluation import paired_difference
    d = paired_difference(SimpleNamespace(discounted_cost=np.asarray(new, dtype=float)),
                          SimpleNamespace(discounted_cost=np.asarray(running, dtype=float)))
    return {**d, 'new': float(np.mean(new)), 'running': float(np.mean(running))}


def shadow(running: dict, summary: dict, mdp: dict, pomdp: dict | None, selector: str,
           settings: dict, seed: int) -> tuple[dict, dict]:
    """The running pair (its configuration, policy and, for pomdp / fib, POMDP policy) and
    the new one, each planning with its own model and belief filter, in the world of the
    fitted configuration: `hrc-evaluate --true-config`'s machinery on the same seeded
    episodes, so every difference is paired (common random numbers)."""
    from ..study.evaluation import evaluate
    t0 = time.perf_counter()
    world = HRCModel(summary['config'])
    common = dict(episodes=settings['episodes'], epochs=settings['epochs'], seed=seed,
                  task_rate=settings['task_rate'], selectors=(selector,), world=world)
    try:
        old = evaluate(HRCModel(running['config']), running['policy'],
                       pomdp=running.get('pomdp'), **common)[selector]
        new = evaluate(world, mdp['result'], pomdp=None if pomdp is None else pomdp['policy'],
                       **common)[selector]
    except (ValueError, RuntimeError) as exc:
        raise CellError(f'shadow check: {exc}') from None
    facts = {metric: paired(getattr(new, metric), getattr(old, metric))
             for metric in SHADOW_METRICS}
    facts.update(episodes=settings['episodes'], epochs=settings['epochs'], seed=seed,
                 selector=selector, seconds=_seconds(t0))
    return facts, {'difference': new.discounted_cost - old.discounted_cost}


# -- outputs ----------------------------------------------------------------------------------
def outputs(report: dict, summary: dict | None, mdp: dict | None, pomdp: dict | None,
            shadow_payload: dict | None) -> tuple[dict, dict]:
    """The cell's files as bytes, by name: fitted.yaml, fitted.report.json, fitted.png,
    policy.npz, pomdp.npz, shadow.png and cell_report.json (last: its presence says the
    others are complete)."""
    from . import report as reporting
    t0 = time.perf_counter()
    files: dict[str, bytes] = {}
    if summary is not None:
        files['fitted.yaml'] = summary['yaml'].encode()
        fit_report = fitting.report_dict(summary['result'])
        files['fitted.report.json'] = (json.dumps(fit_report, indent=2) + '\n').encode()
        files['fitted.png'] = reporting.figure_bytes(reporting.plot_fit, summary['result'])
    if mdp is not None:
        files['policy.npz'] = mdp['npz']
    if pomdp is not None:
        files['pomdp.npz'] = pomdp['npz']
    if shadow_payload is not None:
        files['shadow.png'] = reporting.figure_bytes(reporting.plot_shadow, report,
                                                     shadow_payload['difference'])
    files['cell_report.json'] = (json.dumps(report, indent=2, default=float) + '\n').encode()
    return {'files': sorted(files), 'seconds': _seconds(t0)}, files


STAGES = {f.__name__: f for f in (generate, read, drift_observed, drift_null, fit_point,
                                  bootstrap, fit_summary, solve_mdp, solve_pomdp, shadow,
                                  outputs)}
