"""How long the bounded readers take on the worst files they still accept, and to refuse a bomb.

    .venv/bin/python bench/hostile_files_bench.py          # ~10 s
    .venv/bin/python bench/hostile_files_bench.py --repeat 5

A node's `config` parameter is parsed in its parameter callback, on the executor's thread, so
the worst configuration under the cap (64 KiB) bounds how long a live `ros2 param set` can hold
the node: files of that size made of many small values (a block mapping, a flow list, nested
lists at the depth cap: refused at 5,000 values, config.MAX_VALUES), one just under that count,
and, for the refusals, /dev/zero, an alias bomb and an MCAP zstd bomb (a chunk that inflates
to 1 GiB) are timed through their readers. Each
figure is the median of `--repeat` runs in this process (libyaml's parser when PyYAML has it).
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

import yaml

from hrc_ros.core import bagfile, paths
from hrc_ros.core.config import ConfigError, load_config
from hrc_ros.core.paths import default_config_path, file_limit


def worst_configs(folder: Path) -> dict:
    """name -> a configuration file just under the cap, built of the most values it can hold."""
    base = default_config_path().read_text()
    room = file_limit('config') - len(base) - 64
    cases = {
        'block mapping of 1-key entries': 'x:\n' + ''.join(
            f' k{i}: 1\n' for i in range(room // 10)),
        'flow list of zeros': 'x: [' + '0,' * (room // 2 - 4) + '0]\n',
        'lists 30 deep (the cap: 32 levels)': 'x: [' + ', '.join(
            ['[' * 29 + '0' + ']' * 29] * (room // 62)) + ']\n',
        'configuration of 4,900 values': 'x: [' + '0,' * 4700 + '0]\n',
    }
    out = {}
    for name, prefix in cases.items():
        path = folder / f'{len(out)}.yaml'
        path.write_text(prefix + base)
        assert path.stat().st_size <= file_limit('config'), (name, path.stat().st_size)
        out[name] = path
    return out


def timed(call, repeat: int) -> tuple[float, str]:
    """Median seconds of `call()` (which must raise or return) and what it said the last time."""
    times, said = [], ''
    for _ in range(repeat):
        start = time.perf_counter()
        try:
            call()
            said = 'accepted'
        except (ConfigError, bagfile.BagError) as exc:
            said = str(exc).split(': ', 1)[-1][:70]
        times.append(time.perf_counter() - start)
    return statistics.median(times), said


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--repeat', type=int, default=3)
    args = parser.parse_args(argv)
    print(f'# {" ".join(shlex.quote(a) for a in [sys.executable, *sys.argv])}')
    print(f'# YAML parser: {paths._YAML_LOADER.__name__} (PyYAML {yaml.__version__})')
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        rows = [(name, path.stat().st_size, *timed(lambda p=path: load_config(p), args.repeat))
                for name, path in worst_configs(folder).items()]
        bomb = folder / 'bomb.yaml'
        lines = ['l0: &l0 [' + ', '.join(['lol'] * 9) + ']'] + [
            f'l{i}: &l{i} [' + ', '.join([f'*l{i - 1}'] * 9) + ']' for i in range(1, 9)]
        bomb.write_text('\n'.join(lines) + '\n' + default_config_path().read_text())
        rows.append(('alias bomb (9^9 values)', bomb.stat().st_size,
                     *timed(lambda: load_config(bomb), args.repeat)))
        rows.append(('/dev/zero', 0, *timed(lambda: load_config('/dev/zero'), args.repeat)))
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'test'))
        from test_hostile_files import GIB, mcap_with_chunks, zstd_zeros
        mcap = mcap_with_chunks(folder / 'bomb.mcap', [('zstd', GIB, zstd_zeros(GIB))])
        rows.append(('MCAP zstd bomb (1 GiB chunk)', mcap.stat().st_size,
                     *timed(lambda: bagfile.bag_info(mcap), args.repeat)))
    print(f'{"file":34} {"bytes":>8} {"median s":>9}  outcome')
    for name, size, seconds, said in rows:
        print(f'{name:34} {size:8,} {seconds:9.3f}  {said}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
