"""The house as it reads: the core and the command-line tools never import ROS, and the tree
passes the linter (ruff, configured in ruff.toml)."""

import os
import pkgutil
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROS_MODULES = ('rclpy', 'rcl_interfaces', 'builtin_interfaces', 'std_msgs', 'sensor_msgs',
               'geometry_msgs', 'diagnostic_msgs', 'visualization_msgs', 'trajectory_msgs',
               'ament_index_python',
               'launch', 'launch_ros', 'rosidl_runtime_py', 'rosidl_parser')
ROS_FREE_PACKAGES = ('hrc_ros.core', 'hrc_ros.tools')

IMPORT_WITHOUT_ROS = '''
import importlib, importlib.abc, sys
BLOCKED = set(sys.argv[1].split(','))

class NoRos(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in BLOCKED:
            raise ImportError(f'{name} is ROS: the core must not import it')
        return None

sys.meta_path.insert(0, NoRos())
for name in sys.argv[2:]:
    importlib.import_module(name)
loaded = sorted(m for m in sys.modules if m.split('.')[0] in BLOCKED)
assert not loaded, loaded
print(len(sys.argv) - 2, 'modules imported without ROS')
'''


def ros_free_modules() -> list[str]:
    import hrc_ros
    names = []
    for package in ROS_FREE_PACKAGES:
        path = Path(hrc_ros.__file__).parent / package.split('.')[1]
        names.append(package)
        names += [f'{package}.{m.name}' for m in pkgutil.iter_modules([str(path)])]
    return names


def test_every_core_and_tool_module_imports_with_ros_unimportable():
    modules = ros_free_modules()
    assert {'hrc_ros.core.protocol', 'hrc_ros.core.bagfile', 'hrc_ros.core.model',
            'hrc_ros.tools.solve'} <= set(modules)
    result = subprocess.run([sys.executable, '-c', IMPORT_WITHOUT_ROS, ','.join(ROS_MODULES),
                             *modules], capture_output=True, text=True, timeout=120,
                            cwd='/')
    assert result.returncode == 0, result.stderr[-3000:]
    assert f'{len(modules)} modules imported without ROS' in result.stdout


def test_the_guard_does_catch_a_ros_import():
    """The check above can fail: a ring module is refused under the same guard."""
    result = subprocess.run([sys.executable, '-c', IMPORT_WITHOUT_ROS, ','.join(ROS_MODULES),
                             'hrc_ros.ros.conversions'], capture_output=True, text=True,
                            timeout=120, cwd='/')
    assert result.returncode != 0 and 'is ROS: the core must not import it' in result.stderr


def test_lint():
    ruff = shutil.which('ruff') or str(Path(sys.executable).parent / 'ruff')
    if not Path(ruff).is_file():
        pytest.fail('ruff is not installed: pip install -r requirements-dev.txt')
    result = subprocess.run([ruff, 'check', '--no-cache', '.'], cwd=REPO, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stdout[-5000:] + result.stderr[-2000:]


def test_no_tracked_file_holds_a_merge_conflict_marker():
    """A merge resolved by hand once left `<<<<<<< HEAD` ... `>>>>>>> branch` in a doc."""
    files = subprocess.run(['git', 'ls-files', '-z'], cwd=REPO, capture_output=True, check=True,
                           timeout=60).stdout.decode().split('\0')
    marked = []
    for name in filter(None, files):
        path = REPO / name
        if not path.is_file() or path.stat().st_size > 1 << 22:
            continue
        for number, line in enumerate(path.read_bytes().splitlines(), 1):
            if line.startswith((b'<<<<<<< ', b'>>>>>>> ')) or line == b'=======':
                marked.append(f'{name}:{number}')
    assert not marked, marked


def test_an_explicit_ros_domain_id_wins_over_the_test_sessions_own():
    """scripts/test.sh and the README promise that an explicit ROS_DOMAIN_ID is used."""
    probe = 'import os, conftest; print(os.environ["ROS_DOMAIN_ID"], conftest.ROS_DOMAIN_ID)'
    env = {k: v for k, v in os.environ.items()
           if k not in ('ROS_DOMAIN_ID', 'PYTEST_XDIST_WORKER')}
    given = subprocess.run([sys.executable, '-c', probe], cwd=REPO / 'test', text=True,
                           capture_output=True, env={**env, 'ROS_DOMAIN_ID': '5'}, timeout=60)
    assert given.stdout.split() == ['5', '5'], given.stderr
    # the first xdist worker's graph is in the given domain, every other worker's in its own
    domains = []
    for worker in ('gw0', 'gw1', 'gw2', 'gw3'):
        run = subprocess.run([sys.executable, '-c', probe], cwd=REPO / 'test', text=True,
                             capture_output=True, timeout=60,
                             env={**env, 'ROS_DOMAIN_ID': '5', 'PYTEST_XDIST_WORKER': worker})
        domain, same = run.stdout.split()
        assert domain == same, run.stderr
        domains.append(int(domain))
    assert domains[0] == 5 and len(set(domains)) == 4 and all(1 <= d <= 100 for d in domains)
    chosen = subprocess.run([sys.executable, '-c', probe], cwd=REPO / 'test', text=True,
                            capture_output=True, env=env, timeout=60)
    domain, same = chosen.stdout.split()
    assert domain == same and 30 <= int(domain) <= 99, chosen.stderr


def test_the_test_sessions_dds_profile_is_written_and_removed_when_the_process_exits(tmp_path):
    """conftest writes the tests' Fast DDS profile into a folder of its own for each pytest
    process; every run of the suite left those folders in /tmp (20 after a day's runs)."""
    probe = ('import os, conftest; print(os.environ["FASTDDS_DEFAULT_PROFILES_FILE"]); '
             'print(os.path.isfile(os.environ["FASTDDS_DEFAULT_PROFILES_FILE"]))')
    env = {k: v for k, v in os.environ.items()
           if k not in ('FASTDDS_DEFAULT_PROFILES_FILE', 'FASTRTPS_DEFAULT_PROFILES_FILE')}
    result = subprocess.run([sys.executable, '-c', probe], cwd=REPO / 'test', text=True,
                            capture_output=True, env={**env, 'TMPDIR': str(tmp_path)},
                            timeout=60)
    profile, written = result.stdout.split()
    assert written == 'True' and Path(profile).parent.parent == tmp_path, result.stderr
    assert list(tmp_path.iterdir()) == []


HANGING_TEST = ('import threading, time\n\n'
                'def test_hangs():\n'
                '    threading.Thread(target=time.sleep, args=(60,), name="helper",\n'
                '                     daemon=True).start()\n'
                '    time.sleep(60)\n')

# a test folder's conftest that registers test/hang_stacks.py, as the suite's does
HANG_STACKS_CONFTEST = (f'import sys\nsys.path.insert(0, {str(REPO / "test")!r})\n'
                        'from hang_stacks import HangStacks\n\n\n'
                        'def pytest_configure(config):\n'
                        '    config.pluginmanager.register(HangStacks(config), '
                        '"hrc-hang-stacks")\n')


class HangRun:
    """A pytest run of a hanging test in a session of its own, started at once and waited for
    on a thread: `hang_runs` starts every run the module's selected tests read before the
    first of them, so that their waits for the timeouts overlap (one after the other they
    were 30 s of the module's 37, the one-process backstop alone 14)."""

    def __init__(self, folder: Path, test: str, args: list, env: dict, conftest: bool,
                 merge_stderr: bool):
        (folder / 'test_hang.py').write_text(test)
        if conftest:
            (folder / 'conftest.py').write_text(HANG_STACKS_CONFTEST)
        self.folder, self.ended = folder, threading.Event()
        self.started = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, '-m', 'pytest', '-c', str(REPO / 'pytest.ini'), *args,
             '-p', 'no:cacheprovider', '--rootdir', str(folder), str(folder / 'test_hang.py')],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT if merge_stderr else subprocess.PIPE,
            text=True, cwd=folder, env=env, start_new_session=True)
        threading.Thread(target=self._wait, daemon=True).start()

    def _wait(self):
        self.stdout, self.stderr = self.proc.communicate()
        self.took = time.monotonic() - self.started
        self.kill()             # a worker that still spins holding the GIL goes with its group
        self.ended.set()

    def kill(self):
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def result(self, timeout: float) -> subprocess.CompletedProcess:
        """The run's result once it ended, `timeout` s after it started at most (then it is
        killed: subprocess.TimeoutExpired, as subprocess.run's timeout)."""
        if not self.ended.wait(max(self.started + timeout - time.monotonic(), 0)):
            self.kill()
            raise subprocess.TimeoutExpired(self.proc.args, timeout)
        return subprocess.CompletedProcess(self.proc.args, self.proc.returncode, self.stdout,
                                           self.stderr or '')


HANGING_TEST_NAME = 'test_a_hanging_test_fails_with_the_stacks_of_every_thread'
XDIST_HANG_TEST_NAME = 'test_a_hang_on_an_xdist_worker_is_reported_with_its_stacks'
GIL_TEST_NAME = 'test_a_hang_that_holds_the_gil_still_ends_with_its_stacks'


def without(*names: str) -> dict:
    return {k: v for k, v in os.environ.items() if k not in names}


@pytest.fixture(scope='module', autouse=True)
def hang_runs(request, tmp_path_factory):
    """name of a selected hang test -> its HangRun, all started as the module's first test
    starts (they wait on timeouts, in sleeps that take no CPU: see GIL_HANGING_TEST)."""
    from hang_stacks import ENV
    selected = {item.name for item in request.session.items
                if getattr(item, 'module', None) is request.module}
    runs = {}
    if HANGING_TEST_NAME in selected:
        runs[HANGING_TEST_NAME] = HangRun(
            tmp_path_factory.mktemp('hang'), HANGING_TEST, ['-o', f'timeout={HANG_TIMEOUT}'],
            dict(os.environ), conftest=False, merge_stderr=False)
    if XDIST_HANG_TEST_NAME in selected:
        # a run inside a run of the suite inherits the suite's folder (HRC_TEST_STACKS_DIR):
        # its gw0 wrote to the suite's gw0's file, which that worker emptied as its next test
        # started (CI, 2026-12-06); this run must use a folder of its own and leave the
        # inherited alone
        folder = tmp_path_factory.mktemp('xdist_hang')
        (folder / 'the_suites_stacks').mkdir()
        runs[XDIST_HANG_TEST_NAME] = HangRun(
            folder, HANGING_TEST, ['-o', 'timeout=4', '-n', '1'],
            {**os.environ, ENV: str(folder / 'the_suites_stacks')}, conftest=True,
            merge_stderr=False)
    for case in GIL_CASES:
        name = f'{GIL_TEST_NAME}[{case}]'
        if name in selected:
            test, workers, timeout, _ = GIL_CASES[case]
            runs[name] = HangRun(tmp_path_factory.mktemp('gil_hang'), test,
                                 [f'--timeout={timeout}', *workers],
                                 without(ENV, 'PYTEST_TIMEOUT', 'PYTEST_ADDOPTS'),
                                 conftest=True, merge_stderr=True)
    yield runs
    for run in runs.values():
        run.kill()
        run.ended.wait(60)


# pytest-timeout's timeout of the one-process runs: the shortest whole second (the hang
# starts as the test does; what is checked is that the dump comes, not when)
HANG_TIMEOUT = 1


def test_a_hanging_test_fails_with_the_stacks_of_every_thread(hang_runs):
    """pytest.ini's per-test timeout: a hang is a red test with its stacks, not a stuck CI."""
    result = hang_runs[HANGING_TEST_NAME].result(timeout=60)
    output = result.stdout + result.stderr
    assert result.returncode != 0
    assert 'Timeout' in output and 'test_hangs' in output
    assert 'helper' in output and 'MainThread' in output, output[-3000:]


def test_a_hang_on_an_xdist_worker_is_reported_with_its_stacks(hang_runs):
    """The suite runs on xdist workers, where pytest-timeout's own dump never reaches the log
    (the worker ends with os._exit: "worker 'gw0' crashed"): hang_stacks writes the threads'
    stacks before the timeout and the controller adds them to the crashed test's report
    (the run's timeout, 4 s, is the shortest whose dump comes MARGIN s before it)."""
    run = hang_runs[XDIST_HANG_TEST_NAME]
    result = run.result(timeout=120)
    output = result.stdout + result.stderr
    assert result.returncode != 0
    assert list((run.folder / 'the_suites_stacks').iterdir()) == []
    assert "crashed while running 'test_hang.py::test_hangs'" in output, output[-3000:]
    assert 'its threads 2 s before the test\'s timeout' in output, output[-3000:]
    assert 'test_hang.py", line 6 in test_hangs' in output, output[-3000:]
    assert output.count('Thread 0x') >= 2, output[-3000:]      # the helper's stack too


# a hang in native code that holds the GIL, as Fast DDS's livelock in destroy_participant did
# on a worker of the suite (test/hang_stacks.py): libc's sleep called through ctypes.PyDLL,
# which keeps the GIL for the whole call (a spinning regular expression did the same, at 14 s
# of CPU for the one-process case alone)
GIL_HANGING_TEST = ('import ctypes\n\n'
                    'def test_hangs_holding_the_gil():\n'
                    '    ctypes.PyDLL(None).sleep(60)\n')
# ... in the teardown of a test that failed, when pytest and pytest-timeout stop their timers
GIL_HANGING_TEARDOWN = ('import ctypes\nimport pytest\n\n'
                        '@pytest.fixture\n'
                        'def node():\n'
                        '    yield\n'
                        '    ctypes.PyDLL(None).sleep(60)\n\n'
                        'def test_hangs_holding_the_gil(node):\n'
                        '    assert False\n')
CRASHED = "crashed while running 'test_hang.py::test_hangs_holding_the_gil'"
# case -> (test, workers, --timeout, what the output says). On a worker the timeout is 4 s,
# the shortest whose dump comes MARGIN s before it; in one process HANG_TIMEOUT (the backstop
# then ends it at HANG_TIMEOUT + BACKSTOP = 11 s)
GIL_CASES = {
    'xdist': (GIL_HANGING_TEST, ['-n', '1'], 4,
              (CRASHED, 'when faulthandler ended the worker', 'Timeout (0:00:02)!',
               'test_hang.py", line 4 in test_hangs_holding_the_gil')),
    'one-process': (GIL_HANGING_TEST, [], HANG_TIMEOUT,
                    ('Timeout (0:00:11)!',
                     'test_hang.py", line 4 in test_hangs_holding_the_gil')),
    'xdist-teardown-after-a-failure': (GIL_HANGING_TEARDOWN, ['-n', '1'], 4,
                                       (CRASHED, 'test_hang.py", line 7 in node')),
}


@pytest.mark.parametrize('case', GIL_CASES)
def test_a_hang_that_holds_the_gil_still_ends_with_its_stacks(hang_runs, case):
    """pytest-timeout's timer thread cannot run while native code holds the GIL; faulthandler's
    watchdog can: on a worker it writes the stacks and ends the worker before the timeout (in
    a teardown after a failure too), in one process it ends it BACKSTOP s after. Without it the
    run below never ends (the 120 s limit runs out)."""
    from hang_stacks import BACKSTOP
    _, _, timeout, says = GIL_CASES[case]
    run = hang_runs[f'{GIL_TEST_NAME}[{case}]']
    result = run.result(timeout=120)
    output = result.stdout
    assert result.returncode != 0
    assert run.took < 60 + timeout + BACKSTOP, run.took
    for text in says:
        assert text in output, output[-3000:]


def test_importing_a_node_does_not_import_numba():
    """numba's import is 0.2 s of CPU at every node's start (a cell starts five to eight of
    them, the suite hundreds); the kernels import it where they run (the solver's sweep, the
    arm's distances, which the robot nodes warm up at start), not the nodes' modules."""
    from hrc_ros.ros.entry import COMMANDS
    nodes = [module for name, module in COMMANDS.items() if name.endswith('_node')]
    probe = ('import importlib, sys\n'
             f'for module in {nodes!r}:\n'
             '    importlib.import_module(module)\n'
             '    assert "numba" not in sys.modules, module\n'
             'print(len(sys.argv))\n')
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == '1', result.stderr[-2000:]


def test_the_schedulers_file_lists_name_files_that_exist_on_the_right_side():
    """conftest's work units: the arm's graph files, the plant's graph tests and the long
    computations it hands out first are test files (and tests) of the suite, on the graph's
    side and the computations' side (a renamed file or test would otherwise drop out of its
    unit silently)."""
    import conftest
    files = {p.name for p in (REPO / 'test').glob('test_*.py')}
    assert set(conftest.LONG_COMPUTE_FILES) <= conftest.COMPUTE_FILES & files
    graph_side = files - conftest.COMPUTE_FILES
    assert set(conftest.ARM_GRAPH_FILES) <= graph_side
    fleet = (REPO / 'test' / 'test_fleet.py').read_text()
    assert all(f'\ndef {name}(' in fleet for name in conftest.PLANT_GRAPH_TESTS)
    plant = f'test/test_fleet.py::{conftest.PLANT_GRAPH_TESTS[0]}'
    for split in (True, False):     # three workers or more; two
        assert conftest.work_unit('test/test_robot_nodes.py::t', split) == \
            conftest.GRAPH_UNITS[2 if split else 0]
        assert conftest.work_unit('test/test_replay.py::t', split) == conftest.GRAPH_UNITS[0]
        # the plant's --apply a unit of its own on two workers too, the rest of its file not
        assert conftest.work_unit(plant, split) == conftest.GRAPH_UNITS[1]
        assert conftest.work_unit('test/test_fleet.py::test_ctrl_c', split) == \
            'test/test_fleet.py'
        assert conftest.work_unit('test/test_queue.py::t', split) == 'test/test_queue.py'
    order = sorted(['test/test_belief.py', 'test/test_queue.py', *conftest.GRAPH_UNITS[::-1]],
                   key=conftest.unit_order)
    assert order == [*conftest.GRAPH_UNITS, 'test/test_queue.py', 'test/test_belief.py']


def test_the_plants_tests_have_time_for_their_fixtures_and_the_plant_run():
    """pytest-timeout counts fixture setup in a test's time and, with the thread method, ends
    the whole worker: the plant's tests (whose first one builds small_cell and runs hrc-fleet,
    killed after FLEET_TIMEOUT) get conftest.PLANT_TIMEOUT, with room for small_cell's solves
    at load (more than 2 min at load 8), and no other test does."""
    import ast
    import conftest
    fleet = ast.parse((REPO / 'test' / 'test_fleet.py').read_text())
    (fleet_timeout,) = [node.value.value for node in fleet.body if isinstance(node, ast.Assign)
                        and [t.id for t in node.targets] == ['FLEET_TIMEOUT']]
    assert conftest.PLANT_TIMEOUT >= fleet_timeout + 180

    class Item:
        def __init__(self, nodeid):
            self.nodeid, self.markers, self.fixturenames = nodeid, [], []

        def add_marker(self, marker):
            self.markers.append(marker)
    plant = Item(f'test/test_fleet.py::{conftest.PLANT_GRAPH_TESTS[0]}')
    others = [Item('test/test_fleet.py::test_ctrl_c_on_an_embedded_cluster_exits_130'),
              Item('test/test_queue.py::test_x')]
    conftest.pytest_collection_modifyitems(None, [plant, *others])
    assert [(m.name, m.args) for m in plant.markers] == [('timeout', (conftest.PLANT_TIMEOUT,))]
    assert all(not item.markers for item in others)


def uv_flags(tmp_path, environment: dict, config: str = '') -> subprocess.CompletedProcess:
    """scripts/uv_flags.py run by this interpreter with pip's settings from `config` (a pip.conf
    of the test's) and `environment` alone: no PIP_* variable of the caller's, no user or XDG
    file (the machine's /etc/pip.conf is still read, as pip always does)."""
    env = {key: value for key, value in os.environ.items()
           if not key.startswith(('PIP_', 'UV_', 'SSL_CERT'))}
    (tmp_path / 'pip.conf').write_text(config)
    (tmp_path / 'home').mkdir(exist_ok=True)
    env.update(PIP_CONFIG_FILE=str(tmp_path / 'pip.conf'), HOME=str(tmp_path / 'home'),
               XDG_CONFIG_HOME=str(tmp_path / 'home'), XDG_CONFIG_DIRS=str(tmp_path / 'home'),
               **environment)
    return subprocess.run([sys.executable, str(REPO / 'scripts' / 'uv_flags.py')], env=env,
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=60)


def flag_values(stdout: str, flag: str) -> list[str]:
    items = stdout.splitlines()
    return [items[i + 1] for i, item in enumerate(items) if item == flag]


def test_the_bootstraps_uv_install_gets_what_pip_install_would_use(tmp_path):
    """scripts/bootstrap.sh installs with uv where it can: uv must resolve from the indexes,
    links and constraints `pip install` would use, as pip's own parser reads them: the
    [install] section over [global], a variable over the files, an empty variable ignored.
    uv takes --index-url once only (twice is an error that sends the bootstrap to pip)."""
    config = ('[global]\nindex-url = https://global.example/simple\n'
              'extra-index-url = file:///file-extra/simple\nfind-links = /file-links\n'
              'timeout = 42\ncert = /file/ca.crt\n'
              '[install]\nindex-url = https://install.example/simple\n'
              '[download]\nno-index = true\n')
    run = uv_flags(tmp_path, {'PIP_EXTRA_INDEX_URL': '', 'PIP_FIND_LINKS': '/env-links',
                              'PIP_CONSTRAINT': '/caps.txt', 'PIP_PRE': '1'}, config)
    assert run.returncode == 0, run.stderr
    out = run.stdout
    assert flag_values(out, '--index-strategy') == ['unsafe-best-match']
    assert flag_values(out, '--index-url') == ['https://install.example/simple']
    assert flag_values(out, '--extra-index-url') == ['file:///file-extra/simple']
    assert flag_values(out, '--find-links') == ['/env-links']
    assert flag_values(out, '--constraint') == ['/caps.txt']
    assert flag_values(out, '--prerelease') == ['allow']
    assert '--no-index' not in out.splitlines()          # [download]'s, not install's
    assert out.splitlines()[:2] == ['env SSL_CERT_FILE=/file/ca.crt', 'env UV_HTTP_TIMEOUT=42']

    offline = uv_flags(tmp_path, {'PIP_NO_INDEX': '1', 'PIP_FIND_LINKS': '/wheels'})
    assert offline.returncode == 0, offline.stderr
    assert '--no-index' in offline.stdout.splitlines()
    assert flag_values(offline.stdout, '--index-url') == []
    assert flag_values(offline.stdout, '--find-links') == ['/wheels']


def test_a_pip_setting_uv_is_not_handed_sends_the_bootstrap_to_pip(tmp_path):
    for environment, name in (({'PIP_PROXY': 'http://proxy.example:3128'}, 'proxy'),
                              ({'PIP_ONLY_BINARY': ':all:'}, 'only-binary'),
                              ({'PIP_REQUIRE_HASHES': '1'}, 'require-hashes')):
        run = uv_flags(tmp_path, environment)
        assert run.returncode == 3, (name, run.stdout)
        assert run.stdout == ''
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and name in lines[0], (name, run.stderr)
