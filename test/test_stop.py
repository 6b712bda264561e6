"""Every process of the suite stops the same way (hrc_ros/ros/stop.py): a stop signal at any
moment is a clean exit 0, a second one forces the exit, a hung node's stacks are saved.

The moments are found from outside, by the process's own state, never by sleeping: "during
start-up of the interpreter" is right after the fork (the node is started, as
`processes.NodeProcesses` starts it, with the stop signals blocked); "during the imports" is once
the stop handler is in (/proc/PID/status shows SIGTERM caught) and before rclpy's extension is
mapped (/proc/PID/maps); "building the node" is once rclpy is mapped; "running" is once the node
is on the graph, plus a random delay of up to half a second (seeded, printed in the test id).
Every stop must end within a bounded time with 0 and leave no traceback, no KeyboardInterrupt,
no "Exception ignored" in the node's log.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import rclpy

from hrc_ros.core.paths import share_dir
from hrc_ros.ros import stop
from hrc_ros.ros import processes
from hrc_ros.ros.processes import NodeProcesses

REPO = Path(__file__).resolve().parents[1]
STOP_TIMEOUT = 15.0        # seconds for a stopped node to exit (a loaded machine)
START_TIMEOUT = 60.0
BAD_LOG_LINES = ('Traceback', 'KeyboardInterrupt', 'Exception ignored', 'Fatal Python error')
SEED = 17


def params() -> list[Path]:
    config = share_dir() / 'config'
    return [config / 'hrc_params.yaml', config / 'case_study_params.yaml']


def caught(pid: int, signum: int) -> bool:
    """The process has a handler for `signum` (/proc/PID/status SigCgt)."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return False
    mask = next(int(line.split()[1], 16) for line in status.splitlines()
                if line.startswith('SigCgt:'))
    return bool(mask >> (signum - 1) & 1)


def mapped(pid: int, fragment: str) -> bool:
    try:
        return fragment in Path(f'/proc/{pid}/maps').read_text()
    except OSError:
        return False


def wait_for(predicate, timeout: float, what: str, process=None) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert process is None or process.poll() is None, f'exited {process.returncode} ' \
            f'while waiting for {what}'
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        time.sleep(0.001)


def clean_log(text: str) -> list[str]:
    return [line for line in text.splitlines() if any(bad in line for bad in BAD_LOG_LINES)]


@pytest.fixture
def graph_probe(ros_domain_id):
    context = rclpy.Context()
    rclpy.init(context=context, **stop.init_options())
    node = rclpy.create_node('stop_probe', context=context)
    yield node
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def in_graph(probe, name: str) -> bool:
    return name in {n for n, _ in probe.get_node_names_and_namespaces()}


NODES = {'cell_sim_node': 'cell_sim', 'decision_node': 'decision'}
# The start-up moments run the same code in every node (stop.py, node_support.run): cell_sim
# (50 Hz of motion, the busiest) has them all; the decision node is stopped while it runs.
CASES = [('cell_sim_node', 'exec', signal.SIGTERM), ('cell_sim_node', 'imports', signal.SIGINT),
         ('cell_sim_node', 'imports', signal.SIGTERM),
         ('cell_sim_node', 'building', signal.SIGINT),
         ('cell_sim_node', 'running', signal.SIGINT), ('cell_sim_node', 'running', signal.SIGTERM),
         ('decision_node', 'running', signal.SIGINT), ('decision_node', 'running', signal.SIGTERM)]


@pytest.mark.parametrize('executable, moment, signum', CASES,
                         ids=[f'{e}-{m}-{signal.Signals(s).name}' for e, m, s in CASES])
def test_a_node_stopped_at_any_moment_exits_0_quietly(executable, moment, signum, tmp_path,
                                                      graph_probe):
    nodes = NodeProcesses(tmp_path, params())
    nodes.start(executable)
    process = nodes.processes[executable]
    try:
        if moment == 'imports':
            wait_for(lambda: caught(process.pid, signal.SIGTERM), START_TIMEOUT,
                     'the stop handler', process)
            assert not mapped(process.pid, '_rclpy_pybind11'), 'the imports were over'
        elif moment == 'building':
            wait_for(lambda: mapped(process.pid, '_rclpy_pybind11'), START_TIMEOUT,
                     'rclpy to be imported', process)
        elif moment == 'running':
            wait_for(lambda: in_graph(graph_probe, NODES[executable]), START_TIMEOUT,
                     'the node on the graph', process)
            # the moment, chosen (seeded) anywhere in the next half second of its running
            time.sleep(random.Random(f'{SEED}{executable}{signum}').uniform(0.0, 0.5))
        nodes.send_signal(executable, signum)
        code = process.wait(timeout=STOP_TIMEOUT)
    finally:
        nodes.stop(timeout=5.0)
    log = nodes.log(executable)
    assert code == 0, log
    assert not clean_log(log), log


def test_ctrl_c_during_the_imports_of_a_console_script_is_silent(tmp_path):
    """As a user runs it (no blocked signals): Ctrl-C while the node module imports rclpy,
    numpy and the model (it used to end with a KeyboardInterrupt traceback and exit -2)."""
    script = Path(sys.executable).parent / 'task_manager_node'
    process = subprocess.Popen([str(script), '--ros-args', '--params-file', str(params()[0])],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               start_new_session=True)
    try:
        wait_for(lambda: caught(process.pid, signal.SIGTERM), START_TIMEOUT,
                 'the stop handler', process)
        assert not mapped(process.pid, '_rclpy_pybind11'), 'the imports were over'
        os.killpg(process.pid, signal.SIGINT)
        output, _ = process.communicate(timeout=STOP_TIMEOUT)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 0, output
    assert output == ''


def test_the_entry_module_installs_the_handlers_before_any_heavy_import():
    probe = ('import sys, signal; import hrc_ros.ros.entry as e; '
             'print(sorted({m.split(".")[0] for m in sys.modules} & {"rclpy", "numpy", '
             '"scipy", "yaml", "numba", "std_msgs"}))')
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True,
                            timeout=60, cwd='/')
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == '[]'


LEAVING = textwrap.dedent('''
    import atexit, logging, sys
    from hrc_ros.ros import stop

    class Finalized:
        def __del__(self):
            sys.stdout.write('finalized\\n')

    kept = Finalized()                      # collected only by the interpreter's finalization
    atexit.register(lambda: sys.stdout.write('atexit hook\\n'))
    logging.basicConfig(stream=open(sys.argv[1], 'w'), level=logging.INFO)
    logging.getLogger('x').info('logged')   # buffered in the handler's stream until flushed
    sys.stdout.write('buffered')            # not flushed yet: stdout is a pipe
    stop.leave(int(sys.argv[2]))
    sys.stdout.write('after leave\\n')
''')


@pytest.mark.parametrize('code', [0, 1])
def test_a_command_leaves_after_its_stop_without_the_interpreters_finalization(code, tmp_path):
    """`stop.leave`, which every console script of `entry` ends with once its main() has
    returned: what was written is flushed (stdout, the logging handlers, the atexit hooks), the
    code goes out, and nothing of the interpreter's finalization runs (issue 37: its final
    garbage collection took ~1.8 s under load, past launch's grace)."""
    log = tmp_path / 'log.txt'
    result = subprocess.run([sys.executable, '-c', LEAVING, str(log), str(code)],
                            capture_output=True, text=True, timeout=60, cwd='/')
    assert result.returncode == code, result.stderr
    assert result.stdout == 'bufferedatexit hook\n', result.stdout   # no 'finalized'
    assert 'logged' in log.read_text()


def test_every_console_script_of_entry_leaves_through_stop_leave(monkeypatch):
    """The console scripts run their command, then `stop.leave` with its code."""
    from hrc_ros.ros import entry
    left = []
    monkeypatch.setattr(entry, 'run_command', lambda name: f'code of {name}')
    monkeypatch.setattr(entry.stop, 'leave', left.append)
    for name in entry.COMMANDS:
        getattr(entry, name.replace('-', '_'))()
    assert left == [f'code of {name}' for name in entry.COMMANDS]


SLOW_TO_STOP = textwrap.dedent('''
    import ctypes, signal, sys, time
    from rclpy.node import Node
    from hrc_ros.ros.node_support import run

    class SlowToStop(Node):
        NODE_NAME = 'slow_to_stop'

        def __init__(self):
            super().__init__(self.NODE_NAME)
            self.create_timer(0.05, lambda: None)
            print('running', flush=True)

        def on_stop(self):
            if sys.argv[1] == 'native':   # stuck in C with the interpreter lock released
                # libc's sleep(), with the stop signals blocked in this thread so that they
                # cannot cut it short: the kernel hands them to another thread (pthread_join
                # on a Python thread, which CPython detaches, returned at once with EINVAL,
                # and the test raced the node's own clean stop)
                signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
                print('last word: stuck', flush=True)
                left = ctypes.CDLL(None).sleep(120)
                print(f'out of C with {left} s left', flush=True)
            else:
                print('last word: stuck', flush=True)
                time.sleep(120)

    sys.exit(run(SlowToStop, sys.argv[:1]))   # its own argument is no ROS argument
''')


@pytest.mark.parametrize('stuck_in', ['python', 'native'])
def test_a_second_stop_signal_forces_the_exit(stuck_in, tmp_path, ros_domain_id):
    """The first SIGINT starts the stop; the node hangs in its last word; the second SIGINT
    ends the process at once with stop.FORCED_EXIT, also when the main thread is stuck in C
    (the helper thread that reads the signal wake-up pipe exits then)."""
    script = tmp_path / 'slow_to_stop.py'
    script.write_text(SLOW_TO_STOP)
    log = tmp_path / 'slow.log'
    with open(log, 'w') as output:
        process = subprocess.Popen([sys.executable, str(script), stuck_in], stdout=output,
                                   stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: 'running' in log.read_text(), START_TIMEOUT, 'the node', process)
        os.killpg(process.pid, signal.SIGINT)
        wait_for(lambda: 'last word: stuck' in log.read_text(), STOP_TIMEOUT, 'the last word',
                 process)
        os.killpg(process.pid, signal.SIGINT)
        code = process.wait(timeout=STOP_TIMEOUT)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert code == stop.FORCED_EXIT, log.read_text()
    assert 'out of C' not in log.read_text()      # the second signal ended it, not the sleep
    assert 'second stop signal: exiting at once (3)' in log.read_text()


def test_a_context_shut_down_elsewhere_ends_the_spin():
    """A callback that shuts the context down (what ros2 launch's in-process composition or
    a test may do) ends the spin loop like a stop signal: exit 0, the node destroyed."""
    from rclpy.node import Node

    from hrc_ros.ros.node_support import run
    built = []

    class ShutDown(Node):
        NODE_NAME = 'shut_down_from_inside'

        def __init__(self):
            super().__init__(self.NODE_NAME)
            built.append(self)
            self.create_timer(0.01, rclpy.shutdown)

    assert run(ShutDown, args=[]) == 0
    assert not rclpy.ok()
    from rclpy.exceptions import InvalidHandle
    with pytest.raises(InvalidHandle):   # destroyed
        built[0].get_fully_qualified_name()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler   # given back


def test_a_bug_still_propagates():
    """Nothing is taken for a stop any more but a stop: an error in the constructor or in a
    callback propagates with its traceback."""
    from rclpy.node import Node

    from hrc_ros.ros.node_support import run

    class BrokenAtStart(Node):
        NODE_NAME = 'broken_at_start'

        def __init__(self):
            super().__init__(self.NODE_NAME)
            raise KeyError('a bug')

    class BrokenInCallback(Node):
        NODE_NAME = 'broken_in_callback'

        def __init__(self):
            super().__init__(self.NODE_NAME)
            self.create_timer(0.01, self.fail)

        def fail(self):
            raise RuntimeError('a bug')

    with pytest.raises(KeyError):
        run(BrokenAtStart, args=[])
    with pytest.raises(RuntimeError, match='a bug'):
        run(BrokenInCallback, args=[])
    assert not rclpy.ok()


HANGS = 'import signal, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n' \
    'print("ignoring SIGINT", flush=True)\n' \
    'def stuck_in_shutdown():\n    time.sleep(120)\n\nstuck_in_shutdown()\n'


def test_a_node_that_does_not_stop_leaves_its_stacks_in_its_log(tmp_path):
    """processes.stop: past the timeout, the native and Python stacks (py-spy) go into the
    node's log before it is killed, so a hang says where it was."""
    nodes = NodeProcesses(tmp_path, [])
    log = nodes.log_path('hanging')
    with open(log, 'w') as output:
        nodes.processes['hanging'] = subprocess.Popen(
            [sys.executable, '-c', HANGS], stdout=output, stderr=subprocess.STDOUT,
            start_new_session=True)
    wait_for(lambda: 'ignoring SIGINT' in log.read_text(), START_TIMEOUT, 'the process')
    codes = nodes.stop(timeout=1.0)
    assert codes['hanging'] in (-signal.SIGABRT, -signal.SIGKILL)
    assert nodes.stacks_dumped == ['hanging']
    text = log.read_text()
    assert 'stacks of pid' in text and 'stuck_in_shutdown' in text, text


# A process that notes in a shared file when it is up, when SIGINT reaches it and when it exits,
# `delay` s after the signal (a node destroying its DDS participant); `hang` ignores SIGINT.
NOTING = textwrap.dedent('''
    import os, signal, sys, time
    name, path, hang, delay = sys.argv[1], sys.argv[2], sys.argv[3] == 'hang', float(sys.argv[4])
    def note(what):
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
        os.write(fd, f'{what} {name}\\n'.encode())
        os.close(fd)
    signalled = []
    signal.signal(signal.SIGINT, signal.SIG_IGN if hang else lambda s, f: signalled.append(s))
    note('up')
    while not signalled:
        time.sleep(120 if hang else 0.01)
    note('signalled')
    time.sleep(delay)
    note('exit')
''')


@pytest.fixture
def noting(tmp_path):
    """`noting(kinds, delay)`: NOTING processes (name -> 'stop' or 'hang') in a NodeProcesses,
    all up, and the file of their notes; whatever still runs at the end is killed."""
    made: list[NodeProcesses] = []
    yield lambda kinds, delay=0.3: noting_processes(tmp_path, kinds, delay, made)
    for nodes in made:
        nodes.kill()
        for process in nodes.processes.values():
            process.wait(timeout=10)


def noting_processes(tmp_path, kinds: dict, delay: float, made: list
                     ) -> tuple[NodeProcesses, Path]:
    nodes = NodeProcesses(tmp_path, [])
    made.append(nodes)                  # killed by the fixture, also if they never come up
    events = tmp_path / 'events'
    for name, kind in kinds.items():
        with open(nodes.log_path(name), 'w') as output:
            nodes.processes[name] = subprocess.Popen(
                [sys.executable, '-c', NOTING, name, str(events), kind, str(delay)], stdout=output,
                stderr=subprocess.STDOUT, start_new_session=True)
    wait_for(lambda: events.exists() and events.read_text().count('up ') == len(kinds),
             START_TIMEOUT, 'the processes')
    return nodes, events


def test_the_runner_stops_the_nodes_one_after_another_the_last_started_first(noting):
    """processes.stop: a node is signalled once the one before it has exited (several DDS
    participants destroyed at once can deadlock Fast DDS 2.14; bench/README.md)."""
    nodes, events = noting({'a': 'stop', 'b': 'stop', 'c': 'stop'})
    assert nodes.stop(timeout=10.0) == {'a': 0, 'b': 0, 'c': 0}
    lines = [line for line in events.read_text().splitlines() if not line.startswith('up')]
    assert lines == ['signalled c', 'exit c', 'signalled b', 'exit b', 'signalled a', 'exit a']
    assert set(nodes.stop_seconds) == {'a', 'b', 'c'}
    assert all(0.3 <= s < 10.0 for s in nodes.stop_seconds.values()), nodes.stop_seconds


def test_a_hung_node_is_killed_after_its_timeout_and_the_next_is_stopped(noting):
    nodes, events = noting({'a': 'stop', 'b': 'hang', 'c': 'stop'})
    started = time.monotonic()
    codes = nodes.stop(timeout=1.0)
    assert codes['a'] == codes['c'] == 0
    assert codes['b'] in (-signal.SIGABRT, -signal.SIGKILL)
    assert nodes.stacks_dumped == ['b'] and 'b' not in nodes.stop_seconds
    lines = [line for line in events.read_text().splitlines() if not line.startswith('up')]
    assert lines == ['signalled c', 'exit c', 'signalled a', 'exit a']
    assert time.monotonic() - started < 1.0 + 2 * processes.STACK_DUMP_TIMEOUT + 10.0


def test_together_signals_every_node_before_any_has_exited(noting):
    nodes, events = noting({'a': 'stop', 'b': 'stop', 'c': 'stop'}, 3.0)
    assert nodes.stop(timeout=10.0, order='together') == {'a': 0, 'b': 0, 'c': 0}
    lines = [line for line in events.read_text().splitlines() if not line.startswith('up')]
    assert sorted(lines[:3]) == ['signalled a', 'signalled b', 'signalled c'], lines
    with pytest.raises(ValueError, match='order must be one of sequential, together'):
        nodes.stop(order='reversed')


SPAWNS = textwrap.dedent('''
    import subprocess
    started = []
    popen = subprocess.Popen.__init__
    def noted(self, args, *more, **options):
        started.append(args)
        popen(self, args, *more, **options)
    subprocess.Popen.__init__ = noted
    from hrc_ros.core.robot.arm import Arm
    Arm()
    print(len(started), started[:1])
''')


def test_building_an_arm_starts_no_child_process():
    """MuJoCo's default GL backend (pyglfw) starts a Python child at import to read the GLFW
    version; in a node's process group it took the node's SIGINT during its `site` import and
    printed "Fatal Python error: init_import_site" into the log (core/robot/arm.py)."""
    env = {k: v for k, v in os.environ.items() if k != 'MUJOCO_GL'}
    out = subprocess.run([sys.executable, '-c', SPAWNS], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == '0', out.stdout


# A launcher that starts a node as hrc-case-study does and is then killed without stopping it.
LAUNCHER = textwrap.dedent('''
    import sys, time
    from pathlib import Path
    from hrc_ros.ros.processes import NodeProcesses
    nodes = NodeProcesses(Path(sys.argv[1]), sys.argv[3:])
    nodes.start(sys.argv[2])
    print(nodes.processes[sys.argv[2]].pid, flush=True)
    while True:
        time.sleep(60)
''')


def gone(pid: int) -> bool:
    """The process has exited (a zombie nobody has reaped yet counts as exited)."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return True
    return any(line.startswith('State:') and 'Z' in line.split()[1]
               for line in status.splitlines())


def test_a_node_whose_launcher_is_killed_stops_itself(tmp_path, graph_probe):
    """stop.py point 7: hrc-case-study killed with SIGKILL (its own stop never runs) left its
    nodes running as orphans, the arm's simulation and its topics with them. A node started
    by NodeProcesses sees its parent change and stops the clean way."""
    launcher = subprocess.Popen(
        [sys.executable, '-c', LAUNCHER, str(tmp_path), 'decision_node',
         *map(str, params())], stdout=subprocess.PIPE, text=True, start_new_session=True)
    pid = None
    try:
        pid = int(launcher.stdout.readline())
        wait_for(lambda: in_graph(graph_probe, 'decision'), START_TIMEOUT, 'the node on the graph')
        os.killpg(launcher.pid, signal.SIGKILL)
        launcher.wait(timeout=10)
        wait_for(lambda: gone(pid), STOP_TIMEOUT, 'the orphaned node to stop')
    finally:
        if pid is not None and not gone(pid):
            os.kill(pid, signal.SIGKILL)
    log = (tmp_path / 'decision_node.log').read_text()
    assert f'the launching process {launcher.pid} is gone: stopping' in log, log
    assert not clean_log(log), log


def test_a_robot_node_stopped_while_it_compiles_its_kernels_exits_at_once(
        tmp_path, graph_probe, monkeypatch):
    """robot_bridge_node compiles its numba kernels (about 9 s on a fresh install) before its
    node exists, and a stop signal meanwhile ends the process at once with 0, as during the
    imports (node_support.warm_up_before_the_node). Warmed up after it joined the graph, its
    first start in a colcon install ignored a SIGINT for 10 s in CI. With an empty numba cache
    (NUMBA_CACHE_DIR) and SIGINT once the first kernel is in the cache: exit 0, the node never
    on the graph, and the warm-up's last kernel (guard's path_offset) never compiled."""
    cache = tmp_path / 'numba_cache'
    monkeypatch.setenv('NUMBA_CACHE_DIR', str(cache))
    nodes = NodeProcesses(tmp_path, params())
    nodes.start('robot_bridge_node')
    process = nodes.processes['robot_bridge_node']
    seen = []
    try:
        def compiling():
            seen.append(in_graph(graph_probe, 'robot_bridge'))
            return any(cache.rglob('*.nbc'))
        wait_for(compiling, START_TIMEOUT, 'the first kernel in the cache', process)
        nodes.send_signal('robot_bridge_node', signal.SIGINT)
        code = process.wait(timeout=STOP_TIMEOUT)
    finally:
        nodes.stop(timeout=5.0)
    log = nodes.log('robot_bridge_node')
    assert code == 0 and not clean_log(log), log
    assert not any(seen) and not in_graph(graph_probe, 'robot_bridge')
    compiled = {p.name.split('-')[0] for p in cache.rglob('*.nbc')}
    assert '_kernels.path_offset' not in compiled, compiled
