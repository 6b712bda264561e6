"""The plant of cells (`hrc-fleet`, docs/FLEET.md): per cell, read its recordings, test them for
drift against the running model, fit, solve, check the new policy against the running one in
the cell as now fitted, decide whether to promote it, and write the outputs.

Owns: the plant file's schema (`spec`), the drift test (`drift`), the stages as plain
functions (`stages`), the promotion rule and each cell's pipeline as a state machine that
says which stage runs next (`pipeline`), and the plant report (`report`). Nothing here imports
ROS or Ray: `hrc_ros.tools.fleet` schedules the stages as Ray tasks (or runs them one after
the other in one process), `hrc_ros.ros.fleet_apply` swaps promoted policies on the ROS graph.
"""
