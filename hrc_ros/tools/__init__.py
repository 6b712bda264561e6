"""The ROS-free command lines: `hrc-solve`, `hrc-simulate`, `hrc-evaluate` (argument parsing
and output files around `hrc_ros.core`)."""
