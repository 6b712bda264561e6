"""What `launch/hrc.launch.py` starts, as plain data: the launch file only turns this plan
into launch_ros actions, so its logic runs (and is tested) without ROS `launch` installed.

`ARGUMENTS` are the launch arguments (name, default, choices, description). `cell_nodes(...)`
takes their values and returns one `NodeLaunch` per node: every node reads the shipped
`config/hrc_params.yaml` first, then `params_file`, then the overrides of the arguments the
user set ('' leaves the params files be); `namespace` moves the whole cell (all topics are
relative); `use_sim` false leaves out `cell_sim_node`, for a cell with a real tracker, robot
controller and HMI. `view` starts `cell_view_node` (`hrc/markers` for RViz and Foxglove;
'auto': with the simulated cell). `body_tracking` starts `body_tracking_node`, which reads a
body tracker's MarkerArray stream into `human/*`; with the simulated cell it also starts
`tracker_sim_node`, fed by the cell's motion (remapped to `sim/human/*`), and loads
`config/body_tracking_sim_params.yaml` (the synthetic camera's pose) before `params_file`. On a
real cell the camera's pose comes from `params_file` (`camera_translation`, `camera_rotation`).
`hmi` starts `hmi_node` (the worker's and the operator's web pages, docs/HMI.md): on a real cell
the worker answers the robot's requests on the page; with the simulated cell `hmi:=true` keeps
the simulated person's answers and the page only shows them (`worker_answers: false`, so the
run stays the seeded one), and `hmi:=answers` stops the simulated person's answers
(`answer_requests: false`) so that the worker answers on the page.
`robot` `sim` adds the robot side of docs/ROBOT.md: `robot_bridge_node` (the actions into arm
motion under speed and separation monitoring) and `cobot_sim_node` (the simulated UR5e), and
switches the cell to the arm (`ROBOT_OVERRIDES`): the belief estimator's d from the arm's links
(`distance_source: arm_links`), the task manager's robot counter from the arm's progress
(`robot_progress: true`), the simulated person to a 3D body (`person: 3d`, with use_sim), and
every reader of the 32-joint skeleton to its joint names (`keypoint_joints`), and the model to
the arm's, `config/arm.yaml`, unless `config` or a params file names one (an `AllNodes` layer
before `params_file`).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..core.cell.tracking import K4ABT_JOINTS
from ..core.config import BELIEF_MODES
from ..core.paths import ARM_CONFIG
from ..core.decision.selection import SELECTORS


ROBOTS = ('none', 'sim')


@dataclass(frozen=True)
class LaunchArgument:
    name: str
    default: str
    description: str
    choices: tuple = ()


ARGUMENTS = (
    LaunchArgument('params_file', '', 'ROS parameters YAML loaded after the shipped '
                   'config/hrc_params.yaml (e.g. config/case_study_params.yaml)'),
    LaunchArgument('config', '', "model configuration YAML for every node ('' = the params "
                   "files', else the shipped config/default.yaml, with robot:=sim "
                   'config/arm.yaml)'),
    LaunchArgument('policy', '', "decision policy file from hrc-solve ('' = the params files', "
                   'else the shipped policy solved for config)'),
    LaunchArgument('selector', '', "action selection from the belief ('' = the params files', "
                   'else paper)', ('',) + SELECTORS),
    LaunchArgument('pomdp_policy', '', "POMDP policy file of the pomdp and fib selectors ('' = "
                   "the params files', else the shipped one solved for config)"),
    LaunchArgument('belief_mode', '', "the belief estimator's filter ('' = the params files', "
                   "else the configuration's observation.mode); posterior is the exact posterior "
                   'the pomdp and fib selectors plan with', ('',) + BELIEF_MODES),
    LaunchArgument('namespace', '', 'namespace of the whole cell, e.g. cell1'),
    LaunchArgument('use_sim', 'true', 'start cell_sim_node, the simulated human and cell',
                   ('true', 'false')),
    LaunchArgument('view', 'auto', "start cell_view_node (hrc/markers for RViz and Foxglove); "
                   "'auto': with the simulated cell", ('auto', 'true', 'false')),
    LaunchArgument('body_tracking', 'false', 'start body_tracking_node: human motion from a body '
                   "tracker's MarkerArray stream (with use_sim: tracker_sim_node's)",
                   ('true', 'false')),
    LaunchArgument('hmi', 'false', "start hmi_node, the worker's and the operator's web pages "
                   "(docs/HMI.md). With use_sim, 'true': the simulated person answers the "
                   "robot's requests and the page shows the answers; 'answers': the simulated "
                   'person stops answering and the worker answers on the page',
                   ('false', 'true', 'answers')),
    LaunchArgument('robot', 'none', "the robot side: 'sim' starts robot_bridge_node and "
                   'cobot_sim_node (a simulated UR5e under speed and separation monitoring) and '
                   "runs the cell with the arm (docs/ROBOT.md); 'none': the decision layer "
                   'alone, hrc/action its last word', ROBOTS),
)

# (executable, node name) of the cell's nodes; the simulated cell is the last.
DECISION_NODES = (
    ('belief_estimator_node', 'belief_estimator'),
    ('decision_node', 'decision'),
    ('task_manager_node', 'task_manager'),
)
SIMULATION_NODE = ('cell_sim_node', 'cell_sim')
VIEW_NODE = ('cell_view_node', 'cell_view')
BODY_TRACKING_NODE = ('body_tracking_node', 'body_tracking')
TRACKER_SIM_NODE = ('tracker_sim_node', 'tracker_sim')
HMI_NODE = ('hmi_node', 'hmi')
SYNTHETIC_TRACKER_WITH_ARM = (
    "robot 'sim' with body_tracking and the simulated cell: tracker_sim's synthetic body walks "
    "by the reference point's bands, not as the 3D person by the separation to the arm; use "
    'the simulated cell without body_tracking, or a real tracker (use_sim false)')
ROBOT_NODES = (('robot_bridge_node', 'robot_bridge'), ('cobot_sim_node', 'cobot_sim'))
# robot:=sim: the parameters that run the cell with the arm, per node name.
ROBOT_OVERRIDES = {
    'belief_estimator': {'distance_source': 'arm_links', 'keypoint_joints': list(K4ABT_JOINTS)},
    'task_manager': {'robot_progress': True},
    'cell_sim': {'person': '3d'},
    'robot_bridge': {'keypoint_joints': list(K4ABT_JOINTS)},
    'cobot_sim': {'keypoint_joints': list(K4ABT_JOINTS)},
    'cell_view': {'keypoint_joints': list(K4ABT_JOINTS), 'robot': True},
}
BODY_TRACKING_SIM_PARAMS = 'body_tracking_sim_params.yaml'
# cell_sim's motion goes to tracker_sim instead of the estimator when a tracker is simulated.
SIM_MOTION_REMAPS = [('human/joint_states', 'sim/human/joint_states'),
                     ('human/skeleton', 'sim/human/skeleton')]


class AllNodes(dict):
    """Parameters for every node (a params file's ``/**`` section), in a node's parameters
    between params files: what a later file sets wins over it (`parameter_files`)."""


@dataclass(frozen=True)
class NodeLaunch:
    """One node to start: launch_ros `Node(package, executable, name, namespace, parameters)`."""

    executable: str
    name: str
    namespace: str
    # params file paths (an `AllNodes` among them: robot:=sim's config), then one dict
    parameters: list = field(default_factory=list)
    remappings: list = field(default_factory=list)   # (from, to) topic names


def _flag(name: str, value, choices=('true', 'false')) -> str:
    value = str(value).lower()
    if value not in choices:
        raise ValueError(f"{name} must be {' or '.join(repr(c) for c in choices)}, got {value!r}")
    return value


def cell_nodes(share_dir: str | Path, params_file: str = '', namespace: str = '',
               config: str = '', policy: str = '', selector: str = '', belief_mode: str = '',
               pomdp_policy: str = '',
               use_sim: str | bool = 'true', view: str | bool = 'auto',
               body_tracking: str | bool = 'false',
               hmi: str | bool = 'false', robot: str = 'none') -> list[NodeLaunch]:
    """The nodes of one cell for the launch arguments' values (strings, as launch gives them)."""
    if selector not in ('',) + SELECTORS:
        raise ValueError(f'selector must be one of {", ".join(SELECTORS)} or empty, got '
                         f'{selector!r}')
    if belief_mode not in ('',) + BELIEF_MODES:
        raise ValueError(f'belief_mode must be one of {", ".join(BELIEF_MODES)} or empty, got '
                         f'{belief_mode!r}')
    use_sim = _flag('use_sim', use_sim) == 'true'
    view = _flag('view', view, ('auto', 'true', 'false'))
    view = use_sim if view == 'auto' else view == 'true'
    body_tracking = _flag('body_tracking', body_tracking) == 'true'
    page_answers = _flag('hmi', hmi, ('false', 'true', 'answers')) == 'answers'
    hmi = page_answers or _flag('hmi', hmi, ('false', 'true', 'answers')) == 'true'
    config_dir = os.path.join(str(share_dir), 'config')
    base_params = os.path.join(config_dir, 'hrc_params.yaml')
    params_files = [base_params]
    if body_tracking and use_sim:
        params_files.append(os.path.join(config_dir, BODY_TRACKING_SIM_PARAMS))
    robot = _flag('robot', robot, ROBOTS) == 'sim'
    if robot and not config:   # the arm's model (its program waits under dp and dm), unless
        # the user's params file names a configuration: a layer before that file
        params_files.append(AllNodes(config=os.path.join(config_dir, f'{ARM_CONFIG}.yaml')))
    if params_file and os.path.abspath(params_file) not in map(
            os.path.abspath, (p for p in params_files if isinstance(p, str))):
        params_files.append(params_file)
    common = {'config': config} if config else {}
    decision = dict(common)
    if policy:
        decision['policy'] = policy
    if selector:
        decision['selector'] = selector
    if pomdp_policy:
        decision['pomdp_policy'] = pomdp_policy
    overrides = {'decision': decision}
    if belief_mode:
        overrides['belief_estimator'] = {**common, 'belief_mode': belief_mode}
    if use_sim and page_answers:         # the worker answers on the page, the sim stops
        overrides['cell_sim'] = {**common, 'answer_requests': False}
    elif use_sim and hmi:                # the simulated person answers, the page shows it
        overrides['hmi'] = {**common, 'worker_answers': False}
    if robot and body_tracking and use_sim:
        raise ValueError(SYNTHETIC_TRACKER_WITH_ARM)
    if robot:
        for name, values in ROBOT_OVERRIDES.items():
            overrides[name] = {**common, **overrides.get(name, {}), **values}
    nodes = list(DECISION_NODES) + [VIEW_NODE] * view + [BODY_TRACKING_NODE] * body_tracking \
        + [TRACKER_SIM_NODE] * (body_tracking and use_sim) + [HMI_NODE] * hmi \
        + list(ROBOT_NODES) * robot + [SIMULATION_NODE] * use_sim
    remaps = {'cell_sim': SIM_MOTION_REMAPS} if body_tracking else {}
    return [NodeLaunch(executable, name, namespace,
                       params_files + [overrides.get(name, common)], list(remaps.get(name, [])))
            for executable, name in nodes]


def parameter_files(node: NodeLaunch, params_dir: str | Path) -> list[str]:
    """`node.parameters` as params files: each dict written to a file in `params_dir` under
    the node's own name, ``/**/NAME`` (any namespace). Not under ``/**``, as launch_ros writes a
    dict: rcl merges the files' sections by name, in the order each name first appears, so a
    parameter that `config/hrc_params.yaml` sets in ``/**/NAME`` would win over a later
    file's ``/**`` (the arguments' overrides, `ROBOT_OVERRIDES`, would be lost). An `AllNodes`
    dict is written under ``/**``, so that a later params file (the user's) wins over it. The
    launch file and the tests pass these files."""
    import yaml
    files = []
    for index, parameters in enumerate(node.parameters):
        if isinstance(parameters, dict):
            path = Path(params_dir) / f'{node.name}_{index}.yaml'
            # an AllNodes layer under /**: sections apply in the order each name first appears
            # (config/hrc_params.yaml's /** first), so a later file's /** or /**/NAME wins
            section = '/**' if isinstance(parameters, AllNodes) else f'/**/{node.name}'
            path.write_text(yaml.safe_dump({section: {'ros__parameters': dict(parameters)}}))
            parameters = str(path)
        files.append(str(parameters))
    return files


PARAMS_DIR_PREFIX = 'hrc_launch_'
LEGACY_DIR_AGE = 86400.0    # seconds: a folder of the old form (no pid) older than this goes


def params_dir(root: str | Path | None = None) -> Path:
    """A new folder for one launch's override files (`parameter_files`), named by the launch's
    process, `<tmp>/hrc_launch_<pid>_<random>`. The launch file removes it when launch shuts
    down (`remove_params_dir` on launch's OnShutdown: the nodes read their params files when
    they start, nothing reads them later); the folders of launches whose process is gone (one
    killed with SIGKILL never got to remove its own) are removed first
    (`remove_stale_params_dirs`), so that none accumulate (issue 37: 62 folders after 62
    launches)."""
    root = Path(root or tempfile.gettempdir())
    remove_stale_params_dirs(root)
    return Path(tempfile.mkdtemp(prefix=f'{PARAMS_DIR_PREFIX}{os.getpid()}_', dir=root))


def remove_params_dir(path: str | Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:       # someone else's process: alive
        return True
    return True


def remove_stale_params_dirs(root: str | Path) -> list[Path]:
    """Remove the launch folders in `root` whose launch process no longer runs, and those of
    the old form (no pid in the name) older than a day; returns what was removed."""
    removed = []
    for folder in Path(root).glob(f'{PARAMS_DIR_PREFIX}*'):
        pid, _, rest = folder.name[len(PARAMS_DIR_PREFIX):].partition('_')
        try:
            if not folder.is_dir() or folder.is_symlink():
                continue
            if pid.isdigit() and rest:
                stale = not _alive(int(pid))
            else:
                stale = time.time() - folder.stat().st_mtime > LEGACY_DIR_AGE
        except OSError:
            continue
        if stale:
            remove_params_dir(folder)
            removed.append(folder)
    return removed


def ros_arguments(node: NodeLaunch, params_dir: str | Path) -> list[str]:
    """What launch_ros's `Node` action passes after `--ros-args` for `node` as the launch file
    starts it (Jazzy): `-r __node:=NAME`, `-r __ns:=/NS` (made absolute; none for the root
    namespace), a `--params-file` per file of `parameter_files`, then `-r FROM:=TO` per
    remapping. The tests start the plan with these, as `ros2 launch` would, where ROS `launch`
    is not installed."""
    args = ['-r', f'__node:={node.name}']
    if node.namespace:
        args += ['-r', f'__ns:=/{node.namespace.strip("/")}']
    for path in parameter_files(node, params_dir):
        args += ['--params-file', path]
    for old, new in node.remappings:
        args += ['-r', f'{old}:={new}']
    return args


def scenario_parameters(scenario) -> dict:
    """The ROS parameters that set a `core.study.simulation.Scenario` up on the graph: the task
    manager's `initial_task` and `schedule`, the simulated cell's `initial_emotions` and
    `initial_distance`, as a params-file mapping. `hrc-case-study` passes these for
    `case_study()`, the one definition of the paper's scenario; config/case_study_params.yaml
    holds the same for `ros2 launch ... params_file:=` (test_launch_graph holds them equal).
    ValueError for a scenario the nodes cannot start in (a task already under way, answers or
    held beliefs in the initial state)."""
    em, ea, tp, tc, tx, ty, hp, hc, bp, bc, d = (int(v) for v in scenario.initial_state)
    if any((ty, hp, hc, bp, bc)):
        raise ValueError(f'the nodes start with ty = hp = hc = bp = bc = 0, not '
                         f'{scenario.initial_state}')
    schedule = [f'{epoch}:{",".join(str(int(v)) for v in task)}'
                for epoch, task in scenario.schedule]
    return {
        '/**/task_manager': {'ros__parameters': {'initial_task': [tp, tc, tx],
                                                 'schedule': schedule}},
        '/**/cell_sim': {'ros__parameters': {'initial_emotions': [em, ea],
                                             'initial_distance': d}},
    }
