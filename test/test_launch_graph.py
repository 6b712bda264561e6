"""The cell as `ros2 launch hrc_ros hrc.launch.py` starts it, on a real graph: every node has a
fully qualified name of its own.

ROS `launch` is not installable here, so the plan of launch/hrc.launch.py
(`launch_plan.cell_nodes`) is started with the arguments launch_ros passes each process
(`launch_plan.ros_arguments`: `-r __node:=NAME -r __ns:=/NS --params-file ... -r FROM:=TO`).
The view's helper node (`node_support.SampledInputs`) took those global arguments and was renamed
to `cell_view` too (issue 17: `ros2 node list` showed `/cell_view` twice); a user's own
`-r __node:=` gave two nodes of the new name. The helper must keep a name of its own and still
follow the owner's namespace and topic remappings.
"""

from __future__ import annotations

import time
from collections import Counter

import rclpy

from hrc_ros.core.paths import share_dir
from hrc_ros.ros import stop
from hrc_ros.ros.launch_plan import cell_nodes, ros_arguments
from hrc_ros.ros.processes import NodeProcesses

GRAPH_TIMEOUT = 60.0


def full_names(probe) -> list[str]:
    return [f'{namespace.rstrip("/")}/{name}'
            for name, namespace in probe.get_node_names_and_namespaces()]


def test_every_node_of_a_launched_cell_has_a_name_of_its_own(tmp_path, ros_domain_id):
    plan = cell_nodes(share_dir(), namespace='cell1', body_tracking='true')
    assert 'cell_view' in {n.name for n in plan}
    context = rclpy.Context()
    rclpy.init(context=context, **stop.init_options())
    probe = rclpy.create_node('launch_graph_probe', context=context)
    nodes = NodeProcesses(tmp_path, [])
    try:
        for node in plan:
            nodes.start(node.executable, ros_args=ros_arguments(node, tmp_path))
        # a user's own rename, namespace and topic remapping of a second view
        nodes.start('cell_view_node', name='view2', ros_args=[
            '--params-file', str(share_dir() / 'config' / 'hrc_params.yaml'),
            '-r', '__node:=view2', '-r', '__ns:=/cell2', '-r', 'human/skeleton:=tracked/skeleton'])
        expected = {f'/cell1/{n.name}' for n in plan} | {'/cell1/cell_view_inputs',
                                                         '/cell2/view2', '/cell2/view2_inputs'}
        # every process's nodes: the plan, the two views' helpers and the second view
        wanted = len(plan) + 3
        deadline = time.monotonic() + GRAPH_TIMEOUT
        while len([n for n in full_names(probe) if n != '/launch_graph_probe']) < wanted:
            assert not nodes.dead(), nodes.logs()
            assert time.monotonic() < deadline, (full_names(probe), nodes.logs())
            time.sleep(0.05)
        names = [n for n in full_names(probe) if n != '/launch_graph_probe']
        twice = sorted(n for n, count in Counter(names).items() if count > 1)
        assert not twice, f'nodes that share a fully qualified name: {twice} in {names}'
        assert set(names) == expected
        # the helper follows its owner's namespace and topic remapping
        def readers(topic):
            return {(info.node_namespace, info.node_name)
                    for info in probe.get_subscriptions_info_by_topic(topic)}

        # a reader can be discovered before its node's name (rmw: '_NODE_NAME_UNKNOWN_', seen
        # on a loaded host): wait for the names, not only for the readers
        def named(topic):
            found = readers(topic)
            return found and not any('_UNKNOWN_' in n for pair in found for n in pair)

        while not (named('/cell2/tracked/skeleton') and named('/cell1/hrc/epoch') and
                   ('/cell1', 'cell_view_inputs') in readers('/cell1/hrc/epoch')):
            assert time.monotonic() < deadline, (readers('/cell2/tracked/skeleton'),
                                                 readers('/cell1/hrc/epoch'))
            time.sleep(0.05)
        assert readers('/cell2/tracked/skeleton') == {('/cell2', 'view2_inputs')}
        assert not readers('/cell2/human/skeleton')
        codes = nodes.stop()
    finally:
        nodes.stop(timeout=5.0)
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
    assert codes == {name: 0 for name in codes}, nodes.logs()


def test_the_shipped_case_study_params_are_the_core_scenario():
    """The case study is defined once, by `core.study.simulation.case_study()`; the params file
    shipped for `ros2 launch ... params_file:=config/case_study_params.yaml` must say the
    same (hrc-case-study writes its own from the core)."""
    import yaml

    from hrc_ros.core.study.simulation import case_study
    from hrc_ros.ros.launch_plan import scenario_parameters
    shipped = yaml.safe_load((share_dir() / 'config' / 'case_study_params.yaml').read_text())
    expected = scenario_parameters(case_study())
    assert shipped == expected, ('config/case_study_params.yaml differs from case_study(); '
                                 f'it should read:\n{yaml.safe_dump(expected)}')


def test_the_cell_with_the_arm_launches_with_unique_names_and_its_wiring(tmp_path,
                                                                        ros_domain_id):
    """robot:=sim adds the bridge and the simulated arm and switches the cell to the arm: the
    estimator reads the arm's joint states, the task manager the arm's progress, the
    simulated person the separation, the view both; every node keeps a name of its own."""
    plan = cell_nodes(share_dir(), namespace='cell1', robot='sim')
    names = [n.name for n in plan]
    assert {'robot_bridge', 'cobot_sim', 'cell_sim', 'cell_view'} <= set(names)
    context = rclpy.Context()
    rclpy.init(context=context, **stop.init_options())
    probe = rclpy.create_node('launch_graph_probe', context=context)
    nodes = NodeProcesses(tmp_path, [])

    def readers(topic):
        return {info.node_name for info in probe.get_subscriptions_info_by_topic(topic)}
    wiring = {'/cell1/joint_states': {'belief_estimator', 'robot_bridge', 'cell_view_inputs'},
              '/cell1/hrc/robot_progress': {'task_manager'},
              '/cell1/hrc/separation': {'cell_sim', 'cell_view_inputs'},
              '/cell1/hrc/speed_override': {'cobot_sim'},
              '/cell1/joint_trajectory_controller/joint_trajectory': {'cobot_sim'}}
    try:
        for node in plan:
            nodes.start(node.executable, ros_args=ros_arguments(node, tmp_path))
        # the view and the simulated arm each take their inputs on a second node of their own
        expected = {f'/cell1/{n}' for n in names} | {'/cell1/cell_view_inputs',
                                                     '/cell1/cobot_sim_inputs'}
        deadline = time.monotonic() + GRAPH_TIMEOUT
        def missing():
            return (expected - set(full_names(probe)),
                    {t: want - readers(t) for t, want in wiring.items() if want - readers(t)})
        while any(missing()):
            assert not nodes.dead(), nodes.logs()
            assert time.monotonic() < deadline, (missing(), nodes.logs()[-4000:])
            time.sleep(0.05)
        got = [n for n in full_names(probe) if n != '/launch_graph_probe']
        twice = sorted(n for n, count in Counter(got).items() if count > 1)
        assert not twice, f'nodes that share a fully qualified name: {twice} in {got}'
        assert set(got) == expected
        codes = nodes.stop()
    finally:
        nodes.stop(timeout=5.0)
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
    assert codes == {name: 0 for name in codes}, nodes.logs()
