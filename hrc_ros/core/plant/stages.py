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
    read           recordings -> the fit's arrays: all of them, the drift window, two halves
    drift_observed the likelihood ratio of the window against the running model (drift.py)
    drift_null     the same statistic on recordings simulated under the running model
    fit_point      EM from the running configuration (core.learning.fit)
    bootstrap      resamples of the episodes, refitted (a chunk of them per call)
    fit_summary    intervals, the fitted configuration and what moved
    solve_mdp      value iteration of the fitted configuration
    solve_pomdp    the POMDP over the belief (solver pomdp or both)
    fold           one half of the recordings fitted and solved (bootstrap-free)
    shadow         both policies in the world fitted from all recordings (in-sample figures)
    heldout        the promotion rule's figures: each half's policy and the running one in
                   the world fitted from the other half, paired episodes
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


def halves(recordings: list[Recording]) -> tuple[list[Recording], list[Recording]]:
    """The earlier and the later half of the recordings' epochs, in time order (the episode
    in the middle is cut there): the two folds of the held-out shadow check."""
    total = sum(len(r) for r in recordings)
    return span(recordings, 0, total - total // 2), span(recordings, total - total // 2, total)


def read(paths, rho: int, sigma: int, namespace: str, window: int,
         fit_window: int | None = None, stream_base: Config | None = None,
         prior: bool = False) -> tuple[dict, dict]:
    """The recordings as the fit's arrays: 'all' (or the last `fit_window` epochs) for the
    fit and 'window', the last `window` epochs, for the drift test. A bag holding several
    cells is read at the cell's namespace; a corrupt or unreadable recording fails the cell
    (a fit on what happened to be readable would hide it). With `stream_base` (the base of a
    cell with fit.stream) also 'recordings', the fit's recordings themselves, which the
    stream is counted from (the halves' are cut from them where needed, not kept twice),
    checked as hrc-fit --stream checks them before any work (`stream.check_stream`). With
    `prior` (fit.prior) each half must hold an episode that starts at epoch 1, since the
    held-out check fits the prior on each half (checked here, before any work)."""
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
        folds = tuple(fitting.prepare(h) for h in halves(used))
    except (RecordingError, fitting.FitError) as exc:
        raise CellError(f'recordings: {" ".join(str(exc).split())}') from None
    if prior:
        for which, f in zip(HALVES, folds):
            if not f.true_starts.any():
                raise CellError(f'fit.prior: no episode in {which} of the recordings starts '
                                f'at epoch {fitting.FIRST_EPOCH}, and the held-out check fits '
                                'the person prior on each half; record the runs from their '
                                'start (more episodes), or set fit.prior: false')
    if stream_base is not None:
        try:
            check_stream(used, stream_base)
        except StreamError as exc:
            raise CellError(f'fit.stream: {exc}') from None
    facts = {'files': [str(f) for f in files], 'epochs': data.epochs,
             'episodes': len(data.episodes), 'window_epochs': recent.epochs,
             'halves': [f.epochs for f in folds],
             'issues': len(data.issues), 'first_issues': data.issues[:5],
             'seconds': _seconds(t0)}
    payload = {'all': data, 'window': recent, 'halves': folds}
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
HALVES = ('the earlier half', 'the later half')
IN_SAMPLE_WORLD = ('fitted from all the recordings, the ones the new policy was solved from '
                   '(optimistic for it: not used to decide)')


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
    return {metric: (getattr(new, metric).astype(float), getattr(old, metric).astype(float))
            for metric in SHADOW_METRICS}


def shadow(running: dict, summary: dict, mdp: dict, pomdp: dict | None, selector: str,
           settings: dict, seed: int) -> tuple[dict, dict]:
    """The in-sample figures: the running pair and the new one (fitted from all the
    recordings, its policy) in the world fitted from those same recordings. Reported beside
    the held-out check (`heldout`), which decides: here the new policy is scored in the
    world it was planned for."""
    t0 = time.perf_counter()
    runs = _both_in(summary['config'], running, summary['config'], mdp['result'],
                    None if pomdp is None else pomdp['policy'], selector, settings, seed)
    facts = {metric: paired(*runs[metric]) for metric in SHADOW_METRICS}
    facts.update(world=IN_SAMPLE_WORLD, episodes=settings['episodes'],
                 epochs=settings['epochs'], seed=seed, selector=selector,
                 seconds=_seconds(t0))
    cost = runs['discounted_cost']
    return facts, {'difference': cost[0] - cost[1]}


def fold(data: dict, half: int, base: Config, fit_settings: dict, seed: int,
         max_memory_mb: int | None, pomdp_settings: dict | None, worlds: int
         ) -> tuple[dict, dict]:
    """One half of the recordings (`read`'s 'halves'): fitted as `fit_point` fits and solved
    as `solve_mdp` (and, for the pomdp and fib selectors, as `solve_pomdp`) solves, the
    candidate of this fold; and `worlds` bootstrap resamples of the half's episodes refitted
    from its estimate (as `bootstrap` refits, seeds [seed, 3 + half, b]), the worlds the other
    fold's candidate is evaluated in: what the people of this half may be, given its epochs.
    The model is the cell's fit's (`fit.prior`: with the person prior, each world's the
    resample's; `fit.stream`: with the stream counted from this half's recordings, the same
    in every world: the bootstrap refits the EM's parameters only)."""
    t0 = time.perf_counter()
    which = HALVES[half]
    half_data = {'all': data['halves'][half]}
    if fit_settings.get('stream'):
        half_data['recordings'] = halves(data['recordings'])[half]
    try:
        point_facts, point = fit_point(half_data, base, fit_settings, seed)
        _, summary = fit_summary(point, base, [f'{which} of the recordings'], half_data,
                                 fit_settings, seed)
        _, mdp = solve_mdp(summary, max_memory_mb)
        pomdp = (None if pomdp_settings is None else
                 solve_pomdp(summary, pomdp_settings, seed, max_memory_mb)[1]['policy'])
        draws = resample_fits(half_data['all'], point, fit_settings,
                              [[seed, 3 + half, b] for b in range(worlds)])   # none for 0
        stream = summary['config'].data.get('stream') if summary['stream'] else None
        resampled = [Config(_with_stream(fitting.fitted_data(replace(point, params=params),
                                                             base), stream),
                            source=f'{which}, bootstrap world {b}')
                     for b, params in enumerate(draws)]
    except (CellError, ConfigError) as exc:
        raise CellError(f'{which} of the recordings: {exc}') from None
    facts = {'half': which, 'epochs': point.epochs, 'episodes': point.episodes,
             'iterations': point_facts['iterations'], 'loglik': point_facts['loglik'],
             'worlds': worlds, 'config_sha256': summary['config'].policy_hash,
             'seconds': _seconds(t0)}
    return facts, {'config': summary['config'], 'policy': mdp['result'], 'pomdp': pomdp,
                   'worlds': resampled}


def _with_stream(data: dict, stream: dict | None) -> dict:
    """A configuration's data with the fitted `stream` section, if there is one."""
    if stream is not None:
        data['stream'] = copy.deepcopy(stream)
    return data


def clustered(new: list, running: list) -> dict:
    """Mean of new - running over the episodes of K worlds (lists of per-episode arrays, the
    same episodes for both), its 95% interval by the worlds' means: mean +- t(0.975, K - 1)
    sd / sqrt(K), so that what the worlds disagree on is in the interval, not only the
    episodes' noise."""
    from scipy.stats import t as student
    means = np.array([np.mean(n - r) for n, r in zip(new, running)])
    k = len(means)
    mean = float(means.mean())
    half = float(student.ppf(0.975, k - 1) * means.std(ddof=1) / math.sqrt(k))
    return {'mean': mean, 'half_width': half, 'low': mean - half, 'high': mean + half,
            'worlds': k, 'new': float(np.mean([np.mean(n) for n in new])),
            'running': float(np.mean([np.mean(r) for r in running]))}


def _difference(new: list, running: list) -> dict:
    """`paired` over one world's episodes, `clustered` over several worlds'."""
    if len(new) == 1:
        return {**paired(new[0], running[0]), 'worlds': 1}
    return clustered(new, running)


def heldout(running: dict, first: dict, second: dict, selector: str, settings: dict,
            seed: int) -> tuple[dict, dict]:
    """The held-out shadow check (docs/FLEET.md): the candidate fitted and solved from one
    half of the recordings and the running pair, paired, in each bootstrap world of the
    other half (with `evaluate.worlds: 0`, in the other half's fit alone), then the roles
    swapped. World k of both folds gets the same ceil(episodes / worlds) seeded episodes
    (seed + 1 + k); per world the two folds' differences are averaged episode by episode,
    and the interval is over the worlds (`clustered`; over the episodes for one world).
    Neither candidate is ever scored in a world fitted from its own epochs."""
    t0 = time.perf_counter()
    worlds = [fold['worlds'] or [fold['config']] for fold in (first, second)]
    k = len(worlds[0])
    each = dict(settings, episodes=math.ceil(settings['episodes'] / k))
    folds, runs = [], []
    for candidate, other, fitted, evaluated in ((first, worlds[1], 0, 1),
                                                (second, worlds[0], 1, 0)):
        per_world = [_both_in(world, running, candidate['config'], candidate['policy'],
                              candidate['pomdp'], selector, each, seed + 1 + w)
                     for w, world in enumerate(other)]
        runs.append(per_world)
        folds.append({'policy_fitted_from': HALVES[fitted],
                      'world_fitted_from': HALVES[evaluated],
                      **{metric: _difference([r[metric][0] for r in per_world],
                                             [r[metric][1] for r in per_world])
                         for metric in SHADOW_METRICS}})
    facts = {metric: _difference([(a[metric][0] + b[metric][0]) / 2 for a, b in zip(*runs)],
                                 [(a[metric][1] + b[metric][1]) / 2 for a, b in zip(*runs)])
             for metric in SHADOW_METRICS}
    where = (f'{k} bootstrap worlds of the other half, the interval over the worlds' if k > 1
             else 'the world fitted from the other half, the interval over the episodes')
    facts.update(world=(f'held out: each half\'s candidate in {where}; the two folds '
                        'averaged per episode'), folds=folds, episodes=each['episodes'] * k,
                 epochs=settings['epochs'], seed=seed, selector=selector, worlds=k,
                 seconds=_seconds(t0))
    difference = np.concatenate([(a['discounted_cost'][0] - a['discounted_cost'][1]
                                  + b['discounted_cost'][0] - b['discounted_cost'][1]) / 2
                                 for a, b in zip(*runs)])
    return facts, {'difference': difference}


# -- outputs ----------------------------------------------------------------------------------
def outputs(report: dict, summary: dict | None, mdp: dict | None, pomdp: dict | None,
            shadow_payload: dict | None, heldout_payload: dict | None) -> tuple[dict, dict]:
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
    if heldout_payload is not None:
        files['shadow.png'] = reporting.figure_bytes(reporting.plot_shadow, report,
                                                     heldout_payload['difference'],
                                                     shadow_payload['difference'])
    files['cell_report.json'] = (json.dumps(report, indent=2, default=float) + '\n').encode()
    return {'files': sorted(files), 'seconds': _seconds(t0)}, files


STAGES = {f.__name__: f for f in (generate, read, drift_observed, drift_null, fit_point,
                                  bootstrap, fit_summary, solve_mdp, solve_pomdp, shadow, fold,
                                  heldout, outputs)}
