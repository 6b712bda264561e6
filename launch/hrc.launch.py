"""Start one hrc_ros cell: belief estimator, decision, task manager and the simulated cell.

    ros2 launch hrc_ros hrc.launch.py [params_file:=FILE] [config:=YAML] [policy:=NPZ]
        [selector:=paper|qmdp|mls] [namespace:=cell1] [use_sim:=true|false]

Every node reads the shipped `config/hrc_params.yaml` first and then `params_file`, so a
params file only needs what it changes (`config/case_study_params.yaml` adds the case study's
tasks). `config`, `policy` and `selector`, when given, override both files. `namespace` moves
the whole cell (all topics are relative). `use_sim:=false` leaves out `cell_sim_node`, for a
cell with a real skeleton tracker, robot controller and HMI.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = 'hrc_ros'

# (executable, node name) of the cell's nodes; the simulated cell is the last.
DECISION_NODES = (
    ('belief_estimator_node', 'belief_estimator'),
    ('decision_node', 'decision'),
    ('task_manager_node', 'task_manager'),
)
SIMULATION_NODE = ('cell_sim_node', 'cell_sim')


def _cell_nodes(context):
    """The four Node actions, with the arguments the user gave resolved."""
    base_params = os.path.join(get_package_share_directory(PACKAGE), 'config',
                               'hrc_params.yaml')
    params_file = LaunchConfiguration('params_file').perform(context)
    namespace = LaunchConfiguration('namespace').perform(context)
    config = LaunchConfiguration('config').perform(context)
    policy = LaunchConfiguration('policy').perform(context)
    selector = LaunchConfiguration('selector').perform(context)

    params_files = [base_params]
    if params_file and os.path.abspath(params_file) != os.path.abspath(base_params):
        params_files.append(params_file)
    # Only arguments the user set override the params files ('' = leave them be).
    common = {'config': config} if config else {}
    decision = dict(common)
    if policy:
        decision['policy'] = policy
    if selector:
        decision['selector'] = selector
    overrides = {'decision': decision}

    def node(executable, name, **kwargs):
        return Node(package=PACKAGE, executable=executable, name=name, namespace=namespace,
                    parameters=params_files + [overrides.get(name, common)],
                    output='screen', **kwargs)

    nodes = [node(executable, name) for executable, name in DECISION_NODES]
    nodes.append(node(*SIMULATION_NODE,
                      condition=IfCondition(LaunchConfiguration('use_sim'))))
    return nodes


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument(
            'params_file', default_value='',
            description='ROS parameters YAML loaded after the shipped config/hrc_params.yaml '
                        '(e.g. config/case_study_params.yaml)'),
        DeclareLaunchArgument(
            'config', default_value='',
            description="model configuration YAML for every node ('' = the params files', "
                        'else the shipped config/default.yaml)'),
        DeclareLaunchArgument(
            'policy', default_value='',
            description="decision policy file from hrc-solve ('' = the params files', "
                        'else the shipped policy solved for config)'),
        DeclareLaunchArgument(
            'selector', default_value='', choices=['', 'paper', 'qmdp', 'mls'],
            description="action selection from the belief ('' = the params files', "
                        'else paper)'),
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of the whole cell, e.g. cell1'),
        DeclareLaunchArgument(
            'use_sim', default_value='true', choices=['true', 'false'],
            description='start cell_sim_node, the simulated human and cell'),
        OpaqueFunction(function=_cell_nodes),
    ])
