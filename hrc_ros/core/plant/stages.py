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
    read           recordings -> the fit's arrays: all of them and the drift window
    drift_observed the likelihood ratio of the window against the running model (drift.py)
    drift_null     the same statistic on recordings simulated under the running model
    fit_point      EM from the running configuration (core.learning.fit)
    bootstrap      resamples of the episodes, refitted (a chunk of them per call)
    fit_summary    intervals, the fitted configuration and what moved
    solve_mdp      value iteration of the fitted configuration
    solve_pomdp    the POMDP over the belief (solver pomdp or both)
    shadow         both policies in the world fitted from all recordings (in-sample figures)
    refits         resamples of the episodes fitted and solved as the cell was, each new
                   policy and the running one in its own fitted world and in the cell's: the
                   fit's error, which corrects the in-sample figures (check.py; one per call)
    outputs        the files of the cell: fitted YAML and report, policies, report, plots
"""

from __future__ import annotations

import copy
import csv
import io
import json
import math
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
from ..learning.recordings import (NO_OBSERVATION, UNANSWERED, UNKNOWN_QUEUED, Recording,
                                   RecordingError, read_recordings)
from ..learning.stream import StreamError, check_stream, fit_stream_for
from ..model import ACTIONS, TASK_VARIABLES, HRCModel
from . import check, drift

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
    """Recordings as a trajectory CSV (docs/LEARNING.md): what `read_csv` reads back; with
    the column `queued` (the tasks waiting, MODEL.md 8.1) when every recording has it."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator='\n')
    queued = bool(recordings) and all(r.queued is not None for r in recordings)
    writer.writerow(('episode', 'epoch') + TASK_VARIABLES + ('d', 'O', 'action', 'accepted')
                    + (('queued',) if queued else ()))
    for r in recordings:
        for k in range(len(r)):
            o = int(r.observation[k])
            accepted = int(r.accepted[k])
            writer.writerow([r.episode, int(r.epoch[k]), *map(int, r.task[k]), int(r.d[k]),
                             '' if o == NO_OBSERVATION else o, ACTIONS[int(r.action[k])],
                             '' if accepted == UNANSWERED else accepted]
                            + ([_queued(r.queued[k])] if queued else []))
    return out.getvalue()


def _queued(value) -> int | str:
    """A recording's tasks waiting as its CSV cell: '' where it is not known."""
    return '' if int(value) == UNKNOWN_QUEUED else int(value)


def generate(base: Config, policy, settings: dict, selector: str) -> tuple[dict, str]:
    """`settings['episodes']` x `settings['epochs']` of the running policy (and `selector`) in
    the world `settings['world']`, with `explore` of uniformly drawn actions: hrc-evaluate's
    random task streams and humans, recorded as a robot records them (no em, ea). The people
    are the world's: drawn from its person prior (`observation.prior`, MODEL.md 6.1) when it
    has one, as hrc-evaluate --true-config draws them, uniform otherwise."""
    from ..study.evaluation import BatchSimulator, episodes_of
    t0 = time.perf_counter()
    world = HRCModel(world_config(base, settings['world']))
    model = HRCModel(base)
    if world.dims != model.dims:
        raise CellError(f'generate.world has rho {world.rho}, sigma {world.sigma}; the base '
                        f'{model.rho}, {model.sigma}: they must describe the same cell')
    scenarios, seeds = episodes_of(model, 'random', settings['episodes'], settings['epochs'],
                                   settings['seed'], prior=world.config.observation_prior)
    sim = BatchSimulator(model, policy, world=world)
    mdp_selector = selector if selector in ('paper', 'qmdp', 'mls') else 'paper'
    result = sim.run(scenarios, seeds, mdp_selector, explore=settings['explore'], record=True)
    text = recordings_csv(result.recordings(world))
    return {'epochs': settings['episodes'] * settings['epochs'], 'seconds': _seconds(t0)}, text


# -- read -------------------------------------------------------------------------------------
def span(recordings: list[Recording], start: int, stop: int) -> list[Recording]:
    """Epochs `start`..`stop` - 1 of the recordings taken one after the other, in order; an
    episode that straddles either end is cut there."""
    out, at = [], 0
    for r in recordings:
        low, high = max(start - at, 0), min(stop - at, len(r))
        at += len(r)
        if low >= high:
            continue
        if (low, high) == (0, len(r)):
            out.append(r)
            continue
        cut = slice(low, high)
        fields = FIT_TASK_FIELDS + (('queued',) if r.queued is not None else ())
        out.append(replace(r, **{f: getattr(r, f)[cut] for f in fields}))
    return out


def tail(recordings: list[Recording], epochs: int) -> list[Recording]:
    """The last `epochs` epochs of the recordings, in order; the oldest episode kept is cut
    at the window's start."""
    total = sum(len(r) for r in recordings)
    return span(recordings, max(total - epochs, 0), total)


def read(paths, rho: int, sigma: int, namespace: str, window: int,
         fit_window: int | None = None, stream_base: Config | None = None,
         prior: bool = False) -> tuple[dict, dict]:
    """The recordings as the fit's arrays: 'all' (or the last `fit_window` epochs) for the
    fit and 'window', the last `window` epochs, for the drift test. A bag holding several
    cells is read at the cell's namespace; a corrupt or unreadable recording fails the cell
    (a fit on what happened to be readable would hide it). With `stream_base` (the base of a
    cell with fit.stream) also 'recordings', the fit's recordings themselves, which the
    stream is counted from, checked as hrc-fit --stream checks them before any work
    (`stream.check_stream`). With `prior` (fit.prior) an episode must start at epoch 1, as
    hrc-fit --prior asks (checked here, before any work)."""
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
    if prior and not data.true_starts.any():
        raise CellError(f'fit.prior: no episode in the recordings starts at epoch '
                        f'{fitting.FIRST_EPOCH}, so nothing shows how a person starts; record '
                        'the runs from their start, or set fit.prior: false')
    if stream_base is not None:
        try:
            check_stream(used, stream_base)
        except StreamError as exc:
            raise CellError(f'fit.stream: {exc}') from None
    facts = {'files': [str(f) for f in files], 'epochs': data.epochs,
             'episodes': len(data.episodes), 'window_epochs': recent.epochs,
             'issues': len(data.issues), 'first_issues': data.issues[:5],
             'seconds': _seconds(t0)}
    payload = {'all': data, 'window': recent}
    if stream_base is not None:
        payload['recordings'] = used
    return facts, payload


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
    """EM as hrc-fit runs it, without the bootstrap (that is `bootstrap`, fanned out); with
    `settings['prior']` the person prior too (hrc-fit --prior)."""
    t0 = time.perf_counter()
    try:
        result = fitting.fit(data['all'], base, settings['hold'], n_init=settings['starts'],
                             seed=seed, tol=settings['tol'], max_iter=settings['max_iter'],
                             bootstrap=0, prior=settings.get('prior', False))
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


def resample_fits(data: fitting.FitData, point: fitting.FitResult, settings: dict, seeds
                  ) -> list[fitting.Params]:
    """The fit of one resample of the episodes per seed, from the estimate and by the method
    `point` was fitted with (hrc-fit's bootstrap: the quasi-Newton EM with the estimate's
    curvature, all resamples of the call in one batch; SQUAREM where `point` has none)."""
    if not len(seeds):
        return []
    weights = np.stack([bootstrap_counts(len(data.episodes), seed)[data.seg_episode]
                        for seed in seeds]).astype(float)
    method = fitting.SQUAREM if point.curvature is None else fitting.NEWTON
    runs = fitting.run_em_batch(data, [point.params] * len(seeds), point.hold, settings['tol'],
                                settings['max_iter'], weights, method=method,
                                curvature=point.curvature)
    return [run.params for run in runs]


def bootstrap(data: dict, point: fitting.FitResult, settings: dict, seeds
              ) -> tuple[dict, np.ndarray]:
    """`resample_fits` of all the recordings, as rows of the 57 parameters: (n, 57); with a
    person prior (`point.prior`) each row followed by the resample's prior: (n, 57 + 9)."""
    t0 = time.perf_counter()
    fits = resample_fits(data['all'], point, settings, seeds)
    width = len(fitting.PARAMETER_NAMES) + (len(fitting.PRIOR_NAMES) if point.prior else 0)
    out = np.array([np.concatenate([p.vector(), p.pi]) if point.prior else p.vector()
                    for p in fits]).reshape(len(seeds), width)
    return {'resamples': len(seeds), 'seconds': _seconds(t0)}, out


Z95 = 1.959963984540054


def own_interval(share: float, events: float) -> tuple[float, float]:
    """The 95% Wilson interval of a probability `share` seen over `events` informative
    epochs (the fit's support): how well the data could pin it down if the hidden state were
    known, so no interval claimed for it is narrower. [0, 1] without events."""
    if not events > 0:
        return 0.0, 1.0
    p = min(max(float(share), 0.0), 1.0)
    z2 = Z95 * Z95 / events
    centre = (p + z2 / 2) / (1 + z2)
    half = Z95 * math.sqrt(p * (1 - p) / events + z2 / (4 * events)) / (1 + z2)
    return max(0.0, centre - half), min(1.0, centre + half)


def parameter_interval(result: fitting.FitResult, i: int) -> tuple[float, float]:
    """The 95% interval the plant reports for free parameter `i`: the bootstrap's
    percentiles, widened to hold the fitted value (resamples refitted from the estimate can
    all stop a rounding step beside it) and to at least `own_interval` of its support (a
    bootstrap over one episode, or over episodes that all agree, has no spread at all)."""
    fitted = float(result.params.vector()[i])
    own = own_interval(fitted, float(result.support[i]))
    low, high = result.interval[:, i] if result.interval is not None else own
    return min(float(low), own[0], fitted), max(float(high), own[1], fitted)


def moved_parameters(result: fitting.FitResult) -> list[dict]:
    """The free parameters whose 95% interval (`parameter_interval`) leaves out the base
    value: what moved."""
    if result.interval is None:
        return []
    fitted, base = result.params.vector(), result.base.vector()
    out = []
    for i, name in enumerate(fitting.PARAMETER_NAMES):
        if fitting.PARAMETER_FAMILIES[i] in result.hold:
            continue
        low, high = parameter_interval(result, i)
        if not low <= base[i] <= high:
            out.append({'name': name, 'base': float(base[i]), 'fitted': float(fitted[i]),
                        'ci95': [low, high],
                        'bootstrap': [float(v) for v in result.interval[:, i]],
                        'support': float(result.support[i])})
    return out


def fit_summary(point: fitting.FitResult, base: Config, sources, data: dict | None = None,
                settings: dict | None = None, seed: int = 0, *samples) -> tuple[dict, dict]:
    """The bootstrap's intervals and effective support (hrc-fit's rules), the fitted
    configuration (as its YAML reads back) and the parameters that moved. With
    `settings['stream']` the task stream too, counted from `data['recordings']` as hrc-fit
    --stream counts it (`settings['bootstrap']` resamples from `seed`) and written as the
    configuration's `stream` section; its report is the payload's 'stream'."""
    t0 = time.perf_counter()
    result = point
    if samples:
        draws = np.vstack(samples)
        n = len(fitting.PARAMETER_NAMES)
        result = fitting.with_bootstrap(point, draws[:, :n],
                                        draws[:, n:] if point.prior else None)
    stream = None
    if settings is not None and settings.get('stream'):
        try:
            stream = fit_stream_for(data['recordings'], base, bootstrap=settings['bootstrap'],
                                    seed=seed)
        except StreamError as exc:
            raise CellError(f'fit.stream: {exc}') from None
    try:
        text = fitting.config_yaml(result, base, sources, stream)
        config = Config(validate(yaml.safe_load(text)), source='fitted.yaml')
    except ConfigError as exc:
        raise CellError(f'the fitted configuration does not validate ({exc})') from None
    facts = {'moved': moved_parameters(result), 'warnings': result.warnings,
             'iterations': result.iterations, 'loglik': result.loglik,
             'epochs': result.epochs, 'episodes': result.episodes,
             'bootstrap': 0 if result.samples is None else len(result.samples),
             'config_sha256': config.policy_hash, 'seconds': _seconds(t0)}
    if stream is not None:
        facts['stream'] = {'section': config.data['stream'], 'warnings': stream.warnings()}
    return facts, {'result': result, 'config': config, 'yaml': text, 'stream': stream}


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
CHECK_METRICS = tuple(check.METRICS)      # the figures of the promotion check
IN_SAMPLE_WORLD = ('fitted from all the recordings, the ones the new policy was solved from '
                   '(optimistic for it: corrected by the refits before it decides)')


def paired(new: np.ndarray, running: np.ndarray) -> dict:
    """Mean of new - running over the same episodes with its 95% interval (the rule of
    `evaluation.paired_difference`, applied to any per-episode metric)."""
    from ..study.evaluation import paired_difference
    d = paired_difference(SimpleNamespace(discounted_cost=np.asarray(new, dtype=float)),
                          SimpleNamespace(discounted_cost=np.asarray(running, dtype=float)))
    return {**d, 'new': float(np.mean(new)), 'running': float(np.mean(running))}


def _both_in(world: Config, running: dict, config: Config, policy, pomdp, selector: str,
             settings: dict, seed: int) -> dict:
    """metric -> (new, running) per-episode arrays: the running pair (its configuration,
    policy and, for pomdp / fib, POMDP policy) and the new one, each planning with its own
    model and belief filter, in the world `world`: `hrc-evaluate --true-config`'s machinery
    on the same seeded episodes, so every difference is paired (common random numbers)."""
    from ..study.evaluation import evaluate
    common = dict(episodes=settings['episodes'], epochs=settings['epochs'], seed=seed,
                  task_rate=settings['task_rate'], selectors=(selector,),
                  world=HRCModel(world))
    try:
        old = evaluate(HRCModel(running['config']), running['policy'],
                       pomdp=running.get('pomdp'), **common)[selector]
        new = evaluate(HRCModel(config), policy, pomdp=pomdp, **common)[selector]
    except (ValueError, RuntimeError) as exc:
        raise CellError(f'shadow check: {exc}') from None
    return {metric: (np.asarray(getattr(new, metric), dtype=float),
                     np.asarray(getattr(old, metric), dtype=float))
            for metric in CHECK_METRICS}


def shadow(running: dict, summary: dict, mdp: dict, pomdp: dict | None, selector: str,
           settings: dict, seed: int) -> tuple[dict, dict]:
    """The in-sample figures: the running pair and the new one (fitted from all the
    recordings, its policy) in the world fitted from those same recordings, every metric of
    the check: optimistic for the new policy, which is scored in the world it was planned
    for, until the refits correct them (check.py)."""
    t0 = time.perf_counter()
    runs = _both_in(summary['config'], running, summary['config'], mdp['result'],
                    None if pomdp is None else pomdp['policy'], selector, settings, seed)
    facts = {metric: paired(*runs[metric]) for metric in CHECK_METRICS}
    facts.update(world=IN_SAMPLE_WORLD, episodes=settings['episodes'],
                 epochs=settings['epochs'], seed=seed, selector=selector,
                 seconds=_seconds(t0))
    cost = runs['discounted_cost']
    return facts, {'difference': cost[0] - cost[1]}


# -- the promotion check's refits (check.py) ----------------------------------------------------
MIN_EPISODES = 10     # the check's refits resample episodes: fewer cannot bound the fit's error


def resampled(data: fitting.FitData, counts: np.ndarray) -> fitting.FitData:
    """`data` with episode e taken counts[e] times (each copy its own episode, its segments
    in order): a bootstrap resample as its own recordings, for a refit that runs the cell's
    whole fit on it (starts from the base included)."""
    order = np.argsort(data.seg_episode, kind='stable')
    by_episode = np.split(order, np.cumsum(np.bincount(data.seg_episode,
                                                       minlength=len(data.episodes)))[:-1])
    segments, episode, names = [], [], []
    for e, count in enumerate(np.asarray(counts, dtype=int)):
        for copy_ in range(count):
            segments += list(by_episode[e])
            episode += [len(names)] * len(by_episode[e])
            names.append(f'{data.episodes[e]}#{copy_}')
    starts, stops = data.seg_start[:-1][segments], data.seg_start[1:][segments]
    rows = np.concatenate([np.arange(a, b) for a, b in zip(starts, stops)])
    return fitting.FitData(
        group=np.ascontiguousarray(data.group[rows]), observation=data.observation[rows],
        answer=data.answer[rows], move=np.ascontiguousarray(data.move[rows]),
        has_move=data.has_move[rows], unique_delta=np.ascontiguousarray(data.unique_delta[rows]),
        seg_start=np.concatenate([[0], np.cumsum(stops - starts)]).astype(np.int64),
        seg_episode=np.asarray(episode, dtype=np.int64), episodes=names, issues=[],
        rows_read=int(rows.size), seg_true_start=data.true_starts[segments])


def refit_data(data: fitting.FitData, seed) -> fitting.FitData:
    """The recordings of one refit: a resample of the episodes, with replacement
    (`bootstrap_counts`, from its own seed)."""
    return resampled(data, bootstrap_counts(len(data.episodes), seed))


def refit(data: dict, point: fitting.FitResult, summary: dict, mdp: dict, base: Config,
          fit_settings: dict, pomdp_settings: dict | None, seed: int, draw: int,
          max_memory_mb: int | None) -> tuple[Config, object, object, bool]:
    """One refit of the check (check.py): the episodes resampled (seed [seed, 4, draw]),
    fitted as the cell's fit fits them (`fit_point`'s settings: from the base, its starts),
    solved as `solve_mdp` solves (value iteration started from the fit's values: the same
    fixed point, in fewer sweeps) and, for the pomdp and fib selectors, as `solve_pomdp`. The
    fitted stream (fit.stream) is the cell's, not refitted. (configuration, MDP policy,
    POMDP policy or None, whether EM converged)."""
    from ..mdp.solver import value_iteration
    recordings = refit_data(data['all'], [seed, 4, draw])
    try:
        result = fitting.fit(recordings, base, fit_settings['hold'],
                             n_init=fit_settings['starts'], seed=seed,
                             tol=fit_settings['tol'], max_iter=fit_settings['max_iter'],
                             bootstrap=0, prior=fit_settings.get('prior', False))
        stream = summary['config'].data.get('stream') if summary['stream'] else None
        config = Config(_with_stream(fitting.fitted_data(result, base), stream),
                        source=f'refit {draw}')
    except (fitting.FitError, ConfigError) as exc:
        raise CellError(f'refit {draw}: {exc}') from None
    model = HRCModel(config)
    check_memory(model, max_memory_mb, 'the MDP solve')
    policy = value_iteration(model, start=mdp['result'].value)
    pomdp = None
    if pomdp_settings is not None:
        pomdp = solve_pomdp({'config': config}, pomdp_settings, seed, max_memory_mb
                            )[1]['policy']
    return config, policy, pomdp, bool(result.converged)


def _refit_figures(inside: tuple, fitted: tuple) -> list[float]:
    """[the refit's paired mean in its own world, the same in the cell's fitted world, the
    episodes' variance of their difference]: both over the same seeded episodes, so the
    difference's noise is the variance of the per-episode differences over n."""
    d_in, d_out = inside[0] - inside[1], fitted[0] - fitted[1]
    both = d_in - d_out
    both = both[np.isfinite(both)]
    noise = float(np.var(both, ddof=1) / both.size) if both.size > 1 else 0.0
    return [float(np.mean(d_in)), float(np.mean(d_out)), noise]


def refits(running: dict, data: dict, point: fitting.FitResult, summary: dict, mdp: dict,
           base: Config, selector: str, fit_settings: dict, pomdp_settings: dict | None,
           settings: dict, seed: int, max_memory_mb: int | None, draws
           ) -> tuple[dict, None]:
    """The check's refits `draws` (check.py): per refit b, each metric's paired difference
    new - running of the refit's policy against the running pair in the refit's own fitted
    world and in the cell's fitted world, over the same `settings['episodes']` seeded episodes
    (seed + 1 + b), and the episodes' variance of their difference. Its error e*_b is the
    first minus the second."""
    t0 = time.perf_counter()
    rows = []
    for b in draws:
        config, policy, pomdp, converged = refit(data, point, summary, mdp, base, fit_settings,
                                                 pomdp_settings, seed, b, max_memory_mb)
        inside = _both_in(config, running, config, policy, pomdp, selector, settings,
                          seed + 1 + b)
        fitted = _both_in(summary['config'], running, config, policy, pomdp, selector,
                          settings, seed + 1 + b)
        rows.append({'draw': b, 'converged': converged,
                     **{m: _refit_figures(inside[m], fitted[m]) for m in CHECK_METRICS}})
    return {'rows': rows, 'seconds': _seconds(t0)}, None


def _with_stream(data: dict, stream: dict | None) -> dict:
    """A configuration's data with the fitted `stream` section, if there is one."""
    if stream is not None:
        data['stream'] = copy.deepcopy(stream)
    return data


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
        if summary.get('stream') is not None:      # as hrc-fit --stream reports it
            fit_report['stream'] = summary['stream'].report()
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
                                  bootstrap, fit_summary, solve_mdp, solve_pomdp, shadow, refits,
                                  outputs)}
