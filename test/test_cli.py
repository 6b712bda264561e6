"""Every command refuses bad arguments before any work starts: one line on stderr, exit 2
(issue 13: each of these used to run, crash with a traceback, or run for hours)."""

import subprocess
import sys

import pytest
import yaml

from hrc_ros.core.config import ConfigError, load_config
from hrc_ros.core.paths import default_config_path

MODULES = {'hrc-simulate': 'hrc_ros.tools.simulate', 'hrc-evaluate': 'hrc_ros.tools.evaluate',
           'hrc-solve': 'hrc_ros.tools.solve', 'hrc-case-study': 'hrc_ros.ros.case_study',
           'hrc-bag': 'hrc_ros.ros.bag', 'hrc-fit': 'hrc_ros.tools.fit'}


def refused(command, *args, cwd=None):
    """Run a command that must refuse: exit 2, exactly one line on stderr, nothing on stdout."""
    result = subprocess.run([sys.executable, '-m', MODULES[command], *map(str, args)],
                            capture_output=True, text=True, timeout=120, cwd=cwd)
    assert result.returncode == 2, (result.returncode, result.stdout[-2000:], result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(command) and ': error: ' in lines[0], \
        result.stderr
    assert result.stdout == ''
    return lines[0]


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / 'a_file'
    path.write_text('not a folder')
    return path


@pytest.mark.parametrize('command, args, reason', [
    ('hrc-simulate', ['--seed', '-1'], '-1 is outside 0..'),
    ('hrc-simulate', ['--epochs', '0'], '0 is outside 1..'),
    ('hrc-simulate', ['--epochs', str(10 ** 9)], 'outside 1..100000'),
    ('hrc-evaluate', ['--selectors', ','], 'names no selector'),
    ('hrc-evaluate', ['--episodes', str(10 ** 9)], 'outside 1..1000000'),
    ('hrc-evaluate', ['--episodes', '1000000', '--epochs', '1000'], 'more than'),
    ('hrc-evaluate', ['--task-rate', 'nan'], 'outside [0.0, 1.0]'),
    ('hrc-case-study', ['--epochs', '0'], '0 is outside 1..'),
    ('hrc-case-study', ['--epochs', str(10 ** 9)], 'outside 1..10000'),
    ('hrc-case-study', ['--epoch-period', '0'], 'outside [0.05, 60.0]'),
    ('hrc-solve', ['-o', 'x.npz', '--sweeps', str(10 ** 9)], 'outside 1..100000'),
    ('hrc-bag', ['play', 'x', '--rate', '0'], 'outside'),
    ('hrc-fit', ['x.csv', '-o', 'f.yaml', '--bootstrap', '-1'], '-1 is outside 0..10000'),
    ('hrc-fit', ['x.csv', '-o', 'f.yaml', '--starts', '0'], '0 is outside 1..100'),
    ('hrc-fit', ['x.csv', '-o', 'f.yaml', '--tol', 'nan'], 'outside [1e-15, 1.0]'),
    ('hrc-fit', ['x.csv', '-o', 'f.yaml', '--method', 'bfgs'], "invalid choice: 'bfgs'"),
])
def test_out_of_range_arguments_are_refused(command, args, reason, tmp_path):
    assert reason in refused(command, *args, cwd=tmp_path)
    assert list(tmp_path.iterdir()) == [], 'a refused command wrote something'


@pytest.mark.parametrize('command', ['hrc-simulate', 'hrc-evaluate', 'hrc-case-study'])
def test_an_output_folder_that_is_a_file_or_unwritable_is_refused(command, a_file, tmp_path):
    assert 'is a file' in refused(command, '--out', a_file)
    assert 'cannot write into' in refused(command, '--out', a_file / 'below')


def test_hrc_fit_refuses_an_output_that_is_a_folder_before_reading(tmp_path):
    assert 'is a folder' in refused('hrc-fit', tmp_path / 'missing.csv', '-o', tmp_path)


def test_hrc_solve_refuses_a_model_that_does_not_fit_in_memory(tmp_path, a_file):
    data = yaml.safe_load(default_config_path().read_text())
    data['model'].update(rho=9, sigma=9)          # 576 M states: about 97 GiB
    big = tmp_path / 'big.yaml'
    big.write_text(yaml.safe_dump(data))
    line = refused('hrc-solve', '--config', big, '-o', tmp_path / 'big.npz')
    assert '576,000,000 states needs about' in line and 'GiB are available' in line
    assert 'is a folder' in refused('hrc-solve', '-o', tmp_path)


def test_an_unbounded_sweep_count_is_a_configuration_error(tmp_path):
    with pytest.raises(ConfigError, match=r'solver\.sweeps must be null .* 1\.\.100000'):
        load_config(default_config_path(), overrides={'solver': {'sweeps': 10 ** 9}})


def test_a_wrong_kernel_setting_is_one_line(tmp_path):
    """HRC_KERNEL_THREADS=bogus used to end in a ValueError traceback from the first kernel."""
    import os
    env = {**os.environ, 'HRC_KERNEL_THREADS': 'bogus'}
    result = subprocess.run([sys.executable, '-m', MODULES['hrc-solve'], '--config',
                             str(default_config_path()), '-o', str(tmp_path / 'p.npz')],
                            capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and 'HRC_KERNEL_THREADS' in lines[0] and 'bogus' in lines[0], lines


def test_ctrl_c_ends_a_command_in_one_line_and_writes_nothing(tmp_path):
    """Ctrl-C in a long solve used to print a KeyboardInterrupt traceback: now one line, exit
    130 (the shell's code for an interrupted command), and no policy file half written. The
    signal is sent once the solve reports its first sweep (a condition, not a sleep)."""
    import signal
    output = tmp_path / 'p.npz'
    process = subprocess.Popen(
        [sys.executable, '-u', '-m', MODULES['hrc-solve'], '--config', str(default_config_path()),
         '-o', str(output)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seen = []
    try:
        for line in process.stdout:
            seen.append(line)
            if 'sweep    1' in line:
                process.send_signal(signal.SIGINT)
                break
        rest = process.communicate(timeout=120)[0]
    finally:
        if process.poll() is None:
            process.kill()
    text = ''.join(seen) + rest
    assert process.returncode == 130, text[-2000:]
    assert 'Traceback' not in text and 'hrc-solve: interrupted' in text
    assert list(tmp_path.iterdir()) == []
