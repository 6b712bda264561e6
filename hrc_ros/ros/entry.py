"""The console scripts of the nodes, `hrc-bag` and `hrc-case-study`: install the stop regime
(`stop.install`), then import the command's module and run its `main()`.

A node's module imports rclpy, numpy and the model (about a second, several on a loaded
machine); a Ctrl-C during those imports used to end the process with a KeyboardInterrupt
traceback and exit -2. Entering here, it ends the process at once with exit 0 and no output
(`stop.importing`: nothing exists yet to tear down); once `main()` runs, a signal is a request
that `main()` honours (a node built meanwhile is torn down, then exit 0). Once `main()` has
returned, the process leaves at once (`stop.leave`: flushed, then `os._exit`, without the
interpreter's finalization, seconds of CPU on a loaded machine). setup.py points every
such console script here (`ros2 run` and `colcon build` use the same entry points); `python -m
hrc_ros.ros.entry NAME [ARGS...]` runs one by its script name. This module, `stop` and
`core.streams` (a reader of the output that leaves, `| head`, stops the report, not the
work) import only the standard library.
"""

from __future__ import annotations

import importlib
import sys

from ..core.streams import outliving_stdout
from . import stop

# console script -> module whose main() it runs (every node's main() takes ROS args from argv)
COMMANDS = {
    'belief_estimator_node': 'hrc_ros.ros.nodes.belief_estimator_node',
    'decision_node': 'hrc_ros.ros.nodes.decision_node',
    'task_manager_node': 'hrc_ros.ros.nodes.task_manager_node',
    'cell_sim_node': 'hrc_ros.ros.nodes.cell_sim_node',
    'cell_view_node': 'hrc_ros.ros.nodes.cell_view_node',
    'body_tracking_node': 'hrc_ros.ros.nodes.body_tracking_node',
    'tracker_sim_node': 'hrc_ros.ros.nodes.tracker_sim_node',
    'hmi_node': 'hrc_ros.ros.nodes.hmi_node',
    'robot_bridge_node': 'hrc_ros.ros.nodes.robot_bridge_node',
    'cobot_sim_node': 'hrc_ros.ros.nodes.cobot_sim_node',
    'speed_scaling_node': 'hrc_ros.ros.nodes.speed_scaling_node',
    'hrc-bag': 'hrc_ros.ros.bag',
    'hrc-case-study': 'hrc_ros.ros.case_study',
}


def run_command(name: str) -> int:
    """Install the stop regime, import the command's module, return its main()'s exit code."""
    stop.install()
    with stop.importing():        # a stop signal now ends the process at once, with 0
        module = importlib.import_module(COMMANDS[name])
    with outliving_stdout():       # `| head`: the report stops, the work goes on
        return module.main()


def run_and_leave(name: str):
    """`run_command`, then end the process with its code (`stop.leave`): a console script."""
    stop.leave(run_command(name))


def _command(name: str):
    def main() -> int:
        return run_and_leave(name)
    main.__name__ = main.__qualname__ = name.replace('-', '_')
    main.__doc__ = f'The `{name}` console script ({COMMANDS[name]}.main).'
    return main


belief_estimator_node = _command('belief_estimator_node')
decision_node = _command('decision_node')
task_manager_node = _command('task_manager_node')
cell_sim_node = _command('cell_sim_node')
cell_view_node = _command('cell_view_node')
body_tracking_node = _command('body_tracking_node')
tracker_sim_node = _command('tracker_sim_node')
hmi_node = _command('hmi_node')
robot_bridge_node = _command('robot_bridge_node')
cobot_sim_node = _command('cobot_sim_node')
speed_scaling_node = _command('speed_scaling_node')
hrc_bag = _command('hrc-bag')
hrc_case_study = _command('hrc-case-study')


if __name__ == '__main__':
    if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
        print(f'usage: python -m hrc_ros.ros.entry {{{",".join(COMMANDS)}}} [ARGS...]',
              file=sys.stderr)
        sys.exit(2)
    command = sys.argv.pop(1)
    sys.argv[0] = command
    run_and_leave(command)
