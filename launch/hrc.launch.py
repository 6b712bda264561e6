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
(`launch_plan.parameter_files`) in a folder of this launch's (`launch_plan.params_dir`), removed
when launch shuts down.
"""

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnShutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from hrc_ros.ros.launch_plan import (ARGUMENTS, cell_nodes, parameter_files, params_dir,
                                     remove_params_dir)

PACKAGE = 'hrc_ros'


def _cell_nodes(context):
    values = {a.name: LaunchConfiguration(a.name).perform(context) for a in ARGUMENTS}
    plan = cell_nodes(get_package_share_directory(PACKAGE), **values)
    folder = params_dir()    # the overrides, per node; gone when launch shuts down
    return [RegisterEventHandler(OnShutdown(
                on_shutdown=lambda event, context: remove_params_dir(folder)))] \
        + [Node(package=PACKAGE, executable=node.executable, name=node.name,
                namespace=node.namespace, parameters=parameter_files(node, folder),
                remappings=node.remappings, output='screen')
           for node in plan]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(a.name, default_value=a.default, description=a.description,
                               **({'choices': list(a.choices)} if a.choices else {}))
         for a in ARGUMENTS]
        + [OpaqueFunction(function=_cell_nodes)])
