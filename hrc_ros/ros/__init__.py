"""The ROS ring of hrc_ros: everything that touches rclpy or ROS messages.

- `conversions`: every message <-> numpy conversion and its validation; `qos`: the profiles;
- `node_support`: parameters, guarded inputs, diagnostics, deadlines, the nodes' `main()`;
- `stop`: how every process stops (signals as requests, a second one forces the exit);
  `entry`: the console scripts, which install it before the heavy imports;
- `sources`: who publishes on an input, named from the graph; the followers' `hrc/epoch`;
- `nodes/`: the eight nodes (console scripts `belief_estimator_node`, `decision_node`,
  `task_manager_node`, `cell_sim_node`: the cell's loop, thin around `hrc_ros.core.protocol`;
  `cell_view_node`: the cell as markers; `body_tracking_node`, `tracker_sim_node`: a body
  tracker's stream as the human's input, and a synthetic one; `hmi_node`: the worker's and
  the operator's web pages);
- `bag`: recording and playing rosbag2-compatible bags on the graph (`hrc-bag`);
- `processes`: node processes started as a user would; `case_study`: `hrc-case-study`;
- `launch_plan`: what `launch/hrc.launch.py` starts, as plain data the tests can check, and
  the scenario's node parameters;
- `hmi`: the HMI's web server (aiohttp, in a thread of its own) and pages.

This package's `__init__` imports nothing: `entry` must load before rclpy does.
"""
