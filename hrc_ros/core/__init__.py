"""The ROS-free core of hrc_ros: the paper's model and the decision science (numpy, scipy,
numba; no rclpy, no ROS message package, no ament).

- `config`: configuration YAML, validation, hash; `paths`: where config/ and policies/ live;
- `model`: MODEL.md's state space, rules and cost; `solver` (+ `_kernels`): value and policy
  iteration on the factored Bellman operator; `policy`: policy files;
- `observation`: human motion -> velocity level O and distance level d; `belief`: the filter
  over the hidden emotions; `selection`: actions from (belief, observable state);
- `tasks`: the task book; `cell`: the simulated human; `faults`: injected faults;
- `protocol`: the ROS epoch protocol as pure state machines (the nodes call it);
- `simulation`, `evaluation`, `plots`: closed loops without ROS, many-episode comparisons and
  their figures;
- `bagfile`: the rosbag2-compatible MCAP format (write, read, check) without ROS.
"""
