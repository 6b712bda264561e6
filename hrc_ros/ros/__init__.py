"""The ROS ring of hrc_ros: everything that touches rclpy or ROS messages.

- `conversions`: every message <-> numpy conversion and its validation; `qos`: the profiles;
- `node_support`: parameters, guarded inputs, diagnostics, deadlines, the nodes' `main()`;
- `sources`: who publishes on an input, named from the graph; the followers' `hrc/epoch`;
- `nodes/`: the four nodes (console scripts `belief_estimator_node`, `decision_node`,
  `task_manager_node`, `cell_sim_node`), thin around `hrc_ros.core.protocol`;
- `bag`: recording and playing rosbag2-compatible bags on the graph (`hrc-bag`);
- `processes`: node processes started as a user would; `case_study`: `hrc-case-study`;
- `launch_plan`: what `launch/hrc.launch.py` starts, as plain data the tests can check.
- `hmi`: the HMI's web server (aiohttp, in a thread of its own) and pages; its node is
  `nodes/hmi_node.py`.
"""
