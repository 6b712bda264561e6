"""The ROS-free core of hrc_ros: the paper's model and the decision science (numpy, scipy,
numba; no rclpy, no ROS message package, no ament), grouped by what each part serves.

Modules every part uses:
- `config`: configuration YAML, validation, hash; `paths`: where config/ and policies/ live,
  and reading and writing users' files safely (types, size caps, the one YAML loader);
  `quoting`: capped quotes of user data in errors;
- `model`: MODEL.md's state space, rules and cost; `tasks`: the task book (MODEL.md 3.2);
- `protocol`: the ROS epoch protocol as pure state machines (the nodes call it); `swap`: the
  live-swap rule of the decision node and the belief estimator;
- `bagfile`: the rosbag2-compatible MCAP format (write, read, check) without ROS.

Packages:
- `mdp/`: the factored Bellman operator, value and policy iteration, policy files;
- `pomdp/`: the belief filter, the point-based POMDP solver, alpha-vector policy files;
- `decision/`: human motion into O and d, actions from (belief, observable state);
- `learning/`: recordings as per-epoch records, the model fitted by EM;
- `cell/`: the simulated human, injected faults, body-tracking input, the cell as markers;
- `study/`: closed loops without ROS (one trajectory, many paired episodes) and their plots.
- `hmi/`: the person's side: when a request is open, one answer per request, the task form,
  the pages' words and the web server's access rules (no ROS, no web framework).
"""
