"""Every command refuses bad arguments before any work starts: one line on stderr, exit 2
(issue 13: each of these used to run, crash with a traceback, or run for hours)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from hrc_ros.core.config import ConfigError, load_config
from hrc_ros.core.paths import default_config_path

MODULES = {'hrc-simulate': 'hrc_ros.tools.simulate', 'hrc-evaluate': 'hrc_ros.tools.evaluate',
           'hrc-solve': 'hrc_ros.tools.solve', 'hrc-case-study': 'hrc_ros.ros.case_study',
           'hrc-bag': 'hrc_ros.ros.bag', 'hrc-fit': 'hrc_ros.tools.fit'}


def one_line_refusal(command, code, out, err) -> str:
    """A refusal as every command gives it: exit 2, exactly one line on stderr naming the
    command, nothing on stdout; the line."""
    assert code == 2, (code, out[-2000:], err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(command) and ': error: ' in lines[0], err
    assert out == ''
    return lines[0]


def refused(command, *args, cwd=None):
    """Run a command that must refuse (`one_line_refusal`) as a process of its own."""
    result = subprocess.run([sys.executable, '-m', MODULES[command], *map(str, args)],
                            capture_output=True, text=True, timeout=120, cwd=cwd)
    return one_line_refusal(command, result.returncode, result.stdout, result.stderr)


# the commands whose out-of-range refusals below run as a process of their own: each other
# command's own process refuses in a test below (an output folder, a model too large, a
# wrong kernel setting), and its range checks are the same main(argv) in this process
REFUSED_IN_A_PROCESS = {'hrc-bag'}


def refused_in_this_process(command, args, capfd) -> str:
    """`refused`, through the command's main(argv) here (an interpreter's start, about a CPU
    second, saved): exit 2, exactly one line on stderr (fd 2), nothing on stdout (fd 1)."""
    import importlib
    main = importlib.import_module(MODULES[command]).main
    try:
        code = main([str(a) for a in args])
    except SystemExit as exit_:          # argparse's error
        code = exit_.code
    return one_line_refusal(command, code, *capfd.readouterr())


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / 'a_file'
    path.write_text('not a folder')
    return path


@pytest.mark.parametrize('command, args, reason', [
    ('hrc-simulate', ['--seed', '-1'], '-1 is outside 0..'),
    ('hrc-simulate', ['--epochs', '0'], '0 is outside 1..'),
    ('hrc-simulate', ['--epochs', str(10 ** 9)], 'outside 1..100000'),
    ('hrc-evaluate', ['--selectors', ','], '--selectors names nothing'),
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
def test_out_of_range_arguments_are_refused(command, args, reason, tmp_path, capfd,
                                           monkeypatch):
    monkeypatch.chdir(tmp_path)            # the relative outputs (x.npz, f.yaml) land there
    line = (refused(command, *args, cwd=tmp_path) if command in REFUSED_IN_A_PROCESS
            else refused_in_this_process(command, args, capfd))
    assert reason in line
    assert list(tmp_path.iterdir()) == [], 'a refused command wrote something'


@pytest.mark.parametrize('command', ['hrc-simulate', 'hrc-evaluate', 'hrc-case-study'])
def test_an_output_folder_that_is_a_file_or_unwritable_is_refused(command, a_file, tmp_path,
                                                                 capfd):
    assert 'is a file' in refused(command, '--out', a_file)          # the command's process
    assert 'cannot write into' in refused_in_this_process(command, ['--out', a_file / 'below'],
                                                          capfd)


def test_hrc_fit_refuses_an_output_that_is_a_folder_before_reading(tmp_path):
    assert 'is a folder' in refused('hrc-fit', tmp_path / 'missing.csv', '-o', tmp_path)


def test_hrc_solve_refuses_a_model_that_does_not_fit_in_memory(tmp_path, a_file, capfd):
    data = yaml.safe_load(default_config_path().read_text())
    data['model'].update(rho=9, sigma=9)          # 576 M states: about 97 GiB
    big = tmp_path / 'big.yaml'
    big.write_text(yaml.safe_dump(data))
    # a process of its own: should the check fail, the allocation must not be this process's
    line = refused('hrc-solve', '--config', big, '-o', tmp_path / 'big.npz')
    assert '576,000,000 states needs about' in line and 'GiB are available' in line
    assert 'is a folder' in refused_in_this_process('hrc-solve', ['-o', tmp_path], capfd)


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


# -- hostile output paths and empty list items (issue 37) -------------------------------------
# In this process (main(argv)), so that each case costs milliseconds, not an interpreter's
# start: a refusal is exit 2 and one line on stderr, and nothing is written.

def hostile_paths(tmp_path) -> dict:
    """name -> a path that is no place to write: a FIFO, a device, a regular file, a dangling
    link, a loop of links."""
    import os
    fifo = tmp_path / 'fifo'
    os.mkfifo(fifo)
    regular = tmp_path / 'regular'
    regular.write_text('x')
    (tmp_path / 'dangling').symlink_to(tmp_path / 'nowhere')
    (tmp_path / 'loop').symlink_to(tmp_path / 'loop')
    return {'fifo': fifo, 'device': Path('/dev/null'), 'file': regular,
            'dangling': tmp_path / 'dangling', 'loop': tmp_path / 'loop'}


def refused_here(main, argv, capsys) -> str:
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exit_:          # argparse's error
        code = exit_.code
    err = capsys.readouterr().err.strip()
    assert code == 2, (code, err)
    assert len(err.splitlines()) == 1, err
    return err


HOSTILE = ('fifo', 'device', 'file', 'dangling', 'loop')


def test_hrc_case_study_refuses_a_bag_or_out_that_is_no_folder(tmp_path, capsys):
    """--bag /dev/null, a FIFO or a file ended in a NotADirectoryError traceback and a loop of
    links in a FileExistsError one; now one line each, before any node starts."""
    from hrc_ros.ros.case_study import main
    paths = hostile_paths(tmp_path)
    for name in HOSTILE:
        line = refused_here(main, ['--out', tmp_path / 'out', '--bag', paths[name]], capsys)
        assert line.startswith('hrc-case-study: error: bag folder') and 'not a folder' in line \
            or 'leads to nothing' in line, line
        line = refused_here(main, ['--out', paths[name]], capsys)
        assert 'output folder' in line, line
    full = tmp_path / 'full'
    full.mkdir()
    (full / 'x.mcap').write_text('x')
    assert 'not empty' in refused_here(main, ['--out', tmp_path / 'out', '--bag', full], capsys)
    assert (full / 'x.mcap').read_text() == 'x'
    assert not (tmp_path / 'out' / 'logs').exists(), 'a refused run started'


def test_hrc_case_study_refuses_the_arms_rate_without_the_arm(tmp_path, capsys):
    """config/arm.yaml plans with the arm's measured progress: without --robot sim the task
    manager would count the robot's share down the paper's way, another cell than the plan's.
    One line before any node starts (it ran to the end without a word before)."""
    from hrc_ros.core.paths import arm_config_path
    from hrc_ros.ros.case_study import main
    line = refused_here(main, ['--out', tmp_path / 'out', '--config', arm_config_path()],
                        capsys)
    assert 'model.robot_rate' in line and 'hrc-case-study --robot sim' in line, line
    assert not (tmp_path / 'out' / 'logs').exists(), 'a refused run started'


def test_hrc_bag_record_refuses_its_output_before_waiting_for_publishers(tmp_path, capsys):
    """-o a dangling link or a loop gave a FileExistsError traceback after the wait for the
    topics' publishers; now one line before any wait (a day's --wait-timeout would hang the
    test otherwise)."""
    from hrc_ros.ros.bag import main
    paths = hostile_paths(tmp_path)
    (tmp_path / 'loop.mcap').symlink_to(tmp_path / 'loop.mcap')
    full = tmp_path / 'full'
    full.mkdir()
    (full / 'a').write_text('a')
    for target in [*(paths[name] for name in HOSTILE), tmp_path / 'loop.mcap', full]:
        line = refused_here(main, ['record', '-o', target, '--wait-timeout', 86400,
                                   '/hrc/epoch'], capsys)
        assert line.startswith(f'hrc-bag: cannot record into {target}'), line
    assert 'must not be empty' in refused_here(
        main, ['record', '-o', tmp_path / 'new', '/hrc/epoch', ''], capsys)
    assert not (tmp_path / 'new').exists()


@pytest.mark.parametrize('text, reason', [
    ('', "names nothing"), (' , ', 'names nothing'),
    ('paper,,paper', 'has an empty item'), ('paper,', 'has an empty item'),
    ('paper,paper', 'names paper twice'), ('paper,bogus', "unknown selector 'bogus'")])
def test_hrc_evaluate_refuses_an_empty_or_repeated_selector(text, reason, tmp_path, capsys):
    """--selectors '' ran the defaults and paper,,paper was taken."""
    from hrc_ros.tools.evaluate import main
    line = refused_here(main, ['--selectors', text, '--out', tmp_path / 'out'], capsys)
    assert line.startswith('hrc-evaluate: error: ') and reason in line, line
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('args, reason', [
    (['--hold', ',,,'], '--hold names nothing'),
    (['--hold', 'emotion,,chains'], 'has an empty item'),
    (['--hold', 'emotion,emotion'], 'names emotion twice'),
    (['--namespace', '///'], 'an empty name between slashes'),
    (['--namespace', '/cell1//a'], 'an empty name between slashes'),
    (['--namespace', '/1cell'], "the name '1cell'"),
    (['--namespace', '/' + 'a' * 5000], '5,001 characters'),
])
def test_hrc_fit_refuses_empty_hold_items_and_a_bad_namespace(args, reason, tmp_path, capsys):
    from hrc_ros.tools.fit import main
    data = tmp_path / 'in.csv'
    data.write_text('epoch\n')
    line = refused_here(main, [data, '-o', tmp_path / 'fitted.yaml', *args], capsys)
    assert line.startswith('hrc-fit: error: ') and reason in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ['in.csv']


def test_hrc_fit_refuses_a_hostile_output_before_it_reads_its_inputs(tmp_path, capsys):
    from hrc_ros.tools.fit import main
    paths = hostile_paths(tmp_path)
    data = tmp_path / 'in.csv'
    data.write_text('not read: the output is refused first\n')
    for name in ('fifo', 'device', 'dangling', 'loop'):
        for option in ('-o', '--report', '--plot'):
            argv = [data, '-o', tmp_path / 'fitted.yaml', option, paths[name]]
            line = refused_here(main, argv, capsys)
            assert f'cannot write {paths[name]} ({option})' in line, line


@pytest.mark.parametrize('tool', ['simulate', 'evaluate', 'fleet'])
def test_the_output_folder_of_every_tool_refuses_what_is_no_folder(tool, tmp_path, capsys):
    import importlib
    main = importlib.import_module(f'hrc_ros.tools.{tool}').main
    paths = hostile_paths(tmp_path)
    plant = tmp_path / 'plant.yaml'
    plant.write_text('cells:\n  - name: a\n    recordings: x.csv\n')
    for name in HOSTILE:
        argv = (['run', plant] if tool == 'fleet' else []) + ['--out', paths[name]]
        line = refused_here(main, argv, capsys)
        assert f'output folder {paths[name]}: it is' in line, line


def test_hrc_solve_refuses_a_hostile_output(tmp_path, capsys):
    from hrc_ros.tools.solve import main
    import os
    os.mkfifo(tmp_path / 'fifo.npz')
    (tmp_path / 'dangling.npz').symlink_to(tmp_path / 'nowhere.npz')
    (tmp_path / 'loop.npz').symlink_to(tmp_path / 'loop.npz')
    for name in ('fifo.npz', 'dangling.npz', 'loop.npz'):
        line = refused_here(main, ['-o', tmp_path / name], capsys)
        assert f'cannot write {tmp_path / name}' in line, line


def test_a_plant_cells_namespace_must_be_a_ros_namespace_of_a_usable_length(tmp_path):
    """A namespace of 5,001 characters was accepted: no ROS name under it can exist."""
    from hrc_ros.core.names import MAX_NAMESPACE
    from hrc_ros.core.plant.spec import PlantError, load_plant
    plant = tmp_path / 'plant.yaml'
    for namespace, reason in [('/' + 'a' * 5000, '5,001 characters'),
                              ('///', 'an empty name between slashes'),
                              ('/a b', "the name 'a b'")]:
        plant.write_text(f'cells:\n  - name: a\n    namespace: "{namespace}"\n'
                         '    recordings: x.csv\n')
        with pytest.raises(PlantError, match=reason):
            load_plant(plant)
    longest = '/' + 'a' * (MAX_NAMESPACE - 1)
    plant.write_text(f'cells:\n  - name: a\n    namespace: {longest}/\n    recordings: x.csv\n')
    assert load_plant(plant).cells[0].namespace == longest


def test_namespaces_and_lists_as_the_commands_take_them():
    from hrc_ros.core.names import MAX_NAMESPACE, BadName, items, namespace
    assert namespace('/') == namespace('') == '/'
    assert namespace('cell1') == namespace('/cell1/') == '/cell1'
    assert namespace('/a/b_2') == '/a/b_2'
    for bad in ('//', '///', '/a//b', '/a//', '/1a', '/a-b', 'a' * (MAX_NAMESPACE + 1)):
        with pytest.raises(BadName):
            namespace(bad)
    assert items(' paper , qmdp ', 'x') == ('paper', 'qmdp')
    for bad in ('', ',', 'a,,b', 'a,', ',a', 'a,a'):
        with pytest.raises(BadName):
            items(bad, 'x')
    # and ROS agrees with the limit: the longest name a cell's node uses under the longest
    # namespace is a valid service name, one character more is not
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.validate_full_topic_name import validate_full_topic_name
    from hrc_ros.core.names import LONGEST_CELL_NAME
    validate_full_topic_name('/' + 'a' * (MAX_NAMESPACE - 1) + LONGEST_CELL_NAME)
    with pytest.raises(InvalidTopicNameException):
        validate_full_topic_name('/' + 'a' * MAX_NAMESPACE + LONGEST_CELL_NAME)


# -- what a user's first session tried (a review, 2026-12-06) -----------------------------------
def test_an_empty_output_path_is_refused_by_every_command(tmp_path, capsys, monkeypatch):
    """`--out ''` read as the current folder: hrc-simulate and hrc-evaluate wrote their files
    there, and `hrc-fit -o ''` crashed with a traceback."""
    from hrc_ros.ros import bag, case_study
    from hrc_ros.ros.hmi import shots
    from hrc_ros.tools import evaluate, fit, fleet, simulate, solve
    monkeypatch.chdir(tmp_path)
    for main, argv in [(simulate.main, ['--out', '']), (evaluate.main, ['--out', ' ']),
                       (fit.main, ['x.csv', '-o', '']), (solve.main, ['-o', '']),
                       (bag.main, ['record', '-o', '', '/x']),
                       (case_study.main, ['--out', '']), (fleet.main, ['run', 'p.yaml',
                                                                      '--out', '']),
                       (shots.main, ['--out', ''])]:
        assert 'an empty path names nothing' in refused_here(main, argv, capsys), main
    assert list(tmp_path.iterdir()) == []


def test_hrc_case_study_checks_its_inputs_before_it_makes_a_folder_or_empties_a_bag(tmp_path,
                                                                                    capsys):
    """A refused configuration or policy left an empty --out behind, and a refusal came after
    the last run's bag in <out>/bag was deleted; an HMI port in use failed 4 s into the run,
    with the bag and logs written. Now one line each, and the last run's files stay."""
    import socket
    from hrc_ros.ros.case_study import main
    err = refused_here(main, ['--out', tmp_path / 'new', '--config', tmp_path / 'none.yaml'],
                       capsys)
    assert 'none.yaml' in err and not (tmp_path / 'new').exists()
    err = refused_here(main, ['--out', tmp_path / 'new', '--policy', tmp_path], capsys)
    assert 'not a regular file' in err and not (tmp_path / 'new').exists()
    last = tmp_path / 'last'
    (last / 'bag').mkdir(parents=True)
    (last / 'bag' / 'last_0.mcap').write_bytes(b'the last run')
    refused_here(main, ['--out', last, '--policy', tmp_path / 'none.npz'], capsys)
    assert (last / 'bag' / 'last_0.mcap').read_bytes() == b'the last run'
    with socket.socket() as taken:
        taken.bind(('127.0.0.1', 0))
        taken.listen()
        port = taken.getsockname()[1]
        err = refused_here(main, ['--out', tmp_path / 'new', '--hmi', 'show', '--hmi-port',
                                  port], capsys)
    assert f'--hmi-port {port}' in err and 'in use' in err
    assert not (tmp_path / 'new').exists()


def test_a_policy_error_never_advises_writing_over_what_is_no_policy(tmp_path):
    """`--policy README.md` advised `hrc-solve ... -o README.md`, and a folder `-o <folder>`
    with 'the policy file file itself'."""
    from hrc_ros.core.mdp.policy import PolicyError, load_policy
    readme = tmp_path / 'README.md'
    readme.write_text('# not a policy')
    for path, said in [(readme, 'not a policy file'), (tmp_path, 'name the policy file itself'),
                       (tmp_path / 'gone.npz', 'policy file ')]:
        with pytest.raises(PolicyError) as error:
            load_policy(path)
        text = str(error.value)
        assert said in text and 'file file' not in text, text
        advice = text.split('Solve it again: ')[1]
        assert advice.endswith('-o ' + (str(path) if path.suffix == '.npz' else '<file>.npz'))


def test_hrc_hmi_shots_refuses_an_hmi_it_cannot_reach_in_one_line(tmp_path, capsys):
    """`--url http://127.0.0.1:1/` was a 34-line Playwright traceback and an empty --out."""
    from hrc_ros.ros.hmi.shots import main
    for url, said in [('http://127.0.0.1:1/', 'cannot reach'), ('ftp://x/', 'not an http')]:
        assert said in refused_here(main, ['--out', tmp_path / 'shots', '--url', url], capsys)
    assert not (tmp_path / 'shots').exists()


def test_hrc_hmi_shots_ends_on_ctrl_c_with_one_line(tmp_path):
    """hrc-hmi-shots ran outside the commands' guard (tools.common.command): Ctrl-C was a
    KeyboardInterrupt traceback (and `| head` could break its report). Here Ctrl-C arrives
    while it waits on an HMI that accepted the connection and never answers."""
    import signal
    import socket
    with socket.create_server(('127.0.0.1', 0)) as listening:
        port = listening.getsockname()[1]
        shots = subprocess.Popen([sys.executable, '-m', 'hrc_ros.ros.hmi.shots', '--out',
                                  str(tmp_path / 'shots'), '--url', f'http://127.0.0.1:{port}/'],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            listening.settimeout(60.0)
            connection, _ = listening.accept()      # it is waiting for the page now
            with connection:
                shots.send_signal(signal.SIGINT)
                out, err = shots.communicate(timeout=60)
        finally:
            shots.kill()
            shots.wait()
    assert shots.returncode == 130 and err.strip() == 'hrc-hmi-shots: interrupted', (
        shots.returncode, err)
    assert not (tmp_path / 'shots').exists()


def entry(name: str, *args, stdout=subprocess.PIPE, **kwargs) -> subprocess.Popen:
    """A console script as a user runs it (`python -m hrc_ros.ros.entry` runs the same main
    as the installed script)."""
    return subprocess.Popen([sys.executable, '-m', 'hrc_ros.ros.entry', name, *map(str, args)],
                            stdout=stdout, stderr=subprocess.PIPE, text=True, **kwargs)


@pytest.fixture
def started():
    """The processes a test starts (`entry`), killed at its end whatever happened: a node that
    starts instead of answering must not outlive a failed test (one did, for 20 minutes)."""
    processes: list[subprocess.Popen] = []

    def start(name: str, *args, **kwargs) -> subprocess.Popen:
        processes.append(entry(name, *args, **kwargs))
        return processes[-1]
    yield start
    for process in processes:
        if process.poll() is None:
            process.kill()
        process.wait()


def finished(process: subprocess.Popen, timeout: float = 60.0) -> tuple[int, str, str]:
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        pytest.fail(f'still running after {timeout} s (it started instead of answering):\n'
                    f'{(out or "")[-1500:]}\n{err[-1500:]}')
    return process.returncode, out or '', err


def test_every_node_answers_help_with_its_parameters_and_starts_on_nothing_else(started,
                                                                                tmp_path,
                                                                                capfd,
                                                                                monkeypatch):
    """`decision_node --help` and `robot_bridge_node --bogus-flag` started the node (the
    bridge, a protective stop; the HMI took port 8080), and a missing --params-file was a
    25-line RCLError traceback. Now --help prints the usage and every parameter and exits 0;
    a non-ROS argument, an unknown ROS one and ROS arguments rcl refuses are one line and 2,
    before any ROS work (so no DDS domain is touched here)."""
    import importlib
    from hrc_ros.ros.entry import COMMANDS
    nodes = [name for name in COMMANDS if name.endswith('_node')]
    assert len(nodes) == 11
    running = {name: started(name, '--help') for name in nodes}
    for name, process in running.items():
        code, out, err = finished(process)
        assert code == 0 and out.startswith(f'usage: {name} '), (name, code, out[:300], err)
        for spec in importlib.import_module(COMMANDS[name]).PARAMETERS:
            assert f'\n  {spec.name} (' in out, (name, spec.name)
    fifo = tmp_path / 'params.fifo'
    os.mkfifo(fifo)
    cases = [(('--bogus-flag',), 'unrecognized arguments: --bogus-flag'),
             (('--ros-args', '--bogus-ros'), 'unknown ROS arguments: --bogus-ros'),
             (('--ros-args', '--params-file', '/nonexistent/params.yaml'),
              'params.yaml: cannot read: No such file or directory'),
             # a FIFO was 'no such file'; rcl itself would wait on it for a writer
             (('--ros-args', '--params-file', str(fifo)),
              'cannot read: it is a FIFO (named pipe), not a regular file'),
             (('--ros-args', '-p', 'a=1'), "Couldn't parse parameter override rule")]
    # the refusals through the node's main(argv) in this process (each node's own process
    # answered --help above, through the console script's entry): refused before rclpy.init,
    # which fails the test here rather than start a node in this process
    import rclpy

    def started_a_node(*args, **kwargs):
        raise AssertionError('the node started: rclpy.init was called')
    monkeypatch.setattr(rclpy, 'init', started_a_node)
    for name in ('robot_bridge_node', 'decision_node'):
        main = importlib.import_module(COMMANDS[name]).main
        for args, said in cases:
            code = main([name, *args])
            out, err = capfd.readouterr()
            lines = err.strip().splitlines()
            assert code == 2 and len(lines) == 1 and said in lines[0], (name, args, code, err)
            assert lines[0].startswith(f'{name}: error: ') and '/project/src' not in lines[0]
            assert out == '', (name, args, out)


def test_a_reader_that_leaves_stops_the_report_not_the_work(tmp_path, started):
    """`hrc-fit ... | head -1` ended the fit with 'error: cannot write Broken pipe' before it
    wrote its files, and `hrc-bag info | head -1` with a BrokenPipeError traceback. Here the
    reader leaves before the command's first line: the fit writes its files and exits 0."""
    bag = Path(__file__).resolve().parents[1] / 'bags' / 'case_study'
    fitted = tmp_path / 'fitted.yaml'
    # one EM start (of the default four): what is checked is the output, not the fit
    fit = subprocess.Popen([sys.executable, '-m', MODULES['hrc-fit'], str(bag), '-o',
                            str(fitted), '--bootstrap', '0', '--starts', '1'],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        info = started('hrc-bag', 'info', bag)
        for process in (fit, info):
            process.stdout.close()          # the reader is gone before anything was written
        for process in (fit, info):
            code = process.wait(timeout=120)
            err = process.stderr.read()
            assert code == 0 and err == '', (process.args, code, err)
    finally:
        fit.kill()
        fit.wait()
    assert load_config(fitted).data['model']['p_accept']


def test_an_integer_for_a_decimal_parameter_says_how_to_write_it(started):
    """`epoch_period: 1` in a params file is a YAML integer, which rclpy refuses for a double
    parameter; the one line now says what to write."""
    code, out, err = finished(started('decision_node', '--ros-args', '-p', 'epoch_period:=1'))
    lines = [line for line in (out + err).splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1, (code, out, err)
    assert 'cannot start:' in lines[0] and '(write 1.0: a number with a decimal point)' in lines[0]
