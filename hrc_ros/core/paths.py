"""Where the package's data lives: `config/` and `policies/` under the share folder.

`share_dir()` looks, in order, at

1. ``$HRC_ROS_SHARE`` (a folder holding ``config/`` and ``policies/``);
2. the ament index: the first prefix of ``$AMENT_PREFIX_PATH`` that holds the marker
   ``share/ament_index/resource_index/packages/hrc_ros`` (a colcon build or a ROS install),
   read here as plain files, as `ament_index_python` does, so the core imports nothing of ROS;
3. the source checkout this module lives in (a clone, or ``pip install -e .``);
4. ``<sys.prefix>/share/hrc_ros`` (a ``pip install .``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

PACKAGE = 'hrc_ros'


def ament_share_dir(package: str = PACKAGE) -> Path | None:
    """``<prefix>/share/<package>`` of the first AMENT_PREFIX_PATH prefix that indexes it."""
    marker = Path('share') / 'ament_index' / 'resource_index' / 'packages' / package
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix and (Path(prefix) / marker).is_file():
            return Path(prefix) / 'share' / package
    return None


def share_dir() -> Path:
    """The package's data folder (holding config/ and policies/); see the module docstring."""
    env = os.environ.get('HRC_ROS_SHARE')
    if env:
        return Path(env)
    indexed = ament_share_dir()
    if indexed is not None:
        return indexed
    checkout = Path(__file__).resolve().parents[2]
    if (checkout / 'config' / 'default.yaml').is_file():
        return checkout
    return Path(sys.prefix) / 'share' / PACKAGE


def default_config_path() -> Path:
    """The shipped default configuration, `config/default.yaml`."""
    return share_dir() / 'config' / 'default.yaml'


def shipped_config_path(name: str) -> Path:
    """A shipped configuration by name: ``shipped_config_path('paper')`` is
    `config/paper.yaml` of the share folder."""
    return share_dir() / 'config' / f'{name}.yaml'


def read_text(path: str | Path, error: type[Exception], kind: str) -> str:
    """The text of a user's file, or `error` with one line that names it: cannot read (and why)
    or not UTF-8 text (`kind`: what the file should be, e.g. 'YAML'). A UTF-8 byte order mark,
    as Excel and Notepad write one, is dropped: it is not part of the text."""
    path = Path(path)
    try:
        return path.read_text(encoding='utf-8-sig')
    except OSError as exc:
        raise error(f'{path}: cannot read: {exc.strerror}') from None
    except UnicodeDecodeError:
        raise error(f'{path}: not a text (UTF-8) {kind} file') from None


def replace_file(path: str | Path, write, check=None) -> Path:
    """Write a file whole or not at all: `write(temporary)` a file beside it (same suffix, so
    numpy does not add one), `check(temporary)` it if given, then rename it over `path`
    (os.replace); a `path` that is a symbolic link is written through (its target replaced,
    the link kept). The temporary file is removed in any case, so a run that fails on the way
    leaves `path` as it was. OSError and the check's errors propagate."""
    target = Path(path).resolve()
    temporary = target.with_name(f'{target.name}.{os.getpid()}.tmp{target.suffix}')
    try:
        write(temporary)
        if check is not None:
            check(temporary)
        os.replace(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)
    return Path(path)
