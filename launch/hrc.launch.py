"""Start one hrc_ros cell: belief estimator, decision, task manager, the simulated cell, the view,
the HMI, the robot bridge and a simulated arm.

    ros2 launch hrc_ros hrc.launch.py [params_file:=FILE] [config:=YAML] [policy:=NPZ]
        [selector:=paper|qmdp|mls|pomdp|fib] [pomdp_policy:=NPZ]
        [belief_mode:=bayes|table|posterior]
        [namespace:=cell1] [use_sim:=true|false]
        [view:=auto|true|false] [body_tracking:=false|true]
        [hmi:=false|true|answers] [robot:=none|sim]

The plan (which nodes, which parameters) is `hrc_ros.ros.launch_plan`; this file only turns it
into launch_ros actions, with the arguments' overrides as params files of each node's own name
(`launch_plan.parameter_files`).
"""

import tempfile

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from hrc_ros.ros.launch_plan import ARGUMENTS, cell_nodes, parameter_files

PACKAGE = 'hrc_ros'


def _cell_nodes(context):
    values = {a.name: LaunchConfiguration(a.name).perform(context) for a in ARGUMENTS}
    plan = cell_nodes(get_package_share_directory(PACKAGE), **values)
    params_dir = tempfile.mkdtemp(prefix='hrc_launch_')    # the overrides, per node
    return [Node(package=PACKAGE, executable=node.executable, name=node.name,
                 namespace=node.namespace, parameters=parameter_files(node, params_dir),
                 remappings=node.remappings, output='screen')
            for node in plan]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(a.name, default_value=a.default, description=a.description,
                               **({'choices': list(a.choices)} if a.choices else {}))
         for a in ARGUMENTS]
        + [OpaqueFunction(function=_cell_nodes)])
