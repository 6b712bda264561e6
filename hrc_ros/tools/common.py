"""What the command lines share: one-line errors, bounded arguments, output folders, and the
model and policy arguments with their loading.

Every command refuses what it cannot do before any work starts, with one line on stderr and
exit status 2: an argument out of its range (numbers are bounded, so no typo runs for hours), an
output folder that is a file or cannot be written, a configuration or policy that does not load,
a model that would not fit in memory.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
from pathlib import Path
from typing import NoReturn

from ..core import parallel
from ..core.config import Config, ConfigError, load_config
from ..core.mdp.policy import Policy, PolicyError, default_policy_path, load_policy
from ..core.model import HRCModel
from ..core.paths import default_config_path, folder_target, output_target
from ..core.streams import outliving_stdout

MAX_SEED = 2 ** 31 - 1          # the simulated cell node's seed range
MAX_EPOCHS = 100_000            # one closed-loop run
MAX_EPISODES = 1_000_000
MAX_EPISODE_EPOCHS = 200_000_000   # episodes x epochs of one evaluation (about an hour)


class ToolError(RuntimeError):
    """A command cannot run with what it was given; the text says why (exit status 2)."""


class Parser(argparse.ArgumentParser):
    """argparse with a one-line error: ``prog: error: message`` on stderr, exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f'{self.prog}: error: {" ".join(message.split())}\n')


def _bounded(kind: type, low, high, what: str, span: str):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not {what}') from None
        if not low <= value <= high:   # NaN fails too
            raise argparse.ArgumentTypeError(f'{value} is outside {span}')
        return value
    return parse


def bounded_int(low: int, high: int):
    """An argparse type: an integer in low..high, or a one-line error naming the range."""
    return _bounded(int, low, high, 'an integer', f'{low}..{high}')


def bounded_float(low: float, high: float):
    """An argparse type: a finite number in [low, high]."""
    return _bounded(float, low, high, 'a number', f'[{low}, {high}]')


def path_text(text: str) -> str:
    """An argparse type: a path that names something. An empty one read as the current
    folder: `hrc-simulate --out ''` wrote its files there, `hrc-fit -o ''` crashed."""
    if not text.strip():
        raise argparse.ArgumentTypeError('an empty path names nothing; name a file or folder')
    return text


def check_cell(world: HRCModel) -> None:
    """ToolError when the model's cell cannot run `world` (`simulation.check_model_cell`: a
    robot_rate is the arm's physics)."""
    from ..core.study.simulation import check_model_cell
    try:
        check_model_cell(world)
    except ValueError as exc:
        raise ToolError(str(exc)) from None


def output_folder(path: str | Path, make: bool = True) -> Path:
    """The output folder `path`, created (with its parents) and checked writable; ToolError
    if it is a file, a device, a FIFO, a link that leads to no folder (`paths.folder_target`)
    or cannot be created or written. `make=False` checks only what `path` is (a command that
    makes its folder later, once its work has started)."""
    folder = Path(path)
    try:
        folder_target(folder)
    except OSError as exc:
        raise ToolError(f'cannot write into output folder {folder}: {exc.strerror}') from None
    if not make:
        return folder
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f'.hrc_write_test_{os.getpid()}'
        probe.write_bytes(b'')
        probe.unlink()
    except OSError as exc:
        raise ToolError(f'cannot write into output folder {folder}: '
                        f'{exc.strerror or exc}') from None
    return folder


def output_file(path: str | Path, suffix: str | None = None) -> Path:
    """An output file path whose folder exists (or is created) and is writable, which is a
    new name, a regular file or a link to one (`paths.output_target`: never a folder, a
    device, a FIFO) and, given `suffix`, ends in it; ToolError otherwise."""
    target = Path(path)
    if target.is_dir():
        raise ToolError(f'output {target} is a folder; name a file')
    if suffix is not None and target.suffix != suffix:
        raise ToolError(f'output {target} must end in {suffix}; name it {target}{suffix}')
    try:
        output_target(target)
    except OSError as exc:
        raise ToolError(f'cannot write {target}: {exc.strerror}') from None
    output_folder(target.parent if str(target.parent) else '.')
    return target


def check_memory(needed: int, what: str) -> None:
    """ToolError if `needed` bytes are more than the memory available now."""
    available = parallel.available_memory()
    if available is not None and needed > available:
        raise ToolError(f'{what} needs about {needed / 2**30:.1f} GiB of memory and '
                        f'{available / 2**30:.1f} GiB are available; use a smaller model '
                        '(rho, sigma) or a larger machine')


def add_model_arguments(parser: argparse.ArgumentParser, policy: bool = True) -> None:
    parser.add_argument('--config', default=None,
                        help='configuration YAML (default: the shipped default.yaml)')
    if policy:
        parser.add_argument('--policy', default=None,
                            help='policy file solved for that configuration (default: the '
                                 'shipped policy solved for it, e.g. paper.npz for paper.yaml)')


def load_model(args: argparse.Namespace) -> tuple[Config, HRCModel, Policy | None]:
    """The configuration, its model and (with a --policy argument) the policy for it."""
    try:
        config = load_config(args.config or default_config_path())
        policy = None
        if hasattr(args, 'policy'):
            policy = load_policy(args.policy or default_policy_path(config), config)
    except (ConfigError, PolicyError) as exc:
        raise ToolError(str(exc)) from None
    return config, HRCModel(config), policy


def add_pomdp_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--pomdp-policy', default=None,
                        help='POMDP policy file for the pomdp and fib selectors (default: the '
                             'shipped one solved for the configuration, policies/pomdp/)')


def load_pomdp(args: argparse.Namespace, config: Config, selectors) -> object | None:
    """The POMDP policy when one of `selectors` needs it (pomdp, fib), else None."""
    from ..core.decision.selection import POMDP_SELECTORS
    from ..core.pomdp.policy import default_pomdp_policy_path, load_pomdp_policy
    if not any(s in POMDP_SELECTORS for s in selectors):
        return None
    try:
        return load_pomdp_policy(args.pomdp_policy or default_pomdp_policy_path(config), config)
    except PolicyError as exc:
        raise ToolError(str(exc)) from None


def fail(prog: str, error: Exception) -> int:
    """Print a refusal as one line and return the exit status 2."""
    print(f'{prog}: error: {" ".join(str(error).split())}', file=sys.stderr)
    return 2


INTERRUPTED = 130    # the shell's code for a command ended by Ctrl-C


def command(prog: str):
    """Decorate a command's ``main(argv)``: the kernel setting (``HRC_KERNEL_THREADS``) is
    checked before any work (one line and 2 when it is wrong), Ctrl-C ends the command with one
    line and 130 instead of a traceback, and an output it cannot write (a full disk, a link to
    a device planted in its folder) is one line and 1 (what it was writing is written whole or
    not at all: `paths.replace_file`). A reader of its output that leaves (`| head`) stops the
    report only (`core.streams`)."""
    def decorate(main):
        @functools.wraps(main)
        def run(argv=None) -> int:
            try:
                parallel.current_mode()
            except parallel.KernelSettingError as exc:
                return fail(prog, exc)
            try:
                with outliving_stdout():      # `| head`: the report stops, the work goes on
                    return main(argv)
            except KeyboardInterrupt:
                print(f'\n{prog}: interrupted', file=sys.stderr)
                return INTERRUPTED
            except OSError as exc:      # an output it cannot write: a full disk, a link
                where = f'{exc.filename}: ' if exc.filename else ''
                print(f'{prog}: error: cannot write {where}{exc.strerror or exc}',
                      file=sys.stderr)
                return 1
        return run
    return decorate
