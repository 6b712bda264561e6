"""hrc-fit: learn the cell's model from its recordings (core.learning.fit; docs/LEARNING.md).

    hrc-fit INPUT... -o OUT.yaml [--base CONFIG] [--hold FAMILY,...] [--bootstrap 200] [--plot]
            [--stream] [--prior]

INPUT: bag folders, .mcap files (recorded from the node suite) or trajectory .csv files.
Writes OUT.yaml, a complete configuration (the base's with the fitted families), and
OUT.report.json; prints the report: every parameter with its bootstrap 95% interval and its
support, the log likelihood at every 10th iteration and the last (the JSON report has every
iteration), the epochs used and the warnings. `--stream` also counts the task stream's
arrivals (MODEL.md 8, core.learning.stream) and writes them as OUT.yaml's `stream` section;
on a base with `stream.queue` (MODEL.md 8.1) it counts the releases from the tasks waiting per
epoch (`queued`: the task state's ninth value, a CSV's queued column) and writes arrival_idle,
arrival_busy and q with the base's queue and waiting_cost; recordings without `queued` are
refused in one line.
`--prior` also fits the person prior, the distribution of h = 3*em + ea where an episode starts
(MODEL.md 6.1), from the episodes recorded from epoch 1, and writes it as `observation.prior`.
`--rate` also counts the robot's progress rate by task nature and band (MODEL.md 3.2,
core.learning.rate) and writes it as `model.robot_rate`.

The recordings are read with the base configuration's rules (its robot_paused_by,
retreat_reach, approach_reach; with a robot_rate or `--rate` a working robot's counter may
stay): a recording of the cell with the arm, read with the paper's rules, would show a retreat
that gained nothing as the person stepping closer and a program cycle that SSM slowed as a
task state that cannot follow.

Refused in one line before any work: an output (-o, --report, --plot) that is an input, lies
in an input bag folder, is the base configuration or is another output. Output folders are
made only once the inputs have been read. OUT.yaml is written to a temporary file beside it,
loaded back with load_config and only then renamed over OUT.yaml, so a failed run leaves no
half-written or invalid OUT.yaml (an older one stays as it was).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from ..core.config import ConfigError, load_config
from ..core.learning.fit import (BOOTSTRAP, DEFAULT_METHOD, FAMILIES, MAX_ITER, MIN_SUPPORT,
                                 NEWTON, SQUAREM, TOL, FitError, config_yaml, expand_hold, fit,
                                 prepare, report_dict, report_text)
from ..core.paths import default_config_path, output_target, replace_file
from ..core.learning.rate import fit_rate
from ..core.learning.recordings import RecordingError, read_recordings
from ..core.model import HRCModel
from ..core.learning.stream import StreamError, check_stream, fit_stream_for
from ..core.names import BadName, items, namespace
from .common import (MAX_SEED, Parser, ToolError, bounded_float, bounded_int, command, fail,
                     output_file, path_text)


@command('hrc-fit')
def main(argv=None) -> int:
    parser = Parser(
        prog='hrc-fit', description='Fit the model (acceptance, distance drift, emotion chains, '
        'observation likelihood) to recorded runs by EM; write a configuration and a report.')
    parser.add_argument('inputs', nargs='+', metavar='INPUT',
                        help='bag folders, .mcap files or trajectory .csv files')
    parser.add_argument('-o', '--output', required=True, type=path_text,
                        help='configuration YAML to write')
    parser.add_argument('--base', default=None, help='configuration the fit starts from and '
                        'copies everything else from (default: the shipped default.yaml)')
    parser.add_argument('--hold', default='', help='comma-separated families to keep at the '
                        f'base values: {", ".join(FAMILIES)}, or emotion, emotion.<group>')
    parser.add_argument('--starts', type=bounded_int(1, 100), default=4,
                        help='EM initialisations, the base first (default 4)')
    parser.add_argument('--seed', type=bounded_int(0, MAX_SEED), default=0,
                        help='seed of the starts and bootstrap')
    parser.add_argument('--tol', type=bounded_float(1e-15, 1.0), default=TOL,
                        help='stop when the log likelihood rises by less than this per epoch '
                        f'(default {TOL:g})')
    parser.add_argument('--max-iter', type=bounded_int(1, 100_000), default=MAX_ITER)
    parser.add_argument('--bootstrap', type=bounded_int(0, 10_000), default=BOOTSTRAP,
                        help=f'resamples of the episodes for the 95%% intervals (default '
                        f'{BOOTSTRAP}; 0: none)')
    parser.add_argument('--method', choices=(SQUAREM, NEWTON), default=DEFAULT_METHOD,
                        help='how EM is accelerated: newton (default), SQUAREM and then '
                        "trust-region quasi-Newton steps with the full-data fit's curvature "
                        'for the last iterations and every resample; or squarem alone, which '
                        'stops short of the resamples\' maxima along flat directions '
                        '(docs/LEARNING.md)')
    parser.add_argument('--min-support', type=bounded_float(0.0, 1e12), default=MIN_SUPPORT,
                        help='warn below this many informative epochs per parameter')
    parser.add_argument('--namespace', default=None,
                        help="the cell's namespace in the bags (default: the only one)")
    parser.add_argument('--report', default=None, type=path_text,
                        help='JSON report to write (default: OUT with .report.json)')
    parser.add_argument('--plot', nargs='?', const='', default=None, metavar='PNG',
                        help='also plot fitted vs base parameters (default: OUT with .png)')
    parser.add_argument('--stream', action='store_true',
                        help='also fit the task stream (arrival_idle, arrival_complete, q; '
                        'MODEL.md 8; with a base that has stream.queue: arrival_idle, '
                        'arrival_busy, q from the tasks waiting, MODEL.md 8.1) and write it as '
                        'the stream section')
    parser.add_argument('--prior', action='store_true',
                        help='also fit the person prior (where h = 3*em + ea starts, from the '
                        'episodes recorded from epoch 1; MODEL.md 6.1) and write it as '
                        'observation.prior')
    parser.add_argument('--rate', action='store_true',
                        help="also count the robot's progress rate (the share of the epochs it "
                        'works in which its counter runs down, by task nature and band; '
                        'MODEL.md 3.2) and write it as model.robot_rate')
    parser.add_argument('-q', '--quiet', action='store_true', help='print only the summary')
    args = parser.parse_args(argv)
    try:
        hold = expand_hold(items(args.hold, '--hold')) if args.hold else ()
        if args.namespace is not None:
            args.namespace = namespace(args.namespace, '--namespace')
        output = Path(args.output)
        report_path = Path(args.report or output.with_suffix('.report.json'))
        plot_path = (None if args.plot is None
                     else Path(args.plot or output.with_suffix('.png')))
        outputs = {'-o': output, '--report': report_path, '--plot': plot_path}
        check_outputs(outputs, args.inputs, args.base or default_config_path())
        base = load_config(args.base or default_config_path())
        recordings = read_recordings(args.inputs, base.rho, base.sigma, args.namespace)
        if args.stream:
            check_stream(recordings, base)
        model = HRCModel(base)
        data = prepare(recordings, model, counter_may_stay=args.rate)
        for path in outputs.values():      # folders are made once the inputs have been read
            if path is not None:
                output_file(path)
    except (ToolError, ConfigError, RecordingError, FitError, StreamError, BadName) as exc:
        return fail('hrc-fit', exc)
    say = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    say(f'hrc-fit: {data.epochs} epochs in {len(data.episodes)} episode(s) from '
        f'{len(args.inputs)} input(s); base {base.source}; holding {", ".join(hold) or "none"}')
    try:
        result = fit(data, base, hold, n_init=args.starts, seed=args.seed, tol=args.tol,
                     max_iter=args.max_iter, bootstrap=args.bootstrap,
                     min_support=args.min_support, progress=say, method=args.method,
                     prior=args.prior)
        stream = (fit_stream_for(recordings, base, bootstrap=args.bootstrap, seed=args.seed)
                  if args.stream else None)
        rate = (fit_rate(recordings, model, bootstrap=args.bootstrap, seed=args.seed)
                if args.rate else None)
        text = config_yaml(result, base, args.inputs, stream, rate)
    except FitError as exc:
        return fail('hrc-fit', exc)
    except ConfigError as exc:
        return fail('hrc-fit', f'the fitted configuration does not validate ({exc}); nothing '
                    'written')
    report = report_dict(result)
    report.update(inputs=[str(p) for p in args.inputs], base=base.source, output=str(output))
    if stream is not None:
        report['stream'] = stream.report()
    if rate is not None:
        report['robot_rate'] = rate.report()
    try:
        # what is written is a configuration load_config accepts, or OUT.yaml is left as it was
        write_replacing(output, text, check=load_config)
        write_replacing(report_path, json.dumps(report, indent=2) + '\n')
    except ConfigError as exc:
        return fail('hrc-fit', f'the fitted configuration does not validate ({exc}); {output} '
                    'was not written')
    except ToolError as exc:
        return fail('hrc-fit', exc)
    print(report_text(result) if not args.quiet else
          f'hrc-fit: {result.iterations} EM iterations, log likelihood {result.loglik:.4f}, '
          f'{len(result.warnings)} warning(s)')
    for counted in (stream, rate):
        if counted is not None:
            print('\n'.join(counted.lines()))
    written = [output, report_path]
    if plot_path is not None:
        from ..core.study.plots import plot_fit
        written.append(plot_fit(result, plot_path))
    for path in written:
        print(f'wrote {path}')
    print(f'next: hrc-solve --config {output} -o {output.with_suffix(".npz")}')
    return 0


def check_outputs(outputs: dict, inputs, base) -> None:
    """ToolError, before any work, when an output would overwrite what the run reads (an input,
    a file in an input bag folder, the base configuration) or another output: the same file
    after resolving symbolic links and relative parts (os.path.realpath, which takes a loop of
    links as it is: reading it is refused later). `outputs`: option -> path or None."""
    def resolve(path) -> Path:
        return Path(os.path.realpath(path))
    read = [(resolve(p), f'input {p}') for p in inputs]
    read.append((resolve(base), f'the base configuration {base}'))
    taken: dict = {}
    for option, path in outputs.items():
        if path is None:
            continue
        if path.is_dir():
            raise ToolError(f'output {path} ({option}) is a folder; name a file')
        try:        # a FIFO, a device, a dangling link or a loop: refused before any reading
            output_target(path)
        except OSError as exc:
            raise ToolError(f'cannot write {path} ({option}): {exc.strerror}') from None
        where = resolve(path)
        for source, what in read:
            if where == source or source in where.parents:
                inside = '' if where == source else 'inside '
                raise ToolError(f'output {path} ({option}) is {inside}{what}: the run would '
                                f'overwrite what it reads; name another file with {option}')
        if where in taken:
            raise ToolError(f'output {path} ({option}) is also the {taken[where]} output: name '
                            f'a different file with {option}')
        taken[where] = option


def write_replacing(path: Path, text: str, check=None) -> None:
    """`paths.replace_file` of `text`: `path` is replaced whole once `check(temporary)` passes,
    or left as it was; ToolError when it cannot be written, the check's ConfigError (naming
    `path`) when the check refuses it."""
    def checked(temporary: Path) -> None:
        try:
            check(temporary)
        except ConfigError as exc:    # it names the temporary file, which is about to go
            raise ConfigError(str(exc).replace(str(temporary), str(path))) from None
    try:
        replace_file(path, lambda temporary: temporary.write_text(text),
                     None if check is None else checked)
    except OSError as exc:
        raise ToolError(f'cannot write {path}: {exc.strerror or exc}') from None


if __name__ == '__main__':
    sys.exit(main())
