"""What `launch/hrc.launch.py` starts, as plain data: the launch file only turns this plan
into launch_ros actions, so its logic runs (and is tested) without ROS `launch` installed.

`ARGUMENTS` are the launch arguments (name, default, choices, description). `cell_nodes(...)`
takes their values and returns one `NodeLaunch` per node: every node reads the shipped
`config/hrc_params.yaml` first, then `params_file`, then the overrides of the arguments the
user set ('' leaves the params files be); `namespace` moves the whole cell (all topics are
relative); `use_sim` false leaves out `cell_sim_node`, for a cell with a real tracker, robot
controller and HMI.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..core.selection import SELECTORS


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
                   "files', else the shipped config/default.yaml)"),
    LaunchArgument('policy', '', "decision policy file from hrc-solve ('' = the params files', "
                   'else the shipped policy solved for config)'),
    LaunchArgument('selector', '', "action selection from the belief ('' = the params files', "
                   'else paper)', ('',) + SELECTORS),
    LaunchArgument('namespace', '', 'namespace of the whole cell, e.g. cell1'),
    LaunchArgument('use_sim', 'true', 'start cell_sim_node, the simulated human and cell',
                   ('true', 'false')),
)

# (executable, node name) of the cell's nodes; the simulated cell is the last.
DECISION_NODES = (
    ('belief_estimator_node', 'belief_estimator'),
    ('decision_node', 'decision'),
    ('task_manager_node', 'task_manager'),
)
SIMULATION_NODE = ('cell_sim_node', 'cell_sim')


@dataclass(frozen=True)
class NodeLaunch:
    """One node to start: launch_ros `Node(package, executable, name, namespace, parameters)`."""

    executable: str
    name: str
    namespace: str
    parameters: list = field(default_factory=list)   # params file paths, then one dict


def cell_nodes(share_dir: str | Path, params_file: str = '', namespace: str = '',
               config: str = '', policy: str = '', selector: str = '',
               use_sim: str | bool = 'true') -> list[NodeLaunch]:
    """The nodes of one cell for the launch arguments' values (strings, as launch gives them)."""
    if selector not in ('',) + SELECTORS:
        raise ValueError(f'selector must be one of {", ".join(SELECTORS)} or empty, got '
                         f'{selector!r}')
    use_sim = str(use_sim).lower()
    if use_sim not in ('true', 'false'):
        raise ValueError(f"use_sim must be 'true' or 'false', got {use_sim!r}")
    base_params = os.path.join(str(share_dir), 'config', 'hrc_params.yaml')
    params_files = [base_params]
    if params_file and os.path.abspath(params_file) != os.path.abspath(base_params):
        params_files.append(params_file)
    common = {'config': config} if config else {}
    decision = dict(common)
    if policy:
        decision['policy'] = policy
    if selector:
        decision['selector'] = selector
    overrides = {'decision': decision}
    nodes = list(DECISION_NODES) + ([SIMULATION_NODE] if use_sim == 'true' else [])
    return [NodeLaunch(executable, name, namespace,
                       params_files + [overrides.get(name, common)])
            for executable, name in nodes]
