"""hrc-fleet: learn, re-solve and promote every cell of a plant on Ray (docs/FLEET.md).

    hrc-fleet run PLANT.yaml [--out DIR] [--address ADDR] [--apply]

Per cell (core.plant): read its recordings, test them for drift against the running model,
and where drift is found (or `run: always`) fit, solve, check the new policy against the
running one in the cell as now fitted (paired episodes) and decide: promote, keep or failed.
Writes DIR/cells/<cell>/ (fitted.yaml and its report, policy.npz, pomdp.npz, cell_report.json,
plots) and DIR/plant_report.md, DIR/plant_report.json, DIR/plant_costs.png, each file whole or
not at all. `--apply` then swaps each promoted cell's policy live through its decision node's
parameters in its namespace and checks that the node reports it (hrc_ros.ros.fleet_apply).

Engine: without --address an embedded Ray on this machine (`--num-cpus`, `--object-store-mb`;
no dashboard), stopped at the end; `--address auto` or `ray://host:port` joins an existing
cluster. `--serial` runs the same stages one after the other in this process, without Ray.
The stages are Ray tasks: arrays go between them through Ray's object store, the recordings
are read on this machine's node and the files written by this process, so the workers share
no disk. A task whose worker dies is retried (`retries`, Ray's max_retries); a cell whose
stage fails is reported with the reason and the others go on.

Exit status: 0 when every cell was decided (promote or keep) and, with --apply, every swap
verified; 1 when a cell failed or a swap did not happen (the reports say which and why); 2 when
the plant file or the arguments are refused, before any work.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections import deque
from contextlib import nullcontext
from datetime import datetime, timezone
from pathlib import Path

from ..core.config import ConfigError, load_config
from ..core.mdp.policy import PolicyError, default_policy_path, load_policy
from ..core.paths import replace_file
from ..core.plant import report as reporting
from ..core.plant.pipeline import DRIVER, DRIVER_NODE, CellPipeline, Ref, run_serially, run_stage
from ..core.plant.spec import POMDP_SELECTORS, Plant, PlantError, load_plant
from . import fleet_ray
from .common import (Parser, ToolError, bounded_int, command, fail, output_folder,
                     path_text)

PROGRESS_WIDTH = 110
STARTS = 3          # attempts at starting the embedded Ray (its raylet's start-up can time out)


# -- preparing the cells ----------------------------------------------------------------------
def prepare(plant: Plant, out: Path) -> tuple[list[CellPipeline], dict]:
    """A pipeline per cell and the plant objects its stages read (each cell's base
    configuration and running policy, loaded once here); a cell whose files do not load
    starts failed, with the reason."""
    pipelines, objects, loaded = [], {}, {}

    def once(key, make, *args, **kwargs):   # cells on one file share one object
        if key not in loaded:
            loaded[key] = make(*args, **kwargs)
        return loaded[key]

    for spec in plant.cells:
        folder = out / 'cells' / spec.name
        cache = (None if spec.generate is None else
                 str(out / 'cache' / f'{spec.name}-{spec.generate_key()}.csv'))
        error = None
        rho = sigma = 0
        try:
            base = once(('config', spec.base), load_config, spec.base)
            rho, sigma = base.rho, base.sigma
            policy_path = str(spec.policy or default_policy_path(base))
            policy = once(('policy', spec.base, policy_path), load_policy, policy_path, base)
            pomdp = None
            if spec.selector in POMDP_SELECTORS:
                from ..core.pomdp.policy import load_pomdp_policy, pomdp_policy_path
                pomdp_path = str(pomdp_policy_path(spec.pomdp_policy, base))
                pomdp = once(('pomdp', spec.base, pomdp_path), load_pomdp_policy, pomdp_path,
                             base)
            objects[f'@base:{spec.name}'] = base
            objects[f'@policy:{spec.name}'] = policy
            objects[f'@running:{spec.name}'] = once(
                ('running', spec.base, policy_path, pomdp and pomdp.path), dict, config=base,
                policy=policy, pomdp=pomdp)
            missing = [p for p in spec.recordings if not Path(p).exists()]
            if missing:
                error = f'recordings: {missing[0]} does not exist'
        except ConfigError as exc:
            error = f'base configuration: {exc}'
        except PolicyError as exc:
            error = f'running policy: {exc}'
        pipelines.append(CellPipeline(spec, str(folder), cache, bool(cache and
                                                                     Path(cache).is_file()),
                                      error, rho, sigma))
    return pipelines, objects


# -- progress ---------------------------------------------------------------------------------
class Progress:
    """A bar over the cells and each running cell's stage on stderr: one line redrawn on a
    terminal, a line per change of stage otherwise (logs, CI)."""

    def __init__(self, stream=None, quiet: bool = False):
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, 'isatty', lambda: False)())
        self.quiet = quiet
        self.seen: dict = {}
        self.t0 = time.perf_counter()

    def __call__(self, pipelines) -> None:
        if self.quiet:
            return
        done = sum(p.finished for p in pipelines)
        if self.tty:
            width = 20
            filled = int(width * done / max(1, len(pipelines)))
            running = '; '.join(f'{p.spec.name}: {p.stage}' for p in pipelines
                                if not p.finished and p.stage != 'waiting')
            line = (f'hrc-fleet [{"#" * filled}{"." * (width - filled)}] {done}/'
                    f'{len(pipelines)} cells {time.perf_counter() - self.t0:5.0f} s | {running}')
            self.stream.write('\r' + line[:PROGRESS_WIDTH].ljust(PROGRESS_WIDTH))
            self.stream.flush()
            return
        for p in pipelines:
            if self.seen.get(p.spec.name) != p.stage:
                self.seen[p.spec.name] = p.stage
                self.stream.write(f'hrc-fleet: [{done}/{len(pipelines)}] {p.spec.name}: '
                                  f'{p.stage}\n')
        self.stream.flush()

    def close(self) -> None:
        if self.tty and not self.quiet:
            self.stream.write('\n')
            self.stream.flush()


class Interruptible:
    """Ctrl-C (SIGINT) while the plant runs on Ray, taken as a flag and raised as
    KeyboardInterrupt by `check` between Ray calls: raised inside one (ray.wait, ray.get) it
    left the driver's core worker half way through a call, and the process died with SIGSEGV
    after Ray's shutdown in one run in two. Outside the main thread (a test's runner) nothing
    changes."""

    def __enter__(self):
        import signal
        import threading
        self.hit, self.previous = False, None
        if threading.current_thread() is threading.main_thread():
            self.previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def _handler(self, signum, frame):
        self.hit = True

    def check(self) -> None:
        if self.hit:
            raise KeyboardInterrupt

    def __exit__(self, *exc):
        import signal
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
        return False


# -- Ray --------------------------------------------------------------------------------------
_REMOTE = None


def _remote_stage():
    """The one Ray task every stage runs in (made on first use: no Ray import before)."""
    global _REMOTE
    if _REMOTE is None:
        import ray

        @ray.remote(num_returns=2)
        def stage_task(stage, hook, run, cell, key, *args):
            _threads_as_assigned(ray)
            fleet_ray.record_attempt(ray, run, cell, key)
            if hook is not None:
                hook(stage, cell)
            return run_stage(stage, *args)
        _REMOTE = stage_task
    return _REMOTE


def _threads_as_assigned(ray) -> None:
    """numba's parallel kernels (the solves) on the CPUs Ray gave the task, not on every core
    of the node: two tasks on two CPUs must not run four threads."""
    from ..core import parallel
    parallel.limit_threads(int(ray.get_runtime_context().get_assigned_resources().get('CPU', 1)))


def _died(exc: Exception, stage: str, retries: int) -> str:
    name = type(exc).__name__
    text = ' '.join(str(exc).split())[:300]
    return (f'{stage}: the task failed in Ray after {retries} retries ({name}: {text})')


def run_on_ray(pipelines: list[CellPipeline], objects: dict, progress=None, hook=None,
               client: bool = False, interrupt: 'Interruptible | None' = None) -> dict:
    """Run every cell's stages as Ray tasks (module docstring); returns when all are done,
    with what Ray had to redo: {'retries': (cell, key) -> the attempts' pids and nodes,
    'lost_nodes': [...], 'nodes': the nodes at the start}."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    remote = _remote_stage()
    here = None if client else NodeAffinitySchedulingStrategy(
        ray.get_runtime_context().get_node_id(), soft=False)
    refs: dict = {}
    shared: dict = {}
    for key, value in objects.items():   # one object per distinct configuration or policy
        refs[key] = shared.setdefault(id(value), ray.put(value))
    pending: dict = {}
    local: deque = deque()
    run = f'{os.getpid()}-{time.time_ns()}'     # this run's keys of the attempts
    nodes = fleet_ray.LostNodes(ray)

    def payload_of(job) -> tuple:
        return tuple(refs[a.key if a.key.startswith('@') else (job.cell, a.key)]
                     if isinstance(a, Ref) else a for a in job.args)

    def submit(pipeline, jobs) -> None:
        for job in jobs:
            if job.where == DRIVER or (job.where == DRIVER_NODE and client):
                local.append((pipeline, job))
                continue
            options = {'max_retries': job.retries, 'retry_exceptions': False}
            if job.where == DRIVER_NODE:
                options['scheduling_strategy'] = here
            status, payload = remote.options(**options).remote(
                job.stage, hook, run, job.cell, job.key, *payload_of(job))
            refs[(job.cell, job.key)] = payload
            pending[status] = (pipeline, job)
        if pipeline.finished:     # free what its stages left in the object store
            for key in [k for k in refs if isinstance(k, tuple) and k[0] == pipeline.spec.name]:
                del refs[key]

    for pipeline in pipelines:
        submit(pipeline, pipeline.start())
    with nullcontext(interrupt) if interrupt else Interruptible() as interrupt:
        while pending or local:
            interrupt.check()
            nodes.poll()
            while local:
                pipeline, job = local.popleft()
                args = tuple(ray.get(a) if isinstance(a, ray.ObjectRef) else a
                             for a in payload_of(job))
                facts, payload = run_stage(job.stage, *args)
                refs[(job.cell, job.key)] = ray.put(payload)
                submit(pipeline, pipeline.done(job.key, facts))
                if progress:
                    progress(pipelines)
            if not pending:
                continue
            ready, waiting = ray.wait(list(pending), num_returns=1, timeout=0.5)
            if ready and waiting:         # and whatever else finished meanwhile
                ready += ray.wait(waiting, num_returns=len(waiting), timeout=0)[0]
            for status in ready:
                pipeline, job = pending.pop(status)
                try:
                    facts = ray.get(status)
                except ray.exceptions.RayError as exc:
                    facts = {'error': _died(exc, job.stage, job.retries)}
                submit(pipeline, pipeline.done(job.key, facts))
            if progress:
                progress(pipelines)
    nodes.poll(force=True)
    return {'retries': fleet_ray.attempts(run), 'lost_nodes': nodes.lost, 'nodes': nodes}


def start_ray(address: str | None, num_cpus: int | None, object_store_mb: int | None,
              checked: bool = False):
    """(started here, client mode): join `address` (checked first unless `checked`:
    `fleet_ray.check_address`, one line naming it and the cause), or start an embedded Ray;
    nothing when this process already has one (a test session, a notebook)."""
    import ray
    if ray.is_initialized():
        return False, False
    os.environ.setdefault('RAY_DEDUP_LOGS', '0')
    if address:     # an existing cluster keeps its own resources and dashboard
        target = address if checked else fleet_ray.check_address(address)
        try:
            ray.init(address=address, logging_level='warning')
        except Exception as exc:   # noqa: BLE001 - Ray's own errors (AuthenticationError,
            # RpcError) are RayError(Exception), beside ConnectionError and RuntimeError
            raise ToolError(f'cannot join the Ray cluster at {address} ({target}): '
                            f'{type(exc).__name__}: '
                            f'{" ".join(str(exc).split())[:300]}') from None
        return True, address.startswith('ray://')
    for attempt in range(STARTS):
        try:
            ray.init(num_cpus=num_cpus, include_dashboard=False, logging_level='warning',
                     object_store_memory=None if object_store_mb is None
                     else object_store_mb * 2 ** 20)
            return True, False
        except Exception as exc:   # noqa: BLE001 - Ray raises a bare Exception for this
            # Ray gives its raylet 30 s to come up; a machine loaded enough can take longer
            ray.shutdown()
            if 'timed out during startup' not in str(exc) or attempt == STARTS - 1:
                raise ToolError(f'cannot start Ray on this machine: '
                                f'{" ".join(str(exc).split())[:300]}') from None
    raise AssertionError('unreachable')


# -- the plant report -------------------------------------------------------------------------
def plant_report(plant: Plant, pipelines, started: str, seconds: float, engine: str) -> dict:
    entries = [p.entry for p in pipelines]
    decisions = {d: sum(e['decision'] == d for e in entries) for d in ('promote', 'keep',
                                                                        'failed')}
    return {'plant': plant.name, 'source': plant.source, 'started': started,
            'seconds': round(seconds, 2), 'engine': engine, 'decisions': decisions,
            'cells': entries}


def write_report(out: Path, report: dict) -> list[Path]:
    text = json.dumps(report, indent=2, default=float) + '\n'
    written = []
    costs = out / 'plant_costs.png'
    replace_file(costs, lambda t: t.write_bytes(reporting.plot_bytes(report['cells'])))
    written.append(costs)
    for name, body in (('plant_report.json', text),
                       ('plant_report.md', reporting.markdown(report))):
        replace_file(out / name, lambda t, b=body: t.write_text(b))
        written.append(out / name)
    return written


RAY_LOG = 'ray.log'


def _run_on_own_ray(pipelines, objects, out: Path, address, num_cpus, object_store_mb,
                    progress, hook) -> tuple[dict, str]:
    """The plant on a Ray this run starts or joins (or the one this process has): the
    address checked before OUT is made, Ray's output into OUT/ray.log, Ctrl-C taken between
    Ray calls, and an embedded cluster stopped whole (fleet_ray). (what Ray redid, engine)."""
    import ray
    if ray.is_initialized():           # a test session, a notebook: its Ray and its output
        output_folder(out)
        done = run_on_ray(pipelines, objects, progress, hook, False)
        return done, _engine(ray, address)
    if address:
        fleet_ray.check_address(address)        # one line and nothing made when it fails
    created = not out.exists()
    output_folder(out)
    embedded = fleet_ray.EmbeddedProcesses()
    stream = getattr(progress, 'stream', None)
    mine = False
    try:
        with Interruptible() as interrupt, fleet_ray.RayLog(out / RAY_LOG) as output:
            if stream is not None:
                progress.stream = output.terminal
            try:
                mine, client = start_ray(address, num_cpus, object_store_mb, checked=True)
                embedded.add()
                interrupt.check()
                return (run_on_ray(pipelines, objects, progress, hook, client, interrupt),
                        _engine(ray, address))
            finally:
                if mine:
                    embedded.add()          # the workers started since
                    ray.shutdown()
                    embedded.stop()
                if stream is not None:
                    progress.stream = stream
    except ToolError:
        if not mine:        # Ray could not be started or joined: leave nothing behind
            _remove_made(out, created)
        raise


def _engine(ray, address) -> str:
    cpus = int(ray.cluster_resources().get('CPU', 0))
    return f'Ray {ray.__version__} ({address or "embedded"}, {cpus} CPUs)'


def _remove_made(out: Path, created: bool) -> None:
    """What this run made in OUT before it found it could not work: its Ray log, and OUT
    itself if it made it and nothing else is in it."""
    try:
        (out / RAY_LOG).unlink(missing_ok=True)
        if created:
            out.rmdir()
    except OSError:
        pass


def _redone(report: dict, done: dict) -> None:
    """What Ray had to redo, into the report: per cell the stage tasks it ran more than once
    (`retries`, with the workers they ran on), and the nodes lost during the run."""
    nodes = done.get('nodes')
    for entry in report['cells']:
        entry['retries'] = [
            {'stage': key, 'attempts': len(seen),
             'workers': [{'pid': s['pid'], 'node': nodes.address(s['node']) if nodes else
                          s['node']} for s in seen]}
            for (cell, key), seen in sorted(done.get('retries', {}).items())
            if cell == entry['cell']]
    report['lost_nodes'] = done.get('lost_nodes', [])
    report['retried_tasks'] = sum(len(e['retries']) for e in report['cells'])


def run_plant(plant: Plant, out: Path, address: str | None = None, serial: bool = False,
              apply: bool = False, num_cpus: int | None = None,
              object_store_mb: int | None = None, hook=None, progress=None,
              apply_timeout: float = 30.0) -> dict:
    """Run the plant into `out` (made once the engine is up: a cluster that cannot be joined
    leaves none) and return the plant report (written there too)."""
    started = datetime.now(timezone.utc).isoformat(timespec='seconds')
    t0 = time.perf_counter()
    out = Path(out)
    pipelines, objects = prepare(plant, out)
    progress = progress or Progress()
    if serial:
        output_folder(out)
        engine, done = reporting.SERIAL_ENGINE, {}
        run_serially(pipelines, objects, progress)
    else:
        done, engine = _run_on_own_ray(pipelines, objects, out, address, num_cpus,
                                       object_store_mb, progress, hook)
    progress.close()
    report = plant_report(plant, pipelines, started, time.perf_counter() - t0, engine)
    _redone(report, done)
    if apply:
        from ..ros.fleet_apply import apply_promoted
        results = apply_promoted(report['cells'], timeout=apply_timeout)
        for entry in report['cells']:
            if entry['cell'] in results:
                entry['applied'] = results[entry['cell']]
    write_report(out, report)
    return report


@command('hrc-fleet')
def main(argv=None) -> int:
    parser = Parser(prog='hrc-fleet', description=__doc__.split('\n')[0].split(': ', 1)[1])
    commands = parser.add_subparsers(dest='command', required=True, parser_class=Parser)
    run = commands.add_parser('run', help='run the plant: every cell, then the plant report')
    run.add_argument('plant', help='the plant file (YAML; docs/FLEET.md)')
    run.add_argument('--out', default='out/fleet', type=path_text,
                     help='output folder (default out/fleet)')
    run.add_argument('--address', default=None,
                     help="an existing Ray cluster: 'auto' or ray://host:port (default: an "
                          'embedded Ray on this machine)')
    run.add_argument('--apply', action='store_true',
                     help="swap each promoted cell's policy live in its namespace (ROS 2)")
    run.add_argument('--serial', action='store_true',
                     help='run the stages one after the other in this process, without Ray')
    run.add_argument('--num-cpus', type=bounded_int(1, 4096), default=None,
                     help='embedded Ray: CPUs to use (default: all)')
    run.add_argument('--object-store-mb', type=bounded_int(64, 10 ** 7), default=None,
                     help="embedded Ray: object store size (default: Ray's)")
    run.add_argument('--apply-timeout', type=bounded_int(1, 3600), default=30,
                     help='--apply: seconds to wait for a node to report the new policy')
    run.add_argument('-q', '--quiet', action='store_true', help='no progress on stderr')
    args = parser.parse_args(argv)
    if args.serial and args.address:
        parser.error('--serial runs without Ray; leave out --address')
    try:
        plant = load_plant(args.plant)
        out = output_folder(args.out, make=False)  # made once the engine is up (run_plant)
    except (PlantError, ToolError) as exc:
        return fail('hrc-fleet', exc)
    try:
        report = run_plant(plant, out, args.address, args.serial, args.apply, args.num_cpus,
                           args.object_store_mb, progress=Progress(quiet=args.quiet),
                           apply_timeout=float(args.apply_timeout))
    except ToolError as exc:
        return fail('hrc-fleet', exc)
    for entry in report['cells']:
        applied = entry.get('applied')
        print(f'{entry["cell"]}: {entry["decision"]}: {entry["reason"]}'
              + (f' [apply: {applied["status"]}: {applied["detail"]}]' if applied else ''))
    print(f'wrote {out / "plant_report.md"} and {out / "plant_report.json"} '
          f'({report["seconds"]:.1f} s on {report["engine"]})')
    unapplied = any(e.get('applied', {}).get('status') not in (None, 'swapped')
                    for e in report['cells'])
    return 1 if report['decisions']['failed'] or unapplied else 0


if __name__ == '__main__':
    sys.exit(main())
