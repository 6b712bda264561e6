"""The three QoS profiles of the hrc_ros graph, named once (INTERFACES.md, QoS column).

- `SENSOR_DATA`: human motion streams (`human/joint_states`, `human/skeleton`). Best effort,
  keep last 5: a late sample is worth less than the next one, and a slow subscriber must never
  make the tracker queue up.
- `LATCHED`: state that a late joiner needs at once (`hrc/belief`, `hrc/task_state`,
  `hrc/distance_level`, `hrc/estimator_config`, the simulator's `hrc/sim/true_state`).
  Reliable, transient local, depth 1: the last value is kept by the publisher and handed to
  every new subscriber. A subscriber must use it too, or it does not receive the stored sample.
- `RELIABLE`: events (`hrc/action`, `hrc/epoch`, `hrc/observation`, `hrc/task_request`,
  `hrc/human_response`, `/diagnostics`). Reliable, volatile, keep last 10.
"""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

SENSOR_DATA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                         reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE)

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
