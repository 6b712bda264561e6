"""Test-session isolation of the ROS graph, and the policy files the node tests share.

Before anything can call `rclpy.init`, this module (imported by pytest ahead of every test
module) gives the session its DDS domain: the ROS_DOMAIN_ID of the environment when one is set
(scripts/test.sh sets one per run; set your own to watch a test with other tools), else a
random one in 30..99 (on pytest-xdist, the first worker's; every other worker has one of its
own, `worker_domain`), and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, written to os.environ so that
subprocesses (the multi-process suite, the refused decision node) inherit them. Two sessions on
one machine, or a session next to a running cell, then never see each other's topics.

Discovery speed. A Fast DDS participant that joins the graph discovers the ones already there
only when they next announce themselves, every 3 s by default (measured here: up to ~2 s before
a new process sees an old publisher, with localhost discovery). The multi-process test needs
every node connected before the first epoch, so the session exports a default participant
profile (FASTRTPS_DEFAULT_PROFILES_FILE, unless one is set already) that announces every
0.1 s. Only discovery timing changes; the nodes' QoS and behaviour do not.
"""

from __future__ import annotations

import atexit
import os
import random
import shutil
import signal
import tempfile
import uuid
from pathlib import Path

import pytest
from file_times import CPU_PROPERTY, FileTimes, cpu_now

ROS_DOMAIN_RANGE = (30, 99)

# A suite started with SIGINT ignored (a background job of a non-interactive shell, `cmd &`)
# would pass the ignoring on to every process it starts: Python then installs no
# KeyboardInterrupt handler, and the stop tests' Ctrl-C stops nothing (a run hung 246 s). The
# session takes SIGINT back as Python's default; an exec'd child then gets the default action.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# The suite's CPU (it is bound by CPU on two cores: bench/README.md, "The test suite"):
# - numba kernels serial. Each parallel kernel of core/ is compiled twice, parallel and
#   serial (core/parallel.py), and the parallel build is the costly one: 49 of the 60 CPU
#   seconds of the MDP kernels' first compile on a fresh clone, 20 of 30 for the POMDP's
#   (2026-12-07). Two workers on two cores leave a parallel call no free core to win with,
#   so the suite's processes (workers, nodes, commands, Ray's tasks) run the serial build;
#   test_parallel and test_tie_rule set the modes they test (serial, parallel, auto) and
#   hold both builds equal. An explicit HRC_KERNEL_THREADS wins.
# - compiled Python kept. An environment with PYTHONDONTWRITEBYTECODE (this machine's has it)
#   makes every node process and command of the suite compile hrc_ros again, about 0.1 CPU
#   seconds each, hundreds of times a run; the suite writes its bytecode under the checkout's
#   .pytest_cache (PYTHONPYCACHEPREFIX: never the source tree, never a shared folder another
#   user could fill, gone with the checkout) and reads it from there.
# - numpy's BLAS (OpenBLAS) on one thread, as the kernels. OpenBLAS starts a thread per core
#   in every process, and its threads wait spinning: beside the suite's other worker they
#   take the core the work needs. test_fit_prior's recovery test alone, with two busy loops
#   beside it: 58.5 s with OpenBLAS's default threads, 11.3 s with one (10.8 s and 10.2 s on
#   a quiet machine, where the second thread only burned 50% more CPU; 2026-12-07). An
#   explicit OPENBLAS_NUM_THREADS wins (scripts/test.sh sets it before the warm-up too).
os.environ.setdefault('HRC_KERNEL_THREADS', 'serial')
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
if not os.environ.get('PYTHONPYCACHEPREFIX'):
    os.environ['PYTHONPYCACHEPREFIX'] = str(Path(__file__).resolve().parents[1]
                                            / '.pytest_cache' / 'pycache')
os.environ.pop('PYTHONDONTWRITEBYTECODE', None)


def worker_domain(base: int, worker: str) -> int:
    """The DDS domain of a pytest-xdist worker (`PYTEST_XDIST_WORKER`, gw0, gw1, ...) in a run
    whose domain is `base`: gw0 and a run without workers use `base`, worker k another one of
    1..100 ((base - 1 + 37 k) mod 100 + 1), so that two workers' graphs never see each other."""
    k = int(worker[2:]) if worker.startswith('gw') and worker[2:].isdigit() else 0
    return base if k == 0 else (base - 1 + 37 * k) % 100 + 1


_given = os.environ.get('ROS_DOMAIN_ID', '').strip()
ROS_DOMAIN_ID = worker_domain(
    int(_given) if _given else random.SystemRandom().randint(*ROS_DOMAIN_RANGE),
    os.environ.get('PYTEST_XDIST_WORKER', ''))
os.environ['ROS_DOMAIN_ID'] = str(ROS_DOMAIN_ID)
# this run's name, inherited by its xdist workers and every process they start: the check for
# node processes left behind (`_no_node_left_behind`) takes only this run's
os.environ.setdefault('HRC_TEST_RUN', uuid.uuid4().hex)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_STATIC_PEERS', None)
os.environ.pop('ROS_LOCALHOST_ONLY', None)   # deprecated; conflicts with the range above

FAST_DDS_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="hrc_ros_tests" is_default_profile="true">
    <rtps>
      <builtin>
        <discovery_config>
          <leaseAnnouncement><sec>0</sec><nanosec>100000000</nanosec></leaseAnnouncement>
        </discovery_config>
      </builtin>
    </rtps>
  </participant>
</profiles>
"""
if not (os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
        or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE')):
    # one folder per run (pytest-xdist's workers inherit the controller's variable), removed
    # when the process that made it exits, after its workers: every run left one in /tmp.
    # Fast DDS reads the file when a process makes its first participant
    _folder = tempfile.mkdtemp(prefix='hrc_ros_dds_')
    atexit.register(shutil.rmtree, _folder, True)
    _profile = Path(_folder) / 'fastdds_profile.xml'
    _profile.write_text(FAST_DDS_PROFILE)
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(_profile)   # Fast DDS 2.x
    os.environ['FASTDDS_DEFAULT_PROFILES_FILE'] = str(_profile)    # Fast DDS 3.x


@pytest.fixture(scope='session')
def ros_domain_id() -> int:
    """The session's DDS domain (already in os.environ)."""
    assert os.environ['ROS_DOMAIN_ID'] == str(ROS_DOMAIN_ID)
    return ROS_DOMAIN_ID


# s: how long a module's node processes may take to finish their stop after the module ended
LEFTOVER_GRACE = 10.0


@pytest.fixture(scope='module', autouse=True)
def _no_node_left_behind(request):
    """After every module: no process of hrc_ros's commands of this run's DDS domain may be
    left (test/leftovers.py). One left is killed and fails the module's last test, naming it:
    else it would write on the next module's graph (a second arm, a second clock)."""
    yield
    from leftovers import ancestors, left_behind
    left = left_behind(ROS_DOMAIN_ID, LEFTOVER_GRACE, ancestors(os.getpid()),
                       os.environ['HRC_TEST_RUN'], os.environ.get('PYTEST_XDIST_WORKER'))
    if left:
        pytest.fail(f'{request.module.__name__} left {len(left)} node process(es) running in '
                    f'DDS domain {ROS_DOMAIN_ID} {LEFTOVER_GRACE:g} s after its last test '
                    '(killed now): ' + '; '.join(f'pid {pid}: {command[:200]}'
                                                 for pid, command in left), pytrace=False)


@pytest.fixture(scope='session')
def default_config():
    from hrc_ros.core.config import load_config
    from hrc_ros.core.paths import default_config_path
    return load_config(default_config_path())


@pytest.fixture(scope='session')
def policy_path(default_config) -> str:
    """The shipped policy of the default configuration. It is a tracked file: when it is
    missing or does not match, the tests fail saying so (they never solve one of their own,
    which would hide it)."""
    from hrc_ros.core.mdp.policy import PolicyError, default_policy_path, load_policy
    shipped = default_policy_path()
    try:
        load_policy(shipped, default_config)
    except PolicyError as exc:
        pytest.fail(f'the shipped policy does not load: {exc}')
    return str(shipped)


@pytest.fixture(scope='session')
def other_config_policy_path(default_config, tmp_path_factory) -> str:
    """A policy solved for another configuration: the reduced rho = sigma = 1 model."""
    other = default_config.with_overrides({'model': {'rho': 1, 'sigma': 1}})
    return str(_solve(other, tmp_path_factory.mktemp('policy') / 'rho1_sigma1.npz'))


def _solve(config, path: Path) -> Path:
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.mdp.policy import save_policy
    from hrc_ros.core.mdp.solver import solve
    return save_policy(path, solve(HRCModel(config)), config)


@pytest.fixture(scope='session')
def model(default_config):
    """The full-size default model."""
    from hrc_ros.core.model import HRCModel
    return HRCModel(default_config)


@pytest.fixture(scope='session')
def policy(default_config, policy_path):
    """The default policy (shipped, or solved once), loaded."""
    from hrc_ros.core.mdp.policy import load_policy
    return load_policy(policy_path, default_config)


@pytest.fixture
def graph():
    """test_nodes.Graph: a Context, its executor and a probe node, closed after the test."""
    from test_nodes import Graph
    g = Graph()
    try:
        yield g
    finally:
        g.close()


# -- the HMI's browser tests -------------------------------------------------------------------
CHROMIUM_PACKAGES = ('chromium', 'fonts-liberation')
APT_TIMEOUT = 900


def _apt(*args: str) -> tuple[int, str]:
    import subprocess
    env = {**os.environ, 'DEBIAN_FRONTEND': 'noninteractive'}
    try:
        result = subprocess.run(['apt-get', '-o', 'DPkg::Lock::Timeout=300', *args],
                                stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                env=env, timeout=APT_TIMEOUT)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return 1, str(exc)
    return result.returncode, (result.stdout + result.stderr)[-2000:]


def install_chromium() -> str:
    """Install Debian's Chromium (these machines run as root); '' or why it failed."""
    import shutil
    if not shutil.which('apt-get'):
        return 'no apt-get on this machine'
    if hasattr(os, 'geteuid') and os.geteuid() != 0:
        return 'not root: run apt-get install chromium as root'
    install = ('install', '-y', '-q', '--no-install-recommends', *CHROMIUM_PACKAGES)
    code, output = _apt(*install)
    if code != 0:                       # stale package lists: update them once, then retry
        _apt('update', '-q')
        code, output = _apt(*install)
    return '' if code == 0 else f'apt-get {" ".join(install)} exited {code}:\n{output}'


@pytest.fixture(scope='session')
def chromium() -> str:
    """Debian's Chromium, installed when it is missing. The HMI's browser tests fail (never
    skip) without it: they are part of the suite, in CI too."""
    from hrc_ros.ros.hmi.browser import BrowserError, chromium_path
    try:
        return chromium_path()
    except BrowserError:
        pass
    reason = install_chromium()
    try:
        return chromium_path()
    except BrowserError as exc:
        pytest.fail(f'the HMI browser tests need Chromium: {exc}; '
                    + (f'installing it failed: {reason}' if reason else
                       f'apt-get installed {" ".join(CHROMIUM_PACKAGES)}, yet it is not there'))


@pytest.fixture(scope='session')
def browser(chromium):
    """One headless Chromium for the session (Playwright, Debian's browser), shared by the
    browser tests; every test opens its own context (cookies, pages) in it."""
    from playwright.sync_api import sync_playwright

    from hrc_ros.ros.hmi.browser import launch
    playwright = sync_playwright().start()
    try:
        instance = launch(playwright, chromium)
    except Exception:
        playwright.stop()
        raise
    try:
        yield instance
    finally:
        instance.close()
        playwright.stop()


# -- the time per test file, in the log of every run (test/file_times.py) --------------------
_file_times = FileTimes()
_cpu_at_start = pytest.StashKey[float]()


def pytest_collection_finish(session):
    _file_times.collection_done()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    item.stash[_cpu_at_start] = cpu_now()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if call.when == 'teardown' and _cpu_at_start in item.stash:
        report.user_properties.append((CPU_PROPERTY, cpu_now() - item.stash[_cpu_at_start]))


def pytest_runtest_logreport(report):
    cpu = sum(value for name, value in report.user_properties if name == CPU_PROPERTY)
    _file_times.add(report.nodeid, report.when, report.duration, cpu)


def pytest_terminal_summary(terminalreporter):
    if not _file_times.seconds:
        return
    terminalreporter.section('time per test file')
    terminalreporter.write_line(_file_times.table())
    if os.environ.get('HRC_TEST_TIMES'):
        _file_times.write(os.environ['HRC_TEST_TIMES'])


# -- workers (pytest-xdist, scripts/test.sh) --------------------------------------------------
# The suite is about half computation (solves, fits, evaluations: one core each) and half the
# ROS graph (node processes over DDS, waits on epochs in real time). The graph's tests form
# work units, GRAPH_UNITS, each run one after the other on one worker in that worker's own DDS
# domain (`worker_domain`: two graphs never see each other's topics): the plant's `--apply`
# (PLANT_GRAPH_TESTS: a Ray computation of about 1.5 min with two decision nodes beside it)
# always a unit of its own, which a second worker takes beside the rest of the graph (in one
# unit it made the graph's worker the run's critical path: 580 s against 460 s of computation
# on the other, CI log of 2026-12-06); on three workers or more (HRC_TEST_WORKERS=3) the arm's
# cell, the learning loop and the console a unit too. Each file of
# COMPUTE_FILES is a unit of its own (its module fixtures built once) for whichever worker is
# free. The graph units are handed out first (one to each of the first workers ready), then
# the longest computations (LONG_COMPUTE_FILES, by the time per file in the CI log), then the
# rest, so that no long unit starts last. A file not listed is the graph's: a new test file is
# safe by default, only slower. A test of a listed file that uses the graph (the
# ros_domain_id or graph fixture) must be in GRAPH_TESTS: collection fails otherwise.
# (pytest-xdist's own `--dist loadgroup` does not group under pytest 9.2, whose node ids it can
# no longer rename, so the units come from `GraphScheduling`.)
COMPUTE_FILES = frozenset({
    'test_belief.py', 'test_cell.py', 'test_config_policy.py', 'test_conversions.py',
    'test_evaluate.py', 'test_fit.py', 'test_fit_prior.py', 'test_hmi_core.py',
    'test_model.py', 'test_observation.py', 'test_parallel.py', 'test_plant_fit.py',
    'test_plant_generate.py', 'test_pomdp.py', 'test_pomdp_hrc.py', 'test_protocol.py',
    'test_queue.py', 'test_queue_pomdp.py', 'test_recordings.py', 'test_robot.py',
    'test_robot_monitor.py', 'test_hmi_shift.py',
    'test_selection.py', 'test_simulator.py', 'test_solver.py', 'test_stream.py',
    'test_stream_fit.py', 'test_stream_queue_fit.py', 'test_tasks.py', 'test_tie_rule.py',
    'test_tracking.py', 'test_cli.py', 'test_fit_rate.py', 'test_hostile_files.py',
    'test_layout.py', 'test_liveness.py', 'test_fleet.py', 'test_leftovers.py'})
# hrc-fleet's --apply against decision nodes (the plant run's module fixture starts them), and
# the retry of a killed Ray worker beside them: the rest of test_fleet, the Ray engine's checks
# without nodes, is a unit of its own, on a Ray of its own where it lands on another worker (a
# Ray per worker process, ray_session)
PLANT_GRAPH_TESTS = (
    'test_the_plant_promotes_the_drifted_cell_keeps_the_unchanged_and_reports_the_corrupt',
    'test_apply_swaps_the_promoted_cell_live_and_a_cell_not_running_is_reported',
    'test_apply_changes_nothing_on_a_node_of_another_selector_or_when_the_set_is_refused',
    'test_apply_night_after_night_and_a_set_the_node_refuses_at_the_boundary',
    'test_apply_reports_a_namespace_whose_decision_node_is_not_ours_and_goes_on',
    'test_a_pomdp_cell_is_solved_checked_with_its_selector_and_swapped_with_its_pomdp_policy',
    'test_a_worker_killed_mid_task_is_retried_and_the_report_is_right')
# pytest-timeout (pytest.ini: 300 s, the thread method, which ends the whole worker) counts a
# test's fixtures' setup in its time: the plant's first test builds the POMDP cell's policies
# (small_cell) and runs hrc-fleet (plant_run, killed after test_fleet.FLEET_TIMEOUT), which at
# load 8 came to more than 300 s together (the worker ended 290 s after small_cell began,
# "node down", 2026-12-06): the plant's tests get PLANT_TIMEOUT (hrc-fleet's own limit
# grew from 360 s to 600 s after a load-8 run outran it, 2026-12-07)
PLANT_TIMEOUT = 900
GRAPH_TESTS = frozenset({
    'test_stream_queue_fit.py::test_a_bag_the_node_suite_records_with_a_queue_fits_the_queue_stream',
    # a decision node in-process
    'test_hostile_files.py::test_the_decision_node_refuses_hostile_files_at_once_and_keeps_deciding',
    # ROS commands that must refuse before any node starts: should one start after all, it
    # starts beside the graph's tests, not beside another graph
    'test_cli.py::test_hrc_case_study_refuses_a_bag_or_out_that_is_no_folder',
    'test_cli.py::test_hrc_bag_record_refuses_its_output_before_waiting_for_publishers',
    *(f'test_fleet.py::{name}' for name in PLANT_GRAPH_TESTS)})
GRAPH_FIXTURES = frozenset({'ros_domain_id', 'graph'})
# the graph's third unit on three workers or more: the arm's cell, the learning loop and the
# console (about half of the rest of the graph's time, by the time per test file)
ARM_GRAPH_FILES = frozenset({
    'test_robot_case_study.py', 'test_robot_nodes.py', 'test_robot_scenarios.py',
    'test_robot_hostile.py', 'test_cobot_sim_motion.py', 'test_robot_graph.py',
    'test_speed_scaling.py', 'test_learning_loop.py', 'test_hmi_console.py'})
GRAPH_UNITS = ('graph', 'graph-plant', 'graph-arm')
# the arm's unit apart only on three workers or more: on two cores a third worker is no faster
# once the plant runs beside the graph (518.6 s against 527.3 s from fresh clones, quiet), and
# its higher load met timing flakes (bench/README.md). Two workers with the plant apart were
# measured green once quiet (and at load 8 in bench/README.md's table where it says so)
SPLIT_GRAPH_WORKERS = 3
LONG_COMPUTE_FILES = ('test_fleet.py', 'test_queue_pomdp.py', 'test_queue.py', 'test_stream.py',
                      'test_pomdp_hrc.py', 'test_fit.py', 'test_config_policy.py', 'test_cli.py',
                      'test_fit_prior.py', 'test_liveness.py', 'test_robot.py')


def unit_order(unit: str) -> tuple[int, int]:
    """The rank of a work unit in the order the workers get them (above)."""
    if unit in GRAPH_UNITS:
        return 0, GRAPH_UNITS.index(unit)
    file = unit.rsplit('/', 1)[-1]
    return (1, LONG_COMPUTE_FILES.index(file)) if file in LONG_COMPUTE_FILES else (2, 0)


def is_plant_test(nodeid: str) -> bool:
    """A test of PLANT_GRAPH_TESTS (any of its parameters)."""
    path, _, name = nodeid.partition('::')
    return path.endswith('test_fleet.py') and name.split('[', 1)[0] in PLANT_GRAPH_TESTS


def work_unit(nodeid: str, split: bool = False) -> str:
    """The unit of work of a test on the xdist workers (above): its file, or a graph unit
    (the arm's only when the graph is `split`)."""
    path, _, name = nodeid.partition('::')
    file = path.rsplit('/', 1)[-1]
    if file in COMPUTE_FILES and f'{file}::{name.split("[", 1)[0]}' not in GRAPH_TESTS:
        return path
    if is_plant_test(nodeid):
        return GRAPH_UNITS[1]
    return GRAPH_UNITS[2] if split and file in ARM_GRAPH_FILES else GRAPH_UNITS[0]


def pytest_collection_modifyitems(config, items):
    for item in items:
        if is_plant_test(item.nodeid):
            item.add_marker(pytest.mark.timeout(PLANT_TIMEOUT))
    wrong = [item.nodeid for item in items
             if work_unit(item.nodeid) not in GRAPH_UNITS
             and GRAPH_FIXTURES & set(item.fixturenames)]
    if wrong:
        raise pytest.UsageError('tests of a COMPUTE_FILES file that use the ROS graph must be '
                                f'in conftest.GRAPH_TESTS: {", ".join(wrong)}')


def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling
    split = int(config.getoption('numprocesses') or 0) >= SPLIT_GRAPH_WORKERS

    class GraphScheduling(LoadScopeScheduling):
        """xdist's scheduling by scope, the scope being `work_unit`'s."""

        def _split_scope(self, nodeid: str) -> str:
            return work_unit(nodeid, split)

        def _assign_work_unit(self, node) -> None:
            # the queue in `unit_order` (a stable sort: xdist's order among equals)
            for unit in reversed(sorted(self.workqueue, key=unit_order)):
                self.workqueue.move_to_end(unit, last=False)
            super()._assign_work_unit(node)
    return GraphScheduling(config, log)


def pytest_configure(config):
    # a hang on an xdist worker is reported with its stacks (test/hang_stacks.py)
    from hang_stacks import HangStacks
    config.pluginmanager.register(HangStacks(config), 'hrc-hang-stacks')
