"""The ROS-free command lines: `hrc-solve`, `hrc-simulate`, `hrc-evaluate`, `hrc-fit` (argument
parsing and output files around `hrc_ros.core`)."""
