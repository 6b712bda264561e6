"""The package installs the way its users install it, checked with the real tools.

- ROS workspace: `colcon build` of a copy of the package (so nothing is written into the
  checkout) gives the ament layout, and every console script declared in setup.py is found the
  way `ros2 run hrc_ros EXE` finds it: the first prefix on AMENT_PREFIX_PATH holding the marker
  `share/ament_index/resource_index/packages/hrc_ros`, then a walk of `<prefix>/lib/hrc_ros` for
  an executable file named exactly EXE (ros2cli `ros2run.api.get_executable_path` on
  `ament_index_python.get_package_prefix`). Tools and nodes then run from the install with the
  environment its `local_setup.sh` sets; the nodes join the ROS graph and stop cleanly on SIGINT.
- pip: `pip install` into a fresh environment puts the same scripts in `<venv>/bin` and the
  data in `<venv>/share/hrc_ros`, where `hrc_ros.core.mdp.policy.share_dir()` finds them.
- The launch file and the ROS parameter files, against docs/DESIGN.md's parameter table; the
  params files are parsed by rcl itself (through rclpy), as `--params-file` does.
- `.ci/run` fails when pytest collects no tests.

Nodes run in a DDS domain of their own (215..230: the range above the Linux ephemeral ports) on
localhost only, so parallel test runs do not see each other.
"""

from __future__ import annotations

import ast
import configparser
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PACKAGE = 'hrc_ros'
# What setup.py and package.xml need; copied into a scratch workspace for the builds.
PACKAGE_FILES = ('setup.py', 'setup.cfg', 'package.xml', 'README.md', 'resource', PACKAGE,
                 'config', 'launch', 'policies')
MARKER = Path('share', 'ament_index', 'resource_index', 'packages', PACKAGE)
NODE_NAMES = {  # executable -> node name (DESIGN.md, config/hrc_params.yaml)
    'belief_estimator_node': 'belief_estimator',
    'decision_node': 'decision',
    'task_manager_node': 'task_manager',
    'cell_sim_node': 'cell_sim',
    'cell_view_node': 'cell_view',
    'body_tracking_node': 'body_tracking',
    'tracker_sim_node': 'tracker_sim',
    'hmi_node': 'hmi',
    'robot_bridge_node': 'robot_bridge',
    'cobot_sim_node': 'cobot_sim',
}
# Nodes that cannot start on hrc_params.yaml alone (no camera pose): the params they also need.
EXTRA_PARAMS = {'body_tracking_node': 'body_tracking_sim_params.yaml',
                'tracker_sim_node': 'body_tracking_sim_params.yaml'}
# ... and the arguments: the HMI on a free port, not 8080 that another run may hold. Named for
# the node: the params file's `hmi: port: 8080` outranks a plain `-p port:=0` (rcl: a node's
# own entry beats the wildcard), which left this test on 8080 until 2026-12-06.
EXTRA_ARGS = {'hmi_node': ['-p', 'hmi:port:=0']}
DOMAIN_ID = random.Random().randint(215, 230)
BUILD_TIMEOUT = 120
GRAPH_TIMEOUT = 30.0
SHUTDOWN_TIMEOUT = 10.0
# Variables an outer workspace or install may have set; the checks start without them.
INHERITED = ('PYTHONPATH', 'AMENT_PREFIX_PATH', 'COLCON_PREFIX_PATH', 'CMAKE_PREFIX_PATH',
             'HRC_ROS_SHARE')


def declared_scripts() -> tuple[list[str], list[str]]:
    """setup.py's NODES and TOOLS names (read with ast, setup.py is not run)."""
    found = {}
    for statement in ast.parse((REPO / 'setup.py').read_text()).body:
        if isinstance(statement, ast.Assign) and len(statement.targets) == 1:
            target = statement.targets[0]
            if isinstance(target, ast.Name) and target.id in ('NODES', 'TOOLS',
                                                              'ROS_INSTALL_NODES'):
                found[target.id] = ast.literal_eval(statement.value)
    return list(found['NODES']), list(found['TOOLS']), list(found['ROS_INSTALL_NODES'])


# ROS_INSTALL_NODES: installed, but they run only in a ROS install (control_msgs)
NODES, TOOLS, ROS_INSTALL_NODES = declared_scripts()


def clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in INHERITED}
    env.update(ROS_DOMAIN_ID=str(DOMAIN_ID), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1', **extra)
    return env


def copy_package(destination: Path) -> Path:
    destination.mkdir(parents=True)
    for name in PACKAGE_FILES:
        source = REPO / name
        if source.is_dir():
            shutil.copytree(source, destination / name,
                            ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
        elif source.is_file():
            shutil.copy2(source, destination / name)
    return destination


def run(cmd, *, timeout, **kwargs) -> subprocess.CompletedProcess:
    # Not from the checkout: `python -c` would import its hrc_ros/ (and launch/) from the cwd.
    kwargs.setdefault('cwd', os.path.sep)
    return subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=timeout, **kwargs)


def colcon_build(workspace: Path, *options: str) -> Path:
    """Build the package in `workspace` (src/hrc_ros) with colcon; returns the install base."""
    copy_package(workspace / 'src' / PACKAGE)
    result = run([sys.executable, '-m', 'colcon', '--log-base', str(workspace / 'log'), 'build',
                  '--base-paths', str(workspace / 'src'),
                  '--build-base', str(workspace / 'build'),
                  '--install-base', str(workspace / 'install'), *options],
                 cwd=workspace, timeout=BUILD_TIMEOUT,
                 env=clean_env(COLCON_HOME=str(workspace / 'colcon_home')))
    assert result.returncode == 0, f'colcon build {" ".join(options)} failed:\n{result.stdout}'
    return workspace / 'install'


def sourced_env(install_base: Path) -> dict[str, str]:
    """The environment after `. install/local_setup.sh`, as a user sources it."""
    result = run(['sh', '-c', '. "$1/local_setup.sh" && env -0', 'sh', str(install_base)],
                 env=clean_env(), timeout=30)
    assert result.returncode == 0, result.stdout
    return dict(item.split('=', 1) for item in result.stdout.split('\0') if '=' in item)


def ros2_run_path(package: str, executable: str, ament_prefix_path: str) -> str | None:
    """`ros2 run`'s lookup: ament_index_python.get_package_prefix + ros2run's walk of lib/PKG."""
    for prefix in ament_prefix_path.split(os.pathsep):
        if prefix and (Path(prefix) / 'share' / 'ament_index' / 'resource_index' / 'packages'
                       / package).is_file():
            break
    else:
        raise LookupError(f'package {package} not found on AMENT_PREFIX_PATH')
    matches = []
    for dirpath, dirnames, filenames in os.walk(os.path.join(prefix, 'lib', package)):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith('.'))
        for filename in sorted(filenames):
            path = os.path.join(dirpath, filename)
            if filename == executable and os.access(path, os.X_OK):
                matches.append(path)
    assert len(matches) <= 1, f'ros2 run would refuse: several executables {matches}'
    return matches[0] if matches else None


def interpreter(script: str) -> str:
    with open(script) as handle:
        shebang = handle.readline()
    assert shebang.startswith('#!'), f'{script} has no shebang'
    return shebang[2:].split()[0]


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory) -> Path:
    """A colcon build (the default, copying install) of the package; the install base."""
    return colcon_build(tmp_path_factory.mktemp('colcon_ws'))


@pytest.fixture(scope='module')
def ros_env(colcon_install) -> dict[str, str]:
    return sourced_env(colcon_install)


@pytest.fixture(scope='module')
def prefix(colcon_install) -> Path:
    return colcon_install / PACKAGE   # colcon's default isolated layout: one prefix a package


# --- (b) the ament layout of the colcon install ---------------------------------------------

@pytest.mark.parametrize('relative', [
    str(MARKER),
    'share/hrc_ros/package.xml',
    'share/hrc_ros/config/default.yaml',
    'share/hrc_ros/config/paper.yaml',
    'share/hrc_ros/config/hrc_params.yaml',
    'share/hrc_ros/config/case_study_params.yaml',
    'share/hrc_ros/launch/hrc.launch.py',
])
def test_colcon_install_layout(prefix, relative):
    assert (prefix / relative).is_file(), f'{relative} missing from the colcon install'


def test_colcon_install_ships_the_policies(prefix):
    shipped = sorted(p.name for p in (REPO / 'policies').glob('*.npz'))
    assert 'default.npz' in shipped
    installed = sorted(p.name for p in (prefix / 'share' / PACKAGE / 'policies').glob('*.npz'))
    assert installed == shipped
    pomdp = sorted(p.name for p in (REPO / 'policies' / 'pomdp').glob('*.npz'))
    assert {'default.npz', 'fail_safe_unaware.npz'} <= set(pomdp)
    assert sorted(p.name for p in (prefix / 'share' / PACKAGE / 'policies' / 'pomdp')
                  .glob('*.npz')) == pomdp


def test_colcon_install_ships_the_hmis_pages_and_the_charting_library(prefix):
    """The HMI serves its pages and the console's vendored uPlot from the package (no CDN):
    both are package data, in the colcon install as in pip's (with uPlot's licence)."""
    from hrc_ros.ros.hmi.server import PAGES
    static = next((prefix / 'lib').glob('python3*/site-packages')) / PACKAGE / 'ros' / 'hmi' \
        / 'static'
    for name, _ in PAGES.values():
        assert (static / name).is_file(), f'{static / name} missing'
    assert 'MIT License' in (static / 'vendor' / 'LICENSE-uPlot.txt').read_text()


def test_colcon_install_declares_the_setup_py_scripts(prefix):
    """The built distribution's console scripts are exactly setup.py's NODES and TOOLS."""
    entry_points = list(prefix.glob('lib/python3*/site-packages/hrc_ros-*.egg-info/'
                                    'entry_points.txt'))
    assert len(entry_points) == 1, entry_points
    parser = configparser.ConfigParser()
    parser.read(entry_points[0])
    assert set(parser['console_scripts']) == set(NODES) | set(TOOLS) | set(ROS_INSTALL_NODES)


# --- (c) ros2 run finds every console script ------------------------------------------------

@pytest.mark.parametrize('executable', NODES + TOOLS + ROS_INSTALL_NODES)
def test_ros2_run_finds(executable, prefix, ros_env):
    path = ros2_run_path(PACKAGE, executable, ros_env['AMENT_PREFIX_PATH'])
    assert path == str(prefix / 'lib' / PACKAGE / executable), (
        f'ros2 run {PACKAGE} {executable}: No executable found')
    assert os.access(path, os.X_OK)


def test_ament_index_agrees(prefix, ros_env, monkeypatch):
    packages = pytest.importorskip('ament_index_python.packages')
    monkeypatch.setenv('AMENT_PREFIX_PATH', ros_env['AMENT_PREFIX_PATH'])
    assert Path(packages.get_package_prefix(PACKAGE)) == prefix
    assert Path(packages.get_package_share_directory(PACKAGE)) == prefix / 'share' / PACKAGE


# --- (d) the installed executables run ------------------------------------------------------

def test_installed_tool_runs(prefix, ros_env):
    path = ros2_run_path(PACKAGE, 'hrc-solve', ros_env['AMENT_PREFIX_PATH'])
    result = run([path, '--help'], env=ros_env, timeout=60)
    assert result.returncode == 0, result.stdout
    assert 'usage: hrc-solve' in result.stdout


def test_install_is_self_contained(prefix, ros_env):
    """The install's code and data are used, not the checkout's or the dev venv's."""
    python = interpreter(str(prefix / 'lib' / PACKAGE / 'hrc-solve'))
    result = run([python, '-c', 'import hrc_ros, hrc_ros.core.mdp.policy as p; '
                  'print(hrc_ros.__file__); print(p.share_dir())'], env=ros_env, timeout=60)
    assert result.returncode == 0, result.stdout
    module, share = result.stdout.split()[-2:]
    assert Path(module).is_relative_to(prefix), f'hrc_ros imported from {module}'
    assert Path(share) == prefix / 'share' / PACKAGE


class GraphProbe:
    """An rclpy node in a Context of its own that watches the ROS graph."""

    def __init__(self, rclpy):
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('packaging_probe', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def wait_for(self, name: str, namespace: str, process, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and process.poll() is None:
            if (name, namespace) in self.node.get_node_names_and_namespaces():
                return True
            self.executor.spin_once(timeout_sec=0.1)
        return False

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope='module')
def graph_probe(monkeypatch_module):
    rclpy = pytest.importorskip('rclpy')
    monkeypatch_module.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    probe = GraphProbe(rclpy)
    yield probe
    probe.close()


@pytest.fixture(scope='module')
def monkeypatch_module():
    with pytest.MonkeyPatch.context() as patch:
        yield patch


@pytest.mark.parametrize('executable', NODES)
def test_installed_node_joins_graph_and_stops_on_sigint(executable, prefix, ros_env,
                                                        graph_probe, tmp_path):
    name = NODE_NAMES[executable]
    path = ros2_run_path(PACKAGE, executable, ros_env['AMENT_PREFIX_PATH'])
    config = prefix / 'share' / PACKAGE / 'config'
    params = ['--params-file', str(config / 'hrc_params.yaml')]
    if executable in EXTRA_PARAMS:
        params += ['--params-file', str(config / EXTRA_PARAMS[executable])]
    params += EXTRA_ARGS.get(executable, [])
    log = tmp_path / f'{executable}.log'
    with open(log, 'w') as output:
        process = subprocess.Popen([path, '--ros-args', *params],
                                   env=ros_env, stdin=subprocess.DEVNULL, stdout=output,
                                   stderr=subprocess.STDOUT, start_new_session=True)
    try:
        joined = graph_probe.wait_for(name, '/', process, GRAPH_TIMEOUT)
        assert joined, (f'{executable} did not show up as /{name} within {GRAPH_TIMEOUT} s '
                        f'(exit code {process.poll()}):\n{log.read_text()}')
        if executable == 'hmi_node':        # on the port the OS chose (it joins, then binds)
            deadline = time.monotonic() + GRAPH_TIMEOUT
            while 'worker page' not in log.read_text() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert 'worker page http://127.0.0.1:' in log.read_text(), log.read_text()
            assert ':8080/' not in log.read_text(), log.read_text()
        os.killpg(process.pid, signal.SIGINT)   # what Ctrl-C in a terminal does
        try:
            code = process.wait(timeout=SHUTDOWN_TIMEOUT)
        except subprocess.TimeoutExpired:
            pytest.fail(f'{executable} ignored SIGINT for {SHUTDOWN_TIMEOUT} s:\n'
                        f'{log.read_text()}')
        assert code == 0, f'{executable} exited with {code} on SIGINT:\n{log.read_text()}'
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


# --- colcon build --symlink-install ---------------------------------------------------------

def test_symlink_install_runs_from_the_workspace(tmp_path):
    """`colcon build --symlink-install` (setuptools develop) also gives a working `ros2 run`:
    the scripts in lib/hrc_ros, the code imported through the build directory's symlinks, and
    the data linked into share/hrc_ros."""
    install = colcon_build(tmp_path, '--symlink-install')
    env = sourced_env(install)
    prefix = install / PACKAGE
    assert (prefix / 'share' / PACKAGE / 'config' / 'default.yaml').is_symlink()
    path = ros2_run_path(PACKAGE, 'hrc-solve', env['AMENT_PREFIX_PATH'])
    assert path == str(prefix / 'lib' / PACKAGE / 'hrc-solve')
    result = run([path, '--help'], env=env, timeout=60)
    assert result.returncode == 0 and 'usage: hrc-solve' in result.stdout, result.stdout
    result = run([interpreter(path), '-c', 'import hrc_ros; print(hrc_ros.__file__)'],
                 env=env, timeout=60)
    module = Path(result.stdout.split()[-1]).resolve()
    assert module.is_relative_to(tmp_path / 'src' / PACKAGE), f'hrc_ros imported from {module}'


# --- (e) pip install ------------------------------------------------------------------------

def test_pip_install_puts_scripts_on_path_and_data_in_share(tmp_path):
    """A non-editable pip install into a fresh virtual environment: the console scripts in
    bin/ (pip writes them; setup.cfg's lib/hrc_ros is for colcon only), the data in
    share/hrc_ros, and share_dir() finding it there.

    `pip --python VENV` rather than `--prefix`: with --prefix the scripts' shebang is the
    interpreter running pip, not the one that owns the prefix."""
    source = copy_package(tmp_path / 'src')
    venv = tmp_path / 'venv'
    run([sys.executable, '-m', 'venv', '--without-pip', str(venv)], timeout=60, check=True)
    # Its dependencies (numpy, ..., and setuptools to build) come from this environment,
    # behind the fresh site-packages, so hrc_ros itself comes from the fresh install.
    site = next((venv / 'lib').glob('python3*/site-packages'))
    dependencies = [p for p in sys.path if p.endswith('site-packages')]
    (site / 'zz_dependencies.pth').write_text('\n'.join(dependencies) + '\n')
    result = run([sys.executable, '-m', 'pip', '--python', str(venv / 'bin' / 'python'),
                  'install', '--quiet', '--no-deps', '--no-index', '--no-build-isolation',
                  str(source)], env=clean_env(), timeout=BUILD_TIMEOUT)
    assert result.returncode == 0, result.stdout
    for executable in NODES + TOOLS:
        assert os.access(venv / 'bin' / executable, os.X_OK), f'bin/{executable} missing'
    assert not (venv / 'lib' / PACKAGE).exists()
    share = venv / 'share' / PACKAGE
    for relative in ('package.xml', 'config/default.yaml', 'config/paper.yaml',
                     'config/hrc_params.yaml', 'launch/hrc.launch.py'):
        assert (share / relative).is_file(), f'share/hrc_ros/{relative} missing'
    static = next((venv / 'lib').glob('python3*/site-packages')) / PACKAGE / 'ros' / 'hmi' \
        / 'static'
    from hrc_ros.ros.hmi.server import PAGES
    for name, _ in PAGES.values():            # the HMI's pages are package data
        assert (static / name).is_file(), f'{static / name} missing'
    assert (static / 'vendor' / 'LICENSE-uPlot.txt').is_file()     # with uPlot's licence
    assert (venv / MARKER).is_file()

    result = run([str(venv / 'bin' / 'hrc-solve'), '--help'], env=clean_env(), timeout=60)
    assert result.returncode == 0 and 'usage: hrc-solve' in result.stdout, result.stdout
    result = run([str(venv / 'bin' / 'python'), '-c',
                  'import hrc_ros, hrc_ros.core.paths as p; print(hrc_ros.__file__); '
                  'print(p.share_dir()); print(p.default_config_path())'],
                 env=clean_env(), timeout=60)
    assert result.returncode == 0, result.stdout
    module, share_dir, config = result.stdout.split()[-3:]
    assert Path(module).is_relative_to(venv), f'hrc_ros imported from {module}'
    assert Path(share_dir) == share
    assert Path(config).is_file()


# --- the launch file ------------------------------------------------------------------------

LAUNCH_FILE = REPO / 'launch' / 'hrc.launch.py'
LAUNCH_ARGUMENTS = {'params_file', 'config', 'policy', 'selector', 'pomdp_policy', 'belief_mode',
                    'namespace', 'use_sim', 'view', 'body_tracking', 'hmi', 'robot'}


def test_launch_plan_starts_the_cell_with_the_users_arguments(tmp_path):
    from hrc_ros.ros.launch_plan import ARGUMENTS, cell_nodes
    assert {a.name for a in ARGUMENTS} == LAUNCH_ARGUMENTS
    share = tmp_path / 'share'
    base = str(share / 'config' / 'hrc_params.yaml')
    plan = cell_nodes(share)
    # the default: the decision nodes, the view and the simulated cell, last
    assert [(n.executable, n.name) for n in plan] == [
        ('belief_estimator_node', 'belief_estimator'), ('decision_node', 'decision'),
        ('task_manager_node', 'task_manager'), ('cell_view_node', 'cell_view'),
        ('cell_sim_node', 'cell_sim')]
    assert all(n.namespace == '' and n.remappings == [] for n in plan)
    assert all(n.parameters == [base, {}] for n in plan)   # nothing set: the params file rules
    plan = cell_nodes(share, params_file='extra.yaml', namespace='cell1', config='c.yaml',
                      policy='p.npz', selector='qmdp', use_sim='false')
    by_name = {n.name: n for n in plan}
    # a real cell: no simulated human, and the view only when asked for
    assert set(by_name) == {'belief_estimator', 'decision', 'task_manager'}
    assert all(n.namespace == 'cell1' for n in plan)
    assert by_name['decision'].parameters == [base, 'extra.yaml', {
        'config': 'c.yaml', 'policy': 'p.npz', 'selector': 'qmdp'}]
    assert by_name['task_manager'].parameters == [base, 'extra.yaml', {'config': 'c.yaml'}]
    # the pomdp selector with the exact posterior it plans with
    by_name = {n.name: n for n in cell_nodes(share, config='c.yaml', selector='pomdp',
                                             belief_mode='posterior')}
    assert by_name['belief_estimator'].parameters == [base, {'config': 'c.yaml',
                                                             'belief_mode': 'posterior'}]
    assert by_name['decision'].parameters[-1] == {'config': 'c.yaml', 'selector': 'pomdp'}
    # a POMDP policy of its own (a fitted configuration's): the decision node's alone
    by_name = {n.name: n for n in cell_nodes(share, config='c.yaml', selector='pomdp',
                                             pomdp_policy='q.npz')}
    assert by_name['decision'].parameters[-1] == {'config': 'c.yaml', 'selector': 'pomdp',
                                                  'pomdp_policy': 'q.npz'}
    assert by_name['belief_estimator'].parameters[-1] == {'config': 'c.yaml'}
    assert {n.name for n in cell_nodes(share, use_sim='false', view='true')} == \
        {'belief_estimator', 'decision', 'task_manager', 'cell_view'}
    assert 'cell_view' not in {n.name for n in cell_nodes(share, view='false')}
    # the shipped params file named again is not loaded twice
    assert cell_nodes(share, params_file=base)[0].parameters == [base, {}]
    # the cell with the arm: the bridge and the simulated arm, the cell switched to the arm
    by_name = {n.name: n for n in cell_nodes(share, robot='sim', config='c.yaml',
                                             belief_mode='posterior')}
    assert {'robot_bridge', 'cobot_sim'} <= set(by_name)
    estimator = by_name['belief_estimator'].parameters[-1]
    assert (estimator['distance_source'], estimator['belief_mode'], estimator['config']) == \
        ('arm_links', 'posterior', 'c.yaml')
    assert by_name['task_manager'].parameters[-1] == {'config': 'c.yaml', 'robot_progress': True}
    assert by_name['cell_sim'].parameters[-1] == {'config': 'c.yaml', 'person': '3d'}
    assert by_name['cell_view'].parameters[-1]['robot'] is True
    assert 'robot_bridge' not in {n.name for n in cell_nodes(share)}
    # no config:= with the arm: every node reads the arm's model (docs/ROBOT.md 6), for which
    # the shipped policies hold one
    # (a layer for every node before the user's params file, which may name another)
    from hrc_ros.ros.launch_plan import AllNodes
    arm = str(share / 'config' / 'arm.yaml')
    plan = cell_nodes(share, robot='sim', params_file='mine.yaml')
    assert all(n.parameters[:3] == [base, AllNodes(config=arm), 'mine.yaml']
               and isinstance(n.parameters[1], AllNodes)
               and 'config' not in n.parameters[-1] for n in plan), \
        [(n.name, n.parameters) for n in plan]
    assert all(n.parameters[-1].get('config', '') == '' and len(n.parameters) == 2
               for n in cell_nodes(share))
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path
    from hrc_ros.core.paths import arm_config_path
    assert default_policy_path(load_config(arm_config_path())).name == 'arm.npz'
    with pytest.raises(ValueError, match="tracker_sim's synthetic body"):
        cell_nodes(share, robot='sim', body_tracking='true')
    assert 'body_tracking' in {n.name for n in cell_nodes(share, robot='sim', use_sim='false',
                                                          body_tracking='true')}
    for name, bad in (('selector', 'greedy'), ('belief_mode', 'kalman'), ('use_sim', 'maybe'),
                      ('view', 'yes'),
                      ('body_tracking', 'on'), ('hmi', 'yes'), ('robot', 'real')):
        with pytest.raises(ValueError, match=name):
            cell_nodes(share, **{name: bad})


def _resolved_parameter(node, params_dir, name: str):
    """The value rcl gives parameter `name` of `node` started as the launch file starts it
    (`ros_arguments`: its params files in order, the arguments' overrides last)."""
    import rclpy
    from hrc_ros.ros import stop
    from hrc_ros.ros.launch_plan import ros_arguments
    context = rclpy.Context()
    rclpy.init(args=['plan', '--ros-args', *ros_arguments(node, params_dir)], context=context,
               **stop.init_options())
    try:
        probe = rclpy.create_node('launch_plan_probe', context=context)
        try:
            return probe.declare_parameter(name, '').value
        finally:
            probe.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_the_arm_config_of_robot_sim_yields_to_a_params_file_that_names_one(tmp_path,
                                                                             ros_domain_id):
    """robot:=sim without config:= reads the arm's model (docs/ROBOT.md 4), but, as the
    config argument says ('' = the params files'), a params_file that sets `config` keeps it:
    for every node (`/**`) and for one node's section alike. config:= wins over both."""
    from hrc_ros.core.paths import share_dir
    from hrc_ros.ros.launch_plan import cell_nodes
    share = share_dir()
    arm = str(share / 'config' / 'arm.yaml')
    mine = tmp_path / 'mine.yaml'
    mine.write_text(yaml.safe_dump({
        '/**': {'ros__parameters': {'config': '/cells/mine.yaml'}},
        '/**/decision': {'ros__parameters': {'config': '/cells/decision.yaml'}}}))
    for params_file, config, expected in (
            ('', '', {'decision': arm, 'task_manager': arm}),
            (str(mine), '', {'decision': '/cells/decision.yaml',
                             'task_manager': '/cells/mine.yaml'}),
            (str(mine), 'c.yaml', {'decision': 'c.yaml', 'task_manager': 'c.yaml'})):
        plan = {n.name: n for n in cell_nodes(share, params_file=params_file, config=config,
                                              robot='sim')}
        for name, want in expected.items():
            got = _resolved_parameter(plan[name], tmp_path, 'config')
            assert got == want, (params_file, config, name, plan[name].parameters)


def test_launch_plan_reads_human_motion_from_a_body_tracker(tmp_path):
    """body_tracking:=true: body_tracking_node feeds human/*; with the simulated cell its motion
    goes to tracker_sim_node (remapped), with the synthetic camera's pose."""
    from hrc_ros.ros.launch_plan import cell_nodes
    share = tmp_path / 'share'
    base = str(share / 'config' / 'hrc_params.yaml')
    sim = str(share / 'config' / 'body_tracking_sim_params.yaml')
    plan = {n.name: n for n in cell_nodes(share, body_tracking='true', params_file='mine.yaml')}
    assert set(plan) == {'belief_estimator', 'decision', 'task_manager', 'cell_view',
                         'body_tracking', 'tracker_sim', 'cell_sim'}
    assert plan['cell_sim'].remappings == [('human/joint_states', 'sim/human/joint_states'),
                                           ('human/skeleton', 'sim/human/skeleton')]
    assert all(n.remappings == [] for name, n in plan.items() if name != 'cell_sim')
    assert all(n.parameters == [base, sim, 'mine.yaml', {}] for n in plan.values())
    real = {n.name: n for n in cell_nodes(share, body_tracking='true', use_sim='false',
                                           params_file='camera.yaml')}
    assert set(real) == {'belief_estimator', 'decision', 'task_manager', 'body_tracking'}
    assert real['body_tracking'].parameters == [base, 'camera.yaml', {}]


def test_launch_plan_starts_the_hmi(tmp_path):
    """hmi:=true starts hmi_node; with the simulated cell the simulated person keeps
    answering and the page only shows it, hmi:=answers hands the answers to the page."""
    from hrc_ros.ros.launch_plan import cell_nodes
    share = tmp_path / 'share'
    assert 'hmi' not in {n.name for n in cell_nodes(share)}
    shown = {n.name: n.parameters[-1] for n in cell_nodes(share, hmi='true', config='c.yaml')}
    assert shown['hmi'] == {'config': 'c.yaml', 'worker_answers': False}
    assert shown['cell_sim'] == {'config': 'c.yaml'}
    answered = {n.name: n.parameters[-1] for n in cell_nodes(share, hmi='answers')}
    assert answered['hmi'] == {} and answered['cell_sim'] == {'answer_requests': False}
    real = {n.name: n.parameters[-1] for n in cell_nodes(share, hmi='true', use_sim='false')}
    assert set(real) == {'belief_estimator', 'decision', 'task_manager', 'hmi'}
    assert real['hmi'] == {}                     # on a real cell the worker answers


def test_launch_file_turns_the_plan_into_nodes(monkeypatch, tmp_path):
    """Run launch/hrc.launch.py with recording stand-ins for ROS `launch` and `launch_ros`
    (not installable here): it declares every plan argument and starts the plan's nodes, and
    the folder of its override files is gone once launch shuts down (issue 37: one
    tempfile.mkdtemp folder was left per launch)."""
    import tempfile
    import types

    from hrc_ros.ros.launch_plan import ARGUMENTS, PARAMS_DIR_PREFIX, cell_nodes

    class Recorded:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    class LaunchConfiguration(Recorded):
        def perform(self, context):
            return context[self.args[0]]

    class RegisterEventHandler(Recorded):
        pass

    class OnShutdown(Recorded):
        pass

    modules = {
        'launch': {'LaunchDescription': Recorded},
        'launch.actions': {'DeclareLaunchArgument': Recorded, 'OpaqueFunction': Recorded,
                           'RegisterEventHandler': RegisterEventHandler},
        'launch.event_handlers': {'OnShutdown': OnShutdown},
        'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration},
        'launch_ros': {}, 'launch_ros.actions': {'Node': Recorded},
        'ament_index_python': {},
        'ament_index_python.packages': {'get_package_share_directory': lambda p: str(tmp_path)},
    }
    for name, members in modules.items():
        monkeypatch.setitem(sys.modules, name, types.SimpleNamespace(**members))
    temporary = tmp_path / 'tmp'
    temporary.mkdir()
    monkeypatch.setattr(tempfile, 'tempdir', str(temporary))
    import importlib.util
    spec = importlib.util.spec_from_file_location('hrc_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    *declared, opaque = description.args[0]
    assert [(d.args[0], d.kwargs['default_value'], tuple(d.kwargs.get('choices', ())))
            for d in declared] == [(a.name, a.default, a.choices) for a in ARGUMENTS]
    values = {a.name: a.default for a in ARGUMENTS}
    values.update(namespace='cell2', selector='mls', body_tracking='true')
    launched = [opaque.kwargs['function'](values) for _ in range(3)]     # three launches
    plan = cell_nodes(tmp_path, **values)
    for _handler, *nodes in launched:
        assert [(n.kwargs['package'], n.kwargs['executable'], n.kwargs['name'],
                 n.kwargs['namespace'], n.kwargs['remappings']) for n in nodes] == \
            [(PACKAGE, p.executable, p.name, p.namespace, p.remappings) for p in plan]
        # the parameters: the plan's files, and its overrides as a file of the node's own
        # name (one under `/**` would lose to hrc_params.yaml's section of the node: rcl's merge)
        for node, planned in zip(nodes, plan):
            files = node.kwargs['parameters']
            assert len(files) == len(planned.parameters)
            for path, want in zip(files, planned.parameters):
                if isinstance(want, dict):
                    assert yaml.safe_load(open(path).read()) == \
                        {f'/**/{planned.name}': {'ros__parameters': want}}
                    assert Path(path).parent.parent == temporary
                else:
                    assert path == want
    assert len(list(temporary.glob(f'{PARAMS_DIR_PREFIX}*'))) == 3
    for handler, *_nodes in launched:          # launch shuts down: its OnShutdown handlers run
        assert isinstance(handler, RegisterEventHandler)
        assert isinstance(handler.args[0], OnShutdown)
        handler.args[0].kwargs['on_shutdown'](object(), object())
    assert list(temporary.iterdir()) == [], 'a launch left its folder behind'


def test_a_launch_killed_before_it_could_clean_up_leaves_its_folder_to_the_next(tmp_path):
    """The folder of a launch whose process is gone (killed with SIGKILL: no shutdown event)
    is removed by the next launch; a running launch's folder, and anything else, stays."""
    from hrc_ros.ros.launch_plan import PARAMS_DIR_PREFIX, params_dir
    gone = subprocess.Popen(['true'])
    gone.wait()                               # its pid names no process now
    dead = tmp_path / f'{PARAMS_DIR_PREFIX}{gone.pid}_abc'
    running = tmp_path / f'{PARAMS_DIR_PREFIX}{os.getpid()}_def'
    other = tmp_path / 'hrc_launch_notes.txt'
    for folder in (dead, running):
        folder.mkdir()
        (folder / 'decision_3.yaml').write_text('{}')
    other.write_text('not a launch folder')
    new = params_dir(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [running.name, other.name, new.name])
    assert new.name.startswith(f'{PARAMS_DIR_PREFIX}{os.getpid()}_')


# --- the ROS parameter files against DESIGN.md's table --------------------------------------

RCL_TYPES = {'string': 'STRING', 'double': 'DOUBLE', 'int': 'INTEGER', 'bool': 'BOOL'}


def design_parameters() -> dict[str, dict[str, tuple[str, object]]]:
    """docs/DESIGN.md "Node parameters": node -> {parameter: (type, default)}."""
    text = (REPO / 'docs' / 'DESIGN.md').read_text()
    table = text.split('## Node parameters', 1)[1].split('\n## ', 1)[0]
    nodes = {name: {} for name in NODE_NAMES.values()}
    common = {}
    for line in table.splitlines():
        cells = [cell.strip() for cell in line.strip().strip('|').split('|')]
        if len(cells) < 3 or not cells[1].startswith('`'):
            continue
        node, names, spec = cells[0], re.findall(r'`(\w+)`', cells[1]), cells[2]
        for name in names:
            if spec.startswith('as '):   # "as belief_estimator"
                nodes[node][name] = nodes[spec.split()[1]][name]
                continue
            kind, _, default = spec.partition(', ')
            default = default.split(' = ')[0].replace('`', '')
            (common if node == 'all' else nodes[node])[name] = (kind, yaml.safe_load(default))
    for parameters in nodes.values():
        parameters.update(common)
    return nodes


EFFECTIVE_PARAMETERS = """
import json, os, sys
import rclpy
from rclpy.signals import SignalHandlerOptions
namespace, names, args = sys.argv[1], sys.argv[2].split(','), sys.argv[3:]
context = rclpy.Context()
rclpy.init(args=args, context=context, signal_handler_options=SignalHandlerOptions.NO)
result = {}
for name in names:
    node = rclpy.create_node(name, namespace=namespace, context=context,
                             automatically_declare_parameters_from_overrides=True)
    result[name] = {key: (p.type_.name, p.value if not hasattr(p.value, 'tolist')
                          else p.value.tolist())
                    for key, p in node.get_parameters_by_prefix('').items()
                    if key not in ('use_sim_time', 'start_type_description_service')}
print(json.dumps(result), flush=True)
os._exit(0)   # no destroy_node(): process exit frees the nodes
"""


def effective_parameters(*params_files: Path, namespace: str = '/cell1') -> dict:
    """What rcl gives each node from `--params-file`s: node -> {name: (type, value)}.

    In a process of its own that exits without destroying its nodes: in this test session
    `Node.destroy_node` once spun for minutes in rclpy's `destroy_when_not_in_use` (a node
    handle still counted in use); a process keeps any such hang to this call, which its
    timeout then reports, and skips the destruction path altogether."""
    args = ['--ros-args']
    for path in params_files:
        args += ['--params-file', str(path)]
    result = subprocess.run(
        [sys.executable, '-X', 'faulthandler', '-c', EFFECTIVE_PARAMETERS, namespace,
         ','.join(NODE_NAMES.values()), *args], capture_output=True, text=True, timeout=60,
        env={**os.environ, 'ROS_DOMAIN_ID': str(DOMAIN_ID)})
    assert result.returncode == 0, result.stderr[-3000:]
    return {node: {key: (kind, value) for key, (kind, value) in parameters.items()}
            for node, parameters in json.loads(result.stdout).items()}


def check_type(kind: str, rcl_type: str, value) -> None:
    base, _, size = kind.partition('[')
    if not size:
        assert rcl_type == RCL_TYPES[base]
        return
    assert rcl_type == RCL_TYPES[base] + '_ARRAY'
    if size != ']':
        assert len(value) == int(size[:-1])


@pytest.mark.parametrize('name', ['hrc_params.yaml', 'case_study_params.yaml',
                                  'body_tracking_sim_params.yaml'])
def test_params_file_parses(name):
    document = yaml.safe_load((REPO / 'config' / name).read_text())
    design = design_parameters()
    known = set().union(*design.values())
    for section, content in document.items():
        assert section == '/**' or section.removeprefix('/**/') in design, section
        assert set(content) == {'ros__parameters'}, section
        unknown = set(content['ros__parameters']) - known
        assert not unknown, f'{name} [{section}]: not in DESIGN.md: {unknown}'


def test_hrc_params_give_every_node_the_design_defaults():
    design = design_parameters()
    path = REPO / 'config' / 'hrc_params.yaml'
    shared = set(yaml.safe_load(path.read_text())['/**']['ros__parameters'])
    effective = effective_parameters(path)
    for node, parameters in design.items():
        got = effective[node]
        for name, (kind, default) in parameters.items():
            if default == []:   # rcl cannot type an empty list: left to the node's default
                assert name not in got, f'{node}.{name}'
                continue
            assert name in got, f'config/hrc_params.yaml gives {node} no {name}'
            rcl_type, value = got[name]
            check_type(kind, rcl_type, value)
            assert value == default, f'{node}.{name}: {value!r}, DESIGN.md says {default!r}'
        # `/**` parameters reach every node; a node that does not declare one ignores it.
        assert set(got) <= set(parameters) | shared, f'{node}: {set(got) - set(parameters)}'


def test_case_study_params_add_the_schedule():
    """rcl reads config/case_study_params.yaml into the core's scenario (`case_study()`)."""
    from hrc_ros.core.study.simulation import case_study
    from hrc_ros.ros.launch_plan import scenario_parameters
    design = design_parameters()
    effective = effective_parameters(REPO / 'config' / 'hrc_params.yaml',
                                     REPO / 'config' / 'case_study_params.yaml')
    expected = scenario_parameters(case_study())
    for node, section in (('task_manager', '/**/task_manager'), ('cell_sim', '/**/cell_sim')):
        for name, value in expected[section]['ros__parameters'].items():
            rcl_type, got = effective[node][name]
            check_type(design[node][name][0], rcl_type, got)
            assert (list(got) if isinstance(got, (list, tuple)) else got) == value, name


def test_body_tracking_sim_params_give_both_camera_nodes_one_pose():
    from hrc_ros.core.cell.tracking import RigidTransform
    design = design_parameters()
    effective = effective_parameters(REPO / 'config' / 'hrc_params.yaml',
                                     REPO / 'config' / 'body_tracking_sim_params.yaml')
    poses = []
    for node in ('body_tracking', 'tracker_sim'):
        pose = []
        for name in ('camera_frame', 'camera_translation', 'camera_rotation'):
            rcl_type, value = effective[node][name]
            check_type(design[node][name][0], rcl_type, value)
            pose.append(value if isinstance(value, str) else list(value))
        poses.append(pose)
    assert poses[0] == poses[1]
    RigidTransform.from_parameters(poses[0][1], poses[0][2])   # a unit quaternion
    assert effective['cell_sim']['sensor_rate'][1] == 30.0


# --- .ci/run ---------------------------------------------------------------------------------

@pytest.mark.parametrize('pytest_code, ci_code', [(0, 0), (1, 1), (2, 2), (5, 1)])
def test_ci_run_fails_when_no_test_ran(tmp_path, pytest_code, ci_code):
    """.ci/run passes pytest's exit code through, but 5 (no tests collected) is a failure."""
    (tmp_path / '.ci').mkdir()
    (tmp_path / 'scripts').mkdir()
    shutil.copy2(REPO / '.ci' / 'run', tmp_path / '.ci' / 'run')
    (tmp_path / 'scripts' / 'test.sh').write_text(f'exit {pytest_code}\n')
    result = run(['bash', str(tmp_path / '.ci' / 'run')], timeout=30, cwd='/')
    assert result.returncode == ci_code, result.stdout
