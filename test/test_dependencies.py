"""Every third-party import of the package is declared for both install routes (issue 17: in the
colcon route `hrc-fit` on a bag failed with "decoding bag messages without ROS needs
mcap_ros2": package.xml declared mcap only).

The imports are read from the code (every `import` and `from ... import` in hrc_ros/ and launch/,
also inside functions), not from a list kept by hand; `DEPENDENCIES` says for each import name
which pip requirement and which rosdep key provide it, and the test checks:

- pip route: the requirement is in requirements.txt (what the README's two commands and
  `pip install -r requirements.txt .` install), and the installed distribution that provides
  the module is that requirement or one of its dependencies; a non-ROS package is also in
  setup.py's install_requires (ROS packages are not: in a ROS install they are not pip
  distributions, and colcon's scripts would refuse to start);
- colcon route: the key is an `exec_depend` of package.xml, and either a ROS package, a key of
  rosdistro's python.yaml that resolves on Jazzy's platforms (`ROSDISTRO_KEYS`), or defined in
  the shipped rosdep/hrc_ros.yaml with that pip package (for PyPI-only packages such as mcap).

A new import fails the test until its row is added: import name -> pip name -> rosdep key.
"""

from __future__ import annotations

import ast
import functools
import importlib.metadata as metadata
import re
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SOURCES = ('hrc_ros', 'launch')
ROSDEP_YAML = REPO / 'rosdep' / 'hrc_ros.yaml'
ROS = 'ros'            # the rosdep key is the ROS package of that name
COLCON_ONLY = None     # no pip route: imported only by the launch file (ros2 launch)
ROS_INSTALL_ONLY = 'a ROS install only'   # no wheel: imported only by these modules, which
# stop at start with one line where it is missing (speed_scaling_node: control_msgs)
ROS_INSTALL_ONLY_MODULES = ('hrc_ros/ros/nodes/speed_scaling_node.py',)

# import name: (pip requirement, rosdep key). Add a row for each new third-party import.
DEPENDENCIES = {
    'numpy': ('numpy', 'python3-numpy'),
    'scipy': ('scipy', 'python3-scipy'),
    'yaml': ('pyyaml', 'python3-yaml'),
    'matplotlib': ('matplotlib', 'python3-matplotlib'),
    'PIL': ('pillow', 'python3-pil'),
    'numba': ('numba', 'python3-numba-pip'),
    'mcap': ('mcap', 'python3-mcap-pip'),
    'mcap_ros2': ('mcap-ros2-support', 'python3-mcap-ros2-support-pip'),
    'aiohttp': ('aiohttp', 'python3-aiohttp-pip'),
    'ray': ('ray', 'python3-ray-pip'),
    'grpc': ('grpcio', 'python3-grpcio-pip'),
    'mujoco': ('mujoco', 'python3-mujoco-pip'),
    'playwright': ('playwright', 'python3-playwright-pip'),
    'rclpy': ('ros-jazzy-rclpy', ROS),
    'rcl_interfaces': ('ros-jazzy-rclpy', ROS),
    'builtin_interfaces': ('ros-jazzy-rclpy', ROS),
    'std_msgs': ('ros-jazzy-common-interfaces', ROS),
    'std_srvs': ('ros-jazzy-common-interfaces', ROS),
    'sensor_msgs': ('ros-jazzy-common-interfaces', ROS),
    'geometry_msgs': ('ros-jazzy-common-interfaces', ROS),
    'diagnostic_msgs': ('ros-jazzy-common-interfaces', ROS),
    'visualization_msgs': ('ros-jazzy-common-interfaces', ROS),
    'trajectory_msgs': ('ros-jazzy-common-interfaces', ROS),
    'control_msgs': (ROS_INSTALL_ONLY, ROS),
    'ament_index_python': (COLCON_ONLY, ROS),
    'launch': (COLCON_ONLY, ROS),
    'launch_ros': (COLCON_ONLY, ROS),
}
# rosdistro rosdep/python.yaml keys that resolve on Ubuntu noble and Debian (checked there:
# python3-numba does not resolve on noble, hence the -pip key of rosdep/hrc_ros.yaml).
ROSDISTRO_KEYS = {'python3-numpy', 'python3-scipy', 'python3-yaml', 'python3-matplotlib',
                  'python3-pil', 'python3-pytest'}


def third_party_imports() -> dict[str, set[str]]:
    """Top-level import name -> the files (relative) that import it."""
    found: dict[str, set[str]] = {}
    for source in SOURCES:
        for path in sorted((REPO / source).rglob('*.py')):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split('.')[0]
                    if top not in sys.stdlib_module_names and top != 'hrc_ros':
                        found.setdefault(top, set()).add(str(path.relative_to(REPO)))
    return found


def canonical(name: str) -> str:
    return re.sub(r'[-_.]+', '-', name).lower()


def requirement_names(lines) -> set[str]:
    names = set()
    for line in lines:
        line = line.split('#', 1)[0].strip()
        if line and not line.startswith('-'):
            names.add(canonical(re.match(r'[A-Za-z0-9._-]+', line).group(0)))
    return names


def install_requires() -> set[str]:
    for node in ast.walk(ast.parse((REPO / 'setup.py').read_text())):
        if isinstance(node, ast.keyword) and node.arg == 'install_requires':
            return requirement_names(ast.literal_eval(node.value))
    raise AssertionError('setup.py has no install_requires')


def package_xml_depends(*tags: str) -> set[str]:
    root = ElementTree.parse(REPO / 'package.xml').getroot()
    return {element.text.strip() for tag in tags for element in root.iter(tag)}


@functools.cache
def providers() -> dict[str, list[str]]:
    """Import name -> the installed distributions that provide it."""
    return metadata.packages_distributions()


def distribution_closure(requirement: str) -> set[str]:
    """The installed distribution `requirement` and everything it requires, transitively
    (extras left out)."""
    seen, todo = set(), [canonical(requirement)]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue
        todo += [canonical(re.match(r'[A-Za-z0-9._-]+', r).group(0)) for r in requires
                 if 'extra ==' not in r]
    return seen


IMPORTS = third_party_imports()


def test_every_third_party_import_has_a_row():
    missing = sorted(set(IMPORTS) - set(DEPENDENCIES))
    assert not missing, (f'imports without a row in DEPENDENCIES (import -> pip -> rosdep): '
                         f'{ {name: sorted(IMPORTS[name]) for name in missing} }')
    unused = sorted(set(DEPENDENCIES) - set(IMPORTS))
    assert not unused, f'rows for imports the code no longer has: {unused}'


@pytest.mark.parametrize('module', sorted(IMPORTS))
def test_the_pip_route_installs(module):
    pip, _ = DEPENDENCIES[module]
    if pip is COLCON_ONLY:
        assert all(path.startswith('launch/') for path in IMPORTS[module]), (
            f'{module} is imported by the package itself, not only by the launch file: it '
            f'needs a pip requirement ({sorted(IMPORTS[module])})')
        return
    if pip is ROS_INSTALL_ONLY:
        assert set(IMPORTS[module]) <= set(ROS_INSTALL_ONLY_MODULES), (
            f'{module} has no wheel and may be imported only by {ROS_INSTALL_ONLY_MODULES}, '
            f'not by {sorted(set(IMPORTS[module]) - set(ROS_INSTALL_ONLY_MODULES))}')
        return
    requirements = requirement_names((REPO / 'requirements.txt').read_text().splitlines())
    assert canonical(pip) in requirements, f'requirements.txt does not list {pip} ({module})'
    if not pip.startswith('ros-'):
        assert canonical(pip) in install_requires(), \
            f"setup.py's install_requires does not list {pip} ({module})"
    installed = {canonical(d) for d in providers().get(module, [])}
    assert installed & distribution_closure(pip), (
        f'{module} is installed by {sorted(installed)}, which {pip} does not bring')


@pytest.mark.parametrize('module', sorted(IMPORTS))
def test_the_colcon_route_installs(module):
    _, key = DEPENDENCIES[module]
    key = module if key is ROS else key
    assert key in package_xml_depends('exec_depend', 'depend'), \
        f'package.xml has no <exec_depend>{key}</exec_depend> ({module})'
    if key == module:
        return          # a ROS package: rosdep resolves it from the distribution
    shipped = yaml.safe_load(ROSDEP_YAML.read_text())
    if key in shipped:
        pip, _ = DEPENDENCIES[module]
        for platform in ('debian', 'ubuntu'):
            assert shipped[key][platform]['pip']['packages'] == [pip], (key, platform)
    else:
        assert key in ROSDISTRO_KEYS, (f'{key} is neither a rosdistro key known to resolve on '
                                       f'Jazzy platforms nor defined in {ROSDEP_YAML.name}')


def test_the_readme_colcon_route_uses_the_shipped_rosdep_keys():
    readme = (REPO / 'README.md').read_text()
    assert 'rosdep/hrc_ros.yaml' in readme and 'rosdep install' in readme
