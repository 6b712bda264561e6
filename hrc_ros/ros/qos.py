"""The five QoS profiles of the hrc_ros graph, named once (INTERFACES.md, QoS column).

- `SENSOR_DATA`: human motion streams (`human/joint_states`, `human/skeleton`). Best effort,
  keep last 5: a late sample is worth less than the next one, and a slow subscriber must never
  make the tracker queue up.
- `LATCHED`: what the suite's publishers offer for state that a late joiner needs at once
  (`hrc/belief`, `hrc/task_state`, `hrc/distance_level`, `hrc/estimator_config`, the
  simulator's `hrc/sim/true_state`).
  Reliable, transient local, depth 1: the last value is kept by the publisher and handed to
  every new subscriber that asks for it.
- `STATE_INPUT`: what the nodes subscribe such state with. Reliable but volatile: a volatile
  subscription matches a transient-local publisher and an ordinary (volatile) one alike, so a
  perception node or `ros2 topic pub` with default QoS is heard; a transient-local one would
  refuse the volatile publisher ("offering incompatible QoS ... DURABILITY"). The nodes do not
  need the stored sample: every state is published again each epoch.
- `ORDERS`: `hrc/task_request`, reliable and keep-all: an order is never overwritten unseen.
- `REPORTS`: the task manager's per-request reports, reliable, transient local, last 100.
- `RELIABLE`: events (`hrc/action`, `hrc/epoch`, `hrc/observation`,
  `hrc/human_response`, `/diagnostics`). Reliable, volatile, keep last 10.

Two more live with the one node that uses each: `cell_view_node.SAMPLED` (`STATE_INPUT` with a
history of 100, for inputs read a few times a second) and `tracker_sim_node.DRIVER_QOS` (what
the Azure Kinect driver offers, which the simulated tracker imitates).
"""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

SENSOR_DATA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                         reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE)

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

STATE_INPUT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


# The decision nodes' claims to decide for the cell (`hrc/_clock_claim`, `ClockOwner`):
# reliable and transient local, so a node started later hears every running one's claim at
# once; a reader keeps several, one per decision node that may claim at the same moment.
CLAIMS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                    reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)

# Listeners' ready marks for the epoch clock (`hrc/_epoch_ready`, `core.protocol.EpochListeners`):
# reliable and transient local, so a decision node started after its listeners hears each one's
# latest mark at once; a reader keeps enough for every listener of a cell arriving together.
READY_MARKS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

# Orders that must not be lost (`hrc/task_request`): reliable and keep-all, so a burst is taken
# whole (what the task queue cannot hold is refused with a report), never overwritten unseen in
# the reader's history. Fast DDS bounds a keep-all reader by its resource limits; beyond them a
# reliable writer blocks and its publish fails, so the sender learns of it.
ORDERS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)

# Reports a late joiner should see the recent past of (`hrc/task_request_result`, one per order):
# reliable and transient local, the last `REPORT_DEPTH` kept, so a burst of orders is reported
# whole and an operator page that opens later still lists the recent outcomes.
REPORT_DEPTH = 100
REPORTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=REPORT_DEPTH,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

